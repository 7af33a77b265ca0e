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

/// HTTP/2 flow-control windows: the protocol's initial 65535 bytes at least (smaller only slows
/// every call), 2^31 - 1 at most (RFC 9113, 6.9.1).
const MIN_WINDOW: u32 = 65_535;
const MAX_WINDOW: u32 = (1 << 31) - 1;

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
    pub oip_http: OipHttpConfig,
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
    /// Largest request metadata (headers, counted as HTTP/2 does: name + value + 32 per
    /// entry). A call over it is refused alone with RESOURCE_EXHAUSTED naming this setting;
    /// HTTP/2 itself accepts header blocks up to [`ServerConfig::http2_header_list_bytes`], so
    /// that the refusal is a status and not a protocol error on the whole connection.
    pub max_metadata_bytes: usize,
    /// Connections served at once; one beyond is closed at once (the client sees
    /// UNAVAILABLE and can back off) rather than left waiting unanswered in the accept backlog.
    pub max_connections: usize,
    /// HTTP/2 streams (calls) open at once on one connection, announced to the client in
    /// SETTINGS_MAX_CONCURRENT_STREAMS: a client with more calls queues them itself, so one
    /// connection cannot open unbounded handler tasks.
    pub max_concurrent_streams: u32,
    /// How long in-flight calls may take to finish after SIGINT/SIGTERM, once the drain
    /// (`shutdown_drain_secs`) is over and the listener has closed.
    pub shutdown_grace_secs: u64,
    /// After SIGINT/SIGTERM, how long the server goes on serving everything, new connections
    /// and calls included, while health answers NOT_SERVING, so that load balancers and
    /// health-checking clients see it and stop sending before the listener closes. A second
    /// signal cuts it short. 0: close at once.
    pub shutdown_drain_secs: u64,
    /// HTTP/2 flow-control window of each call (stream), in bytes: what a client may send on a
    /// call ahead of the handler reading it. It bounds the unread data one call that stops
    /// reading (a GradientStream whose client does not read its responses) holds in memory.
    pub http2_stream_window_bytes: u32,
    /// HTTP/2 flow-control window of a whole connection, in bytes. At least
    /// `max_concurrent_streams` x `http2_stream_window_bytes`, so that calls that stop reading
    /// can never hold all of it and starve the other calls on their connection (health checks
    /// included): each holds at most its stream window.
    pub http2_connection_window_bytes: u32,
    /// Compressed responses: "request" (with the request's algorithm, when the request came
    /// compressed and the client accepts it), "accepted" (whenever the client's
    /// grpc-accept-encoding lists gzip or deflate: grpcio lists both on every call) or "off".
    /// Compressed requests (gzip, deflate) are accepted whatever this says.
    pub response_compression: String,
    /// Connections older than this are asked to go away (HTTP/2 GOAWAY; 0: never), so that
    /// long-lived clients reconnect and spread over replicas added since they connected.
    pub max_connection_age_secs: u64,
    /// How long calls still open on such a connection may take before it is closed.
    pub max_connection_age_grace_secs: u64,
    /// What this process does: "serve" (every RPC; submitted jobs go to the queue), "work"
    /// (runs queued jobs; its port answers health checks only) or "all" (both).
    pub role: String,
}

/// What a process does (`server.role`, `--role`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    Serve,
    Work,
    All,
}

impl Role {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "serve" => Some(Self::Serve),
            "work" => Some(Self::Work),
            "all" => Some(Self::All),
            _ => None,
        }
    }

    /// Answers the relreward and OIP APIs.
    pub fn serves(self) -> bool {
        matches!(self, Self::Serve | Self::All)
    }

    /// Takes jobs from the queue and runs them.
    pub fn works(self) -> bool {
        matches!(self, Self::Work | Self::All)
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StorageConfig {
    /// "embedded": SQLite metadata and files under data_dir, for one process. "shared":
    /// PostgreSQL metadata and job queue, files in an S3-compatible object store, for many
    /// processes; data_dir then holds staging files and a local cache of downloaded blobs.
    pub backend: String,
    pub data_dir: PathBuf,
    /// Bytes the data directory may hold (datasets, models, checkpoints, metadata); an upload
    /// that would go beyond it is RESOURCE_EXHAUSTED before any of it is written. 0: no budget.
    /// With the shared backend it bounds the local directory (staging and cache) only.
    pub max_bytes: u64,
    pub postgres: PostgresConfig,
    pub s3: S3Config,
}

/// The shared backend's metadata database (`storage.backend = "shared"`).
#[derive(Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PostgresConfig {
    /// libpq-style URL, e.g. postgres://relreward:PASSWORD@db:5432/relreward. Holds a
    /// password: set it through RELREWARD__STORAGE__POSTGRES__URL from a secret.
    pub url: String,
    /// Connections kept open by this process.
    pub pool_size: usize,
    /// PEM CA certificate(s) for the database server's certificate; empty: the system's roots.
    /// Whether TLS is used follows the URL's `sslmode` (prefer, require, disable).
    pub ca_file: String,
}

/// The shared backend's object store (`storage.backend = "shared"`).
#[derive(Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct S3Config {
    /// Empty: AWS S3 itself; otherwise the URL of an S3-compatible server.
    pub endpoint: String,
    /// Must exist.
    pub bucket: String,
    pub region: String,
    /// Prepended to every key ("team-a/" keeps several deployments in one bucket).
    pub prefix: String,
    pub access_key_id: String,
    pub secret_access_key: String,
    /// Allow a plain-HTTP endpoint (an object store inside the cluster or on loopback).
    pub allow_http: bool,
    /// Unreferenced files younger than this are left alone by start-up garbage collection:
    /// another process may be between publishing them and recording them.
    pub orphan_grace_secs: u64,
    /// Bound on the local blob cache (least recently used evicted first); 0: none.
    pub cache_max_bytes: u64,
    /// A cached blob used this recently is never evicted: its files may still be being read.
    pub cache_hold_secs: u64,
}

// By hand, so that no log line or error message ever prints a password.
impl std::fmt::Debug for PostgresConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let shown = match self.url.split_once('@') {
            Some((_, host)) => format!("postgres://***@{host}"),
            None => self.url.clone(),
        };
        f.debug_struct("PostgresConfig")
            .field("url", &shown)
            .field("pool_size", &self.pool_size)
            .field("ca_file", &self.ca_file)
            .finish()
    }
}

impl std::fmt::Debug for S3Config {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("S3Config")
            .field("endpoint", &self.endpoint)
            .field("bucket", &self.bucket)
            .field("region", &self.region)
            .field("prefix", &self.prefix)
            .field("access_key_id", &self.access_key_id)
            .field("secret_access_key", &"***")
            .field("allow_http", &self.allow_http)
            .field("orphan_grace_secs", &self.orphan_grace_secs)
            .field("cache_max_bytes", &self.cache_max_bytes)
            .field("cache_hold_secs", &self.cache_hold_secs)
            .finish()
    }
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
    /// A running job's lease: its worker renews it every second (lease_secs / 5 if shorter),
    /// reading cancellation requests as it does; a job whose lease ran out (its worker died)
    /// is taken over by another worker, from its last checkpoint.
    pub lease_secs: u64,
    /// How often an idle worker looks for queued jobs (a submission to the same process
    /// wakes it at once).
    pub poll_ms: u64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EngineConfig {
    /// Where tensors live and compute: `cpu`, `cuda`, `cuda:N` or `auto` (resolved once at
    /// start by `engine::init`; a device that is not there stops the start).
    pub device: String,
    /// libtorch intra-op threads (0: one per core).
    pub intra_op_threads: usize,
    /// Batched Score/Gradient passes and Sample runs computed at once (each on a blocking
    /// thread); more wait their turn.
    pub inference_workers: usize,
    /// Where a training step decides whether its update applies and how clipping scales it:
    /// `host` (each step's norm and loss read as it runs), `device` (decided on the device, the
    /// steps' figures read together where progress is reported, an evaluation or a checkpoint
    /// is made, at a stop or after 100 steps: a GPU waits for the host only there) or `auto`
    /// (device on CUDA, host on the CPU, where reading costs nothing). The same events either
    /// way, and on the CPU the same weights bit for bit.
    pub step_checks: String,
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
    /// After a pass of N queries, the next pass waits until N queries are queued again (the
    /// last pass's callers back), for at most this fraction of that pass's time (0: never).
    pub refill_fraction: f64,
    /// Threads one pass may split its rows across (each part on its own thread), taking as
    /// many of the free inference slots; 1: never split.
    pub pass_threads: usize,
    /// A model's passes are split only once one of them took at least this long, in
    /// milliseconds of compute (the threads' handoff must stay small beside a part).
    pub split_above_ms: f64,
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

/// The Open Inference Protocol over HTTP/JSON (KServe v2 REST, `crate::oip_http`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OipHttpConfig {
    /// IP:port of the HTTP listener; empty disables it. Port 0 picks a free port (printed).
    /// Same tokens and TLS as `server.listen`, and the same rule for non-loopback addresses.
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
    pub role: Option<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("configuration: {0}")]
    Load(#[from] config::ConfigError),
    #[error("configuration key {key}: {message}")]
    Invalid { key: &'static str, message: String },
}

impl ServerConfig {
    /// The HTTP/2 header list size the server accepts (SETTINGS_MAX_HEADER_LIST_SIZE): 16 times
    /// `max_metadata_bytes`, so that metadata over the setting still arrives as a call the
    /// server can refuse with a status (HTTP/2 answers a larger block with HTTP 431, and one
    /// much larger with a connection error).
    pub fn http2_header_list_bytes(&self) -> u32 {
        u32::try_from(self.max_metadata_bytes.saturating_mul(16)).unwrap_or(u32::MAX)
    }
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
        if let Some(role) = &overrides.role {
            builder = builder.set_override("server.role", role.as_str())?;
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
        if !(1024..=4 << 20).contains(&self.server.max_metadata_bytes) {
            return invalid("server.max_metadata_bytes", "must be between 1024 and 4194304".into());
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
        if self.server.shutdown_drain_secs > 600 {
            return invalid("server.shutdown_drain_secs", "must be at most 600 (0: no drain)".into());
        }
        if !(MIN_WINDOW..=MAX_WINDOW).contains(&self.server.http2_stream_window_bytes) {
            return invalid(
                "server.http2_stream_window_bytes",
                format!("must be between {MIN_WINDOW} and {MAX_WINDOW} (HTTP/2's largest window)"),
            );
        }
        if self.server.http2_connection_window_bytes > MAX_WINDOW {
            return invalid(
                "server.http2_connection_window_bytes",
                format!("must be at most {MAX_WINDOW} (HTTP/2's largest window)"),
            );
        }
        let all_streams =
            u64::from(self.server.max_concurrent_streams) * u64::from(self.server.http2_stream_window_bytes);
        if u64::from(self.server.http2_connection_window_bytes) < all_streams {
            let hint = if all_streams > u64::from(MAX_WINDOW) {
                format!(
                    "; that is beyond HTTP/2's largest window ({MAX_WINDOW}): lower server.max_concurrent_streams or \
                     server.http2_stream_window_bytes"
                )
            } else {
                String::new()
            };
            return invalid(
                "server.http2_connection_window_bytes",
                format!(
                    "{} is below server.max_concurrent_streams x server.http2_stream_window_bytes ({} x {} = \
                     {all_streams}){hint}: calls that stop reading could then hold the whole connection window and \
                     stall every other call on their connection, health checks included",
                    self.server.http2_connection_window_bytes,
                    self.server.max_concurrent_streams,
                    self.server.http2_stream_window_bytes,
                ),
            );
        }
        if !matches!(self.server.response_compression.as_str(), "request" | "accepted" | "off") {
            return invalid(
                "server.response_compression",
                format!("'{}' is none of \"request\", \"accepted\" or \"off\"", self.server.response_compression),
            );
        }
        if self.server.max_connection_age_grace_secs > 86_400 {
            return invalid("server.max_connection_age_grace_secs", "must be at most 86400".into());
        }
        if Role::parse(&self.server.role).is_none() {
            return invalid(
                "server.role",
                format!("'{}' is not a role (\"serve\", \"work\" or \"all\")", self.server.role),
            );
        }
        match self.storage.backend.as_str() {
            "embedded" => {
                if self.role() != Role::All {
                    return invalid(
                        "server.role",
                        "only \"all\" with storage.backend = \"embedded\": its SQLite file and data directory belong \
                         to one process; separate serve and work processes need storage.backend = \"shared\""
                            .into(),
                    );
                }
            }
            "shared" => self.validate_shared()?,
            other => {
                return invalid(
                    "storage.backend",
                    format!("unknown backend '{other}' (supported: \"embedded\", \"shared\")"),
                );
            }
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
        if !(2..=86_400).contains(&self.jobs.lease_secs) {
            return invalid("jobs.lease_secs", "must be between 2 and 86400".into());
        }
        if !(10..=600_000).contains(&self.jobs.poll_ms) {
            return invalid("jobs.poll_ms", "must be between 10 and 600000".into());
        }
        if self.engine.inference_workers == 0 || self.engine.inference_workers > 256 {
            return invalid("engine.inference_workers", "must be between 1 and 256".into());
        }
        if !["auto", "host", "device"].contains(&self.engine.step_checks.as_str()) {
            return invalid(
                "engine.step_checks",
                format!("'{}' is not one of auto, host or device", self.engine.step_checks),
            );
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
        if !(0.0..=1.0).contains(&self.serving.refill_fraction) {
            return invalid(
                "serving.refill_fraction",
                "must be between 0 and 1 (0: never wait for returning callers)".into(),
            );
        }
        if !(1..=256).contains(&self.serving.pass_threads) {
            return invalid("serving.pass_threads", "must be between 1 and 256 (1: never split a pass)".into());
        }
        if !(0.0..=60_000.0).contains(&self.serving.split_above_ms) {
            return invalid("serving.split_above_ms", "must be between 0 and 60000 (one minute)".into());
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
        if !self.oip_http.listen.is_empty() {
            let Ok(addr) = self.oip_http.listen.parse::<SocketAddr>() else {
                return invalid(
                    "oip_http.listen",
                    format!("'{}' is not an IP:port socket address (or empty to disable)", self.oip_http.listen),
                );
            };
            if let Some(message) = self.unauthenticated_exposure(addr) {
                return invalid("oip_http.listen", message);
            }
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

    /// The shared backend's keys: present and well-formed.
    fn validate_shared(&self) -> Result<(), ConfigError> {
        let invalid = |key, message: String| Err(ConfigError::Invalid { key, message });
        let pg = &self.storage.postgres;
        if !(pg.url.starts_with("postgres://") || pg.url.starts_with("postgresql://")) {
            return invalid(
                "storage.postgres.url",
                "must be a postgres:// URL with storage.backend = \"shared\" (e.g. \
                 postgres://relreward:PASSWORD@db:5432/relreward)"
                    .into(),
            );
        }
        if !(1..=1024).contains(&pg.pool_size) {
            return invalid("storage.postgres.pool_size", "must be between 1 and 1024".into());
        }
        let s3 = &self.storage.s3;
        if s3.bucket.is_empty() {
            return invalid("storage.s3.bucket", "must be set with storage.backend = \"shared\"".into());
        }
        if s3.region.is_empty() {
            return invalid("storage.s3.region", "must not be empty (e.g. us-east-1)".into());
        }
        if !(s3.endpoint.is_empty() || s3.endpoint.starts_with("http://") || s3.endpoint.starts_with("https://")) {
            return invalid("storage.s3.endpoint", format!("'{}' is not an http(s):// URL", s3.endpoint));
        }
        if s3.endpoint.starts_with("http://") && !s3.allow_http {
            return invalid(
                "storage.s3.endpoint",
                "is plain http: set storage.s3.allow_http = true to send data and credentials unencrypted".into(),
            );
        }
        if s3.access_key_id.is_empty() != s3.secret_access_key.is_empty() {
            return invalid(
                "storage.s3.secret_access_key",
                "access_key_id and secret_access_key go together (both empty: credentials from the environment)".into(),
            );
        }
        if s3.prefix.starts_with('/') || s3.prefix.contains("..") {
            return invalid("storage.s3.prefix", "must be relative and must not contain '..'".into());
        }
        Ok(())
    }

    /// The validated `server.role`.
    pub fn role(&self) -> Role {
        Role::parse(&self.server.role).unwrap_or(Role::All)
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

        let o = Overrides { listen: Some("127.0.0.1:7002".into()), data_dir: Some("/tmp/x".into()), role: None };
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
            // 257 streams x 1 MiB no longer fit the default 256 MiB connection window.
            (&[("RELREWARD__SERVER__MAX_CONCURRENT_STREAMS", "257")], "server.http2_connection_window_bytes"),
            (
                &[("RELREWARD__SERVER__HTTP2_CONNECTION_WINDOW_BYTES", "1048576")],
                "server.http2_connection_window_bytes",
            ),
            (&[("RELREWARD__SERVER__HTTP2_STREAM_WINDOW_BYTES", "1024")], "server.http2_stream_window_bytes"),
            (&[("RELREWARD__SERVER__HTTP2_STREAM_WINDOW_BYTES", "2147483648")], "server.http2_stream_window_bytes"),
            (&[("RELREWARD__SERVER__SHUTDOWN_DRAIN_SECS", "601")], "server.shutdown_drain_secs"),
            (&[("RELREWARD__SERVER__RESPONSE_COMPRESSION", "zstd")], "server.response_compression"),
            (&[("RELREWARD__SERVING__DEFAULT_DEADLINE_MS", "3600001")], "serving.default_deadline_ms"),
            (&[("RELREWARD__SERVING__REFILL_FRACTION", "1.5")], "serving.refill_fraction"),
            (&[("RELREWARD__SERVING__REFILL_FRACTION", "NaN")], "serving.refill_fraction"),
            (&[("RELREWARD__SERVING__PASS_THREADS", "0")], "serving.pass_threads"),
            (&[("RELREWARD__SERVING__SPLIT_ABOVE_MS", "-1")], "serving.split_above_ms"),
            (&[("RELREWARD__SERVER__ROLE", "boss")], "server.role"),
            // Separate roles need the shared backend: the SQLite file belongs to one process.
            (&[("RELREWARD__SERVER__ROLE", "serve")], "server.role"),
            (&[("RELREWARD__JOBS__LEASE_SECS", "1")], "jobs.lease_secs"),
            (&[("RELREWARD__ENGINE__STEP_CHECKS", "gpu")], "engine.step_checks"),
            (&[("RELREWARD__STORAGE__BACKEND", "shared")], "storage.postgres.url"),
        ];
        for (vars, key) in cases {
            let err = load(None, vars, &Overrides::default()).expect_err(key).to_string();
            assert!(err.contains(key), "{err} should name {key}");
        }
    }

    #[test]
    fn the_connection_window_holds_every_stream_window() {
        let c = load(None, &[], &Overrides::default()).expect("defaults");
        let s = &c.server;
        assert!(
            u64::from(s.http2_connection_window_bytes)
                >= u64::from(s.max_concurrent_streams) * u64::from(s.http2_stream_window_bytes),
            "{s:?}"
        );
        assert_eq!((s.http2_stream_window_bytes, s.response_compression.as_str()), (1 << 20, "request"));
        // Raising the streams alone is refused; with the connection window raised too, fine.
        let more = [("RELREWARD__SERVER__MAX_CONCURRENT_STREAMS", "512")];
        let err = load(None, &more, &Overrides::default()).expect_err("window too small").to_string();
        assert!(err.contains("512 x 1048576 = 536870912"), "{err}");
        let both = [more[0], ("RELREWARD__SERVER__HTTP2_CONNECTION_WINDOW_BYTES", "536870912")];
        assert!(load(None, &both, &Overrides::default()).is_ok());
        // Beyond what HTTP/2 can announce: says which keys to lower.
        let huge = [("RELREWARD__SERVER__MAX_CONCURRENT_STREAMS", "4096")];
        let err = load(None, &huge, &Overrides::default()).expect_err("beyond 2^31 - 1").to_string();
        assert!(err.contains("largest window") && err.contains("lower server.max_concurrent_streams"), "{err}");
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
    fn the_shared_backend_checks_its_keys_and_never_prints_secrets() {
        let shared = [
            ("RELREWARD__STORAGE__BACKEND", "shared"),
            ("RELREWARD__SERVER__ROLE", "work"),
            ("RELREWARD__STORAGE__POSTGRES__URL", "postgres://rr:hunter2@db:5432/rr"),
            ("RELREWARD__STORAGE__S3__BUCKET", "b"),
            ("RELREWARD__STORAGE__S3__ENDPOINT", "http://s3:9000"),
            ("RELREWARD__STORAGE__S3__ACCESS_KEY_ID", "AKIA"),
            ("RELREWARD__STORAGE__S3__SECRET_ACCESS_KEY", "s3cret"),
        ];
        let err = load(None, &shared, &Overrides::default()).expect_err("plain http").to_string();
        assert!(err.contains("storage.s3.endpoint") && err.contains("allow_http"), "{err}");
        let mut vars = shared.to_vec();
        vars.push(("RELREWARD__STORAGE__S3__ALLOW_HTTP", "true"));
        let c = load(None, &vars, &Overrides::default()).expect("shared config");
        assert_eq!(c.role(), Role::Work);
        let o = Overrides { role: Some("serve".into()), ..Overrides::default() };
        assert_eq!(load(None, &vars, &o).expect("flag").role(), Role::Serve, "--role wins");
        let shown = format!("{c:?}");
        assert!(!shown.contains("hunter2") && !shown.contains("s3cret"), "{shown}");

        let mut one_key = vars.clone();
        one_key.retain(|(k, _)| *k != "RELREWARD__STORAGE__S3__SECRET_ACCESS_KEY");
        let err = load(None, &one_key, &Overrides::default()).expect_err("half the credentials").to_string();
        assert!(err.contains("storage.s3.secret_access_key"), "{err}");
        let mut no_bucket = vars.clone();
        no_bucket.retain(|(k, _)| *k != "RELREWARD__STORAGE__S3__BUCKET");
        let err = load(None, &no_bucket, &Overrides::default()).expect_err("no bucket").to_string();
        assert!(err.contains("storage.s3.bucket"), "{err}");
    }

    #[test]
    fn missing_file_is_an_error() {
        let err = load(Some(Path::new("/nonexistent/relreward.toml")), &[], &Overrides::default());
        assert!(err.is_err());
    }
}
