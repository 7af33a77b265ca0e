//! The job system, shared by every kind of training job: submission with idempotent ids, a
//! bounded queue, a configured number of jobs running at once (each on its own named OS
//! thread checking a cancellation token every step), durable events with sequence numbers,
//! replay-then-follow watching, checkpoints, cancellation, and resumption after a restart.
//!
//! Module map:
//! - [`spec`]: the stored, fully explicit job specification.
//! - [`context`]: [`context::JobContext`], what a running job may do.
//! - [`datasets`]: stored datasets read back as training rows and windows.
//! - [`training`]: [`training::TrainLoop`], the optimisation loop every runner shares.
//! - [`diffusion`]: the diffusion-training runner.
//! - [`reward`]: the relative-reward runner (Algorithm 1).
//!
//! State machine: PENDING -> RUNNING -> SUCCEEDED | FAILED | CANCELLED, and PENDING ->
//! CANCELLED. The store refuses any way out of a terminal state. A job found RUNNING at start
//! (the server stopped or crashed under it) is queued again and resumes from its checkpoint.

pub mod context;
pub mod datasets;
pub mod diffusion;
pub mod reward;
pub mod spec;
pub mod training;

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::Stream;
use tokio::sync::{Notify, broadcast};
use tokio_util::sync::CancellationToken;

use self::context::{JobContext, Stop};
use self::spec::{JobKind, JobSpec};
use crate::config::JobsConfig;
use crate::error::{Error, Result};
use crate::store::ingest::now_ms;
use crate::store::names::validate_name;
use crate::store::{JobEvent, JobEventKind, JobRecord, JobState, Store};

/// Live-event buffer per job; a watcher further behind re-reads from the store.
const LIVE_BUFFER: usize = 256;
/// Events read from the store per page while replaying.
const REPLAY_PAGE: usize = 500;

#[derive(Clone)]
pub struct JobManager {
    inner: Arc<Inner>,
}

struct Inner {
    store: Store,
    config: JobsConfig,
    rt: tokio::runtime::Handle,
    queue: Mutex<VecDeque<String>>,
    wake: Notify,
    /// Jobs queued or running: their cancel token and live event channel.
    live: Mutex<HashMap<String, Live>>,
    running: Mutex<HashMap<String, std::thread::JoinHandle<()>>>,
    shutdown: CancellationToken,
}

#[derive(Clone)]
struct Live {
    cancel: CancellationToken,
    events: broadcast::Sender<JobEvent>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic while holding these locks cannot leave their data inconsistent (each critical
    // section is a single insert/remove), so a poisoned lock is still usable.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl JobManager {
    /// Starts the dispatcher and re-queues jobs left PENDING or RUNNING by a previous process.
    pub async fn start(store: Store, config: JobsConfig, shutdown: CancellationToken) -> Result<Self> {
        let inner = Arc::new(Inner {
            store,
            config,
            rt: tokio::runtime::Handle::current(),
            queue: Mutex::new(VecDeque::new()),
            wake: Notify::new(),
            live: Mutex::new(HashMap::new()),
            running: Mutex::new(HashMap::new()),
            shutdown,
        });
        let manager = Self { inner };
        let mut recovered = manager.inner.store.meta.jobs_in_states(&[JobState::Running]).await?;
        recovered.extend(manager.inner.store.meta.jobs_in_states(&[JobState::Pending]).await?);
        for job in &recovered {
            manager.enqueue(&job.id);
        }
        if !recovered.is_empty() {
            tracing::info!(jobs = recovered.len(), "re-queued jobs interrupted by the previous shutdown");
        }
        let dispatcher = manager.clone();
        tokio::spawn(async move { dispatcher.dispatch().await });
        Ok(manager)
    }

    fn enqueue(&self, id: &str) {
        let (events, _) = broadcast::channel(LIVE_BUFFER);
        lock(&self.inner.live).insert(id.to_owned(), Live { cancel: CancellationToken::new(), events });
        lock(&self.inner.queue).push_back(id.to_owned());
        self.inner.wake.notify_one();
    }

    /// Starts queued jobs while fewer than `max_concurrent` run.
    async fn dispatch(self) {
        loop {
            tokio::select! {
                () = self.inner.wake.notified() => {}
                () = self.inner.shutdown.cancelled() => return,
                // Finished threads are reaped on a timer as well as on wake-ups.
                () = tokio::time::sleep(Duration::from_millis(200)) => {}
            }
            lock(&self.inner.running).retain(|_, h| !h.is_finished());
            loop {
                if self.inner.shutdown.is_cancelled()
                    || lock(&self.inner.running).len() >= self.inner.config.max_concurrent
                {
                    break;
                }
                let Some(id) = lock(&self.inner.queue).pop_front() else { break };
                if let Err(e) = self.launch(&id).await {
                    tracing::error!(job = id, error = %e, "could not start job");
                    self.fail_unstarted(&id, &e).await;
                }
            }
        }
    }

    async fn launch(&self, id: &str) -> Result<()> {
        let record =
            self.inner.store.meta.get_job(id).await?.ok_or_else(|| Error::NotFound(format!("job '{id}' not found")))?;
        if record.state.is_terminal() {
            lock(&self.inner.live).remove(id);
            return Ok(());
        }
        let spec: JobSpec = serde_json::from_value(record.spec.clone())
            .map_err(|e| Error::DataLoss(format!("job '{id}' has an unreadable spec: {e}")))?;
        let live =
            lock(&self.inner.live).get(id).cloned().ok_or_else(|| Error::internal("jobs", "job without live entry"))?;
        let ctx = JobContext::new(
            record,
            spec,
            self.inner.store.clone(),
            self.inner.rt.clone(),
            live.cancel.clone(),
            self.inner.shutdown.clone(),
            live.events.clone(),
        );
        let manager = self.clone();
        let job_id = id.to_owned();
        let handle = std::thread::Builder::new()
            .name(format!("job-{}", &id[..id.len().min(11)]))
            .spawn(move || {
                run_job(ctx);
                lock(&manager.inner.live).remove(&job_id);
                manager.inner.wake.notify_one();
            })
            .map_err(|e| Error::internal("spawning job thread", e))?;
        lock(&self.inner.running).insert(id.to_owned(), handle);
        Ok(())
    }

    /// Records FAILED for a job that could not even start (its stored spec is unreadable, its
    /// thread could not be spawned), so it does not stay PENDING forever.
    async fn fail_unstarted(&self, id: &str, error: &Error) {
        lock(&self.inner.live).remove(id);
        let Ok(Some(mut record)) = self.inner.store.meta.get_job(id).await else { return };
        if record.state.is_terminal() {
            return;
        }
        record.state = JobState::Failed;
        record.error = format!("could not start: {error}");
        record.finished_at_ms = Some(now_ms());
        record.last_seq += 1;
        let event = JobEvent {
            seq: record.last_seq,
            time_ms: now_ms(),
            event: JobEventKind::State { state: JobState::Failed, message: record.error.clone() },
        };
        if let Err(e) = self.inner.store.meta.record_job(&record, &[event]).await {
            tracing::error!(job = id, error = %e, "could not record the job's failure");
        }
    }

    /// Validates and queues a job. With a client-chosen id, resubmitting the same spec returns
    /// the existing job; a different spec under that id is ALREADY_EXISTS.
    pub async fn submit(&self, id: Option<String>, spec: JobSpec) -> Result<JobRecord> {
        spec.validate()?;
        let id = match id {
            Some(id) => {
                validate_name("job_id", &id)?;
                if let Some(existing) = self.inner.store.meta.get_job(&id).await? {
                    let same = serde_json::to_value(&spec).ok().as_ref() == Some(&existing.spec);
                    return if same {
                        Ok(existing)
                    } else {
                        Err(Error::AlreadyExists(format!("job '{id}' already exists with a different spec")))
                    };
                }
                id
            }
            None => format!("job-{}", &uuid::Uuid::new_v4().simple().to_string()[..12]),
        };
        validate_name("spec.output_model", &spec.output_model)?;
        if self.inner.store.meta.get_model(&spec.output_model).await?.is_some() {
            return Err(Error::AlreadyExists(format!(
                "spec.output_model: model '{}' already exists",
                spec.output_model
            )));
        }
        match &spec.kind {
            JobKind::Diffusion(d) => diffusion::validate_inputs(&self.inner.store, d).await?,
            JobKind::Reward(r) => reward::validate_inputs(&self.inner.store, r).await?,
            JobKind::Discriminator(d) => reward::validate_discriminator(&self.inner.store, d).await?,
        }
        let queued = lock(&self.inner.queue).len();
        if queued >= self.inner.config.queue_capacity {
            return Err(Error::ResourceExhausted(format!(
                "the job queue is full ({queued} jobs waiting, jobs.queue_capacity = {})",
                self.inner.config.queue_capacity
            )));
        }
        let record = JobRecord {
            id: id.clone(),
            kind: spec.kind.name().to_owned(),
            spec: serde_json::to_value(&spec).map_err(|e| Error::internal("encoding spec", e))?,
            state: JobState::Pending,
            step: 0,
            total_steps: spec.optimization.steps,
            loss: None,
            error: String::new(),
            created_at_ms: now_ms(),
            started_at_ms: None,
            finished_at_ms: None,
            last_seq: 1,
            checkpoint: None,
            inputs: spec.inputs(),
            output_model: spec.output_model.clone(),
        };
        let first = JobEvent {
            seq: 1,
            time_ms: record.created_at_ms,
            event: JobEventKind::State { state: JobState::Pending, message: "queued".into() },
        };
        // The job and its first event appear together: a watcher never sees a job without it.
        self.inner.store.meta.insert_job(&record, &[first]).await?;
        self.enqueue(&id);
        tracing::info!(job = id, kind = record.kind, "job submitted");
        Ok(record)
    }

    pub async fn get(&self, id: &str) -> Result<JobRecord> {
        validate_name("id", id)?;
        self.inner.store.meta.get_job(id).await?.ok_or_else(|| Error::NotFound(format!("job '{id}' not found")))
    }

    pub async fn list(&self, state: Option<JobState>, after: i64, limit: usize) -> Result<Vec<(i64, JobRecord)>> {
        self.inner.store.meta.list_jobs(state, after, limit).await
    }

    /// Cancels a job: a PENDING job becomes CANCELLED at once; a RUNNING job stops at its next
    /// step (this waits briefly for that). Cancelling a finished job is FAILED_PRECONDITION.
    pub async fn cancel(&self, id: &str) -> Result<JobRecord> {
        let record = self.get(id).await?;
        if record.state.is_terminal() {
            return Err(Error::FailedPrecondition(format!("job '{id}' already finished ({})", record.state.as_str())));
        }
        let live = lock(&self.inner.live).get(id).cloned();
        let was_queued = {
            let mut q = lock(&self.inner.queue);
            let before = q.len();
            q.retain(|j| j != id);
            q.len() != before
        };
        if was_queued {
            let mut next = record.clone();
            next.state = JobState::Cancelled;
            next.finished_at_ms = Some(now_ms());
            next.last_seq += 1;
            let event = JobEvent {
                seq: next.last_seq,
                time_ms: now_ms(),
                event: JobEventKind::State {
                    state: JobState::Cancelled,
                    message: "cancelled before it started".into(),
                },
            };
            self.inner.store.meta.record_job(&next, std::slice::from_ref(&event)).await?;
            if let Some(live) = lock(&self.inner.live).remove(id) {
                let _ = live.events.send(event);
            }
            return Ok(next);
        }
        if let Some(live) = live {
            live.cancel.cancel();
        }
        for _ in 0..50 {
            let current = self.get(id).await?;
            if current.state.is_terminal() {
                return Ok(current);
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        self.get(id).await
    }

    /// A non-terminal job that reads `name` (a dataset or model), if any.
    pub async fn job_using(&self, name: &str) -> Result<Option<String>> {
        let active = self.inner.store.meta.jobs_in_states(&[JobState::Pending, JobState::Running]).await?;
        Ok(active.into_iter().find(|j| j.inputs.iter().any(|i| i == name)).map(|j| j.id))
    }

    /// Events from `from_seq` on: first those recorded, then live ones, until the job is in a
    /// terminal state and every event has been sent. Never blocks the job: a watcher that
    /// falls behind the live buffer re-reads from the store.
    pub async fn watch(
        &self,
        id: &str,
        from_seq: u64,
    ) -> Result<impl Stream<Item = Result<JobEvent>> + Send + 'static> {
        self.get(id).await?;
        let manager = self.clone();
        let id = id.to_owned();
        let (tx, rx) = tokio::sync::mpsc::channel(64);
        tokio::spawn(async move {
            if let Err(e) = manager.follow(&id, from_seq.max(1), &tx).await {
                let _ = tx.send(Err(e)).await;
            }
        });
        Ok(tokio_stream::wrappers::ReceiverStream::new(rx))
    }

    async fn follow(&self, id: &str, mut next: u64, tx: &tokio::sync::mpsc::Sender<Result<JobEvent>>) -> Result<()> {
        loop {
            // Subscribe before reading the store, so nothing recorded in between is missed.
            let mut live = lock(&self.inner.live).get(id).map(|l| l.events.subscribe());
            loop {
                let page = self.inner.store.meta.job_events(id, next, REPLAY_PAGE).await?;
                let n = page.len();
                for e in page {
                    next = e.seq + 1;
                    if tx.send(Ok(e)).await.is_err() {
                        return Ok(()); // the watcher left
                    }
                }
                if n < REPLAY_PAGE {
                    break;
                }
            }
            let job = self.get(id).await?;
            if job.state.is_terminal() && next > job.last_seq {
                return Ok(());
            }
            match live.as_mut() {
                Some(rx) => loop {
                    tokio::select! {
                        () = tx.closed() => return Ok(()),
                        () = self.inner.shutdown.cancelled() => return Err(Error::Unavailable("the server is shutting down".into())),
                        received = rx.recv() => match received {
                            Ok(e) if e.seq < next => {}
                            Ok(e) if e.seq == next => {
                                next += 1;
                                let terminal = matches!(e.event, JobEventKind::State { state, .. } if state.is_terminal());
                                if tx.send(Ok(e)).await.is_err() {
                                    return Ok(());
                                }
                                if terminal {
                                    return Ok(());
                                }
                            }
                            // A gap (lagged or out of order): replay from the store.
                            Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => break,
                            Err(broadcast::error::RecvError::Closed) => break,
                        }
                    }
                },
                // Not live in this process (e.g. just finished): poll the store.
                None => {
                    tokio::select! {
                        () = tx.closed() => return Ok(()),
                        () = self.inner.shutdown.cancelled() => return Err(Error::Unavailable("the server is shutting down".into())),
                        () = tokio::time::sleep(Duration::from_millis(250)) => {}
                    }
                }
            }
        }
    }

    /// Stops every running job at its next step (they stay RUNNING and resume at the next
    /// start) and waits for their threads, at most `grace`.
    pub async fn shutdown(&self, grace: Duration) {
        self.inner.shutdown.cancel();
        let handles: Vec<_> = lock(&self.inner.running).drain().collect();
        let deadline = tokio::time::Instant::now() + grace;
        for (id, h) in handles {
            while !h.is_finished() && tokio::time::Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            if !h.is_finished() {
                tracing::warn!(job = id, "job did not stop within the grace period");
            }
        }
    }
}

/// The body of a job thread: RUNNING, run the kind's runner, then the terminal state (or,
/// when interrupted by shutdown, nothing: the job stays RUNNING and resumes later).
fn run_job(mut ctx: JobContext) {
    let id = ctx.id().to_owned();
    let resumed = ctx.record().state == JobState::Running;
    let message = if resumed { format!("resumed at step {}", ctx.record().step) } else { "started".to_owned() };
    let started = ctx.update(
        |r| {
            r.state = JobState::Running;
            r.started_at_ms.get_or_insert_with(now_ms);
        },
        vec![JobEventKind::State { state: JobState::Running, message }],
    );
    let outcome = match started {
        Err(e) => Err(Stop::Failed(e)),
        Ok(()) => {
            let kind = ctx.spec.kind.clone();
            // A panic in a runner is a bug; contain it to this job rather than the process.
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match &kind {
                JobKind::Diffusion(d) => diffusion::run(&mut ctx, d),
                JobKind::Reward(r) => reward::run(&mut ctx, r),
                JobKind::Discriminator(d) => reward::run_discriminator(&mut ctx, d),
            }))
            .unwrap_or_else(|_| Err(Stop::Failed(Error::internal("job runner", "panicked"))))
        }
    };
    let (state, message, error) = match outcome {
        Ok(msg) => (JobState::Succeeded, msg, String::new()),
        Err(Stop::Cancelled) => (JobState::Cancelled, "cancelled".to_owned(), String::new()),
        Err(Stop::Interrupted) => {
            tracing::info!(
                job = id,
                step = ctx.record().step,
                "job interrupted by shutdown; it resumes at the next start"
            );
            return;
        }
        Err(Stop::Failed(e)) => {
            let text = match &e {
                Error::Internal(inner) => format!("internal error: {inner:#}"),
                other => other.to_string(),
            };
            (JobState::Failed, text.clone(), text)
        }
    };
    tracing::info!(job = id, state = state.as_str(), "job finished");
    // A finished job never resumes: its checkpoints are released with the terminal state
    // (record first, files after, so a crash in between leaves only collectable files).
    let checkpoints = ctx.record().checkpoint.clone();
    let finished = ctx.update(
        |r| {
            r.state = state;
            r.error = error;
            r.finished_at_ms = Some(now_ms());
            r.checkpoint = None;
        },
        vec![JobEventKind::State { state, message }],
    );
    match finished {
        Ok(()) => ctx.remove_checkpoints(checkpoints),
        Err(e) => tracing::error!(job = id, error = %e, "could not record the job's final state"),
    }
}
