//! `relreward demo`: the paper's Maze2D result end to end against a running server.
//!
//! For one layout and K goals: generate base data (uniform goals) and one expert dataset per
//! goal with the built-in generator, upload them, train a base diffusion model and one expert
//! model per goal (all sharing one normalizer, computed over every dataset), extract a relative
//! reward per goal (Algorithm 1), then measure what the paper reports:
//! - goal recovery: the smoothed reward heatmap over base sub-trajectories peaks within one
//!   cell of the goal (`eval heatmap`);
//! - discriminability: held-out balanced accuracy of a logistic regression on the reward
//!   alone, base vs expert windows (`eval discriminate`);
//! - steering: guided sampling from the base model with the reward puts more final states near
//!   the goal than unguided sampling. Omega is chosen by a small sweep on one seed and reported
//!   on another, so the reported fraction is not the one it was selected on.
//!
//! The demo is the maze-generating front end of `relreward extract`: it writes the datasets,
//! then calls the same operation ([`relreward_cli::ops::extract::pipeline`]: upload or reuse,
//! diffusion models, rewards, evaluation, report) with its fixed sizes, and adds steering
//! ([`relreward_cli::ops::steer`]). Each step is the library function behind the CLI command
//! of the same name (`dataset upload`, `train`, `eval`, `job plot`, `sample`).
//! Outputs in `--out`: the datasets, heatmaps, histograms, loss curves, `report.md` /
//! `report.json` (the pipeline's) and `summary.md` / `summary.json` (with steering).
//!
//! Sizes ([`Size`]): `default` is scaled down to finish in minutes on a 2-core CPU (MLP
//! denoisers over horizon-16 windows, T = 20, a few thousand steps); `full` uses the paper's
//! (TemporalUnet dim 32, dim_mults (1, 4, 8), horizon 256, T = 100, 100k reward steps at batch
//! 256), which needs a GPU-sized budget; `tiny` only checks that the pipeline runs (tests).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use relreward_cli::ops::Progress;
use relreward_cli::ops::extract::report::{mean_balanced_accuracy, write_report};
use relreward_cli::ops::extract::sizes::{Size, Sizes, Sizing};
use relreward_cli::ops::extract::{ExpertResult, Inputs, path_str, pipeline};
use relreward_cli::ops::steer::{Steering, steer};
use relreward_toolkit::maze::{self, GenerateConfig, Layout, LayoutName, Mode};
use serde::Serialize;
use serde_json::json;

use super::train::flags::AlgorithmArg;
use super::watch::JobView;
use super::{Ctx, Report, UsageError};

/// `relreward demo` flags.
#[derive(Debug, Clone, Args)]
pub struct DemoArgs {
    /// The maze: open, umaze, medium or large.
    #[arg(long, default_value = "umaze")]
    pub layout: String,
    /// Number of goals (expert datasets and rewards), spread over the free cells starting at
    /// the layout's D4RL goal.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..=32))]
    pub goals: u32,
    /// Directory for datasets, pictures and the summary (created if missing).
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Run sizes: tiny, default, or the paper's (`--full` is the same as `--size full`).
    #[arg(long, value_enum, default_value_t = Size::Default)]
    pub size: Size,
    /// The paper's sizes (hours; for machines that have the time).
    #[arg(long, conflicts_with = "size")]
    pub full: bool,
    /// Seed of data generation, training and sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Standard deviation of the Gaussian noise added to the controller's actions in base and
    /// expert data (D4RL's `--noisy` generation uses 0.5) [default: 0.5].
    #[arg(long, value_name = "STD", value_parser = parse_action_noise)]
    pub action_noise: Option<f64>,
    /// Training steps of each diffusion model [default: the size's].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    pub diffusion_steps: Option<u64>,
    /// Training steps of each relative reward [default: the size's].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    pub reward_steps: Option<u64>,
    /// Passed on to every `train reward` (Algorithm 1's amortised targets; off unless given).
    #[command(flatten)]
    pub amortised: super::train::flags::AmortisedArgs,
}

fn parse_action_noise(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("'{s}' is not a standard deviation (a finite number >= 0)")),
    }
}

/// D4RL generates its Maze2D data with `--noisy`: N(0, 0.5^2) added to each action component
/// before clipping. The demo needs it, not only for fidelity: without noise the expert hovers
/// perfectly still at its goal, base windows (always moving) never look like that, and the
/// reward's maximum over base windows lands on the approach corridor instead of the goal
/// (docs/results.md measures both).
const D4RL_ACTION_NOISE: f64 = 0.5;

/// The knobs a size sets: the pipeline's [`Sizes`] (the maze's own, fixed: the demo's
/// horizon is the one `extract` derives from this generator's data, see
/// `relreward_toolkit::profile`) and what only the demo does.
#[derive(Debug, Clone)]
struct Plan {
    base_transitions: usize,
    expert_transitions: usize,
    sizes: Sizes,
    samples: u32,
    omegas: &'static [f64],
    action_noise: f64,
}

impl Plan {
    fn new(size: Size, layout: LayoutName) -> Self {
        let big = matches!(layout, LayoutName::Medium | LayoutName::Large);
        let mut sizes = Sizes::preset(size);
        match size {
            Size::Tiny => Self {
                base_transitions: 20_000,
                expert_transitions: 5_000,
                sizes,
                samples: 8,
                omegas: &[0.1],
                action_noise: D4RL_ACTION_NOISE,
            },
            Size::Default => Self {
                base_transitions: if big { 400_000 } else { 200_000 },
                expert_transitions: if big { 120_000 } else { 60_000 },
                sizes,
                samples: 128,
                omegas: &[0.03, 0.1, 0.3, 1.0],
                action_noise: D4RL_ACTION_NOISE,
            },
            Size::Full => {
                if layout == LayoutName::Open {
                    // The paper's open-maze reward: MLP (32,) over windows of 64.
                    (sizes.window, sizes.reward_hidden) = (64, vec![32]);
                }
                Self {
                    base_transitions: 1_000_000,
                    expert_transitions: 250_000,
                    sizes,
                    samples: 256,
                    omegas: &[0.01, 0.03, 0.1, 0.3, 1.0],
                    action_noise: D4RL_ACTION_NOISE,
                }
            }
        }
    }
}

/// K goal cells: the layout's D4RL goal first, then each next the free cell farthest from
/// those chosen (cell-centre distance), ties broken by position.
pub fn spread_goals(layout: &Layout, first: (usize, usize), k: usize) -> Vec<(usize, usize)> {
    let free = layout.free_cells();
    let mut chosen = vec![first];
    while chosen.len() < k.min(free.len()) {
        let dist = |c: &(usize, usize)| {
            chosen
                .iter()
                .map(|g| {
                    let (dr, dc) = (c.0 as f64 - g.0 as f64, c.1 as f64 - g.1 as f64);
                    dr.hypot(dc)
                })
                .fold(f64::INFINITY, f64::min)
        };
        let next = free
            .iter()
            .filter(|c| !chosen.contains(c))
            .max_by(|a, b| dist(a).total_cmp(&dist(b)).then(b.cmp(a)))
            .copied();
        match next {
            Some(c) => chosen.push(c),
            None => break,
        }
    }
    chosen
}

pub async fn run(ctx: &Ctx, args: DemoArgs) -> Result<Report> {
    let started = Instant::now();
    let name = LayoutName::from_name(&args.layout)
        .ok_or_else(|| UsageError(format!("--layout: '{}' is not one of open, umaze, medium, large", args.layout)))?;
    let size = if args.full { Size::Full } else { args.size };
    let mut plan = Plan::new(size, name);
    if let Some(noise) = args.action_noise {
        plan.action_noise = noise;
    }
    let layout = name.layout();
    let goals = spread_goals(&layout, name.default_goal(), args.goals as usize);
    if let Some(steps) = args.diffusion_steps {
        plan.sizes.diffusion_steps = steps;
    }
    if let Some(steps) = args.reward_steps {
        plan.sizes.reward_steps = steps;
    }

    let out = args.out.clone();
    let data_dir = out.join("data");
    std::fs::create_dir_all(&data_dir).with_context(|| format!("--out: cannot create {}", data_dir.display()))?;

    // ---- 1. data (the demo's own part); everything after it is `extract`'s pipeline.
    let progress = JobView::new(ctx.json, false);
    progress.stage(&format!("generating {} data: base and {} expert datasets", name.as_str(), goals.len()));
    let base_path = data_dir.join("base.npz");
    let mut config = GenerateConfig::new(layout.clone(), Mode::Base, plan.base_transitions, args.seed);
    config.action_noise = plan.action_noise;
    let base = maze::generate(&config)?;
    base.write_npz(&base_path)?;
    let mut expert_paths = Vec::new();
    for (k, &goal) in goals.iter().enumerate() {
        let mut config =
            GenerateConfig::new(layout.clone(), Mode::Expert, plan.expert_transitions, args.seed + 1 + k as u64);
        config.goal = Some(goal);
        config.action_noise = plan.action_noise;
        let path = data_dir.join(format!("expert-{}-{}.npz", goal.0, goal.1));
        maze::generate(&config)?.write_npz(&path)?;
        expert_paths.push(path);
    }
    let inputs = Inputs {
        base: base_path,
        experts: expert_paths,
        labels: goals.iter().map(|g| format!("goal-{}-{}", g.0, g.1)).collect(),
        // Cell (row, col) has its centre at position (row, col) in the generator's frame.
        goals: goals.iter().map(|g| Some((g.0 as f64, g.1 as f64))).collect(),
        walls: None,
        out: out.clone(),
        prefix: format!("demo-{}", name.as_str()),
        algorithm: AlgorithmArg::WithDataset,
        discriminator: false,
        seed: args.seed,
        amortised: args.amortised.clone(),
    };
    let client = ctx.connect().await?;
    let extracted = pipeline(&progress, &client, &inputs, Sizing::Fixed(plan.sizes.clone())).await?;

    // ---- steering (the demo's own part): guided vs unguided sampling from the base model.
    let mut rows = Vec::new();
    for (k, goal) in goals.iter().enumerate() {
        progress.stage(&format!("steering with reward {} of {} (goal cell {},{})", k + 1, goals.len(), goal.0, goal.1));
        let (base, reward) = (&extracted.base_model, &extracted.rewards[k]);
        let steering = steer(&client, base, reward, *goal, plan.omegas, plan.samples, args.seed).await?;
        let expert = &extracted.experts[k];
        let expert_model = &extracted.expert_models[k];
        rows.push(GoalRow { expert, goal_cell: *goal, reward_model: &expert.reward.model, expert_model, steering });
    }

    let recovered = rows.iter().filter(|r| r.expert.goal_recovered() == Some(true)).count();
    let steered = rows.iter().filter(|r| r.steering.steered()).count();
    let summary = Summary {
        layout: name.as_str(),
        size: format!("{size:?}").to_lowercase(),
        seed: args.seed,
        elapsed_seconds: started.elapsed().as_secs_f64(),
        goals_recovered: recovered,
        mean_balanced_accuracy: mean_balanced_accuracy(&extracted),
        goals_steered: steered,
        base_model: &extracted.base_model,
    };
    let json = json!({
        "layout": summary.layout,
        "size": summary.size,
        "seed": summary.seed,
        "action_noise": plan.action_noise,
        "diffusion_steps": plan.sizes.diffusion_steps,
        "reward_steps": plan.sizes.reward_steps,
        "amortised_targets": args.amortised.to_argv().join(" "),
        "goals": rows,
        "goals_recovered": summary.goals_recovered,
        "goals_total": goals.len(),
        "mean_balanced_accuracy": summary.mean_balanced_accuracy,
        "goals_steered": summary.goals_steered,
        "models": {"base": extracted.base_model, "experts": extracted.expert_models, "rewards": extracted.rewards},
        "elapsed_seconds": summary.elapsed_seconds,
        "out": path_str(&out),
    });
    // The pipeline's report (report.md / report.json), and the demo's summary with steering.
    write_report(&inputs, &extracted, started.elapsed().as_secs_f64(), Some(name.as_str()))?;
    let table = summary_table(&summary, &rows);
    std::fs::write(out.join("summary.md"), &table)?;
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&json)?)?;
    Ok(Report::ok(table, json))
}

/// One goal of the summary: its reward's evaluation (a row of report.json), the goal cell and
/// the steering.
#[derive(Debug, Serialize)]
struct GoalRow<'a> {
    #[serde(flatten)]
    expert: &'a ExpertResult,
    goal_cell: (usize, usize),
    reward_model: &'a str,
    /// The expert diffusion model the reward was extracted from (the base model is shared).
    expert_model: &'a str,
    steering: Steering,
}

/// What the summary table says besides its rows.
struct Summary<'a> {
    layout: &'static str,
    size: String,
    seed: u64,
    elapsed_seconds: f64,
    goals_recovered: usize,
    mean_balanced_accuracy: f64,
    goals_steered: usize,
    base_model: &'a str,
}

/// A number as report.json holds it: non-finite numbers are null, which the table shows as NaN.
fn finite_or_nan(v: f64) -> f64 {
    if v.is_finite() { v } else { f64::NAN }
}

/// The summary as a Markdown table.
fn summary_table(s: &Summary<'_>, rows: &[GoalRow<'_>]) -> String {
    let mut t = format!(
        "relreward demo: {} ({} size, seed {}), {:.0} s\n\n| goal cell | reward max at | recovered | balanced accuracy | near goal unguided | near goal guided (omega) |\n|---|---|---|---|---|---|\n",
        s.layout, s.size, s.seed, s.elapsed_seconds
    );
    for g in rows {
        // A missing maximum reads as JSON's null, as the table always showed it.
        let argmax = g.expert.argmax_cell().map_or("null,null".to_owned(), |(i, j)| format!("{i},{j}"));
        t.push_str(&format!(
            "| {},{} | {argmax} | {} | {:.3} | {:.3} | {:.3} ({}) |\n",
            g.goal_cell.0,
            g.goal_cell.1,
            if g.expert.goal_recovered() == Some(true) { "yes" } else { "no" },
            finite_or_nan(g.expert.reward.balanced_accuracy),
            finite_or_nan(g.steering.unguided_near_goal),
            finite_or_nan(g.steering.guided_near_goal),
            json!(g.steering.omega),
        ));
    }
    t.push_str(&format!(
        "\ngoals recovered: {} of {}; mean balanced accuracy {:.3}; guidance moved more final states near the goal for {} of {} goals\n",
        s.goals_recovered,
        rows.len(),
        finite_or_nan(s.mean_balanced_accuracy),
        s.goals_steered,
        rows.len()
    ));
    // The models' names (they carry fingerprints, so nobody can guess them): what `relreward
    // score`, `grad`, `sample` and the Python client take (README, "From Python").
    t.push_str("\n| goal cell | reward model | expert diffusion model |\n|---|---|---|\n");
    for g in rows {
        t.push_str(&format!("| {},{} | {} | {} |\n", g.goal_cell.0, g.goal_cell.1, g.reward_model, g.expert_model));
    }
    t.push_str(&format!("\nbase diffusion model: {}\n", s.base_model));
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn goals_spread_from_the_d4rl_goal() {
        let layout = LayoutName::Umaze.layout();
        let goals = spread_goals(&layout, (1, 1), 4);
        assert_eq!(goals[0], (1, 1));
        assert_eq!(goals[1], (3, 3), "the far corner of the U is farthest");
        assert_eq!(goals.len(), 4);
        let mut unique = goals.clone();
        unique.dedup();
        assert_eq!(unique.len(), 4);
        assert!(goals.iter().all(|&(r, c)| layout.is_free(r as i64, c as i64)));
    }
}
