//! The commands of the `relreward` binary, one family per module. The top-level `Cli`, the
//! dispatch and the exit status are in `main.rs`.
//!
//! - [`datasets`]: `dataset upload|list|show|delete`;
//! - [`models`]: `model upload|import|list|show|delete`, with [`manifest`] (the manifest file format);
//! - [`jobs`]: `train diffusion|reward|discriminator` (specs built by [`train`]) and
//!   `job list|show|cancel|watch`;
//! - [`rewards`]: `score`, `grad` and `sample` (the RewardService: inputs from `.npz` files,
//!   trajectories cut into windows, results written as `.npz`), one module per command;
//! - [`extract`]: `extract` (recordings to rewards: convert, profile, upload or reuse, train,
//!   evaluate; composed of the other commands, run in process);
//! - [`demo`]: `demo` (the whole Maze2D pipeline: generated data, then `extract`'s steps and steering);
//! - [`eval`]: `eval discriminate|heatmap` and `job plot` (the paper's evaluation and its
//!   pictures, over scores of local trajectory files);
//! - [`maze`]: `maze generate` (Maze2D datasets from the built-in generator, no server);
//! - [`output`]: JSON and text formatting (job state names included), progress bars, terminal
//!   I/O.

pub mod datasets;
pub mod demo;
pub mod eval;
pub mod extract;
pub mod jobs;
pub mod manifest;
pub mod maze;
pub mod models;
pub mod output;
pub mod rewards;
pub mod train;

use std::fmt;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context as _, Result, bail};
use relreward_client::Client;
use relreward_client::client::{ConnectOptions, TlsOptions};
use serde_json::{Value, json};
use tonic_health::pb::health_check_response::ServingStatus;

pub const DEFAULT_ENDPOINT: &str = "http://127.0.0.1:50051";

/// The URL of an `--endpoint` as given: a URL with a scheme (`http://`, `https://`) is kept as
/// it is; a bare `host:port` (no `://`) is taken as plain `http://host:port`.
pub fn endpoint_url(given: &str) -> String {
    let given = given.trim();
    if given.contains("://") { given.to_owned() } else { format!("http://{given}") }
}
/// How long to wait for the server to accept the connection.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(15);

/// The global options saying how to reach the server beyond its address: a token, and TLS
/// files for `https://` endpoints.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ConnectArgs {
    /// Access token, sent with every call (servers with security.tokens; made by
    /// `relreward-server token create`).
    #[arg(long, global = true, env = "RELREWARD_TOKEN", hide_env_values = true, value_name = "TOKEN")]
    pub token: Option<String>,
    /// PEM CA certificate that signed the server's certificate (https:// endpoints)
    /// [default: the system's roots].
    #[arg(long, global = true, env = "RELREWARD_CA_CERT", value_name = "FILE")]
    pub ca_cert: Option<PathBuf>,
    /// PEM client certificate, for servers that require mutual TLS (with --client-key).
    #[arg(long, global = true, env = "RELREWARD_CLIENT_CERT", value_name = "FILE")]
    pub client_cert: Option<PathBuf>,
    /// PEM private key of --client-cert.
    #[arg(long, global = true, env = "RELREWARD_CLIENT_KEY", value_name = "FILE")]
    pub client_key: Option<PathBuf>,
    /// Name to verify the server's certificate against, when it is not the endpoint's host.
    #[arg(long, global = true, env = "RELREWARD_TLS_SERVER_NAME", value_name = "NAME")]
    pub tls_server_name: Option<String>,
}

impl ConnectArgs {
    /// The client library's options, with the files read.
    pub fn options(&self) -> Result<ConnectOptions> {
        let identity = match (&self.client_cert, &self.client_key) {
            (Some(cert), Some(key)) => Some((cert.as_path(), key.as_path())),
            (None, None) => None,
            (Some(_), None) => return Err(UsageError("--client-cert needs --client-key".into()).into()),
            (None, Some(_)) => return Err(UsageError("--client-key needs --client-cert".into()).into()),
        };
        let tls = if self.ca_cert.is_some() || identity.is_some() || self.tls_server_name.is_some() {
            let tls = TlsOptions::from_files(self.ca_cert.as_deref(), identity, self.tls_server_name.clone())
                .context("reading the TLS files")?;
            Some(tls)
        } else {
            None
        };
        let token = self.token.clone().filter(|t| !t.trim().is_empty());
        Ok(ConnectOptions { token, tls })
    }
}

/// What every command gets from the global options.
#[derive(Debug, Clone)]
pub struct Ctx {
    pub endpoint: String,
    /// `--json`: machine-readable output on stdout, no progress bars.
    pub json: bool,
    /// `--token`, `--ca-cert`, `--client-cert`, `--client-key`, `--tls-server-name`.
    pub connect: ConnectArgs,
}

impl Ctx {
    pub async fn connect(&self) -> Result<Client> {
        let endpoint = self.endpoint.as_str();
        let options = self.connect.options()?;
        match tokio::time::timeout(CONNECT_TIMEOUT, Client::connect_with(endpoint, &options)).await {
            Ok(client) => Ok(client?),
            Err(_) => bail!("cannot connect to {endpoint}: no answer within {} s", CONNECT_TIMEOUT.as_secs()),
        }
    }
}

/// What a command prints when it is done: `text`, or with `--json` the `json` document (none
/// for commands that already streamed their output); `success: false` exits with status 1.
#[derive(Debug)]
pub struct Report {
    pub text: String,
    pub json: Option<Value>,
    pub success: bool,
}

impl Report {
    pub fn ok(text: String, json: Value) -> Self {
        Self { text, json: Some(json), success: true }
    }

    /// A successful command whose JSON output was already written as it went.
    pub fn streamed(text: String) -> Self {
        Self { text, json: None, success: true }
    }
}

/// A command line that parses but cannot be run as given (exit status 2, like clap's errors).
#[derive(Debug)]
pub struct UsageError(pub String);

impl fmt::Display for UsageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

/// `relreward health`.
pub async fn health(ctx: &Ctx) -> Result<Report> {
    let status = ctx.connect().await?.health().await?;
    let name = status.as_str_name();
    Ok(Report {
        text: format!("{name}\n"),
        json: Some(json!({ "status": name })),
        success: status == ServingStatus::Serving,
    })
}
