//! A trajectory archive's rewards replaced by a reward model's ([`relabel`]), for offline RL:
//! the same `.npz` back with `rewards` the model's and the file's own kept as
//! `rewards_original`, every other member copied byte for byte.
//!
//! The reward of row i is the model's value of the H-row window that ends at row i (the last
//! entry of `per_window`: for a windowed reward of window h, rho of rows i-h+1..i). Rows before
//! the episode's first row are that first observation with zero actions. This is the rule of
//! the Python package's `relreward.relabel` and its online wrapper (`docs/relabel.md`), so the
//! CLI, Python and a policy trained online see the same reward.
//!
//! Everything is checked and scored before anything is written; the archive appears at the
//! output only once complete. HDF5 (D4RL, Minari) is relabelled by the Python package, which
//! writes HDF5; the CLI refuses it with that pointer.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use relreward_client::{Client, pb, tensor};
use relreward_toolkit::npz::{self, NpzSource};
use relreward_toolkit::npz_write::NpzWriter;
use serde::Serialize;

use super::Progress;
use super::items::{Trajectories, batches, read_trajectories, reward_info};
use super::scoring::floats;
use crate::UsageError;

/// Where the file's own rewards are kept.
pub const ORIGINAL: &str = "rewards_original";

/// What to relabel, with what, and where to write it.
#[derive(Debug, Clone)]
pub struct RelabelQuery {
    pub model: String,
    pub input: PathBuf,
    pub output: PathBuf,
    /// Diffusion time the windows are scored at (0: clean data).
    pub t: u32,
    /// Windows per Score request.
    pub batch: usize,
    pub overwrite: bool,
}

/// What was written.
#[derive(Debug, Clone, Serialize)]
pub struct Relabelled {
    pub output: PathBuf,
    pub rows: usize,
    pub episodes: usize,
    /// The member the file's own rewards were kept under (`None`: it had none).
    pub original: Option<String>,
    pub mean: f64,
    pub min: f32,
    pub max: f32,
}

/// Checks the paths before any reading: a `.npz` input that exists, an output that is not the
/// input and does not exist (unless `overwrite`), in a folder that does.
fn check_paths(q: &RelabelQuery) -> Result<()> {
    let input = &q.input;
    if !input.is_file() {
        bail!(UsageError(format!("--input {}: no such file", input.display())));
    }
    let ext = |p: &Path| p.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    match ext(input).as_deref() {
        Some("npz") => {}
        Some("hdf5" | "h5") => bail!(UsageError(format!(
            "--input {}: HDF5 (D4RL, Minari) is relabelled by the Python package, which writes HDF5 back: \
             relreward.relabel(client, model, src, dst) (docs/relabel.md); the CLI relabels .npz archives",
            input.display()
        ))),
        _ => bail!(UsageError(format!(
            "--input {}: not an .npz archive of trajectories (observations, actions, terminals, timeouts)",
            input.display()
        ))),
    }
    if ext(&q.output).as_deref() != Some("npz") {
        bail!(UsageError(format!("--output {}: must end in .npz (the input's form)", q.output.display())));
    }
    let same = match (input.canonicalize(), q.output.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if same {
        bail!(UsageError("--output: is --input; write the relabelled archive to a new file".into()));
    }
    if q.output.exists() && !q.overwrite {
        bail!(UsageError(format!("--output {}: exists; pass --overwrite to replace it", q.output.display())));
    }
    let folder = q.output.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !folder.is_dir() {
        bail!(UsageError(format!("--output {}: no folder {}", q.output.display(), folder.display())));
    }
    if q.batch == 0 {
        bail!(UsageError("--batch: must be at least 1".into()));
    }
    Ok(())
}

/// The first row of row i's episode, for every row.
fn episode_firsts(episodes: &[Range<usize>], n: usize) -> Vec<usize> {
    let mut first = vec![0; n];
    for e in episodes {
        first[e.clone()].fill(e.start);
    }
    first
}

/// The `[b, H, D]` windows ending at rows `range`, padded before each episode's first row with
/// that row's observation and zero actions.
fn windows(traj: &Trajectories, first: &[usize], horizon: usize, range: Range<usize>) -> Vec<f32> {
    let dim = traj.act_dim + traj.obs_dim;
    let mut out = Vec::with_capacity(range.len() * horizon * dim);
    for i in range {
        let f = first[i];
        for k in 0..horizon {
            // Row i - (H - 1) + k, or the padding where that is before the episode.
            match (i + 1 + k).checked_sub(horizon).filter(|&j| j >= f) {
                Some(j) => out.extend_from_slice(&traj.rows[j * dim..(j + 1) * dim]),
                None => {
                    out.extend(std::iter::repeat_n(0.0, traj.act_dim));
                    out.extend_from_slice(&traj.rows[f * dim + traj.act_dim..(f + 1) * dim]);
                }
            }
        }
    }
    out
}

/// Relabels `q.input` into `q.output` (see the module documentation).
pub async fn relabel(client: &Client, progress: &dyn Progress, q: &RelabelQuery) -> Result<Relabelled> {
    check_paths(q)?;
    let info = reward_info(client, &q.model).await?;
    let input_shape = info.input_shape;
    let &[horizon, dim] = input_shape.as_slice() else {
        bail!("--model {}: takes items of shape {input_shape:?}, not [H, D] trajectory windows", q.model);
    };
    let n_timesteps = info.n_timesteps;
    if n_timesteps > 0 && q.t >= n_timesteps {
        bail!(UsageError(format!("--t {}: outside 0..{n_timesteps} (model '{}' has T = {n_timesteps})", q.t, q.model)));
    }
    let (path, name) = (q.input.clone(), q.model.clone());
    let (traj, had_rewards, had_original) = tokio::task::spawn_blocking(move || -> Result<_> {
        let mut source: NpzSource = npz::trajectories_from_npz(&path).map_err(|e| anyhow!("--input: {e}"))?;
        let traj = read_trajectories(&mut source, &name, horizon, dim)?;
        let keys = npz::npz_keys(&path).map_err(|e| anyhow!("--input: {e}"))?;
        Ok((traj, keys.iter().any(|k| k == "rewards"), keys.iter().any(|k| k == ORIGINAL)))
    })
    .await
    .context("reading the input crashed")??;
    let n = traj.rows.len() / (dim as usize).max(1);
    if n == 0 {
        bail!("--input {}: holds no rows", q.input.display());
    }

    // Score everything first: a refusal half-way leaves no file behind.
    let first = episode_firsts(&traj.episodes, n);
    let mut rewards = Vec::with_capacity(n);
    let ranges = batches(n, q.batch);
    for (k, range) in ranges.iter().enumerate() {
        if !progress.quiet() && (k % 16 == 0 || k + 1 == ranges.len()) {
            progress.stage(&format!("scoring rows {}..{} of {n}", range.start, range.end));
        }
        let b = range.len() as u64;
        let x = tensor::encode_f32(&[b, horizon, dim], &windows(&traj, &first, horizon as usize, range.clone()));
        let request = pb::ScoreRequest {
            model: q.model.clone(),
            x: Some(x),
            t: vec![q.t],
            input_units: pb::Units::Raw as i32,
            per_window: true,
            per_step: false,
        };
        let answer =
            client.score(request).await.with_context(|| format!("scoring rows {}..{}", range.start, range.end))?;
        let width = match answer.per_window.as_ref() {
            Some(t) if t.shape.len() == 2 && t.shape[1] > 0 => t.shape[1],
            other => bail!("the server's answer has no per-window values [{b}, K] (got {:?})", other.map(|t| &t.shape)),
        };
        let values = floats(answer.per_window.as_ref(), "per_window", &[b, width])?;
        rewards.extend(values.chunks(width as usize).map(|w| w[w.len() - 1]));
    }

    let (input, output) = (q.input.clone(), q.output.clone());
    let written = rewards.clone();
    tokio::task::spawn_blocking(move || -> Result<()> {
        let mut out = NpzWriter::create(&output).with_context(|| format!("--output {}", output.display()))?;
        // The file's own rewards become the original, unless an earlier relabelling kept one.
        out.copy_members(&input, |array| match array {
            "rewards" if had_original => None,
            "rewards" => Some(ORIGINAL.to_owned()),
            other => Some(other.to_owned()),
        })
        .with_context(|| format!("copying {}", input.display()))?;
        out.add_f32("rewards", &[written.len() as u64], &written)?;
        out.finish().with_context(|| format!("--output {}", output.display()))?;
        Ok(())
    })
    .await
    .context("writing the output crashed")??;

    let mean = rewards.iter().map(|&r| f64::from(r)).sum::<f64>() / n as f64;
    Ok(Relabelled {
        output: q.output.clone(),
        rows: n,
        episodes: traj.episodes.len(),
        original: (had_rewards || had_original).then(|| ORIGINAL.to_owned()),
        mean,
        min: rewards.iter().copied().fold(f32::INFINITY, f32::min),
        max: rewards.iter().copied().fold(f32::NEG_INFINITY, f32::max),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_end_at_each_row_and_pad_episode_starts() {
        // Two episodes: rows 0..3 and 3..5; rows [a | o] with a = 10 i, o = i.
        let rows: Vec<f32> = (0..5).flat_map(|i| [10.0 * i as f32, i as f32]).collect();
        let traj = Trajectories { rows, act_dim: 1, obs_dim: 1, episodes: vec![0..3, 3..5] };
        let first = episode_firsts(&traj.episodes, 5);
        assert_eq!(first, [0, 0, 0, 3, 3]);
        let w = windows(&traj, &first, 3, 0..5);
        assert_eq!(&w[0..6], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "row 0: two pads then row 0 (all zero here)");
        assert_eq!(&w[6..12], [0.0, 0.0, 0.0, 0.0, 10.0, 1.0], "row 1: a pad, rows 0 and 1");
        assert_eq!(&w[12..18], [0.0, 0.0, 10.0, 1.0, 20.0, 2.0], "row 2: rows 0..3");
        assert_eq!(&w[18..24], [0.0, 3.0, 0.0, 3.0, 30.0, 3.0], "row 3: a new episode, padded with its own first obs");
        assert_eq!(&w[24..30], [0.0, 3.0, 30.0, 3.0, 40.0, 4.0]);
    }
}
