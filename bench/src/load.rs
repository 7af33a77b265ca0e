//! The load itself: N closed-loop clients, each on its own connection with exactly one request
//! in flight, recording what completes inside the measurement window.
//!
//! Timeline, shared by every client: connect all, then `start`; warmup until `measure_start`;
//! record until `measure_end` (duration mode) or until each client has recorded its quota
//! (requests mode). A request is recorded when it *completes* inside the window, whenever it
//! was sent, so completions per second over the window is an unbiased throughput; the one
//! request per client still in flight at `measure_end` is awaited but not recorded.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use hdrhistogram::Histogram;
use relreward_client::Client;
use relreward_client::client::Transport;
use relreward_client::tensor::encode_f32;
use relreward_proto::v1::reward_service_client::RewardServiceClient;
use relreward_proto::v1::{GradientRequest, GradientResponse, Units};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Streaming};

use crate::args::{Mode, Stop};

/// Largest latency the histograms hold exactly (one hour, in microseconds); longer ones are
/// clamped, and no request waits that long (`--timeout` is at most a day, default 30 s).
const MAX_LATENCY_US: u64 = 3_600_000_000;
/// Pause after a failed request, so that a dead server is not hammered in a tight loop.
const ERROR_BACKOFF: Duration = Duration::from_millis(10);
/// How long closing a stream may take once nothing is in flight.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(5);

/// What to send and for how long.
#[derive(Debug, Clone)]
pub struct Plan {
    pub model: String,
    pub mode: Mode,
    pub clients: u32,
    pub batch: u32,
    pub item_shape: Vec<u64>,
    pub t: u32,
    pub warmup: Duration,
    pub stop: Stop,
    pub timeout: Duration,
}

/// Everything recorded, merged across clients.
pub struct Totals {
    /// Latency of each successful recorded request, in microseconds.
    pub latency_us: Histogram<u64>,
    pub requests: u64,
    pub items: u64,
    /// Failed recorded requests by gRPC code name (or a client-side reason).
    pub errors: BTreeMap<&'static str, u64>,
    /// Length of the measurement window.
    pub elapsed: Duration,
    /// When the measurement window started (after connecting and the warmup).
    pub measure_start: Instant,
}

/// One client's record.
struct ClientStats {
    latency_us: Histogram<u64>,
    requests: u64,
    items: u64,
    errors: BTreeMap<&'static str, u64>,
    last_done: Option<Instant>,
}

impl ClientStats {
    fn new() -> Self {
        Self { latency_us: new_histogram(), requests: 0, items: 0, errors: BTreeMap::new(), last_done: None }
    }
}

fn new_histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, MAX_LATENCY_US, 3).expect("constant histogram bounds are valid")
}

/// Runs the plan against `endpoints` (already checked to be loopback), client i on the
/// (i mod n)-th.
pub async fn run(endpoints: &[String], plan: Plan) -> Result<Totals> {
    // Connect everyone first, one connection each (as separate planner processes would), so
    // that connection set-up is not part of the load.
    let mut callers = Vec::with_capacity(plan.clients as usize);
    for i in 0..plan.clients {
        let endpoint = &endpoints[i as usize % endpoints.len()];
        let client = Client::connect(endpoint).await.with_context(|| format!("client {i} ({endpoint})"))?;
        callers.push(Caller::new(plan.mode, client.rewards()));
    }
    let plan = Arc::new(plan);
    let start = Instant::now();
    let measure_start = start + plan.warmup;
    let measure_end = match plan.stop {
        Stop::Duration(d) => Some(measure_start + d),
        Stop::Requests(_) => None,
    };
    let mut tasks = JoinSet::new();
    for (i, caller) in callers.into_iter().enumerate() {
        let template = request_template(&plan, i as u64);
        let plan = plan.clone();
        tasks.spawn(drive(caller, template, plan, measure_start, measure_end));
    }
    let mut totals = Totals {
        latency_us: new_histogram(),
        requests: 0,
        items: 0,
        errors: BTreeMap::new(),
        elapsed: Duration::ZERO,
        measure_start,
    };
    let mut last_done = measure_start;
    while let Some(joined) = tasks.join_next().await {
        let stats = joined.context("a client task failed")?;
        totals.latency_us.add(&stats.latency_us).expect("histograms share their bounds");
        totals.requests += stats.requests;
        totals.items += stats.items;
        for (code, n) in stats.errors {
            *totals.errors.entry(code).or_default() += n;
        }
        last_done = last_done.max(stats.last_done.unwrap_or(measure_start));
    }
    totals.elapsed = match measure_end {
        Some(end) => end - measure_start,
        None => last_done - measure_start,
    };
    Ok(totals)
}

/// One client's closed loop: send, wait for the answer, record it if it completed inside the
/// window, repeat until the window closes or the quota is recorded.
async fn drive(
    mut caller: Caller,
    template: GradientRequest,
    plan: Arc<Plan>,
    measure_start: Instant,
    measure_end: Option<Instant>,
) -> ClientStats {
    let mut stats = ClientStats::new();
    let mut recorded = 0u64;
    let mut request_id = 0u64;
    loop {
        match (plan.stop, measure_end) {
            (Stop::Requests(n), _) if recorded >= n => break,
            (_, Some(end)) if Instant::now() >= end => break,
            _ => {}
        }
        request_id += 1;
        let mut request = template.clone();
        request.request_id = request_id;
        let sent = Instant::now();
        let outcome = caller.call(request, plan.timeout).await.and_then(|r| check_response(&r, request_id, &plan));
        let done = Instant::now();
        let in_window = done >= measure_start && measure_end.is_none_or(|end| done <= end);
        if in_window {
            recorded += 1;
            stats.last_done = Some(done);
            match outcome {
                Ok(()) => {
                    let us = u64::try_from((done - sent).as_micros()).unwrap_or(u64::MAX).max(1);
                    stats.latency_us.saturating_record(us);
                    stats.requests += 1;
                    stats.items += u64::from(plan.batch);
                }
                Err(code) => *stats.errors.entry(code).or_default() += 1,
            }
        }
        if outcome.is_err() {
            tokio::time::sleep(ERROR_BACKOFF).await;
        }
    }
    caller.close().await;
    stats
}

/// The client's request, encoded once and cloned per send (only `request_id` changes):
/// `[batch, *item_shape]` deterministic pseudo-random values in [-1, 1], seeded by the client's
/// index so that clients differ, in normalized units (the diffusion models' space, where a
/// planner works), gradient in the same units.
fn request_template(plan: &Plan, client: u64) -> GradientRequest {
    let mut shape = vec![u64::from(plan.batch)];
    shape.extend_from_slice(&plan.item_shape);
    let n = shape.iter().product::<u64>() as usize;
    let mut rng = SplitMix64(0x5EED_0000 + client);
    let values: Vec<f32> = (0..n).map(|_| rng.next_unit() * 2.0 - 1.0).collect();
    GradientRequest {
        request_id: 0,
        model: plan.model.clone(),
        x: Some(encode_f32(&shape, &values)),
        t: vec![plan.t],
        input_units: Units::Normalized as i32,
        gradient_units: Units::Normalized as i32,
        omega: None,
        scale_by_posterior_variance_of: String::new(),
    }
}

/// A response is only a success when it answers this request and has the shapes asked for
/// (a gradient of the input's size, one reward per item); a cheap check on the byte counts.
fn check_response(r: &GradientResponse, request_id: u64, plan: &Plan) -> Result<(), &'static str> {
    if let Some(e) = &r.error {
        return Err(code_name(Code::from_i32(e.code)));
    }
    if r.request_id != request_id {
        return Err("WRONG_REQUEST_ID");
    }
    let items = plan.batch as usize;
    let item_len = plan.item_shape.iter().product::<u64>() as usize;
    let gradient_ok = r.gradient.as_ref().is_some_and(|g| g.data.len() == items * item_len * 4);
    let rewards_ok = r.rewards.as_ref().is_some_and(|t| t.data.len() == items * 4);
    if gradient_ok && rewards_ok { Ok(()) } else { Err("MALFORMED_RESPONSE") }
}

/// How one client talks to the server: one Gradient call per request (unary), or one
/// GradientStream, opened on the first request and again after a stream-level failure.
struct Caller {
    rpc: RewardServiceClient<Transport>,
    mode: Mode,
    /// The open stream (stream mode).
    open: Option<OpenStream>,
}

struct OpenStream {
    requests: mpsc::Sender<GradientRequest>,
    responses: Streaming<GradientResponse>,
}

impl Caller {
    fn new(mode: Mode, rpc: RewardServiceClient<Transport>) -> Self {
        Self { rpc, mode, open: None }
    }

    /// Sends one request and waits for its answer, at most `timeout`. Failures are named by
    /// gRPC code (DEADLINE_EXCEEDED for the client's own timeout) or, for a stream that ended
    /// without an error, STREAM_ENDED.
    async fn call(&mut self, request: GradientRequest, timeout: Duration) -> Result<GradientResponse, &'static str> {
        let Self { rpc, mode, open } = self;
        match mode {
            Mode::Unary => {
                let mut request = tonic::Request::new(request);
                request.set_timeout(timeout);
                // The server answers DEADLINE_EXCEEDED itself; the local bound covers a server
                // that does not answer at all.
                match tokio::time::timeout(timeout + Duration::from_secs(1), rpc.gradient(request)).await {
                    Err(_) => Err(code_name(Code::DeadlineExceeded)),
                    Ok(Err(status)) => Err(code_name(status.code())),
                    Ok(Ok(response)) => Ok(response.into_inner()),
                }
            }
            Mode::Stream => {
                // No grpc-timeout on the stream: the server would apply it to the whole stream.
                let result = tokio::time::timeout(timeout, Self::stream_call(rpc, open, request)).await;
                let result = result.unwrap_or(Err(code_name(Code::DeadlineExceeded)));
                if result.is_err() {
                    // Whatever went wrong, the next request starts on a fresh stream, so a late
                    // answer to this one can never be taken for the next one's.
                    *open = None;
                }
                result
            }
        }
    }

    async fn stream_call(
        rpc: &mut RewardServiceClient<Transport>,
        open: &mut Option<OpenStream>,
        request: GradientRequest,
    ) -> Result<GradientResponse, &'static str> {
        let request_id = request.request_id;
        let stream = match open {
            Some(stream) => {
                stream.requests.send(request).await.map_err(|_| "STREAM_ENDED")?;
                stream
            }
            None => {
                // The first request is queued before the call so the server has it at once.
                let (tx, rx) = mpsc::channel(1);
                tx.send(request).await.map_err(|_| "STREAM_ENDED")?;
                let responses = rpc
                    .gradient_stream(ReceiverStream::new(rx))
                    .await
                    .map_err(|status| code_name(status.code()))?
                    .into_inner();
                open.insert(OpenStream { requests: tx, responses })
            }
        };
        match stream.responses.message().await {
            // Also a response whose `error` is set: that request failed but the stream goes on
            // (`check_response` counts it).
            Ok(Some(response)) if response.request_id == request_id => Ok(response),
            // With one request in flight any other id is a protocol error: start afresh.
            Ok(Some(_)) => Err("WRONG_REQUEST_ID"),
            Ok(None) => Err("STREAM_ENDED"),
            Err(status) => Err(code_name(status.code())),
        }
    }

    /// Ends the request side of an open stream and waits (bounded) for the server to end it.
    async fn close(self) {
        if let Some(OpenStream { requests, mut responses }) = self.open {
            drop(requests);
            let _ = tokio::time::timeout(CLOSE_TIMEOUT, async { while let Ok(Some(_)) = responses.message().await {} })
                .await;
        }
    }
}

/// The canonical upper-case name of a gRPC status code.
pub fn code_name(code: Code) -> &'static str {
    match code {
        Code::Ok => "OK",
        Code::Cancelled => "CANCELLED",
        Code::Unknown => "UNKNOWN",
        Code::InvalidArgument => "INVALID_ARGUMENT",
        Code::DeadlineExceeded => "DEADLINE_EXCEEDED",
        Code::NotFound => "NOT_FOUND",
        Code::AlreadyExists => "ALREADY_EXISTS",
        Code::PermissionDenied => "PERMISSION_DENIED",
        Code::ResourceExhausted => "RESOURCE_EXHAUSTED",
        Code::FailedPrecondition => "FAILED_PRECONDITION",
        Code::Aborted => "ABORTED",
        Code::OutOfRange => "OUT_OF_RANGE",
        Code::Unimplemented => "UNIMPLEMENTED",
        Code::Internal => "INTERNAL",
        Code::Unavailable => "UNAVAILABLE",
        Code::DataLoss => "DATA_LOSS",
        Code::Unauthenticated => "UNAUTHENTICATED",
    }
}

/// SplitMix64: a tiny deterministic generator for the inputs (their values do not matter for
/// speed, only that they are finite and differ between clients).
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1) with 24 bits (every value exact in f32).
    fn next_unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan() -> Plan {
        Plan {
            model: "m".into(),
            mode: Mode::Stream,
            clients: 2,
            batch: 3,
            item_shape: vec![64, 6],
            t: 7,
            warmup: Duration::ZERO,
            stop: Stop::Requests(1),
            timeout: Duration::from_secs(1),
        }
    }

    #[test]
    fn templates_are_deterministic_in_range_and_differ_per_client() {
        let p = plan();
        let a = request_template(&p, 0);
        let x = a.x.as_ref().expect("x");
        assert_eq!(x.shape, vec![3, 64, 6]);
        assert_eq!(x.data.len(), 3 * 64 * 6 * 4);
        assert_eq!(a.t, vec![7]);
        assert_eq!(a.input_units, Units::Normalized as i32);
        assert_eq!(a, request_template(&p, 0));
        assert_ne!(a.x, request_template(&p, 1).x);
        let values = x.data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
        assert!(values.into_iter().all(|v| (-1.0..1.0).contains(&v)));
    }

    #[test]
    fn responses_are_checked() {
        let p = plan();
        let good = GradientResponse {
            request_id: 5,
            gradient: Some(encode_f32(&[3, 64, 6], &[0.0; 3 * 64 * 6])),
            rewards: Some(encode_f32(&[3], &[0.0; 3])),
            error: None,
        };
        assert_eq!(check_response(&good, 5, &p), Ok(()));
        assert_eq!(check_response(&good, 6, &p), Err("WRONG_REQUEST_ID"));
        let short = GradientResponse { rewards: Some(encode_f32(&[2], &[0.0; 2])), ..good.clone() };
        assert_eq!(check_response(&short, 5, &p), Err("MALFORMED_RESPONSE"));
        let failed = GradientResponse {
            request_id: 5,
            error: Some(relreward_proto::v1::StreamError {
                code: Code::ResourceExhausted as i32,
                message: "full".into(),
            }),
            ..Default::default()
        };
        assert_eq!(check_response(&failed, 5, &p), Err("RESOURCE_EXHAUSTED"));
    }
}
