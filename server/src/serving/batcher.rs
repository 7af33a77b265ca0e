//! The per-model dynamic batcher.
//!
//! One [`ModelQueue`] per loaded reward model (keyed by its blob key, so a re-registered model
//! gets a fresh queue), each drained by its own serving thread, started on first use and
//! stopped after [`IDLE`] without work, or at shutdown once its queue is empty (the threads
//! are the `serving` group of [`crate::tasks`], woken by `Serving::stop`). The thread:
//!
//! 1. waits for a query, then up to `max_delay_us` after its arrival, and until as many
//!    queries as its last pass had are queued again for at most `refill_fraction` of that
//!    pass's time ([`wait_for_company`]; never once `max_batch` items of the same
//!    [`BatchKind`] are queued);
//! 2. takes queries of the first query's kind, in arrival order, up to `max_batch` items (the
//!    first is always taken, even if larger): a query whose caller went away is skipped, one
//!    whose deadline passed is answered DEADLINE_EXCEEDED, neither is computed;
//! 3. takes an inference slot (shared with sampling), concatenates the items, runs one
//!    forward (Score) or forward/backward (Gradient) pass, and splits the results back. A
//!    long pass is computed in parts by the thread and its helpers ([`super::split`]), one
//!    per further slot free, up to `pass_threads`.
//!
//! Queries of different kinds never share a pass; gradient options (units, omega, variance)
//! are per-item factors applied after the shared backward pass, so they do not split batches.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use tch::Tensor;
use tokio::sync::oneshot;

use super::query::BatchKind;
use super::split::{Helpers, Split};
use super::{Answer, HostTensor, Inner, Prepared};
use crate::config::ServingConfig;
use crate::engine::normalizer::Normalize;
use crate::error::{Error, Result};
use crate::registry::SharedReward;

/// A serving thread with nothing to do for this long exits (the next query starts another).
const IDLE: Duration = Duration::from_secs(30);

/// The queues of every model with a serving thread.
#[derive(Default)]
pub(super) struct Queues {
    by_key: Mutex<HashMap<String, Arc<ModelQueue>>>,
}

struct ModelQueue {
    model: SharedReward,
    state: Mutex<QueueState>,
    arrived: Condvar,
}

#[derive(Default)]
struct QueueState {
    pending: VecDeque<Pending>,
    /// Set by the exiting thread: submitters must start a new queue.
    closed: bool,
}

struct Pending {
    query: Prepared,
    reply: oneshot::Sender<Result<Answer>>,
    arrived: Instant,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Critical sections only move queries in and out of a deque; a panic cannot leave it
    // half-updated.
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Queues `query` with its model's thread (starting one if needed). RESOURCE_EXHAUSTED when
/// the model's queue is full, UNAVAILABLE once serving is stopping.
pub(super) fn submit(inner: &Arc<Inner>, query: Prepared) -> Result<oneshot::Receiver<Result<Answer>>> {
    let (reply, answer) = oneshot::channel();
    let mut pending = Some(Pending { query, reply, arrived: Instant::now() });
    loop {
        let queue = queue_for(inner, pending.as_ref().map(|p| &p.query.model).ok_or_else(lost_query)?)?;
        let mut state = lock(&queue.state);
        if state.closed {
            // The thread exited between the lookup and now; forget it and start another.
            drop(state);
            let mut map = lock(&inner.queues.by_key);
            if map.get(&queue.model.blob_key).is_some_and(|q| Arc::ptr_eq(q, &queue)) {
                map.remove(&queue.model.blob_key);
            }
            continue;
        }
        if state.pending.len() >= inner.config.queue_capacity {
            inner.metrics.dropped(&queue.model.name, "queue_full");
            return Err(Error::ResourceExhausted(format!(
                "model '{}' has {} queries waiting (serving.queue_capacity); retry with backoff",
                queue.model.name,
                state.pending.len()
            )));
        }
        state.pending.push_back(pending.take().ok_or_else(lost_query)?);
        inner.metrics.set_queue_depth(&queue.model.name, state.pending.len());
        queue.arrived.notify_one();
        return Ok(answer);
    }
}

fn lost_query() -> Error {
    Error::internal("serving", "query lost before queueing")
}

/// The live queue of `model`, started with its thread if there is none.
fn queue_for(inner: &Arc<Inner>, model: &SharedReward) -> Result<Arc<ModelQueue>> {
    let mut map = lock(&inner.queues.by_key);
    if let Some(q) = map.get(&model.blob_key) {
        return Ok(Arc::clone(q));
    }
    if inner.tasks.token().is_cancelled() {
        return Err(Error::Unavailable("the server is shutting down".into()));
    }
    let queue = Arc::new(ModelQueue {
        model: Arc::clone(model),
        state: Mutex::new(QueueState::default()),
        arrived: Condvar::new(),
    });
    let (thread_queue, thread_inner) = (Arc::clone(&queue), Arc::clone(inner));
    let tracked = inner.tasks.enlist();
    std::thread::Builder::new()
        .name(format!("serve-{}", model.name))
        .spawn(move || {
            let _tracked = tracked;
            serve(&thread_inner, &thread_queue);
        })
        .map_err(|e| Error::internal("starting a serving thread", e))?;
    map.insert(model.blob_key.clone(), Arc::clone(&queue));
    Ok(queue)
}

/// The serving thread of one model.
fn serve(inner: &Arc<Inner>, queue: &Arc<ModelQueue>) {
    let name = queue.model.name.clone();
    tracing::debug!(model = name, "serving thread started");
    let mut last: Option<LastPass> = None;
    let mut helpers = Helpers::default();
    while let Some((kind, batch)) = next_batch(inner, queue, last.as_ref()) {
        // Wait for a compute slot; queries may expire or be abandoned meanwhile.
        let Ok(_slot) = futures::executor::block_on(Arc::clone(&inner.slots).acquire_owned()) else {
            for p in batch {
                let _ = p.reply.send(Err(Error::Unavailable("the server is shutting down".into())));
            }
            continue;
        };
        let batch = drop_expired(inner, &name, batch, Instant::now());
        if batch.is_empty() {
            continue;
        }
        let started = Instant::now();
        for p in &batch {
            inner.metrics.observe_queue_wait(&name, started.duration_since(p.arrived).as_secs_f64());
        }
        let items: i64 = batch.iter().map(|p| p.query.batch()).sum();
        let cost_per_item = last.as_ref().map_or(Duration::ZERO, |l| l.cost_per_item);
        let split = Split { inner, helpers: &mut helpers, cost_per_item };
        // A panic in a pass is a bug; contained here, it fails this batch's callers and the
        // thread goes on serving (unwound, the queue would stay registered with nobody to
        // answer it, and every later query for the model would wait out its deadline).
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            compute(queue, kind, &batch, inner.config.max_batch as i64, split)
        }))
        .unwrap_or_else(|_| Err(Error::internal("serving batch", "a pass panicked")));
        let took = started.elapsed();
        inner.metrics.observe_batch(&name, batch.len(), items as usize, took.as_secs_f64());
        let parts = result.as_ref().map_or(1, |(_, parts)| *parts);
        if parts > 1 {
            inner.metrics.observe_split_pass(&name);
        }
        // What the pass would have taken per item on one thread, roughly: the split's criterion.
        let queries = batch.len();
        let cost_per_item = took.saturating_mul(parts as u32) / items.clamp(1, i64::from(u32::MAX)) as u32;
        match result.map(|(answers, _)| answers) {
            Ok(answers) => {
                for (p, a) in batch.into_iter().zip(answers) {
                    let _ = p.reply.send(Ok(a));
                }
            }
            Err(e) => {
                tracing::error!(model = name, error = %e, "a merged batch failed");
                let msg = e.to_string();
                for p in batch {
                    let _ = p.reply.send(Err(Error::internal("serving batch", &msg)));
                }
            }
        }
        last = Some(LastPass { queries, took, cost_per_item, ended: Instant::now() });
    }
    tracing::debug!(model = name, "serving thread idle: stopped");
}

/// Waits for work and returns the next batch, or `None` after [`IDLE`] without work or, at
/// shutdown, once nothing is queued (the queue is then closed).
fn next_batch(inner: &Inner, queue: &ModelQueue, last: Option<&LastPass>) -> Option<(BatchKind, Vec<Pending>)> {
    let max_batch = inner.config.max_batch as i64;
    let mut state = lock(&queue.state);
    loop {
        while state.pending.is_empty() {
            // Checked under the queue's lock, which `stop` takes to wake the thread: a stop
            // is never missed between this check and the wait.
            if inner.tasks.token().is_cancelled() {
                state.closed = true;
                return None;
            }
            let (s, timeout) = queue.arrived.wait_timeout(state, IDLE).unwrap_or_else(PoisonError::into_inner);
            state = s;
            if timeout.timed_out() && state.pending.is_empty() {
                state.closed = true;
                return None;
            }
        }
        let (kind, first_arrived) = {
            let first = state.pending.front()?;
            (first.query.kind, first.arrived)
        };
        loop {
            let same_kind = || state.pending.iter().filter(|p| p.query.kind == kind);
            let queued = Queued { items: same_kind().map(|p| p.query.batch()).sum(), queries: same_kind().count() };
            let Some(wake) = wait_for_company(&inner.config, first_arrived, last, queued, Instant::now()) else {
                break;
            };
            let timeout = wake.saturating_duration_since(Instant::now());
            state = queue.arrived.wait_timeout(state, timeout).unwrap_or_else(PoisonError::into_inner).0;
        }
        let now = Instant::now();
        let mut batch = Vec::new();
        let mut items = 0i64;
        let mut rest = VecDeque::with_capacity(state.pending.len());
        while let Some(p) = state.pending.pop_front() {
            if p.query.kind != kind || (items > 0 && items + p.query.batch() > max_batch) {
                rest.push_back(p);
                continue;
            }
            if let Some(p) = keep(inner, &queue.model.name, p, now) {
                items += p.query.batch();
                batch.push(p);
            }
        }
        state.pending = rest;
        inner.metrics.set_queue_depth(&queue.model.name, state.pending.len());
        if !batch.is_empty() {
            return Some((kind, batch));
        }
    }
}

/// Queries of the next batch's kind waiting, and their items.
#[derive(Debug, Clone, Copy)]
struct Queued {
    items: i64,
    queries: usize,
}

/// Until when the next batch waits for company (`None`: go now), its first query having
/// arrived at `first_arrived`: until that query's `max_delay_us` is spent, and until as many
/// queries as the last pass had are queued again (its callers back), for at most
/// `refill_fraction` of that pass's time after it ended; never once `max_batch` items wait.
fn wait_for_company(
    config: &ServingConfig,
    first_arrived: Instant,
    last: Option<&LastPass>,
    queued: Queued,
    now: Instant,
) -> Option<Instant> {
    if queued.items >= config.max_batch as i64 {
        return None;
    }
    let delay_until = first_arrived + Duration::from_micros(config.max_delay_us);
    let refill_until =
        last.filter(|l| queued.queries < l.queries).map(|l| l.ended + l.took.mul_f64(config.refill_fraction));
    let until = refill_until.map_or(delay_until, |r| r.max(delay_until));
    (now < until).then_some(until)
}

/// The pass a serving thread computed last.
struct LastPass {
    queries: usize,
    /// Its wall time, from the compute slot to the answers.
    took: Duration,
    /// Its wall time times the threads it was split across, per item.
    cost_per_item: Duration,
    ended: Instant,
}

/// `Some(p)` if its caller still waits and its deadline has not passed; otherwise it is
/// answered (or dropped) here and counted.
fn keep(inner: &Inner, model: &str, p: Pending, now: Instant) -> Option<Pending> {
    if p.reply.is_closed() {
        inner.metrics.dropped(model, "cancelled");
        return None;
    }
    if p.query.deadline.is_some_and(|d| d <= now) {
        inner.metrics.dropped(model, "deadline");
        let waited = now.duration_since(p.arrived);
        let _ = p.reply.send(Err(Error::DeadlineExceeded(format!(
            "the deadline passed after {:.1} ms in model '{model}''s queue; the query was not computed",
            waited.as_secs_f64() * 1e3
        ))));
        return None;
    }
    Some(p)
}

/// Wakes every serving thread after the serving group's token was cancelled: each serves
/// what its queue still holds, then exits.
pub(super) fn wake_all(inner: &Inner) {
    let queues: Vec<Arc<ModelQueue>> = lock(&inner.queues.by_key).values().cloned().collect();
    for queue in queues {
        let _state = lock(&queue.state);
        queue.arrived.notify_all();
    }
}

fn drop_expired(inner: &Inner, model: &str, batch: Vec<Pending>, now: Instant) -> Vec<Pending> {
    batch.into_iter().filter_map(|p| keep(inner, model, p, now)).collect()
}

/// One forward (and backward) pass over the concatenated batch, split back per query, with
/// how many threads computed it. The queries' floats are joined into one tensor and each
/// result is copied to the host once; everything per query (splitting, omega and variance
/// factors, the Jacobian) is plain arithmetic on those host values, so the per-query cost is a
/// few copies of its own rows.
fn compute(
    queue: &ModelQueue,
    kind: BatchKind,
    batch: &[Pending],
    max_rows: i64,
    split: Split<'_>,
) -> Result<(Vec<Answer>, usize)> {
    let sizes: Vec<i64> = batch.iter().map(|p| p.query.batch()).collect();
    let n: i64 = sizes.iter().sum();
    // Padded with zero items (t = 0) where the network's kernels are compiled per batch size
    // (`RewardNet::padded_batch`), never past `max_batch` (a batch of one large query already
    // is); rows are independent, and only the first n are read back.
    let rows = queue.model.lock().padded_batch(n).min(max_rows.max(n));
    let mut shape = vec![rows];
    shape.extend(&queue.model.item_shape);
    // Floats per item (an item shape has no zero dimension).
    let per_item = (queue.model.item_shape.iter().product::<i64>() as usize).max(1);
    let mut xs = Vec::with_capacity(per_item * rows as usize);
    let mut ts = Vec::with_capacity(rows as usize);
    for p in batch {
        xs.extend_from_slice(&p.query.x);
        ts.extend_from_slice(&p.query.t);
    }
    xs.resize(per_item * rows as usize, 0.0);
    ts.resize(rows as usize, 0);
    let x_host = Tensor::f_from_slice(&xs)?.f_reshape(&shape)?;
    let t = Tensor::f_from_slice(&ts)?;
    // On a GPU (`engine.device`): one copy of the whole batch there (pinned, asynchronous:
    // `engine::upload`) and one of each result back, never one per query. On the CPU both
    // moves are no-ops.
    let device = crate::engine::device();
    let (x, t) = (crate::engine::upload(&x_host, device)?, crate::engine::upload(&t, device)?);
    let (out, parts) = split.evaluate(&queue.model, kind, &x, &t)?;
    let real = |v: &Tensor| v.f_narrow(0, 0, n);
    let rewards = split_host(&real(&out.rho)?, &sizes)?;
    let _no_grad = tch::no_grad_guard();
    let answers = match (kind, out.grad) {
        (BatchKind::Score { .. }, _) => {
            let mut windows = out.windows.map(|w| split_host(&real(&w)?, &sizes)).transpose()?.map(Vec::into_iter);
            let mut steps = out.steps.map(|s| split_host(&real(&s)?, &sizes)).transpose()?.map(Vec::into_iter);
            rewards
                .into_iter()
                .map(|rewards| Answer {
                    rewards,
                    gradient: None,
                    per_window: windows.as_mut().and_then(Iterator::next),
                    per_step: steps.as_mut().and_then(Iterator::next),
                })
                .collect()
        }
        (BatchKind::Gradient, Some(grad)) => {
            // The normalizer's Jacobian (one item's worth of per-element factors) only for
            // batches with a raw-unit gradient (planners ask in normalized units).
            let raw_units = batch.iter().any(|p| p.query.gradient_post.as_ref().is_some_and(|g| g.raw_units));
            let jacobian = if raw_units { Some(item_jacobian(queue, &x_host)?) } else { None };
            let mut answers = Vec::with_capacity(batch.len());
            for ((p, rewards), mut gradient) in batch.iter().zip(rewards).zip(split_host(&real(&grad)?, &sizes)?) {
                if let Some(post) = &p.query.gradient_post {
                    if let Some(factor) = &post.factor {
                        for (row, f) in gradient.values.chunks_mut(per_item).zip(factor) {
                            row.iter_mut().for_each(|g| *g *= f);
                        }
                    }
                    if let (Some(j), true) = (&jacobian, post.raw_units) {
                        for row in gradient.values.chunks_mut(per_item) {
                            row.iter_mut().zip(j).for_each(|(g, j)| *g *= j);
                        }
                    }
                }
                answers.push(Answer { rewards, gradient: Some(gradient), per_window: None, per_step: None });
            }
            answers
        }
        (BatchKind::Gradient, None) => {
            return Err(Error::internal("serving batch", "a gradient pass without a gradient"));
        }
    };
    Ok((answers, parts))
}

/// d(normalized x) / d(raw x) for each element of one item (the normalizer is affine, so the
/// same for every item), as host values in the item's row-major order.
fn item_jacobian(queue: &ModelQueue, x_host: &Tensor) -> Result<Vec<f32>> {
    let m = &queue.model.manifest;
    let one = x_host.f_narrow(0, 0, 1)?;
    let j = one.f_ones_like()?.f_mul(&m.normalizer.jacobian(&one, m.space.normalizer_dims()))?;
    let numel = j.numel();
    let mut values = vec![0f32; numel];
    j.f_to_kind(tch::Kind::Float)?.f_contiguous()?.f_copy_data(&mut values, numel)?;
    Ok(values)
}

/// `v` (`[N, ...]`) copied to the host once and split into the queries' rows.
fn split_host(v: &Tensor, sizes: &[i64]) -> Result<Vec<HostTensor>> {
    let v = v.f_to_device(tch::Device::Cpu)?.f_to_kind(tch::Kind::Float)?.f_contiguous()?;
    let shape = v.size();
    let numel = v.numel();
    let mut all = vec![0f32; numel];
    v.f_copy_data(&mut all, numel)?;
    let per_item = shape[1..].iter().product::<i64>() as usize;
    let mut at = 0;
    let mut out = Vec::with_capacity(sizes.len());
    for &b in sizes {
        let len = b as usize * per_item;
        let values =
            all.get(at..at + len).ok_or_else(|| Error::internal("serving batch", "a result shorter than its batch"))?;
        let mut s = vec![b];
        s.extend(&shape[1..]);
        out.push(HostTensor { shape: s, values: values.to_vec() });
        at += len;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(max_delay_us: u64, refill_fraction: f64) -> ServingConfig {
        ServingConfig {
            max_request_items: 4096,
            max_batch: 256,
            max_delay_us,
            refill_fraction,
            pass_threads: 2,
            split_above_ms: 4.0,
            queue_capacity: 1024,
            default_deadline_ms: 0,
        }
    }

    fn queued(queries: usize) -> Queued {
        Queued { items: queries as i64, queries }
    }

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn the_next_batch_waits_for_the_last_passs_callers_for_a_fraction_of_its_time() {
        let ended = Instant::now();
        let last = LastPass { queries: 64, took: 20 * MS, cost_per_item: MS, ended };
        let c = config(0, 0.5);
        let arrived = ended + MS;
        // 10 of the 64 callers are back: wait until half the pass's 20 ms after it ended.
        assert_eq!(wait_for_company(&c, arrived, Some(&last), queued(10), ended + 2 * MS), Some(ended + 10 * MS));
        // All back, or the wait spent: go with what is there.
        assert_eq!(wait_for_company(&c, arrived, Some(&last), queued(64), ended + 2 * MS), None);
        assert_eq!(wait_for_company(&c, arrived, Some(&last), queued(10), ended + 10 * MS), None);
        // A full batch never waits.
        let full = Queued { items: 256, queries: 3 };
        assert_eq!(wait_for_company(&c, arrived, Some(&last), full, ended + 2 * MS), None);
        // Without refilling, the first query's own delay alone.
        assert_eq!(wait_for_company(&config(0, 0.0), arrived, Some(&last), queued(10), ended + 2 * MS), None);
        let delayed = config(50_000, 0.5);
        assert_eq!(
            wait_for_company(&delayed, arrived, Some(&last), queued(64), ended + 2 * MS),
            Some(arrived + 50 * MS)
        );
        // Whichever ends later, when both apply.
        assert_eq!(
            wait_for_company(&delayed, arrived, Some(&last), queued(10), ended + 2 * MS),
            Some(arrived + 50 * MS)
        );
    }

    #[test]
    fn a_lone_caller_never_waits_for_company() {
        let ended = Instant::now();
        let c = config(0, 0.5);
        // Its own last pass had one query: it is back, nothing to wait for.
        let last = LastPass { queries: 1, took: 20 * MS, cost_per_item: MS, ended };
        assert_eq!(wait_for_company(&c, ended + MS, Some(&last), queued(1), ended + MS), None);
        // A model's first pass has no callers to wait for.
        assert_eq!(wait_for_company(&c, ended, None, queued(1), ended), None);
    }
}
