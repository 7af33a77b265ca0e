//! Job specifications as the job system stores and runs them: every hyperparameter explicit,
//! defaults filled in at submission, so a stored job means the same thing forever (a later
//! change of defaults does not change a running job, and idempotent resubmission compares
//! complete specs).

use serde::{Deserialize, Serialize};

use crate::engine::manifest::{Architecture, Parametrization, ScheduleSpec};
use crate::engine::nets::reward::RewardArchitecture;
use crate::engine::relative_reward::{EvalPoint, Target};
use crate::engine::target_pool::AmortisedTargets;
use crate::error::{Error, Result};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    /// Name of the model a successful job registers.
    pub output_model: String,
    pub seed: u64,
    pub optimization: Optimization,
    pub kind: JobKind,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Optimization {
    pub steps: u64,
    pub batch_size: usize,
    pub learning_rate: f64,
    pub grad_clip: Option<f64>,
    pub ema_decay: f64,
    pub ema_every: u64,
    pub ema_start: u64,
    pub checkpoint_every: u64,
    pub eval_every: u64,
    pub log_every: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum JobKind {
    Diffusion(DiffusionJob),
    Reward(RewardJob),
    Discriminator(DiscriminatorJob),
}

/// The paper's baseline: a classifier of base vs expert items with the reward's architecture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiscriminatorJob {
    pub base_dataset: String,
    pub expert_dataset: String,
    pub architecture: RewardArchitecture,
    /// The diffusion model whose schedule (for noising) and normalizer it shares.
    pub diffusion_model: String,
    /// Trained on x_t with the first observation clean, as the reward job's option.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub inpaint_condition: bool,
}

impl JobKind {
    pub fn name(&self) -> &'static str {
        match self {
            Self::Diffusion(_) => "diffusion",
            Self::Reward(_) => "reward",
            Self::Discriminator(_) => "discriminator",
        }
    }
}

/// Extract a relative reward from a base and an expert diffusion model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RewardJob {
    pub base_model: String,
    pub expert_model: String,
    pub architecture: RewardArchitecture,
    pub target: Target,
    pub eval_point: EvalPoint,
    pub algorithm: RewardAlgorithm,
    /// Weight of the rho^2 regularizer (0: off).
    pub rho_l2: f64,
    /// Algorithm 1's amortised targets (None: off, targets computed for every batch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub amortised_targets: Option<AmortisedTargets>,
    /// Weights of the first step's action and observation entries in the alignment loss
    /// (trajectory models; 1 and 1: unweighted). See `engine::relative_reward::entry_weights`.
    #[serde(default = "one")]
    pub action_weight: f64,
    #[serde(default = "one")]
    pub condition_weight: f64,
    /// Algorithm 1 on x_t with the first observation clean (trajectory models; see
    /// `engine::relative_reward::noised`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub inpaint_condition: bool,
}

/// Serde's default for weights that jobs stored before they existed did not carry.
fn one() -> f64 {
    1.0
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum RewardAlgorithm {
    /// Algorithm 1: x_t from the forward process on these datasets' items (their union).
    WithDataset { datasets: Vec<String> },
    /// Algorithm 2: pairs from `num_chains` chains run from noise, half following each model.
    ModelsOnly { num_chains: usize },
}

/// Train a native diffusion model on a dataset with the DDPM loss.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiffusionJob {
    pub dataset: String,
    pub parametrization: Parametrization,
    pub schedule: ScheduleSpec,
    pub n_timesteps: usize,
    /// Sub-trajectory length H (trajectory datasets).
    pub horizon: usize,
    pub architecture: Architecture,
    /// Diffuser's weight on the first action's loss (1: none).
    pub action_weight: f64,
    pub clip_denoised: bool,
    /// More datasets the normalizer is computed over, with `dataset` (see the proto).
    #[serde(default)]
    pub normalizer_datasets: Vec<String>,
    /// Sample datasets: one mean and std over every element (see the proto).
    #[serde(default)]
    pub pooled_normalizer: bool,
}

impl JobSpec {
    /// Names of the datasets and models the job reads.
    pub fn inputs(&self) -> Vec<String> {
        match &self.kind {
            JobKind::Diffusion(d) => std::iter::once(&d.dataset).chain(&d.normalizer_datasets).cloned().collect(),
            JobKind::Reward(r) => {
                let mut v = vec![r.base_model.clone(), r.expert_model.clone()];
                if let RewardAlgorithm::WithDataset { datasets } = &r.algorithm {
                    v.extend(datasets.iter().cloned());
                }
                v
            }
            JobKind::Discriminator(d) => {
                vec![d.diffusion_model.clone(), d.base_dataset.clone(), d.expert_dataset.clone()]
            }
        }
    }

    /// Range checks that need no stored data (existence and shapes are checked by the
    /// manager against the store).
    pub fn validate(&self) -> Result<()> {
        let o = &self.optimization;
        let positive = [
            ("spec.optimization.steps", o.steps),
            ("spec.optimization.batch_size", o.batch_size as u64),
            ("spec.optimization.ema_every", o.ema_every),
            ("spec.optimization.checkpoint_every", o.checkpoint_every),
            ("spec.optimization.eval_every", o.eval_every),
            ("spec.optimization.log_every", o.log_every),
        ];
        for (field, v) in positive {
            if v == 0 {
                return Err(Error::invalid(format!("{field}: must be positive")));
            }
        }
        if o.steps > 100_000_000 {
            return Err(Error::invalid(format!("spec.optimization.steps: {} is above 1e8", o.steps)));
        }
        if o.batch_size > 1 << 16 {
            return Err(Error::invalid(format!("spec.optimization.batch_size: {} is above 65536", o.batch_size)));
        }
        if !(o.learning_rate.is_finite() && o.learning_rate > 0.0 && o.learning_rate < 1.0) {
            return Err(Error::invalid(format!(
                "spec.optimization.learning_rate: {} is not in (0, 1)",
                crate::fields::number(o.learning_rate)
            )));
        }
        if let Some(c) = o.grad_clip
            && !(c.is_finite() && c > 0.0)
        {
            return Err(Error::invalid(format!(
                "spec.optimization.grad_clip: {} must be positive",
                crate::fields::number(c)
            )));
        }
        if !(0.0..1.0).contains(&o.ema_decay) {
            return Err(Error::invalid(format!(
                "spec.optimization.ema_decay: {} is not in [0, 1)",
                crate::fields::number(o.ema_decay)
            )));
        }
        match &self.kind {
            JobKind::Diffusion(d) => {
                if d.horizon == 0 || d.horizon > 4096 {
                    return Err(Error::invalid(format!("spec.diffusion.horizon: {} is outside 1..=4096", d.horizon)));
                }
                if !(d.action_weight.is_finite() && d.action_weight > 0.0) {
                    return Err(Error::invalid(format!(
                        "spec.diffusion.action_weight: {} must be positive",
                        crate::fields::number(d.action_weight)
                    )));
                }
            }
            JobKind::Reward(r) => {
                if !(r.rho_l2.is_finite() && r.rho_l2 >= 0.0) {
                    return Err(Error::invalid(format!(
                        "spec.reward.rho_l2: {} must be zero or positive",
                        crate::fields::number(r.rho_l2)
                    )));
                }
                for (field, w) in [("action_weight", r.action_weight), ("condition_weight", r.condition_weight)] {
                    if !(w.is_finite() && w >= 0.0) {
                        return Err(Error::invalid(format!(
                            "spec.reward.{field}: {} must be finite and zero or positive",
                            crate::fields::number(w)
                        )));
                    }
                }
                match &r.algorithm {
                    RewardAlgorithm::WithDataset { datasets } if datasets.is_empty() => {
                        return Err(Error::invalid("spec.reward.with_dataset.datasets: name at least one dataset"));
                    }
                    RewardAlgorithm::ModelsOnly { num_chains } if *num_chains < 2 || *num_chains > 1 << 16 => {
                        return Err(Error::invalid(format!(
                            "spec.reward.models_only.num_chains: {num_chains} is outside 2..=65536"
                        )));
                    }
                    _ => {}
                }
                if r.inpaint_condition && matches!(r.algorithm, RewardAlgorithm::ModelsOnly { .. }) {
                    return Err(Error::invalid(
                        "spec.reward.inpaint_condition: applies to with_dataset (Algorithm 1) only; models_only draws x_t from the models' own chains",
                    ));
                }
                if let Some(a) = &r.amortised_targets {
                    a.validate()?;
                    if matches!(r.algorithm, RewardAlgorithm::ModelsOnly { .. }) {
                        return Err(Error::invalid(
                            "spec.reward.amortised_targets: applies to with_dataset (Algorithm 1) only; models_only already computes its pairs once",
                        ));
                    }
                }
            }
            JobKind::Discriminator(_) => {}
        }
        Ok(())
    }
}
