//! [`Trajectories`]: a trajectory dataset held in memory, the form every reader that has to
//! convert (HDF5, Minari episodes) produces. It becomes an upload
//! ([`Trajectories::upload_source`]) or the project's canonical `.npz`
//! ([`Trajectories::write_npz`]), which the commands that read windows from files (`score`,
//! `eval`, `extract`) take directly.

use std::io;
use std::path::{Path, PathBuf};

use relreward_client::tensor;
use relreward_client::upload::MemorySource;

use crate::episodes::Walls;
use crate::npz_write::NpzWriter;

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
    /// What the reader left out, for a note to the user (keys, groups).
    pub ignored: Vec<String>,
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

    /// Treats terminal states as absorbing (`extract --absorbing N`): each episode that ends
    /// with a `terminals` row gets `n` more rows holding its last observation with zero action,
    /// the last of them flagged terminal. Why: in an MDP a terminal state is absorbing (the
    /// agent stays there forever), but goal-terminated demonstrations stop recording at it, so
    /// the expert's data holds the goal for one row only and a reward fitted to it learns the
    /// approach (motion toward the goal) rather than the goal (docs/results.md, issue 19).
    /// Padding restores the time the expert would spend there.
    pub fn absorb_terminals(&mut self, n: usize) {
        if n == 0 || self.terminals.is_empty() {
            return;
        }
        let episodes = self.episodes();
        let (od, ad) = (self.obs_dim, self.act_dim);
        let mut out = Trajectories {
            obs_dim: od,
            act_dim: ad,
            walls: self.walls.clone(),
            ignored: self.ignored.clone(),
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
            let last = ep.end - 1;
            if flag(&self.terminals, last) {
                *out.terminals.last_mut().expect("an episode has rows") = false;
                for k in 0..n {
                    out.observations.extend_from_slice(&self.observations[last * od..(last + 1) * od]);
                    out.actions.extend(std::iter::repeat_n(0.0, ad));
                    out.terminals.push(k + 1 == n);
                    out.timeouts.push(false);
                    out.episode_starts.push(false);
                }
            }
        }
        *self = out;
    }

    /// Reads a trajectories `.npz` whole (through [`crate::npz::trajectories_from_npz`], so
    /// with the same rules) plus its walls.
    pub fn from_npz(path: &Path) -> io::Result<Self> {
        let mut source = crate::npz::trajectories_from_npz(path).map_err(io::Error::other)?;
        let specs = relreward_client::UploadSource::arrays(&source).to_vec();
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

    /// Writes the canonical `.npz`: the upload's arrays plus `walls` (bool `[rows, cols]`) when
    /// known.
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
        t.absorb_terminals(3);
        // Episode 0..2 ends at a terminal: held 3 more rows; episode 2..5 (a timeout) is not.
        assert_eq!(t.observations, [0.0, 1.0, 1.0, 1.0, 1.0, 2.0, 3.0, 4.0]);
        assert_eq!(t.actions, [9.0, 9.0, 0.0, 0.0, 0.0, 9.0, 9.0, 9.0]);
        assert_eq!(t.episodes(), vec![0..5, 5..8]);
        assert_eq!(t.terminals.iter().filter(|&&b| b).count(), 1);
        assert!(t.terminals[4]);
    }
}
