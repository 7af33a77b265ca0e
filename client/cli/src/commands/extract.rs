//! `relreward extract`: from a user's recordings to served rewards and their report.
//!
//! One base dataset and one or more expert datasets (`.npz`, D4RL HDF5, Minari), then, against
//! a running server and with the same code as the commands a user would type:
//! 1. read each file ([`relreward_toolkit::hdf5`] files become the canonical `.npz` in
//!    `OUT/data`), profile it and derive the sizes ([`relreward_toolkit::profile`]: the horizon
//!    from how far the agent moves per row, capped by the episode lengths), `--config` on top;
//! 2. upload each dataset, or reuse it: names carry a fingerprint of the file's bytes, so a
//!    second run finds its datasets (and, names carrying a fingerprint of the sizes too, its
//!    models and rewards) and continues where the first stopped;
//! 3. train a base and one expert diffusion model per expert dataset under one normalizer
//!    (computed over every dataset of the run);
//! 4. extract a reward per expert (Algorithm 1 by default, `--algorithm 2`), and with
//!    `--discriminator` the discriminator baseline of the same network;
//! 5. evaluate: discriminability (held-out balanced accuracy) with both classes' reward
//!    histograms, the loss curve, and when the maze's walls are known (in the base file, or
//!    `--walls`) the reward heatmap with goal recovery for goals given by `--goal` or by a
//!    constant `goals` array in the expert file, twice: over base sub-trajectories (the
//!    paper's) and at rest (`eval heatmap --probe at-rest`: the reward of staying at each
//!    position; docs/results.md, issue 19);
//! 6. write `report.md` and `report.json` beside the pictures in `OUT`.
//!
//! `relreward demo` is the maze-generating front end of [`pipeline`]: it writes its datasets
//! and calls the same function, then adds its steering measurement.

use std::collections::hash_map::DefaultHasher;
use std::hash::{Hash, Hasher};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, FromArgMatches, Subcommand, ValueEnum};
use relreward_client::pb;
use relreward_toolkit::profile::{self, DataProfile};
use relreward_toolkit::trajectories::Trajectories;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::datasets::DatasetCommand;
use super::eval::EvalCommand;
use super::jobs::{JobCommand, TrainCommand};
use super::train::flags::AlgorithmArg;
use super::{Ctx, Report, UsageError};

/// How big a run is: the steps, batches and networks; the horizon comes from the data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Size {
    /// Seconds: checks that every step runs (tests); numbers are meaningless.
    Tiny,
    /// Minutes on a 2-core CPU: MLP denoisers, a few thousand steps.
    Default,
    /// The paper's sizes (TemporalUnet, horizon 256, T = 100, 100k reward steps): hours, for a
    /// GPU machine.
    Full,
}

/// Every size of a run. [`Sizes::preset`] fills them, the data sets `horizon` and `window`,
/// `--config`'s `[extract]` table overrides any of them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Sizes {
    pub horizon: u32,
    /// Transitions per window of the windowed-MLP reward (divides `horizon`).
    pub window: u32,
    pub n_timesteps: u32,
    /// `[diffusion] architecture` of the diffusion models, as a TOML value.
    pub diffusion_architecture: toml::Value,
    pub diffusion_steps: u64,
    pub diffusion_batch: u64,
    pub reward_steps: u64,
    pub reward_batch: u64,
    pub reward_lr: f64,
    pub reward_hidden: Vec<u32>,
    /// Algorithm 2's chains.
    pub num_chains: u32,
    /// Windows scored per class by the evaluation at most.
    pub max_windows: u64,
}

/// `--config`'s `[extract]` table: any field of [`Sizes`].
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct SizeOverrides {
    horizon: Option<u32>,
    window: Option<u32>,
    n_timesteps: Option<u32>,
    diffusion_architecture: Option<toml::Value>,
    diffusion_steps: Option<u64>,
    diffusion_batch: Option<u64>,
    reward_steps: Option<u64>,
    reward_batch: Option<u64>,
    reward_lr: Option<f64>,
    reward_hidden: Option<Vec<u32>>,
    num_chains: Option<u32>,
    max_windows: Option<u64>,
}

fn arch(kind: &str, pairs: &[(&str, Vec<i64>)], dim: Option<i64>) -> toml::Value {
    let mut t = toml::Table::new();
    t.insert("kind".into(), toml::Value::String(kind.into()));
    for (k, v) in pairs {
        t.insert((*k).into(), toml::Value::Array(v.iter().map(|&x| toml::Value::Integer(x)).collect()));
    }
    if let Some(d) = dim {
        t.insert("dim".into(), toml::Value::Integer(d));
    }
    toml::Value::Table(t)
}

impl Sizes {
    /// The steps, batches and networks of a size, with a horizon and window to be replaced
    /// by the data's.
    pub fn preset(size: Size) -> Self {
        match size {
            Size::Tiny => Self {
                horizon: 16,
                window: 4,
                n_timesteps: 10,
                diffusion_architecture: arch("mlp", &[("hidden", vec![64, 64])], None),
                diffusion_steps: 200,
                diffusion_batch: 32,
                reward_steps: 200,
                reward_batch: 32,
                reward_lr: 1e-3,
                reward_hidden: vec![32, 32],
                num_chains: 64,
                max_windows: 2_000,
            },
            Size::Default => Self {
                horizon: 16,
                window: 4,
                n_timesteps: 20,
                diffusion_architecture: arch("mlp", &[("hidden", vec![256, 256, 256])], None),
                diffusion_steps: 4_000,
                diffusion_batch: 64,
                reward_steps: 3_000,
                reward_batch: 64,
                reward_lr: 1e-3,
                reward_hidden: vec![128, 64, 32],
                num_chains: 512,
                max_windows: 50_000,
            },
            Size::Full => Self {
                horizon: 256,
                window: 4,
                n_timesteps: 100,
                diffusion_architecture: arch("temporal_unet", &[("dim_mults", vec![1, 4, 8])], Some(32)),
                diffusion_steps: 200_000,
                diffusion_batch: 32,
                reward_steps: 100_000,
                reward_batch: 256,
                reward_lr: 5e-5,
                reward_hidden: vec![128, 64, 32],
                num_chains: 1024,
                max_windows: 200_000,
            },
        }
    }

    /// Reads `--config`'s `[extract]` table over these sizes.
    pub fn apply_config(&mut self, path: &Path) -> Result<()> {
        let text = std::fs::read_to_string(path).with_context(|| format!("--config {}", path.display()))?;
        let mut doc: toml::Table = toml::from_str(&text).with_context(|| format!("--config {}", path.display()))?;
        if let Some(other) = doc.keys().find(|k| *k != "extract") {
            bail!(UsageError(format!("--config {}: unknown table '{other}' (sizes go in [extract])", path.display())));
        }
        let table = doc.remove("extract").unwrap_or(toml::Value::Table(toml::Table::new()));
        let o: SizeOverrides =
            table.try_into().map_err(|e| UsageError(format!("--config {}: [extract]: {e}", path.display())))?;
        macro_rules! set {
            ($($f:ident),*) => { $( if let Some(v) = o.$f { self.$f = v; } )* };
        }
        set!(horizon, window, n_timesteps, diffusion_architecture, diffusion_steps, diffusion_batch);
        set!(reward_steps, reward_batch, reward_lr, reward_hidden, num_chains, max_windows);
        self.check().map_err(|m| UsageError(format!("--config {}: [extract]: {m}", path.display())).into())
    }

    fn check(&self) -> Result<(), String> {
        if self.horizon == 0 || self.window == 0 || !self.horizon.is_multiple_of(self.window) {
            return Err(format!("window = {} must divide horizon = {}", self.window, self.horizon));
        }
        if self.n_timesteps < 2 || self.diffusion_steps == 0 || self.reward_steps == 0 {
            return Err("n_timesteps must be >= 2 and the step counts >= 1".into());
        }
        Ok(())
    }

    /// A short fingerprint of every size (part of the rewards' names).
    fn fingerprint(&self) -> String {
        short_hash(&serde_json::to_string(self).unwrap_or_default())
    }

    /// A short fingerprint of the sizes that shape the diffusion models only (part of their
    /// names), so a run that changes only the reward's sizes reuses the diffusion models.
    fn diffusion_fingerprint(&self) -> String {
        let shaping = serde_json::json!([
            self.horizon,
            self.n_timesteps,
            self.diffusion_architecture,
            self.diffusion_steps,
            self.diffusion_batch
        ]);
        short_hash(&shaping.to_string())
    }
}

fn short_hash(text: &str) -> String {
    let mut h = DefaultHasher::new();
    text.hash(&mut h);
    format!("{:08x}", h.finish() as u32)
}

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

/// What [`pipeline`] runs on: canonical `.npz` files and their labels.
#[derive(Debug, Clone)]
pub struct Inputs {
    pub base: PathBuf,
    pub experts: Vec<PathBuf>,
    /// One label per expert (names, pictures).
    pub labels: Vec<String>,
    /// One goal position per expert, when known.
    pub goals: Vec<Option<(f64, f64)>>,
    pub walls: Option<PathBuf>,
    pub out: PathBuf,
    pub prefix: String,
    pub algorithm: AlgorithmArg,
    pub discriminator: bool,
    pub seed: u64,
    /// Amortised-target flags for Algorithm 1's reward jobs (empty: per-step targets).
    pub amortised: Vec<String>,
}

/// What [`pipeline`] made: server names and one evaluation row per expert.
#[derive(Debug, Clone)]
pub struct Extracted {
    pub base_model: String,
    pub expert_models: Vec<String>,
    pub rewards: Vec<String>,
    pub rows: Vec<Value>,
    pub profiles: Vec<DataProfile>,
}

/// Parses `args` as one of the CLI's subcommand families (the same parser as the command line).
pub fn parse<T: Subcommand + FromArgMatches>(args: &[String]) -> Result<T> {
    let command = T::augment_subcommands(clap::Command::new("relreward").no_binary_name(true));
    let matches = command.try_get_matches_from(args).map_err(|e| anyhow::anyhow!("step {args:?}: {e}"))?;
    Ok(T::from_arg_matches(&matches)?)
}

pub fn strings(args: &[&str]) -> Vec<String> {
    args.iter().map(|s| (*s).to_owned()).collect()
}

pub fn path_str(p: &Path) -> String {
    p.to_string_lossy().into_owned()
}

/// Prints a stage line on stderr (not with `--json`).
pub fn stage(ctx: &Ctx, text: &str) {
    if !ctx.json {
        eprintln!("==> {text}");
    }
}

/// A name part made of the allowed characters (`[a-z0-9._-]`), at most `max` long.
fn slug(text: &str, max: usize) -> String {
    let s: String = text
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '-' })
        .collect::<String>()
        .trim_matches('-')
        .chars()
        .take(max)
        .collect::<String>()
        .trim_end_matches('-')
        .to_owned();
    if s.is_empty() { "data".into() } else { s }
}

/// A fingerprint of a file's bytes (for names, not security).
fn file_fingerprint(path: &Path) -> Result<String> {
    let mut f = std::fs::File::open(path).with_context(|| format!("{}", path.display()))?;
    let mut h = DefaultHasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        buf[..n].hash(&mut h);
    }
    Ok(format!("{:08x}", h.finish() as u32))
}

/// Reads any supported file; HDF5 and Minari inputs are written as `.npz` into `data_dir`.
/// Returns the `.npz` to use and the data.
/// With `absorbing > 0`, terminal states are padded ([`Trajectories::absorb_terminals`], the
/// `at_rest` columns zeroed, found by [`Trajectories::velocity_columns`] when `None`) and the
/// result written there too.
fn canonical(
    path: &Path,
    data_dir: &Path,
    label: &str,
    absorbing: usize,
    at_rest: Option<&[usize]>,
) -> Result<(PathBuf, Trajectories)> {
    let hdf5 = relreward_toolkit::hdf5::is_hdf5(path);
    let mut t = if hdf5 { relreward_toolkit::hdf5::read_hdf5(path)? } else { Trajectories::from_npz(path)? };
    for note in &t.notes {
        eprintln!("{label}: {note}");
    }
    let padded = absorbing > 0 && t.terminals.iter().any(|&b| b);
    if padded {
        let columns = match at_rest {
            Some(c) => {
                if let Some(&bad) = c.iter().find(|&&j| j >= t.obs_dim) {
                    bail!(UsageError(format!(
                        "--velocity-columns: column {bad} is out of range; observations have {} columns",
                        t.obs_dim
                    )));
                }
                c.to_vec()
            }
            None => t.velocity_columns(),
        };
        eprintln!("{label}: terminal states held {absorbing} rows at rest in observation columns {columns:?}");
        t.absorb_terminals(absorbing, &columns);
    }
    if hdf5 || padded {
        let dest = data_dir.join(format!("{label}.npz"));
        t.write_npz(&dest).with_context(|| format!("writing {}", dest.display()))?;
        Ok((dest, t))
    } else {
        Ok((path.to_owned(), t))
    }
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
    stage(ctx, "reading the datasets");
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
        amortised: args.amortised.to_argv(),
    };
    let extracted = pipeline(ctx, &inputs, Sizing::Derive { size: args.size, config: args.config.clone() }).await?;
    let report = write_report(&inputs, &extracted, started.elapsed().as_secs_f64(), json!({}))?;
    Ok(report)
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

/// Where a run's sizes come from.
#[derive(Debug, Clone)]
pub enum Sizing {
    /// A preset's steps and networks, the horizon and window from the data, then `--config`.
    Derive { size: Size, config: Option<PathBuf> },
    /// Exactly these (the demo's plans).
    Fixed(Sizes),
}

/// Steps 2 to 5 of the module docs over canonical `.npz` inputs.
pub async fn pipeline(ctx: &Ctx, inputs: &Inputs, sizing: Sizing) -> Result<Extracted> {
    let client = ctx.connect().await?;
    client.health().await.context("the server is not answering health checks")?;
    let quiet = Ctx { json: true, ..ctx.clone() };
    let out = &inputs.out;

    // ---- sizes from the data
    let mut profiles = Vec::new();
    for path in std::iter::once(&inputs.base).chain(&inputs.experts) {
        let p = path.clone();
        let profile = tokio::task::spawn_blocking(move || -> Result<DataProfile> {
            let t = Trajectories::from_npz(&p)?;
            Ok(profile::profile(&t.observations, t.obs_dim, &t.episodes()))
        })
        .await??;
        profiles.push(profile);
    }
    let sizes = match sizing {
        Sizing::Fixed(s) => s,
        Sizing::Derive { size, config } => {
            let mut s = Sizes::preset(size);
            if size != Size::Full {
                let (h, w) = profile::derive_window(&profiles);
                (s.horizon, s.window) = (h as u32, w as u32);
            }
            if let Some(path) = &config {
                s.apply_config(path)?;
            }
            s.check().map_err(UsageError)?;
            s
        }
    };
    stage(
        ctx,
        &format!(
            "sizes: horizon {} (reward window {}), T = {}, {} diffusion steps, {} reward steps; mean motion per row {:.4}",
            sizes.horizon,
            sizes.window,
            sizes.n_timesteps,
            sizes.diffusion_steps,
            sizes.reward_steps,
            profiles.iter().map(|p| p.displacement_per_row).sum::<f64>() / profiles.len().max(1) as f64
        ),
    );

    // ---- upload or reuse
    let prefix = &inputs.prefix;
    let mut datasets = Vec::new();
    for (path, label) in
        std::iter::once((&inputs.base, &"base".to_owned())).chain(inputs.experts.iter().zip(&inputs.labels))
    {
        let p = path.clone();
        let fp = tokio::task::spawn_blocking(move || file_fingerprint(&p)).await??;
        let name = format!("{prefix}-{label}-{fp}");
        if client.get_dataset(&name).await.is_ok() {
            stage(ctx, &format!("reusing dataset {name}"));
        } else {
            stage(ctx, &format!("uploading {} as {name}", path.display()));
            let command: DatasetCommand = parse(&strings(&["upload", &path_str(path), "--name", &name]))?;
            super::datasets::run(&quiet, command).await.with_context(|| format!("uploading {}", path.display()))?;
        }
        datasets.push(name);
    }
    let (base_ds, expert_ds) = (&datasets[0], &datasets[1..]);

    // ---- diffusion models: one base, one per expert, one normalizer over every dataset.
    let fp = sizes.diffusion_fingerprint();
    let mut diffusion = toml::Table::new();
    let mut table = toml::Table::new();
    table.insert("horizon".into(), toml::Value::Integer(i64::from(sizes.horizon)));
    table.insert("n_timesteps".into(), toml::Value::Integer(i64::from(sizes.n_timesteps)));
    table.insert("architecture".into(), sizes.diffusion_architecture.clone());
    diffusion.insert("diffusion".into(), toml::Value::Table(table));
    let config_path = out.join("diffusion.toml");
    std::fs::write(&config_path, toml::to_string(&diffusion)?)?;
    let mut normalizer_flags = Vec::new();
    for ds in &datasets {
        normalizer_flags.extend(["--normalizer-dataset".to_owned(), ds.clone()]);
    }
    // Model names: the dataset's (with its content fingerprint) and the sizes' fingerprint.
    let model_name = |ds: &str| format!("{}-m{fp}", ds.chars().take(64 - 10).collect::<String>());
    let base_model = model_name(base_ds);
    let expert_models: Vec<String> = expert_ds.iter().map(|d| model_name(d)).collect();
    let jobs: Vec<(&String, &String)> =
        std::iter::once((&base_model, base_ds)).chain(expert_models.iter().zip(expert_ds)).collect();
    for (i, (model, ds)) in jobs.iter().enumerate() {
        if client.get_model(model).await.is_ok() {
            stage(ctx, &format!("reusing diffusion model {model}"));
            continue;
        }
        stage(
            ctx,
            &format!("training diffusion model {} of {}: {model} ({} steps)", i + 1, jobs.len(), sizes.diffusion_steps),
        );
        let mut argv = strings(&[
            "diffusion",
            "--name",
            model,
            "--dataset",
            ds,
            "--config",
            &path_str(&config_path),
            "--steps",
            &sizes.diffusion_steps.to_string(),
            "--batch-size",
            &sizes.diffusion_batch.to_string(),
            "--seed",
            &(inputs.seed + i as u64).to_string(),
            "--job-id",
            model,
            "--watch",
        ]);
        argv.extend(normalizer_flags.iter().cloned());
        train(ctx, &argv).await?;
    }

    // ---- rewards (and discriminators)
    let algorithm = match inputs.algorithm {
        AlgorithmArg::WithDataset => "1",
        AlgorithmArg::ModelsOnly => "2",
    };
    let hidden = sizes.reward_hidden.iter().map(u32::to_string).collect::<Vec<_>>().join(",");
    let net = |argv: &mut Vec<String>| {
        argv.extend(strings(&[
            "--arch",
            "windowed_mlp",
            "--window",
            &sizes.window.to_string(),
            "--hidden",
            &hidden,
            "--steps",
            &sizes.reward_steps.to_string(),
            "--batch-size",
            &sizes.reward_batch.to_string(),
            "--lr",
            &sizes.reward_lr.to_string(),
        ]));
    };
    // Rewards and discriminators: named by every size, the reward's own included.
    let fp = sizes.fingerprint();
    let mut rewards = Vec::new();
    let mut discriminators = Vec::new();
    for (k, label) in inputs.labels.iter().enumerate() {
        // Amortised targets are a different recipe: a name of their own, so a rerun without
        // them never reuses an amortised reward (and the reverse).
        let recipe =
            if inputs.amortised.is_empty() || inputs.algorithm != AlgorithmArg::WithDataset { "" } else { "a" };
        let reward = format!("{prefix}-r{algorithm}{recipe}-{label}-{fp}");
        let reward = reward.chars().take(64).collect::<String>();
        if client.get_model(&reward).await.is_ok() {
            stage(ctx, &format!("reusing reward {reward}"));
        } else {
            stage(
                ctx,
                &format!(
                    "extracting reward {} of {} (Algorithm {algorithm}): {reward} ({} steps)",
                    k + 1,
                    inputs.labels.len(),
                    sizes.reward_steps
                ),
            );
            let mut argv =
                strings(&["reward", "--name", &reward, "--base", &base_model, "--expert", &expert_models[k]]);
            if inputs.algorithm == AlgorithmArg::WithDataset {
                argv.extend(strings(&["--dataset", base_ds, "--dataset", &expert_ds[k]]));
                argv.extend(inputs.amortised.iter().cloned());
            } else {
                argv.extend(strings(&["--algorithm", "2", "--num-chains", &sizes.num_chains.to_string()]));
            }
            net(&mut argv);
            argv.extend(strings(&[
                "--seed",
                &(inputs.seed + 100 + k as u64).to_string(),
                "--job-id",
                &reward,
                "--watch",
            ]));
            train(ctx, &argv).await?;
        }
        rewards.push(reward);
        if inputs.discriminator {
            let disc = format!("{prefix}-d-{label}-{fp}").chars().take(64).collect::<String>();
            if client.get_model(&disc).await.is_ok() {
                stage(ctx, &format!("reusing discriminator {disc}"));
            } else {
                stage(ctx, &format!("training discriminator {} of {}: {disc}", k + 1, inputs.labels.len()));
                let mut argv = strings(&[
                    "discriminator",
                    "--name",
                    &disc,
                    "--base-dataset",
                    base_ds,
                    "--expert-dataset",
                    &expert_ds[k],
                    "--diffusion-model",
                    &base_model,
                ]);
                net(&mut argv);
                argv.extend(strings(&[
                    "--seed",
                    &(inputs.seed + 200 + k as u64).to_string(),
                    "--job-id",
                    &disc,
                    "--watch",
                ]));
                train(ctx, &argv).await?;
            }
            discriminators.push(disc);
        }
    }

    // ---- evaluation
    let walls_file = match &inputs.walls {
        Some(w) => Some(w.clone()),
        None => relreward_toolkit::npz::walls_from_npz(&inputs.base)
            .with_context(|| format!("{}: maze walls", inputs.base.display()))?
            .map(|_| inputs.base.clone()),
    };
    let mut rows = Vec::new();
    for (k, label) in inputs.labels.iter().enumerate() {
        stage(ctx, &format!("evaluating reward {} of {} ({label})", k + 1, inputs.labels.len()));
        let mut row = evaluate(&quiet, inputs, &sizes, k, &rewards[k], walls_file.as_deref(), "reward").await?;
        if let Some(disc) = discriminators.get(k) {
            let d = evaluate(&quiet, inputs, &sizes, k, disc, None, "discriminator").await?;
            row["discriminator"] = d;
        }
        row["label"] = json!(label);
        row["expert_data"] = json!(path_str(&inputs.experts[k]));
        rows.push(row);
    }
    Ok(Extracted { base_model, expert_models, rewards, rows, profiles }).map(|mut e| {
        e.rows.iter_mut().for_each(|r| r["sizes"] = serde_json::to_value(&sizes).unwrap_or(Value::Null));
        e
    })
}

/// Discriminability with histograms, the loss curve and (with walls) the heatmap of one model.
async fn evaluate(
    quiet: &Ctx,
    inputs: &Inputs,
    sizes: &Sizes,
    k: usize,
    model: &str,
    walls: Option<&Path>,
    what: &str,
) -> Result<Value> {
    let out = &inputs.out;
    let seed = inputs.seed.to_string();
    let hist_png = out.join(format!("hist-{model}.png"));
    let disc = eval(
        quiet,
        &[
            "discriminate",
            "--model",
            model,
            "--base-data",
            &path_str(&inputs.base),
            "--expert-data",
            &path_str(&inputs.experts[k]),
            "--max-windows",
            &sizes.max_windows.min(20_000).to_string(),
            "--seed",
            &seed,
            "--hist-out",
            &path_str(&hist_png),
        ],
    )
    .await?;
    let loss_png = out.join(format!("loss-{model}.png"));
    let command: JobCommand = parse(&strings(&["plot", model, "--out", &path_str(&loss_png)]))?;
    super::jobs::run(quiet, command).await.with_context(|| format!("plotting the loss of {model}"))?;
    let mut row = json!({
        "kind": what,
        "model": model,
        "balanced_accuracy": disc["balanced_accuracy"],
        "auc": disc["test"]["auc"],
        "expert_scores_higher": disc["expert_scores_higher"],
        "histogram": path_str(&hist_png),
        "loss_plot": path_str(&loss_png),
    });
    if let Some(walls) = walls {
        let heat_png = out.join(format!("heatmap-{model}.png"));
        let mut argv = strings(&[
            "heatmap",
            "--model",
            model,
            "--dataset",
            &path_str(&inputs.base),
            "--out",
            &path_str(&heat_png),
            "--walls",
            &path_str(walls),
            "--max-windows",
            &sizes.max_windows.to_string(),
            "--seed",
            &seed,
        ]);
        match inputs.goals[k] {
            Some((x, y)) => argv.extend(["--goal".to_owned(), format!("{x},{y}")]),
            None => argv.extend(["--goal-from".to_owned(), path_str(&inputs.experts[k])]),
        }
        let command: EvalCommand = parse(&argv)?;
        let heat = super::eval::run(quiet, command).await?.json.context("heatmap returned no JSON")?;
        row["heatmap"] = json!(path_str(&heat_png));
        row["argmax_cell"] = heat["argmax"]["cell"].clone();
        row["distance_cells"] = heat["distance_cells"].clone();
        row["goal_recovered"] = heat["goal_recovered"].clone();
        // The same maze scored at rest (`eval heatmap --probe at-rest`): the reward of staying
        // at each position. Reported beside the paper's heatmap, never instead of it; data
        // whose states are more than a position and its velocities cannot be probed (null).
        let rest_png = out.join(format!("heatmap-at-rest-{model}.png"));
        let at = argv.iter().position(|a| a == "--out").map_or(0, |i| i + 1);
        argv[at] = path_str(&rest_png);
        argv.extend(strings(&["--probe", "at-rest"]));
        let command: EvalCommand = parse(&argv)?;
        match super::eval::run(quiet, command).await {
            Ok(report) => {
                let heat = report.json.context("heatmap returned no JSON")?;
                row["heatmap_at_rest"] = json!(path_str(&rest_png));
                row["argmax_cell_at_rest"] = heat["argmax"]["cell"].clone();
                row["distance_cells_at_rest"] = heat["distance_cells"].clone();
                row["goal_recovered_at_rest"] = heat["goal_recovered"].clone();
            }
            Err(e) if e.downcast_ref::<UsageError>().is_some() => {
                row["at_rest_refused"] = json!(e.to_string());
            }
            Err(e) => return Err(e),
        }
    }
    Ok(row)
}

/// Writes `report.md` and `report.json` into the run's directory and returns them as the
/// command's report. `extra` is merged into the JSON (the demo's steering, layout).
pub fn write_report(inputs: &Inputs, e: &Extracted, elapsed: f64, extra: Value) -> Result<Report> {
    let with_goal: Vec<&Value> =
        e.rows.iter().filter(|r| r.get("goal_recovered").is_some_and(Value::is_boolean)).collect();
    let recovered = with_goal.iter().filter(|r| r["goal_recovered"] == true).count();
    let at_rest: Vec<&Value> =
        e.rows.iter().filter(|r| r.get("goal_recovered_at_rest").is_some_and(Value::is_boolean)).collect();
    let recovered_at_rest = at_rest.iter().filter(|r| r["goal_recovered_at_rest"] == true).count();
    let accuracies: Vec<f64> = e.rows.iter().filter_map(|r| r["balanced_accuracy"].as_f64()).collect();
    let mean_accuracy = accuracies.iter().sum::<f64>() / accuracies.len().max(1) as f64;
    let mut report = json!({
        "base_data": path_str(&inputs.base),
        "algorithm": match inputs.algorithm { AlgorithmArg::WithDataset => 1, AlgorithmArg::ModelsOnly => 2 },
        "seed": inputs.seed,
        "profiles": e.profiles.iter().map(|p| json!({
            "rows": p.rows, "episodes": p.episodes, "episode_len_min_q25_median_max": p.episode_len,
            "displacement_per_row": p.displacement_per_row,
        })).collect::<Vec<_>>(),
        "sizes": e.rows.first().map(|r| r["sizes"].clone()).unwrap_or(Value::Null),
        "models": {"base": e.base_model, "experts": e.expert_models, "rewards": e.rewards},
        "rewards": e.rows,
        "goals_recovered": recovered,
        "goals_evaluated": with_goal.len(),
        "goals_recovered_at_rest": recovered_at_rest,
        "goals_evaluated_at_rest": at_rest.len(),
        "mean_balanced_accuracy": mean_accuracy,
        "elapsed_seconds": elapsed,
        "out": path_str(&inputs.out),
    });
    if let (Value::Object(r), Value::Object(x)) = (&mut report, extra) {
        r.extend(x);
    }
    let md = report_markdown(&report);
    std::fs::write(inputs.out.join("report.md"), &md)?;
    std::fs::write(inputs.out.join("report.json"), serde_json::to_string_pretty(&report)?)?;
    Ok(Report::ok(md, report))
}

fn report_markdown(r: &Value) -> String {
    let num = |v: &Value| v.as_f64().map_or("-".to_owned(), |x| format!("{x:.3}"));
    let mut t = format!(
        "# relreward extract\n\nbase data: `{}`; Algorithm {}; seed {}; {:.0} s\n\nsizes: `{}`\n\n",
        r["base_data"].as_str().unwrap_or(""),
        r["algorithm"],
        r["seed"],
        r["elapsed_seconds"].as_f64().unwrap_or(0.0),
        r["sizes"]
    );
    t.push_str("| expert | reward | balanced accuracy | AUC | reward max at | recovered | max at rest | recovered at rest | discriminator accuracy |\n|---|---|---|---|---|---|---|---|---|\n");
    for row in r["rewards"].as_array().map(Vec::as_slice).unwrap_or(&[]) {
        let cell = |v: &Value| {
            v.as_array().map_or("-".to_owned(), |a| a.iter().map(|x| x.to_string()).collect::<Vec<_>>().join(","))
        };
        let yes_no = |v: Option<&Value>| match v {
            Some(Value::Bool(true)) => "yes",
            Some(Value::Bool(false)) => "no",
            _ => "-",
        };
        t.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            row["label"].as_str().unwrap_or(""),
            row["model"].as_str().unwrap_or(""),
            num(&row["balanced_accuracy"]),
            num(&row["auc"]),
            cell(&row["argmax_cell"]),
            yes_no(row.get("goal_recovered")),
            cell(&row["argmax_cell_at_rest"]),
            yes_no(row.get("goal_recovered_at_rest")),
            num(&row["discriminator"]["balanced_accuracy"]),
        ));
    }
    t.push_str(&format!(
        "\nmean balanced accuracy {}; goals recovered {} of {} evaluated (the paper's heatmap: base sub-trajectories); at rest {} of {}\n\nPictures: `hist-*.png` (reward histograms, base vs expert), `loss-*.png` (loss curves), `heatmap-*.png` (maze reward heatmaps over base sub-trajectories), `heatmap-at-rest-*.png` (the reward of a window held still at each position).\n",
        num(&r["mean_balanced_accuracy"]),
        r["goals_recovered"],
        r["goals_evaluated"],
        r["goals_recovered_at_rest"],
        r["goals_evaluated_at_rest"]
    ));
    t
}

/// Submits a training job from CLI arguments (its id is its `--job-id`) and follows it: with a
/// progress bar, or silently with `--json` (stdout then carries only the report). An
/// unsuccessful job stops the run.
pub async fn train(ctx: &Ctx, argv: &[String]) -> Result<()> {
    let id = argv.iter().skip_while(|a| *a != "--job-id").nth(1).cloned().context("a job without --job-id")?;
    if !ctx.json {
        let command: TrainCommand = parse(argv)?;
        let report = super::jobs::run_train(ctx, command).await?;
        if !report.success {
            bail!("training job {id} did not succeed:\n{}", report.text);
        }
        return Ok(());
    }
    let quiet: Vec<String> = argv.iter().filter(|a| *a != "--watch").cloned().collect();
    let command: TrainCommand = parse(&quiet)?;
    super::jobs::run_train(ctx, command).await?;
    let client = ctx.connect().await?;
    loop {
        let job = client.jobs().get_job(pb::GetJobRequest { id: id.clone() }).await?.into_inner();
        match job.state() {
            pb::JobState::Succeeded => return Ok(()),
            pb::JobState::Failed | pb::JobState::Cancelled => {
                bail!("training job {id} ended {:?}: {}", job.state(), job.error)
            }
            _ => tokio::time::sleep(std::time::Duration::from_millis(200)).await,
        }
    }
}

/// Runs an `eval` command and returns its JSON document.
pub async fn eval(quiet: &Ctx, argv: &[&str]) -> Result<Value> {
    let command: EvalCommand = parse(&strings(argv))?;
    let report = super::eval::run(quiet, command).await?;
    report.json.ok_or_else(|| anyhow::anyhow!("eval {argv:?} returned no JSON"))
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

    #[test]
    fn config_overrides_sizes_and_refuses_unknown_keys() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("c.toml");
        std::fs::write(&path, "[extract]\nhorizon = 32\nwindow = 8\nreward_hidden = [16]\n").expect("write");
        let mut s = Sizes::preset(Size::Tiny);
        s.apply_config(&path).expect("ok");
        assert_eq!((s.horizon, s.window, s.reward_hidden.clone()), (32, 8, vec![16]));
        std::fs::write(&path, "[extract]\nhorizn = 32\n").expect("write");
        let err = Sizes::preset(Size::Tiny).apply_config(&path).expect_err("typo").to_string();
        assert!(err.contains("horizn"), "{err}");
        std::fs::write(&path, "[extract]\nhorizon = 30\nwindow = 8\n").expect("write");
        let err = Sizes::preset(Size::Tiny).apply_config(&path).expect_err("window").to_string();
        assert!(err.contains("window = 8 must divide horizon = 30"), "{err}");
    }

    #[test]
    fn the_diffusion_models_name_depends_on_their_sizes_only() {
        let base = Sizes::preset(Size::Default);
        let mut reward_only = base.clone();
        (reward_only.reward_steps, reward_only.reward_lr, reward_only.window) = (600, 3e-4, 8);
        assert_eq!(base.diffusion_fingerprint(), reward_only.diffusion_fingerprint());
        assert_ne!(base.fingerprint(), reward_only.fingerprint());
        for change in [
            |s: &mut Sizes| s.horizon = 32,
            |s: &mut Sizes| s.n_timesteps = 50,
            |s: &mut Sizes| s.diffusion_steps += 1,
            |s: &mut Sizes| s.diffusion_batch = 7,
            |s: &mut Sizes| s.diffusion_architecture = toml::Value::String("other".into()),
        ] {
            let mut changed = base.clone();
            change(&mut changed);
            assert_ne!(base.diffusion_fingerprint(), changed.diffusion_fingerprint(), "{changed:?}");
        }
    }

    #[test]
    fn names_are_made_of_allowed_characters() {
        assert_eq!(slug("PointMaze_UMaze-v3 (goal 1)", 16), "pointmaze-umaze");
        assert_eq!(slug("!!!", 8), "data");
    }

    #[test]
    fn every_step_parses_as_the_cli_would() {
        let train: TrainCommand =
            parse(&strings(&["reward", "--name", "r", "--base", "b", "--expert", "e", "--algorithm", "2"])).expect("t");
        assert!(matches!(train, TrainCommand::Reward(_)));
        let d: TrainCommand = parse(&strings(&[
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
            "windowed_mlp",
        ]))
        .expect("d");
        assert!(matches!(d, TrainCommand::Discriminator(_)));
    }
}
