//! The built-in Maze2D data generator: D4RL's point-mass mazes, a shortest-path waypoint
//! controller, and datasets with D4RL's keys (`relreward maze generate`).
//!
//! Module map:
//! - this file: [`Layout`] (the four D4RL layouts and a parser for others), the geometry
//!   ([`cell_of`]) and every constant of the simulation;
//! - [`sim`]: [`PointMass`], the dynamics and the wall collisions;
//! - [`controller`]: [`Planner`] (breadth-first shortest paths over free cells, cached per goal
//!   cell) and [`Controller`] (waypoints at cell centres followed with a PD law);
//! - [`generate`](mod@generate): [`generate()`] a dataset from a [`GenerateConfig`] into
//!   [`MazeData`], and [`MazeData::write_npz`] (through [`crate::npz_write`]);
//! - [`rng`]: [`Rng`], the generator's own seedable stream (xoshiro256++ seeded by SplitMix64).
//!
//! Nothing here links libtorch or talks to a server.
//!
//! # Conventions
//!
//! **Layouts.** A layout is a grid of cells, `#` a wall and `O` free, rows listed top to bottom
//! (docs/method.md section 5). Cells outside the grid count as walls. The four built-in layouts
//! and their episode length caps are `open` (5 x 7, cap 150), `umaze` (5 x 5, cap 300),
//! `medium` (8 x 8, cap 600) and `large` (9 x 12, cap 800).
//!
//! **Geometry** (D4RL's convention). Cell (row i, col j) is the unit square centred at
//! (x, y) = (i, j): x grows with the row index, y with the column index. The cell of a position
//! is [`cell_of`]: both coordinates rounded to the nearest integer, halves away from zero
//! (`f64::round`). A position is free iff its cell is free. Walls are solid unit squares.
//!
//! **State and action.** The observation is `[x, y, vx, vy]`; the action `a` in `[-1, 1]^2` is a
//! force, one component per axis.
//!
//! **Dynamics** ([`sim`]). One step (one dataset row) holds the action for [`FRAME_SKIP`] = 2
//! substeps of [`DT`] = 0.01 s of semi-implicit Euler: `v += DT * (FORCE_GAIN * a - DAMPING *
//! v)`, then `p += DT * v` (with the collisions below), with [`FORCE_GAIN`] = 25 (acceleration
//! per unit of action) and [`DAMPING`] = 0.25 per second: D4RL's MuJoCo point (gear 100 on a
//! sphere of about 4.2 kg, joint damping 1, timestep 0.01). The frame skip of 2 is ours: the PD
//! law below brakes into every waypoint with a time constant of about `D_GAIN / P_GAIN` = 0.1 s
//! whatever the force, so a cell takes about 0.27 s, i.e. about 14 steps. The longest shortest
//! path of each layout then takes at most about half its cap (`open` 72 of 150 steps, `umaze`
//! 76 of 300, `medium` 151 of 600, `large` 248 of 800); one substep per step would need all
//! 150 steps of `open`.
//!
//! **Matched physics** ([`Physics::MUJOCO`], `relreward maze generate --physics mujoco`).
//! gymnasium-robotics' PointMaze (the MuJoCo model D4RL's maze2d uses: `point.xml`, timestep
//! 0.01, frame skip 1, a sphere of radius 0.1 and density 1000, so mass 4.19, gear 100, joint
//! damping 1, MuJoCo's Euler integrator, velocities clipped to [-5, 5] before each step) is,
//! in free space, exactly: `v = clip(v, -5, 5)`, `v = (v + DT * G * a) / (1 + DT * D)` (MuJoCo's
//! Euler integrates joint damping implicitly), `p += DT * v`, with `G = 100 / 4.19 = 23.87`
//! and `D = 1 / 4.19 = 0.2387`, one step per row. [`Physics::MUJOCO`] is that, with the wall
//! collisions below (MuJoCo's contacts are soft: the point sinks up to about 0.03 into a wall
//! and springs back, where ours stops at the face). The test `tests/maze_vs_mujoco.rs` drives
//! both with the same actions against a recording of MuJoCo (`tests/data/pointmaze_mujoco.npz`):
//! free space within 1e-5 per row, a wall contact within 0.035. The default stays
//! [`Physics::RELREWARD`] (two substeps, explicit damping): the demo's sizes and its measured
//! results (docs/results.md) were made on it and each layout's cap assumes its speed (one
//! substep per row would need all 150 steps of `open` for its longest path); it moves about
//! 2.1 times as far per row as MuJoCo's point (0.068 vs 0.031 cells on umaze base data).
//!
//! **Collisions** (every substep). The agent is a disc of radius [`RADIUS`] = 0.1, collided as
//! its bounding square (which contains the disc, so the disc never touches a wall either). The
//! position moves along x first: if the square would overlap a wall cell, x is clamped so the
//! square rests against the wall face ([`CONTACT_GAP`] short of it) and vx is set to zero; then
//! the same along y, from the updated x. The sweep checks every cell crossed, so no speed
//! tunnels through a wall.
//!
//! **Controller** ([`controller`]). A breadth-first search over the 4-connected free cells
//! gives the shortest path from the agent's cell to the goal's cell (ties broken in the fixed
//! neighbour order up, down, left, right: row - 1, row + 1, col - 1, col + 1). The waypoints are
//! the centres of the cells after the agent's own, and the goal position itself in place of
//! the goal cell's centre. The action is `a = P_GAIN * (waypoint - pos) - D_GAIN * vel`
//! ([`P_GAIN`] = 10, [`D_GAIN`] = 1), clipped to `[-1, 1]` per component; the controller moves
//! to the next waypoint when within [`WAYPOINT_RADIUS`] = 0.1 of the current one. Should the
//! agent leave the two cells it is travelling between (an overshoot), the path is planned
//! again from the cell it is in.
//!
//! **Goals.** A goal is reached when the agent is within [`GOAL_RADIUS`] = 0.5 of it (D4RL's
//! sparse-reward radius), checked on the state after each step.
//!
//! **Random positions.** A uniform position is a uniform free cell, then a uniform point of
//! that cell's square shrunk by `RADIUS + CONTACT_GAP` on every side, so the disc starts clear
//! of every wall. Drawn goals and expert starts are redrawn while within `GOAL_RADIUS` of the
//! point they must avoid (the start, resp. the goal).
//!
//! **Modes** ([`generate()`]):
//! - *base*: start and goal uniform; when the goal is reached a new goal is drawn and the same
//!   episode continues. Episodes end only at the layout's cap (`timeouts = 1`); a new episode
//!   starts at rest at a new uniform start with a new goal.
//! - *expert*: one fixed goal, the centre of a free cell (by default the cell D4RL marks `G`:
//!   [`Layout::default_goal`]); starts uniform. As in D4RL's maze2d, reaching the goal ends
//!   nothing: the goal stays, and the controller keeps steering the agent onto it (its final
//!   waypoint is the goal itself, so the agent comes to rest there and hovers) until the
//!   layout's cap ends the episode (`timeouts = 1`); the next one starts at rest at a new
//!   uniform start. Most rows therefore lie at the goal, where expert data concentrates.
//!
//! In both modes an episode ends only at the cap: `terminals` is never set (as in D4RL's
//! maze2d datasets). [`MazeData::goals_reached`] counts, in base mode, the goals reached; in
//! expert mode, the episodes in which the goal was reached at least once.
//!
//! **Rows.** Row t holds the observation *before* step t, the action taken from it, the goal
//! in force when it was chosen, and the flags of the transition: `terminals[t]` is always 0,
//! `timeouts[t]` is 1 iff the step is the cap-th of its episode. The file's last row always
//! ends its episode (a timeout, however few steps it has), so every episode in a file is
//! closed by a flag and all but the file's last are exactly the cap long.
//!
//! **File** ([`MazeData::write_npz`]). `observations` float32 `[N, 4]`, `actions` float32
//! `[N, 2]`, `terminals` and `timeouts` bool `[N]` (D4RL's keys), `goals` float32 `[N, 2]` (the
//! goal in force at each row) and `walls` bool `[rows, cols]` (true = wall; the same bytes as
//! D4RL-style uint8 0/1). `relreward dataset upload` sends the first four and reports the
//! other two as left out.
//!
//! **Determinism.** One stream ([`Rng`]) seeded by the seed drives every draw in a fixed order
//! and generation is single-threaded: the same configuration gives the same arrays on every run
//! and any thread count, and the same archive bytes but for the time stamps the zip writer
//! puts on its entries. Without action noise the arithmetic is only IEEE additions,
//! multiplications, comparisons and rounding, so the arrays are also identical across
//! platforms (the noise's `ln` and `cos` come from the platform's math library).

pub mod controller;
pub mod generate;
pub mod rng;
pub mod sim;

use std::fmt;

pub use controller::{Controller, Planner};
pub use generate::{GenerateConfig, MazeData, MazeError, Mode, generate};
pub use rng::Rng;
pub use sim::{Physics, PointMass};

/// Seconds of simulated time per substep (D4RL's MuJoCo timestep).
pub const DT: f64 = 0.01;
/// Substeps per step (per dataset row), the action held throughout.
pub const FRAME_SKIP: u32 = 2;
/// Acceleration per unit of action: `dv/dt = FORCE_GAIN * a - DAMPING * v`.
pub const FORCE_GAIN: f64 = 25.0;
/// Linear velocity damping, per second.
pub const DAMPING: f64 = 0.25;
/// Radius of the agent's disc (collided as its bounding square).
pub const RADIUS: f64 = 0.1;
/// How far short of a wall face a collision leaves the agent's square, so that rounding never
/// puts it inside the wall.
pub const CONTACT_GAP: f64 = 1e-9;
/// Proportional gain of the PD law.
pub const P_GAIN: f64 = 10.0;
/// Derivative (velocity) gain of the PD law.
pub const D_GAIN: f64 = 1.0;
/// The controller moves to the next waypoint within this distance of the current one.
pub const WAYPOINT_RADIUS: f64 = 0.1;
/// A goal is reached within this distance (D4RL's sparse-reward radius).
pub const GOAL_RADIUS: f64 = 0.5;
/// Largest number of rows or columns [`Layout::parse`] accepts (path tables grow with the
/// square of the cell count).
pub const MAX_LAYOUT_SIDE: usize = 64;

/// The cell containing position (x, y): `(round(x), round(y))`, halves away from zero.
pub fn cell_of(x: f64, y: f64) -> (i64, i64) {
    (x.round() as i64, y.round() as i64)
}

/// The four D4RL layouts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LayoutName {
    Open,
    Umaze,
    Medium,
    Large,
}

impl LayoutName {
    pub const ALL: [LayoutName; 4] = [LayoutName::Open, LayoutName::Umaze, LayoutName::Medium, LayoutName::Large];

    pub fn as_str(self) -> &'static str {
        match self {
            LayoutName::Open => "open",
            LayoutName::Umaze => "umaze",
            LayoutName::Medium => "medium",
            LayoutName::Large => "large",
        }
    }

    /// The name in any case, surrounding spaces ignored.
    pub fn from_name(name: &str) -> Option<Self> {
        let name = name.trim();
        Self::ALL.into_iter().find(|n| n.as_str().eq_ignore_ascii_case(name))
    }

    /// The map, rows top to bottom (docs/method.md section 5).
    pub fn map(self) -> &'static [&'static str] {
        match self {
            LayoutName::Open => &["#######", "#OOOOO#", "#OOOOO#", "#OOOOO#", "#######"],
            LayoutName::Umaze => &["#####", "#OOO#", "###O#", "#OOO#", "#####"],
            LayoutName::Medium => {
                &["########", "#OO##OO#", "#OO#OOO#", "##OOO###", "#OO#OOO#", "#O#OO#O#", "#OOO#OO#", "########"]
            }
            LayoutName::Large => &[
                "############",
                "#OOOO#OOOOO#",
                "#O##O#O#O#O#",
                "#OOOOOO#OOO#",
                "#O####O###O#",
                "#OO#O#OOOOO#",
                "##O#O#O#O###",
                "#OO#OOO#OOO#",
                "############",
            ],
        }
    }

    /// D4RL's episode length cap for the layout.
    pub fn max_episode_steps(self) -> u32 {
        match self {
            LayoutName::Open => 150,
            LayoutName::Umaze => 300,
            LayoutName::Medium => 600,
            LayoutName::Large => 800,
        }
    }

    /// The expert goal cell: where D4RL's map of the layout has its `G`.
    pub fn default_goal(self) -> (usize, usize) {
        match self {
            LayoutName::Open => (2, 3),
            LayoutName::Umaze => (1, 1),
            LayoutName::Medium => (6, 6),
            LayoutName::Large => (7, 9),
        }
    }

    pub fn layout(self) -> Layout {
        let mut layout =
            Layout::from_rows(self.as_str(), self.map().iter().copied()).expect("the built-in layouts are valid");
        layout.max_episode_steps = Some(self.max_episode_steps());
        layout.default_goal = Some(self.default_goal());
        layout
    }
}

impl fmt::Display for LayoutName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Why a layout text was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid maze layout: {0}")]
pub struct LayoutError(pub String);

/// A maze: which cells are free. See the module documentation for the geometry.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    name: String,
    rows: usize,
    cols: usize,
    /// Row-major, `rows * cols`.
    free: Vec<bool>,
    max_episode_steps: Option<u32>,
    default_goal: Option<(usize, usize)>,
}

impl Layout {
    /// A built-in layout by name (`open`, `umaze`, `medium`, `large`, any case), or a map: rows
    /// of `#` (wall) and `O` (free) top to bottom, separated by newlines, spaces or D4RL's `\`.
    /// A map may mark one free cell `G` (D4RL's goal), which becomes [`Layout::default_goal`].
    /// Maps have no episode cap of their own; rows must have equal lengths, at most
    /// [`MAX_LAYOUT_SIDE`] rows and columns, and at least one free cell.
    pub fn parse(text: &str) -> Result<Layout, LayoutError> {
        if let Some(name) = LayoutName::from_name(text) {
            return Ok(name.layout());
        }
        let rows = text.split(|c: char| c == '\\' || c.is_whitespace()).filter(|r| !r.is_empty());
        Self::from_rows("custom", rows).map_err(|e| {
            let looks_like_name = text.trim().chars().all(|c| c.is_ascii_alphabetic()) && !text.trim().is_empty();
            if looks_like_name && !text.contains(['#', 'O']) {
                LayoutError(format!(
                    "unknown layout '{}': expected one of open, umaze, medium, large, or a map of '#' and 'O' rows",
                    text.trim()
                ))
            } else {
                e
            }
        })
    }

    fn from_rows<'a>(name: &str, rows: impl Iterator<Item = &'a str>) -> Result<Layout, LayoutError> {
        let mut free = Vec::new();
        let mut cols = None;
        let mut n_rows = 0;
        let mut goal = None;
        for (i, row) in rows.enumerate() {
            let len = row.chars().count();
            match cols {
                None => cols = Some(len),
                Some(c) if c != len => {
                    return Err(LayoutError(format!("row {i} has {len} cells but row 0 has {c}")));
                }
                Some(_) => {}
            }
            for (j, c) in row.chars().enumerate() {
                match c {
                    '#' => free.push(false),
                    'O' | 'o' | '0' => free.push(true),
                    'G' | 'g' => {
                        if goal.replace((i, j)).is_some() {
                            return Err(LayoutError("more than one goal cell 'G'".into()));
                        }
                        free.push(true);
                    }
                    other => {
                        return Err(LayoutError(format!(
                            "unexpected {other:?} at row {i}, col {j}: cells are '#' (wall) or 'O' (free)"
                        )));
                    }
                }
            }
            n_rows += 1;
        }
        let cols = cols.ok_or_else(|| LayoutError("the map has no rows".into()))?;
        if n_rows > MAX_LAYOUT_SIDE || cols > MAX_LAYOUT_SIDE {
            return Err(LayoutError(format!(
                "{n_rows} x {cols} cells; at most {MAX_LAYOUT_SIDE} rows and {MAX_LAYOUT_SIDE} columns"
            )));
        }
        if !free.contains(&true) {
            return Err(LayoutError("no free cell".into()));
        }
        Ok(Layout { name: name.to_owned(), rows: n_rows, cols, free, max_episode_steps: None, default_goal: goal })
    }

    /// `open`, `umaze`, `medium`, `large`, or `custom` for a parsed map.
    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Whether cell (row, col) is free; cells outside the grid (negative included) are not.
    pub fn is_free(&self, row: impl TryInto<i64>, col: impl TryInto<i64>) -> bool {
        match (row.try_into(), col.try_into()) {
            (Ok(i), Ok(j)) => self.free_at(i, j),
            _ => false,
        }
    }

    /// [`Layout::is_free`] on the hot path.
    #[inline]
    pub(crate) fn free_at(&self, i: i64, j: i64) -> bool {
        i >= 0
            && j >= 0
            && (i as usize) < self.rows
            && (j as usize) < self.cols
            && self.free[i as usize * self.cols + j as usize]
    }

    /// Whether position (x, y) is free: its [`cell_of`] is a free cell.
    pub fn is_free_position(&self, x: f64, y: f64) -> bool {
        let (i, j) = cell_of(x, y);
        self.free_at(i, j)
    }

    /// Every free cell as (row, col), row-major.
    pub fn free_cells(&self) -> Vec<(usize, usize)> {
        (0..self.rows).flat_map(|i| (0..self.cols).map(move |j| (i, j))).filter(|&(i, j)| self.is_free(i, j)).collect()
    }

    /// The wall map, row-major `[rows, cols]`: 1 = wall, 0 = free (D4RL's `maze_arr == WALL`).
    pub fn walls(&self) -> Vec<u8> {
        self.free.iter().map(|&f| u8::from(!f)).collect()
    }

    /// D4RL's episode length cap for a built-in layout; `None` for a parsed map.
    pub fn max_episode_steps(&self) -> Option<u32> {
        self.max_episode_steps
    }

    /// The expert goal cell of a built-in layout (D4RL's `G`), or a parsed map's `G`.
    pub fn default_goal(&self) -> Option<(usize, usize)> {
        self.default_goal
    }

    /// Whether every free cell can reach every other through 4-connected free cells.
    pub fn is_connected(&self) -> bool {
        let cells = self.free_cells();
        let Some(&first) = cells.first() else { return false };
        let mut planner = Planner::new(self);
        let dist = planner.distances(first.0 * self.cols + first.1);
        cells.iter().all(|&(i, j)| dist[i * self.cols + j] != controller::UNREACHABLE)
    }

    /// The map as text, rows top to bottom.
    pub fn to_text(&self) -> String {
        let mut out = String::with_capacity(self.rows * (self.cols + 1));
        for i in 0..self.rows {
            for j in 0..self.cols {
                out.push(if self.is_free(i, j) { 'O' } else { '#' });
            }
            out.push('\n');
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn built_in_layouts_have_d4rl_sizes_and_free_cells() {
        // (name, rows, cols, free cells, cap)
        let expected = [
            (LayoutName::Open, 5, 7, 15, 150),
            (LayoutName::Umaze, 5, 5, 7, 300),
            (LayoutName::Medium, 8, 8, 26, 600),
            (LayoutName::Large, 9, 12, 46, 800),
        ];
        for (name, rows, cols, free, cap) in expected {
            let layout = name.layout();
            assert_eq!((layout.rows(), layout.cols()), (rows, cols), "{name}");
            assert_eq!(layout.free_cells().len(), free, "{name}");
            assert_eq!(layout.max_episode_steps(), Some(cap), "{name}");
            assert_eq!(layout.walls().len(), rows * cols);
            assert_eq!(layout.walls().iter().filter(|&&w| w == 0).count(), free);
            let (gi, gj) = layout.default_goal().expect("goal");
            assert!(layout.is_free(gi, gj), "{name}: default goal {gi},{gj} is a wall");
            assert!(layout.is_connected(), "{name}");
            // Bordered by walls, like every D4RL maze.
            for j in 0..cols {
                assert!(!layout.is_free(0, j) && !layout.is_free(rows - 1, j));
            }
            assert_eq!(layout.to_text().lines().collect::<Vec<_>>(), name.map());
            assert_eq!(Layout::parse(&layout.to_text()).expect("reparse").free, layout.free);
            assert_eq!(Layout::parse(name.as_str()).expect("by name"), layout);
        }
        let umaze = Layout::parse(" UMaze ").expect("any case");
        assert_eq!(umaze.free_cells(), [(1, 1), (1, 2), (1, 3), (2, 3), (3, 1), (3, 2), (3, 3)]);
        assert_eq!(umaze.walls()[..5], [1, 1, 1, 1, 1]);
        assert_eq!(umaze.walls()[5..10], [1, 0, 0, 0, 1]);
    }

    #[test]
    fn geometry_rounds_to_the_nearest_cell() {
        assert_eq!(cell_of(1.0, 2.0), (1, 2));
        assert_eq!(cell_of(1.49, 2.51), (1, 3));
        assert_eq!(cell_of(0.5, -0.5), (1, -1), "halves away from zero");
        assert_eq!(cell_of(-0.2, 0.2), (0, 0));
        let umaze = LayoutName::Umaze.layout();
        assert!(umaze.is_free_position(1.0, 1.0));
        assert!(umaze.is_free_position(1.4, 2.0));
        assert!(!umaze.is_free_position(2.0, 2.0), "row 2 col 2 is a wall");
        assert!(!umaze.is_free_position(-3.0, 1.0) && !umaze.is_free_position(1.0, 99.0));
        assert!(!umaze.is_free(-1i64, 0) && !umaze.is_free(usize::MAX, 1usize) && !umaze.is_free(1, 5));
    }

    #[test]
    fn maps_parse_from_d4rl_strings_and_bad_ones_are_refused() {
        let d4rl = Layout::parse("#####\\#GOO#\\###O#\\#OOO#\\#####").expect("d4rl string");
        assert_eq!(d4rl.free, LayoutName::Umaze.layout().free);
        assert_eq!((d4rl.name(), d4rl.default_goal(), d4rl.max_episode_steps()), ("custom", Some((1, 1)), None));
        let err = |text: &str| Layout::parse(text).expect_err(text).to_string();
        assert!(err("umazee").contains("unknown layout 'umazee'"), "{}", err("umazee"));
        assert!(err("").contains("no rows"));
        assert!(err("### ##").contains("row 1 has 2 cells but row 0 has 3"));
        assert!(err("#O# #X#").contains("unexpected 'X' at row 1, col 1"));
        assert!(err("### ###").contains("no free cell"));
        assert!(err("#G# #G#").contains("more than one goal"));
        assert!(err(&"O".repeat(MAX_LAYOUT_SIDE + 1)).contains("at most 64"));
        let split = Layout::parse("#O#\n#O#\n#OO").expect("no outer walls needed");
        assert!(split.is_connected());
        assert!(!Layout::parse("O#O").expect("two islands").is_connected());
    }
}
