//! [`Trajectories`]: a trajectory dataset held in memory, the form every reader that has to
//! convert (HDF5, Minari episodes) produces. It becomes an upload
//! ([`Trajectories::upload_source`]) or the project's canonical `.npz`
//! ([`Trajectories::write_npz`]), which the commands that read windows from files (`score`,
//! `eval`, `extract`) take directly.

use std::io;
use std::path::{Path, PathBuf};

use relreward_proto::tensor;
use relreward_proto::upload::MemorySource;

use crate::episodes::Walls;
use crate::npz_write::NpzWriter;

/// How closely (Pearson correlation) a column must track another's per-row change to count as
/// its velocity ([`Trajectories::velocity_columns`]). MuJoCo's PointMaze, relreward's maze
/// generator and any explicit or semi-implicit Euler integrator give 0.99 or more; 0.9 leaves
/// room for noise while a position against its own neighbour's change stays far below.
pub const VELOCITY_CORRELATION: f64 = 0.9;

/// Rows of observations and actions with their episode flags, as D4RL lays them out.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trajectories {
    /// `[N, obs_dim]`, row-major.
    pub observations: Vec<f32>,
    pub obs_dim: usize,
    /// `[N, act_dim]`, row-major.
    pub actions: Vec<f32>,
    pub act_dim: usize,
    /// `[N]` or empty: the episode ended (reached a terminal state) after this row.
    pub terminals: Vec<bool>,
    /// `[N]` or empty: the episode was cut (time limit) after this row.
    pub timeouts: Vec<bool>,
    /// `[N]` or empty: an episode starts at this row.
    pub episode_starts: Vec<bool>,
    /// Maze walls found in the file.
    pub walls: Option<Walls>,
    /// The file's `goals` array (shape, values as float32): `[w]` one goal for every row, or
    /// `[N, w]` one per row. Not uploaded (the server trains on states and actions), but
    /// carried by every conversion ([`Trajectories::write_npz`],
    /// [`Trajectories::absorb_terminals`]) because the evaluation reads the true goal from it
    /// (`extract`'s default for `--goal`, `eval heatmap --goal-from`).
    pub goals: Option<(Vec<u64>, Vec<f32>)>,
    /// What the reader left out, for a note to the user (keys, groups).
    pub ignored: Vec<String>,
    /// Other things the reader did that the user should hear of (e.g. empty Minari episodes
    /// skipped), one sentence each.
    pub notes: Vec<String>,
}

impl Trajectories {
    /// Rows (transitions).
    pub fn len(&self) -> usize {
        self.observations.len().checked_div(self.obs_dim).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Row ranges of the episodes: a row starts one where `episode_starts` says so or after a
    /// `terminals` / `timeouts` row (the server's rule too).
    pub fn episodes(&self) -> Vec<std::ops::Range<usize>> {
        let n = self.len();
        let mut out = Vec::new();
        let mut start = 0;
        for t in 0..n {
            let end_here = self.terminals.get(t).copied().unwrap_or(false)
                || self.timeouts.get(t).copied().unwrap_or(false)
                || self.episode_starts.get(t + 1).copied().unwrap_or(false);
            if end_here || t + 1 == n {
                out.push(start..t + 1);
                start = t + 1;
            }
        }
        out
    }

    /// The observation coordinates that are velocities, by a rule that needs no names: column
    /// `j` is the velocity of column `i != j` when, over consecutive rows inside episodes, the
    /// change of `i` (`obs[t + 1][i] - obs[t][i]`) correlates with the mean of `j` over the two
    /// rows (`(obs[t][j] + obs[t + 1][j]) / 2`, the midpoint rule of integration) at
    /// [`VELOCITY_CORRELATION`] or more. Why this rule: whatever the simulator, time step or
    /// units, a position integrates its velocity, so the per-row change of a position is its
    /// velocity times a constant step; positions, angles and other state do not predict a
    /// change that way. Columns that never change are left out. Used by `extract --absorbing`
    /// to put the held state at rest (`--velocity-columns` overrides it).
    pub fn velocity_columns(&self) -> Vec<usize> {
        let d = self.obs_dim;
        // Sums for the correlation of every (change of i, value of j) pair.
        let (mut n, mut sx, mut sxx) = (0f64, vec![0f64; d], vec![0f64; d]);
        let (mut sy, mut syy, mut sxy) = (vec![0f64; d], vec![0f64; d], vec![0f64; d * d]);
        for ep in self.episodes() {
            for t in ep.start..ep.end.saturating_sub(1) {
                let (a, b) = (&self.observations[t * d..(t + 1) * d], &self.observations[(t + 1) * d..(t + 2) * d]);
                n += 1.0;
                for i in 0..d {
                    let x = f64::from(b[i]) - f64::from(a[i]);
                    let y = (f64::from(a[i]) + f64::from(b[i])) / 2.0;
                    sx[i] += x;
                    sxx[i] += x * x;
                    sy[i] += y;
                    syy[i] += y * y;
                }
                for i in 0..d {
                    let x = f64::from(b[i]) - f64::from(a[i]);
                    for j in 0..d {
                        sxy[i * d + j] += x * (f64::from(a[j]) + f64::from(b[j])) / 2.0;
                    }
                }
            }
        }
        if n < 3.0 {
            return Vec::new();
        }
        let var = |s: f64, ss: f64| (ss / n - (s / n).powi(2)).max(0.0);
        let mut out = Vec::new();
        for j in 0..d {
            let vy = var(sy[j], syy[j]);
            let is_velocity = (0..d).filter(|&i| i != j).any(|i| {
                let vx = var(sx[i], sxx[i]);
                if vx <= 0.0 || vy <= 0.0 {
                    return false;
                }
                let cov = sxy[i * d + j] / n - (sx[i] / n) * (sy[j] / n);
                cov / (vx * vy).sqrt() >= VELOCITY_CORRELATION
            });
            if is_velocity {
                out.push(j);
            }
        }
        out
    }

    /// Treats terminal states as absorbing (`extract --absorbing N`): each episode that ends
    /// with a `terminals` row gets `n` more rows holding its last observation with zero action
    /// and the coordinates in `at_rest` (velocities, [`Trajectories::velocity_columns`]) set
    /// to zero, the last of them flagged terminal. Why: in an MDP a terminal state is absorbing
    /// (the agent stays there forever), but goal-terminated demonstrations stop recording at
    /// it, so the expert's data holds the goal for one row only and a reward fitted to it
    /// learns the approach (motion toward the goal) rather than the goal (docs/results.md,
    /// issue 19). Padding restores the time the expert would spend there; an agent that stays
    /// somewhere does not move, so its velocities are zero (repeating the arrival row instead
    /// would hold a point that moves fast without moving, a state no data resembles).
    /// Per-row `goals` (`[N, w]`) get the held row's goal on each added row, so they stay row
    /// aligned; any other `goals` (one `[w]` goal) is kept as it is, as are the walls.
    pub fn absorb_terminals(&mut self, n: usize, at_rest: &[usize]) {
        if n == 0 || self.terminals.is_empty() {
            return;
        }
        let episodes = self.episodes();
        let (od, ad) = (self.obs_dim, self.act_dim);
        // Goals with one row per row are padded with the rows; a single goal needs nothing.
        let goal_rows = match &self.goals {
            Some((shape, values)) if shape.len() == 2 && shape[0] as usize == self.len() => {
                Some((shape[1] as usize, values))
            }
            _ => None,
        };
        let mut goals_out: Vec<f32> = Vec::new();
        let mut out = Trajectories {
            obs_dim: od,
            act_dim: ad,
            walls: self.walls.clone(),
            goals: self.goals.clone(),
            ignored: self.ignored.clone(),
            notes: self.notes.clone(),
            ..Default::default()
        };
        let flag = |v: &Vec<bool>, t: usize| v.get(t).copied().unwrap_or(false);
        for ep in episodes {
            for t in ep.clone() {
                out.observations.extend_from_slice(&self.observations[t * od..(t + 1) * od]);
                out.actions.extend_from_slice(&self.actions[t * ad..(t + 1) * ad]);
                out.terminals.push(flag(&self.terminals, t));
                out.timeouts.push(flag(&self.timeouts, t));
                out.episode_starts.push(t == ep.start);
            }
            if let Some((w, values)) = goal_rows {
                goals_out.extend_from_slice(&values[ep.start * w..ep.end * w]);
            }
            let last = ep.end - 1;
            if flag(&self.terminals, last) {
                *out.terminals.last_mut().expect("an episode has rows") = false;
                let mut held = self.observations[last * od..(last + 1) * od].to_vec();
                for &j in at_rest.iter().filter(|&&j| j < od) {
                    held[j] = 0.0;
                }
                for k in 0..n {
                    out.observations.extend_from_slice(&held);
                    out.actions.extend(std::iter::repeat_n(0.0, ad));
                    out.terminals.push(k + 1 == n);
                    out.timeouts.push(false);
                    out.episode_starts.push(false);
                    if let Some((w, values)) = goal_rows {
                        goals_out.extend_from_slice(&values[last * w..(last + 1) * w]);
                    }
                }
            }
        }
        if let Some((w, _)) = goal_rows {
            out.goals = Some((vec![out.len() as u64, w as u64], goals_out));
        }
        *self = out;
    }

    /// Reads a trajectories `.npz` whole (through [`crate::npz::trajectories_from_npz`], so
    /// with the same rules) plus its walls and `goals` (any numeric dtype, read as float32;
    /// refused unless finite).
    pub fn from_npz(path: &Path) -> io::Result<Self> {
        let mut source = crate::npz::trajectories_from_npz(path).map_err(io::Error::other)?;
        let specs = relreward_proto::upload::UploadSource::arrays(&source).to_vec();
        let bad = |name: &str, e: String| {
            io::Error::new(io::ErrorKind::InvalidData, format!("{}: '{name}': {e}", path.display()))
        };
        let mut t = Trajectories { ignored: source.ignored_keys().to_vec(), ..Default::default() };
        for (i, spec) in specs.iter().enumerate() {
            let tensor = source.read_tensor(i)?;
            let width = spec.shape.get(1).copied().unwrap_or(1) as usize;
            match spec.name.as_str() {
                "observations" => {
                    t.observations = tensor::decode_finite_f32(&tensor).map_err(|e| bad(&spec.name, e.to_string()))?;
                    t.obs_dim = width;
                }
                "actions" => {
                    t.actions = tensor::decode_finite_f32(&tensor).map_err(|e| bad(&spec.name, e.to_string()))?;
                    t.act_dim = width;
                }
                name => {
                    let flags = tensor::decode_flags(&tensor).map_err(|e| bad(name, e.to_string()))?;
                    match name {
                        "terminals" => t.terminals = flags,
                        "timeouts" => t.timeouts = flags,
                        _ => t.episode_starts = flags,
                    }
                }
            }
        }
        t.walls = crate::npz::walls_from_npz(path)?;
        if let Some((shape, values)) =
            crate::npz::read_numbers(path, "goals").map_err(|e| bad("goals", e.to_string()))?
        {
            let goals: Vec<f32> = values.iter().map(|&v| v as f32).collect();
            if let Some(i) = goals.iter().position(|v| !v.is_finite()) {
                return Err(bad("goals", format!("value {} at flat index {i} is not finite as float32", values[i])));
            }
            t.goals = Some((shape, goals));
        }
        Ok(t)
    }

    /// The arrays as an upload: `observations`, `actions` float32, then whichever flags exist.
    pub fn upload_source(&self) -> MemorySource {
        let n = self.len() as u64;
        let mut source = MemorySource::new();
        source.push_f32("observations", &[n, self.obs_dim as u64], &self.observations);
        source.push_f32("actions", &[n, self.act_dim as u64], &self.actions);
        for (name, flags) in
            [("terminals", &self.terminals), ("timeouts", &self.timeouts), ("episode_starts", &self.episode_starts)]
        {
            if !flags.is_empty() {
                source.push_bool(name, flags);
            }
        }
        source
    }

    /// Writes the canonical `.npz`: the upload's arrays plus `walls` (bool `[rows, cols]`) and
    /// `goals` (float32, their shape) when known: what the evaluation reads besides the rows.
    pub fn write_npz(&self, dest: &Path) -> io::Result<PathBuf> {
        let n = self.len() as u64;
        let mut w = NpzWriter::create(dest)?;
        w.add_f32("observations", &[n, self.obs_dim as u64], &self.observations)?;
        w.add_f32("actions", &[n, self.act_dim as u64], &self.actions)?;
        for (name, flags) in
            [("terminals", &self.terminals), ("timeouts", &self.timeouts), ("episode_starts", &self.episode_starts)]
        {
            if !flags.is_empty() {
                w.add_bool(name, &[n], flags)?;
            }
        }
        if let Some((rows, cols, walls)) = &self.walls {
            w.add_bool("walls", &[*rows as u64, *cols as u64], walls)?;
        }
        if let Some((shape, values)) = &self.goals {
            w.add_f32("goals", shape, values)?;
        }
        w.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episodes_end_at_flags_and_start_at_starts() {
        let t = Trajectories {
            observations: vec![0.0; 7],
            obs_dim: 1,
            actions: vec![0.0; 7],
            act_dim: 1,
            terminals: vec![false, true, false, false, false, false, false],
            timeouts: vec![],
            episode_starts: vec![true, false, false, false, true, false, false],
            ..Default::default()
        };
        assert_eq!(t.episodes(), vec![0..2, 2..4, 4..7]);
    }

    #[test]
    fn terminal_states_become_absorbing() {
        let mut t = Trajectories {
            observations: vec![0.0, 1.0, 2.0, 3.0, 4.0],
            obs_dim: 1,
            actions: vec![9.0; 5],
            act_dim: 1,
            terminals: vec![false, true, false, false, false],
            timeouts: vec![false, false, false, false, true],
            ..Default::default()
        };
        t.absorb_terminals(3, &[]);
        // Episode 0..2 ends at a terminal: held 3 more rows; episode 2..5 (a timeout) is not.
        assert_eq!(t.observations, [0.0, 1.0, 1.0, 1.0, 1.0, 2.0, 3.0, 4.0]);
        assert_eq!(t.actions, [9.0, 9.0, 0.0, 0.0, 0.0, 9.0, 9.0, 9.0]);
        assert_eq!(t.episodes(), vec![0..5, 5..8]);
        assert_eq!(t.terminals.iter().filter(|&&b| b).count(), 1);
        assert!(t.terminals[4]);
    }

    #[test]
    fn held_terminal_states_are_at_rest_in_the_named_columns() {
        // [x, v]: the episode arrives at x = 2 moving at v = 5; held, it stays at x = 2, v = 0.
        let mut t = Trajectories {
            observations: vec![0.0, 5.0, 2.0, 5.0],
            obs_dim: 2,
            actions: vec![1.0; 2],
            act_dim: 1,
            terminals: vec![false, true],
            ..Default::default()
        };
        t.absorb_terminals(2, &[1, 7]);
        assert_eq!(t.observations, [0.0, 5.0, 2.0, 5.0, 2.0, 0.0, 2.0, 0.0]);
        assert_eq!(t.actions, [1.0, 1.0, 0.0, 0.0]);
    }

    /// Issue 34 item 4: goals survive the absorbing conversion and the `.npz` round trip (the
    /// evaluation reads the true goal from the converted file). Per-row goals stay row aligned
    /// (the held rows carry the held row's goal), a single goal is kept as it is.
    #[test]
    fn absorbing_and_writing_keep_the_goals() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut t = Trajectories {
            observations: vec![0.0, 1.0, 2.0, 3.0, 4.0],
            obs_dim: 1,
            actions: vec![9.0; 5],
            act_dim: 1,
            terminals: vec![false, true, false, false, true],
            walls: Some((1, 2, vec![true, false])),
            goals: Some((vec![5, 2], vec![3.0, 4.0, 3.0, 4.0, 5.0, 6.0, 5.0, 6.0, 5.0, 6.0])),
            ..Default::default()
        };
        let path = t.write_npz(&dir.path().join("in.npz")).expect("write");
        assert_eq!(Trajectories::from_npz(&path).expect("read").goals, t.goals, "written and read back");
        t.absorb_terminals(2, &[]);
        let per_row = [3.0, 4.0, 3.0, 4.0, 3.0, 4.0, 3.0, 4.0, 5.0, 6.0, 5.0, 6.0, 5.0, 6.0, 5.0, 6.0, 5.0, 6.0];
        assert_eq!(t.goals, Some((vec![9, 2], per_row.to_vec())));
        let out = t.write_npz(&dir.path().join("absorbed.npz")).expect("write");
        let back = Trajectories::from_npz(&out).expect("read");
        assert_eq!((back.len(), back.goals, back.walls), (9, t.goals.clone(), t.walls.clone()));

        // One goal for the whole file: kept unchanged.
        let mut one = Trajectories {
            observations: vec![0.0, 1.0],
            obs_dim: 1,
            actions: vec![0.0; 2],
            act_dim: 1,
            terminals: vec![false, true],
            goals: Some((vec![2], vec![7.0, 8.0])),
            ..Default::default()
        };
        one.absorb_terminals(3, &[]);
        assert_eq!((one.len(), one.goals.clone()), (5, Some((vec![2], vec![7.0, 8.0]))));
        let back = Trajectories::from_npz(&one.write_npz(&dir.path().join("one.npz")).expect("write")).expect("read");
        assert_eq!(back.goals, one.goals);
    }

    /// A damped point mass under random pushes, integrated semi-implicitly (as MuJoCo does)
    /// with an unrelated slowly drifting coordinate: `[x, y, phase, vx, vy]`.
    fn point_mass(rows: usize, seed: u64) -> Trajectories {
        let mut rng = crate::maze::Rng::new(seed);
        let (dt, mut x, mut v, mut phase) = (0.01f64, [0.0f64; 2], [0.0f64; 2], 0.0f64);
        let mut obs = Vec::new();
        let mut timeouts = Vec::new();
        for t in 0..rows {
            obs.extend([x[0], x[1], phase, v[0], v[1]].map(|c| c as f32));
            timeouts.push(t % 100 == 99);
            for k in 0..2 {
                v[k] += dt * (50.0 * (rng.uniform() - 0.5) - 2.0 * v[k]);
                x[k] += dt * v[k];
            }
            phase += 0.001 * (rng.uniform() - 0.3);
        }
        Trajectories {
            observations: obs,
            obs_dim: 5,
            actions: vec![0.0; rows],
            act_dim: 1,
            timeouts,
            ..Default::default()
        }
    }

    #[test]
    fn velocities_are_the_columns_that_predict_a_change() {
        assert_eq!(point_mass(3000, 1).velocity_columns(), vec![3, 4]);
        // Columns permuted ([vy, phase, x, vx, y]): found where they are, not by position.
        let t = point_mass(3000, 2);
        let mut p = t.clone();
        for (r, row) in t.observations.chunks_exact(5).enumerate() {
            p.observations[r * 5..(r + 1) * 5].copy_from_slice(&[row[4], row[2], row[0], row[3], row[1]]);
        }
        assert_eq!(p.velocity_columns(), vec![0, 3]);
        // No velocities (positions alone, a random walk): none found.
        let mut q = t.clone();
        q.observations = t.observations.chunks_exact(5).flat_map(|r| [r[0], r[1], r[2]]).collect();
        q.obs_dim = 3;
        assert!(q.velocity_columns().is_empty());
    }
}
