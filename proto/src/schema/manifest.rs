//! The diffusion model manifest: the contract between a model's weights and the service's math
//! (parametrization, schedule, T, data layout, normalizer, and for native models the
//! architecture). One set of types for the file a user uploads with a model (TOML or JSON), the
//! record the server stores, and the `relreward.v1.DiffusionManifest` message.
//!
//! ```toml
//! parametrization = "x0"                  # or "epsilon"
//! n_timesteps = 20
//! clip_denoised = true                    # default false
//! schedule = { kind = "diffuser_cosine" } # linear | cosine | diffuser_cosine (s) | betas (betas)
//! space = { kind = "trajectory", horizon = 32, action_dim = 2, obs_dim = 4 }
//! # or space = { kind = "sample", shape = [4, 8, 8] }
//! normalizer = { kind = "limits", min = [..], max = [..] }
//! # or { kind = "gaussian", mean = [..], std = [..] } or { kind = "identity" } (the default)
//! # native safetensors weights only (absent for a TorchScript module, its own architecture):
//! architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 4, 8] }
//! # or { kind = "mlp", hidden = [..] } or { kind = "unet2d", block_out_channels = [..],
//! #    layers_per_block, attention, norm_num_groups, attention_head_dim }
//! # conditional models only (unet2d or TorchScript):
//! conditioning = { kind = "labels", num_classes = 11, null_class = 10 }
//! # or { kind = "embedding", dim = 128 }
//! ```
//!
//! One rule decides what an uploaded model is: a manifest with an `architecture` describes
//! native weights, one without describes a TorchScript module. An architecture field left out
//! takes the same default in a file as on the wire (the `DEFAULT_*` constants below).

use serde::{Deserialize, Serialize};

use super::{Invalid, invalid, known, or_default, wire_u32, wire_u32s};
use crate::given_number;
use crate::v1 as pb;

/// Upper bound on T: far above any schedule in use (Diffuser 20..100, DDPM 1000), low enough
/// that schedule tables stay small.
pub const MAX_TIMESTEPS: usize = 100_000;

/// Most elements in one item of a model uploaded now, or in one row of a dataset (a trajectory
/// window, an image, a latent): 2^24 float32 values, 64 MiB, above a 3 x 2048 x 2048 image. An
/// upload's probe runs the network on two such items, and nothing else bounds them (a net's
/// parameter count does not grow with its items' size). Checked where a manifest arrives
/// ([`Space::check_new_item`]), not where a stored one is read: what was stored before the bound
/// stays readable.
pub const MAX_ITEM_ELEMENTS: u64 = 1 << 24;

/// The cosine schedules' offset s when none is given (Nichol & Dhariwal's value; the wire
/// sends 0 for it).
pub const DEFAULT_COSINE_S: f64 = 0.008;

/// TemporalUnet defaults: Diffuser's `dim = 32, dim_mults = (1, 2, 4, 8)`.
pub const DEFAULT_TEMPORAL_UNET_DIM: usize = 32;
pub const DEFAULT_TEMPORAL_UNET_DIM_MULTS: [usize; 4] = [1, 2, 4, 8];
/// MLP denoiser default widths.
pub const DEFAULT_MLP_HIDDEN: [usize; 2] = [256, 256];
/// UNet2D defaults: a small diffusers `UNet2DModel` for this machine's image sizes (two
/// levels, one ResNet layer per block, attention at the lowest resolution, GroupNorm(8)).
pub const DEFAULT_UNET2D_BLOCK_OUT_CHANNELS: [usize; 2] = [32, 64];
pub const DEFAULT_UNET2D_LAYERS_PER_BLOCK: usize = 1;
pub const DEFAULT_UNET2D_ATTENTION: bool = true;
pub const DEFAULT_UNET2D_NORM_NUM_GROUPS: usize = 8;
pub const DEFAULT_UNET2D_ATTENTION_HEAD_DIM: usize = 8;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Parametrization {
    /// The network predicts the noise eps.
    Epsilon,
    /// The network predicts x0 (Diffuser's maze and locomotion configs).
    X0,
    /// The network predicts the velocity v = sqrt(abar_t) eps - sqrt(1 - abar_t) x0 (Salimans
    /// & Ho 2022; diffusers' `prediction_type = "v_prediction"`).
    #[serde(alias = "v_prediction")]
    V,
}

/// Which beta schedule, before T is applied.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ScheduleSpec {
    /// beta linear from 1e-4 to 0.02, both scaled by 1000 / T.
    Linear,
    /// Nichol & Dhariwal: abar(x) = cos(((x / T) + s) / (1 + s) * pi / 2)^2, x = 0..T.
    Cosine {
        #[serde(default = "default_cosine_s")]
        s: f64,
    },
    /// Diffuser's variant (see the server's `engine/schedule.rs`).
    DiffuserCosine {
        #[serde(default = "default_cosine_s")]
        s: f64,
    },
    /// Exactly these T betas.
    Betas { betas: Vec<f64> },
}

fn default_cosine_s() -> f64 {
    DEFAULT_COSINE_S
}

/// The space a model's samples live in.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Space {
    /// [B, horizon, action_dim + obs_dim], each row [action | observation].
    Trajectory { horizon: usize, action_dim: usize, obs_dim: usize },
    /// [B, *shape], e.g. latents [C, H, W].
    Sample { shape: Vec<usize> },
}

impl Space {
    /// Shape of one item (without the batch dimension).
    pub fn item_shape(&self) -> Vec<i64> {
        match self {
            Self::Trajectory { horizon, action_dim, obs_dim } => vec![*horizon as i64, (*action_dim + *obs_dim) as i64],
            Self::Sample { shape } => shape.iter().map(|&d| d as i64).collect(),
        }
    }

    /// Dimensions of an item that the normalizer's coordinates span (see [`Normalizer`]).
    pub fn normalizer_dims(&self) -> usize {
        match self {
            Self::Trajectory { .. } => 1,
            Self::Sample { shape } => shape.len(),
        }
    }

    /// Number of normalizer coordinates (saturating: a manifest that passed `validate` never
    /// gets near `usize::MAX`, and an unvalidated one must not panic here).
    pub fn coordinates(&self) -> usize {
        match self {
            Self::Trajectory { action_dim, obs_dim, .. } => action_dim.saturating_add(*obs_dim),
            Self::Sample { shape } => shape.iter().fold(1usize, |acc, &d| acc.saturating_mul(d)),
        }
    }

    /// Positive dimensions whose element count fits tch's sizes; messages name `field` (the
    /// space's path, e.g. "manifest.space").
    pub fn validate_at(&self, field: &str) -> Result<(), Invalid> {
        match self {
            Self::Trajectory { horizon, action_dim, obs_dim } => {
                if *horizon == 0 || action_dim.checked_add(*obs_dim).is_none_or(|d| d == 0) {
                    return invalid(format!(
                        "{field}: horizon {horizon}, action_dim {action_dim}, obs_dim {obs_dim}: horizon and action_dim + obs_dim must be positive"
                    ));
                }
            }
            Self::Sample { shape } => {
                if shape.is_empty() || shape.contains(&0) {
                    return invalid(format!("{field}.shape: {shape:?} must be non-empty with positive dimensions"));
                }
            }
        }
        // Regression inputs in fuzz/regressions/manifest_parse: huge dimensions overflowed the
        // coordinate count and, cast to i64, became negative sizes.
        if self.checked_item_elements().is_none() {
            return invalid(format!("{field}: {self:?} has more elements per item than fit in 64 bits"));
        }
        Ok(())
    }

    /// [`MAX_ITEM_ELEMENTS`], for a manifest that arrives (an upload), after
    /// [`Space::validate_at`].
    pub fn check_new_item(&self, field: &str) -> Result<(), Invalid> {
        if self.checked_item_elements().is_none_or(|n| n as u64 > MAX_ITEM_ELEMENTS) {
            return invalid(format!("{field}: {self:?} has more than {MAX_ITEM_ELEMENTS} elements per item"));
        }
        Ok(())
    }

    /// Elements of one item, `None` when the count does not fit in an `i64` (tch's sizes).
    fn checked_item_elements(&self) -> Option<usize> {
        let n = match self {
            Self::Trajectory { horizon, action_dim, obs_dim } => {
                action_dim.checked_add(*obs_dim)?.checked_mul(*horizon)?
            }
            Self::Sample { shape } => shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d))?,
        };
        i64::try_from(n).is_ok().then_some(n)
    }
}

/// The map between a dataset's raw units and the normalized units models work in, per
/// coordinate (along the last dimension for trajectories, over all trailing elements for
/// samples). A model is only meaningful with the normalizer it was trained under, so every
/// manifest carries one. The arithmetic on tensors is the server's (`engine/normalizer.rs`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Normalizer {
    /// x_norm = 2 (x - min) / (max - min) - 1 (Diffuser's LimitsNormalizer): the default for
    /// trajectories.
    Limits { min: Vec<f64>, max: Vec<f64> },
    /// x_norm = (x - mean) / std: the default for latents.
    Gaussian { mean: Vec<f64>, std: Vec<f64> },
    #[default]
    Identity,
}

impl Normalizer {
    /// Number of coordinates it covers (`None` for identity: any).
    pub fn coordinates(&self) -> Option<usize> {
        match self {
            Self::Limits { min, .. } => Some(min.len()),
            Self::Gaussian { mean, .. } => Some(mean.len()),
            Self::Identity => None,
        }
    }

    /// Checks lengths, finiteness and orientation; `field` prefixes messages.
    pub fn validate(&self, field: &str, coordinates: usize) -> Result<(), Invalid> {
        let (a, b, names) = match self {
            Self::Identity => return Ok(()),
            Self::Limits { min, max } => (min, max, ("min", "max")),
            Self::Gaussian { mean, std } => (mean, std, ("mean", "std")),
        };
        for (v, name) in [(a, names.0), (b, names.1)] {
            if v.len() != coordinates {
                return invalid(format!(
                    "{field}.{name}: {} values but the model has {coordinates} coordinates",
                    v.len()
                ));
            }
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return invalid(format!("{field}.{name}[{i}]: not finite"));
            }
        }
        if let Self::Limits { min, max } = self
            && let Some(i) = min.iter().zip(max).position(|(lo, hi)| lo > hi)
        {
            return invalid(format!(
                "{field}: min[{i}] = {} exceeds max[{i}] = {}",
                given_number(min[i]),
                given_number(max[i])
            ));
        }
        if let Self::Gaussian { std, .. } = self
            && let Some(i) = std.iter().position(|&s| s < 0.0)
        {
            return invalid(format!("{field}.std[{i}]: negative"));
        }
        Ok(())
    }

    /// On the wire.
    pub fn to_proto(&self) -> pb::Normalizer {
        use pb::normalizer::{Gaussian, Identity, Kind, Limits};
        let kind = match self {
            Self::Limits { min, max } => Kind::Limits(Limits { min: min.clone(), max: max.clone() }),
            Self::Gaussian { mean, std } => Kind::Gaussian(Gaussian { mean: mean.clone(), std: std.clone() }),
            Self::Identity => Kind::Identity(Identity {}),
        };
        pb::Normalizer { kind: Some(kind) }
    }

    /// From the wire, required: "none" must be said explicitly (`identity {}`), as a model is
    /// meaningless without the normalizer it was trained under. Lengths are checked against a
    /// space by [`Normalizer::validate`].
    pub fn from_proto(n: Option<pb::Normalizer>, field: &str) -> Result<Self, Invalid> {
        use pb::normalizer::Kind;
        const KINDS: &str = "one of limits, gaussian or identity (identity {} for a model working in raw units)";
        let n = n.ok_or_else(|| Invalid(format!("{field}: missing; set {KINDS}")))?;
        match n.kind {
            None => invalid(format!("{field}: no normalizer kind set, or one this server does not know; set {KINDS}")),
            Some(Kind::Limits(l)) => Ok(Self::Limits { min: l.min, max: l.max }),
            Some(Kind::Gaussian(g)) => Ok(Self::Gaussian { mean: g.mean, std: g.std }),
            Some(Kind::Identity(_)) => Ok(Self::Identity),
        }
    }
}

/// Built-in denoiser architectures (native models only). A field left out of a file takes the
/// `DEFAULT_*` value, as an unset field on the wire does.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Architecture {
    /// Diffuser's TemporalUnet over [B, H, D].
    TemporalUnet {
        #[serde(default = "default_temporal_unet_dim")]
        dim: usize,
        #[serde(default = "default_temporal_unet_dim_mults")]
        dim_mults: Vec<usize>,
    },
    /// An MLP over flattened samples with a sinusoidal time embedding.
    Mlp {
        #[serde(default = "default_mlp_hidden")]
        hidden: Vec<usize>,
    },
    /// diffusers' `UNet2DModel` over images [C, H, W] (the server's `nets/unet2d.rs`).
    Unet2d {
        #[serde(default = "default_unet2d_block_out_channels")]
        block_out_channels: Vec<usize>,
        #[serde(default = "default_unet2d_layers_per_block")]
        layers_per_block: usize,
        /// Attention at the lowest resolution (last down block, mid block, first up block).
        #[serde(default = "default_unet2d_attention")]
        attention: bool,
        #[serde(default = "default_unet2d_norm_num_groups")]
        norm_num_groups: usize,
        #[serde(default = "default_unet2d_attention_head_dim")]
        attention_head_dim: usize,
    },
}

fn default_temporal_unet_dim() -> usize {
    DEFAULT_TEMPORAL_UNET_DIM
}
fn default_temporal_unet_dim_mults() -> Vec<usize> {
    DEFAULT_TEMPORAL_UNET_DIM_MULTS.to_vec()
}
fn default_mlp_hidden() -> Vec<usize> {
    DEFAULT_MLP_HIDDEN.to_vec()
}
fn default_unet2d_block_out_channels() -> Vec<usize> {
    DEFAULT_UNET2D_BLOCK_OUT_CHANNELS.to_vec()
}
fn default_unet2d_layers_per_block() -> usize {
    DEFAULT_UNET2D_LAYERS_PER_BLOCK
}
fn default_unet2d_attention() -> bool {
    DEFAULT_UNET2D_ATTENTION
}
fn default_unet2d_norm_num_groups() -> usize {
    DEFAULT_UNET2D_NORM_NUM_GROUPS
}
fn default_unet2d_attention_head_dim() -> usize {
    DEFAULT_UNET2D_ATTENTION_HEAD_DIM
}

impl Architecture {
    /// The architecture's `kind` in files ("temporal_unet", "mlp", "unet2d"), for messages.
    pub fn kind_name(&self) -> &'static str {
        match self {
            Self::TemporalUnet { .. } => "temporal_unet",
            Self::Mlp { .. } => "mlp",
            Self::Unet2d { .. } => "unet2d",
        }
    }

    /// The default denoiser for a dataset of trajectories (`true`) or of samples.
    pub fn default_for(trajectories: bool) -> Self {
        if trajectories {
            Self::TemporalUnet { dim: DEFAULT_TEMPORAL_UNET_DIM, dim_mults: DEFAULT_TEMPORAL_UNET_DIM_MULTS.to_vec() }
        } else {
            Self::Mlp { hidden: DEFAULT_MLP_HIDDEN.to_vec() }
        }
    }

    /// On the wire, every default explicit (a manifest's oneof; [`Architecture::to_train_proto`]
    /// gives TrainDiffusion's).
    pub fn to_proto(&self) -> pb::diffusion_manifest::Architecture {
        use pb::diffusion_manifest::Architecture as Wire;
        match self {
            Self::TemporalUnet { dim, dim_mults } => {
                Wire::TemporalUnet(pb::TemporalUnet { dim: Some(wire_u32(*dim)), dim_mults: wire_u32s(dim_mults) })
            }
            Self::Mlp { hidden } => Wire::Mlp(pb::Mlp { hidden: wire_u32s(hidden) }),
            Self::Unet2d { block_out_channels, layers_per_block, attention, norm_num_groups, attention_head_dim } => {
                Wire::Unet2d(pb::Unet2d {
                    block_out_channels: wire_u32s(block_out_channels),
                    layers_per_block: Some(wire_u32(*layers_per_block)),
                    attention: Some(*attention),
                    norm_num_groups: Some(wire_u32(*norm_num_groups)),
                    attention_head_dim: Some(wire_u32(*attention_head_dim)),
                })
            }
        }
    }

    /// The same three messages in TrainDiffusion's oneof.
    pub fn to_train_proto(&self) -> pb::train_diffusion::Architecture {
        use pb::diffusion_manifest::Architecture as M;
        use pb::train_diffusion::Architecture as T;
        match self.to_proto() {
            M::TemporalUnet(u) => T::TemporalUnet(u),
            M::Mlp(m) => T::Mlp(m),
            M::Unet2d(u) => T::Unet2d(u),
        }
    }

    /// From the wire; unset fields take the `DEFAULT_*` values.
    pub fn from_proto(a: pb::diffusion_manifest::Architecture) -> Self {
        use pb::diffusion_manifest::Architecture as Wire;
        match a {
            Wire::TemporalUnet(u) => Self::TemporalUnet {
                dim: u.dim.map_or(DEFAULT_TEMPORAL_UNET_DIM, |d| d as usize),
                dim_mults: or_default(&u.dim_mults, &DEFAULT_TEMPORAL_UNET_DIM_MULTS),
            },
            Wire::Mlp(m) => Self::Mlp { hidden: or_default(&m.hidden, &DEFAULT_MLP_HIDDEN) },
            Wire::Unet2d(u) => Self::Unet2d {
                block_out_channels: or_default(&u.block_out_channels, &DEFAULT_UNET2D_BLOCK_OUT_CHANNELS),
                layers_per_block: u.layers_per_block.map_or(DEFAULT_UNET2D_LAYERS_PER_BLOCK, |v| v as usize),
                attention: u.attention.unwrap_or(DEFAULT_UNET2D_ATTENTION),
                norm_num_groups: u.norm_num_groups.map_or(DEFAULT_UNET2D_NORM_NUM_GROUPS, |v| v as usize),
                attention_head_dim: u.attention_head_dim.map_or(DEFAULT_UNET2D_ATTENTION_HEAD_DIM, |v| v as usize),
            },
        }
    }

    /// TrainDiffusion's oneof, as [`Architecture::from_proto`].
    pub fn from_train_proto(a: pb::train_diffusion::Architecture) -> Self {
        use pb::diffusion_manifest::Architecture as M;
        use pb::train_diffusion::Architecture as T;
        Self::from_proto(match a {
            T::TemporalUnet(u) => M::TemporalUnet(u),
            T::Mlp(m) => M::Mlp(m),
            T::Unet2d(u) => M::Unet2d(u),
        })
    }
}

impl Parametrization {
    pub fn to_proto(self) -> pb::Parametrization {
        match self {
            Self::Epsilon => pb::Parametrization::Epsilon,
            Self::X0 => pb::Parametrization::X0,
            Self::V => pb::Parametrization::V,
        }
    }

    /// From the wire; UNSPECIFIED is `None` (the caller decides whether that is allowed).
    pub fn from_proto(v: i32, field: &str) -> Result<Option<Self>, Invalid> {
        const VALUES: &str = "PARAMETRIZATION_EPSILON (1), PARAMETRIZATION_X0 (2) or PARAMETRIZATION_V (3)";
        Ok(match known(field, v, VALUES)? {
            pb::Parametrization::Epsilon => Some(Self::Epsilon),
            pb::Parametrization::X0 => Some(Self::X0),
            pb::Parametrization::V => Some(Self::V),
            pb::Parametrization::Unspecified => None,
        })
    }

    /// From the wire, required (a model must say what its net predicts).
    pub fn required_from_proto(v: i32, field: &str) -> Result<Self, Invalid> {
        Self::from_proto(v, field)?.ok_or_else(|| {
            Invalid(format!(
                "{field}: unspecified; set PARAMETRIZATION_EPSILON (1), PARAMETRIZATION_X0 (2) or PARAMETRIZATION_V (3)"
            ))
        })
    }
}

impl ScheduleSpec {
    /// Checks what needs no arithmetic on the schedule (the server then builds it and checks
    /// for underflow); `field` names the schedule.
    pub fn validate(&self, field: &str, n_timesteps: usize) -> Result<(), Invalid> {
        match self {
            Self::Betas { betas } => {
                if betas.len() != n_timesteps {
                    return invalid(format!("{field}.betas: {} values but n_timesteps is {n_timesteps}", betas.len()));
                }
                if let Some(i) = betas.iter().position(|b| !(b.is_finite() && *b > 0.0 && *b < 1.0)) {
                    return invalid(format!("{field}.betas[{i}]: {} is not in (0, 1)", given_number(betas[i])));
                }
            }
            // s = 0 cannot travel (the wire's 0 means the default), so it is refused everywhere.
            Self::Cosine { s } | Self::DiffuserCosine { s } => {
                if !(s.is_finite() && *s > 0.0 && *s < 1.0) {
                    return invalid(format!(
                        "{field}.s: {} is not in (0, 1) (omit it for the default {DEFAULT_COSINE_S})",
                        given_number(*s)
                    ));
                }
            }
            Self::Linear => {}
        }
        Ok(())
    }

    pub fn to_proto(&self) -> pb::Schedule {
        use pb::schedule::{Cosine, ExplicitBetas, Kind, Linear};
        let kind = match self {
            Self::Linear => Kind::Linear(Linear {}),
            Self::Cosine { s } => Kind::Cosine(Cosine { s: *s }),
            Self::DiffuserCosine { s } => Kind::DiffuserCosine(Cosine { s: *s }),
            Self::Betas { betas } => Kind::Betas(ExplicitBetas { betas: betas.clone() }),
        };
        pb::Schedule { kind: Some(kind) }
    }

    /// From the wire, required: a missing message, or one whose kind is unset (or a kind this
    /// build does not know, which protobuf drops), is refused. Cosine `s = 0` means the default.
    pub fn from_proto(s: Option<pb::Schedule>, field: &str) -> Result<Self, Invalid> {
        use pb::schedule::Kind;
        const KINDS: &str = "one of linear, cosine, diffuser_cosine or betas";
        let s = s.ok_or_else(|| Invalid(format!("{field}: missing; set {KINDS}")))?;
        let cosine_s = |c: &pb::schedule::Cosine| if c.s == 0.0 { DEFAULT_COSINE_S } else { c.s };
        match s.kind {
            None => invalid(format!("{field}: no schedule kind set, or one this server does not know; set {KINDS}")),
            Some(Kind::Linear(_)) => Ok(Self::Linear),
            Some(Kind::Cosine(c)) => Ok(Self::Cosine { s: cosine_s(&c) }),
            Some(Kind::DiffuserCosine(c)) => Ok(Self::DiffuserCosine { s: cosine_s(&c) }),
            Some(Kind::Betas(b)) => {
                if b.betas.is_empty() {
                    return invalid(format!("{field}.betas: empty; give exactly n_timesteps values"));
                }
                Ok(Self::Betas { betas: b.betas })
            }
        }
    }
}

impl Space {
    pub fn to_proto(&self) -> pb::diffusion_manifest::Space {
        use pb::diffusion_manifest::{Sample, Space as S, Trajectory};
        match self {
            Self::Trajectory { horizon, action_dim, obs_dim } => S::Trajectory(Trajectory {
                horizon: wire_u32(*horizon),
                action_dim: wire_u32(*action_dim),
                obs_dim: wire_u32(*obs_dim),
            }),
            Self::Sample { shape } => S::Sample(Sample { shape: shape.iter().map(|&d| d as u64).collect() }),
        }
    }

    pub fn from_proto(s: Option<pb::diffusion_manifest::Space>, field: &str) -> Result<Self, Invalid> {
        use pb::diffusion_manifest::Space as S;
        match s {
            None => invalid(format!(
                "{field}: missing; set trajectory {{horizon, action_dim, obs_dim}} or sample {{shape}}"
            )),
            Some(S::Trajectory(t)) => Ok(Self::Trajectory {
                horizon: t.horizon as usize,
                action_dim: t.action_dim as usize,
                obs_dim: t.obs_dim as usize,
            }),
            Some(S::Sample(s)) => Ok(Self::Sample {
                shape: s
                    .shape
                    .iter()
                    .map(|&d| {
                        usize::try_from(d).map_err(|_| Invalid(format!("{field}.sample.shape: {d} is too large")))
                    })
                    .collect::<Result<_, _>>()?,
            }),
        }
    }
}

/// Upper bound on class labels and embedding widths: far above any class count or text
/// embedding in use, low enough that an embedding table stays within the parameter budget.
pub const MAX_CONDITION_SIZE: usize = 1 << 20;

/// A conditional denoiser's extra input, one per item (`relreward.v1.Conditioning`): class
/// labels or embedding vectors. Classifier-free guidance needs the null condition: `null_class`
/// for labels, the zero vector for embeddings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Conditioning {
    /// int64 labels in `0..num_classes` (diffusers' `num_class_embeds`: the table's rows).
    Labels {
        num_classes: usize,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        null_class: Option<usize>,
    },
    /// float32 vectors `[dim]` (diffusers' `class_embed_type = "identity"` in a unet2d).
    Embedding { dim: usize },
}

impl Conditioning {
    pub fn validate_at(&self, field: &str) -> Result<(), Invalid> {
        match *self {
            Self::Labels { num_classes, null_class } => {
                if num_classes == 0 || num_classes > MAX_CONDITION_SIZE {
                    return invalid(format!(
                        "{field}.labels.num_classes: {num_classes} is outside 1..={MAX_CONDITION_SIZE}"
                    ));
                }
                if let Some(null) = null_class
                    && null >= num_classes
                {
                    return invalid(format!(
                        "{field}.labels.null_class: {null} is not a label (labels are 0..{num_classes})"
                    ));
                }
            }
            Self::Embedding { dim } => {
                if dim == 0 || dim > MAX_CONDITION_SIZE {
                    return invalid(format!("{field}.embedding.dim: {dim} is outside 1..={MAX_CONDITION_SIZE}"));
                }
            }
        }
        Ok(())
    }

    /// Whether classifier-free guidance can form the unconditional prediction.
    pub fn has_null(&self) -> bool {
        match self {
            Self::Labels { null_class, .. } => null_class.is_some(),
            Self::Embedding { .. } => true,
        }
    }

    pub fn to_proto(&self) -> pb::Conditioning {
        use pb::conditioning::{Embedding, Kind, Labels};
        let kind = match *self {
            Self::Labels { num_classes, null_class } => {
                Kind::Labels(Labels { num_classes: wire_u32(num_classes), null_class: null_class.map(wire_u32) })
            }
            Self::Embedding { dim } => Kind::Embedding(Embedding { dim: wire_u32(dim) }),
        };
        pb::Conditioning { kind: Some(kind) }
    }

    /// From the wire, validated; `field` names the message in the request.
    pub fn from_proto(c: pb::Conditioning, field: &str) -> Result<Self, Invalid> {
        use pb::conditioning::Kind;
        let c = match c.kind {
            None => return invalid(format!("{field}: set labels or embedding (or leave conditioning unset)")),
            Some(Kind::Labels(l)) => {
                Self::Labels { num_classes: l.num_classes as usize, null_class: l.null_class.map(|n| n as usize) }
            }
            Some(Kind::Embedding(e)) => Self::Embedding { dim: e.dim as usize },
        };
        c.validate_at(field)?;
        Ok(c)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionManifest {
    pub parametrization: Parametrization,
    pub schedule: ScheduleSpec,
    pub n_timesteps: usize,
    #[serde(default)]
    pub clip_denoised: bool,
    pub space: Space,
    #[serde(default)]
    pub normalizer: Normalizer,
    /// Set for native models; absent for TorchScript, whose module is the architecture.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub architecture: Option<Architecture>,
    /// Conditional models only: the input the denoiser takes beside (x, t).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub conditioning: Option<Conditioning>,
}

impl DiffusionManifest {
    /// Parses a manifest file, TOML or JSON (see [`super::Format::guess`]; `name` is the file's
    /// name, if any, and prefixes parse errors), and validates it.
    pub fn parse(text: &str, name: Option<&str>) -> Result<Self, Invalid> {
        let format = super::Format::guess(name, text);
        let m: Self = super::parse_text(text, format, name.unwrap_or("manifest"))?;
        m.validate()?;
        Ok(m)
    }

    /// [`DiffusionManifest::validate_at`] with messages naming `manifest.*`.
    pub fn validate(&self) -> Result<(), Invalid> {
        self.validate_at("manifest")
    }

    /// Checks everything a schedule or a forward pass would otherwise trip over, except the
    /// schedule's arithmetic (the server's); messages name `field.*`.
    pub fn validate_at(&self, field: &str) -> Result<(), Invalid> {
        let t = self.n_timesteps;
        if t == 0 || t > MAX_TIMESTEPS {
            return invalid(format!("{field}.n_timesteps: {t} is outside 1..={MAX_TIMESTEPS}"));
        }
        self.schedule.validate(&format!("{field}.schedule"), t)?;
        self.space.validate_at(&format!("{field}.space"))?;
        self.normalizer.validate(&format!("{field}.normalizer"), self.space.coordinates())?;
        if let Some(arch) = &self.architecture {
            self.validate_architecture(arch, field)?;
        }
        if let Some(c) = &self.conditioning {
            c.validate_at(&format!("{field}.conditioning"))?;
            // Native conditioning is built into the unet2d alone (its embedding-width rule is
            // checked where the network is planned, the server's `nets::unet2d`).
            if let Some(arch) = &self.architecture
                && !matches!(arch, Architecture::Unet2d { .. })
            {
                return invalid(format!(
                    "{field}.conditioning: the native {} takes no condition; only unet2d is conditional (or upload a TorchScript module)",
                    arch.kind_name()
                ));
            }
        }
        Ok(())
    }

    fn validate_architecture(&self, arch: &Architecture, field: &str) -> Result<(), Invalid> {
        match arch {
            Architecture::TemporalUnet { dim, dim_mults } => {
                let Space::Trajectory { horizon, .. } = self.space else {
                    return invalid(format!("{field}.architecture: temporal_unet needs a trajectory space"));
                };
                if *dim == 0 || dim % 8 != 0 || dim_mults.is_empty() || dim_mults.contains(&0) {
                    return invalid(format!(
                        "{field}.architecture: temporal_unet dim {dim} must be a positive multiple of 8 (GroupNorm(8)) and dim_mults {dim_mults:?} non-empty and positive"
                    ));
                }
                // 65 or more levels overflowed the shift (fuzz/regressions/manifest_parse).
                let Some(factor) = u32::try_from(dim_mults.len() - 1).ok().and_then(|l| 1usize.checked_shl(l)) else {
                    return invalid(format!(
                        "{field}.architecture: temporal_unet has {} levels (dim_mults), far more than any horizon allows",
                        dim_mults.len()
                    ));
                };
                if horizon % factor != 0 {
                    return invalid(format!(
                        "{field}.space.horizon: {horizon} must be divisible by 2^(levels - 1) = {factor} for dim_mults {dim_mults:?}"
                    ));
                }
            }
            Architecture::Mlp { hidden } => {
                if hidden.is_empty() || hidden.contains(&0) {
                    return invalid(format!("{field}.architecture.hidden: {hidden:?} must be non-empty and positive"));
                }
            }
            // The widths, groups and image sizes are checked where the network is planned
            // (the server's `nets::unet2d::Unet2dConfig::validate`); here only the space's kind.
            Architecture::Unet2d { .. } => {
                if !matches!(&self.space, Space::Sample { shape } if shape.len() == 3) {
                    return invalid(format!("{field}.architecture: unet2d needs a sample space of shape [C, H, W]"));
                }
            }
        }
        Ok(())
    }

    /// On the wire, every default explicit.
    pub fn to_proto(&self) -> pb::DiffusionManifest {
        pb::DiffusionManifest {
            parametrization: self.parametrization.to_proto() as i32,
            schedule: Some(self.schedule.to_proto()),
            n_timesteps: wire_u32(self.n_timesteps),
            clip_denoised: self.clip_denoised,
            space: Some(self.space.to_proto()),
            normalizer: Some(self.normalizer.to_proto()),
            architecture: self.architecture.as_ref().map(Architecture::to_proto),
            conditioning: self.conditioning.as_ref().map(Conditioning::to_proto),
        }
    }

    /// From the wire, validated (every field present, lengths consistent with the space and T,
    /// the architecture consistent with the space); `field` is the manifest's path in the
    /// request ("header.manifest") and every message names the field below it.
    pub fn from_proto(m: Option<pb::DiffusionManifest>, field: &str) -> Result<Self, Invalid> {
        let m = m.ok_or_else(|| Invalid(format!("{field}: missing; a model needs its DiffusionManifest")))?;
        if m.n_timesteps == 0 {
            return invalid(format!("{field}.n_timesteps: missing or 0; set T, the number of diffusion steps"));
        }
        let manifest = Self {
            parametrization: Parametrization::required_from_proto(
                m.parametrization,
                &format!("{field}.parametrization"),
            )?,
            schedule: ScheduleSpec::from_proto(m.schedule, &format!("{field}.schedule"))?,
            n_timesteps: m.n_timesteps as usize,
            clip_denoised: m.clip_denoised,
            space: Space::from_proto(m.space, &format!("{field}.space"))?,
            normalizer: Normalizer::from_proto(m.normalizer, &format!("{field}.normalizer"))?,
            architecture: m.architecture.map(Architecture::from_proto),
            conditioning: m
                .conditioning
                .map(|c| Conditioning::from_proto(c, &format!("{field}.conditioning")))
                .transpose()?,
        };
        manifest.validate_at(field)?;
        manifest.space.check_new_item(&format!("{field}.space"))?;
        Ok(manifest)
    }
}

/// How the server calls a bring-your-own TorchScript reward (`relreward.v1.RewardSignature`).
/// In both, `x` is float32 `[B, *item_shape]` in normalized units and `t` int64 `[B]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RewardSignature {
    /// `forward(x, t) -> rho [B]`.
    Rho,
    /// Diffuser's ValueFunction: `forward(x, cond: Dict[str, Tensor], t) -> [B, 1]`, called
    /// with an empty `cond`.
    ValueFunction,
}

impl RewardSignature {
    pub fn to_proto(self) -> pb::RewardSignature {
        match self {
            Self::Rho => pb::RewardSignature::Rho,
            Self::ValueFunction => pb::RewardSignature::ValueFunction,
        }
    }

    /// From the wire, required: the server cannot guess how to call a module.
    pub fn from_proto(v: i32, field: &str) -> Result<Self, Invalid> {
        const VALUES: &str = "REWARD_SIGNATURE_RHO (1: forward(x, t) -> [B]) or REWARD_SIGNATURE_VALUE_FUNCTION (2: \
                              Diffuser's forward(x, cond, t) -> [B, 1])";
        match known(field, v, VALUES)? {
            pb::RewardSignature::Rho => Ok(Self::Rho),
            pb::RewardSignature::ValueFunction => Ok(Self::ValueFunction),
            pb::RewardSignature::Unspecified => invalid(format!("{field}: unspecified; set {VALUES}")),
        }
    }
}

impl std::fmt::Display for RewardSignature {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Rho => "rho",
            Self::ValueFunction => "value_function",
        })
    }
}

/// The manifest of a bring-your-own TorchScript reward (`UploadModelHeader.reward`): what the
/// server needs to call the module and to serve it as it serves trained rewards. What a
/// trained reward's manifest also holds (its architecture, objective, training data and
/// losses) it need not state: the module is its own architecture, and how it was trained is
/// its author's business.
///
/// ```toml
/// signature = "value_function"            # or "rho"
/// n_timesteps = 20
/// space = { kind = "trajectory", horizon = 32, action_dim = 2, obs_dim = 4 }
/// normalizer = { kind = "limits", min = [..], max = [..] }   # default identity
/// base_model = "hopper-base"              # optional: must then agree with it
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardUploadManifest {
    pub signature: RewardSignature,
    pub n_timesteps: usize,
    pub space: Space,
    #[serde(default)]
    pub normalizer: Normalizer,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub base_model: String,
}

impl RewardUploadManifest {
    /// Parses a manifest file, TOML or JSON, and validates it (as [`DiffusionManifest::parse`]).
    pub fn parse(text: &str, name: Option<&str>) -> Result<Self, Invalid> {
        let format = super::Format::guess(name, text);
        let m: Self = super::parse_text(text, format, name.unwrap_or("reward manifest"))?;
        m.validate_at("reward manifest")?;
        Ok(m)
    }

    /// T, the space and the normalizer's lengths; messages name `field.*`.
    pub fn validate_at(&self, field: &str) -> Result<(), Invalid> {
        let t = self.n_timesteps;
        if t == 0 || t > MAX_TIMESTEPS {
            return invalid(format!("{field}.n_timesteps: {t} is outside 1..={MAX_TIMESTEPS}"));
        }
        self.space.validate_at(&format!("{field}.space"))?;
        self.normalizer.validate(&format!("{field}.normalizer"), self.space.coordinates())
    }

    pub fn to_proto(&self) -> pb::RewardUploadManifest {
        use pb::diffusion_manifest::Space as S;
        use pb::reward_upload_manifest::Space as R;
        pb::RewardUploadManifest {
            signature: self.signature.to_proto() as i32,
            space: Some(match self.space.to_proto() {
                S::Trajectory(t) => R::Trajectory(t),
                S::Sample(s) => R::Sample(s),
            }),
            normalizer: Some(self.normalizer.to_proto()),
            n_timesteps: wire_u32(self.n_timesteps),
            base_model: self.base_model.clone(),
        }
    }

    /// From the wire, validated; `field` is the manifest's path in the request
    /// ("header.reward") and every message names the field below it.
    pub fn from_proto(m: pb::RewardUploadManifest, field: &str) -> Result<Self, Invalid> {
        use pb::diffusion_manifest::Space as S;
        use pb::reward_upload_manifest::Space as R;
        if m.n_timesteps == 0 {
            return invalid(format!("{field}.n_timesteps: missing or 0; set T, the diffusion steps it was made for"));
        }
        let space = m.space.map(|s| match s {
            R::Trajectory(t) => S::Trajectory(t),
            R::Sample(s) => S::Sample(s),
        });
        let manifest = Self {
            signature: RewardSignature::from_proto(m.signature, &format!("{field}.signature"))?,
            n_timesteps: m.n_timesteps as usize,
            space: Space::from_proto(space, &format!("{field}.space"))?,
            normalizer: Normalizer::from_proto(m.normalizer, &format!("{field}.normalizer"))?,
            base_model: m.base_model,
        };
        manifest.validate_at(field)?;
        manifest.space.check_new_item(&format!("{field}.space"))?;
        Ok(manifest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reward_upload_manifest_round_trips_and_names_fields() {
        let text = r#"
            signature = "value_function"
            n_timesteps = 20
            space = { kind = "trajectory", horizon = 8, action_dim = 1, obs_dim = 2 }
            normalizer = { kind = "gaussian", mean = [0, 1, 2], std = [1, 1, 2] }
        "#;
        let m = RewardUploadManifest::parse(text, Some("r.toml")).expect("parses");
        assert_eq!(m.space.item_shape(), vec![8, 3]);
        assert_eq!(RewardUploadManifest::from_proto(m.to_proto(), "header.reward").expect("wire"), m);
        let mut wire = m.to_proto();
        wire.signature = 0;
        let err = RewardUploadManifest::from_proto(wire, "header.reward").expect_err("unspecified");
        assert!(err.0.starts_with("header.reward.signature: unspecified"), "{}", err.0);
        let mut wire = m.to_proto();
        wire.normalizer = None;
        let err = RewardUploadManifest::from_proto(wire, "header.reward").expect_err("no normalizer");
        assert!(err.0.starts_with("header.reward.normalizer: missing"), "{}", err.0);
        let mut wire = m.to_proto();
        wire.space = None;
        let err = RewardUploadManifest::from_proto(wire, "header.reward").expect_err("no space");
        assert!(err.0.starts_with("header.reward.space: missing"), "{}", err.0);
        let short = text.replace("std = [1, 1, 2]", "std = [1, 1]");
        let err = RewardUploadManifest::parse(&short, None).expect_err("short std");
        assert!(err.0.contains("reward manifest.normalizer.std: 2 values"), "{}", err.0);
    }

    const TOML: &str = r#"
        parametrization = "x0"
        n_timesteps = 20
        clip_denoised = true
        schedule = { kind = "diffuser_cosine" }
        space = { kind = "trajectory", horizon = 32, action_dim = 2, obs_dim = 4 }
        normalizer = { kind = "limits", min = [0, 0, 0, 0, 0, 0], max = [1, 1, 1, 1, 1, 1] }
        architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 4, 8] }
    "#;

    #[test]
    fn toml_and_json_forms_agree() {
        let m = DiffusionManifest::parse(TOML, None).expect("toml");
        assert_eq!(m.schedule, ScheduleSpec::DiffuserCosine { s: 0.008 });
        assert_eq!(m.space.item_shape(), vec![32, 6]);
        let json = serde_json::to_string(&m).expect("json");
        assert_eq!(DiffusionManifest::parse(&json, None).expect("json parses"), m);
    }

    #[test]
    fn bad_manifests_name_the_field() {
        let cases = [
            (TOML.replace("n_timesteps = 20", "n_timesteps = 0"), "manifest.n_timesteps"),
            (TOML.replace("\"diffuser_cosine\"", "\"quadratic\""), "unknown variant `quadratic`"),
            (TOML.replace("parametrization = \"x0\"", ""), "missing field `parametrization`"),
            (TOML.replace("horizon = 32", "horizon = 30"), "manifest.space.horizon"),
            (TOML.replace("max = [1, 1, 1, 1, 1, 1]", "max = [1, 1]"), "manifest.normalizer.max"),
            (
                TOML.replace("{ kind = \"diffuser_cosine\" }", "{ kind = \"betas\", betas = [0.1, 0.2] }"),
                "manifest.schedule.betas",
            ),
            (TOML.replace("clip_denoised = true", "clip_denoised = true\nextra = 1"), "unknown field `extra`"),
        ];
        for (text, needle) in cases {
            let err = DiffusionManifest::parse(&text, None).expect_err(needle).to_string();
            assert!(err.contains(needle), "{err} should contain {needle}");
        }
    }

    /// The inputs in fuzz/regressions/manifest_parse: each once overflowed (a panic in debug
    /// builds, a wrong size in release) and must now be a clean refusal (INVALID_ARGUMENT at the server).
    #[test]
    fn fuzz_regressions_manifest_sizes_overflow() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/regressions/manifest_parse");
        let cases = [
            ("trajectory_dims_overflow.json", "manifest.space"),
            ("sample_shape_overflow.json", "manifest.space"),
            ("item_elements_over_i64.json", "manifest.space"),
            ("unet_levels_shift_overflow.json", "manifest.architecture"),
        ];
        for (file, needle) in cases {
            let text = std::fs::read_to_string(dir.join(file)).expect(file);
            let err = DiffusionManifest::parse(&text, None).expect_err(file);
            assert!(err.to_string().contains(needle), "{file}: {err} should contain {needle}");
        }
    }

    #[test]
    fn uploaded_items_are_bounded_in_size_not_only_in_bits() {
        // 1 x 65536 x 65536 fits an i64 but is 2^32 elements: the upload's probe would allocate
        // tens of gigabytes before any message. The bound itself is accepted.
        let at = |shape: Vec<usize>| Space::Sample { shape }.check_new_item("manifest.space");
        let err = at(vec![1, 65536, 65536]).expect_err("too large");
        assert!(err.to_string().contains("manifest.space") && err.to_string().contains("16777216"), "{err}");
        assert!(at(vec![1, 4096, 4096]).is_ok());
        assert!(at(vec![2, 4096, 4096]).is_err());
        let traj = Space::Trajectory { horizon: 1 << 20, action_dim: 8, obs_dim: 9 };
        assert!(traj.check_new_item("manifest.space").is_err());
        // A stored manifest from before the bound is still valid where it is read.
        let stored = Space::Sample { shape: vec![3, 4096, 4096] };
        assert!(stored.validate_at("manifest.space").is_ok() && stored.check_new_item("m").is_err());
        // Both uploads' wire forms are bounded.
        let wire = |shape: Vec<u64>| pb::DiffusionManifest {
            parametrization: pb::Parametrization::Epsilon as i32,
            schedule: Some(ScheduleSpec::DiffuserCosine { s: 0.008 }.to_proto()),
            n_timesteps: 10,
            space: Some(pb::diffusion_manifest::Space::Sample(pb::diffusion_manifest::Sample { shape })),
            normalizer: Some(Normalizer::Identity.to_proto()),
            ..Default::default()
        };
        let err = DiffusionManifest::from_proto(Some(wire(vec![1, 65536, 65536])), "header.manifest")
            .expect_err("an upload of 2^32 elements per item");
        assert!(err.to_string().contains("header.manifest.space") && err.to_string().contains("16777216"), "{err}");
        DiffusionManifest::from_proto(Some(wire(vec![1, 64, 64])), "header.manifest").expect("a small item");
    }

    #[test]
    fn validation_names_the_problem() {
        let n = Normalizer::Limits { min: vec![0.0], max: vec![1.0, 2.0] };
        assert!(
            n.validate("manifest.normalizer", 2).unwrap_err().to_string().contains("manifest.normalizer.min: 1 values")
        );
        let n = Normalizer::Limits { min: vec![3.0], max: vec![1.0] };
        assert!(n.validate("m", 1).unwrap_err().to_string().contains("exceeds"));
        let n = Normalizer::Gaussian { mean: vec![f64::NAN], std: vec![1.0] };
        assert!(n.validate("m", 1).unwrap_err().to_string().contains("mean[0]: not finite"));
    }
}
