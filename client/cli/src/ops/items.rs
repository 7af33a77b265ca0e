//! Local files read as a reward model's items ([`Items`]): an array of items, or trajectories
//! cut into the model's `[H, D]` windows ([`Windows`]: rows are `[action | observation]` as in
//! Diffuser, a window is H consecutive rows of one episode, windows start every `stride` rows),
//! and the batches they are sent in. `score`, `grad` and the evaluation read their inputs here.
//!
//! Errors name `--input` (and `--key`, `--stride`, `--model`): the flags of `score` and
//! `grad`; the evaluation relabels them with the flag its file came from.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use relreward_client::{Client, UploadSource, pb, tensor};
use relreward_toolkit::npz::{self, NpzSource};
use serde::Serialize;

use crate::UsageError;
use crate::output::eprint_line;

/// Largest payload of one Score/Gradient request: half the server's default request limit
/// (16 MiB), leaving room for framing and for servers configured lower.
pub const MAX_REQUEST_BYTES: u64 = 8 << 20;

/// Consecutive ranges of at most `batch` items: the requests items are sent in.
pub use relreward_toolkit::eval::scorer::batches;

/// Which items to read: the file, which array (`key`) or, for trajectories, the windows'
/// `stride`, and the reward model whose item shape they must have.
#[derive(Debug, Clone)]
pub struct ItemsQuery {
    pub model: String,
    pub input: PathBuf,
    pub key: Option<String>,
    pub stride: Option<u64>,
}

/// Trajectory windows: `[H, D]` slices of consecutive rows within one episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Windows {
    /// `[N, D]` rows, `[action | observation]`, float32.
    pub rows: Vec<f32>,
    pub dim: usize,
    pub horizon: usize,
    /// First row of each window.
    pub starts: Vec<usize>,
    pub stride: usize,
    pub episodes: usize,
}

/// Episodes of `n` rows as row ranges: an episode ends after a row flagged in `ends_after`
/// (terminals or timeouts) and a new one begins at a row flagged in `starts_at`.
pub fn episodes(n: usize, ends_after: &[bool], starts_at: &[bool]) -> Vec<Range<usize>> {
    let mut out = Vec::new();
    let mut begin = 0;
    for i in 0..n {
        if i > begin && starts_at.get(i).copied().unwrap_or(false) {
            out.push(begin..i);
            begin = i;
        }
        if ends_after.get(i).copied().unwrap_or(false) {
            out.push(begin..i + 1);
            begin = i + 1;
        }
    }
    if begin < n {
        out.push(begin..n);
    }
    out
}

/// First rows of every `horizon`-row window lying inside one episode, `stride` rows apart
/// within each episode (every episode's windows start at its first row).
pub fn window_starts(episodes: &[Range<usize>], horizon: usize, stride: usize) -> Vec<usize> {
    let stride = stride.max(1);
    let mut starts = Vec::new();
    for e in episodes {
        if horizon > 0 && e.len() >= horizon {
            starts.extend((e.start..=e.end - horizon).step_by(stride));
        }
    }
    starts
}

/// `[action | observation]` rows from `[N, act_dim]` actions and `[N, obs_dim]` observations.
pub fn trajectory_rows(actions: &[f32], act_dim: usize, observations: &[f32], obs_dim: usize) -> Vec<f32> {
    let n = actions.len().checked_div(act_dim).unwrap_or_else(|| observations.len() / obs_dim.max(1));
    let mut rows = Vec::with_capacity(n * (act_dim + obs_dim));
    for i in 0..n {
        rows.extend_from_slice(&actions[i * act_dim..(i + 1) * act_dim]);
        rows.extend_from_slice(&observations[i * obs_dim..(i + 1) * obs_dim]);
    }
    rows
}

impl Windows {
    fn window(&self, k: usize) -> &[f32] {
        let start = self.starts[k] * self.dim;
        &self.rows[start..start + self.horizon * self.dim]
    }
}

/// What `score` and `grad` send: items of one shape.
#[derive(Debug, Clone)]
pub enum Items {
    Array { key: String, values: Vec<f32>, item_shape: Vec<u64> },
    Windows(Windows),
}

impl Items {
    /// How many items there are.
    pub fn len(&self) -> usize {
        match self {
            Self::Array { values, item_shape, .. } => {
                let per = item_shape.iter().product::<u64>() as usize;
                values.len().checked_div(per).unwrap_or(0)
            }
            Self::Windows(w) => w.starts.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn item_shape(&self) -> Vec<u64> {
        match self {
            Self::Array { item_shape, .. } => item_shape.clone(),
            Self::Windows(w) => vec![w.horizon as u64, w.dim as u64],
        }
    }

    pub fn item_len(&self) -> usize {
        self.item_shape().iter().product::<u64>() as usize
    }

    /// Items `range` as one `[b, *item_shape]` float32 tensor.
    pub fn batch(&self, range: Range<usize>) -> pb::Tensor {
        let mut shape = vec![range.len() as u64];
        shape.extend(self.item_shape());
        match self {
            Self::Array { values, .. } => {
                let per = self.item_len();
                tensor::encode_f32(&shape, &values[range.start * per..range.end * per])
            }
            Self::Windows(w) => {
                let mut values = Vec::with_capacity(range.len() * w.horizon * w.dim);
                for k in range {
                    values.extend_from_slice(w.window(k));
                }
                tensor::encode_f32(&shape, &values)
            }
        }
    }

    /// A line for the summary: where the items came from.
    pub fn describe(&self) -> String {
        match self {
            Self::Array { key, .. } => format!("array '{key}'"),
            Self::Windows(w) => format!(
                "trajectory windows of {} rows, stride {}, from {} episode{}",
                w.horizon,
                w.stride,
                w.episodes,
                if w.episodes == 1 { "" } else { "s" }
            ),
        }
    }

    /// Where the items came from, for reports.
    pub fn source(&self) -> ItemsSource {
        match self {
            Self::Array { key, .. } => ItemsSource::Array { key: key.clone() },
            Self::Windows(w) => {
                ItemsSource::Trajectories { horizon: w.horizon, stride: w.stride, episodes: w.episodes }
            }
        }
    }
}

/// Where items came from: an array of a file, or windows of its trajectories.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum ItemsSource {
    Array { key: String },
    Trajectories { horizon: usize, stride: usize, episodes: usize },
}

/// An input file after its headers were read: which arrays to load.
enum InputFile {
    Array(NpzSource),
    Trajectories(NpzSource),
}

/// Opens `--input`: `--key`'s array, else trajectories for an archive holding `observations`,
/// else `x`, else `samples` or the only array.
fn inspect_input(path: &Path, key: Option<&str>, stride: Option<u64>) -> Result<InputFile> {
    let shown = path.display();
    let kind = npz::detect_kind(path).map_err(|e| anyhow!("--input: {e}"))?;
    let keys = npz::npz_keys(path).map_err(|e| anyhow!("--input: {e}"))?;
    let file = match key {
        Some(key) => {
            if !keys.is_empty() && !keys.iter().any(|k| k == key) {
                let held = keys.iter().map(|k| format!("'{k}'")).collect::<Vec<_>>().join(", ");
                return Err(UsageError(format!("--key {key}: {shown} holds no array '{key}' (it holds {held})")).into());
            }
            InputFile::Array(npz::samples_from_npz_or_npy(path, Some(key)).map_err(|e| anyhow!("--key {key}: {e}"))?)
        }
        None if kind == pb::DatasetKind::Trajectories => {
            InputFile::Trajectories(npz::trajectories_from_npz(path).map_err(|e| anyhow!("--input: {e}"))?)
        }
        None => {
            let key = keys.iter().any(|k| k == "x").then_some("x");
            InputFile::Array(npz::samples_from_npz_or_npy(path, key).map_err(|e| anyhow!("--input: {e}"))?)
        }
    };
    if let (Some(stride), InputFile::Array(source)) = (stride, &file) {
        let key = source.file_key(0).unwrap_or("x");
        return Err(UsageError(format!(
            "--stride {stride}: only trajectory inputs (observations, actions) are cut into windows; \
             {shown} is read as array '{key}'"
        ))
        .into());
    }
    Ok(file)
}

/// Reads the items of `file` for a model whose items are `input_shape`.
fn load_items(file: InputFile, model: &str, input_shape: &[u64], stride: usize) -> Result<Items> {
    match file {
        InputFile::Array(mut source) => {
            let key = source.file_key(0).unwrap_or("x").to_owned();
            let t = source.read_tensor(0).map_err(|e| anyhow!("--input: {e}"))?;
            let item_shape = t.shape[1..].to_vec();
            if !input_shape.is_empty() && item_shape != input_shape {
                bail!(
                    "--input: array '{key}' has shape {:?}, items of shape {item_shape:?}, but model '{model}' takes \
                     items of shape {input_shape:?}",
                    t.shape
                );
            }
            let values = tensor::decode_finite_f32(&t).map_err(|e| anyhow!("--input: array '{key}': {e}"))?;
            Ok(Items::Array { key, values, item_shape })
        }
        InputFile::Trajectories(mut source) => {
            let &[horizon, dim] = input_shape else {
                bail!(
                    "--input: {} holds trajectories, but model '{model}' takes items of shape {input_shape:?}, not \
                     [H, D] windows; pass an array of such items (--key)",
                    source.path().display()
                );
            };
            let Trajectories { rows, episodes, .. } = read_trajectories(&mut source, model, horizon, dim)?;
            let starts = window_starts(&episodes, horizon as usize, stride);
            if starts.is_empty() {
                let longest = episodes.iter().map(ExactSizeIterator::len).max().unwrap_or(0);
                bail!(
                    "--input: no episode is as long as model '{model}''s horizon H = {horizon} (the longest of {} has \
                     {longest} rows)",
                    episodes.len()
                );
            }
            Ok(Items::Windows(Windows {
                rows,
                dim: dim as usize,
                horizon: horizon as usize,
                starts,
                stride,
                episodes: episodes.len(),
            }))
        }
    }
}

/// A trajectory file's rows and episodes, checked against a model of `[horizon, dim]` items.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectories {
    /// `[N, dim]` rows, `[action | observation]`, float32.
    pub rows: Vec<f32>,
    pub act_dim: usize,
    pub obs_dim: usize,
    /// Row ranges: an episode ends after a `terminals` or `timeouts` row and begins at an
    /// `episode_starts` row.
    pub episodes: Vec<Range<usize>>,
}

/// Reads the rows and episodes of a trajectory archive (the D4RL names the toolkit's reader
/// gives) for model `model`, whose items are `[horizon, dim]`; errors name `--input`.
pub fn read_trajectories(source: &mut NpzSource, model: &str, horizon: u64, dim: u64) -> Result<Trajectories> {
    let specs = source.arrays().to_vec();
    let index = |name: &str| specs.iter().position(|s| s.name == name);
    let mut floats = |name: &str| -> Result<(Vec<f32>, usize)> {
        let i = index(name).ok_or_else(|| anyhow!("--input: no '{name}' array"))?;
        let t = source.read_tensor(i).map_err(|e| anyhow!("--input: {e}"))?;
        let values = tensor::decode_finite_f32(&t).map_err(|e| anyhow!("--input: array '{name}': {e}"))?;
        Ok((values, t.shape.get(1).copied().unwrap_or(1) as usize))
    };
    let (observations, obs_dim) = floats("observations")?;
    let (actions, act_dim) = floats("actions")?;
    if (act_dim + obs_dim) as u64 != dim {
        bail!(
            "--input: rows of {act_dim} action and {obs_dim} observation values make windows of {} columns, \
             but model '{model}' takes [H = {horizon}, D = {dim}] windows (D = action_dim + obs_dim)",
            act_dim + obs_dim
        );
    }
    let n = observations.len() / obs_dim.max(1);
    let mut flags = |name: &str| -> Result<Vec<bool>> {
        let Some(i) = index(name) else { return Ok(Vec::new()) };
        let t = source.read_tensor(i).map_err(|e| anyhow!("--input: {e}"))?;
        tensor::decode_flags(&t).map_err(|e| anyhow!("--input: array '{name}': {e}"))
    };
    let mut ends = flags("terminals")?;
    ends.resize(n, false);
    for (e, t) in ends.iter_mut().zip(flags("timeouts")?) {
        *e |= t;
    }
    let starts_at = flags("episode_starts")?;
    let episodes = episodes(n, &ends, &starts_at);
    let rows = trajectory_rows(&actions, act_dim, &observations, obs_dim);
    Ok(Trajectories { rows, act_dim, obs_dim, episodes })
}

/// The reward model's item shape, refusing diffusion models by name.
pub async fn reward_input_shape(client: &Client, name: &str) -> Result<Vec<u64>> {
    Ok(reward_info(client, name).await?.input_shape)
}

/// The reward model's record (item shape, T, ...), refusing diffusion models by name.
pub async fn reward_info(client: &Client, name: &str) -> Result<pb::RewardInfo> {
    let model = client.get_model(name).await.with_context(|| format!("--model {name}"))?;
    match model.kind() {
        pb::ModelKind::Reward | pb::ModelKind::Discriminator => {}
        pb::ModelKind::Diffusion => bail!(
            "--model {name}: is a diffusion model; scores and gradients come from a reward or discriminator model \
             (relreward model list --kind reward)"
        ),
        pb::ModelKind::Autoencoder => bail!(
            "--model {name}: is an autoencoder; scores and gradients come from a reward or discriminator model \
             (relreward model list --kind reward)"
        ),
        pb::ModelKind::Recipe => bail!(
            "--model {name}: is a sampling recipe; scores and gradients come from a reward or discriminator model \
             (relreward model list --kind reward)"
        ),
        pb::ModelKind::Unspecified => bail!("--model {name}: the server did not say what kind of model this is"),
    }
    Ok(model.reward.unwrap_or_default())
}

/// Opens `--input`, asks the server for the model's item shape and loads the items.
pub async fn read_items(client: &Client, args: &ItemsQuery) -> Result<Items> {
    let (path, key, stride) = (args.input.clone(), args.key.clone(), args.stride);
    let file = tokio::task::spawn_blocking(move || inspect_input(&path, key.as_deref(), stride))
        .await
        .context("reading the input crashed")??;
    let input_shape = reward_input_shape(client, &args.model).await?;
    let model = args.model.clone();
    let stride = stride.unwrap_or(1) as usize;
    let items = tokio::task::spawn_blocking(move || load_items(file, &model, &input_shape, stride))
        .await
        .context("reading the input crashed")??;
    if items.is_empty() {
        bail!("--input: {} holds no items", args.input.display());
    }
    Ok(items)
}

/// `--batch`, lowered (with a note) so that one request carries at most [`MAX_REQUEST_BYTES`].
pub fn request_batch(requested: u64, item_bytes: u64, quiet: bool) -> usize {
    let fits = (MAX_REQUEST_BYTES / item_bytes.max(1)).max(1);
    if requested > fits {
        if !quiet {
            eprint_line(&format!(
                "note: --batch {requested} lowered to {fits} so that one request stays under {} MiB",
                MAX_REQUEST_BYTES >> 20
            ));
        }
        return fits as usize;
    }
    requested as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episodes_end_at_flags_and_start_at_episode_starts() {
        let f = |ones: &[usize], n: usize| {
            let mut v = vec![false; n];
            for &i in ones {
                v[i] = true;
            }
            v
        };
        // Ends after rows 2 and 5 (terminals | timeouts); the tail 6..10 is an episode too.
        assert_eq!(episodes(10, &f(&[2, 5], 10), &[]), vec![0..3, 3..6, 6..10]);
        // An end on the last row leaves no empty tail.
        assert_eq!(episodes(4, &f(&[3], 4), &[]), vec![0..4]);
        // No flags: one episode; no rows: none.
        assert_eq!(episodes(5, &[], &[]), vec![0..5]);
        assert_eq!(episodes(0, &[], &[]), Vec::<Range<usize>>::new());
        // episode_starts split too, and agree with an end just before them.
        assert_eq!(episodes(8, &f(&[2], 8), &f(&[0, 3, 6], 8)), vec![0..3, 3..6, 6..8]);
        // Consecutive ends make one-row episodes.
        assert_eq!(episodes(3, &f(&[0, 1, 2], 3), &[]), vec![0..1, 1..2, 2..3]);
    }

    #[test]
    fn windows_never_cross_episode_boundaries() {
        let eps = vec![0..3, 3..10, 10..12, 12..16];
        // H = 3: 1 + 5 + 0 + 2 windows.
        assert_eq!(window_starts(&eps, 3, 1), vec![0, 3, 4, 5, 6, 7, 12, 13]);
        for &s in &window_starts(&eps, 3, 1) {
            assert!(eps.iter().any(|e| e.start <= s && s + 3 <= e.end), "window at {s} crosses an episode end");
        }
        // Stride 2 restarts at each episode's first row.
        assert_eq!(window_starts(&eps, 3, 2), vec![0, 3, 5, 7, 12]);
        // Longer than every episode: no windows.
        assert!(window_starts(&eps, 8, 1).is_empty());
        assert_eq!(window_starts(&eps, 7, 1), vec![3]);
    }

    #[test]
    fn rows_are_actions_then_observations_and_windows_slice_them() {
        let actions = [10.0, 11.0, 20.0, 21.0, 30.0, 31.0, 40.0, 41.0];
        let observations = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0];
        let rows = trajectory_rows(&actions, 2, &observations, 3);
        assert_eq!(&rows[..10], &[10.0, 11.0, 1.0, 2.0, 3.0, 20.0, 21.0, 4.0, 5.0, 6.0]);
        assert_eq!(rows.len(), 4 * 5);
        // Rows 0..2 are one episode, 2..4 another: with H = 2, windows at 0, 1 and 2.
        let eps = episodes(4, &[false, true, false, false], &[]);
        let starts = window_starts(&eps, 2, 1);
        assert_eq!(starts, vec![0, 2]);
        let w = Windows { rows, dim: 5, horizon: 2, starts, stride: 1, episodes: eps.len() };
        let items = Items::Windows(w);
        assert_eq!((items.len(), items.item_shape()), (2, vec![2, 5]));
        let t = items.batch(1..2);
        assert_eq!(t.shape, vec![1, 2, 5]);
        let values = tensor::decode_finite_f32(&t).expect("finite");
        assert_eq!(values, vec![30.0, 31.0, 7.0, 8.0, 9.0, 40.0, 41.0, 10.0, 11.0, 12.0]);
    }

    #[test]
    fn array_items_are_batched_in_order() {
        let items =
            Items::Array { key: "x".into(), values: (0..12).map(|v| v as f32).collect(), item_shape: vec![2, 2] };
        assert_eq!(items.len(), 3);
        assert_eq!(batches(3, 2), vec![0..2, 2..3]);
        let t = items.batch(2..3);
        assert_eq!(
            (t.shape.clone(), tensor::decode_finite_f32(&t).expect("finite")),
            (vec![1, 2, 2], vec![8.0, 9.0, 10.0, 11.0])
        );
        assert_eq!(batches(0, 5), Vec::<Range<usize>>::new());
        assert_eq!(batches(10, 5), vec![0..5, 5..10]);
    }

    #[test]
    fn trajectory_files_are_windowed_with_the_models_shape() {
        use relreward_toolkit::npz_write::NpzWriter;
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("traj.npz");
        // 9 rows, obs_dim 2, act_dim 1, one episode.
        let n = 9u64;
        let obs: Vec<f32> = (0..18).map(|v| v as f32).collect();
        let act: Vec<f32> = (0..9).map(|v| -(v as f32)).collect();
        let mut w = NpzWriter::create(&path).expect("create");
        w.add_f32("observations", &[n, 2], &obs).expect("obs");
        w.add_f32("actions", &[n, 1], &act).expect("act");
        w.finish().expect("finish");
        let file = inspect_input(&path, None, None).expect("inspect");
        let items = load_items(file, "r", &[3, 3], 1).expect("load");
        // One episode of 9 rows: 7 windows.
        assert_eq!(items.len(), 7);
        let first = tensor::decode_finite_f32(&items.batch(0..1)).expect("finite");
        assert_eq!(first, vec![0.0, 0.0, 1.0, -1.0, 2.0, 3.0, -2.0, 4.0, 5.0]);

        // A terminal after row 3 and a timeout after row 6: episodes of 4, 3 and 2 rows.
        let flagged = dir.path().join("flagged.npz");
        let flags = |at: usize| (0..9).map(|i| i == at).collect::<Vec<bool>>();
        let mut w = NpzWriter::create(&flagged).expect("create");
        w.add_f32("observations", &[n, 2], &obs).expect("obs");
        w.add_f32("actions", &[n, 1], &act).expect("act");
        w.add_bool("terminals", &[n], &flags(3)).expect("terminals");
        w.add_bool("timeouts", &[n], &flags(6)).expect("timeouts");
        w.finish().expect("finish");
        let file = inspect_input(&flagged, None, None).expect("inspect");
        let Items::Windows(windows) = load_items(file, "r", &[3, 3], 1).expect("load") else {
            panic!("trajectories are windowed")
        };
        assert_eq!((windows.starts.clone(), windows.episodes), (vec![0, 1, 4], 3));
        let file = inspect_input(&flagged, None, Some(2)).expect("inspect");
        let Items::Windows(windows) = load_items(file, "r", &[2, 3], 2).expect("load") else {
            panic!("trajectories are windowed")
        };
        assert_eq!(windows.starts, vec![0, 2, 4, 7]);

        // D must be action_dim + obs_dim.
        let file = inspect_input(&path, None, None).expect("inspect");
        let err = load_items(file, "r", &[3, 4], 1).expect_err("wrong D").to_string();
        assert!(
            err.contains("--input") && err.contains("D = 4") && err.contains("1 action and 2 observation"),
            "{err}"
        );
        // A horizon longer than every episode.
        let file = inspect_input(&path, None, None).expect("inspect");
        let err = load_items(file, "r", &[10, 3], 1).expect_err("too long").to_string();
        assert!(err.contains("H = 10") && err.contains("9 rows"), "{err}");
        // A sample-space model cannot take trajectories.
        let file = inspect_input(&path, None, None).expect("inspect");
        assert!(load_items(file, "r", &[4, 4, 4], 1).expect_err("not windows").to_string().contains("--key"));
        // --stride is for trajectories only; --key must name an array of the file.
        let xpath = dir.path().join("x.npz");
        let mut w = NpzWriter::create(&xpath).expect("create");
        w.add_f32("x", &[2, 3, 3], &[0.5; 18]).expect("x");
        w.finish().expect("finish");
        let err = inspect_input(&xpath, None, Some(2)).err().expect("stride on an array").to_string();
        assert!(err.contains("--stride 2"), "{err}");
        let err = inspect_input(&xpath, Some("y"), None).err().expect("missing key").to_string();
        assert!(err.contains("--key y") && err.contains("'x'"), "{err}");
        let file = inspect_input(&xpath, None, None).expect("x");
        let items = load_items(file, "r", &[3, 3], 1).expect("x items");
        assert_eq!((items.len(), items.item_shape()), (2, vec![3, 3]));
        let file = inspect_input(&xpath, None, None).expect("x");
        let err = load_items(file, "r", &[4, 3], 1).expect_err("shape").to_string();
        assert!(err.contains("--input") && err.contains("[3, 3]") && err.contains("[4, 3]"), "{err}");
        let err = inspect_input(&dir.path().join("missing.npz"), None, None).err().expect("missing").to_string();
        assert!(err.starts_with("--input"), "{err}");
    }

    #[test]
    fn batches_are_lowered_to_fit_a_request() {
        assert_eq!(request_batch(256, 32 * 6 * 4, true), 256);
        assert_eq!(request_batch(256, 4 * 64 * 64 * 4, true), 128);
        assert_eq!(request_batch(4, MAX_REQUEST_BYTES * 2, true), 1);
    }
}
