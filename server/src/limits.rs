//! Limits that protect the whole server rather than one service: connections accepted at
//! once, request metadata size, call deadlines (a default for unary calls, and
//! DEADLINE_EXCEEDED rather than tonic's CANCELLED when one passes), and the disk budget of
//! the data directory.
//!
//! Message sizes, upload quotas and queue capacities live with the services they bound
//! (`api`, `serving`, `jobs`); HTTP/2 streams per connection are a builder setting in `run`.

use std::collections::HashSet;
use std::future::Future;
use std::io;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use futures::{Stream, StreamExt};
use http::{HeaderValue, Request, Response};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tonic::transport::server::Connected;

use crate::error::Error;

// ---------------------------------------------------------------------------------------------
// Request metadata

/// Refuses a call whose metadata is over `server.max_metadata_bytes`, with RESOURCE_EXHAUSTED
/// naming the setting, before authentication and routing. Only that call: the connection and
/// its other calls (an open GradientStream) go on. Sizes are counted as HTTP/2 counts a header
/// list (RFC 9113 6.5.2: name + value + 32 per entry), so the limit means what HTTP/2's does.
#[derive(Debug, Clone, Copy)]
pub struct MetadataLimitLayer {
    max: usize,
}

impl MetadataLimitLayer {
    pub fn new(max: usize) -> Self {
        Self { max }
    }
}

/// The HTTP/2 size of a header list.
pub fn metadata_bytes(headers: &http::HeaderMap) -> usize {
    headers.iter().map(|(name, value)| name.as_str().len() + value.len() + 32).sum()
}

impl<S> tower_layer::Layer<S> for MetadataLimitLayer {
    type Service = MetadataLimitService<S>;

    fn layer(&self, inner: S) -> Self::Service {
        MetadataLimitService { inner, max: self.max }
    }
}

#[derive(Debug, Clone)]
pub struct MetadataLimitService<S> {
    inner: S,
    max: usize,
}

impl<S, ReqBody, ResBody> tower_service::Service<Request<ReqBody>> for MetadataLimitService<S>
where
    S: tower_service::Service<Request<ReqBody>, Response = Response<ResBody>>,
    ResBody: Default,
{
    type Response = Response<ResBody>;
    type Error = S::Error;
    type Future = futures::future::Either<futures::future::Ready<Result<Response<ResBody>, S::Error>>, S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<ReqBody>) -> Self::Future {
        let bytes = metadata_bytes(request.headers());
        if bytes <= self.max {
            return futures::future::Either::Right(self.inner.call(request));
        }
        let status = tonic::Status::resource_exhausted(format!(
            "request metadata is {bytes} bytes (headers counted as HTTP/2 does, 32 bytes per entry \
             on top of name and value), above server.max_metadata_bytes = {}",
            self.max
        ));
        tracing::warn!(method = request.uri().path(), bytes, max = self.max, "call refused: metadata too large");
        futures::future::Either::Left(futures::future::ready(Ok(status.into_http())))
    }
}

// ---------------------------------------------------------------------------------------------
// Connections

/// Admits at most `max` connections at once from `incoming`. One beyond is accepted and closed
/// at once, so its client fails fast with UNAVAILABLE and can back off, instead of waiting in
/// the kernel's accept backlog with no answer until its own deadline.
pub fn limit_connections<S, IO>(incoming: S, max: usize) -> impl Stream<Item = io::Result<Limited<IO>>>
where
    S: Stream<Item = io::Result<IO>>,
    IO: Connected,
{
    let slots = Arc::new(Semaphore::new(max));
    let refused = Arc::new(AtomicU64::new(0));
    incoming.filter_map(move |accepted| {
        let item = match accepted {
            Ok(io) => match slots.clone().try_acquire_owned() {
                Ok(permit) => Some(Ok(Limited { inner: io, _permit: permit })),
                Err(_) => {
                    let n = refused.fetch_add(1, Ordering::Relaxed) + 1;
                    // The first refusal and then every 100th: a flood must not flood the log.
                    if n == 1 || n.is_multiple_of(100) {
                        tracing::warn!(max, refused_so_far = n, "connection refused: server.max_connections reached");
                    }
                    None // dropping `io` closes the socket
                }
            },
            Err(e) => Some(Err(e)),
        };
        std::future::ready(item)
    })
}

pin_project_lite::pin_project! {
    /// A connection holding one of [`limit_connections`]'s slots until it is dropped, which
    /// hyper does when the connection ends.
    pub struct Limited<IO> {
        #[pin]
        inner: IO,
        _permit: OwnedSemaphorePermit,
    }
}

impl<IO: Connected> Connected for Limited<IO> {
    // The inner type's, so the security layer still finds `TcpConnectInfo` (and, under TLS,
    // `TlsConnectInfo<TcpConnectInfo>` with the client's certificates).
    type ConnectInfo = IO::ConnectInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        self.inner.connect_info()
    }
}

impl<IO: AsyncRead> AsyncRead for Limited<IO> {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        self.project().inner.poll_read(cx, buf)
    }
}

impl<IO: AsyncWrite> AsyncWrite for Limited<IO> {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        self.project().inner.poll_write(cx, buf)
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        self.project().inner.poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        self.project().inner.poll_shutdown(cx)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        self.project().inner.poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

// ---------------------------------------------------------------------------------------------
// Deadlines

/// Unary calls that queue for compute, and so get `serving.default_deadline_ms` when the
/// caller sets no deadline: a query nobody waits for any more is dropped from the queue
/// instead of computed. Streams are left alone (a GradientStream or Sample may rightly run
/// for minutes), as are uploads and the metadata calls (they do not queue).
pub const DEFAULT_DEADLINE_METHODS: &[&str] = &[
    "/relreward.v1.RewardService/Score",
    "/relreward.v1.RewardService/Gradient",
    "/inference.GRPCInferenceService/ModelInfer",
];

/// How long before the caller's deadline this server answers DEADLINE_EXCEEDED itself: 5 % of
/// it, between 2 and 50 ms. tonic runs its own timer for `grpc-timeout`, server side outside
/// every layer and client side too, and either one ends the call as CANCELLED ("Timeout
/// expired"); answering a little ahead of both gives the caller the code the gRPC spec
/// prescribes, which retry policies rely on. The answer could not have arrived in time anyway.
fn ahead_of(timeout: Duration) -> Duration {
    (timeout / 20).clamp(Duration::from_millis(2), Duration::from_millis(50))
}

/// Gives unary serving calls without a `grpc-timeout` the default one (by adding the header,
/// so the handlers' `serving::deadline_of` sees it), and answers DEADLINE_EXCEEDED when a call's
/// deadline passes before its response (headers, for a stream) is ready.
#[derive(Debug, Clone)]
pub struct DeadlineLayer {
    /// `None`: no default (`serving.default_deadline_ms = 0`).
    default: Option<(Duration, HeaderValue)>,
    methods: Arc<HashSet<&'static str>>,
}

impl DeadlineLayer {
    pub fn new(default_ms: u64) -> Self {
        let default = (default_ms > 0).then(|| {
            // grpc-timeout allows 8 digits; config validation keeps default_ms below that.
            let value = HeaderValue::from_str(&format!("{default_ms}m")).unwrap_or(HeaderValue::from_static("1H"));
            (Duration::from_millis(default_ms), value)
        });
        Self { default, methods: Arc::new(DEFAULT_DEADLINE_METHODS.iter().copied().collect()) }
    }
}

impl<S> tower_layer::Layer<S> for DeadlineLayer {
    type Service = DeadlineService<S>;

    fn layer(&self, inner: S) -> Self::Service {
        DeadlineService { inner, layer: self.clone() }
    }
}

#[derive(Debug, Clone)]
pub struct DeadlineService<S> {
    inner: S,
    layer: DeadlineLayer,
}

impl<S, ReqBody, ResBody> tower_service::Service<Request<ReqBody>> for DeadlineService<S>
where
    S: tower_service::Service<Request<ReqBody>, Response = Response<ResBody>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
    ResBody: Default + Send + 'static,
{
    type Response = Response<ResBody>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Response<ResBody>, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: Request<ReqBody>) -> Self::Future {
        let timeout = match request.headers().get("grpc-timeout") {
            // An unparsable value is ignored here as by tonic (no deadline).
            Some(value) => value.to_str().ok().and_then(crate::serving::parse_grpc_timeout),
            None => match &self.layer.default {
                Some((timeout, value)) if self.layer.methods.contains(request.uri().path()) => {
                    request.headers_mut().insert("grpc-timeout", value.clone());
                    Some(*timeout)
                }
                _ => None,
            },
        };
        let response = self.inner.call(request);
        let Some(timeout) = timeout else { return Box::pin(response) };
        let budget = timeout.saturating_sub(ahead_of(timeout));
        Box::pin(async move {
            match tokio::time::timeout(budget, response).await {
                Ok(result) => result,
                // Dropping the handler's future stops its work at its next await; a query
                // already queued is dropped by the batcher, which checks the same deadline.
                Err(_) => Ok(tonic::Status::deadline_exceeded(format!(
                    "the call's deadline ({} ms) passed before it was answered",
                    timeout.as_millis()
                ))
                .into_http()),
            }
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Disk budget

/// `storage.max_bytes`: the bytes the data directory may hold, checked when an upload starts
/// against what is on disk plus what uploads in progress have reserved. Uploads declare their
/// size in the header, so the check happens before a byte of payload is written.
#[derive(Debug, Clone)]
pub struct DiskBudget {
    data_dir: PathBuf,
    /// 0: no budget.
    max_bytes: u64,
    /// Bytes reserved by uploads in progress (their staging directories are not counted on
    /// disk, or they would count twice). The lock also makes check-and-reserve one step.
    reserved: Arc<Mutex<u64>>,
}

impl DiskBudget {
    pub fn new(data_dir: &Path, max_bytes: u64) -> Self {
        Self { data_dir: data_dir.to_path_buf(), max_bytes, reserved: Arc::default() }
    }

    /// Reserves `bytes` for an upload of `what` until the reservation is dropped (by then the
    /// files are published and counted on disk, or removed). Blocking: walks the data directory.
    pub fn reserve(&self, bytes: u64, what: &str) -> Result<Reservation, Error> {
        if self.max_bytes == 0 {
            return Ok(Reservation { bytes: 0, reserved: self.reserved.clone() });
        }
        let mut reserved = self.reserved.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let used = dir_bytes(&self.data_dir, Some(&self.data_dir.join("staging")))
            .map_err(|e| Error::internal(&format!("measuring {}", self.data_dir.display()), e))?;
        let after = used.saturating_add(*reserved).saturating_add(bytes);
        if after > self.max_bytes {
            return Err(Error::ResourceExhausted(format!(
                "{what} needs {bytes} bytes but the data directory holds {used} bytes and uploads in progress have \
                 reserved {} more, of a budget of {} bytes (storage.max_bytes); delete datasets or models, or raise \
                 the budget",
                *reserved, self.max_bytes
            )));
        }
        *reserved += bytes;
        Ok(Reservation { bytes, reserved: self.reserved.clone() })
    }
}

/// Bytes held for an upload in progress; given back when dropped.
#[derive(Debug)]
#[must_use = "the reservation ends when dropped"]
pub struct Reservation {
    bytes: u64,
    reserved: Arc<Mutex<u64>>,
}

impl Drop for Reservation {
    fn drop(&mut self) {
        let mut reserved = self.reserved.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        *reserved = reserved.saturating_sub(self.bytes);
    }
}

/// Total length of the files under `dir`, skipping `skip`. Files that vanish meanwhile (a
/// delete, a finished staging rename) are skipped, not errors.
fn dir_bytes(dir: &Path, skip: Option<&Path>) -> io::Result<u64> {
    let mut total = 0u64;
    let mut pending = vec![dir.to_path_buf()];
    while let Some(d) = pending.pop() {
        let entries = match std::fs::read_dir(&d) {
            Ok(e) => e,
            Err(e) if e.kind() == io::ErrorKind::NotFound => continue,
            Err(e) => return Err(e),
        };
        for entry in entries {
            let entry = entry?;
            let path = entry.path();
            if skip == Some(path.as_path()) {
                continue;
            }
            let meta = match entry.metadata() {
                Ok(m) => m,
                Err(e) if e.kind() == io::ErrorKind::NotFound => continue,
                Err(e) => return Err(e),
            };
            if meta.is_dir() {
                pending.push(path);
            } else {
                total = total.saturating_add(meta.len());
            }
        }
    }
    Ok(total)
}

/// Whether `error` is a full disk or an exhausted filesystem quota, whatever wraps it.
pub fn is_disk_full(error: &Error) -> bool {
    let Error::Internal(e) = error else { return false };
    e.chain().filter_map(|c| c.downcast_ref::<io::Error>()).any(|io| {
        matches!(io.kind(), io::ErrorKind::StorageFull | io::ErrorKind::QuotaExceeded | io::ErrorKind::FileTooLarge)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn budget_counts_disk_and_reservations_and_gives_back_on_drop() {
        let dir = tempfile::tempdir().expect("tmp");
        std::fs::create_dir_all(dir.path().join("blobs/a")).expect("mkdir");
        std::fs::create_dir_all(dir.path().join("staging/x")).expect("mkdir");
        std::fs::write(dir.path().join("blobs/a/f"), vec![0u8; 600]).expect("write");
        // Staging is counted through reservations only.
        std::fs::write(dir.path().join("staging/x/g"), vec![0u8; 10_000]).expect("write");
        let budget = DiskBudget::new(dir.path(), 1000);
        let first = budget.reserve(300, "upload 1").expect("600 + 300 fits in 1000");
        let err = budget.reserve(200, "upload 2").expect_err("600 + 300 + 200 > 1000");
        let msg = err.to_string();
        assert!(matches!(err, Error::ResourceExhausted(_)), "{err:?}");
        assert!(msg.contains("storage.max_bytes") && msg.contains("upload 2"), "{msg}");
        drop(first);
        let _second = budget.reserve(400, "upload 2").expect("the first reservation was given back");
        assert!(DiskBudget::new(dir.path(), 0).reserve(u64::MAX, "x").is_ok(), "0: no budget");
    }

    #[test]
    fn disk_full_is_recognized_through_the_error_chain() {
        let full: Error = io::Error::from(io::ErrorKind::StorageFull).into();
        assert!(is_disk_full(&full));
        let other: Error = io::Error::from(io::ErrorKind::PermissionDenied).into();
        assert!(!is_disk_full(&other));
        assert!(!is_disk_full(&Error::invalid("x")));
    }
}

#[cfg(test)]
mod deadline_tests {
    use std::convert::Infallible;

    use tower_layer::Layer;
    use tower_service::Service;

    use super::*;

    #[derive(Clone)]
    struct Never;

    impl Service<Request<()>> for Never {
        type Response = Response<tonic::body::Body>;
        type Error = Infallible;
        type Future = futures::future::Pending<Result<Self::Response, Infallible>>;

        fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
            Poll::Ready(Ok(()))
        }

        fn call(&mut self, _: Request<()>) -> Self::Future {
            futures::future::pending()
        }
    }

    #[tokio::test]
    async fn a_call_past_its_deadline_is_answered_deadline_exceeded() {
        let mut svc = DeadlineLayer::new(0).layer(Never);
        let request = Request::builder().uri("/x.Y/Z").header("grpc-timeout", "100000u").body(()).expect("request");
        let started = std::time::Instant::now();
        let response = svc.call(request).await.expect("answered");
        assert!(started.elapsed() < Duration::from_millis(100), "{:?}", started.elapsed());
        assert_eq!(response.headers().get("grpc-status").map(HeaderValue::as_bytes), Some(&b"4"[..]));
    }

    #[tokio::test]
    async fn only_unary_serving_calls_get_the_default() {
        let mut svc = DeadlineLayer::new(50).layer(Never);
        let request = Request::builder().uri(DEFAULT_DEADLINE_METHODS[0]).body(()).expect("request");
        let response = svc.call(request).await.expect("answered");
        assert_eq!(response.headers().get("grpc-status").map(HeaderValue::as_bytes), Some(&b"4"[..]));
        let request = Request::builder().uri("/relreward.v1.RewardService/Sample").body(()).expect("request");
        let pending = tokio::time::timeout(Duration::from_millis(200), svc.call(request)).await;
        assert!(pending.is_err(), "a stream got a default deadline");
    }
}
