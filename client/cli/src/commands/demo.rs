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
//! then runs the same pipeline ([`super::extract::pipeline`]: upload or reuse, diffusion
//! models, rewards, evaluation, report) with its fixed sizes, and adds steering. Every step
//! runs the same code as the corresponding CLI command (parsed from argument lists and
//! dispatched in process), so it is also a script of commands a user can run one by one.
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
use relreward_client::pb;
use relreward_toolkit::maze::{self, GenerateConfig, Layout, LayoutName, Mode};
use serde_json::{Value, json};
use tokio_stream::StreamExt;

pub use super::extract::Size;
use super::extract::{Inputs, Sizes, Sizing, path_str, pipeline, stage, write_report};
use super::train::flags::AlgorithmArg;
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
    stage(ctx, &format!("generating {} data: base and {} expert datasets", name.as_str(), goals.len()));
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
        amortised: args.amortised.to_argv(),
    };
    let extracted = pipeline(ctx, &inputs, Sizing::Fixed(plan.sizes.clone())).await?;

    // ---- steering (the demo's own part): guided vs unguided sampling from the base model.
    let client = ctx.connect().await?;
    let mut rows = Vec::new();
    for (k, goal) in goals.iter().enumerate() {
        stage(ctx, &format!("steering with reward {} of {} (goal cell {},{})", k + 1, goals.len(), goal.0, goal.1));
        let steering = steer(&client, &extracted.base_model, &extracted.rewards[k], *goal, &plan, args.seed).await?;
        let mut row = extracted.rows[k].clone();
        row["goal_cell"] = json!([goal.0, goal.1]);
        row["reward_model"] = row["model"].clone();
        row["steering"] = steering;
        rows.push(row);
    }

    let recovered = rows.iter().filter(|r| r["goal_recovered"] == true).count();
    let accuracies: Vec<f64> = rows.iter().filter_map(|r| r["balanced_accuracy"].as_f64()).collect();
    let mean_accuracy = accuracies.iter().sum::<f64>() / accuracies.len().max(1) as f64;
    let steered = rows
        .iter()
        .filter(|r| r["steering"]["guided_near_goal"].as_f64() > r["steering"]["unguided_near_goal"].as_f64())
        .count();
    let summary = json!({
        "layout": name.as_str(),
        "size": format!("{size:?}").to_lowercase(),
        "seed": args.seed,
        "action_noise": plan.action_noise,
        "diffusion_steps": plan.sizes.diffusion_steps,
        "reward_steps": plan.sizes.reward_steps,
        "amortised_targets": args.amortised.to_argv().join(" "),
        "goals": rows,
        "goals_recovered": recovered,
        "goals_total": goals.len(),
        "mean_balanced_accuracy": mean_accuracy,
        "goals_steered": steered,
        "models": {"base": extracted.base_model, "experts": extracted.expert_models, "rewards": extracted.rewards},
        "elapsed_seconds": started.elapsed().as_secs_f64(),
        "out": path_str(&out),
    });
    // The pipeline's report (report.md / report.json), and the demo's summary with steering.
    write_report(&inputs, &extracted, started.elapsed().as_secs_f64(), json!({"demo": {"layout": name.as_str()}}))?;
    let table = summary_table(&summary);
    std::fs::write(out.join("summary.md"), &table)?;
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&summary)?)?;
    Ok(Report::ok(table, summary))
}

/// Final states of `n` samples within one cell (Euclidean, cell units) of `goal`.
const NEAR_GOAL: f64 = 1.0;

/// Fraction of `n` sampled trajectories whose last state lies near the goal.
async fn near_goal_fraction(
    client: &relreward_client::Client,
    base: &str,
    reward: &str,
    omega: f64,
    goal: (usize, usize),
    n: u32,
    seed: u64,
) -> Result<f64> {
    let request = pb::SampleRequest {
        model: base.into(),
        reward_model: if omega == 0.0 { String::new() } else { reward.into() },
        omega,
        n,
        seed: Some(seed),
        ..Default::default()
    };
    let mut stream = client.sample(request).await?;
    let (mut near, mut count) = (0usize, 0usize);
    while let Some(item) = stream.next().await {
        let item = item?;
        let x = item.x.as_ref().context("a sample without x")?;
        let values = relreward_client::tensor::decode_finite_f32(x)?;
        let d = *x.shape.last().context("a scalar sample")? as usize;
        // Rows are [action (2) | x, y, vx, vy]: the last row's position.
        let last = &values[values.len() - d..];
        let (px, py) = (f64::from(last[2]), f64::from(last[3]));
        if (px - goal.0 as f64).hypot(py - goal.1 as f64) <= NEAR_GOAL {
            near += 1;
        }
        count += 1;
    }
    Ok(near as f64 / count.max(1) as f64)
}

/// Steering: unguided vs guided sampling from the base model. Omega is picked on one seed (the
/// sweep) and the fractions are reported on another.
async fn steer(
    client: &relreward_client::Client,
    base: &str,
    reward: &str,
    goal: (usize, usize),
    plan: &Plan,
    seed: u64,
) -> Result<Value> {
    let (sweep_seed, report_seed) = (seed.wrapping_add(1000), seed.wrapping_add(2000));
    let mut sweep = Vec::new();
    for &omega in plan.omegas {
        let f = near_goal_fraction(client, base, reward, omega, goal, plan.samples / 2 + 1, sweep_seed).await?;
        sweep.push((omega, f));
    }
    let best = sweep.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1)).map_or(0.0, |(o, _)| o);
    let unguided = near_goal_fraction(client, base, reward, 0.0, goal, plan.samples, report_seed).await?;
    let guided = near_goal_fraction(client, base, reward, best, goal, plan.samples, report_seed).await?;
    Ok(json!({
        "omega": best,
        "sweep": sweep.iter().map(|(o, f)| json!({"omega": o, "near_goal": f})).collect::<Vec<_>>(),
        "samples": plan.samples,
        "near_goal_radius_cells": NEAR_GOAL,
        "unguided_near_goal": unguided,
        "guided_near_goal": guided,
    }))
}

/// The summary as a Markdown table.
fn summary_table(s: &Value) -> String {
    let mut t = format!(
        "relreward demo: {} ({} size, seed {}), {:.0} s\n\n| goal cell | reward max at | recovered | balanced accuracy | near goal unguided | near goal guided (omega) |\n|---|---|---|---|---|---|\n",
        s["layout"].as_str().unwrap_or(""),
        s["size"].as_str().unwrap_or(""),
        s["seed"],
        s["elapsed_seconds"].as_f64().unwrap_or(0.0)
    );
    for g in s["goals"].as_array().map(Vec::as_slice).unwrap_or(&[]) {
        let cell = |v: &Value| format!("{},{}", v[0], v[1]);
        t.push_str(&format!(
            "| {} | {} | {} | {:.3} | {:.3} | {:.3} ({}) |\n",
            cell(&g["goal_cell"]),
            cell(&g["argmax_cell"]),
            if g["goal_recovered"] == true { "yes" } else { "no" },
            g["balanced_accuracy"].as_f64().unwrap_or(f64::NAN),
            g["steering"]["unguided_near_goal"].as_f64().unwrap_or(f64::NAN),
            g["steering"]["guided_near_goal"].as_f64().unwrap_or(f64::NAN),
            g["steering"]["omega"],
        ));
    }
    t.push_str(&format!(
        "\ngoals recovered: {} of {}; mean balanced accuracy {:.3}; guidance moved more final states near the goal for {} of {} goals\n",
        s["goals_recovered"],
        s["goals_total"],
        s["mean_balanced_accuracy"].as_f64().unwrap_or(f64::NAN),
        s["goals_steered"],
        s["goals_total"]
    ));
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
