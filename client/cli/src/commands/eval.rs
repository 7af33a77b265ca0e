//! `relreward eval discriminate|heatmap` and `relreward job plot`: the paper's evaluation and
//! pictures, computed here from the server's `Score` (the math and the drawing are in
//! [`relreward_toolkit::eval`], whose module docs cite the paper passage behind each step).
//!
//! Inputs are local files read like `relreward score --input` reads them
//! ([`super::rewards::read_items`]): a D4RL-style trajectories `.npz` cut into the reward model's
//! `[H, D]` windows (`--stride` rows apart, never across an episode end), or an `.npz` holding
//! `x` `[B, H, D]`. Every subset is drawn from `--seed`, so a run is reproduced exactly.
//!
//! - `eval discriminate`: scores a balanced, seeded subset of windows of a base and an expert
//!   file at `--t` (0), winsorizes the pooled scores (1%), splits each class 80/20 and fits a
//!   logistic regression on the reward alone; reports held-out (balanced) accuracy, AUC, the
//!   coefficients and each class's mean reward; `--hist-out` draws both classes' histograms.
//! - `eval heatmap`: scores the sub-trajectories of a (base) dataset, winsorizes (0.5%) and
//!   min-max scales them, averages them per 2D bin (10 per maze cell) over the positions they
//!   pass through, masks sparse bins, draws the map with walls and goal, and checks whether
//!   the smoothed maximum lies within one cell of the goal.
//! - `job plot`: the loss curve (and held-out loss) of a job from its events; optionally a
//!   histogram of a reward over the windows of one or more datasets.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, Subcommand, ValueEnum};
use futures::StreamExt;
use relreward_client::{Client, ClientError, pb};
use relreward_toolkit::eval::discriminate::{self, Protocol};
use relreward_toolkit::eval::heatmap::{self, Accumulator, Grid};
use relreward_toolkit::eval::plot::{self, HeatmapPicture, Series};
use relreward_toolkit::eval::stats::{Rng, min_max_scale, winsorize};
use relreward_toolkit::npz;
use serde_json::{Value, json};

use super::output::{check_out_file, fmt_num, key_values};
use super::rewards::{
    IN_FLIGHT, InputArgs, Items, UnitsArg, batches, floats, item_bar, read_items, request_batch, request_error,
};
use super::{Ctx, Report, UsageError};

/// Histogram bins of the reward pictures.
const HISTOGRAM_BINS: usize = 40;

#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Discriminability: a logistic regression on the reward alone, base vs expert windows,
    /// held-out balanced accuracy (paper section 5.1).
    Discriminate(DiscriminateArgs),
    /// Reward heatmap over a maze and goal recovery: the smoothed maximum within one cell of
    /// the goal (paper Figure 2 and appendix).
    Heatmap(HeatmapArgs),
}

/// What every scoring command shares: the model, diffusion time, windowing and subset.
#[derive(Debug, Clone, Args)]
pub struct ScoringArgs {
    /// Reward (or discriminator) model.
    #[arg(long, value_name = "R")]
    pub model: String,
    /// Diffusion time of every scored item (0: clean trajectories, as the paper evaluates).
    #[arg(long, value_name = "T", default_value_t = 0, allow_negative_numbers = true)]
    pub t: u32,
    /// Trajectory files: rows between the starts of consecutive windows [default: 1; heatmap:
    /// H for windowed rewards, H/4 otherwise].
    #[arg(long, value_name = "S", value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub stride: Option<u64>,
    /// Seed of the random subsets and of the train/test split.
    #[arg(long, value_name = "S", default_value_t = 0, allow_negative_numbers = true)]
    pub seed: u64,
    /// Items per Score request.
    #[arg(long, value_name = "N", default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub batch: u64,
}

#[derive(Debug, Clone, Args)]
pub struct DiscriminateArgs {
    #[command(flatten)]
    pub scoring: ScoringArgs,
    /// Base (undirected) trajectories: a D4RL-style .npz, or an .npz holding x [B, H, D].
    #[arg(long, value_name = "FILE.npz")]
    pub base_data: PathBuf,
    /// Expert trajectories, in the same form.
    #[arg(long, value_name = "FILE.npz")]
    pub expert_data: PathBuf,
    /// Windows scored per class at most: a seeded uniform subset; both classes get the same
    /// number, min(this, base windows, expert windows).
    #[arg(long, value_name = "N", default_value_t = 20_000, value_parser = clap::value_parser!(u64).range(2..), allow_negative_numbers = true)]
    pub max_windows: u64,
    /// Winsorize the pooled scores at the P and 1 - P quantiles (the paper's 1%: 0.01).
    #[arg(long, value_name = "P", default_value_t = 0.01, value_parser = parse_tail, allow_negative_numbers = true)]
    pub winsorize: f64,
    /// Also draw both classes' reward histograms (winsorized scores) to this PNG.
    #[arg(long, value_name = "FILE.png")]
    pub hist_out: Option<PathBuf>,
}

/// What a heatmap attributes rewards to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum UnitArg {
    /// `window` for windowed rewards, else `item`.
    Auto,
    /// Each scored H-row item (rho, the mean over its windows) is one sub-trajectory.
    Item,
    /// Each h-row window of a windowed reward (its own value, Score's per-window output) is
    /// one sub-trajectory: the network's own input, the finest the reward resolves.
    Window,
}

#[derive(Debug, Clone, Args)]
pub struct HeatmapArgs {
    #[command(flatten)]
    pub scoring: ScoringArgs,
    /// Trajectories to score (the base dataset): a D4RL-style .npz (positions are the first two
    /// observation coordinates), or an .npz with x [B, H, D] and --xy-columns.
    #[arg(long, value_name = "FILE.npz")]
    pub dataset: PathBuf,
    /// Where to draw the heatmap (PNG).
    #[arg(long, value_name = "FILE.png")]
    pub out: PathBuf,
    /// The true goal position [default: --goal-from's goals, else the dataset's `goals` when
    /// they are all the same].
    #[arg(long, value_name = "X,Y", value_parser = parse_point, allow_hyphen_values = true)]
    pub goal: Option<(f64, f64)>,
    /// Take the goal from this file's `goals` array (e.g. the expert dataset; must be constant).
    #[arg(long, value_name = "FILE.npz")]
    pub goal_from: Option<PathBuf>,
    /// Maze walls: an .npz holding `walls`, `wall_map` or `maze_map` [rows, cols] (nonzero:
    /// wall), or an .npy
    /// [default: the dataset's `walls`; without walls the grid covers the data].
    #[arg(long, value_name = "FILE")]
    pub walls: Option<PathBuf>,
    /// Bins along each side of a maze cell.
    #[arg(long, value_name = "N", default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=100), allow_negative_numbers = true)]
    pub bins_per_cell: u32,
    /// Mask bins crossed by fewer than K sub-trajectories.
    #[arg(long, value_name = "K", default_value_t = 5, allow_negative_numbers = true)]
    pub min_count: u32,
    /// What one sub-trajectory is.
    #[arg(long, value_enum, value_name = "UNIT", default_value_t = UnitArg::Auto)]
    pub unit: UnitArg,
    /// Items (H-row windows) scored at most: a seeded uniform subset.
    #[arg(long, value_name = "N", default_value_t = 50_000, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub max_windows: u64,
    /// Winsorize the sub-trajectory rewards at the P and 1 - P quantiles before scaling
    /// (REFERENCE: the authors' heatmaps use 0.5%).
    #[arg(long, value_name = "P", default_value_t = 0.005, value_parser = parse_tail, allow_negative_numbers = true)]
    pub winsorize: f64,
    /// Gaussian smoothing before the arg-max, standard deviation in cells (0: none).
    #[arg(long, value_name = "SIGMA", default_value_t = 0.2, value_parser = parse_non_negative, allow_negative_numbers = true)]
    pub smooth: f64,
    /// Columns of a row ([action | observation]) holding the position x and y [default for
    /// trajectories: the first two observation coordinates].
    #[arg(long, value_name = "I,J", value_parser = parse_columns)]
    pub xy_columns: Option<(usize, usize)>,
    /// What is scored at each position: `base`, the dataset's sub-trajectories passing there
    /// (the paper's heatmap), or `at-rest`, a window holding the agent still at each bin's
    /// centre (velocities zero, by the rule of docs/data-formats.md; zero action): the reward
    /// of staying there, the question a goal answers (trajectory files with walls only).
    #[arg(long, value_enum, default_value_t = ProbeArg::Base)]
    pub probe: ProbeArg,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ProbeArg {
    Base,
    AtRest,
}

/// `--probe at-rest`: one `[horizon, dim]` item per bin of `grid` where the agent can be (its
/// square of half side [`relreward_toolkit::maze::RADIUS`] in free cells), each row the bin's
/// centre in columns `cx, cy`, zero in every other column (the action and the velocities).
/// Refused unless every observation column (from `act` on) is the position or a velocity
/// (`velocities`, observation indices): a held state must be fully specified.
fn at_rest_items(
    grid: &Grid,
    walls: &(usize, usize, Vec<bool>),
    (cx, cy): (usize, usize),
    act: usize,
    dim: usize,
    horizon: usize,
    velocities: &[usize],
) -> Result<Items> {
    for c in act..dim {
        if c != cx && c != cy && !velocities.contains(&(c - act)) {
            return Err(UsageError(format!(
                "--probe at-rest: observation column {} is neither the position ({}, {}) nor a velocity {velocities:?}; \
                 an at-rest state cannot be built (use --probe base)",
                c - act,
                cx - act,
                cy - act
            ))
            .into());
        }
    }
    let (rows, cols, wall) = walls;
    let free = |x: f64, y: f64| {
        let (i, j) = heatmap::cell_of(x, y);
        i >= 0 && j >= 0 && (i as usize) < *rows && (j as usize) < *cols && !wall[i as usize * cols + j as usize]
    };
    let r = relreward_toolkit::maze::RADIUS;
    let mut values = Vec::new();
    for k in 0..grid.len() {
        let (x, y) = grid.bin_centre(k);
        if [(-r, -r), (-r, r), (r, -r), (r, r)].iter().all(|(dx, dy)| free(x + dx, y + dy)) {
            for _ in 0..horizon {
                let start = values.len();
                values.resize(start + dim, 0.0f32);
                values[start + cx] = x as f32;
                values[start + cy] = y as f32;
            }
        }
    }
    Ok(Items::Array { key: "at-rest probe".to_owned(), values, item_shape: vec![horizon as u64, dim as u64] })
}

/// `relreward job plot`.
#[derive(Debug, Clone, Args)]
pub struct JobPlotArgs {
    pub id: String,
    /// Where to draw the loss curve (PNG).
    #[arg(long, value_name = "FILE.png")]
    pub out: PathBuf,
    /// Also draw a histogram of the reward over the windows of each --dataset to this PNG.
    #[arg(long, value_name = "FILE.png", requires = "datasets")]
    pub hist_out: Option<PathBuf>,
    /// Reward model of the histogram [default: the job's model, for reward and discriminator
    /// jobs].
    #[arg(long, value_name = "R", requires = "hist_out")]
    pub model: Option<String>,
    /// Trajectories whose windows the histogram scores (repeatable: one overlaid histogram
    /// each, e.g. base and expert).
    #[arg(long = "dataset", value_name = "FILE.npz", requires = "hist_out")]
    pub datasets: Vec<PathBuf>,
    /// Histogram: diffusion time of the scored windows.
    #[arg(long, value_name = "T", default_value_t = 0, allow_negative_numbers = true)]
    pub t: u32,
    /// Histogram: rows between window starts in trajectory files [default: 1].
    #[arg(long, value_name = "S", value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub stride: Option<u64>,
    /// Histogram: windows scored per dataset at most (a seeded uniform subset).
    #[arg(long, value_name = "N", default_value_t = 20_000, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub max_windows: u64,
    /// Histogram: seed of the subsets.
    #[arg(long, value_name = "S", default_value_t = 0, allow_negative_numbers = true)]
    pub seed: u64,
}

fn parse_tail(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(p) if (0.0..0.5).contains(&p) => Ok(p),
        _ => Err(format!("'{text}' is not a tail fraction in [0, 0.5) (0.01: the 1st and 99th percentiles)")),
    }
}

fn parse_non_negative(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v >= 0.0 && v.is_finite() => Ok(v),
        _ => Err(format!("'{text}' is not a finite number >= 0")),
    }
}

fn parse_point(text: &str) -> Result<(f64, f64), String> {
    let usage = "expected X,Y (a maze position, e.g. 3,4.5)";
    let (x, y) = text.split_once(',').ok_or_else(|| usage.to_owned())?;
    let number = |v: &str| match v.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(format!("'{v}' is not a finite number; {usage}")),
    };
    Ok((number(x)?, number(y)?))
}

fn parse_columns(text: &str) -> Result<(usize, usize), String> {
    let usage = "expected I,J (two column indices of a row, e.g. 2,3)";
    let (i, j) = text.split_once(',').ok_or_else(|| usage.to_owned())?;
    let index = |v: &str| v.trim().parse::<usize>().map_err(|_| format!("'{v}' is not a column index; {usage}"));
    Ok((index(i)?, index(j)?))
}

pub async fn run(ctx: &Ctx, command: EvalCommand) -> Result<Report> {
    match command {
        EvalCommand::Discriminate(args) => discriminate(ctx, args).await,
        EvalCommand::Heatmap(args) => heatmap(ctx, args).await,
    }
}

// ---------------------------------------------------------------------------------------------
// Reading and scoring

/// `read_items`' errors name `--input`; ours name the flag the file came from.
fn relabel(err: anyhow::Error, flag: &str) -> anyhow::Error {
    let text = err.to_string();
    let Some(rest) = text.strip_prefix("--input") else { return err };
    let text = format!("{flag}{rest}");
    if err.downcast_ref::<UsageError>().is_some() { UsageError(text).into() } else { anyhow!(text) }
}

/// The items of `path` for `model` (see the module docs), with `flag` in every error.
async fn load_items(client: &Client, model: &str, path: &Path, flag: &str, stride: Option<u64>) -> Result<Items> {
    let kind = npz::detect_kind(path).map_err(|e| anyhow!("{flag}: {e}"))?;
    // A stride only means something for trajectories; read_items refuses it for arrays, naming
    // --stride, which is what the user typed.
    let stride = if kind == pb::DatasetKind::Trajectories { stride.or(Some(1)) } else { stride };
    let args = InputArgs {
        model: model.to_owned(),
        input: path.to_owned(),
        key: None,
        stride,
        units: UnitsArg::Raw,
        batch: 1,
        out: None,
    };
    read_items(client, &args).await.map_err(|e| relabel(e, &format!("{flag} {}", path.display())))
}

/// Items `idx` of `items` (in that order).
fn subset(items: Items, idx: &[usize]) -> Items {
    match items {
        Items::Windows(mut w) => {
            w.starts = idx.iter().map(|&i| w.starts[i]).collect();
            Items::Windows(w)
        }
        Items::Array { key, values, item_shape } => {
            let per = item_shape.iter().product::<u64>() as usize;
            let values = idx.iter().flat_map(|&i| values[i * per..(i + 1) * per].iter().copied()).collect();
            Items::Array { key, values, item_shape }
        }
    }
}

/// The `[H, D]` rows of item `k`, row-major.
fn item_rows(items: &Items, k: usize) -> &[f32] {
    match items {
        Items::Windows(w) => &w.rows[w.starts[k] * w.dim..(w.starts[k] + w.horizon) * w.dim],
        Items::Array { values, item_shape, .. } => {
            let per = item_shape.iter().product::<u64>() as usize;
            &values[k * per..(k + 1) * per]
        }
    }
}

/// Scores of every item: rho `[n]` and, with `per_window`, the values of the model's windows
/// `[n, K]` (as `(K, values)`).
type Scores = (Vec<f64>, Option<(usize, Vec<f64>)>);

/// Scores every item of `items` with `model` at diffusion time `t`, `batch` items a request
/// (two in flight), with a progress bar; `flag` labels errors about the items.
async fn score_items(
    ctx: &Ctx,
    client: &Client,
    scoring: &ScoringArgs,
    items: &Items,
    flag: &str,
    per_window: bool,
) -> Result<Scores> {
    let n = items.len();
    let t = scoring.t;
    let batch = request_batch(scoring.batch, items.item_len() as u64 * 4, ctx.json);
    let ranges = batches(n, batch);
    let several = ranges.len() > 1;
    let fields = vec![
        ("model", format!("--model {}", scoring.model)),
        ("x", flag.to_owned()),
        ("t", format!("--t {t}")),
        ("per_window", "--unit window".to_owned()),
    ];
    let bar = item_bar(ctx.json, n as u64, "windows");
    let requests = ranges.iter().map(|range| {
        let request = pb::ScoreRequest {
            model: scoring.model.clone(),
            x: Some(items.batch(range.clone())),
            t: vec![t],
            input_units: pb::Units::Raw as i32,
            per_window,
            per_step: false,
        };
        let client = client.clone();
        async move { client.score(request).await }
    });
    let mut answers = futures::stream::iter(requests).buffered(IN_FLIGHT);
    let mut next = ranges.iter();
    let mut rewards = Vec::with_capacity(n);
    let mut windows: Option<(usize, Vec<f64>)> = None;
    while let Some(answer) = answers.next().await {
        let range = next.next().ok_or_else(|| anyhow!("more answers than requests"))?;
        let b = range.len() as u64;
        let answer = answer.map_err(|e| request_error(e, &fields, range, n, several))?;
        rewards.extend(floats(answer.rewards.as_ref(), "rewards", &[b])?.into_iter().map(f64::from));
        if per_window {
            let width = match (&windows, answer.per_window.as_ref()) {
                (Some((w, _)), _) => *w as u64,
                (None, Some(t)) if t.shape.len() == 2 && t.shape[1] > 0 => t.shape[1],
                (None, other) => {
                    bail!(
                        "the server's answer has no per-window values of shape [{b}, K] (got {:?})",
                        other.map(|t| &t.shape)
                    )
                }
            };
            let values = floats(answer.per_window.as_ref(), "per_window", &[b, width])?;
            windows.get_or_insert_with(|| (width as usize, Vec::new())).1.extend(values.into_iter().map(f64::from));
        }
        bar.inc(b);
    }
    bar.finish_and_clear();
    if let Some(bad) = rewards.iter().find(|v| !v.is_finite()) {
        bail!("the server returned a non-finite reward ({bad}) for {flag}");
    }
    Ok((rewards, windows))
}

/// A seeded subset of at most `max` items of a file, and their scores.
struct Scored {
    items: Items,
    available: usize,
    rewards: Vec<f64>,
    per_window: Option<(usize, Vec<f64>)>,
}

async fn score_subset(
    ctx: &Ctx,
    client: &Client,
    scoring: &ScoringArgs,
    items: Items,
    idx: &[usize],
    flag: &str,
    per_window: bool,
) -> Result<Scored> {
    let available = items.len();
    let items = subset(items, idx);
    let (rewards, per_window) = score_items(ctx, client, scoring, &items, flag, per_window).await?;
    Ok(Scored { items, available, rewards, per_window })
}

fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}

/// A fraction as a percentage with two decimals.
fn percent(v: f64) -> String {
    if v.is_finite() { format!("{:.2}%", 100.0 * v) } else { "-".to_owned() }
}

// ---------------------------------------------------------------------------------------------
// eval discriminate

async fn discriminate(ctx: &Ctx, args: DiscriminateArgs) -> Result<Report> {
    if let Some(out) = &args.hist_out {
        check_out_file("--hist-out", out)?;
    }
    let s = &args.scoring;
    let client = ctx.connect().await?;
    let base = load_items(&client, &s.model, &args.base_data, "--base-data", s.stride).await?;
    let expert = load_items(&client, &s.model, &args.expert_data, "--expert-data", s.stride).await?;
    let mut rng = Rng::new(s.seed);
    let (base_idx, expert_idx) =
        discriminate::balanced_subsets(base.len(), expert.len(), args.max_windows as usize, &mut rng);
    let (base_source, expert_source) = (base.source_json(), expert.source_json());
    let base = score_subset(ctx, &client, s, base, &base_idx, "--base-data", false).await?;
    let expert = score_subset(ctx, &client, s, expert, &expert_idx, "--expert-data", false).await?;
    let protocol = Protocol { winsorize: args.winsorize, ..Protocol::default() };
    let d = discriminate::discriminate(&base.rewards, &expert.rewards, protocol, &mut rng).map_err(|e| anyhow!(e))?;

    if let Some(out) = &args.hist_out {
        let groups = vec![
            (format!("base: {}", file_name(&args.base_data)), d.base_winsorized.clone()),
            (format!("expert: {}", file_name(&args.expert_data)), d.expert_winsorized.clone()),
        ];
        let title =
            format!("rho of {} at t = {}: test balanced accuracy {}", s.model, s.t, percent(d.test_balanced_accuracy));
        let x_label = format!("reward (winsorized at {}%)", fmt_p(args.winsorize));
        plot::histogram_png(out, &title, &x_label, &groups, HISTOGRAM_BINS)?;
    }

    let m = &d.model;
    let (w_raw, b_raw) = m.raw_coefficients();
    let class_json = |c: &discriminate::ClassSummary, available: usize, source: &Value| {
        json!({
            "windows_available": available,
            "n": c.n,
            "n_train": c.n_train,
            "n_test": c.n_test,
            "mean_reward": c.mean,
            "std_reward": c.std,
            "mean_reward_winsorized": c.mean_winsorized,
            "source": source,
        })
    };
    let json = json!({
        "model": s.model,
        "t": s.t,
        "base_data": args.base_data.display().to_string(),
        "expert_data": args.expert_data.display().to_string(),
        "seed": s.seed,
        "max_windows": args.max_windows,
        "winsorize": { "p": args.winsorize, "limits": [d.limits.0, d.limits.1] },
        "train_fraction": protocol.train_fraction,
        "base": class_json(&d.base, base.available, &base_source),
        "expert": class_json(&d.expert, expert.available, &expert_source),
        "logistic": {
            "weight": m.weight,
            "bias": m.bias,
            "feature_mean": m.mean,
            "feature_std": m.scale,
            "weight_reward_units": w_raw,
            "bias_reward_units": b_raw,
            "threshold": m.threshold(),
            "l2": m.l2,
            "iterations": m.iterations,
            "converged": m.converged,
        },
        "train": { "accuracy": d.train_accuracy, "balanced_accuracy": d.train_balanced_accuracy },
        "test": { "accuracy": d.test_accuracy, "balanced_accuracy": d.test_balanced_accuracy, "auc": d.test_auc },
        "balanced_accuracy": d.test_balanced_accuracy,
        "expert_scores_higher": m.weight > 0.0,
        "hist_out": args.hist_out.as_ref().map(|p| p.display().to_string()),
    });
    let class_text = |c: &discriminate::ClassSummary, available: usize| {
        format!(
            "{} windows of {available} ({} train, {} test); mean reward {} (winsorized {}), std {}",
            c.n,
            c.n_train,
            c.n_test,
            fmt_num(c.mean),
            fmt_num(c.mean_winsorized),
            fmt_num(c.std)
        )
    };
    let mut fields = vec![
        ("model", format!("{} (t = {})", s.model, s.t)),
        ("base", class_text(&d.base, base.available)),
        ("expert", class_text(&d.expert, expert.available)),
        (
            "winsorized",
            format!("at {}% per tail: [{}, {}]", fmt_p(args.winsorize), fmt_num(d.limits.0), fmt_num(d.limits.1)),
        ),
        (
            "logistic",
            format!(
                "P(expert) = sigmoid({} * rho + {}); threshold rho = {}; {} Newton steps{}",
                fmt_num(w_raw),
                fmt_num(b_raw),
                m.threshold().map_or_else(|| "-".to_owned(), fmt_num),
                m.iterations,
                if m.converged { "" } else { " (not converged)" }
            ),
        ),
        ("train", format!("accuracy {}, balanced {}", percent(d.train_accuracy), percent(d.train_balanced_accuracy))),
        (
            "test",
            format!(
                "accuracy {}, balanced {}, AUC {}",
                percent(d.test_accuracy),
                percent(d.test_balanced_accuracy),
                fmt_num(d.test_auc)
            ),
        ),
        ("balanced accuracy", percent(d.test_balanced_accuracy)),
    ];
    if m.weight < 0.0 {
        fields.push((
            "note",
            "the fitted weight is negative: this reward ranks expert windows BELOW base ones".to_owned(),
        ));
    }
    if let Some(out) = &args.hist_out {
        fields.push(("histogram", out.display().to_string()));
    }
    Ok(Report::ok(key_values(&fields, 0), json))
}

/// `1 point`, `4 points`.
fn points(n: usize) -> String {
    format!("{n} point{}", if n == 1 { "" } else { "s" })
}

/// A tail fraction as a percentage: `1`, `0.5`.
fn fmt_p(p: f64) -> String {
    let text = format!("{:.3}", 100.0 * p);
    text.trim_end_matches('0').trim_end_matches('.').to_owned()
}

// ---------------------------------------------------------------------------------------------
// eval heatmap

/// One numeric array of an `.npz` (or a plain `.npy`) as f64 with its shape; `None` when an
/// archive has no such array (see [`npz::read_numbers`]).
fn read_numbers(path: &Path, key: &str) -> Result<Option<(Vec<u64>, Vec<f64>)>> {
    npz::read_numbers(path, key).with_context(|| format!("{}: array '{key}'", path.display()))
}

/// The maze walls: `(rows, cols, flags)`.
type Walls = relreward_toolkit::episodes::Walls;

fn walls_of(path: &Path, required: bool) -> Result<Option<Walls>> {
    // `walls`, `wall_map` or `maze_map` (rule: relreward_toolkit::episodes).
    let walls = npz::walls_from_npz(path).with_context(|| format!("{}: maze walls", path.display()))?;
    if walls.is_none() && required {
        bail!("--walls {}: no 'walls', 'wall_map' or 'maze_map' array", path.display())
    }
    Ok(walls)
}

/// The goal of a file's `goals` ([2], [N, >=2]): `Ok(None)` when absent or not constant.
fn constant_goal(path: &Path) -> Result<Option<(f64, f64)>> {
    let Some((shape, values)) = read_numbers(path, "goals")? else { return Ok(None) };
    let width = match shape.as_slice() {
        [w] if *w >= 2 => *w as usize,
        [_, w] if *w >= 2 => *w as usize,
        _ => bail!("{}: 'goals' has shape {shape:?}; expected [2] or [N, 2]", path.display()),
    };
    let mut rows = values.chunks_exact(width).map(|r| (r[0], r[1]));
    let Some(first) = rows.next() else { return Ok(None) };
    let constant = rows.all(|g| (g.0 - first.0).abs() <= 1e-6 && (g.1 - first.1).abs() <= 1e-6);
    Ok(constant.then_some(first))
}

/// Observation width of a trajectories file (its `observations` header): the values per row,
/// trailing dimensions flattened as the readers do (`[N]` is 1).
fn obs_dim(path: &Path) -> Result<usize> {
    let shape = npz::npz_array_shape(path, "observations")
        .with_context(|| format!("--dataset {}", path.display()))?
        .ok_or_else(|| anyhow!("--dataset {}: no 'observations' array", path.display()))?;
    Ok(shape.iter().skip(1).product::<u64>() as usize)
}

async fn heatmap(ctx: &Ctx, args: HeatmapArgs) -> Result<Report> {
    check_out_file("--out", &args.out)?;
    let s = &args.scoring;
    let dataset = &args.dataset;
    let is_trajectories =
        npz::detect_kind(dataset).map_err(|e| anyhow!("--dataset: {e}"))? == pb::DatasetKind::Trajectories;
    if !is_trajectories && args.xy_columns.is_none() {
        return Err(UsageError(format!(
            "--dataset {}: holds items x [B, H, D], not trajectories; say which columns hold the position with \
             --xy-columns I,J",
            dataset.display()
        ))
        .into());
    }
    let client = ctx.connect().await?;
    let model = client.get_model(&s.model).await.with_context(|| format!("--model {}", s.model))?;
    let info = model.reward.clone().unwrap_or_default();
    let horizon = info.input_shape.first().copied().unwrap_or(1).max(1);
    let window = u64::from(info.window);
    let windowed = window > 0 && window < horizon && horizon % window == 0;
    let per_window = match args.unit {
        UnitArg::Auto => windowed,
        UnitArg::Item => false,
        UnitArg::Window if windowed || window == horizon => windowed,
        UnitArg::Window => {
            return Err(UsageError(format!(
                "--unit window: model '{}' is not a windowed reward ({}); use --unit item",
                s.model, info.architecture
            ))
            .into());
        }
    };
    let stride = s.stride.or(is_trajectories.then(|| if per_window { horizon } else { (horizon / 4).max(1) }));
    let items = load_items(&client, &s.model, dataset, "--dataset", stride).await?;
    let dim = items.item_shape().get(1).copied().unwrap_or(0) as usize;
    let (cx, cy) = match args.xy_columns {
        Some(c) => c,
        None => {
            let path = dataset.clone();
            let obs = tokio::task::spawn_blocking(move || obs_dim(&path)).await.context("reading crashed")??;
            let act = dim.saturating_sub(obs);
            if obs < 2 {
                bail!("--dataset {}: observations have {obs} coordinate(s); a position needs 2", dataset.display());
            }
            (act, act + 1)
        }
    };
    if cx >= dim || cy >= dim {
        return Err(UsageError(format!("--xy-columns {cx},{cy}: rows have {dim} columns")).into());
    }
    // Walls and goal, read before the (long) scoring so that a bad file fails fast.
    let walls = match &args.walls {
        Some(path) => walls_of(path, true)?,
        None => walls_of(dataset, false)?,
    };
    let (goal, goal_source) = match (&args.goal, &args.goal_from) {
        (Some(g), _) => (Some(*g), "--goal".to_owned()),
        (None, Some(path)) => match constant_goal(path)? {
            Some(g) => (Some(g), format!("goals of {}", path.display())),
            None => bail!("--goal-from {}: no 'goals' array with one constant goal", path.display()),
        },
        (None, None) => match constant_goal(dataset)? {
            Some(g) => (Some(g), format!("goals of {}", dataset.display())),
            None => (None, String::new()),
        },
    };

    let (items, min_count) = match (args.probe, &walls) {
        (ProbeArg::Base, _) => (items, args.min_count),
        (ProbeArg::AtRest, None) => {
            return Err(
                UsageError("--probe at-rest: needs the maze's walls (--walls, or walls in --dataset)".into()).into()
            );
        }
        (ProbeArg::AtRest, Some(w)) => {
            if !is_trajectories {
                return Err(UsageError("--probe at-rest: --dataset must hold trajectories".into()).into());
            }
            let path = dataset.clone();
            let velocities = tokio::task::spawn_blocking(move || -> Result<Vec<usize>> {
                Ok(relreward_toolkit::trajectories::Trajectories::from_npz(&path)?.velocity_columns())
            })
            .await
            .context("reading crashed")??;
            let grid = Grid::of_maze(w.0, w.1, args.bins_per_cell as usize);
            let act = dim - obs_dim(dataset)?;
            // Each bin is probed once, by one item (whose windows all land in it).
            (at_rest_items(&grid, w, (cx, cy), act, dim, horizon as usize, &velocities)?, 1)
        }
    };
    let mut rng = Rng::new(s.seed);
    let idx = rng.subset(items.len(), args.max_windows as usize);
    let scored = score_subset(ctx, &client, s, items, &idx, "--dataset", per_window).await?;
    let items = &scored.items;

    // Sub-trajectories: (item, first row within it, rows, reward). A window of a trajectory
    // file is the same rows whichever item it was scored in: counted once.
    let h_rows = horizon as usize;
    let mut units: Vec<(usize, usize, usize, f64)> = Vec::new();
    match &scored.per_window {
        Some((k_windows, values)) => {
            let h = h_rows / k_windows.max(&1);
            let mut seen = HashSet::new();
            for k in 0..items.len() {
                for m in 0..*k_windows {
                    if let Items::Windows(w) = items
                        && !seen.insert(w.starts[k] + m * h)
                    {
                        continue;
                    }
                    units.push((k, m * h, h, values[k * k_windows + m]));
                }
            }
        }
        None => units.extend(scored.rewards.iter().enumerate().map(|(k, &r)| (k, 0, h_rows, r))),
    }
    let unit_rows = units.first().map_or(h_rows, |u| u.2);
    let mut values: Vec<f64> = units.iter().map(|u| u.3).collect();
    let limits = winsorize(&mut values, args.winsorize);
    let scale = min_max_scale(&mut values);
    let points = |&(k, first, rows, _): &(usize, usize, usize, f64)| {
        item_rows(items, k)[first * dim..(first + rows) * dim]
            .chunks_exact(dim)
            .map(move |r| (f64::from(r[cx]), f64::from(r[cy])))
    };
    let bins_per_cell = args.bins_per_cell as usize;
    let grid = match &walls {
        Some((rows, cols, _)) => Grid::of_maze(*rows, *cols, bins_per_cell),
        None => Grid::covering(units.iter().flat_map(points), bins_per_cell)
            .ok_or_else(|| anyhow!("--dataset {}: no finite positions", dataset.display()))?,
    };
    let mut acc = Accumulator::new(grid);
    for (unit, &v) in units.iter().zip(&values) {
        acc.add(points(unit), v);
    }
    let means = acc.means(min_count);
    let covered = means.iter().filter(|v| v.is_some()).count();
    let smoothed = heatmap::smooth(&grid, &means, args.smooth * bins_per_cell as f64);
    let best = heatmap::argmax(&smoothed).map(|(k, v)| (grid.bin_centre(k), v));
    let recovered = match (best, goal) {
        (Some((pos, _)), Some(g)) => Some(heatmap::goal_recovered(pos, g)),
        _ => None,
    };
    let distance = best.zip(goal).map(|((pos, _), g)| heatmap::chebyshev(pos, g));
    let euclidean = best.zip(goal).map(|((pos, _), g)| ((pos.0 - g.0).powi(2) + (pos.1 - g.1).powi(2)).sqrt());

    let picture = HeatmapPicture {
        title: format!("reward {} over {} (t = {})", s.model, file_name(dataset), s.t),
        grid,
        values: &means,
        walls: walls.as_ref().map(|(r, c, w)| (*r, *c, w.as_slice())),
        goal,
        argmax: best.map(|(pos, _)| pos),
        scale_label: "mean reward per bin (scaled to [0, 1])".to_owned(),
    };
    plot::heatmap_png(&args.out, &picture)?;

    let unit_name = if per_window { "window" } else { "item" };
    let argmax_json = best.map_or(Value::Null, |((x, y), v)| {
        let (i, j) = heatmap::cell_of(x, y);
        json!({ "x": x, "y": y, "cell": [i, j], "value": v })
    });
    let json = json!({
        "model": s.model,
        "dataset": dataset.display().to_string(),
        "t": s.t,
        "seed": s.seed,
        "out": args.out.display().to_string(),
        "unit": unit_name,
        "unit_rows": unit_rows,
        "horizon": horizon,
        "stride": stride,
        "xy_columns": [cx, cy],
        "items_available": scored.available,
        "items_scored": items.len(),
        "sub_trajectories": units.len(),
        "winsorize": { "p": args.winsorize, "limits": [limits.0, limits.1] },
        "scale": { "min": scale.0, "max": scale.1 },
        "grid": {
            "rows": grid.rows,
            "cols": grid.cols,
            "row0": grid.row0,
            "col0": grid.col0,
            "bins_per_cell": grid.bins_per_cell,
            "walls": walls.is_some(),
        },
        "bins": grid.len(),
        "bins_covered": covered,
        "min_count": min_count,
        "probe": if args.probe == ProbeArg::AtRest { "at-rest" } else { "base" },
        "states_outside": acc.outside,
        "smooth_sigma_cells": args.smooth,
        "argmax": argmax_json,
        "goal": goal.map(|(x, y)| json!({ "x": x, "y": y, "source": goal_source })),
        "distance_cells": distance,
        "distance_euclidean": euclidean,
        "recovery_radius_cells": heatmap::RECOVERY_RADIUS,
        "goal_recovered": recovered,
    });
    let mut fields = vec![
        ("model", format!("{} (t = {})", s.model, s.t)),
        (
            "sub-trajectories",
            format!(
                "{} {unit_name}s of {unit_rows} rows, from {} of {} items (H = {horizon}{})",
                units.len(),
                items.len(),
                scored.available,
                stride.map_or_else(String::new, |s| format!(", stride {s}"))
            ),
        ),
        (
            "rewards",
            format!(
                "winsorized at {}% per tail [{}, {}], scaled to [0, 1]",
                fmt_p(args.winsorize),
                fmt_num(limits.0),
                fmt_num(limits.1)
            ),
        ),
        (
            "grid",
            format!(
                "{} x {} cells{}, {} bins per cell: {covered} of {} bins with >= {} sub-trajectories",
                grid.rows,
                grid.cols,
                if walls.is_some() { " (walls)" } else { " (covering the data)" },
                grid.bins_per_cell,
                grid.len(),
                min_count
            ),
        ),
    ];
    if acc.outside > 0 {
        fields.push(("outside", format!("{} states outside the grid", acc.outside)));
    }
    fields.push((
        "maximum",
        best.map_or_else(
            || "- (no bin has enough sub-trajectories)".to_owned(),
            |((x, y), v)| {
                let (i, j) = heatmap::cell_of(x, y);
                format!(
                    "x = {x:.2}, y = {y:.2} (cell {i}, {j}); smoothed value {} (sigma {} cells)",
                    fmt_num(v),
                    args.smooth
                )
            },
        ),
    ));
    fields.push((
        "goal",
        goal.map_or_else(
            || "- (pass --goal X,Y or --goal-from FILE)".to_owned(),
            |(x, y)| format!("x = {x:.2}, y = {y:.2} ({goal_source})"),
        ),
    ));
    if let (Some(d), Some(r)) = (distance, recovered) {
        fields.push(("distance", format!("{d:.2} cells (Chebyshev)")));
        fields.push((
            "goal recovered",
            format!("{} (within {} cell)", if r { "yes" } else { "no" }, heatmap::RECOVERY_RADIUS),
        ));
    }
    fields.push(("heatmap", args.out.display().to_string()));
    Ok(Report::ok(key_values(&fields, 0), json))
}

// ---------------------------------------------------------------------------------------------
// job plot

/// `relreward job plot ID --out loss.png [--hist-out rewards.png [--model R] --dataset FILE..]`.
pub async fn job_plot(ctx: &Ctx, args: JobPlotArgs) -> Result<Report> {
    check_out_file("--out", &args.out)?;
    if let Some(out) = &args.hist_out {
        check_out_file("--hist-out", out)?;
    }
    let client = ctx.connect().await?;
    let job = client.get_job(&args.id).await?;
    let spec = job.spec.clone().unwrap_or_default();
    let kind = match &spec.kind {
        Some(pb::job_spec::Kind::Diffusion(_)) => "diffusion",
        Some(pb::job_spec::Kind::Reward(_)) => "reward",
        Some(pb::job_spec::Kind::Discriminator(_)) => "discriminator",
        None => "job",
    };
    // Replay the recorded events up to the last one the job had when asked (a running job's
    // stream would go on).
    let (mut loss, mut eval) = (Vec::new(), Vec::new());
    if job.last_seq > 0 {
        let mut stream = client.watch_job(&args.id, 1).await?;
        while let Some(event) = stream.message().await.map_err(ClientError::Status)? {
            if let Some(pb::job_event::Event::Progress(p)) = &event.event {
                loss.push((p.step as f64, p.loss));
                if let Some(e) = p.eval_loss {
                    eval.push((p.step as f64, e));
                }
            }
            if event.seq >= job.last_seq {
                break;
            }
        }
    }
    if loss.is_empty() {
        bail!("job {} has no progress events yet: nothing to plot", args.id);
    }
    let mut series = vec![Series { name: "training loss".to_owned(), points: loss.clone() }];
    if !eval.is_empty() {
        series.push(Series { name: "held-out loss".to_owned(), points: eval.clone() });
    }
    let log = plot::wants_log_scale(&series);
    let state = super::output::state_name(job.state());
    let title = format!("job {} ({kind}, {state}): loss", args.id);
    plot::loss_png(&args.out, &title, "loss", &series, log)?;

    let mut fields = vec![
        ("job", format!("{} ({kind}, {state})", args.id)),
        (
            "loss",
            format!(
                "{}, steps {}..{}, last {}",
                points(loss.len()),
                loss[0].0,
                loss[loss.len() - 1].0,
                fmt_num(loss[loss.len() - 1].1)
            ),
        ),
        ("held-out loss", if eval.is_empty() { "-".to_owned() } else { points(eval.len()) }),
        ("scale", if log { "log".to_owned() } else { "linear".to_owned() }),
        ("plot", args.out.display().to_string()),
    ];
    let mut hist_json = Value::Null;
    if let Some(out) = &args.hist_out {
        let model = match (&args.model, kind) {
            (Some(m), _) => m.clone(),
            (None, "reward" | "discriminator") => spec.output_model.clone(),
            (None, _) => {
                return Err(UsageError(format!(
                    "--hist-out: job {} trains a {kind} model, not a reward; name the reward with --model",
                    args.id
                ))
                .into());
            }
        };
        let scoring = ScoringArgs { model: model.clone(), t: args.t, stride: args.stride, seed: args.seed, batch: 256 };
        let mut rng = Rng::new(args.seed);
        let mut groups = Vec::new();
        let mut per_dataset = Vec::new();
        for path in &args.datasets {
            let items = load_items(&client, &model, path, "--dataset", args.stride).await?;
            let idx = rng.subset(items.len(), args.max_windows as usize);
            let scored = score_subset(ctx, &client, &scoring, items, &idx, "--dataset", false).await?;
            let summary = super::rewards::summarize(scored.rewards.iter().copied());
            per_dataset.push(json!({
                "dataset": path.display().to_string(),
                "windows_available": scored.available,
                "windows": scored.rewards.len(),
                "mean": summary.map(|s| s.mean),
                "std": summary.map(|s| s.std),
            }));
            groups.push((file_name(path), scored.rewards));
        }
        // Pooled 1% winsorization, so that a few extreme windows do not squeeze the rest.
        let mut pooled: Vec<f64> = groups.iter().flat_map(|(_, v)| v.iter().copied()).collect();
        let limits = winsorize(&mut pooled, 0.01);
        for (_, values) in &mut groups {
            for v in values.iter_mut() {
                *v = v.clamp(limits.0, limits.1);
            }
        }
        let title = format!("rho of {model} at t = {}", args.t);
        plot::histogram_png(out, &title, "reward (winsorized at 1%)", &groups, HISTOGRAM_BINS)?;
        fields.push(("histogram", format!("{} ({model} over {} dataset(s))", out.display(), groups.len())));
        hist_json = json!({
            "out": out.display().to_string(),
            "model": model,
            "t": args.t,
            "datasets": per_dataset,
        });
    }
    let json = json!({
        "job": args.id,
        "kind": kind,
        "state": state,
        "out": args.out.display().to_string(),
        "log_scale": log,
        "loss_points": loss.len(),
        "eval_loss_points": eval.len(),
        "first_step": loss[0].0,
        "last_step": loss[loss.len() - 1].0,
        "last_loss": loss[loss.len() - 1].1,
        "histogram": hist_json,
    });
    Ok(Report::ok(key_values(&fields, 0), json))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn at_rest_items_hold_each_reachable_bin_still() {
        // 3 x 3 cells, only the centre free; rows [a0, a1, x, y, vx, vy]; 2 bins per cell.
        let mut wall = vec![true; 9];
        wall[4] = false;
        let walls = (3, 3, wall);
        let grid = Grid::of_maze(3, 3, 2);
        let items = at_rest_items(&grid, &walls, (2, 3), 2, 6, 4, &[2, 3]).expect("items");
        // The centre cell's 4 bins (centres at 1 +- 0.25), each 0.25 from the faces > RADIUS.
        assert_eq!(items.len(), 4);
        assert_eq!(items.item_shape(), vec![4, 6]);
        for k in 0..4 {
            let rows = item_rows(&items, k);
            let first = &rows[..6];
            assert!((first[2] - 1.0).abs() == 0.25 && (first[3] - 1.0).abs() == 0.25, "{first:?}");
            assert_eq!([first[0], first[1], first[4], first[5]], [0.0; 4]);
            assert!(rows.chunks_exact(6).all(|r| r == first), "every row the same state");
        }
        // A column that is neither position nor velocity cannot be held: refused, named.
        let err = at_rest_items(&grid, &walls, (2, 3), 2, 6, 4, &[2]).expect_err("column 3");
        assert!(err.downcast_ref::<UsageError>().is_some());
        assert!(err.to_string().contains("observation column 3"), "{err}");
    }

    #[test]
    fn flag_values_parse() {
        assert_eq!(parse_point("3,4.5"), Ok((3.0, 4.5)));
        assert_eq!(parse_point("-1, 2"), Ok((-1.0, 2.0)));
        assert!(parse_point("3").is_err() && parse_point("a,1").is_err() && parse_point("1,inf").is_err());
        assert_eq!(parse_columns("2,3"), Ok((2, 3)));
        assert!(parse_columns("2").is_err() && parse_columns("-1,2").is_err());
        assert_eq!(parse_tail("0.01"), Ok(0.01));
        assert_eq!(parse_tail("0"), Ok(0.0));
        assert!(parse_tail("0.5").is_err() && parse_tail("-0.1").is_err() && parse_tail("x").is_err());
        assert!(parse_non_negative("-1").is_err() && parse_non_negative("nan").is_err());
        assert_eq!((fmt_p(0.01), fmt_p(0.005), fmt_p(0.0)), ("1".to_owned(), "0.5".to_owned(), "0".to_owned()));
        assert_eq!(percent(0.8376), "83.76%");
    }

    /// The commands as `relreward` mounts them: `eval ..` and `job plot ..`.
    #[derive(Debug, clap::Parser)]
    struct Cli {
        #[command(subcommand)]
        command: Top,
    }

    #[derive(Debug, clap::Subcommand)]
    enum Top {
        #[command(subcommand)]
        Eval(EvalCommand),
        Plot(JobPlotArgs),
    }

    fn parse(args: &[&str]) -> Result<Top, clap::Error> {
        use clap::Parser;
        Cli::try_parse_from(std::iter::once("relreward").chain(args.iter().copied())).map(|c| c.command)
    }

    #[test]
    fn commands_parse_with_their_defaults() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
        let Ok(Top::Eval(EvalCommand::Discriminate(a))) =
            parse(&["eval", "discriminate", "--model", "r", "--base-data", "b.npz", "--expert-data", "e.npz"])
        else {
            panic!("discriminate")
        };
        assert_eq!((a.scoring.t, a.scoring.stride, a.scoring.seed, a.max_windows), (0, None, 0, 20_000));
        assert_eq!((a.winsorize, a.hist_out.is_none()), (0.01, true));
        let Ok(Top::Eval(EvalCommand::Heatmap(a))) = parse(&[
            "eval",
            "heatmap",
            "--model",
            "r",
            "--dataset",
            "d.npz",
            "--out",
            "h.png",
            "--goal",
            "-1,2.5",
            "--walls",
            "w.npz",
            "--bins-per-cell",
            "4",
            "--min-count",
            "2",
            "--unit",
            "item",
            "--smooth",
            "0",
        ]) else {
            panic!("heatmap")
        };
        assert_eq!((a.goal, a.bins_per_cell, a.min_count, a.unit), (Some((-1.0, 2.5)), 4, 2, UnitArg::Item));
        assert_eq!((a.winsorize, a.smooth, a.max_windows), (0.005, 0.0, 50_000));
        let Ok(Top::Plot(a)) =
            parse(&["plot", "j", "--out", "l.png", "--hist-out", "h.png", "--dataset", "a.npz", "--dataset", "b.npz"])
        else {
            panic!("plot")
        };
        assert_eq!((a.id.as_str(), a.datasets.len(), a.model.is_none()), ("j", 2, true));
        let refused = |args: &[&str], flag: &str| {
            let err = parse(args).expect_err(&format!("{args:?} parsed")).to_string();
            assert!(err.contains(flag), "{args:?}: {err}");
        };
        refused(&["eval", "discriminate", "--model", "r", "--base-data", "b"], "--expert-data");
        refused(
            &["eval", "discriminate", "--model", "r", "--base-data", "b", "--expert-data", "e", "--winsorize", "0.6"],
            "--winsorize",
        );
        refused(
            &["eval", "discriminate", "--model", "r", "--base-data", "b", "--expert-data", "e", "--max-windows", "1"],
            "--max-windows",
        );
        refused(&["eval", "heatmap", "--model", "r", "--dataset", "d"], "--out");
        refused(&["eval", "heatmap", "--model", "r", "--dataset", "d", "--out", "h", "--goal", "1"], "--goal");
        refused(
            &["eval", "heatmap", "--model", "r", "--dataset", "d", "--out", "h", "--bins-per-cell", "0"],
            "--bins-per-cell",
        );
        refused(&["eval", "heatmap", "--model", "r", "--dataset", "d", "--out", "h", "--smooth", "-1"], "--smooth");
        refused(&["eval", "heatmap", "--model", "r", "--dataset", "d", "--out", "h", "--unit", "cell"], "--unit");
        refused(&["plot", "j"], "--out");
        refused(&["plot", "j", "--out", "l.png", "--hist-out", "h.png"], "--dataset");
        refused(&["plot", "j", "--out", "l.png", "--dataset", "a.npz"], "--hist-out");
    }

    #[test]
    fn errors_name_the_flag_the_file_came_from() {
        let e = relabel(anyhow!("--input: no 'actions' array"), "--base-data a.npz");
        assert_eq!(e.to_string(), "--base-data a.npz: no 'actions' array");
        let e = relabel(UsageError("--input x: bad".into()).into(), "--dataset");
        assert!(e.downcast_ref::<UsageError>().is_some());
        let e = relabel(anyhow!("--model r: NOT_FOUND"), "--dataset");
        assert_eq!(e.to_string(), "--model r: NOT_FOUND");
    }

    #[test]
    fn subsets_and_rows_of_items() {
        use super::super::rewards::input::Windows;
        // 2 columns, rows 0..6 of one episode, windows of 3 rows at every row.
        let rows: Vec<f32> = (0..12).map(|v| v as f32).collect();
        let w = Windows { rows, dim: 2, horizon: 3, starts: vec![0, 1, 2, 3], stride: 1, episodes: 1 };
        let items = subset(Items::Windows(w), &[3, 1]);
        assert_eq!(items.len(), 2);
        assert_eq!(item_rows(&items, 0), &[6.0, 7.0, 8.0, 9.0, 10.0, 11.0]);
        assert_eq!(item_rows(&items, 1), &[2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        let array =
            Items::Array { key: "x".into(), values: (0..8).map(|v| v as f32).collect(), item_shape: vec![2, 2] };
        let items = subset(array, &[1]);
        assert_eq!((items.len(), item_rows(&items, 0)), (1, &[4.0, 5.0, 6.0, 7.0][..]));
    }

    #[test]
    fn arrays_of_any_numeric_dtype_are_read() {
        use relreward_toolkit::npz_write::NpzWriter;
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("maze.npz");
        let mut w = NpzWriter::create(&path).expect("create");
        w.add_bool("walls", &[2, 3], &[true, false, true, false, false, true]).expect("walls");
        w.add_f32("goals", &[3, 2], &[1.0, 2.0, 1.0, 2.0, 1.0, 2.0]).expect("goals");
        w.add_i64("other", &[2], &[4, 5]).expect("i64");
        w.finish().expect("finish");
        assert_eq!(walls_of(&path, true).expect("walls"), Some((2, 3, vec![true, false, true, false, false, true])));
        assert_eq!(constant_goal(&path).expect("goals"), Some((1.0, 2.0)));
        assert_eq!(read_numbers(&path, "other").expect("i64"), Some((vec![2], vec![4.0, 5.0])));
        assert_eq!(read_numbers(&path, "missing").expect("absent"), None);
        let varying = dir.path().join("varying.npz");
        let mut w = NpzWriter::create(&varying).expect("create");
        w.add_f32("goals", &[2, 2], &[1.0, 2.0, 3.0, 2.0]).expect("goals");
        w.finish().expect("finish");
        assert_eq!(constant_goal(&varying).expect("goals"), None);
        assert!(walls_of(&varying, true).is_err());
        assert_eq!(walls_of(&varying, false).expect("none"), None);
    }
}
