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
use relreward_proto::inference::{
    self as pb, InferParameter, infer_parameter::ParameterChoice, model_infer_request::InferInputTensor,
    model_infer_request::InferRequestedOutputTensor,
};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value, json};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tonic::Code;
use tracing::Instrument;

use crate::api::oip::Inference;
use crate::error::{Error, brief, quote};
use crate::metrics::Metrics;
use crate::security::Policy;

/// The header of the binary tensor extension: the JSON part's length in bytes.
const HEADER_LENGTH: &str = "inference-header-content-length";
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

/// The request's `timeout` parameter (microseconds, as Triton's HTTP API takes it).
fn request_timeout(request: &pb::ModelInferRequest) -> crate::error::Result<Option<Duration>> {
    match request.parameters.get("timeout").and_then(|p| p.parameter_choice.as_ref()) {
        None => Ok(None),
        Some(ParameterChoice::Int64Param(us)) if *us > 0 => Ok(Some(Duration::from_micros(*us as u64))),
        Some(ParameterChoice::Uint64Param(us)) if *us > 0 => Ok(Some(Duration::from_micros(*us))),
        Some(other) => Err(Error::invalid(format!(
            "parameters.timeout: expected a positive integer of microseconds, got {}",
            brief(other)
        ))),
    }
}

// ---------------------------------------------------------------------------------------------
// Infer: JSON (and binary) to the gRPC request and back.

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InferRequestJson {
    #[serde(default)]
    id: String,
    #[serde(default)]
    parameters: Map<String, Value>,
    inputs: Vec<InputJson>,
    #[serde(default)]
    outputs: Vec<OutputJson>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InputJson {
    name: String,
    shape: Vec<i64>,
    datatype: String,
    #[serde(default)]
    parameters: Map<String, Value>,
    #[serde(default)]
    data: Option<Value>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct OutputJson {
    name: String,
    #[serde(default)]
    parameters: Map<String, Value>,
}

/// A JSON parameter as the gRPC request carries it.
fn parameter(field: &str, value: &Value) -> crate::error::Result<InferParameter> {
    let choice = match value {
        Value::Bool(b) => ParameterChoice::BoolParam(*b),
        Value::String(s) => ParameterChoice::StringParam(s.clone()),
        Value::Number(n) => match (n.as_i64(), n.as_u64(), n.as_f64()) {
            (Some(i), _, _) => ParameterChoice::Int64Param(i),
            (None, Some(u), _) => ParameterChoice::Uint64Param(u),
            (None, None, Some(f)) => ParameterChoice::DoubleParam(f),
            _ => return Err(Error::invalid(format!("{field}: not a number a parameter can hold"))),
        },
        _ => return Err(Error::invalid(format!("{field}: a parameter is a bool, a number or a string"))),
    };
    Ok(InferParameter { parameter_choice: Some(choice) })
}

/// The parameters the gRPC request carries, without the REST-only keys in `skip`.
fn parameters(
    what: &str,
    map: &Map<String, Value>,
    skip: &[&str],
) -> crate::error::Result<std::collections::HashMap<String, InferParameter>> {
    map.iter()
        .filter(|(k, _)| !skip.contains(&k.as_str()))
        .map(|(k, v)| Ok((k.clone(), parameter(&format!("{what}.parameters.{k}"), v)?)))
        .collect()
}

/// The bytes per element of the datatypes reward models take (others are refused by name in
/// [`Inference::infer`], whose checks come before any count).
fn element_bytes(datatype: &str) -> Option<usize> {
    match datatype {
        "FP32" => Some(4),
        "INT64" => Some(8),
        _ => None,
    }
}

/// `data` flattened in row-major order (nested arrays or already flat) into little-endian
/// bytes of `datatype`.
fn encode_data(name: &str, datatype: &str, data: &Value) -> crate::error::Result<(usize, Vec<u8>)> {
    fn walk(v: &Value, out: &mut Vec<Value>) {
        match v {
            Value::Array(items) => items.iter().for_each(|i| walk(i, out)),
            other => out.push(other.clone()),
        }
    }
    let mut flat = Vec::new();
    walk(data, &mut flat);
    let mut bytes = Vec::with_capacity(flat.len() * element_bytes(datatype).unwrap_or(0));
    for (i, v) in flat.iter().enumerate() {
        match datatype {
            "FP32" => {
                let f = v
                    .as_f64()
                    .ok_or_else(|| Error::invalid(format!("{name}: data[{i}] is {}, not a number", json_text(v))))?;
                bytes.extend_from_slice(&(f as f32).to_le_bytes());
            }
            "INT64" => {
                let n = v
                    .as_i64()
                    .ok_or_else(|| Error::invalid(format!("{name}: data[{i}] is {}, not an integer", json_text(v))))?;
                bytes.extend_from_slice(&n.to_le_bytes());
            }
            _ => {}
        }
    }
    Ok((flat.len(), bytes))
}

/// The ModelInferRequest a REST infer body stands for (every input's data as raw contents),
/// and for each output the gRPC answer will carry (in request order; all when none is named)
/// whether it goes back as binary.
fn infer_request(
    name: String,
    version: String,
    headers: &HeaderMap,
    body: &[u8],
) -> crate::error::Result<(pb::ModelInferRequest, Vec<(String, bool)>)> {
    let (json, mut binary) = match headers.get(HEADER_LENGTH) {
        None => (body, &[][..]),
        Some(v) => {
            let n = v.to_str().ok().and_then(|s| s.trim().parse::<usize>().ok()).ok_or_else(|| {
                Error::invalid(format!("Inference-Header-Content-Length: {} is not a byte count", brief(v)))
            })?;
            if n > body.len() {
                return Err(Error::invalid(format!(
                    "Inference-Header-Content-Length: {n} bytes, but the body has {}",
                    body.len()
                )));
            }
            body.split_at(n)
        }
    };
    let parsed: InferRequestJson = serde_json::from_slice(json)
        .map_err(|e| Error::invalid(format!("request body: not a KServe v2 inference request: {e}")))?;
    let mut request = pb::ModelInferRequest {
        model_name: name,
        model_version: version,
        id: parsed.id,
        parameters: parameters("request", &parsed.parameters, &["binary_data_output"])?,
        ..Default::default()
    };
    for input in parsed.inputs {
        let InputJson { name, shape, datatype, parameters: params, data } = input;
        let size = params.get("binary_data_size");
        let raw = match (size, data) {
            (Some(size), None) => {
                let size = size.as_u64().and_then(|s| usize::try_from(s).ok()).ok_or_else(|| {
                    Error::invalid(format!(
                        "{name}: parameters.binary_data_size is {}, not a byte count",
                        json_text(size)
                    ))
                })?;
                if size > binary.len() {
                    return Err(Error::invalid(format!(
                        "{name}: parameters.binary_data_size is {size}, but only {} bytes of binary data are left",
                        binary.len()
                    )));
                }
                let (mine, rest) = binary.split_at(size);
                binary = rest;
                if let (Some(width), Ok(count)) = (element_bytes(&datatype), element_count(&shape))
                    && Some(size) != count.checked_mul(width)
                {
                    return Err(Error::invalid(format!(
                        "{name}: parameters.binary_data_size is {size}, but {datatype} shape {} needs {} bytes",
                        brief(&shape),
                        count.saturating_mul(width)
                    )));
                }
                mine.to_vec()
            }
            (None, Some(data)) => {
                let (values, bytes) = encode_data(&name, &datatype, &data)?;
                if let (Some(_), Ok(count)) = (element_bytes(&datatype), element_count(&shape))
                    && values != count
                {
                    return Err(Error::invalid(format!(
                        "{name}: data holds {values} values but shape {} needs {count}",
                        brief(&shape)
                    )));
                }
                bytes
            }
            (Some(_), Some(_)) => {
                return Err(Error::invalid(format!(
                    "{name}: both data and parameters.binary_data_size are given; send one"
                )));
            }
            (None, None) => {
                return Err(Error::invalid(format!(
                    "{name}: no data; give `data`, or binary data with parameters.binary_data_size"
                )));
            }
        };
        let parameters = parameters(&name, &params, &["binary_data_size"])?;
        request.inputs.push(InferInputTensor { name, datatype, shape, parameters, contents: None });
        request.raw_input_contents.push(Bytes::from(raw));
    }
    if !binary.is_empty() {
        return Err(Error::invalid(format!(
            "request body: {} bytes of binary data that no input's parameters.binary_data_size accounts for",
            binary.len()
        )));
    }
    let all_binary = match parsed.parameters.get("binary_data_output") {
        None => false,
        Some(Value::Bool(b)) => *b,
        Some(other) => {
            return Err(Error::invalid(format!(
                "request.parameters.binary_data_output: expected true or false, got {}",
                json_text(other)
            )));
        }
    };
    let mut binary_outputs = Vec::new();
    for output in parsed.outputs {
        let binary = match output.parameters.get("binary_data") {
            None => all_binary,
            Some(Value::Bool(b)) => *b,
            Some(other) => {
                return Err(Error::invalid(format!(
                    "{}: parameters.binary_data: expected true or false, got {}",
                    output.name,
                    json_text(other)
                )));
            }
        };
        let parameters = parameters(&output.name, &output.parameters, &["binary_data"])?;
        binary_outputs.push((output.name.clone(), binary));
        request.outputs.push(InferRequestedOutputTensor { name: output.name, parameters });
    }
    if binary_outputs.is_empty() {
        // None named: the server's choice of outputs, each in the request's default form.
        binary_outputs.push((String::new(), all_binary));
    }
    Ok((request, binary_outputs))
}

/// A JSON value as the client wrote it, shortened for a message.
fn json_text(v: &Value) -> String {
    quote(&v.to_string()).trim_matches('\'').to_owned()
}

fn element_count(shape: &[i64]) -> Result<usize, ()> {
    shape.iter().try_fold(1usize, |n, &d| usize::try_from(d).ok().and_then(|d| n.checked_mul(d)).ok_or(()))
}

#[derive(Serialize)]
struct OutputTensorJson<'a> {
    name: &'a str,
    datatype: &'a str,
    shape: &'a [i64],
    #[serde(skip_serializing_if = "Option::is_none")]
    parameters: Option<BinarySize>,
    /// FP32 values written as f32 (the shortest text that reads back as the same float).
    #[serde(skip_serializing_if = "Option::is_none")]
    data: Option<Vec<f32>>,
}

#[derive(Serialize)]
struct BinarySize {
    binary_data_size: usize,
}

#[derive(Serialize)]
struct InferResponseJson<'a> {
    model_name: &'a str,
    model_version: &'a str,
    #[serde(skip_serializing_if = "str::is_empty")]
    id: &'a str,
    outputs: Vec<OutputTensorJson<'a>>,
}

/// The REST answer to a gRPC infer response: JSON, or with the binary extension the JSON
/// header followed by the binary outputs in order.
fn infer_reply(response: pb::ModelInferResponse, binary_outputs: &[(String, bool)]) -> crate::error::Result<Reply> {
    // Named outputs come back in request order; with none named, one default applies to all.
    let is_binary =
        |name: &str| binary_outputs.iter().find(|(n, _)| n == name || n.is_empty()).is_some_and(|(_, binary)| *binary);
    let mut outputs = Vec::with_capacity(response.outputs.len());
    let mut blobs: Vec<&[u8]> = Vec::new();
    for (meta, raw) in response.outputs.iter().zip(&response.raw_output_contents) {
        let (parameters, data) = if is_binary(&meta.name) {
            blobs.push(raw);
            (Some(BinarySize { binary_data_size: raw.len() }), None)
        } else {
            let values = raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            (None, Some(values))
        };
        outputs.push(OutputTensorJson {
            name: &meta.name,
            datatype: &meta.datatype,
            shape: &meta.shape,
            parameters,
            data,
        });
    }
    let header = InferResponseJson {
        model_name: &response.model_name,
        model_version: &response.model_version,
        id: &response.id,
        outputs,
    };
    let mut body = serde_json::to_vec(&header).map_err(|e| Error::internal("infer response", e))?;
    if blobs.is_empty() {
        return Ok(Reply { status: StatusCode::OK, content_type: "application/json", body, headers: Vec::new() });
    }
    let json_length = body.len();
    for blob in blobs {
        body.extend_from_slice(blob);
    }
    let headers = vec![(http::HeaderName::from_static(HEADER_LENGTH), HeaderValue::from(json_length))];
    Ok(Reply { status: StatusCode::OK, content_type: "application/octet-stream", body, headers })
}

// ---------------------------------------------------------------------------------------------
// Config and statistics in Triton's JSON (the protobuf messages' field names, numbers as numbers).

fn config_json(c: pb::ModelConfig) -> Value {
    let data_type =
        |t: i32| pb::DataType::try_from(t).map_or_else(|_| "TYPE_INVALID".to_owned(), |t| t.as_str_name().to_owned());
    let reshape = |r: &Option<pb::ModelTensorReshape>| r.as_ref().map(|r| json!({ "shape": r.shape }));
    let inputs: Vec<Value> = c
        .input
        .iter()
        .map(|i| {
            let mut v =
                json!({ "name": i.name, "data_type": data_type(i.data_type), "dims": i.dims, "optional": i.optional });
            if let Some(r) = reshape(&i.reshape) {
                v["reshape"] = r;
            }
            v
        })
        .collect();
    let outputs: Vec<Value> = c
        .output
        .iter()
        .map(|o| {
            let mut v = json!({ "name": o.name, "data_type": data_type(o.data_type), "dims": o.dims });
            if let Some(r) = reshape(&o.reshape) {
                v["reshape"] = r;
            }
            v
        })
        .collect();
    let parameters: Map<String, Value> =
        c.parameters.iter().map(|(k, p)| (k.clone(), json!({ "string_value": p.string_value }))).collect();
    let mut config = json!({
        "name": c.name,
        "platform": c.platform,
        "backend": c.backend,
        "max_batch_size": c.max_batch_size,
        "input": inputs,
        "output": outputs,
        "parameters": parameters,
    });
    if let Some(pb::model_version_policy::PolicyChoice::Specific(s)) =
        c.version_policy.as_ref().and_then(|p| p.policy_choice.as_ref())
    {
        config["version_policy"] = json!({ "specific": { "versions": s.versions } });
    }
    if let Some(pb::model_config::SchedulingChoice::DynamicBatching(d)) = &c.scheduling_choice {
        let mut batching = json!({
            "preferred_batch_size": d.preferred_batch_size,
            "max_queue_delay_microseconds": d.max_queue_delay_microseconds,
            "preserve_ordering": d.preserve_ordering,
        });
        if let Some(q) = &d.default_queue_policy {
            let action =
                pb::model_queue_policy::TimeoutAction::try_from(q.timeout_action).map_or("REJECT", |a| a.as_str_name());
            batching["default_queue_policy"] = json!({
                "timeout_action": action,
                "default_timeout_microseconds": q.default_timeout_microseconds,
                "allow_timeout_override": q.allow_timeout_override,
                "max_queue_size": q.max_queue_size,
            });
        }
        config["dynamic_batching"] = batching;
    }
    config
}

fn statistics_json(s: &pb::ModelStatistics) -> Value {
    let d = |d: &Option<pb::StatisticDuration>| {
        let d = d.unwrap_or_default();
        json!({ "count": d.count, "ns": d.ns })
    };
    let i = s.inference_stats.unwrap_or_default();
    json!({
        "name": s.name,
        "version": s.version,
        "last_inference": s.last_inference,
        "inference_count": s.inference_count,
        "execution_count": s.execution_count,
        "inference_stats": {
            "success": d(&i.success),
            "fail": d(&i.fail),
            "queue": d(&i.queue),
            "compute_input": d(&i.compute_input),
            "compute_infer": d(&i.compute_infer),
            "compute_output": d(&i.compute_output),
            "cache_hit": d(&i.cache_hit),
            "cache_miss": d(&i.cache_miss),
        },
        "batch_stats": [],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
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
    fn json_inputs_become_raw_contents_flat_or_nested() {
        let body = br#"{"id": "7", "inputs": [
            {"name": "x", "shape": [2, 2], "datatype": "FP32", "data": [[0.1, 2], [-3.5, 4e-3]]},
            {"name": "t", "shape": [2], "datatype": "INT64", "data": [1, 9]}],
            "outputs": [{"name": "reward"}], "parameters": {"timeout": 5000}}"#;
        let (req, binary) = infer_request("m".into(), String::new(), &HeaderMap::new(), body).expect("parse");
        assert_eq!(req.id, "7");
        assert_eq!(req.inputs.len(), 2);
        let x: Vec<f32> =
            req.raw_input_contents[0].chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(x, [0.1f32, 2.0, -3.5, 4e-3]);
        let t: Vec<i64> =
            req.raw_input_contents[1].chunks(8).map(|c| i64::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(t, [1, 9]);
        assert_eq!(binary, [("reward".to_owned(), false)]);
        assert_eq!(request_timeout(&req).expect("timeout"), Some(Duration::from_micros(5000)));
    }

    #[test]
    fn binary_inputs_are_split_by_their_sizes() {
        let json = br#"{"inputs": [
            {"name": "x", "shape": [1, 2], "datatype": "FP32", "parameters": {"binary_data_size": 8}},
            {"name": "t", "shape": [1], "datatype": "INT64", "data": [3]}],
            "parameters": {"binary_data_output": true}}"#;
        let mut body = json.to_vec();
        body.extend(1.5f32.to_le_bytes());
        body.extend((-2.0f32).to_le_bytes());
        let h = headers(&[(HEADER_LENGTH, &json.len().to_string())]);
        let (req, binary) = infer_request("m".into(), String::new(), &h, &body).expect("parse");
        assert_eq!(&req.raw_input_contents[0][..], &body[json.len()..]);
        assert_eq!(&req.raw_input_contents[1][..], &3i64.to_le_bytes());
        assert_eq!(binary, [(String::new(), true)]);
        assert!(!req.parameters.contains_key("binary_data_output"));
        assert!(req.inputs[0].parameters.is_empty());

        // Too few bytes, too many, a size that does not fit the shape.
        let err = |body: &[u8], h: &HeaderMap| {
            infer_request("m".into(), String::new(), h, body).expect_err("refused").to_string()
        };
        let e = err(&body[..body.len() - 1], &h);
        assert!(e.starts_with("x: parameters.binary_data_size is 8, but only 7"), "{e}");
        let mut extra = body.clone();
        extra.push(0);
        assert!(err(&extra, &h).contains("1 bytes of binary data that no input"), "{}", err(&extra, &h));
        let wrong = br#"{"inputs": [{"name": "x", "shape": [1, 3], "datatype": "FP32", "parameters": {"binary_data_size": 8}}]}"#;
        let mut body = wrong.to_vec();
        body.extend([0u8; 8]);
        let h = headers(&[(HEADER_LENGTH, &wrong.len().to_string())]);
        assert!(err(&body, &h).contains("FP32 shape [1, 3] needs 12 bytes"), "{}", err(&body, &h));
        let h = headers(&[(HEADER_LENGTH, "999")]);
        assert!(err(&body, &h).starts_with("Inference-Header-Content-Length: 999 bytes"), "{}", err(&body, &h));
    }

    #[test]
    fn malformed_bodies_name_the_field() {
        let err = |body: &str| {
            infer_request("m".into(), String::new(), &HeaderMap::new(), body.as_bytes()).expect_err(body).to_string()
        };
        assert!(err("{}").contains("missing field `inputs`"), "{}", err("{}"));
        assert!(err("not json").starts_with("request body:"));
        let e = err(r#"{"inputs": [], "outptus": []}"#);
        assert!(e.contains("unknown field `outptus`"), "{e}");
        let e = err(r#"{"inputs": [{"name": "x", "shape": [2], "datatype": "FP32", "data": [1, "a"]}]}"#);
        assert!(e.starts_with("x: data[1] is"), "{e}");
        let e = err(r#"{"inputs": [{"name": "x", "shape": [3], "datatype": "FP32", "data": [1, 2]}]}"#);
        assert_eq!(e, "x: data holds 2 values but shape [3] needs 3");
        let e = err(r#"{"inputs": [{"name": "t", "shape": [1], "datatype": "INT64", "data": [1.5]}]}"#);
        assert!(e.starts_with("t: data[0] is 1.5, not an integer"), "{e}");
        let e = err(r#"{"inputs": [{"name": "x", "shape": [1], "datatype": "FP32"}]}"#);
        assert!(e.starts_with("x: no data"), "{e}");
        let e = err(r#"{"inputs": [], "outputs": [{"name": "reward", "parameters": {"binary_data": 1}}]}"#);
        assert!(e.starts_with("reward: parameters.binary_data"), "{e}");
        let e = err(r#"{"inputs": [], "parameters": {"x": null}}"#);
        assert!(e.starts_with("request.parameters.x"), "{e}");
    }

    #[test]
    fn replies_are_json_or_binary_per_output() {
        let response = pb::ModelInferResponse {
            model_name: "m".into(),
            model_version: "1".into(),
            outputs: vec![
                pb::model_infer_response::InferOutputTensor {
                    name: "reward".into(),
                    datatype: "FP32".into(),
                    shape: vec![2],
                    ..Default::default()
                },
                pb::model_infer_response::InferOutputTensor {
                    name: "grad_x".into(),
                    datatype: "FP32".into(),
                    shape: vec![2, 1],
                    ..Default::default()
                },
            ],
            raw_output_contents: vec![
                [0.1f32, -7.25].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>().into(),
                [1f32, 2.0].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>().into(),
            ],
            ..Default::default()
        };
        let reply = infer_reply(response.clone(), &[("reward".into(), false), ("grad_x".into(), true)]).expect("reply");
        let n: usize = reply.headers[0].1.to_str().expect("ascii").parse().expect("length");
        let header: Value = serde_json::from_slice(&reply.body[..n]).expect("json");
        assert_eq!(header["outputs"][0]["data"], json!([0.1, -7.25]));
        assert_eq!(header["outputs"][1]["parameters"]["binary_data_size"], 8);
        assert_eq!(&reply.body[n..], &response.raw_output_contents[1][..]);
        assert!(header.get("id").is_none());

        let reply = infer_reply(response, &[(String::new(), false)]).expect("reply");
        assert!(reply.headers.is_empty());
        let all: Value = serde_json::from_slice(&reply.body).expect("json");
        assert_eq!(all["outputs"][1]["data"], json!([1.0, 2.0]));
        assert_eq!(all["outputs"][1]["shape"], json!([2, 1]));
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
