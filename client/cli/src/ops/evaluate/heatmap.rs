//! The Maze2D reward heatmap and goal recovery (paper Figure 2 and appendix): the
//! sub-trajectories of a (base) dataset scored, winsorized (0.5%) and min-max scaled, averaged
//! per 2D bin (10 per maze cell) over the positions they pass through, sparse bins masked, the
//! map drawn with walls and goal, and whether the smoothed maximum lies within one cell of the
//! goal. With [`Probe::AtRest`] the items are windows holding the agent still at each bin's
//! centre instead: the reward of staying there.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use clap::ValueEnum;
use relreward_client::{Client, pb};
use relreward_toolkit::eval::heatmap::{self, Accumulator, Grid};
use relreward_toolkit::eval::plot::{self, HeatmapPicture};
use relreward_toolkit::eval::stats::{Rng, min_max_scale, winsorize};
use relreward_toolkit::npz;

use super::{Scoring, Walls, constant_goal, file_name, item_rows, load_items, obs_dim, score_subset, walls_of};
use crate::UsageError;
use crate::ops::Progress;
use crate::ops::items::Items;
use crate::output::check_out_file;

/// Bins along each side of a maze cell, unless asked otherwise.
pub const DEFAULT_BINS_PER_CELL: u32 = 10;
/// Bins crossed by fewer sub-trajectories are masked.
pub const DEFAULT_MIN_COUNT: u32 = 5;
/// Items scored at most, unless asked otherwise.
pub const DEFAULT_MAX_WINDOWS: u64 = 50_000;
/// The authors' heatmaps winsorize at 0.5% per tail.
pub const DEFAULT_WINSORIZE: f64 = 0.005;
/// Gaussian smoothing before the arg-max, in cells.
pub const DEFAULT_SMOOTH: f64 = 0.2;

/// What a heatmap attributes rewards to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Unit {
    /// `window` for windowed rewards, else `item`.
    Auto,
    /// Each scored H-row item (rho, the mean over its windows) is one sub-trajectory.
    Item,
    /// Each h-row window of a windowed reward (its own value, Score's per-window output) is
    /// one sub-trajectory: the network's own input, the finest the reward resolves.
    Window,
}

/// What is scored at each position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Probe {
    // The dataset's sub-trajectories passing there (the paper's heatmap). (Plain comments:
    // `--probe`'s help describes both values.)
    Base,
    // A window holding the agent still at each bin's centre: the reward of staying there.
    AtRest,
}

impl Probe {
    pub fn name(self) -> &'static str {
        match self {
            Self::Base => "base",
            Self::AtRest => "at-rest",
        }
    }
}

/// What to draw.
#[derive(Debug, Clone)]
pub struct HeatmapInput {
    pub scoring: Scoring,
    /// Trajectories to score (the base dataset), or an .npz with x [B, H, D] and `xy_columns`.
    pub dataset: PathBuf,
    /// Where to draw the heatmap (PNG).
    pub out: PathBuf,
    /// The true goal position (else `goal_from`'s goals, else the dataset's when constant).
    pub goal: Option<(f64, f64)>,
    /// Take the goal from this file's constant `goals` array.
    pub goal_from: Option<PathBuf>,
    /// Maze walls (else the dataset's; without walls the grid covers the data).
    pub walls: Option<PathBuf>,
    pub bins_per_cell: u32,
    pub min_count: u32,
    pub unit: Unit,
    pub max_windows: u64,
    pub winsorize: f64,
    /// Gaussian smoothing before the arg-max, standard deviation in cells (0: none).
    pub smooth: f64,
    /// Columns of a row holding the position (else the first two observation coordinates).
    pub xy_columns: Option<(usize, usize)>,
    pub probe: Probe,
}

impl HeatmapInput {
    /// The paper's heatmap of `dataset` with default sizes.
    pub fn new(scoring: Scoring, dataset: PathBuf, out: PathBuf) -> Self {
        Self {
            scoring,
            dataset,
            out,
            goal: None,
            goal_from: None,
            walls: None,
            bins_per_cell: DEFAULT_BINS_PER_CELL,
            min_count: DEFAULT_MIN_COUNT,
            unit: Unit::Auto,
            max_windows: DEFAULT_MAX_WINDOWS,
            winsorize: DEFAULT_WINSORIZE,
            smooth: DEFAULT_SMOOTH,
            xy_columns: None,
            probe: Probe::Base,
        }
    }

    /// The checks that need no server (a usage error before connecting); whether the dataset
    /// holds trajectories.
    pub fn check(&self) -> Result<bool> {
        check_out_file("--out", &self.out)?;
        let dataset = &self.dataset;
        let is_trajectories =
            npz::detect_kind(dataset).map_err(|e| anyhow!("--dataset: {e}"))? == pb::DatasetKind::Trajectories;
        if !is_trajectories && self.xy_columns.is_none() {
            return Err(UsageError(format!(
                "--dataset {}: holds items x [B, H, D], not trajectories; say which columns hold the position with \
                 --xy-columns I,J",
                dataset.display()
            ))
            .into());
        }
        Ok(is_trajectories)
    }
}

/// The goal a heatmap is measured against, and where it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct Goal {
    pub position: (f64, f64),
    /// `--goal`, or `goals of FILE`.
    pub source: String,
}

/// What [`heatmap`] drew and measured.
#[derive(Debug, Clone)]
pub struct Heatmap {
    /// Each sub-trajectory is one window of a windowed reward (else one item).
    pub per_window: bool,
    /// Rows of one sub-trajectory.
    pub unit_rows: usize,
    pub horizon: u64,
    pub stride: Option<u64>,
    pub xy_columns: (usize, usize),
    pub items_available: usize,
    pub items_scored: usize,
    pub sub_trajectories: usize,
    /// Winsorization limits of the sub-trajectory rewards, then their min and max.
    pub limits: (f64, f64),
    pub scale: (f64, f64),
    pub grid: Grid,
    /// Whether the grid is the maze's (walls known) rather than covering the data.
    pub walls: bool,
    pub bins_covered: usize,
    /// Bins crossed by fewer sub-trajectories are masked (1 at rest: each bin probed once).
    pub min_count: u32,
    pub states_outside: usize,
    /// The smoothed maximum: its bin centre and value.
    pub argmax: Option<((f64, f64), f64)>,
    pub goal: Option<Goal>,
    /// Chebyshev and Euclidean distances of the maximum from the goal, in cells.
    pub distance_cells: Option<f64>,
    pub distance_euclidean: Option<f64>,
    /// The maximum within [`heatmap::RECOVERY_RADIUS`] cells of the goal.
    pub goal_recovered: Option<bool>,
}

impl Heatmap {
    /// The maze cell (row, column) of the smoothed maximum.
    pub fn argmax_cell(&self) -> Option<(i64, i64)> {
        self.argmax.map(|((x, y), _)| heatmap::cell_of(x, y))
    }

    /// `window` or `item`.
    pub fn unit_name(&self) -> &'static str {
        if self.per_window { "window" } else { "item" }
    }
}

/// `Probe::AtRest`: one `[horizon, dim]` item per bin of `grid` where the agent can be (its
/// square of half side [`relreward_toolkit::maze::RADIUS`] in free cells), each row the bin's
/// centre in columns `cx, cy`, zero in every other column (the action and the velocities).
/// Refused unless every observation column (from `act` on) is the position or a velocity
/// (`velocities`, observation indices): a held state must be fully specified.
fn at_rest_items(
    grid: &Grid,
    walls: &Walls,
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

/// The goal: `--goal`, else `--goal-from`'s constant goals (required), else the dataset's.
fn find_goal(input: &HeatmapInput) -> Result<Option<Goal>> {
    let found = |g: Option<(f64, f64)>, path: &Path| {
        g.map(|position| Goal { position, source: format!("goals of {}", path.display()) })
    };
    Ok(match (&input.goal, &input.goal_from) {
        (Some(g), _) => Some(Goal { position: *g, source: "--goal".to_owned() }),
        (None, Some(path)) => match constant_goal(path)? {
            Some(g) => found(Some(g), path),
            None => bail!("--goal-from {}: no 'goals' array with one constant goal", path.display()),
        },
        (None, None) => found(constant_goal(&input.dataset)?, &input.dataset),
    })
}

/// Scores the dataset's sub-trajectories (or the maze at rest), draws the heatmap to
/// `input.out` and measures goal recovery.
pub async fn heatmap(progress: &dyn Progress, client: &Client, input: &HeatmapInput) -> Result<Heatmap> {
    let is_trajectories = input.check()?;
    let s = &input.scoring;
    let dataset = &input.dataset;
    let model = client.get_model(&s.model).await.with_context(|| format!("--model {}", s.model))?;
    let info = model.reward.clone().unwrap_or_default();
    let horizon = info.input_shape.first().copied().unwrap_or(1).max(1);
    let window = u64::from(info.window);
    let windowed = window > 0 && window < horizon && horizon % window == 0;
    let per_window = match input.unit {
        Unit::Auto => windowed,
        Unit::Item => false,
        Unit::Window if windowed || window == horizon => windowed,
        Unit::Window => {
            return Err(UsageError(format!(
                "--unit window: model '{}' is not a windowed reward ({}); use --unit item",
                s.model, info.architecture
            ))
            .into());
        }
    };
    let stride = s.stride.or(is_trajectories.then(|| if per_window { horizon } else { (horizon / 4).max(1) }));
    let items = load_items(client, &s.model, dataset, "--dataset", stride).await?;
    let dim = items.item_shape().get(1).copied().unwrap_or(0) as usize;
    let (cx, cy) = match input.xy_columns {
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
    let walls = match &input.walls {
        Some(path) => walls_of(path, true)?,
        None => walls_of(dataset, false)?,
    };
    let goal = find_goal(input)?;

    let (items, min_count) = match (input.probe, &walls) {
        (Probe::Base, _) => (items, input.min_count),
        (Probe::AtRest, None) => {
            return Err(
                UsageError("--probe at-rest: needs the maze's walls (--walls, or walls in --dataset)".into()).into()
            );
        }
        (Probe::AtRest, Some(w)) => {
            if !is_trajectories {
                return Err(UsageError("--probe at-rest: --dataset must hold trajectories".into()).into());
            }
            let path = dataset.clone();
            let velocities = tokio::task::spawn_blocking(move || -> Result<Vec<usize>> {
                Ok(relreward_toolkit::trajectories::Trajectories::from_npz(&path)?.velocity_columns())
            })
            .await
            .context("reading crashed")??;
            let grid = Grid::of_maze(w.0, w.1, input.bins_per_cell as usize);
            let act = dim - obs_dim(dataset)?;
            // Each bin is probed once, by one item (whose windows all land in it).
            (at_rest_items(&grid, w, (cx, cy), act, dim, horizon as usize, &velocities)?, 1)
        }
    };
    let mut rng = Rng::new(s.seed);
    let idx = rng.subset(items.len(), input.max_windows as usize);
    let scored = score_subset(progress, client, s, items, &idx, "--dataset", per_window).await?;
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
    let limits = winsorize(&mut values, input.winsorize);
    let scale = min_max_scale(&mut values);
    let points = |&(k, first, rows, _): &(usize, usize, usize, f64)| {
        item_rows(items, k)[first * dim..(first + rows) * dim]
            .chunks_exact(dim)
            .map(move |r| (f64::from(r[cx]), f64::from(r[cy])))
    };
    let bins_per_cell = input.bins_per_cell as usize;
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
    let smoothed = heatmap::smooth(&grid, &means, input.smooth * bins_per_cell as f64);
    let best = heatmap::argmax(&smoothed).map(|(k, v)| (grid.bin_centre(k), v));
    let goal_at = goal.as_ref().map(|g| g.position);
    let recovered = match (best, goal_at) {
        (Some((pos, _)), Some(g)) => Some(heatmap::goal_recovered(pos, g)),
        _ => None,
    };
    let distance = best.zip(goal_at).map(|((pos, _), g)| heatmap::chebyshev(pos, g));
    let euclidean = best.zip(goal_at).map(|((pos, _), g)| ((pos.0 - g.0).powi(2) + (pos.1 - g.1).powi(2)).sqrt());

    let picture = HeatmapPicture {
        title: format!("reward {} over {} (t = {})", s.model, file_name(dataset), s.t),
        grid,
        values: &means,
        walls: walls.as_ref().map(|(r, c, w)| (*r, *c, w.as_slice())),
        goal: goal_at,
        argmax: best.map(|(pos, _)| pos),
        scale_label: "mean reward per bin (scaled to [0, 1])".to_owned(),
    };
    plot::heatmap_png(&input.out, &picture)?;

    Ok(Heatmap {
        per_window,
        unit_rows,
        horizon,
        stride,
        xy_columns: (cx, cy),
        items_available: scored.available,
        items_scored: items.len(),
        sub_trajectories: units.len(),
        limits,
        scale,
        grid,
        walls: walls.is_some(),
        bins_covered: covered,
        min_count,
        states_outside: acc.outside,
        argmax: best,
        goal,
        distance_cells: distance,
        distance_euclidean: euclidean,
        goal_recovered: recovered,
    })
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
}
