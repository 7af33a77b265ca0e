//! The relative reward network rho_theta(x, t): a scalar per item whose input gradient is
//! trained to match the difference of two diffusion models (Algorithm 1 of "Extracting Reward
//! Functions from Diffusion Models"). [`RewardNet`] owns its `VarStore`, validates its
//! architecture against the item shape before allocating, computes rho, its input gradient
//! (for guidance) and the same gradient with a differentiable graph (for the double backward
//! of training), and stores its weights as strict safetensors under PyTorch module names
//! (`tests/python/reward_nets_reference.py` is the independent PyTorch implementation).
//!
//! Architectures ([`RewardArchitecture`]); every activation is Mish (smooth, as the double
//! backward and the paper's existence theorem want), every time embedding is Diffuser's
//! `Sequential(SinusoidalPosEmb(d), Linear(d, 4 d), Mish, Linear(4 d, d))` under `time_mlp.1.*`
//! and `time_mlp.3.*`, fed the diffusion step t as a float:
//!
//! - `windowed_mlp { window: h, hidden }` (maze rewards), item [H, D] with h dividing H.
//!   d = 32. `net = Sequential(Linear(h D + 32, hidden[0]), Mish, ..., Linear(hidden[-1], 1))`
//!   (`net.0.*`, `net.2.*`, ..., `net.{2 len(hidden)}.*`) scores one window: its h rows
//!   flattened row-major ([row_k | row_k+1 | ...], each row [action | observation]) and
//!   concatenated with the time embedding. The trajectory is split into H / h non-overlapping
//!   windows (per-window values [B, H / h]); rho is their MEAN. Per-step values [B, H] score
//!   the stride-1 window starting at each step k (rows k..k+h-1, the end padded by repeating
//!   the last row), so per_step[:, j h] = per_window[:, j] and h = 1 gives g(s, a, t). The
//!   weights depend on h and D only, so one file loads for any horizon divisible by h.
//! - `value_function { widths }` (locomotion rewards), item [H, D]: Diffuser's `ValueFunction`
//!   (`diffuser/models/temporal.py`) with `widths` the channels after each level, i.e. Diffuser's
//!   `[dim * m for m in dim_mults]`, and time width `widths[0]` (= Diffuser's `dim`, whose
//!   `dim_mults` start at 1; the paper's (64, 64, 128, 128) is dim 64, dim_mults (1, 1, 2, 2)).
//!   For dims = [D, *widths]: `blocks.{i}.0` = ResidualTemporalBlock(dims[i], dims[i + 1]),
//!   `blocks.{i}.1` = ResidualTemporalBlock(dims[i + 1], dims[i + 1]), `blocks.{i}.2` =
//!   Downsample1d on *every* level; `mid_block1` = ResidualTemporalBlock(w, w / 2),
//!   `mid_down1` = Downsample1d(w / 2), `mid_block2` = ResidualTemporalBlock(w / 2, w / 4),
//!   `mid_down2` = Downsample1d(w / 4) for w = widths[-1]; flatten [B, w / 4 * L] (channel-major)
//!   and concatenate the time embedding; `final_block = Sequential(Linear(fc + d, fc / 2), Mish,
//!   Linear(fc / 2, 1))` with fc = w / 4 * L. L is the length after the len(widths) + 2
//!   downsamplings; the horizon must halve evenly through them (a power of two, or a multiple
//!   of 2^(len(widths) + 2)), and then L = max(H / 2^(len(widths) + 2), 1) equals Diffuser's own
//!   `fc_dim` bookkeeping, so Diffuser ValueFunction checkpoints load unchanged. (Diffuser's
//!   bookkeeping and its actual lengths disagree for other horizons, where its forward fails.)
//!   widths must be multiples of 8 (GroupNorm(8)), the last a multiple of 32 (w / 4 too).
//! - `conv_encoder { widths }` (image-like latents), item [C, H, W]: d = widths[0]; per width
//!   w_i, `blocks.{i}`: h = Mish(GroupNorm(8)(Conv2d(3x3, stride 2, padding 1)(h))) + Linear(d,
//!   w_i)(Mish(t_emb)) broadcast over the pixels (`blocks.{i}.conv.*`, `blocks.{i}.norm.*`,
//!   `blocks.{i}.time_mlp.1.*`: the time embedding is projected and added per block, as in
//!   Diffuser's residual blocks); then global average pooling to [B, w], concatenation with the
//!   time embedding and `final_block = Sequential(Linear(w + d, w / 2), Mish, Linear(w / 2, 1))`.
//!   Any H, W >= 1 (each stride-2 convolution maps n to ceil(n / 2)).
//! - `mlp { hidden }` (flat samples), item [*shape]: the windowed MLP's layout over the whole
//!   flattened sample (d = 32, `time_mlp`, `net`).
//!
//! All forward passes use tch's fallible operations: bad shapes are errors, never panics.
//! Mish is libtorch's fused op except in `grad_create_graph`, the pass Algorithm 1
//! differentiates twice ([`Mish::TwiceDifferentiable`]).

use std::fmt;
use std::path::Path;

use serde::{Deserialize, Serialize};
use tch::nn::{self, Init, VarStore};
use tch::{Device, Kind, Tensor};

use super::blocks::{
    Downsample1d, GROUPS, GroupNorm, Linear, Mish, ResidualTemporalBlock, TEMPORAL_KERNEL, TimeMlp, conv_params,
    linear_params, total,
};
use super::mlp::{MAX_FEATURES, MAX_HIDDEN, MAX_LAYERS, MLP_TIME_DIM, MLP_TIME_HIDDEN};
use super::native::MAX_PARAMETERS;
use super::temporal_unet::{MAX_LEVELS, MAX_WIDTH};
use super::weights;
use crate::error::{Error, Result};

/// The architecture of a relative reward network (see the module documentation for the exact
/// layers and parameter names).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RewardArchitecture {
    /// An MLP over windows of `window` transitions of a trajectory [H, D]; rho is the mean over
    /// the H / window non-overlapping windows. The paper's maze nets: window 64, hidden (32,)
    /// (open maze) and window 4, hidden (128, 64, 32) (the others).
    WindowedMlp { window: usize, hidden: Vec<usize> },
    /// Diffuser's ValueFunction (the TemporalUnet's down path) over a trajectory [H, D], with
    /// the channels after each level. The paper's locomotion nets: (64, 64, 128, 128).
    ValueFunction { widths: Vec<usize> },
    /// A strided 2D convolutional encoder over image-like items [C, H, W], one stride-2 block per
    /// width. The paper's Stable Diffusion latent nets: (32, 64, 128, 256).
    ConvEncoder { widths: Vec<usize> },
    /// An MLP over flattened samples of any shape.
    Mlp { hidden: Vec<usize> },
}

impl fmt::Display for RewardArchitecture {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::WindowedMlp { window, hidden } => write!(f, "windowed_mlp(h={window}, hidden={hidden:?})"),
            Self::ValueFunction { widths } => write!(f, "value_function(widths={widths:?})"),
            Self::ConvEncoder { widths } => write!(f, "conv_encoder(widths={widths:?})"),
            Self::Mlp { hidden } => write!(f, "mlp(hidden={hidden:?})"),
        }
    }
}

fn to_i64(value: usize, field: &str) -> Result<i64> {
    i64::try_from(value).map_err(|_| Error::invalid(format!("{field}: {value} is too large")))
}

fn to_i64s(values: &[usize], field: &str) -> Result<Vec<i64>> {
    values.iter().map(|&v| to_i64(v, field)).collect()
}

fn shape_text(shape: &[i64]) -> String {
    shape.iter().map(i64::to_string).collect::<Vec<_>>().join(", ")
}

/// Number of parameters as a u128 (for arithmetic that must not overflow).
fn count(x: i64) -> u128 {
    u128::try_from(x.max(0)).unwrap_or(0)
}

/// The hyperparameters in i64, validated against the item shape.
#[derive(Debug, Clone)]
enum Plan {
    WindowedMlp { horizon: i64, transition_dim: i64, window: i64, hidden: Vec<i64> },
    ValueFunction { transition_dim: i64, widths: Vec<i64>, final_length: i64 },
    ConvEncoder { channels: i64, widths: Vec<i64> },
    Mlp { features: i64, hidden: Vec<i64> },
}

fn validate_hidden(hidden: &[usize]) -> Result<Vec<i64>> {
    let hidden = to_i64s(hidden, "architecture.hidden")?;
    if hidden.is_empty() || hidden.len() > MAX_LAYERS || hidden.iter().any(|&h| h <= 0 || h > MAX_HIDDEN) {
        return Err(Error::invalid(format!(
            "architecture.hidden: {hidden:?} must hold 1 to {MAX_LAYERS} widths in 1..={MAX_HIDDEN}"
        )));
    }
    Ok(hidden)
}

/// Widths of the convolutional architectures: 1 to [`MAX_LEVELS`] positive multiples of 8.
fn validate_widths(widths: &[usize]) -> Result<Vec<i64>> {
    let widths = to_i64s(widths, "architecture.widths")?;
    if widths.is_empty() || widths.len() > MAX_LEVELS {
        return Err(Error::invalid(format!("architecture.widths: {widths:?} must hold 1 to {MAX_LEVELS} widths")));
    }
    if let Some(w) = widths.iter().find(|&&w| w <= 0 || w % GROUPS != 0 || w > MAX_WIDTH) {
        return Err(Error::invalid(format!(
            "architecture.widths: {w} in {widths:?} must be a positive multiple of {GROUPS} (GroupNorm with {GROUPS} groups) up to {MAX_WIDTH}"
        )));
    }
    Ok(widths)
}

fn trajectory_shape(item_shape: &[i64], kind: &str) -> Result<(i64, i64)> {
    match item_shape {
        &[horizon, transition_dim] => Ok((horizon, transition_dim)),
        _ => Err(Error::invalid(format!(
            "architecture: {kind} needs a trajectory item shape [horizon, transition_dim], got [{}]",
            shape_text(item_shape)
        ))),
    }
}

impl Plan {
    fn new(architecture: &RewardArchitecture, item_shape: &[i64]) -> Result<Self> {
        if item_shape.is_empty() || item_shape.iter().any(|&d| d <= 0) {
            return Err(Error::invalid(format!(
                "item shape: [{}] must be non-empty with positive dimensions",
                shape_text(item_shape)
            )));
        }
        let features =
            item_shape.iter().try_fold(1i64, |acc, &d| acc.checked_mul(d)).filter(|&n| n <= MAX_FEATURES).ok_or_else(
                || {
                    Error::invalid(format!(
                        "item shape: [{}] has more than {MAX_FEATURES} elements",
                        shape_text(item_shape)
                    ))
                },
            )?;
        Ok(match architecture {
            RewardArchitecture::WindowedMlp { window, hidden } => {
                let (horizon, transition_dim) = trajectory_shape(item_shape, "windowed_mlp")?;
                let window = to_i64(*window, "architecture.window")?;
                if window <= 0 {
                    return Err(Error::invalid(format!("architecture.window: {window} must be positive")));
                }
                if horizon % window != 0 {
                    return Err(Error::invalid(format!(
                        "architecture.window: horizon {horizon} is not divisible by window {window}"
                    )));
                }
                let hidden = validate_hidden(hidden)?;
                Self::WindowedMlp { horizon, transition_dim, window, hidden }
            }
            RewardArchitecture::ValueFunction { widths } => {
                let (horizon, transition_dim) = trajectory_shape(item_shape, "value_function")?;
                let widths = validate_widths(widths)?;
                let last = widths[widths.len() - 1];
                if last % (4 * GROUPS) != 0 {
                    return Err(Error::invalid(format!(
                        "architecture.widths: the last width {last} must be a multiple of {} (the mid blocks use {last} / 2 and {last} / 4 channels with GroupNorm({GROUPS}))",
                        4 * GROUPS
                    )));
                }
                let downsamplings = widths.len() + 2;
                let mut length = horizon;
                for _ in 0..downsamplings {
                    if length > 1 && length % 2 != 0 {
                        return Err(Error::invalid(format!(
                            "item shape: horizon {horizon} does not halve evenly through value_function's {downsamplings} downsamplings ({} levels + 2 mid); use a power of two or a multiple of {}",
                            widths.len(),
                            1i64 << downsamplings
                        )));
                    }
                    length = (length + 1) / 2;
                }
                Self::ValueFunction { transition_dim, widths, final_length: length }
            }
            RewardArchitecture::ConvEncoder { widths } => {
                let &[channels, _, _] = item_shape else {
                    return Err(Error::invalid(format!(
                        "architecture: conv_encoder needs an image-like item shape [channels, height, width], got [{}]",
                        shape_text(item_shape)
                    )));
                };
                Self::ConvEncoder { channels, widths: validate_widths(widths)? }
            }
            RewardArchitecture::Mlp { hidden } => Self::Mlp { features, hidden: validate_hidden(hidden)? },
        })
    }

    /// Number of parameters, within [`MAX_PARAMETERS`], computed without allocating.
    fn params(&self) -> Result<u64> {
        let count = match self {
            Self::WindowedMlp { transition_dim, window, hidden, .. } => {
                MlpHead::params(transition_dim.saturating_mul(*window), hidden)
            }
            Self::Mlp { features, hidden } => MlpHead::params(*features, hidden),
            Self::ValueFunction { transition_dim, widths, final_length } => {
                ValueFunctionNet::params(*transition_dim, widths, *final_length)
            }
            Self::ConvEncoder { channels, widths } => ConvEncoderNet::params(*channels, widths),
        };
        if count > u128::from(MAX_PARAMETERS) {
            return Err(Error::invalid(format!(
                "architecture: {count} parameters exceed the limit of {MAX_PARAMETERS}"
            )));
        }
        u64::try_from(count).map_err(|_| Error::invalid("architecture: too many parameters"))
    }
}

/// `time_mlp` + `net`: Linear/Mish layers over [..., features] concatenated with a 32-wide time
/// embedding, ending in one output.
#[derive(Debug)]
struct MlpHead {
    time_mlp: TimeMlp,
    layers: Vec<Linear>,
}

impl MlpHead {
    fn params(features: i64, hidden: &[i64]) -> u128 {
        let mut parts = vec![TimeMlp::params(MLP_TIME_DIM, MLP_TIME_HIDDEN, MLP_TIME_DIM)];
        let mut width_in = features.saturating_add(MLP_TIME_DIM);
        for &h in hidden {
            parts.push(linear_params(width_in, h));
            width_in = h;
        }
        parts.push(linear_params(width_in, 1));
        total(&parts)
    }

    fn new(p: &nn::Path, features: i64, hidden: &[i64]) -> Result<Self> {
        let time_mlp = TimeMlp::new(&(p / "time_mlp"), MLP_TIME_DIM, MLP_TIME_HIDDEN, MLP_TIME_DIM)?;
        let net = p / "net";
        let mut layers = Vec::with_capacity(hidden.len() + 1);
        let mut width_in = features + MLP_TIME_DIM;
        for (i, &h) in hidden.iter().enumerate() {
            layers.push(Linear::new(&(&net / (2 * i)), width_in, h)?);
            width_in = h;
        }
        layers.push(Linear::new(&(&net / (2 * hidden.len())), width_in, 1)?);
        Ok(Self { time_mlp, layers })
    }

    fn output_layer(&self) -> Option<&Linear> {
        self.layers.last()
    }

    /// `features`: [B, N, F], `t`: float [B] -> [B, N] (one score per row, all rows of an item
    /// sharing its time embedding).
    fn forward(&self, features: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let size = features.size();
        let (batch, rows) = match size.as_slice() {
            &[batch, rows, _] => (batch, rows),
            other => return Err(Error::internal("reward MLP", format!("features of shape {other:?}"))),
        };
        let t_emb = self.time_mlp.forward(t, mish)?.f_unsqueeze(1)?.f_expand([batch, rows, MLP_TIME_DIM], false)?;
        let mut h = Tensor::f_cat(&[features, &t_emb], 2)?;
        let last = self.layers.len().saturating_sub(1);
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.forward(&h)?;
            if i < last {
                h = mish.forward(&h)?;
            }
        }
        Ok(h.f_squeeze_dim(-1)?)
    }
}

/// The windowed MLP over trajectories [B, H, D].
#[derive(Debug)]
struct WindowedMlpNet {
    horizon: i64,
    transition_dim: i64,
    window: i64,
    head: MlpHead,
}

impl WindowedMlpNet {
    /// [B, H / h]: one value per non-overlapping window.
    fn per_window(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let batch = x.size().first().copied().unwrap_or(0);
        let windows = x.f_reshape([batch, self.horizon / self.window, self.window * self.transition_dim])?;
        self.head.forward(&windows, t, mish)
    }

    /// [B, H]: one value per stride-1 window starting at each step, the end padded by
    /// repeating the last row.
    fn per_step(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let batch = x.size().first().copied().unwrap_or(0);
        let padded = if self.window > 1 {
            let last =
                x.f_narrow(1, self.horizon - 1, 1)?.f_expand([batch, self.window - 1, self.transition_dim], false)?;
            Tensor::f_cat(&[x, &last], 1)?
        } else {
            x.shallow_clone()
        };
        // [B, H, D, h] -> [B, H, h, D] -> [B, H, h D] (rows of each window in order).
        let windows = padded.f_unfold(1, self.window, 1)?.f_permute([0, 1, 3, 2])?.f_reshape([
            batch,
            self.horizon,
            self.window * self.transition_dim,
        ])?;
        self.head.forward(&windows, t, mish)
    }
}

/// The flat MLP over samples [B, *shape].
#[derive(Debug)]
struct MlpNet {
    features: i64,
    head: MlpHead,
}

impl MlpNet {
    fn forward(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let batch = x.size().first().copied().unwrap_or(0);
        let flat = x.f_reshape([batch, 1, self.features])?;
        Ok(self.head.forward(&flat, t, mish)?.f_squeeze_dim(1)?)
    }
}

#[derive(Debug)]
struct ValueLevel {
    first: ResidualTemporalBlock,
    second: ResidualTemporalBlock,
    downsample: Downsample1d,
}

/// Diffuser's ValueFunction over trajectories [B, H, D].
#[derive(Debug)]
struct ValueFunctionNet {
    time_mlp: TimeMlp,
    levels: Vec<ValueLevel>,
    mid_block1: ResidualTemporalBlock,
    mid_down1: Downsample1d,
    mid_block2: ResidualTemporalBlock,
    mid_down2: Downsample1d,
    final_first: Linear,
    final_second: Linear,
}

impl ValueFunctionNet {
    /// Call only with a validated plan (non-empty widths, the last a multiple of 32).
    fn params(transition_dim: i64, widths: &[i64], final_length: i64) -> u128 {
        let time_dim = widths[0];
        let mut parts = vec![TimeMlp::params(time_dim, 4 * time_dim, time_dim)];
        let mut w_in = transition_dim;
        for &w_out in widths {
            parts.push(ResidualTemporalBlock::params(w_in, w_out, time_dim, TEMPORAL_KERNEL));
            parts.push(ResidualTemporalBlock::params(w_out, w_out, time_dim, TEMPORAL_KERNEL));
            parts.push(Downsample1d::params(w_out));
            w_in = w_out;
        }
        let (mid2, mid3) = (w_in / 2, w_in / 4);
        parts.push(ResidualTemporalBlock::params(w_in, mid2, time_dim, TEMPORAL_KERNEL));
        parts.push(Downsample1d::params(mid2));
        parts.push(ResidualTemporalBlock::params(mid2, mid3, time_dim, TEMPORAL_KERNEL));
        parts.push(Downsample1d::params(mid3));
        let fc = count(mid3).saturating_mul(count(final_length));
        let half = fc / 2;
        parts.push(fc.saturating_add(count(time_dim)).saturating_mul(half).saturating_add(half));
        parts.push(half.saturating_add(1));
        total(&parts)
    }

    fn new(p: &nn::Path, transition_dim: i64, widths: &[i64], final_length: i64) -> Result<Self> {
        let time_dim = widths[0];
        let block = |path: nn::Path, w_in: i64, w_out: i64| {
            ResidualTemporalBlock::new(&path, w_in, w_out, time_dim, TEMPORAL_KERNEL)
        };
        let time_mlp = TimeMlp::new(&(p / "time_mlp"), time_dim, 4 * time_dim, time_dim)?;
        let mut levels = Vec::with_capacity(widths.len());
        let mut w_in = transition_dim;
        for (i, &w_out) in widths.iter().enumerate() {
            let level = p / "blocks" / i;
            levels.push(ValueLevel {
                first: block(&level / "0", w_in, w_out)?,
                second: block(&level / "1", w_out, w_out)?,
                downsample: Downsample1d::new(&(&level / "2"), w_out)?,
            });
            w_in = w_out;
        }
        let (mid2, mid3) = (w_in / 2, w_in / 4);
        let fc = mid3
            .checked_mul(final_length)
            .filter(|&n| n <= MAX_FEATURES)
            .ok_or_else(|| Error::invalid("architecture: value_function's flattened features are too many"))?;
        let final_path = p / "final_block";
        Ok(Self {
            time_mlp,
            levels,
            mid_block1: block(p / "mid_block1", w_in, mid2)?,
            mid_down1: Downsample1d::new(&(p / "mid_down1"), mid2)?,
            mid_block2: block(p / "mid_block2", mid2, mid3)?,
            mid_down2: Downsample1d::new(&(p / "mid_down2"), mid3)?,
            final_first: Linear::new(&(&final_path / "0"), fc + time_dim, fc / 2)?,
            final_second: Linear::new(&(&final_path / "2"), fc / 2, 1)?,
        })
    }

    /// `x`: [B, H, D], `t`: float [B] -> [B].
    fn forward(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let batch = x.size().first().copied().unwrap_or(0);
        let mut x = x.f_permute([0, 2, 1])?;
        let t_emb = self.time_mlp.forward(t, mish)?;
        for level in &self.levels {
            x = level.first.forward(&x, &t_emb, mish)?;
            x = level.second.forward(&x, &t_emb, mish)?;
            x = level.downsample.forward(&x)?;
        }
        x = self.mid_down1.forward(&self.mid_block1.forward(&x, &t_emb, mish)?)?;
        x = self.mid_down2.forward(&self.mid_block2.forward(&x, &t_emb, mish)?)?;
        let flat = x.f_reshape([batch, -1])?;
        let h = self.final_first.forward(&Tensor::f_cat(&[&flat, &t_emb], 1)?)?;
        Ok(self.final_second.forward(&mish.forward(&h)?)?.f_squeeze_dim(1)?)
    }
}

/// PyTorch's default initialisation for convolutions and linear layers:
/// U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weights and biases.
fn torch_default_init(fan_in: i64) -> Init {
    let bound = 1.0 / (fan_in.max(1) as f64).sqrt();
    Init::Uniform { lo: -bound, up: bound }
}

/// `nn.Conv2d(in, out, 3, stride = 2, padding = 1)`: `weight` [out, in, 3, 3], `bias` [out].
#[derive(Debug)]
struct StridedConv2d {
    weight: Tensor,
    bias: Tensor,
}

impl StridedConv2d {
    fn new(p: &nn::Path, in_channels: i64, out_channels: i64) -> Result<Self> {
        let init = torch_default_init(in_channels * 9);
        Ok(Self {
            weight: p.f_var("weight", &[out_channels, in_channels, 3, 3], init)?,
            bias: p.f_var("bias", &[out_channels], init)?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_conv2d(&self.weight, Some(&self.bias), [2, 2], [1, 1], [1, 1], 1)?)
    }
}

/// One encoder level: Mish(GroupNorm(Conv2d(x))) + Linear(Mish(t_emb)) per channel.
#[derive(Debug)]
struct EncoderBlock {
    conv: StridedConv2d,
    norm: GroupNorm,
    time_linear: Linear,
}

impl EncoderBlock {
    fn forward(&self, x: &Tensor, t_emb: &Tensor, mish: Mish) -> Result<Tensor> {
        let h = mish.forward(&self.norm.forward(&self.conv.forward(x)?)?)?;
        let time = self.time_linear.forward(&mish.forward(t_emb)?)?.f_unsqueeze(-1)?.f_unsqueeze(-1)?;
        Ok(h.f_add(&time)?)
    }
}

/// The strided convolutional encoder over images [B, C, H, W].
#[derive(Debug)]
struct ConvEncoderNet {
    time_mlp: TimeMlp,
    blocks: Vec<EncoderBlock>,
    final_first: Linear,
    final_second: Linear,
}

impl ConvEncoderNet {
    /// Call only with validated (non-empty) widths.
    fn params(channels: i64, widths: &[i64]) -> u128 {
        let time_dim = widths[0];
        let mut parts = vec![TimeMlp::params(time_dim, 4 * time_dim, time_dim)];
        let mut w_in = channels;
        for &w_out in widths {
            parts.push(conv_params(w_in, w_out, 9));
            parts.push(2 * count(w_out));
            parts.push(linear_params(time_dim, w_out));
            w_in = w_out;
        }
        parts.push(linear_params(w_in + time_dim, w_in / 2));
        parts.push(linear_params(w_in / 2, 1));
        total(&parts)
    }

    fn new(p: &nn::Path, channels: i64, widths: &[i64]) -> Result<Self> {
        let time_dim = widths[0];
        let time_mlp = TimeMlp::new(&(p / "time_mlp"), time_dim, 4 * time_dim, time_dim)?;
        let mut blocks = Vec::with_capacity(widths.len());
        let mut w_in = channels;
        for (i, &w_out) in widths.iter().enumerate() {
            let block = p / "blocks" / i;
            blocks.push(EncoderBlock {
                conv: StridedConv2d::new(&(&block / "conv"), w_in, w_out)?,
                norm: GroupNorm::new(&(&block / "norm"), GROUPS, w_out)?,
                time_linear: Linear::new(&(&block / "time_mlp" / "1"), time_dim, w_out)?,
            });
            w_in = w_out;
        }
        let final_path = p / "final_block";
        Ok(Self {
            time_mlp,
            blocks,
            final_first: Linear::new(&(&final_path / "0"), w_in + time_dim, w_in / 2)?,
            final_second: Linear::new(&(&final_path / "2"), w_in / 2, 1)?,
        })
    }

    /// `x`: [B, C, H, W], `t`: float [B] -> [B].
    fn forward(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let t_emb = self.time_mlp.forward(t, mish)?;
        let mut h = x.shallow_clone();
        for block in &self.blocks {
            h = block.forward(&h, &t_emb, mish)?;
        }
        let pooled = h.f_mean_dim([2i64, 3].as_slice(), false, None::<Kind>)?;
        let out = self.final_first.forward(&Tensor::f_cat(&[&pooled, &t_emb], 1)?)?;
        Ok(self.final_second.forward(&mish.forward(&out)?)?.f_squeeze_dim(1)?)
    }
}

#[derive(Debug)]
enum Network {
    WindowedMlp(WindowedMlpNet),
    ValueFunction(Box<ValueFunctionNet>),
    ConvEncoder(Box<ConvEncoderNet>),
    Mlp(MlpNet),
}

/// A relative reward network rho_theta(x, t) with its variables.
#[derive(Debug)]
pub struct RewardNet {
    vs: VarStore,
    network: Network,
    architecture: RewardArchitecture,
    item_shape: Vec<i64>,
    parameter_count: u64,
}

impl RewardNet {
    /// Validates the architecture against the item shape and returns the number of parameters
    /// the network would have, without allocating it. Errors name the field at fault.
    pub fn planned_parameter_count(architecture: &RewardArchitecture, item_shape: &[i64]) -> Result<u64> {
        Plan::new(architecture, item_shape)?.params()
    }

    /// A freshly initialised network (PyTorch's default initialisation) on `device`, for items
    /// of `item_shape` ([H, D] for trajectories, the sample shape otherwise).
    pub fn new(architecture: &RewardArchitecture, item_shape: &[i64], device: Device) -> Result<Self> {
        let plan = Plan::new(architecture, item_shape)?;
        let planned = plan.params()?;
        let vs = VarStore::new(device);
        let root = vs.root();
        let network = match &plan {
            Plan::WindowedMlp { horizon, transition_dim, window, hidden } => Network::WindowedMlp(WindowedMlpNet {
                horizon: *horizon,
                transition_dim: *transition_dim,
                window: *window,
                head: MlpHead::new(&root, window * transition_dim, hidden)?,
            }),
            Plan::Mlp { features, hidden } => {
                Network::Mlp(MlpNet { features: *features, head: MlpHead::new(&root, *features, hidden)? })
            }
            Plan::ValueFunction { transition_dim, widths, final_length } => {
                Network::ValueFunction(Box::new(ValueFunctionNet::new(&root, *transition_dim, widths, *final_length)?))
            }
            Plan::ConvEncoder { channels, widths } => {
                Network::ConvEncoder(Box::new(ConvEncoderNet::new(&root, *channels, widths)?))
            }
        };
        let parameter_count = vs
            .variables()
            .values()
            .map(|t| u64::try_from(t.numel()).unwrap_or(u64::MAX))
            .fold(0u64, u64::saturating_add);
        if parameter_count != planned {
            return Err(Error::internal("RewardNet", format!("built {parameter_count} parameters, planned {planned}")));
        }
        Ok(Self { vs, network, architecture: architecture.clone(), item_shape: item_shape.to_vec(), parameter_count })
    }

    /// Builds the network and loads its weights from a safetensors file (strictly, see
    /// [`Self::load_weights`]).
    pub fn load(architecture: &RewardArchitecture, item_shape: &[i64], path: &Path, device: Device) -> Result<Self> {
        let mut net = Self::new(architecture, item_shape, device)?;
        net.load_weights(path)?;
        Ok(net)
    }

    /// Replaces every weight with the tensor of the same name in a safetensors file, strictly
    /// (see [`weights::load_strict`]): on any mismatch nothing is changed.
    pub fn load_weights(&mut self, path: &Path) -> Result<()> {
        weights::load_strict(&self.vs, self.parameter_count, path)
    }

    /// Writes every weight to `path` atomically (see [`weights::save_atomic`]).
    pub fn save(&self, path: &Path) -> Result<()> {
        weights::save_atomic(&self.vs, path)
    }

    pub fn var_store(&self) -> &VarStore {
        &self.vs
    }

    /// Mutable access for a trainer (optimizer, freezing, `double()` for precise checks).
    /// Changing the set of variables breaks the network.
    pub fn var_store_mut(&mut self) -> &mut VarStore {
        &mut self.vs
    }

    pub fn parameter_count(&self) -> u64 {
        self.parameter_count
    }

    /// The parameter names (the PyTorch state-dict keys), sorted.
    pub fn parameter_names(&self) -> Vec<String> {
        let mut names: Vec<String> = self.vs.variables().into_keys().collect();
        names.sort();
        names
    }

    pub fn architecture(&self) -> &RewardArchitecture {
        &self.architecture
    }

    /// Shape of one item, without the batch dimension.
    pub fn item_shape(&self) -> &[i64] {
        &self.item_shape
    }

    /// E.g. "windowed_mlp(h=4, hidden=[128, 64, 32])".
    pub fn describe(&self) -> String {
        self.architecture.to_string()
    }

    /// Whether per-step values exist (windowed architectures).
    pub fn is_windowed(&self) -> bool {
        matches!(self.network, Network::WindowedMlp(_))
    }

    /// Window length h of the windowed MLP (`None` for the other architectures).
    pub fn window(&self) -> Option<usize> {
        match &self.network {
            Network::WindowedMlp(net) => Some(net.window as usize),
            _ => None,
        }
    }

    /// The dtype of the weights (float32 unless the store was converted); inputs must match.
    pub fn kind(&self) -> Kind {
        let output = match &self.network {
            Network::WindowedMlp(net) => net.head.output_layer(),
            Network::Mlp(net) => net.head.output_layer(),
            Network::ValueFunction(net) => Some(&net.final_second),
            Network::ConvEncoder(net) => Some(&net.final_second),
        };
        output.map_or(Kind::Float, |layer| layer.weight.kind())
    }

    /// rho(x, t): `x` [B, *item_shape] in the weights' dtype, `t` int64 [B] -> [B].
    /// Differentiable with respect to `x` and the parameters when grad mode is on.
    pub fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let t = self.check_inputs(x, t)?;
        self.rho_unchecked(x, &t, Mish::Fused)
    }

    /// Per-window values: [B, H / h] for the windowed MLP (rho is their mean); [B, 1] = rho
    /// for the other architectures.
    pub fn per_window(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let t = self.check_inputs(x, t)?;
        match &self.network {
            Network::WindowedMlp(net) => net.per_window(x, &t, Mish::Fused),
            _ => Ok(self.rho_unchecked(x, &t, Mish::Fused)?.f_unsqueeze(1)?),
        }
    }

    /// Per-step values [B, H] of the windowed MLP: the window starting at each step (the end
    /// padded by repeating the last row). InvalidArgument for other architectures.
    pub fn per_step(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let Network::WindowedMlp(net) = &self.network else {
            return Err(Error::invalid(format!(
                "per-step values need a windowed reward (windowed_mlp); this one is {}",
                self.describe()
            )));
        };
        let t = self.check_inputs(x, t)?;
        net.per_step(x, &t, Mish::Fused)
    }

    /// (rho [B], grad_x of sum(rho), the shape of `x`), both without autograd history. Works
    /// inside a no-grad region (grad mode is enabled locally); parameter gradients are not
    /// accumulated.
    pub fn grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        let t = self.check_inputs(x, t)?;
        tch::with_grad(|| {
            let x_req = x.f_detach_copy()?.f_set_requires_grad(true)?;
            let rho = self.rho_unchecked(&x_req, &t, Mish::Fused)?;
            let grad_x = input_gradient(&rho, &x_req, false)?;
            Ok((rho.f_detach()?, grad_x))
        })
    }

    /// grad_x of sum(rho) WITH its graph (create_graph): a loss computed from it (with grad mode
    /// on) backpropagates to the parameters through the double backward of Algorithm 1. The
    /// graph is built from a detached copy of `x`, so no gradient flows back into `x`. The one
    /// pass differentiated twice, hence [`Mish::TwiceDifferentiable`] (the fused op's second
    /// derivative is NaN for inputs above about 88.7; blocks.rs).
    pub fn grad_create_graph(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let t = self.check_inputs(x, t)?;
        tch::with_grad(|| {
            let x_req = x.f_detach_copy()?.f_set_requires_grad(true)?;
            let rho = self.rho_unchecked(&x_req, &t, Mish::TwiceDifferentiable)?;
            input_gradient(&rho, &x_req, true)
        })
    }

    fn rho_unchecked(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        match &self.network {
            Network::WindowedMlp(net) => {
                Ok(net.per_window(x, t, mish)?.f_mean_dim([1i64].as_slice(), false, None::<Kind>)?)
            }
            Network::Mlp(net) => net.forward(x, t, mish),
            Network::ValueFunction(net) => net.forward(x, t, mish),
            Network::ConvEncoder(net) => net.forward(x, t, mish),
        }
    }

    /// Checks x [B >= 1, *item_shape] (the weights' dtype) and t int64 [B]; returns t as the
    /// weights' float dtype for the time embedding.
    fn check_inputs(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let size = x.size();
        let batch = size.first().copied().unwrap_or(0);
        if size.len() != self.item_shape.len() + 1 || batch < 1 || size[1..] != self.item_shape[..] {
            return Err(Error::invalid(format!(
                "reward input x: shape [{}] does not match [B >= 1, {}]",
                shape_text(&size),
                shape_text(&self.item_shape)
            )));
        }
        let kind = self.kind();
        if x.kind() != kind {
            return Err(Error::invalid(format!("reward input x: dtype {:?}, expected {kind:?}", x.kind())));
        }
        if t.size() != [batch] || t.kind() != Kind::Int64 {
            return Err(Error::invalid(format!(
                "reward input t: shape [{}] and dtype {:?}, expected int64 [{batch}]",
                shape_text(&t.size()),
                t.kind()
            )));
        }
        Ok(t.f_to_kind(kind)?)
    }
}

/// d sum(rho) / d x_req, with or without a differentiable graph (PyTorch's
/// `autograd.grad(rho.sum(), x, create_graph = c, retain_graph = c)`).
fn input_gradient(rho: &Tensor, x_req: &Tensor, create_graph: bool) -> Result<Tensor> {
    let sum = rho.f_sum(None::<Kind>)?;
    let grad = Tensor::f_run_backward(&[&sum], &[x_req], create_graph, create_graph)?
        .pop()
        .ok_or_else(|| Error::internal("reward gradient", "autograd returned no gradient"))?;
    if grad.defined() { Ok(grad) } else { Ok(x_req.f_zeros_like()?) }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;

    const CPU: Device = Device::Cpu;

    fn windowed(window: usize, hidden: &[usize]) -> RewardArchitecture {
        RewardArchitecture::WindowedMlp { window, hidden: hidden.to_vec() }
    }

    fn value_function(widths: &[usize]) -> RewardArchitecture {
        RewardArchitecture::ValueFunction { widths: widths.to_vec() }
    }

    fn conv_encoder(widths: &[usize]) -> RewardArchitecture {
        RewardArchitecture::ConvEncoder { widths: widths.to_vec() }
    }

    fn mlp(hidden: &[usize]) -> RewardArchitecture {
        RewardArchitecture::Mlp { hidden: hidden.to_vec() }
    }

    fn build(arch: &RewardArchitecture, item_shape: &[i64]) -> RewardNet {
        RewardNet::new(arch, item_shape, CPU).expect("reward network builds")
    }

    /// Deterministic pseudo-random values in [-1, 1) (a sine hash): the tests do not draw from
    /// libtorch's global generator, which tests running in parallel threads share.
    fn pseudo_random(shape: &[i64], seed: f64, kind: Kind) -> Tensor {
        let n: i64 = shape.iter().product();
        let hashed = ((Tensor::arange(n, (Kind::Double, CPU)) * 12.9898 + seed * 78.233).sin() * 43758.5453).frac();
        let unit = &hashed - hashed.floor();
        (unit * 2.0 - 1.0).reshape(shape).to_kind(kind)
    }

    /// Replaces every weight with deterministic values at PyTorch-like scales (GroupNorm
    /// weights around 1, biases around 0): moves every weight off its initial value.
    fn perturb(net: &RewardNet) {
        let variables: BTreeMap<String, Tensor> = net.var_store().variables().into_iter().collect();
        tch::no_grad(|| {
            for (i, (name, mut var)) in variables.into_iter().enumerate() {
                let size = var.size();
                let noise = pseudo_random(&size, i as f64 + 0.5, var.kind());
                let value = match size.as_slice() {
                    [out, ..] if size.len() > 1 => {
                        let fan_in = (var.numel() as i64 / out).max(1) as f64;
                        noise * (1.5 / fan_in.sqrt())
                    }
                    _ if name.ends_with(".weight") => noise * 0.3 + 1.0,
                    _ => noise * 0.3,
                };
                var.copy_(&value);
            }
        });
    }

    fn inputs(net: &RewardNet, batch: i64, kind: Kind) -> (Tensor, Tensor) {
        let mut shape = vec![batch];
        shape.extend_from_slice(net.item_shape());
        let x = pseudo_random(&shape, 0.25, kind) * 1.5;
        let t = Tensor::arange(batch, (Kind::Int64, CPU)) * 7 + 1;
        (x, t)
    }

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
        assert_eq!(a.size(), b.size());
        (a - b).abs().max().double_value(&[])
    }

    /// Asserts max |a - b| <= tolerance * max(1, max |b|) (float32 rounding scales with the
    /// values).
    #[track_caller]
    fn assert_close(a: &Tensor, b: &Tensor, tolerance: f64, what: &str) {
        let diff = max_abs_diff(a, b);
        let scale = b.abs().max().double_value(&[]).max(1.0);
        assert!(diff <= tolerance * scale, "{what}: max |difference| {diff:e} exceeds {tolerance:e} * {scale}");
    }

    fn invalid_message<T: std::fmt::Debug>(result: Result<T>) -> String {
        match result {
            Err(Error::InvalidArgument(msg)) => msg,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    /// Every architecture at a small size, with its item shape. Widths keep at least two
    /// channels per GroupNorm group (w / 4 = 16 in the value function's mid blocks): with one
    /// channel per group a convolution's bias is normalized away and cannot receive gradients.
    fn small_cases() -> Vec<(RewardArchitecture, Vec<i64>)> {
        vec![
            (windowed(4, &[32, 16]), vec![16, 3]),
            (windowed(1, &[16]), vec![8, 3]),
            (value_function(&[16, 64]), vec![16, 3]),
            (value_function(&[16, 64]), vec![64, 3]),
            (conv_encoder(&[16, 32]), vec![3, 7, 5]),
            (mlp(&[16, 8]), vec![2, 3, 2]),
        ]
    }

    #[test]
    fn reward_windowed_rho_is_the_mean_of_its_windows() {
        let net = build(&windowed(4, &[32, 16]), &[16, 3]);
        perturb(&net);
        let (x, t) = inputs(&net, 3, Kind::Float);
        let rho = tch::no_grad(|| net.rho(&x, &t)).expect("rho");
        let windows = tch::no_grad(|| net.per_window(&x, &t)).expect("per window");
        assert_eq!(rho.size(), [3]);
        assert_eq!(windows.size(), [3, 4]);
        assert_close(&rho, &windows.mean_dim(1, false, Kind::Float), 1e-6, "rho vs mean of windows");
        // Not the sum, and not trivially constant.
        assert!(max_abs_diff(&rho, &windows.sum_dim_intlist(1, false, Kind::Float)) > 1e-3);
        assert!(windows.std(true).double_value(&[]) > 1e-3);

        // Every 4th per-step value is a per-window value.
        let steps = tch::no_grad(|| net.per_step(&x, &t)).expect("per step");
        assert_eq!(steps.size(), [3, 16]);
        let aligned = steps.slice(1, 0, 16, 4);
        assert_close(&aligned, &windows, 1e-6, "every h-th step vs windows");
    }

    #[test]
    fn reward_windowed_per_step_values_line_up_with_states() {
        let (h, horizon) = (4i64, 16i64);
        let net = build(&windowed(4, &[32, 16]), &[horizon, 3]);
        perturb(&net);
        let (x, t) = inputs(&net, 2, Kind::Float);
        let run = |x: &Tensor| {
            tch::no_grad(|| (net.per_step(x, &t).expect("per step"), net.per_window(x, &t).expect("per window")))
        };
        let (steps, windows) = run(&x);
        for k in [0i64, 6, 9, 15] {
            let changed = x.copy();
            let _ = changed.narrow(1, k, 1).f_add_scalar_(0.5).expect("edit");
            let (steps2, windows2) = run(&changed);
            let step_moved = (&steps2 - &steps).abs().amax(0, false);
            let window_moved = (&windows2 - &windows).abs().amax(0, false);
            for j in 0..horizon {
                let moved = step_moved.double_value(&[j]) > 1e-6;
                assert_eq!(moved, (k - h + 1..=k).contains(&j), "state {k}: per_step[{j}] moved = {moved}");
            }
            for w in 0..horizon / h {
                let moved = window_moved.double_value(&[w]) > 1e-6;
                assert_eq!(moved, w == k / h, "state {k}: per_window[{w}] moved = {moved}");
            }
        }
    }

    #[test]
    fn reward_windowed_per_step_pads_by_repeating_the_last_row() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (h, horizon, d) = (4i64, 12i64, 3i64);
        let arch = windowed(4, &[32, 16]);
        let net = build(&arch, &[horizon, d]);
        perturb(&net);
        let path = dir.path().join("windowed.safetensors");
        net.save(&path).expect("save");
        // The same weights score single windows: they depend on h and D only.
        let single = RewardNet::load(&arch, &[h, d], &path, CPU).expect("loads for another horizon");

        let (x, t) = inputs(&net, 2, Kind::Float);
        let steps = tch::no_grad(|| net.per_step(&x, &t)).expect("per step");
        let last = x.narrow(1, horizon - 1, 1);
        let padded = Tensor::cat(&[x.shallow_clone(), last.repeat([1, h - 1, 1])], 1);
        for k in 0..horizon {
            let window = padded.narrow(1, k, h).contiguous();
            let value = tch::no_grad(|| single.rho(&window, &t)).expect("window rho");
            assert_close(&value, &steps.select(1, k), 1e-6, &format!("step {k} vs its padded window"));
        }

        // h = 1: per-step and per-window values coincide.
        let net1 = build(&windowed(1, &[16]), &[8, 3]);
        perturb(&net1);
        let (x, t) = inputs(&net1, 2, Kind::Float);
        let steps = tch::no_grad(|| net1.per_step(&x, &t)).expect("per step");
        let windows = tch::no_grad(|| net1.per_window(&x, &t)).expect("per window");
        assert_eq!(steps.size(), [2, 8]);
        assert_close(&steps, &windows, 1e-6, "h = 1: steps vs windows");
    }

    #[test]
    fn reward_window_must_divide_the_horizon() {
        let msg = invalid_message(RewardNet::new(&windowed(4, &[32]), &[30, 6], CPU));
        assert!(msg.contains("horizon 30 is not divisible by window 4"), "{msg}");
        assert!(msg.contains("architecture.window"), "{msg}");
    }

    #[test]
    fn reward_non_windowed_nets_have_one_window_and_no_steps() {
        for (arch, shape) in small_cases().into_iter().skip(2) {
            let net = build(&arch, &shape);
            let (x, t) = inputs(&net, 2, Kind::Float);
            let rho = tch::no_grad(|| net.rho(&x, &t)).expect("rho");
            let windows = tch::no_grad(|| net.per_window(&x, &t)).expect("per window");
            assert_eq!(windows.size(), [2, 1]);
            assert_close(&windows.squeeze_dim(1), &rho, 1e-6, "one window vs rho");
            assert!(!net.is_windowed());
            let msg = invalid_message(net.per_step(&x, &t));
            assert!(msg.contains("per-step values need a windowed reward"), "{msg}");
        }
    }

    /// Central finite differences of rho in float64 against `grad`, for every architecture,
    /// also from inside a no-grad region.
    #[test]
    fn reward_grad_matches_finite_differences() {
        for (arch, shape) in small_cases() {
            let mut net = build(&arch, &shape);
            perturb(&net);
            net.var_store_mut().double();
            assert_eq!(net.kind(), Kind::Double);
            let (x, t) = inputs(&net, 2, Kind::Double);
            let (rho, grad) = tch::no_grad(|| net.grad(&x, &t)).expect("grad inside no_grad");
            assert_eq!(grad.size(), x.size());
            assert!(!rho.requires_grad() && !grad.requires_grad());
            let (rho_outside, grad_outside) = net.grad(&x, &t).expect("grad");
            assert_eq!(max_abs_diff(&rho, &rho_outside), 0.0);
            assert_eq!(max_abs_diff(&grad, &grad_outside), 0.0);
            // Parameter gradients are not accumulated by `grad`.
            assert!(net.var_store().variables().values().all(|v| !v.grad().defined()));

            let flat_x = x.reshape([-1]);
            let flat_grad = grad.reshape([-1]);
            let eps = 1e-5;
            let n = flat_x.size()[0];
            let scale = flat_grad.abs().max().double_value(&[]);
            let mut worst = 0.0f64;
            for index in (0..n).step_by(usize::try_from((n / 24).max(1)).expect("step")) {
                // d sum(rho) / dx: the sum also catches any coupling between batch items.
                let bump = |delta: f64| {
                    let y = flat_x.copy();
                    let _ = y.narrow(0, index, 1).f_add_scalar_(delta).expect("bump");
                    tch::no_grad(|| net.rho(&y.reshape(x.size()), &t)).expect("rho").sum(Kind::Double).double_value(&[])
                };
                let numeric = (bump(eps) - bump(-eps)) / (2.0 * eps);
                let analytic = flat_grad.double_value(&[index]);
                worst = worst.max((numeric - analytic).abs());
                assert!(
                    (numeric - analytic).abs() <= 1e-6 * scale + 1e-9,
                    "{arch}: coordinate {index}: finite difference {numeric} vs grad {analytic}"
                );
            }
            eprintln!("{arch}: worst |finite difference - grad| = {worst:.2e} (max |grad| {scale:.2e})");
            assert!(scale > 1e-3, "{arch}: gradient trivially zero");
        }
    }

    /// The double backward reaches every parameter that grad_x depends on (all but the output
    /// bias), and grad_create_graph equals grad.
    #[test]
    fn reward_double_backward_reaches_the_parameters() {
        for (arch, shape) in small_cases() {
            let net = build(&arch, &shape);
            perturb(&net);
            let (x, t) = inputs(&net, 3, Kind::Float);
            let graph_grad = tch::no_grad(|| net.grad_create_graph(&x, &t)).expect("grad_create_graph");
            assert!(graph_grad.requires_grad());
            let (_, grad) = net.grad(&x, &t).expect("grad");
            assert_close(&graph_grad, &grad, 1e-5, &format!("{arch}: grad_create_graph vs grad"));

            let target = pseudo_random(&x.size(), 0.75, Kind::Float);
            let loss = (&graph_grad - &target).square().sum(Kind::Float) / 3.0;
            loss.backward();
            let output_bias = match &arch {
                RewardArchitecture::WindowedMlp { hidden, .. } | RewardArchitecture::Mlp { hidden } => {
                    format!("net.{}.bias", 2 * hidden.len())
                }
                _ => "final_block.2.bias".to_string(),
            };
            for (name, var) in net.var_store().variables() {
                let g = var.grad();
                let size = if g.defined() { g.abs().sum(Kind::Float).double_value(&[]) } else { 0.0 };
                if name == output_bias {
                    assert!(size == 0.0, "{arch}: {name} cannot affect grad_x, got {size}");
                } else {
                    assert!(size > 0.0, "{arch}: {name} received no gradient through the double backward");
                }
            }
            // No gradient leaks into the caller's x.
            assert!(!x.grad().defined());
        }
    }

    /// Mish inputs past exp's overflow (every bias raised by 100) leave the double backward
    /// finite: libtorch's fused Mish would make every parameter gradient NaN here.
    #[test]
    fn reward_double_backward_stays_finite_for_large_activations() {
        for (arch, shape) in small_cases() {
            let net = build(&arch, &shape);
            perturb(&net);
            tch::no_grad(|| {
                for (name, var) in net.var_store().variables() {
                    if name.ends_with("bias") {
                        let _ = var.shallow_clone().f_add_scalar_(100.0).expect("raise bias");
                    }
                }
            });
            let (x, t) = inputs(&net, 3, Kind::Float);
            let graph_grad = tch::no_grad(|| net.grad_create_graph(&x, &t)).expect("grad_create_graph");
            let target = pseudo_random(&x.size(), 0.75, Kind::Float);
            (&graph_grad - &target).square().sum(Kind::Float).backward();
            for (name, var) in net.var_store().variables() {
                let g = var.grad();
                if g.defined() {
                    let finite = bool::try_from(g.isfinite().all()).expect("bool");
                    assert!(finite, "{arch}: {name}'s gradient is not finite");
                }
            }
        }
    }

    #[test]
    fn reward_parameter_names_and_counts() {
        let net = build(&value_function(&[64, 64, 128, 128]), &[32, 23]);
        let names = net.parameter_names();
        for expected in [
            "time_mlp.1.weight",
            "time_mlp.3.bias",
            "blocks.0.0.blocks.0.block.0.weight",
            "blocks.0.0.residual_conv.weight",
            "blocks.0.0.time_mlp.1.weight",
            "blocks.3.1.blocks.1.block.2.bias",
            "blocks.3.2.conv.weight",
            "mid_block1.residual_conv.weight",
            "mid_down1.conv.weight",
            "mid_block2.blocks.1.block.2.weight",
            "mid_down2.conv.bias",
            "final_block.0.weight",
            "final_block.2.bias",
        ] {
            assert!(names.iter().any(|n| n == expected), "{expected} missing from {names:?}");
        }
        assert!(!names.iter().any(|n| n == "blocks.1.0.residual_conv.weight"), "same widths: identity residual");
        // Horizon 32 through 6 downsamplings: length 1, fc = 128 / 4 = 32.
        let vars = net.var_store().variables();
        assert_eq!(vars["final_block.0.weight"].size(), [16, 32 + 64]);
        assert_eq!(vars["mid_down2.conv.weight"].size(), [32, 32, 3]);
        assert_eq!(
            u128::from(net.parameter_count()),
            RewardNet::planned_parameter_count(&net.architecture, &[32, 23]).expect("plan").into()
        );
        // HalfCheetah's horizon 4: still length 1.
        let cheetah = build(&value_function(&[64, 64, 128, 128]), &[4, 23]);
        assert_eq!(cheetah.var_store().variables()["final_block.0.weight"].size(), [16, 32 + 64]);
        // Horizon 256 with two levels: 256 / 2^4 = 16, fc = 8 * 16.
        let long = build(&value_function(&[16, 32]), &[256, 6]);
        assert_eq!(long.var_store().variables()["final_block.0.weight"].size(), [64, 128 + 16]);

        let net = build(&windowed(4, &[128, 64, 32]), &[256, 6]);
        assert_eq!(
            net.parameter_names(),
            [
                "net.0.bias",
                "net.0.weight",
                "net.2.bias",
                "net.2.weight",
                "net.4.bias",
                "net.4.weight",
                "net.6.bias",
                "net.6.weight",
                "time_mlp.1.bias",
                "time_mlp.1.weight",
                "time_mlp.3.bias",
                "time_mlp.3.weight"
            ]
        );
        // (24 + 32) * 128 + 128, 128 * 64 + 64, 64 * 32 + 32, 32 + 1, time MLP 8352.
        assert_eq!(net.parameter_count(), 7296 + 8256 + 2080 + 33 + 8352);
        assert_eq!(net.describe(), "windowed_mlp(h=4, hidden=[128, 64, 32])");

        let net = build(&conv_encoder(&[32, 64, 128, 256]), &[4, 64, 64]);
        let vars = net.var_store().variables();
        assert_eq!(vars["blocks.0.conv.weight"].size(), [32, 4, 3, 3]);
        assert_eq!(vars["blocks.3.norm.weight"].size(), [256]);
        assert_eq!(vars["blocks.2.time_mlp.1.weight"].size(), [128, 32]);
        assert_eq!(vars["final_block.0.weight"].size(), [128, 256 + 32]);
        assert_eq!(net.describe(), "conv_encoder(widths=[32, 64, 128, 256])");
        for (arch, shape) in small_cases() {
            let net = build(&arch, &shape);
            let planned = RewardNet::planned_parameter_count(&arch, &shape).expect("plan");
            assert_eq!(net.parameter_count(), planned, "{arch}");
        }
    }

    #[test]
    fn reward_inputs_are_checked() {
        let net = build(&value_function(&[8, 32]), &[16, 3]);
        let (x, t) = inputs(&net, 2, Kind::Float);
        let wrong = Tensor::zeros([2, 15, 3], (Kind::Float, CPU));
        let msg = invalid_message(net.rho(&wrong, &t));
        assert!(msg.contains("[2, 15, 3]") && msg.contains("[B >= 1, 16, 3]"), "{msg}");
        assert!(invalid_message(net.grad(&wrong, &t)).contains("reward input x"));
        assert!(invalid_message(net.rho(&x.to_kind(Kind::Double), &t)).contains("Float"));
        assert!(invalid_message(net.rho(&x, &t.to_kind(Kind::Float))).contains("reward input t"));
        assert!(invalid_message(net.grad_create_graph(&x, &t.narrow(0, 0, 1))).contains("reward input t"));
        let empty = Tensor::zeros([0, 16, 3], (Kind::Float, CPU));
        assert!(invalid_message(net.rho(&empty, &t.narrow(0, 0, 0))).contains("reward input x"));
    }

    #[test]
    fn reward_invalid_architectures_name_the_field() {
        let cases = [
            (windowed(0, &[32]), vec![16, 6], "architecture.window"),
            (windowed(4, &[]), vec![16, 6], "architecture.hidden"),
            (windowed(4, &[32, 0]), vec![16, 6], "architecture.hidden"),
            (windowed(4, &[32]), vec![4, 4, 4], "trajectory item shape"),
            (windowed(4, &[32]), vec![16, 0], "item shape"),
            (windowed(usize::MAX, &[32]), vec![16, 6], "architecture.window"),
            (value_function(&[]), vec![32, 6], "architecture.widths"),
            (value_function(&[12, 32]), vec![32, 6], "architecture.widths: 12"),
            (value_function(&[8, 16]), vec![32, 6], "last width 16"),
            (value_function(&[64, 64, 128, 128]), vec![48, 6], "horizon 48"),
            (value_function(&[64, 64, 128, 128]), vec![12, 6], "horizon 12"),
            (value_function(&[32]), vec![6], "trajectory item shape"),
            (conv_encoder(&[32, 20]), vec![4, 8, 8], "architecture.widths: 20"),
            (conv_encoder(&[32]), vec![4, 8], "image-like item shape"),
            (conv_encoder(&[1 << 21]), vec![4, 8, 8], "architecture.widths"),
            (mlp(&[]), vec![4], "architecture.hidden"),
            (mlp(&[1 << 20, 1 << 20]), vec![4], "exceed the limit"),
            (mlp(&[16]), vec![], "item shape"),
            (mlp(&[16]), vec![i64::MAX, 4], "item shape"),
        ];
        for (arch, shape, needle) in cases {
            let msg = invalid_message(RewardNet::new(&arch, &shape, CPU));
            assert!(msg.contains(needle), "{arch} {shape:?}: {msg} should contain {needle}");
        }
        // Powers of two below 2^(levels + 2) are fine (HalfCheetah's horizon 4), as are multiples.
        for horizon in [1, 2, 4, 8, 64, 128, 192] {
            assert!(RewardNet::planned_parameter_count(&value_function(&[64, 64, 128, 128]), &[horizon, 6]).is_ok());
        }
    }

    #[test]
    fn reward_architecture_serde() {
        let arch: RewardArchitecture =
            serde_json::from_str(r#"{"kind": "windowed_mlp", "window": 4, "hidden": [128, 64, 32]}"#).expect("json");
        assert_eq!(arch, windowed(4, &[128, 64, 32]));
        let arch: RewardArchitecture =
            toml::from_str("kind = \"value_function\"\nwidths = [64, 64, 128, 128]").expect("toml");
        assert_eq!(arch, value_function(&[64, 64, 128, 128]));
        let json = serde_json::to_string(&conv_encoder(&[32, 64])).expect("serialize");
        assert_eq!(json, r#"{"kind":"conv_encoder","widths":[32,64]}"#);
        for (text, needle) in [
            (r#"{"kind": "mlp", "hidden": [8], "extra": 1}"#, "unknown field `extra`"),
            (r#"{"kind": "transformer"}"#, "unknown variant `transformer`"),
            (r#"{"kind": "windowed_mlp", "hidden": [8]}"#, "missing field `window`"),
        ] {
            let err = serde_json::from_str::<RewardArchitecture>(text).expect_err(needle).to_string();
            assert!(err.contains(needle), "{err} should contain {needle}");
        }
        assert_eq!(mlp(&[8]).to_string(), "mlp(hidden=[8])");
        assert_eq!(value_function(&[8, 32]).to_string(), "value_function(widths=[8, 32])");
    }

    #[test]
    fn reward_save_then_load_reproduces_rho_exactly() {
        let dir = tempfile::tempdir().expect("tempdir");
        for (i, (arch, shape)) in small_cases().into_iter().enumerate() {
            let original = build(&arch, &shape);
            perturb(&original);
            let path = dir.path().join(format!("reward-{i}.bin"));
            original.save(&path).expect("save");
            let loaded = RewardNet::load(&arch, &shape, &path, CPU).expect("load");
            let (x, t) = inputs(&original, 3, Kind::Float);
            let run = |net: &RewardNet| tch::no_grad(|| net.rho(&x, &t)).expect("rho");
            assert_eq!(max_abs_diff(&run(&original), &run(&loaded)), 0.0, "{arch}");
            assert!(max_abs_diff(&run(&original), &run(&build(&arch, &shape))) > 0.0, "{arch}");
        }
        assert_eq!(std::fs::read_dir(dir.path()).expect("list").count(), small_cases().len(), "no temporary files");
    }

    #[test]
    fn reward_strict_loading_rejects_mismatched_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        let arch = value_function(&[8, 32]);
        let shape = [16i64, 3];
        let net = build(&arch, &shape);
        let named: Vec<(String, Tensor)> = net
            .var_store()
            .variables()
            .into_iter()
            .collect::<BTreeMap<_, _>>()
            .into_iter()
            .map(|(n, t)| (n, t.detach().contiguous()))
            .collect();
        let write = |name: &str, tensors: &[(String, Tensor)]| {
            let path = dir.path().join(name);
            Tensor::write_safetensors(tensors, &path).expect("write");
            path
        };
        let victim = "mid_block2.blocks.0.block.2.weight";
        let replace = |with: &dyn Fn(&Tensor) -> Tensor| -> Vec<(String, Tensor)> {
            named.iter().map(|(n, t)| (n.clone(), if n == victim { with(t) } else { t.shallow_clone() })).collect()
        };
        let missing: Vec<_> =
            named.iter().filter(|(n, _)| n != victim).map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
        let wrong_shape = replace(&|_| Tensor::ones([3], (Kind::Float, CPU)));
        let wrong_dtype = replace(&|t| t.to_kind(Kind::Double));
        let mut extra: Vec<_> = named.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
        extra.push(("mid_attn.weight".to_string(), Tensor::ones([2], (Kind::Float, CPU))));
        let mut oversized: Vec<_> = named.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
        oversized.push(("padding".to_string(), Tensor::zeros([1 << 19], (Kind::Float, CPU))));
        let garbage = dir.path().join("garbage.safetensors");
        std::fs::write(&garbage, b"\xff\xff\xff\xff\xff\xff\xff\x7fnot a header").expect("write");
        let cases = [
            (write("missing.safetensors", &missing), format!("missing tensor(s) '{victim}'")),
            (write("shape.safetensors", &wrong_shape), format!("tensor '{victim}' has shape [3], expected [8]")),
            (write("dtype.safetensors", &wrong_dtype), format!("tensor '{victim}' has dtype Double")),
            (write("extra.safetensors", &extra), "unexpected tensor(s) 'mid_attn.weight'".to_string()),
            (garbage, "not a valid safetensors file".to_string()),
            (write("oversized.safetensors", &oversized), "more than the".to_string()),
        ];
        let mut target = build(&arch, &shape);
        let before: BTreeMap<String, Tensor> =
            target.var_store().variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
        for (path, needle) in cases {
            let msg = invalid_message(target.load_weights(&path));
            assert!(msg.contains(&needle), "{msg} should contain {needle}");
            assert!(!msg.contains(&dir.path().display().to_string()), "{msg} leaks the path");
        }
        let after: BTreeMap<String, Tensor> =
            target.var_store().variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
        assert!(before.iter().zip(&after).all(|((na, a), (nb, b))| na == nb && a.equal(b)), "nothing copied");
        // Another architecture's file is refused by name.
        let other = build(&windowed(4, &[16]), &[16, 3]);
        let other_path = dir.path().join("other.safetensors");
        other.save(&other_path).expect("save");
        assert!(invalid_message(target.load_weights(&other_path)).contains("missing tensor(s)"));
        assert!(matches!(target.load_weights(&dir.path().join("absent")), Err(Error::Internal(_))));
    }

    #[test]
    fn reward_net_is_send() {
        fn send<T: Send>() {}
        send::<RewardNet>();
    }

    #[test]
    fn reward_paper_sizes_run() {
        // Walker2d-sized value function and an SD-latent-sized encoder: forward and grad run.
        for (arch, shape) in [
            (value_function(&[64, 64, 128, 128]), vec![32i64, 23]),
            (conv_encoder(&[32, 64, 128, 256]), vec![4, 32, 32]),
        ] {
            let net = build(&arch, &shape);
            let (x, t) = inputs(&net, 2, Kind::Float);
            let (rho, grad) = net.grad(&x, &t).expect("grad");
            assert_eq!(rho.size(), [2]);
            assert_eq!(grad.size(), x.size());
            assert!(grad.isfinite().all().int64_value(&[]) == 1);
        }
    }
}
