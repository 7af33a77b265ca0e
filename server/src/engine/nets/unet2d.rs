//! A 2D U-Net denoiser for image-like samples [B, C, H, W], laid out exactly as diffusers'
//! `UNet2DModel` (`diffusers/models/unets/unet_2d.py`) with `DownBlock2D` / `UpBlock2D` levels,
//! `AttnDownBlock2D` / `AttnUpBlock2D` at the lowest resolution when attention is on, and the
//! `UNetMidBlock2D`. Parameter names are diffusers' state-dict keys, so a `UNet2DModel` of the
//! same configuration loads these weights with `load_state_dict(strict=True)` and the other way
//! round (`relreward_dev.unet2d`, driven by `tests/python/unet2d_reference.py`, checks forward
//! passes and a training step).
//!
//! Structure, for widths w = block_out_channels and L = len(w) levels:
//! - `time_proj`: sinusoidal(w[0]) with cos first (`flip_sin_to_cos`, frequency shift 0), then
//!   `time_embedding.linear_1` (w[0] -> 4 w[0]), SiLU, `time_embedding.linear_2` (4 w[0] -> 4 w[0]);
//! - conditional models only, `class_embedding`: an nn.Embedding(rows, 4 w[0]) whose row for
//!   each item's label is added to the time embedding (diffusers' `num_class_embeds`), or the
//!   item's embedding vector of width 4 w[0] added as it is (`class_embed_type = "identity"`,
//!   no parameters);
//! - `conv_in`: Conv2d(C, w[0], 3, padding 1);
//! - `down_blocks.{i}`: `layers_per_block` ResNet blocks (`resnets.{j}`), each followed by
//!   attention (`attentions.{j}`) on the last level when attention is on; every output is kept
//!   as a skip; `downsamplers.0.conv` (Conv2d 3x3, stride 2) except on the last level, whose
//!   output is a skip too;
//! - `mid_block`: `resnets.0`, `attentions.0` (when attention is on), `resnets.1`;
//! - `up_blocks.{i}` over the levels reversed: `layers_per_block + 1` ResNet blocks, each on the
//!   concatenation with the most recent skip, attention after each on the first (lowest) level
//!   when on, then `upsamplers.0.conv` (nearest x2, Conv2d 3x3) except on the last;
//! - `conv_norm_out` (GroupNorm), SiLU, `conv_out` (Conv2d(w[0], C, 3, padding 1)).
//!
//! A ResNet block (`ResnetBlock2D`, pre-norm): h = conv1(silu(norm1(x))) + time_emb_proj(silu(emb));
//! h = conv2(silu(norm2(h))); out = shortcut(x) + h, with a 1x1 `conv_shortcut` when the widths
//! differ. Attention (`Attention` with `group_norm`, `residual_connection`): multi-head
//! self-attention over the H x W positions of the group-normalised input, heads = width /
//! `attention_head_dim`, plus the input. Every GroupNorm has `norm_num_groups` groups and eps 1e-5.

use tch::nn::{Init, Path};
use tch::{Kind, Tensor};

use super::blocks::{GroupNorm, Linear, linear_params, torch_default_init, total};
use super::weights::first_values;
use crate::error::{Error, Result};

/// Levels beyond this would need images of 2^15 pixels a side and more.
pub const MAX_LEVELS: usize = 16;
/// Upper bound on any width and on layers per block, far above practical networks; it keeps
/// the width arithmetic inside i64. The parameter budget of the caller is the real guard.
pub const MAX_WIDTH: i64 = 1 << 20;
pub const MAX_LAYERS_PER_BLOCK: i64 = 64;

/// The hyperparameters, in diffusers' names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Unet2dConfig {
    /// Channels of the image (in and out).
    pub channels: i64,
    pub height: i64,
    pub width: i64,
    pub block_out_channels: Vec<i64>,
    pub layers_per_block: i64,
    /// Attention at the lowest resolution: the last down block, the mid block, the first up block.
    pub attention: bool,
    pub norm_num_groups: i64,
    pub attention_head_dim: i64,
    /// Conditional models: how the condition enters the time embedding.
    pub class_embedding: Option<ClassEmbedding>,
}

/// How a conditional unet2d takes its condition (diffusers' `class_embed_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClassEmbedding {
    /// Labels through an nn.Embedding of `rows` rows (`num_class_embeds`).
    Table { rows: i64 },
    /// Vectors of width `dim` added as they are (`"identity"`); dim must be 4 w[0].
    Identity { dim: i64 },
}

impl Unet2dConfig {
    /// Checks the hyperparameters; errors name the manifest field at fault.
    pub fn validate(&self) -> Result<()> {
        let w = &self.block_out_channels;
        if self.channels <= 0 || self.channels > MAX_WIDTH {
            return Err(Error::invalid(format!("space.shape: {} channels must be in 1..={MAX_WIDTH}", self.channels)));
        }
        if w.is_empty() || w.len() > MAX_LEVELS || w.iter().any(|&c| c <= 0 || c > MAX_WIDTH) {
            return Err(Error::invalid(format!(
                "architecture.block_out_channels: {w:?} must hold 1 to {MAX_LEVELS} widths in 1..={MAX_WIDTH}"
            )));
        }
        if self.layers_per_block <= 0 || self.layers_per_block > MAX_LAYERS_PER_BLOCK {
            return Err(Error::invalid(format!(
                "architecture.layers_per_block: {} must be in 1..={MAX_LAYERS_PER_BLOCK}",
                self.layers_per_block
            )));
        }
        let g = self.norm_num_groups;
        if g <= 0 || w.iter().any(|&c| c % g != 0) {
            return Err(Error::invalid(format!(
                "architecture.norm_num_groups: {g} must be positive and divide every width of block_out_channels {w:?}"
            )));
        }
        if w[0] % 2 != 0 || w[0] < 4 {
            return Err(Error::invalid(format!(
                "architecture.block_out_channels: the first width {} must be even and at least 4 (it is the sinusoidal time embedding's size)",
                w[0]
            )));
        }
        if self.attention {
            let deepest = w[w.len() - 1];
            let d = self.attention_head_dim;
            if d <= 0 || deepest % d != 0 {
                return Err(Error::invalid(format!(
                    "architecture.attention_head_dim: {d} must be positive and divide the deepest width {deepest}"
                )));
            }
        }
        match self.class_embedding {
            Some(ClassEmbedding::Table { rows }) if rows <= 0 || rows > MAX_WIDTH => {
                return Err(Error::invalid(format!(
                    "conditioning.labels.num_classes: {rows} must be in 1..={MAX_WIDTH}"
                )));
            }
            Some(ClassEmbedding::Identity { dim }) if dim != 4 * w[0] => {
                return Err(Error::invalid(format!(
                    "conditioning.embedding.dim: {dim} must equal the time embedding's width 4 * block_out_channels[0] = {} \
                     (the embedding is added to it as it is, diffusers' class_embed_type \"identity\")",
                    4 * w[0]
                )));
            }
            _ => {}
        }
        let factor = 1i64 << (w.len() - 1);
        for (size, name) in [(self.height, "height"), (self.width, "width")] {
            if size <= 0 || size % factor != 0 {
                return Err(Error::invalid(format!(
                    "space.shape: {name} {size} must be a positive multiple of 2^(levels - 1) = {factor} for block_out_channels {w:?}"
                )));
            }
        }
        Ok(())
    }

    /// Number of parameters, computed without allocating; call after [`Self::validate`].
    pub fn params(&self) -> u128 {
        let w = &self.block_out_channels;
        let temb = 4 * w[0];
        let layers = self.layers_per_block;
        let levels = w.len();
        let attn = |c: i64| if self.attention { attention_params(c) } else { 0 };
        let mut parts = vec![linear_params(w[0], temb), linear_params(temb, temb), conv_params(self.channels, w[0], 3)];
        if let Some(ClassEmbedding::Table { rows }) = self.class_embedding {
            parts.push(n(rows) * n(temb));
        }
        let mut out = w[0];
        for (i, &width) in w.iter().enumerate() {
            let input = out;
            out = width;
            let last = i + 1 == levels;
            for j in 0..layers {
                parts.push(resnet_params(if j == 0 { input } else { out }, out, temb));
                if last {
                    parts.push(attn(out));
                }
            }
            if !last {
                parts.push(conv_params(out, out, 3));
            }
        }
        let deepest = w[levels - 1];
        parts.push(2 * resnet_params(deepest, deepest, temb));
        parts.push(attn(deepest));
        let reversed: Vec<i64> = w.iter().rev().copied().collect();
        let mut out = reversed[0];
        for i in 0..levels {
            let prev = out;
            out = reversed[i];
            let input = reversed[(i + 1).min(levels - 1)];
            for j in 0..=layers {
                let skip = if j == layers { input } else { out };
                let resnet_in = if j == 0 { prev } else { out };
                parts.push(resnet_params(resnet_in + skip, out, temb));
                if i == 0 {
                    parts.push(attn(out));
                }
            }
            if i + 1 < levels {
                parts.push(conv_params(out, out, 3));
            }
        }
        parts.push(2 * n(w[0]));
        parts.push(conv_params(w[0], self.channels, 3));
        total(&parts)
    }
}

fn n(x: i64) -> u128 {
    u128::try_from(x.max(0)).unwrap_or(0)
}

/// Parameters of `Conv2d(in, out, k)`.
fn conv_params(in_channels: i64, out_channels: i64, kernel: i64) -> u128 {
    n(in_channels)
        .saturating_mul(n(out_channels))
        .saturating_mul(n(kernel))
        .saturating_mul(n(kernel))
        .saturating_add(n(out_channels))
}

fn resnet_params(in_channels: i64, out_channels: i64, temb: i64) -> u128 {
    let shortcut = if in_channels == out_channels { 0 } else { conv_params(in_channels, out_channels, 1) };
    total(&[
        2 * n(in_channels),
        conv_params(in_channels, out_channels, 3),
        linear_params(temb, out_channels),
        2 * n(out_channels),
        conv_params(out_channels, out_channels, 3),
        shortcut,
    ])
}

fn attention_params(channels: i64) -> u128 {
    total(&[2 * n(channels), 4 * linear_params(channels, channels)])
}

/// `nn.Conv2d(in, out, k, stride, padding)` with PyTorch's default initialisation
/// (U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weights and biases).
#[derive(Debug)]
struct Conv2d {
    weight: Tensor,
    bias: Tensor,
    stride: i64,
    padding: i64,
}

impl Conv2d {
    fn new(p: &Path, in_channels: i64, out_channels: i64, kernel: i64, stride: i64, padding: i64) -> Result<Self> {
        let init = torch_default_init(in_channels * kernel * kernel);
        Ok(Self {
            weight: p.f_var("weight", &[out_channels, in_channels, kernel, kernel], init)?,
            bias: p.f_var("bias", &[out_channels], init)?,
            stride,
            padding,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_conv2d(&self.weight, Some(&self.bias), [self.stride], [self.padding], [1], 1)?)
    }
}

/// diffusers' `ResnetBlock2D` (pre-norm, time embedding added after the first convolution).
#[derive(Debug)]
struct ResnetBlock {
    norm1: GroupNorm,
    conv1: Conv2d,
    time_emb_proj: Linear,
    norm2: GroupNorm,
    conv2: Conv2d,
    conv_shortcut: Option<Conv2d>,
}

impl ResnetBlock {
    fn new(p: &Path, in_channels: i64, out_channels: i64, temb: i64, groups: i64) -> Result<Self> {
        Ok(Self {
            norm1: GroupNorm::new(&(p / "norm1"), groups, in_channels)?,
            conv1: Conv2d::new(&(p / "conv1"), in_channels, out_channels, 3, 1, 1)?,
            time_emb_proj: Linear::new(&(p / "time_emb_proj"), temb, out_channels)?,
            norm2: GroupNorm::new(&(p / "norm2"), groups, out_channels)?,
            conv2: Conv2d::new(&(p / "conv2"), out_channels, out_channels, 3, 1, 1)?,
            conv_shortcut: if in_channels == out_channels {
                None
            } else {
                Some(Conv2d::new(&(p / "conv_shortcut"), in_channels, out_channels, 1, 1, 0)?)
            },
        })
    }

    /// `x`: [B, in, H, W]; `emb_act`: silu(time embedding) [B, temb] (computed once per forward,
    /// where diffusers recomputes it in every block: the same values).
    fn forward(&self, x: &Tensor, emb_act: &Tensor) -> Result<Tensor> {
        let h = self.conv1.forward(&self.norm1.forward(x)?.f_silu()?)?;
        let time = self.time_emb_proj.forward(emb_act)?.f_unsqueeze(-1)?.f_unsqueeze(-1)?;
        let h = self.conv2.forward(&self.norm2.forward(&h.f_add(&time)?)?.f_silu()?)?;
        let shortcut = match &self.conv_shortcut {
            Some(conv) => conv.forward(x)?,
            None => x.shallow_clone(),
        };
        Ok(shortcut.f_add(&h)?)
    }
}

/// diffusers' `Attention` as its 2D blocks build it: GroupNorm, q/k/v projections, scaled
/// dot-product attention per head over the H x W positions, `to_out.0`, plus the input.
#[derive(Debug)]
struct Attention {
    group_norm: GroupNorm,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: i64,
    head_dim: i64,
}

impl Attention {
    fn new(p: &Path, channels: i64, head_dim: i64, groups: i64) -> Result<Self> {
        Ok(Self {
            group_norm: GroupNorm::new(&(p / "group_norm"), groups, channels)?,
            to_q: Linear::new(&(p / "to_q"), channels, channels)?,
            to_k: Linear::new(&(p / "to_k"), channels, channels)?,
            to_v: Linear::new(&(p / "to_v"), channels, channels)?,
            to_out: Linear::new(&(p / "to_out" / "0"), channels, channels)?,
            heads: channels / head_dim,
            head_dim,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        // No size here names the batch (flatten and unflatten keep it), so a traced export of
        // the net (`engine::export`) serves any batch size.
        let size = x.size();
        // [B, HW, C]: one token per position.
        let h = self.group_norm.forward(x)?.f_flatten(2, 3)?.f_transpose(1, 2)?;
        let split =
            |t: Tensor| -> Result<Tensor> { Ok(t.f_unflatten(2, [self.heads, self.head_dim])?.f_transpose(1, 2)?) };
        let q = split(self.to_q.forward(&h)?)?;
        let k = split(self.to_k.forward(&h)?)?;
        let v = split(self.to_v.forward(&h)?)?;
        let scores = q.f_matmul(&k.f_transpose(-1, -2)?)?.f_mul_scalar(1.0 / (self.head_dim as f64).sqrt())?;
        let attended = scores.f_softmax(-1, Kind::Float)?.f_matmul(&v)?;
        let merged = attended.f_transpose(1, 2)?.f_flatten(2, 3)?;
        let out = self.to_out.forward(&merged)?.f_transpose(1, 2)?.f_unflatten(2, [size[2], size[3]])?;
        Ok(out.f_add(x)?)
    }
}

#[derive(Debug)]
struct Level {
    resnets: Vec<ResnetBlock>,
    attentions: Vec<Attention>,
    /// Downsampler (stride-2 conv) on the way down, upsampler (nearest x2 then conv) on the way up.
    resample: Option<Conv2d>,
}

#[derive(Debug)]
pub struct Unet2d {
    config: Unet2dConfig,
    linear_1: Linear,
    linear_2: Linear,
    /// `class_embedding.weight` [rows, 4 w[0]] of a label-conditional model.
    class_table: Option<Tensor>,
    conv_in: Conv2d,
    downs: Vec<Level>,
    mid_resnets: [ResnetBlock; 2],
    mid_attention: Option<Attention>,
    ups: Vec<Level>,
    conv_norm_out: GroupNorm,
    conv_out: Conv2d,
}

impl Unet2d {
    /// Registers the parameters under `p` (the root of the model's `VarStore`, for weights that
    /// load in diffusers as `UNet2DModel.state_dict()`).
    pub fn new(p: &Path, config: &Unet2dConfig) -> Result<Self> {
        config.validate()?;
        let w = &config.block_out_channels;
        let (levels, layers, groups) = (w.len(), config.layers_per_block, config.norm_num_groups);
        let temb = 4 * w[0];
        let attention = |path: Path, c: i64| Attention::new(&path, c, config.attention_head_dim, groups);

        let mut downs = Vec::with_capacity(levels);
        let mut out = w[0];
        for (i, &width) in w.iter().enumerate() {
            let (input, last) = (out, i + 1 == levels);
            out = width;
            let block = p / "down_blocks" / i;
            let mut level = Level { resnets: Vec::new(), attentions: Vec::new(), resample: None };
            for j in 0..layers {
                let resnet_in = if j == 0 { input } else { out };
                level.resnets.push(ResnetBlock::new(&(&block / "resnets" / j), resnet_in, out, temb, groups)?);
                if last && config.attention {
                    level.attentions.push(attention(&block / "attentions" / j, out)?);
                }
            }
            if !last {
                level.resample = Some(Conv2d::new(&(&block / "downsamplers" / 0 / "conv"), out, out, 3, 2, 1)?);
            }
            downs.push(level);
        }
        let deepest = w[levels - 1];
        let mid = p / "mid_block";
        let mid_resnets = [
            ResnetBlock::new(&(&mid / "resnets" / 0), deepest, deepest, temb, groups)?,
            ResnetBlock::new(&(&mid / "resnets" / 1), deepest, deepest, temb, groups)?,
        ];
        let mid_attention = if config.attention { Some(attention(&mid / "attentions" / 0, deepest)?) } else { None };

        let reversed: Vec<i64> = w.iter().rev().copied().collect();
        let mut ups = Vec::with_capacity(levels);
        let mut out = reversed[0];
        for i in 0..levels {
            let prev = out;
            out = reversed[i];
            let input = reversed[(i + 1).min(levels - 1)];
            let block = p / "up_blocks" / i;
            let mut level = Level { resnets: Vec::new(), attentions: Vec::new(), resample: None };
            for j in 0..=layers {
                let skip = if j == layers { input } else { out };
                let resnet_in = if j == 0 { prev } else { out };
                level.resnets.push(ResnetBlock::new(&(&block / "resnets" / j), resnet_in + skip, out, temb, groups)?);
                if i == 0 && config.attention {
                    level.attentions.push(attention(&block / "attentions" / j, out)?);
                }
            }
            if i + 1 < levels {
                level.resample = Some(Conv2d::new(&(&block / "upsamplers" / 0 / "conv"), out, out, 3, 1, 1)?);
            }
            ups.push(level);
        }
        Ok(Self {
            config: config.clone(),
            linear_1: Linear::new(&(p / "time_embedding" / "linear_1"), w[0], temb)?,
            linear_2: Linear::new(&(p / "time_embedding" / "linear_2"), temb, temb)?,
            // nn.Embedding's own initialisation: N(0, 1).
            class_table: match config.class_embedding {
                Some(ClassEmbedding::Table { rows }) => Some((p / "class_embedding").f_var(
                    "weight",
                    &[rows, temb],
                    first_values(Init::Randn { mean: 0.0, stdev: 1.0 }),
                )?),
                _ => None,
            },
            conv_in: Conv2d::new(&(p / "conv_in"), config.channels, w[0], 3, 1, 1)?,
            downs,
            mid_resnets,
            mid_attention,
            ups,
            conv_norm_out: GroupNorm::new(&(p / "conv_norm_out"), groups, w[0])?,
            conv_out: Conv2d::new(&(p / "conv_out"), w[0], config.channels, 3, 1, 1)?,
        })
    }

    pub fn config(&self) -> &Unet2dConfig {
        &self.config
    }

    /// diffusers' `get_timestep_embedding(t, dim, flip_sin_to_cos=True, downscale_freq_shift=0)`:
    /// freqs = exp(-ln(10000) * arange(half) / half), emb = [cos(t freqs), sin(t freqs)].
    fn time_proj(&self, t: &Tensor) -> Result<Tensor> {
        let half = self.config.block_out_channels[0] / 2;
        let freqs =
            Tensor::f_arange(half, (Kind::Float, t.device()))?.f_mul_scalar(-(10000f64).ln() / half as f64)?.f_exp()?;
        let args = t.f_unsqueeze(1)?.f_mul(&freqs.f_unsqueeze(0)?)?;
        Ok(Tensor::f_cat(&[args.f_cos()?, args.f_sin()?], -1)?)
    }

    /// `x`: float [B, C, H, W]; `t`: float [B] (the diffusion step); `cond`: a conditional
    /// model's int64 labels [B] or float embeddings [B, 4 w[0]] (checked by the caller).
    /// Returns [B, C, H, W].
    pub fn forward(&self, x: &Tensor, t: &Tensor, cond: Option<&Tensor>) -> Result<Tensor> {
        let mut emb = self.linear_2.forward(&self.linear_1.forward(&self.time_proj(t)?)?.f_silu()?)?;
        match (self.config.class_embedding, cond) {
            (None, None) => {}
            (Some(ClassEmbedding::Table { .. }), Some(labels)) => {
                let table = self.class_table.as_ref().ok_or_else(|| Error::internal("Unet2d", "no class table"))?;
                emb = emb.f_add(&table.f_index_select(0, labels)?)?;
            }
            (Some(ClassEmbedding::Identity { .. }), Some(vectors)) => emb = emb.f_add(vectors)?,
            _ => return Err(Error::invalid("denoiser condition: does not match the network's conditioning")),
        }
        // Every ResNet block applies SiLU to the embedding before its projection.
        let emb_act = emb.f_silu()?;
        let mut h = self.conv_in.forward(x)?;
        let mut skips = vec![h.shallow_clone()];
        for level in &self.downs {
            for (j, resnet) in level.resnets.iter().enumerate() {
                h = resnet.forward(&h, &emb_act)?;
                if let Some(attention) = level.attentions.get(j) {
                    h = attention.forward(&h)?;
                }
                skips.push(h.shallow_clone());
            }
            if let Some(down) = &level.resample {
                h = down.forward(&h)?;
                skips.push(h.shallow_clone());
            }
        }
        h = self.mid_resnets[0].forward(&h, &emb_act)?;
        if let Some(attention) = &self.mid_attention {
            h = attention.forward(&h)?;
        }
        h = self.mid_resnets[1].forward(&h, &emb_act)?;
        for level in &self.ups {
            for (j, resnet) in level.resnets.iter().enumerate() {
                let skip =
                    skips.pop().ok_or_else(|| Error::internal("Unet2d", "more up blocks than skip connections"))?;
                h = resnet.forward(&Tensor::f_cat(&[&h, &skip], 1)?, &emb_act)?;
                if let Some(attention) = level.attentions.get(j) {
                    h = attention.forward(&h)?;
                }
            }
            if let Some(up) = &level.resample {
                let size = h.size();
                let upsampled = h.f_upsample_nearest2d([size[2] * 2, size[3] * 2], Some(2.0), Some(2.0))?;
                h = up.forward(&upsampled)?;
            }
        }
        self.conv_out.forward(&self.conv_norm_out.forward(&h)?.f_silu()?)
    }
}

#[cfg(test)]
mod tests {
    use tch::Device;
    use tch::nn::VarStore;

    use super::*;

    fn config(widths: &[i64], attention: bool) -> Unet2dConfig {
        Unet2dConfig {
            channels: 1,
            height: 8,
            width: 8,
            block_out_channels: widths.to_vec(),
            layers_per_block: 2,
            attention,
            norm_num_groups: 8,
            attention_head_dim: 8,
            class_embedding: None,
        }
    }

    #[test]
    fn unet2d_planned_parameters_equal_the_built_ones_and_shapes_are_kept() {
        for (widths, attention) in [(vec![16, 32], true), (vec![8, 16, 16], false), (vec![16], true)] {
            let c = config(&widths, attention);
            let vs = VarStore::new(Device::Cpu);
            let net = Unet2d::new(&vs.root(), &c).expect("builds");
            let built: i64 = vs.variables().values().map(Tensor::numel).map(|n| n as i64).sum();
            assert_eq!(u128::from(built as u64), c.params(), "{c:?}");
            let x = Tensor::randn([3, 1, 8, 8], (Kind::Float, Device::Cpu));
            let y = net.forward(&x, &Tensor::from_slice(&[0f32, 5.0, 49.0]), None).expect("forward");
            assert_eq!(y.size(), x.size());
        }
    }

    #[test]
    fn unet2d_invalid_configurations_name_the_field() {
        let mut cases: Vec<(Unet2dConfig, &str)> = Vec::new();
        let base = config(&[16, 32], true);
        cases.push((Unet2dConfig { block_out_channels: vec![], ..base.clone() }, "architecture.block_out_channels"));
        cases.push((
            Unet2dConfig { block_out_channels: vec![16, 0], ..base.clone() },
            "architecture.block_out_channels",
        ));
        cases.push((Unet2dConfig { layers_per_block: 0, ..base.clone() }, "architecture.layers_per_block"));
        cases.push((Unet2dConfig { norm_num_groups: 5, ..base.clone() }, "architecture.norm_num_groups"));
        cases.push((Unet2dConfig { norm_num_groups: 0, ..base.clone() }, "architecture.norm_num_groups"));
        cases.push((Unet2dConfig { attention_head_dim: 5, ..base.clone() }, "architecture.attention_head_dim"));
        cases.push((Unet2dConfig { height: 7, ..base.clone() }, "space.shape: height 7"));
        cases.push((Unet2dConfig { width: 0, ..base.clone() }, "space.shape: width 0"));
        cases.push((Unet2dConfig { channels: 0, ..base.clone() }, "space.shape"));
        cases.push((
            Unet2dConfig { block_out_channels: vec![2, 16], norm_num_groups: 2, ..base.clone() },
            "architecture.block_out_channels: the first width 2",
        ));
        for (c, needle) in cases {
            match c.validate() {
                Err(Error::InvalidArgument(msg)) => assert!(msg.contains(needle), "{msg} should contain {needle}"),
                other => panic!("{c:?}: expected InvalidArgument, got {other:?}"),
            }
        }
        // Attention off: the head size is not checked.
        assert!(Unet2dConfig { attention: false, attention_head_dim: 5, ..base }.validate().is_ok());
    }
}
