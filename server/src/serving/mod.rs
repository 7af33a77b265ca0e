//! Serving rho: Score and Gradient queries against reward models, merged across concurrent
//! callers by a per-model dynamic batcher. Both the native RewardService and the Open
//! Inference Protocol endpoint call [`Serving::run`]; neither touches tensors themselves.
//!
//! - [`Serving::prepare`] validates a query against the model (shape, B, t, finiteness,
//!   per-step support) before any compute, so bad input costs nothing and names its field.
//! - [`batcher`] queues prepared queries per loaded model (bounded: RESOURCE_EXHAUSTED when
//!   full), and one serving thread per model merges compatible queries into one forward (and
//!   backward) pass of at most `serving.max_batch` items, waiting at most
//!   `serving.max_delay_us` after the first for company. A query whose deadline passed while
//!   queued is answered DEADLINE_EXCEEDED without being computed; one whose caller went away
//!   (dropped its reply) is skipped.
//! - Compute is bounded by the inference slots (`engine.inference_workers`) shared with guided
//!   sampling; training jobs run on their own threads and never take a slot.
//!
//! - Per-request work stays off libtorch: a query carries plain floats from the wire to the
//!   serving thread, which builds one tensor per batch, copies each result to the host once
//!   per batch and hands every caller its rows as a [`HostTensor`] (omega, variance and the
//!   Jacobian applied there as row factors). A profile at 64 streaming clients (BENCHMARKS.md,
//!   issue 21) found a fifth of the server's CPU in per-request tensor calls on the tokio
//!   threads (creating, range-checking, finiteness-checking and copying one small tensor at
//!   a time), more than the gRPC framing.
//!
//! Units: rho is a function of normalized inputs. Raw inputs are normalized first; a gradient
//! in raw units is the normalized gradient times the normalizer's Jacobian (it is affine), so
//! finite differences of Score in raw units match Gradient in raw units.

mod batcher;

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use tch::Tensor;
use tokio::sync::Semaphore;

use crate::config::ServingConfig;
use crate::engine::manifest::DiffusionManifest;
use crate::engine::registry::{ModelRegistry, SharedReward};
use crate::engine::schedule::{Schedule, Table};
use crate::error::{Error, Result, brief};
use crate::metrics::Metrics;

use batcher::BatchKind;

/// Largest |x| accepted in the model's normalized units. The normalizer maps the training data
/// to about [-1, 1] (limits) or to z-scores (gaussian), and a noisy x_t stays within a few
/// units of that; values beyond this bound are far outside anything the model has seen and
/// only make rho overflow.
pub const MAX_NORMALIZED_X: f64 = 1e4;

/// Units of inputs and gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Units {
    /// The dataset's units (the default everywhere).
    Raw,
    /// The diffusion models' normalized units, which rho takes.
    Normalized,
}

/// What to compute for a query.
#[derive(Debug, Clone, PartialEq)]
pub enum Op {
    /// rho, and optionally per-window and per-step values.
    Score { per_window: bool, per_step: bool },
    /// rho and grad_x rho in `units`, times `omega` and, when given, times the posterior
    /// variance of the named diffusion model's schedule at each item's t.
    Gradient { units: Units, omega: f64, variance_of: Option<String> },
}

/// A query as it arrives from either protocol: `values` holds `shape` row-major.
#[derive(Debug)]
pub struct Query {
    pub shape: Vec<i64>,
    pub values: Vec<f32>,
    /// Empty: t = 0 for all items; one value: broadcast; else one per item.
    pub t: Vec<i64>,
    pub input_units: Units,
    pub op: Op,
    /// The caller's deadline (gRPC `grpc-timeout`).
    pub deadline: Option<Instant>,
}

/// The answer to one query: float32 values on the host, batch first.
#[derive(Debug)]
pub struct Answer {
    pub rewards: HostTensor,
    pub gradient: Option<HostTensor>,
    pub per_window: Option<HostTensor>,
    pub per_step: Option<HostTensor>,
}

/// A float32 result as plain values (row-major `shape`): what a caller's task encodes for the
/// wire without a libtorch call.
#[derive(Debug, Clone, PartialEq)]
pub struct HostTensor {
    pub shape: Vec<i64>,
    pub values: Vec<f32>,
}

impl HostTensor {
    /// The values as a CPU tensor (tests and callers that compute further).
    pub fn to_tensor(&self) -> Result<Tensor> {
        Ok(Tensor::f_from_slice(&self.values)?.f_reshape(&self.shape)?)
    }
}

/// A validated query, ready for the batcher.
#[derive(Debug)]
pub struct Prepared {
    model: SharedReward,
    /// `[B, *item_shape]` row-major, float32, in normalized units.
    x: Vec<f32>,
    /// `[B]`.
    t: Vec<i64>,
    kind: BatchKind,
    /// Per-item gradient factor `[B]` (omega times posterior variance), with the Jacobian to
    /// apply for raw-unit gradients.
    gradient_post: Option<GradientPost>,
    deadline: Option<Instant>,
}

#[derive(Debug)]
struct GradientPost {
    /// `[B]`; `None` when every factor is exactly 1 (omega unset or 1, no variance scaling:
    /// the planner's common case), which saves a multiply per query.
    factor: Option<Vec<f32>>,
    raw_units: bool,
}

impl Prepared {
    pub fn batch(&self) -> i64 {
        self.t.len() as i64
    }
}

/// exp(posterior_log_variance_clipped[t]) for t in [0, T).
type VarianceTable = Arc<Vec<f64>>;

#[derive(Clone)]
pub struct Serving {
    inner: Arc<Inner>,
}

struct Inner {
    registry: ModelRegistry,
    config: ServingConfig,
    slots: Arc<Semaphore>,
    metrics: Metrics,
    queues: batcher::Queues,
    /// exp(posterior_log_variance_clipped) per diffusion model name, with the store's models
    /// generation it was read at: while no model record changed, the table is served without
    /// a metadata read (the planner hot path); after any change the record is read again, so
    /// a model registered again under the same name is never scaled with a stale table.
    variances: Mutex<HashMap<String, (u64, VarianceTable)>>,
}

impl Serving {
    /// `slots` bounds concurrent inference compute (shared with guided sampling).
    pub fn new(registry: ModelRegistry, config: ServingConfig, slots: Arc<Semaphore>, metrics: Metrics) -> Self {
        Self {
            inner: Arc::new(Inner {
                registry,
                config,
                slots,
                metrics,
                queues: batcher::Queues::default(),
                variances: Mutex::new(HashMap::new()),
            }),
        }
    }

    pub fn registry(&self) -> &ModelRegistry {
        &self.inner.registry
    }

    /// The `[serving]` settings (limits and batching, which the OIP ModelConfig reports).
    pub fn config(&self) -> &ServingConfig {
        &self.inner.config
    }

    /// The per-model statistics serving records.
    pub fn metrics(&self) -> &Metrics {
        &self.inner.metrics
    }

    /// The reward model `name` (NotFound, FailedPrecondition for a diffusion model, DataLoss).
    pub async fn reward(&self, name: &str) -> Result<SharedReward> {
        crate::fields::validate_name("model", name)?;
        self.inner.registry.get_reward(name).await
    }

    /// Validates `query` against `model` and converts it to normalized float32 values. Costs
    /// no model compute (and, for normalized inputs, no libtorch call); every error names the
    /// field (`x`, `t`, `per_step`, ...).
    pub async fn prepare(&self, model: SharedReward, query: Query) -> Result<Prepared> {
        let item = &model.item_shape;
        let n_items = check_shape(&query.shape, item, self.inner.config.max_request_items)?;
        if query.values.len() != n_items * item.iter().product::<i64>() as usize {
            return Err(Error::invalid(format!(
                "x: {} values do not fill the shape {}",
                query.values.len(),
                brief(&query.shape)
            )));
        }
        if let Some(i) = query.values.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(format!("x: element {i} is not finite ({})", query.values[i])));
        }
        let big_t = model.manifest.n_timesteps as i64;
        let t = broadcast_t(&query.t, n_items, big_t)?;
        let kind = match &query.op {
            Op::Score { per_window, per_step } => {
                if *per_step && model.window.is_none() {
                    return Err(Error::invalid(format!(
                        "per_step: model '{}' is not windowed ({}); per-step values need a windowed_mlp reward",
                        model.name, model.manifest.architecture
                    )));
                }
                BatchKind::Score { per_window: *per_window, per_step: *per_step }
            }
            Op::Gradient { .. } => BatchKind::Gradient,
        };
        let gradient_post = match &query.op {
            Op::Score { .. } => None,
            Op::Gradient { units, omega, variance_of } => {
                crate::fields::check_omega(*omega)?;
                let mut factor = vec![*omega; n_items];
                if let Some(base) = variance_of {
                    let variance = self.posterior_variance(base, big_t).await?;
                    for (f, &ti) in factor.iter_mut().zip(&t) {
                        *f *= variance[ti as usize];
                    }
                }
                let factor =
                    (!factor.iter().all(|&f| f == 1.0)).then(|| factor.iter().map(|&f| f as f32).collect::<Vec<_>>());
                Some(GradientPost { factor, raw_units: *units == Units::Raw })
            }
        };
        let identity = model.manifest.normalizer == crate::engine::normalizer::Normalizer::Identity;
        let x = match query.input_units {
            Units::Normalized => query.values,
            Units::Raw if identity => query.values,
            Units::Raw => {
                let mut shape = vec![n_items as i64];
                shape.extend(item);
                let x = Tensor::f_from_slice(&query.values)?.f_reshape(&shape)?;
                let x =
                    tch::no_grad(|| model.manifest.normalizer.normalize(&x, model.manifest.space.normalizer_dims()));
                let mut values = vec![0f32; query.values.len()];
                x.f_contiguous()?.f_copy_data(&mut values, query.values.len())?;
                values
            }
        };
        // Only a normalizer fitted to data says what range is meaningful; with identity, the
        // results' own finiteness is the check.
        if !identity {
            check_normalized_range("x", &x, query.input_units)?;
        }
        Ok(Prepared { model, x, t, kind, gradient_post, deadline: query.deadline })
    }

    /// Queues `prepared` with its model's batcher and waits for the answer. Dropping the
    /// returned future (a cancelled call) frees the query's place: it is skipped, not computed.
    pub async fn run(&self, prepared: Prepared) -> Result<Answer> {
        if prepared.deadline.is_some_and(|d| d <= Instant::now()) {
            return Err(Error::DeadlineExceeded("the deadline passed before the query was queued".into()));
        }
        let reply = batcher::submit(&self.inner, prepared)?;
        let answer = reply
            .await
            .map_err(|_| Error::Unavailable("the serving thread stopped (the server is shutting down)".into()))??;
        check_finite(&answer)?;
        Ok(answer)
    }

    /// Validates and runs in one call, counting the outcome in the model's statistics (see
    /// [`crate::metrics::ModelStats`]).
    pub async fn query(&self, name: &str, query: Query) -> Result<Answer> {
        let model = self.reward(name).await?;
        let (started, items) = (Instant::now(), query.shape.first().map_or(0, |&b| b.max(0) as u64));
        let answer = match self.prepare(model, query).await {
            Ok(prepared) => self.run(prepared).await,
            Err(e) => Err(e),
        };
        self.inner.metrics.observe_query(name, answer.is_ok(), items, started.elapsed());
        answer
    }

    /// exp(posterior_log_variance_clipped[t]) of diffusion model `name` for t in [0, T): the
    /// factor Diffuser's `scale_grad_by_std` applies. Its T must equal the reward's.
    async fn posterior_variance(&self, name: &str, big_t: i64) -> Result<VarianceTable> {
        let field = "scale_by_posterior_variance_of";
        crate::fields::validate_name(field, name)?;
        let generation = self.inner.registry.models_generation();
        let cached = self.inner.variances.lock().unwrap_or_else(PoisonError::into_inner).get(name).cloned();
        if let Some((checked, table)) = cached
            && checked == generation
        {
            return check_steps(field, name, &table, big_t);
        }
        let record = self.inner.registry.diffusion_record(name).await.map_err(|e| match e {
            Error::NotFound(m) => Error::NotFound(format!("{field}: {m}")),
            Error::FailedPrecondition(m) => Error::FailedPrecondition(format!("{field}: {m}")),
            other => other,
        })?;
        let manifest: DiffusionManifest = serde_json::from_value(record.manifest)
            .map_err(|e| Error::DataLoss(format!("{field}: model '{name}' has an unreadable manifest: {e}")))?;
        let schedule = Schedule::new(&manifest.schedule, manifest.n_timesteps)?;
        let table =
            Arc::new(schedule.values(Table::PosteriorLogVarianceClipped).iter().map(|v| v.exp()).collect::<Vec<_>>());
        self.inner
            .variances
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(name.to_owned(), (generation, Arc::clone(&table)));
        check_steps(field, name, &table, big_t)
    }
}

fn check_steps(field: &str, name: &str, table: &VarianceTable, big_t: i64) -> Result<VarianceTable> {
    if table.len() as i64 != big_t {
        return Err(Error::invalid(format!(
            "{field}: model '{name}' has {} diffusion steps but the reward model was trained with {big_t}",
            table.len()
        )));
    }
    Ok(Arc::clone(table))
}

/// Refuses normalized inputs beyond [`MAX_NORMALIZED_X`], naming `field`, its first such
/// element and the units it was given in (Score and Gradient's `x`, Sample's condition states).
pub(crate) fn check_normalized_range(field: &str, x: &[f32], units: Units) -> Result<()> {
    let Some(first) = x.iter().position(|v| v.is_nan() || f64::from(v.abs()) > MAX_NORMALIZED_X) else {
        return Ok(());
    };
    let value = x[first];
    let given = match units {
        Units::Raw => "after normalizing the raw input",
        Units::Normalized => "as given (input_units normalized)",
    };
    Err(Error::invalid(format!(
        "{field}: element {first} is {value:e} in the model's normalized units ({given}), outside the accepted \
         [-{MAX_NORMALIZED_X:e}, {MAX_NORMALIZED_X:e}]; the normalizer maps the training data to about [-1, 1], so \
         check the input's units and scale"
    )))
}

/// An answer must never carry Inf or NaN: inputs inside the accepted ranges that still
/// overflow the model are refused rather than answered.
fn check_finite(answer: &Answer) -> Result<()> {
    let parts = [("rewards", Some(&answer.rewards)), ("gradient", answer.gradient.as_ref())];
    let parts =
        parts.into_iter().chain([("per_window", answer.per_window.as_ref()), ("per_step", answer.per_step.as_ref())]);
    for (what, host) in parts {
        let Some(host) = host else { continue };
        if !host.values.iter().all(|v| v.is_finite()) {
            return Err(Error::invalid(format!(
                "x: the model's {what} for these inputs is not finite (the inputs or omega are too large for it); \
                 nothing was returned"
            )));
        }
    }
    Ok(())
}

/// Checks `shape` = [B, *item] with 1 <= B <= max; returns B.
fn check_shape(shape: &[i64], item: &[i64], max: usize) -> Result<usize> {
    if shape.len() != item.len() + 1 || shape[1..] != *item {
        let mut want = vec!["B".to_owned()];
        want.extend(item.iter().map(i64::to_string));
        return Err(Error::invalid(format!(
            "x: expected shape [{}] for this model, got {}",
            want.join(", "),
            brief(&shape)
        )));
    }
    let b = shape[0];
    if b < 1 {
        return Err(Error::invalid("x: the batch is empty (B = 0); send at least one item"));
    }
    if b as usize > max {
        return Err(Error::invalid(format!(
            "x: {b} items is above the limit of {max} per request (serving.max_request_items); split the batch"
        )));
    }
    Ok(b as usize)
}

/// t per item: empty means 0, one value is broadcast, else exactly B values in [0, T).
fn broadcast_t(t: &[i64], b: usize, big_t: i64) -> Result<Vec<i64>> {
    let t = match t.len() {
        0 => vec![0; b],
        1 => vec![t[0]; b],
        n if n == b => t.to_vec(),
        n => return Err(Error::invalid(format!("t: {n} values for {b} items (give none, one, or one per item)"))),
    };
    // The field is named only for the first bad value (no formatting on the hot path).
    if let Some((i, &v)) = t.iter().enumerate().find(|(_, v)| !(0..big_t).contains(*v)) {
        crate::fields::diffusion_time(&format!("t[{i}]"), v, big_t as usize)?;
    }
    Ok(t)
}

/// Parses a gRPC `grpc-timeout` header value ("100m", "5S", ...) into a duration.
pub fn parse_grpc_timeout(value: &str) -> Option<Duration> {
    let (digits, unit) = value.split_at(value.len().checked_sub(1)?);
    if digits.is_empty() || digits.len() > 8 || !digits.bytes().all(|c| c.is_ascii_digit()) {
        return None;
    }
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.saturating_mul(3600)),
        "M" => Duration::from_secs(n.saturating_mul(60)),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

/// The deadline a gRPC request carries, if any.
pub fn deadline_of(metadata: &tonic::metadata::MetadataMap) -> Option<Instant> {
    let value = metadata.get("grpc-timeout")?.to_str().ok()?;
    Some(Instant::now() + parse_grpc_timeout(value)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grpc_timeouts_parse() {
        assert_eq!(parse_grpc_timeout("100m"), Some(Duration::from_millis(100)));
        assert_eq!(parse_grpc_timeout("5S"), Some(Duration::from_secs(5)));
        assert_eq!(parse_grpc_timeout("7u"), Some(Duration::from_micros(7)));
        assert_eq!(parse_grpc_timeout("2H"), Some(Duration::from_secs(7200)));
        assert_eq!(parse_grpc_timeout("m"), None);
        assert_eq!(parse_grpc_timeout("123456789S"), None, "at most 8 digits");
        assert_eq!(parse_grpc_timeout("10x"), None);
        assert_eq!(parse_grpc_timeout(""), None);
    }

    #[test]
    fn shapes_and_times_are_checked_with_named_fields() {
        assert_eq!(check_shape(&[3, 4, 2], &[4, 2], 10).expect("ok"), 3);
        let e = check_shape(&[3, 4], &[4, 2], 10).unwrap_err().to_string();
        assert!(e.contains("x: expected shape [B, 4, 2]") && e.contains("[3, 4]"), "{e}");
        assert!(check_shape(&[0, 4, 2], &[4, 2], 10).unwrap_err().to_string().contains("B = 0"));
        assert!(check_shape(&[11, 4, 2], &[4, 2], 10).unwrap_err().to_string().contains("max_request_items"));
        assert_eq!(broadcast_t(&[], 2, 10).expect("zeros"), [0, 0]);
        assert_eq!(broadcast_t(&[3], 2, 10).expect("broadcast"), [3, 3]);
        assert!(broadcast_t(&[1, 2, 3], 2, 10).unwrap_err().to_string().contains("t: 3 values for 2 items"));
        assert!(broadcast_t(&[1, 10], 2, 10).unwrap_err().to_string().contains("t[1]: 10 is outside [0, 10)"));
        assert!(broadcast_t(&[-1], 2, 10).unwrap_err().to_string().contains("t[0]: -1"));
    }
}

#[cfg(test)]
mod serving_tests;
