//! The relative-reward runner (Algorithm 1): rho trained by gradient alignment against a
//! frozen base and expert diffusion model on the union of the named datasets, registered as
//! a reward model when it succeeds.

use std::cell::RefCell;

use tch::{Device, Kind, Tensor};

use super::context::{JobContext, Stop};
use super::datasets::load_rows;
use super::spec::{DiscriminatorJob, RewardAlgorithm, RewardJob};
use super::training::TrainLoop;
use crate::engine::data::TrainingData;
use crate::engine::diffusion::DiffusionModel;
use crate::engine::manifest::{DiffusionManifest, Space};
use crate::engine::nets::reward::{RewardArchitecture, RewardNet};
use crate::engine::normalizer::Normalizer;
use crate::engine::registry::load_diffusion_copy;
use crate::engine::relative_reward::{
    ConditionEntries, EvalPoint, Objective, RewardManifest, Target, alignment_error, alignment_loss, check_pair,
    entry_weights, noised, noised_target_and_point,
};
use crate::engine::reward_model::STEP_NORM_FILE;
use crate::engine::rng::Rng;
use crate::engine::target_pool::{TargetPool, TargetSource};
use crate::error::{Error, Result};
use crate::store::ingest::now_ms;
use crate::store::{DatasetKind, ModelFormat, ModelKind, ModelRecord, Provenance, Store};

/// Held-out items per evaluation.
const EVAL_ITEMS: usize = 256;

/// The default reward network for a space (the paper's tables): windowed MLP h = 4 with
/// (128, 64, 32) for trajectories (h = 1 if the horizon is not a multiple of 4), the latent
/// conv encoder for [C, H, W] samples, an MLP for other samples.
pub fn default_architecture(space: &Space) -> RewardArchitecture {
    match space {
        Space::Trajectory { horizon, .. } => {
            RewardArchitecture::WindowedMlp { window: if horizon % 4 == 0 { 4 } else { 1 }, hidden: vec![128, 64, 32] }
        }
        Space::Sample { shape } if shape.len() == 3 => {
            RewardArchitecture::ConvEncoder { widths: vec![32, 64, 128, 256] }
        }
        Space::Sample { .. } => RewardArchitecture::Mlp { hidden: vec![128, 64, 32] },
    }
}

async fn diffusion_manifest(store: &Store, field: &str, name: &str) -> Result<DiffusionManifest> {
    let record = store
        .meta
        .get_model(name)
        .await?
        .ok_or_else(|| Error::NotFound(format!("{field}: model '{name}' not found")))?;
    if record.kind != ModelKind::Diffusion {
        return Err(Error::invalid(format!("{field}: model '{name}' is not a diffusion model")));
    }
    serde_json::from_value(record.manifest)
        .map_err(|e| Error::DataLoss(format!("model '{name}': manifest unreadable: {e}")))
}

/// Submission-time checks: both models exist and agree (shape, schedule, normalizer), the
/// architecture fits their item shape, and every dataset exists and matches their layout.
pub async fn validate_inputs(store: &Store, job: &RewardJob) -> Result<()> {
    let base = diffusion_manifest(store, "spec.reward.base_model", &job.base_model).await?;
    let expert = diffusion_manifest(store, "spec.reward.expert_model", &job.expert_model).await?;
    if base.space != expert.space {
        return Err(Error::invalid(format!(
            "spec.reward: base model space {:?} differs from expert model space {:?}",
            base.space, expert.space
        )));
    }
    if base.n_timesteps != expert.n_timesteps || base.schedule != expert.schedule {
        return Err(Error::invalid(format!(
            "spec.reward: base schedule ({:?}, T = {}) differs from expert schedule ({:?}, T = {})",
            base.schedule, base.n_timesteps, expert.schedule, expert.n_timesteps
        )));
    }
    // Different normalizers are aligned through raw coordinates in Algorithm 1
    // (engine::relative_reward::Alignment). Algorithm 2 steps both models from one shared
    // chain state in one unit system, which has no such alignment yet.
    if base.normalizer != expert.normalizer && matches!(job.algorithm, RewardAlgorithm::ModelsOnly { .. }) {
        return Err(Error::invalid(
            "spec.reward: base and expert models have different normalizers; Algorithm 2 (models_only) needs one \
             shared normalizer (Algorithm 1, with_dataset, aligns them through raw coordinates)",
        ));
    }
    RewardNet::planned_parameter_count(&job.architecture, &base.space.item_shape())
        .map_err(|e| Error::invalid(format!("spec.reward.architecture: {e}")))?;
    if let Some(a) = &job.amortised_targets {
        a.check_memory(base.space.item_shape().iter().product::<i64>() as usize)?;
    }
    // Weights other than 1 need a trajectory space: refused at submission, not at run time.
    entry_weights(&base.space, job.action_weight, job.condition_weight, tch::Device::Cpu, "spec.reward")?;
    if job.inpaint_condition {
        ConditionEntries::of(&base.space, "spec.reward.inpaint_condition")?;
    }
    match &job.algorithm {
        RewardAlgorithm::ModelsOnly { .. } => {}
        RewardAlgorithm::WithDataset { datasets } => {
            for (i, name) in datasets.iter().enumerate() {
                let field = format!("spec.reward.with_dataset.datasets[{i}]");
                let ds = store
                    .meta
                    .get_dataset(name)
                    .await?
                    .ok_or_else(|| Error::NotFound(format!("{field}: dataset '{name}' not found")))?;
                let width = |array: &str| {
                    ds.arrays.iter().find(|a| a.name == array).and_then(|a| a.shape.get(1).copied()).unwrap_or(0)
                        as usize
                };
                match (&base.space, ds.kind) {
                    (Space::Trajectory { horizon, action_dim, obs_dim }, DatasetKind::Trajectories) => {
                        if (width("actions"), width("observations")) != (*action_dim, *obs_dim) {
                            return Err(Error::invalid(format!(
                                "{field}: dataset '{name}' has action_dim {} and obs_dim {} but the models have {action_dim} and {obs_dim}",
                                width("actions"),
                                width("observations")
                            )));
                        }
                        if ds.episodes.as_ref().is_some_and(|e| (e.max_length as usize) < *horizon) {
                            return Err(Error::invalid(format!(
                                "{field}: dataset '{name}' has no episode as long as the models' horizon {horizon}"
                            )));
                        }
                    }
                    (Space::Sample { shape }, DatasetKind::Samples) => {
                        let item: Vec<usize> = ds
                            .arrays
                            .iter()
                            .find(|a| a.name == "samples")
                            .map(|a| a.shape[1..].iter().map(|&d| d as usize).collect())
                            .unwrap_or_default();
                        if &item != shape {
                            return Err(Error::invalid(format!(
                                "{field}: dataset '{name}' items have shape {item:?} but the models' have {shape:?}"
                            )));
                        }
                    }
                    _ => {
                        return Err(Error::invalid(format!(
                            "{field}: dataset '{name}' is {:?} but the models sample {:?}",
                            ds.kind, base.space
                        )));
                    }
                }
            }
        }
    }
    Ok(())
}

/// Where training items come from.
enum Pairs {
    /// Algorithm 1: clean items, noised at every step.
    Dataset(TrainingData),
    /// Algorithm 2: recorded chain steps.
    Chains(ChainPairs),
}

impl Pairs {
    fn train_len(&self) -> usize {
        match self {
            Self::Dataset(d) => d.train_len(),
            Self::Chains(c) => c.train as usize,
        }
    }
}

/// Algorithm 2's recorded steps: at x (time t) both models stepped from the same point with
/// the same noise; target = x_{t-1}^expert - x_{t-1}^base, both standardised per step (see
/// [`chain_pairs`]). The last 5% are held out.
struct ChainPairs {
    x: Tensor,
    t: Tensor,
    target: Tensor,
    train: i64,
    /// Per-step standardisation tables [T, *item] by time index: `input_mean` and `input_std`
    /// map a state at time t to rho's input; `target_std` scales the targets.
    step_norm: Vec<(String, Tensor)>,
}

/// Runs `k` chains from x_T ~ N(0, I); at every step both models' next states are computed
/// from the same x_t with the same noise, and the chain follows the base model's step in the
/// first half of the chains and the expert's in the second half (the paper's Algorithm 2).
fn chain_pairs(base: &DiffusionModel, expert: &DiffusionModel, k: usize, rng: &mut Rng) -> Result<ChainPairs> {
    let _guard = tch::no_grad_guard();
    let device = crate::engine::device();
    let mut shape = vec![k as i64];
    shape.extend(base.item_shape());
    let mut x = rng.randn(&shape, device);
    let half = (k / 2) as i64;
    let (mut xs, mut ts, mut targets) = (Vec::new(), Vec::new(), Vec::new());
    // Per-step statistics of the chain states, pooled over both halves: `level_stats[t]` is
    // the state the step at time index t starts from, and the (mean, std) of the states it
    // produces is the next entry.
    let mut in_stats = Vec::new();
    let mut out_stats = Vec::new();
    for step in (0..base.n_timesteps()).rev() {
        let t = Tensor::full([k as i64], step as i64, (Kind::Int64, device));
        let mu_b = base.model_mean(&x, &t)?;
        let mu_e = expert.model_mean(&x, &t)?;
        let (x_b, x_e) = if step > 0 {
            let sigma =
                base.schedule.extract(crate::engine::schedule::Table::PosteriorLogVarianceClipped, &t, shape.len())?;
            let noise = rng.randn(&shape, device) * (sigma * 0.5).exp();
            (mu_b + &noise, mu_e + noise)
        } else {
            (mu_b, mu_e)
        };
        in_stats.push(step_stats(&x));
        out_stats.push(step_stats(&Tensor::cat(&[&x_b, &x_e], 0)));
        xs.push(x.shallow_clone());
        ts.push(t);
        targets.push(&x_e - &x_b);
        x = Tensor::cat(&[x_b.narrow(0, 0, half), x_e.narrow(0, half, k as i64 - half)], 0);
    }
    // Standardise per step (the authors' treatment of Stable Diffusion latents): inputs with
    // their own step's statistics, targets by the scale of the states they point between.
    // Time index t = T-1-i for the i-th recorded step. The scales are one number per step (see
    // [`step_stats`]), so that within a step grad_x rho stays parallel to x^expert - x^base.
    let mut norm_x = Vec::with_capacity(xs.len());
    let mut norm_target = Vec::with_capacity(xs.len());
    for (i, (x, target)) in xs.iter().zip(&targets).enumerate() {
        let (mean, std) = &in_stats[i];
        norm_x.push((x - mean) / std);
        norm_target.push(target / &out_stats[i].1);
    }
    // Tables indexed by time index t (the recorded order runs from T-1 down to 0).
    let input_mean = Tensor::stack(&in_stats.iter().rev().map(|(m, _)| m.shallow_clone()).collect::<Vec<_>>(), 0);
    let input_std = Tensor::stack(&in_stats.iter().rev().map(|(_, s)| s.shallow_clone()).collect::<Vec<_>>(), 0);
    let target_std = Tensor::stack(&out_stats.iter().rev().map(|(_, s)| s.shallow_clone()).collect::<Vec<_>>(), 0);
    let x = Tensor::cat(&norm_x, 0);
    let t = Tensor::cat(&ts, 0);
    let target = Tensor::cat(&norm_target, 0);
    // Shuffle once (seeded) so the held-out tail covers every t.
    let n = x.size()[0];
    let mut order: Vec<i64> = (0..n).collect();
    for i in (1..order.len()).rev() {
        order.swap(i, rng.below(i as u64 + 1) as usize);
    }
    let order = crate::engine::upload(&Tensor::from_slice(&order), x.device())?;
    let train = n - (n / 20).max(1);
    Ok(ChainPairs {
        x: x.index_select(0, &order),
        t: t.index_select(0, &order),
        target: target.index_select(0, &order),
        train,
        step_norm: vec![
            ("input_mean".into(), input_mean),
            ("input_std".into(), input_std),
            ("target_std".into(), target_std),
        ],
    })
}

/// A step's standardisation: the per-element mean over the batch, and one standard deviation
/// pooled over the batch and every element (deviations from that mean), broadcast to the item
/// shape; floored at 1e-6 so that a constant step standardises to 0 instead of dividing by zero.
///
/// Why one scale per step and not one per element: rho is fitted in standardised coordinates
/// z = (x - mean) / std to target / target_std, so in the state's own coordinates
/// grad_x rho = (x^expert - x^base) / (std * target_std). Per-element scales would reweight the
/// target element by element: on images, the background pixels that every model keeps nearly
/// constant have scales near 0 (the noise of the last steps, the spread of the denoised mean),
/// and their tiny, meaningless disagreements then outweighed the digit strokes by orders of
/// magnitude (Algorithm 2 on scikit-learn's digits: docs/results.md). One scale per step only
/// rescales the target per t, as the models' own noise levels do. The per-element mean is a
/// translation and leaves gradients unchanged.
fn step_stats(x: &Tensor) -> (Tensor, Tensor) {
    let mean = x.mean_dim(0, false, Kind::Float);
    let std = (x - &mean).square().mean(Kind::Float).sqrt().clamp_min(1e-6);
    let std = std.expand(mean.size(), false).contiguous();
    (mean, std)
}

/// The union of the datasets in the models' normalized units: rows concatenated, window
/// starts shifted accordingly.
fn dataset_union(
    ctx: &JobContext,
    datasets: &[String],
    space: &Space,
    normalizer: &Normalizer,
    seed: u64,
) -> Result<TrainingData> {
    let horizon = match space {
        Space::Trajectory { horizon, .. } => Some(*horizon),
        Space::Sample { .. } => None,
    };
    let store = ctx.store().clone();
    let (mut all_rows, mut all_starts, mut offset) = (Vec::new(), Vec::new(), 0i64);
    for name in datasets {
        let ds = ctx
            .block_on(store.meta.get_dataset(name))?
            .ok_or_else(|| Error::NotFound(format!("dataset '{name}' was deleted")))?;
        let dir = ctx.block_on(store.blobs.local_dir(&ds.blob_key))?;
        let (rows, starts) = load_rows(&dir, &ds, horizon.unwrap_or(1))?;
        let n = rows.size()[0];
        match starts {
            Some(s) => all_starts.extend(s.into_iter().map(|i| i + offset)),
            None => all_starts.extend(offset..offset + n),
        }
        offset += n;
        all_rows.push(rows);
    }
    let rows = Tensor::cat(&all_rows, 0);
    Ok(TrainingData::new(&rows, normalizer, space.normalizer_dims(), horizon, Some(all_starts), seed)?
        .to_device(crate::engine::device()))
}

fn load_model(ctx: &JobContext, name: &str) -> Result<DiffusionModel> {
    let store = ctx.store().clone();
    let record = ctx
        .block_on(store.meta.get_model(name))?
        .ok_or_else(|| Error::NotFound(format!("model '{name}' was deleted")))?;
    let dir = ctx.block_on(store.blobs.local_dir(&record.blob_key))?;
    load_diffusion_copy(&record, &dir, crate::engine::device())
}

pub fn run(ctx: &mut JobContext, job: &RewardJob) -> std::result::Result<String, Stop> {
    let spec = ctx.spec.clone();
    let opt = &spec.optimization;
    let device = crate::engine::device();
    let base = load_model(ctx, &job.base_model)?;
    let expert = load_model(ctx, &job.expert_model)?;
    check_pair(&base, &expert)?;
    if matches!(job.algorithm, RewardAlgorithm::ModelsOnly { .. })
        && crate::engine::relative_reward::Alignment::between(&base, &expert).is_some()
    {
        return Err(Error::invalid(
            "spec.reward: base and expert models have different normalizers; Algorithm 2 needs one shared normalizer",
        )
        .into());
    }
    let space = base.manifest.space.clone();
    let normalizer = base.manifest.normalizer.clone();
    let pairs = match &job.algorithm {
        RewardAlgorithm::WithDataset { datasets } => {
            Pairs::Dataset(dataset_union(ctx, datasets, &space, &normalizer, spec.seed)?)
        }
        RewardAlgorithm::ModelsOnly { num_chains } => {
            ctx.check_stop()?;
            // Regenerated identically after a resume (own seed), so pairs need no checkpoint.
            let mut rng = Rng::new(spec.seed ^ 0xa162);
            Pairs::Chains(chain_pairs(&base, &expert, *num_chains, &mut rng)?)
        }
    };
    let datasets = match &job.algorithm {
        RewardAlgorithm::WithDataset { datasets } => datasets.clone(),
        RewardAlgorithm::ModelsOnly { .. } => Vec::new(),
    };
    tch::manual_seed(spec.seed as i64); // initialization only; every later draw uses the loop's Rng
    let item_shape = space.item_shape();
    let reward = RewardNet::new(&job.architecture, &item_shape, device)?;
    let mut train = TrainLoop::new(reward.var_store(), opt, spec.seed);
    if train.resume(ctx)?.is_none() {
        ctx.log(format!(
            "extracting a relative reward ({}, {} parameters) from '{}' (base) and '{}' (expert) on {} training items",
            reward.describe(),
            reward.parameter_count(),
            job.base_model,
            job.expert_model,
            pairs.train_len()
        ))?;
    }
    let weights = entry_weights(&space, job.action_weight, job.condition_weight, device, "spec.reward")?;
    let condition =
        job.inpaint_condition.then(|| ConditionEntries::of(&space, "spec.reward.inpaint_condition")).transpose()?;
    let t_max = base.manifest.n_timesteps as u64;
    let batch = opt.batch_size;
    // The training step and the held-out evaluation both compute targets, one at a time; each
    // borrows the expert mutably for the duration (it runs on a helper thread beside the base,
    // engine/threads.rs).
    let expert = RefCell::new(expert);
    let expert_mut =
        || expert.try_borrow_mut().map_err(|_| Error::internal("reward job", "the expert model is already in use"));
    // (t, target, evaluation point) for a batch.
    let draw = |rng: &mut Rng, held_out: bool| -> Result<Option<(Tensor, Tensor, Tensor)>> {
        match &pairs {
            Pairs::Dataset(data) => {
                let x0 = if held_out {
                    match data.held_out(EVAL_ITEMS) {
                        Some(x) => x,
                        None => return Ok(None),
                    }
                } else {
                    data.batch(rng, batch)
                };
                let n = x0.size()[0] as usize;
                let t = rng.randint(t_max, n, device);
                let noise = rng.randn(&x0.size(), device);
                let mut expert = expert_mut()?;
                let (target, point) = noised_target_and_point(
                    &base,
                    &mut expert,
                    &x0,
                    &t,
                    &noise,
                    condition,
                    job.target,
                    job.eval_point,
                )?;
                Ok(Some((t, target, point)))
            }
            Pairs::Chains(c) => {
                let idx: Vec<i64> = if held_out {
                    (c.train..c.t.size()[0]).take(EVAL_ITEMS).collect()
                } else {
                    (0..batch).map(|_| rng.below(c.train as u64) as i64).collect()
                };
                if idx.is_empty() {
                    return Ok(None);
                }
                let idx = crate::engine::upload(&Tensor::from_slice(&idx), c.t.device())?;
                Ok(Some((c.t.index_select(0, &idx), c.target.index_select(0, &idx), c.x.index_select(0, &idx))))
            }
        }
    };
    // Amortised targets: a pool filled and refreshed on the step schedule (see
    // engine/target_pool.rs); `step` mirrors the loop's counter, which starts at the resumed step.
    let mut pool = match (&job.amortised_targets, &pairs) {
        (Some(a), Pairs::Dataset(_)) => Some(TargetPool::new(*a, spec.seed, batch, t_max)),
        _ => None,
    };
    if let Some(a) = job.amortised_targets.as_ref().filter(|_| pool.is_some()) {
        ctx.log(format!(
            "amortised targets: pool {}, reuse {}, refresh fraction {} ({} items every {} steps)",
            a.pool_size,
            a.reuse,
            a.refresh_fraction,
            a.refresh_items(),
            a.steps_per_epoch(batch)
        ))?;
    }
    let mut step = train.step;
    train.run(
        ctx,
        |rng| {
            step += 1;
            let (t, target, point) = match (&mut pool, &pairs) {
                (Some(pool), Pairs::Dataset(data)) => {
                    let mut expert = expert_mut()?;
                    let mut src = TargetSource {
                        base: &base,
                        expert: &mut expert,
                        data,
                        condition,
                        target: job.target,
                        eval_point: job.eval_point,
                    };
                    pool.ensure(step, &mut src)?;
                    pool.sample(rng)
                }
                _ => draw(rng, false)?.ok_or_else(|| Error::internal("reward job", "empty batch"))?,
            };
            alignment_loss(&reward, &point, &t, &target, weights.as_ref(), job.rho_l2)
        },
        || {
            let mut eval_rng = Rng::new(spec.seed ^ 0xe7a1);
            let Some((t, target, point)) = draw(&mut eval_rng, true)? else { return Ok(None) };
            let (_, grad) = reward.grad(&point, &t)?;
            // The training objective on held-out items, weights included.
            Ok(Some(alignment_error(&grad, &target, weights.as_ref()).double_value(&[])))
        },
    )?;

    let manifest = RewardManifest {
        architecture: job.architecture.clone(),
        space,
        normalizer,
        n_timesteps: base.manifest.n_timesteps,
        base_model: job.base_model.clone(),
        expert_model: job.expert_model.clone(),
        datasets,
        objective: Objective::Alignment {
            target: job.target,
            eval_point: job.eval_point,
            models_only: matches!(job.algorithm, RewardAlgorithm::ModelsOnly { .. }),
            action_weight: job.action_weight,
            condition_weight: job.condition_weight,
        },
        step_normalization: matches!(job.algorithm, RewardAlgorithm::ModelsOnly { .. }),
        inpaint_condition: job.inpaint_condition,
        final_loss: train.loss,
        eval_loss: train.eval_loss,
    };
    let description =
        format!("relative reward of '{}' over '{}' ({})", job.expert_model, job.base_model, reward.describe());
    let step_norm: Vec<(String, Tensor)> = match &pairs {
        Pairs::Chains(c) => c.step_norm.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect(),
        Pairs::Dataset(_) => Vec::new(),
    };
    register(ctx, &train, &reward, manifest, ModelKind::Reward, description, &step_norm)
}

/// Registers the job's output: EMA weights and the manifest, as a reward or discriminator model.
fn register(
    ctx: &mut JobContext,
    train: &TrainLoop,
    net: &RewardNet,
    manifest: RewardManifest,
    kind: ModelKind,
    description: String,
    step_norm: &[(String, Tensor)],
) -> std::result::Result<String, Stop> {
    let spec = ctx.spec.clone();
    train.use_ema_weights();
    let staging = ctx.staging()?;
    if !step_norm.is_empty() {
        let step_norm: Vec<(&String, Tensor)> = step_norm.iter().map(|(n, t)| (n, t.to_device(Device::Cpu))).collect();
        Tensor::write_safetensors(&step_norm, staging.path().join(STEP_NORM_FILE))
            .map_err(|e| Error::internal("writing step normalization", e))?;
    }
    let (sha256, size_bytes) = train.write_final(&staging.path().join("weights.safetensors"))?;
    let manifest_json = serde_json::to_value(&manifest).map_err(|e| Error::internal("encoding manifest", e))?;
    let pretty = serde_json::to_vec_pretty(&manifest_json).map_err(|e| Error::internal("encoding manifest", e))?;
    std::fs::write(staging.path().join("manifest.json"), pretty)?;
    let mut models = vec![manifest.base_model.clone()];
    if !manifest.expert_model.is_empty() {
        models.push(manifest.expert_model.clone());
    }
    let record = ModelRecord {
        name: spec.output_model.clone(),
        kind,
        format: ModelFormat::Native,
        manifest: manifest_json,
        parameter_count: net.parameter_count(),
        sha256,
        size_bytes,
        file: "weights.safetensors".into(),
        provenance: Provenance::Trained {
            job_id: ctx.id().to_owned(),
            datasets: manifest.datasets.clone(),
            models,
            final_loss: train.loss,
        },
        created_at_ms: now_ms(),
        description,
        blob_key: String::new(),
    };
    ctx.register_model(staging, record)?;
    Ok(format!("registered model '{}' (final loss {:.6})", spec.output_model, train.loss))
}

/// Submission-time checks of a discriminator job: the diffusion model exists, both datasets
/// match its layout, and the architecture fits.
pub async fn validate_discriminator(store: &Store, job: &DiscriminatorJob) -> Result<()> {
    let as_reward = RewardJob {
        base_model: job.diffusion_model.clone(),
        expert_model: job.diffusion_model.clone(),
        architecture: job.architecture.clone(),
        target: Target::Mean,
        eval_point: EvalPoint::XT,
        algorithm: RewardAlgorithm::WithDataset {
            datasets: vec![job.base_dataset.clone(), job.expert_dataset.clone()],
        },
        rho_l2: 0.0,
        amortised_targets: None,
        action_weight: 1.0,
        condition_weight: 1.0,
        inpaint_condition: false,
    };
    // The reward job's field names, renamed to the discriminator's own.
    let rename = |m: String| {
        [
            ("spec.reward.with_dataset.datasets[0]", "spec.discriminator.base_dataset"),
            ("spec.reward.with_dataset.datasets[1]", "spec.discriminator.expert_dataset"),
            ("spec.reward.base_model", "spec.discriminator.diffusion_model"),
            ("spec.reward.expert_model", "spec.discriminator.diffusion_model"),
            ("spec.reward", "spec.discriminator"),
        ]
        .iter()
        .fold(m, |m, (from, to)| m.replace(from, to))
    };
    validate_inputs(store, &as_reward).await.map_err(|e| match e {
        Error::InvalidArgument(m) => Error::InvalidArgument(rename(m)),
        Error::NotFound(m) => Error::NotFound(rename(m)),
        other => other,
    })?;
    if job.inpaint_condition {
        let model = diffusion_manifest(store, "spec.discriminator.diffusion_model", &job.diffusion_model).await?;
        ConditionEntries::of(&model.space, "spec.discriminator.inpaint_condition")?;
    }
    Ok(())
}

/// The discriminator baseline: the same networks trained with binary cross-entropy to tell
/// noised expert items (label 1) from noised base items (label 0) at every diffusion time, so
/// that it can guide sampling like the relative reward.
pub fn run_discriminator(ctx: &mut JobContext, job: &DiscriminatorJob) -> std::result::Result<String, Stop> {
    let spec = ctx.spec.clone();
    let opt = &spec.optimization;
    let device = crate::engine::device();
    let model = load_model(ctx, &job.diffusion_model)?;
    let space = model.manifest.space.clone();
    let normalizer = model.manifest.normalizer.clone();
    let base = dataset_union(ctx, std::slice::from_ref(&job.base_dataset), &space, &normalizer, spec.seed)?;
    let expert = dataset_union(ctx, std::slice::from_ref(&job.expert_dataset), &space, &normalizer, spec.seed ^ 1)?;
    tch::manual_seed(spec.seed as i64);
    let net = RewardNet::new(&job.architecture, &space.item_shape(), device)?;
    let mut train = TrainLoop::new(net.var_store(), opt, spec.seed);
    if train.resume(ctx)?.is_none() {
        ctx.log(format!(
            "training a discriminator ({}) on '{}' vs '{}'",
            net.describe(),
            job.base_dataset,
            job.expert_dataset
        ))?;
    }
    let condition = job
        .inpaint_condition
        .then(|| ConditionEntries::of(&space, "spec.discriminator.inpaint_condition"))
        .transpose()?;
    let t_max = model.manifest.n_timesteps as u64;
    let half = (opt.batch_size / 2).max(1);
    let bce = |x0: Tensor, labels: Tensor, rng: &mut Rng| -> Result<Tensor> {
        let n = x0.size()[0] as usize;
        let t = rng.randint(t_max, n, device);
        let noise = rng.randn(&x0.size(), device);
        let x_t = noised(&model, &x0, &t, &noise, condition)?;
        let logits = net.rho(&x_t, &t)?;
        Ok(logits.f_binary_cross_entropy_with_logits::<Tensor>(&labels, None, None, tch::Reduction::Mean)?)
    };
    let labelled = |b: Tensor, e: Tensor| {
        let (nb, ne) = (b.size()[0], e.size()[0]);
        let labels =
            Tensor::cat(&[Tensor::zeros([nb], (Kind::Float, device)), Tensor::ones([ne], (Kind::Float, device))], 0);
        (Tensor::cat(&[b, e], 0), labels)
    };
    train.run(
        ctx,
        |rng| {
            let (x0, labels) = labelled(base.batch(rng, half), expert.batch(rng, half));
            bce(x0, labels, rng)
        },
        || {
            let (Some(b), Some(e)) = (base.held_out(EVAL_ITEMS / 2), expert.held_out(EVAL_ITEMS / 2)) else {
                return Ok(None);
            };
            let (x0, labels) = labelled(b, e);
            let mut eval_rng = Rng::new(spec.seed ^ 0xe7a1);
            Ok(Some(tch::no_grad(|| bce(x0, labels, &mut eval_rng))?.double_value(&[])))
        },
    )?;
    let manifest = RewardManifest {
        architecture: job.architecture.clone(),
        space,
        normalizer,
        n_timesteps: model.manifest.n_timesteps,
        base_model: job.diffusion_model.clone(),
        expert_model: String::new(),
        datasets: vec![job.base_dataset.clone(), job.expert_dataset.clone()],
        objective: Objective::Discriminator,
        step_normalization: false,
        inpaint_condition: job.inpaint_condition,
        final_loss: train.loss,
        eval_loss: train.eval_loss,
    };
    let description =
        format!("discriminator of '{}' vs '{}' ({})", job.expert_dataset, job.base_dataset, net.describe());
    register(ctx, &train, &net, manifest, ModelKind::Discriminator, description, &[])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Elements with spreads from 1e-3 to 3 (an image's near-constant background beside its
    /// strokes) share one scale per step: the pooled root-mean-square deviation from the
    /// per-element mean, so standardised targets keep the direction of x^expert - x^base.
    #[test]
    fn step_stats_share_one_scale_over_the_elements() {
        tch::manual_seed(7);
        let n = 20_000;
        let scales = [1e-3, 0.5, 1.0, 2.0, 0.0, 3.0];
        let offsets = [-1.0, 0.0, 2.0, 0.5, -0.3, 4.0];
        let s = Tensor::from_slice(&scales).reshape([1, 2, 3]);
        let o = Tensor::from_slice(&offsets).reshape([1, 2, 3]);
        let x = (Tensor::randn([n, 2, 3], (Kind::Double, Device::Cpu)) * s + o).to_kind(Kind::Float);
        let (mean, std) = step_stats(&x);
        assert_eq!((mean.size(), std.size()), (vec![2, 3], vec![2, 3]));
        let std: Vec<f64> = Vec::try_from(std.flatten(0, -1).to_kind(Kind::Double)).expect("std");
        assert!(std.iter().all(|s| *s == std[0]), "one scale for every element: {std:?}");
        // sqrt(mean of scale^2) = sqrt(14.251 / 6), up to sampling error (~0.5%).
        let want = (scales.iter().map(|s| s * s).sum::<f64>() / 6.0).sqrt();
        assert!((std[0] - want).abs() < 0.01 * want, "pooled std {} vs {want}", std[0]);
        let mean: Vec<f64> = Vec::try_from(mean.flatten(0, -1).to_kind(Kind::Double)).expect("mean");
        for (m, o) in mean.iter().zip(offsets) {
            assert!((m - o).abs() < 0.05, "per-element mean {m} vs {o}");
        }
        // A constant step standardises to 0 rather than dividing by zero.
        let (_, std) = step_stats(&Tensor::ones([8, 2, 3], (Kind::Float, Device::Cpu)));
        assert_eq!(std.min().double_value(&[]), 1e-6_f32 as f64);
    }
}
