//! The diffusion model manifest as a file, read with the shared schema
//! (`relreward_proto::schema::manifest`: the file's fields, defaults and checks, the server's
//! own), and the proto back to JSON for `model show --json`.
//!
//! One rule decides what an uploaded file is: a manifest with an `architecture` describes
//! native weights (`MODEL_FORMAT_NATIVE`), one without describes a TorchScript module.

use std::path::Path;

use anyhow::{Context, Result};
use relreward_client::pb;
use relreward_proto::schema::autoencoder::AutoencoderManifest;
use relreward_proto::schema::manifest::{DEFAULT_COSINE_S, DiffusionManifest, RewardUploadManifest};
use relreward_proto::schema::{Format, parse_text as parse_document};
use serde::de::DeserializeOwned;
use serde_json::{Value, json};

use crate::output::normalizer_json;

/// Parses TOML or JSON: JSON for a `.json` file or text starting with `{`, TOML otherwise.
/// Errors carry the parser's line and column and the field.
pub fn parse_text<T: DeserializeOwned>(text: &str, path: &Path) -> Result<T> {
    let name = path.display().to_string();
    Ok(parse_document(text, Format::guess(Some(&name), text), &name)?)
}

/// Reads a file of type `T` (see [`parse_text`]).
pub fn read_file<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    parse_text(&text, path)
}

/// A manifest file's text as the proto, after the schema's checks (the server's own, so a
/// manifest it would refuse is refused here, naming the field).
pub fn load_text(text: &str, path: &Path) -> Result<pb::DiffusionManifest> {
    let manifest: DiffusionManifest = parse_text(text, path)?;
    manifest.validate().with_context(|| format!("{}", path.display()))?;
    Ok(manifest.to_proto())
}

/// Reads and converts a manifest file.
pub fn load(path: &Path) -> Result<pb::DiffusionManifest> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    load_text(&text, path)
}

/// A bring-your-own reward's manifest file (`model upload --reward`) as the proto, after the
/// schema's checks (signature, n_timesteps, space, normalizer, base_model).
pub fn load_reward(path: &Path) -> Result<pb::RewardUploadManifest> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let name = path.display().to_string();
    Ok(RewardUploadManifest::parse(&text, Some(&name))?.to_proto())
}

/// An autoencoder's manifest file (`model upload --autoencoder`) as the proto, after the
/// schema's checks (image_shape, latent_shape, scaling_factor, shift_factor).
pub fn load_autoencoder(path: &Path) -> Result<pb::AutoencoderUploadManifest> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let name = path.display().to_string();
    Ok(AutoencoderManifest::parse(&text, Some(&name))?.to_proto())
}

/// A TrainDiffusion architecture as a manifest's (the same three messages), e.g. to print it
/// with [`architecture_json`].
pub fn manifest_architecture(a: &pb::train_diffusion::Architecture) -> pb::diffusion_manifest::Architecture {
    use pb::diffusion_manifest::Architecture as M;
    use pb::train_diffusion::Architecture as T;
    match a.clone() {
        T::TemporalUnet(u) => M::TemporalUnet(u),
        T::Mlp(m) => M::Mlp(m),
        T::Unet2d(u) => M::Unet2d(u),
    }
}

// ---------------------------------------------------------------------------------------------
// Proto to JSON (the file's fields)

pub fn parametrization_name(p: pb::Parametrization) -> Option<&'static str> {
    match p {
        pb::Parametrization::Epsilon => Some("epsilon"),
        pb::Parametrization::X0 => Some("x0"),
        pb::Parametrization::V => Some("v"),
        pb::Parametrization::Unspecified => None,
    }
}

/// `{"kind": "linear"}`, `{"kind": "cosine" | "diffuser_cosine", "s": X}` (the effective s),
/// `{"kind": "betas", "betas": [..]}`, or `null`.
pub fn schedule_json(s: Option<&pb::Schedule>) -> Value {
    use pb::schedule::Kind;
    let effective = |s: f64| if s == 0.0 { DEFAULT_COSINE_S } else { s };
    match s.and_then(|s| s.kind.as_ref()) {
        Some(Kind::Linear(_)) => json!({ "kind": "linear" }),
        Some(Kind::Cosine(c)) => json!({ "kind": "cosine", "s": effective(c.s) }),
        Some(Kind::DiffuserCosine(c)) => json!({ "kind": "diffuser_cosine", "s": effective(c.s) }),
        Some(Kind::Betas(b)) => json!({ "kind": "betas", "betas": b.betas }),
        None => Value::Null,
    }
}

/// A schedule in a few words: `cosine (s = 0.008)`, `betas (20 values)`.
pub fn schedule_text(s: Option<&pb::Schedule>) -> String {
    use pb::schedule::Kind;
    let effective = |s: f64| if s == 0.0 { DEFAULT_COSINE_S } else { s };
    match s.and_then(|s| s.kind.as_ref()) {
        Some(Kind::Linear(_)) => "linear".to_owned(),
        Some(Kind::Cosine(c)) => format!("cosine (s = {})", effective(c.s)),
        Some(Kind::DiffuserCosine(c)) => format!("diffuser_cosine (s = {})", effective(c.s)),
        Some(Kind::Betas(b)) => format!("betas ({} values)", b.betas.len()),
        None => "-".to_owned(),
    }
}

/// The manifest with the file's fields:
///
/// ```json
/// {"parametrization": "epsilon" | "x0" | "v" | null, "schedule": {..} | null, "n_timesteps": T,
///  "clip_denoised": bool,
///  "space": {"kind": "trajectory", "horizon": H, "action_dim": A, "obs_dim": O}
///         | {"kind": "sample", "shape": [..]} | null,
///  "normalizer": {"kind": "limits", "min": [..], "max": [..]}
///              | {"kind": "gaussian", "mean": [..], "std": [..]} | {"kind": "identity"},
///  "architecture": {"kind": "temporal_unet", ..} | {"kind": "mlp", ..} | {"kind": "unet2d", ..}}
/// ```
/// (`architecture` only for native models).
pub fn manifest_json(m: &pb::DiffusionManifest) -> Value {
    let mut json = json!({
        "parametrization": parametrization_name(m.parametrization()),
        "schedule": schedule_json(m.schedule.as_ref()),
        "n_timesteps": m.n_timesteps,
        "clip_denoised": m.clip_denoised,
        "space": space_json(m.space.as_ref()),
        "normalizer": normalizer_json(m.normalizer.as_ref()),
    });
    if let Some(a) = &m.architecture {
        json["architecture"] = architecture_json(a);
    }
    json
}

/// `{"kind": "temporal_unet" | "mlp" | "unet2d", ..fields}`, the file's form.
pub fn architecture_json(a: &pb::diffusion_manifest::Architecture) -> Value {
    use pb::diffusion_manifest::Architecture as Wire;
    match a {
        Wire::TemporalUnet(u) => json!({ "kind": "temporal_unet", "dim": u.dim, "dim_mults": u.dim_mults }),
        Wire::Mlp(m) => json!({ "kind": "mlp", "hidden": m.hidden }),
        Wire::Unet2d(u) => json!({
            "kind": "unet2d",
            "block_out_channels": u.block_out_channels,
            "layers_per_block": u.layers_per_block,
            "attention": u.attention,
            "norm_num_groups": u.norm_num_groups,
            "attention_head_dim": u.attention_head_dim,
        }),
    }
}

/// An architecture in a few words, `-` for none (a TorchScript module).
pub fn architecture_text(a: Option<&pb::diffusion_manifest::Architecture>) -> String {
    use pb::diffusion_manifest::Architecture as Wire;
    match a {
        Some(Wire::TemporalUnet(u)) => {
            format!("temporal_unet (dim {}, dim_mults {:?})", u.dim.unwrap_or(32), u.dim_mults)
        }
        Some(Wire::Mlp(m)) => format!("mlp (hidden {:?})", m.hidden),
        Some(Wire::Unet2d(u)) => format!("unet2d (block_out_channels {:?})", u.block_out_channels),
        None => "-".to_owned(),
    }
}

fn space_json(s: Option<&pb::diffusion_manifest::Space>) -> Value {
    use pb::diffusion_manifest::Space as PbSpace;
    match s {
        Some(PbSpace::Trajectory(t)) => {
            json!({ "kind": "trajectory", "horizon": t.horizon, "action_dim": t.action_dim, "obs_dim": t.obs_dim })
        }
        Some(PbSpace::Sample(s)) => json!({ "kind": "sample", "shape": s.shape }),
        None => Value::Null,
    }
}

/// A space in a few words.
pub fn space_text(s: Option<&pb::diffusion_manifest::Space>) -> String {
    use pb::diffusion_manifest::Space as PbSpace;
    match s {
        Some(PbSpace::Trajectory(t)) => {
            format!("trajectory (horizon {}, action_dim {}, obs_dim {})", t.horizon, t.action_dim, t.obs_dim)
        }
        Some(PbSpace::Sample(s)) => format!("sample {:?}", s.shape),
        None => "-".to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use pb::diffusion_manifest::{Sample, Space as PbSpace, Trajectory};
    use pb::normalizer::Kind as NKind;
    use pb::schedule::Kind as SKind;

    use super::*;

    const TOML: &str = r#"
        parametrization = "x0"
        n_timesteps = 4
        clip_denoised = true
        schedule = { kind = "diffuser_cosine" }
        space = { kind = "trajectory", horizon = 32, action_dim = 2, obs_dim = 1 }
        normalizer = { kind = "limits", min = [0, 0, -1], max = [1, 1, 1] }
    "#;

    fn parse(text: &str) -> Result<pb::DiffusionManifest> {
        load_text(text, Path::new("m.toml"))
    }

    fn with_schedule(schedule: &str) -> pb::DiffusionManifest {
        let text = TOML.replace(r#"{ kind = "diffuser_cosine" }"#, schedule);
        parse(&text).unwrap_or_else(|e| panic!("{schedule}: {e:#}"))
    }

    #[test]
    fn a_toml_manifest_becomes_the_proto() {
        let m = parse(TOML).expect("parses");
        assert_eq!(m.parametrization(), pb::Parametrization::X0);
        assert_eq!(m.n_timesteps, 4);
        assert!(m.clip_denoised);
        assert_eq!(m.space, Some(PbSpace::Trajectory(Trajectory { horizon: 32, action_dim: 2, obs_dim: 1 })));
        let Some(NKind::Limits(l)) = m.normalizer.and_then(|n| n.kind) else { panic!("limits") };
        assert_eq!((l.min, l.max), (vec![0.0, 0.0, -1.0], vec![1.0, 1.0, 1.0]));
        // Defaults: clip_denoised false, identity normalizer; epsilon parametrization.
        let m = parse(
            r#"parametrization = "epsilon"
               n_timesteps = 1000
               schedule = { kind = "linear" }
               space = { kind = "sample", shape = [4, 8, 8] }"#,
        )
        .expect("parses");
        assert_eq!(m.parametrization(), pb::Parametrization::Epsilon);
        assert!(!m.clip_denoised);
        assert_eq!(m.space, Some(PbSpace::Sample(Sample { shape: vec![4, 8, 8] })));
        assert!(matches!(m.normalizer.and_then(|n| n.kind), Some(NKind::Identity(_))));
    }

    #[test]
    fn every_schedule_kind() {
        let kind = |m: pb::DiffusionManifest| m.schedule.and_then(|s| s.kind).expect("schedule");
        assert_eq!(kind(with_schedule(r#"{ kind = "linear" }"#)), SKind::Linear(pb::schedule::Linear {}));
        // An omitted s goes out as the schema's default (0.008), explicitly.
        assert_eq!(kind(with_schedule(r#"{ kind = "cosine" }"#)), SKind::Cosine(pb::schedule::Cosine { s: 0.008 }));
        assert_eq!(
            kind(with_schedule(r#"{ kind = "cosine", s = 0.01 }"#)),
            SKind::Cosine(pb::schedule::Cosine { s: 0.01 })
        );
        assert_eq!(
            kind(with_schedule(r#"{ kind = "diffuser_cosine", s = 0.02 }"#)),
            SKind::DiffuserCosine(pb::schedule::Cosine { s: 0.02 })
        );
        assert_eq!(
            kind(with_schedule(r#"{ kind = "betas", betas = [0.1, 0.2, 0.3, 0.4] }"#)),
            SKind::Betas(pb::schedule::ExplicitBetas { betas: vec![0.1, 0.2, 0.3, 0.4] })
        );
    }

    #[test]
    fn every_normalizer() {
        let with = |normalizer: &str| {
            let text = TOML.replace(r#"{ kind = "limits", min = [0, 0, -1], max = [1, 1, 1] }"#, normalizer);
            parse(&text).unwrap_or_else(|e| panic!("{normalizer}: {e:#}")).normalizer.and_then(|n| n.kind)
        };
        assert!(matches!(with(r#"{ kind = "identity" }"#), Some(NKind::Identity(_))));
        let Some(NKind::Gaussian(g)) = with(r#"{ kind = "gaussian", mean = [0, 1, 2], std = [1, 1, 0.5] }"#) else {
            panic!("gaussian")
        };
        assert_eq!((g.mean, g.std), (vec![0.0, 1.0, 2.0], vec![1.0, 1.0, 0.5]));
        assert!(matches!(with(r#"{ kind = "limits", min = [0, 0, 0], max = [1, 1, 1] }"#), Some(NKind::Limits(_))));
    }

    #[test]
    fn json_manifests_parse_too() {
        let text = r#"{"parametrization": "x0", "n_timesteps": 4, "schedule": {"kind": "cosine"},
                       "space": {"kind": "sample", "shape": [2]},
                       "normalizer": {"kind": "gaussian", "mean": [0, 0], "std": [1, 1]}}"#;
        for name in ["m.json", "m"] {
            assert_eq!(load_text(text, Path::new(name)).expect("valid").n_timesteps, 4);
        }
        let err = load_text(r#"{"parametrization": "w"}"#, Path::new("m.json")).expect_err("bad");
        assert!(err.to_string().contains("m.json (JSON): unknown variant `w`"), "{err}");
        assert!(err.to_string().contains("line 1"), "{err}");
    }

    #[test]
    fn errors_name_the_field_or_line() {
        let cases = [
            (TOML.replace("n_timesteps = 4", "n_timesteps = 0"), "manifest.n_timesteps"),
            (TOML.replace("\"diffuser_cosine\"", "\"quadratic\""), "unknown variant `quadratic`"),
            (TOML.replace("\"diffuser_cosine\"", "\"quadratic\""), "line 5"),
            (TOML.replace("parametrization = \"x0\"", ""), "missing field `parametrization`"),
            (TOML.replace("n_timesteps = 4", "n_timesteps = -4"), "line 3"),
            (TOML.replace("n_timesteps = 4", "n_timesteps = \"4\""), "n_timesteps"),
            (TOML.replace("max = [1, 1, 1]", "max = [1, 1]"), "manifest.normalizer.max: 2 values but the model has 3"),
            (TOML.replace("max = [1, 1, 1]", "max = [1, 1, -2]"), "manifest.normalizer: min[2] = -1 exceeds max[2]"),
            (TOML.replace("min = [0, 0, -1], max = [1, 1, 1]", "mean = [0, 0, 0], std = [1, 1, 1]"), "line 7"),
            (
                TOML.replace("{ kind = \"diffuser_cosine\" }", "{ kind = \"betas\", betas = [0.1, 0.2] }"),
                "manifest.schedule.betas: 2 values but n_timesteps is 4",
            ),
            (
                TOML.replace("{ kind = \"diffuser_cosine\" }", "{ kind = \"betas\", betas = [0.1, 0.2, 1.5, 0.1] }"),
                "manifest.schedule.betas[2]: 1.5 is not in (0, 1)",
            ),
            (TOML.replace("{ kind = \"diffuser_cosine\" }", "{ kind = \"cosine\", s = 0 }"), "manifest.schedule.s"),
            (TOML.replace("horizon = 32", "horizon = 0"), "manifest.space"),
            (TOML.replace("clip_denoised = true", "clip_denoised = true\nextra = 1"), "unknown field `extra`"),
            (
                TOML.replace("clip_denoised = true", "clip_denoised = true\narchitecture = { kind = \"transformer\" }"),
                "unknown variant `transformer`",
            ),
            (
                TOML.replace(
                    "clip_denoised = true",
                    "clip_denoised = true\narchitecture = { kind = \"mlp\", width = 3 }",
                ),
                "unknown field `width`",
            ),
            (
                TOML.replace(
                    "{ kind = \"trajectory\", horizon = 32, action_dim = 2, obs_dim = 1 }",
                    "{ kind = \"sample\", shape = [3, 0] }",
                ),
                "manifest.space.shape",
            ),
            ("parametrization = \"x0\"\nn_timesteps = [".to_owned(), "line 2"),
        ];
        for (text, needle) in cases {
            let err = format!("{:#}", parse(&text).expect_err(needle));
            assert!(err.contains(needle), "{err:?} should contain {needle:?}");
        }
    }

    #[test]
    fn manifest_json_mirrors_the_file() {
        let schedules = [
            r#"{ kind = "linear" }"#,
            r#"{ kind = "cosine", s = 0.01 }"#,
            r#"{ kind = "diffuser_cosine", s = 0.02 }"#,
            r#"{ kind = "betas", betas = [0.1, 0.2, 0.3, 0.4] }"#,
        ];
        for schedule in schedules {
            let proto = with_schedule(schedule);
            let json = manifest_json(&proto);
            // The JSON document is itself a valid manifest file describing the same model.
            let back: DiffusionManifest = serde_json::from_value(json.clone()).expect("json is a manifest file");
            assert_eq!(back.to_proto(), proto, "{json}");
        }
        let json = manifest_json(&with_schedule(r#"{ kind = "diffuser_cosine" }"#));
        assert_eq!(
            json,
            json!({
                "parametrization": "x0",
                "schedule": {"kind": "diffuser_cosine", "s": 0.008},
                "n_timesteps": 4,
                "clip_denoised": true,
                "space": {"kind": "trajectory", "horizon": 32, "action_dim": 2, "obs_dim": 1},
                "normalizer": {"kind": "limits", "min": [0.0, 0.0, -1.0], "max": [1.0, 1.0, 1.0]},
            })
        );
        // A native model's architecture round-trips too (unet2d over images [C, H, W]).
        let image = r#"{ kind = "sample", shape = [1, 8, 8] }"#;
        let limits = r#"{ kind = "limits", min = [0, 0, -1], max = [1, 1, 1] }"#;
        for (architecture, space) in [
            (r#"{ kind = "temporal_unet", dim = 16, dim_mults = [1, 2] }"#, None),
            (r#"{ kind = "mlp", hidden = [64, 64] }"#, None),
            (
                r#"{ kind = "unet2d", block_out_channels = [16, 32], layers_per_block = 1, attention = false, norm_num_groups = 8, attention_head_dim = 8 }"#,
                Some(image),
            ),
        ] {
            let mut text = TOML.replace(r#"{ kind = "diffuser_cosine" }"#, r#"{ kind = "linear" }"#);
            if let Some(space) = space {
                text = text
                    .replace(r#"{ kind = "trajectory", horizon = 32, action_dim = 2, obs_dim = 1 }"#, space)
                    .replace(limits, r#"{ kind = "identity" }"#);
            }
            let proto = parse(&format!("{text}\narchitecture = {architecture}")).expect("native manifest");
            assert!(proto.architecture.is_some());
            let back: DiffusionManifest =
                serde_json::from_value(manifest_json(&proto)).expect("json is a manifest file");
            assert_eq!(back.to_proto(), proto, "{architecture}");
        }
        let empty = manifest_json(&pb::DiffusionManifest::default());
        assert!(empty["parametrization"].is_null() && empty["schedule"].is_null() && empty["space"].is_null());
        assert_eq!(empty["normalizer"], json!({"kind": "identity"}));
    }
}
