//! The commands of the `relreward` binary, one family per module. The top-level `Cli`, the
//! dispatch and the exit status are in `main.rs`.
//!
//! - [`datasets`]: `dataset upload|list|show|delete`;
//! - [`models`]: `model upload|list|show|delete`, with [`manifest`] (the manifest file format);
//! - [`jobs`]: `train diffusion|reward|discriminator` (specs built by [`train`]) and
//!   `job list|show|cancel|watch`;
//! - [`serve`]: `score`, `grad` and `sample` (the RewardService: inputs from `.npz` files,
//!   trajectories cut into windows, results written as `.npz`);
//! - [`demo`]: `demo` (the whole Maze2D pipeline, composed of the commands below);
//! - [`eval`]: `eval discriminate|heatmap` and `job plot` (the paper's evaluation and its
//!   pictures, over scores of local trajectory files);
//! - [`maze`]: `maze generate` (Maze2D datasets from the built-in generator, no server);
//! - [`output`]: JSON and text formatting, progress bars, terminal I/O.

pub mod datasets;
pub mod demo;
pub mod eval;
pub mod jobs;
pub mod manifest;
pub mod maze;
pub mod models;
pub mod output;
pub mod serve;
pub mod train;

use std::fmt;
use std::time::Duration;

use anyhow::{Result, bail};
use relreward_client::Client;
use serde_json::{Value, json};
use tonic_health::pb::health_check_response::ServingStatus;

pub const DEFAULT_ENDPOINT: &str = "http://127.0.0.1:50051";
/// How long to wait for the server to accept the connection.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(15);

/// What every command gets from the global options.
#[derive(Debug, Clone)]
pub struct Ctx {
    pub endpoint: String,
    /// `--json`: machine-readable output on stdout, no progress bars.
    pub json: bool,
}

impl Ctx {
    pub async fn connect(&self) -> Result<Client> {
        let endpoint = self.endpoint.as_str();
        match tokio::time::timeout(CONNECT_TIMEOUT, Client::connect(endpoint)).await {
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
