//! The `--config` file of `train`: the job spec's fields as TOML (see the parent module's
//! example), and the value kinds that flags and file share ([`Target`], [`EvalPoint`],
//! [`ArchKind`]).

use clap::ValueEnum;
use relreward_client::pb;
use serde::Deserialize;

// The denoiser of a diffusion job: the same built-in architectures a native manifest names.
pub use crate::manifest::Architecture;
use crate::manifest::{Parametrization, Schedule};

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

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionConfig {
    pub dataset: Option<String>,
    pub parametrization: Option<Parametrization>,
    pub schedule: Option<Schedule>,
    pub n_timesteps: Option<u32>,
    pub horizon: Option<u32>,
    pub architecture: Option<Architecture>,
    pub action_weight: Option<f64>,
    pub clip_denoised: Option<bool>,
    pub normalizer_datasets: Option<Vec<String>>,
    /// Sample datasets: one mean and std over every element (the proto's `pooled_normalizer`).
    pub pooled_normalizer: Option<bool>,
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

/// The network rho(x, t) of a reward or discriminator job; empty widths are left to the server.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RewardArchitecture {
    WindowedMlp {
        window: Option<u32>,
        #[serde(default)]
        hidden: Vec<u32>,
    },
    ValueFunction {
        #[serde(default)]
        widths: Vec<u32>,
    },
    ConvEncoder {
        #[serde(default)]
        widths: Vec<u32>,
    },
    Mlp {
        #[serde(default)]
        hidden: Vec<u32>,
    },
}

impl RewardArchitecture {
    pub(crate) fn kind(&self) -> ArchKind {
        match self {
            Self::WindowedMlp { .. } => ArchKind::WindowedMlp,
            Self::ValueFunction { .. } => ArchKind::ValueFunction,
            Self::ConvEncoder { .. } => ArchKind::ConvEncoder,
            Self::Mlp { .. } => ArchKind::Mlp,
        }
    }

    /// `kind` with every field unset.
    pub(crate) fn unset(kind: ArchKind) -> Self {
        match kind {
            ArchKind::WindowedMlp => Self::WindowedMlp { window: None, hidden: Vec::new() },
            ArchKind::ValueFunction => Self::ValueFunction { widths: Vec::new() },
            ArchKind::ConvEncoder => Self::ConvEncoder { widths: Vec::new() },
            ArchKind::Mlp => Self::Mlp { hidden: Vec::new() },
        }
    }

    pub(crate) fn into_proto(self) -> pb::RewardArchitecture {
        use pb::reward_architecture::{ConvEncoder, Kind, ValueFunction, WindowedMlp};
        let kind = match self {
            Self::WindowedMlp { window, hidden } => Kind::WindowedMlp(WindowedMlp { window, hidden }),
            Self::ValueFunction { widths } => Kind::ValueFunction(ValueFunction { widths }),
            Self::ConvEncoder { widths } => Kind::ConvEncoder(ConvEncoder { widths }),
            Self::Mlp { hidden } => Kind::Mlp(pb::Mlp { hidden }),
        };
        pb::RewardArchitecture { kind: Some(kind) }
    }
}

/// How a reward job gets its x_t.
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

/// What grad rho is aligned with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// mu_expert - mu_base (the server's default).
    Mean,
    /// s_expert - s_base.
    Score,
}

impl Target {
    pub(crate) fn to_proto(self) -> pb::RewardTarget {
        match self {
            Self::Mean => pb::RewardTarget::Mean,
            Self::Score => pb::RewardTarget::Score,
        }
    }
}

/// Where grad rho is evaluated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, ValueEnum)]
pub enum EvalPoint {
    /// At x_t, as in the paper's formula (the server's default).
    #[serde(rename = "x_t")]
    #[value(name = "x_t")]
    XT,
    /// At mu_base(x_t, t), as in the authors' code.
    #[serde(rename = "mu_base")]
    #[value(name = "mu_base")]
    MuBase,
}

impl EvalPoint {
    pub(crate) fn to_proto(self) -> pb::EvalPoint {
        match self {
            Self::XT => pb::EvalPoint::XT,
            Self::MuBase => pb::EvalPoint::MuBase,
        }
    }
}

/// The kinds of [`RewardArchitecture`], as `--arch` names them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ArchKind {
    /// MLP over windows of H transitions, averaged.
    #[value(name = "windowed_mlp")]
    WindowedMlp,
    /// Diffuser's ValueFunction temporal convolutions.
    #[value(name = "value_function")]
    ValueFunction,
    /// 2D convolutions over [C, H, W] latents.
    #[value(name = "conv_encoder")]
    ConvEncoder,
    /// MLP over the whole sample.
    #[value(name = "mlp")]
    Mlp,
}

impl ArchKind {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::WindowedMlp => "windowed_mlp",
            Self::ValueFunction => "value_function",
            Self::ConvEncoder => "conv_encoder",
            Self::Mlp => "mlp",
        }
    }
}
