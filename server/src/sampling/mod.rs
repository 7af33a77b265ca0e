//! Sample: ancestral (DDPM) or DDIM sampling from a diffusion model, plain, with inpainting
//! conditions, a conditional model's prompts and recipe (classifier-free and safety guidance),
//! or guided by a reward model (Diffuser's guided planning), behind its own
//! workers beside [`crate::serving`]. The door (`api::rewards`) hands over a request and gets back a stream
//! of host rows: it never touches a tensor or a model's lock.
//!
//! - [`Sampling::submit`]: the one place that validates a Sample request, in this order: the
//!   model's name and the model (a diffusion model, or a named recipe: its model, with its
//!   prompts and guidance); omega and the guide steps; n and the batch size; the input
//!   units and `t_stopgrad`; the sampler (`ddim`: its steps, eta and spacing, and the
//!   guidance settings DDIM does not take); each condition (trajectories only, index within the horizon and
//!   given once, one observation of finite values, normalized on its floats and then within
//!   range); a conditional model's prompts, guidance scale and safety guidance
//!   ([`prompts`], against the manifest's conditioning); the guiding reward (its name, then the same diffusion steps, item shape and
//!   normalizer as the model). Then the run is queued: a bounded queue of
//!   [`QUEUE_CAPACITY`] runs waiting (RESOURCE_EXHAUSTED beyond it, UNAVAILABLE once the
//!   server is stopping).
//! - [`worker`]: `engine.inference_workers` named threads take runs in arrival order, each
//!   with an inference slot (shared with the Score/Gradient batcher, so sampling and serving
//!   together cannot oversubscribe the CPU), lock the model for the run (a guiding reward
//!   only for each of its passes) and send every sample back as a [`SampleRow`] as its batch
//!   finishes. A run stops at its next denoising step when its caller goes away, or when the
//!   server stops the `sampling` group of [`crate::tasks`] after the shutdown grace.
//! - A run's stream ends after its last row, or with its error: a run that stops without
//!   finishing (a failure, a stop at shutdown) never ends its stream as if it had finished.

mod prompts;
mod worker;

use std::sync::Arc;
use std::time::Duration;

use relreward_proto::tensor;
use relreward_proto::v1 as pb;
use tokio::sync::{Semaphore, mpsc};
use tokio_stream::wrappers::ReceiverStream;

use crate::engine::ddim::{Ddim, Spacing};
use crate::engine::manifest::Space;
use crate::engine::normalizer::{Normalize, Normalizer};
use crate::error::{Error, Result, brief};
use crate::fields::{self, validate_name};
use crate::registry::{ModelRegistry, SharedReward};
use crate::serving::{self, Units};
use crate::tasks::Tasks;

/// Most samples per request and per denoised batch.
const MAX_SAMPLES: u32 = 10_000;
const MAX_BATCH: u32 = 1024;
/// Most guide steps per denoising step.
const MAX_GUIDE_STEPS: u32 = 100;
/// Runs waiting for a worker before new ones are refused with RESOURCE_EXHAUSTED. A run
/// lasts seconds (a Score query microseconds), so this is a long wait already.
pub const QUEUE_CAPACITY: usize = 256;
/// Rows buffered per run before its worker waits for the client to read.
const ROW_BUFFER: usize = 16;

/// One sample as plain float32 values (row-major, the model's item shape).
#[derive(Debug, Clone, PartialEq)]
pub struct SampleRow {
    /// Its place among the run's samples, 0 to n - 1, in order.
    pub index: u32,
    /// In the dataset's raw units.
    pub x: Vec<f32>,
    /// In the model's normalized units, as sampled.
    pub x_normalized: Vec<f32>,
    /// rho(x, 0) under the guiding reward, when one was given.
    pub reward: Option<f64>,
    /// The condition it was sampled under (conditional models).
    pub prompt: Option<pb::Prompts>,
}

/// A queued run: the shape of each row's values, and its rows as they come.
pub struct SampleRun {
    pub item_shape: Vec<i64>,
    pub rows: ReceiverStream<Result<SampleRow>>,
}

/// Validated inputs of one Sample request.
#[derive(Debug)]
struct Plan {
    model: String,
    n: usize,
    batch: usize,
    seed: u64,
    /// (horizon index, observation in normalized units).
    conditions: Vec<(usize, Vec<f32>)>,
    omega: f64,
    n_guide_steps: usize,
    t_stopgrad: usize,
    scale_grad_by_std: bool,
    /// DDIM instead of DDPM.
    ddim: Option<Ddim>,
    /// A conditional model's prompts and recipe (None: unconditional).
    recipe: Option<prompts::RecipePlan>,
}

/// The handle the door holds: validates, queues, and stops the workers at shutdown.
#[derive(Clone)]
pub struct Sampling {
    inner: Arc<Inner>,
}

struct Inner {
    registry: ModelRegistry,
    queue: mpsc::Sender<worker::Run>,
    tasks: Tasks,
}

impl Sampling {
    /// Starts `workers` worker threads (`engine.inference_workers`) in the `tasks` group,
    /// computing under `slots`.
    pub fn start(registry: ModelRegistry, slots: Arc<Semaphore>, workers: usize, tasks: Tasks) -> Self {
        let (queue, runs) = mpsc::channel(QUEUE_CAPACITY);
        worker::start(workers.max(1), runs, slots, &tasks);
        Self { inner: Arc::new(Inner { registry, queue, tasks }) }
    }

    /// Validates `req` (see the module's order), then queues its run. Errors here are the
    /// call's status; a run's own failure ends its stream instead.
    pub async fn submit(&self, req: &pb::SampleRequest) -> Result<SampleRun> {
        validate_name("model", &req.model)?;
        let (model, named) = self.inner.registry.get_sampled(&req.model).await?;
        let manifest = &model.manifest;
        let mut plan = plan(req, &manifest.space, manifest.n_timesteps, &manifest.normalizer)?;
        plan.recipe = match &named {
            Some(recipe) => Some(prompts::plan_named(req, recipe, plan.n)?),
            None => prompts::plan(req, manifest.conditioning.as_ref(), plan.n)?,
        };
        let reward =
            guiding_reward(&self.inner.registry, req, &manifest.space, manifest.n_timesteps, &manifest.normalizer)
                .await?;
        let item_shape = manifest.space.item_shape();
        if self.inner.tasks.token().is_cancelled() {
            return Err(stopping());
        }
        let (rows, rx) = mpsc::channel(ROW_BUFFER);
        match self.inner.queue.try_send(worker::Run::new(model, reward, plan, rows)) {
            Ok(()) => Ok(SampleRun { item_shape, rows: ReceiverStream::new(rx) }),
            Err(mpsc::error::TrySendError::Full(_)) => Err(Error::ResourceExhausted(format!(
                "{QUEUE_CAPACITY} sampling runs are waiting for a worker; retry with backoff"
            ))),
            Err(mpsc::error::TrySendError::Closed(_)) => Err(stopping()),
        }
    }

    /// Shutdown, after the calls' grace: runs still going stop at their next denoising step
    /// and end their streams UNAVAILABLE, as do runs still queued; waits at most `bound` for
    /// the workers.
    pub async fn stop(&self, bound: Duration) -> bool {
        self.inner.tasks.stop(bound).await
    }
}

fn stopping() -> Error {
    Error::Unavailable("the server is shutting down".into())
}

/// Checks the request's own fields against the model's space, steps and normalizer.
fn plan(req: &pb::SampleRequest, space: &Space, n_timesteps: usize, normalizer: &Normalizer) -> Result<Plan> {
    fields::check_omega(req.omega)?;
    if req.reward_model.is_empty() && req.omega != 0.0 {
        return Err(Error::invalid("omega: guidance needs a reward_model (omit omega for plain sampling)"));
    }
    let n_guide_steps = req.n_guide_steps.unwrap_or(1);
    if n_guide_steps > MAX_GUIDE_STEPS {
        return Err(Error::invalid(format!("n_guide_steps: {n_guide_steps} is above the limit of {MAX_GUIDE_STEPS}")));
    }
    // Zero guide steps would silently sample unguided while the caller asked for omega != 0.
    if n_guide_steps == 0 && req.omega != 0.0 {
        return Err(Error::invalid(format!(
            "n_guide_steps: 0 guides nothing, but omega is {}; omit n_guide_steps (1) or set omega to 0 for unguided sampling",
            req.omega
        )));
    }
    let n = if req.n == 0 { 1 } else { req.n };
    if n > MAX_SAMPLES {
        return Err(Error::invalid(format!("n: {n} is above the limit of {MAX_SAMPLES}")));
    }
    let batch = if req.batch_size == 0 { n.min(MAX_BATCH) } else { req.batch_size };
    if batch > MAX_BATCH {
        return Err(Error::invalid(format!("batch_size: {batch} is above the limit of {MAX_BATCH}")));
    }
    let units = Units::from_wire("input_units", req.input_units)?;
    let t_stopgrad = req.t_stopgrad.unwrap_or(0);
    fields::diffusion_time("t_stopgrad", i64::from(t_stopgrad), n_timesteps)?;
    let ddim = req.ddim.as_ref().map(|d| ddim_options(d, req, n_timesteps)).transpose()?;
    let mut conditions = Vec::with_capacity(req.conditions.len());
    for (i, c) in req.conditions.iter().enumerate() {
        let Space::Trajectory { horizon, obs_dim, action_dim } = space else {
            return Err(Error::invalid(format!(
                "conditions[{i}]: model '{}' samples fixed-shape items, not trajectories",
                req.model
            )));
        };
        if c.index as usize >= *horizon {
            return Err(Error::invalid(format!(
                "conditions[{i}].index: {} is outside the horizon 0..{horizon}",
                c.index
            )));
        }
        if let Some((j, _)) = conditions.iter().enumerate().find(|(_, (index, _))| *index == c.index as usize) {
            return Err(Error::invalid(format!(
                "conditions[{i}].index: {} is already fixed by conditions[{j}]; give each index once",
                c.index
            )));
        }
        let state = c.state.as_ref().ok_or_else(|| Error::invalid(format!("conditions[{i}].state: missing")))?;
        if state.shape != [*obs_dim as u64] {
            return Err(Error::invalid(format!(
                "conditions[{i}].state: shape {} but one observation of the model has shape [{obs_dim}]",
                brief(&state.shape)
            )));
        }
        let values =
            tensor::decode_finite_f32(state).map_err(|e| Error::invalid(format!("conditions[{i}].state: {e}")))?;
        let values = match units {
            Units::Normalized => values,
            Units::Raw => normalize_observation(normalizer, *action_dim, values),
        };
        // As Score's inputs: a state far outside the data overflows the model (Inf samples).
        serving::check_normalized_range(&format!("conditions[{i}].state"), &values, units)?;
        conditions.push((c.index as usize, values));
    }
    let seed = req.seed.unwrap_or_else(|| {
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
    });
    Ok(Plan {
        model: req.model.clone(),
        n: n as usize,
        batch: batch as usize,
        seed,
        conditions,
        omega: req.omega,
        n_guide_steps: n_guide_steps as usize,
        t_stopgrad: t_stopgrad as usize,
        scale_grad_by_std: req.scale_grad_by_std,
        ddim,
        recipe: None,
    })
}

/// The DDIM options of a request, checked against the model's T, with the guidance settings
/// DDIM does not take refused by name (it guides once per step through eps; see
/// `engine::sampling`).
fn ddim_options(d: &pb::Ddim, req: &pb::SampleRequest, n_timesteps: usize) -> Result<Ddim> {
    let spacing = match fields::known(
        "ddim.timestep_spacing",
        d.timestep_spacing,
        "TIMESTEP_SPACING_LEADING (the default), TIMESTEP_SPACING_TRAILING or TIMESTEP_SPACING_LINSPACE",
    )? {
        pb::TimestepSpacing::Unspecified | pb::TimestepSpacing::Leading => Spacing::Leading,
        pb::TimestepSpacing::Trailing => Spacing::Trailing,
        pb::TimestepSpacing::Linspace => Spacing::Linspace,
    };
    let ddim = Ddim {
        n_steps: if d.n_steps == 0 { n_timesteps } else { d.n_steps as usize },
        eta: d.eta,
        spacing,
        set_alpha_to_one: d.set_alpha_to_one.unwrap_or(true),
    };
    ddim.check(n_timesteps, "ddim")?;
    if let Some(k) = req.n_guide_steps.filter(|&k| k > 1) {
        return Err(Error::invalid(format!(
            "n_guide_steps: {k} with ddim; DDIM guides through eps once per step (omit n_guide_steps or set 1)"
        )));
    }
    if req.scale_grad_by_std {
        return Err(Error::invalid(
            "scale_grad_by_std: not with ddim, whose guidance scales the gradient by sqrt(1 - abar_t) through eps",
        ));
    }
    Ok(ddim)
}

/// An observation in raw units normalized as the observation part of a full
/// `[action | observation]` row (the normalizer covers whole rows), on host floats.
fn normalize_observation(normalizer: &Normalizer, action_dim: usize, obs: Vec<f32>) -> Vec<f32> {
    let mut row = vec![0f32; action_dim];
    row.extend(obs);
    normalizer.normalize_values(&mut row);
    row.split_off(action_dim)
}

/// The reward model that guides a Sample request, checked against the base model: same
/// number of diffusion steps, item shape and normalizer (rho is a function of the base
/// model's normalized units).
async fn guiding_reward(
    registry: &ModelRegistry,
    req: &pb::SampleRequest,
    space: &Space,
    n_timesteps: usize,
    normalizer: &Normalizer,
) -> Result<Option<SharedReward>> {
    if req.reward_model.is_empty() {
        return Ok(None);
    }
    validate_name("reward_model", &req.reward_model)?;
    let reward = registry.get_reward(&req.reward_model).await.map_err(|e| match e {
        Error::NotFound(m) => Error::NotFound(format!("reward_model: {m}")),
        Error::FailedPrecondition(m) => Error::FailedPrecondition(format!("reward_model: {m}")),
        other => other,
    })?;
    let name = &req.reward_model;
    if reward.manifest.n_timesteps != n_timesteps {
        return Err(Error::invalid(format!(
            "reward_model: '{name}' was trained for {} diffusion steps, model '{}' has {n_timesteps}",
            reward.manifest.n_timesteps, req.model
        )));
    }
    if reward.item_shape != space.item_shape() {
        return Err(Error::invalid(format!(
            "reward_model: '{name}' takes items of shape {:?}, model '{}' samples {:?}",
            reward.item_shape,
            req.model,
            space.item_shape()
        )));
    }
    if &reward.manifest.normalizer != normalizer {
        return Err(Error::invalid(format!(
            "reward_model: '{name}' was trained under another normalizer than model '{}' uses, so its gradient would point the wrong way in this model's units",
            req.model
        )));
    }
    Ok(Some(reward))
}
