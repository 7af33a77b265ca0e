//! [`AuthLayer`]: the tower layer in front of every gRPC service that admits or refuses each
//! call from its method path and its `authorization: Bearer <token>` metadata alone.
//!
//! It runs before routing, so no handler (and no lookup of a named resource) happens for a
//! refused call: a caller without the scope gets PERMISSION_DENIED whether or not the dataset
//! or model it names exists. Its two status codes are made here rather than in
//! `crate::error` because no handler, and so no `Error`, is involved.

use std::future::{Ready, ready};
use std::net::SocketAddr;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::SystemTime;

use futures::future::Either;
use http::header::AUTHORIZATION;
use http::{HeaderMap, Request, Response};
use tonic::Status;
use tonic::transport::server::{TcpConnectInfo, TlsConnectInfo};

use super::scopes::{Access, Scope, access};
use super::tokens::{Principal, TokenTable, Verdict};

/// How to reach a server that wants a token, for the UNAUTHENTICATED message.
const HOW_TO_SEND: &str = "send metadata `authorization: Bearer <token>` (relreward CLI: --token or RELREWARD_TOKEN)";

/// Who may call what.
#[derive(Debug)]
pub enum Policy {
    /// No tokens configured: every call is admitted (a loopback listener, or an operator who
    /// set `security.allow_unauthenticated`).
    Open,
    /// Every call but health needs a valid token with the method's scope.
    Tokens(TokenTable),
}

impl Policy {
    /// Admits a call to `path` (returning who made it, when tokens are in use) or refuses it
    /// with UNAUTHENTICATED (no, malformed, unknown or expired token) or PERMISSION_DENIED
    /// (a valid token without the scope, or a method not in the table).
    pub fn authorize(&self, path: &str, headers: &HeaderMap, now: SystemTime) -> Result<Option<Principal>, Status> {
        let Policy::Tokens(table) = self else { return Ok(None) };
        let required = access(path);
        if required == Some(Access::Open) {
            return Ok(None);
        }
        let principal = authenticate(table, headers, now)?;
        match required {
            Some(Access::Needs(scope)) if principal.scope >= scope => Ok(Some(principal)),
            Some(Access::Needs(scope)) => Err(Status::permission_denied(format!(
                "token '{}' has scope '{}', and {} needs '{scope}'{}",
                principal.name,
                principal.scope,
                method_name(path),
                match scope {
                    Scope::Read => "",
                    Scope::Train => " (or 'admin')",
                    Scope::Admin => "",
                }
            ))),
            // A method missing from the access table is denied to everyone: fail closed.
            Some(Access::Open) | None => Err(Status::permission_denied(format!(
                "{} is not a method this server grants to any token",
                method_name(path)
            ))),
        }
    }
}

fn method_name(path: &str) -> String {
    crate::error::quote(path.strip_prefix('/').unwrap_or(path))
}

fn authenticate(table: &TokenTable, headers: &HeaderMap, now: SystemTime) -> Result<Principal, Status> {
    let mut values = headers.get_all(AUTHORIZATION).iter();
    let Some(value) = values.next() else {
        return Err(Status::unauthenticated(format!(
            "authorization: missing; this server requires a token: {HOW_TO_SEND}"
        )));
    };
    // Two credentials are ambiguous (which one did the caller mean?): refused, not resolved by
    // taking either.
    let more = values.count();
    if more > 0 {
        return Err(Status::unauthenticated(format!(
            "authorization: sent {} times; send it once: {HOW_TO_SEND}",
            more + 1
        )));
    }
    let token = bearer_token(value)
        .ok_or_else(|| Status::unauthenticated(format!("authorization: not a bearer token; {HOW_TO_SEND}")))?;
    match table.verify(token, now) {
        Verdict::Valid(principal) => Ok(principal),
        Verdict::Expired { name, expires } => Err(Status::unauthenticated(format!(
            "authorization: token '{name}' expired at {expires}; ask the operator for a new one"
        ))),
        Verdict::Unknown => {
            Err(Status::unauthenticated("authorization: the bearer token is not valid for this server"))
        }
    }
}

/// The token of a well-formed `Bearer <token>` value: the scheme in any case, exactly one
/// space, then a token holding no whitespace. Anything looser (`Bearer  TOKEN`, a trailing
/// space, a tab) is refused rather than repaired, so that one credential has one spelling.
fn bearer_token(value: &http::HeaderValue) -> Option<&str> {
    let (scheme, token) = value.to_str().ok()?.split_once(' ')?;
    let well_formed =
        scheme.eq_ignore_ascii_case("bearer") && !token.is_empty() && !token.contains(char::is_whitespace);
    well_formed.then_some(token)
}

/// Whether an admitted call to `path` goes to the audit log: calls to methods that need
/// `train` or `admin` (changes), whatever the caller's token could do; reads are too many to log.
fn audited(path: &str) -> bool {
    matches!(access(path), Some(Access::Needs(scope)) if scope > Scope::Read)
}

/// The remote address of the connection a request arrived on (plain TCP or TLS), for logs.
fn remote_addr<B>(request: &Request<B>) -> Option<SocketAddr> {
    let ext = request.extensions();
    ext.get::<TcpConnectInfo>()
        .and_then(TcpConnectInfo::remote_addr)
        .or_else(|| ext.get::<TlsConnectInfo<TcpConnectInfo>>().and_then(|i| i.get_ref().remote_addr()))
}

/// Applied with `tonic::transport::Server::builder().layer(..)`, inside the metrics layer so
/// refusals are counted like any other status.
#[derive(Debug, Clone)]
pub struct AuthLayer {
    policy: Arc<Policy>,
}

impl AuthLayer {
    pub fn new(policy: Policy) -> Self {
        Self { policy: Arc::new(policy) }
    }

    /// Whether every call is admitted (no tokens configured).
    pub fn is_open(&self) -> bool {
        matches!(*self.policy, Policy::Open)
    }

    /// The policy itself, for a listener that is not a tower stack (`crate::oip_http`).
    pub fn policy(&self) -> Arc<Policy> {
        self.policy.clone()
    }
}

impl<S> tower_layer::Layer<S> for AuthLayer {
    type Service = AuthService<S>;

    fn layer(&self, inner: S) -> Self::Service {
        AuthService { inner, policy: self.policy.clone() }
    }
}

/// The service [`AuthLayer`] wraps around the router.
#[derive(Debug, Clone)]
pub struct AuthService<S> {
    inner: S,
    policy: Arc<Policy>,
}

impl<S, ReqBody, ResBody> tower_service::Service<Request<ReqBody>> for AuthService<S>
where
    S: tower_service::Service<Request<ReqBody>, Response = Response<ResBody>>,
    ResBody: Default,
{
    type Response = Response<ResBody>;
    type Error = S::Error;
    type Future = Either<Ready<Result<Response<ResBody>, S::Error>>, S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: Request<ReqBody>) -> Self::Future {
        let path = request.uri().path();
        match self.policy.authorize(path, request.headers(), SystemTime::now()) {
            Ok(principal) => {
                if let Some(principal) = principal {
                    if audited(path) {
                        tracing::info!(token = &*principal.name, method = path, "authorized call");
                    }
                    // Handlers never see the secret (nothing can log it by accident).
                    request.headers_mut().remove(AUTHORIZATION);
                    request.extensions_mut().insert(principal);
                }
                Either::Right(self.inner.call(request))
            }
            Err(status) => {
                tracing::warn!(
                    method = path,
                    remote = remote_addr(&request).map(|a| a.to_string()).unwrap_or_default(),
                    code = ?status.code(),
                    reason = status.message(),
                    "call refused"
                );
                Either::Left(ready(Ok(status.into_http())))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use http::HeaderValue;
    use tonic::Code;

    use super::*;
    use crate::config::TokenConfig;
    use crate::security::tokens::generate;

    struct Fixture {
        policy: Policy,
        read: String,
        train: String,
        admin: String,
        expired: String,
    }

    fn fixture() -> Fixture {
        let mut tokens = Vec::new();
        let mut secrets = Vec::new();
        for (name, scopes, expires) in [
            ("reader", "read", None),
            ("trainer", "train", None),
            ("operator", "admin", None),
            ("old", "admin", Some("2001-01-01T00:00:00Z")),
        ] {
            let t = generate().expect("random");
            tokens.push(TokenConfig {
                name: name.into(),
                hash: t.hash,
                scopes: vec![scopes.into()],
                expires: expires.map(str::to_owned),
            });
            secrets.push(t.token);
        }
        let policy = Policy::Tokens(TokenTable::from_config(&tokens).expect("table"));
        let [read, train, admin, expired]: [String; 4] = secrets.try_into().expect("four");
        Fixture { policy, read, train, admin, expired }
    }

    fn headers(auth: Option<&str>) -> HeaderMap {
        let mut h = HeaderMap::new();
        if let Some(a) = auth {
            h.insert(AUTHORIZATION, HeaderValue::from_str(a).expect("header"));
        }
        h
    }

    fn code(policy: &Policy, path: &str, auth: Option<&str>) -> Code {
        match policy.authorize(path, &headers(auth), SystemTime::now()) {
            Ok(_) => Code::Ok,
            Err(s) => s.code(),
        }
    }

    #[test]
    fn scopes_against_methods() {
        let f = fixture();
        let bearer = |t: &str| format!("Bearer {t}");
        let (r, t, a) = (bearer(&f.read), bearer(&f.train), bearer(&f.admin));
        let cases = [
            ("/relreward.v1.RewardService/Score", [Code::Ok, Code::Ok, Code::Ok]),
            ("/inference.GRPCInferenceService/ModelInfer", [Code::Ok, Code::Ok, Code::Ok]),
            ("/relreward.v1.DatasetService/UploadDataset", [Code::PermissionDenied, Code::Ok, Code::Ok]),
            ("/relreward.v1.JobService/CancelJob", [Code::PermissionDenied, Code::Ok, Code::Ok]),
            ("/relreward.v1.ModelService/UploadModel", [Code::PermissionDenied, Code::PermissionDenied, Code::Ok]),
            ("/relreward.v1.ModelService/DeleteModel", [Code::PermissionDenied, Code::PermissionDenied, Code::Ok]),
            // Not in the table: nobody, not even admin.
            ("/relreward.v1.ModelService/Rename", [Code::PermissionDenied; 3]),
        ];
        for (path, want) in cases {
            let got =
                [code(&f.policy, path, Some(&r)), code(&f.policy, path, Some(&t)), code(&f.policy, path, Some(&a))];
            assert_eq!(got, want, "{path}");
        }
    }

    #[test]
    fn credentials_are_checked_before_scopes() {
        let f = fixture();
        let score = "/relreward.v1.RewardService/Score";
        let unknown = "/relreward.v1.ModelService/Rename";
        for auth in [
            None,
            Some("Bearer"),
            Some("Bearer "),
            Some("Basic dXNlcjpwYXNz"),
            Some(f.read.as_str()),
            Some("Bearer rrt_0000"),
        ] {
            assert_eq!(code(&f.policy, score, auth), Code::Unauthenticated, "{auth:?}");
            assert_eq!(code(&f.policy, unknown, auth), Code::Unauthenticated, "{auth:?}");
        }
        let expired = format!("Bearer {}", f.expired);
        let err = f.policy.authorize(score, &headers(Some(&expired)), SystemTime::now()).expect_err("expired");
        assert_eq!(err.code(), Code::Unauthenticated);
        assert!(err.message().contains("'old' expired at 2001-01-01T00:00:00Z"), "{}", err.message());
        // The scheme is case-insensitive.
        assert_eq!(code(&f.policy, score, Some(&format!("bearer {}", f.read))), Code::Ok);
    }

    /// Issue 34, item 8: one credential, one spelling. A second `authorization` header and a
    /// value with extra whitespace are refused (today's main took the first header and trimmed).
    #[test]
    fn duplicate_and_loosely_spelled_credentials_are_refused() {
        let f = fixture();
        let score = "/relreward.v1.RewardService/Score";
        for auth in [
            format!("Bearer  {}", f.read),
            format!("Bearer {} ", f.read),
            format!("Bearer\t{}", f.read),
            format!("Bearer {} {}", f.read, f.read),
        ] {
            let err = f.policy.authorize(score, &headers(Some(&auth)), SystemTime::now()).expect_err("loose");
            assert_eq!(err.code(), Code::Unauthenticated, "{auth:?}");
            assert!(err.message().starts_with("authorization: not a bearer token"), "{}", err.message());
        }
        let mut twice = headers(Some(&format!("Bearer {}", f.read)));
        twice.append(AUTHORIZATION, HeaderValue::from_str(&format!("Bearer {}", f.admin)).expect("header"));
        let err = f.policy.authorize(score, &twice, SystemTime::now()).expect_err("two headers");
        assert_eq!(err.code(), Code::Unauthenticated);
        assert!(err.message().starts_with("authorization: sent 2 times; send it once"), "{}", err.message());
    }

    #[test]
    fn only_calls_that_need_train_or_admin_are_audited() {
        assert!(audited("/relreward.v1.DatasetService/UploadDataset"));
        assert!(audited("/relreward.v1.ModelService/DeleteModel"));
        for read in ["/relreward.v1.RewardService/Score", "/relreward.v1.DatasetService/ListDatasets", "/x"] {
            assert!(!audited(read), "{read}");
        }
    }

    #[test]
    fn health_is_open_and_an_open_policy_admits_everything() {
        let f = fixture();
        assert_eq!(code(&f.policy, "/grpc.health.v1.Health/Check", None), Code::Ok);
        assert_eq!(
            code(&f.policy, "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo", None),
            Code::Unauthenticated
        );
        for path in ["/relreward.v1.ModelService/UploadModel", "/anything/at-all"] {
            assert_eq!(code(&Policy::Open, path, None), Code::Ok);
        }
    }

    #[test]
    fn messages_name_the_token_and_the_scope() {
        let f = fixture();
        let auth = format!("Bearer {}", f.read);
        let err = f
            .policy
            .authorize("/relreward.v1.DatasetService/DeleteDataset", &headers(Some(&auth)), SystemTime::now())
            .expect_err("denied");
        assert_eq!(
            err.message(),
            "token 'reader' has scope 'read', and 'relreward.v1.DatasetService/DeleteDataset' needs 'train' (or 'admin')"
        );
        let err = f.policy.authorize("/x", &headers(None), SystemTime::now() + Duration::ZERO).expect_err("missing");
        assert!(err.message().starts_with("authorization: missing"), "{}", err.message());
    }
}
