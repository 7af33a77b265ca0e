//! [`generate`]: a Maze2D dataset in D4RL's layout, base (undirected) or expert (one goal), from
//! a [`GenerateConfig`]; [`MazeData::write_npz`] writes it for `relreward dataset upload`.
//! Episodes, goals, flags and determinism are described in the [module documentation](super).

use std::ops::Range;

use super::controller::dist2;
use super::{Controller, GOAL_RADIUS, Layout, Physics, Planner, PointMass, RADIUS, Rng};

/// Margin between a drawn position's disc and its cell's border.
const SPAWN_MARGIN: f64 = 1e-6;
/// Draws of a position away from another before the last draw is taken as is (only a layout
/// with a single free cell could ever need that many).
const MAX_DRAWS: usize = 1_000;
/// Rows between two calls of the progress callback.
pub const PROGRESS_EVERY: usize = 1 << 16;

/// Base: uniform goals, redrawn when reached. Expert: one fixed goal, reached and then held
/// until the episode's cap (D4RL's maze2d). Episodes end only at the cap in both modes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Base,
    Expert,
}

impl Mode {
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Base => "base",
            Mode::Expert => "expert",
        }
    }
}

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct GenerateConfig {
    pub layout: Layout,
    pub mode: Mode,
    /// Expert mode: the goal cell (row, col), whose centre is the goal; `None` for the layout's
    /// [`Layout::default_goal`]. Must be `None` in base mode.
    pub goal: Option<(usize, usize)>,
    /// Rows of the dataset (at least 1).
    pub transitions: usize,
    pub seed: u64,
    /// Episode length cap; `None` for the layout's [`Layout::max_episode_steps`].
    pub max_episode_steps: Option<u32>,
    /// Standard deviation of Gaussian noise added to each action component before clipping
    /// (0: none; the recorded action is the one applied).
    pub action_noise: f64,
    /// The point's dynamics: [`Physics::RELREWARD`] (default) or [`Physics::MUJOCO`].
    pub physics: Physics,
}

impl GenerateConfig {
    /// `transitions` rows of `mode` data in `layout`, with the layout's goal and cap, no noise.
    pub fn new(layout: Layout, mode: Mode, transitions: usize, seed: u64) -> Self {
        Self {
            layout,
            mode,
            goal: None,
            transitions,
            seed,
            max_episode_steps: None,
            action_noise: 0.0,
            physics: Physics::RELREWARD,
        }
    }

    /// The cap and, in expert mode, the goal cell; or why the configuration cannot be run.
    fn resolve(&self) -> Result<(u32, Option<(usize, usize)>), MazeError> {
        let layout = &self.layout;
        let name = layout.name().to_owned();
        if self.transitions == 0 {
            return Err(MazeError::NoTransitions);
        }
        if !(self.action_noise.is_finite() && self.action_noise >= 0.0) {
            return Err(MazeError::BadActionNoise(self.action_noise));
        }
        let cap = match self.max_episode_steps.or(layout.max_episode_steps()) {
            None => return Err(MazeError::NoEpisodeCap { layout: name }),
            Some(0) => return Err(MazeError::ZeroEpisodeCap),
            Some(cap) => cap,
        };
        let goal = match (self.mode, self.goal) {
            (Mode::Base, None) => None,
            (Mode::Base, Some(_)) => return Err(MazeError::GoalInBaseMode),
            (Mode::Expert, goal) => {
                let (row, col) = goal.or(layout.default_goal()).ok_or(MazeError::NoDefaultGoal { layout: name })?;
                check_goal(layout, row, col)?;
                Some((row, col))
            }
        };
        if !layout.is_connected() {
            return Err(MazeError::Disconnected { layout: layout.name().to_owned() });
        }
        Ok((cap, goal))
    }
}

/// Whether cell (row, col) can be an expert goal in `layout`.
pub fn check_goal(layout: &Layout, row: usize, col: usize) -> Result<(), MazeError> {
    let name = layout.name().to_owned();
    if row >= layout.rows() || col >= layout.cols() {
        return Err(MazeError::GoalOutside { layout: name, row, col, rows: layout.rows(), cols: layout.cols() });
    }
    if !layout.is_free(row, col) {
        return Err(MazeError::GoalIsWall { layout: name, row, col });
    }
    Ok(())
}

/// Why a configuration cannot be generated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MazeError {
    #[error("the number of transitions must be at least 1")]
    NoTransitions,
    #[error("action noise {0} must be a finite number >= 0")]
    BadActionNoise(f64),
    #[error("the {layout} layout has no episode length cap of its own: give one")]
    NoEpisodeCap { layout: String },
    #[error("the episode length cap must be at least 1")]
    ZeroEpisodeCap,
    #[error("a goal applies to expert mode only (base mode draws its own goals)")]
    GoalInBaseMode,
    #[error("the {layout} layout has no default goal: give one")]
    NoDefaultGoal { layout: String },
    #[error("cell ({row}, {col}) is outside the {layout} layout ({rows} rows x {cols} columns)")]
    GoalOutside { layout: String, row: usize, col: usize, rows: usize, cols: usize },
    #[error("cell ({row}, {col}) of the {layout} layout is a wall")]
    GoalIsWall { layout: String, row: usize, col: usize },
    #[error("the free cells of the {layout} layout are not all connected")]
    Disconnected { layout: String },
    #[error("{transitions} transitions need {bytes} bytes of memory, which could not be reserved")]
    TooLarge { transitions: usize, bytes: u64 },
}

/// A generated dataset: D4RL's arrays (row-major, `N` rows) and what produced them.
#[derive(Debug, Clone, PartialEq)]
pub struct MazeData {
    pub layout: String,
    pub mode: Mode,
    pub rows: usize,
    pub cols: usize,
    /// `[N, 4]`: x, y, vx, vy before each step.
    pub observations: Vec<f32>,
    /// `[N, 2]`: the applied force, in `[-1, 1]`.
    pub actions: Vec<f32>,
    /// `[N]`: always false, in both modes (D4RL's maze2d never sets it: reaching the goal ends
    /// no episode). Kept for D4RL's keys.
    pub terminals: Vec<bool>,
    /// `[N]`: the step ended its episode: the cap-th step, or the file's last row.
    pub timeouts: Vec<bool>,
    /// `[N, 2]`: the goal in force at each step.
    pub goals: Vec<f32>,
    /// `[rows, cols]`: 1 = wall ([`Layout::walls`]).
    pub walls: Vec<u8>,
    /// Expert mode: the goal cell.
    pub goal_cell: Option<(usize, usize)>,
    pub max_episode_steps: u32,
    /// Episodes in the file (rows whose timeout flag is set; no terminal flag is ever set).
    pub episodes: usize,
    /// Base mode: goals reached (each one is then replaced by a new goal). Expert mode: episodes
    /// in which the goal was reached at least once (the agent then stays there, and the steps
    /// it spends within [`GOAL_RADIUS`] afterwards are not counted again).
    pub goals_reached: usize,
}

impl MazeData {
    /// Rows (transitions).
    pub fn len(&self) -> usize {
        self.terminals.len()
    }

    pub fn is_empty(&self) -> bool {
        self.terminals.is_empty()
    }

    /// The rows of each episode, in order (each closed by a terminal or a timeout flag; this
    /// generator sets only timeouts).
    pub fn episode_ranges(&self) -> Vec<Range<usize>> {
        let mut out = Vec::with_capacity(self.episodes);
        let mut start = 0;
        for (t, (&term, &timeout)) in self.terminals.iter().zip(&self.timeouts).enumerate() {
            if term || timeout {
                out.push(start..t + 1);
                start = t + 1;
            }
        }
        out
    }

    /// Writes the arrays as an `.npz` archive (moved into place once complete):
    /// `observations` float32 `[N, 4]`, `actions` float32 `[N, 2]`, `terminals` bool `[N]`,
    /// `timeouts` bool `[N]`, `goals` float32 `[N, 2]` and `walls` bool `[rows, cols]` (true =
    /// wall: the bytes of a uint8 0/1 array; `np.load(..)["walls"].astype(np.uint8)` gives
    /// D4RL's form). `relreward dataset upload` sends the first four and leaves `goals` and
    /// `walls` out.
    pub fn write_npz(&self, path: impl AsRef<std::path::Path>) -> std::io::Result<std::path::PathBuf> {
        let n = self.len() as u64;
        let walls: Vec<bool> = self.walls.iter().map(|&w| w != 0).collect();
        let mut w = crate::npz_write::NpzWriter::create(path)?;
        w.add_f32("observations", &[n, 4], &self.observations)?;
        w.add_f32("actions", &[n, 2], &self.actions)?;
        w.add_bool("terminals", &[n], &self.terminals)?;
        w.add_bool("timeouts", &[n], &self.timeouts)?;
        w.add_f32("goals", &[n, 2], &self.goals)?;
        w.add_bool("walls", &[self.rows as u64, self.cols as u64], &walls)?;
        w.finish()
    }
}

/// Generates the dataset `config` describes.
pub fn generate(config: &GenerateConfig) -> Result<MazeData, MazeError> {
    generate_with_progress(config, |_| {})
}

/// [`generate`], calling `progress(rows done)` every [`PROGRESS_EVERY`] rows and at the end.
pub fn generate_with_progress(config: &GenerateConfig, mut progress: impl FnMut(usize)) -> Result<MazeData, MazeError> {
    let (cap, goal_cell) = config.resolve()?;
    let layout = &config.layout;
    let n = config.transitions;
    let mut planner = Planner::new(layout);
    let cells = layout.free_cells();
    let mut rng = Rng::new(config.seed);
    let mut data = MazeData {
        layout: layout.name().to_owned(),
        mode: config.mode,
        rows: layout.rows(),
        cols: layout.cols(),
        observations: reserve(n, 4)?,
        actions: reserve(n, 2)?,
        terminals: reserve(n, 1)?,
        timeouts: reserve(n, 1)?,
        goals: reserve(n, 2)?,
        walls: layout.walls(),
        goal_cell,
        max_episode_steps: cap,
        episodes: 0,
        goals_reached: 0,
    };
    let fixed_goal = goal_cell.map(|(i, j)| [i as f64, j as f64]);
    let reached_r2 = GOAL_RADIUS * GOAL_RADIUS;

    let mut agent = PointMass::at_rest([0.0, 0.0]);
    let mut goal = [0.0, 0.0];
    // The episode's controller; `None` between episodes.
    let mut episode: Option<Controller> = None;
    let mut steps = 0u32;
    // Expert mode: whether this episode has reached the goal yet.
    let mut reached_before = false;
    for row in 0..n {
        let controller = episode.get_or_insert_with(|| {
            // A new episode: at rest at a uniform start, with the expert goal or a new one.
            let start = match fixed_goal {
                Some(g) => {
                    goal = g;
                    draw_away(&mut rng, &cells, g)
                }
                None => {
                    let start = uniform_position(&mut rng, &cells);
                    goal = draw_away(&mut rng, &cells, start);
                    start
                }
            };
            agent = PointMass::at_rest(start);
            steps = 0;
            reached_before = false;
            Controller::new(&mut planner, start, goal)
        });
        let [x, y, vx, vy] = agent.observation();
        data.observations.extend_from_slice(&[x as f32, y as f32, vx as f32, vy as f32]);
        data.goals.extend_from_slice(&[goal[0] as f32, goal[1] as f32]);
        let mut a = controller.act(&mut planner, agent.pos, agent.vel);
        if config.action_noise > 0.0 {
            for v in &mut a {
                *v = (*v + config.action_noise * rng.normal()).clamp(-1.0, 1.0);
            }
        }
        data.actions.extend_from_slice(&[a[0] as f32, a[1] as f32]);
        agent.step_with(layout, a, &config.physics);
        steps += 1;

        if dist2(agent.pos, goal) <= reached_r2 {
            match config.mode {
                // The goal stays; the controller's last waypoint is the goal itself, so the agent
                // keeps being steered onto it until the cap.
                Mode::Expert => {
                    if !reached_before {
                        reached_before = true;
                        data.goals_reached += 1;
                    }
                }
                Mode::Base => {
                    data.goals_reached += 1;
                    goal = draw_away(&mut rng, &cells, agent.pos);
                    *controller = Controller::new(&mut planner, agent.pos, goal);
                }
            }
        }
        // Only the cap (or the file's end) ends an episode: no terminals, as in D4RL's maze2d.
        let timeout = steps == cap || row + 1 == n;
        data.terminals.push(false);
        data.timeouts.push(timeout);
        if timeout {
            data.episodes += 1;
            episode = None;
        }
        if (row + 1) % PROGRESS_EVERY == 0 {
            progress(row + 1);
        }
    }
    progress(n);
    Ok(data)
}

/// Bytes of memory one row takes: observations, actions, the two flags and the goal.
pub const BYTES_PER_TRANSITION: u64 = 4 * 4 + 2 * 4 + 1 + 1 + 2 * 4;

/// An empty vector with room for `rows * width` values, or [`MazeError::TooLarge`].
fn reserve<T>(rows: usize, width: usize) -> Result<Vec<T>, MazeError> {
    let too_large =
        || MazeError::TooLarge { transitions: rows, bytes: (rows as u64).saturating_mul(BYTES_PER_TRANSITION) };
    let mut v = Vec::new();
    v.try_reserve_exact(rows.checked_mul(width).ok_or_else(too_large)?).map_err(|_| too_large())?;
    Ok(v)
}

/// A uniform free cell, then a uniform point of its square shrunk so the disc clears the walls.
fn uniform_position(rng: &mut Rng, cells: &[(usize, usize)]) -> [f64; 2] {
    let (i, j) = cells[rng.below(cells.len() as u64) as usize];
    let half = 0.5 - RADIUS - SPAWN_MARGIN;
    let x = i as f64 + (2.0 * rng.uniform() - 1.0) * half;
    let y = j as f64 + (2.0 * rng.uniform() - 1.0) * half;
    [x, y]
}

/// A uniform position farther than [`GOAL_RADIUS`] from `avoid` (the last of [`MAX_DRAWS`]
/// draws if none is).
fn draw_away(rng: &mut Rng, cells: &[(usize, usize)], avoid: [f64; 2]) -> [f64; 2] {
    let mut p = uniform_position(rng, cells);
    for _ in 1..MAX_DRAWS {
        if dist2(p, avoid) > GOAL_RADIUS * GOAL_RADIUS {
            break;
        }
        p = uniform_position(rng, cells);
    }
    p
}

#[cfg(test)]
mod tests {
    use super::super::{LayoutName, cell_of};
    use super::*;

    fn config(name: LayoutName, mode: Mode, n: usize, seed: u64) -> GenerateConfig {
        GenerateConfig::new(name.layout(), mode, n, seed)
    }

    /// Whether the disc's square (shrunk by `margin`) at row `t` lies in free cells only.
    fn clear(layout: &Layout, obs: &[f32], t: usize, margin: f64) -> bool {
        let (x, y) = (f64::from(obs[4 * t]), f64::from(obs[4 * t + 1]));
        let r = RADIUS - margin;
        [(-r, -r), (-r, r), (r, -r), (r, r)].iter().all(|(dx, dy)| layout.is_free_position(x + dx, y + dy))
    }

    #[test]
    fn the_same_seed_gives_the_same_data() {
        for mode in [Mode::Base, Mode::Expert] {
            let a = generate(&config(LayoutName::Medium, mode, 5_000, 9)).expect("a");
            let b = generate(&config(LayoutName::Medium, mode, 5_000, 9)).expect("b");
            assert_eq!(a, b);
            let c = generate(&config(LayoutName::Medium, mode, 5_000, 10)).expect("c");
            assert_ne!(a.observations, c.observations);
            // A prefix of a longer run is the shorter run (up to the closing flag).
            let long = generate(&config(LayoutName::Medium, mode, 7_000, 9)).expect("long");
            assert_eq!(long.observations[..4 * 5_000], a.observations[..]);
            assert_eq!(long.actions[..2 * 5_000], a.actions[..]);
        }
    }

    #[test]
    fn base_mode_redraws_goals_and_cuts_episodes_at_the_cap() {
        let data = generate(&config(LayoutName::Umaze, Mode::Base, 10_000, 1)).expect("generate");
        assert_eq!(
            (data.len(), data.observations.len(), data.actions.len(), data.goals.len()),
            (10_000, 40_000, 20_000, 20_000)
        );
        assert_eq!((data.rows, data.cols, data.walls.len(), data.max_episode_steps), (5, 5, 25, 300));
        assert!(data.terminals.iter().all(|&t| !t), "no terminals in base mode");
        let episodes = data.episode_ranges();
        assert_eq!(episodes.len(), data.episodes);
        assert_eq!(data.episodes, 34, "33 full episodes of 300 and one of 100 closed by the file's end");
        assert!(episodes[..33].iter().all(|e| e.len() == 300));
        assert!(*data.timeouts.last().expect("last"));
        // Goals change within episodes, as many times as goals are reached.
        let mut changes = 0;
        for e in &episodes {
            for t in e.start + 1..e.end {
                if data.goals[2 * t..2 * t + 2] != data.goals[2 * t - 2..2 * t] {
                    changes += 1;
                    // The previous step ended within GOAL_RADIUS of the old goal.
                    let (x, y) = (f64::from(data.observations[4 * t]), f64::from(data.observations[4 * t + 1]));
                    let (gx, gy) = (f64::from(data.goals[2 * t - 2]), f64::from(data.goals[2 * t - 1]));
                    assert!((x - gx).hypot(y - gy) <= GOAL_RADIUS + 1e-5);
                }
            }
            // Each episode starts at rest.
            assert_eq!(data.observations[4 * e.start + 2..4 * e.start + 4], [0.0, 0.0]);
        }
        // A goal reached on an episode's last row is replaced by the next episode's own.
        assert!(changes <= data.goals_reached && data.goals_reached <= changes + episodes.len());
        assert!(changes > 100, "{changes}");
        assert!(data.actions.iter().all(|a| (-1.0..=1.0).contains(a)));
        // Goals are uniform over free space: every free cell holds some.
        let layout = LayoutName::Umaze.layout();
        for (i, j) in layout.free_cells() {
            let hits =
                data.goals.chunks(2).filter(|g| cell_of(f64::from(g[0]), f64::from(g[1])) == (i as i64, j as i64));
            assert!(hits.count() > 0, "no goal in cell ({i}, {j})");
        }
    }

    /// Per episode, whether some observation after its first lies within [`GOAL_RADIUS`] of the
    /// goal in force (the state after every step but the episode's last is recorded).
    fn reached_in(data: &MazeData, e: &Range<usize>) -> bool {
        (e.start + 1..e.end).any(|t| near(data, t, GOAL_RADIUS))
    }

    /// Whether row `t`'s position lies within `r` of its goal (plus float32 rounding).
    fn near(data: &MazeData, t: usize, r: f64) -> bool {
        let (x, y) = (f64::from(data.observations[4 * t]), f64::from(data.observations[4 * t + 1]));
        let (gx, gy) = (f64::from(data.goals[2 * t]), f64::from(data.goals[2 * t + 1]));
        (x - gx).hypot(y - gy) <= r + 1e-5
    }

    #[test]
    fn expert_mode_concentrates_on_its_goal() {
        let data = generate(&config(LayoutName::Umaze, Mode::Expert, 100_000, 2)).expect("generate");
        let goal = [1.0f32, 1.0];
        assert_eq!(data.goal_cell, Some((1, 1)));
        assert!(data.goals.chunks(2).all(|g| g == goal));
        // D4RL's maze2d: reaching the goal ends nothing; only the cap (or the file's end) does.
        assert!(data.terminals.iter().all(|&t| !t), "no terminals in expert mode");
        let episodes = data.episode_ranges();
        assert_eq!(episodes.len(), data.episodes);
        assert_eq!(data.episodes, 334, "333 full episodes of 300 and one of 100 closed by the file's end");
        assert!(episodes[..333].iter().all(|e| e.len() == 300));
        assert_eq!(episodes[333], 99_900..100_000);
        assert!(episodes.iter().all(|e| data.timeouts[e.end - 1]));
        assert_eq!(data.timeouts.iter().filter(|&&t| t).count(), data.episodes);
        // `goals_reached` counts episodes that reached the goal, each once.
        let reached: Vec<&Range<usize>> = episodes.iter().filter(|e| reached_in(&data, e)).collect();
        assert_eq!(reached.len(), data.goals_reached);
        assert!(reached.len() as f64 / episodes.len() as f64 >= 0.9, "{} of {}", reached.len(), episodes.len());
        for e in &episodes {
            assert!(!near(&data, e.start, GOAL_RADIUS), "starts away from the goal");
            // Each episode starts at rest.
            assert_eq!(data.observations[4 * e.start + 2..4 * e.start + 4], [0.0, 0.0]);
        }
        // Once reached, the goal is held: the agent hovers there to the episode's end.
        for e in &reached {
            assert!(near(&data, e.end - 1, GOAL_RADIUS), "episode {e:?} ends away from the goal");
            let first = (e.start + 1..e.end).find(|&t| near(&data, t, GOAL_RADIUS)).expect("reached");
            assert!((first..e.end).all(|t| near(&data, t, GOAL_RADIUS)), "episode {e:?} leaves the goal");
        }
        // Positions concentrate at the goal: most rows lie within 0.5 of it (about 86% here; the
        // longest shortest path takes 76 of the 300 steps).
        let at_goal = (0..data.len()).filter(|&t| near(&data, t, 0.5)).count();
        assert!(at_goal as f64 / data.len() as f64 > 0.7, "{at_goal} of {}", data.len());

        // Every layout: the default goal is reached in nearly every episode and then held, no
        // terminals, and most rows lie at the goal.
        for name in LayoutName::ALL {
            let data = generate(&config(name, Mode::Expert, 20_000, 3)).expect("generate");
            assert!(data.terminals.iter().all(|&t| !t), "{name}");
            let cap = name.max_episode_steps() as usize;
            let episodes = data.episode_ranges();
            assert_eq!(episodes.len(), 20_000_usize.div_ceil(cap), "{name}");
            assert!(episodes.iter().rev().skip(1).all(|e| e.len() == cap), "{name}");
            let reached: Vec<_> = episodes.iter().filter(|e| reached_in(&data, e)).collect();
            assert_eq!(reached.len(), data.goals_reached, "{name}");
            assert!(reached.len() + 1 >= episodes.len(), "{name}: {} of {}", reached.len(), episodes.len());
            assert!(reached.iter().all(|e| near(&data, e.end - 1, GOAL_RADIUS)), "{name}");
            let at_goal = (0..data.len()).filter(|&t| near(&data, t, 0.5)).count();
            assert!(at_goal as f64 / data.len() as f64 > 0.7, "{name}: {at_goal} of {}", data.len());
        }
    }

    #[test]
    fn no_position_is_ever_inside_a_wall() {
        for (mode, noise) in [(Mode::Base, 0.0), (Mode::Base, 0.5), (Mode::Expert, 0.3)] {
            let mut cfg = config(LayoutName::Large, mode, 200_000, 4);
            cfg.action_noise = noise;
            let layout = cfg.layout.clone();
            let data = generate(&cfg).expect("generate");
            for t in 0..data.len() {
                // f32 positions: allow for their rounding (~1e-7 at these magnitudes).
                assert!(clear(&layout, &data.observations, t, 1e-5), "{mode:?} row {t}");
            }
            assert!(data.actions.iter().all(|a| (-1.0..=1.0).contains(a)));
        }
    }

    #[test]
    fn action_noise_changes_the_data_deterministically() {
        let mut cfg = config(LayoutName::Open, Mode::Base, 3_000, 5);
        let clean = generate(&cfg).expect("clean");
        cfg.action_noise = 0.2;
        let noisy = generate(&cfg).expect("noisy");
        assert_ne!(clean.actions, noisy.actions);
        assert_eq!(noisy, generate(&cfg).expect("again"));
    }

    #[test]
    fn bad_configurations_are_refused() {
        let err = |cfg: GenerateConfig| generate(&cfg).expect_err("refused");
        assert_eq!(err(config(LayoutName::Umaze, Mode::Base, 0, 1)), MazeError::NoTransitions);
        let mut cfg = config(LayoutName::Umaze, Mode::Expert, 10, 1);
        cfg.goal = Some((2, 2));
        assert_eq!(err(cfg.clone()), MazeError::GoalIsWall { layout: "umaze".into(), row: 2, col: 2 });
        assert_eq!(err(cfg.clone()).to_string(), "cell (2, 2) of the umaze layout is a wall");
        cfg.goal = Some((5, 1));
        assert!(matches!(err(cfg.clone()), MazeError::GoalOutside { row: 5, col: 1, rows: 5, cols: 5, .. }));
        cfg.goal = Some((3, 3));
        assert_eq!(generate(&cfg).expect("free goal").goal_cell, Some((3, 3)));
        let mut base = config(LayoutName::Umaze, Mode::Base, 10, 1);
        base.goal = Some((1, 1));
        assert_eq!(err(base), MazeError::GoalInBaseMode);
        let mut noisy = config(LayoutName::Umaze, Mode::Base, 10, 1);
        noisy.action_noise = f64::NAN;
        assert!(matches!(err(noisy.clone()), MazeError::BadActionNoise(_)));
        noisy.action_noise = -0.1;
        assert!(matches!(err(noisy), MazeError::BadActionNoise(_)));
        let custom = Layout::parse("#### #OO# ####").expect("map");
        assert!(matches!(err(GenerateConfig::new(custom.clone(), Mode::Base, 10, 1)), MazeError::NoEpisodeCap { .. }));
        let mut capped = GenerateConfig::new(custom.clone(), Mode::Base, 10, 1);
        capped.max_episode_steps = Some(4);
        assert_eq!(generate(&capped).expect("capped").episodes, 3);
        capped.max_episode_steps = Some(0);
        assert_eq!(err(capped), MazeError::ZeroEpisodeCap);
        let mut no_goal = GenerateConfig::new(custom, Mode::Expert, 10, 1);
        no_goal.max_episode_steps = Some(4);
        assert!(matches!(err(no_goal), MazeError::NoDefaultGoal { .. }));
        let huge = config(LayoutName::Umaze, Mode::Base, usize::MAX / 2, 1);
        assert!(matches!(err(huge), MazeError::TooLarge { .. }));
        let mut islands = GenerateConfig::new(Layout::parse("O#O").expect("map"), Mode::Base, 10, 1);
        islands.max_episode_steps = Some(4);
        assert!(matches!(err(islands), MazeError::Disconnected { .. }));
    }

    #[test]
    fn the_npz_holds_d4rl_keys_and_uploads_as_trajectories() {
        use std::io::Read;

        use crate::npz::trajectories_from_npz;
        use relreward_proto::upload::UploadSource;

        let dir = tempfile::tempdir().expect("tempdir");
        let data = generate(&config(LayoutName::Umaze, Mode::Expert, 2_000, 6)).expect("generate");
        let path = dir.path().join("maze.npz");
        data.write_npz(&path).expect("write");
        let source = trajectories_from_npz(&path).expect("readable as trajectories");
        let arrays: Vec<(String, Vec<u64>)> =
            source.arrays().iter().map(|a| (a.name.clone(), a.shape.clone())).collect();
        assert_eq!(
            arrays,
            [
                ("observations".to_owned(), vec![2_000, 4]),
                ("actions".to_owned(), vec![2_000, 2]),
                ("terminals".to_owned(), vec![2_000]),
                ("timeouts".to_owned(), vec![2_000]),
            ]
        );
        assert_eq!(source.ignored_keys(), ["goals", "walls"]);

        // The same data writes the same archive members (the zip writer stamps entries with
        // the time, so whole files are compared member by member).
        let again = dir.path().join("again.npz");
        generate(&config(LayoutName::Umaze, Mode::Expert, 2_000, 6)).expect("again").write_npz(&again).expect("write");
        let members = |p: &std::path::Path| {
            let mut zip = npyz::zip::ZipArchive::new(std::fs::File::open(p).expect("open")).expect("zip");
            (0..zip.len())
                .map(|i| {
                    let mut entry = zip.by_index(i).expect("entry");
                    let mut bytes = Vec::new();
                    entry.read_to_end(&mut bytes).expect("read");
                    (entry.name().to_owned(), entry.crc32(), bytes)
                })
                .collect::<Vec<_>>()
        };
        let (a, b) = (members(&path), members(&again));
        assert_eq!(a, b);
        assert_eq!(std::fs::metadata(&path).expect("a").len(), std::fs::metadata(&again).expect("b").len());
        let walls = &a.iter().find(|(name, ..)| name == "walls.npy").expect("walls").2;
        assert_eq!(walls[walls.len() - 25..], data.walls[..], "bool bytes are the 0/1 wall map");
    }
}
