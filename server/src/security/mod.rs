//! Access control and transport security (docs/security.md has the threat model).
//!
//! - [`scopes`]: the scopes (`read` < `train` < `admin`) and [`scopes::METHOD_ACCESS`], the
//!   one table of which scope each gRPC method needs (health is open; a method not in the
//!   table is denied).
//! - [`tokens`]: bearer tokens: generation, the salted-hash configuration format, expiry,
//!   constant-time verification.
//! - [`layer`]: [`AuthLayer`], the tower layer that admits or refuses every call before any
//!   handler runs (UNAUTHENTICATED, PERMISSION_DENIED).
//! - [`tls`]: rustls server settings, with optional client certificates (mutual TLS).
//!
//! [`Security::load`] turns the configuration into the layer and the TLS settings, enforcing
//! the safe-default rule: no tokens on a non-loopback address only with
//! `security.allow_unauthenticated = true`.

pub mod layer;
pub mod scopes;
pub mod tls;
pub mod tokens;

use std::net::SocketAddr;
use std::time::SystemTime;

pub use layer::{AuthLayer, Policy};
pub use scopes::Scope;
pub use tokens::{Principal, TokenTable};
use tonic::transport::ServerTlsConfig;

use crate::config::Config;

/// A security setting that cannot be used as configured; `key` names it.
#[derive(Debug, thiserror::Error)]
#[error("configuration key {key}: {message}")]
pub struct SecurityError {
    pub key: String,
    pub message: String,
}

impl SecurityError {
    pub fn new(key: impl Into<String>, message: impl Into<String>) -> Self {
        Self { key: key.into(), message: message.into() }
    }
}

/// What the server needs to enforce `[security]`.
#[derive(Debug)]
pub struct Security {
    /// Goes in front of every service.
    pub layer: AuthLayer,
    /// `None`: plaintext.
    pub tls: Option<ServerTlsConfig>,
    /// The same for the OIP's HTTP listener (`crate::oip_http`).
    pub http_tls: Option<std::sync::Arc<rustls::ServerConfig>>,
    /// Settings that are allowed but risky, for the log at start.
    pub warnings: Vec<String>,
}

impl Security {
    /// Parses the tokens, reads the TLS files and applies the listener rule to `listen`, the
    /// address actually bound (which a test or an embedding program may choose itself).
    pub fn load(config: &Config, listen: SocketAddr) -> Result<Self, SecurityError> {
        let sec = &config.security;
        let table =
            TokenTable::from_config(&sec.tokens).map_err(|e| SecurityError { key: e.key, message: e.message })?;
        let loopback = listen.ip().to_canonical().is_loopback();
        let mut warnings = Vec::new();
        if table.is_empty() && !loopback {
            if let Some(message) = config.unauthenticated_exposure(listen) {
                return Err(SecurityError::new("server.listen", message));
            }
            warnings.push(format!(
                "security.allow_unauthenticated = true: serving {listen} without authentication; anyone who can reach \
                 it can upload data, start jobs and delete models{}",
                if sec.tls.client_ca.as_os_str().is_empty() {
                    ""
                } else {
                    " (mutual TLS still requires a client certificate)"
                }
            ));
        } else if sec.allow_unauthenticated {
            warnings.push(format!(
                "security.allow_unauthenticated = true has no effect here ({})",
                if table.is_empty() { "the listener is loopback" } else { "tokens are configured" }
            ));
        }
        if table.is_empty() && config.models.allow_torchscript_upload {
            warnings.push(
                "models.allow_torchscript_upload = true with no security.tokens: any caller can upload TorchScript, \
                 which is code run inside this server; configure tokens so that only 'admin' can"
                    .into(),
            );
        }
        if !table.is_empty() && !loopback && !sec.tls.enabled() {
            warnings.push(format!(
                "tokens are required but {listen} is plaintext: they cross the network readable by anyone on the \
                 path; configure security.tls (or terminate TLS in front of the server)"
            ));
        }
        if let Ok(http) = config.oip_http.listen.parse::<SocketAddr>()
            && !table.is_empty()
            && !http.ip().to_canonical().is_loopback()
            && !sec.tls.enabled()
        {
            warnings.push(format!(
                "tokens are required but oip_http.listen = {http} is plaintext: they cross the network readable by \
                 anyone on the path; configure security.tls (or terminate TLS in front of the server)"
            ));
        }
        let expired = table.expired_names(SystemTime::now());
        if !expired.is_empty() {
            warnings.push(format!("security.tokens: already expired, refused: {}", expired.join(", ")));
        }
        if let Ok(metrics) = config.metrics.listen.parse::<SocketAddr>()
            && !metrics.ip().to_canonical().is_loopback()
        {
            warnings.push(format!(
                "metrics.listen = {metrics}: the Prometheus endpoint has no authentication (model names and call \
                 counts are visible to anyone who reaches it)"
            ));
        }
        let tls = tls::server_config(&sec.tls)?;
        let http_tls = tls::http_server_config(&sec.tls)?;
        let policy = if table.is_empty() { Policy::Open } else { Policy::Tokens(table) };
        Ok(Self { layer: AuthLayer::new(policy), tls, http_tls, warnings })
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;
    use std::io::Write;

    use super::*;
    use crate::config::Overrides;

    fn config(vars: &[(&str, &str)], file: Option<&str>) -> Result<Config, crate::config::ConfigError> {
        let map: HashMap<String, String> = vars.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned())).collect();
        let env = config::Environment::with_prefix("RELREWARD").source(Some(map));
        let mut f = tempfile::Builder::new().suffix(".toml").tempfile().expect("temp");
        let path = file.map(|text| {
            f.write_all(text.as_bytes()).expect("write");
            f.path().to_owned()
        });
        Config::load_with_env(path.as_deref(), &Overrides::default(), env)
    }

    fn token_file() -> String {
        let t = tokens::generate().expect("random");
        format!("[security]\ntokens = [{{ name = \"ops\", hash = \"{}\", scopes = [\"admin\"] }}]\n", t.hash)
    }

    fn addr(s: &str) -> SocketAddr {
        s.parse().expect("addr")
    }

    #[test]
    fn non_loopback_without_tokens_is_refused_unless_allowed() {
        // At configuration load...
        for listen in ["0.0.0.0:50051", "[::]:50051", "192.168.1.10:50051"] {
            let err = config(&[("RELREWARD__SERVER__LISTEN", listen)], None).expect_err(listen).to_string();
            assert!(err.contains("server.listen") && err.contains("allow_unauthenticated"), "{err}");
        }
        // ... and against the address actually bound.
        let c = config(&[], None).expect("defaults");
        let err = Security::load(&c, addr("0.0.0.0:1234")).expect_err("refused");
        assert_eq!(err.key, "server.listen");
        for ok in ["127.0.0.1:1", "[::1]:1", "[::ffff:127.0.0.1]:1"] {
            let s = Security::load(&c, addr(ok)).expect(ok);
            assert!(s.warnings.is_empty(), "{:?}", s.warnings);
        }

        let allowed =
            [("RELREWARD__SERVER__LISTEN", "0.0.0.0:50051"), ("RELREWARD__SECURITY__ALLOW_UNAUTHENTICATED", "true")];
        let c = config(&allowed, None).expect("allowed");
        let s = Security::load(&c, addr("0.0.0.0:50051")).expect("allowed");
        assert!(s.layer.is_open());
        assert!(s.warnings.iter().any(|w| w.contains("without authentication")), "{:?}", s.warnings);

        let c = config(&[("RELREWARD__SERVER__LISTEN", "0.0.0.0:50051")], Some(&token_file())).expect("tokens");
        let s = Security::load(&c, addr("0.0.0.0:50051")).expect("tokens");
        assert!(!s.layer.is_open());
        assert!(s.warnings.iter().any(|w| w.contains("plaintext")), "{:?}", s.warnings);
    }

    #[test]
    fn torchscript_upload_without_tokens_warns() {
        let c = config(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")], None).expect("config");
        let s = Security::load(&c, addr("127.0.0.1:1")).expect("load");
        assert!(s.warnings.iter().any(|w| w.contains("TorchScript")), "{:?}", s.warnings);
    }

    #[test]
    fn tls_settings_are_checked_at_start() {
        let err = config(&[("RELREWARD__SECURITY__TLS__CERT", "/x.pem")], None).expect_err("cert alone").to_string();
        assert!(err.contains("security.tls"), "{err}");
        let err =
            config(&[("RELREWARD__SECURITY__TLS__CLIENT_CA", "/ca.pem")], None).expect_err("ca alone").to_string();
        assert!(err.contains("security.tls.client_ca"), "{err}");

        let c = config(
            &[
                ("RELREWARD__SECURITY__TLS__CERT", "/nonexistent/cert.pem"),
                ("RELREWARD__SECURITY__TLS__KEY", "/nonexistent/key.pem"),
            ],
            None,
        )
        .expect("config");
        let err = Security::load(&c, addr("127.0.0.1:1")).expect_err("missing file");
        assert_eq!(err.key, "security.tls.cert");

        let dir = tempfile::tempdir().expect("dir");
        let junk = dir.path().join("junk.pem");
        std::fs::write(&junk, "-----BEGIN CERTIFICATE-----\nnot base64\n-----END CERTIFICATE-----\n").expect("write");
        let key = dir.path().join("key.pem");
        std::fs::write(&key, "-----BEGIN PRIVATE KEY-----\nAAAA\n-----END PRIVATE KEY-----\n").expect("write");
        let (junk, key) = (junk.to_str().expect("utf8"), key.to_str().expect("utf8"));
        let c = config(&[("RELREWARD__SECURITY__TLS__CERT", junk), ("RELREWARD__SECURITY__TLS__KEY", key)], None)
            .expect("config");
        let err = Security::load(&c, addr("127.0.0.1:1")).expect_err("junk PEM");
        assert!(err.key.starts_with("security.tls"), "{err}");
    }

    #[test]
    fn bad_token_entries_stop_the_start() {
        let file = "[security]\ntokens = [{ name = \"a\", hash = \"rrt_abc\", scopes = [\"read\"] }]\n";
        let c = config(&[], Some(file)).expect("config parses");
        let err = Security::load(&c, addr("127.0.0.1:1")).expect_err("bad hash");
        assert_eq!(err.key, "security.tokens[0].hash");
        // Unknown fields in an entry are configuration errors naming the field.
        let file = "[security]\ntokens = [{ name = \"a\", hash = \"x\", scopes = [\"read\"], role = \"x\" }]\n";
        let err = config(&[], Some(file)).expect_err("unknown field").to_string();
        assert!(err.contains("role"), "{err}");
    }
}
