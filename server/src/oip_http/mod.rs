//! The Open Inference Protocol over HTTP/JSON (KServe v2 REST, as Triton serves it), on its own
//! listener (`oip_http.listen`; off when empty), so that HTTP clients such as Python's
//! `tritonclient.http`, `curl` or an RL trainer's reward client score and differentiate reward
//! models with no gRPC stack.
//!
//! It is a third door onto the same [`Inference`] as the gRPC OIP (and through it onto
//! [`crate::serving::Serving`]): every route becomes the gRPC request it stands for, so the
//! validation, batching, numbers and statistics are those of the gRPC endpoints, bit for bit.
//! What is here is the translation:
//! - routes: `GET /v2/health/live`, `GET /v2/health/ready`, `GET /v2`, `GET /v2/models/stats`,
//!   and per model (optionally `/versions/{v}` after the name) `GET /v2/models/{name}`,
//!   `.../ready`, `.../config`, `.../stats` and `POST .../infer`; `POST /v2/repository/index`;
//! - infer bodies: JSON tensors (`data`, flat or nested, row-major), and the binary tensor
//!   extension both ways (`Inference-Header-Content-Length`; inputs with
//!   `parameters.binary_data_size`, outputs asked with `parameters.binary_data` or the request's
//!   `binary_data_output`), which is what `tritonclient.http` sends by default; the request
//!   parameter `timeout` (microseconds, Triton's) is the query's deadline;
//! - gzip or deflate request bodies (`Content-Encoding`) and responses (`Accept-Encoding`);
//! - errors: an HTTP status from the gRPC code the same request would get, and a JSON body
//!   `{"error": "..."}` whose message names the field, as the gRPC message does.
//!
//! Access control and TLS are the gRPC listener's: each route is authorized as the gRPC method
//! it stands for ([`crate::security::scopes`]' one table, `authorization: Bearer <token>`), and
//! with `security.tls` the listener speaks TLS only (mutual TLS included). Bodies are bounded
//! by `server.max_request_bytes` (after decompression too), connections by
//! `server.max_connections`.
//!
//! Layering: above [`crate::security`] and [`crate::api`] (it uses both), like `run`.
//!
//! Module map: here the listener, the routes, authorization and the answers' HTTP form;
//! [`infer`] the infer body's translation (JSON and binary tensors to the gRPC request and
//! back); [`messages`] config and statistics in Triton's JSON.

mod infer;
mod messages;

use std::convert::Infallible;
use std::io::{Read, Write};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use bytes::Bytes;
use http::header::{ACCEPT_ENCODING, ALLOW, CONTENT_ENCODING, CONTENT_LENGTH, CONTENT_TYPE, WWW_AUTHENTICATE};
use http::{HeaderMap, HeaderValue, Method, Request, Response, StatusCode};
use http_body_util::{BodyExt, Full, Limited};
use hyper_util::rt::{TokioIo, TokioTimer};
use relreward_proto::inference as pb;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tonic::Code;
use tracing::Instrument;

use self::infer::{infer_reply, infer_request, request_timeout};
use self::messages::{config_json, statistics_json};
use crate::api::oip::Inference;
use crate::error::{Error, quote};
use crate::metrics::Metrics;
use crate::security::Policy;

/// How long a connection may take to send its request headers (and a TLS client its handshake).
const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// How long connections get to finish the request in flight once the listener stops.
const CLOSE_GRACE: Duration = Duration::from_secs(5);

/// What one listener needs to answer requests.
pub struct OipHttp {
    inference: Inference,
    metrics: Metrics,
    policy: Arc<Policy>,
    max_request_bytes: usize,
    default_deadline: Option<Duration>,
    /// Cancelled when the shutdown drain starts: readiness then answers 503, as gRPC health
    /// answers NOT_SERVING.
    draining: CancellationToken,
}

impl OipHttp {
    pub fn new(
        inference: Inference,
        metrics: Metrics,
        policy: Arc<Policy>,
        max_request_bytes: usize,
        default_deadline_ms: u64,
        draining: CancellationToken,
    ) -> Self {
        let default_deadline = (default_deadline_ms > 0).then(|| Duration::from_millis(default_deadline_ms));
        Self { inference, metrics, policy, max_request_bytes, default_deadline, draining }
    }
}

// ---------------------------------------------------------------------------------------------
// The listener.

/// Serves `listener` (through `tls` when set) until `shutdown` is cancelled; then stops
/// accepting, lets each connection finish the request it is answering (at most
/// [`CLOSE_GRACE`]) and returns. At most `max_connections` connections are served at once; one
/// more is closed at once.
pub async fn serve(
    listener: TcpListener,
    tls: Option<tokio_rustls::TlsAcceptor>,
    service: Arc<OipHttp>,
    max_connections: usize,
    shutdown: CancellationToken,
) {
    let connections = TaskTracker::new();
    let slots = Arc::new(tokio::sync::Semaphore::new(max_connections));
    loop {
        let (stream, remote) = tokio::select! {
            () = shutdown.cancelled() => break,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    tracing::warn!(error = %e, "oip_http: accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let Ok(permit) = slots.clone().try_acquire_owned() else {
            tracing::warn!(%remote, max_connections, "oip_http: connection refused (server.max_connections)");
            continue;
        };
        let _ = stream.set_nodelay(true);
        let (service, tls, shutdown) = (service.clone(), tls.clone(), shutdown.clone());
        connections.spawn(async move {
            let _permit = permit;
            match tls {
                None => connection(stream, remote, service, shutdown).await,
                Some(acceptor) => match tokio::time::timeout(HEADER_READ_TIMEOUT, acceptor.accept(stream)).await {
                    Ok(Ok(stream)) => connection(stream, remote, service, shutdown).await,
                    Ok(Err(e)) => tracing::debug!(%remote, error = %e, "oip_http: TLS handshake failed"),
                    Err(_) => tracing::debug!(%remote, "oip_http: TLS handshake timed out"),
                },
            }
        });
    }
    drop(listener);
    connections.close();
    connections.wait().await;
}

async fn connection<S>(stream: S, remote: SocketAddr, service: Arc<OipHttp>, shutdown: CancellationToken)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    let handler = hyper::service::service_fn(move |request: Request<hyper::body::Incoming>| {
        let service = service.clone();
        async move { Ok::<_, Infallible>(service.handle(request, remote).await) }
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder.timer(TokioTimer::new()).header_read_timeout(HEADER_READ_TIMEOUT);
    let conn = builder.serve_connection(TokioIo::new(stream), handler);
    tokio::pin!(conn);
    let result = tokio::select! {
        result = conn.as_mut() => result,
        () = shutdown.cancelled() => {
            // Finish the request in flight (if any), then close.
            conn.as_mut().graceful_shutdown();
            tokio::time::timeout(CLOSE_GRACE, conn.as_mut()).await.unwrap_or(Ok(()))
        }
    };
    if let Err(e) = result {
        tracing::debug!(%remote, error = %e, "oip_http: connection ended with an error");
    }
}

// ---------------------------------------------------------------------------------------------
// Routes.

/// A request's route: what it asks, and the gRPC method whose access rule applies.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Route {
    Live,
    Ready,
    ServerMetadata,
    /// Statistics of every model (empty name) or of one.
    Stats {
        name: String,
        version: String,
    },
    Metadata {
        name: String,
        version: String,
    },
    ModelReady {
        name: String,
        version: String,
    },
    Config {
        name: String,
        version: String,
    },
    Infer {
        name: String,
        version: String,
    },
    Index,
}

impl Route {
    /// The gRPC method this route stands for, for [`Policy::authorize`].
    fn grpc_path(&self) -> &'static str {
        match self {
            Self::Live => "/inference.GRPCInferenceService/ServerLive",
            Self::Ready => "/inference.GRPCInferenceService/ServerReady",
            Self::ServerMetadata => "/inference.GRPCInferenceService/ServerMetadata",
            Self::Stats { .. } => "/inference.GRPCInferenceService/ModelStatistics",
            Self::Metadata { .. } => "/inference.GRPCInferenceService/ModelMetadata",
            Self::ModelReady { .. } => "/inference.GRPCInferenceService/ModelReady",
            Self::Config { .. } => "/inference.GRPCInferenceService/ModelConfig",
            Self::Infer { .. } => "/inference.GRPCInferenceService/ModelInfer",
            Self::Index => "/inference.GRPCInferenceService/RepositoryIndex",
        }
    }

    /// The `route` label of `relreward_oip_http_requests_total`.
    fn label(&self) -> &'static str {
        match self {
            Self::Live => "live",
            Self::Ready => "ready",
            Self::ServerMetadata => "server_metadata",
            Self::Stats { .. } => "stats",
            Self::Metadata { .. } => "metadata",
            Self::ModelReady { .. } => "model_ready",
            Self::Config { .. } => "config",
            Self::Infer { .. } => "infer",
            Self::Index => "index",
        }
    }

    fn method(&self) -> Method {
        match self {
            Self::Infer { .. } | Self::Index => Method::POST,
            _ => Method::GET,
        }
    }
}

/// `%XX` escapes decoded (tritonclient quotes model names); a malformed escape or a name that
/// is not UTF-8 is kept as written, for the name check to refuse.
fn percent_decode(segment: &str) -> String {
    let bytes = segment.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |b: u8| (b as char).to_digit(16);
        if bytes[i] == b'%'
            && let (Some(h), Some(l)) = (bytes.get(i + 1).and_then(|&b| hex(b)), bytes.get(i + 2).and_then(|&b| hex(b)))
        {
            out.push((h * 16 + l) as u8);
            i += 3;
            continue;
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8(out).unwrap_or_else(|_| segment.to_owned())
}

/// The route of `path`, or None (404).
fn route(path: &str) -> Option<Route> {
    let segments: Vec<&str> = path.trim_end_matches('/').split('/').skip(1).collect();
    let model = |name: &str, rest: &[&str]| -> Option<Route> {
        let name = percent_decode(name);
        let (version, rest) = match rest {
            ["versions", v, rest @ ..] => (percent_decode(v), rest),
            _ => (String::new(), rest),
        };
        Some(match rest {
            [] => Route::Metadata { name, version },
            ["ready"] => Route::ModelReady { name, version },
            ["config"] => Route::Config { name, version },
            ["stats"] => Route::Stats { name, version },
            ["infer"] => Route::Infer { name, version },
            _ => return None,
        })
    };
    match segments.as_slice() {
        ["v2"] => Some(Route::ServerMetadata),
        ["v2", "health", "live"] => Some(Route::Live),
        ["v2", "health", "ready"] => Some(Route::Ready),
        ["v2", "models", "stats"] => Some(Route::Stats { name: String::new(), version: String::new() }),
        ["v2", "models", name, rest @ ..] => model(name, rest),
        ["v2", "repository", "index"] => Some(Route::Index),
        _ => None,
    }
}

// ---------------------------------------------------------------------------------------------
// Answers.

/// A response with a body and the encoding the client accepts.
struct Reply {
    status: StatusCode,
    content_type: &'static str,
    body: Vec<u8>,
    headers: Vec<(http::HeaderName, HeaderValue)>,
}

impl Reply {
    fn json(status: StatusCode, value: &impl Serialize) -> Self {
        // Serializing our own types cannot fail (no maps with non-string keys).
        let body = serde_json::to_vec(value).unwrap_or_else(|_| b"{}".to_vec());
        Self { status, content_type: "application/json", body, headers: Vec::new() }
    }

    /// `{"error": message}` with the HTTP status for `code`.
    fn error(code: Code, message: &str) -> Self {
        let mut reply = Self::json(http_status(code), &json!({ "error": message }));
        if code == Code::Unauthenticated {
            reply.headers.push((WWW_AUTHENTICATE, HeaderValue::from_static("Bearer")));
        }
        reply
    }

    fn from_error(e: Error) -> Self {
        let status = tonic::Status::from(e);
        Self::error(status.code(), status.message())
    }
}

/// The HTTP status for a gRPC code (KServe v2: 400 for a bad request, 404 for an unknown model).
fn http_status(code: Code) -> StatusCode {
    match code {
        Code::Ok => StatusCode::OK,
        Code::InvalidArgument | Code::OutOfRange => StatusCode::BAD_REQUEST,
        Code::Unauthenticated => StatusCode::UNAUTHORIZED,
        Code::PermissionDenied => StatusCode::FORBIDDEN,
        Code::NotFound => StatusCode::NOT_FOUND,
        Code::AlreadyExists | Code::Aborted | Code::FailedPrecondition => StatusCode::CONFLICT,
        Code::ResourceExhausted => StatusCode::TOO_MANY_REQUESTS,
        Code::Unimplemented => StatusCode::NOT_IMPLEMENTED,
        Code::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
        Code::DeadlineExceeded => StatusCode::GATEWAY_TIMEOUT,
        Code::Cancelled | Code::Unknown | Code::Internal | Code::DataLoss => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

/// The encoding of a gzip or deflate body the client accepts (`Accept-Encoding`), if any.
fn accepted_encoding(headers: &HeaderMap) -> Option<&'static str> {
    let accepted = headers.get(ACCEPT_ENCODING)?.to_str().ok()?;
    let offers: Vec<&str> = accepted.split(',').map(|s| s.split(';').next().unwrap_or("").trim()).collect();
    ["gzip", "deflate"].into_iter().find(|e| offers.contains(e))
}

fn compress(encoding: &str, body: &[u8]) -> std::io::Result<Vec<u8>> {
    let level = flate2::Compression::fast();
    if encoding == "gzip" {
        let mut w = flate2::write::GzEncoder::new(Vec::new(), level);
        w.write_all(body)?;
        w.finish()
    } else {
        // HTTP's "deflate" is the zlib format (RFC 9110, 8.4.1.2).
        let mut w = flate2::write::ZlibEncoder::new(Vec::new(), level);
        w.write_all(body)?;
        w.finish()
    }
}

fn finish(reply: Reply, encoding: Option<&'static str>) -> Response<Full<Bytes>> {
    let Reply { status, content_type, mut body, headers } = reply;
    let mut encoded = None;
    if let Some(encoding) = encoding.filter(|_| !body.is_empty())
        && let Ok(compressed) = compress(encoding, &body)
    {
        body = compressed;
        encoded = Some(encoding);
    }
    let mut response = Response::new(Full::new(Bytes::from(body)));
    *response.status_mut() = status;
    let h = response.headers_mut();
    h.insert(CONTENT_TYPE, HeaderValue::from_static(content_type));
    if let Some(encoding) = encoded {
        h.insert(CONTENT_ENCODING, HeaderValue::from_static(encoding));
    }
    for (name, value) in headers {
        h.insert(name, value);
    }
    response
}

// ---------------------------------------------------------------------------------------------
// Requests.

impl OipHttp {
    async fn handle(&self, request: Request<hyper::body::Incoming>, remote: SocketAddr) -> Response<Full<Bytes>> {
        let encoding = accepted_encoding(request.headers());
        let path = request.uri().path().to_owned();
        let span = tracing::info_span!("oip_http", method = %request.method(), path = %quote(&path), %remote);
        let start = Instant::now();
        let label = route(&path).map_or("unknown", |r| r.label());
        let reply = self.answer(request, &path).instrument(span).await;
        self.metrics.observe_http(label, reply.status.as_u16(), start.elapsed().as_secs_f64());
        finish(reply, encoding)
    }

    async fn answer(&self, request: Request<hyper::body::Incoming>, path: &str) -> Reply {
        let Some(route) = route(path) else {
            return Reply::error(
                Code::NotFound,
                &format!("no endpoint {}; this server speaks KServe v2 under /v2", quote(path)),
            );
        };
        // HEAD answers as GET, without the body (hyper leaves it out).
        let method = if request.method() == Method::HEAD { Method::GET } else { request.method().clone() };
        if method != route.method() {
            let mut reply = Reply::error(
                Code::InvalidArgument,
                &format!("{} takes {}, not {}", quote(path), route.method(), request.method()),
            );
            reply.status = StatusCode::METHOD_NOT_ALLOWED;
            let allow = if route.method() == Method::POST { "POST" } else { "GET, HEAD" };
            reply.headers.push((ALLOW, HeaderValue::from_static(allow)));
            return reply;
        }
        // Authorized before the body is read or any model looked up, as on gRPC.
        if let Err(status) = self.policy.authorize(route.grpc_path(), request.headers(), SystemTime::now()) {
            return Reply::error(status.code(), status.message());
        }
        let (parts, body) = request.into_parts();
        let body = if method == Method::POST {
            match self.read_body(&parts.headers, body).await {
                Ok(body) => body,
                Err(reply) => return reply,
            }
        } else {
            Bytes::new()
        };
        match self.dispatch(route, &parts.headers, body).await {
            Ok(reply) => reply,
            Err(e) => Reply::from_error(e),
        }
    }

    /// The request body, decompressed, at most `server.max_request_bytes` either way.
    async fn read_body(&self, headers: &HeaderMap, body: hyper::body::Incoming) -> Result<Bytes, Reply> {
        let limit = self.max_request_bytes;
        let too_large = || {
            let mut reply = Reply::error(
                Code::ResourceExhausted,
                &format!("request body: larger than server.max_request_bytes ({limit} bytes)"),
            );
            reply.status = StatusCode::PAYLOAD_TOO_LARGE;
            reply
        };
        let declared = headers.get(CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());
        if declared.is_some_and(|n| n > limit as u64) {
            return Err(too_large());
        }
        let body = match Limited::new(body, limit).collect().await {
            Ok(collected) => collected.to_bytes(),
            Err(e) if e.downcast_ref::<http_body_util::LengthLimitError>().is_some() => return Err(too_large()),
            Err(e) => {
                return Err(Reply::error(Code::InvalidArgument, &format!("request body: cannot be read: {e}")));
            }
        };
        let encoding = headers.get(CONTENT_ENCODING).map(|v| v.to_str().unwrap_or("?").trim().to_ascii_lowercase());
        let mut decoded = Vec::new();
        let read = match encoding.as_deref() {
            None | Some("identity") => return Ok(body),
            Some("gzip") => flate2::read::GzDecoder::new(&body[..]).take(limit as u64 + 1).read_to_end(&mut decoded),
            Some("deflate") => {
                flate2::read::ZlibDecoder::new(&body[..]).take(limit as u64 + 1).read_to_end(&mut decoded)
            }
            Some(other) => {
                let mut reply = Reply::error(
                    Code::InvalidArgument,
                    &format!("Content-Encoding: {} is not supported (gzip, deflate or identity)", quote(other)),
                );
                reply.status = StatusCode::UNSUPPORTED_MEDIA_TYPE;
                return Err(reply);
            }
        };
        match read {
            Ok(n) if n > limit => Err(too_large()),
            Ok(_) => Ok(Bytes::from(decoded)),
            Err(e) => Err(Reply::error(Code::InvalidArgument, &format!("request body: cannot be decompressed: {e}"))),
        }
    }

    async fn dispatch(&self, route: Route, headers: &HeaderMap, body: Bytes) -> crate::error::Result<Reply> {
        let inference = &self.inference;
        Ok(match route {
            Route::Live => Reply::json(StatusCode::OK, &json!({ "live": true })),
            Route::Ready => {
                if self.draining.is_cancelled() {
                    Reply::error(Code::Unavailable, "the server is shutting down")
                } else {
                    Reply::json(StatusCode::OK, &json!({ "ready": true }))
                }
            }
            Route::ServerMetadata => Reply::json(
                StatusCode::OK,
                &json!({
                    "name": "relreward",
                    "version": env!("CARGO_PKG_VERSION"),
                    "extensions": ["binary_tensor_data"],
                }),
            ),
            Route::Metadata { name, version } => {
                let m = inference.metadata(pb::ModelMetadataRequest { name, version }).await?;
                let tensors = |list: &[pb::model_metadata_response::TensorMetadata]| -> Vec<Value> {
                    list.iter().map(|t| json!({ "name": t.name, "datatype": t.datatype, "shape": t.shape })).collect()
                };
                Reply::json(
                    StatusCode::OK,
                    &json!({
                        "name": m.name,
                        "versions": m.versions,
                        "platform": m.platform,
                        "inputs": tensors(&m.inputs),
                        "outputs": tensors(&m.outputs),
                    }),
                )
            }
            Route::ModelReady { name, version } => {
                if inference.ready(pb::ModelReadyRequest { name: name.clone(), version }).await? {
                    Reply::json(StatusCode::OK, &json!({ "name": name, "ready": true }))
                } else {
                    // KServe: any status but 200 means not ready; Triton answers 400.
                    let mut reply =
                        Reply::error(Code::InvalidArgument, &format!("model {} is not ready", quote(&name)));
                    reply.status = StatusCode::BAD_REQUEST;
                    reply
                }
            }
            Route::Config { name, version } => {
                let c = inference.config(pb::ModelConfigRequest { name, version }).await?;
                Reply::json(StatusCode::OK, &config_json(c.config.unwrap_or_default()))
            }
            Route::Stats { name, version } => {
                let s = inference.statistics(pb::ModelStatisticsRequest { name, version }).await?;
                let stats: Vec<Value> = s.model_stats.iter().map(statistics_json).collect();
                Reply::json(StatusCode::OK, &json!({ "model_stats": stats }))
            }
            Route::Index => {
                let ready = if body.is_empty() {
                    false
                } else {
                    let index: IndexRequest = serde_json::from_slice(&body)
                        .map_err(|e| Error::invalid(format!("request body: not a repository index request: {e}")))?;
                    index.ready
                };
                let index =
                    inference.index(pb::RepositoryIndexRequest { repository_name: String::new(), ready }).await?;
                let models: Vec<Value> = index
                    .models
                    .iter()
                    .map(|m| json!({ "name": m.name, "version": m.version, "state": m.state, "reason": m.reason }))
                    .collect();
                Reply::json(StatusCode::OK, &models)
            }
            Route::Infer { name, version } => {
                let (request, binary_outputs) = infer_request(name, version, headers, &body)?;
                let deadline = request_timeout(&request)?.or(self.default_deadline).map(|d| Instant::now() + d);
                let response = inference.infer(request, deadline).await?;
                infer_reply(response, &binary_outputs)?
            }
        })
    }
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct IndexRequest {
    #[serde(default)]
    ready: bool,
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// A header map of `pairs` (also for `infer`'s tests).
    pub(in crate::oip_http) fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, HeaderValue::from_str(v).expect("value"));
        }
        h
    }

    #[test]
    fn routes_name_their_grpc_method() {
        assert_eq!(route("/v2"), Some(Route::ServerMetadata));
        assert_eq!(route("/v2/"), Some(Route::ServerMetadata));
        assert_eq!(route("/v2/health/live"), Some(Route::Live));
        assert_eq!(route("/v2/health/ready"), Some(Route::Ready));
        assert_eq!(route("/v2/models/r%2Dx"), Some(Route::Metadata { name: "r-x".into(), version: String::new() }));
        assert_eq!(
            route("/v2/models/r/versions/1/infer"),
            Some(Route::Infer { name: "r".into(), version: "1".into() })
        );
        assert_eq!(route("/v2/models/r/ready"), Some(Route::ModelReady { name: "r".into(), version: String::new() }));
        assert_eq!(route("/v2/models/r/config"), Some(Route::Config { name: "r".into(), version: String::new() }));
        assert_eq!(route("/v2/models/stats"), Some(Route::Stats { name: String::new(), version: String::new() }));
        assert_eq!(route("/v2/models/r/stats"), Some(Route::Stats { name: "r".into(), version: String::new() }));
        assert_eq!(route("/v2/repository/index"), Some(Route::Index));
        for missing in ["/", "/v1/models/r", "/v2/models/r/explain", "/v2/models/r/versions", "/metrics"] {
            assert_eq!(route(missing), None, "{missing}");
        }
        assert_eq!(percent_decode("a%zz%41"), "a%zzA");
        assert_eq!(
            Route::Infer { name: "r".into(), version: String::new() }.grpc_path(),
            "/inference.GRPCInferenceService/ModelInfer"
        );
    }

    #[test]
    fn statuses_follow_the_grpc_codes() {
        assert_eq!(http_status(Code::InvalidArgument), StatusCode::BAD_REQUEST);
        assert_eq!(http_status(Code::NotFound), StatusCode::NOT_FOUND);
        assert_eq!(http_status(Code::Unauthenticated), StatusCode::UNAUTHORIZED);
        assert_eq!(http_status(Code::PermissionDenied), StatusCode::FORBIDDEN);
        assert_eq!(http_status(Code::FailedPrecondition), StatusCode::CONFLICT);
        assert_eq!(http_status(Code::DeadlineExceeded), StatusCode::GATEWAY_TIMEOUT);
        let reply = Reply::error(Code::Unauthenticated, "authorization: missing");
        assert_eq!(reply.headers[0].0, WWW_AUTHENTICATE);
        assert_eq!(accepted_encoding(&headers(&[("accept-encoding", "br, deflate;q=0.5")])), Some("deflate"));
        assert_eq!(accepted_encoding(&headers(&[("accept-encoding", "br")])), None);
    }
}
