//! Conversions between the wire types (`relreward.v1`) and the domain types of `engine` and
//! `store`. Wire -> domain conversions validate and name the offending field in every error
//! (the caller passes the field path, e.g. "header.manifest"); domain -> wire conversions of
//! stored records report an unreadable record as `DataLoss`.

use relreward_proto::v1 as pb;

use super::timestamp;
use crate::engine::manifest::{Architecture, DiffusionManifest, Parametrization, ScheduleSpec, Space};
use crate::engine::nets::reward::RewardArchitecture;
use crate::engine::normalizer::Normalizer;
use crate::engine::relative_reward::RewardManifest;
use crate::engine::schedule::Schedule;
use crate::error::{Error, Result};
use crate::store::{ModelFormat, ModelKind, ModelRecord, Provenance};

// ============================================================================================
// Models: diffusion manifests, normalizers, model records (ModelService).
// ============================================================================================

/// The cosine schedules' offset s when the wire leaves it at 0.
const DEFAULT_COSINE_S: f64 = 0.008;

/// Rewrites an engine validation message ("manifest.x: ..." or "schedule...: ...") so that it
/// names the request field `field` ("header.manifest.x: ...").
fn at_field(err: Error, field: &str) -> Error {
    match err {
        Error::InvalidArgument(m) => {
            if let Some(rest) = m.strip_prefix("manifest") {
                Error::InvalidArgument(format!("{field}{rest}"))
            } else if m.starts_with("schedule") {
                Error::InvalidArgument(format!("{field}.{m}"))
            } else {
                Error::InvalidArgument(format!("{field}: {m}"))
            }
        }
        other => other,
    }
}

fn to_usize(v: u64, field: &str) -> Result<usize> {
    usize::try_from(v).map_err(|_| Error::invalid(format!("{field}: {v} is too large")))
}

/// Wire parametrization; UNSPECIFIED is an error (a model must say what its net predicts).
pub fn parametrization_from_proto(v: i32, field: &str) -> Result<Parametrization> {
    const VALUES: &str = "PARAMETRIZATION_EPSILON (1) or PARAMETRIZATION_X0 (2)";
    match crate::fields::known(field, v, VALUES)? {
        pb::Parametrization::Epsilon => Ok(Parametrization::Epsilon),
        pb::Parametrization::X0 => Ok(Parametrization::X0),
        pb::Parametrization::Unspecified => Err(Error::invalid(format!("{field}: unspecified; set {VALUES}"))),
    }
}

pub fn parametrization_to_proto(p: Parametrization) -> pb::Parametrization {
    match p {
        Parametrization::Epsilon => pb::Parametrization::Epsilon,
        Parametrization::X0 => pb::Parametrization::X0,
    }
}

/// Wire schedule, required: a missing message, or one whose kind is unset (or a kind this
/// server does not know, which protobuf drops), is an error. Cosine `s = 0` means 0.008.
pub fn schedule_from_proto(s: Option<pb::Schedule>, field: &str) -> Result<ScheduleSpec> {
    use pb::schedule::Kind;
    const KINDS: &str = "one of linear, cosine, diffuser_cosine or betas";
    let s = s.ok_or_else(|| Error::invalid(format!("{field}: missing; set {KINDS}")))?;
    let cosine_s = |c: &pb::schedule::Cosine| if c.s == 0.0 { DEFAULT_COSINE_S } else { c.s };
    match s.kind {
        None => {
            Err(Error::invalid(format!("{field}: no schedule kind set, or one this server does not know; set {KINDS}")))
        }
        Some(Kind::Linear(_)) => Ok(ScheduleSpec::Linear),
        Some(Kind::Cosine(c)) => Ok(ScheduleSpec::Cosine { s: cosine_s(&c) }),
        Some(Kind::DiffuserCosine(c)) => Ok(ScheduleSpec::DiffuserCosine { s: cosine_s(&c) }),
        Some(Kind::Betas(b)) => {
            if b.betas.is_empty() {
                return Err(Error::invalid(format!("{field}.betas: empty; give exactly n_timesteps values")));
            }
            Ok(ScheduleSpec::Betas { betas: b.betas })
        }
    }
}

pub fn schedule_to_proto(s: &ScheduleSpec) -> pb::Schedule {
    use pb::schedule::{Cosine, ExplicitBetas, Kind, Linear};
    let kind = match s {
        ScheduleSpec::Linear => Kind::Linear(Linear {}),
        ScheduleSpec::Cosine { s } => Kind::Cosine(Cosine { s: *s }),
        ScheduleSpec::DiffuserCosine { s } => Kind::DiffuserCosine(Cosine { s: *s }),
        ScheduleSpec::Betas { betas } => Kind::Betas(ExplicitBetas { betas: betas.clone() }),
    };
    pb::Schedule { kind: Some(kind) }
}

/// Wire normalizer, required: a model is only meaningful with the normalizer it was trained
/// under, so "none" must be said explicitly (`identity {}`). Lengths are checked later
/// against the space (see [`diffusion_manifest_from_proto`]).
pub fn normalizer_from_proto(n: Option<pb::Normalizer>, field: &str) -> Result<Normalizer> {
    use pb::normalizer::Kind;
    const KINDS: &str = "one of limits, gaussian or identity (identity {} for a model working in raw units)";
    let n = n.ok_or_else(|| Error::invalid(format!("{field}: missing; set {KINDS}")))?;
    match n.kind {
        None => Err(Error::invalid(format!(
            "{field}: no normalizer kind set, or one this server does not know; set {KINDS}"
        ))),
        Some(Kind::Limits(l)) => Ok(Normalizer::Limits { min: l.min, max: l.max }),
        Some(Kind::Gaussian(g)) => Ok(Normalizer::Gaussian { mean: g.mean, std: g.std }),
        Some(Kind::Identity(_)) => Ok(Normalizer::Identity),
    }
}

pub fn normalizer_to_proto(n: &Normalizer) -> pb::Normalizer {
    use pb::normalizer::{Gaussian, Identity, Kind, Limits};
    let kind = match n {
        Normalizer::Limits { min, max } => Kind::Limits(Limits { min: min.clone(), max: max.clone() }),
        Normalizer::Gaussian { mean, std } => Kind::Gaussian(Gaussian { mean: mean.clone(), std: std.clone() }),
        Normalizer::Identity => Kind::Identity(Identity {}),
    };
    pb::Normalizer { kind: Some(kind) }
}

fn space_from_proto(s: Option<pb::diffusion_manifest::Space>, field: &str) -> Result<Space> {
    use pb::diffusion_manifest::Space as S;
    match s {
        None => Err(Error::invalid(format!(
            "{field}: missing; set trajectory {{horizon, action_dim, obs_dim}} or sample {{shape}}"
        ))),
        Some(S::Trajectory(t)) => Ok(Space::Trajectory {
            horizon: t.horizon as usize,
            action_dim: t.action_dim as usize,
            obs_dim: t.obs_dim as usize,
        }),
        Some(S::Sample(s)) => Ok(Space::Sample {
            shape: s.shape.iter().map(|&d| to_usize(d, &format!("{field}.sample.shape"))).collect::<Result<_>>()?,
        }),
    }
}

fn space_to_proto(s: &Space) -> pb::diffusion_manifest::Space {
    use pb::diffusion_manifest::{Sample, Space as S, Trajectory};
    match s {
        Space::Trajectory { horizon, action_dim, obs_dim } => S::Trajectory(Trajectory {
            horizon: u32::try_from(*horizon).unwrap_or(u32::MAX),
            action_dim: u32::try_from(*action_dim).unwrap_or(u32::MAX),
            obs_dim: u32::try_from(*obs_dim).unwrap_or(u32::MAX),
        }),
        Space::Sample { shape } => S::Sample(Sample { shape: shape.iter().map(|&d| d as u64).collect() }),
    }
}

/// A wire TemporalUnet; unset fields take TrainDiffusion's defaults (dim 32, mults 1, 2, 4, 8).
pub fn temporal_unet_from_proto(u: pb::TemporalUnet) -> Architecture {
    Architecture::TemporalUnet {
        dim: u.dim.unwrap_or(32) as usize,
        dim_mults: if u.dim_mults.is_empty() { vec![1, 2, 4, 8] } else { to_usizes(&u.dim_mults) },
    }
}

/// A wire MLP denoiser; no hidden widths means (256, 256).
pub fn mlp_from_proto(m: pb::Mlp) -> Architecture {
    Architecture::Mlp { hidden: if m.hidden.is_empty() { vec![256, 256] } else { to_usizes(&m.hidden) } }
}

/// A wire UNet2D; unset fields take TrainDiffusion's defaults (widths 32, 64, one layer per
/// block, attention, 8 groups, head dim 8).
pub fn unet2d_from_proto(u: pb::Unet2d) -> Architecture {
    Architecture::Unet2d {
        block_out_channels: if u.block_out_channels.is_empty() {
            vec![32, 64]
        } else {
            to_usizes(&u.block_out_channels)
        },
        layers_per_block: u.layers_per_block.unwrap_or(1) as usize,
        attention: u.attention.unwrap_or(true),
        norm_num_groups: u.norm_num_groups.unwrap_or(8) as usize,
        attention_head_dim: u.attention_head_dim.unwrap_or(8) as usize,
    }
}

fn to_usizes(v: &[u32]) -> Vec<usize> {
    v.iter().map(|&x| x as usize).collect()
}

fn to_u32s(v: &[usize]) -> Vec<u32> {
    v.iter().map(|&x| u32::try_from(x).unwrap_or(u32::MAX)).collect()
}

/// An engine architecture on the wire, every default explicit (as a manifest's oneof; a
/// TrainDiffusion spec maps the same three messages into its own oneof).
pub fn architecture_to_proto(a: &Architecture) -> pb::diffusion_manifest::Architecture {
    use pb::diffusion_manifest::Architecture as Wire;
    match a {
        Architecture::TemporalUnet { dim, dim_mults } => Wire::TemporalUnet(pb::TemporalUnet {
            dim: Some(u32::try_from(*dim).unwrap_or(u32::MAX)),
            dim_mults: to_u32s(dim_mults),
        }),
        Architecture::Mlp { hidden } => Wire::Mlp(pb::Mlp { hidden: to_u32s(hidden) }),
        Architecture::Unet2d {
            block_out_channels,
            layers_per_block,
            attention,
            norm_num_groups,
            attention_head_dim,
        } => Wire::Unet2d(pb::Unet2d {
            block_out_channels: to_u32s(block_out_channels),
            layers_per_block: Some(u32::try_from(*layers_per_block).unwrap_or(u32::MAX)),
            attention: Some(*attention),
            norm_num_groups: Some(u32::try_from(*norm_num_groups).unwrap_or(u32::MAX)),
            attention_head_dim: Some(u32::try_from(*attention_head_dim).unwrap_or(u32::MAX)),
        }),
    }
}

/// A wire manifest as an engine manifest, fully validated: every field present, lengths
/// consistent with the space and T, the architecture (native models only; absent for
/// TorchScript) consistent with the space, and the schedule buildable (every beta in (0, 1),
/// no underflow). `field` is the manifest's path in the request, e.g. "header.manifest"; every
/// error names the offending field below it.
pub fn diffusion_manifest_from_proto(m: Option<pb::DiffusionManifest>, field: &str) -> Result<DiffusionManifest> {
    let m = m.ok_or_else(|| Error::invalid(format!("{field}: missing; a model needs its DiffusionManifest")))?;
    if m.n_timesteps == 0 {
        return Err(Error::invalid(format!("{field}.n_timesteps: missing or 0; set T, the number of diffusion steps")));
    }
    let manifest = DiffusionManifest {
        parametrization: parametrization_from_proto(m.parametrization, &format!("{field}.parametrization"))?,
        schedule: schedule_from_proto(m.schedule, &format!("{field}.schedule"))?,
        n_timesteps: m.n_timesteps as usize,
        clip_denoised: m.clip_denoised,
        space: space_from_proto(m.space, &format!("{field}.space"))?,
        normalizer: normalizer_from_proto(m.normalizer, &format!("{field}.normalizer"))?,
        architecture: m.architecture.map(|a| match a {
            pb::diffusion_manifest::Architecture::TemporalUnet(u) => temporal_unet_from_proto(u),
            pb::diffusion_manifest::Architecture::Mlp(m) => mlp_from_proto(m),
            pb::diffusion_manifest::Architecture::Unet2d(u) => unet2d_from_proto(u),
        }),
    };
    manifest.validate().map_err(|e| at_field(e, field))?;
    Schedule::new(&manifest.schedule, manifest.n_timesteps).map_err(|e| at_field(e, field))?;
    Ok(manifest)
}

pub fn diffusion_manifest_to_proto(m: &DiffusionManifest) -> pb::DiffusionManifest {
    pb::DiffusionManifest {
        parametrization: parametrization_to_proto(m.parametrization) as i32,
        schedule: Some(schedule_to_proto(&m.schedule)),
        n_timesteps: u32::try_from(m.n_timesteps).unwrap_or(u32::MAX),
        clip_denoised: m.clip_denoised,
        space: Some(space_to_proto(&m.space)),
        normalizer: Some(normalizer_to_proto(&m.normalizer)),
        architecture: m.architecture.as_ref().map(architecture_to_proto),
    }
}

/// Wire kind filter: UNSPECIFIED means any kind (`None`).
pub fn model_kind_filter_from_proto(v: i32, field: &str) -> Result<Option<ModelKind>> {
    const KINDS: &str =
        "MODEL_KIND_UNSPECIFIED (any), MODEL_KIND_DIFFUSION, MODEL_KIND_REWARD or MODEL_KIND_DISCRIMINATOR";
    Ok(match crate::fields::known(field, v, KINDS)? {
        pb::ModelKind::Unspecified => None,
        pb::ModelKind::Diffusion => Some(ModelKind::Diffusion),
        pb::ModelKind::Reward => Some(ModelKind::Reward),
        pb::ModelKind::Discriminator => Some(ModelKind::Discriminator),
    })
}

pub fn model_kind_to_proto(k: ModelKind) -> pb::ModelKind {
    match k {
        ModelKind::Diffusion => pb::ModelKind::Diffusion,
        ModelKind::Reward => pb::ModelKind::Reward,
        ModelKind::Discriminator => pb::ModelKind::Discriminator,
    }
}

pub fn model_format_to_proto(f: ModelFormat) -> pb::ModelFormat {
    match f {
        ModelFormat::Torchscript => pb::ModelFormat::Torchscript,
        ModelFormat::Native => pb::ModelFormat::Native,
    }
}

pub fn provenance_to_proto(p: &Provenance) -> pb::Provenance {
    use pb::provenance::{Source, Trained, Uploaded};
    let source = match p {
        Provenance::Uploaded => Source::Uploaded(Uploaded {}),
        Provenance::Trained { job_id, datasets, models, final_loss } => Source::Trained(Trained {
            job_id: job_id.clone(),
            datasets: datasets.clone(),
            models: models.clone(),
            final_loss: *final_loss,
        }),
    };
    pb::Provenance { source: Some(source) }
}

/// A stored model record on the wire. A diffusion model's manifest is parsed from the
/// record's JSON; an unreadable one is `DataLoss`. Reward and discriminator details
/// (`Model.reward`) are not filled yet: their stored manifest is defined by the reward trainer.
pub fn model_to_proto(r: &ModelRecord) -> Result<pb::Model> {
    let manifest = match r.kind {
        ModelKind::Diffusion => {
            let m: DiffusionManifest = serde_json::from_value(r.manifest.clone())
                .map_err(|e| Error::DataLoss(format!("model '{}': its stored manifest is unreadable: {e}", r.name)))?;
            Some(diffusion_manifest_to_proto(&m))
        }
        ModelKind::Reward | ModelKind::Discriminator => None,
    };
    let reward = match r.kind {
        ModelKind::Diffusion => None,
        ModelKind::Reward | ModelKind::Discriminator => {
            let m: RewardManifest = serde_json::from_value(r.manifest.clone())
                .map_err(|e| Error::DataLoss(format!("model '{}': its stored manifest is unreadable: {e}", r.name)))?;
            Some(pb::RewardInfo {
                base_model: m.base_model.clone(),
                expert_model: m.expert_model.clone(),
                architecture: m.architecture.to_string(),
                window: match &m.architecture {
                    RewardArchitecture::WindowedMlp { window, .. } => *window as u32,
                    _ => 0,
                },
                input_shape: m.space.item_shape().iter().map(|&d| d as u64).collect(),
                normalizer: Some(normalizer_to_proto(&m.normalizer)),
                n_timesteps: m.n_timesteps as u32,
            })
        }
    };
    Ok(pb::Model {
        name: r.name.clone(),
        kind: model_kind_to_proto(r.kind) as i32,
        format: model_format_to_proto(r.format) as i32,
        manifest,
        reward,
        parameter_count: r.parameter_count,
        sha256: r.sha256.clone(),
        size_bytes: r.size_bytes,
        provenance: Some(provenance_to_proto(&r.provenance)),
        created_at: Some(timestamp(r.created_at_ms)),
        description: r.description.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use pb::diffusion_manifest::{Sample, Space as S, Trajectory};

    fn wire() -> pb::DiffusionManifest {
        pb::DiffusionManifest {
            parametrization: pb::Parametrization::X0 as i32,
            schedule: Some(schedule_to_proto(&ScheduleSpec::DiffuserCosine { s: 0.008 })),
            n_timesteps: 20,
            clip_denoised: true,
            space: Some(S::Trajectory(Trajectory { horizon: 8, action_dim: 2, obs_dim: 1 })),
            normalizer: Some(normalizer_to_proto(&Normalizer::Limits { min: vec![0.0; 3], max: vec![1.0; 3] })),
            architecture: None,
        }
    }

    type Edit = Box<dyn Fn(&mut pb::DiffusionManifest)>;

    fn err(m: pb::DiffusionManifest) -> String {
        match diffusion_manifest_from_proto(Some(m), "header.manifest") {
            Err(Error::InvalidArgument(msg)) => msg,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn convert_manifest_round_trips() {
        let m = diffusion_manifest_from_proto(Some(wire()), "header.manifest").expect("valid");
        assert_eq!(m.space.item_shape(), vec![8, 3]);
        assert_eq!(diffusion_manifest_to_proto(&m), wire());
        let mut w = wire();
        w.schedule = Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.0 })) });
        w.space = Some(S::Sample(Sample { shape: vec![3] }));
        let m = diffusion_manifest_from_proto(Some(w), "m").expect("valid");
        assert_eq!(m.schedule, ScheduleSpec::Cosine { s: 0.008 }, "s = 0 means the default");
        let betas = ScheduleSpec::Betas { betas: vec![0.1; 20] };
        let mut w = wire();
        w.schedule = Some(schedule_to_proto(&betas));
        assert_eq!(diffusion_manifest_from_proto(Some(w), "m").expect("valid").schedule, betas);
    }

    #[test]
    fn convert_bad_manifests_name_the_field() {
        let cases: Vec<(Edit, &str)> = vec![
            (Box::new(|w| w.parametrization = 0), "header.manifest.parametrization: unspecified"),
            (Box::new(|w| w.parametrization = 9), "header.manifest.parametrization: unknown value 9"),
            (Box::new(|w| w.schedule = None), "header.manifest.schedule: missing"),
            (
                Box::new(|w| w.schedule = Some(pb::Schedule { kind: None })),
                "header.manifest.schedule: no schedule kind",
            ),
            (Box::new(|w| w.n_timesteps = 0), "header.manifest.n_timesteps"),
            (Box::new(|w| w.space = None), "header.manifest.space: missing"),
            (Box::new(|w| w.normalizer = None), "header.manifest.normalizer: missing"),
            (Box::new(|w| w.normalizer = Some(pb::Normalizer { kind: None })), "header.manifest.normalizer: no"),
            (
                Box::new(|w| w.schedule = Some(schedule_to_proto(&ScheduleSpec::Betas { betas: vec![0.1; 5] }))),
                "header.manifest.schedule.betas: 5 values but n_timesteps is 20",
            ),
            (
                Box::new(|w| w.schedule = Some(schedule_to_proto(&ScheduleSpec::Betas { betas: vec![] }))),
                "header.manifest.schedule.betas: empty",
            ),
            (
                Box::new(|w| {
                    w.normalizer = Some(normalizer_to_proto(&Normalizer::Limits { min: vec![0.0], max: vec![1.0] }))
                }),
                "header.manifest.normalizer.min: 1 values",
            ),
            (
                Box::new(|w| w.schedule = Some(schedule_to_proto(&ScheduleSpec::Linear))),
                "header.manifest.schedule: beta[",
            ),
            (Box::new(|w| w.space = Some(S::Sample(Sample { shape: vec![] }))), "header.manifest.space.shape"),
        ];
        for (edit, needle) in cases {
            let mut w = wire();
            edit(&mut w);
            let msg = err(w);
            assert!(msg.starts_with(needle), "{msg} should start with {needle}");
        }
        assert!(diffusion_manifest_from_proto(None, "header.manifest").is_err());
    }
}
