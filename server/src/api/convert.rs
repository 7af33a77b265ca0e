//! Conversions between the wire types (`relreward.v1`) and the domain types of `engine` and
//! `store`. Wire -> domain conversions validate and name the offending field in every error
//! (the caller passes the field path, e.g. "header.manifest"); domain -> wire conversions of
//! stored records report an unreadable record as `DataLoss`.

use relreward_proto::v1 as pb;

use super::timestamp;
use crate::engine::autoencoder::AutoencoderManifest;
use crate::engine::manifest::DiffusionManifest;
use crate::engine::nets::reward::RewardArchitecture;
use crate::engine::relative_reward::{RewardManifest, RewardSource};
use crate::engine::schedule::Schedule;
use crate::error::{Error, Result};
use crate::store::{ModelFormat, ModelKind, ModelRecord, Provenance};
use relreward_proto::schema::recipe::RecipeManifest;

// ============================================================================================
// Models: diffusion manifests (their wire forms are the shared schema's), model records.
// ============================================================================================

/// Rewrites a schedule-building message ("schedule...: ...") so that it names the request
/// field `field` ("header.manifest.schedule...: ...").
fn at_field(err: Error, field: &str) -> Error {
    match err {
        Error::InvalidArgument(m) if m.starts_with("schedule") => Error::InvalidArgument(format!("{field}.{m}")),
        Error::InvalidArgument(m) => Error::InvalidArgument(format!("{field}: {m}")),
        other => other,
    }
}

/// A wire manifest as an engine manifest, fully validated: the shared schema's checks
/// (`DiffusionManifest::from_proto`: every field present, lengths consistent with the space and
/// T, the architecture with the space) and then the schedule built (every beta in (0, 1), no
/// underflow). `field` is the manifest's path in the request, e.g. "header.manifest"; every
/// error names the offending field below it.
pub fn diffusion_manifest_from_proto(m: Option<pb::DiffusionManifest>, field: &str) -> Result<DiffusionManifest> {
    let manifest = DiffusionManifest::from_proto(m, field)?;
    Schedule::new(&manifest.schedule, manifest.n_timesteps).map_err(|e| at_field(e, field))?;
    Ok(manifest)
}

/// Wire kind filter: UNSPECIFIED means any kind (`None`).
pub fn model_kind_filter_from_proto(v: i32, field: &str) -> Result<Option<ModelKind>> {
    const KINDS: &str = "MODEL_KIND_UNSPECIFIED (any), MODEL_KIND_DIFFUSION, MODEL_KIND_REWARD, \
                         MODEL_KIND_DISCRIMINATOR, MODEL_KIND_AUTOENCODER or MODEL_KIND_RECIPE";
    Ok(match crate::fields::known(field, v, KINDS)? {
        pb::ModelKind::Unspecified => None,
        pb::ModelKind::Diffusion => Some(ModelKind::Diffusion),
        pb::ModelKind::Reward => Some(ModelKind::Reward),
        pb::ModelKind::Discriminator => Some(ModelKind::Discriminator),
        pb::ModelKind::Autoencoder => Some(ModelKind::Autoencoder),
        pb::ModelKind::Recipe => Some(ModelKind::Recipe),
    })
}

pub fn model_kind_to_proto(k: ModelKind) -> pb::ModelKind {
    match k {
        ModelKind::Diffusion => pb::ModelKind::Diffusion,
        ModelKind::Reward => pb::ModelKind::Reward,
        ModelKind::Discriminator => pb::ModelKind::Discriminator,
        ModelKind::Autoencoder => pb::ModelKind::Autoencoder,
        ModelKind::Recipe => pb::ModelKind::Recipe,
    }
}

pub fn model_format_to_proto(f: ModelFormat) -> pb::ModelFormat {
    match f {
        ModelFormat::Torchscript => pb::ModelFormat::Torchscript,
        ModelFormat::Native => pb::ModelFormat::Native,
        ModelFormat::Recipe => pb::ModelFormat::Recipe,
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

/// A stored model record on the wire: a diffusion model's manifest (`Model.manifest`), a reward's
/// or discriminator's details (`Model.reward`), an autoencoder's (`Model.autoencoder`) or a
/// recipe's (`Model.recipe`), each parsed from the record's JSON; an unreadable one is `DataLoss`.
pub fn model_to_proto(r: &ModelRecord) -> Result<pb::Model> {
    fn parse<T: serde::de::DeserializeOwned>(r: &ModelRecord) -> Result<T> {
        serde_json::from_value(r.manifest.clone())
            .map_err(|e| Error::DataLoss(format!("model '{}': its stored manifest is unreadable: {e}", r.name)))
    }
    let (mut manifest, mut reward, mut autoencoder, mut recipe) = (None, None, None, None);
    match r.kind {
        ModelKind::Diffusion => manifest = Some(parse::<DiffusionManifest>(r)?.to_proto()),
        ModelKind::Autoencoder => autoencoder = Some(parse::<AutoencoderManifest>(r)?.to_info()),
        ModelKind::Recipe => recipe = Some(parse::<RecipeManifest>(r)?.to_proto()),
        ModelKind::Reward | ModelKind::Discriminator => {
            let m: RewardManifest = parse(r)?;
            reward = Some(pb::RewardInfo {
                base_model: m.base_model.clone(),
                expert_model: m.expert_model.clone(),
                architecture: m.architecture.to_string(),
                window: match &m.architecture {
                    RewardSource::Native(RewardArchitecture::WindowedMlp { window, .. }) => *window as u32,
                    _ => 0,
                },
                input_shape: m.space.item_shape().iter().map(|&d| d as u64).collect(),
                normalizer: Some(m.normalizer.to_proto()),
                n_timesteps: m.n_timesteps as u32,
                base_recipe: m.base_recipe.as_ref().map(RecipeManifest::to_proto),
                expert_recipe: m.expert_recipe.as_ref().map(RecipeManifest::to_proto),
            });
        }
    }
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
        autoencoder,
        recipe,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::manifest::ScheduleSpec;
    use crate::engine::normalizer::Normalizer;
    use pb::diffusion_manifest::{Sample, Space as S, Trajectory};

    fn wire() -> pb::DiffusionManifest {
        pb::DiffusionManifest {
            parametrization: pb::Parametrization::X0 as i32,
            schedule: Some(ScheduleSpec::to_proto(&ScheduleSpec::DiffuserCosine { s: 0.008 })),
            n_timesteps: 20,
            clip_denoised: true,
            space: Some(S::Trajectory(Trajectory { horizon: 8, action_dim: 2, obs_dim: 1 })),
            normalizer: Some(Normalizer::to_proto(&Normalizer::Limits { min: vec![0.0; 3], max: vec![1.0; 3] })),
            architecture: None,
            conditioning: None,
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
        assert_eq!(m.to_proto(), wire());
        let mut w = wire();
        w.schedule = Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.0 })) });
        w.space = Some(S::Sample(Sample { shape: vec![3] }));
        let m = diffusion_manifest_from_proto(Some(w), "m").expect("valid");
        assert_eq!(m.schedule, ScheduleSpec::Cosine { s: 0.008 }, "s = 0 means the default");
        let betas = ScheduleSpec::Betas { betas: vec![0.1; 20] };
        let mut w = wire();
        w.schedule = Some(ScheduleSpec::to_proto(&betas));
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
                Box::new(|w| w.schedule = Some(ScheduleSpec::to_proto(&ScheduleSpec::Betas { betas: vec![0.1; 5] }))),
                "header.manifest.schedule.betas: 5 values but n_timesteps is 20",
            ),
            (
                Box::new(|w| w.schedule = Some(ScheduleSpec::to_proto(&ScheduleSpec::Betas { betas: vec![] }))),
                "header.manifest.schedule.betas: empty",
            ),
            (
                Box::new(|w| {
                    w.normalizer = Some(Normalizer::to_proto(&Normalizer::Limits { min: vec![0.0], max: vec![1.0] }))
                }),
                "header.manifest.normalizer.min: 1 values",
            ),
            (
                Box::new(|w| w.schedule = Some(ScheduleSpec::to_proto(&ScheduleSpec::Linear))),
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
