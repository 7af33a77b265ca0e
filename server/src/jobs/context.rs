//! What a running job sees: its spec, stop signals, and the durable side effects it may
//! cause (progress events, checkpoints, logs, the registration of its output model).
//!
//! A job runs on its own OS thread; this context bridges to the async store with the
//! runtime handle. Every event is written to the metadata store before it is broadcast to
//! live watchers, so a watcher that replays from the store and then follows live events sees
//! each sequence number exactly once.
//!
//! Progress is written behind the job: the write (a transaction the embedded store commits
//! with an fsync, a round trip with the shared one) runs on the runtime while training goes
//! on, and the next write of any kind (a checkpoint's and a model's registration included)
//! waits for it first, so events stay in order and a failed progress write fails the job at
//! its next write, before anything else is stored, as it did when written in line. (A job
//! already cancelled or interrupted by then keeps that outcome, the error logged.)
//! Written in line, the embedded store's commits every `log_every` = 10 steps took about a
//! tenth of a small reward's training time on this project's two-core machine.

use std::path::PathBuf;
use std::time::Instant;

use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;

use crate::error::{Error, Result};
use crate::store::ingest::now_ms;
use crate::store::{CheckpointRef, JobEvent, JobEventKind, JobRecord, ModelRecord, Staging, Store};
use relreward_proto::schema::job::JobSpec;

/// Why a job stopped without finishing.
#[derive(Debug)]
pub enum Stop {
    /// A user cancelled it: the job ends CANCELLED.
    Cancelled,
    /// The server is shutting down, or another worker took the job over: the job stays
    /// RUNNING and resumes on the next worker to claim it.
    Interrupted,
    /// It failed: the job ends FAILED with this error.
    Failed(Error),
}

impl From<Error> for Stop {
    fn from(e: Error) -> Self {
        Self::Failed(e)
    }
}

impl From<std::io::Error> for Stop {
    fn from(e: std::io::Error) -> Self {
        Self::Failed(e.into())
    }
}

impl From<tch::TchError> for Stop {
    fn from(e: tch::TchError) -> Self {
        Self::Failed(Error::internal("tensor operation", e))
    }
}

/// One optimisation step's figures, as a runner reports them.
#[derive(Debug, Clone, Copy)]
pub struct StepReport {
    pub step: u64,
    pub loss: f64,
    pub grad_norm: f64,
    pub learning_rate: f64,
    pub eval_loss: Option<f64>,
}

pub struct JobContext {
    pub spec: JobSpec,
    record: JobRecord,
    store: Store,
    rt: tokio::runtime::Handle,
    /// The lease holder's name: every record write is made in it.
    owner: String,
    cancel: CancellationToken,
    shutdown: CancellationToken,
    /// Cancelled when another worker took the job over (see `JobManager::keep_lease`).
    lost: CancellationToken,
    live: broadcast::Sender<JobEvent>,
    /// Rate measurement: (instant, step) at the start of this run (after a resume, too).
    started: (Instant, u64),
    /// The progress write still in flight, if any (module doc).
    behind: Option<BehindWrite>,
}

/// A progress write running on the runtime, and the record as it was before it (restored if
/// the write fails, so the next event takes the sequence number the failed one had).
struct BehindWrite {
    task: tokio::task::JoinHandle<Result<()>>,
    before: JobRecord,
}

impl JobContext {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new(
        record: JobRecord,
        spec: JobSpec,
        store: Store,
        rt: tokio::runtime::Handle,
        owner: String,
        cancel: CancellationToken,
        shutdown: CancellationToken,
        lost: CancellationToken,
        live: broadcast::Sender<JobEvent>,
    ) -> Self {
        let step = record.step;
        Self {
            spec,
            record,
            store,
            rt,
            owner,
            cancel,
            shutdown,
            lost,
            live,
            started: (Instant::now(), step),
            behind: None,
        }
    }

    /// The worker (process) running this job.
    pub fn owner(&self) -> &str {
        &self.owner
    }

    /// Another worker took the job over: this one must stop and write nothing more.
    pub(super) fn lease_lost(&self) -> bool {
        self.lost.is_cancelled()
    }

    pub fn id(&self) -> &str {
        &self.record.id
    }

    pub fn record(&self) -> &JobRecord {
        &self.record
    }

    pub fn store(&self) -> &Store {
        &self.store
    }

    /// Runs an async store call from the job thread.
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.rt.block_on(f)
    }

    /// Called by runners between steps: a cancellation or shutdown stops the job here.
    pub fn check_stop(&self) -> std::result::Result<(), Stop> {
        if self.cancel.is_cancelled() {
            Err(Stop::Cancelled)
        } else if self.shutdown.is_cancelled() || self.lost.is_cancelled() {
            Err(Stop::Interrupted)
        } else {
            Ok(())
        }
    }

    /// Appends events durably (with the updated record) and then broadcasts them.
    pub(super) fn emit(&mut self, kinds: Vec<JobEventKind>) -> Result<()> {
        self.settle()?;
        let (next, events) = self.next_record(kinds);
        self.rt.block_on(self.store.meta.record_job(&next, &events, Some(&self.owner)))?;
        self.record = next;
        for e in events {
            // No receiver is fine; a lagging receiver re-reads from the store.
            let _ = self.live.send(e);
        }
        Ok(())
    }

    /// The record with `kinds` appended as the next events, and those events.
    fn next_record(&self, kinds: Vec<JobEventKind>) -> (JobRecord, Vec<JobEvent>) {
        let time_ms = now_ms();
        let events: Vec<JobEvent> = kinds
            .into_iter()
            .enumerate()
            .map(|(i, event)| JobEvent { seq: self.record.last_seq + 1 + i as u64, time_ms, event })
            .collect();
        let mut next = self.record.clone();
        next.last_seq += events.len() as u64;
        (next, events)
    }

    /// Waits for the progress write in flight, if any: its error is this write's (the record
    /// restored to before it).
    pub(super) fn settle(&mut self) -> Result<()> {
        let Some(BehindWrite { task, before }) = self.behind.take() else { return Ok(()) };
        let written = match self.rt.block_on(task) {
            Ok(written) => written,
            // The task was dropped (the runtime shutting down) or panicked: whether its
            // transaction committed is the store's to say (the embedded store's blocking call
            // runs to its end either way), so a later event never reuses a stored number.
            Err(e) => match self.rt.block_on(self.store.meta.get_job(&self.record.id)) {
                Ok(Some(stored)) if stored.last_seq == self.record.last_seq => Ok(()),
                _ => Err(Error::internal("job progress write", e)),
            },
        };
        if written.is_err() {
            self.record = before;
        }
        written
    }

    /// Updates the record (state, timestamps, ...) together with events.
    pub(super) fn update(&mut self, f: impl FnOnce(&mut JobRecord), kinds: Vec<JobEventKind>) -> Result<()> {
        self.settle()?;
        let saved = self.record.clone();
        f(&mut self.record);
        if let Err(e) = self.emit(kinds) {
            self.record = saved;
            return Err(e);
        }
        Ok(())
    }

    /// Whether step `step`'s progress is written whatever it evaluated: the first, every
    /// `log_every`-th and the last.
    pub fn reports_at(&self, step: u64) -> bool {
        let o = &self.spec.optimization;
        step == 1 || step.is_multiple_of(o.log_every) || step == o.steps
    }

    /// Records a step. Progress events are written every `log_every` steps, at the first and
    /// the last step and whenever a held-out loss was evaluated; the record's step and loss
    /// follow. The write runs behind the job (module doc): its error is the next write's.
    pub fn progress(&mut self, r: StepReport) -> Result<()> {
        let total = self.spec.optimization.steps;
        if !(self.reports_at(r.step) || r.eval_loss.is_some()) {
            return Ok(());
        }
        let elapsed = self.started.0.elapsed().as_secs_f64();
        let done = r.step.saturating_sub(self.started.1) as f64;
        let rate = if elapsed > 0.0 { done / elapsed } else { 0.0 };
        let eta = if rate > 0.0 { (total.saturating_sub(r.step)) as f64 / rate } else { 0.0 };
        let event = JobEventKind::Progress {
            step: r.step,
            total_steps: total,
            loss: r.loss,
            grad_norm: r.grad_norm,
            learning_rate: r.learning_rate,
            steps_per_second: rate,
            eta_seconds: eta,
            eval_loss: r.eval_loss,
        };
        // Written behind (module doc): the record moves on now, the write lands meanwhile.
        self.settle()?;
        let (mut next, events) = self.next_record(vec![event]);
        next.step = r.step;
        next.loss = Some(r.loss);
        let before = std::mem::replace(&mut self.record, next.clone());
        let (store, owner, live) = (self.store.clone(), self.owner.clone(), self.live.clone());
        let task = self.rt.spawn(async move {
            store.meta.record_job(&next, &events, Some(&owner)).await?;
            for e in events {
                let _ = live.send(e);
            }
            Ok(())
        });
        self.behind = Some(BehindWrite { task, before });
        Ok(())
    }

    pub fn log(&mut self, message: impl Into<String>) -> Result<()> {
        self.emit(vec![JobEventKind::Log { message: message.into() }])
    }

    /// Writes a checkpoint: `write` fills a staging directory, which is published and then
    /// recorded as the job's latest checkpoint in one store transaction. The checkpoint it
    /// replaces stays as `previous` (the fallback if the new one is ever found corrupt); only
    /// the one before that is removed, after the record is committed. A crash at any point
    /// leaves the recorded checkpoints intact; unrecorded files are collected at next start.
    pub fn checkpoint(&mut self, step: u64, write: impl FnOnce(&std::path::Path) -> Result<()>) -> Result<()> {
        self.settle()?;
        let staging = self.store.blobs.staging()?;
        write(staging.path())?;
        crate::fault::point("checkpoint.before_publish");
        let key = format!("checkpoints/{}", uuid::Uuid::new_v4().simple());
        self.rt.block_on(self.store.blobs.publish(staging, &key))?;
        crate::fault::point("checkpoint.after_publish");
        let saved = self.record.checkpoint.clone();
        let (previous, released) = match self.record.checkpoint.take() {
            Some(mut latest) => {
                let released = latest.previous.take();
                (Some(Box::new(latest)), released)
            }
            None => (None, None),
        };
        let new = CheckpointRef { blob_key: key.clone(), step, previous };
        let result = self.update(
            |rec| {
                rec.checkpoint = Some(new);
                rec.step = step;
            },
            vec![JobEventKind::Checkpoint { step }],
        );
        match result {
            Ok(()) => {
                crate::fault::point("checkpoint.after_record");
                if let Some(old) = released {
                    self.remove_checkpoint(&old.blob_key);
                }
                Ok(())
            }
            Err(e) => {
                self.record.checkpoint = saved;
                let _ = self.rt.block_on(self.store.blobs.remove(&key));
                Err(e)
            }
        }
    }

    fn remove_checkpoint(&self, key: &str) {
        if let Err(e) = self.rt.block_on(self.store.blobs.remove(key)) {
            tracing::warn!(job = self.record.id, key, error = %e, "old checkpoint not removed; removed at next start");
        }
    }

    /// The job's newest intact checkpoint, as its step and local directory, each candidate
    /// checked against its digest list (the latest, then its fallback). A corrupt one is
    /// logged, reported as a job log event and dropped from the record (its files removed),
    /// so later checkpoints never keep it as their fallback. `DataLoss` if the job has
    /// checkpoints and none is intact: the job must not silently start over.
    pub fn intact_checkpoint(&mut self) -> Result<Option<(u64, PathBuf)>> {
        let mut candidates = Vec::new();
        if let Some(latest) = &self.record.checkpoint {
            let mut first = latest.clone();
            let previous = first.previous.take();
            candidates.push(first);
            candidates.extend(previous.map(|p| *p));
        }
        let mut first_error = None;
        for (i, candidate) in candidates.iter().enumerate() {
            let dir = self.rt.block_on(self.store.blobs.local_dir(&candidate.blob_key))?;
            let what = format!("job '{}': checkpoint at step {}", self.record.id, candidate.step);
            match crate::store::digests::verify_dir(&dir, &what) {
                Ok(_) if i == 0 => return Ok(Some((candidate.step, dir))),
                Ok(_) => {
                    // The fallback becomes the only checkpoint; the corrupt one goes.
                    let kept = candidate.clone();
                    let message = format!("resuming from the previous checkpoint, at step {}", kept.step);
                    self.update(|r| r.checkpoint = Some(kept), vec![JobEventKind::Log { message }])?;
                    self.remove_checkpoint(&candidates[0].blob_key);
                    return Ok(Some((candidate.step, dir)));
                }
                Err(Error::DataLoss(m)) => {
                    tracing::error!(job = self.record.id, step = candidate.step, blob = candidate.blob_key, "{m}");
                    self.log(format!("{m}; not resuming from it"))?;
                    first_error.get_or_insert(Error::DataLoss(m));
                }
                Err(e) => return Err(e),
            }
        }
        first_error.map_or(Ok(None), Err)
    }

    /// Removes the files of checkpoints the record no longer refers to (a finished job's,
    /// after its terminal state was recorded without them).
    pub(super) fn remove_checkpoints(&self, released: Option<CheckpointRef>) {
        if let Some(latest) = released {
            if let Some(previous) = &latest.previous {
                self.remove_checkpoint(&previous.blob_key);
            }
            self.remove_checkpoint(&latest.blob_key);
        }
    }

    /// A staging directory for the job's output model.
    pub fn staging(&self) -> Result<Staging> {
        self.store.blobs.staging()
    }

    /// Registers the job's output model.
    pub fn register_model(&mut self, staging: Staging, record: ModelRecord) -> Result<ModelRecord> {
        // A progress write that failed (the lease lost meanwhile) stops the job before its
        // model is registered, as it did when written in line.
        self.settle()?;
        let stored = self.rt.block_on(self.store.commit_model(staging, record))?;
        self.log(format!("registered model '{}'", stored.name))?;
        Ok(stored)
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;
    use std::time::Duration;

    use relreward_proto::schema::job::Facts;
    use relreward_proto::v1 as pb;

    use super::*;
    use crate::config::{Config, Overrides};

    /// A job's context over a fresh embedded store, the job leased to "w1" for `lease`; the
    /// store, a live receiver and the runtime (kept alive) beside it.
    fn context(
        dir: &std::path::Path,
        lease: Duration,
    ) -> (JobContext, Store, broadcast::Receiver<JobEvent>, tokio::runtime::Runtime) {
        let rt = tokio::runtime::Runtime::new().expect("runtime");
        let overrides = Overrides { data_dir: Some(dir.join("data")), ..Overrides::default() };
        let env = config::Environment::with_prefix("RELREWARD").source(Some(HashMap::new()));
        let config = Config::load_with_env(None, &overrides, env).expect("config");
        let store = rt.block_on(Store::open(&config)).expect("store");
        let proto = pb::JobSpec {
            output_model: "out".into(),
            kind: Some(pb::job_spec::Kind::Diffusion(pb::TrainDiffusion { dataset: "d".into(), ..Default::default() })),
            ..Default::default()
        };
        let spec = JobSpec::from_proto(proto, &Facts::Dataset { name: "d".into(), trajectories: false }).expect("spec");
        let (record, first) = crate::jobs::pending_record("job-1".into(), &spec).expect("record");
        rt.block_on(store.meta.insert_job(&record, &[first])).expect("insert");
        let claimed = rt.block_on(store.meta.claim_job("w1", lease)).expect("claim").expect("a job to claim");
        let (live, receiver) = broadcast::channel(16);
        let ctx = JobContext::new(
            claimed,
            spec,
            store.clone(),
            rt.handle().clone(),
            "w1".into(),
            CancellationToken::new(),
            CancellationToken::new(),
            CancellationToken::new(),
            live,
        );
        (ctx, store, receiver, rt)
    }

    fn report(step: u64) -> StepReport {
        StepReport { step, loss: step as f64, grad_norm: 1.0, learning_rate: 1e-3, eval_loss: None }
    }

    fn described(e: &JobEvent) -> String {
        match &e.event {
            JobEventKind::Progress { step, .. } => format!("{} progress {step}", e.seq),
            JobEventKind::Log { message } => format!("{} log {message}", e.seq),
            other => format!("{} {other:?}", e.seq),
        }
    }

    /// Progress written behind the job lands in order with the writes after it, in the store
    /// and live, and the record follows every step it reports.
    #[test]
    fn progress_written_behind_keeps_the_events_in_order() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (mut ctx, store, mut live, rt) = context(dir.path(), Duration::from_secs(600));
        ctx.progress(report(1)).expect("progress 1");
        assert_eq!((ctx.record().step, ctx.record().last_seq), (1, 2), "the record moves on at once");
        ctx.progress(report(10)).expect("progress 10");
        ctx.log("a log line").expect("log");
        ctx.progress(report(20)).expect("progress 20");
        ctx.settle().expect("the last write");
        let stored: Vec<String> =
            rt.block_on(store.meta.job_events("job-1", 2, 100)).expect("events").iter().map(described).collect();
        let want = ["2 progress 1", "3 progress 10", "4 log a log line", "5 progress 20"];
        assert_eq!(stored, want);
        let heard: Vec<String> = (0..4).map(|_| described(&live.try_recv().expect("a live event"))).collect();
        assert_eq!(heard, want, "broadcast in the store's order");
        let record = rt.block_on(store.meta.get_job("job-1")).expect("get").expect("the job");
        assert_eq!((record.step, record.loss, record.last_seq), (20, Some(20.0), 5));
    }

    /// A progress write that fails (the lease was lost meanwhile) fails the next write with
    /// its error (a log line; a checkpoint, before it writes anything), and the record is as it
    /// was before it: nothing was stored, and once the job is this worker's again the next event
    /// takes the failed one's sequence number.
    #[test]
    fn a_failed_progress_write_fails_the_next_write_and_leaves_no_gap() {
        for next in ["log", "checkpoint"] {
            let dir = tempfile::tempdir().expect("tempdir");
            let (mut ctx, store, _live, rt) = context(dir.path(), Duration::ZERO);
            // w1's lease lapses at once (expiry is compared in milliseconds, so one passes
            // first): another worker takes the job over.
            std::thread::sleep(Duration::from_millis(5));
            rt.block_on(store.meta.claim_job("w2", Duration::from_secs(600))).expect("claim").expect("the job again");
            ctx.progress(report(1)).expect("written behind: no error yet");
            let mut wrote = false;
            let e = match next {
                "log" => ctx.log("after").expect_err("the failed progress write's error"),
                _ => ctx
                    .checkpoint(1, |_| {
                        wrote = true;
                        Ok(())
                    })
                    .expect_err("the failed progress write's error"),
            };
            assert!(e.to_string().contains("lease on it was lost"), "{next}: {e}");
            assert!(!wrote, "the checkpoint was not written");
            // The queued event is the job's first (sequence number 1).
            let record = (ctx.record().step, ctx.record().last_seq);
            assert_eq!(record, (0, 1), "{next}: the record before the failed write");
            assert!(rt.block_on(store.meta.job_events("job-1", 2, 100)).expect("events").is_empty(), "{next}");
            let stored = rt.block_on(store.meta.get_job("job-1")).expect("get").expect("the job");
            assert!(stored.checkpoint.is_none() && stored.last_seq == 1, "{next}: nothing recorded");
            ctx.settle().expect("nothing in flight any more");
            // The job back with w1: its next event is number 2.
            rt.block_on(store.meta.release_lease("job-1", "w2")).expect("release");
            rt.block_on(store.meta.claim_job("w1", Duration::from_secs(600))).expect("claim").expect("the job");
            ctx.log("again").expect("written");
            let events = rt.block_on(store.meta.job_events("job-1", 0, 100)).expect("events");
            let seqs: Vec<String> = events.iter().map(described).collect();
            assert_eq!(seqs[1..], ["2 log again".to_owned()], "{next}");
        }
    }
}
