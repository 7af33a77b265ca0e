//! `relreward eval discriminate|heatmap` and `relreward job plot`: the flags of the paper's
//! evaluation, and its reports. The evaluation itself (reading the files, scoring, the protocol,
//! the pictures) is [`relreward_cli::ops::evaluate`]'s; this module turns flags into its inputs
//! and its typed results into text and JSON.
//!
//! - `eval discriminate`: held-out (balanced) accuracy, AUC, the logistic coefficients and each
//!   class's mean reward; `--hist-out` draws both classes' histograms.
//! - `eval heatmap`: the maze heatmap, its maximum and whether it recovers the goal.
//! - `job plot`: the loss curve (and held-out loss) of a job; optionally a histogram of a
//!   reward over the windows of one or more datasets.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Subcommand};
use relreward_cli::ops::evaluate::discriminate::{self as disc, Discriminability, DiscriminateInput};
use relreward_cli::ops::evaluate::heatmap::{self as heat, Heatmap, HeatmapInput};
use relreward_cli::ops::evaluate::plot::{HistogramInput, JobPlot, JobPlotInput};
use relreward_cli::ops::evaluate::{self, DEFAULT_BATCH, Scoring};
use relreward_cli::output::{fmt_num, fmt_p, key_values, percent};
use relreward_toolkit::eval::discriminate::ClassSummary;
use relreward_toolkit::eval::heatmap::{RECOVERY_RADIUS, cell_of};
use serde_json::{Value, json};

pub use relreward_cli::ops::evaluate::heatmap::{Probe as ProbeArg, Unit as UnitArg};

use super::{Ctx, Report};

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
    #[arg(long, value_name = "N", default_value_t = DEFAULT_BATCH, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
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
    #[arg(long, value_name = "N", default_value_t = disc::DEFAULT_MAX_WINDOWS, value_parser = clap::value_parser!(u64).range(2..), allow_negative_numbers = true)]
    pub max_windows: u64,
    /// Winsorize the pooled scores at the P and 1 - P quantiles (the paper's 1%: 0.01).
    #[arg(long, value_name = "P", default_value_t = disc::DEFAULT_WINSORIZE, value_parser = parse_tail, allow_negative_numbers = true)]
    pub winsorize: f64,
    /// Also draw both classes' reward histograms (winsorized scores) to this PNG.
    #[arg(long, value_name = "FILE.png")]
    pub hist_out: Option<PathBuf>,
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
    #[arg(long, value_name = "N", default_value_t = heat::DEFAULT_BINS_PER_CELL, value_parser = clap::value_parser!(u32).range(1..=100), allow_negative_numbers = true)]
    pub bins_per_cell: u32,
    /// Mask bins crossed by fewer than K sub-trajectories.
    #[arg(long, value_name = "K", default_value_t = heat::DEFAULT_MIN_COUNT, allow_negative_numbers = true)]
    pub min_count: u32,
    /// What one sub-trajectory is.
    #[arg(long, value_enum, value_name = "UNIT", default_value_t = UnitArg::Auto)]
    pub unit: UnitArg,
    /// Items (H-row windows) scored at most: a seeded uniform subset.
    #[arg(long, value_name = "N", default_value_t = heat::DEFAULT_MAX_WINDOWS, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub max_windows: u64,
    /// Winsorize the sub-trajectory rewards at the P and 1 - P quantiles before scaling
    /// (docs/method.md section 4.1: the authors' heatmaps use 0.5%).
    #[arg(long, value_name = "P", default_value_t = heat::DEFAULT_WINSORIZE, value_parser = parse_tail, allow_negative_numbers = true)]
    pub winsorize: f64,
    /// Gaussian smoothing before the arg-max, standard deviation in cells (0: none).
    #[arg(long, value_name = "SIGMA", default_value_t = heat::DEFAULT_SMOOTH, value_parser = parse_non_negative, allow_negative_numbers = true)]
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

impl ScoringArgs {
    fn scoring(&self) -> Scoring {
        Scoring { model: self.model.clone(), t: self.t, stride: self.stride, seed: self.seed, batch: self.batch }
    }
}

// ---------------------------------------------------------------------------------------------
// eval discriminate

async fn discriminate(ctx: &Ctx, args: DiscriminateArgs) -> Result<Report> {
    let input = DiscriminateInput {
        scoring: args.scoring.scoring(),
        base_data: args.base_data,
        expert_data: args.expert_data,
        max_windows: args.max_windows,
        winsorize: args.winsorize,
        hist_out: args.hist_out,
    };
    input.check()?;
    let client = ctx.connect().await?;
    let measured = disc::discriminate(ctx, &client, &input).await?;
    Ok(discriminate_report(&input, &measured))
}

fn discriminate_report(input: &DiscriminateInput, measured: &Discriminability) -> Report {
    let (s, d) = (&input.scoring, &measured.result);
    let (base, expert) = (&measured.base, &measured.expert);
    let m = &d.model;
    let (w_raw, b_raw) = m.raw_coefficients();
    let class_json = |c: &ClassSummary, available: usize, source: &relreward_cli::ops::items::ItemsSource| {
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
        "base_data": input.base_data.display().to_string(),
        "expert_data": input.expert_data.display().to_string(),
        "seed": s.seed,
        "max_windows": input.max_windows,
        "winsorize": { "p": input.winsorize, "limits": [d.limits.0, d.limits.1] },
        "train_fraction": measured.protocol.train_fraction,
        "base": class_json(&d.base, base.available, &base.source),
        "expert": class_json(&d.expert, expert.available, &expert.source),
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
        "balanced_accuracy": measured.balanced_accuracy(),
        "expert_scores_higher": measured.expert_scores_higher(),
        "hist_out": input.hist_out.as_ref().map(|p| p.display().to_string()),
    });
    let class_text = |c: &ClassSummary, available: usize| {
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
            format!("at {}% per tail: [{}, {}]", fmt_p(input.winsorize), fmt_num(d.limits.0), fmt_num(d.limits.1)),
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
    if let Some(out) = &input.hist_out {
        fields.push(("histogram", out.display().to_string()));
    }
    Report::ok(key_values(&fields, 0), json)
}

/// `1 point`, `4 points`.
fn points(n: usize) -> String {
    format!("{n} point{}", if n == 1 { "" } else { "s" })
}

// ---------------------------------------------------------------------------------------------
// eval heatmap

async fn heatmap(ctx: &Ctx, args: HeatmapArgs) -> Result<Report> {
    let input = HeatmapInput {
        scoring: args.scoring.scoring(),
        dataset: args.dataset,
        out: args.out,
        goal: args.goal,
        goal_from: args.goal_from,
        walls: args.walls,
        bins_per_cell: args.bins_per_cell,
        min_count: args.min_count,
        unit: args.unit,
        max_windows: args.max_windows,
        winsorize: args.winsorize,
        smooth: args.smooth,
        xy_columns: args.xy_columns,
        probe: args.probe,
    };
    input.check()?;
    let client = ctx.connect().await?;
    let map = heat::heatmap(ctx, &client, &input).await?;
    Ok(heatmap_report(&input, &map))
}

fn heatmap_report(input: &HeatmapInput, map: &Heatmap) -> Report {
    let s = &input.scoring;
    let grid = &map.grid;
    let unit_name = map.unit_name();
    let (unit_rows, horizon, stride, covered) = (map.unit_rows, map.horizon, map.stride, map.bins_covered);
    let argmax_json = map.argmax.map_or(Value::Null, |((x, y), v)| {
        let (i, j) = cell_of(x, y);
        json!({ "x": x, "y": y, "cell": [i, j], "value": v })
    });
    let json = json!({
        "model": s.model,
        "dataset": input.dataset.display().to_string(),
        "t": s.t,
        "seed": s.seed,
        "out": input.out.display().to_string(),
        "unit": unit_name,
        "unit_rows": unit_rows,
        "horizon": horizon,
        "stride": stride,
        "xy_columns": [map.xy_columns.0, map.xy_columns.1],
        "items_available": map.items_available,
        "items_scored": map.items_scored,
        "sub_trajectories": map.sub_trajectories,
        "winsorize": { "p": input.winsorize, "limits": [map.limits.0, map.limits.1] },
        "scale": { "min": map.scale.0, "max": map.scale.1 },
        "grid": {
            "rows": grid.rows,
            "cols": grid.cols,
            "row0": grid.row0,
            "col0": grid.col0,
            "bins_per_cell": grid.bins_per_cell,
            "walls": map.walls,
        },
        "bins": grid.len(),
        "bins_covered": covered,
        "min_count": map.min_count,
        "probe": input.probe.name(),
        "states_outside": map.states_outside,
        "smooth_sigma_cells": input.smooth,
        "argmax": argmax_json,
        "goal": map.goal.as_ref().map(|g| json!({ "x": g.position.0, "y": g.position.1, "source": g.source })),
        "distance_cells": map.distance_cells,
        "distance_euclidean": map.distance_euclidean,
        "recovery_radius_cells": RECOVERY_RADIUS,
        "goal_recovered": map.goal_recovered,
    });
    let mut fields = vec![
        ("model", format!("{} (t = {})", s.model, s.t)),
        (
            "sub-trajectories",
            format!(
                "{} {unit_name}s of {unit_rows} rows, from {} of {} items (H = {horizon}{})",
                map.sub_trajectories,
                map.items_scored,
                map.items_available,
                stride.map_or_else(String::new, |s| format!(", stride {s}"))
            ),
        ),
        (
            "rewards",
            format!(
                "winsorized at {}% per tail [{}, {}], scaled to [0, 1]",
                fmt_p(input.winsorize),
                fmt_num(map.limits.0),
                fmt_num(map.limits.1)
            ),
        ),
        (
            "grid",
            format!(
                "{} x {} cells{}, {} bins per cell: {covered} of {} bins with >= {} sub-trajectories",
                grid.rows,
                grid.cols,
                if map.walls { " (walls)" } else { " (covering the data)" },
                grid.bins_per_cell,
                grid.len(),
                map.min_count
            ),
        ),
    ];
    if map.states_outside > 0 {
        fields.push(("outside", format!("{} states outside the grid", map.states_outside)));
    }
    fields.push((
        "maximum",
        map.argmax.map_or_else(
            || "- (no bin has enough sub-trajectories)".to_owned(),
            |((x, y), v)| {
                let (i, j) = cell_of(x, y);
                format!(
                    "x = {x:.2}, y = {y:.2} (cell {i}, {j}); smoothed value {} (sigma {} cells)",
                    fmt_num(v),
                    input.smooth
                )
            },
        ),
    ));
    fields.push((
        "goal",
        map.goal.as_ref().map_or_else(
            || "- (pass --goal X,Y or --goal-from FILE)".to_owned(),
            |g| format!("x = {:.2}, y = {:.2} ({})", g.position.0, g.position.1, g.source),
        ),
    ));
    if let (Some(d), Some(r)) = (map.distance_cells, map.goal_recovered) {
        fields.push(("distance", format!("{d:.2} cells (Chebyshev)")));
        fields.push(("goal recovered", format!("{} (within {} cell)", if r { "yes" } else { "no" }, RECOVERY_RADIUS)));
    }
    fields.push(("heatmap", input.out.display().to_string()));
    Report::ok(key_values(&fields, 0), json)
}

// ---------------------------------------------------------------------------------------------
// job plot

/// `relreward job plot ID --out loss.png [--hist-out rewards.png [--model R] --dataset FILE..]`.
pub async fn job_plot(ctx: &Ctx, args: JobPlotArgs) -> Result<Report> {
    let histogram = args.hist_out.clone().map(|out| HistogramInput {
        out,
        model: args.model.clone(),
        datasets: args.datasets.clone(),
        t: args.t,
        stride: args.stride,
        max_windows: args.max_windows,
        seed: args.seed,
    });
    let input = JobPlotInput { id: args.id.clone(), out: args.out.clone(), histogram };
    input.check()?;
    let client = ctx.connect().await?;
    let plot = evaluate::plot::job_plot(ctx, &client, &input).await?;
    Ok(job_plot_report(&input, &plot))
}

fn job_plot_report(input: &JobPlotInput, plot: &JobPlot) -> Report {
    let (loss, eval) = (&plot.loss, &plot.eval_loss);
    let (kind, state, log) = (plot.kind, plot.state, plot.log_scale);
    let last = loss[loss.len() - 1];
    let mut fields = vec![
        ("job", format!("{} ({kind}, {state})", input.id)),
        ("loss", format!("{}, steps {}..{}, last {}", points(loss.len()), loss[0].0, last.0, fmt_num(last.1))),
        ("held-out loss", if eval.is_empty() { "-".to_owned() } else { points(eval.len()) }),
        ("scale", if log { "log".to_owned() } else { "linear".to_owned() }),
        ("plot", input.out.display().to_string()),
    ];
    let mut hist_json = Value::Null;
    if let (Some(h), Some(drawn)) = (&input.histogram, &plot.histogram) {
        let model = &drawn.model;
        fields.push(("histogram", format!("{} ({model} over {} dataset(s))", h.out.display(), drawn.datasets.len())));
        let per_dataset: Vec<Value> = drawn
            .datasets
            .iter()
            .map(|d| {
                json!({
                    "dataset": d.dataset.display().to_string(),
                    "windows_available": d.windows_available,
                    "windows": d.windows,
                    "mean": d.summary.map(|s| s.mean),
                    "std": d.summary.map(|s| s.std),
                })
            })
            .collect();
        hist_json = json!({
            "out": h.out.display().to_string(),
            "model": model,
            "t": h.t,
            "datasets": per_dataset,
        });
    }
    let json = json!({
        "job": input.id,
        "kind": kind,
        "state": state,
        "out": input.out.display().to_string(),
        "log_scale": log,
        "loss_points": loss.len(),
        "eval_loss_points": eval.len(),
        "first_step": loss[0].0,
        "last_step": last.0,
        "last_loss": last.1,
        "histogram": hist_json,
    });
    Report::ok(key_values(&fields, 0), json)
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
