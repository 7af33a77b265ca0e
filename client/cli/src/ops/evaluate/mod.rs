//! The paper's evaluation of a reward over local files, computed here from the server's
//! `Score` (the math and the drawing are [`relreward_toolkit::eval`]'s, whose module docs cite
//! the paper passage behind each step; the scores reach it through its `Scorer`, implemented by
//! [`super::scoring::ServerScorer`]).
//!
//! Inputs are local files read as [`super::items`] reads them: a D4RL-style trajectories `.npz`
//! cut into the reward model's `[H, D]` windows (`stride` rows apart, never across an episode
//! end), or an `.npz` holding `x` `[B, H, D]`. Every subset is drawn from the seed, so a run is
//! reproduced exactly.
//!
//! - [`discriminate`]: a balanced, seeded subset of windows of a base and an expert file,
//!   winsorized, split 80/20, a logistic regression on the reward alone; held-out (balanced)
//!   accuracy, AUC, each class's mean reward, and optionally both classes' histograms.
//! - [`heatmap`]: the sub-trajectories of a (base) dataset, or the maze held at rest, scored,
//!   winsorized and scaled, averaged per 2D bin, masked where sparse, drawn with walls and goal;
//!   whether the smoothed maximum lies within one cell of the goal.
//! - [`plot`]: a job's loss curve (and held-out loss) from its events; optionally a histogram
//!   of a reward over the windows of datasets.
//!
//! This module holds what the three share: reading a file's items for a model, seeded subsets,
//! scoring them, and the maze's walls and goal in files. Errors name the flag each input comes
//! from on the command line (`--base-data`, `--dataset`, ...).

pub mod discriminate;
pub mod heatmap;
pub mod plot;

use std::path::Path;

use anyhow::{Context, Result, anyhow, bail};
use relreward_client::{Client, pb};
use relreward_toolkit::eval::scorer::{ScoreError, Scores, score_all};
use relreward_toolkit::npz;

use super::Progress;
use super::items::{Items, ItemsQuery, read_items, request_batch};
use super::scoring::{IN_FLIGHT, ServerScorer};
use crate::UsageError;
use crate::output::item_bar;

/// Histogram bins of the reward pictures.
pub const HISTOGRAM_BINS: usize = 40;

/// Items per Score request unless asked otherwise.
pub const DEFAULT_BATCH: u64 = 256;

/// What every scoring evaluation shares: the model, diffusion time, windowing, subset and batch.
#[derive(Debug, Clone)]
pub struct Scoring {
    /// Reward (or discriminator) model.
    pub model: String,
    /// Diffusion time of every scored item (0: clean trajectories, as the paper evaluates).
    pub t: u32,
    /// Trajectory files: rows between the starts of consecutive windows (`None`: each
    /// evaluation's default).
    pub stride: Option<u64>,
    /// Seed of the random subsets and of the train/test split.
    pub seed: u64,
    /// Items per Score request.
    pub batch: u64,
}

impl Scoring {
    /// `model` at t = 0, default strides, seed 0, [`DEFAULT_BATCH`].
    pub fn new(model: &str) -> Self {
        Self { model: model.to_owned(), t: 0, stride: None, seed: 0, batch: DEFAULT_BATCH }
    }
}

/// `read_items`' errors name `--input`; ours name the flag the file came from.
fn relabel(err: anyhow::Error, flag: &str) -> anyhow::Error {
    let text = err.to_string();
    let Some(rest) = text.strip_prefix("--input") else { return err };
    let text = format!("{flag}{rest}");
    if err.downcast_ref::<UsageError>().is_some() { UsageError(text).into() } else { anyhow!(text) }
}

/// The items of `path` for `model` (see the module docs), with `flag` in every error.
async fn load_items(client: &Client, model: &str, path: &Path, flag: &str, stride: Option<u64>) -> Result<Items> {
    let kind = npz::detect_kind(path).map_err(|e| anyhow!("{flag}: {e}"))?;
    // A stride only means something for trajectories; read_items refuses it for arrays, naming
    // --stride, which is what the user typed.
    let stride = if kind == pb::DatasetKind::Trajectories { stride.or(Some(1)) } else { stride };
    let query = ItemsQuery { model: model.to_owned(), input: path.to_owned(), key: None, stride };
    read_items(client, &query).await.map_err(|e| relabel(e, &format!("{flag} {}", path.display())))
}

/// Items `idx` of `items` (in that order).
fn subset(items: Items, idx: &[usize]) -> Items {
    match items {
        Items::Windows(mut w) => {
            w.starts = idx.iter().map(|&i| w.starts[i]).collect();
            Items::Windows(w)
        }
        Items::Array { key, values, item_shape } => {
            let per = item_shape.iter().product::<u64>() as usize;
            let values = idx.iter().flat_map(|&i| values[i * per..(i + 1) * per].iter().copied()).collect();
            Items::Array { key, values, item_shape }
        }
    }
}

/// The `[H, D]` rows of item `k`, row-major.
fn item_rows(items: &Items, k: usize) -> &[f32] {
    match items {
        Items::Windows(w) => &w.rows[w.starts[k] * w.dim..(w.starts[k] + w.horizon) * w.dim],
        Items::Array { values, item_shape, .. } => {
            let per = item_shape.iter().product::<u64>() as usize;
            &values[k * per..(k + 1) * per]
        }
    }
}

/// Scores every item of `items` with the model at diffusion time `t`, `batch` items a request
/// (two in flight), with a progress bar; `flag` labels errors about the items.
async fn score_items(
    progress: &dyn Progress,
    client: &Client,
    scoring: &Scoring,
    items: &Items,
    flag: &str,
    per_window: bool,
) -> Result<Scores> {
    let n = items.len();
    let batch = request_batch(scoring.batch, items.item_len() as u64 * 4, progress.quiet());
    let fields = vec![
        ("model", format!("--model {}", scoring.model)),
        ("x", flag.to_owned()),
        ("t", format!("--t {}", scoring.t)),
        ("per_window", "--unit window".to_owned()),
    ];
    let scorer = ServerScorer { client, model: &scoring.model, t: scoring.t, items, fields, several: n > batch };
    let bar = item_bar(progress.quiet(), n as u64, "windows");
    let scores = score_all(&scorer, n, batch, IN_FLIGHT, per_window, |b| bar.inc(b as u64)).await;
    bar.finish_and_clear();
    scores.map_err(|e| match e {
        ScoreError::Scorer { error, .. } => error,
        ScoreError::NonFinite(bad) => anyhow!("the server returned a non-finite reward ({bad}) for {flag}"),
        ScoreError::Shape { .. } => anyhow!("the server's answer: {e}"),
    })
}

/// A seeded subset of the items of a file, and their scores.
struct Scored {
    items: Items,
    /// Items in the file before the subset was drawn.
    available: usize,
    rewards: Vec<f64>,
    per_window: Option<(usize, Vec<f64>)>,
}

async fn score_subset(
    progress: &dyn Progress,
    client: &Client,
    scoring: &Scoring,
    items: Items,
    idx: &[usize],
    flag: &str,
    per_window: bool,
) -> Result<Scored> {
    let available = items.len();
    let items = subset(items, idx);
    let scores = score_items(progress, client, scoring, &items, flag, per_window).await?;
    Ok(Scored { items, available, rewards: scores.rewards, per_window: scores.per_window })
}

/// A file's name for picture legends.
pub fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}

/// One numeric array of an `.npz` (or a plain `.npy`) as f64 with its shape; `None` when an
/// archive has no such array (see [`npz::read_numbers`]).
fn read_numbers(path: &Path, key: &str) -> Result<Option<(Vec<u64>, Vec<f64>)>> {
    npz::read_numbers(path, key).with_context(|| format!("{}: array '{key}'", path.display()))
}

/// The maze walls: `(rows, cols, flags)`.
pub type Walls = relreward_toolkit::episodes::Walls;

/// The walls of a file (`walls`, `wall_map` or `maze_map`; rule: relreward_toolkit::episodes);
/// `required` makes their absence an error naming `--walls`.
pub fn walls_of(path: &Path, required: bool) -> Result<Option<Walls>> {
    let walls = npz::walls_from_npz(path).with_context(|| format!("{}: maze walls", path.display()))?;
    if walls.is_none() && required {
        bail!("--walls {}: no 'walls', 'wall_map' or 'maze_map' array", path.display())
    }
    Ok(walls)
}

/// The goal of a file's `goals` ([2], [N, >=2]): `Ok(None)` when absent or not constant.
pub fn constant_goal(path: &Path) -> Result<Option<(f64, f64)>> {
    let Some((shape, values)) = read_numbers(path, "goals")? else { return Ok(None) };
    let width = match shape.as_slice() {
        [w] if *w >= 2 => *w as usize,
        [_, w] if *w >= 2 => *w as usize,
        _ => bail!("{}: 'goals' has shape {shape:?}; expected [2] or [N, 2]", path.display()),
    };
    let mut rows = values.chunks_exact(width).map(|r| (r[0], r[1]));
    let Some(first) = rows.next() else { return Ok(None) };
    let constant = rows.all(|g| (g.0 - first.0).abs() <= 1e-6 && (g.1 - first.1).abs() <= 1e-6);
    Ok(constant.then_some(first))
}

/// Observation width of a trajectories file (its `observations` header): the values per row,
/// trailing dimensions flattened as the readers do (`[N]` is 1).
fn obs_dim(path: &Path) -> Result<usize> {
    let shape = npz::npz_array_shape(path, "observations")
        .with_context(|| format!("--dataset {}", path.display()))?
        .ok_or_else(|| anyhow!("--dataset {}: no 'observations' array", path.display()))?;
    Ok(shape.iter().skip(1).product::<u64>() as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_the_flag_the_file_came_from() {
        let e = relabel(anyhow!("--input: no 'actions' array"), "--base-data a.npz");
        assert_eq!(e.to_string(), "--base-data a.npz: no 'actions' array");
        let e = relabel(UsageError("--input x: bad".into()).into(), "--dataset");
        assert!(e.downcast_ref::<UsageError>().is_some());
        let e = relabel(anyhow!("--model r: NOT_FOUND"), "--dataset");
        assert_eq!(e.to_string(), "--model r: NOT_FOUND");
    }

    #[test]
    fn subsets_and_rows_of_items() {
        use super::super::items::Windows;
        // 2 columns, rows 0..6 of one episode, windows of 3 rows at every row.
        let rows: Vec<f32> = (0..12).map(|v| v as f32).collect();
        let w = Windows { rows, dim: 2, horizon: 3, starts: vec![0, 1, 2, 3], stride: 1, episodes: 1 };
        let items = subset(Items::Windows(w), &[3, 1]);
        assert_eq!(items.len(), 2);
        assert_eq!(item_rows(&items, 0), &[6.0, 7.0, 8.0, 9.0, 10.0, 11.0]);
        assert_eq!(item_rows(&items, 1), &[2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        let array =
            Items::Array { key: "x".into(), values: (0..8).map(|v| v as f32).collect(), item_shape: vec![2, 2] };
        let items = subset(array, &[1]);
        assert_eq!((items.len(), item_rows(&items, 0)), (1, &[4.0, 5.0, 6.0, 7.0][..]));
    }

    #[test]
    fn arrays_of_any_numeric_dtype_are_read() {
        use relreward_toolkit::npz_write::NpzWriter;
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("maze.npz");
        let mut w = NpzWriter::create(&path).expect("create");
        w.add_bool("walls", &[2, 3], &[true, false, true, false, false, true]).expect("walls");
        w.add_f32("goals", &[3, 2], &[1.0, 2.0, 1.0, 2.0, 1.0, 2.0]).expect("goals");
        w.add_i64("other", &[2], &[4, 5]).expect("i64");
        w.finish().expect("finish");
        assert_eq!(walls_of(&path, true).expect("walls"), Some((2, 3, vec![true, false, true, false, false, true])));
        assert_eq!(constant_goal(&path).expect("goals"), Some((1.0, 2.0)));
        assert_eq!(read_numbers(&path, "other").expect("i64"), Some((vec![2], vec![4.0, 5.0])));
        assert_eq!(read_numbers(&path, "missing").expect("absent"), None);
        let varying = dir.path().join("varying.npz");
        let mut w = NpzWriter::create(&varying).expect("create");
        w.add_f32("goals", &[2, 2], &[1.0, 2.0, 3.0, 2.0]).expect("goals");
        w.finish().expect("finish");
        assert_eq!(constant_goal(&varying).expect("goals"), None);
        assert!(walls_of(&varying, true).is_err());
        assert_eq!(walls_of(&varying, false).expect("none"), None);
    }
}
