//! Building blocks of the Diffuser family of networks (Janner et al., `diffuser/models/helpers.py`
//! and `temporal.py`), shared by the denoisers here and by the reward networks.
//!
//! Every block registers its parameters under the same names as the PyTorch module it mirrors
//! (`nn.Sequential` indices included), so a state dict saved as safetensors on either side loads
//! on the other. All forward passes use tch's fallible (`f_`) operations: a shape problem becomes
//! an [`Error`], never a panic inside a request.
//!
//! Parameter counts are also available *before* allocation (the `*_params` functions), so a
//! constructor can refuse an architecture whose weights would not fit in memory.
//!
//! Besides the forward passes: `*_taped` forwards and `input_backward`s (the input gradient
//! by hand, for serving the convolutional rewards), and in `second_order` the tangents and
//! second-order reverses their training takes.

use tch::nn::{Init, Path};
use tch::{Kind, Tensor};

use super::kernels::{self, MishParts};
use crate::error::{Error, Result};

pub mod second_order;

/// GroupNorm groups in every [`Conv1dBlock`] (Diffuser's `n_groups = 8`).
pub const GROUPS: i64 = 8;
/// PyTorch's `nn.GroupNorm` default epsilon.
pub const GROUP_NORM_EPS: f64 = 1e-5;
/// Kernel size of the convolutions inside Diffuser's residual temporal blocks.
pub const TEMPORAL_KERNEL: i64 = 5;

/// PyTorch's default for `Linear`, `Conv1d` and `ConvTranspose1d`: kaiming_uniform with
/// a = sqrt(5) for weights, which reduces to U(-1/sqrt(fan_in), 1/sqrt(fan_in)), and the same bound
/// for biases. Matching it keeps training behaviour comparable with the PyTorch originals
/// (tch's own defaults differ: zero conv biases, ReLU-gain Kaiming weights). Zeros instead,
/// nothing drawn, while a network is built to have its values replaced
/// ([`weights::first_values`](super::weights::first_values)).
pub fn torch_default_init(fan_in: i64) -> Init {
    let bound = 1.0 / (fan_in.max(1) as f64).sqrt();
    super::weights::first_values(Init::Uniform { lo: -bound, up: bound })
}

/// Mish, x * tanh(softplus(x)): Diffuser's activation everywhere (smooth, as the reward
/// existence theorem wants), in one of two forms with the same values and first derivative (to
/// float32 rounding on the CPU, where the first form takes a kernel of our own).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mish {
    /// For every pass differentiated at most once. On float32 CPU tensors, the hand-fused
    /// kernel (`kernels`, about 4x faster than libtorch's op and equal to it to float32
    /// rounding): its value where nothing needs a gradient, and where autograd records,
    /// `value + (x - x.detach()) slope` with value and slope from one kernel pass, whose forward
    /// is the value bit for bit and whose derivative is mish' (its second derivative is not
    /// Mish's: hence [`Mish::TwiceDifferentiable`]). So a pass gives the same numbers with or
    /// without a graph for finite inputs (rho served with its gradient equals rho scored
    /// alone; an infinite activation gives NaN under a graph). libtorch's
    /// fused op elsewhere (float64, a GPU).
    Fused,
    /// For a pass differentiated twice: a reward's input gradient with a graph, whose loss
    /// (Algorithm 1's, a function of grad_x rho) needs Mish's second derivative. libtorch's ops
    /// (its values equal [`Mish::Fused`]'s to float32 rounding, not bit for bit).
    /// libtorch's second derivative of Mish is NaN wherever the input exceeds about 88.7 (its
    /// double backward multiplies a zero gradient by exp(x), infinite there); a locomotion
    /// reward's last hidden layer got there after 2528 steps at lr 2e-4 and most later batches'
    /// gradients were NaN. Here inputs above [`MISH_PASS_THROUGH`] pass through unchanged: there
    /// mish(x) = x and mish'(x) = 1 exactly in float32, so values and first derivatives are
    /// libtorch's fused op's, bit for bit, and the second derivative is 0 instead of NaN.
    TwiceDifferentiable,
}

pub use super::kernels::MISH_PASS_THROUGH;

impl Mish {
    pub fn forward(self, x: &Tensor) -> Result<Tensor> {
        match self {
            Self::Fused => {
                if !x.requires_grad() {
                    if let Some(value) = kernels::mish(x)? {
                        return Ok(value);
                    }
                } else if let Some(parts) = kernels::mish_parts(x, false)? {
                    let tangent = x.f_sub(&x.f_detach()?)?.f_mul(&parts.slope)?;
                    return Ok(parts.value.f_add(&tangent)?);
                }
                Ok(x.f_mish()?)
            }
            Self::TwiceDifferentiable => {
                let below = x.f_clamp_max(MISH_PASS_THROUGH)?.f_mish()?;
                Ok(x.f_where_self(&x.f_gt(MISH_PASS_THROUGH)?, &below)?)
            }
        }
    }
}

/// What Mish's hand-written backward needs from a [`Mish::Fused`] pass: its slope where the
/// kernel ran (float32 on the CPU), else its input for libtorch's `mish_backward`.
#[derive(Debug)]
pub enum MishTape {
    Slope(Tensor),
    Input(Tensor),
}

impl Mish {
    /// [`Mish::Fused`]'s value (bit for bit) and its tape, for a pass differentiated by hand
    /// (the blocks' `forward_taped` and `input_backward`); no graph is recorded.
    pub fn forward_taped(x: &Tensor) -> Result<(Tensor, MishTape)> {
        if let Some(parts) = kernels::mish_parts(x, false)? {
            return Ok((parts.value, MishTape::Slope(parts.slope)));
        }
        Ok((x.f_mish()?, MishTape::Input(x.shallow_clone())))
    }
}

impl MishTape {
    /// g mish'(x).
    pub fn backward(&self, g: &Tensor) -> Result<Tensor> {
        match self {
            Self::Slope(slope) => Ok(g.f_mul(slope)?),
            Self::Input(x) => Ok(x.f_mish_backward(g)?),
        }
    }
}

/// mish(a) (bit for bit `Mish::Fused`'s), mish'(a) and, when asked, mish''(a): one fused loop
/// over a float32 CPU tensor (`nets::kernels`), libtorch's elementwise operations elsewhere
/// (float64, a GPU).
pub fn mish_parts(a: &Tensor, second: bool) -> Result<MishParts> {
    if let Some(parts) = kernels::mish_parts(a, second)? {
        return Ok(parts);
    }
    // One exp where softplus, tanh and sigmoid would take three transcendental passes: with
    // e = exp(a), tanh(softplus(a)) = n / w for n = e (e + 2) and w = n + 2, and
    // (1 - T^2) sigmoid(a) = 4 e (1 + e) / w^2. Above the pass-through the input is clamped for
    // e: there T rounds to 1 and the slope's correction to under 1e-16, as the training pass's
    // pass-through has them. In place where a temporary is ours.
    let e = a.f_clamp_max(MISH_PASS_THROUGH)?.f_exp_()?;
    let n = e.f_add_scalar(2.0)?.f_mul_(&e)?;
    let rw = n.f_add_scalar(2.0)?.f_reciprocal_()?;
    let tanh = n.f_mul(&rw)?;
    // k = (1 - T^2) sigmoid(a).
    let one_e = e.f_add_scalar(1.0)?;
    let k = e.f_mul(&one_e)?.f_mul_(&rw)?.f_mul_(&rw)?.f_mul_scalar_(4.0)?;
    // mish' = T + a k.
    let slope = a.f_mul(&k)?.f_add_(&tanh)?;
    let curvature = if second {
        // mish'' = k (2 + a (1 - sigmoid(a) (1 + 2 T))), sigmoid(a) = e / (1 + e).
        let sigmoid = e.f_div(&one_e)?;
        let mut inner = tanh.f_mul_scalar(-2.0)?.f_sub_scalar_(1.0)?.f_mul_(&sigmoid)?.f_add_scalar_(1.0)?;
        Some(inner.f_mul_(a)?.f_add_scalar_(2.0)?.f_mul_(&k)?)
    } else {
        None
    };
    Ok(MishParts { value: Mish::Fused.forward(a)?, slope, curvature })
}

/// `nn.Linear(in, out)`: parameters `weight` [out, in], `bias` [out].
#[derive(Debug)]
pub struct Linear {
    pub weight: Tensor,
    pub bias: Tensor,
}

impl Linear {
    pub fn new(p: &Path, in_features: i64, out_features: i64) -> Result<Self> {
        let init = torch_default_init(in_features);
        Ok(Self {
            weight: p.f_var("weight", &[out_features, in_features], init)?,
            bias: p.f_var("bias", &[out_features], init)?,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_linear(&self.weight, Some(&self.bias))?)
    }
}

/// `nn.Conv1d(in, out, kernel, stride, padding)`: `weight` [out, in, k], `bias` [out].
#[derive(Debug)]
pub struct Conv1d {
    pub weight: Tensor,
    pub bias: Tensor,
    stride: i64,
    padding: i64,
}

impl Conv1d {
    pub fn new(p: &Path, in_channels: i64, out_channels: i64, kernel: i64, stride: i64, padding: i64) -> Result<Self> {
        let init = torch_default_init(in_channels * kernel);
        Ok(Self {
            weight: p.f_var("weight", &[out_channels, in_channels, kernel], init)?,
            bias: p.f_var("bias", &[out_channels], init)?,
            stride,
            padding,
        })
    }

    /// `x`: [B, in, L] -> [B, out, L'].
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_conv1d(&self.weight, Some(&self.bias), [self.stride], [self.padding], [1], 1)?)
    }

    /// d sum(g * forward(x)) / dx for an input of length `input_len`: the transposed
    /// convolution with the same weight (the output padding restores the lengths a stride
    /// rounded away).
    pub fn input_backward(&self, g: &Tensor, input_len: i64) -> Result<Tensor> {
        let (kernel, out_len) = (self.weight.size()[2], g.size()[2]);
        let output_padding = input_len - ((out_len - 1) * self.stride - 2 * self.padding + kernel);
        Ok(g.f_conv_transpose1d(
            &self.weight,
            None::<&Tensor>,
            [self.stride],
            [self.padding],
            [output_padding],
            1,
            [1],
        )?)
    }
}

/// `nn.ConvTranspose1d(in, out, kernel, stride, padding)`: `weight` [in, out, k] (PyTorch's
/// layout for transposed convolutions), `bias` [out].
#[derive(Debug)]
pub struct ConvTranspose1d {
    pub weight: Tensor,
    pub bias: Tensor,
    stride: i64,
    padding: i64,
}

impl ConvTranspose1d {
    pub fn new(p: &Path, in_channels: i64, out_channels: i64, kernel: i64, stride: i64, padding: i64) -> Result<Self> {
        // PyTorch computes fan_in from weight.size(1) * k, i.e. out_channels * k here.
        let init = torch_default_init(out_channels * kernel);
        Ok(Self {
            weight: p.f_var("weight", &[in_channels, out_channels, kernel], init)?,
            bias: p.f_var("bias", &[out_channels], init)?,
            stride,
            padding,
        })
    }

    /// `x`: [B, in, L] -> [B, out, L'].
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_conv_transpose1d(&self.weight, Some(&self.bias), [self.stride], [self.padding], [0], 1, [1])?)
    }
}

/// `nn.GroupNorm(groups, channels)` with affine parameters `weight` (ones) and `bias` (zeros).
#[derive(Debug)]
pub struct GroupNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    groups: i64,
}

impl GroupNorm {
    pub fn new(p: &Path, groups: i64, channels: i64) -> Result<Self> {
        if groups <= 0 || channels % groups != 0 {
            return Err(Error::invalid(format!(
                "GroupNorm: {channels} channels are not divisible into {groups} groups"
            )));
        }
        Ok(Self {
            weight: p.f_var("weight", &[channels], Init::Const(1.0))?,
            bias: p.f_var("bias", &[channels], Init::Const(0.0))?,
            groups,
        })
    }

    /// `x`: [B, C, ...]. Normalizing [B, C, L] directly equals Diffuser's detour through
    /// [B, C, 1, L]: the statistics are per (sample, group) over all remaining elements.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_group_norm(self.groups, Some(&self.weight), Some(&self.bias), GROUP_NORM_EPS, true)?)
    }

    /// [`GroupNorm::forward`]'s value (bit for bit: `group_norm` is this same
    /// `native_group_norm`) and the statistics its input backward needs.
    pub fn forward_taped(&self, x: &Tensor) -> Result<(Tensor, GroupNormTape)> {
        let x = x.f_contiguous()?;
        let size = x.size();
        let (batch, channels) = (size[0], size[1]);
        let (y, mean, rstd) = x.f_native_group_norm(
            Some(&self.weight),
            Some(&self.bias),
            batch,
            channels,
            size[2..].iter().product(),
            self.groups,
            GROUP_NORM_EPS,
        )?;
        Ok((y, GroupNormTape { input: x, mean, rstd }))
    }

    /// d sum(g * forward(x)) / dx. Per (sample, group) with x^ = (x - mean) rstd and
    /// g^ = g weight: dx = rstd (g^ - mean(g^) - x^ mean(g^ x^)), means over the group.
    pub fn input_backward(&self, tape: &GroupNormTape, g: &Tensor) -> Result<Tensor> {
        let size = g.size();
        let mut channel_shape = vec![1, size[1]];
        channel_shape.resize(size.len(), 1);
        let grouped = [size[0], self.groups, -1];
        let g_hat = g.f_mul(&self.weight.f_view(channel_shape.as_slice())?)?.f_reshape(grouped)?;
        let mean = tape.mean.f_unsqueeze(-1)?;
        let rstd = tape.rstd.f_unsqueeze(-1)?;
        let x_hat = tape.input.f_reshape(grouped)?.f_sub(&mean)?.f_mul(&rstd)?;
        let last = [-1i64];
        let m1 = g_hat.f_mean_dim(last.as_slice(), true, None::<Kind>)?;
        let m2 = g_hat.f_mul(&x_hat)?.f_mean_dim(last.as_slice(), true, None::<Kind>)?;
        let dx = g_hat.f_sub(&m1)?.f_sub(&x_hat.f_mul(&m2)?)?.f_mul(&rstd)?;
        Ok(dx.f_reshape(size.as_slice())?)
    }

    /// Mish(GroupNorm(x)) with [`Mish::Fused`] (the value bit for bit) and its tape: the
    /// epilogue of Diffuser's convolution blocks and of the encoder's.
    pub fn mish_forward_taped(&self, x: &Tensor) -> Result<(Tensor, NormMishTape)> {
        let (normed, norm) = self.forward_taped(x)?;
        let (y, mish) = Mish::forward_taped(&normed)?;
        Ok((y, NormMishTape { norm, mish }))
    }

    /// d sum(g * mish(forward(x))) / dx: one kernel where Mish's slope is on the tape
    /// (`kernels::mish_group_norm_backward`), libtorch's operations otherwise.
    pub fn mish_input_backward(&self, tape: &NormMishTape, g: &Tensor) -> Result<Tensor> {
        match &tape.mish {
            MishTape::Slope(slope) => self.slope_input_backward(&tape.norm, slope, g),
            MishTape::Input(_) => self.input_backward(&tape.norm, &tape.mish.backward(g)?),
        }
    }

    /// d sum(g * y) / dx for y = mish(forward(x)) given Mish's slope: one kernel where it
    /// applies (`kernels::mish_group_norm_backward`), the input backward of `g * slope`
    /// otherwise. Serving's backward and training's adjoint sweep (`second_order`) both.
    pub fn slope_input_backward(&self, norm: &GroupNormTape, slope: &Tensor, g: &Tensor) -> Result<Tensor> {
        Ok(self.slope_input_backward_parts(norm, slope, g)?.0)
    }

    /// [`GroupNorm::slope_input_backward`], and `g * slope` where the libtorch path computed it
    /// (None where the kernel ran), for a caller that keeps that product too.
    pub fn slope_input_backward_parts(
        &self,
        norm: &GroupNormTape,
        slope: &Tensor,
        g: &Tensor,
    ) -> Result<(Tensor, Option<Tensor>)> {
        let stats = (&norm.mean, &norm.rstd);
        match kernels::mish_group_norm_backward(g, slope, &norm.input, stats, &self.weight, self.groups)? {
            Some(dx) => Ok((dx, None)),
            None => {
                let g_slope = g.f_mul(slope)?;
                Ok((self.input_backward(norm, &g_slope)?, Some(g_slope)))
            }
        }
    }
}

/// What [`GroupNorm::mish_input_backward`] needs from the forward.
#[derive(Debug)]
pub struct NormMishTape {
    norm: GroupNormTape,
    mish: MishTape,
}

/// What [`GroupNorm::input_backward`] needs from the forward.
#[derive(Debug)]
pub struct GroupNormTape {
    input: Tensor,
    mean: Tensor,
    rstd: Tensor,
}

/// Diffuser's `SinusoidalPosEmb(dim)`: for half = dim / 2, freqs = exp(-arange(half) *
/// ln(10000) / (half - 1)); emb = [sin(t * freqs), cos(t * freqs)]. No parameters.
#[derive(Debug, Clone, Copy)]
pub struct SinusoidalPosEmb {
    dim: i64,
}

impl SinusoidalPosEmb {
    /// `dim` must be even (the output has 2 * (dim / 2) features) and at least 4 (the frequency
    /// step divides by half - 1).
    pub fn new(dim: i64) -> Result<Self> {
        if dim < 4 || dim % 2 != 0 {
            return Err(Error::invalid(format!("time embedding dim {dim} must be even and at least 4")));
        }
        Ok(Self { dim })
    }

    pub fn dim(&self) -> i64 {
        self.dim
    }

    /// `t`: float [B] -> [B, dim].
    pub fn forward(&self, t: &Tensor) -> Result<Tensor> {
        let half = self.dim / 2;
        let step = (10000f64).ln() / (half - 1) as f64;
        let freqs = Tensor::f_arange(half, (Kind::Float, t.device()))?.f_mul_scalar(-step)?.f_exp()?;
        let args = t.f_unsqueeze(1)?.f_mul(&freqs.f_unsqueeze(0)?)?;
        Ok(Tensor::f_cat(&[args.f_sin()?, args.f_cos()?], -1)?)
    }
}

/// Diffuser's time MLP `nn.Sequential(SinusoidalPosEmb(dim), Linear(dim, hidden), Mish,
/// Linear(hidden, out))`: parameters under `1.` and `3.` of its path.
#[derive(Debug)]
pub struct TimeMlp {
    emb: SinusoidalPosEmb,
    first: Linear,
    second: Linear,
}

impl TimeMlp {
    pub fn new(p: &Path, dim: i64, hidden: i64, out: i64) -> Result<Self> {
        Ok(Self {
            emb: SinusoidalPosEmb::new(dim)?,
            first: Linear::new(&(p / "1"), dim, hidden)?,
            second: Linear::new(&(p / "3"), hidden, out)?,
        })
    }

    pub fn params(dim: i64, hidden: i64, out: i64) -> u128 {
        total(&[linear_params(dim, hidden), linear_params(hidden, out)])
    }

    /// `t`: float [B] (diffusion step as a float) -> [B, out].
    pub fn forward(&self, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let h = self.first.forward(&self.emb.forward(t)?)?;
        self.second.forward(&mish.forward(&h)?)
    }
}

/// Diffuser's `Conv1dBlock`: `block = Sequential(Conv1d(in, out, k, padding = k / 2),
/// Rearrange, GroupNorm(8, out), Rearrange, Mish)`, hence parameters `block.0.*` and `block.2.*`.
#[derive(Debug)]
pub struct Conv1dBlock {
    conv: Conv1d,
    norm: GroupNorm,
}

impl Conv1dBlock {
    pub fn new(p: &Path, in_channels: i64, out_channels: i64, kernel: i64) -> Result<Self> {
        let block = p / "block";
        Ok(Self {
            conv: Conv1d::new(&(&block / "0"), in_channels, out_channels, kernel, 1, kernel / 2)?,
            norm: GroupNorm::new(&(&block / "2"), GROUPS, out_channels)?,
        })
    }

    pub fn params(in_channels: i64, out_channels: i64, kernel: i64) -> u128 {
        total(&[conv_params(in_channels, out_channels, kernel), n(out_channels), n(out_channels)])
    }

    /// `x`: [B, in, L] -> [B, out, L] (odd kernels keep the length).
    pub fn forward(&self, x: &Tensor, mish: Mish) -> Result<Tensor> {
        mish.forward(&self.norm.forward(&self.conv.forward(x)?)?)
    }

    /// [`Conv1dBlock::forward`] with [`Mish::Fused`] (the same value bit for bit) and what
    /// its input backward needs.
    pub fn forward_taped(&self, x: &Tensor) -> Result<(Tensor, Conv1dBlockTape)> {
        let (y, epilogue) = self.norm.mish_forward_taped(&self.conv.forward(x)?)?;
        Ok((y, Conv1dBlockTape { input_len: x.size()[2], epilogue }))
    }

    pub fn input_backward(&self, tape: &Conv1dBlockTape, g: &Tensor) -> Result<Tensor> {
        let g = self.norm.mish_input_backward(&tape.epilogue, g)?;
        self.conv.input_backward(&g, tape.input_len)
    }
}

#[derive(Debug)]
pub struct Conv1dBlockTape {
    input_len: i64,
    epilogue: NormMishTape,
}

/// Diffuser's `ResidualTemporalBlock(in, out, embed_dim, kernel_size)`:
/// out = blocks[1](blocks[0](x) + time_mlp(t)) + residual_conv(x), where time_mlp =
/// `Sequential(Mish, Linear(embed_dim, out), Rearrange)` (parameters `time_mlp.1.*`) is broadcast
/// over the horizon, and residual_conv is a 1x1 Conv1d only when the widths differ (identity,
/// without parameters, otherwise).
#[derive(Debug)]
pub struct ResidualTemporalBlock {
    blocks: [Conv1dBlock; 2],
    time_linear: Linear,
    residual_conv: Option<Conv1d>,
}

impl ResidualTemporalBlock {
    pub fn new(p: &Path, in_channels: i64, out_channels: i64, embed_dim: i64, kernel: i64) -> Result<Self> {
        let blocks = p / "blocks";
        Ok(Self {
            blocks: [
                Conv1dBlock::new(&(&blocks / "0"), in_channels, out_channels, kernel)?,
                Conv1dBlock::new(&(&blocks / "1"), out_channels, out_channels, kernel)?,
            ],
            time_linear: Linear::new(&(p / "time_mlp" / "1"), embed_dim, out_channels)?,
            residual_conv: if in_channels == out_channels {
                None
            } else {
                Some(Conv1d::new(&(p / "residual_conv"), in_channels, out_channels, 1, 1, 0)?)
            },
        })
    }

    pub fn params(in_channels: i64, out_channels: i64, embed_dim: i64, kernel: i64) -> u128 {
        let residual = if in_channels == out_channels { 0 } else { conv_params(in_channels, out_channels, 1) };
        total(&[
            Conv1dBlock::params(in_channels, out_channels, kernel),
            Conv1dBlock::params(out_channels, out_channels, kernel),
            linear_params(embed_dim, out_channels),
            residual,
        ])
    }

    /// `x`: [B, in, L], `t_emb`: [B, embed_dim] -> [B, out, L].
    pub fn forward(&self, x: &Tensor, t_emb: &Tensor, mish: Mish) -> Result<Tensor> {
        let time = self.time_linear.forward(&mish.forward(t_emb)?)?.f_unsqueeze(-1)?;
        let out = self.blocks[0].forward(x, mish)?.f_add(&time)?;
        let out = self.blocks[1].forward(&out, mish)?;
        match &self.residual_conv {
            Some(conv) => Ok(out.f_add(&conv.forward(x)?)?),
            None => Ok(out.f_add(x)?),
        }
    }

    /// [`ResidualTemporalBlock::forward`] with [`Mish::Fused`] (the same value bit for bit)
    /// and what its input backward needs (the time term does not depend on `x`).
    pub fn forward_taped(&self, x: &Tensor, t_emb: &Tensor) -> Result<(Tensor, ResidualTape)> {
        let time = self.time_linear.forward(&Mish::Fused.forward(t_emb)?)?.f_unsqueeze(-1)?;
        let (out, first) = self.blocks[0].forward_taped(x)?;
        let (out, second) = self.blocks[1].forward_taped(&out.f_add(&time)?)?;
        let out = match &self.residual_conv {
            Some(conv) => out.f_add(&conv.forward(x)?)?,
            None => out.f_add(x)?,
        };
        Ok((out, ResidualTape { first, second }))
    }

    pub fn input_backward(&self, tape: &ResidualTape, g: &Tensor) -> Result<Tensor> {
        let inner = self.blocks[1].input_backward(&tape.second, g)?;
        let through = self.blocks[0].input_backward(&tape.first, &inner)?;
        match &self.residual_conv {
            Some(conv) => Ok(through.f_add(&conv.input_backward(g, tape.first.input_len)?)?),
            None => Ok(through.f_add(g)?),
        }
    }
}

#[derive(Debug)]
pub struct ResidualTape {
    first: Conv1dBlockTape,
    second: Conv1dBlockTape,
}

/// Diffuser's `Downsample1d(dim)`: `conv = Conv1d(dim, dim, 3, stride 2, padding 1)`; halves an
/// even length.
#[derive(Debug)]
pub struct Downsample1d {
    conv: Conv1d,
}

impl Downsample1d {
    pub fn new(p: &Path, channels: i64) -> Result<Self> {
        Ok(Self { conv: Conv1d::new(&(p / "conv"), channels, channels, 3, 2, 1)? })
    }

    pub fn params(channels: i64) -> u128 {
        conv_params(channels, channels, 3)
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.conv.forward(x)
    }

    pub fn input_backward(&self, g: &Tensor, input_len: i64) -> Result<Tensor> {
        self.conv.input_backward(g, input_len)
    }
}

/// Diffuser's `Upsample1d(dim)`: `conv = ConvTranspose1d(dim, dim, 4, stride 2, padding 1)`;
/// doubles the length.
#[derive(Debug)]
pub struct Upsample1d {
    conv: ConvTranspose1d,
}

impl Upsample1d {
    pub fn new(p: &Path, channels: i64) -> Result<Self> {
        Ok(Self { conv: ConvTranspose1d::new(&(p / "conv"), channels, channels, 4, 2, 1)? })
    }

    pub fn params(channels: i64) -> u128 {
        // Same count as a Conv1d of the same widths and kernel.
        conv_params(channels, channels, 4)
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.conv.forward(x)
    }
}

/// Widening for parameter arithmetic: counts are computed in u128 so that absurd requested
/// sizes compare as large instead of overflowing.
fn n(x: i64) -> u128 {
    u128::try_from(x.max(0)).unwrap_or(0)
}

/// Saturating sum of parameter counts.
pub fn total(parts: &[u128]) -> u128 {
    parts.iter().fold(0u128, |acc, &x| acc.saturating_add(x))
}

/// Parameters of `Linear(in, out)`.
pub fn linear_params(in_features: i64, out_features: i64) -> u128 {
    n(in_features).saturating_mul(n(out_features)).saturating_add(n(out_features))
}

/// Parameters of `Conv1d(in, out, k)` (and of `ConvTranspose1d`).
pub fn conv_params(in_channels: i64, out_channels: i64, kernel: i64) -> u128 {
    n(in_channels).saturating_mul(n(out_channels)).saturating_mul(n(kernel)).saturating_add(n(out_channels))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (mish(x), mish'(x), mish''(x)) at every x (float32), by double backward through `f`.
    fn derivatives(f: impl Fn(&Tensor) -> Tensor, x: &[f32]) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let x = Tensor::from_slice(x).set_requires_grad(true);
        let y = f(&x);
        let first = Tensor::run_backward(&[y.sum(Kind::Float)], &[&x], true, true).remove(0);
        if first.requires_grad() {
            first.sum(Kind::Float).backward();
        }
        let grad = x.grad();
        let v = |t: &Tensor| Vec::<f32>::try_from(t.detach().contiguous()).expect("floats");
        (v(&y), v(&first), if grad.defined() { v(&grad) } else { vec![0.0; x.numel()] })
    }

    const POINTS: [f32; 16] =
        [-200.0, -90.0, -20.0, -3.0, -0.5, 0.0, 0.7, 5.0, 19.9, 20.0, 20.1, 60.0, 88.0, 89.0, 96.3, 1e4];

    #[test]
    fn the_fused_mish_is_libtorchs_to_float_rounding_with_or_without_a_graph() {
        let (libtorch, libtorch_first, _) = derivatives(|x| x.mish(), &POINTS);
        let (fused, fused_first, _) = derivatives(|x| Mish::Fused.forward(x).expect("mish"), &POINTS);
        let no_graph = Mish::Fused.forward(&Tensor::from_slice(&POINTS)).expect("mish");
        // The same values with and without a graph, bit for bit.
        assert_eq!(Vec::<f32>::try_from(no_graph).expect("floats"), fused);
        for i in 0..POINTS.len() {
            for (got, want, what) in [(fused[i], libtorch[i], "mish"), (fused_first[i], libtorch_first[i], "mish'")] {
                let tolerance = 2e-6 * want.abs().max(1.0);
                assert!((got - want).abs() <= tolerance, "{what}({}) = {got}, libtorch {want}", POINTS[i]);
            }
        }
    }

    #[test]
    fn the_twice_differentiable_mish_matches_the_fused_op_and_keeps_its_second_derivative_finite() {
        let x = POINTS;
        let (fused, fused_first, fused_second) = derivatives(|x| x.mish(), &x);
        let (twice, twice_first, twice_second) =
            derivatives(|x| Mish::TwiceDifferentiable.forward(x).expect("mish"), &x);
        // Values and first derivatives: libtorch's fused op's floats.
        assert_eq!(fused, twice);
        assert_eq!(fused_first, twice_first);
        // libtorch's own second derivative is NaN past exp's overflow (the bug worked around).
        assert!(fused_second[x.iter().position(|&v| v == 89.0).expect("89")].is_nan(), "{fused_second:?}");
        for (i, &xi) in x.iter().enumerate() {
            assert!(twice_second[i].is_finite(), "mish''({xi}) = {}", twice_second[i]);
            if f64::from(xi) <= MISH_PASS_THROUGH {
                assert_eq!(twice_second[i], fused_second[i], "mish''({xi})");
            } else {
                // The exact second derivative is below 1e-6 there.
                assert_eq!(twice_second[i], 0.0, "mish''({xi})");
            }
        }
    }
}
