//! The training job spec, in its two forms and the one rule between them:
//!
//! - [`request`]: what a user writes (the `train --config` file, flags, the Python specs): every
//!   field optional, mirroring the proto `JobSpec`, sent with unset fields left unset.
//! - [`JobSpec`]: what the server stores and runs: every hyperparameter explicit, so a stored job
//!   means the same thing forever (a later change of defaults does not change a running job, and
//!   idempotent resubmission compares complete specs).
//! - [`JobSpec::from_proto`] fills every unset field with its default: the constants below (the
//!   paper's and Diffuser's settings, stated once) and, where the default depends on stored data
//!   the server looked up, [`Facts`].

use std::fmt;

use serde::{Deserialize, Serialize};

use super::manifest::{Architecture, DEFAULT_COSINE_S, Parametrization, ScheduleSpec, Space};
use super::recipe::RecipeSpec;
use super::{Invalid, invalid, known, or_default, wire_u32, wire_u32s};
use crate::given_number;
use crate::v1 as pb;

pub mod request;

// ---------------------------------------------------------------------------------------------
// Defaults

/// Optimisation settings a job kind defaults to (the rest: [`Optimization::DEFAULT_EMA_DECAY`]
/// and the other shared constants).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KindDefaults {
    pub steps: u64,
    pub batch_size: usize,
    pub learning_rate: f64,
}

/// Diffusion jobs: Diffuser's configs (batch 32, learning rate 2e-4), 10k steps.
pub const DIFFUSION_OPTIMIZATION: KindDefaults = KindDefaults { steps: 10_000, batch_size: 32, learning_rate: 2e-4 };
/// Reward jobs: the paper's maze reward nets (100k steps, batch 256, learning rate 5e-5).
pub const REWARD_OPTIMIZATION: KindDefaults = KindDefaults { steps: 100_000, batch_size: 256, learning_rate: 5e-5 };
/// Discriminator jobs: the same settings as the reward they are compared with.
pub const DISCRIMINATOR_OPTIMIZATION: KindDefaults = REWARD_OPTIMIZATION;

/// Diffusion jobs: x0-prediction with Diffuser's cosine schedule, T = 20, H = 32, the first
/// action unweighted, denoised estimates clipped (Diffuser's maze configs).
pub const DEFAULT_PARAMETRIZATION: Parametrization = Parametrization::X0;
pub const DEFAULT_SCHEDULE: ScheduleSpec = ScheduleSpec::DiffuserCosine { s: DEFAULT_COSINE_S };
pub const DEFAULT_N_TIMESTEPS: usize = 20;
pub const DEFAULT_HORIZON: usize = 32;
pub const DEFAULT_CLIP_DENOISED: bool = true;

/// Reward jobs, Algorithm 2: chains run from noise, half following each model.
pub const DEFAULT_NUM_CHAINS: usize = 1024;

/// Reward architecture widths when a kind is named without them: the paper's maze nets
/// (window 4, hidden (128, 64, 32)), locomotion nets (64, 64, 128, 128) and Stable Diffusion
/// latent nets (32, 64, 128, 256).
pub const DEFAULT_WINDOW: usize = 4;
pub const DEFAULT_WINDOWED_HIDDEN: [usize; 3] = [128, 64, 32];
pub const DEFAULT_VALUE_FUNCTION_WIDTHS: [usize; 4] = [64, 64, 128, 128];
pub const DEFAULT_CONV_ENCODER_WIDTHS: [usize; 4] = [32, 64, 128, 256];
pub const DEFAULT_REWARD_MLP_HIDDEN: [usize; 3] = [128, 64, 32];

// ---------------------------------------------------------------------------------------------
// The stored spec

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

impl Optimization {
    /// Diffuser's trainer: EMA 0.995 every 10 steps from step 2000.
    pub const DEFAULT_EMA_DECAY: f64 = 0.995;
    pub const DEFAULT_EMA_EVERY: u64 = 10;
    pub const DEFAULT_EMA_START: u64 = 2000;
    pub const DEFAULT_CHECKPOINT_EVERY: u64 = 1000;
    pub const DEFAULT_EVAL_EVERY: u64 = 500;
    pub const DEFAULT_LOG_EVERY: u64 = 10;

    /// The wire's settings with a kind's defaults for what is unset.
    pub fn from_proto(o: &pb::Optimization, d: KindDefaults) -> Self {
        Self {
            steps: o.steps.unwrap_or(d.steps),
            batch_size: o.batch_size.map_or(d.batch_size, |b| b as usize),
            learning_rate: o.learning_rate.unwrap_or(d.learning_rate),
            grad_clip: o.grad_clip,
            ema_decay: o.ema_decay.unwrap_or(Self::DEFAULT_EMA_DECAY),
            ema_every: o.ema_every.map_or(Self::DEFAULT_EMA_EVERY, u64::from),
            ema_start: o.ema_start.unwrap_or(Self::DEFAULT_EMA_START),
            checkpoint_every: o.checkpoint_every.unwrap_or(Self::DEFAULT_CHECKPOINT_EVERY),
            eval_every: o.eval_every.unwrap_or(Self::DEFAULT_EVAL_EVERY),
            log_every: o.log_every.unwrap_or(Self::DEFAULT_LOG_EVERY),
        }
    }

    pub fn to_proto(&self) -> pb::Optimization {
        pb::Optimization {
            steps: Some(self.steps),
            batch_size: Some(wire_u32(self.batch_size)),
            learning_rate: Some(self.learning_rate),
            grad_clip: self.grad_clip,
            ema_decay: Some(self.ema_decay),
            ema_every: Some(u32::try_from(self.ema_every).unwrap_or(u32::MAX)),
            ema_start: Some(self.ema_start),
            checkpoint_every: Some(self.checkpoint_every),
            eval_every: Some(self.eval_every),
            log_every: Some(self.log_every),
        }
    }

    fn validate(&self) -> Result<(), Invalid> {
        let positive = [
            ("spec.optimization.steps", self.steps),
            ("spec.optimization.batch_size", self.batch_size as u64),
            ("spec.optimization.ema_every", self.ema_every),
            ("spec.optimization.checkpoint_every", self.checkpoint_every),
            ("spec.optimization.eval_every", self.eval_every),
            ("spec.optimization.log_every", self.log_every),
        ];
        if let Some((field, _)) = positive.iter().find(|(_, v)| *v == 0) {
            return invalid(format!("{field}: must be positive"));
        }
        if self.steps > 100_000_000 {
            return invalid(format!("spec.optimization.steps: {} is above 1e8", self.steps));
        }
        if self.batch_size > 1 << 16 {
            return invalid(format!("spec.optimization.batch_size: {} is above 65536", self.batch_size));
        }
        let lr = self.learning_rate;
        if !(lr.is_finite() && lr > 0.0 && lr < 1.0) {
            return invalid(format!("spec.optimization.learning_rate: {} is not in (0, 1)", given_number(lr)));
        }
        if let Some(c) = self.grad_clip
            && !(c.is_finite() && c > 0.0)
        {
            return invalid(format!("spec.optimization.grad_clip: {} must be positive", given_number(c)));
        }
        if !(0.0..1.0).contains(&self.ema_decay) {
            return invalid(format!("spec.optimization.ema_decay: {} is not in [0, 1)", given_number(self.ema_decay)));
        }
        Ok(())
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum JobKind {
    Diffusion(DiffusionJob),
    Reward(RewardJob),
    Discriminator(DiscriminatorJob),
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
    /// Class-conditional training on the datasets' labels (see the proto); the two settings
    /// below apply only with it (and are refused without it).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub conditional: bool,
    /// Probability of the null label in training (classifier-free guidance).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub condition_dropout: Option<f64>,
    /// Real classes C (None: the largest label of the datasets + 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub num_classes: Option<usize>,
}

/// Ho & Salimans' condition dropout (their 0.1 to 0.2; diffusers' training examples 0.1).
pub const DEFAULT_CONDITION_DROPOUT: f64 = 0.1;

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
    /// (trajectory models; 1 and 1: unweighted). See the server's `engine::relative_reward`.
    #[serde(default = "one")]
    pub action_weight: f64,
    #[serde(default = "one")]
    pub condition_weight: f64,
    /// Algorithm 1 on x_t with the first observation clean (trajectory models).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub inpaint_condition: bool,
    /// Algorithm 2 with conditional models: how each side is sampled (see the proto).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base_recipe: Option<RecipeSpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expert_recipe: Option<RecipeSpec>,
}

/// Serde's default for weights that jobs stored before they existed did not carry.
fn one() -> f64 {
    1.0
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

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum RewardAlgorithm {
    /// Algorithm 1: x_t from the forward process on these datasets' items (their union).
    WithDataset { datasets: Vec<String> },
    /// Algorithm 2: pairs from `num_chains` chains run from noise, half following each model.
    ModelsOnly { num_chains: usize },
}

/// What grad rho is aligned with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Target {
    /// mu_expert - mu_base (the default).
    Mean,
    /// s_expert - s_base.
    Score,
}

/// Where grad rho is evaluated: `x_t` or `mu_base` in files, flags and stored specs alike.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum EvalPoint {
    /// At x_t, as in the paper's formula (the default).
    #[serde(rename = "x_t")]
    #[cfg_attr(feature = "clap", value(name = "x_t"))]
    XT,
    /// At mu_base(x_t, t), as in the authors' code.
    #[serde(rename = "mu_base")]
    #[cfg_attr(feature = "clap", value(name = "mu_base"))]
    MuBase,
}

impl Target {
    pub fn to_proto(self) -> pb::RewardTarget {
        match self {
            Self::Mean => pb::RewardTarget::Mean,
            Self::Score => pb::RewardTarget::Score,
        }
    }

    /// From the wire; UNSPECIFIED is the default, `Mean`.
    pub fn from_proto(v: i32, field: &str) -> Result<Self, Invalid> {
        Ok(match known(field, v, "REWARD_TARGET_MEAN or REWARD_TARGET_SCORE")? {
            pb::RewardTarget::Unspecified | pb::RewardTarget::Mean => Self::Mean,
            pb::RewardTarget::Score => Self::Score,
        })
    }
}

impl EvalPoint {
    pub fn to_proto(self) -> pb::EvalPoint {
        match self {
            Self::XT => pb::EvalPoint::XT,
            Self::MuBase => pb::EvalPoint::MuBase,
        }
    }

    /// From the wire; UNSPECIFIED is the default, `XT`.
    pub fn from_proto(v: i32, field: &str) -> Result<Self, Invalid> {
        Ok(match known(field, v, "EVAL_POINT_X_T or EVAL_POINT_MU_BASE")? {
            pb::EvalPoint::Unspecified | pb::EvalPoint::XT => Self::XT,
            pb::EvalPoint::MuBase => Self::MuBase,
        })
    }
}

/// The architecture of a relative reward network rho(x, t) (the server's
/// `engine/nets/reward/` builds it). A width left out takes the `DEFAULT_*` value.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RewardArchitecture {
    /// An MLP over windows of `window` transitions of a trajectory [H, D]; rho is the mean over
    /// the H / window non-overlapping windows. The paper's maze nets: window 64, hidden (32,)
    /// (open maze) and window 4, hidden (128, 64, 32) (the others).
    WindowedMlp {
        #[serde(default = "default_window")]
        window: usize,
        #[serde(default = "default_windowed_hidden")]
        hidden: Vec<usize>,
    },
    /// Diffuser's ValueFunction (the TemporalUnet's down path) over a trajectory [H, D], with
    /// the channels after each level. The paper's locomotion nets: (64, 64, 128, 128).
    ValueFunction {
        #[serde(default = "default_value_function_widths")]
        widths: Vec<usize>,
    },
    /// A strided 2D convolutional encoder over image-like items [C, H, W], one stride-2 block per
    /// width. The paper's Stable Diffusion latent nets: (32, 64, 128, 256).
    ConvEncoder {
        #[serde(default = "default_conv_encoder_widths")]
        widths: Vec<usize>,
    },
    /// An MLP over flattened samples of any shape.
    Mlp {
        #[serde(default = "default_reward_mlp_hidden")]
        hidden: Vec<usize>,
    },
}

fn default_window() -> usize {
    DEFAULT_WINDOW
}
fn default_windowed_hidden() -> Vec<usize> {
    DEFAULT_WINDOWED_HIDDEN.to_vec()
}
fn default_value_function_widths() -> Vec<usize> {
    DEFAULT_VALUE_FUNCTION_WIDTHS.to_vec()
}
fn default_conv_encoder_widths() -> Vec<usize> {
    DEFAULT_CONV_ENCODER_WIDTHS.to_vec()
}
fn default_reward_mlp_hidden() -> Vec<usize> {
    DEFAULT_REWARD_MLP_HIDDEN.to_vec()
}

impl fmt::Display for RewardArchitecture {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::WindowedMlp { window, hidden } => write!(f, "windowed_mlp(h={window}, hidden={hidden:?})"),
            Self::ValueFunction { widths } => write!(f, "value_function(widths={widths:?})"),
            Self::ConvEncoder { widths } => write!(f, "conv_encoder(widths={widths:?})"),
            Self::Mlp { hidden } => write!(f, "mlp(hidden={hidden:?})"),
        }
    }
}

impl RewardArchitecture {
    /// The paper's network for a pair of models in `space`: the maze's windowed MLP over
    /// trajectories (window 4 where it divides the horizon, else 1), the latent convolutional
    /// encoder over [C, H, W] samples, an MLP over other samples.
    pub fn default_for(space: &Space) -> Self {
        match space {
            Space::Trajectory { horizon, .. } => Self::WindowedMlp {
                window: if horizon % DEFAULT_WINDOW == 0 { DEFAULT_WINDOW } else { 1 },
                hidden: DEFAULT_WINDOWED_HIDDEN.to_vec(),
            },
            Space::Sample { shape } if shape.len() == 3 => {
                Self::ConvEncoder { widths: DEFAULT_CONV_ENCODER_WIDTHS.to_vec() }
            }
            Space::Sample { .. } => Self::Mlp { hidden: DEFAULT_REWARD_MLP_HIDDEN.to_vec() },
        }
    }

    /// From the wire: unset, the default for the models' `space`; a kind with widths unset, the
    /// `DEFAULT_*` widths of that kind.
    pub fn from_proto(a: Option<pb::RewardArchitecture>, space: &Space) -> Self {
        use pb::reward_architecture::Kind;
        match a.and_then(|a| a.kind) {
            None => Self::default_for(space),
            Some(Kind::WindowedMlp(w)) => Self::WindowedMlp {
                window: w.window.map_or(DEFAULT_WINDOW, |v| v as usize),
                hidden: or_default(&w.hidden, &DEFAULT_WINDOWED_HIDDEN),
            },
            Some(Kind::ValueFunction(v)) => {
                Self::ValueFunction { widths: or_default(&v.widths, &DEFAULT_VALUE_FUNCTION_WIDTHS) }
            }
            Some(Kind::ConvEncoder(c)) => {
                Self::ConvEncoder { widths: or_default(&c.widths, &DEFAULT_CONV_ENCODER_WIDTHS) }
            }
            Some(Kind::Mlp(m)) => Self::Mlp { hidden: or_default(&m.hidden, &DEFAULT_REWARD_MLP_HIDDEN) },
        }
    }

    pub fn to_proto(&self) -> pb::RewardArchitecture {
        use pb::reward_architecture::{ConvEncoder, Kind, ValueFunction, WindowedMlp};
        let kind = match self {
            Self::WindowedMlp { window, hidden } => {
                Kind::WindowedMlp(WindowedMlp { window: Some(wire_u32(*window)), hidden: wire_u32s(hidden) })
            }
            Self::ValueFunction { widths } => Kind::ValueFunction(ValueFunction { widths: wire_u32s(widths) }),
            Self::ConvEncoder { widths } => Kind::ConvEncoder(ConvEncoder { widths: wire_u32s(widths) }),
            Self::Mlp { hidden } => Kind::Mlp(pb::Mlp { hidden: wire_u32s(hidden) }),
        };
        pb::RewardArchitecture { kind: Some(kind) }
    }
}

/// Settings of the amortised-target option (`TrainReward.amortised_targets`); the server's
/// `engine/target_pool.rs` runs it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AmortisedTargets {
    /// Triples held in the pool.
    pub pool_size: usize,
    /// Expected uses of each triple per epoch.
    pub reuse: u32,
    /// Fraction of the pool replaced after every epoch, in (0, 1].
    pub refresh_fraction: f64,
}

/// The most bytes an amortised-target pool's two float tensors (targets and evaluation points)
/// may take.
pub const MAX_POOL_BYTES: u64 = 2 << 30;

impl AmortisedTargets {
    /// 16384 triples, 4 uses per epoch, a quarter refreshed per epoch: each triple is used
    /// about 16 times and the models see 1/16 of the per-step recipe's items.
    pub const DEFAULT: Self = Self { pool_size: 16384, reuse: 4, refresh_fraction: 0.25 };

    /// From the wire, unset fields from [`AmortisedTargets::DEFAULT`].
    pub fn from_proto(a: &pb::AmortisedTargets) -> Self {
        let d = Self::DEFAULT;
        Self {
            pool_size: a.pool_size.map_or(d.pool_size, |v| v as usize),
            reuse: a.reuse.unwrap_or(d.reuse),
            refresh_fraction: a.refresh_fraction.unwrap_or(d.refresh_fraction),
        }
    }

    pub fn to_proto(&self) -> pb::AmortisedTargets {
        pb::AmortisedTargets {
            pool_size: Some(wire_u32(self.pool_size)),
            reuse: Some(self.reuse),
            refresh_fraction: Some(self.refresh_fraction),
        }
    }

    /// Range checks (field names as the wire's).
    pub fn validate(&self) -> Result<(), Invalid> {
        let field = "spec.reward.amortised_targets";
        if self.pool_size == 0 || self.pool_size > 1 << 22 {
            return invalid(format!("{field}.pool_size: {} is outside 1..=4194304", self.pool_size));
        }
        if self.reuse == 0 || self.reuse > 1024 {
            return invalid(format!("{field}.reuse: {} is outside 1..=1024", self.reuse));
        }
        let f = self.refresh_fraction;
        if !(f.is_finite() && f > 0.0 && f <= 1.0) {
            return invalid(format!("{field}.refresh_fraction: {} is not in (0, 1]", given_number(f)));
        }
        Ok(())
    }

    /// Checks the pool's memory for items of `item_numel` floats.
    pub fn check_memory(&self, item_numel: usize) -> Result<(), Invalid> {
        let bytes = 2 * 4 * self.pool_size as u64 * item_numel as u64;
        if bytes > MAX_POOL_BYTES {
            return invalid(format!(
                "spec.reward.amortised_targets.pool_size: {} items of {item_numel} floats need {:.2} GiB, above the {} GiB limit",
                self.pool_size,
                bytes as f64 / (1u64 << 30) as f64,
                MAX_POOL_BYTES >> 30
            ));
        }
        Ok(())
    }

    /// Slots refreshed per epoch (at least one).
    pub fn refresh_items(&self) -> usize {
        ((self.pool_size as f64 * self.refresh_fraction).ceil() as usize).clamp(1, self.pool_size)
    }

    /// Training steps per epoch at this batch size (at least one).
    pub fn steps_per_epoch(&self, batch: usize) -> u64 {
        ((self.pool_size as u64 * u64::from(self.reuse)).div_ceil(batch.max(1) as u64)).max(1)
    }
}

// ---------------------------------------------------------------------------------------------
// Defaults that depend on stored data

/// What the server looked up before filling a spec's defaults: the kind of a diffusion job's
/// dataset, the item space of a reward job's base model or a discriminator's diffusion model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Facts {
    /// A diffusion job's dataset holds trajectories (`true`) or fixed-shape samples.
    Dataset { name: String, trajectories: bool },
    /// The space of the diffusion model a reward or discriminator job reads.
    Models { space: Space },
}

impl JobSpec {
    /// The stored spec for a submitted one: every unset field filled with its default, then
    /// range-checked. `facts` are what the server looked up for this kind (see [`Facts`]).
    /// Checks of names and of the stored inputs' existence are the server's, before this.
    pub fn from_proto(spec: pb::JobSpec, facts: &Facts) -> Result<Self, Invalid> {
        use pb::job_spec::Kind;
        let kind =
            spec.kind.ok_or_else(|| Invalid("spec.kind: none of diffusion, reward or discriminator is set".into()))?;
        let o = spec.optimization.unwrap_or_default();
        let (optimization, kind) = match (kind, facts) {
            (Kind::Diffusion(d), Facts::Dataset { name, trajectories }) => {
                // Checked here, where "unset" is still visible: the stored spec holds the
                // effective horizon, as resubmissions compare against it.
                if let (false, Some(h)) = (*trajectories, d.horizon) {
                    return invalid(format!(
                        "spec.diffusion.horizon: {h} applies to trajectories only (the sub-trajectory length); '{name}' holds samples of a fixed shape"
                    ));
                }
                let job = DiffusionJob {
                    dataset: d.dataset,
                    parametrization: Parametrization::from_proto(d.parametrization, "spec.diffusion.parametrization")?
                        .unwrap_or(DEFAULT_PARAMETRIZATION),
                    schedule: match d.schedule {
                        None => DEFAULT_SCHEDULE,
                        some => ScheduleSpec::from_proto(some, "spec.diffusion.schedule")?,
                    },
                    n_timesteps: d.n_timesteps.map_or(DEFAULT_N_TIMESTEPS, |t| t as usize),
                    horizon: d.horizon.map_or(DEFAULT_HORIZON, |h| h as usize),
                    architecture: d
                        .architecture
                        .map_or_else(|| Architecture::default_for(*trajectories), Architecture::from_train_proto),
                    action_weight: d.action_weight.unwrap_or(1.0),
                    clip_denoised: d.clip_denoised.unwrap_or(DEFAULT_CLIP_DENOISED),
                    normalizer_datasets: d.normalizer_datasets,
                    pooled_normalizer: d.pooled_normalizer.unwrap_or(false),
                    conditional: d.conditional.unwrap_or(false),
                    condition_dropout: match d.conditional {
                        Some(true) => Some(d.condition_dropout.unwrap_or(DEFAULT_CONDITION_DROPOUT)),
                        _ => d.condition_dropout,
                    },
                    num_classes: d.num_classes.map(|c| c as usize),
                };
                if let (true, true) = (*trajectories, job.conditional) {
                    return invalid(format!(
                        "spec.diffusion.conditional: '{name}' holds trajectories; class-conditional training takes a sample dataset with labels"
                    ));
                }
                (Optimization::from_proto(&o, DIFFUSION_OPTIMIZATION), JobKind::Diffusion(job))
            }
            (Kind::Reward(r), Facts::Models { space }) => {
                let algorithm = match r.algorithm {
                    Some(pb::train_reward::Algorithm::WithDataset(w)) => {
                        RewardAlgorithm::WithDataset { datasets: w.datasets }
                    }
                    Some(pb::train_reward::Algorithm::ModelsOnly(m)) => RewardAlgorithm::ModelsOnly {
                        num_chains: m.num_chains.map_or(DEFAULT_NUM_CHAINS, |k| k as usize),
                    },
                    None => {
                        return invalid(
                            "spec.reward.algorithm: set with_dataset (Algorithm 1) or models_only (Algorithm 2)",
                        );
                    }
                };
                let job = RewardJob {
                    architecture: RewardArchitecture::from_proto(r.architecture, space),
                    target: Target::from_proto(r.target, "spec.reward.target")?,
                    eval_point: EvalPoint::from_proto(r.eval_point, "spec.reward.eval_point")?,
                    algorithm,
                    rho_l2: r.rho_l2.unwrap_or(0.0),
                    action_weight: r.action_weight.unwrap_or(1.0),
                    condition_weight: r.condition_weight.unwrap_or(1.0),
                    inpaint_condition: r.inpaint_condition.unwrap_or(false),
                    base_recipe: r
                        .base_recipe
                        .as_ref()
                        .map(|x| RecipeSpec::from_proto(x, "spec.reward.base_recipe"))
                        .transpose()?,
                    expert_recipe: r
                        .expert_recipe
                        .as_ref()
                        .map(|x| RecipeSpec::from_proto(x, "spec.reward.expert_recipe"))
                        .transpose()?,
                    amortised_targets: r.amortised_targets.as_ref().map(AmortisedTargets::from_proto),
                    base_model: r.base_model,
                    expert_model: r.expert_model,
                };
                (Optimization::from_proto(&o, REWARD_OPTIMIZATION), JobKind::Reward(job))
            }
            (Kind::Discriminator(d), Facts::Models { space }) => {
                let job = DiscriminatorJob {
                    architecture: RewardArchitecture::from_proto(d.architecture, space),
                    inpaint_condition: d.inpaint_condition.unwrap_or(false),
                    base_dataset: d.base_dataset,
                    expert_dataset: d.expert_dataset,
                    diffusion_model: d.diffusion_model,
                };
                (Optimization::from_proto(&o, DISCRIMINATOR_OPTIMIZATION), JobKind::Discriminator(job))
            }
            (kind, facts) => {
                let name = match kind {
                    Kind::Diffusion(_) => "diffusion",
                    Kind::Reward(_) => "reward",
                    Kind::Discriminator(_) => "discriminator",
                };
                // A caller's mistake, not a user's: the facts must match the kind.
                return invalid(format!("spec.{name}: looked up {facts:?}, which does not fit this kind"));
            }
        };
        let spec = Self { output_model: spec.output_model, seed: spec.seed.unwrap_or(0), optimization, kind };
        spec.validate()?;
        Ok(spec)
    }

    /// The stored spec back on the wire, every default explicit.
    pub fn to_proto(&self) -> pb::JobSpec {
        let kind = match &self.kind {
            JobKind::Diffusion(d) => pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
                dataset: d.dataset.clone(),
                parametrization: d.parametrization.to_proto() as i32,
                schedule: Some(d.schedule.to_proto()),
                n_timesteps: Some(wire_u32(d.n_timesteps)),
                horizon: Some(wire_u32(d.horizon)),
                architecture: Some(d.architecture.to_train_proto()),
                action_weight: Some(d.action_weight),
                clip_denoised: Some(d.clip_denoised),
                normalizer_datasets: d.normalizer_datasets.clone(),
                pooled_normalizer: Some(d.pooled_normalizer),
                conditional: Some(d.conditional),
                condition_dropout: d.condition_dropout,
                num_classes: d.num_classes.map(wire_u32),
            }),
            JobKind::Reward(r) => pb::job_spec::Kind::Reward(pb::TrainReward {
                base_model: r.base_model.clone(),
                expert_model: r.expert_model.clone(),
                architecture: Some(r.architecture.to_proto()),
                target: r.target.to_proto() as i32,
                eval_point: r.eval_point.to_proto() as i32,
                algorithm: Some(match &r.algorithm {
                    RewardAlgorithm::WithDataset { datasets } => {
                        pb::train_reward::Algorithm::WithDataset(pb::train_reward::WithDataset {
                            datasets: datasets.clone(),
                        })
                    }
                    RewardAlgorithm::ModelsOnly { num_chains } => {
                        pb::train_reward::Algorithm::ModelsOnly(pb::train_reward::ModelsOnly {
                            num_chains: Some(wire_u32(*num_chains)),
                        })
                    }
                }),
                rho_l2: Some(r.rho_l2),
                action_weight: Some(r.action_weight),
                condition_weight: Some(r.condition_weight),
                inpaint_condition: Some(r.inpaint_condition),
                amortised_targets: r.amortised_targets.as_ref().map(AmortisedTargets::to_proto),
                base_recipe: r.base_recipe.as_ref().map(RecipeSpec::to_proto),
                expert_recipe: r.expert_recipe.as_ref().map(RecipeSpec::to_proto),
            }),
            JobKind::Discriminator(d) => pb::job_spec::Kind::Discriminator(pb::TrainDiscriminator {
                base_dataset: d.base_dataset.clone(),
                expert_dataset: d.expert_dataset.clone(),
                architecture: Some(d.architecture.to_proto()),
                diffusion_model: d.diffusion_model.clone(),
                inpaint_condition: Some(d.inpaint_condition),
            }),
        };
        pb::JobSpec {
            output_model: self.output_model.clone(),
            seed: Some(self.seed),
            optimization: Some(self.optimization.to_proto()),
            kind: Some(kind),
        }
    }

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

    /// Range checks that need no stored data (existence and shapes are checked by the server
    /// against its store).
    pub fn validate(&self) -> Result<(), Invalid> {
        self.optimization.validate()?;
        match &self.kind {
            JobKind::Diffusion(d) => {
                if d.horizon == 0 || d.horizon > 4096 {
                    return invalid(format!("spec.diffusion.horizon: {} is outside 1..=4096", d.horizon));
                }
                if !(d.action_weight.is_finite() && d.action_weight > 0.0) {
                    return invalid(format!(
                        "spec.diffusion.action_weight: {} must be positive",
                        given_number(d.action_weight)
                    ));
                }
                // Settings of conditional training without it are refused, not ignored.
                if !d.conditional {
                    let field = match (d.condition_dropout, d.num_classes) {
                        (Some(_), _) => Some("condition_dropout"),
                        (_, Some(_)) => Some("num_classes"),
                        _ => None,
                    };
                    if let Some(field) = field {
                        return invalid(format!(
                            "spec.diffusion.{field}: applies to conditional training; set conditional = true"
                        ));
                    }
                }
                if let Some(p) = d.condition_dropout
                    && !(0.0..1.0).contains(&p)
                {
                    return invalid(format!("spec.diffusion.condition_dropout: {} must be in [0, 1)", given_number(p)));
                }
                if let Some(n) = d.num_classes
                    && (n == 0 || n >= crate::schema::manifest::MAX_CONDITION_SIZE)
                {
                    return invalid(format!(
                        "spec.diffusion.num_classes: {n} is outside 1..{}",
                        crate::schema::manifest::MAX_CONDITION_SIZE
                    ));
                }
            }
            JobKind::Reward(r) => r.validate()?,
            JobKind::Discriminator(_) => {}
        }
        Ok(())
    }
}

impl RewardJob {
    fn validate(&self) -> Result<(), Invalid> {
        if !(self.rho_l2.is_finite() && self.rho_l2 >= 0.0) {
            return invalid(format!("spec.reward.rho_l2: {} must be zero or positive", given_number(self.rho_l2)));
        }
        for (field, w) in [("action_weight", self.action_weight), ("condition_weight", self.condition_weight)] {
            if !(w.is_finite() && w >= 0.0) {
                return invalid(format!(
                    "spec.reward.{field}: {} must be finite and zero or positive",
                    given_number(w)
                ));
            }
        }
        let models_only = matches!(self.algorithm, RewardAlgorithm::ModelsOnly { .. });
        match &self.algorithm {
            RewardAlgorithm::WithDataset { datasets } if datasets.is_empty() => {
                return invalid("spec.reward.with_dataset.datasets: name at least one dataset");
            }
            RewardAlgorithm::ModelsOnly { num_chains } if *num_chains < 2 || *num_chains > 1 << 16 => {
                return invalid(format!("spec.reward.models_only.num_chains: {num_chains} is outside 2..=65536"));
            }
            _ => {}
        }
        for (name, recipe) in [("base_recipe", &self.base_recipe), ("expert_recipe", &self.expert_recipe)] {
            if let Some(r) = recipe {
                if !models_only {
                    return invalid(format!(
                        "spec.reward.{name}: applies to models_only (Algorithm 2) only; with_dataset noises the data's items, not chains"
                    ));
                }
                r.validate(&format!("spec.reward.{name}"))?;
            }
        }
        if self.inpaint_condition && models_only {
            return invalid(
                "spec.reward.inpaint_condition: applies to with_dataset (Algorithm 1) only; models_only draws x_t from the models' own chains",
            );
        }
        if let Some(a) = &self.amortised_targets {
            a.validate()?;
            if models_only {
                return invalid(
                    "spec.reward.amortised_targets: applies to with_dataset (Algorithm 1) only; models_only already computes its pairs once",
                );
            }
        }
        Ok(())
    }
}
