//! Serving rho: Score and Gradient queries against reward models, merged across concurrent
//! callers by a per-model dynamic batcher. Both the native RewardService and the Open
//! Inference Protocol endpoint call [`Serving::query`]; neither touches tensors themselves.
//!
//! - [`query`]: the one place that validates a reward query, from the wire (Score, Gradient
//!   and GradientStream messages; OIP's parsed inputs) to [`Serving::prepare`], which checks it
//!   against the model (shape, B, t, finiteness, per-step support, omega, units and range)
//!   before any compute, so bad input costs nothing and names its field.
//! - [`batcher`] queues prepared queries per loaded model (bounded: RESOURCE_EXHAUSTED when
//!   full), and one serving thread per model merges compatible queries into one forward (and
//!   backward) pass of at most `serving.max_batch` items, waiting at most
//!   `serving.max_delay_us` after the first for company (and up to `serving.refill_fraction`
//!   of the last pass's time for its callers to come back). A query whose deadline passed
//!   while queued is answered DEADLINE_EXCEEDED without being computed; one whose caller went
//!   away (dropped its reply) is skipped.
//! - [`split`]: a long pass split by rows across the serving thread and helper threads, each
//!   with its own handle on the weights (`serving.pass_threads`), and a pass's outputs.
//! - Compute is bounded by the inference slots (`engine.inference_workers`) shared with
//!   sampling ([`crate::sampling`]); training jobs run on their own threads and never take a
//!   slot.
//!
//! - Per-request work stays off libtorch: a query carries plain floats from the wire to the
//!   serving thread (raw inputs are normalized on those floats), which builds one tensor per batch, copies each result to the host once
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
pub mod query;
mod split;

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use tch::Tensor;
use tokio::sync::Semaphore;

use crate::config::ServingConfig;
use crate::engine::manifest::DiffusionManifest;
use crate::engine::schedule::{Schedule, Table};
use crate::error::{Error, Result};
use crate::metrics::Metrics;
use crate::registry::{ModelRegistry, SharedReward};
use crate::tasks::Tasks;

pub(crate) use query::check_normalized_range;
pub use query::{MAX_NORMALIZED_X, Op, Prepared, Query, Units};

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
    /// The serving threads (one per model with a queue) and the token that stops them.
    tasks: Tasks,
    /// exp(posterior_log_variance_clipped) per diffusion model name, with the store's models
    /// generation it was read at: while no model record changed, the table is served without
    /// a metadata read (the planner hot path); after any change the record is read again, so
    /// a model registered again under the same name is never scaled with a stale table.
    variances: Mutex<HashMap<String, (u64, VarianceTable)>>,
}

impl Serving {
    /// `slots` bounds concurrent inference compute (shared with guided sampling); `tasks` is
    /// the group the serving threads belong to (see [`Serving::stop`]).
    pub fn new(
        registry: ModelRegistry,
        config: ServingConfig,
        slots: Arc<Semaphore>,
        metrics: Metrics,
        tasks: Tasks,
    ) -> Self {
        Self {
            inner: Arc::new(Inner {
                registry,
                config,
                slots,
                metrics,
                queues: batcher::Queues::default(),
                tasks,
                variances: Mutex::new(HashMap::new()),
            }),
        }
    }

    /// Shutdown, after the calls' grace: new queries are refused UNAVAILABLE, each serving
    /// thread answers what its queue still holds and exits; waits at most `bound` for them.
    pub async fn stop(&self, bound: Duration) -> bool {
        self.inner.tasks.token().cancel();
        batcher::wake_all(&self.inner);
        self.inner.tasks.stop(bound).await
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

    /// Queues `prepared` with its model's batcher and waits for the answer. Dropping the
    /// returned future (a cancelled call) frees the query's place: it is skipped, not computed.
    pub async fn run(&self, prepared: Prepared) -> Result<Answer> {
        let reply = self.enqueue(prepared)?;
        Self::answer(reply).await
    }

    /// Puts `prepared` in its model's queue: refused (DEADLINE_EXCEEDED) when its deadline
    /// passed before it arrived, RESOURCE_EXHAUSTED when the queue is full.
    fn enqueue(&self, prepared: Prepared) -> Result<tokio::sync::oneshot::Receiver<Result<Answer>>> {
        if prepared.deadline.is_some_and(|d| d <= Instant::now()) {
            return Err(Error::DeadlineExceeded("the deadline passed before the query was queued".into()));
        }
        batcher::submit(&self.inner, prepared)
    }

    /// The answer of a queued query (checked finite: a model that yields NaN fails the query).
    async fn answer(reply: tokio::sync::oneshot::Receiver<Result<Answer>>) -> Result<Answer> {
        let answer = reply
            .await
            .map_err(|_| Error::Unavailable("the serving thread stopped (the server is shutting down)".into()))??;
        query::check_finite(&answer)?;
        Ok(answer)
    }

    /// Validates and runs in one call, counting the outcome in the model's statistics (see
    /// [`crate::metrics::ModelStats`]) with Triton's semantics: a query counts once it is in
    /// the model's queue (Triton counts a request once its scheduler accepted it). Refusals
    /// before that (validation against the model, a deadline already passed, a full queue)
    /// answer the caller and are not counted, as Triton's failures of `PrepareForInference`
    /// and `Enqueue` are not; after it, every end counts once: success, or fail for a deadline
    /// passed in the queue (Triton's REJECTED), a cancelled call (CANCELED), a compute error or
    /// a non-finite answer (BACKEND), or shutdown.
    pub async fn query(&self, name: &str, query: Query) -> Result<Answer> {
        let model = self.reward(name).await?;
        let (started, items) = (Instant::now(), query.shape.first().map_or(0, |&b| b.max(0) as u64));
        let prepared = self.prepare(model, query).await?;
        let reply = self.enqueue(prepared)?;
        let mut outcome = Outcome { metrics: &self.inner.metrics, model: name, started, items, counted: false };
        let answer = Self::answer(reply).await;
        outcome.count(answer.is_ok());
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

/// The statistics entry of one queued query: counted once, when its answer comes or, for a
/// call dropped while queued or computing (its client cancelled), as a failure on drop.
struct Outcome<'a> {
    metrics: &'a Metrics,
    model: &'a str,
    started: Instant,
    items: u64,
    counted: bool,
}

impl Outcome<'_> {
    fn count(&mut self, ok: bool) {
        if !self.counted {
            self.counted = true;
            self.metrics.observe_query(self.model, ok, self.items, self.started.elapsed());
        }
    }
}

impl Drop for Outcome<'_> {
    fn drop(&mut self) {
        self.count(false);
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
}

#[cfg(test)]
mod serving_tests;
