//! The diffusion-training runner: a native denoiser trained on a stored dataset with the DDPM
//! loss, with Adam, optional gradient clipping, EMA weights, periodic held-out loss and
//! checkpoints, registering the EMA model when it succeeds.

use super::context::{JobContext, Stop};
use super::datasets::{array, load_labels, load_rows};
use super::training::TrainLoop;
use crate::engine::data::TrainingData;
use crate::engine::diffusion::DiffusionModel;
use crate::engine::manifest::{Architecture, Conditioning, DiffusionManifest, Space};
use crate::engine::nets::native::NativeDenoiser;
use crate::engine::normalizer::Normalizer;
use crate::engine::rng::Rng;
use crate::error::{Error, Result};
use crate::fields::validate_name;
use crate::store::ingest::now_ms;
use crate::store::{ArrayStats, DatasetKind, DatasetRecord, ModelFormat, ModelKind, ModelRecord, Provenance, Store};
use relreward_proto::schema::job::DiffusionJob;

/// Held-out items per evaluation.
const EVAL_ITEMS: usize = 256;

/// Submission-time checks against the stored dataset: it exists, its kind fits the
/// architecture, and (trajectories) some episode is at least one horizon long.
pub async fn validate_inputs(store: &Store, job: &DiffusionJob) -> Result<()> {
    let ds = store
        .meta
        .get_dataset(&job.dataset)
        .await?
        .ok_or_else(|| Error::NotFound(format!("spec.diffusion.dataset: dataset '{}' not found", job.dataset)))?;
    let mut pooled = Vec::with_capacity(job.normalizer_datasets.len());
    for (i, name) in job.normalizer_datasets.iter().enumerate() {
        validate_name(&format!("spec.diffusion.normalizer_datasets[{i}]"), name)?;
        pooled.push(store.meta.get_dataset(name).await?.ok_or_else(|| {
            Error::NotFound(format!("spec.diffusion.normalizer_datasets[{i}]: dataset '{name}' not found"))
        })?);
    }
    // Fields that only mean something for the other kind of dataset are refused, not ignored.
    if ds.kind == DatasetKind::Trajectories && job.pooled_normalizer {
        return Err(Error::invalid(format!(
            "spec.diffusion.pooled_normalizer: applies to sample datasets only; '{}' holds trajectories (normalized per coordinate by their limits)",
            ds.name
        )));
    }
    if ds.kind == DatasetKind::Samples && job.action_weight != 1.0 {
        return Err(Error::invalid(format!(
            "spec.diffusion.action_weight: {} applies to trajectories only (the first action's loss); '{}' holds samples",
            job.action_weight, ds.name
        )));
    }
    if job.conditional && array(&ds, "labels").is_none() {
        return Err(Error::invalid(format!(
            "spec.diffusion.conditional: dataset '{}' has no 'labels' array to condition on (upload one with the samples)",
            ds.name
        )));
    }
    let manifest = manifest_for(job, &ds, &pooled)?;
    // The network is planned (sizes, parameter count) here, so that an architecture the server
    // cannot build is refused at submission rather than failing the accepted job.
    manifest
        .validate()
        .map_err(Error::from)
        .and_then(|()| match &manifest.architecture {
            Some(arch) => {
                NativeDenoiser::planned_parameter_count(arch, &manifest.space, manifest.conditioning.as_ref())
                    .map(|_| ())
            }
            None => Ok(()),
        })
        .map_err(|e| job_field(e, &job.architecture))?;
    if let (DatasetKind::Trajectories, Some(ep)) = (ds.kind, &ds.episodes)
        && (ep.max_length as usize) < job.horizon
    {
        return Err(Error::invalid(format!(
            "spec.diffusion.horizon: {} exceeds the longest episode ({}) of dataset '{}'",
            job.horizon, ep.max_length, ds.name
        )));
    }
    Ok(())
}

/// Renames the manifest's and the network plan's fields in an error after the job's own
/// (`manifest.n_timesteps` -> `spec.diffusion.n_timesteps`, `architecture.hidden` ->
/// `spec.diffusion.mlp.hidden`), so the message names what the caller sent.
fn job_field(err: Error, architecture: &Architecture) -> Error {
    let Error::InvalidArgument(m) = err else { return err };
    let arch = match architecture {
        Architecture::TemporalUnet { .. } => "spec.diffusion.temporal_unet",
        Architecture::Mlp { .. } => "spec.diffusion.mlp",
        Architecture::Unet2d { .. } => "spec.diffusion.unet2d",
    };
    let renamed = [
        ("manifest.space.horizon", "spec.diffusion.horizon".to_string()),
        ("manifest.architecture", arch.to_string()),
        ("architecture", arch.to_string()),
        ("manifest.space", "spec.diffusion.dataset (its item layout)".to_string()),
        ("manifest.normalizer", "spec.diffusion.dataset (the normalizer from its statistics)".to_string()),
        ("manifest", "spec.diffusion".to_string()),
    ]
    .into_iter()
    .find_map(|(from, to)| m.strip_prefix(from).map(|rest| format!("{to}{rest}")));
    Error::InvalidArgument(renamed.unwrap_or(m))
}

/// The manifest of the model this job trains: layout and normalizer from the dataset.
fn manifest_for(job: &DiffusionJob, ds: &DatasetRecord, pooled: &[DatasetRecord]) -> Result<DiffusionManifest> {
    let one = |ds: &DatasetRecord, name: &str| {
        array(ds, name)
            .and_then(|a| a.stats.clone())
            .map(|s| (ds.num_rows, s))
            .ok_or_else(|| Error::DataLoss(format!("dataset '{}' has no statistics for '{name}'", ds.name)))
    };
    // The statistics of `name` over `ds` and the pooled datasets together.
    let stats = |name: &str| -> Result<ArrayStats> {
        let mut parts = vec![one(ds, name)?];
        for (i, other) in pooled.iter().enumerate() {
            if other.kind != ds.kind {
                return Err(Error::invalid(format!(
                    "spec.diffusion.normalizer_datasets[{i}]: dataset '{}' holds {:?}, '{}' holds {:?}",
                    other.name, other.kind, ds.name, ds.kind
                )));
            }
            let part = one(other, name)?;
            if part.1.min.len() != parts[0].1.min.len() {
                return Err(Error::invalid(format!(
                    "spec.diffusion.normalizer_datasets[{i}]: '{name}' of dataset '{}' has {} coordinates, '{}' has {}",
                    other.name,
                    part.1.min.len(),
                    ds.name,
                    parts[0].1.min.len()
                )));
            }
            parts.push(part);
        }
        Ok(pool(&parts))
    };
    let (space, normalizer) = match ds.kind {
        // Trajectories take either the TemporalUnet (Diffuser's) or an MLP over the flattened
        // window [H * D] (small horizons, CPU budgets: the demo's default).
        DatasetKind::Trajectories => {
            let (act, obs) = (stats("actions")?, stats("observations")?);
            let space = Space::Trajectory { horizon: job.horizon, action_dim: act.min.len(), obs_dim: obs.min.len() };
            // Rows are [action | observation], so the normalizer's coordinates follow suit.
            let normalizer = Normalizer::Limits {
                min: act.min.iter().chain(&obs.min).copied().collect(),
                max: act.max.iter().chain(&obs.max).copied().collect(),
            };
            (space, normalizer)
        }
        DatasetKind::Samples => {
            if !matches!(job.architecture, Architecture::Mlp { .. } | Architecture::Unet2d { .. }) {
                return Err(Error::invalid(format!(
                    "spec.diffusion.architecture: sample dataset '{}' needs mlp or unet2d",
                    ds.name
                )));
            }
            let s = stats("samples")?;
            let shape =
                array(ds, "samples").map(|a| a.shape[1..].iter().map(|&d| d as usize).collect()).unwrap_or_default();
            let s = if job.pooled_normalizer { pool_elements(&s) } else { s };
            (Space::Sample { shape }, Normalizer::Gaussian { mean: s.mean, std: s.std })
        }
    };
    let conditioning = match job.conditional {
        false => None,
        true => {
            // The largest label over the dataset and the pooled ones that have labels (a base
            // and an expert model trained over each other's data share one class count).
            let largest = std::iter::once(ds)
                .chain(pooled)
                .filter_map(|d| array(d, "labels").and_then(|a| a.stats.as_ref()).and_then(|s| s.max.first()))
                .fold(0.0f64, |m, &v| m.max(v)) as usize;
            let classes = job.num_classes.unwrap_or(largest + 1);
            if classes <= largest {
                return Err(Error::invalid(format!(
                    "spec.diffusion.num_classes: {classes}, but dataset '{}' (or a normalizer dataset) holds label {largest}",
                    ds.name
                )));
            }
            // Labels 0..C are the classes, C is the null label the dropout trains.
            Some(Conditioning::Labels { num_classes: classes + 1, null_class: Some(classes) })
        }
    };
    Ok(DiffusionManifest {
        parametrization: job.parametrization,
        schedule: job.schedule.clone(),
        n_timesteps: job.n_timesteps,
        clip_denoised: job.clip_denoised,
        space,
        normalizer,
        architecture: Some(job.architecture.clone()),
        conditioning,
    })
}

/// Classifier-free guidance's condition dropout: each label replaced by `null` with
/// probability `p`, drawn from the loop's stream (one uniform per item, so a resumed job draws
/// the same).
fn drop_labels(labels: &tch::Tensor, p: f64, null: i64, rng: &mut Rng) -> Result<tch::Tensor> {
    if p == 0.0 {
        return Ok(labels.shallow_clone());
    }
    let n = labels.size()[0];
    let keep: Vec<bool> = (0..n).map(|_| rng.uniform() >= p).collect();
    let keep = crate::engine::upload(&tch::Tensor::from_slice(&keep), labels.device())?;
    Ok(labels.f_where_scalarother(&keep, null)?)
}

/// Statistics of the union of datasets from each one's (rows, stats): min of mins, max of
/// maxes, and the pooled mean and (population) standard deviation.
fn pool(parts: &[(u64, ArrayStats)]) -> ArrayStats {
    let d = parts[0].1.min.len();
    let total: f64 = parts.iter().map(|(n, _)| *n as f64).sum::<f64>().max(1.0);
    let mut out = ArrayStats {
        min: vec![f64::INFINITY; d],
        max: vec![f64::NEG_INFINITY; d],
        mean: vec![0.0; d],
        std: vec![0.0; d],
    };
    for j in 0..d {
        let mut second = 0.0;
        for (n, s) in parts {
            let w = *n as f64 / total;
            out.min[j] = out.min[j].min(s.min[j]);
            out.max[j] = out.max[j].max(s.max[j]);
            out.mean[j] += w * s.mean[j];
            second += w * (s.std[j] * s.std[j] + s.mean[j] * s.mean[j]);
        }
        out.std[j] = (second - out.mean[j] * out.mean[j]).max(0.0).sqrt();
    }
    out
}

/// Every coordinate's mean and std replaced by those of all elements together (each coordinate
/// holds the same number of rows, so the pooled moments are plain averages of the per-coordinate
/// ones), for `pooled_normalizer`.
fn pool_elements(s: &ArrayStats) -> ArrayStats {
    let d = s.mean.len().max(1) as f64;
    let mean = s.mean.iter().sum::<f64>() / d;
    let second = s.mean.iter().zip(&s.std).map(|(m, sd)| sd * sd + m * m).sum::<f64>() / d;
    let std = (second - mean * mean).max(0.0).sqrt();
    let n = s.mean.len();
    ArrayStats {
        min: vec![s.min.iter().copied().fold(f64::INFINITY, f64::min); n],
        max: vec![s.max.iter().copied().fold(f64::NEG_INFINITY, f64::max); n],
        mean: vec![mean; n],
        std: vec![std; n],
    }
}

pub fn run(ctx: &mut JobContext, job: &DiffusionJob) -> std::result::Result<String, Stop> {
    let spec = ctx.spec.clone();
    let opt = &spec.optimization;
    let store = ctx.store().clone();
    let ds = ctx
        .block_on(store.meta.get_dataset(&job.dataset))?
        .ok_or_else(|| Error::NotFound(format!("dataset '{}' was deleted", job.dataset)))?;
    let mut pooled = Vec::with_capacity(job.normalizer_datasets.len());
    for name in &job.normalizer_datasets {
        pooled.push(
            ctx.block_on(store.meta.get_dataset(name))?
                .ok_or_else(|| Error::NotFound(format!("dataset '{name}' was deleted")))?,
        );
    }
    let manifest = manifest_for(job, &ds, &pooled)?;
    let dir = ctx.block_on(store.blobs.local_dir(&ds.blob_key))?;
    let (rows, starts) = load_rows(&dir, &ds, job.horizon)?;
    let mut data = TrainingData::new(
        &rows,
        &manifest.normalizer,
        manifest.space.normalizer_dims(),
        starts.as_ref().map(|_| job.horizon),
        starts,
        spec.seed,
    )?;
    // (dropout probability, null label) of conditional training.
    let dropout = match manifest.conditioning {
        Some(Conditioning::Labels { null_class: Some(null), .. }) => {
            let labels = load_labels(&dir, &ds)?
                .ok_or_else(|| Error::NotFound(format!("dataset '{}' lost its labels", ds.name)))?;
            data = data.with_labels(labels)?;
            Some((job.condition_dropout.unwrap_or(0.0), null as i64))
        }
        _ => None,
    };
    let data = data.to_device(crate::engine::device());

    let device = crate::engine::device();
    let arch = manifest.architecture.clone().ok_or_else(|| Error::internal("diffusion job", "no architecture"))?;
    // The seed draws the first weights only; every later draw uses the loop's Rng.
    let denoiser = NativeDenoiser::new(&arch, &manifest.space, manifest.conditioning.as_ref(), spec.seed, device)?;
    let mut train = TrainLoop::new(denoiser.weights().var_store(), opt, spec.seed);
    let model = DiffusionModel::new(manifest.clone(), Box::new(denoiser))?;
    if train.resume(ctx)?.is_none() {
        ctx.log(format!(
            "training {} parameters on {} windows of dataset '{}'",
            model.net().parameter_count(),
            data.train_len(),
            ds.name
        ))?;
    }

    let action_weight = match manifest.space {
        Space::Trajectory { action_dim, .. } if job.action_weight != 1.0 && action_dim > 0 => {
            Some((job.action_weight, action_dim))
        }
        _ => None,
    };
    let t_max = manifest.n_timesteps as u64;
    let held_out = data.labeled_held_out(EVAL_ITEMS);
    let batch = opt.batch_size;
    train.run(
        ctx,
        |rng| {
            let (x0, labels) = data.labeled_batch(rng, batch);
            let t = rng.randint(t_max, batch, device);
            let noise = rng.randn(&x0.size(), device);
            let cond = match (labels, dropout) {
                (Some(labels), Some((p, null))) => Some(drop_labels(&labels, p, null, rng)?),
                _ => None,
            };
            model.loss(&x0, &t, &noise, action_weight, cond.as_ref())
        },
        || {
            let Some((x, labels)) = &held_out else { return Ok(None) };
            // A fixed draw of t and noise, so successive held-out losses are comparable; the
            // held-out loss is the conditional one (no dropout).
            let mut eval_rng = Rng::new(spec.seed ^ 0xe7a1);
            let n = x.size()[0] as usize;
            let t = eval_rng.randint(t_max, n, device);
            let noise = eval_rng.randn(&x.size(), device);
            Ok(Some(tch::no_grad(|| model.loss(x, &t, &noise, action_weight, labels.as_ref()))?.double_value(&[])))
        },
    )?;

    // The registered model carries the EMA weights (what Diffuser samples with).
    train.use_ema_weights();
    let staging = ctx.staging()?;
    let (sha256, size_bytes) = train.write_final(&staging.path().join("weights.safetensors"))?;
    let manifest_json = serde_json::to_value(&manifest).map_err(|e| Error::internal("encoding manifest", e))?;
    let pretty = serde_json::to_vec_pretty(&manifest_json).map_err(|e| Error::internal("encoding manifest", e))?;
    std::fs::write(staging.path().join("manifest.json"), pretty)?;
    let record = ModelRecord {
        name: spec.output_model.clone(),
        kind: ModelKind::Diffusion,
        format: ModelFormat::Native,
        manifest: manifest_json,
        parameter_count: model.net().parameter_count(),
        sha256,
        size_bytes,
        file: "weights.safetensors".into(),
        provenance: Provenance::Trained {
            job_id: ctx.id().to_owned(),
            datasets: vec![ds.name.clone()],
            models: Vec::new(),
            final_loss: train.loss,
        },
        created_at_ms: now_ms(),
        description: format!("diffusion model trained on '{}' for {} steps", ds.name, opt.steps),
        blob_key: String::new(),
    };
    ctx.register_model(staging, record)?;
    Ok(format!("registered model '{}' (final loss {:.6})", spec.output_model, train.loss))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pooled statistics equal those of the concatenated data.
    #[test]
    fn pooled_statistics_are_those_of_the_union() {
        let a = [1.0f64, 2.0, 6.0];
        let b = [-3.0f64, 0.5];
        let stats = |v: &[f64]| {
            let n = v.len() as f64;
            let mean = v.iter().sum::<f64>() / n;
            let std = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
            let min = v.iter().copied().fold(f64::INFINITY, f64::min);
            let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            ArrayStats { min: vec![min], max: vec![max], mean: vec![mean], std: vec![std] }
        };
        let pooled = pool(&[(3, stats(&a)), (2, stats(&b))]);
        let all: Vec<f64> = a.iter().chain(&b).copied().collect();
        let want = stats(&all);
        assert_eq!((pooled.min[0], pooled.max[0]), (want.min[0], want.max[0]));
        assert!((pooled.mean[0] - want.mean[0]).abs() < 1e-12);
        assert!((pooled.std[0] - want.std[0]).abs() < 1e-12);
    }
}
