//! Prometheus metrics: one [`Metrics`] per server, rendered in the text exposition format.
//!
//! - [`GrpcMetricsLayer`]: a tower layer around every RPC. It opens a `grpc` tracing span per
//!   call and records `relreward_grpc_requests_total{method,code}` and
//!   `relreward_grpc_request_seconds{method}` when the response ends: the status code comes
//!   from the `grpc-status` header (trailers-only errors) or from the trailers that close the
//!   body ([`RecordedBody`]); a stream is timed to its last message.
//! - Serving records queue time, compute time, batch sizes, split passes, queue depth and
//!   dropped queries, and the outcome of every query ([`Metrics::observe_query`]); the same
//!   observations also add up, per model, to the cumulative [`ModelStats`] the Open Inference
//!   Protocol's ModelStatistics reports (Triton's counts and nanoseconds, which a histogram
//!   cannot give back exactly).
//! - The OIP over HTTP (`crate::oip_http`) counts its requests by route and HTTP status
//!   ([`Metrics::observe_http`]); their queries count in serving's metrics like gRPC's.
//! - [`serve_http`]: `GET /metrics` over HTTP/1.1; jobs by state and loaded models are read
//!   when scraped.
use std::collections::{HashMap, HashSet};
use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::task::{Context, Poll, ready};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use bytes::Bytes;
use http::header::{CONTENT_TYPE, HeaderName, HeaderValue};
use http::{HeaderMap, Method, Request, Response, StatusCode};
use http_body::{Body, Frame, SizeHint};
use http_body_util::Full;
use hyper_util::rt::{TokioIo, TokioTimer};
use pin_project_lite::pin_project;
use prometheus::{
    Encoder, HistogramOpts, HistogramVec, IntCounterVec, IntGauge, IntGaugeVec, Opts, Registry, TextEncoder,
};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::Span;

/// Latency buckets from 50 us to 60 s: gradient queries live at the low end, uploads and
/// sampling at the high end.
const SECONDS_BUCKETS: &[f64] = &[
    5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0,
];
const BATCH_BUCKETS: &[f64] = &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0, 4096.0];

#[derive(Clone)]
pub struct Metrics {
    inner: Arc<Inner>,
}

struct Inner {
    registry: Registry,
    requests: IntCounterVec,
    request_seconds: HistogramVec,
    http_requests: IntCounterVec,
    http_request_seconds: HistogramVec,
    queue_seconds: HistogramVec,
    compute_seconds: HistogramVec,
    batch_items: HistogramVec,
    split_passes: IntCounterVec,
    queue_depth: IntGaugeVec,
    dropped: IntCounterVec,
    queries: IntCounterVec,
    jobs: IntGaugeVec,
    loaded_models: IntGauge,
    /// Cumulative statistics per model name, for the life of the process.
    model_stats: Mutex<HashMap<String, ModelStats>>,
}

/// A count of events and their cumulative duration (Triton's `StatisticDuration`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CountNs {
    pub count: u64,
    pub ns: u64,
}

impl CountNs {
    fn add(&mut self, count: u64, ns: u64) {
        self.count = self.count.saturating_add(count);
        self.ns = self.ns.saturating_add(ns);
    }
}

/// What serving did for one model since the process started, in the terms (and with the
/// semantics) of Triton's `ModelStatistics`. A query of either protocol counts once it is in
/// the model's queue, as a Triton request counts once its scheduler accepted it: `success`
/// and `fail` from its arrival at the serving layer to its answer, `fail` being a deadline
/// that passed while it was queued (Triton's REJECTED), a call cancelled by its client while
/// queued or computing (CANCELED), a compute error or non-finite answer (BACKEND) or
/// shutdown; `queue` per computed query, `compute_infer` per computed query with the duration
/// of the merged batch it was part of. A request refused before it was queued is answered
/// with its error and not counted, as Triton does not count a request that fails
/// `PrepareForInference` or `Enqueue`: a malformed message, an unknown model, a query that
/// fails validation against the model (shape, B over `serving.max_request_items`, `t` out of
/// range, non-finite or out-of-range `x`, ...), a deadline passed before it was queued or a
/// full queue (`relreward_serving_dropped_total{reason="queue_full"}` counts those).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ModelStats {
    pub success: CountNs,
    pub fail: CountNs,
    pub queue: CountNs,
    pub compute_infer: CountNs,
    /// Items (batch elements) of successful queries.
    pub inference_count: u64,
    /// Merged batches computed (one forward, or forward and backward, pass each).
    pub execution_count: u64,
    /// Milliseconds since the epoch when the last query was answered (0: never).
    pub last_inference_ms: u64,
}

fn nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

/// Whole nanoseconds of a non-negative duration in seconds (saturating; NaN reads as 0).
fn seconds_to_ns(seconds: f64) -> u64 {
    (seconds * 1e9).round() as u64
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let registry = Registry::new_custom(Some("relreward".into()), None).unwrap_or_default();
        let seconds = |name: &str, help: &str| HistogramOpts::new(name, help).buckets(SECONDS_BUCKETS.to_vec());
        // The names and labels below are constants, so construction cannot fail; a failure
        // would be a programming error caught by the tests.
        let inner = Inner {
            requests: IntCounterVec::new(
                Opts::new("grpc_requests_total", "gRPC calls by method and status code"),
                &["method", "code"],
            )
            .expect("metric"),
            request_seconds: HistogramVec::new(
                seconds("grpc_request_seconds", "gRPC call duration (to the last message of a stream)"),
                &["method"],
            )
            .expect("metric"),
            http_requests: IntCounterVec::new(
                Opts::new("oip_http_requests_total", "OIP over HTTP requests by route and HTTP status"),
                &["route", "status"],
            )
            .expect("metric"),
            http_request_seconds: HistogramVec::new(
                seconds("oip_http_request_seconds", "OIP over HTTP request duration (body read to answer)"),
                &["route"],
            )
            .expect("metric"),
            queue_seconds: HistogramVec::new(
                seconds("serving_queue_seconds", "time a Score/Gradient query waited for its batch"),
                &["model"],
            )
            .expect("metric"),
            compute_seconds: HistogramVec::new(
                seconds("serving_compute_seconds", "forward/backward time of one merged batch"),
                &["model"],
            )
            .expect("metric"),
            batch_items: HistogramVec::new(
                HistogramOpts::new("serving_batch_items", "items per merged batch").buckets(BATCH_BUCKETS.to_vec()),
                &["model"],
            )
            .expect("metric"),
            split_passes: IntCounterVec::new(
                Opts::new("serving_split_passes_total", "merged batches whose rows were split across threads"),
                &["model"],
            )
            .expect("metric"),
            queue_depth: IntGaugeVec::new(Opts::new("serving_queue_depth", "queries waiting per model"), &["model"])
                .expect("metric"),
            dropped: IntCounterVec::new(
                Opts::new("serving_dropped_total", "queries not computed: deadline passed, caller gone, queue full"),
                &["model", "reason"],
            )
            .expect("metric"),
            queries: IntCounterVec::new(
                Opts::new("serving_queries_total", "Score/Gradient queries (either protocol) by model and outcome"),
                &["model", "outcome"],
            )
            .expect("metric"),
            jobs: IntGaugeVec::new(Opts::new("jobs", "jobs by state"), &["state"]).expect("metric"),
            loaded_models: IntGauge::new("loaded_models", "models loaded in memory").expect("metric"),
            model_stats: Mutex::new(HashMap::new()),
            registry,
        };
        for c in [
            Box::new(inner.requests.clone()) as Box<dyn prometheus::core::Collector>,
            Box::new(inner.request_seconds.clone()),
            Box::new(inner.http_requests.clone()),
            Box::new(inner.http_request_seconds.clone()),
            Box::new(inner.queue_seconds.clone()),
            Box::new(inner.compute_seconds.clone()),
            Box::new(inner.batch_items.clone()),
            Box::new(inner.split_passes.clone()),
            Box::new(inner.queue_depth.clone()),
            Box::new(inner.dropped.clone()),
            Box::new(inner.queries.clone()),
            Box::new(inner.jobs.clone()),
            Box::new(inner.loaded_models.clone()),
        ] {
            inner.registry.register(c).expect("unique metric names");
        }
        Self { inner: Arc::new(inner) }
    }

    /// One finished gRPC call.
    pub fn observe_call(&self, method: &str, code: &str, seconds: f64) {
        self.inner.requests.with_label_values(&[method, code]).inc();
        self.inner.request_seconds.with_label_values(&[method]).observe(seconds);
    }

    /// One answered request of the OIP over HTTP (`crate::oip_http`).
    pub fn observe_http(&self, route: &str, status: u16, seconds: f64) {
        self.inner.http_requests.with_label_values(&[route, &status.to_string()]).inc();
        self.inner.http_request_seconds.with_label_values(&[route]).observe(seconds);
    }

    /// One merged batch of `queries` queries and `items` items computed in `seconds`.
    pub fn observe_batch(&self, model: &str, queries: usize, items: usize, seconds: f64) {
        self.inner.batch_items.with_label_values(&[model]).observe(items as f64);
        self.inner.compute_seconds.with_label_values(&[model]).observe(seconds);
        let queries = queries as u64;
        self.update_model(model, |s| {
            s.execution_count = s.execution_count.saturating_add(1);
            s.compute_infer.add(queries, seconds_to_ns(seconds).saturating_mul(queries));
        });
    }

    /// One merged batch computed in parts on several threads (counted beside its
    /// [`Metrics::observe_batch`]).
    pub fn observe_split_pass(&self, model: &str) {
        self.inner.split_passes.with_label_values(&[model]).inc();
    }

    /// Time one query waited between arrival and the start of its batch's compute.
    pub fn observe_queue_wait(&self, model: &str, seconds: f64) {
        self.inner.queue_seconds.with_label_values(&[model]).observe(seconds);
        self.update_model(model, |s| s.queue.add(1, seconds_to_ns(seconds)));
    }

    /// One queued query for `model` answered (`ok`) or failed after `elapsed`; `items` is its
    /// batch size (counted only when it succeeded). See [`ModelStats`] for what is counted.
    pub fn observe_query(&self, model: &str, ok: bool, items: u64, elapsed: Duration) {
        self.inner.queries.with_label_values(&[model, if ok { "success" } else { "failure" }]).inc();
        let now_ms = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64);
        self.update_model(model, |s| {
            if ok {
                s.success.add(1, nanos(elapsed));
                s.inference_count = s.inference_count.saturating_add(items);
            } else {
                s.fail.add(1, nanos(elapsed));
            }
            s.last_inference_ms = s.last_inference_ms.max(now_ms);
        });
    }

    fn update_model(&self, model: &str, update: impl FnOnce(&mut ModelStats)) {
        // Each update is a few additions: a panic cannot leave a half-updated entry.
        let mut stats = self.inner.model_stats.lock().unwrap_or_else(PoisonError::into_inner);
        match stats.get_mut(model) {
            Some(s) => update(s),
            None => update(stats.entry(model.to_owned()).or_default()),
        }
    }

    /// The statistics of `model`, if serving has seen it.
    pub fn model_stats(&self, model: &str) -> Option<ModelStats> {
        self.inner.model_stats.lock().unwrap_or_else(PoisonError::into_inner).get(model).copied()
    }

    /// Every model serving has seen, with its statistics, sorted by name.
    pub fn all_model_stats(&self) -> Vec<(String, ModelStats)> {
        let stats = self.inner.model_stats.lock().unwrap_or_else(PoisonError::into_inner);
        let mut all: Vec<_> = stats.iter().map(|(k, v)| (k.clone(), *v)).collect();
        all.sort_by(|a, b| a.0.cmp(&b.0));
        all
    }

    pub fn set_queue_depth(&self, model: &str, depth: usize) {
        self.inner.queue_depth.with_label_values(&[model]).set(depth as i64);
    }

    /// A query dropped without compute; `reason`: "deadline", "cancelled" or "queue_full".
    pub fn dropped(&self, model: &str, reason: &str) {
        self.inner.dropped.with_label_values(&[model, reason]).inc();
    }

    pub fn set_jobs(&self, state: &str, count: usize) {
        self.inner.jobs.with_label_values(&[state]).set(count as i64);
    }

    pub fn set_loaded_models(&self, count: usize) {
        self.inner.loaded_models.set(count as i64);
    }

    /// The text exposition of every metric.
    pub fn render(&self) -> String {
        let mut out = Vec::new();
        // Encoding into a Vec only fails on invalid metric families, which ours are not.
        let _ = TextEncoder::new().encode(&self.inner.registry.gather(), &mut out);
        String::from_utf8(out).unwrap_or_default()
    }
}

// ---------------------------------------------------------------------------------------------
// Per-call recording: the tower layer, its response future and the response body wrapper.

/// The `method` label of a path no served service declares. Labels come only from the
/// descriptor sets below, so a client inventing paths cannot grow the number of series.
pub const UNKNOWN_METHOD: &str = "unknown";

/// Every service the server can route (ours, the inference protocol's, health, both
/// reflection versions). A service served without its descriptor set here is counted as
/// `method="unknown"`.
pub(crate) const DESCRIPTOR_SETS: &[&[u8]] = &[
    relreward_proto::FILE_DESCRIPTOR_SET,
    relreward_proto::INFERENCE_FILE_DESCRIPTOR_SET,
    tonic_health::pb::FILE_DESCRIPTOR_SET,
    tonic_reflection::pb::v1::FILE_DESCRIPTOR_SET,
    tonic_reflection::pb::v1alpha::FILE_DESCRIPTOR_SET,
];

/// `package.Service/Method` for every method in [`DESCRIPTOR_SETS`], built once per process;
/// labels borrow from it, so recording a call allocates nothing.
fn known_methods() -> &'static HashSet<String> {
    static METHODS: OnceLock<HashSet<String>> = OnceLock::new();
    METHODS.get_or_init(|| {
        use prost::Message as _;
        let mut methods = HashSet::new();
        for encoded in DESCRIPTOR_SETS {
            // Compiled-in constants; one that failed to decode would only leave its methods
            // counted as "unknown".
            let Ok(set) = prost_types::FileDescriptorSet::decode(*encoded) else { continue };
            for file in &set.file {
                let package = file.package();
                for service in &file.service {
                    for method in &service.method {
                        let name = match package {
                            "" => format!("{}/{}", service.name(), method.name()),
                            p => format!("{p}.{}/{}", service.name(), method.name()),
                        };
                        methods.insert(name);
                    }
                }
            }
        }
        methods
    })
}

/// The `method` label of a request path `/package.Service/Method`.
pub fn method_label(path: &str) -> &'static str {
    let name = path.strip_prefix('/').unwrap_or(path);
    known_methods().get(name).map_or(UNKNOWN_METHOD, String::as_str)
}

/// gRPC status names by code number.
const CODE_NAMES: [&str; 17] = [
    "OK",
    "CANCELLED",
    "UNKNOWN",
    "INVALID_ARGUMENT",
    "DEADLINE_EXCEEDED",
    "NOT_FOUND",
    "ALREADY_EXISTS",
    "PERMISSION_DENIED",
    "RESOURCE_EXHAUSTED",
    "FAILED_PRECONDITION",
    "ABORTED",
    "OUT_OF_RANGE",
    "UNIMPLEMENTED",
    "INTERNAL",
    "UNAVAILABLE",
    "DATA_LOSS",
    "UNAUTHENTICATED",
];

const GRPC_STATUS: HeaderName = HeaderName::from_static("grpc-status");

/// The status name in `grpc-status` of `headers` (response headers or trailers), if present;
/// a value that is not a known code reads as "UNKNOWN".
fn status_code(headers: &HeaderMap) -> Option<&'static str> {
    let value = headers.get(GRPC_STATUS)?.as_bytes();
    let code = match value {
        [d] if d.is_ascii_digit() => usize::from(d - b'0'),
        [a, b] if a.is_ascii_digit() && b.is_ascii_digit() => usize::from(a - b'0') * 10 + usize::from(b - b'0'),
        _ => return Some("UNKNOWN"),
    };
    Some(CODE_NAMES.get(code).copied().unwrap_or("UNKNOWN"))
}

/// One call in flight; records itself exactly once, as CANCELLED if dropped unfinished
/// (the client went away, or the connection was closed under it).
struct Call {
    metrics: Metrics,
    method: &'static str,
    start: Instant,
    recorded: bool,
}

impl Call {
    fn finish(&mut self, code: &str) {
        if !self.recorded {
            self.recorded = true;
            self.metrics.observe_call(self.method, code, self.start.elapsed().as_secs_f64());
        }
    }
}

impl Drop for Call {
    fn drop(&mut self) {
        self.finish("CANCELLED");
    }
}

/// Tower layer recording every gRPC call in [`Metrics`] and running it in a `grpc` span;
/// applied with `tonic::transport::Server::builder().layer(..)`.
#[derive(Clone)]
pub struct GrpcMetricsLayer {
    metrics: Metrics,
}

impl GrpcMetricsLayer {
    pub fn new(metrics: Metrics) -> Self {
        // Build the method table now rather than on the first call.
        known_methods();
        Self { metrics }
    }
}

impl<S> tower_layer::Layer<S> for GrpcMetricsLayer {
    type Service = GrpcMetricsService<S>;

    fn layer(&self, inner: S) -> Self::Service {
        GrpcMetricsService { inner, metrics: self.metrics.clone() }
    }
}

/// The service [`GrpcMetricsLayer`] wraps around the router.
#[derive(Clone)]
pub struct GrpcMetricsService<S> {
    inner: S,
    metrics: Metrics,
}

impl<S, ReqBody, ResBody> tower_service::Service<Request<ReqBody>> for GrpcMetricsService<S>
where
    S: tower_service::Service<Request<ReqBody>, Response = Response<ResBody>>,
{
    type Response = Response<RecordedBody<ResBody>>;
    type Error = S::Error;
    type Future = ResponseFuture<S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<ReqBody>) -> Self::Future {
        let start = Instant::now();
        let path = request.uri().path();
        let method = method_label(path);
        // The span names what was asked for, even a path no service declares.
        let span = tracing::info_span!("grpc", method = %path.strip_prefix('/').unwrap_or(path));
        let call = Call { metrics: self.metrics.clone(), method, start, recorded: false };
        let inner = {
            let _entered = span.enter();
            self.inner.call(request)
        };
        ResponseFuture { inner, call: Some(call), span }
    }
}

pin_project! {
    /// Runs the call in its span; hands the call over to the response body once the headers
    /// are ready.
    pub struct ResponseFuture<F> {
        #[pin]
        inner: F,
        call: Option<Call>,
        span: Span,
    }
}

impl<F, ResBody, E> Future for ResponseFuture<F>
where
    F: Future<Output = Result<Response<ResBody>, E>>,
{
    type Output = Result<Response<RecordedBody<ResBody>>, E>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let this = self.project();
        let result = {
            let _entered = this.span.enter();
            ready!(this.inner.poll(cx))
        };
        let mut call = this.call.take();
        match result {
            Ok(response) => {
                // Trailers-only response (most errors): the status is in the headers and the
                // body is empty, so the call ends here.
                if let (Some(code), Some(call)) = (status_code(response.headers()), call.as_mut()) {
                    call.finish(code);
                }
                let span = std::mem::replace(this.span, Span::none());
                Poll::Ready(Ok(response.map(|inner| RecordedBody { inner, call, span })))
            }
            Err(e) => {
                if let Some(call) = call.as_mut() {
                    call.finish("UNKNOWN");
                }
                Poll::Ready(Err(e))
            }
        }
    }
}

pin_project! {
    /// A response body that records its call when the trailers frame passes (their
    /// `grpc-status`), or when it ends without trailers (UNKNOWN) or is dropped before its end
    /// (CANCELLED). Frames pass through untouched; each poll runs in the call's span, where a
    /// streaming handler's work happens.
    pub struct RecordedBody<B> {
        #[pin]
        inner: B,
        call: Option<Call>,
        span: Span,
    }
}

impl<B: Body> Body for RecordedBody<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        let this = self.project();
        let polled = {
            let _entered = this.span.enter();
            ready!(this.inner.poll_frame(cx))
        };
        if let Some(call) = this.call.as_mut() {
            match &polled {
                Some(Ok(frame)) => {
                    if let Some(trailers) = frame.trailers_ref() {
                        call.finish(status_code(trailers).unwrap_or("UNKNOWN"));
                    }
                }
                Some(Err(_)) | None => call.finish("UNKNOWN"),
            }
        }
        Poll::Ready(polled)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

// ---------------------------------------------------------------------------------------------
// The scrape endpoint.

/// The Prometheus text exposition format.
pub const CONTENT_TYPE_TEXT: &str = "text/plain; version=0.0.4";

/// How long a connection may take to send its request headers.
const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);

/// Serves `GET /metrics` (404 for anything else) on `listener` until `shutdown` is
/// cancelled, then closes the listener and every open connection. `refresh` runs before each
/// scrape to update the gauges read at scrape time. Connections are independent tasks, so
/// concurrent scrapes are fine; errors end one connection, never the endpoint.
pub async fn serve_http<R, Fut>(listener: TcpListener, metrics: Metrics, refresh: R, shutdown: CancellationToken)
where
    R: Fn() -> Fut + Clone + Send + Sync + 'static,
    Fut: Future<Output = ()> + Send + 'static,
{
    let connections = TaskTracker::new();
    loop {
        let stream = tokio::select! {
            () = shutdown.cancelled() => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(e) => {
                    // Out of file descriptors and the like: wait a little rather than spin.
                    tracing::warn!(error = %e, "metrics endpoint: accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let (metrics, refresh, shutdown) = (metrics.clone(), refresh.clone(), shutdown.clone());
        connections.spawn(async move {
            let service = hyper::service::service_fn(move |request: Request<hyper::body::Incoming>| {
                let (metrics, refresh) = (metrics.clone(), refresh.clone());
                async move { Ok::<_, Infallible>(respond(request.method(), request.uri().path(), &metrics, refresh).await) }
            });
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder.timer(TokioTimer::new()).header_read_timeout(HEADER_READ_TIMEOUT);
            let connection = builder.serve_connection(TokioIo::new(stream), service);
            tokio::select! {
                result = connection => {
                    if let Err(e) = result {
                        tracing::debug!(error = %e, "metrics endpoint: connection ended with an error");
                    }
                }
                () = shutdown.cancelled() => {}
            }
        });
    }
    drop(listener);
    connections.close();
    connections.wait().await;
}

async fn respond<R, Fut>(method: &Method, path: &str, metrics: &Metrics, refresh: R) -> Response<Full<Bytes>>
where
    R: Fn() -> Fut,
    Fut: Future<Output = ()>,
{
    let (status, content_type, body) = if path == "/metrics" && (method == Method::GET || method == Method::HEAD) {
        refresh().await;
        (StatusCode::OK, CONTENT_TYPE_TEXT, Bytes::from(metrics.render()))
    } else {
        (StatusCode::NOT_FOUND, "text/plain", Bytes::from_static(b"not found; try GET /metrics\n"))
    };
    let mut response = Response::new(Full::new(body));
    *response.status_mut() = status;
    response.headers_mut().insert(CONTENT_TYPE, HeaderValue::from_static(content_type));
    response
}

#[cfg(test)]
mod tests {
    use std::convert::Infallible;

    use http_body_util::{BodyExt, StreamBody};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tower_layer::Layer;
    use tower_service::Service;

    use super::*;

    const GET_DATASET: &str = "relreward.v1.DatasetService/GetDataset";

    fn count(text: &str, method: &str, code: &str) -> Option<u64> {
        let prefix = format!("relreward_grpc_requests_total{{code=\"{code}\",method=\"{method}\"}} ");
        text.lines().find_map(|l| l.strip_prefix(&prefix)).map(|v| v.parse().expect("count"))
    }

    fn trailers(code: &str) -> HeaderMap {
        let mut t = HeaderMap::new();
        t.insert(GRPC_STATUS, HeaderValue::from_str(code).expect("value"));
        t
    }

    type Frames = Vec<Result<Frame<Bytes>, Infallible>>;
    type TestBody =
        RecordedBody<StreamBody<futures::stream::Iter<std::vec::IntoIter<Result<Frame<Bytes>, Infallible>>>>>;

    fn body(metrics: &Metrics, frames: Frames) -> TestBody {
        let call = Call {
            metrics: metrics.clone(),
            method: method_label("/relreward.v1.DatasetService/GetDataset"),
            start: Instant::now(),
            recorded: false,
        };
        RecordedBody { inner: StreamBody::new(futures::stream::iter(frames)), call: Some(call), span: Span::none() }
    }

    #[test]
    fn render_lists_every_metric_with_its_labels() {
        let m = Metrics::new();
        m.observe_call(GET_DATASET, "OK", 0.002);
        m.observe_call(GET_DATASET, "OK", 0.003);
        m.observe_call(GET_DATASET, "NOT_FOUND", 0.001);
        m.observe_batch("r", 2, 8, 0.01);
        m.observe_queue_wait("r", 0.001);
        m.observe_query("r", true, 8, Duration::from_millis(12));
        m.set_queue_depth("r", 3);
        m.dropped("r", "deadline");
        m.set_jobs("running", 2);
        m.set_loaded_models(4);
        let text = m.render();
        assert_eq!(count(&text, GET_DATASET, "OK"), Some(2), "{text}");
        assert_eq!(count(&text, GET_DATASET, "NOT_FOUND"), Some(1), "{text}");
        for needle in [
            "# TYPE relreward_grpc_request_seconds histogram",
            "relreward_grpc_request_seconds_count{method=\"relreward.v1.DatasetService/GetDataset\"} 3",
            "relreward_grpc_request_seconds_bucket{method=\"relreward.v1.DatasetService/GetDataset\",le=\"0.0025\"} 2",
            "relreward_serving_batch_items_count{model=\"r\"} 1",
            "relreward_serving_compute_seconds_count{model=\"r\"} 1",
            "relreward_serving_queue_seconds_count{model=\"r\"} 1",
            "relreward_serving_queue_depth{model=\"r\"} 3",
            "relreward_serving_dropped_total{model=\"r\",reason=\"deadline\"} 1",
            "relreward_serving_queries_total{model=\"r\",outcome=\"success\"} 1",
            "relreward_jobs{state=\"running\"} 2",
            "relreward_loaded_models 4",
        ] {
            assert!(text.contains(needle), "missing {needle:?} in\n{text}");
        }
    }

    #[test]
    fn model_stats_add_up_per_model() {
        let m = Metrics::new();
        assert_eq!(m.model_stats("r"), None);
        // Two queries (3 and 5 items) merged into one batch, then one that failed validation.
        m.observe_queue_wait("r", 0.000_002);
        m.observe_queue_wait("r", 0.000_001);
        m.observe_batch("r", 2, 8, 0.000_010);
        m.observe_query("r", true, 3, Duration::from_nanos(20_000));
        m.observe_query("r", true, 5, Duration::from_nanos(15_000));
        m.observe_query("r", false, 4, Duration::from_nanos(700));
        m.observe_query("other", true, 1, Duration::from_nanos(1));
        let s = m.model_stats("r").expect("stats");
        assert_eq!(s.success, CountNs { count: 2, ns: 35_000 });
        assert_eq!(s.fail, CountNs { count: 1, ns: 700 });
        assert_eq!(s.queue, CountNs { count: 2, ns: 3_000 });
        assert_eq!(s.compute_infer, CountNs { count: 2, ns: 20_000 }, "each query with its batch's time");
        assert_eq!((s.inference_count, s.execution_count), (8, 1), "failed items are not inferences");
        let now_ms = SystemTime::now().duration_since(UNIX_EPOCH).expect("clock").as_millis() as u64;
        assert!(s.last_inference_ms > 0 && s.last_inference_ms <= now_ms);
        let names: Vec<String> = m.all_model_stats().into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["other", "r"]);
        let text = m.render();
        assert!(text.contains("relreward_serving_queries_total{model=\"r\",outcome=\"failure\"} 1"), "{text}");
        assert!(text.contains("relreward_serving_queries_total{model=\"r\",outcome=\"success\"} 2"), "{text}");
    }

    #[test]
    fn methods_come_from_the_descriptor_sets_and_codes_from_grpc_status() {
        assert_eq!(method_label("/relreward.v1.DatasetService/GetDataset"), GET_DATASET);
        assert_eq!(method_label("/grpc.health.v1.Health/Check"), "grpc.health.v1.Health/Check");
        assert_eq!(
            method_label("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"),
            "grpc.reflection.v1.ServerReflection/ServerReflectionInfo"
        );
        assert_eq!(method_label("/relreward.v1.DatasetService/Invented"), UNKNOWN_METHOD);
        assert_eq!(method_label("/"), UNKNOWN_METHOD);
        assert_eq!(status_code(&trailers("0")), Some("OK"));
        assert_eq!(status_code(&trailers("5")), Some("NOT_FOUND"));
        assert_eq!(status_code(&trailers("16")), Some("UNAUTHENTICATED"));
        assert_eq!(status_code(&trailers("17")), Some("UNKNOWN"));
        assert_eq!(status_code(&trailers("x")), Some("UNKNOWN"));
        assert_eq!(status_code(&HeaderMap::new()), None);
    }

    #[tokio::test]
    async fn the_body_records_the_code_of_its_trailers_once() {
        let m = Metrics::new();
        let mut b = body(&m, vec![Ok(Frame::data(Bytes::from_static(b"payload"))), Ok(Frame::trailers(trailers("5")))]);
        let first = b.frame().await.expect("frame").expect("ok");
        assert_eq!(first.into_data().ok(), Some(Bytes::from_static(b"payload")), "frames pass through");
        assert_eq!(count(&m.render(), GET_DATASET, "NOT_FOUND"), None, "not recorded before the trailers");
        let last = b.frame().await.expect("frame").expect("ok");
        assert!(last.is_trailers());
        assert_eq!(count(&m.render(), GET_DATASET, "NOT_FOUND"), Some(1));
        assert!(b.frame().await.is_none());
        drop(b);
        let text = m.render();
        assert_eq!(count(&text, GET_DATASET, "NOT_FOUND"), Some(1), "end and drop do not record again");
        assert!(
            text.contains("relreward_grpc_request_seconds_count{method=\"relreward.v1.DatasetService/GetDataset\"} 1")
        );
    }

    #[tokio::test]
    async fn a_body_without_trailers_is_unknown_and_one_dropped_early_is_cancelled() {
        let m = Metrics::new();
        let mut ended = body(&m, vec![Ok(Frame::data(Bytes::from_static(b"x")))]);
        while ended.frame().await.is_some() {}
        assert_eq!(count(&m.render(), GET_DATASET, "UNKNOWN"), Some(1));
        let mut dropped = body(&m, vec![Ok(Frame::data(Bytes::from_static(b"x"))), Ok(Frame::trailers(trailers("0")))]);
        let _ = dropped.frame().await;
        drop(dropped);
        let text = m.render();
        assert_eq!(count(&text, GET_DATASET, "CANCELLED"), Some(1), "{text}");
        assert_eq!(count(&text, GET_DATASET, "OK"), None);
    }

    /// Answers every request with the given `grpc-status` header (trailers-only) or none.
    #[derive(Clone)]
    struct Answer(Option<&'static str>);

    impl Service<Request<()>> for Answer {
        type Response = Response<Full<Bytes>>;
        type Error = Infallible;
        type Future = std::future::Ready<Result<Self::Response, Infallible>>;

        fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
            Poll::Ready(Ok(()))
        }

        fn call(&mut self, _: Request<()>) -> Self::Future {
            let mut response = Response::new(Full::new(Bytes::new()));
            if let Some(code) = self.0 {
                response.headers_mut().insert(GRPC_STATUS, HeaderValue::from_static(code));
            }
            std::future::ready(Ok(response))
        }
    }

    fn request(path: &str) -> Request<()> {
        Request::builder().uri(path).body(()).expect("request")
    }

    #[tokio::test]
    async fn the_layer_takes_trailers_only_codes_from_the_headers() {
        let m = Metrics::new();
        let mut svc = GrpcMetricsLayer::new(m.clone()).layer(Answer(Some("3")));
        let response = svc.call(request("/relreward.v1.DatasetService/GetDataset")).await.expect("response");
        assert_eq!(count(&m.render(), GET_DATASET, "INVALID_ARGUMENT"), Some(1), "recorded with the headers");
        let _ = response.into_body().collect().await;
        let mut svc = GrpcMetricsLayer::new(m.clone()).layer(Answer(None));
        let pending = svc.call(request("/no.Such/Path"));
        drop(pending);
        let text = m.render();
        assert_eq!(count(&text, GET_DATASET, "INVALID_ARGUMENT"), Some(1), "{text}");
        assert_eq!(count(&text, UNKNOWN_METHOD, "CANCELLED"), Some(1), "{text}");
    }

    async fn http_get(addr: std::net::SocketAddr, request: &str) -> String {
        let mut stream = tokio::net::TcpStream::connect(addr).await.expect("connect");
        stream.write_all(request.as_bytes()).await.expect("write");
        let mut out = String::new();
        stream.read_to_string(&mut out).await.expect("read");
        out
    }

    #[tokio::test]
    async fn the_endpoint_serves_metrics_refreshed_at_scrape_time_and_404_otherwise() {
        let m = Metrics::new();
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("addr");
        let shutdown = CancellationToken::new();
        let scrapes = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let refresh = {
            let (m, scrapes) = (m.clone(), scrapes.clone());
            move || {
                let (m, scrapes) = (m.clone(), scrapes.clone());
                async move {
                    let n = scrapes.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
                    m.set_loaded_models(n);
                }
            }
        };
        let server = tokio::spawn(serve_http(listener, m.clone(), refresh, shutdown.clone()));
        let (a, b) = tokio::join!(
            http_get(addr, "GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"),
            http_get(
                addr,
                "POST /metrics?x=1 HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\nConnection: close\r\n\r\nhello"
            ),
        );
        assert!(a.starts_with("HTTP/1.1 200 OK\r\n"), "{a}");
        assert!(a.to_ascii_lowercase().contains("content-type: text/plain; version=0.0.4\r\n"), "{a}");
        assert!(a.contains("relreward_loaded_models 1"), "{a}");
        assert!(b.starts_with("HTTP/1.1 404 Not Found\r\n"), "{b}");
        let c = http_get(addr, "GET /other HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").await;
        assert!(c.starts_with("HTTP/1.1 404 Not Found\r\n"), "{c}");
        assert_eq!(scrapes.load(std::sync::atomic::Ordering::SeqCst), 1, "only scrapes refresh");
        // An idle keep-alive connection does not hold shutdown up.
        let _idle = tokio::net::TcpStream::connect(addr).await.expect("connect");
        shutdown.cancel();
        tokio::time::timeout(Duration::from_secs(5), server).await.expect("stops").expect("task");
        assert!(tokio::net::TcpStream::connect(addr).await.is_err(), "listener closed");
    }
}
