//! `relreward score`, `relreward grad` and `relreward sample`: the RewardService from the
//! command line.
//!
//! Inputs of `score` and `grad` (`--input`) are read whole into memory:
//! - an array of items `[B, *item_shape]` (`x` by default, another with `--key`; float32 or
//!   float64), whose item shape must be the reward model's `input_shape`;
//! - or a D4RL-style trajectories archive (`observations`, `actions`, optional `terminals`,
//!   `timeouts`, `episode_starts`), cut into the model's `[H, D]` windows ([`Windows`]): rows
//!   are `[action | observation]` as in Diffuser, a window is H consecutive rows of one episode,
//!   and windows start every `--stride` rows.
//!
//! Items go to the server in requests of `--batch` (two in flight), lowered when needed so that
//! one request stays under [`MAX_REQUEST_BYTES`]. Results are written with `--out` as an `.npz`
//! ([`relreward_client::npz_write`]) and summarised as text or, with `--json`, one document.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, ValueEnum};
use futures::StreamExt;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use relreward_client::npz::{self, NpzSource};
use relreward_client::npz_write::NpzWriter;
use relreward_client::{Client, ClientError, UploadSource, pb, tensor};
use serde_json::{Value, json};

use super::output::{bars_visible, eprint_line, fmt_num, key_values};
use super::{Ctx, Report, UsageError};

/// Largest payload of one Score/Gradient request: half the server's default request limit
/// (16 MiB), leaving room for framing and for servers configured lower.
pub const MAX_REQUEST_BYTES: u64 = 8 << 20;
/// Requests in flight at once: one computing while the next travels.
pub(crate) const IN_FLIGHT: usize = 2;

// ---------------------------------------------------------------------------------------------
// Flags

/// Units of inputs and gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum UnitsArg {
    /// The dataset's units.
    Raw,
    /// The diffusion models' normalized units.
    Normalized,
}

impl UnitsArg {
    fn to_proto(self) -> pb::Units {
        match self {
            Self::Raw => pb::Units::Raw,
            Self::Normalized => pb::Units::Normalized,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Raw => "raw",
            Self::Normalized => "normalized",
        }
    }
}

/// What `score` and `grad` read and where they send it.
#[derive(Debug, Clone, Args)]
pub struct InputArgs {
    /// Reward (or discriminator) model.
    #[arg(long, value_name = "R")]
    pub model: String,
    /// .npz holding `x` [B, H, D] (or [B, ...] samples), a D4RL-style trajectories .npz
    /// (observations, actions, terminals/timeouts) cut into the model's windows, or an .npy.
    #[arg(long, value_name = "FILE.npz")]
    pub input: PathBuf,
    /// The array of --input holding the items [default: x; an archive holding 'observations'
    /// is read as trajectories].
    #[arg(long, value_name = "KEY")]
    pub key: Option<String>,
    /// Trajectories: rows between the starts of consecutive windows [default: 1].
    #[arg(long, value_name = "S", value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub stride: Option<u64>,
    /// Units of the input values.
    #[arg(long, value_enum, value_name = "UNITS", default_value_t = UnitsArg::Raw)]
    pub units: UnitsArg,
    /// Items per request.
    #[arg(long, value_name = "N", default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub batch: u64,
    /// Write the results to this .npz file.
    #[arg(long, value_name = "OUT.npz")]
    pub out: Option<PathBuf>,
}

#[derive(Debug, Clone, Args)]
pub struct ScoreArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// Diffusion time of every item (0: clean data).
    #[arg(long, value_name = "T", default_value_t = 0, allow_negative_numbers = true)]
    pub t: u32,
    /// Also rho per window ([B, H / h]; windowed rewards).
    #[arg(long)]
    pub per_window: bool,
    /// Also rho per step ([B, H]; windowed rewards).
    #[arg(long)]
    pub per_step: bool,
}

#[derive(Debug, Clone, Args)]
pub struct GradArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// Diffusion time of every item.
    #[arg(long, value_name = "T", allow_negative_numbers = true)]
    pub t: u32,
    /// Units of the returned gradient (raw: through the normalizer's chain rule).
    #[arg(long, value_enum, value_name = "UNITS", default_value_t = UnitsArg::Raw)]
    pub gradient_units: UnitsArg,
    /// Multiply the gradient by W [default: 1].
    #[arg(long, value_name = "W", allow_negative_numbers = true)]
    pub omega: Option<f64>,
    /// Multiply the gradient by this diffusion model's posterior variance at t (Diffuser's
    /// scale_grad_by_std).
    #[arg(long, value_name = "BASE")]
    pub scale_by_posterior_variance_of: Option<String>,
}

#[derive(Debug, Clone, Args)]
pub struct SampleArgs {
    /// Base diffusion model.
    #[arg(long, value_name = "B")]
    pub base: String,
    /// Reward model that guides the sampler (needs --scale).
    #[arg(long, value_name = "R")]
    pub reward: Option<String>,
    /// Guidance scale omega (0: no guidance, the reward of each sample is still reported).
    #[arg(long, value_name = "W", allow_negative_numbers = true)]
    pub scale: Option<f64>,
    /// Guided sampling: no guidance at diffusion times below K [default: the server's].
    #[arg(long, value_name = "K", allow_negative_numbers = true)]
    pub t_stopgrad: Option<u32>,
    /// Guided sampling: gradient steps per denoising step [default: the server's].
    #[arg(long, value_name = "N", allow_negative_numbers = true)]
    pub n_guide_steps: Option<u32>,
    /// Guided sampling: scale the gradient by the posterior variance.
    #[arg(long)]
    pub scale_grad_by_std: bool,
    /// Inpainting: the observation at horizon index INDEX, in raw units (repeatable).
    #[arg(long = "condition", value_name = "INDEX=v1,v2,..", value_parser = parse_condition, allow_hyphen_values = true)]
    pub conditions: Vec<ConditionArg>,
    /// Number of samples.
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..), allow_negative_numbers = true)]
    pub n: u32,
    /// Seed of the sampler's noise [default: the server picks one].
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    pub seed: Option<u64>,
    /// Samples denoised together [default: all of them, up to the server's limit].
    #[arg(long, value_name = "M", value_parser = clap::value_parser!(u32).range(1..), allow_negative_numbers = true)]
    pub batch_size: Option<u32>,
    /// Write the samples to this .npz file.
    #[arg(long, value_name = "FILE.npz")]
    pub out: Option<PathBuf>,
}

/// `--condition INDEX=v1,v2,..`.
#[derive(Debug, Clone, PartialEq)]
pub struct ConditionArg {
    pub index: u32,
    pub state: Vec<f64>,
}

impl ConditionArg {
    fn text(&self) -> String {
        let values: Vec<String> = self.state.iter().map(f64::to_string).collect();
        format!("{}={}", self.index, values.join(","))
    }
}

fn parse_condition(text: &str) -> Result<ConditionArg, String> {
    let usage = "expected INDEX=v1,v2,.. (a horizon index and the observation there, e.g. 0=1.5,2,0,0)";
    let (index, values) = text.split_once('=').ok_or_else(|| usage.to_owned())?;
    let index = index.trim().parse::<u32>().map_err(|_| format!("'{index}' is not a horizon index; {usage}"))?;
    let state = values
        .split(',')
        .map(|v| match v.trim().parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(x),
            _ => Err(format!("'{v}' is not a finite number; {usage}")),
        })
        .collect::<Result<Vec<f64>, String>>()?;
    Ok(ConditionArg { index, state })
}

// ---------------------------------------------------------------------------------------------
// Items

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
pub(crate) enum Items {
    Array { key: String, values: Vec<f32>, item_shape: Vec<u64> },
    Windows(Windows),
}

impl Items {
    pub(crate) fn len(&self) -> usize {
        match self {
            Self::Array { values, item_shape, .. } => {
                let per = item_shape.iter().product::<u64>() as usize;
                values.len().checked_div(per).unwrap_or(0)
            }
            Self::Windows(w) => w.starts.len(),
        }
    }

    pub(crate) fn item_shape(&self) -> Vec<u64> {
        match self {
            Self::Array { item_shape, .. } => item_shape.clone(),
            Self::Windows(w) => vec![w.horizon as u64, w.dim as u64],
        }
    }

    pub(crate) fn item_len(&self) -> usize {
        self.item_shape().iter().product::<u64>() as usize
    }

    /// Items `range` as one `[b, *item_shape]` float32 tensor.
    pub(crate) fn batch(&self, range: Range<usize>) -> pb::Tensor {
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
    pub(crate) fn describe(&self) -> String {
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

    pub(crate) fn source_json(&self) -> Value {
        match self {
            Self::Array { key, .. } => json!({ "kind": "array", "key": key }),
            Self::Windows(w) => json!({
                "kind": "trajectories",
                "horizon": w.horizon,
                "stride": w.stride,
                "episodes": w.episodes,
            }),
        }
    }
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
            let starts = window_starts(&episodes, horizon as usize, stride);
            if starts.is_empty() {
                let longest = episodes.iter().map(ExactSizeIterator::len).max().unwrap_or(0);
                bail!(
                    "--input: no episode is as long as model '{model}''s horizon H = {horizon} (the longest of {} has \
                     {longest} rows)",
                    episodes.len()
                );
            }
            let rows = trajectory_rows(&actions, act_dim, &observations, obs_dim);
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

/// The reward model's item shape, refusing diffusion models by name.
async fn reward_input_shape(client: &Client, name: &str) -> Result<Vec<u64>> {
    let model = client.get_model(name).await.with_context(|| format!("--model {name}"))?;
    match model.kind() {
        pb::ModelKind::Reward | pb::ModelKind::Discriminator => {}
        pb::ModelKind::Diffusion => bail!(
            "--model {name}: is a diffusion model; scores and gradients come from a reward or discriminator model \
             (relreward model list --kind reward)"
        ),
        pb::ModelKind::Unspecified => bail!("--model {name}: the server did not say what kind of model this is"),
    }
    Ok(model.reward.map(|r| r.input_shape).unwrap_or_default())
}

/// Opens `--input`, asks the server for the model's item shape and loads the items.
pub(crate) async fn read_items(client: &Client, args: &InputArgs) -> Result<Items> {
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
    if items.len() == 0 {
        bail!("--input: {} holds no items", args.input.display());
    }
    Ok(items)
}

/// `--batch`, lowered (with a note) so that one request carries at most [`MAX_REQUEST_BYTES`].
pub(crate) fn request_batch(requested: u64, item_bytes: u64, quiet: bool) -> usize {
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

pub(crate) fn batches(n: usize, batch: usize) -> Vec<Range<usize>> {
    (0..n).step_by(batch.max(1)).map(|s| s..(s + batch).min(n)).collect()
}

// ---------------------------------------------------------------------------------------------
// Results

/// float32 or float64 values of a response tensor (non-finite values are kept).
pub(crate) fn floats(t: Option<&pb::Tensor>, field: &str, shape: &[u64]) -> Result<Vec<f32>> {
    let t = t.ok_or_else(|| anyhow!("the server's answer has no {field}"))?;
    if t.shape != shape {
        bail!("the server's answer has {field} of shape {:?} where {shape:?} was expected", t.shape);
    }
    let mut out = Vec::with_capacity(t.data.len() / 4);
    tensor::for_each_float(t, |v| out.push(v as f32)).map_err(|e| anyhow!("the server's {field}: {e}"))?;
    Ok(out)
}

/// Mean, population standard deviation, min and max (`None` for no values).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Summary {
    pub mean: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
}

pub fn summarize(values: impl IntoIterator<Item = f64>) -> Option<Summary> {
    let (mut n, mut mean, mut m2) = (0u64, 0.0f64, 0.0f64);
    let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        n += 1;
        let delta = v - mean;
        mean += delta / n as f64;
        m2 += delta * (v - mean);
        min = min.min(v);
        max = max.max(v);
    }
    (n > 0).then(|| Summary { mean, std: (m2 / n as f64).sqrt(), min, max })
}

fn summary_json(s: Option<Summary>) -> Value {
    s.map_or(Value::Null, |s| json!({ "mean": s.mean, "std": s.std, "min": s.min, "max": s.max }))
}

fn summary_text(s: Option<Summary>) -> String {
    s.map_or_else(
        || "-".to_owned(),
        |s| format!("mean {}  std {}  min {}  max {}", fmt_num(s.mean), fmt_num(s.std), fmt_num(s.min), fmt_num(s.max)),
    )
}

/// Arrays for `--out`, in the order they are written.
#[derive(Debug, Default)]
struct OutArrays {
    f32s: Vec<(&'static str, Vec<u64>, Vec<f32>)>,
    i64s: Vec<(&'static str, Vec<u64>, Vec<i64>)>,
}

impl OutArrays {
    fn shapes_json(&self) -> Value {
        let mut map = serde_json::Map::new();
        for (name, shape, _) in &self.f32s {
            map.insert((*name).to_owned(), json!(shape));
        }
        for (name, shape, _) in &self.i64s {
            map.insert((*name).to_owned(), json!(shape));
        }
        Value::Object(map)
    }

    fn shapes_text(&self) -> String {
        let f = self.f32s.iter().map(|(n, s, _)| format!("{n} {s:?}"));
        let i = self.i64s.iter().map(|(n, s, _)| format!("{n} {s:?}"));
        f.chain(i).collect::<Vec<_>>().join(", ")
    }

    /// Writes the arrays to `out` when given; returns their shapes as JSON and as text.
    async fn write_to(self, out: Option<&Path>) -> Result<(Value, String)> {
        let shapes = (self.shapes_json(), self.shapes_text());
        if let Some(out) = out {
            self.write(out).await?;
        }
        Ok(shapes)
    }

    /// Writes the arrays to `path` (on a blocking thread).
    async fn write(self, path: &Path) -> Result<()> {
        let dest = path.to_owned();
        tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            let mut w = NpzWriter::create(&dest)?;
            for (name, shape, values) in &self.f32s {
                w.add_f32(name, shape, values)?;
            }
            for (name, shape, values) in &self.i64s {
                w.add_i64(name, shape, values)?;
            }
            w.finish()?;
            Ok(())
        })
        .await
        .context("writing the output crashed")?
        .map_err(|e| anyhow!("--out {}: {e}", path.display()))
    }
}

/// Refuses an `--out` whose directory does not exist before any work is done.
fn check_out(out: Option<&Path>) -> Result<()> {
    let Some(out) = out else { return Ok(()) };
    if out.file_name().is_none() || out.is_dir() {
        return Err(UsageError(format!("--out {}: not a file name", out.display())).into());
    }
    let dir = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(UsageError(format!("--out {}: directory {} does not exist", out.display(), dir.display())).into());
    }
    Ok(())
}

/// A count progress bar on stderr, hidden with `--json` or off a terminal.
pub(crate) fn item_bar(json: bool, total: u64, what: &str) -> ProgressBar {
    let target = if bars_visible(json) { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() };
    let template =
        format!("{{spinner}} {{elapsed_precise}} [{{wide_bar}}] {{pos}}/{{len}} {what} {{per_sec}} ETA {{eta}}");
    let style = ProgressStyle::with_template(&template)
        .map(|s| s.progress_chars("=> "))
        .unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::with_draw_target(Some(total), target).with_style(style)
}

/// The flag behind a server error whose message starts with a request field (`t[0]: ..`,
/// `omega: ..`), from `fields`: (request field, flag as the user gave it).
fn flag_of(err: &ClientError, fields: &[(&str, String)]) -> Option<String> {
    let ClientError::Status(status) = err else { return None };
    let message = status.message();
    let end = message.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(message.len());
    let (field, rest) = message.split_at(end);
    if !rest.starts_with([':', '[', '.']) {
        return None;
    }
    fields.iter().find(|(f, _)| *f == field).map(|(_, flag)| flag.clone())
}

/// A failed request's error, labelled with the flag it concerns (see [`flag_of`]) and, when
/// the input took several requests and the fault may lie in the items, with the items sent.
pub(crate) fn request_error(
    err: ClientError,
    fields: &[(&str, String)],
    range: &Range<usize>,
    n: usize,
    several: bool,
) -> anyhow::Error {
    let flag = flag_of(&err, fields);
    let items = format!("items {}..{} of {n}", range.start, range.end);
    let label = match flag {
        Some(flag) if flag == "--input" && several => Some(format!("--input, {items}")),
        Some(flag) => Some(flag),
        None if several => Some(items),
        None => None,
    };
    let err = anyhow::Error::new(err);
    match label {
        Some(label) => err.context(label),
        None => err,
    }
}

/// Request fields of Score and Gradient and the flags that set them.
fn query_fields(input: &InputArgs, t: u32) -> Vec<(&'static str, String)> {
    vec![
        ("model", format!("--model {}", input.model)),
        ("x", "--input".to_owned()),
        ("t", format!("--t {t}")),
        ("input_units", "--units".to_owned()),
    ]
}

/// Sends a request per range of items, `send(index, range)`, at most [`IN_FLIGHT`] at a time,
/// and hands each answer in order to `take` with its item count; a failed request's error is
/// labelled as [`request_error`] does. A bar on stderr counts the items answered.
async fn query_batches<A, F>(
    ctx: &Ctx,
    ranges: &[Range<usize>],
    fields: &[(&str, String)],
    send: impl Fn(usize, Range<usize>) -> F,
    mut take: impl FnMut(u64, A) -> Result<()>,
) -> Result<()>
where
    F: std::future::Future<Output = Result<A, ClientError>>,
{
    let n = ranges.last().map_or(0, |r| r.end);
    let several = ranges.len() > 1;
    let bar = item_bar(ctx.json, n as u64, "items");
    let requests = ranges.iter().enumerate().map(|(i, range)| send(i, range.clone()));
    let mut answers = futures::stream::iter(requests).buffered(IN_FLIGHT);
    let mut next = ranges.iter();
    while let Some(answer) = answers.next().await {
        let range = next.next().ok_or_else(|| anyhow!("more answers than requests"))?;
        let b = range.len() as u64;
        let answer = answer.map_err(|e| request_error(e, fields, range, n, several))?;
        take(b, answer)?;
        bar.inc(b);
    }
    bar.finish_and_clear();
    Ok(())
}

/// The output of `score` and `grad`: `reward` [N], then `more` arrays, then `window_start` [N]
/// for windows cut from trajectories, written to `--out` when given; the report's fields are
/// model, items, t and reward, then `more_text`, then out, and its JSON document has the
/// fields both commands share plus those of `more_json` (an object).
async fn query_report(
    input: &InputArgs,
    items: &Items,
    t: u32,
    rewards: Vec<f32>,
    more: Vec<(&'static str, Vec<u64>, Vec<f32>)>,
    more_text: Vec<(&'static str, String)>,
    more_json: Value,
) -> Result<Report> {
    let n = items.len();
    let item_shape = items.item_shape();
    let summary = summarize(rewards.iter().map(|&v| f64::from(v)));
    let mut arrays = OutArrays::default();
    arrays.f32s.push(("reward", vec![n as u64], rewards));
    arrays.f32s.extend(more);
    if let Items::Windows(w) = items {
        arrays.i64s.push(("window_start", vec![n as u64], w.starts.iter().map(|&s| s as i64).collect()));
    }
    let (shapes_json, shapes_text) = arrays.write_to(input.out.as_deref()).await?;

    let mut fields = vec![
        ("model", input.model.clone()),
        ("items", format!("{n} ({}, each {item_shape:?})", items.describe())),
        ("t", t.to_string()),
        ("reward", summary_text(summary)),
    ];
    fields.extend(more_text);
    if let Some(out) = &input.out {
        fields.push(("out", format!("{} ({shapes_text})", out.display())));
    }
    let mut json = json!({
        "model": input.model,
        "input": input.input.display().to_string(),
        "source": items.source_json(),
        "count": n,
        "item_shape": item_shape,
        "t": t,
        "units": input.units.name(),
        "reward": summary_json(summary),
        "out": input.out.as_ref().map(|p| p.display().to_string()),
        "arrays": shapes_json,
    });
    if let (Some(doc), Value::Object(more)) = (json.as_object_mut(), more_json) {
        doc.extend(more);
    }
    Ok(Report::ok(key_values(&fields, 0), json))
}

// ---------------------------------------------------------------------------------------------
// score

pub async fn score(ctx: &Ctx, args: ScoreArgs) -> Result<Report> {
    let ScoreArgs { input, t, per_window, per_step } = args;
    check_out(input.out.as_deref())?;
    let client = ctx.connect().await?;
    let items = read_items(&client, &input).await?;
    let n = items.len();
    let batch = request_batch(input.batch, items.item_len() as u64 * 4, ctx.json);
    let ranges = batches(n, batch);

    let mut fields = query_fields(&input, t);
    fields.push(("per_window", "--per-window".to_owned()));
    fields.push(("per_step", "--per-step".to_owned()));
    let mut rewards = Vec::with_capacity(n);
    let mut windows: Option<(u64, Vec<f32>)> = None;
    let mut steps: Option<(u64, Vec<f32>)> = None;
    let send = |_, range| {
        let request = pb::ScoreRequest {
            model: input.model.clone(),
            x: Some(items.batch(range)),
            t: vec![t],
            input_units: input.units.to_proto() as i32,
            per_window,
            per_step,
        };
        let client = client.clone();
        async move { client.score(request).await }
    };
    query_batches(ctx, &ranges, &fields, send, |b, answer: pb::ScoreResponse| {
        rewards.extend(floats(answer.rewards.as_ref(), "rewards", &[b])?);
        for (wanted, field, tensor, acc) in [
            (per_window, "per_window", answer.per_window.as_ref(), &mut windows),
            (per_step, "per_step", answer.per_step.as_ref(), &mut steps),
        ] {
            if !wanted {
                continue;
            }
            let width = match (acc.as_ref(), tensor) {
                (Some((w, _)), _) => *w,
                (None, Some(t)) if t.shape.len() == 2 => t.shape[1],
                (None, Some(t)) => bail!("the server's answer has {field} of shape {:?}; expected [{b}, K]", t.shape),
                (None, None) => bail!("the server's answer has no {field}"),
            };
            let values = floats(tensor, field, &[b, width])?;
            acc.get_or_insert_with(|| (width, Vec::new())).1.extend(values);
        }
        Ok(())
    })
    .await?;

    let mut more = Vec::new();
    if let Some((w, values)) = windows {
        more.push(("per_window", vec![n as u64, w], values));
    }
    if let Some((w, values)) = steps {
        more.push(("per_step", vec![n as u64, w], values));
    }
    query_report(&input, &items, t, rewards, more, Vec::new(), json!({})).await
}

// ---------------------------------------------------------------------------------------------
// grad

pub async fn grad(ctx: &Ctx, args: GradArgs) -> Result<Report> {
    let GradArgs { input, t, gradient_units, omega, scale_by_posterior_variance_of } = args;
    if let Some(w) = omega.filter(|w| !w.is_finite()) {
        return Err(UsageError(format!("--omega {w}: must be a finite number")).into());
    }
    if scale_by_posterior_variance_of.as_deref() == Some("") {
        return Err(UsageError("--scale-by-posterior-variance-of: needs a diffusion model name".into()).into());
    }
    check_out(input.out.as_deref())?;
    let client = ctx.connect().await?;
    let items = read_items(&client, &input).await?;
    let n = items.len();
    let item_shape = items.item_shape();
    let item_len = items.item_len();
    // The answer carries a gradient as large as the request: keep both under the limit.
    let batch = request_batch(input.batch, item_len as u64 * 4, ctx.json);
    let ranges = batches(n, batch);

    let mut fields = query_fields(&input, t);
    fields.push(("gradient_units", "--gradient-units".to_owned()));
    if let Some(w) = omega {
        fields.push(("omega", format!("--omega {w}")));
    }
    if let Some(base) = &scale_by_posterior_variance_of {
        fields.push(("scale_by_posterior_variance_of", format!("--scale-by-posterior-variance-of {base}")));
    }
    let mut rewards = Vec::with_capacity(n);
    let mut gradients = Vec::with_capacity(n * item_len);
    let send = |i: usize, range| {
        let request = pb::GradientRequest {
            request_id: i as u64,
            model: input.model.clone(),
            x: Some(items.batch(range)),
            t: vec![t],
            input_units: input.units.to_proto() as i32,
            gradient_units: gradient_units.to_proto() as i32,
            omega,
            scale_by_posterior_variance_of: scale_by_posterior_variance_of.clone().unwrap_or_default(),
        };
        let client = client.clone();
        async move { client.gradient(request).await }
    };
    query_batches(ctx, &ranges, &fields, send, |b, answer: pb::GradientResponse| {
        rewards.extend(floats(answer.rewards.as_ref(), "rewards", &[b])?);
        let mut shape = vec![b];
        shape.extend(&item_shape);
        gradients.extend(floats(answer.gradient.as_ref(), "gradient", &shape)?);
        Ok(())
    })
    .await?;

    let norms = summarize(
        gradients.chunks(item_len.max(1)).map(|g| g.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>().sqrt()),
    );
    let mut grad_shape = vec![n as u64];
    grad_shape.extend(&item_shape);
    let more = vec![("grad_x", grad_shape, gradients)];
    let text = vec![("|grad_x|", summary_text(norms))];
    let json = json!({
        "gradient_units": gradient_units.name(),
        "omega": omega.unwrap_or(1.0),
        "scale_by_posterior_variance_of": scale_by_posterior_variance_of,
        "gradient_norm": summary_json(norms),
    });
    query_report(&input, &items, t, rewards, more, text, json).await
}

// ---------------------------------------------------------------------------------------------
// sample

/// Checks the guidance flags together: `--reward` and `--scale` come as a pair, and the
/// guidance settings need them.
fn check_guidance(args: &SampleArgs) -> Result<(), UsageError> {
    match (&args.reward, args.scale) {
        (Some(r), None) => {
            return Err(UsageError(format!(
                "--reward {r} needs --scale W, the guidance scale omega (e.g. --scale 0.1)"
            )));
        }
        (None, Some(_)) => {
            return Err(UsageError(
                "--scale needs --reward R: the guidance scale multiplies that reward model's gradient".into(),
            ));
        }
        (Some(_), Some(w)) if !w.is_finite() => {
            return Err(UsageError(format!("--scale {w}: must be a finite number")));
        }
        _ => {}
    }
    if args.reward.is_none() {
        let given = [
            ("--t-stopgrad", args.t_stopgrad.is_some()),
            ("--n-guide-steps", args.n_guide_steps.is_some()),
            ("--scale-grad-by-std", args.scale_grad_by_std),
        ];
        if let Some((flag, _)) = given.iter().find(|(_, set)| *set) {
            return Err(UsageError(format!("{flag} only applies to guided sampling: give --reward R and --scale W")));
        }
    }
    if args.reward.as_deref() == Some("") {
        return Err(UsageError("--reward: needs a reward model name".into()));
    }
    Ok(())
}

/// Checks `--condition`s against the base model's trajectory space (horizon, obs_dim).
fn check_conditions(base: &pb::Model, conditions: &[ConditionArg]) -> Result<()> {
    use pb::diffusion_manifest::Space;
    if base.kind() != pb::ModelKind::Diffusion {
        bail!(
            "--base {}: is not a diffusion model; sampling needs one (relreward model list --kind diffusion)",
            base.name
        );
    }
    if conditions.is_empty() {
        return Ok(());
    }
    let space = base.manifest.as_ref().and_then(|m| m.space.as_ref());
    let Some(Space::Trajectory(traj)) = space else {
        bail!(
            "--condition {}: model '{}' samples fixed-shape items, not trajectories; conditions fix an observation \
             at a horizon index",
            conditions[0].text(),
            base.name
        );
    };
    for c in conditions {
        if c.index >= traj.horizon {
            bail!(
                "--condition {}: index {} is outside model '{}''s horizon 0..{}",
                c.text(),
                c.index,
                base.name,
                traj.horizon
            );
        }
        if c.state.len() != traj.obs_dim as usize {
            bail!(
                "--condition {}: {} values but model '{}' has obs_dim {}",
                c.text(),
                c.state.len(),
                base.name,
                traj.obs_dim
            );
        }
    }
    Ok(())
}

/// Request fields of Sample and the flags that set them.
fn sample_fields(args: &SampleArgs) -> Vec<(&'static str, String)> {
    let opt = |flag: &str, v: Option<String>| v.map_or_else(|| flag.to_owned(), |v| format!("{flag} {v}"));
    vec![
        ("model", format!("--base {}", args.base)),
        ("reward_model", opt("--reward", args.reward.clone())),
        ("omega", opt("--scale", args.scale.map(|w| w.to_string()))),
        ("n_guide_steps", opt("--n-guide-steps", args.n_guide_steps.map(|v| v.to_string()))),
        ("t_stopgrad", opt("--t-stopgrad", args.t_stopgrad.map(|v| v.to_string()))),
        ("scale_grad_by_std", "--scale-grad-by-std".to_owned()),
        ("conditions", "--condition".to_owned()),
        ("n", format!("--n {}", args.n)),
        ("batch_size", opt("--batch-size", args.batch_size.map(|v| v.to_string()))),
    ]
}

/// One sample as it arrived: raw values, normalized values and its reward (guided sampling).
type Sampled = (Vec<f32>, Vec<f32>, Option<f64>);

pub async fn sample(ctx: &Ctx, args: SampleArgs) -> Result<Report> {
    check_guidance(&args)?;
    check_out(args.out.as_deref())?;
    let client = ctx.connect().await?;
    let base = client.get_model(&args.base).await.with_context(|| format!("--base {}", args.base))?;
    check_conditions(&base, &args.conditions)?;
    let guided = args.reward.is_some();
    let request = pb::SampleRequest {
        model: args.base.clone(),
        reward_model: args.reward.clone().unwrap_or_default(),
        omega: args.scale.unwrap_or(0.0),
        n_guide_steps: args.n_guide_steps,
        t_stopgrad: args.t_stopgrad,
        scale_grad_by_std: args.scale_grad_by_std,
        conditions: args
            .conditions
            .iter()
            .map(|c| pb::Condition {
                index: c.index,
                state: Some(tensor::encode_f64(&[c.state.len() as u64], &c.state)),
            })
            .collect(),
        input_units: pb::Units::Raw as i32,
        n: args.n,
        seed: args.seed,
        batch_size: args.batch_size.unwrap_or(0),
    };
    let n = args.n as usize;
    let bar = item_bar(ctx.json, n as u64, "samples");
    let fields = sample_fields(&args);
    let labelled = |e: ClientError| match flag_of(&e, &fields) {
        Some(flag) => anyhow::Error::new(e).context(flag),
        None => anyhow::Error::new(e),
    };
    let mut stream = client.sample(request).await.map_err(labelled)?;
    let mut shape: Option<Vec<u64>> = None;
    let mut x: Vec<Option<Sampled>> = vec![None; n];
    while let Some(item) = stream.message().await.map_err(|e| labelled(e.into()))? {
        let i = item.index as usize;
        if i >= n || x[i].is_some() {
            bail!("the server sent sample {i} {}", if i >= n { "beyond --n" } else { "twice" });
        }
        let got = item.x.as_ref().map(|t| t.shape.clone()).unwrap_or_default();
        let shape = shape.get_or_insert(got);
        let raw = floats(item.x.as_ref(), "x", shape)?;
        let normalized = floats(item.x_normalized.as_ref(), "x_normalized", shape)?;
        if guided && item.reward.is_none() {
            bail!("the server sent sample {i} without its reward");
        }
        x[i] = Some((raw, normalized, item.reward));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let missing = x.iter().filter(|v| v.is_none()).count();
    if missing > 0 {
        bail!("the server's stream ended after {} of {n} samples", n - missing);
    }
    let shape = shape.unwrap_or_default();
    let (mut raw, mut normalized, mut rewards) = (Vec::new(), Vec::new(), Vec::new());
    for (r, z, reward) in x.into_iter().flatten() {
        raw.extend(r);
        normalized.extend(z);
        rewards.extend(reward);
    }
    let summary = guided.then(|| summarize(rewards.iter().copied())).flatten();
    let mut full = vec![n as u64];
    full.extend(&shape);
    let mut arrays = OutArrays::default();
    arrays.f32s.push(("x", full.clone(), raw));
    arrays.f32s.push(("x_normalized", full, normalized));
    if guided {
        arrays.f32s.push(("reward", vec![n as u64], rewards.iter().map(|&r| r as f32).collect()));
    }
    let (shapes_json, shapes_text) = arrays.write_to(args.out.as_deref()).await?;

    let mut fields = vec![
        ("base", args.base.clone()),
        ("samples", format!("{n}, each {shape:?}")),
        ("seed", args.seed.map_or_else(|| "-".to_owned(), |s| s.to_string())),
    ];
    if let (Some(r), Some(w)) = (&args.reward, args.scale) {
        fields.push(("guidance", format!("{r}, scale {w}")));
        fields.push(("reward", summary_text(summary)));
    }
    if let Some(out) = &args.out {
        fields.push(("out", format!("{} ({shapes_text})", out.display())));
    }
    let json = json!({
        "base": args.base,
        "reward_model": args.reward,
        "scale": args.scale,
        "t_stopgrad": args.t_stopgrad,
        "n_guide_steps": args.n_guide_steps,
        "scale_grad_by_std": args.scale_grad_by_std,
        "conditions": args.conditions.iter().map(|c| json!({ "index": c.index, "state": c.state })).collect::<Vec<_>>(),
        "count": n,
        "shape": shape,
        "seed": args.seed,
        "reward": if guided { summary_json(summary) } else { Value::Null },
        "out": args.out.as_ref().map(|p| p.display().to_string()),
        "arrays": shapes_json,
    });
    Ok(Report::ok(key_values(&fields, 0), json))
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
        use relreward_client::npz_write::NpzWriter;
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
    fn conditions_parse_and_summaries_are_population_statistics() {
        assert_eq!(parse_condition("3=1.5,-2,0").expect("ok"), ConditionArg { index: 3, state: vec![1.5, -2.0, 0.0] });
        assert!(parse_condition("3").is_err());
        assert!(parse_condition("x=1").is_err());
        assert!(parse_condition("-1=1").is_err());
        assert!(parse_condition("0=1,,2").is_err());
        assert!(parse_condition("0=nan").is_err());
        assert_eq!(ConditionArg { index: 2, state: vec![1.5, -2.0] }.text(), "2=1.5,-2");
        let s = summarize([1.0, 2.0, 3.0, 4.0]).expect("values");
        assert_eq!((s.mean, s.min, s.max), (2.5, 1.0, 4.0));
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-12);
        assert_eq!(summarize(std::iter::empty()), None);
        assert_eq!(summary_json(None), Value::Null);
    }

    #[test]
    fn server_errors_name_the_flag_of_the_field_they_name() {
        let fields = vec![("t", "--t 100".to_owned()), ("x", "--input".to_owned()), ("omega", "--omega 2".to_owned())];
        let status = |m: &str| ClientError::Status(tonic::Status::invalid_argument(m));
        assert_eq!(flag_of(&status("t[0]: 100 is outside [0, 10)"), &fields).as_deref(), Some("--t 100"));
        assert_eq!(flag_of(&status("omega: inf is not finite"), &fields).as_deref(), Some("--omega 2"));
        assert_eq!(flag_of(&status("x.shape: no"), &fields).as_deref(), Some("--input"));
        assert_eq!(flag_of(&status("tx: other"), &fields), None);
        assert_eq!(flag_of(&status("the server is busy"), &fields), None);
        assert_eq!(flag_of(&ClientError::Invalid("t: local".into()), &fields), None);
        // The label and the status, as `relreward` prints them (without the status's sources).
        let text = |e: anyhow::Error| e.chain().take(2).map(ToString::to_string).collect::<Vec<_>>().join(": ");
        let r = 16..32;
        assert_eq!(
            text(request_error(status("t[0]: bad"), &fields, &r, 40, true)),
            "--t 100: INVALID_ARGUMENT: t[0]: bad"
        );
        assert!(
            text(request_error(status("x: bad"), &fields, &r, 40, true)).starts_with("--input, items 16..32 of 40: ")
        );
        assert!(text(request_error(status("busy"), &fields, &r, 40, true)).starts_with("items 16..32 of 40: "));
        let plain = request_error(status("busy"), &fields, &r, 40, false);
        assert_eq!(plain.to_string(), "INVALID_ARGUMENT: busy");
    }

    #[test]
    fn batches_are_lowered_to_fit_a_request() {
        assert_eq!(request_batch(256, 32 * 6 * 4, true), 256);
        assert_eq!(request_batch(256, 4 * 64 * 64 * 4, true), 128);
        assert_eq!(request_batch(4, MAX_REQUEST_BYTES * 2, true), 1);
    }
}
