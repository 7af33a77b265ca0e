//! Following a job's events across reconnects.
//!
//! `WatchJob` replays a job's recorded events from a sequence number, then follows live ones
//! until the job finishes. Sequence numbers start at 1 and have no gaps, so a watcher whose
//! stream breaks (server restart, network) resumes with `from_seq = last seen + 1` and neither
//! loses nor repeats an event. The pieces:
//!
//! - [`EventCursor`]: the resume bookkeeping (which `from_seq` to ask for, which events are
//!   replays of ones already shown);
//! - [`crate::retry`]: the delays between attempts and which failures are worth a retry;
//! - [`follow`]: the loop over any [`EventSource`]; [`Client::follow_job`] runs it against a
//!   server.

use std::future::Future;
use std::time::Duration;

use futures::{Stream, StreamExt};
use relreward_proto::v1 as pb;
use tonic::Status;

use crate::client::{Client, ClientError};
use crate::retry::{Backoff, RetryPolicy, is_retryable};

/// Which events have been seen, and where to resume.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EventCursor {
    next_seq: u64,
}

impl EventCursor {
    /// A cursor that starts at `from_seq` (0 and 1 both mean the first event).
    pub fn new(from_seq: u64) -> Self {
        Self { next_seq: from_seq.max(1) }
    }

    /// The `from_seq` of the next `WatchJob` call: one past the last event seen.
    pub fn from_seq(&self) -> u64 {
        self.next_seq
    }

    /// The last event seen (0: none yet).
    pub fn last_seq(&self) -> u64 {
        self.next_seq - 1
    }

    /// Records the event numbered `seq`: true if it is new (show it), false for an event
    /// already seen (a replay overlapping what an earlier stream delivered: drop it).
    pub fn accept(&mut self, seq: u64) -> bool {
        if seq < self.next_seq {
            return false;
        }
        self.next_seq = seq.saturating_add(1);
        true
    }
}

/// Whether `state` is final.
pub fn is_terminal(state: pb::JobState) -> bool {
    matches!(state, pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
}

/// The terminal state an event announces, with its message.
pub fn terminal_state(event: &pb::JobEvent) -> Option<(pb::JobState, &str)> {
    match &event.event {
        Some(pb::job_event::Event::State(change)) if is_terminal(change.state()) => {
            Some((change.state(), change.message.as_str()))
        }
        _ => None,
    }
}

/// What [`follow`] reports as it goes.
#[derive(Debug)]
pub enum WatchNotice<'a> {
    /// A new event (never one already reported).
    Event(&'a pb::JobEvent),
    /// The stream failed with a retryable `error`; the next attempt, number `attempt` (from
    /// 1), asks for events from `from_seq` after `delay`.
    Reconnecting { error: &'a Status, from_seq: u64, delay: Duration, attempt: u32 },
    /// A new stream is open, from `from_seq`.
    Reconnected { from_seq: u64 },
}

/// How a followed job ended.
#[derive(Debug, Clone, PartialEq)]
pub struct WatchOutcome {
    /// SUCCEEDED, FAILED or CANCELLED.
    pub state: pb::JobState,
    /// The terminal event's message (or the job's error when the end was learnt from GetJob).
    pub message: String,
    /// The last event seen.
    pub last_seq: u64,
}

/// Where [`follow`] gets events: `WatchJob` of one job, or a fake in tests.
pub trait EventSource {
    type Events: Stream<Item = Result<pb::JobEvent, Status>> + Unpin;
    /// Opens a stream of events from `from_seq`.
    fn open(&mut self, from_seq: u64) -> impl Future<Output = Result<Self::Events, Status>>;
    /// The job as it is now (asked when a stream ends without a terminal event).
    fn job(&mut self) -> impl Future<Output = Result<pb::Job, Status>>;
}

/// Follows a job's events until a terminal state, reconnecting on retryable failures with
/// `from_seq = last seen + 1` and dropping replayed events, so `on` sees every event from
/// `from_seq` exactly once, in order. A stream that ends without a terminal event is checked
/// against the job (it may have finished before `from_seq`) and otherwise resumed.
pub async fn follow<S: EventSource>(
    source: &mut S,
    from_seq: u64,
    policy: RetryPolicy,
    mut on: impl FnMut(WatchNotice<'_>),
) -> Result<WatchOutcome, ClientError> {
    let mut cursor = EventCursor::new(from_seq);
    let mut backoff = Backoff::new(policy);
    let mut down_since: Option<tokio::time::Instant> = None;
    // Whether an attempt failed before (then a stream that opens is a reconnection).
    let mut retrying = false;
    loop {
        let failure = match source.open(cursor.from_seq()).await {
            Err(status) => status,
            Ok(mut events) => {
                if retrying {
                    on(WatchNotice::Reconnected { from_seq: cursor.from_seq() });
                }
                loop {
                    match events.next().await {
                        Some(Ok(event)) => {
                            down_since = None;
                            backoff.reset();
                            if !cursor.accept(event.seq) {
                                continue;
                            }
                            on(WatchNotice::Event(&event));
                            if let Some((state, message)) = terminal_state(&event) {
                                return Ok(WatchOutcome {
                                    state,
                                    message: message.to_owned(),
                                    last_seq: cursor.last_seq(),
                                });
                            }
                        }
                        Some(Err(status)) => break status,
                        None => match source.job().await {
                            Ok(job) if is_terminal(job.state()) => {
                                return Ok(WatchOutcome {
                                    state: job.state(),
                                    message: job.error,
                                    last_seq: cursor.last_seq(),
                                });
                            }
                            Ok(_) => break Status::unavailable("the event stream ended before the job finished"),
                            Err(status) => break status,
                        },
                    }
                }
            }
        };
        if !is_retryable(&failure) {
            return Err(failure.into());
        }
        let since = *down_since.get_or_insert_with(tokio::time::Instant::now);
        let Some(delay) = backoff.next_delay(since.elapsed()) else {
            let message = format!(
                "{} (gave up reconnecting after {:.0} s; events from {} on were not seen)",
                failure.message(),
                since.elapsed().as_secs_f64(),
                cursor.from_seq()
            );
            return Err(Status::new(failure.code(), message).into());
        };
        on(WatchNotice::Reconnecting {
            error: &failure,
            from_seq: cursor.from_seq(),
            delay,
            attempt: backoff.attempt(),
        });
        retrying = true;
        tokio::time::sleep(delay).await;
    }
}

/// `WatchJob` and `GetJob` of one job on a [`Client`].
struct JobEvents<'a> {
    client: &'a Client,
    id: &'a str,
}

impl EventSource for JobEvents<'_> {
    type Events = tonic::Streaming<pb::JobEvent>;

    async fn open(&mut self, from_seq: u64) -> Result<Self::Events, Status> {
        let req = pb::WatchJobRequest { id: self.id.to_owned(), from_seq };
        Ok(self.client.jobs().watch_job(req).await?.into_inner())
    }

    async fn job(&mut self) -> Result<pb::Job, Status> {
        Ok(self.client.jobs().get_job(pb::GetJobRequest { id: self.id.to_owned() }).await?.into_inner())
    }
}

impl Client {
    /// Follows job `id` from event `from_seq` until it finishes, surviving reconnects (see
    /// [`follow`]). `on` sees each event once, and the reconnection attempts.
    pub async fn follow_job(
        &self,
        id: &str,
        from_seq: u64,
        policy: RetryPolicy,
        on: impl FnMut(WatchNotice<'_>),
    ) -> Result<WatchOutcome, ClientError> {
        follow(&mut JobEvents { client: self, id }, from_seq, policy, on).await
    }
}

#[cfg(test)]
mod tests {
    use std::collections::VecDeque;

    use futures::stream;
    use pb::job_event::Event;
    use tonic::Code;

    use super::*;

    fn progress(seq: u64) -> pb::JobEvent {
        pb::JobEvent {
            seq,
            time: None,
            event: Some(Event::Progress(pb::job_event::Progress { step: seq * 10, ..Default::default() })),
        }
    }

    fn state(seq: u64, state: pb::JobState, message: &str) -> pb::JobEvent {
        pb::JobEvent {
            seq,
            time: None,
            event: Some(Event::State(pb::job_event::StateChange { state: state as i32, message: message.into() })),
        }
    }

    /// A transport failure as tonic reports it: a status with the I/O error as its source.
    fn broken() -> Status {
        Status::from_error(Box::new(std::io::Error::new(std::io::ErrorKind::ConnectionReset, "connection reset")))
    }

    type Script = Result<Vec<Result<pb::JobEvent, Status>>, Status>;

    /// Plays one scripted answer per `open`, recording the `from_seq` asked for.
    struct Fake {
        opens: VecDeque<Script>,
        asked: Vec<u64>,
        job: pb::Job,
    }

    impl Fake {
        fn new(opens: Vec<Script>) -> Self {
            Self { opens: opens.into(), asked: Vec::new(), job: pb::Job::default() }
        }
    }

    impl EventSource for Fake {
        type Events = stream::Iter<std::vec::IntoIter<Result<pb::JobEvent, Status>>>;

        async fn open(&mut self, from_seq: u64) -> Result<Self::Events, Status> {
            self.asked.push(from_seq);
            match self.opens.pop_front() {
                Some(Ok(events)) => Ok(stream::iter(events)),
                Some(Err(status)) => Err(status),
                None => Err(Status::unavailable("script exhausted")),
            }
        }

        async fn job(&mut self) -> Result<pb::Job, Status> {
            Ok(self.job.clone())
        }
    }

    fn fast() -> RetryPolicy {
        RetryPolicy { initial_delay: Duration::ZERO, max_delay: Duration::ZERO, budget: Duration::from_secs(30) }
    }

    /// Runs `follow`, returning the outcome, the event numbers shown and the notices.
    async fn run(fake: &mut Fake, from_seq: u64) -> (Result<WatchOutcome, ClientError>, Vec<u64>, Vec<String>) {
        let mut seen = Vec::new();
        let mut notices = Vec::new();
        let outcome = follow(fake, from_seq, fast(), |n| match n {
            WatchNotice::Event(e) => seen.push(e.seq),
            WatchNotice::Reconnecting { from_seq, attempt, .. } => {
                notices.push(format!("retry {attempt} from {from_seq}"))
            }
            WatchNotice::Reconnected { from_seq } => notices.push(format!("back from {from_seq}")),
        })
        .await;
        (outcome, seen, notices)
    }

    #[test]
    fn cursor_computes_from_seq_and_drops_duplicates() {
        let mut c = EventCursor::new(0);
        assert_eq!((c.from_seq(), c.last_seq()), (1, 0));
        assert!(c.accept(1) && c.accept(2) && c.accept(3));
        assert_eq!(c.from_seq(), 4);
        // A replay after reconnecting overlaps: 2 and 3 were shown already.
        assert!(!c.accept(2) && !c.accept(3));
        assert!(c.accept(4));
        assert_eq!((c.from_seq(), c.last_seq()), (5, 4));
        // Starting later: earlier events are not shown.
        let mut c = EventCursor::new(10);
        assert!(!c.accept(9));
        assert!(c.accept(10));
        assert_eq!(EventCursor::new(1), EventCursor::new(0));
        let mut c = EventCursor::new(u64::MAX);
        assert!(c.accept(u64::MAX));
    }

    #[tokio::test]
    async fn a_broken_stream_resumes_after_the_last_event_without_repeats() {
        let mut fake = Fake::new(vec![
            Ok(vec![Ok(state(1, pb::JobState::Running, "")), Ok(progress(2)), Ok(progress(3)), Err(broken())]),
            // The server is restarting: refused twice.
            Err(Status::unavailable("connection refused")),
            Err(broken()),
            // A server that replays a little too much: 2 and 3 must not show again.
            Ok(vec![Ok(progress(2)), Ok(progress(3)), Ok(progress(4)), Err(Status::unavailable("shutting down"))]),
            Ok(vec![Ok(progress(5)), Ok(state(6, pb::JobState::Succeeded, "done")), Ok(progress(7))]),
        ]);
        let (outcome, seen, notices) = run(&mut fake, 0).await;
        let outcome = outcome.expect("succeeds");
        assert_eq!(outcome, WatchOutcome { state: pb::JobState::Succeeded, message: "done".into(), last_seq: 6 });
        assert_eq!(seen, [1, 2, 3, 4, 5, 6], "every event once, in order, nothing after the terminal one");
        assert_eq!(fake.asked, [1, 4, 4, 4, 5]);
        assert_eq!(
            notices,
            ["retry 1 from 4", "retry 2 from 4", "retry 3 from 4", "back from 4", "retry 1 from 5", "back from 5"]
        );
    }

    #[tokio::test]
    async fn watching_from_a_later_event_asks_for_it() {
        let mut fake = Fake::new(vec![Ok(vec![Ok(progress(7)), Ok(state(8, pb::JobState::Failed, "nan loss"))])]);
        let (outcome, seen, _) = run(&mut fake, 7).await;
        let outcome = outcome.expect("finishes");
        assert_eq!((outcome.state, outcome.message.as_str()), (pb::JobState::Failed, "nan loss"));
        assert_eq!(seen, [7, 8]);
        assert_eq!(fake.asked, [7]);
    }

    #[tokio::test]
    async fn errors_of_the_request_are_final() {
        for status in [Status::not_found("job 'x' not found"), Status::unimplemented("not yet")] {
            let code = status.code();
            let mut fake = Fake::new(vec![Err(status)]);
            let (outcome, seen, notices) = run(&mut fake, 0).await;
            match outcome {
                Err(ClientError::Status(s)) => assert_eq!(s.code(), code),
                other => panic!("expected a status, got {other:?}"),
            }
            assert!(seen.is_empty() && notices.is_empty());
            assert_eq!(fake.asked, [1]);
        }
    }

    #[tokio::test]
    async fn a_stream_that_ends_early_is_checked_against_the_job() {
        // Finished before from_seq: the stream is empty and the job says how it ended.
        let mut fake = Fake::new(vec![Ok(vec![])]);
        fake.job = pb::Job { state: pb::JobState::Cancelled as i32, error: "by user".into(), ..Default::default() };
        let (outcome, seen, _) = run(&mut fake, 50).await;
        let outcome = outcome.expect("ends");
        assert_eq!(
            (outcome.state, outcome.message.as_str(), outcome.last_seq),
            (pb::JobState::Cancelled, "by user", 49)
        );
        assert!(seen.is_empty());

        // Still running: resume where the stream stopped.
        let mut fake = Fake::new(vec![Ok(vec![Ok(progress(1))]), Ok(vec![Ok(state(2, pb::JobState::Succeeded, ""))])]);
        fake.job = pb::Job { state: pb::JobState::Running as i32, ..Default::default() };
        let (outcome, seen, _) = run(&mut fake, 0).await;
        assert_eq!(outcome.expect("ends").state, pb::JobState::Succeeded);
        assert_eq!(seen, [1, 2]);
        assert_eq!(fake.asked, [1, 2]);
    }

    #[tokio::test]
    async fn reconnecting_gives_up_when_the_budget_is_spent() {
        let mut fake = Fake::new(vec![Ok(vec![Ok(progress(1)), Err(broken())])]);
        let mut seen = Vec::new();
        let policy = RetryPolicy { budget: Duration::ZERO, ..fast() };
        let outcome = follow(&mut fake, 0, policy, |n| {
            if let WatchNotice::Event(e) = n {
                seen.push(e.seq);
            }
        })
        .await;
        match outcome {
            Err(ClientError::Status(s)) => {
                assert_eq!(s.code(), Code::Unknown);
                assert!(s.message().contains("gave up reconnecting") && s.message().contains("from 2 on"), "{s}");
            }
            other => panic!("expected a status, got {other:?}"),
        }
        assert_eq!(seen, [1]);
    }
}
