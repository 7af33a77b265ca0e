//! Service configuration: embedded defaults, then an optional TOML file, then
//! `RELREWARD__SECTION__KEY` environment variables, then command-line flags (highest).
//!
//! Unknown keys are errors (a typo must not silently fall back to a default), and
//! [`Config::validate`] names the offending key in every message.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::Deserialize;

/// The defaults, also shipped as documentation in `deploy/config.example.toml`.
pub const DEFAULTS: &str = include_str!("defaults.toml");

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub server: ServerConfig,
    pub storage: StorageConfig,
    pub datasets: DatasetsConfig,
    pub models: ModelsConfig,
    pub jobs: JobsConfig,
    pub engine: EngineConfig,
    pub serving: ServingConfig,
    pub metrics: MetricsConfig,
    pub log: LogConfig,
    pub security: SecurityConfig,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    /// Address to listen on; loopback by default so nothing is exposed by accident.
    pub listen: String,
    /// Largest request message accepted (tonic's own default of 4 MiB is too small for
    /// tensors, and unbounded would let one client exhaust memory).
    pub max_request_bytes: usize,
    /// Largest response message sent.
    pub max_response_bytes: usize,
    /// Connections served at once; one beyond is closed at once (the client sees
    /// UNAVAILABLE and can back off) rather than left waiting unanswered in the accept backlog.
    pub max_connections: usize,
    /// HTTP/2 streams (calls) open at once on one connection, announced to the client in
    /// SETTINGS_MAX_CONCURRENT_STREAMS: a client with more calls queues them itself, so one
    /// connection cannot open unbounded handler tasks.
    pub max_concurrent_streams: u32,
    /// How long in-flight calls may take to finish after SIGINT/SIGTERM.
    pub shutdown_grace_secs: u64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StorageConfig {
    /// Only "embedded" (SQLite metadata + files under data_dir) exists today; the storage
    /// traits leave room for a PostgreSQL + object store backend.
    pub backend: String,
    pub data_dir: PathBuf,
    /// Bytes the data directory may hold (datasets, models, checkpoints, metadata); an upload
    /// that would go beyond it is RESOURCE_EXHAUSTED before any of it is written. 0: no budget.
    pub max_bytes: u64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetsConfig {
    /// Largest payload of one dataset upload, in bytes (RESOURCE_EXHAUSTED above it).
    pub max_upload_bytes: u64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelsConfig {
    /// Accept TorchScript uploads. Off by default: a TorchScript file is a program, and
    /// loading it runs its author's code inside the server.
    pub allow_torchscript_upload: bool,
    /// Largest TorchScript upload, in bytes.
    pub max_upload_bytes: u64,
    /// Loaded models kept in memory, by their parameter and buffer bytes; beyond it the least
    /// recently used are dropped and reloaded from disk on demand.
    pub cache_bytes: u64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobsConfig {
    /// Jobs running at once (each on its own thread).
    pub max_concurrent: usize,
    /// Jobs waiting beyond those; more submissions are RESOURCE_EXHAUSTED.
    pub queue_capacity: usize,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EngineConfig {
    /// libtorch intra-op threads (0: one per core).
    pub intra_op_threads: usize,
    /// Sampling requests computed at once (each on a blocking thread); more wait their turn.
    pub inference_workers: usize,
}

/// Score and Gradient serving: dynamic batching per reward model (see `serving`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServingConfig {
    /// Most items one request may carry (INVALID_ARGUMENT above it).
    pub max_request_items: usize,
    /// Most items merged into one forward/backward pass.
    pub max_batch: usize,
    /// How long a batch waits for more requests after its first one arrived, in microseconds
    /// (0: take whatever is queued and go).
    pub max_delay_us: u64,
    /// Requests waiting per model; more are RESOURCE_EXHAUSTED at once.
    pub queue_capacity: usize,
    /// Deadline given to Score, Gradient and OIP ModelInfer calls that carry no
    /// `grpc-timeout`, in milliseconds, so an abandoned query leaves the queue instead of
    /// being computed (0: none; see `limits::DeadlineLayer`).
    pub default_deadline_ms: u64,
}

/// Prometheus metrics over plain HTTP (`GET /metrics`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetricsConfig {
    /// IP:port of the metrics endpoint; empty disables it. Port 0 picks a free port (logged).
    pub listen: String,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogConfig {
    /// "human" or "json".
    pub format: String,
    /// A tracing filter such as "info" or "relreward_server=debug,info". RUST_LOG overrides it.
    pub level: String,
}

/// Access control and TLS (see `crate::security` and docs/security.md).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SecurityConfig {
    /// Bearer tokens, as salted hashes (`relreward-server token create` makes one). When
    /// empty, every call is admitted, which is allowed only on a loopback listener unless
    /// `allow_unauthenticated` says otherwise.
    pub tokens: Vec<TokenConfig>,
    /// Serve without tokens on a non-loopback address. Off: anyone who can reach the port
    /// could upload data, start jobs and delete models, so the server refuses to start.
    pub allow_unauthenticated: bool,
    pub tls: TlsConfig,
}

/// One entry of `security.tokens` (checked by `security::TokenTable::from_config`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenConfig {
    /// Shown in logs and refusals; unique.
    pub name: String,
    /// `sha256:SALT:DIGEST`; the token itself is never configured.
    pub hash: String,
    /// Any of "read", "train", "admin"; the highest one counts (admin includes train,
    /// which includes read).
    pub scopes: Vec<String>,
    /// RFC 3339 time after which the token is refused; absent or empty: never.
    #[serde(default)]
    pub expires: Option<String>,
}

/// TLS on the gRPC listener (native API and OIP alike); all empty: plaintext.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// PEM certificate chain of the server (leaf first).
    pub cert: PathBuf,
    /// PEM private key of `cert`.
    pub key: PathBuf,
    /// PEM CA certificate(s); when set, every client must present a certificate they signed
    /// (mutual TLS).
    pub client_ca: PathBuf,
}

impl TlsConfig {
    pub fn enabled(&self) -> bool {
        !self.cert.as_os_str().is_empty()
    }
}

/// Values given on the command line; they override every other source.
#[derive(Debug, Default, Clone)]
pub struct Overrides {
    pub listen: Option<String>,
    pub data_dir: Option<PathBuf>,
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("configuration: {0}")]
    Load(#[from] config::ConfigError),
    #[error("configuration key {key}: {message}")]
    Invalid { key: &'static str, message: String },
}

impl Config {
    /// Loads defaults, the optional file, the environment and the overrides, then validates.
    pub fn load(file: Option<&Path>, overrides: &Overrides) -> Result<Self, ConfigError> {
        Self::load_with_env(file, overrides, config::Environment::with_prefix("RELREWARD"))
    }

    /// As [`Config::load`], reading environment variables from `env` (tests pass a map).
    pub fn load_with_env(
        file: Option<&Path>,
        overrides: &Overrides,
        env: config::Environment,
    ) -> Result<Self, ConfigError> {
        let mut builder =
            config::Config::builder().add_source(config::File::from_str(DEFAULTS, config::FileFormat::Toml));
        if let Some(path) = file {
            builder = builder.add_source(config::File::from(path).format(config::FileFormat::Toml).required(true));
        }
        builder = builder.add_source(env.prefix_separator("__").separator("__").try_parsing(true));
        if let Some(listen) = &overrides.listen {
            builder = builder.set_override("server.listen", listen.as_str())?;
        }
        if let Some(dir) = &overrides.data_dir {
            builder = builder.set_override("storage.data_dir", dir.to_string_lossy().as_ref())?;
        }
        let cfg: Config = builder.build()?.try_deserialize()?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks what types alone cannot; every error names its key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |key, message: String| Err(ConfigError::Invalid { key, message });
        if self.server.listen.parse::<SocketAddr>().is_err() {
            return invalid(
                "server.listen",
                format!("'{}' is not an IP:port socket address (e.g. 127.0.0.1:50051)", self.server.listen),
            );
        }
        if !(1024..=1 << 30).contains(&self.server.max_request_bytes) {
            return invalid("server.max_request_bytes", "must be between 1024 and 1073741824".into());
        }
        if !(1024..=1 << 30).contains(&self.server.max_response_bytes) {
            return invalid("server.max_response_bytes", "must be between 1024 and 1073741824".into());
        }
        if !(1..=1 << 20).contains(&self.server.max_connections) {
            return invalid("server.max_connections", "must be between 1 and 1048576".into());
        }
        if self.server.max_concurrent_streams == 0 {
            return invalid("server.max_concurrent_streams", "must be positive".into());
        }
        if self.server.shutdown_grace_secs > 3600 {
            return invalid("server.shutdown_grace_secs", "must be at most 3600".into());
        }
        if self.storage.backend != "embedded" {
            return invalid(
                "storage.backend",
                format!("unknown backend '{}' (supported: \"embedded\")", self.storage.backend),
            );
        }
        if self.storage.data_dir.as_os_str().is_empty() {
            return invalid("storage.data_dir", "must not be empty".into());
        }
        if self.datasets.max_upload_bytes == 0 {
            return invalid("datasets.max_upload_bytes", "must be positive".into());
        }
        if self.models.max_upload_bytes == 0 {
            return invalid("models.max_upload_bytes", "must be positive".into());
        }
        if self.jobs.max_concurrent == 0 || self.jobs.max_concurrent > 64 {
            return invalid("jobs.max_concurrent", "must be between 1 and 64".into());
        }
        if self.jobs.queue_capacity == 0 {
            return invalid("jobs.queue_capacity", "must be positive".into());
        }
        if self.engine.inference_workers == 0 || self.engine.inference_workers > 256 {
            return invalid("engine.inference_workers", "must be between 1 and 256".into());
        }
        if self.engine.intra_op_threads > 1024 {
            return invalid("engine.intra_op_threads", "must be at most 1024 (0: one per core)".into());
        }
        if !(1..=1 << 20).contains(&self.serving.max_request_items) {
            return invalid("serving.max_request_items", "must be between 1 and 1048576".into());
        }
        if !(1..=1 << 20).contains(&self.serving.max_batch) {
            return invalid("serving.max_batch", "must be between 1 and 1048576".into());
        }
        if self.serving.max_delay_us > 1_000_000 {
            return invalid("serving.max_delay_us", "must be at most 1000000 (one second)".into());
        }
        if !(1..=1 << 20).contains(&self.serving.queue_capacity) {
            return invalid("serving.queue_capacity", "must be between 1 and 1048576".into());
        }
        if self.serving.default_deadline_ms > 3_600_000 {
            return invalid("serving.default_deadline_ms", "must be at most 3600000 (one hour; 0: none)".into());
        }
        if !self.metrics.listen.is_empty() && self.metrics.listen.parse::<SocketAddr>().is_err() {
            return invalid(
                "metrics.listen",
                format!("'{}' is not an IP:port socket address (or empty to disable)", self.metrics.listen),
            );
        }
        if !matches!(self.log.format.as_str(), "human" | "json") {
            return invalid("log.format", format!("'{}' is neither \"human\" nor \"json\"", self.log.format));
        }
        if tracing_subscriber::EnvFilter::try_new(&self.log.level).is_err() {
            return invalid("log.level", format!("'{}' is not a tracing filter", self.log.level));
        }
        let tls = &self.security.tls;
        if tls.cert.as_os_str().is_empty() != tls.key.as_os_str().is_empty() {
            return invalid("security.tls", "cert and key go together: set both (TLS) or neither (plaintext)".into());
        }
        if !tls.client_ca.as_os_str().is_empty() && !tls.enabled() {
            return invalid("security.tls.client_ca", "mutual TLS needs TLS: set security.tls.cert and key too".into());
        }
        // Tokens themselves are parsed by `security::Security::load` at start; here only the
        // listener rule, which needs no more than whether there are any.
        if let Some(message) = self.unauthenticated_exposure(self.listen_addr()) {
            return invalid("server.listen", message);
        }
        Ok(())
    }

    /// Why serving on `listen` is refused: a non-loopback address with no tokens, unless
    /// `security.allow_unauthenticated` is set. `None` when allowed.
    pub fn unauthenticated_exposure(&self, listen: SocketAddr) -> Option<String> {
        let exposed = !listen.ip().to_canonical().is_loopback()
            && self.security.tokens.is_empty()
            && !self.security.allow_unauthenticated;
        exposed.then(|| {
            format!(
                "{listen} is not a loopback address and security.tokens is empty: anyone who can reach the port could \
                 upload data, start jobs and delete models. Configure tokens (`relreward-server token create \
                 --scopes read`), or set security.allow_unauthenticated = true to serve without them on purpose"
            )
        })
    }

    pub fn listen_addr(&self) -> SocketAddr {
        // Checked by validate().
        self.server.listen.parse().unwrap_or_else(|_| SocketAddr::from(([127, 0, 0, 1], 50051)))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;
    use std::io::Write;

    use super::*;

    fn env(vars: &[(&str, &str)]) -> config::Environment {
        let map: HashMap<String, String> = vars.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned())).collect();
        config::Environment::with_prefix("RELREWARD").source(Some(map))
    }

    fn load(file: Option<&Path>, vars: &[(&str, &str)], o: &Overrides) -> Result<Config, ConfigError> {
        Config::load_with_env(file, o, env(vars))
    }

    fn write_file(text: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::Builder::new().suffix(".toml").tempfile().expect("temp file");
        f.write_all(text.as_bytes()).expect("write");
        f
    }

    #[test]
    fn defaults_are_valid_and_loopback() {
        let c = load(None, &[], &Overrides::default()).expect("defaults load");
        assert_eq!(c.server.listen, "127.0.0.1:50051");
        assert!(c.listen_addr().ip().is_loopback());
        assert_eq!(c.storage.data_dir, PathBuf::from("./data"));
        assert_eq!(c.server.max_request_bytes, 16 << 20);
    }

    #[test]
    fn precedence_is_defaults_file_env_flags() {
        let f =
            write_file("[server]\nlisten = \"127.0.0.1:7000\"\nshutdown_grace_secs = 3\n[log]\nformat = \"json\"\n");
        let c = load(Some(f.path()), &[], &Overrides::default()).expect("file");
        assert_eq!(
            (c.server.listen.as_str(), c.server.shutdown_grace_secs, c.log.format.as_str()),
            ("127.0.0.1:7000", 3, "json")
        );

        let vars =
            [("RELREWARD__SERVER__LISTEN", "127.0.0.1:7001"), ("RELREWARD__DATASETS__MAX_UPLOAD_BYTES", "12345")];
        let c = load(Some(f.path()), &vars, &Overrides::default()).expect("env");
        assert_eq!(c.server.listen, "127.0.0.1:7001");
        assert_eq!(c.datasets.max_upload_bytes, 12345);
        assert_eq!(c.server.shutdown_grace_secs, 3, "file value kept where env is silent");

        let o = Overrides { listen: Some("127.0.0.1:7002".into()), data_dir: Some("/tmp/x".into()) };
        let c = load(Some(f.path()), &vars, &o).expect("flags");
        assert_eq!(c.server.listen, "127.0.0.1:7002");
        assert_eq!(c.storage.data_dir, PathBuf::from("/tmp/x"));
    }

    #[test]
    fn invalid_values_name_their_key() {
        let cases: &[(&[(&str, &str)], &str)] = &[
            (&[("RELREWARD__SERVER__LISTEN", "localhost")], "server.listen"),
            (&[("RELREWARD__SERVER__MAX_REQUEST_BYTES", "10")], "server.max_request_bytes"),
            (&[("RELREWARD__STORAGE__BACKEND", "cassandra")], "storage.backend"),
            (&[("RELREWARD__DATASETS__MAX_UPLOAD_BYTES", "0")], "datasets.max_upload_bytes"),
            (&[("RELREWARD__LOG__FORMAT", "xml")], "log.format"),
            (&[("RELREWARD__SERVER__MAX_CONNECTIONS", "0")], "server.max_connections"),
            (&[("RELREWARD__SERVER__MAX_CONCURRENT_STREAMS", "0")], "server.max_concurrent_streams"),
            (&[("RELREWARD__SERVING__DEFAULT_DEADLINE_MS", "3600001")], "serving.default_deadline_ms"),
        ];
        for (vars, key) in cases {
            let err = load(None, vars, &Overrides::default()).expect_err(key).to_string();
            assert!(err.contains(key), "{err} should name {key}");
        }
    }

    #[test]
    fn wrong_types_and_unknown_keys_are_errors_naming_the_key() {
        let f = write_file("[server]\nshutdown_grace_secs = \"soon\"\n");
        let err = load(Some(f.path()), &[], &Overrides::default()).expect_err("type").to_string();
        assert!(err.contains("shutdown_grace_secs"), "{err}");

        let f = write_file("[server]\nlisten_address = \"127.0.0.1:1\"\n");
        let err = load(Some(f.path()), &[], &Overrides::default()).expect_err("unknown").to_string();
        assert!(err.contains("listen_address"), "{err}");
    }

    #[test]
    fn example_config_in_deploy_matches_the_defaults() {
        let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/config.example.toml");
        let from_file = load(Some(&example), &[], &Overrides::default()).expect("example loads");
        assert_eq!(from_file, load(None, &[], &Overrides::default()).expect("defaults"));
    }

    #[test]
    fn tokens_load_from_a_file_in_either_toml_form() {
        let inline = "[security]\ntokens = [{ name = \"a\", hash = \"h1\", scopes = [\"read\"] }, \
                      { name = \"b\", hash = \"h2\", scopes = [\"train\"], expires = \"2030-01-01T00:00:00Z\" }]\n";
        let tables = "[[security.tokens]]\nname = \"a\"\nhash = \"h1\"\nscopes = [\"read\"]\n\
                      [[security.tokens]]\nname = \"b\"\nhash = \"h2\"\nscopes = [\"train\"]\n\
                      expires = \"2030-01-01T00:00:00Z\"\n";
        for text in [inline, tables] {
            let f = write_file(text);
            let c = load(Some(f.path()), &[], &Overrides::default()).expect("tokens load");
            let names: Vec<_> = c.security.tokens.iter().map(|t| t.name.as_str()).collect();
            assert_eq!(names, ["a", "b"]);
            assert_eq!(c.security.tokens[0].expires, None);
            assert_eq!(c.security.tokens[1].expires.as_deref(), Some("2030-01-01T00:00:00Z"));
            assert_eq!(c.security.tokens[1].scopes, ["train"]);
        }
        // With tokens, a non-loopback listener is allowed.
        let f = write_file(inline);
        let c = load(Some(f.path()), &[("RELREWARD__SERVER__LISTEN", "0.0.0.0:1")], &Overrides::default());
        assert!(c.is_ok(), "{c:?}");
    }

    #[test]
    fn missing_file_is_an_error() {
        let err = load(Some(Path::new("/nonexistent/relreward.toml")), &[], &Overrides::default());
        assert!(err.is_err());
    }
}
