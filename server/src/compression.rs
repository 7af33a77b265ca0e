//! `server.response_compression = "request"`: a response is compressed only when its request
//! was, with the request's algorithm. tonic compresses a response whenever the client's
//! `grpc-accept-encoding` lists an algorithm the service may send, and grpcio (tritonclient
//! included) lists gzip and deflate on every call, compressed or not: every large tensor it
//! asked for would cost the server a gzip pass. So before tonic reads it, this narrows
//! `grpc-accept-encoding` to the request's own `grpc-encoding` (when the client accepts it),
//! or removes it for an uncompressed request.

use std::task::{Context, Poll};

use http::{HeaderMap, HeaderValue, Request};

const ENCODING: &str = "grpc-encoding";
const ACCEPT: &str = "grpc-accept-encoding";

#[derive(Debug, Clone, Copy)]
pub struct RequestMirrorLayer {
    enabled: bool,
}

impl RequestMirrorLayer {
    /// `enabled: false` passes every request through untouched.
    pub fn new(enabled: bool) -> Self {
        Self { enabled }
    }
}

impl<S> tower_layer::Layer<S> for RequestMirrorLayer {
    type Service = RequestMirror<S>;

    fn layer(&self, inner: S) -> Self::Service {
        RequestMirror { inner, enabled: self.enabled }
    }
}

#[derive(Debug, Clone)]
pub struct RequestMirror<S> {
    inner: S,
    enabled: bool,
}

impl<S, B> tower_service::Service<Request<B>> for RequestMirror<S>
where
    S: tower_service::Service<Request<B>>,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = S::Future;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: Request<B>) -> Self::Future {
        if self.enabled {
            narrow(request.headers_mut());
        }
        self.inner.call(request)
    }
}

/// Leaves in `grpc-accept-encoding` only the request's own compression, if accepted.
pub(crate) fn narrow(headers: &mut HeaderMap) {
    let sent = match headers.get(ENCODING).and_then(|v| v.to_str().ok()).map(str::trim) {
        Some("gzip") => Some("gzip"),
        Some("deflate") => Some("deflate"),
        _ => None,
    };
    let accepted = sent.filter(|sent| {
        headers
            .get_all(ACCEPT)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(','))
            .any(|a| a.trim() == *sent)
    });
    match accepted {
        Some(encoding) => {
            headers.insert(ACCEPT, HeaderValue::from_static(encoding));
        }
        None => {
            headers.remove(ACCEPT);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn narrowed(pairs: &[(&'static str, &'static str)]) -> Vec<String> {
        let mut headers = HeaderMap::new();
        for (k, v) in pairs {
            headers.append(*k, HeaderValue::from_static(v));
        }
        narrow(&mut headers);
        headers.get_all(ACCEPT).iter().map(|v| v.to_str().unwrap_or_default().to_owned()).collect()
    }

    #[test]
    fn responses_follow_the_request() {
        // grpcio's uncompressed call: no compressed response.
        assert!(narrowed(&[(ACCEPT, "identity,deflate,gzip")]).is_empty());
        assert!(narrowed(&[(ENCODING, "identity"), (ACCEPT, "identity, deflate, gzip")]).is_empty());
        // Compressed: the same algorithm back, if the client accepts it.
        assert_eq!(narrowed(&[(ENCODING, "gzip"), (ACCEPT, "identity, deflate, gzip")]), ["gzip"]);
        assert_eq!(narrowed(&[(ENCODING, "deflate"), (ACCEPT, "gzip"), (ACCEPT, "deflate")]), ["deflate"]);
        assert!(narrowed(&[(ENCODING, "gzip"), (ACCEPT, "deflate")]).is_empty());
        assert!(narrowed(&[(ENCODING, "gzip")]).is_empty());
        assert!(narrowed(&[(ENCODING, "zstd"), (ACCEPT, "zstd,gzip")]).is_empty());
    }
}
