//! `relreward.v1.RewardService`: Score, Gradient and GradientStream over [`Serving`] (which
//! validates, batches and computes), and Sample: ancestral sampling from a diffusion model,
//! plain, with inpainting conditions, or guided by a reward model.

use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use futures::stream::FuturesUnordered;
use futures::{Stream, StreamExt};
use relreward_proto::tensor;
use relreward_proto::v1::{self as pb, reward_service_server::RewardService};
use tch::{Kind, Tensor};
use tokio::sync::{Semaphore, mpsc};
use tonic::{Request, Response, Status, Streaming};

use crate::engine::manifest::Space;
use crate::engine::registry::{ModelRegistry, ServedReward};
use crate::engine::rng::Rng;
use crate::engine::sampling::{Condition, Guidance, GuidedSampler, RewardFn};
use crate::error::{Error, Result, brief};
use crate::fields::{self, validate_name};
use crate::serving::{self, Answer, HostTensor, Op, Query, Serving, Units};

/// Most samples per request and per denoised batch.
const MAX_SAMPLES: u32 = 10_000;
const MAX_BATCH: u32 = 1024;
/// Most guide steps per denoising step.
const MAX_GUIDE_STEPS: u32 = 100;
/// Responses buffered per GradientStream before the server waits for the client to read.
const STREAM_BUFFER: usize = 64;

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

pub struct Rewards {
    serving: Serving,
    registry: ModelRegistry,
    /// Inference slots shared with the Score/Gradient batcher, so sampling and serving
    /// together cannot oversubscribe the CPU; training runs on its own job threads.
    slots: Arc<Semaphore>,
}

impl Rewards {
    pub fn new(serving: Serving, slots: Arc<Semaphore>) -> Self {
        Self { registry: serving.registry().clone(), serving, slots }
    }
}

/// `Units` from the wire: unspecified means raw.
fn units(field: &str, raw: i32) -> Result<Units> {
    Ok(match fields::known(field, raw, "UNITS_RAW (the default) or UNITS_NORMALIZED")? {
        pb::Units::Unspecified | pb::Units::Raw => Units::Raw,
        pb::Units::Normalized => Units::Normalized,
    })
}

/// The shape and float32 values of a float32 or float64 tensor field (finiteness is checked
/// by `Serving::prepare`, which knows the model).
fn decode_x(field: &str, x: Option<&pb::Tensor>) -> Result<(Vec<i64>, Vec<f32>)> {
    let x = x.ok_or_else(|| Error::invalid(format!("{field}: missing")))?;
    // Sized for float32 (float64 needs half): one allocation per request, not a doubling series.
    let mut values = Vec::with_capacity(x.data.len() / 4);
    // NaN and infinities are refused later with their element (serving::prepare); a finite
    // float64 that float32 cannot hold is refused here, before it becomes an infinity.
    let mut overflow = None;
    tensor::for_each_float(x, |v| {
        if overflow.is_none() && tensor::beyond_f32(v) {
            overflow = Some((values.len(), v));
        }
        values.push(v as f32);
    })
    .map_err(|e| Error::invalid(format!("{field}: {e}")))?;
    if let Some((i, v)) = overflow {
        return Err(Error::invalid(format!("{field}: element {i} ({v:e}) is {}", tensor::OUTSIDE_F32)));
    }
    let shape = x
        .shape
        .iter()
        .map(|&d| i64::try_from(d).map_err(|_| Error::invalid(format!("{field}: dimension {d} is too large"))))
        .collect::<Result<Vec<_>>>()?;
    Ok((shape, values))
}

fn times(t: &[u32]) -> Vec<i64> {
    t.iter().map(|&v| i64::from(v)).collect()
}

/// A Gradient request as a serving query.
fn gradient_query(req: &pb::GradientRequest, deadline: Option<std::time::Instant>) -> Result<Query> {
    let (shape, values) = decode_x("x", req.x.as_ref())?;
    let variance_of =
        (!req.scale_by_posterior_variance_of.is_empty()).then(|| req.scale_by_posterior_variance_of.clone());
    Ok(Query {
        shape,
        values,
        t: times(&req.t),
        input_units: units("input_units", req.input_units)?,
        op: Op::Gradient {
            units: units("gradient_units", req.gradient_units)?,
            omega: req.omega.unwrap_or(1.0),
            variance_of,
        },
        deadline,
    })
}

async fn answer_gradient(
    serving: &Serving,
    req: &pb::GradientRequest,
    deadline: Option<std::time::Instant>,
) -> Result<pb::GradientResponse> {
    let query = gradient_query(req, deadline)?;
    let answer = serving.query(&req.model, query).await?;
    let gradient = answer.gradient.as_ref().map(host_f32).transpose()?;
    Ok(pb::GradientResponse {
        request_id: req.request_id,
        gradient,
        rewards: Some(host_f32(&answer.rewards)?),
        error: None,
    })
}

fn score_response(answer: &Answer) -> Result<pb::ScoreResponse> {
    Ok(pb::ScoreResponse {
        rewards: Some(host_f32(&answer.rewards)?),
        per_window: answer.per_window.as_ref().map(host_f32).transpose()?,
        per_step: answer.per_step.as_ref().map(host_f32).transpose()?,
    })
}

/// A reward model used for guidance: locked for each forward pass only, so that a long
/// sampling run does not hold off the model's Score/Gradient queries. The backward pass
/// through the returned graph only reads the weights (gradients are taken with respect to
/// `x` alone), which libtorch allows concurrently with other readers.
struct PerCall<'a>(&'a ServedReward);

impl RewardFn for PerCall<'_> {
    fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.0.lock().rho(x, t)
    }
}

/// Validated inputs of one Sample request.
struct SamplePlan {
    n: usize,
    batch: usize,
    seed: u64,
    /// (horizon index, observation in normalized units).
    conditions: Vec<(usize, Vec<f32>)>,
    omega: f64,
    n_guide_steps: usize,
    t_stopgrad: usize,
}

fn plan(
    req: &pb::SampleRequest,
    space: &Space,
    n_timesteps: usize,
    normalize_obs: impl Fn(&[f32]) -> Vec<f32>,
) -> Result<SamplePlan> {
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
    let units = units("input_units", req.input_units)?;
    let t_stopgrad = req.t_stopgrad.unwrap_or(0);
    fields::diffusion_time("t_stopgrad", i64::from(t_stopgrad), n_timesteps)?;
    let mut conditions = Vec::with_capacity(req.conditions.len());
    for (i, c) in req.conditions.iter().enumerate() {
        let Space::Trajectory { horizon, obs_dim, .. } = space else {
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
        let values = if units == Units::Normalized { values } else { normalize_obs(&values) };
        // As Score's inputs: a state far outside the data overflows the model (Inf samples).
        serving::check_normalized_range(&format!("conditions[{i}].state"), &values, units)?;
        conditions.push((c.index as usize, values));
    }
    let seed = req.seed.unwrap_or_else(|| {
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
    });
    Ok(SamplePlan {
        n: n as usize,
        batch: batch as usize,
        seed,
        conditions,
        omega: req.omega,
        n_guide_steps: n_guide_steps as usize,
        t_stopgrad: t_stopgrad as usize,
    })
}

/// A float32 wire tensor, its bytes copied straight out of the tensor's storage (one copy, no
/// intermediate `Vec<f32>`): the wire is little-endian, as every target this builds for.
fn tensor_f32(t: &Tensor) -> Result<pb::Tensor> {
    const _: () = assert!(cfg!(target_endian = "little"), "tensor_f32 copies native floats as little-endian");
    let shape: Vec<u64> = t.size().iter().map(|&d| d as u64).collect();
    let flat = t.f_to_kind(Kind::Float)?.f_contiguous()?;
    let numel = flat.numel();
    let mut data = vec![0u8; numel * 4];
    flat.f_copy_data_u8(&mut data, numel).map_err(|e| Error::internal("reading a result tensor", e))?;
    tensor::from_raw(&shape, pb::Dtype::Float32, data).map_err(|e| Error::internal("encoding a result tensor", e))
}

/// A float32 wire tensor from host values (Score and Gradient answers): one copy into the
/// wire's little-endian bytes, no libtorch call.
fn host_f32(h: &HostTensor) -> Result<pb::Tensor> {
    let shape: Vec<u64> = h.shape.iter().map(|&d| d as u64).collect();
    let mut data = Vec::with_capacity(h.values.len() * 4);
    for v in &h.values {
        data.extend_from_slice(&v.to_le_bytes());
    }
    tensor::from_raw(&shape, pb::Dtype::Float32, data).map_err(|e| Error::internal("encoding a result tensor", e))
}

/// The reward model that guides a Sample request, checked against the base model: same
/// number of diffusion steps, item shape and normalizer (rho is a function of the base
/// model's normalized units).
async fn guiding_reward(
    registry: &ModelRegistry,
    req: &pb::SampleRequest,
    space: &Space,
    n_timesteps: usize,
    normalizer: &crate::engine::normalizer::Normalizer,
) -> Result<Option<Arc<ServedReward>>> {
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

#[tonic::async_trait]
impl RewardService for Rewards {
    type GradientStreamStream = BoxStream<pb::GradientResponse>;
    type SampleStream = BoxStream<pb::SampleResponse>;

    async fn score(&self, request: Request<pb::ScoreRequest>) -> Result<Response<pb::ScoreResponse>, Status> {
        let deadline = serving::deadline_of(request.metadata());
        let req = request.into_inner();
        let (shape, values) = decode_x("x", req.x.as_ref())?;
        let query = Query {
            shape,
            values,
            t: times(&req.t),
            input_units: units("input_units", req.input_units)?,
            op: Op::Score { per_window: req.per_window, per_step: req.per_step },
            deadline,
        };
        let answer = self.serving.query(&req.model, query).await?;
        Ok(Response::new(score_response(&answer)?))
    }

    async fn gradient(&self, request: Request<pb::GradientRequest>) -> Result<Response<pb::GradientResponse>, Status> {
        let deadline = serving::deadline_of(request.metadata());
        let req = request.into_inner();
        Ok(Response::new(answer_gradient(&self.serving, &req, deadline).await?))
    }

    /// Answers every request of the stream as soon as its batch is done (in any order,
    /// matched by request_id); a failed request gets its error in its response and the
    /// stream goes on. A frame that cannot be read (undecodable, or over the size limit) ends
    /// the stream with INVALID_ARGUMENT (RESOURCE_EXHAUSTED) once the requests before it are
    /// answered. When the client goes away, queries still queued are skipped.
    async fn gradient_stream(
        &self,
        request: Request<Streaming<pb::GradientRequest>>,
    ) -> Result<Response<Self::GradientStreamStream>, Status> {
        let deadline = serving::deadline_of(request.metadata());
        let mut inbound = request.into_inner();
        let serving = self.serving.clone();
        let (tx, rx) = mpsc::channel::<Result<pb::GradientResponse, Status>>(STREAM_BUFFER);
        tokio::spawn(async move {
            let mut in_flight = FuturesUnordered::new();
            let mut inbound_open = true;
            // Why the inbound stream broke, if it did: the stream then ends with this status
            // once the requests in flight are answered, never with OK.
            let mut broken: Option<Status> = None;
            loop {
                tokio::select! {
                    message = inbound.message(), if inbound_open => match message {
                        Ok(Some(req)) => {
                            let serving = serving.clone();
                            in_flight.push(async move {
                                match answer_gradient(&serving, &req, deadline).await {
                                    Ok(response) => response,
                                    Err(e) => {
                                        let status = Status::from(e);
                                        pb::GradientResponse {
                                            request_id: req.request_id,
                                            error: Some(pb::StreamError {
                                                code: status.code() as i32,
                                                message: status.message().to_owned(),
                                            }),
                                            ..Default::default()
                                        }
                                    }
                                }
                            });
                        }
                        Ok(None) => inbound_open = false,
                        Err(status) => {
                            // A broken inbound stream (an undecodable frame, one over the size
                            // limit, or the client gone): answer what is in flight if anyone
                            // still listens, accept nothing more, end with the error.
                            tracing::debug!(error = %status, "GradientStream: inbound stream ended with an error");
                            inbound_open = false;
                            broken = Some(Error::from_inbound("request stream", &status).into());
                        }
                    },
                    Some(response) = in_flight.next(), if !in_flight.is_empty() => {
                        if tx.send(Ok(response)).await.is_err() {
                            return;
                        }
                    }
                    () = tx.closed() => return,
                }
                if !inbound_open && in_flight.is_empty() {
                    if let Some(status) = broken {
                        let _ = tx.send(Err(status)).await;
                    }
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    /// Samples in batches on a blocking thread and streams each sample as its batch finishes,
    /// with its reward rho(x, 0) when a reward model is given (guiding when omega != 0).
    /// Stops early when the client goes away.
    async fn sample(&self, request: Request<pb::SampleRequest>) -> Result<Response<Self::SampleStream>, Status> {
        let req = request.into_inner();
        validate_name("model", &req.model)?;
        let shared = self.registry.get_diffusion(&req.model).await?;
        let (space, normalizer, n_timesteps) = {
            let m = shared.lock().map_err(|_| Error::internal("model", "lock poisoned"))?;
            (m.manifest.space.clone(), m.manifest.normalizer.clone(), m.n_timesteps())
        };
        let plan = {
            let norm = normalizer.clone();
            let action_dim = match &space {
                Space::Trajectory { action_dim, .. } => *action_dim,
                Space::Sample { .. } => 0,
            };
            plan(&req, &space, n_timesteps, move |obs| {
                // Normalize an observation as the obs part of a full [action | obs] row.
                let mut row = vec![0f32; action_dim];
                row.extend_from_slice(obs);
                let t = norm.normalize(&Tensor::from_slice(&row).reshape([1, row.len() as i64]), 1);
                Vec::<f32>::try_from(&t.view(-1).narrow(0, action_dim as i64, obs.len() as i64)).unwrap_or_default()
            })?
        };
        let reward = guiding_reward(&self.registry, &req, &space, n_timesteps, &normalizer).await?;
        let scale_grad_by_std = req.scale_grad_by_std;
        let req_model = req.model.clone();
        let permit = Arc::clone(&self.slots)
            .acquire_owned()
            .await
            .map_err(|_| Error::Unavailable("the server is shutting down".into()))?;
        let (tx, rx) = mpsc::channel::<Result<pb::SampleResponse, Status>>(16);
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let gone = AtomicBool::new(false);
            let result = (|| -> Result<()> {
                let model = shared.lock().map_err(|_| Error::internal("model", "lock poisoned"))?;
                let _no_grad = tch::no_grad_guard();
                let conditions: Vec<Condition> = plan
                    .conditions
                    .iter()
                    .map(|(index, v)| Condition { index: *index, state: Tensor::from_slice(v) })
                    .collect();
                let per_call = reward.as_deref().map(PerCall);
                let mut sampler =
                    GuidedSampler::new(&model).on_device(crate::engine::device()).with_conditions(conditions);
                if let Some(r) = &per_call {
                    sampler = sampler.with_guidance(Guidance {
                        reward: r,
                        omega: plan.omega,
                        n_guide_steps: plan.n_guide_steps,
                        t_stopgrad: plan.t_stopgrad,
                        scale_grad_by_std,
                    });
                }
                let mut rng = Rng::new(plan.seed);
                let item_dims = space.normalizer_dims();
                let mut done = 0usize;
                while done < plan.n {
                    let b = plan.batch.min(plan.n - done);
                    let mut stop_if_gone = |_: &crate::engine::sampling::Step<'_>| -> Result<()> {
                        if tx.is_closed() {
                            gone.store(true, Ordering::Relaxed);
                            return Err(Error::Unavailable("client went away".into()));
                        }
                        Ok(())
                    };
                    let sampled = sampler.sample_with(b, &mut rng, &mut stop_if_gone)?;
                    if !bool::try_from(sampled.x.f_isfinite()?.f_all()?).unwrap_or(false) {
                        // Refused rather than sent as Inf or NaN. With guidance acting, omega is
                        // the likely cause; without it, the model itself diverged.
                        return Err(if per_call.is_some() && plan.omega != 0.0 {
                            Error::invalid(format!(
                                "omega: the samples of batch {} are not finite with omega = {}; lower omega or n_guide_steps",
                                done / plan.batch,
                                plan.omega
                            ))
                        } else {
                            Error::FailedPrecondition(format!(
                                "model '{}': its unguided samples of batch {} are not finite (the model's outputs overflow or are NaN at these inputs)",
                                req_model,
                                done / plan.batch
                            ))
                        });
                    }
                    let rewards = match &per_call {
                        Some(r) => {
                            let t0 = Tensor::zeros([b as i64], (Kind::Int64, sampled.x.device()));
                            Some(
                                Vec::<f64>::try_from(
                                    &r.rho(&sampled.x, &t0)?.to_kind(Kind::Double).to_device(tch::Device::Cpu),
                                )
                                .map_err(|e| Error::internal("reading rewards", e))?,
                            )
                        }
                        None => None,
                    };
                    // One copy of the batch to the host (a no-op on the CPU), then per-item views.
                    let x_host = sampled.x.to_device(tch::Device::Cpu);
                    let raw = normalizer.unnormalize(&x_host, item_dims);
                    if !bool::try_from(raw.f_isfinite()?.f_all()?).unwrap_or(false) {
                        return Err(Error::FailedPrecondition(format!(
                            "model '{req_model}': the samples of batch {} overflow float32 in raw units (the normalizer's scale is too large for them)",
                            done / plan.batch
                        )));
                    }
                    for i in 0..b {
                        let response = pb::SampleResponse {
                            index: (done + i) as u32,
                            x: Some(tensor_f32(&raw.get(i as i64))?),
                            x_normalized: Some(tensor_f32(&x_host.get(i as i64))?),
                            reward: rewards.as_ref().map(|r| r[i]),
                        };
                        if tx.blocking_send(Ok(response)).is_err() {
                            return Ok(());
                        }
                    }
                    done += b;
                }
                Ok(())
            })();
            if let Err(e) = result
                && !gone.load(Ordering::Relaxed)
            {
                let _ = tx.blocking_send(Err(e.into()));
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }
}
