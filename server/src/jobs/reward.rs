//! The relative-reward runners: submission-time checks against the store, then the job's
//! side of a training run: loading the models and datasets, driving the engine's
//! [`RelativeRewardTrainer`] (Algorithms 1 and 2) through the shared [`TrainLoop`] (optimiser,
//! checkpoints, events), and registering the result as a reward model. Also the
//! discriminator baseline, trained by the same loop and registered the same way.

use tch::{Device, Kind, Tensor};

use super::context::{JobContext, Stop};
use super::datasets::load_rows;
use super::training::TrainLoop;
use crate::engine::data::TrainingData;
use crate::engine::diffusion::DiffusionModel;
use crate::engine::manifest::{DiffusionManifest, Space};
use crate::engine::nets::inputs::describe;
use crate::engine::nets::reward::RewardNet;
use crate::engine::normalizer::Normalizer;
use crate::engine::recipe::{prompt_tensor, recipe_of};
use crate::engine::relative_reward::{
    ConditionEntries, EvalPoint, Objective, RewardManifest, Target, check_pair, entry_weights, noised,
};
use crate::engine::reward_model::STEP_NORM_FILE;
use crate::engine::reward_trainer::{
    AlignmentSettings, ChainRecipe, ChainSide, EVAL_ITEMS, RelativeRewardTrainer, TrainingPairs,
};
use crate::engine::rng::Rng;
use crate::error::{Error, Result};
use crate::registry::{load_diffusion_copy, resolve_sampled};
use crate::store::ingest::now_ms;
use crate::store::{DatasetKind, ModelFormat, ModelKind, ModelRecord, Provenance, Store};
use relreward_proto::schema::job::{DiscriminatorJob, RewardAlgorithm, RewardJob};
use relreward_proto::schema::recipe::{RecipeManifest, RecipeSpec};

/// What a job's model field names: a diffusion model, or a named recipe over one (its model's
/// manifest and the recipe); `field` names it in messages.
async fn sampled_manifest(
    store: &Store,
    field: &str,
    name: &str,
) -> Result<(DiffusionManifest, Option<RecipeManifest>)> {
    let (record, recipe) = resolve_sampled(store, name).await.map_err(|e| match e {
        Error::NotFound(m) => Error::NotFound(format!("{field}: {m}")),
        // At submission a wrong kind of model is a wrong field value.
        Error::FailedPrecondition(m) => Error::invalid(format!("{field}: {m}")),
        other => other,
    })?;
    let manifest = serde_json::from_value(record.manifest)
        .map_err(|e| Error::DataLoss(format!("model '{}': manifest unreadable: {e}", record.name)))?;
    Ok((manifest, recipe))
}

/// Submission-time checks: both models exist and agree (shape, schedule, normalizer), the
/// architecture fits their item shape, every dataset exists and matches their layout, and a
/// conditional model comes with a recipe that fits it (Algorithm 2 only): the job's own
/// `*_recipe`, or the model field naming a recipe (not both).
pub async fn validate_inputs(store: &Store, job: &RewardJob) -> Result<()> {
    let ((base, base_named), (expert, expert_named)) = validate_models_and_data(store, job).await?;
    for (side, manifest, name, inline, named) in [
        ("base", &base, &job.base_model, &job.base_recipe, &base_named),
        ("expert", &expert, &job.expert_model, &job.expert_recipe, &expert_named),
    ] {
        let conditioning = manifest.conditioning.as_ref();
        if let (Some(_), Some(named)) = (inline, named) {
            return Err(Error::invalid(format!(
                "spec.reward.{side}_recipe: set, but {side}_model '{name}' is a recipe over '{}' that brings its own; \
                 leave {side}_recipe unset, or name the model '{}' itself",
                named.model, named.model
            )));
        }
        let (recipe, field, model) = match (inline, named) {
            (Some(r), _) => (Some(r), format!("spec.reward.{side}_recipe"), name.as_str()),
            (None, Some(n)) => {
                (Some(&n.recipe), format!("spec.reward.{side}_model (recipe '{name}')"), n.model.as_str())
            }
            (None, None) => (None, String::new(), name.as_str()),
        };
        match (recipe, conditioning, &job.algorithm) {
            (Some(_), _, RewardAlgorithm::WithDataset { .. }) => {
                return Err(Error::invalid(format!(
                    "{field}: with_dataset (Algorithm 1) takes unconditional models; a recipe stands in \
                     models_only (Algorithm 2)"
                )));
            }
            (Some(r), c, RewardAlgorithm::ModelsOnly { .. }) => r.check_against(c, &field, model)?,
            (None, Some(c), RewardAlgorithm::ModelsOnly { .. }) => {
                return Err(Error::invalid(format!(
                    "spec.reward.{side}_recipe: missing; model '{name}' is conditional ({}): give the prompt set its \
                     chains draw from (and its guidance), or name a recipe as {side}_model",
                    describe(c)
                )));
            }
            (None, Some(_), RewardAlgorithm::WithDataset { .. }) => {
                return Err(Error::invalid(format!(
                    "spec.reward.{side}_model: model '{name}' is conditional; with_dataset (Algorithm 1) takes \
                     unconditional models (a conditional one: models_only with {side}_recipe)"
                )));
            }
            (None, None, _) => {}
        }
    }
    Ok(())
}

/// The checks a reward job and a discriminator job share (module doc of [`validate_inputs`],
/// less the recipes); returns both sides' manifests and named recipes.
async fn validate_models_and_data(store: &Store, job: &RewardJob) -> Result<(Sampled, Sampled)> {
    let (base, base_named) = sampled_manifest(store, "spec.reward.base_model", &job.base_model).await?;
    let (expert, expert_named) = sampled_manifest(store, "spec.reward.expert_model", &job.expert_model).await?;
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
    Ok(((base, base_named), (expert, expert_named)))
}

/// A job's model side at submission: the diffusion model's manifest and, when the field names a
/// recipe, the recipe.
type Sampled = (DiffusionManifest, Option<RecipeManifest>);

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

/// A stored recipe as the engine's: its prompt set as a tensor, its guidance as a `Recipe`.
fn chain_recipe(spec: &RecipeSpec) -> Result<ChainRecipe> {
    Ok(ChainRecipe { recipe: recipe_of(spec), prompts: prompt_tensor(&spec.prompts) })
}

/// A job's model field loaded: a private copy of the diffusion model it samples, that model's
/// record, and the recipe when the field names one.
fn load_sampled(ctx: &JobContext, name: &str) -> Result<(DiffusionModel, ModelRecord, Option<RecipeManifest>)> {
    let store = ctx.store().clone();
    let (record, recipe) = ctx.block_on(resolve_sampled(&store, name)).map_err(|e| match e {
        Error::NotFound(_) => Error::NotFound(format!("model '{name}' was deleted")),
        other => other,
    })?;
    let dir = ctx.block_on(store.blobs.local_dir(&record.blob_key))?;
    let model = load_diffusion_copy(&record, &dir, crate::engine::device())?;
    Ok((model, record, recipe))
}

/// The recipe a side is sampled through: the named one, or the job's own bound to the model.
fn side_recipe(
    record: &ModelRecord,
    named: Option<RecipeManifest>,
    inline: Option<&RecipeSpec>,
) -> Option<RecipeManifest> {
    named.or_else(|| {
        inline.map(|r| RecipeManifest {
            model: record.name.clone(),
            model_sha256: record.sha256.clone(),
            recipe: r.clone(),
            prompt_dataset: None,
        })
    })
}

pub fn run(ctx: &mut JobContext, job: &RewardJob) -> std::result::Result<String, Stop> {
    let spec = ctx.spec.clone();
    let opt = &spec.optimization;
    let (base, base_record, base_named) = load_sampled(ctx, &job.base_model)?;
    let (expert, expert_record, expert_named) = load_sampled(ctx, &job.expert_model)?;
    let base_recipe = side_recipe(&base_record, base_named, job.base_recipe.as_ref());
    let expert_recipe = side_recipe(&expert_record, expert_named, job.expert_recipe.as_ref());
    check_pair(&base, &expert)?;
    let space = base.manifest.space.clone();
    let normalizer = base.manifest.normalizer.clone();
    let (pairs, datasets) = match &job.algorithm {
        RewardAlgorithm::WithDataset { datasets } => {
            let data = dataset_union(ctx, datasets, &space, &normalizer, spec.seed)?;
            (TrainingPairs::Dataset(data), datasets.clone())
        }
        RewardAlgorithm::ModelsOnly { num_chains } => {
            ctx.check_stop()?;
            let base_chain = base_recipe.as_ref().map(|r| chain_recipe(&r.recipe)).transpose()?;
            let expert_chain = expert_recipe.as_ref().map(|r| chain_recipe(&r.recipe)).transpose()?;
            let base_side = ChainSide { model: &base, recipe: base_chain.as_ref() };
            let expert_side = ChainSide { model: &expert, recipe: expert_chain.as_ref() };
            let pairs = TrainingPairs::chains(base_side, expert_side, *num_chains, spec.seed)?;
            (pairs, Vec::new())
        }
    };
    let n_timesteps = base.manifest.n_timesteps;
    let settings = AlignmentSettings {
        architecture: job.architecture.clone(),
        target: job.target,
        eval_point: job.eval_point,
        rho_l2: job.rho_l2,
        action_weight: job.action_weight,
        condition_weight: job.condition_weight,
        inpaint_condition: job.inpaint_condition,
        amortised_targets: job.amortised_targets,
        batch_size: opt.batch_size,
        seed: spec.seed,
        field: "spec.reward",
    };
    let trainer = RelativeRewardTrainer::new(base, expert, pairs, settings)?;
    let reward = trainer.reward();
    let mut train = TrainLoop::new(reward.weights().var_store(), opt, spec.seed);
    if train.resume(ctx)?.is_none() {
        ctx.log(format!(
            "extracting a relative reward ({}, {} parameters) from '{}' (base) and '{}' (expert) on {} training items",
            reward.describe(),
            reward.parameter_count(),
            job.base_model,
            job.expert_model,
            trainer.train_len()
        ))?;
    }
    if let Some(a) = trainer.amortised_targets() {
        ctx.log(format!(
            "amortised targets: pool {}, reuse {}, refresh fraction {} ({} items every {} steps)",
            a.pool_size,
            a.reuse,
            a.refresh_fraction,
            a.refresh_items(),
            a.steps_per_epoch(opt.batch_size)
        ))?;
    }
    // `step` mirrors the loop's counter (which starts at the resumed step): the trainer's
    // target pool refreshes on it.
    let mut step = train.step;
    train.run(
        ctx,
        |rng| {
            step += 1;
            trainer.loss(step, rng)
        },
        || trainer.held_out_error(),
    )?;

    let models_only = matches!(job.algorithm, RewardAlgorithm::ModelsOnly { .. });
    let manifest = RewardManifest {
        architecture: job.architecture.clone().into(),
        space,
        normalizer,
        n_timesteps,
        base_model: job.base_model.clone(),
        expert_model: job.expert_model.clone(),
        datasets,
        objective: Objective::Alignment {
            target: job.target,
            eval_point: job.eval_point,
            models_only,
            action_weight: job.action_weight,
            condition_weight: job.condition_weight,
        },
        step_normalization: models_only,
        inpaint_condition: job.inpaint_condition,
        base_recipe,
        expert_recipe,
        final_loss: train.loss,
        eval_loss: train.eval_loss,
    };
    let description =
        format!("relative reward of '{}' over '{}' ({})", job.expert_model, job.base_model, reward.describe());
    let step_norm = trainer.step_normalization();
    register(ctx, &train, reward, manifest, ModelKind::Reward, description, &step_norm)
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
        base_recipe: None,
        expert_recipe: None,
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
    validate_models_and_data(store, &as_reward).await.map_err(|e| match e {
        Error::InvalidArgument(m) => Error::InvalidArgument(rename(m)),
        Error::NotFound(m) => Error::NotFound(rename(m)),
        other => other,
    })?;
    if job.inpaint_condition {
        let (model, _) = sampled_manifest(store, "spec.discriminator.diffusion_model", &job.diffusion_model).await?;
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
    let (model, _, _) = load_sampled(ctx, &job.diffusion_model)?;
    let space = model.manifest.space.clone();
    let normalizer = model.manifest.normalizer.clone();
    let base = dataset_union(ctx, std::slice::from_ref(&job.base_dataset), &space, &normalizer, spec.seed)?;
    let expert = dataset_union(ctx, std::slice::from_ref(&job.expert_dataset), &space, &normalizer, spec.seed ^ 1)?;
    let net = RewardNet::new(&job.architecture, &space.item_shape(), spec.seed, device)?;
    let mut train = TrainLoop::new(net.weights().var_store(), opt, spec.seed);
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
        architecture: job.architecture.clone().into(),
        space,
        normalizer,
        n_timesteps: model.manifest.n_timesteps,
        base_model: job.diffusion_model.clone(),
        expert_model: String::new(),
        datasets: vec![job.base_dataset.clone(), job.expert_dataset.clone()],
        objective: Objective::Discriminator,
        step_normalization: false,
        inpaint_condition: job.inpaint_condition,
        base_recipe: None,
        expert_recipe: None,
        final_loss: train.loss,
        eval_loss: train.eval_loss,
    };
    let description =
        format!("discriminator of '{}' vs '{}' ({})", job.expert_dataset, job.base_dataset, net.describe());
    register(ctx, &train, &net, manifest, ModelKind::Discriminator, description, &[])
}
