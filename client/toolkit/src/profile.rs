//! What `relreward extract` learns about a dataset before it picks sizes: [`DataProfile`]
//! (episode lengths, how far the agent moves per row) and [`derive_window`], the rule that
//! turns it into a diffusion horizon and a reward window.
//!
//! Why: a horizon tuned to one simulator's time scale is wrong for another's. The demo's
//! horizon of 16 rows was tuned on relreward's maze generator; MuJoCo's PointMaze moves about
//! half as far per row (docs/results.md, "The maze generator against MuJoCo", issue 19), so the
//! same 16 rows see half the motion. The rule keeps the motion a window sees constant instead of its row count: `H` is the power of
//! two nearest to [`MOTION_PER_WINDOW`] / (mean per-row displacement), the displacement measured
//! in the limits normalizer's units (each observation coordinate scaled by its range over the
//! data, as the diffusion model sees it). It is clamped to `[8, 64]` and to the shortest
//! quarter of the episodes, so that most episodes hold at least one window.

/// The motion (in normalized units, summed over a window's rows) a horizon should span, chosen
/// so that the rule reproduces the demo's H = 16 on the data that size was tuned on (test
/// `generator_motion_matches_the_demo_horizon`). Measured (docs/results.md): the generator's
/// umaze base data moves 0.084 normalized units per row (0.068 cells), MuJoCo PointMaze's
/// 0.052 (0.031 cells); both round to H = 16 (1 / 0.084 = 11.9 and 1 / 0.052 = 19.3 are
/// nearest 16 among powers of two), so on these two the rule changes nothing, while data
/// moving 1.5x slower than PointMaze per row gets H = 32.
pub const MOTION_PER_WINDOW: f64 = 1.0;

/// Smallest and largest horizon the rule picks.
pub const HORIZON_RANGE: (usize, usize) = (8, 64);

/// Facts about one dataset that sizes are derived from.
#[derive(Debug, Clone, PartialEq)]
pub struct DataProfile {
    pub rows: usize,
    pub episodes: usize,
    /// Episode lengths: shortest, 25th percentile, median, longest.
    pub episode_len: [usize; 4],
    /// Mean over consecutive rows inside an episode of the Euclidean norm of the observation
    /// change, each coordinate divided by half its range (the limits normalizer's scale); rows
    /// identical to the one before (held absorbing states) are left out.
    pub displacement_per_row: f64,
}

/// Profiles `observations` (`[N, obs_dim]`, row-major) cut into `episodes` (row ranges).
pub fn profile(observations: &[f32], obs_dim: usize, episodes: &[std::ops::Range<usize>]) -> DataProfile {
    let rows = observations.len().checked_div(obs_dim).unwrap_or(0);
    let mut lo = vec![f64::INFINITY; obs_dim];
    let mut hi = vec![f64::NEG_INFINITY; obs_dim];
    for row in observations.chunks_exact(obs_dim.max(1)) {
        for (j, &v) in row.iter().enumerate() {
            lo[j] = lo[j].min(f64::from(v));
            hi[j] = hi[j].max(f64::from(v));
        }
    }
    // Half ranges; a constant coordinate does not move and is left out.
    let half: Vec<f64> = lo.iter().zip(&hi).map(|(l, h)| (h - l) / 2.0).collect();
    let (mut sum, mut count) = (0.0, 0usize);
    for ep in episodes {
        for t in ep.start..ep.end.saturating_sub(1) {
            let (a, b) =
                (&observations[t * obs_dim..(t + 1) * obs_dim], &observations[(t + 1) * obs_dim..(t + 2) * obs_dim]);
            let d2: f64 = a
                .iter()
                .zip(b)
                .zip(&half)
                .filter(|(_, h)| **h > 0.0)
                .map(|((x, y), h)| ((f64::from(*y) - f64::from(*x)) / h).powi(2))
                .sum();
            // A row that repeats the one before records no motion and no time scale (absorbing
            // padding, `extract --absorbing`; a paused recorder): not counted.
            if d2 > 0.0 {
                sum += d2.sqrt();
                count += 1;
            }
        }
    }
    let mut lengths: Vec<usize> = episodes.iter().map(ExactSizeIterator::len).collect();
    lengths.sort_unstable();
    let at =
        |q: f64| lengths.get(((lengths.len().saturating_sub(1)) as f64 * q).round() as usize).copied().unwrap_or(0);
    DataProfile {
        rows,
        episodes: episodes.len(),
        episode_len: [at(0.0), at(0.25), at(0.5), at(1.0)],
        displacement_per_row: if count == 0 { 0.0 } else { sum / count as f64 },
    }
}

/// `(horizon, reward window)` for the profiles of every dataset of a run (module docs): the
/// horizon from the mean displacement over all of them, the window a quarter of it.
pub fn derive_window(profiles: &[DataProfile]) -> (usize, usize) {
    let moving: Vec<f64> = profiles.iter().map(|p| p.displacement_per_row).filter(|d| *d > 0.0).collect();
    let displacement = if moving.is_empty() { 0.0 } else { moving.iter().sum::<f64>() / moving.len() as f64 };
    let wanted = if displacement > 0.0 { MOTION_PER_WINDOW / displacement } else { HORIZON_RANGE.1 as f64 };
    // The power of two nearest in log scale.
    let mut horizon = 2f64.powf(wanted.max(1.0).log2().round()) as usize;
    horizon = horizon.clamp(HORIZON_RANGE.0, HORIZON_RANGE.1);
    // Most episodes must hold a window: at most the 25th-percentile episode length (rounded
    // down to a multiple of 4 so the window divides it), never below 4.
    let short = profiles.iter().map(|p| p.episode_len[1]).min().unwrap_or(horizon);
    if short < horizon {
        horizon = (short / 4 * 4).max(4);
    }
    (horizon, (horizon / 4).max(1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::maze::{self, GenerateConfig, LayoutName, Mode};

    #[test]
    fn displacement_is_measured_in_normalized_units() {
        // x moves 0, 1, 2, 3 over a range of 3 (half range 1.5): 1/1.5 per row; y is constant.
        let obs = [0.0, 5.0, 1.0, 5.0, 2.0, 5.0, 3.0, 5.0];
        let one_episode = std::iter::once(0..4usize).collect::<Vec<_>>();
        let p = profile(&obs, 2, &one_episode);
        assert!((p.displacement_per_row - 1.0 / 1.5).abs() < 1e-12);
        assert_eq!((p.rows, p.episodes, p.episode_len), (4, 1, [4, 4, 4, 4]));
        // No step crosses an episode boundary.
        let p = profile(&obs, 2, &[0..2, 2..4]);
        assert!((p.displacement_per_row - 1.0 / 1.5).abs() < 1e-12);
        // A held (repeated) last row adds no motion and no row to the mean.
        let held = [0.0, 5.0, 1.0, 5.0, 2.0, 5.0, 3.0, 5.0, 3.0, 5.0, 3.0, 5.0];
        let p = profile(&held, 2, std::slice::from_ref(&(0..6)));
        assert!((p.displacement_per_row - 1.0 / 1.5).abs() < 1e-12);
    }

    #[test]
    fn slower_data_gets_a_longer_horizon_and_short_episodes_cap_it() {
        let p = |d: f64, short: usize| DataProfile {
            rows: 1000,
            episodes: 10,
            episode_len: [short, short, 100, 100],
            displacement_per_row: d,
        };
        assert_eq!(derive_window(&[p(1.0 / 16.0, 100)]), (16, 4));
        assert_eq!(derive_window(&[p(1.0 / 32.0, 100)]), (32, 8));
        assert_eq!(derive_window(&[p(1.0, 100)]), (8, 2));
        assert_eq!(derive_window(&[p(1.0 / 32.0, 20)]), (20, 5));
        assert_eq!(derive_window(&[p(0.0, 100)]), (64, 16));
    }

    #[test]
    fn generator_motion_matches_the_demo_horizon() {
        let config = GenerateConfig::new(LayoutName::Umaze.layout(), Mode::Base, 20_000, 0);
        let data = maze::generate(&config).expect("generate");
        let p = profile(&data.observations, 4, &data.episode_ranges());
        assert_eq!(derive_window(std::slice::from_ref(&p)).0, 16, "{p:?}");
    }

    #[test]
    fn matched_physics_moves_as_far_per_row_as_mujoco_pointmaze() {
        // MuJoCo PointMaze umaze base data (experiments/pointmaze/generate.py, docs/results.md)
        // moves 0.052 normalized units per row; the generator's default 0.084.
        let mut config = GenerateConfig::new(LayoutName::Umaze.layout(), Mode::Base, 20_000, 0);
        config.physics = maze::Physics::MUJOCO;
        let data = maze::generate(&config).expect("generate");
        let p = profile(&data.observations, 4, &data.episode_ranges());
        assert!((0.04..0.065).contains(&p.displacement_per_row), "{p:?}");
        // The velocity rule finds [vx, vy] in both physics' data.
        for physics in [maze::Physics::MUJOCO, maze::Physics::RELREWARD] {
            config.physics = physics;
            let data = maze::generate(&config).expect("generate");
            let t = crate::trajectories::Trajectories {
                observations: data.observations.clone(),
                obs_dim: 4,
                actions: data.actions.clone(),
                act_dim: 2,
                timeouts: data.timeouts.clone(),
                ..Default::default()
            };
            assert_eq!(t.velocity_columns(), vec![2, 3], "{physics:?}");
        }
    }
}
