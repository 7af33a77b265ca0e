//! The diffusion model manifest: the contract between a model's weights and the service's math
//! (parametrization, schedule, T, data layout, normalizer, and for native models the
//! architecture). Read from TOML or JSON files and from the `DiffusionManifest` proto message.

use serde::{Deserialize, Serialize};

use super::normalizer::Normalizer;
use crate::error::{Error, Result};

/// Upper bound on T: far above any schedule in use (Diffuser 20..100, DDPM 1000), low enough
/// that schedule tables stay small.
pub const MAX_TIMESTEPS: usize = 100_000;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Parametrization {
    /// The network predicts the noise eps.
    Epsilon,
    /// The network predicts x0 (Diffuser's maze and locomotion configs).
    X0,
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
    /// Diffuser's variant: x = linspace(0, T + 1, T + 1), divided by T + 1... see schedule.rs.
    DiffuserCosine {
        #[serde(default = "default_cosine_s")]
        s: f64,
    },
    /// Exactly these T betas.
    Betas { betas: Vec<f64> },
}

fn default_cosine_s() -> f64 {
    0.008
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

    /// Dimensions of an item that the normalizer's coordinates span (see `Normalizer`).
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

/// Built-in denoiser architectures (native models only).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Architecture {
    /// Diffuser's TemporalUnet over [B, H, D].
    TemporalUnet { dim: usize, dim_mults: Vec<usize> },
    /// An MLP over flattened samples with a sinusoidal time embedding.
    Mlp { hidden: Vec<usize> },
    /// diffusers' `UNet2DModel` over images [C, H, W] (`nets/unet2d.rs`); the defaults are
    /// diffusers' own, except attention, off unless asked for.
    Unet2d {
        block_out_channels: Vec<usize>,
        #[serde(default = "default_layers_per_block")]
        layers_per_block: usize,
        /// Attention at the lowest resolution (last down block, mid block, first up block).
        #[serde(default)]
        attention: bool,
        #[serde(default = "default_norm_num_groups")]
        norm_num_groups: usize,
        #[serde(default = "default_attention_head_dim")]
        attention_head_dim: usize,
    },
}

fn default_layers_per_block() -> usize {
    2
}

fn default_norm_num_groups() -> usize {
    32
}

fn default_attention_head_dim() -> usize {
    8
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
}

impl DiffusionManifest {
    /// Parses TOML or JSON (by the first non-blank character).
    pub fn parse(text: &str) -> Result<Self> {
        let m: Self = if text.trim_start().starts_with('{') {
            serde_json::from_str(text).map_err(|e| Error::invalid(format!("manifest (JSON): {e}")))?
        } else {
            toml::from_str(text).map_err(|e| Error::invalid(format!("manifest (TOML): {e}")))?
        };
        m.validate()?;
        Ok(m)
    }

    /// Checks everything a schedule or a forward pass would otherwise trip over.
    pub fn validate(&self) -> Result<()> {
        let t = self.n_timesteps;
        if t == 0 || t > MAX_TIMESTEPS {
            return Err(Error::invalid(format!("manifest.n_timesteps: {t} is outside 1..={MAX_TIMESTEPS}")));
        }
        match &self.schedule {
            ScheduleSpec::Betas { betas } => {
                if betas.len() != t {
                    return Err(Error::invalid(format!(
                        "manifest.schedule.betas: {} values but n_timesteps is {t}",
                        betas.len()
                    )));
                }
                if let Some(i) = betas.iter().position(|b| !(b.is_finite() && *b > 0.0 && *b < 1.0)) {
                    return Err(Error::invalid(format!(
                        "manifest.schedule.betas[{i}]: {} is not in (0, 1)",
                        crate::fields::number(betas[i])
                    )));
                }
            }
            ScheduleSpec::Cosine { s } | ScheduleSpec::DiffuserCosine { s } => {
                if !(s.is_finite() && *s >= 0.0 && *s < 1.0) {
                    return Err(Error::invalid(format!(
                        "manifest.schedule.s: {} is not in [0, 1)",
                        crate::fields::number(*s)
                    )));
                }
            }
            ScheduleSpec::Linear => {}
        }
        match &self.space {
            Space::Trajectory { horizon, action_dim, obs_dim } => {
                if *horizon == 0 || action_dim.checked_add(*obs_dim).is_none_or(|d| d == 0) {
                    return Err(Error::invalid(format!(
                        "manifest.space: horizon {horizon}, action_dim {action_dim}, obs_dim {obs_dim}: horizon and action_dim + obs_dim must be positive"
                    )));
                }
            }
            Space::Sample { shape } => {
                if shape.is_empty() || shape.contains(&0) {
                    return Err(Error::invalid(format!(
                        "manifest.space.shape: {shape:?} must be non-empty with positive dimensions"
                    )));
                }
            }
        }
        // Regression inputs in fuzz/regressions/manifest_parse: huge dimensions overflowed the
        // coordinate count and, cast to i64, became negative sizes.
        if self.space.checked_item_elements().is_none() {
            return Err(Error::invalid(format!(
                "manifest.space: {:?} has more elements per item than fit in 64 bits",
                self.space
            )));
        }
        self.normalizer.validate("manifest.normalizer", self.space.coordinates())?;
        if let Some(arch) = &self.architecture {
            match arch {
                Architecture::TemporalUnet { dim, dim_mults } => {
                    let Space::Trajectory { horizon, .. } = self.space else {
                        return Err(Error::invalid("manifest.architecture: temporal_unet needs a trajectory space"));
                    };
                    if *dim == 0 || dim % 8 != 0 || dim_mults.is_empty() || dim_mults.contains(&0) {
                        return Err(Error::invalid(format!(
                            "manifest.architecture: temporal_unet dim {dim} must be a positive multiple of 8 (GroupNorm(8)) and dim_mults {dim_mults:?} non-empty and positive"
                        )));
                    }
                    // 65 or more levels overflowed the shift (fuzz/regressions/manifest_parse).
                    let Some(factor) = u32::try_from(dim_mults.len() - 1).ok().and_then(|l| 1usize.checked_shl(l))
                    else {
                        return Err(Error::invalid(format!(
                            "manifest.architecture: temporal_unet has {} levels (dim_mults), far more than any horizon allows",
                            dim_mults.len()
                        )));
                    };
                    if horizon % factor != 0 {
                        return Err(Error::invalid(format!(
                            "manifest.space.horizon: {horizon} must be divisible by 2^(levels - 1) = {factor} for dim_mults {dim_mults:?}"
                        )));
                    }
                }
                Architecture::Mlp { hidden } => {
                    if hidden.is_empty() || hidden.contains(&0) {
                        return Err(Error::invalid(format!(
                            "manifest.architecture.hidden: {hidden:?} must be non-empty and positive"
                        )));
                    }
                }
                // The widths, groups and image sizes are checked where the network is planned
                // (`nets::unet2d::Unet2dConfig::validate`); here only the space's kind.
                Architecture::Unet2d { .. } => {
                    if !matches!(&self.space, Space::Sample { shape } if shape.len() == 3) {
                        return Err(Error::invalid(
                            "manifest.architecture: unet2d needs a sample space of shape [C, H, W]",
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let m = DiffusionManifest::parse(TOML).expect("toml");
        assert_eq!(m.schedule, ScheduleSpec::DiffuserCosine { s: 0.008 });
        assert_eq!(m.space.item_shape(), vec![32, 6]);
        let json = serde_json::to_string(&m).expect("json");
        assert_eq!(DiffusionManifest::parse(&json).expect("json parses"), m);
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
            let err = DiffusionManifest::parse(&text).expect_err(needle).to_string();
            assert!(err.contains(needle), "{err} should contain {needle}");
        }
    }

    /// The inputs in fuzz/regressions/manifest_parse: each once overflowed (a panic in debug
    /// builds, a wrong size in release) and must now be a clean INVALID_ARGUMENT.
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
            let err = DiffusionManifest::parse(&text).expect_err(file);
            assert!(matches!(err, Error::InvalidArgument(_)), "{file}: {err}");
            assert!(err.to_string().contains(needle), "{file}: {err} should contain {needle}");
        }
    }
}
