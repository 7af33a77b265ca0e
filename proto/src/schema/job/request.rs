//! A job spec as a user writes it: the `train --config` file (TOML or JSON) and what the CLI's
//! flags and the Python specs fill in. Every field is optional and mirrors the proto `JobSpec`;
//! the CLI sends it with unset fields left unset, for the server to fill from the one set of
//! defaults ([`super::JobSpec::from_proto`]).
//!
//! Nested documents are the stored form's own types ([`Architecture`], [`RewardArchitecture`],
//! [`ScheduleSpec`]): a width or offset left out of them takes its default as the file is read,
//! the same default the server would give it.
//!
//! ```toml
//! output_model = "maze-expert"
//! seed = 0
//! [optimization]                    # steps, batch_size, learning_rate, grad_clip, ema_decay,
//! steps = 1000                      # ema_every, ema_start, checkpoint_every, eval_every,
//! batch_size = 32                   # log_every
//!
//! [diffusion]                       # a diffusion job
//! dataset = "maze-umaze-base"
//! horizon = 32
//! n_timesteps = 20
//! parametrization = "x0"
//! schedule = { kind = "cosine" }
//! architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 2, 4, 8] }
//! action_weight = 10.0
//! clip_denoised = true
//!
//! [reward]                          # a reward job
//! base_model = "maze-base"
//! expert_model = "maze-expert"
//! algorithm = { kind = "with_dataset", datasets = ["maze-umaze-base"] }
//! # or algorithm = { kind = "models_only", num_chains = 512 }
//! target = "score"                  # mean | score
//! eval_point = "mu_base"            # x_t | mu_base
//! rho_l2 = 0.0
//! action_weight = 10.0
//! condition_weight = 0.0
//! inpaint_condition = true
//! architecture = { kind = "windowed_mlp", window = 4, hidden = [128, 64, 32] }
//!
//! [discriminator]                   # a discriminator job
//! base_dataset = "maze-umaze-base"
//! expert_dataset = "maze-expert"
//! diffusion_model = "maze-base"
//! inpaint_condition = true
//! architecture = { kind = "value_function", widths = [32, 64] }
//! ```

use serde::Deserialize;

use super::{EvalPoint, RewardArchitecture, Target};
use crate::schema::manifest::{Architecture, Parametrization, ScheduleSpec};
use crate::v1 as pb;

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub output_model: Option<String>,
    pub seed: Option<u64>,
    #[serde(default)]
    pub optimization: OptimizationConfig,
    pub diffusion: Option<DiffusionConfig>,
    pub reward: Option<RewardConfig>,
    pub discriminator: Option<DiscriminatorConfig>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OptimizationConfig {
    pub steps: Option<u64>,
    pub batch_size: Option<u32>,
    pub learning_rate: Option<f64>,
    pub grad_clip: Option<f64>,
    pub ema_decay: Option<f64>,
    pub ema_every: Option<u32>,
    pub ema_start: Option<u64>,
    pub checkpoint_every: Option<u64>,
    pub eval_every: Option<u64>,
    pub log_every: Option<u64>,
}

impl OptimizationConfig {
    /// On the wire, unset fields left unset.
    pub fn to_proto(&self) -> pb::Optimization {
        pb::Optimization {
            steps: self.steps,
            batch_size: self.batch_size,
            learning_rate: self.learning_rate,
            grad_clip: self.grad_clip,
            ema_decay: self.ema_decay,
            ema_every: self.ema_every,
            ema_start: self.ema_start,
            checkpoint_every: self.checkpoint_every,
            eval_every: self.eval_every,
            log_every: self.log_every,
        }
    }
}

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionConfig {
    pub dataset: Option<String>,
    pub parametrization: Option<Parametrization>,
    pub schedule: Option<ScheduleSpec>,
    pub n_timesteps: Option<u32>,
    pub horizon: Option<u32>,
    pub architecture: Option<Architecture>,
    pub action_weight: Option<f64>,
    pub clip_denoised: Option<bool>,
    pub normalizer_datasets: Option<Vec<String>>,
    /// Sample datasets: one mean and std over every element (the proto's `pooled_normalizer`).
    pub pooled_normalizer: Option<bool>,
    /// Class-conditional training on the dataset's labels, with its dropout and class count.
    pub conditional: Option<bool>,
    pub condition_dropout: Option<f64>,
    pub num_classes: Option<u32>,
}

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardConfig {
    pub base_model: Option<String>,
    pub expert_model: Option<String>,
    pub architecture: Option<RewardArchitecture>,
    pub target: Option<Target>,
    pub eval_point: Option<EvalPoint>,
    pub algorithm: Option<Algorithm>,
    pub rho_l2: Option<f64>,
    pub action_weight: Option<f64>,
    pub condition_weight: Option<f64>,
    pub inpaint_condition: Option<bool>,
    /// Algorithm 2 with conditional models: each side's sampling recipe, e.g.
    /// `expert_recipe = { prompts = { labels = [0, 1] }, guidance_scale = 3.0 }`.
    pub base_recipe: Option<crate::schema::recipe::RecipeSpec>,
    pub expert_recipe: Option<crate::schema::recipe::RecipeSpec>,
}

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiscriminatorConfig {
    pub base_dataset: Option<String>,
    pub expert_dataset: Option<String>,
    pub architecture: Option<RewardArchitecture>,
    pub diffusion_model: Option<String>,
    pub inpaint_condition: Option<bool>,
}

/// How a reward job gets its x_t; an unset chain count is the server's default.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Algorithm {
    WithDataset {
        #[serde(default)]
        datasets: Vec<String>,
    },
    ModelsOnly {
        num_chains: Option<u32>,
    },
}

/// The kinds of [`RewardArchitecture`], as the CLI's `--arch` names them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum ArchKind {
    /// MLP over windows of H transitions, averaged.
    #[cfg_attr(feature = "clap", value(name = "windowed_mlp"))]
    WindowedMlp,
    /// Diffuser's ValueFunction temporal convolutions.
    #[cfg_attr(feature = "clap", value(name = "value_function"))]
    ValueFunction,
    /// 2D convolutions over [C, H, W] latents.
    #[cfg_attr(feature = "clap", value(name = "conv_encoder"))]
    ConvEncoder,
    /// MLP over the whole sample.
    #[cfg_attr(feature = "clap", value(name = "mlp"))]
    Mlp,
}

impl ArchKind {
    pub fn name(self) -> &'static str {
        match self {
            Self::WindowedMlp => "windowed_mlp",
            Self::ValueFunction => "value_function",
            Self::ConvEncoder => "conv_encoder",
            Self::Mlp => "mlp",
        }
    }
}

impl RewardArchitecture {
    pub fn kind(&self) -> ArchKind {
        match self {
            Self::WindowedMlp { .. } => ArchKind::WindowedMlp,
            Self::ValueFunction { .. } => ArchKind::ValueFunction,
            Self::ConvEncoder { .. } => ArchKind::ConvEncoder,
            Self::Mlp { .. } => ArchKind::Mlp,
        }
    }

    /// `kind` with its default widths (the paper's, `DEFAULT_*`).
    pub fn default_of(kind: ArchKind) -> Self {
        use super::{
            DEFAULT_CONV_ENCODER_WIDTHS, DEFAULT_REWARD_MLP_HIDDEN, DEFAULT_VALUE_FUNCTION_WIDTHS, DEFAULT_WINDOW,
            DEFAULT_WINDOWED_HIDDEN,
        };
        match kind {
            ArchKind::WindowedMlp => {
                Self::WindowedMlp { window: DEFAULT_WINDOW, hidden: DEFAULT_WINDOWED_HIDDEN.to_vec() }
            }
            ArchKind::ValueFunction => Self::ValueFunction { widths: DEFAULT_VALUE_FUNCTION_WIDTHS.to_vec() },
            ArchKind::ConvEncoder => Self::ConvEncoder { widths: DEFAULT_CONV_ENCODER_WIDTHS.to_vec() },
            ArchKind::Mlp => Self::Mlp { hidden: DEFAULT_REWARD_MLP_HIDDEN.to_vec() },
        }
    }
}
