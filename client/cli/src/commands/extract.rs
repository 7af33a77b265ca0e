//! `relreward extract`: from a user's recordings to served rewards and their report. The flags
//! become [`relreward_cli::ops::extract`]'s inputs: each file read (HDF5 and Minari recordings
//! written as the canonical `.npz` in `OUT/data`, terminal states optionally held at rest),
//! then its pipeline (sizes from the data, upload or reuse, diffusion models, rewards,
//! evaluation) and `report.md` / `report.json` in `OUT`, whose Markdown is printed (`--json`:
//! the JSON). Training jobs show as `train --watch` shows them; stages go to stderr.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use relreward_cli::ops::Progress;
use relreward_cli::ops::extract::files::{canonical, slug};
use relreward_cli::ops::extract::report::write_report;
use relreward_cli::ops::extract::sizes::Sizing;
use relreward_cli::ops::extract::{Inputs, pipeline};

pub use relreward_cli::ops::extract::sizes::Size;

use super::train::flags::AlgorithmArg;
use super::watch::JobView;
use super::{Ctx, Report, UsageError};

/// `relreward extract` flags.
#[derive(Debug, Clone, Args)]
pub struct ExtractArgs {
    /// The base (undirected, low-reward) recordings: .npz, D4RL HDF5, or a Minari dataset
    /// (main_data.hdf5 or its directory).
    #[arg(long, value_name = "FILE")]
    pub base: PathBuf,
    /// Expert recordings, in any of the same forms (repeatable: one reward each).
    #[arg(long = "expert", value_name = "FILE", required = true)]
    pub experts: Vec<PathBuf>,
    /// Directory for the converted data, pictures and report (created if missing).
    #[arg(long, default_value = "extract-out")]
    pub out: PathBuf,
    /// Prefix of the server-side names of this run's datasets and models.
    #[arg(long, default_value = "extract")]
    pub name: String,
    /// Steps, batches and networks: tiny, default or full (the paper's).
    #[arg(long, value_enum, default_value_t = Size::Default)]
    pub size: Size,
    /// TOML file whose [extract] table overrides any size (horizon, window, n_timesteps,
    /// diffusion_architecture, diffusion_steps, diffusion_batch, reward_steps, reward_batch,
    /// reward_lr, reward_hidden, num_chains, max_windows).
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Where the reward's training points come from [default: 1].
    #[arg(long, value_enum)]
    pub algorithm: Option<AlgorithmArg>,
    /// Also train the discriminator baseline (same network, base vs expert) and evaluate it.
    #[arg(long)]
    pub discriminator: bool,
    /// The true goal of each expert, as the position X,Y (repeat once per --expert, in order)
    /// [default: the expert file's `goals` when they are constant].
    #[arg(long = "goal", value_name = "X,Y")]
    pub goals: Vec<String>,
    /// Maze walls for the heatmap (.npz with walls / wall_map / maze_map, or .npy)
    /// [default: the base file's].
    #[arg(long, value_name = "FILE")]
    pub walls: Option<PathBuf>,
    /// Treat terminal states as absorbing: each episode ending with a `terminals` row gets N
    /// more rows holding its last observation (zero action). For goal-terminated
    /// demonstrations, whose goal state is otherwise recorded once (docs/results.md).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub absorbing: usize,
    /// Which observation columns the held (absorbing) rows set to zero, as an agent at rest:
    /// `auto` (the columns that predict another column's per-row change, i.e. velocities;
    /// docs/data-formats.md), `none`, or a list I,J,... (0-based). Only with --absorbing.
    #[arg(long, value_name = "auto|none|I,J,...", default_value = "auto")]
    pub velocity_columns: String,
    /// Seed of training and evaluation.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Passed on to every Algorithm 1 `train reward` (amortised targets; off unless given).
    #[command(flatten)]
    pub amortised: super::train::flags::AmortisedArgs,
}

pub async fn run(ctx: &Ctx, args: ExtractArgs) -> Result<Report> {
    let started = Instant::now();
    if !args.goals.is_empty() && args.goals.len() != args.experts.len() {
        bail!(UsageError(format!(
            "--goal: {} given for {} --expert files; give one per expert, in order, or none",
            args.goals.len(),
            args.experts.len()
        )));
    }
    let goals: Vec<Option<(f64, f64)>> = if args.goals.is_empty() {
        vec![None; args.experts.len()]
    } else {
        args.goals.iter().map(|g| parse_point(g).map(Some)).collect::<Result<_>>()?
    };
    let data_dir = args.out.join("data");
    std::fs::create_dir_all(&data_dir).with_context(|| format!("--out: cannot create {}", data_dir.display()))?;
    let progress = JobView::new(ctx.json, false);
    progress.stage("reading the datasets");
    let (base, _) = {
        let (p, d) = (args.base.clone(), data_dir.clone());
        tokio::task::spawn_blocking(move || canonical(&p, &d, "base", 0, None)).await?.context("--base")?
    };
    let mut experts = Vec::new();
    let mut labels = Vec::new();
    let absorbing = args.absorbing;
    let at_rest = parse_columns(&args.velocity_columns)?;
    for (k, path) in args.experts.iter().enumerate() {
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let label = format!("e{k}-{}", slug(&stem, 16));
        let (p, d, l) = (path.clone(), data_dir.clone(), label.clone());
        let r = at_rest.clone();
        let (npz, _) = tokio::task::spawn_blocking(move || canonical(&p, &d, &l, absorbing, r.as_deref()))
            .await?
            .with_context(|| format!("--expert {}", path.display()))?;
        experts.push(npz);
        labels.push(label);
    }
    let inputs = Inputs {
        base,
        experts,
        labels,
        goals,
        walls: args.walls.clone(),
        out: args.out.clone(),
        prefix: slug(&args.name, 24),
        algorithm: args.algorithm.unwrap_or(AlgorithmArg::WithDataset),
        discriminator: args.discriminator,
        seed: args.seed,
        amortised: args.amortised.clone(),
    };
    let client = ctx.connect().await?;
    let sizing = Sizing::Derive { size: args.size, config: args.config.clone() };
    let extracted = pipeline(&progress, &client, &inputs, sizing).await?;
    let report = write_report(&inputs, &extracted, started.elapsed().as_secs_f64(), None)?;
    Ok(Report::ok(report.markdown, report.json))
}

/// `--velocity-columns`: `None` for `auto` (the rule), else the explicit list (`none`: empty).
fn parse_columns(text: &str) -> Result<Option<Vec<usize>>> {
    match text.trim() {
        "auto" => Ok(None),
        "none" | "" => Ok(Some(Vec::new())),
        list => list
            .split(',')
            .map(|c| {
                c.trim().parse::<usize>().map_err(|_| {
                    UsageError(format!(
                        "--velocity-columns '{text}': expected auto, none or column numbers I,J,... (0-based)"
                    ))
                    .into()
                })
            })
            .collect::<Result<Vec<_>>>()
            .map(Some),
    }
}

fn parse_point(text: &str) -> Result<(f64, f64)> {
    let bad = || UsageError(format!("--goal '{text}': expected X,Y (two numbers)"));
    let (x, y) = text.split_once(',').ok_or_else(bad)?;
    let (x, y) = (x.trim().parse::<f64>().map_err(|_| bad())?, y.trim().parse::<f64>().map_err(|_| bad())?);
    if !(x.is_finite() && y.is_finite()) {
        return Err(bad().into());
    }
    Ok((x, y))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn velocity_columns_flag_parses_and_refuses_naming_itself() {
        assert_eq!(parse_columns("auto").expect("auto"), None);
        assert_eq!(parse_columns("none").expect("none"), Some(vec![]));
        assert_eq!(parse_columns("2, 3").expect("list"), Some(vec![2, 3]));
        let err = parse_columns("2,x").expect_err("bad");
        assert!(err.to_string().starts_with("--velocity-columns '2,x'"), "{err}");
    }
}
