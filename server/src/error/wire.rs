//! The error rules for statuses that do not come from [`super::Error`]: those tonic makes
//! itself (a message over `server.max_request_bytes` or `max_response_bytes`, which tonic
//! answers OUT_OF_RANGE "decoded message length too large" before any handler runs) and those
//! of the other layers (security, deadlines). [`WireStatusLayer`], just inside the metrics
//! layer, rewrites such a status where it travels, in the headers of a trailers-only response
//! or in the trailers of a stream:
//! - a message over a size limit is RESOURCE_EXHAUSTED naming the limit and its setting (as
//!   gRPC specifies, and as a client-streaming handler answers through
//!   [`super::Error::from_inbound`]);
//! - a method the server does not serve (tonic answers UNIMPLEMENTED with no message, for an
//!   unknown service or method alike) is named, with where to find what is served;
//! - no message passes [`super::MAX_MESSAGE_BYTES`].

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use http::{HeaderMap, Request, Response};
use http_body::{Body, Frame, SizeHint};
use tonic::{Code, Status};

use super::{MAX_MESSAGE_BYTES, bounded};

/// tonic's messages for a message over its limits (`tonic::codec`), and the settings behind them.
const DECODE_PREFIX: &str = "Error, decoded message length too large: found ";
const ENCODE_PREFIX: &str = "Error, encoded message length too large: found ";
/// tonic's RESOURCE_EXHAUSTED for a compressed (gzip, deflate) request that inflates past the
/// same limit: "Error decompressing: size limit, of N bytes, exceeded while decompressing message".
const INFLATE_PREFIX: &str = "Error decompressing: size limit, of ";

/// The RESOURCE_EXHAUSTED message for tonic's status about a message over a size limit, or
/// `None` when `status` is not one.
pub fn message_too_large(status: &Status) -> Option<String> {
    let message = status.message();
    if status.code() == Code::ResourceExhausted
        && let Some(rest) = message.strip_prefix(INFLATE_PREFIX)
    {
        // tonic stops inflating at the limit, so the whole size is unknown.
        let limit = rest.split(|c: char| !c.is_ascii_digit()).find(|s| !s.is_empty())?;
        return Some(format!(
            "the request message, decompressed, is over the server's limit of {limit} bytes \
             (server.max_request_bytes); send less per message (fewer items per call, smaller upload chunks)"
        ));
    }
    if status.code() != Code::OutOfRange {
        return None;
    }
    let (rest, what, setting, advice) = if let Some(rest) = message.strip_prefix(DECODE_PREFIX) {
        (
            rest,
            "request",
            "server.max_request_bytes",
            "send less per message (fewer items per call, smaller upload chunks)",
        )
    } else if let Some(rest) = message.strip_prefix(ENCODE_PREFIX) {
        (rest, "response", "server.max_response_bytes", "ask for less per call (fewer items)")
    } else {
        return None;
    };
    // "N bytes, the limit is: M bytes"
    let mut numbers = rest.split(|c: char| !c.is_ascii_digit()).filter(|s| !s.is_empty());
    let (found, limit) = (numbers.next()?, numbers.next()?);
    Some(format!("the {what} message is {found} bytes, over the server's limit of {limit} bytes ({setting}); {advice}"))
}

/// The UNIMPLEMENTED message for a call to `path` that no service here answers.
pub fn not_served(path: &str) -> String {
    bounded(format!(
        "'{path}' is not a method this server serves: it serves relreward.v1's services, the Open \
         Inference Protocol's inference.GRPCInferenceService (without ModelStreamInfer, model \
         loading, shared memory or log settings), \
         grpc.health.v1.Health and server reflection, which lists every method"
    ))
}

/// Applies the rules to a `grpc-status` in `headers` (response headers or trailers), if any;
/// `path` is the call's (only a trailers-only response, in the headers, has it).
fn rewrite(headers: &mut HeaderMap, path: Option<&str>) {
    // Cheap for the common case (response headers without a status, OK trailers): only an
    // OUT_OF_RANGE status, an UNIMPLEMENTED one without a message, or a long message
    // (percent-encoded, so never shorter than the message) is decoded at all.
    let Some(code) = headers.get(Status::GRPC_STATUS) else { return };
    let message = headers.get(Status::GRPC_MESSAGE);
    let long = message.is_some_and(|m| m.len() > MAX_MESSAGE_BYTES);
    let unnamed = code.as_bytes() == b"12" && message.is_none_or(|m| m.is_empty());
    // 11: OUT_OF_RANGE (a message over a limit); 8: RESOURCE_EXHAUSTED (one that inflates past it).
    if !long && !unnamed && code.as_bytes() != b"11" && code.as_bytes() != b"8" {
        return;
    }
    let Some(status) = Status::from_header_map(headers) else { return };
    let replacement = match message_too_large(&status) {
        Some(message) => Status::resource_exhausted(message),
        None if unnamed => match path {
            Some(path) => Status::unimplemented(not_served(path)),
            None => return,
        },
        None if status.message().len() > MAX_MESSAGE_BYTES => {
            Status::new(status.code(), bounded(status.message().to_owned()))
        }
        None => return,
    };
    headers.remove(Status::GRPC_MESSAGE);
    headers.remove(Status::GRPC_STATUS_DETAILS);
    if replacement.add_header(headers).is_err() {
        // Only a message that cannot be a header value fails; ours are percent-encoded.
        headers.insert(Status::GRPC_STATUS, http::HeaderValue::from(replacement.code() as i32));
    }
}

/// The tower layer that applies [`rewrite`] to every response of the gRPC server.
#[derive(Debug, Clone, Copy, Default)]
pub struct WireStatusLayer;

impl<S> tower_layer::Layer<S> for WireStatusLayer {
    type Service = WireStatusService<S>;

    fn layer(&self, inner: S) -> Self::Service {
        WireStatusService { inner }
    }
}

#[derive(Debug, Clone)]
pub struct WireStatusService<S> {
    inner: S,
}

impl<S, ReqBody, ResBody> tower_service::Service<Request<ReqBody>> for WireStatusService<S>
where
    S: tower_service::Service<Request<ReqBody>, Response = Response<ResBody>>,
    S::Future: Send + 'static,
{
    type Response = Response<WireBody<ResBody>>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<ReqBody>) -> Self::Future {
        // A clone of the URI shares its bytes: no copy per call for the rare UNIMPLEMENTED.
        let uri = request.uri().clone();
        let response = self.inner.call(request);
        Box::pin(async move {
            let mut response = response.await?;
            // A trailers-only response (most errors, and every error tonic raises before a
            // handler runs) carries its status in the headers.
            rewrite(response.headers_mut(), Some(uri.path()));
            Ok(response.map(|inner| WireBody { inner }))
        })
    }
}

pin_project_lite::pin_project! {
    /// A response body whose trailers pass through [`rewrite`]; data frames pass untouched.
    pub struct WireBody<B> {
        #[pin]
        inner: B,
    }
}

impl<B: Body> Body for WireBody<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        let mut polled = ready!(self.project().inner.poll_frame(cx));
        if let Some(Ok(frame)) = polled.as_mut()
            && let Some(trailers) = frame.trailers_mut()
        {
            rewrite(trailers, None);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn oversized_messages_become_resource_exhausted_naming_the_setting() {
        let decode = Status::out_of_range(format!("{DECODE_PREFIX}17000000 bytes, the limit is: 16777216 bytes"));
        let m = message_too_large(&decode).expect("recognised");
        assert!(m.contains("17000000") && m.contains("16777216") && m.contains("server.max_request_bytes"), "{m}");
        let encode = Status::out_of_range(format!("{ENCODE_PREFIX}9 bytes, the limit is: 8 bytes"));
        assert!(message_too_large(&encode).expect("recognised").contains("server.max_response_bytes"));
        assert_eq!(message_too_large(&Status::out_of_range("t: 5 is out of range")), None);
        assert_eq!(message_too_large(&Status::invalid_argument(decode.message())), None);

        let mut headers = HeaderMap::new();
        decode.add_header(&mut headers).expect("header");
        rewrite(&mut headers, None);
        let s = Status::from_header_map(&headers).expect("status");
        assert_eq!(s.code(), Code::ResourceExhausted);
        assert!(s.message().contains("server.max_request_bytes"), "{}", s.message());
    }

    /// Issue 34, item 2: a gzip/deflate request that inflates past the limit gets the same code
    /// and the same setting named as an uncompressed one, in every RPC kind (unary through
    /// [`rewrite`], streams through `Error::from_inbound`).
    #[test]
    fn a_message_that_inflates_past_the_limit_names_the_setting_too() {
        let inflated = Status::resource_exhausted(
            "Error decompressing: size limit, of 1048576 bytes, exceeded while decompressing message",
        );
        let m = message_too_large(&inflated).expect("recognised");
        assert!(m.contains("1048576") && m.contains("server.max_request_bytes") && m.contains("decompressed"), "{m}");
        assert_eq!(message_too_large(&Status::resource_exhausted("queue full")), None);
        let e = crate::error::Error::from_inbound("upload stream", &inflated);
        assert!(
            matches!(&e, crate::error::Error::ResourceExhausted(m) if m.contains("server.max_request_bytes")),
            "{e:?}"
        );

        let mut headers = HeaderMap::new();
        inflated.add_header(&mut headers).expect("header");
        rewrite(&mut headers, None);
        let s = Status::from_header_map(&headers).expect("status");
        assert_eq!(s.code(), Code::ResourceExhausted);
        assert!(s.message().contains("server.max_request_bytes"), "{}", s.message());
        // The server's own RESOURCE_EXHAUSTED statuses pass untouched.
        let mut headers = HeaderMap::new();
        Status::resource_exhausted("the queue is full").add_header(&mut headers).expect("header");
        rewrite(&mut headers, None);
        assert_eq!(Status::from_header_map(&headers).expect("status").message(), "the queue is full");
    }

    #[test]
    fn long_messages_are_cut_and_others_untouched() {
        let mut headers = HeaderMap::new();
        Status::permission_denied(format!("'{}' is not a method", "a".repeat(100_000)))
            .add_header(&mut headers)
            .expect("header");
        rewrite(&mut headers, None);
        let s = Status::from_header_map(&headers).expect("status");
        assert_eq!(s.code(), Code::PermissionDenied);
        assert!(s.message().len() <= MAX_MESSAGE_BYTES);

        let mut ok = HeaderMap::new();
        ok.insert(Status::GRPC_STATUS, http::HeaderValue::from(0));
        let before = ok.clone();
        rewrite(&mut ok, Some("/a.B/C"));
        assert_eq!(ok, before);
        let mut plain = HeaderMap::new();
        rewrite(&mut plain, Some("/a.B/C"));
        assert!(plain.is_empty());
    }

    #[test]
    fn an_unserved_method_is_named_and_a_handlers_own_unimplemented_kept() {
        let path = "/inference.GRPCInferenceService/ModelStreamInfer";
        let mut headers = HeaderMap::new();
        Status::unimplemented("").add_header(&mut headers).expect("header");
        rewrite(&mut headers, Some(path));
        let s = Status::from_header_map(&headers).expect("status");
        assert_eq!(s.code(), Code::Unimplemented);
        assert!(s.message().contains(path) && s.message().contains("reflection"), "{}", s.message());

        let mut own = HeaderMap::new();
        Status::unimplemented("format 'onnx' is not supported").add_header(&mut own).expect("header");
        let before = own.clone();
        rewrite(&mut own, Some(path));
        assert_eq!(own, before);
        // A path far over the message limit is cut like any message.
        assert!(not_served(&"x".repeat(100_000)).len() <= MAX_MESSAGE_BYTES);
    }
}
