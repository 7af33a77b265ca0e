//! `relreward maze generate`: Maze2D datasets from the built-in generator
//! ([`relreward_toolkit::maze`]: D4RL's layouts, a point mass, a shortest-path waypoint
//! controller). Runs locally; no server is involved. The file has D4RL's keys and uploads with
//! `relreward dataset upload FILE --name NAME` (which leaves the extra `goals` and `walls` out).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use relreward_toolkit::maze::generate::{check_goal, generate_with_progress};
use relreward_toolkit::maze::{GenerateConfig, LayoutName, MazeData, MazeError, Mode, Physics};
use serde_json::{Value, json};

use super::output::{bars_visible, check_out_file, fmt_fixed, key_values};
use super::{Ctx, Report, UsageError};

/// Runs this long or longer get a progress bar (at well over a million transitions per second,
/// anything smaller is done in a moment).
const BAR_FROM_TRANSITIONS: u64 = 10_000_000;

#[derive(Debug, Subcommand)]
pub enum MazeCommand {
    /// Generate a Maze2D dataset (D4RL keys) with the built-in point mass and waypoint
    /// controller.
    Generate(GenerateArgs),
}

#[derive(Debug, Args)]
pub struct GenerateArgs {
    /// The maze: open (5 x 7 cells, episodes of 150 steps), umaze (5 x 5, 300), medium
    /// (8 x 8, 600) or large (9 x 12, 800).
    #[arg(long, value_enum)]
    pub layout: LayoutArg,
    /// base: uniform starts and goals, a new goal whenever one is reached; expert: uniform
    /// starts and one fixed goal, held once reached (the agent hovers there) as in D4RL. Either
    /// way episodes end only at the cap (timeouts; terminals are never set).
    #[arg(long, value_enum)]
    pub mode: ModeArg,
    /// Expert mode: the goal cell, counted from 0 at the top left [default: D4RL's goal cell:
    /// open 2,3; umaze 1,1; medium 6,6; large 7,9].
    #[arg(long, value_name = "ROW,COL", value_parser = parse_cell)]
    pub goal: Option<(usize, usize)>,
    /// Rows (transitions) to generate.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub transitions: u64,
    /// Seed of the generator: the same arguments give the same data.
    #[arg(long, value_name = "S", default_value_t = 0, allow_negative_numbers = true)]
    pub seed: u64,
    /// Standard deviation of Gaussian noise added to each action component before clipping.
    #[arg(long, value_name = "STD", default_value_t = 0.0, value_parser = parse_noise, allow_negative_numbers = true)]
    pub action_noise: f64,
    /// The point's dynamics: relreward (two 0.01 s substeps per row, the demo's data) or mujoco
    /// (one MuJoCo PointMaze step per row, gymnasium-robotics' / D4RL's point matched in free
    /// space: `relreward_toolkit::maze` docs, "Matched physics").
    #[arg(long, value_enum, default_value_t = PhysicsArg::Relreward)]
    pub physics: PhysicsArg,
    /// The .npz file to write (replaced if it exists).
    #[arg(long, value_name = "FILE.npz")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PhysicsArg {
    Relreward,
    Mujoco,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LayoutArg {
    Open,
    Umaze,
    Medium,
    Large,
}

impl From<LayoutArg> for LayoutName {
    fn from(arg: LayoutArg) -> Self {
        match arg {
            LayoutArg::Open => LayoutName::Open,
            LayoutArg::Umaze => LayoutName::Umaze,
            LayoutArg::Medium => LayoutName::Medium,
            LayoutArg::Large => LayoutName::Large,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ModeArg {
    Base,
    Expert,
}

/// `ROW,COL`: two non-negative integers.
fn parse_cell(text: &str) -> Result<(usize, usize), String> {
    let bad = || format!("'{text}': expected ROW,COL (two non-negative integers, e.g. 1,1)");
    let (row, col) = text.split_once(',').ok_or_else(bad)?;
    let row = row.trim().parse().map_err(|_| bad())?;
    let col = col.trim().parse().map_err(|_| bad())?;
    Ok((row, col))
}

fn parse_noise(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("'{text}': expected a finite number >= 0")),
    }
}

pub async fn run(ctx: &Ctx, command: MazeCommand) -> Result<Report> {
    match command {
        MazeCommand::Generate(args) => generate(ctx, args).await,
    }
}

/// The generator's configuration; arguments that cannot be run are [`UsageError`]s naming
/// their flag.
pub fn config_from_args(args: &GenerateArgs) -> Result<GenerateConfig> {
    let layout = LayoutName::from(args.layout).layout();
    let mode = match args.mode {
        ModeArg::Base => Mode::Base,
        ModeArg::Expert => Mode::Expert,
    };
    if let Some((row, col)) = args.goal {
        if mode == Mode::Base {
            return Err(UsageError(format!(
                "--goal {row},{col}: a goal applies to --mode expert only (base mode draws its own goals)"
            ))
            .into());
        }
        if let Err(e) = check_goal(&layout, row, col) {
            let map = layout.to_text().lines().collect::<Vec<_>>().join(" ");
            return Err(UsageError(format!(
                "--goal {row},{col}: {e}; pick a free cell 'O' (rows top to bottom, from 0): {map}"
            ))
            .into());
        }
    }
    let transitions = usize::try_from(args.transitions)
        .map_err(|_| UsageError(format!("--transitions {}: too many for this machine", args.transitions)))?;
    let mut config = GenerateConfig::new(layout, mode, transitions, args.seed);
    config.goal = args.goal;
    config.action_noise = args.action_noise;
    config.physics = match args.physics {
        PhysicsArg::Relreward => Physics::RELREWARD,
        PhysicsArg::Mujoco => Physics::MUJOCO,
    };
    Ok(config)
}

/// A transitions bar on stderr for long runs, hidden otherwise, with `--json` or off a terminal.
fn transitions_bar(json: bool, total: u64) -> ProgressBar {
    let visible = bars_visible(json) && total >= BAR_FROM_TRANSITIONS;
    let target = if visible { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() };
    let style = ProgressStyle::with_template(
        "{spinner} {elapsed_precise} [{wide_bar}] {human_pos}/{human_len} transitions {per_sec} ETA {eta} {msg}",
    )
    .map(|s| s.progress_chars("=> "))
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::with_draw_target(Some(total), target).with_style(style)
}

async fn generate(ctx: &Ctx, args: GenerateArgs) -> Result<Report> {
    let config = config_from_args(&args)?;
    check_out_file("--out", &args.out)?;
    let bar = transitions_bar(ctx.json, args.transitions);
    let worker_bar = bar.clone();
    let out = args.out.clone();
    let seed = config.seed;
    let action_noise = config.action_noise;
    let free_cells = config.layout.free_cells().len();
    let (data, generate_s, write_s) = tokio::task::spawn_blocking(move || -> Result<(MazeData, f64, f64)> {
        let started = Instant::now();
        let data =
            generate_with_progress(&config, |done| worker_bar.set_position(done as u64)).map_err(|e| match e {
                MazeError::TooLarge { transitions, .. } => {
                    UsageError(format!("--transitions {transitions}: {e}")).into()
                }
                e => anyhow::Error::new(e),
            })?;
        let generate_s = started.elapsed().as_secs_f64();
        worker_bar.set_message("writing");
        let written = Instant::now();
        data.write_npz(&out).with_context(|| format!("--out {}", out.display()))?;
        Ok((data, generate_s, written.elapsed().as_secs_f64()))
    })
    .await
    .context("generating the dataset crashed")??;
    bar.finish_and_clear();
    let physics = args.physics.to_possible_value().map(|v| v.get_name().to_owned()).unwrap_or_default();
    Ok(summary(&data, &args.out, free_cells, seed, action_noise, &physics, generate_s, write_s))
}

// One row of the report per argument: bundling them would only rename them.
#[allow(clippy::too_many_arguments)]
fn summary(
    data: &MazeData,
    out: &Path,
    free_cells: usize,
    seed: u64,
    action_noise: f64,
    physics: &str,
    generate_s: f64,
    write_s: f64,
) -> Report {
    let n = data.len();
    let rate = if generate_s > 0.0 { n as f64 / generate_s } else { f64::INFINITY };
    let goal_text = match data.goal_cell {
        Some((row, col)) => format!("cell ({row}, {col})"),
        None => "uniform, redrawn when reached".to_owned(),
    };
    // Expert mode counts episodes that reached the goal (once reached, it is held to the cap);
    // base mode counts goals reached (each then replaced by a new one).
    let reached_text = match data.mode {
        Mode::Expert if data.episodes > 0 => {
            format!(
                "in {} of {} episodes ({}%), then held to the cap",
                data.goals_reached,
                data.episodes,
                fmt_fixed(100.0 * data.goals_reached as f64 / data.episodes as f64, 1)
            )
        }
        _ => data.goals_reached.to_string(),
    };
    let fields = [
        ("layout", format!("{} ({} x {}, {free_cells} free cells)", data.layout, data.rows, data.cols)),
        ("mode", data.mode.as_str().to_owned()),
        ("goal", goal_text),
        ("transitions", n.to_string()),
        ("episodes", format!("{} (cap {} steps)", data.episodes, data.max_episode_steps)),
        ("goals reached", reached_text),
        ("seed", seed.to_string()),
        ("action noise", action_noise.to_string()),
        ("physics", physics.to_owned()),
        (
            "time",
            format!(
                "{} s generating ({:.0} transitions/s), {} s writing",
                fmt_fixed(generate_s, 3),
                rate,
                fmt_fixed(write_s, 3)
            ),
        ),
    ];
    let text = format!("wrote {}\n{}", out.display(), key_values(&fields, 2));
    let json = json!({
        "out": out.display().to_string(),
        "layout": data.layout,
        "rows": data.rows,
        "cols": data.cols,
        "mode": data.mode.as_str(),
        "goal": data.goal_cell.map_or(Value::Null, |(r, c)| json!([r, c])),
        "transitions": n,
        "episodes": data.episodes,
        "goals_reached": data.goals_reached,
        "max_episode_steps": data.max_episode_steps,
        "seed": seed,
        "action_noise": action_noise,
        "physics": physics,
        "generate_seconds": generate_s,
        "write_seconds": write_s,
        "transitions_per_second": if rate.is_finite() { json!(rate) } else { Value::Null },
    });
    Report::ok(text, json)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_and_noise_parse() {
        assert_eq!(parse_cell("1,1"), Ok((1, 1)));
        assert_eq!(parse_cell(" 7 , 9 "), Ok((7, 9)));
        for bad in ["1", "1,", "a,1", "-1,2", "1,2,3", ""] {
            assert!(parse_cell(bad).is_err(), "{bad}");
        }
        assert_eq!(parse_noise("0.1"), Ok(0.1));
        assert!(parse_noise("-0.1").is_err() && parse_noise("nan").is_err() && parse_noise("inf").is_err());
    }

    #[test]
    fn goals_are_checked_against_the_layout() {
        let args = |mode, goal| GenerateArgs {
            layout: LayoutArg::Umaze,
            mode,
            goal,
            transitions: 10,
            seed: 0,
            action_noise: 0.0,
            physics: PhysicsArg::Relreward,
            out: PathBuf::from("x.npz"),
        };
        let usage = |a: GenerateArgs| {
            let err = config_from_args(&a).expect_err("refused");
            assert!(err.downcast_ref::<UsageError>().is_some(), "{err}");
            err.to_string()
        };
        let wall = usage(args(ModeArg::Expert, Some((2, 2))));
        assert!(wall.starts_with("--goal 2,2: cell (2, 2) of the umaze layout is a wall"), "{wall}");
        assert!(wall.contains("##### #OOO# ###O# #OOO# #####"), "{wall}");
        assert!(usage(args(ModeArg::Expert, Some((9, 1)))).contains("outside the umaze layout"));
        assert!(usage(args(ModeArg::Base, Some((1, 1)))).contains("--mode expert only"));
        let ok = config_from_args(&args(ModeArg::Expert, Some((3, 3)))).expect("free cell");
        assert_eq!((ok.goal, ok.mode, ok.transitions), (Some((3, 3)), Mode::Expert, 10));
        assert_eq!(config_from_args(&args(ModeArg::Base, None)).expect("base").goal, None);
    }
}
