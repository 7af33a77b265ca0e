//! Importing a model folder written by diffusers' `save_pretrained` (a `UNet1DModel` or a
//! `UNet2DModel` with its `DDPMScheduler`) into relreward's native weights and a manifest,
//! offline: without Python, libtorch or a network.
//!
//! Module map:
//! - [`locate`]: the files of an import in a directory: the model's `config.json` and
//!   `diffusion_pytorch_model.safetensors` (at the top, in `--subfolder`, or in a pipeline's
//!   `unet/`) and the scheduler's `scheduler_config.json` (`scheduler/`);
//! - [`hub_cache`], [`hub_snapshot`]: the same folder in a local Hugging Face cache, by
//!   repository id (`$HF_HOME/hub/models--ORG--NAME/snapshots/<refs/main>/`); nothing is
//!   downloaded;
//! - [`import_folder`]: reads and checks both configs, reads the weights, checks every tensor
//!   and returns the native tensors with the manifest; everything refused is named, every
//!   config problem and every tensor mismatch at once;
//! - [`unet1d_table`], [`unet2d_table`]: every tensor the accepted configurations have, under
//!   diffusers' name and relreward's, with its shape;
//! - [`schedule_betas`]: a `DDPMScheduler` config's betas, as diffusers computes them.
//!
//! What is accepted, and why only that (relreward runs its own networks, so a config is
//! accepted only where relreward's network computes exactly what diffusers' does):
//! - `UNet1DModel` in the configuration of Diffuser's `TemporalUnet` (what diffusers'
//!   `scripts/convert_models_diffuser_to_diffusers.py` converts for its value-guided RL
//!   planners): `DownResnetBlock1D` on every level, `UpResnetBlock1D` on all but one,
//!   `MidResTemporalBlock1D`, `OutConv1DBlock`, positional time embedding through
//!   `TimestepEmbedding` (`use_timestep_embedding`), mish, one extra layer per block, GroupNorm(8).
//!   Diffuser's sinusoid divides the log-frequency step by half - 1, which is diffusers'
//!   `freq_shift = 1`; `flip_sin_to_cos` only swaps the embedding's halves, so either value is
//!   taken, the swap carried into the first time layer's columns. The names differ
//!   (`down_blocks.0.resnets.1.conv_in.conv1d` is Diffuser's `downs.0.1.blocks.0.block.0`).
//! - `UNet2DModel` in the configuration of relreward's `unet2d` (`server/src/engine/nets/unet2d.rs`,
//!   whose names are diffusers' own): `DownBlock2D` / `UpBlock2D`, attention (`AttnDownBlock2D`,
//!   `AttnUpBlock2D`, `add_attention`) at the lowest resolution or nowhere, silu, GroupNorm eps
//!   1e-5, `freq_shift = 0` (either `flip_sin_to_cos`, as above); a class embedding as
//!   `num_class_embeds` (an nn.Embedding of labels, relreward's `labels` conditioning, with the
//!   null label the model was trained with given by `--null-class`, if any) or
//!   `class_embed_type = "identity"` (an embedding vector of the time embedding's width added
//!   as it is, relreward's `embedding` conditioning, whose null is the zero vector); the
//!   `"timestep"` and projection types are refused.
//! - `DDPMScheduler`: any `beta_schedule` diffusers has (linear, scaled_linear,
//!   squaredcos_cap_v2, sigmoid, laplace, trained_betas), written to the manifest as the
//!   explicit float32 betas diffusers uses; `prediction_type` epsilon, sample (relreward's x0)
//!   or v_prediction (relreward's v);
//!   `clip_sample` with range 1 (relreward's `clip_denoised`); `variance_type` fixed_small or
//!   fixed_small_log (the posterior variance relreward's sampler adds). Thresholding,
//!   zero-SNR rescaling and the other variances are refused.
//!
//! A field a config leaves out takes diffusers' default (as `from_pretrained` does); a field
//! this module does not know is refused, since it could change what the network computes.
//! `timestep_spacing` and `steps_offset` choose the steps of a shortened inference schedule;
//! relreward samples every one of the T steps, so they change nothing here (nor do
//! `sample_size` of a UNet1DModel, `sample_rate` and `num_train_timesteps` of a UNet2DModel,
//! nor `dropout`, which acts in training only).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use relreward_proto::schema::manifest::{
    Architecture, Conditioning, DiffusionManifest, Normalizer, Parametrization, ScheduleSpec, Space,
};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde_json::{Map, Value, json};

use crate::diffuser_import::{Mismatch, NamedTensor, check_shapes};
use crate::values::f16_to_f32;

/// The model's configuration, beside its weights.
pub const CONFIG: &str = "config.json";
/// The weights `save_pretrained` writes (safetensors, its default since diffusers 0.19).
pub const WEIGHTS: &str = "diffusion_pytorch_model.safetensors";
/// The scheduler's configuration, in `scheduler/` in a pipeline's folder.
pub const SCHEDULER_CONFIG: &str = "scheduler_config.json";

/// Why an import was refused or failed; the message names the file and the field or tensor.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct ImportError(pub String);

fn fail<T>(message: String) -> Result<T, ImportError> {
    Err(ImportError(message))
}

// ---------------------------------------------------------------------------------------------
// Finding the files

/// The files of one import.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Folder {
    /// The directory holding `config.json` and the weights.
    pub model_dir: PathBuf,
    /// The scheduler's `scheduler_config.json`.
    pub scheduler_config: PathBuf,
}

impl Folder {
    pub fn config(&self) -> PathBuf {
        self.model_dir.join(CONFIG)
    }

    pub fn weights(&self) -> PathBuf {
        self.model_dir.join(WEIGHTS)
    }
}

/// Finds the model and its scheduler under `root`, a directory laid out as `save_pretrained`
/// writes it:
/// - the model: `root/<subfolder>` when given; else `root` when it holds `config.json` (a model
///   saved on its own); else `root/unet` (a pipeline: `model_index.json`, `unet/`,
///   `scheduler/`, ...);
/// - the scheduler: `scheduler_config` when given; else the first of `root/scheduler/`,
///   `<model>/scheduler/`, `<model>/` and `root/` that holds `scheduler_config.json`.
pub fn locate(root: &Path, subfolder: Option<&str>, scheduler_config: Option<&Path>) -> Result<Folder, ImportError> {
    if !root.is_dir() {
        return fail(format!("{}: not a directory", root.display()));
    }
    let model_dir = match subfolder {
        Some(sub) => {
            let dir = root.join(sub);
            if !dir.join(CONFIG).is_file() {
                return fail(format!("--subfolder {sub}: {} has no {CONFIG}", dir.display()));
            }
            dir
        }
        None if root.join(CONFIG).is_file() => root.to_owned(),
        None if root.join("unet").join(CONFIG).is_file() => root.join("unet"),
        None => {
            return fail(format!(
                "{}: no {CONFIG} and no unet/{CONFIG}: not a folder written by save_pretrained (a model: {CONFIG} and \
                 {WEIGHTS}; a pipeline: unet/ and scheduler/; another subfolder: --subfolder NAME)",
                root.display()
            ));
        }
    };
    let scheduler_config = match scheduler_config {
        Some(path) if path.is_file() => path.to_owned(),
        Some(path) => return fail(format!("--scheduler-config: {} is not a file", path.display())),
        None => {
            let mut candidates =
                vec![root.join("scheduler"), model_dir.join("scheduler"), model_dir.clone(), root.to_owned()];
            candidates.dedup();
            let candidates: Vec<PathBuf> = candidates.into_iter().map(|d| d.join(SCHEDULER_CONFIG)).collect();
            match candidates.iter().find(|p| p.is_file()) {
                Some(found) => found.clone(),
                None => {
                    let looked: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
                    return fail(format!(
                        "no {SCHEDULER_CONFIG} (looked at {}): the schedule, T and the parametrization come from \
                         the DDPMScheduler saved with the model (scheduler.save_pretrained(DIR/\"scheduler\")), \
                         or from --scheduler-config FILE",
                        looked.join(", ")
                    ));
                }
            }
        }
    };
    Ok(Folder { model_dir, scheduler_config })
}

/// The Hugging Face hub cache directory, as `huggingface_hub` finds it: `HF_HUB_CACHE`, else
/// `HF_HOME/hub`, else `XDG_CACHE_HOME/huggingface/hub`, else `~/.cache/huggingface/hub`.
/// `env` reads a variable (`|k| std::env::var(k).ok()`); empty values count as unset.
pub fn hub_cache(env: &dyn Fn(&str) -> Option<String>) -> Option<PathBuf> {
    let var = |k: &str| env(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    if let Some(dir) = var("HF_HUB_CACHE") {
        return Some(dir);
    }
    let home = var("HF_HOME")
        .or_else(|| var("XDG_CACHE_HOME").map(|d| d.join("huggingface")))
        .or_else(|| var("HOME").map(|d| d.join(".cache").join("huggingface")))?;
    Some(home.join("hub"))
}

/// Whether `s` has the form of a hub repository id: `NAME` or `ORG/NAME`, each part of ASCII
/// letters, digits, `-`, `_` and `.`, not starting with `.` or `-`.
pub fn is_repo_id(s: &str) -> bool {
    let parts: Vec<&str> = s.split('/').collect();
    parts.len() <= 2
        && parts.iter().all(|p| {
            !p.is_empty()
                && !p.starts_with(['.', '-'])
                && p.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        })
}

/// The snapshot directory of `repo_id` at `revision` in the hub cache `cache`:
/// `models--ORG--NAME/snapshots/<commit>`, the commit read from `refs/<revision>`, or
/// `revision` itself when it is a commit whose snapshot is there.
pub fn hub_snapshot(cache: &Path, repo_id: &str, revision: &str) -> Result<PathBuf, ImportError> {
    if !is_repo_id(repo_id) {
        return fail(format!("{repo_id:?} is neither a directory nor a repository id (ORG/NAME)"));
    }
    let repo = cache.join(format!("models--{}", repo_id.replace('/', "--")));
    if !repo.is_dir() {
        return fail(format!(
            "{repo_id}: not in the local Hugging Face cache ({} does not exist; the cache is HF_HUB_CACHE, else \
             HF_HOME/hub, else ~/.cache/huggingface/hub). Nothing is downloaded: fetch it once (e.g. \
             `huggingface-cli download {repo_id}`) or give the folder's path",
            repo.display()
        ));
    }
    if revision.is_empty() || revision.starts_with('/') || revision.split('/').any(|part| part == "..") {
        return fail(format!("--revision: {revision:?} is not a branch, tag or commit"));
    }
    let reference = repo.join("refs").join(revision);
    let commit = if reference.is_file() {
        std::fs::read_to_string(&reference)
            .map_err(|e| ImportError(format!("{}: {e}", reference.display())))?
            .trim()
            .to_owned()
    } else {
        revision.to_owned()
    };
    let snapshot = repo.join("snapshots").join(&commit);
    if commit.is_empty() || commit.contains(['/', '\\']) || !snapshot.is_dir() {
        return fail(format!(
            "{repo_id}: revision {revision:?} is not in the cache (no {} and no snapshot {})",
            reference.display(),
            snapshot.display()
        ));
    }
    Ok(snapshot)
}

// ---------------------------------------------------------------------------------------------
// Configs

/// A config file's fields, read with diffusers' defaults for those left out, and the problems
/// found so far (all of them are reported together).
struct Config {
    file: String,
    map: Map<String, Value>,
    problems: Vec<String>,
}

impl Config {
    fn read(path: &Path) -> Result<Self, ImportError> {
        let text = std::fs::read_to_string(path).map_err(|e| ImportError(format!("{}: {e}", path.display())))?;
        let value: Value =
            serde_json::from_str(&text).map_err(|e| ImportError(format!("{}: not JSON: {e}", path.display())))?;
        let Value::Object(map) = value else {
            return fail(format!("{}: not a JSON object", path.display()));
        };
        Ok(Self { file: path.display().to_string(), map, problems: Vec::new() })
    }

    fn class_name(&self) -> Option<&str> {
        self.map.get("_class_name").and_then(Value::as_str)
    }

    /// Refuses every field neither in `known` nor metadata (`_class_name`, `_diffusers_version`..).
    fn refuse_unknown(&mut self, known: &[&str], class: &str) {
        let unknown: Vec<String> =
            self.map.keys().filter(|k| !k.starts_with('_') && !known.contains(&k.as_str())).cloned().collect();
        for key in unknown {
            self.problems.push(format!(
                "{key}: not a field relreward knows for a {class} (diffusers {}); it could change what the model computes",
                self.map.get("_diffusers_version").and_then(Value::as_str).unwrap_or("version unknown")
            ));
        }
    }

    /// The field's value, or diffusers' default when the config leaves it out.
    fn get(&self, key: &str, default: Value) -> Value {
        self.map.get(key).cloned().unwrap_or(default)
    }

    /// The value as the message shows it: JSON, marked as the default when left out.
    fn shown(&self, key: &str, value: &Value) -> String {
        if self.map.contains_key(key) { value.to_string() } else { format!("{value} (left out: diffusers' default)") }
    }

    fn problem(&mut self, key: &str, value: &Value, why: &str) {
        let shown = self.shown(key, value);
        self.problems.push(format!("{key}: {shown} is not supported: {why}"));
    }

    /// Requires the field to equal `want` (numbers compared as numbers).
    fn require(&mut self, key: &str, default: Value, want: Value, why: &str) {
        let value = self.get(key, default);
        if !same(&value, &want) {
            self.problem(key, &value, &format!("{why}; relreward needs {want}"));
        }
    }

    fn boolean(&mut self, key: &str, default: bool) -> Option<bool> {
        let value = self.get(key, json!(default));
        let b = value.as_bool();
        if b.is_none() {
            self.problem(key, &value, "expected true or false");
        }
        b
    }

    fn count(&mut self, key: &str, default: Value) -> Option<usize> {
        let value = self.get(key, default);
        let n = value.as_u64().and_then(|n| usize::try_from(n).ok()).filter(|&n| n > 0);
        if n.is_none() {
            self.problem(key, &value, "expected a positive integer");
        }
        n
    }

    fn counts(&mut self, key: &str, default: Value) -> Option<Vec<usize>> {
        let value = self.get(key, default);
        let list = value.as_array().and_then(|a| {
            a.iter().map(|v| v.as_u64().and_then(|n| usize::try_from(n).ok()).filter(|&n| n > 0)).collect()
        });
        if list.is_none() {
            self.problem(key, &value, "expected a list of positive integers");
        }
        list
    }

    fn strings(&mut self, key: &str, default: Value) -> Option<Vec<String>> {
        let value = self.get(key, default);
        let list = value.as_array().and_then(|a| a.iter().map(|v| v.as_str().map(str::to_owned)).collect());
        if list.is_none() {
            self.problem(key, &value, "expected a list of block type names");
        }
        list
    }

    /// Every problem found, in one error (`what` says what the file is not).
    fn error(&self, what: &str) -> ImportError {
        let lines: Vec<String> = self.problems.iter().map(|p| format!("  {p}")).collect();
        ImportError(format!("{}: {what}:\n{}", self.file, lines.join("\n")))
    }

    fn finish<T>(self, what: &str, value: T) -> Result<T, ImportError> {
        if self.problems.is_empty() { Ok(value) } else { Err(self.error(what)) }
    }
}

/// JSON equality with numbers compared by value (a config may write 1 or 1.0).
fn same(a: &Value, b: &Value) -> bool {
    match (a.as_f64(), b.as_f64()) {
        (Some(x), Some(y)) => x == y,
        _ => a == b,
    }
}

/// Checks a list of block types: `want[i]` for entry i; the list's length must be `want`'s.
fn block_types(cfg: &mut Config, key: &str, found: &[String], want: &[&str], why: &str) {
    if found.len() != want.len() {
        let value = cfg.get(key, Value::Null);
        cfg.problem(key, &value, &format!("{} entries, expected {} ({why})", found.len(), want.len()));
        return;
    }
    for (i, (f, w)) in found.iter().zip(want).enumerate() {
        if f != w {
            cfg.problems.push(format!("{key}[{i}]: block type {f:?} is not supported ({why}); relreward needs {w:?}"));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// UNet1DModel -> temporal_unet

/// Every `UNet1DModel.__init__` argument (diffusers 0.42).
const UNET1D_FIELDS: &[&str] = &[
    "sample_size",
    "sample_rate",
    "in_channels",
    "out_channels",
    "extra_in_channels",
    "time_embedding_type",
    "time_embedding_dim",
    "flip_sin_to_cos",
    "use_timestep_embedding",
    "freq_shift",
    "down_block_types",
    "up_block_types",
    "mid_block_type",
    "out_block_type",
    "block_out_channels",
    "act_fn",
    "norm_num_groups",
    "layers_per_block",
    "downsample_each_block",
];

/// One tensor of an import: its name in the diffusers file, its name in relreward's weights,
/// and its shape (the same on both sides).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Entry {
    pub source: String,
    pub target: String,
    pub shape: Vec<u64>,
}

/// What a model config maps to.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Plan {
    class: ModelClass,
    architecture: Architecture,
    /// Channels of the input (and output): the transition dim or the image's channels.
    channels: usize,
    /// Levels (len(block_out_channels)): sizes must divide by 2^(levels - 1).
    levels: usize,
    /// `UNet2DModel.sample_size`, when it gives the image size.
    sample_size: Option<(usize, usize)>,
    table: Vec<Entry>,
    /// diffusers' embedding has its sine and cosine halves the other way round from
    /// relreward's: swap the first time layer's input columns.
    swap_time_halves: bool,
    /// A class-conditional UNet2DModel's conditioning (its null label from the hints).
    conditioning: Option<Conditioning>,
}

/// The two model classes accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelClass {
    Unet1d,
    Unet2d,
}

impl ModelClass {
    pub fn name(self) -> &'static str {
        match self {
            Self::Unet1d => "UNet1DModel",
            Self::Unet2d => "UNet2DModel",
        }
    }
}

const TEMPORAL: &str = "relreward imports a UNet1DModel in the configuration of Diffuser's TemporalUnet, as diffusers' \
                        convert_models_diffuser_to_diffusers.py writes it";

fn unet1d_plan(mut cfg: Config) -> Result<Plan, ImportError> {
    cfg.refuse_unknown(UNET1D_FIELDS, "UNet1DModel");
    cfg.require(
        "time_embedding_type",
        json!("fourier"),
        json!("positional"),
        "Diffuser's time embedding is sinusoidal",
    );
    cfg.require(
        "use_timestep_embedding",
        json!(false),
        json!(true),
        "Diffuser's time embedding goes through an MLP (time_mlp)",
    );
    cfg.require(
        "freq_shift",
        json!(0.0),
        json!(1),
        "Diffuser's sinusoid divides the log-frequency step by half - 1, which is freq_shift 1",
    );
    let flip = cfg.boolean("flip_sin_to_cos", true);
    cfg.require("act_fn", Value::Null, json!("mish"), "Diffuser's TemporalUnet uses mish");
    cfg.require("mid_block_type", json!("UNetMidBlock1D"), json!("MidResTemporalBlock1D"), TEMPORAL);
    cfg.require("out_block_type", Value::Null, json!("OutConv1DBlock"), TEMPORAL);
    cfg.require("layers_per_block", json!(1), json!(1), "Diffuser's TemporalUnet has two residual blocks per level");
    cfg.require("downsample_each_block", json!(false), json!(false), TEMPORAL);
    cfg.require("extra_in_channels", json!(0), json!(0), "the network's input is the trajectory itself");
    let in_channels = cfg.count("in_channels", json!(2));
    let out_channels = cfg.count("out_channels", json!(2));
    if let (Some(i), Some(o)) = (in_channels, out_channels)
        && i != o
    {
        let value = cfg.get("out_channels", Value::Null);
        cfg.problem("out_channels", &value, &format!("a denoiser's output has its input's {i} channels"));
    }
    let widths = cfg.counts("block_out_channels", json!([32, 32, 64]));
    let mut dim_mults = None;
    if let Some(w) = &widths {
        let dim = w.first().copied().unwrap_or(0);
        let value = cfg.get("block_out_channels", Value::Null);
        if w.is_empty() || w.len() > 16 {
            cfg.problem("block_out_channels", &value, "1 to 16 levels");
        } else if dim % 8 != 0 {
            cfg.problem(
                "block_out_channels",
                &value,
                "the first width is the TemporalUnet's dim, a multiple of 8 (GroupNorm with 8 groups)",
            );
        } else if let Some(bad) = w.iter().find(|&&c| c % dim != 0) {
            cfg.problem(
                "block_out_channels",
                &value,
                &format!(
                    "{bad} is not a multiple of the first width {dim} (the TemporalUnet's widths are dim * dim_mults)"
                ),
            );
        } else {
            dim_mults = Some(w.iter().map(|c| c / dim).collect::<Vec<usize>>());
        }
        // GroupNorm of the output block: norm_num_groups, or diffusers' rule when null.
        let groups = cfg.get("norm_num_groups", json!(8));
        let effective = if groups.is_null() { json!((dim / 4).min(32)) } else { groups.clone() };
        if !same(&effective, &json!(8)) {
            cfg.problem(
                "norm_num_groups",
                &groups,
                "Diffuser's final Conv1dBlock normalises with GroupNorm(8); relreward needs 8",
            );
        }
        let levels = w.len();
        if let Some(down) =
            cfg.strings("down_block_types", json!(["DownBlock1DNoSkip", "DownBlock1D", "AttnDownBlock1D"]))
        {
            block_types(&mut cfg, "down_block_types", &down, &vec!["DownResnetBlock1D"; levels], TEMPORAL);
        }
        if let Some(up) = cfg.strings("up_block_types", json!(["AttnUpBlock1D", "UpBlock1D", "UpBlock1DNoSkip"])) {
            let why = "Diffuser's TemporalUnet has one up level fewer than its down levels";
            block_types(&mut cfg, "up_block_types", &up, &vec!["UpResnetBlock1D"; levels.saturating_sub(1)], why);
        }
    }
    let (Some(channels), Some(widths), Some(dim_mults), Some(flip)) = (in_channels, widths, dim_mults, flip) else {
        return Err(cfg.error("not an importable UNet1DModel"));
    };
    let dim = widths[0];
    let table = unet1d_table(channels as u64, dim as u64, &dim_mults.iter().map(|&m| m as u64).collect::<Vec<_>>());
    let plan = Plan {
        class: ModelClass::Unet1d,
        architecture: Architecture::TemporalUnet { dim, dim_mults },
        channels,
        levels: widths.len(),
        sample_size: None,
        table,
        swap_time_halves: flip,
        conditioning: None,
    };
    cfg.finish("not an importable UNet1DModel", plan)
}

/// The kernel of Diffuser's residual blocks' convolutions (diffusers' Conv1dBlock default).
const KERNEL: u64 = 5;

/// Every tensor of a `UNet1DModel` in TemporalUnet configuration with `dims = [transition_dim,
/// dim * m...]`: diffusers' name, relreward's (Diffuser's) name and the shape. The targets are
/// exactly [`crate::diffuser_import::temporal_unet_shapes`] (a test holds them together).
pub fn unet1d_table(transition_dim: u64, dim: u64, dim_mults: &[u64]) -> Vec<Entry> {
    let mut out = Vec::new();
    let mut put = |source: String, target: String, shape: Vec<u64>| out.push(Entry { source, target, shape });
    fn params(put: &mut dyn FnMut(String, String, Vec<u64>), src: &str, dst: &str, weight: Vec<u64>) {
        let bias = vec![weight[0]];
        put(format!("{src}.weight"), format!("{dst}.weight"), weight);
        put(format!("{src}.bias"), format!("{dst}.bias"), bias);
    }
    // Conv1d, GroupNorm (Diffuser's Conv1dBlock `block.0`, `block.2`).
    fn conv_block(put: &mut dyn FnMut(String, String, Vec<u64>), src: &str, dst: &str, i: u64, o: u64, k: u64) {
        params(put, &format!("{src}.conv1d"), &format!("{dst}.block.0"), vec![o, i, k]);
        params(put, &format!("{src}.group_norm"), &format!("{dst}.block.2"), vec![o]);
    }
    let res_block = |put: &mut dyn FnMut(String, String, Vec<u64>), src: &str, dst: &str, i: u64, o: u64| {
        conv_block(put, &format!("{src}.conv_in"), &format!("{dst}.blocks.0"), i, o, KERNEL);
        conv_block(put, &format!("{src}.conv_out"), &format!("{dst}.blocks.1"), o, o, KERNEL);
        params(put, &format!("{src}.time_emb"), &format!("{dst}.time_mlp.1"), vec![o, dim]);
        if i != o {
            params(put, &format!("{src}.residual_conv"), &format!("{dst}.residual_conv"), vec![o, i, 1]);
        }
    };
    let dims: Vec<u64> = std::iter::once(transition_dim).chain(dim_mults.iter().map(|m| dim * m)).collect();
    let levels = dims.len() - 1;
    params(&mut put, "time_mlp.linear_1", "time_mlp.1", vec![4 * dim, dim]);
    params(&mut put, "time_mlp.linear_2", "time_mlp.3", vec![dim, 4 * dim]);
    for (i, pair) in dims.windows(2).enumerate() {
        let (w_in, w_out) = (pair[0], pair[1]);
        res_block(&mut put, &format!("down_blocks.{i}.resnets.0"), &format!("downs.{i}.0"), w_in, w_out);
        res_block(&mut put, &format!("down_blocks.{i}.resnets.1"), &format!("downs.{i}.1"), w_out, w_out);
        if i + 1 < levels {
            params(
                &mut put,
                &format!("down_blocks.{i}.downsample.conv"),
                &format!("downs.{i}.3.conv"),
                vec![w_out, w_out, 3],
            );
        }
    }
    let mid = dims[levels];
    res_block(&mut put, "mid_block.resnets.0", "mid_block1", mid, mid);
    res_block(&mut put, "mid_block.resnets.1", "mid_block2", mid, mid);
    for (i, pair) in dims[1..].windows(2).rev().enumerate() {
        let (w_in, w_out) = (pair[0], pair[1]);
        res_block(&mut put, &format!("up_blocks.{i}.resnets.0"), &format!("ups.{i}.0"), 2 * w_out, w_in);
        res_block(&mut put, &format!("up_blocks.{i}.resnets.1"), &format!("ups.{i}.1"), w_in, w_in);
        // ConvTranspose1d: [in, out, k].
        params(&mut put, &format!("up_blocks.{i}.upsample.conv"), &format!("ups.{i}.3.conv"), vec![w_in, w_in, 4]);
    }
    params(&mut put, "out_block.final_conv1d_1", "final_conv.0.block.0", vec![dim, dims[1], KERNEL]);
    params(&mut put, "out_block.final_conv1d_gn", "final_conv.0.block.2", vec![dim]);
    params(&mut put, "out_block.final_conv1d_2", "final_conv.1", vec![transition_dim, dim, 1]);
    out
}

// ---------------------------------------------------------------------------------------------
// UNet2DModel -> unet2d

/// Every `UNet2DModel.__init__` argument (diffusers 0.42).
const UNET2D_FIELDS: &[&str] = &[
    "sample_size",
    "in_channels",
    "out_channels",
    "center_input_sample",
    "time_embedding_type",
    "time_embedding_dim",
    "freq_shift",
    "flip_sin_to_cos",
    "down_block_types",
    "mid_block_type",
    "up_block_types",
    "block_out_channels",
    "layers_per_block",
    "mid_block_scale_factor",
    "downsample_padding",
    "downsample_type",
    "upsample_type",
    "dropout",
    "act_fn",
    "attention_head_dim",
    "norm_num_groups",
    "attn_norm_num_groups",
    "norm_eps",
    "resnet_time_scale_shift",
    "add_attention",
    "class_embed_type",
    "num_class_embeds",
    "num_train_timesteps",
];

const UNET2D: &str = "relreward's unet2d is a UNet2DModel of DownBlock2D / UpBlock2D levels with attention at the \
                      lowest resolution (AttnDownBlock2D last, AttnUpBlock2D first, add_attention) or nowhere";

fn unet2d_plan(mut cfg: Config) -> Result<Plan, ImportError> {
    cfg.refuse_unknown(UNET2D_FIELDS, "UNet2DModel");
    cfg.require("center_input_sample", json!(false), json!(false), "relreward feeds the model its input unscaled");
    cfg.require(
        "time_embedding_type",
        json!("positional"),
        json!("positional"),
        "relreward's unet2d embeds time with sinusoids",
    );
    cfg.require("freq_shift", json!(0), json!(0), "relreward's unet2d sinusoid has no frequency shift");
    let flip = cfg.boolean("flip_sin_to_cos", true);
    cfg.require("mid_block_type", json!("UNetMidBlock2D"), json!("UNetMidBlock2D"), UNET2D);
    cfg.require("mid_block_scale_factor", json!(1), json!(1), "relreward's mid block does not rescale its outputs");
    cfg.require("downsample_padding", json!(1), json!(1), "relreward downsamples with a padded stride-2 convolution");
    cfg.require("downsample_type", json!("conv"), json!("conv"), "relreward downsamples with a convolution");
    cfg.require("upsample_type", json!("conv"), json!("conv"), "relreward upsamples by nearest x2 then a convolution");
    cfg.require("act_fn", json!("silu"), json!("silu"), "relreward's unet2d uses silu");
    cfg.require("resnet_time_scale_shift", json!("default"), json!("default"), "relreward adds the time embedding");
    let class_embed_type = cfg.get("class_embed_type", Value::Null);
    let num_class_embeds = cfg.get("num_class_embeds", Value::Null);
    let conditioning = match (class_embed_type.as_str(), &num_class_embeds) {
        (None, Value::Null) if class_embed_type.is_null() => Some(None),
        (None, n) if class_embed_type.is_null() => match n.as_u64().and_then(|n| usize::try_from(n).ok()) {
            Some(n) if n > 0 => Some(Some(ClassEmbedding::Table(n))),
            _ => {
                cfg.problem("num_class_embeds", n, "expected a positive number of classes");
                None
            }
        },
        (Some("identity"), _) => Some(Some(ClassEmbedding::Identity)),
        _ => {
            cfg.problem(
                "class_embed_type",
                &class_embed_type,
                "relreward's unet2d takes num_class_embeds (labels) or \"identity\" (embeddings added as they are)",
            );
            None
        }
    };
    let eps = cfg.get("norm_eps", json!(1e-5));
    if !eps.as_f64().is_some_and(|e| (e - 1e-5).abs() < 1e-12) {
        cfg.problem("norm_eps", &eps, "relreward's GroupNorms use eps 1e-5");
    }
    let dropout = cfg.get("dropout", json!(0.0));
    if !dropout.as_f64().is_some_and(|d| (0.0..1.0).contains(&d)) {
        cfg.problem("dropout", &dropout, "expected a probability in [0, 1)");
    }
    let in_channels = cfg.count("in_channels", json!(3));
    let out_channels = cfg.count("out_channels", json!(3));
    if let (Some(i), Some(o)) = (in_channels, out_channels)
        && i != o
    {
        let value = cfg.get("out_channels", Value::Null);
        cfg.problem("out_channels", &value, &format!("a denoiser's output has its input's {i} channels"));
    }
    let layers = cfg.count("layers_per_block", json!(2)).filter(|&l| {
        l <= 64 || {
            cfg.problems.push(format!("layers_per_block: {l} is more than relreward's 64"));
            false
        }
    });
    let widths = cfg.counts("block_out_channels", json!([224, 448, 672, 896]));
    let groups = cfg.count("norm_num_groups", json!(32));
    let mut attention = None;
    let mut head_dim = None;
    if let Some(w) = &widths {
        let value = cfg.get("block_out_channels", Value::Null);
        let levels = w.len();
        if levels == 0 || levels > 16 {
            cfg.problem("block_out_channels", &value, "1 to 16 levels");
        } else if w[0] % 2 != 0 || w[0] < 4 {
            cfg.problem(
                "block_out_channels",
                &value,
                "the first width, the sinusoid's size, must be even and at least 4",
            );
        }
        let temb = cfg.get("time_embedding_dim", Value::Null);
        if !temb.is_null() && !w.is_empty() && !same(&temb, &json!(4 * w[0])) {
            cfg.problem("time_embedding_dim", &temb, &format!("relreward's time embedding has 4 x {} features", w[0]));
        }
        if let Some(g) = groups
            && let Some(bad) = w.iter().find(|&&c| c % g != 0)
        {
            let value = cfg.get("norm_num_groups", Value::Null);
            cfg.problem("norm_num_groups", &value, &format!("it must divide every width ({bad} is not a multiple)"));
        }
        let attn_groups = cfg.get("attn_norm_num_groups", Value::Null);
        if !attn_groups.is_null() && groups.is_some_and(|g| !same(&attn_groups, &json!(g))) {
            cfg.problem(
                "attn_norm_num_groups",
                &attn_groups,
                "relreward's attention normalises with norm_num_groups groups",
            );
        }
        let down = cfg.strings(
            "down_block_types",
            json!(["DownBlock2D", "AttnDownBlock2D", "AttnDownBlock2D", "AttnDownBlock2D"]),
        );
        let up = cfg.strings("up_block_types", json!(["AttnUpBlock2D", "AttnUpBlock2D", "AttnUpBlock2D", "UpBlock2D"]));
        let add_attention = cfg.boolean("add_attention", true);
        if let (Some(down), Some(up), Some(add_attention)) = (down, up, add_attention)
            && levels > 0
        {
            // The down blocks decide; the rest must agree.
            let attn = down.last().is_some_and(|b| b == "AttnDownBlock2D");
            let want_down: Vec<&str> =
                (0..levels).map(|i| if attn && i + 1 == levels { "AttnDownBlock2D" } else { "DownBlock2D" }).collect();
            let want_up: Vec<&str> =
                (0..levels).map(|i| if attn && i == 0 { "AttnUpBlock2D" } else { "UpBlock2D" }).collect();
            block_types(&mut cfg, "down_block_types", &down, &want_down, UNET2D);
            block_types(&mut cfg, "up_block_types", &up, &want_up, UNET2D);
            if add_attention != attn {
                let value = cfg.get("add_attention", json!(true));
                let why = if attn {
                    "the last down block has attention, so the mid block must too"
                } else {
                    "no down block has attention, so the mid block must have none (set add_attention false)"
                };
                cfg.problem("add_attention", &value, why);
            }
            attention = Some(attn);
            if attn {
                let deepest = w[levels - 1];
                let head = cfg.get("attention_head_dim", json!(8));
                match if head.is_null() { Some(deepest) } else { head.as_u64().and_then(|h| usize::try_from(h).ok()) } {
                    Some(h) if h > 0 && deepest % h == 0 => head_dim = Some(h),
                    _ => cfg.problem(
                        "attention_head_dim",
                        &head,
                        &format!("it must be a positive divisor of the deepest width {deepest}"),
                    ),
                }
            } else {
                head_dim = Some(8);
            }
        }
    }
    let sample_size = match cfg.get("sample_size", Value::Null) {
        Value::Null => None,
        v => {
            let size = match &v {
                Value::Number(n) => n.as_u64().map(|s| (s, s)),
                Value::Array(a) if a.len() == 2 => a[0].as_u64().zip(a[1].as_u64()),
                _ => None,
            };
            let size = size.and_then(|(h, w)| Some((usize::try_from(h).ok()?, usize::try_from(w).ok()?)));
            if size.is_none_or(|(h, w)| h == 0 || w == 0) {
                cfg.problem("sample_size", &v, "expected a positive size or [height, width]");
            }
            size
        }
    };
    let (
        Some(channels),
        Some(widths),
        Some(layers),
        Some(groups),
        Some(attention),
        Some(head_dim),
        Some(flip),
        Some(class_embedding),
    ) = (in_channels, widths, layers, groups, attention, head_dim, flip, conditioning)
    else {
        return Err(cfg.error("not an importable UNet2DModel"));
    };
    let mut table =
        unet2d_table(channels as u64, &widths.iter().map(|&w| w as u64).collect::<Vec<_>>(), layers as u64, attention);
    if let Some(ClassEmbedding::Table(rows)) = class_embedding {
        let name = "class_embedding.weight".to_owned();
        table.push(Entry { source: name.clone(), target: name, shape: vec![rows as u64, 4 * widths[0] as u64] });
    }
    let temb = 4 * widths[0];
    let plan = Plan {
        class: ModelClass::Unet2d,
        levels: widths.len(),
        architecture: Architecture::Unet2d {
            block_out_channels: widths,
            layers_per_block: layers,
            attention,
            norm_num_groups: groups,
            attention_head_dim: head_dim,
        },
        channels,
        sample_size,
        table,
        // relreward's sinusoid is diffusers' flip_sin_to_cos = true (cosines first).
        swap_time_halves: !flip,
        conditioning: class_embedding.map(|c| match c {
            ClassEmbedding::Table(rows) => Conditioning::Labels { num_classes: rows, null_class: None },
            ClassEmbedding::Identity => Conditioning::Embedding { dim: temb },
        }),
    };
    cfg.finish("not an importable UNet2DModel", plan)
}

/// Every tensor of relreward's `unet2d` (diffusers' `UNet2DModel` names, the same on both
/// sides), in the order `server/src/engine/nets/unet2d.rs` builds them.
pub fn unet2d_table(channels: u64, widths: &[u64], layers: u64, attention: bool) -> Vec<Entry> {
    let mut out = Vec::new();
    let mut put = |name: String, shape: Vec<u64>| out.push(Entry { source: name.clone(), target: name, shape });
    fn params(put: &mut dyn FnMut(String, Vec<u64>), p: &str, weight: Vec<u64>) {
        let bias = vec![weight[0]];
        put(format!("{p}.weight"), weight);
        put(format!("{p}.bias"), bias);
    }
    let temb = 4 * widths[0];
    let resnet = |put: &mut dyn FnMut(String, Vec<u64>), p: &str, i: u64, o: u64| {
        params(put, &format!("{p}.norm1"), vec![i]);
        params(put, &format!("{p}.conv1"), vec![o, i, 3, 3]);
        params(put, &format!("{p}.time_emb_proj"), vec![o, temb]);
        params(put, &format!("{p}.norm2"), vec![o]);
        params(put, &format!("{p}.conv2"), vec![o, o, 3, 3]);
        if i != o {
            params(put, &format!("{p}.conv_shortcut"), vec![o, i, 1, 1]);
        }
    };
    let attn = |put: &mut dyn FnMut(String, Vec<u64>), p: &str, c: u64| {
        params(put, &format!("{p}.group_norm"), vec![c]);
        for proj in ["to_q", "to_k", "to_v", "to_out.0"] {
            params(put, &format!("{p}.{proj}"), vec![c, c]);
        }
    };
    let levels = widths.len();
    params(&mut put, "time_embedding.linear_1", vec![temb, widths[0]]);
    params(&mut put, "time_embedding.linear_2", vec![temb, temb]);
    params(&mut put, "conv_in", vec![widths[0], channels, 3, 3]);
    let mut out_c = widths[0];
    for (i, &width) in widths.iter().enumerate() {
        let (input, last) = (out_c, i + 1 == levels);
        out_c = width;
        for j in 0..layers {
            resnet(&mut put, &format!("down_blocks.{i}.resnets.{j}"), if j == 0 { input } else { out_c }, out_c);
            if last && attention {
                attn(&mut put, &format!("down_blocks.{i}.attentions.{j}"), out_c);
            }
        }
        if !last {
            params(&mut put, &format!("down_blocks.{i}.downsamplers.0.conv"), vec![out_c, out_c, 3, 3]);
        }
    }
    let deepest = widths[levels - 1];
    resnet(&mut put, "mid_block.resnets.0", deepest, deepest);
    if attention {
        attn(&mut put, "mid_block.attentions.0", deepest);
    }
    resnet(&mut put, "mid_block.resnets.1", deepest, deepest);
    let reversed: Vec<u64> = widths.iter().rev().copied().collect();
    let mut out_c = reversed[0];
    for i in 0..levels {
        let prev = out_c;
        out_c = reversed[i];
        let input = reversed[(i + 1).min(levels - 1)];
        for j in 0..=layers {
            let skip = if j == layers { input } else { out_c };
            let resnet_in = if j == 0 { prev } else { out_c };
            resnet(&mut put, &format!("up_blocks.{i}.resnets.{j}"), resnet_in + skip, out_c);
            if i == 0 && attention {
                attn(&mut put, &format!("up_blocks.{i}.attentions.{j}"), out_c);
            }
        }
        if i + 1 < levels {
            params(&mut put, &format!("up_blocks.{i}.upsamplers.0.conv"), vec![out_c, out_c, 3, 3]);
        }
    }
    params(&mut put, "conv_norm_out", vec![widths[0]]);
    params(&mut put, "conv_out", vec![channels, widths[0], 3, 3]);
    out
}

// ---------------------------------------------------------------------------------------------
// DDPMScheduler -> parametrization, schedule, clip_denoised

/// Every `DDPMScheduler.__init__` argument (diffusers 0.42).
const SCHEDULER_FIELDS: &[&str] = &[
    "num_train_timesteps",
    "beta_start",
    "beta_end",
    "beta_schedule",
    "trained_betas",
    "variance_type",
    "clip_sample",
    "prediction_type",
    "thresholding",
    "dynamic_thresholding_ratio",
    "clip_sample_range",
    "sample_max_value",
    "timestep_spacing",
    "steps_offset",
    "rescale_betas_zero_snr",
];

/// What the scheduler config gives the manifest.
#[derive(Debug, Clone, PartialEq)]
pub struct SchedulerPlan {
    pub parametrization: Parametrization,
    /// diffusers' float32 betas, as f64.
    pub betas: Vec<f64>,
    pub clip_denoised: bool,
    /// `beta_schedule`, or "trained_betas".
    pub source: String,
}

fn scheduler_plan(path: &Path) -> Result<SchedulerPlan, ImportError> {
    let mut cfg = Config::read(path)?;
    match cfg.class_name() {
        Some("DDPMScheduler") => {}
        other => {
            let shown = other.map_or("missing".to_owned(), |c| format!("{c:?}"));
            return fail(format!(
                "{}: _class_name: {shown}; relreward imports a DDPMScheduler's config (the training schedule it samples \
                 with, all T steps)",
                cfg.file
            ));
        }
    }
    cfg.refuse_unknown(SCHEDULER_FIELDS, "DDPMScheduler");
    let t = cfg.count("num_train_timesteps", json!(1000)).filter(|&t| {
        t <= relreward_proto::schema::manifest::MAX_TIMESTEPS || {
            cfg.problems.push(format!("num_train_timesteps: {t} is more than relreward's maximum"));
            false
        }
    });
    let prediction = cfg.get("prediction_type", json!("epsilon"));
    let parametrization = match prediction.as_str() {
        Some("epsilon") => Some(Parametrization::Epsilon),
        Some("sample") => Some(Parametrization::X0),
        Some("v_prediction") => Some(Parametrization::V),
        _ => {
            cfg.problem(
                "prediction_type",
                &prediction,
                "relreward's parametrizations are epsilon, x0 (diffusers' \"sample\") and v (\"v_prediction\")",
            );
            None
        }
    };
    let variance = cfg.get("variance_type", json!("fixed_small"));
    if !matches!(variance.as_str(), Some("fixed_small" | "fixed_small_log")) {
        cfg.problem(
            "variance_type",
            &variance,
            "relreward's sampler adds the posterior variance (fixed_small or fixed_small_log)",
        );
    }
    cfg.require("thresholding", json!(false), json!(false), "relreward clips x0_hat to [-1, 1] or not at all");
    cfg.require("rescale_betas_zero_snr", json!(false), json!(false), "a zero terminal SNR has beta = 1 at T - 1");
    let clip = cfg.boolean("clip_sample", true);
    if clip == Some(true) {
        cfg.require("clip_sample_range", json!(1.0), json!(1.0), "relreward's clip_denoised clips to [-1, 1]");
    }
    let schedule = cfg.get("beta_schedule", json!("linear"));
    let trained = cfg.get("trained_betas", Value::Null);
    let start = cfg.get("beta_start", json!(0.0001));
    let end = cfg.get("beta_end", json!(0.02));
    let mut betas = None;
    let mut source = String::new();
    if let Some(t) = t {
        if !trained.is_null() {
            source = "trained_betas".into();
            match trained.as_array().and_then(|a| a.iter().map(Value::as_f64).collect::<Option<Vec<f64>>>()) {
                Some(b) if b.len() == t => betas = Some(b),
                Some(b) => {
                    cfg.problems.push(format!("trained_betas: {} values but num_train_timesteps is {t}", b.len()))
                }
                None => cfg.problem("trained_betas", &trained, "expected a list of numbers"),
            }
        } else {
            source = schedule.as_str().unwrap_or_default().to_owned();
            match (start.as_f64(), end.as_f64()) {
                (Some(start), Some(end)) => match schedule_betas(&source, start, end, t) {
                    Some(b) => betas = Some(b),
                    None => cfg.problem(
                        "beta_schedule",
                        &schedule,
                        "relreward knows linear, scaled_linear, squaredcos_cap_v2, sigmoid, laplace and trained_betas",
                    ),
                },
                _ => cfg.problems.push(format!("beta_start, beta_end: {start} and {end} must be numbers")),
            }
        }
    }
    if let Some(b) = &betas
        && let Some(i) = b.iter().position(|b| !(b.is_finite() && *b > 0.0 && *b < 1.0))
    {
        cfg.problems
            .push(format!("{source}: beta[{i}] = {} is not in (0, 1), which every relreward schedule needs", b[i]));
        betas = None;
    }
    let (Some(parametrization), Some(betas), Some(clip)) = (parametrization, betas, clip) else {
        return Err(cfg.error("not an importable DDPMScheduler"));
    };
    let plan = SchedulerPlan {
        parametrization,
        // diffusers holds its betas as float32: the manifest lists those values.
        betas: betas.into_iter().map(|b| f64::from(b as f32)).collect(),
        clip_denoised: clip,
        source,
    };
    cfg.finish("not an importable DDPMScheduler", plan)
}

/// The betas of `DDPMScheduler(beta_schedule = kind, beta_start, beta_end,
/// num_train_timesteps = t)` (before diffusers' rounding to float32); `None` for a kind it does
/// not have.
pub fn schedule_betas(kind: &str, start: f64, end: f64, t: usize) -> Option<Vec<f64>> {
    let linspace = |a: f64, b: f64| -> Vec<f64> {
        if t == 1 {
            return vec![a];
        }
        (0..t).map(|i| a + (b - a) * i as f64 / (t - 1) as f64).collect()
    };
    // diffusers' betas_for_alpha_bar: beta_i = min(1 - abar((i + 1) / T) / abar(i / T), 0.999).
    let from_alpha_bar = |abar: &dyn Fn(f64) -> f64| -> Vec<f64> {
        (0..t).map(|i| (1.0 - abar((i + 1) as f64 / t as f64) / abar(i as f64 / t as f64)).min(0.999)).collect()
    };
    Some(match kind {
        "linear" => linspace(start, end),
        "scaled_linear" => linspace(start.sqrt(), end.sqrt()).into_iter().map(|b| b * b).collect(),
        "squaredcos_cap_v2" => from_alpha_bar(&|x| ((x + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2).cos().powi(2)),
        "laplace" => from_alpha_bar(&|x| {
            let lambda = -0.5 * (0.5 - x).signum() * (1.0 - 2.0 * (0.5 - x).abs() + 1e-6).ln();
            let snr = lambda.exp();
            (snr / (1.0 + snr)).sqrt()
        }),
        "sigmoid" => linspace(-6.0, 6.0).into_iter().map(|x| (end - start) / (1.0 + (-x).exp()) + start).collect(),
        _ => return None,
    })
}

// ---------------------------------------------------------------------------------------------
// safetensors

/// The file's tensors by name (the `safetensors` crate: the format's maintained reader, which
/// checks the header, offsets and sizes).
fn safetensors_tensors<'a>(bytes: &'a [u8], file: &str) -> Result<SafeTensors<'a>, ImportError> {
    SafeTensors::deserialize(bytes).map_err(|e| ImportError(format!("{file}: not a safetensors file: {e}")))
}

/// One stored tensor as float32 values (F32, F16, BF16 and F64 are read; other dtypes refused).
fn stored_values(name: &str, t: &TensorView<'_>, file: &str) -> Result<Vec<f32>, ImportError> {
    let data = t.data();
    Ok(match t.dtype() {
        Dtype::F32 => data.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect(),
        Dtype::F64 => data.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")) as f32).collect(),
        Dtype::F16 => data.chunks_exact(2).map(|c| f16_to_f32(u16::from_le_bytes([c[0], c[1]]))).collect(),
        Dtype::BF16 => {
            data.chunks_exact(2).map(|c| f32::from_bits(u32::from(u16::from_le_bytes([c[0], c[1]])) << 16)).collect()
        }
        other => {
            return fail(format!(
                "{file}: tensor '{name}' is {other:?}; relreward reads float weights (F32, F16, BF16, F64)"
            ));
        }
    })
}

// ---------------------------------------------------------------------------------------------
// The import

/// What the command line adds to the folder, which does not say everything a manifest needs.
#[derive(Debug, Clone, Default)]
pub struct Hints {
    /// `--horizon`: a UNet1DModel's trajectory length (its `sample_size` is not one: the
    /// converted planners say 65536).
    pub horizon: Option<usize>,
    /// `--action-dim`: how many of a UNet1DModel's channels are the action (each row is
    /// [action | observation], Diffuser's layout); the rest are the observation.
    pub action_dim: Option<usize>,
    /// `--image-size`: a UNet2DModel's [height, width], when its `sample_size` is absent or
    /// another size is wanted.
    pub image_size: Option<(usize, usize)>,
    /// `--normalizer`: the normalizer the model was trained under (a folder has none; identity
    /// without it).
    pub normalizer: Option<Normalizer>,
    /// `--null-class`: a class-conditional UNet2DModel's label for "no class" (what its
    /// classifier-free training dropped labels to), which guidance needs; a config has none.
    pub null_class: Option<usize>,
}

/// A UNet2DModel's class embedding as its config gives it.
#[derive(Debug, Clone, Copy)]
enum ClassEmbedding {
    /// `num_class_embeds` rows.
    Table(usize),
    Identity,
}

/// An imported model: the native tensors (relreward's names, float32) and the manifest.
#[derive(Debug)]
pub struct Imported {
    pub class: ModelClass,
    pub manifest: DiffusionManifest,
    pub tensors: Vec<NamedTensor>,
    /// `beta_schedule` (or "trained_betas") the betas were computed from.
    pub schedule_source: String,
}

/// Reads, checks and converts the folder (see the module doc for what is accepted).
pub fn import_folder(folder: &Folder, hints: &Hints) -> Result<Imported, ImportError> {
    let config_path = folder.config();
    let cfg = Config::read(&config_path)?;
    let plan = match cfg.class_name() {
        Some("UNet1DModel") => unet1d_plan(cfg)?,
        Some("UNet2DModel") => unet2d_plan(cfg)?,
        other => {
            let shown = other.map_or("missing".to_owned(), |c| format!("{c:?}"));
            return fail(format!(
                "{}: _class_name: {shown}; relreward imports a UNet1DModel (Diffuser's TemporalUnet) or a UNet2DModel",
                config_path.display()
            ));
        }
    };
    let scheduler = scheduler_plan(&folder.scheduler_config)?;
    let space = space(&plan, hints)?;
    let n_timesteps = scheduler.betas.len();
    let manifest = DiffusionManifest {
        parametrization: scheduler.parametrization,
        schedule: ScheduleSpec::Betas { betas: scheduler.betas },
        n_timesteps,
        clip_denoised: scheduler.clip_denoised,
        space,
        normalizer: hints.normalizer.clone().unwrap_or_default(),
        architecture: Some(plan.architecture.clone()),
        conditioning: conditioning(&plan, hints)?,
    };
    manifest.validate().map_err(|e| {
        ImportError(format!("the manifest derived from {} is not valid: {e}", folder.model_dir.display()))
    })?;
    let tensors = read_tensors(&folder.weights(), &plan)?;
    Ok(Imported { class: plan.class, manifest, tensors, schedule_source: scheduler.source })
}

/// The manifest's conditioning: the plan's, with `--null-class` (labels only).
fn conditioning(plan: &Plan, hints: &Hints) -> Result<Option<Conditioning>, ImportError> {
    match (plan.conditioning, hints.null_class) {
        (None, Some(_)) => fail("--null-class applies to a class-conditional UNet2DModel (num_class_embeds)".into()),
        (Some(Conditioning::Embedding { .. }), Some(_)) => fail(
            "--null-class applies to labels (num_class_embeds); an \"identity\" class embedding's null is the zero vector"
                .into(),
        ),
        (Some(Conditioning::Labels { num_classes, .. }), Some(null)) if null >= num_classes => {
            fail(format!("--null-class: {null} is not one of the model's labels 0..{num_classes} (num_class_embeds)"))
        }
        (Some(Conditioning::Labels { num_classes, .. }), null) => {
            Ok(Some(Conditioning::Labels { num_classes, null_class: null }))
        }
        (other, None) => Ok(other),
    }
}

/// The manifest's space: the config's channels with the hints' sizes.
fn space(plan: &Plan, hints: &Hints) -> Result<Space, ImportError> {
    let factor = 1usize << (plan.levels - 1);
    let wrong = |flag: &str| {
        ImportError(format!("{flag} applies to a {}, not to this {}", other(plan.class).name(), plan.class.name()))
    };
    match plan.class {
        ModelClass::Unet1d => {
            if hints.image_size.is_some() {
                return Err(wrong("--image-size"));
            }
            let Some(horizon) = hints.horizon else {
                return fail(format!(
                    "--horizon: required for a UNet1DModel (the length of its trajectories, a multiple of {factor}; \
                     the config's sample_size is not one)"
                ));
            };
            if horizon == 0 || horizon % factor != 0 {
                return fail(format!(
                    "--horizon: {horizon} must be a positive multiple of 2^(levels - 1) = {factor} for this UNet1DModel's {} levels",
                    plan.levels
                ));
            }
            let Some(action_dim) = hints.action_dim else {
                return fail(format!(
                    "--action-dim: required for a UNet1DModel (how many of its {} channels are the action; each row is \
                     [action | observation], Diffuser's layout)",
                    plan.channels
                ));
            };
            if action_dim > plan.channels {
                return fail(format!("--action-dim: {action_dim} exceeds the model's {} channels", plan.channels));
            }
            Ok(Space::Trajectory { horizon, action_dim, obs_dim: plan.channels - action_dim })
        }
        ModelClass::Unet2d => {
            if hints.horizon.is_some() {
                return Err(wrong("--horizon"));
            }
            if hints.action_dim.is_some() {
                return Err(wrong("--action-dim"));
            }
            let (flag, size) = match (hints.image_size, plan.sample_size) {
                (Some(size), _) => ("--image-size", size),
                (None, Some(size)) => ("config.json sample_size", size),
                (None, None) => {
                    return fail("--image-size: required, as config.json gives no sample_size".to_owned());
                }
            };
            if size.0 == 0 || size.1 == 0 || size.0 % factor != 0 || size.1 % factor != 0 {
                return fail(format!(
                    "{flag}: {}x{} must be positive multiples of 2^(levels - 1) = {factor} for this UNet2DModel's {} levels",
                    size.0, size.1, plan.levels
                ));
            }
            Ok(Space::Sample { shape: vec![plan.channels, size.0, size.1] })
        }
    }
}

fn other(class: ModelClass) -> ModelClass {
    match class {
        ModelClass::Unet1d => ModelClass::Unet2d,
        ModelClass::Unet2d => ModelClass::Unet1d,
    }
}

/// Reads the weights, checks every tensor against the plan (all problems in one error), and
/// converts them to relreward's names, float32.
fn read_tensors(path: &Path, plan: &Plan) -> Result<Vec<NamedTensor>, ImportError> {
    let file = path.display().to_string();
    if !path.is_file() {
        let dir = path.parent().unwrap_or(path);
        let hint = if dir.join("diffusion_pytorch_model.safetensors.index.json").is_file() {
            "; the weights are sharded (diffusion_pytorch_model.safetensors.index.json), which relreward does not read"
        } else if dir.join("diffusion_pytorch_model.bin").is_file() {
            "; only diffusion_pytorch_model.bin is there, a pickle, which only Python reads safely: load the model in \
             diffusers and save_pretrained it again (safetensors is the default)"
        } else {
            ""
        };
        return fail(format!("{file}: no such file{hint}"));
    }
    let bytes = std::fs::read(path).map_err(|e| ImportError(format!("{file}: {e}")))?;
    let stored = safetensors_tensors(&bytes, &file)?;
    let found: BTreeMap<String, Vec<u64>> =
        stored.tensors().into_iter().map(|(k, v)| (k, v.shape().iter().map(|&d| d as u64).collect())).collect();
    let expected: BTreeMap<String, Vec<u64>> = plan.table.iter().map(|e| (e.source.clone(), e.shape.clone())).collect();
    let mismatch = check_shapes(&found, &expected);
    if !mismatch.is_empty() {
        return fail(mismatch_text(&file, plan.class, &mismatch));
    }
    let mut out = Vec::with_capacity(plan.table.len());
    for entry in &plan.table {
        let view = stored.tensor(&entry.source).map_err(|e| ImportError(format!("{file}: {e}")))?;
        let mut values = stored_values(&entry.source, &view, &file)?;
        if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
            return fail(format!("{file}: tensor '{}' holds a non-finite value at flat index {bad}", entry.source));
        }
        if plan.swap_time_halves && entry.target.ends_with(".weight") && is_first_time_layer(&entry.source) {
            swap_column_halves(&mut values, &entry.shape);
        }
        out.push((entry.target.clone(), entry.shape.clone(), values));
    }
    Ok(out)
}

fn is_first_time_layer(source: &str) -> bool {
    matches!(source, "time_mlp.linear_1.weight" | "time_embedding.linear_1.weight")
}

/// Swaps the two halves of a [rows, cols] matrix's columns: the layer then reads [sin, cos]
/// where it read [cos, sin] (and the other way round).
fn swap_column_halves(values: &mut [f32], shape: &[u64]) {
    let cols = shape[1] as usize;
    let half = cols / 2;
    for row in values.chunks_exact_mut(cols) {
        row.rotate_left(half);
    }
}

fn mismatch_text(file: &str, class: ModelClass, m: &Mismatch) -> String {
    let mut lines = vec![format!("{file}: the tensors do not match the {} that config.json describes:", class.name())];
    for (name, shape) in &m.missing {
        lines.push(format!("  missing tensor '{name}' (expected shape {shape:?})"));
    }
    for (name, shape) in &m.unexpected {
        lines.push(format!("  unexpected tensor '{name}' (shape {shape:?})"));
    }
    for (name, found, expected) in &m.misshaped {
        lines.push(format!("  tensor '{name}' has shape {found:?}, expected {expected:?}"));
    }
    lines.push(format!(
        "({} missing, {} unexpected, {} mis-shaped)",
        m.missing.len(),
        m.unexpected.len(),
        m.misshaped.len()
    ));
    lines.join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diffuser_import::{temporal_unet_shapes, write_safetensors};

    /// The config of a UNet1DModel as convert_models_diffuser_to_diffusers.py makes it (dims
    /// [5, 8, 16]), as save_pretrained writes it.
    fn unet1d_config() -> Value {
        json!({
            "_class_name": "UNet1DModel", "_diffusers_version": "0.42.1", "act_fn": "mish",
            "block_out_channels": [8, 16], "down_block_types": ["DownResnetBlock1D", "DownResnetBlock1D"],
            "downsample_each_block": false, "extra_in_channels": 0, "flip_sin_to_cos": false, "freq_shift": 1,
            "in_channels": 5, "layers_per_block": 1, "mid_block_type": "MidResTemporalBlock1D",
            "norm_num_groups": 8, "out_block_type": "OutConv1DBlock", "out_channels": 5, "sample_rate": null,
            "sample_size": 65536, "time_embedding_dim": null, "time_embedding_type": "positional",
            "up_block_types": ["UpResnetBlock1D"], "use_timestep_embedding": true
        })
    }

    fn unet2d_config() -> Value {
        json!({
            "_class_name": "UNet2DModel", "_diffusers_version": "0.42.1", "act_fn": "silu", "add_attention": true,
            "attention_head_dim": 8, "attn_norm_num_groups": null, "block_out_channels": [16, 32],
            "center_input_sample": false, "class_embed_type": null,
            "down_block_types": ["DownBlock2D", "AttnDownBlock2D"], "downsample_padding": 1,
            "downsample_type": "conv", "dropout": 0.0, "flip_sin_to_cos": true, "freq_shift": 0, "in_channels": 2,
            "layers_per_block": 1, "mid_block_scale_factor": 1, "mid_block_type": "UNetMidBlock2D",
            "norm_eps": 1e-05, "norm_num_groups": 8, "num_class_embeds": null, "num_train_timesteps": null,
            "out_channels": 2, "resnet_time_scale_shift": "default", "sample_size": 8,
            "time_embedding_dim": null, "time_embedding_type": "positional",
            "up_block_types": ["AttnUpBlock2D", "UpBlock2D"], "upsample_type": "conv"
        })
    }

    fn scheduler_config() -> Value {
        json!({
            "_class_name": "DDPMScheduler", "_diffusers_version": "0.42.1", "beta_end": 0.02,
            "beta_schedule": "squaredcos_cap_v2", "beta_start": 0.0001, "clip_sample": true,
            "clip_sample_range": 1.0, "dynamic_thresholding_ratio": 0.995, "num_train_timesteps": 20,
            "prediction_type": "epsilon", "rescale_betas_zero_snr": false, "sample_max_value": 1.0,
            "steps_offset": 0, "thresholding": false, "timestep_spacing": "leading", "trained_betas": null,
            "variance_type": "fixed_small"
        })
    }

    /// Distinct values per tensor and element, so that a wrong mapping shows.
    fn values(k: usize, shape: &[u64]) -> Vec<f32> {
        let n: u64 = shape.iter().product();
        (0..n).map(|i| k as f32 + i as f32 * 1e-3).collect()
    }

    fn write_weights(dir: &Path, tensors: &[(String, Vec<u64>)]) {
        let named: Vec<NamedTensor> =
            tensors.iter().enumerate().map(|(k, (n, s))| (n.clone(), s.clone(), values(k, s))).collect();
        write_safetensors(&dir.join(WEIGHTS), &named).unwrap();
    }

    fn sources(table: &[Entry]) -> Vec<(String, Vec<u64>)> {
        table.iter().map(|e| (e.source.clone(), e.shape.clone())).collect()
    }

    /// A model saved on its own with its scheduler in `scheduler/`.
    fn write_folder(dir: &Path, config: &Value, scheduler: &Value, tensors: &[(String, Vec<u64>)]) {
        std::fs::create_dir_all(dir.join("scheduler")).unwrap();
        std::fs::write(dir.join(CONFIG), config.to_string()).unwrap();
        std::fs::write(dir.join("scheduler").join(SCHEDULER_CONFIG), scheduler.to_string()).unwrap();
        write_weights(dir, tensors);
    }

    fn trajectory_hints() -> Hints {
        Hints { horizon: Some(8), action_dim: Some(2), ..Hints::default() }
    }

    fn import_dir(dir: &Path, hints: &Hints) -> Result<Imported, ImportError> {
        import_folder(&locate(dir, None, None)?, hints)
    }

    /// The refusal's message (an accepted import is not printed: its tensors are large).
    fn refused(result: Result<Imported, ImportError>) -> String {
        match result {
            Ok(imported) => panic!("accepted: {:?}", imported.manifest.architecture),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn unet1d_targets_are_exactly_the_temporal_unet() {
        for (d, dim, mults) in
            [(5u64, 8u64, vec![1u64, 2]), (14, 32, vec![1, 2, 4, 8]), (3, 16, vec![1]), (4, 8, vec![1, 4, 8])]
        {
            let table = unet1d_table(d, dim, &mults);
            let targets: BTreeMap<String, Vec<u64>> =
                table.iter().map(|e| (e.target.clone(), e.shape.clone())).collect();
            assert_eq!(targets.len(), table.len(), "two sources map to one target");
            assert_eq!(targets, temporal_unet_shapes(d, dim, &mults), "dims {d} {dim} {mults:?}");
        }
        let table = unet1d_table(5, 8, &[1, 2]);
        let find = |s: &str| table.iter().find(|e| e.source == s).map(|e| e.target.as_str());
        assert_eq!(find("down_blocks.0.resnets.1.conv_in.conv1d.weight"), Some("downs.0.1.blocks.0.block.0.weight"));
        assert_eq!(find("mid_block.resnets.1.conv_out.group_norm.bias"), Some("mid_block2.blocks.1.block.2.bias"));
        assert_eq!(find("up_blocks.0.upsample.conv.weight"), Some("ups.0.3.conv.weight"));
        assert_eq!(find("out_block.final_conv1d_gn.weight"), Some("final_conv.0.block.2.weight"));
        assert_eq!(find("time_mlp.linear_2.bias"), Some("time_mlp.3.bias"));
    }

    #[test]
    fn a_unet1d_folder_imports_with_diffusers_schedule_and_renamed_tensors() {
        let dir = tempfile::tempdir().unwrap();
        let table = unet1d_table(5, 8, &[1, 2]);
        let mut config = unet1d_config();
        config["flip_sin_to_cos"] = json!(true);
        write_folder(dir.path(), &config, &scheduler_config(), &sources(&table));
        let imported = import_dir(dir.path(), &trajectory_hints()).unwrap();
        assert_eq!(imported.class, ModelClass::Unet1d);
        let m = &imported.manifest;
        assert_eq!(m.architecture, Some(Architecture::TemporalUnet { dim: 8, dim_mults: vec![1, 2] }));
        assert_eq!(m.space, Space::Trajectory { horizon: 8, action_dim: 2, obs_dim: 3 });
        assert_eq!(m.parametrization, Parametrization::Epsilon);
        assert!(m.clip_denoised);
        assert_eq!(m.normalizer, Normalizer::Identity);
        let ScheduleSpec::Betas { betas } = &m.schedule else { panic!("{:?}", m.schedule) };
        assert_eq!((betas.len(), m.n_timesteps), (20, 20));
        assert_eq!(betas[19], f64::from(0.999f32), "squaredcos_cap_v2 caps at 0.999");
        assert_eq!(imported.schedule_source, "squaredcos_cap_v2");

        let got: BTreeMap<&str, &NamedTensor> = imported.tensors.iter().map(|t| (t.0.as_str(), t)).collect();
        assert_eq!(got.len(), table.len());
        for (k, e) in table.iter().enumerate() {
            let (_, shape, v) = got[e.target.as_str()];
            assert_eq!(shape, &e.shape);
            let want = values(k, &e.shape);
            if e.target == "time_mlp.1.weight" {
                // flip_sin_to_cos: each row's two halves (cos | sin) become (sin | cos).
                let cols = e.shape[1] as usize;
                assert_eq!(&v[..cols / 2], &want[cols / 2..cols]);
                assert_eq!(&v[cols / 2..cols], &want[..cols / 2]);
            } else {
                assert_eq!(v, &want, "{}", e.source);
            }
        }
    }

    #[test]
    fn a_unet2d_pipeline_folder_imports() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        std::fs::create_dir_all(root.join("unet")).unwrap();
        std::fs::write(root.join("model_index.json"), r#"{"_class_name": "DDPMPipeline"}"#).unwrap();
        let mut config = unet2d_config();
        config["flip_sin_to_cos"] = json!(false);
        config["sample_size"] = json!([8, 12]);
        let table = unet2d_table(2, &[16, 32], 1, true);
        write_folder(&root.join("unet"), &config, &json!({}), &sources(&table));
        // The pipeline's scheduler sits beside unet/; its config may leave everything out.
        std::fs::remove_dir_all(root.join("unet/scheduler")).unwrap();
        std::fs::create_dir_all(root.join("scheduler")).unwrap();
        let mut sched = json!({"_class_name": "DDPMScheduler", "prediction_type": "sample", "clip_sample": false});
        sched["num_train_timesteps"] = json!(100);
        std::fs::write(root.join("scheduler").join(SCHEDULER_CONFIG), sched.to_string()).unwrap();

        let folder = locate(root, None, None).unwrap();
        assert_eq!(folder.model_dir, root.join("unet"));
        assert_eq!(folder.scheduler_config, root.join("scheduler").join(SCHEDULER_CONFIG));
        let imported = import_folder(&folder, &Hints::default()).unwrap();
        let m = &imported.manifest;
        assert_eq!(m.space, Space::Sample { shape: vec![2, 8, 12] });
        assert_eq!(m.parametrization, Parametrization::X0);
        // v_prediction is relreward's v.
        let mut v_sched = sched.clone();
        v_sched["prediction_type"] = json!("v_prediction");
        std::fs::write(root.join("scheduler").join(SCHEDULER_CONFIG), v_sched.to_string()).unwrap();
        let v_imported = import_folder(&locate(root, None, None).unwrap(), &Hints::default()).unwrap();
        assert_eq!(v_imported.manifest.parametrization, Parametrization::V);
        std::fs::write(root.join("scheduler").join(SCHEDULER_CONFIG), sched.to_string()).unwrap();
        assert!(!m.clip_denoised);
        let ScheduleSpec::Betas { betas } = &m.schedule else { panic!() };
        // diffusers' default: linear from 1e-4 to 0.02 (not scaled by 1000 / T).
        assert_eq!((betas.len(), betas[0], betas[99]), (100, f64::from(1e-4f32), f64::from(0.02f32)));
        assert_eq!(
            m.architecture,
            Some(Architecture::Unet2d {
                block_out_channels: vec![16, 32],
                layers_per_block: 1,
                attention: true,
                norm_num_groups: 8,
                attention_head_dim: 8
            })
        );
        // Names are kept; flip_sin_to_cos false swaps the first time layer's halves.
        let first = imported.tensors.iter().find(|t| t.0 == "time_embedding.linear_1.weight").unwrap();
        assert_eq!(first.1, vec![64, 16]);
        assert_eq!(first.2[0], values(0, &first.1)[8]);
        let conv = imported.tensors.iter().find(|t| t.0 == "up_blocks.0.attentions.1.to_out.0.weight").unwrap();
        assert_eq!(conv.1, vec![32, 32]);

        // --image-size overrides sample_size; a size the levels cannot halve is named.
        let hints = Hints { image_size: Some((5, 6)), ..Hints::default() };
        let err = refused(import_folder(&folder, &hints));
        assert!(err.contains("--image-size: 5x6 must be positive multiples of 2^(levels - 1) = 2"), "{err}");
        let err = refused(import_folder(&folder, &trajectory_hints()));
        assert!(err.contains("--horizon applies to a UNet1DModel, not to this UNet2DModel"), "{err}");
    }

    #[test]
    fn a_unet2d_without_attention_needs_no_attention_anywhere() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = unet2d_config();
        config["down_block_types"] = json!(["DownBlock2D", "DownBlock2D", "DownBlock2D"]);
        config["up_block_types"] = json!(["UpBlock2D", "UpBlock2D", "UpBlock2D"]);
        config["block_out_channels"] = json!([16, 16, 32]);
        config["layers_per_block"] = json!(2);
        let table = unet2d_table(2, &[16, 16, 32], 2, false);
        write_folder(dir.path(), &config, &scheduler_config(), &sources(&table));
        // add_attention (true) would give the mid block an attention relreward's unet2d lacks.
        let err = refused(import_dir(dir.path(), &Hints::default()));
        assert!(err.contains("add_attention: true is not supported: no down block has attention"), "{err}");
        config["add_attention"] = json!(false);
        config["sample_size"] = json!(8);
        std::fs::write(dir.path().join(CONFIG), config.to_string()).unwrap();
        let imported = import_dir(dir.path(), &Hints::default()).unwrap();
        assert!(matches!(imported.manifest.architecture, Some(Architecture::Unet2d { attention: false, .. })));
        assert_eq!(imported.tensors.len(), table.len());
    }

    #[test]
    fn a_missing_unexpected_or_misshaped_tensor_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let mut tensors = sources(&unet1d_table(5, 8, &[1, 2]));
        tensors.retain(|(n, _)| n != "mid_block.resnets.1.conv_out.group_norm.bias");
        for (n, s) in &mut tensors {
            if n == "out_block.final_conv1d_2.weight" {
                *s = vec![5, 16, 1];
            }
        }
        tensors.push(("down_blocks.0.attentions.0.query.weight".into(), vec![8, 8]));
        write_folder(dir.path(), &unet1d_config(), &scheduler_config(), &tensors);
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        for needle in [
            "the tensors do not match the UNet1DModel that config.json describes",
            "missing tensor 'mid_block.resnets.1.conv_out.group_norm.bias' (expected shape [16])",
            "tensor 'out_block.final_conv1d_2.weight' has shape [5, 16, 1], expected [5, 8, 1]",
            "unexpected tensor 'down_blocks.0.attentions.0.query.weight' (shape [8, 8])",
            "(1 missing, 1 unexpected, 1 mis-shaped)",
        ] {
            assert!(err.contains(needle), "{needle:?} not in:\n{err}");
        }
    }

    #[test]
    fn a_non_finite_weight_and_a_missing_weights_file_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let table = unet1d_table(5, 8, &[1]);
        let mut config = unet1d_config();
        config["block_out_channels"] = json!([8]);
        config["down_block_types"] = json!(["DownResnetBlock1D"]);
        config["up_block_types"] = json!([]);
        write_folder(dir.path(), &config, &scheduler_config(), &[]);
        let mut named: Vec<NamedTensor> =
            table.iter().enumerate().map(|(k, e)| (e.source.clone(), e.shape.clone(), values(k, &e.shape))).collect();
        named[3].2[1] = f32::NAN;
        write_safetensors(&dir.path().join(WEIGHTS), &named).unwrap();
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        assert!(err.contains(&format!("tensor '{}' holds a non-finite value at flat index 1", named[3].0)), "{err}");

        std::fs::remove_file(dir.path().join(WEIGHTS)).unwrap();
        std::fs::write(dir.path().join("diffusion_pytorch_model.bin"), b"pickle").unwrap();
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        assert!(
            err.contains("diffusion_pytorch_model.safetensors: no such file; only diffusion_pytorch_model.bin"),
            "{err}"
        );
    }

    #[test]
    fn unknown_block_types_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = unet1d_config();
        config["down_block_types"] = json!(["DownResnetBlock1D", "AttnDownBlock1D"]);
        config["up_block_types"] = json!(["UpResnetBlock1D", "UpResnetBlock1D"]);
        config["mid_block_type"] = json!("UNetMidBlock1D");
        write_folder(dir.path(), &config, &scheduler_config(), &[]);
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        for needle in [
            "not an importable UNet1DModel",
            "down_block_types[1]: block type \"AttnDownBlock1D\" is not supported",
            "relreward needs \"DownResnetBlock1D\"",
            "up_block_types: [\"UpResnetBlock1D\",\"UpResnetBlock1D\"] is not supported: 2 entries, expected 1",
            "mid_block_type: \"UNetMidBlock1D\" is not supported",
        ] {
            assert!(err.contains(needle), "{needle:?} not in:\n{err}");
        }

        let mut config = unet2d_config();
        config["down_block_types"] = json!(["CrossAttnDownBlock2D", "AttnDownBlock2D"]);
        std::fs::write(dir.path().join(CONFIG), config.to_string()).unwrap();
        let err = refused(import_dir(dir.path(), &Hints::default()));
        assert!(err.contains("down_block_types[0]: block type \"CrossAttnDownBlock2D\" is not supported"), "{err}");
        assert!(err.contains("relreward needs \"DownBlock2D\""), "{err}");

        config["_class_name"] = json!("UNet2DConditionModel");
        std::fs::write(dir.path().join(CONFIG), config.to_string()).unwrap();
        let err = refused(import_dir(dir.path(), &Hints::default()));
        assert!(err.contains("_class_name: \"UNet2DConditionModel\""), "{err}");
    }

    #[test]
    fn unsupported_config_fields_are_named_all_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = unet2d_config();
        config["class_embed_type"] = json!("timestep");
        config["norm_eps"] = json!(1e-6);
        config["freq_shift"] = json!(1);
        config["cross_attention_dim"] = json!(768);
        write_folder(dir.path(), &config, &scheduler_config(), &sources(&unet2d_table(2, &[16, 32], 1, true)));
        let err = refused(import_dir(dir.path(), &Hints::default()));
        for needle in [
            "class_embed_type: \"timestep\" is not supported",
            "norm_eps: 1e-6 is not supported",
            "freq_shift: 1 is not supported",
            "cross_attention_dim: not a field relreward knows for a UNet2DModel",
        ] {
            assert!(err.contains(needle), "{needle:?} not in:\n{err}");
        }

        // diffusers' defaults count for a field left out: UNet1DModel's are not a TemporalUnet.
        let mut config = unet1d_config();
        for key in ["freq_shift", "time_embedding_type", "use_timestep_embedding", "act_fn"] {
            config.as_object_mut().unwrap().remove(key);
        }
        write_folder(dir.path(), &config, &scheduler_config(), &sources(&unet1d_table(5, 8, &[1, 2])));
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        for needle in [
            "freq_shift: 0.0 (left out: diffusers' default) is not supported",
            "time_embedding_type: \"fourier\" (left out: diffusers' default) is not supported",
            "use_timestep_embedding: false (left out: diffusers' default)",
            "act_fn: null (left out: diffusers' default) is not supported: Diffuser's TemporalUnet uses mish",
        ] {
            assert!(err.contains(needle), "{needle:?} not in:\n{err}");
        }

        // The scheduler: an unknown prediction type, thresholding, a variance relreward does not
        // sample with.
        let mut sched = scheduler_config();
        sched["prediction_type"] = json!("flow");
        sched["thresholding"] = json!(true);
        sched["variance_type"] = json!("fixed_large");
        sched["clip_sample_range"] = json!(2.0);
        write_folder(dir.path(), &unet1d_config(), &sched, &sources(&unet1d_table(5, 8, &[1, 2])));
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        for needle in [
            "scheduler_config.json: not an importable DDPMScheduler",
            "prediction_type: \"flow\" is not supported",
            "thresholding: true is not supported",
            "variance_type: \"fixed_large\" is not supported",
            "clip_sample_range: 2.0 is not supported",
        ] {
            assert!(err.contains(needle), "{needle:?} not in:\n{err}");
        }
        let mut sched = scheduler_config();
        sched["beta_schedule"] = json!("exp");
        sched["_class_name"] = json!("DDPMScheduler");
        write_folder(dir.path(), &unet1d_config(), &sched, &sources(&unet1d_table(5, 8, &[1, 2])));
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        assert!(err.contains("beta_schedule: \"exp\" is not supported"), "{err}");
        sched["_class_name"] = json!("DDIMScheduler");
        write_folder(dir.path(), &unet1d_config(), &sched, &sources(&unet1d_table(5, 8, &[1, 2])));
        let err = refused(import_dir(dir.path(), &trajectory_hints()));
        assert!(err.contains("_class_name: \"DDIMScheduler\""), "{err}");
    }

    #[test]
    fn trajectory_hints_are_required_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        write_folder(dir.path(), &unet1d_config(), &scheduler_config(), &sources(&unet1d_table(5, 8, &[1, 2])));
        let cases = [
            (Hints { action_dim: Some(2), ..Hints::default() }, "--horizon: required for a UNet1DModel"),
            (Hints { horizon: Some(8), ..Hints::default() }, "--action-dim: required for a UNet1DModel"),
            (
                Hints { horizon: Some(7), action_dim: Some(2), ..Hints::default() },
                "--horizon: 7 must be a positive multiple of 2^(levels - 1) = 2",
            ),
            (
                Hints { horizon: Some(8), action_dim: Some(6), ..Hints::default() },
                "--action-dim: 6 exceeds the model's 5 channels",
            ),
        ];
        for (hints, needle) in cases {
            let err = refused(import_dir(dir.path(), &hints));
            assert!(err.contains(needle), "{needle:?} not in {err}");
        }
    }

    #[test]
    fn locate_finds_the_files_or_says_where_it_looked() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let err = locate(root, None, None).unwrap_err().to_string();
        assert!(err.contains("no config.json and no unet/config.json"), "{err}");
        std::fs::create_dir_all(root.join("value_function")).unwrap();
        std::fs::write(root.join("value_function").join(CONFIG), "{}").unwrap();
        let err = locate(root, Some("value_function"), None).unwrap_err().to_string();
        assert!(err.contains("no scheduler_config.json (looked at"), "{err}");
        assert!(err.contains("--scheduler-config FILE"), "{err}");
        std::fs::create_dir_all(root.join("scheduler")).unwrap();
        std::fs::write(root.join("scheduler").join(SCHEDULER_CONFIG), "{}").unwrap();
        let found = locate(root, Some("value_function"), None).unwrap();
        assert_eq!(found.model_dir, root.join("value_function"));
        assert_eq!(found.scheduler_config, root.join("scheduler").join(SCHEDULER_CONFIG));
        let err = locate(root, Some("unet"), None).unwrap_err().to_string();
        assert!(err.contains("--subfolder unet"), "{err}");
    }

    #[test]
    fn the_hub_cache_is_found_as_huggingface_hub_finds_it() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| pairs.iter().find(|(n, _)| *n == k).map(|(_, v)| (*v).to_owned())
        };
        assert_eq!(hub_cache(&env(&[("HOME", "/h")])), Some(PathBuf::from("/h/.cache/huggingface/hub")));
        assert_eq!(
            hub_cache(&env(&[("HOME", "/h"), ("XDG_CACHE_HOME", "/x")])),
            Some(PathBuf::from("/x/huggingface/hub"))
        );
        assert_eq!(hub_cache(&env(&[("HOME", "/h"), ("HF_HOME", "/hf")])), Some(PathBuf::from("/hf/hub")));
        assert_eq!(hub_cache(&env(&[("HF_HOME", "/hf"), ("HF_HUB_CACHE", "/c")])), Some(PathBuf::from("/c")));
        assert_eq!(hub_cache(&env(&[("HF_HOME", "")])), None);

        assert!(is_repo_id("bglick13/hopper-medium-v2-value-function-hor32"));
        assert!(is_repo_id("gpt2"));
        assert!(!is_repo_id("a/b/c") && !is_repo_id("../x") && !is_repo_id("/abs") && !is_repo_id("a b"));

        let dir = tempfile::tempdir().unwrap();
        let repo = dir.path().join("models--org--tiny");
        let commit = "0123456789abcdef0123456789abcdef01234567";
        std::fs::create_dir_all(repo.join("refs")).unwrap();
        std::fs::create_dir_all(repo.join("snapshots").join(commit)).unwrap();
        std::fs::write(repo.join("refs/main"), format!("{commit}\n")).unwrap();
        assert_eq!(hub_snapshot(dir.path(), "org/tiny", "main").unwrap(), repo.join("snapshots").join(commit));
        assert_eq!(hub_snapshot(dir.path(), "org/tiny", commit).unwrap(), repo.join("snapshots").join(commit));
        let err = hub_snapshot(dir.path(), "org/tiny", "../../x").unwrap_err().to_string();
        assert!(err.contains("--revision: \"../../x\" is not a branch"), "{err}");
        let err = hub_snapshot(dir.path(), "org/tiny", "v2").unwrap_err().to_string();
        assert!(err.contains("revision \"v2\" is not in the cache"), "{err}");
        let err = hub_snapshot(dir.path(), "org/other", "main").unwrap_err().to_string();
        assert!(err.contains("org/other: not in the local Hugging Face cache"), "{err}");
        assert!(err.contains("Nothing is downloaded"), "{err}");
    }

    #[test]
    fn betas_follow_diffusers_formulas() {
        let linear = schedule_betas("linear", 1e-4, 0.02, 5).unwrap();
        for (b, want) in linear.iter().zip([1e-4, 0.005075, 0.01005, 0.015025, 0.02]) {
            assert!((b - want).abs() < 1e-15, "{linear:?}");
        }
        let scaled = schedule_betas("scaled_linear", 0.00085, 0.012, 3).unwrap();
        assert!((scaled[0] - 0.00085).abs() < 1e-15 && (scaled[2] - 0.012).abs() < 1e-15);
        assert!((scaled[1] - ((0.00085f64.sqrt() + 0.012f64.sqrt()) / 2.0).powi(2)).abs() < 1e-15);
        let cosine = schedule_betas("squaredcos_cap_v2", 0.0, 0.0, 1000).unwrap();
        assert_eq!(cosine[999], 0.999);
        // Values printed by diffusers 0.42's betas_for_alpha_bar.
        assert!((cosine[0] - 4.1284e-5).abs() < 1e-9, "{}", cosine[0]);
        let sigmoid = schedule_betas("sigmoid", 1e-4, 0.02, 3).unwrap();
        assert!((sigmoid[1] - (1e-4 + 0.0199 / 2.0)).abs() < 1e-15);
        let laplace = schedule_betas("laplace", 0.0, 0.0, 10).unwrap();
        for (i, want) in [(0, 0.1683), (4, 0.0268), (9, 0.9431)] {
            assert!((laplace[i] - want).abs() < 1e-4, "{laplace:?}");
        }
        assert_eq!(schedule_betas("linear", 0.1, 0.2, 1).unwrap(), vec![0.1]);
        assert!(schedule_betas("exp", 0.0, 0.0, 3).is_none());
    }
}
