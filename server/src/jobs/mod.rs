//! The job system, shared by every kind of training job: submission with idempotent ids, a
//! bounded queue, a configured number of jobs running at once (each on its own named OS
//! thread checking a cancellation token every step), durable events with sequence numbers,
//! replay-then-follow watching, checkpoints, cancellation, and resumption after a restart.
//!
//! The queue is the metadata store: a submitted job is a PENDING record, and a worker process
//! (role "work" or "all") claims jobs with a lease it renews while the job runs
//! ([`crate::store::MetadataStore::claim_job`]). So with the shared backend any replica can
//! take a submission, any worker runs it (exactly one at a time: a worker whose lease was taken
//! over can no longer write), a worker that dies loses its jobs to another worker once their
//! leases lapse, and cancellation reaches the worker through the store. Watching replays the
//! store and then follows live events when the job runs in this process, or polls the store
//! when it runs elsewhere.
//!
//! Module map:
//! - The stored, fully explicit job specification is the shared schema's
//!   (`relreward_proto::schema::job::JobSpec`: its defaults and checks, one definition).
//! - [`context`]: [`context::JobContext`], what a running job may do.
//! - [`datasets`]: stored datasets read back as training rows and windows.
//! - [`training`]: [`training::TrainLoop`], the optimisation loop every runner shares.
//! - [`diffusion`]: the diffusion-training runner.
//! - [`reward`]: the relative-reward runner (Algorithm 1).
//!
//! State machine: PENDING -> RUNNING -> SUCCEEDED | FAILED | CANCELLED, and PENDING ->
//! CANCELLED. The store refuses any way out of a terminal state. A RUNNING job whose worker
//! stopped or crashed is claimed again and resumes from its checkpoint.

pub mod context;
pub mod datasets;
pub mod diffusion;
pub mod reward;
pub mod training;

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::Stream;
use tokio::sync::{Notify, broadcast};
use tokio_util::sync::CancellationToken;

use self::context::{JobContext, Stop};
use crate::config::JobsConfig;
use crate::error::{Error, Result};
use crate::fields::validate_name;
use crate::store::ingest::now_ms;
use crate::store::{JobEvent, JobEventKind, JobRecord, JobState, Lease, Store};
use crate::tasks::Tasks;
use relreward_proto::schema::job::{JobKind, JobSpec};

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
    /// This process's name in job leases and events: host, pid and a random suffix, unique
    /// per start.
    owner: String,
    wake: Notify,
    /// Jobs running in this process: their cancel token and live event channel.
    live: Mutex<HashMap<String, Live>>,
    running: Mutex<HashMap<String, std::thread::JoinHandle<()>>>,
    /// The job system's group of the server's background work: its token is the shutdown
    /// signal every job, watcher and dispatcher sees; its tracker counts them all.
    tasks: Tasks,
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
    /// Starts the job system. With `work`, this process also runs jobs: a dispatcher claims
    /// queued jobs, and jobs interrupted by a previous process are resumed (with the embedded
    /// store at once, its leases broken by `Store::open`; with the shared store once their
    /// leases lapse).
    pub async fn start(store: Store, config: JobsConfig, work: bool, tasks: Tasks) -> Result<Self> {
        let inner = Arc::new(Inner {
            store,
            config,
            rt: tokio::runtime::Handle::current(),
            owner: process_name(),
            wake: Notify::new(),
            live: Mutex::new(HashMap::new()),
            running: Mutex::new(HashMap::new()),
            shutdown: tasks.token().clone(),
            tasks,
        });
        let manager = Self { inner };
        if work {
            tracing::info!(
                worker = manager.inner.owner,
                max_concurrent = manager.inner.config.max_concurrent,
                "running jobs"
            );
            let dispatcher = manager.clone();
            manager.inner.tasks.spawn(async move { dispatcher.dispatch().await });
        }
        Ok(manager)
    }

    fn lease(&self) -> Duration {
        Duration::from_secs(self.inner.config.lease_secs)
    }

    /// Claims queued jobs while fewer than `max_concurrent` run here; looks again when woken
    /// (a job was submitted here or finished) and every `jobs.poll_ms`.
    async fn dispatch(self) {
        let poll = Duration::from_millis(self.inner.config.poll_ms);
        loop {
            lock(&self.inner.running).retain(|_, h| !h.is_finished());
            while !self.inner.shutdown.is_cancelled()
                && lock(&self.inner.running).len() < self.inner.config.max_concurrent
            {
                match self.inner.store.meta.claim_job(&self.inner.owner, self.lease()).await {
                    Ok(Some(record)) => {
                        let id = record.id.clone();
                        if let Err(e) = self.launch(record).await {
                            tracing::error!(job = id, error = %e, "could not start job");
                            self.fail_unstarted(&id, &e).await;
                        }
                    }
                    Ok(None) => break,
                    Err(e) => {
                        tracing::warn!(error = %e, "cannot claim jobs; trying again");
                        break;
                    }
                }
            }
            tokio::select! {
                () = self.inner.wake.notified() => {}
                () = self.inner.shutdown.cancelled() => return,
                () = tokio::time::sleep(poll) => {}
            }
        }
    }

    /// Runs a claimed job on its own thread, with a task renewing its lease.
    async fn launch(&self, record: JobRecord) -> Result<()> {
        let id = record.id.clone();
        let spec: JobSpec = serde_json::from_value(record.spec.clone())
            .map_err(|e| Error::DataLoss(format!("job '{id}' has an unreadable spec: {e}")))?;
        let (events, _) = broadcast::channel(LIVE_BUFFER);
        let live = Live { cancel: CancellationToken::new(), events };
        // Stops the job like a shutdown does when another worker took it over.
        let lost = CancellationToken::new();
        let ctx = JobContext::new(
            record,
            spec,
            self.inner.store.clone(),
            self.inner.rt.clone(),
            self.inner.owner.clone(),
            live.cancel.clone(),
            self.inner.shutdown.clone(),
            lost.clone(),
            live.events.clone(),
        );
        lock(&self.inner.live).insert(id.clone(), live.clone());
        let finished = CancellationToken::new();
        self.inner.tasks.spawn(self.clone().keep_lease(id.clone(), live.cancel.clone(), lost, finished.clone()));
        let manager = self.clone();
        let job_id = id.clone();
        let tracked = self.inner.tasks.enlist();
        let spawned = std::thread::Builder::new().name(format!("job-{}", &id[..id.len().min(11)])).spawn(move || {
            let _tracked = tracked;
            let released = run_job(ctx);
            finished.cancel();
            if released {
                // Interrupted (shutdown): hand the job over at once rather than at lease expiry.
                let store = manager.inner.store.clone();
                if let Err(e) = manager.inner.rt.block_on(store.meta.release_lease(&job_id, &manager.inner.owner)) {
                    tracing::warn!(job = job_id, error = %e, "could not release the lease; it lapses instead");
                }
            }
            lock(&manager.inner.live).remove(&job_id);
            manager.inner.wake.notify_one();
        });
        match spawned {
            Ok(handle) => {
                lock(&self.inner.running).insert(id, handle);
                Ok(())
            }
            Err(e) => {
                lock(&self.inner.live).remove(&id);
                Err(Error::internal("spawning job thread", e))
            }
        }
    }

    /// Renews a running job's lease until it finishes: every second, or lease/5 if shorter.
    /// A requested cancellation cancels the job; a lost lease stops it without a write.
    async fn keep_lease(
        self,
        id: String,
        cancel: CancellationToken,
        lost: CancellationToken,
        finished: CancellationToken,
    ) {
        let lease = self.lease();
        let mut every = tokio::time::interval((lease / 5).min(Duration::from_secs(1)));
        every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                () = finished.cancelled() => return,
                _ = every.tick() => {}
            }
            match self.inner.store.meta.renew_lease(&id, &self.inner.owner, lease).await {
                Ok(Lease::Held { cancel_requested }) => {
                    if cancel_requested {
                        cancel.cancel();
                    }
                }
                Ok(Lease::Lost) => {
                    // The job's own thread ends the lease when it records the final state, a
                    // moment before it signals `finished`: that is not a takeover.
                    // (Stopping is harmless then, and right if another worker finished it.)
                    let ended =
                        matches!(self.inner.store.meta.get_job(&id).await, Ok(Some(r)) if r.state.is_terminal());
                    if finished.is_cancelled() || ended {
                        tracing::debug!(job = id, "lease ended with the job");
                        lost.cancel();
                        return;
                    }
                    tracing::warn!(job = id, "lease lost: another worker runs this job now; stopping here");
                    lost.cancel();
                    return;
                }
                // The store is unreachable: keep computing and retrying. If the lease lapses
                // meanwhile, another worker may take over, and this one's writes are refused.
                Err(e) => tracing::warn!(job = id, error = %e, "cannot renew the job's lease"),
            }
        }
    }

    /// Records FAILED for a job that could not even start (its stored spec is unreadable, its
    /// thread could not be spawned), so it does not stay PENDING forever.
    async fn fail_unstarted(&self, id: &str, error: &Error) {
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
        if let Err(e) = self.inner.store.meta.record_job(&record, &[event], Some(&self.inner.owner)).await {
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
        // From the inputs' lookups to the job's record: a deletion of one of them waits, then
        // sees the job.
        let _references = self.inner.store.references().await;
        match &spec.kind {
            JobKind::Diffusion(d) => diffusion::validate_inputs(&self.inner.store, d).await?,
            JobKind::Reward(r) => reward::validate_inputs(&self.inner.store, r).await?,
            JobKind::Discriminator(d) => reward::validate_discriminator(&self.inner.store, d).await?,
        }
        let counts = self.inner.store.meta.count_jobs_by_state().await?;
        let queued = counts.iter().find(|(s, _)| *s == JobState::Pending).map_or(0, |(_, n)| *n);
        if queued >= self.inner.config.queue_capacity as u64 {
            return Err(Error::ResourceExhausted(format!(
                "the job queue is full ({queued} jobs waiting, jobs.queue_capacity = {})",
                self.inner.config.queue_capacity
            )));
        }
        let (record, first) = pending_record(id.clone(), &spec)?;
        // The job and its first event appear together: a watcher never sees a job without it.
        self.inner.store.meta.insert_job(&record, &[first]).await?;
        self.inner.wake.notify_one();
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

    /// Cancels a job: a queued job becomes CANCELLED at once; a running one stops at its next
    /// step, wherever it runs (its worker sees the request when renewing its lease; this waits
    /// a few seconds for that). Cancelling a finished job is FAILED_PRECONDITION.
    pub async fn cancel(&self, id: &str) -> Result<JobRecord> {
        let record = self.get(id).await?;
        if record.state.is_terminal() {
            return Err(Error::FailedPrecondition(format!("job '{id}' already finished ({})", record.state.as_str())));
        }
        if record.state == JobState::Pending {
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
            // Refused if a worker claimed it meanwhile: then it is cancelled as a running job.
            match self.inner.store.meta.record_job(&next, std::slice::from_ref(&event), None).await {
                Ok(()) => return Ok(next),
                Err(Error::FailedPrecondition(_)) => {}
                Err(e) => return Err(e),
            }
        }
        self.inner.store.meta.request_cancel(id).await?;
        if let Some(live) = lock(&self.inner.live).get(id) {
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

    /// Events from `from_seq` on (0 and 1 both mean the first; beyond the last event, the next
    /// one): first those recorded, then live ones, until the job is in a terminal state and
    /// every event has been sent. Never blocks the job: a watcher that
    /// falls behind the live buffer re-reads from the store.
    pub async fn watch(
        &self,
        id: &str,
        from_seq: u64,
    ) -> Result<impl Stream<Item = Result<JobEvent>> + Send + 'static> {
        let job = self.get(id).await?;
        // A from_seq beyond the last event follows live from the next one: a client resuming
        // with a stale or made-up number waits for what comes, it never replays from 1.
        let from_seq = from_seq.clamp(1, job.last_seq.saturating_add(1));
        let manager = self.clone();
        let id = id.to_owned();
        let (tx, rx) = tokio::sync::mpsc::channel(64);
        self.inner.tasks.spawn(async move {
            if let Err(e) = manager.follow(&id, from_seq, &tx).await {
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
        // The dispatcher, lease keepers and watchers end with their jobs or at the token.
        self.inner.tasks.stop(deadline.saturating_duration_since(tokio::time::Instant::now())).await;
    }
}

/// This process's name in leases and job events: `host/pid/random`, so a log line or an event
/// tells which pod ran a job, and a restarted process never passes for its predecessor.
fn process_name() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_owned())
        .ok()
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "localhost".to_owned());
    let suffix = &uuid::Uuid::new_v4().simple().to_string()[..6];
    format!("{host}/{}/{suffix}", std::process::id())
}

/// A submitted job's record, PENDING, and its first event (sequence number 1), which the store
/// inserts together.
fn pending_record(id: String, spec: &JobSpec) -> Result<(JobRecord, JobEvent)> {
    let record = JobRecord {
        id,
        kind: spec.kind.name().to_owned(),
        spec: serde_json::to_value(spec).map_err(|e| Error::internal("encoding spec", e))?,
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
    Ok((record, first))
}

/// The body of a job thread: RUNNING, run the kind's runner, then the terminal state. When
/// halted (shutdown, or the lease was lost) it records nothing more: the job stays RUNNING
/// and resumes on the next worker to claim it. Returns true when halted by shutdown, i.e.
/// when the lease is still this process's to release.
fn run_job(mut ctx: JobContext) -> bool {
    let id = ctx.id().to_owned();
    let resumed = ctx.record().state == JobState::Running;
    let worker = ctx.owner().to_owned();
    let message = if resumed {
        // The step training goes on from is its latest recorded checkpoint's (0 without one),
        // not the last progress before the interruption: the steps after the checkpoint are
        // trained again. (Should that checkpoint prove corrupt, the runner falls back to the
        // previous one and its log says so: "resumed from the checkpoint at step N".)
        let progress = ctx.record().step;
        match ctx.record().checkpoint.as_ref().map(|c| c.step) {
            Some(step) => format!(
                "resumed at step {step} on {worker} (its latest checkpoint; progress had reached step {progress})"
            ),
            None => format!(
                "resumed at step 0 on {worker} (no checkpoint was recorded; progress had reached step {progress})"
            ),
        }
    } else {
        format!("started on {worker}")
    };
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
    // The last progress write lands before anything else happens to the job; had it failed in
    // line, the runner would have failed with it.
    let outcome = match (ctx.settle(), outcome) {
        (Err(e), Ok(_)) => Err(Stop::Failed(e)),
        (Err(e), stopped) => {
            tracing::warn!(job = id, error = %e, "the job's last progress event was not recorded");
            stopped
        }
        (Ok(()), outcome) => outcome,
    };
    if ctx.lease_lost() {
        // Whatever the runner ended with, another worker owns the job now.
        tracing::info!(job = id, step = ctx.record().step, "job handed over to another worker");
        return false;
    }
    let (state, message, error) = match outcome {
        Ok(msg) => (JobState::Succeeded, msg, String::new()),
        Err(Stop::Cancelled) => (JobState::Cancelled, "cancelled".to_owned(), String::new()),
        Err(Stop::Interrupted) => {
            tracing::info!(
                job = id,
                step = ctx.record().step,
                "job interrupted by shutdown; it resumes on the next worker to claim it"
            );
            return true;
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
    false
}
