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
//! optionally with per-entry weights on the squared error ([`entry_weights`]): for trajectory
//! models, the first step's action and observation entries, as Diffuser weights its denoising
//! loss. Why a planner wants them: the target's action entries depend on the state (the
//! policy) while its state entries hardly depend on the action, and a gradient's Jacobian is
//! symmetric, so no rho fits both; an unweighted loss splits the error between the two blocks
//! (experiments/locomotion/diagnose.py measures both the asymmetry and the split).
//!
//! with x_eval = x_t (the paper's formula, default) or mu_base(x_t, t) (the authors' code).
//! Expert minus base, so grad rho points from base toward expert (docs/method.md section 1). Both
//! diffusion models are frozen and evaluated under no-grad; the loss reaches rho's parameters
//! through a double backward (grad_x computed with create_graph).
//!
//! Posterior means are taken without clipping x0_hat: the target is a property of the two
//! models' networks, and clipping would make it depend on where x0_hat leaves [-1, 1].
//!
//! **Models with different normalizers** (each trained on its own dataset, the usual case for
//! models a user brings) are aligned through raw coordinates ([`Alignment`]): everything is
//! computed in the base model's normalized units, the expert is called at x_t mapped into its
//! own units (raw = base.unnormalize(x_t), then expert.normalize(raw), an affine map per
//! coordinate), and its estimate of the clean data x0_hat, a point of data space, is mapped
//! back the same way. The expert's mean and score then follow from that x0_hat in the base's
//! units (mu = coef1 x0_hat + coef2 x_t; s = -eps / sqrt(1 - abar_t) with eps from x0_hat), so
//! an expert that denoises the same raw trajectories in other coordinates gives exactly the
//! shared-normalizer target (test `aligned_target_equals_the_shared_normalizer_target`). The
//! noise an expert was trained with is isotropic in *its* units, so a real expert trained in
//! other coordinates is a different process and the alignment is the best affine reading of
//! it, not an identity. rho lives in the base's units (its manifest records the base's
//! normalizer).

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

use super::diffusion::DiffusionModel;
use super::manifest::{RewardSignature, RewardUploadManifest, Space};
pub use super::nets::reward::alignment_error;
use super::nets::reward::{AlignmentGradients, RewardArchitecture, RewardNet};
use super::normalizer::{Normalize, Normalizer};
use super::optim::StepLoss;
use super::threads::side_by_side;
use crate::error::{Error, Result};
use relreward_proto::schema::recipe::RecipeManifest;

/// What grad rho is aligned with and where it is evaluated: the job spec's choices (shared
/// schema, `relreward_proto::schema::job`).
pub use relreward_proto::schema::job::{EvalPoint, Target};

/// Checks that two diffusion models can be compared: same item shape, same T and schedule.
/// Different normalizers are aligned ([`Alignment`]), except with identity on one side only
/// where no raw coordinates are known for the other.
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
    Ok(())
}

/// The map between the base model's and the expert's normalized units (module docs); `None`
/// when they share a normalizer.
pub struct Alignment {
    base: Normalizer,
    expert: Normalizer,
    /// Dimensions after the batch dimension that a normalizer coordinate spans.
    item_dims: usize,
}

impl Alignment {
    pub fn between(base: &DiffusionModel, expert: &DiffusionModel) -> Option<Self> {
        let (b, e) = (&base.manifest, &expert.manifest);
        (b.normalizer != e.normalizer).then(|| Self {
            base: b.normalizer.clone(),
            expert: e.normalizer.clone(),
            item_dims: b.space.normalizer_dims(),
        })
    }

    /// Base units -> expert units, through raw coordinates.
    pub fn to_expert(&self, x: &Tensor) -> Tensor {
        self.expert.normalize(&self.base.unnormalize(x, self.item_dims), self.item_dims)
    }

    /// Expert units -> base units, through raw coordinates.
    pub fn to_base(&self, x: &Tensor) -> Tensor {
        self.base.normalize(&self.expert.unnormalize(x, self.item_dims), self.item_dims)
    }
}

/// The expert's side of the target, computed from the expert alone (so that it can run on
/// another thread than the base's side): its posterior mean or score at x_t when the two
/// models share a normalizer, else its x0_hat at x_t mapped through raw coordinates into the
/// base's units (the base turns that into a mean or score, [`target_and_point`]).
enum ExpertSide {
    Output(Tensor),
    AlignedX0(Tensor),
}

fn expert_side(
    expert: &DiffusionModel,
    alignment: Option<&Alignment>,
    x_t: &Tensor,
    t: &Tensor,
    target: Target,
) -> Result<ExpertSide> {
    Ok(match (alignment, target) {
        (None, Target::Mean) => ExpertSide::Output(expert.posterior_mean(x_t, t, false)?),
        (None, Target::Score) => ExpertSide::Output(expert.score(x_t, t)?),
        (Some(a), _) => ExpertSide::AlignedX0(a.to_base(&expert.x0_hat(&a.to_expert(x_t), t, false)?)),
    })
}

/// The regression target and the evaluation point for a batch of x_t, under no-grad.
///
/// The base's and the expert's passes are independent, so on the CPU with two or more intra-op
/// threads they run side by side, one thread each ([`side_by_side`]); the numbers are those of
/// running them one after the other. The expert is borrowed mutably only because it is handed
/// to that other thread for the duration of the call.
pub fn target_and_point(
    base: &DiffusionModel,
    expert: &mut DiffusionModel,
    x_t: &Tensor,
    t: &Tensor,
    target: Target,
    eval_point: EvalPoint,
) -> Result<(Tensor, Tensor)> {
    let _guard = tch::no_grad_guard();
    let alignment = Alignment::between(base, expert);
    let parallel = x_t.device() == tch::Device::Cpu;
    let (x_e, t_e) = (x_t.shallow_clone(), t.shallow_clone());
    let (mu_base, side) = side_by_side(
        parallel,
        || base.posterior_mean(x_t, t, false),
        move || expert_side(expert, alignment.as_ref(), &x_e, &t_e, target),
    )?;
    let y = match (side, target) {
        (ExpertSide::Output(e), Target::Mean) => e - &mu_base,
        (ExpertSide::Output(e), Target::Score) => e - base.score(x_t, t)?,
        (ExpertSide::AlignedX0(x0), Target::Mean) => base.q_posterior_mean(&x0, x_t, t)? - &mu_base,
        (ExpertSide::AlignedX0(x0), Target::Score) => base.score_from_x0(x_t, t, &x0)? - base.score(x_t, t)?,
    };
    let point = match eval_point {
        EvalPoint::XT => x_t.shallow_clone(),
        EvalPoint::MuBase => mu_base,
    };
    Ok((y.detach(), point.detach()))
}

/// The entries of a trajectory item a planner conditions on by inpainting: the first step's
/// observation, as (offset, length) along the transition dimension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConditionEntries {
    offset: i64,
    len: i64,
}

impl ConditionEntries {
    /// The first observation of `space`'s items; an error naming `field` for a space without one.
    pub fn of(space: &Space, field: &str) -> Result<Self> {
        match *space {
            Space::Trajectory { action_dim, obs_dim, .. } => {
                Ok(Self { offset: action_dim as i64, len: obs_dim as i64 })
            }
            _ => Err(Error::invalid(format!(
                "{field}: only trajectory models have a first observation to inpaint; this space is {space:?}"
            ))),
        }
    }

    /// Copies these entries of `x0` into `x_t`, in place ([B, H, A + O] both).
    pub fn inpaint_(&self, x_t: &Tensor, x0: &Tensor) -> Result<()> {
        let clean = x0.f_narrow(1, 0, 1)?.f_narrow(2, self.offset, self.len)?;
        x_t.f_narrow(1, 0, 1)?.f_narrow(2, self.offset, self.len)?.f_copy_(&clean)?;
        Ok(())
    }
}

/// A training item's noised input: x_t = q_sample(x0, t, noise), under no-grad, with the
/// condition entries kept clean when given (`inpaint_condition`). Why: a planner that inpaints
/// its current state was trained, and plans, with that state clean at every t, so its outputs
/// on a noised state are outside what it learned (Diffuser's value training applies the same
/// conditioning to its noised input); the relative reward and the discriminator are then
/// fitted on the inputs they meet when guiding.
pub fn noised(
    model: &DiffusionModel,
    x0: &Tensor,
    t: &Tensor,
    noise: &Tensor,
    condition: Option<ConditionEntries>,
) -> Result<Tensor> {
    let _guard = tch::no_grad_guard();
    // q_sample's result is a fresh tensor, so the condition is written into it in place.
    let x_t = model.q_sample(x0, t, noise)?;
    if let Some(c) = condition {
        c.inpaint_(&x_t, x0)?;
    }
    Ok(x_t)
}

/// Algorithm 1's batch at given draws: x_t from [`noised`], then [`target_and_point`]. The
/// reward job passes its own Rng's draws; the PyTorch cross-check
/// (server/tests/training_vs_pytorch.rs) passes fixed ones, so both run this same code.
#[allow(clippy::too_many_arguments)]
pub fn noised_target_and_point(
    base: &DiffusionModel,
    expert: &mut DiffusionModel,
    x0: &Tensor,
    t: &Tensor,
    noise: &Tensor,
    condition: Option<ConditionEntries>,
    target: Target,
    eval_point: EvalPoint,
) -> Result<(Tensor, Tensor)> {
    let x_t = noised(base, x0, t, noise, condition)?;
    target_and_point(base, expert, &x_t, t, target, eval_point)
}

/// || grad_x rho(point, t) - target ||^2 summed over an item, averaged over the batch, plus
/// the optional rho^2 penalty, through autograd: differentiable with respect to rho's
/// parameters by its double backward. Training takes [`alignment_step`] (no autograd); this
/// is the reference its gradients are checked against (`nets/reward/tests.rs`).
pub fn alignment_loss(
    reward: &RewardNet,
    point: &Tensor,
    t: &Tensor,
    target: &Tensor,
    weights: Option<&Tensor>,
    rho_l2: f64,
) -> Result<Tensor> {
    let grad = reward.grad_create_graph(point, t)?;
    let mut loss = alignment_error(&grad, target, weights)?;
    if rho_l2 > 0.0 {
        loss += reward.rho(point, t)?.square().mean(None::<Kind>) * rho_l2;
    }
    Ok(loss)
}

/// One training step's [`alignment_loss`] as the optimizer takes it: the loss and its
/// parameter gradients computed without autograd ([`RewardNet::alignment_gradients`]: the MLP
/// heads in closed form, the convolutional rewards by reverse over forward sweeps).
pub fn alignment_step(
    reward: &RewardNet,
    point: &Tensor,
    t: &Tensor,
    target: &Tensor,
    weights: Option<&Tensor>,
    rho_l2: f64,
) -> Result<StepLoss> {
    let AlignmentGradients { loss, grads } = reward.alignment_gradients(point, t, target, weights, rho_l2)?;
    Ok(StepLoss::Computed { loss, grads })
}

/// What a reward model is: stored as its record's manifest and next to its weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardManifest {
    /// What computes rho: a built-in network (its weights beside the manifest), or an uploaded
    /// TorchScript module (a bring-your-own reward).
    pub architecture: RewardSource,
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
    /// Algorithm 2 only: rho's input at time t is the state standardised elementwise with the
    /// `input_mean[t]` and `input_std[t]` tables stored beside the weights
    /// (`step_norm.safetensors`), and its gradient targets were divided by `target_std[t]`.
    /// New rewards' scale tables hold one value per step, broadcast over the item (see
    /// `engine/reward_trainer.rs`, `step_stats`); rewards stored with per-element scales load unchanged.
    #[serde(default)]
    pub step_normalization: bool,
    /// Trained on x_t with the first observation clean (the job's `inpaint_condition`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub inpaint_condition: bool,
    /// How each side was sampled when it was a recipe (Algorithm 2 over a conditional model: a
    /// named recipe, or the job's own base_recipe / expert_recipe): provenance, reported in
    /// `Model.reward` and OIP's ModelConfig.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base_recipe: Option<RecipeManifest>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expert_recipe: Option<RecipeManifest>,
    pub final_loss: f64,
    pub eval_loss: Option<f64>,
}

/// Per-entry weights [H, A + O] of the alignment loss for a trajectory space: `action_weight`
/// on the first step's action entries, `condition_weight` on its observation entries, 1
/// elsewhere; None when both are 1 (the unweighted loss). `field` names the job's fields in
/// the error for a space without a first action and observation.
pub fn entry_weights(
    space: &Space,
    action_weight: f64,
    condition_weight: f64,
    device: Device,
    field: &str,
) -> Result<Option<Tensor>> {
    if action_weight == 1.0 && condition_weight == 1.0 {
        return Ok(None);
    }
    let Space::Trajectory { horizon, action_dim, obs_dim } = *space else {
        return Err(Error::invalid(format!(
            "{field}.action_weight / condition_weight: only trajectory models have a first action and observation; \
             this space is {space:?}"
        )));
    };
    let weights = Tensor::f_ones([horizon as i64, (action_dim + obs_dim) as i64], (Kind::Float, device))?;
    let _ = weights.f_narrow(0, 0, 1)?.f_narrow(1, 0, action_dim as i64)?.f_fill_(action_weight)?;
    let _ = weights.f_narrow(0, 0, 1)?.f_narrow(1, action_dim as i64, obs_dim as i64)?.f_fill_(condition_weight)?;
    Ok(Some(weights))
}

impl Objective {
    /// The paper's alignment objective: unweighted (entry weights 1).
    pub fn alignment(target: Target, eval_point: EvalPoint, models_only: bool) -> Self {
        Self::Alignment { target, eval_point, models_only, action_weight: 1.0, condition_weight: 1.0 }
    }
}

fn one() -> f64 {
    1.0
}

fn is_one(w: &f64) -> bool {
    *w == 1.0
}

/// What computes a stored reward: a built-in architecture with safetensors weights (what
/// training jobs write), or a bring-your-own TorchScript module. Stored under the manifest's
/// `architecture` key in either form, so the manifests of trained rewards read as before:
/// `{"kind": "windowed_mlp", ...}` or `{"kind": "torchscript", "signature": "rho" |
/// "value_function"}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum RewardSource {
    Native(RewardArchitecture),
    Uploaded(UploadedReward),
}

/// A bring-your-own reward's module (see [`RewardSource`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum UploadedReward {
    /// `module.pt`, called as its signature says.
    Torchscript { signature: RewardSignature },
}

impl From<RewardArchitecture> for RewardSource {
    fn from(a: RewardArchitecture) -> Self {
        Self::Native(a)
    }
}

impl std::fmt::Display for RewardSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Native(a) => a.fmt(f),
            Self::Uploaded(UploadedReward::Torchscript { signature }) => write!(f, "torchscript({signature})"),
        }
    }
}

impl RewardManifest {
    /// The stored manifest of a bring-your-own reward: what its upload states, the rest empty
    /// (no training data, objective [`Objective::Uploaded`], no losses).
    pub fn uploaded(m: &RewardUploadManifest) -> Self {
        Self {
            architecture: RewardSource::Uploaded(UploadedReward::Torchscript { signature: m.signature }),
            space: m.space.clone(),
            normalizer: m.normalizer.clone(),
            n_timesteps: m.n_timesteps,
            base_model: m.base_model.clone(),
            expert_model: String::new(),
            datasets: Vec::new(),
            objective: Objective::Uploaded,
            step_normalization: false,
            inpaint_condition: false,
            base_recipe: None,
            expert_recipe: None,
            final_loss: 0.0,
            eval_loss: None,
        }
    }
}

#[cfg(test)]
impl RewardManifest {
    /// A native reward's manifest for tests that build a `RewardModel` by hand: the network,
    /// its space, normalizer and T as given, the rest plain (no data, a discriminator
    /// objective, no step normalization); struct update syntax changes the rest.
    pub(crate) fn for_tests(
        architecture: RewardArchitecture,
        space: Space,
        normalizer: Normalizer,
        n_timesteps: usize,
    ) -> Self {
        Self {
            architecture: architecture.into(),
            space,
            normalizer,
            n_timesteps,
            base_model: "base".into(),
            expert_model: "expert".into(),
            datasets: vec![],
            objective: Objective::Discriminator,
            step_normalization: false,
            inpaint_condition: false,
            base_recipe: None,
            expert_recipe: None,
            final_loss: 0.0,
            eval_loss: None,
        }
    }
}

/// How rho was trained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Objective {
    /// Gradient alignment (the paper's relative reward), with the loss's entry weights
    /// ([`entry_weights`]; 1 and 1, the unweighted loss, are not written).
    Alignment {
        target: Target,
        eval_point: EvalPoint,
        models_only: bool,
        #[serde(default = "one", skip_serializing_if = "is_one")]
        action_weight: f64,
        #[serde(default = "one", skip_serializing_if = "is_one")]
        condition_weight: f64,
    },
    /// Binary cross-entropy, expert = 1 vs base = 0 (the paper's baseline).
    Discriminator,
    /// Not trained here: a bring-your-own reward uploaded as TorchScript (its `final_loss` is
    /// 0 and means nothing).
    Uploaded,
}

#[cfg(test)]
mod tests {
    use tch::{Kind, Tensor};

    use super::*;
    use crate::engine::denoiser::Denoiser;
    use crate::engine::manifest::{DiffusionManifest, Parametrization, ScheduleSpec, Space};

    /// A fixed nonlinear network: tanh(x W + 0.05 t) along the last dimension.
    struct Nonlinear {
        w: Tensor,
    }

    impl Denoiser for Nonlinear {
        fn forward(&self, x: &Tensor, t: &Tensor, _cond: Option<&Tensor>) -> Result<Tensor> {
            let tt = t.to_kind(Kind::Float).reshape([-1, 1, 1]) * 0.05;
            Ok((x.matmul(&self.w) + tt).tanh())
        }

        fn parameter_count(&self) -> u64 {
            0
        }
    }

    /// The same raw-space denoiser as `inner` (whose normalizer is `shared`), written in the
    /// units of another normalizer: x0-parametrized, pred(x') = M(x0_hat_inner(M^-1(x'))).
    struct InOtherUnits {
        inner: DiffusionModel,
        shared: Normalizer,
        other: Normalizer,
    }

    impl Denoiser for InOtherUnits {
        fn forward(&self, x: &Tensor, t: &Tensor, _cond: Option<&Tensor>) -> Result<Tensor> {
            let x_shared = self.shared.normalize(&self.other.unnormalize(x, 1), 1);
            let x0 = self.inner.x0_hat(&x_shared, t, false)?;
            Ok(self.other.normalize(&self.shared.unnormalize(&x0, 1), 1))
        }

        fn parameter_count(&self) -> u64 {
            0
        }
    }

    const SPACE: Space = Space::Trajectory { horizon: 4, action_dim: 1, obs_dim: 2 };

    fn manifest(parametrization: Parametrization, normalizer: Normalizer) -> DiffusionManifest {
        DiffusionManifest {
            parametrization,
            schedule: ScheduleSpec::Cosine { s: 0.008 },
            n_timesteps: 20,
            clip_denoised: false,
            space: SPACE,
            normalizer,
            architecture: None,
            conditioning: None,
        }
    }

    fn nonlinear(seed: i64, p: Parametrization, n: &Normalizer) -> DiffusionModel {
        tch::manual_seed(seed);
        let w = Tensor::randn([3, 3], (Kind::Float, tch::Device::Cpu)) * 0.5;
        DiffusionModel::new(manifest(p, n.clone()), Box::new(Nonlinear { w })).expect("model")
    }

    #[test]
    fn entry_weights_cover_the_first_action_and_observation_only() {
        let space = Space::Trajectory { horizon: 3, action_dim: 2, obs_dim: 3 };
        let cpu = tch::Device::Cpu;
        assert!(entry_weights(&space, 1.0, 1.0, cpu, "spec.reward").expect("unweighted").is_none());
        let w = entry_weights(&space, 10.0, 0.0, cpu, "spec.reward").expect("weights").expect("some");
        let expected = Tensor::from_slice(&[
            10.0f32, 10.0, 0.0, 0.0, 0.0, //
            1.0, 1.0, 1.0, 1.0, 1.0, //
            1.0, 1.0, 1.0, 1.0, 1.0,
        ])
        .reshape([3, 5]);
        assert_eq!(w.size(), [3, 5]);
        assert!(w.equal(&expected), "{w}");
        let err = entry_weights(&Space::Sample { shape: vec![2, 2] }, 2.0, 1.0, cpu, "spec.reward").unwrap_err();
        assert!(matches!(&err, Error::InvalidArgument(m) if m.starts_with("spec.reward.action_weight")), "{err}");
    }

    /// With the condition inpainted, x_t is q_sample's everywhere but the first observation,
    /// which is x0's; the target is the two models' difference at that x_t.
    #[test]
    fn inpainted_x_t_keeps_the_first_observation_clean_and_the_target_follows_it() {
        let n = Normalizer::Identity;
        let (base, mut expert) = (nonlinear(1, Parametrization::X0, &n), nonlinear(2, Parametrization::X0, &n));
        let x0 = Tensor::randn([5, 4, 3], (Kind::Float, tch::Device::Cpu));
        let noise = Tensor::randn([5, 4, 3], (Kind::Float, tch::Device::Cpu));
        let t = Tensor::from_slice(&[0i64, 3, 7, 12, 19]);
        let c = ConditionEntries::of(&SPACE, "spec.reward.inpaint_condition").expect("trajectory");
        let plain = noised(&base, &x0, &t, &noise, None).expect("plain");
        let clean = noised(&base, &x0, &t, &noise, Some(c)).expect("inpainted");
        // The first step's observation (entries 1..3 of row 0) is x0's, the rest q_sample's.
        assert!(clean.narrow(1, 0, 1).narrow(2, 1, 2).equal(&x0.narrow(1, 0, 1).narrow(2, 1, 2)));
        assert!(clean.narrow(1, 0, 1).narrow(2, 0, 1).equal(&plain.narrow(1, 0, 1).narrow(2, 0, 1)));
        assert!(clean.narrow(1, 1, 3).equal(&plain.narrow(1, 1, 3)));
        assert!(!clean.equal(&plain), "q_sample left the first observation unchanged: the test proves nothing");
        let (target, point) =
            noised_target_and_point(&base, &mut expert, &x0, &t, &noise, Some(c), Target::Mean, EvalPoint::XT)
                .expect("inpainted target");
        let (direct, _) =
            target_and_point(&base, &mut expert, &clean, &t, Target::Mean, EvalPoint::XT).expect("direct");
        assert!(point.equal(&clean) && target.equal(&direct));
        let err = ConditionEntries::of(&Space::Sample { shape: vec![3] }, "spec.reward.inpaint_condition").unwrap_err();
        assert!(matches!(&err, Error::InvalidArgument(m) if m.starts_with("spec.reward.inpaint_condition:")), "{err}");
    }

    #[test]
    fn objective_records_entry_weights_only_when_set() {
        let objective = |action_weight, condition_weight| Objective::Alignment {
            target: Target::Mean,
            eval_point: EvalPoint::XT,
            models_only: false,
            action_weight,
            condition_weight,
        };
        // Manifests written before the weights existed read as unweighted, and are written unchanged.
        let old = r#"{"kind":"alignment","target":"mean","eval_point":"x_t","models_only":false}"#;
        assert_eq!(serde_json::from_str::<Objective>(old).expect("old manifest"), objective(1.0, 1.0));
        assert_eq!(serde_json::to_string(&objective(1.0, 1.0)).expect("json"), old);
        let weighted = serde_json::to_string(&objective(10.0, 0.0)).expect("json");
        assert!(weighted.contains(r#""action_weight":10.0"#) && weighted.contains(r#""condition_weight":0.0"#));
        assert_eq!(serde_json::from_str::<Objective>(&weighted).expect("round trip"), objective(10.0, 0.0));
    }

    #[test]
    fn aligned_target_equals_the_shared_normalizer_target() {
        let shared = Normalizer::Limits { min: vec![-1.0, 0.0, -3.0], max: vec![1.0, 5.0, 2.0] };
        let other = Normalizer::Limits { min: vec![-2.0, -1.0, -3.5], max: vec![0.5, 9.0, 4.0] };
        let gaussian = Normalizer::Gaussian { mean: vec![0.3, 2.0, -1.0], std: vec![0.7, 3.0, 1.5] };
        tch::manual_seed(7);
        let x_t = Tensor::randn([16, 4, 3], (Kind::Float, tch::Device::Cpu));
        let t = Tensor::randint(20, [16], (Kind::Int64, tch::Device::Cpu));
        for p in [Parametrization::Epsilon, Parametrization::X0] {
            for theirs in [&other, &gaussian] {
                let base = nonlinear(1, Parametrization::Epsilon, &shared);
                let mut expert = nonlinear(2, p, &shared);
                let moved =
                    InOtherUnits { inner: nonlinear(2, p, &shared), shared: shared.clone(), other: theirs.clone() };
                let mut moved =
                    DiffusionModel::new(manifest(Parametrization::X0, theirs.clone()), Box::new(moved)).expect("m");
                check_pair(&base, &moved).expect("different normalizers are aligned, not refused");
                for target in [Target::Mean, Target::Score] {
                    for point in [EvalPoint::XT, EvalPoint::MuBase] {
                        let (y_shared, p_shared) =
                            target_and_point(&base, &mut expert, &x_t, &t, target, point).expect("s");
                        let (y_moved, p_moved) =
                            target_and_point(&base, &mut moved, &x_t, &t, target, point).expect("m");
                        let diff = f64::try_from((&y_shared - &y_moved).abs().max()).expect("max");
                        let scale = f64::try_from(y_shared.abs().max()).expect("max");
                        assert!(diff <= 1e-4 * scale.max(1.0), "{p:?} {target:?} {point:?}: {diff} (scale {scale})");
                        assert!(p_shared.allclose(&p_moved, 1e-6, 1e-6, false));
                    }
                }
                // Without the alignment the moved expert's outputs are in other units: the
                // naive difference is far from the shared target (the test can fail).
                let _g = tch::no_grad_guard();
                let naive = moved.posterior_mean(&x_t, &t, false).expect("m")
                    - base.posterior_mean(&x_t, &t, false).expect("b");
                let (y_shared, _) =
                    target_and_point(&base, &mut expert, &x_t, &t, Target::Mean, EvalPoint::XT).expect("s");
                let off = f64::try_from((&y_shared - &naive).abs().max()).expect("max");
                assert!(off > 1e-2, "{p:?}: the units did not matter ({off})");
            }
        }
    }

    #[test]
    fn alignment_maps_through_raw_coordinates() {
        let a = Normalizer::Limits { min: vec![0.0, -2.0], max: vec![4.0, 2.0] };
        let b = Normalizer::Gaussian { mean: vec![1.0, 0.0], std: vec![2.0, 0.5] };
        let base = DiffusionModel::new(
            DiffusionManifest {
                space: Space::Trajectory { horizon: 1, action_dim: 1, obs_dim: 1 },
                ..manifest(Parametrization::Epsilon, a)
            },
            Box::new(Nonlinear { w: Tensor::eye(2, (Kind::Float, tch::Device::Cpu)) }),
        )
        .expect("base");
        let expert = DiffusionModel::new(
            DiffusionManifest {
                space: Space::Trajectory { horizon: 1, action_dim: 1, obs_dim: 1 },
                ..manifest(Parametrization::Epsilon, b)
            },
            Box::new(Nonlinear { w: Tensor::eye(2, (Kind::Float, tch::Device::Cpu)) }),
        )
        .expect("expert");
        let al = Alignment::between(&base, &expert).expect("differ");
        // Base units (1, 0) = raw (4, 0) = expert units ((4 - 1) / 2, 0 / 0.5) = (1.5, 0).
        let x = Tensor::from_slice(&[1.0f32, 0.0]).reshape([1, 1, 2]);
        let e = al.to_expert(&x);
        assert!(e.allclose(&Tensor::from_slice(&[1.5f32, 0.0]).reshape([1, 1, 2]), 1e-6, 1e-6, false), "{e}");
        assert!(al.to_base(&e).allclose(&x, 1e-6, 1e-6, false));
        assert!(Alignment::between(&base, &base).is_none());
    }

    /// Trained rewards' stored manifests read as native architectures, as before
    /// `RewardSource`; a bring-your-own reward's as `{"kind": "torchscript", "signature"}`.
    #[test]
    fn reward_source_reads_old_manifests_and_writes_torchscript() {
        let native: RewardSource = serde_json::from_str(r#"{"kind": "mlp", "hidden": [8]}"#).expect("native");
        assert_eq!(native, RewardSource::Native(RewardArchitecture::Mlp { hidden: vec![8] }));
        let byo = RewardSource::Uploaded(UploadedReward::Torchscript { signature: RewardSignature::ValueFunction });
        let text = serde_json::to_string(&byo).expect("json");
        assert_eq!(text, r#"{"kind":"torchscript","signature":"value_function"}"#);
        assert_eq!(serde_json::from_str::<RewardSource>(&text).expect("back"), byo);
        assert_eq!(byo.to_string(), "torchscript(value_function)");
        assert!(serde_json::from_str::<RewardSource>(r#"{"kind": "torchscript"}"#).is_err(), "signature required");
    }
}
