//! The commands of the `relreward` binary, one family per module, each parsing its flags into
//! the inputs of an operation of the library ([`relreward_cli::ops`]) and printing its typed
//! result as text or JSON. No command runs another command: those that compose others
//! (`extract`, `demo`) call the operations. The top-level `Cli`, the dispatch and the exit
//! status are in `main.rs`; this file holds what every command gets ([`Ctx`], [`Report`]).
//!
//! - [`datasets`]: `dataset upload|list|show|delete`;
//! - [`models`]: `model upload|import|list|show|download|export|delete|recipe` (the manifest
//!   file: [`manifest`]);
//! - [`jobs`]: `train diffusion|reward|discriminator` (specs from [`train`]) and
//!   `job list|show|cancel|watch`;
//! - [`watch`]: how a job being waited for is shown ([`watch::JobView`]), by `job watch` and by
//!   the commands that train (`extract`, `demo`);
//! - [`score`], [`grad`], [`sample`]: the RewardService over `.npz` files, with what they share
//!   in [`rewards`] (input flags, the request loop, the `--out` archive);
//! - [`relabel`]: `relabel` (a trajectory file's rewards replaced by a reward model's, the
//!   originals kept);
//! - [`latents`]: `encode` and `decode` (an `.npz` of images to latents through an
//!   autoencoder model, and back);
//! - [`eval`]: `eval discriminate|heatmap` and `job plot`;
//! - [`extract`]: `extract` (recordings to rewards and their report);
//! - [`demo`]: `demo` (generated Maze2D data, then `extract`'s pipeline, and steering);
//! - [`maze`]: `maze generate` (Maze2D datasets from the built-in generator, no server).
//!
//! [`manifest`], [`output`], [`train`] and [`UsageError`] are the library's, re-exported here
//! for the commands.

pub mod datasets;
pub mod demo;
pub mod eval;
pub mod extract;
pub mod grad;
pub mod jobs;
pub mod latents;
pub mod maze;
pub mod models;
pub mod relabel;
pub mod rewards;
pub mod sample;
pub mod score;
pub mod watch;

pub use relreward_cli::{UsageError, manifest, output, train};

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context as _, Result, bail};
use relreward_cli::ops::Progress;
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

/// The commands' own progress: stages on stderr, bars unless `--json`.
impl Progress for Ctx {
    fn quiet(&self) -> bool {
        self.json
    }

    fn stage(&self, text: &str) {
        if !self.json {
            output::eprint_line(&format!("==> {text}"));
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
