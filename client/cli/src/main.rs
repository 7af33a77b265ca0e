//! `relreward`: the command-line client of a relreward server.
//!
//! Module map: this file holds the top-level flags, the dispatch and the exit status;
//! [`commands`] one thin module per command family, which parses flags and prints results.
//! What the commands do is the library's ([`relreward_cli`]: `ops`, the operations with typed
//! inputs and results; `train` and `manifest`, the spec and manifest files; `output`); the
//! connection is `relreward-client`; file formats, the maze generator and the evaluation's math
//! are `relreward-toolkit`.
//!
//! Commands (each family lives in `commands/`; `relreward COMMAND --help` lists every flag, from
//! the flags' own doc comments, so they are not repeated here):
//! - `health`: the server's serving status; exits 1 unless serving.
//! - `dataset upload|list|show|delete`: uploads `.npz`/`.npy`, D4RL HDF5 or Minari recordings
//!   (the reader by the file's signature; docs/data-formats.md) with a progress bar.
//! - `model upload|import|list|show|download|export|delete|recipe`: TorchScript (`.pt`) or
//!   native (`.safetensors`) diffusion models with a manifest (and bring-your-own rewards,
//!   autoencoders); `import` converts a Diffuser TemporalUnet state_dict (exported to `.npz`) or
//!   a diffusers folder into native weights, locally; `download` / `export` fetch a model's
//!   files (and its traced `module.pt`); `recipe` registers a conditional model's sampling recipe.
//! - `train diffusion|reward|discriminator`: submits a training job (flags override
//!   `--config`), `--watch` to follow it.
//! - `job list|show|cancel|watch|plot`: jobs, a live progress bar resuming across reconnects,
//!   and a job's loss curve (with reward histograms over datasets' windows).
//! - `score`, `grad`, `sample`: the RewardService over `.npz` inputs (trajectories cut into
//!   windows; per-window and per-step values), results as `.npz`.
//! - `relabel`: a trajectory file's rewards replaced by a reward model's (offline RL), the
//!   originals kept.
//! - `encode`, `decode`: an `.npz` of images to latents through an autoencoder model, and back.
//! - `eval discriminate|heatmap`: the paper's evaluation over scores of local files.
//! - `maze generate`: Maze2D datasets with D4RL's keys from the built-in generator (no server).
//! - `demo`: the paper's Maze2D pipeline (data, diffusion models, rewards, heatmaps,
//!   discriminability, steering); `extract`: recordings to rewards with their evaluation,
//!   `demo` being its maze-generating front end (both call `ops::extract::pipeline`).
//!
//! Global options: `--endpoint URL` (env `RELREWARD_ENDPOINT`, default
//! `http://127.0.0.1:50051`; `https://` for TLS; a bare `host:port` means `http://host:port`)
//! and `--json`, which prints one JSON document
//! on stdout per command (`job watch`: one JSON object per event per line). For servers with
//! access control and TLS: `--token TOKEN` (env `RELREWARD_TOKEN`), `--ca-cert FILE`
//! (`RELREWARD_CA_CERT`), `--client-cert FILE --client-key FILE` (`RELREWARD_CLIENT_CERT`,
//! `RELREWARD_CLIENT_KEY`; mutual TLS) and `--tls-server-name NAME`.
//!
//! Errors are printed to stderr as `error: MESSAGE` (gRPC errors as `CODE: message`), also with
//! `--json`. Exit status: 0 on success, 1 on failure, 2 on a usage error.

mod commands;

use std::io;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Result;
use clap::{Parser, Subcommand};
use relreward_client::ClientError;

use commands::output::{eprint_line, json_text, write_stdout};
use commands::{Ctx, Report, UsageError};

#[derive(Debug, Parser)]
#[command(name = "relreward", version, about = "Command-line client of the relreward service")]
struct Cli {
    /// Server address: http://HOST:PORT, https://HOST:PORT (TLS) or HOST:PORT (plain http)
    /// [default: http://127.0.0.1:50051].
    // No clap default_value: clap would then list `--endpoint` in every usage error.
    #[arg(long, global = true, env = "RELREWARD_ENDPOINT", value_name = "URL")]
    endpoint: Option<String>,
    /// Print one machine-readable JSON document on stdout instead of text.
    #[arg(long, global = true)]
    json: bool,
    #[command(flatten)]
    connect: commands::ConnectArgs,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Check that the server is serving (exit status 1 otherwise).
    Health,
    /// Upload, list, show and delete datasets.
    #[command(subcommand)]
    Dataset(commands::datasets::DatasetCommand),
    /// Upload, import, list, show and delete models.
    #[command(subcommand)]
    Model(commands::models::ModelCommand),
    /// Submit a training job.
    #[command(subcommand)]
    Train(commands::jobs::TrainCommand),
    /// List, show, cancel, watch and plot jobs.
    #[command(subcommand)]
    Job(commands::jobs::JobCommand),
    /// Score items with a reward model: rho per item (and per window, per step).
    Score(commands::score::ScoreArgs),
    /// Gradients of a reward model: grad_x rho(x_t, t) per item.
    Grad(commands::grad::GradArgs),
    /// Replace a trajectory file's rewards with a reward model's (offline RL), keeping the originals.
    Relabel(commands::relabel::RelabelArgs),
    /// Sample from a diffusion model, optionally guided by a reward model.
    Sample(commands::sample::SampleArgs),
    /// Encode an .npz of images into latents through an autoencoder model (one uploaded with
    /// `model upload --autoencoder`).
    Encode(commands::latents::LatentArgs),
    /// Decode an .npz of latents into images through an autoencoder model.
    Decode(commands::latents::LatentArgs),
    /// Evaluate a reward: discriminability of base vs expert, reward heatmaps and goal recovery.
    #[command(subcommand)]
    Eval(commands::eval::EvalCommand),
    /// Generate Maze2D datasets locally (D4RL layouts, point mass, waypoint controller).
    #[command(subcommand)]
    Maze(commands::maze::MazeCommand),
    /// The paper's Maze2D result end to end: data, models, rewards, heatmaps, summary.
    Demo(commands::demo::DemoArgs),
    /// From recordings to rewards: upload (or reuse) base and expert data (.npz, D4RL HDF5,
    /// Minari), train both diffusion models under one normalizer, extract the rewards,
    /// evaluate them, and write report.md / report.json with pictures.
    Extract(commands::extract::ExtractArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let json = cli.json;
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().build() {
        Ok(runtime) => runtime,
        Err(e) => {
            print_error(&anyhow::Error::new(e).context("cannot start the async runtime"));
            return ExitCode::FAILURE;
        }
    };
    let result = runtime.block_on(run(cli));
    runtime.shutdown_timeout(Duration::from_secs(1));
    match result {
        Ok(report) => {
            let out = match (json, &report.json) {
                (true, Some(value)) => json_text(value),
                (true, None) => String::new(),
                (false, _) => report.text,
            };
            match write_stdout(&out) {
                Ok(()) => {}
                // A closed pipe (`relreward dataset list | head -1`) is not an error.
                Err(e) if e.kind() == io::ErrorKind::BrokenPipe => {}
                Err(e) => {
                    print_error(&anyhow::Error::new(e).context("writing to stdout"));
                    return ExitCode::FAILURE;
                }
            }
            if report.success { ExitCode::SUCCESS } else { ExitCode::FAILURE }
        }
        Err(e) => {
            print_error(&e);
            if e.downcast_ref::<UsageError>().is_some() { ExitCode::from(2) } else { ExitCode::FAILURE }
        }
    }
}

async fn run(cli: Cli) -> Result<Report> {
    let ctx = Ctx {
        endpoint: commands::endpoint_url(cli.endpoint.as_deref().unwrap_or(commands::DEFAULT_ENDPOINT)),
        json: cli.json,
        connect: cli.connect,
    };
    match cli.command {
        Command::Health => commands::health(&ctx).await,
        Command::Dataset(command) => commands::datasets::run(&ctx, command).await,
        Command::Model(command) => commands::models::run(&ctx, command).await,
        Command::Train(command) => commands::jobs::run_train(&ctx, command).await,
        Command::Job(command) => commands::jobs::run(&ctx, command).await,
        Command::Score(args) => commands::score::score(&ctx, args).await,
        Command::Grad(args) => commands::grad::grad(&ctx, args).await,
        Command::Relabel(args) => commands::relabel::relabel(&ctx, args).await,
        Command::Sample(args) => commands::sample::sample(&ctx, args).await,
        Command::Encode(args) => commands::latents::encode(&ctx, args).await,
        Command::Decode(args) => commands::latents::decode(&ctx, args).await,
        Command::Eval(command) => commands::eval::run(&ctx, command).await,
        Command::Maze(command) => commands::maze::run(&ctx, command).await,
        Command::Demo(args) => commands::demo::run(&ctx, args).await,
        Command::Extract(args) => commands::extract::run(&ctx, args).await,
    }
}

fn print_error(err: &anyhow::Error) {
    eprint_line(&format!("error: {}", error_message(err)));
}

/// The error and its causes, `: `-separated, leaving out causes the message already contains.
/// A gRPC status is complete in itself (`CODE: message`): its transport causes are left out.
fn error_message(err: &anyhow::Error) -> String {
    let mut message = String::new();
    for cause in err.chain() {
        let text = cause.to_string();
        if message.is_empty() {
            message = text;
        } else if !text.is_empty() && !message.contains(&text) {
            message.push_str(": ");
            message.push_str(&text);
        }
        if matches!(cause.downcast_ref::<ClientError>(), Some(ClientError::Status(_))) {
            break;
        }
    }
    message
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    use super::*;

    #[test]
    fn cli_definition_is_valid() {
        Cli::command().debug_assert();
    }

    #[test]
    fn endpoints_without_a_scheme_are_plain_http() {
        assert_eq!(commands::endpoint_url("127.0.0.1:50051"), "http://127.0.0.1:50051");
        assert_eq!(commands::endpoint_url(" localhost:9 "), "http://localhost:9");
        assert_eq!(commands::endpoint_url("http://h:1"), "http://h:1");
        assert_eq!(commands::endpoint_url("https://h.example:443"), "https://h.example:443");
        let cli = Cli::try_parse_from(["relreward", "health", "--endpoint", "10.0.0.2:7"]).expect("parse");
        let endpoint = cli.endpoint.as_deref().map(commands::endpoint_url);
        assert_eq!(endpoint.as_deref(), Some("http://10.0.0.2:7"));
    }

    #[test]
    fn grpc_errors_read_code_colon_message() {
        let err = anyhow::Error::new(ClientError::Status(tonic::Status::not_found("dataset 'x' not found")));
        assert_eq!(error_message(&err), "NOT_FOUND: dataset 'x' not found");
        let err = anyhow::Error::new(ClientError::Status(tonic::Status::unimplemented("relreward.v1.ModelService")));
        assert_eq!(error_message(&err), "UNIMPLEMENTED: relreward.v1.ModelService");
        let io = ClientError::Io(io::Error::other("disk on fire"));
        assert_eq!(error_message(&anyhow::Error::new(io)), "reading upload data: disk on fire");
        let file = ClientError::File { path: "/m.pt".into(), source: io::Error::other("gone") };
        assert_eq!(error_message(&anyhow::Error::new(file)), "/m.pt: gone");
        let chained = anyhow::anyhow!("inner").context("outer");
        assert_eq!(error_message(&chained), "outer: inner");
    }

    #[test]
    fn usage_errors_are_reported_by_clap() {
        assert!(Cli::try_parse_from(["relreward", "dataset", "upload", "x.npz"]).is_err());
        assert!(
            Cli::try_parse_from(["relreward", "dataset", "upload", "x.npz", "--name", "a", "--kind", "images"])
                .is_err()
        );
        let cli = Cli::try_parse_from(["relreward", "--json", "dataset", "show", "a", "--endpoint", "http://h:1"])
            .expect("parse");
        assert!(cli.json);
        assert_eq!(cli.endpoint.as_deref(), Some("http://h:1"));
        assert!(Cli::try_parse_from(["relreward", "model", "upload", "m.pt", "--name", "m"]).is_err(), "--manifest");
        assert!(Cli::try_parse_from(["relreward", "model", "list", "--kind", "image"]).is_err());
        assert!(Cli::try_parse_from(["relreward", "job", "list", "--state", "done"]).is_err());
        assert!(Cli::try_parse_from(["relreward", "job", "watch", "j", "--from-seq", "-1"]).is_err());
        assert!(Cli::try_parse_from(["relreward", "train", "diffusion", "--lr", "fast"]).is_err());
        let refused = |args: &[&str]| {
            let parsed = Cli::try_parse_from(["relreward", "train"].iter().chain(args).copied());
            assert!(parsed.is_err(), "{args:?} parsed");
        };
        refused(&["reward", "--algorithm", "3"]);
        refused(&["reward", "--algorithm", "0"]);
        refused(&["reward", "--target", "median"]);
        refused(&["reward", "--eval-point", "xt"]);
        refused(&["reward", "--arch", "resnet"]);
        refused(&["reward", "--hidden", "128,x"]);
        refused(&["reward", "--hidden", "128,-1"]);
        refused(&["reward", "--num-chains", "many"]);
        refused(&["reward", "--rho-l2", "big"]);
        refused(&["reward", "--window", "-4"]);
        refused(&["discriminator", "--widths", "a"]);
        refused(&["discriminator", "--dataset", "d"]);
        refused(&["discriminator", "--arch", "transformer"]);
        let serve_refused = |args: &[&str], flag: &str| {
            let err = Cli::try_parse_from(std::iter::once("relreward").chain(args.iter().copied()))
                .expect_err(&format!("{args:?} parsed"))
                .to_string();
            assert!(err.contains(flag), "{args:?}: {err}");
        };
        serve_refused(&["score", "--input", "x.npz"], "--model");
        serve_refused(&["score", "--model", "r"], "--input");
        serve_refused(&["score", "--model", "r", "--input", "x", "--batch", "0"], "--batch");
        serve_refused(&["score", "--model", "r", "--input", "x", "--stride", "0"], "--stride");
        serve_refused(&["score", "--model", "r", "--input", "x", "--t", "-1"], "--t");
        serve_refused(&["score", "--model", "r", "--input", "x", "--units", "si"], "--units");
        serve_refused(&["grad", "--model", "r", "--input", "x"], "--t");
        serve_refused(&["grad", "--model", "r", "--input", "x", "--t", "1", "--omega", "big"], "--omega");
        serve_refused(
            &["grad", "--model", "r", "--input", "x", "--t", "1", "--gradient-units", "m"],
            "--gradient-units",
        );
        serve_refused(&["sample"], "--base");
        serve_refused(&["sample", "--base", "b", "--n", "0"], "--n");
        serve_refused(&["sample", "--base", "b", "--batch-size", "0"], "--batch-size");
        serve_refused(&["sample", "--base", "b", "--condition", "1"], "--condition");
        serve_refused(&["sample", "--base", "b", "--condition", "a=1"], "--condition");
        serve_refused(&["sample", "--base", "b", "--condition", "1=1,x"], "--condition");
        serve_refused(&["sample", "--base", "b", "--seed", "-3"], "--seed");
        serve_refused(&["sample", "--base", "b", "--n", "-3"], "--n");
        serve_refused(&["score", "--model", "r", "--input", "x", "--batch", "-3"], "--batch");
    }

    #[test]
    fn latent_commands_parse_with_their_defaults() {
        let parse = |args: &[&str]| Cli::try_parse_from(std::iter::once("relreward").chain(args.iter().copied()));
        let files = ["--model", "ae", "--input", "i.npz", "--out", "o.npz"];
        let Ok(Cli { command: Command::Encode(args), .. }) = parse(&[&["encode"][..], &files].concat()) else {
            panic!("encode")
        };
        assert_eq!((args.key.as_str(), args.out_key.as_str(), args.batch), ("x", "x", 64));
        let decode = parse(&[&["decode"][..], &files, &["--key", "z", "--out-key", "images"]].concat());
        let Ok(Cli { command: Command::Decode(args), .. }) = decode else { panic!("decode") };
        assert_eq!((args.key.as_str(), args.out_key.as_str()), ("z", "images"));
        assert!(parse(&[&["encode"][..], &files, &["--batch", "0"]].concat()).is_err());
        let upload = ["model", "upload", "m.pt", "--name", "m", "--manifest", "m.toml"];
        assert!(parse(&[&upload[..], &["--autoencoder"]].concat()).is_ok());
        assert!(parse(&[&upload[..], &["--autoencoder", "--reward"]].concat()).is_err(), "one kind per upload");
    }

    #[test]
    fn new_commands_parse() {
        let parse = |args: &[&str]| {
            Cli::try_parse_from(std::iter::once("relreward").chain(args.iter().copied()))
                .unwrap_or_else(|e| panic!("{args:?}: {e}"))
                .command
        };
        let Command::Model(commands::models::ModelCommand::Upload(_)) =
            parse(&["model", "upload", "m.pt", "--name", "m", "--manifest", "m.toml", "--description", "d"])
        else {
            panic!("model upload")
        };
        assert!(matches!(parse(&["model", "list", "--kind", "reward"]), Command::Model(_)));
        assert!(matches!(parse(&["model", "show", "m"]), Command::Model(_)));
        assert!(matches!(parse(&["model", "delete", "m"]), Command::Model(_)));
        let Command::Train(commands::jobs::TrainCommand::Diffusion(args)) = parse(&[
            "train",
            "diffusion",
            "--name",
            "m",
            "--dataset",
            "d",
            "--config",
            "t.toml",
            "--steps",
            "10",
            "--batch-size",
            "4",
            "--lr",
            "1e-3",
            "--horizon",
            "32",
            "--n-timesteps",
            "20",
            "--seed",
            "1",
            "--job-id",
            "j",
            "--watch",
        ]) else {
            panic!("train diffusion")
        };
        let job = &args.job;
        assert_eq!((job.steps, job.batch_size, job.lr, args.horizon), (Some(10), Some(4), Some(1e-3), Some(32)));
        assert_eq!(
            (args.n_timesteps, job.seed, job.job_id.as_deref(), job.watch),
            (Some(20), Some(1), Some("j"), true)
        );
        assert_eq!((job.name.as_deref(), args.dataset.as_deref()), (Some("m"), Some("d")));
        let Command::Train(commands::jobs::TrainCommand::Reward(args)) = parse(&[
            "train",
            "reward",
            "--name",
            "r",
            "--base",
            "b",
            "--expert",
            "e",
            "--dataset",
            "d1",
            "--dataset",
            "d2",
            "--algorithm",
            "2",
            "--num-chains",
            "512",
            "--target",
            "score",
            "--eval-point",
            "mu_base",
            "--arch",
            "windowed_mlp",
            "--window",
            "4",
            "--hidden",
            "128,64,32",
            "--widths",
            "8,16",
            "--rho-l2",
            "0.5",
            "--config",
            "r.toml",
            "--steps",
            "10",
            "--batch-size",
            "4",
            "--lr",
            "1e-3",
            "--seed",
            "1",
            "--job-id",
            "j",
            "--watch",
        ]) else {
            panic!("train reward")
        };
        use commands::train::config::{ArchKind, EvalPoint, Target};
        use commands::train::flags::AlgorithmArg;
        assert_eq!((args.base.as_deref(), args.expert.as_deref()), (Some("b"), Some("e")));
        assert_eq!(args.datasets, ["d1", "d2"]);
        assert_eq!((args.algorithm, args.num_chains), (Some(AlgorithmArg::ModelsOnly), Some(512)));
        assert_eq!((args.target, args.eval_point), (Some(Target::Score), Some(EvalPoint::MuBase)));
        assert_eq!((args.arch.arch, args.arch.window), (Some(ArchKind::WindowedMlp), Some(4)));
        assert_eq!((args.arch.hidden, args.arch.widths), (Some(vec![128, 64, 32]), Some(vec![8, 16])));
        assert_eq!(args.rho_l2, Some(0.5));
        let job = &args.job;
        assert_eq!((job.name.as_deref(), job.config.as_deref()), (Some("r"), Some(std::path::Path::new("r.toml"))));
        assert_eq!((job.steps, job.batch_size, job.lr, job.seed), (Some(10), Some(4), Some(1e-3), Some(1)));
        assert_eq!((job.job_id.as_deref(), job.watch), (Some("j"), true));
        let Command::Train(commands::jobs::TrainCommand::Reward(args)) =
            parse(&["train", "reward", "--algorithm", "1", "--eval-point", "x_t", "--target", "mean", "--arch", "mlp"])
        else {
            panic!("train reward")
        };
        assert_eq!((args.algorithm, args.eval_point), (Some(AlgorithmArg::WithDataset), Some(EvalPoint::XT)));
        assert_eq!((args.target, args.arch.arch), (Some(Target::Mean), Some(ArchKind::Mlp)));
        let Command::Train(commands::jobs::TrainCommand::Discriminator(args)) = parse(&[
            "train",
            "discriminator",
            "--name",
            "d",
            "--base-dataset",
            "a",
            "--expert-dataset",
            "b",
            "--diffusion-model",
            "m",
            "--arch",
            "conv_encoder",
            "--widths",
            "32,64",
            "--steps",
            "5",
            "--seed",
            "2",
            "--watch",
        ]) else {
            panic!("train discriminator")
        };
        assert_eq!(
            (args.base_dataset.as_deref(), args.expert_dataset.as_deref(), args.diffusion_model.as_deref()),
            (Some("a"), Some("b"), Some("m"))
        );
        assert_eq!((args.arch.arch, args.arch.widths), (Some(ArchKind::ConvEncoder), Some(vec![32, 64])));
        assert_eq!(
            (args.job.name.as_deref(), args.job.steps, args.job.seed, args.job.watch),
            (Some("d"), Some(5), Some(2), true)
        );
        let Command::Job(commands::jobs::JobCommand::Watch { id, from_seq }) =
            parse(&["job", "watch", "j", "--from-seq", "5"])
        else {
            panic!("job watch")
        };
        assert_eq!((id.as_str(), from_seq), ("j", 5));
        assert!(matches!(parse(&["job", "list", "--state", "running"]), Command::Job(_)));
        let Command::Score(args) = parse(&[
            "score",
            "--model",
            "r",
            "--input",
            "x.npz",
            "--key",
            "obs",
            "--t",
            "3",
            "--units",
            "normalized",
            "--per-window",
            "--per-step",
            "--batch",
            "64",
            "--out",
            "o.npz",
        ]) else {
            panic!("score")
        };
        assert_eq!((args.input.model.as_str(), args.input.key.as_deref(), args.t), ("r", Some("obs"), 3));
        assert_eq!((args.input.units, args.input.batch), (commands::rewards::UnitsArg::Normalized, 64));
        assert!(args.per_window && args.per_step && args.input.out.is_some());
        let Command::Score(args) = parse(&["score", "--model", "r", "--input", "t.npz", "--stride", "4"]) else {
            panic!("score")
        };
        assert_eq!((args.t, args.input.stride, args.input.batch), (0, Some(4), 256));
        assert_eq!(args.input.units, commands::rewards::UnitsArg::Raw);
        let Command::Grad(args) = parse(&[
            "grad",
            "--model",
            "r",
            "--input",
            "x.npz",
            "--t",
            "5",
            "--gradient-units",
            "normalized",
            "--omega",
            "-0.5",
            "--scale-by-posterior-variance-of",
            "b",
        ]) else {
            panic!("grad")
        };
        assert_eq!((args.t, args.omega, args.scale_by_posterior_variance_of.as_deref()), (5, Some(-0.5), Some("b")));
        assert_eq!(args.gradient_units, commands::rewards::UnitsArg::Normalized);
        let Command::Sample(args) = parse(&[
            "sample",
            "--base",
            "b",
            "--reward",
            "r",
            "--scale",
            "0.1",
            "--t-stopgrad",
            "2",
            "--n-guide-steps",
            "3",
            "--scale-grad-by-std",
            "--condition",
            "0=1,-2.5",
            "--condition",
            "7=-1,0",
            "--n",
            "4",
            "--seed",
            "9",
            "--batch-size",
            "2",
            "--out",
            "s.npz",
        ]) else {
            panic!("sample")
        };
        assert_eq!((args.base.as_str(), args.reward.as_deref(), args.scale), ("b", Some("r"), Some(0.1)));
        assert_eq!((args.t_stopgrad, args.n_guide_steps, args.scale_grad_by_std), (Some(2), Some(3), true));
        assert_eq!((args.n, args.seed, args.batch_size), (4, Some(9), Some(2)));
        assert_eq!(args.conditions.len(), 2);
        assert_eq!((args.conditions[1].index, args.conditions[1].state.clone()), (7, vec![-1.0, 0.0]));
        let Command::Sample(args) = parse(&["sample", "--base", "b"]) else { panic!("sample") };
        assert_eq!((args.n, args.seed, args.reward.is_none()), (1, None, true));
        assert!(matches!(parse(&["job", "show", "j"]), Command::Job(_)));
        assert!(matches!(parse(&["job", "cancel", "j"]), Command::Job(_)));
    }
}
