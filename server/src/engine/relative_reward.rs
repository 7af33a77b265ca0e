//! The relative reward objective (the paper's Algorithm 1): fit rho so that its input
//! gradient matches the difference of the expert's and the base's denoising outputs,
//!
//! ```text
//! t ~ U{0..T-1},  x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps
//! target = mu_expert(x_t, t) - mu_base(x_t, t)     ("mean", default)
//!       or s_expert(x_t, t)  - s_base(x_t, t)      ("score")
//! loss   = mean_batch || grad_x rho(x_eval, t) - target ||^2  (+ rho_l2 * mean rho^2)
//! ```
//!
//! with x_eval = x_t (the paper's formula, default) or mu_base(x_t, t) (the authors' code).
//! Expert minus base, so grad rho points from base toward expert (REFERENCE section 1). Both
//! diffusion models are frozen and evaluated under no-grad; the loss reaches rho's parameters
//! through a double backward (grad_x computed with create_graph).
//!
//! Posterior means are taken without clipping x0_hat: the target is a property of the two
//! models' networks, and clipping would make it depend on where x0_hat leaves [-1, 1].

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use super::diffusion::DiffusionModel;
use super::manifest::Space;
use super::nets::reward::{RewardArchitecture, RewardNet};
use super::normalizer::Normalizer;
use crate::error::{Error, Result};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    Mean,
    Score,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EvalPoint {
    XT,
    MuBase,
}

/// Checks that two diffusion models can be compared: same item shape, same T and schedule,
/// same normalizer (their outputs must live in the same coordinates).
pub fn check_pair(base: &DiffusionModel, expert: &DiffusionModel) -> Result<()> {
    let (b, e) = (&base.manifest, &expert.manifest);
    if b.space.item_shape() != e.space.item_shape() {
        return Err(Error::invalid(format!(
            "spec.reward: base item shape {:?} differs from expert item shape {:?}",
            b.space.item_shape(),
            e.space.item_shape()
        )));
    }
    if b.n_timesteps != e.n_timesteps
        || base.schedule.values(super::schedule::Table::Betas) != expert.schedule.values(super::schedule::Table::Betas)
    {
        return Err(Error::invalid(format!(
            "spec.reward: base and expert use different noise schedules (T = {} vs {}); the difference of their outputs is only meaningful on one schedule",
            b.n_timesteps, e.n_timesteps
        )));
    }
    if b.normalizer != e.normalizer {
        return Err(Error::invalid(
            "spec.reward: base and expert have different normalizers; their outputs are in different units",
        ));
    }
    Ok(())
}

/// The regression target and the evaluation point for a batch of x_t, under no-grad.
pub fn target_and_point(
    base: &DiffusionModel,
    expert: &DiffusionModel,
    x_t: &Tensor,
    t: &Tensor,
    target: Target,
    eval_point: EvalPoint,
) -> Result<(Tensor, Tensor)> {
    let _guard = tch::no_grad_guard();
    let mu_base = base.posterior_mean(x_t, t, false)?;
    let y = match target {
        Target::Mean => expert.posterior_mean(x_t, t, false)? - &mu_base,
        Target::Score => expert.score(x_t, t)? - base.score(x_t, t)?,
    };
    let point = match eval_point {
        EvalPoint::XT => x_t.shallow_clone(),
        EvalPoint::MuBase => mu_base,
    };
    Ok((y.detach(), point.detach()))
}

/// Algorithm 1's batch at given draws: x_t = q_sample(x0, t, noise) under no-grad, then
/// [`target_and_point`]. The reward job passes its own Rng's draws; the PyTorch cross-check
/// (server/tests/training_vs_pytorch.rs) passes fixed ones, so both run this same code.
pub fn noised_target_and_point(
    base: &DiffusionModel,
    expert: &DiffusionModel,
    x0: &Tensor,
    t: &Tensor,
    noise: &Tensor,
    target: Target,
    eval_point: EvalPoint,
) -> Result<(Tensor, Tensor)> {
    let x_t = tch::no_grad(|| base.q_sample(x0, t, noise))?;
    target_and_point(base, expert, &x_t, t, target, eval_point)
}

/// || grad_x rho(point, t) - target ||^2 summed over an item, averaged over the batch, plus
/// the optional rho^2 penalty. Differentiable with respect to rho's parameters.
pub fn alignment_loss(reward: &RewardNet, point: &Tensor, t: &Tensor, target: &Tensor, rho_l2: f64) -> Result<Tensor> {
    let grad = reward.grad_create_graph(point, t)?;
    let per_item = (grad - target).square().flatten(1, -1).sum_dim_intlist(1, false, Kind::Float);
    let mut loss = per_item.mean(Kind::Float);
    if rho_l2 > 0.0 {
        loss += reward.rho(point, t)?.square().mean(Kind::Float) * rho_l2;
    }
    Ok(loss)
}

/// What a reward model is: stored as its record's manifest and next to its weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardManifest {
    pub architecture: RewardArchitecture,
    /// The space of the diffusion models it was extracted from (its input layout).
    pub space: Space,
    /// Their normalizer: rho takes normalized inputs.
    pub normalizer: Normalizer,
    pub n_timesteps: usize,
    /// The base model (for a discriminator: the diffusion model whose schedule and normalizer
    /// it shares).
    pub base_model: String,
    /// The expert model (empty for a discriminator).
    pub expert_model: String,
    pub datasets: Vec<String>,
    pub objective: Objective,
    /// Algorithm 2 only: rho's input at time t is the state standardised per element with the
    /// `input_mean[t]` and `input_std[t]` tables stored beside the weights
    /// (`step_norm.safetensors`), and its gradient targets were divided by `target_std[t]`.
    #[serde(default)]
    pub step_normalization: bool,
    pub final_loss: f64,
    pub eval_loss: Option<f64>,
}

/// How rho was trained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Objective {
    /// Gradient alignment (the paper's relative reward).
    Alignment { target: Target, eval_point: EvalPoint, models_only: bool },
    /// Binary cross-entropy, expert = 1 vs base = 0 (the paper's baseline).
    Discriminator,
}
