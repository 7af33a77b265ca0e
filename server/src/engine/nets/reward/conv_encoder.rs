//! `conv_encoder { widths }` (image-like latents), item [C, H, W]: d = widths[0]; per width
//! w_i, `blocks.{i}`: h = Mish(GroupNorm(8)(Conv2d(3x3, stride 2, padding 1)(h))) + Linear(d,
//! w_i)(Mish(t_emb)) broadcast over the pixels (`blocks.{i}.conv.*`, `blocks.{i}.norm.*`,
//! `blocks.{i}.time_mlp.1.*`: the time embedding is projected and added per block, as in
//! Diffuser's residual blocks); then global average pooling to [B, w], concatenation with the
//! time embedding and `final_block = Sequential(Linear(w + d, w / 2), Mish, Linear(w / 2, 1))`.
//! Any H, W >= 1 (each stride-2 convolution maps n to ceil(n / 2)).

use tch::nn;
use tch::{Kind, Tensor};

use super::checks::{count, shape_text, validate_widths};
use super::second_order::{AlignmentTerms, TimeSweep, top_forward, top_second_backward, top_tangent};
use crate::engine::nets::blocks::second_order::{
    GroupNormTangent, NormMishAdjoints, NormMishPass, ParamGrads, conv_param_grads,
};
use crate::engine::nets::blocks::{
    GROUPS, GroupNorm, Linear, Mish, NormMishTape, TimeMlp, conv_params, linear_params, torch_default_init, total,
};
use crate::error::{Error, Result};

/// The encoder's hyperparameters: the item's channels and one width per stride-2 block.
#[derive(Debug, Clone)]
pub(super) struct ConvEncoderPlan {
    channels: i64,
    widths: Vec<i64>,
}

impl ConvEncoderPlan {
    pub(super) fn new(item_shape: &[i64], widths: &[usize]) -> Result<Self> {
        let &[channels, _, _] = item_shape else {
            return Err(Error::invalid(format!(
                "architecture: conv_encoder needs an image-like item shape [channels, height, width], got [{}]",
                shape_text(item_shape)
            )));
        };
        Ok(Self { channels, widths: validate_widths(widths)? })
    }

    pub(super) fn params(&self) -> u128 {
        ConvEncoderNet::params(self.channels, &self.widths)
    }

    pub(super) fn build(&self, root: &nn::Path) -> Result<ConvEncoderNet> {
        ConvEncoderNet::new(root, self.channels, &self.widths)
    }
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

    /// d sum(g * forward(x)) / dx for an input of height and width `input_hw`: the transposed
    /// convolution, its output padding restoring what the stride rounded away.
    fn input_backward(&self, g: &Tensor, input_hw: [i64; 2]) -> Result<Tensor> {
        let size = g.size();
        let padding = |input: i64, output: i64| input - ((output - 1) * 2 - 2 + 3);
        let output_padding = [padding(input_hw[0], size[2]), padding(input_hw[1], size[3])];
        Ok(g.f_conv_transpose2d(&self.weight, None::<&Tensor>, [2, 2], [1, 1], output_padding, 1, [1, 1])?)
    }

    /// ẏ = W * ẋ (`blocks::second_order`).
    fn tangent(&self, x_dot: &Tensor) -> Result<Tensor> {
        Ok(x_dot.f_conv2d(&self.weight, None::<&Tensor>, [2, 2], [1, 1], [1, 1], 1)?)
    }

    /// The reverse of (y, ẏ) (`blocks::second_order`): pushes dW and db, returns p_x.
    fn second_backward(
        &self,
        (x, x_dot): (&Tensor, &Tensor),
        g_y: &Tensor,
        p_y: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<Tensor> {
        conv_param_grads((&self.weight, &self.bias), (&[2, 2], &[1, 1]), (x, x_dot), (g_y, p_y), grads)?;
        let size = x.size();
        self.input_backward(p_y, [size[2], size[3]])
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

    /// [`EncoderBlock::forward`] with [`Mish::Fused`] (the value bit for bit) and its tape.
    fn forward_taped(&self, x: &Tensor, t_emb: &Tensor) -> Result<(Tensor, ([i64; 2], NormMishTape))> {
        let (h, epilogue) = self.norm.mish_forward_taped(&self.conv.forward(x)?)?;
        let time = self.time_linear.forward(&Mish::Fused.forward(t_emb)?)?.f_unsqueeze(-1)?.f_unsqueeze(-1)?;
        let size = x.size();
        Ok((h.f_add(&time)?, ([size[2], size[3]], epilogue)))
    }

    fn input_backward(&self, (input_hw, epilogue): &([i64; 2], NormMishTape), g: &Tensor) -> Result<Tensor> {
        self.conv.input_backward(&self.norm.mish_input_backward(epilogue, g)?, *input_hw)
    }

    /// The forward for the four sweeps of `blocks::second_order`; `time_act` is Mish(e).
    fn forward_second(&self, x: &Tensor, time_act: &Tensor) -> Result<(Tensor, EncoderPass)> {
        let (h, epilogue) = self.norm.mish_forward_second(&self.conv.forward(x)?)?;
        let time = self.time_linear.forward(time_act)?.f_unsqueeze(-1)?.f_unsqueeze(-1)?;
        Ok((h.f_add(&time)?, EncoderPass { input: x.shallow_clone(), epilogue }))
    }

    fn adjoints(&self, pass: &EncoderPass, g: &Tensor) -> Result<(Tensor, EncoderAdjoints)> {
        let (g_conv, epilogue) = self.norm.mish_adjoints(&pass.epilogue, g)?;
        let size = pass.input.size();
        Ok((self.conv.input_backward(&g_conv, [size[2], size[3]])?, EncoderAdjoints { g_conv, epilogue }))
    }

    fn tangent(&self, pass: &EncoderPass, x_dot: &Tensor) -> Result<(Tensor, EncoderTangents)> {
        let (h_dot, norm) = self.norm.mish_tangent(&pass.epilogue, &self.conv.tangent(x_dot)?)?;
        Ok((h_dot, EncoderTangents { input: x_dot.shallow_clone(), norm }))
    }

    /// The reverse from p (of the block's output): pushes the block's gradients, returns (p_x,
    /// the adjoint of Mish(e) from the time projection).
    fn second_backward(
        &self,
        (pass, adjoints, tangents): (&EncoderPass, &EncoderAdjoints, &EncoderTangents),
        p: &Tensor,
        time_act: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<(Tensor, Tensor)> {
        let p_time = p.f_sum_dim_intlist([2i64, 3].as_slice(), false, None::<Kind>)?;
        let p_time_act = self.time_linear.backward(time_act, &p_time, grads)?;
        let p_conv = self.norm.mish_second_backward(&pass.epilogue, &adjoints.epilogue, &tangents.norm, p, grads)?;
        let p_x = self.conv.second_backward((&pass.input, &tangents.input), &adjoints.g_conv, &p_conv, grads)?;
        Ok((p_x, p_time_act))
    }
}

/// What each sweep keeps of an [`EncoderBlock`].
struct EncoderPass {
    input: Tensor,
    epilogue: NormMishPass,
}

struct EncoderAdjoints {
    g_conv: Tensor,
    epilogue: NormMishAdjoints,
}

struct EncoderTangents {
    input: Tensor,
    norm: GroupNormTangent,
}

/// The strided convolutional encoder over images [B, C, H, W].
#[derive(Debug)]
pub(super) struct ConvEncoderNet {
    time_mlp: TimeMlp,
    blocks: Vec<EncoderBlock>,
    final_first: Linear,
    pub(super) final_second: Linear,
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
    pub(super) fn forward(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let t_emb = self.time_mlp.forward(t, mish)?;
        let mut h = x.shallow_clone();
        for block in &self.blocks {
            h = block.forward(&h, &t_emb, mish)?;
        }
        let pooled = h.f_mean_dim([2i64, 3].as_slice(), false, None::<Kind>)?;
        let out = self.final_first.forward(&Tensor::f_cat(&[&pooled, &t_emb], 1)?)?;
        Ok(self.final_second.forward(&mish.forward(&out)?)?.f_squeeze_dim(1)?)
    }

    /// (rho [B], d sum(rho) / dx [B, C, H, W]) by a hand-written backward, without autograd,
    /// as `ValueFunctionNet::value_and_grad`: rho is [`ConvEncoderNet::forward`]'s with
    /// [`Mish::Fused`] bit for bit, the gradient autograd's to float rounding (`tests.rs`).
    /// Call without a graph.
    pub(super) fn value_and_grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        let t_emb = self.time_mlp.forward(t, Mish::Fused)?;
        let mut h = x.shallow_clone();
        let mut tapes = Vec::with_capacity(self.blocks.len());
        for block in &self.blocks {
            let (next, tape) = block.forward_taped(&h, &t_emb)?;
            tapes.push(tape);
            h = next;
        }
        let pooled = h.f_mean_dim([2i64, 3].as_slice(), false, None::<Kind>)?;
        let pre = self.final_first.forward(&Tensor::f_cat(&[&pooled, &t_emb], 1)?)?;
        let (act, act_tape) = Mish::forward_taped(&pre)?;
        let rho = self.final_second.forward(&act)?.f_squeeze_dim(1)?;

        let g = act_tape.backward(&self.final_second.weight.f_expand_as(&act)?)?;
        let g = g.f_matmul(&self.final_first.weight.f_narrow(1, 0, pooled.size()[1])?)?;
        // The mean over the pixels spreads each channel's gradient evenly.
        let size = h.size();
        let pixels = (size[2] * size[3]) as f64;
        let mut g = g.f_div_scalar(pixels)?.f_unsqueeze(-1)?.f_unsqueeze(-1)?.f_expand(size.as_slice(), false)?;
        for (block, tape) in self.blocks.iter().zip(&tapes).rev() {
            g = block.input_backward(tape, &g)?;
        }
        Ok((rho, g))
    }

    /// The alignment loss and every parameter's gradient by the four sweeps of
    /// `blocks::second_order` (no autograd), as `ValueFunctionNet::alignment_grads`; the mean
    /// over the pixels is linear (its tangent the tangent's mean, its adjoints spread evenly).
    pub(super) fn alignment_grads(
        &self,
        x: &Tensor,
        t: &Tensor,
        terms: impl FnOnce(&Tensor, &Tensor) -> Result<AlignmentTerms>,
    ) -> Result<(Tensor, ParamGrads)> {
        let top_layers = (&self.final_first, &self.final_second);
        let mut time = TimeSweep::forward(&self.time_mlp, t)?;
        let pixels = [2i64, 3];
        let mean_pixels = |t: &Tensor| t.f_mean_dim(pixels.as_slice(), false, None::<Kind>);
        // 1. The forward.
        let mut passes = Vec::with_capacity(self.blocks.len());
        let mut h = x.shallow_clone();
        for block in &self.blocks {
            let (next, pass) = block.forward_second(&h, &time.act)?;
            passes.push(pass);
            h = next;
        }
        let size = h.size();
        let count = (size[2] * size[3]) as f64;
        let spread = |t: &Tensor| -> Result<Tensor> {
            Ok(t.f_div_scalar(count)?.f_unsqueeze(-1)?.f_unsqueeze(-1)?.f_expand(size.as_slice(), false)?)
        };
        let (rho, g_pooled, top) = top_forward(top_layers, &mean_pixels(&h)?, &time.e)?;
        // 2. The input backward.
        let mut g = spread(&g_pooled)?;
        let mut adjoints = Vec::with_capacity(self.blocks.len());
        for (block, pass) in self.blocks.iter().zip(&passes).rev() {
            let (below, adjoint) = block.adjoints(pass, &g)?;
            adjoints.push(adjoint);
            g = below;
        }
        adjoints.reverse();
        let AlignmentTerms { loss, r, p_rho } = terms(&rho, &g)?;
        // 3. The tangent along r.
        let mut h_dot = r;
        let mut tangents = Vec::with_capacity(self.blocks.len());
        for (block, pass) in self.blocks.iter().zip(&passes) {
            let (next, tangent) = block.tangent(pass, &h_dot)?;
            tangents.push(tangent);
            h_dot = next;
        }
        let top_dot = top_tangent(&self.final_first, &top, &mean_pixels(&h_dot)?)?;
        // 4. The reverse of the pairs.
        let mut grads = ParamGrads::new();
        let (p_pooled, p_e) = top_second_backward(top_layers, &top, &top_dot, p_rho.as_ref(), &mut grads)?;
        let mut p = spread(&p_pooled)?;
        for (((block, pass), adjoint), tangent) in self.blocks.iter().zip(&passes).zip(&adjoints).zip(&tangents).rev() {
            let (below, from_time) = block.second_backward((pass, adjoint, tangent), &p, &time.act, &mut grads)?;
            time.add_act_adjoint(from_time)?;
            p = below;
        }
        time.backward(&self.time_mlp, p_e, &mut grads)?;
        Ok((loss, grads))
    }
}
