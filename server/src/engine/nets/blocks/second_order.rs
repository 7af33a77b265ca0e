//! Reverse over forward through Diffuser's blocks (issue 38): every parameter's gradient of a
//! loss of a network's input gradient, without autograd's double backward, for the
//! convolutional rewards (`reward/value_function.rs`, `reward/conv_encoder.rs`; the MLP head's
//! version is `reward/closed_form.rs`, the same derivation for linear layers alone).
//!
//! A loss L(grad_x rho) with `r = dL / d grad` changes with the parameters as
//! `S = sum_b d rho_b(x + eps r) / d eps` does (r held fixed): the forward-mode derivative of
//! rho along r. So a pass runs four sweeps, keeping at every value v of the network:
//! 1. the forward: v itself (and what the layers' derivatives need: group-norm statistics,
//!    Mish's slope s = mish' and curvature q = mish'');
//! 2. the input backward: `g_v = d sum(rho) / dv` (the gradient the loss is a function of);
//! 3. the tangent, once r is known: `v̇ = dv(x + eps r) / d eps`, from `ẋ = r`;
//! 4. the reverse of the pair (v, v̇) from S: the tangent's adjoint is `g_v` again (the
//!    tangent pass is linear in ẋ with the forward's Jacobians, so its adjoint from
//!    S = sum rhȯ is the input backward's), and the value's adjoint `p_v = dS / dv` (from a
//!    loss term on rho itself at the top, zero otherwise) goes back with the parameters'
//!    gradients. Through `y = f(x; θ)` with `ẏ = J ẋ`:
//!    `p_x = J^T p_y + d <g_y, J ẋ> / dx` and `dθ = J_θ^T p_y + d <g_y, J ẋ> / dθ`.
//!
//! The rules per layer:
//! - a convolution (bias b, no other dependence on x): `ẏ = W * ẋ` (no bias),
//!   `p_x = W^T * p_y` (the transposed convolution of the input backward),
//!   `dW = wgrad(x, p_y) + wgrad(ẋ, g_y)` (one convolution over both pairs stacked along the
//!   batch, `conv_weight_grad`), `db = sum p_y`;
//! - Mish: `ẏ = s ẋ`, `p_x = s p_y + q ẋ g_y`;
//! - GroupNorm `y = γ x̂ + β` with `x̂ = (x - mean) rstd` per (sample, group) of M values:
//!   `x̂̇ = P(ẋ)` where `P(v) = rstd (v - mean(v) - x̂ mean(x̂ v))` (symmetric, so also the
//!   input backward's map), `ẏ = γ x̂̇`; with `u = γ g_y` (the adjoint of x̂̇) and the
//!   group means `A = mean(u ẋ_c)`, `B = mean(x̂ ẋ)`, `C = mean(u x̂)` (`v_c = v - mean(v)`):
//!   `p_x = P(γ p_y) + rstd² ((3 B C - A) x̂ - C ẋ_c - B u_c)` (the derivative of
//!   `<u, x̂̇>` along x, through rstd's and x̂'s dependence on x), `dγ = sum(p_y x̂ + g_y x̂̇)`,
//!   `dβ = sum p_y`;
//! - a term that does not depend on x (the time embedding's projection added per block):
//!   no tangent, its parameters take the ordinary backward of `p`.
//!
//! `reward/tests.rs` checks the whole against autograd's float64 double backward on every
//! convolutional architecture: 1e-10 in float64, 1e-5 in float32 (1e-4 where group norms see
//! groups of two values, ill-conditioned in float32 for autograd too);
//! `server/tests/reward_nets_vs_pytorch.rs` against PyTorch's.

use tch::{Kind, Tensor};

use super::{Conv1d, Conv1dBlock, Downsample1d, GroupNorm, GroupNormTape, ResidualTemporalBlock, mish_parts};
use crate::error::{Error, Result};

/// (parameter, d loss / d parameter) pairs, in no particular order.
pub type ParamGrads = Vec<(Tensor, Tensor)>;

/// Sums `t` over every dimension but the channels (dimension 1): a bias's gradient.
pub fn sum_but_channels(t: &Tensor) -> Result<Tensor> {
    let dims: Vec<i64> = (0..t.dim() as i64).filter(|&d| d != 1).collect();
    Ok(t.f_sum_dim_intlist(dims.as_slice(), false, None::<Kind>)?)
}

/// The weight's gradient of `sum(adjoint * conv(input))` summed over the pairs given, for a
/// convolution with `weight` [O, C, k...], `stride` and `padding` per spatial dimension (1 or
/// 2 of them): one convolution of the inputs, stacked along the batch, with the adjoints as
/// its kernel. With N the stacked batch, `dW[o, c, k] = sum_{n, j} g[n, o, j] x_pad[n, c, k +
/// s j]`: the inputs transposed to [C, N, ...] convolved with the adjoints transposed to
/// [O, N, ...], the stride as the dilation, cut to the kernel's size (a stride that does not
/// divide the padded length leaves extra positions at the end). oneDNN takes it as it takes
/// any convolution; im2col and a matrix product ran 1.7x to 2.7x slower
/// (`tests/bench/conv_weight_grad.py`).
fn conv_weight_grad(weight: &Tensor, stride: &[i64], padding: &[i64], pairs: &[(&Tensor, &Tensor)]) -> Result<Tensor> {
    let inputs: Vec<&Tensor> = pairs.iter().map(|(x, _)| *x).collect();
    let adjoints: Vec<&Tensor> = pairs.iter().map(|(_, g)| *g).collect();
    let x = Tensor::f_cat(&inputs, 0)?.f_transpose(0, 1)?;
    let g = Tensor::f_cat(&adjoints, 0)?.f_transpose(0, 1)?;
    let size = weight.size();
    let ones = vec![1i64; stride.len()];
    let mut dw = match stride.len() {
        1 => x.f_conv1d(&g, None::<&Tensor>, ones.as_slice(), padding, stride, 1)?,
        2 => x.f_conv2d(&g, None::<&Tensor>, ones.as_slice(), padding, stride, 1)?,
        n => return Err(Error::internal("convolution weight gradient", format!("{n} spatial dimensions"))),
    };
    for (dim, &k) in size[2..].iter().enumerate() {
        dw = dw.f_narrow(dim as i64 + 2, 0, k)?;
    }
    Ok(dw.f_transpose(0, 1)?.f_contiguous()?)
}

/// A convolution's parameters' part of the reverse of (y, ẏ) (module doc): pushes
/// `dW = wgrad(x, p_y) + wgrad(ẋ, g_y)` and `db = sum p_y`. The caller adds the input's
/// adjoint, its transposed convolution of p_y.
pub fn conv_param_grads(
    (weight, bias): (&Tensor, &Tensor),
    (stride, padding): (&[i64], &[i64]),
    (x, x_dot): (&Tensor, &Tensor),
    (g_y, p_y): (&Tensor, &Tensor),
    grads: &mut ParamGrads,
) -> Result<()> {
    let dw = conv_weight_grad(weight, stride, padding, &[(x, p_y), (x_dot, g_y)])?;
    grads.push((weight.shallow_clone(), dw));
    grads.push((bias.shallow_clone(), sum_but_channels(p_y)?));
    Ok(())
}

impl Conv1d {
    /// ẏ = W * ẋ (the bias does not move with x).
    pub fn tangent(&self, x_dot: &Tensor) -> Result<Tensor> {
        Ok(x_dot.f_conv1d(&self.weight, None::<&Tensor>, [self.stride], [self.padding], [1], 1)?)
    }

    /// The reverse of (y, ẏ) (module doc): pushes dW and db, returns p_x.
    pub fn second_backward(
        &self,
        (x, x_dot): (&Tensor, &Tensor),
        g_y: &Tensor,
        p_y: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<Tensor> {
        let layer = (&self.weight, &self.bias);
        conv_param_grads(layer, (&[self.stride], &[self.padding]), (x, x_dot), (g_y, p_y), grads)?;
        self.input_backward(p_y, x.size()[2])
    }
}

/// What the tangent sweep keeps of a group norm: grouped [B, G, M] values and [B, G, 1] means.
#[derive(Debug)]
pub struct GroupNormTangent {
    x_hat: Tensor,
    x_dot: Tensor,
    /// mean(ẋ) and B = mean(x̂ ẋ).
    mean_dot: Tensor,
    b: Tensor,
    x_hat_dot: Tensor,
    /// ẏ = γ x̂̇ in the input's layout.
    pub y_dot: Tensor,
}

impl GroupNorm {
    fn grouped(&self, size: &[i64]) -> [i64; 3] {
        [size[0], self.groups, -1]
    }

    /// γ viewed to broadcast over [B, C, ...].
    fn per_channel(&self, dims: usize) -> Result<Tensor> {
        let mut shape = vec![1, self.weight.size()[0]];
        shape.resize(dims, 1);
        Ok(self.weight.f_view(shape.as_slice())?)
    }

    /// ẏ from ẋ (module doc), keeping what the reverse needs. As one pass per term:
    /// `x̂̇ = rstd ẋ - (rstd B) x̂ - rstd mean(ẋ)` with per-group coefficients.
    pub fn tangent(&self, tape: &GroupNormTape, x_dot: &Tensor) -> Result<GroupNormTangent> {
        let size = x_dot.size();
        let mean = |t: &Tensor| t.f_mean_dim([-1i64].as_slice(), true, None::<Kind>);
        let rstd = tape.rstd.f_unsqueeze(-1)?;
        let x_hat = tape.input.f_reshape(self.grouped(&size))?.f_sub(&tape.mean.f_unsqueeze(-1)?)?.f_mul(&rstd)?;
        let x_dot = x_dot.f_reshape(self.grouped(&size))?;
        let mean_dot = mean(&x_dot)?;
        let b = mean(&x_hat.f_mul(&x_dot)?)?;
        let x_hat_dot =
            x_dot.f_mul(&rstd)?.f_addcmul_(&x_hat, &rstd.f_mul(&b)?.f_neg_()?)?.f_sub_(&rstd.f_mul(&mean_dot)?)?;
        let y_dot = x_hat_dot.f_reshape(size.as_slice())?.f_mul(&self.per_channel(size.len())?)?;
        Ok(GroupNormTangent { x_hat, x_dot, mean_dot, b, x_hat_dot, y_dot })
    }

    /// The reverse of (y, ẏ) (module doc): pushes dγ and dβ, returns p_x. With v = γ p_y, the
    /// module doc's `P(v) + rstd² ((3 B C - A) x̂ - C ẋ_c - B u_c)` expands to
    /// `rstd v - rstd² B u - rstd² C ẋ + c_4 x̂ + c_5` with per-group coefficients
    /// `c_4 = rstd² (3 B C - A) - rstd mean(v x̂)` and
    /// `c_5 = rstd² (C mean(ẋ) + B mean(u)) - rstd mean(v)`: one pass per term over the group.
    pub fn second_backward(
        &self,
        tape: &GroupNormTape,
        tangent: &GroupNormTangent,
        g_y: &Tensor,
        p_y: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<Tensor> {
        let size = p_y.size();
        let grouped = self.grouped(&size);
        let mean = |t: &Tensor| t.f_mean_dim([-1i64].as_slice(), true, None::<Kind>);
        let gamma = self.per_channel(size.len())?;
        let rstd = tape.rstd.f_unsqueeze(-1)?;
        let rstd2 = rstd.f_square()?;
        let GroupNormTangent { x_hat, x_dot, mean_dot, b, x_hat_dot, .. } = tangent;
        let v = p_y.f_mul(&gamma)?.f_reshape(grouped)?;
        let u = g_y.f_mul(&gamma)?.f_reshape(grouped)?;
        let mean_u = mean(&u)?;
        let c = mean(&u.f_mul(x_hat)?)?;
        // A = mean(u ẋ_c) = mean(u ẋ) - mean(u) mean(ẋ).
        let a = mean(&u.f_mul(x_dot)?)?.f_sub_(&mean_u.f_mul(mean_dot)?)?;
        let c4 = b
            .f_mul(&c)?
            .f_mul_scalar_(3.0)?
            .f_sub_(&a)?
            .f_mul_(&rstd2)?
            .f_sub_(&mean(&v.f_mul(x_hat)?)?.f_mul_(&rstd)?)?;
        let c5 = c.f_mul(mean_dot)?.f_add_(&b.f_mul(&mean_u)?)?.f_mul_(&rstd2)?.f_sub_(&mean(&v)?.f_mul_(&rstd)?)?;
        let p_x = v
            .f_mul(&rstd)?
            .f_addcmul_(&u, &rstd2.f_mul(b)?.f_neg_()?)?
            .f_addcmul_(x_dot, &rstd2.f_mul(&c)?.f_neg_()?)?
            .f_addcmul_(x_hat, &c4)?
            .f_add_(&c5)?;
        let d_gamma =
            p_y.f_mul(&x_hat.f_reshape(size.as_slice())?)?.f_addcmul_(g_y, &x_hat_dot.f_reshape(size.as_slice())?)?;
        grads.push((self.weight.shallow_clone(), sum_but_channels(&d_gamma)?));
        grads.push((self.bias.shallow_clone(), sum_but_channels(p_y)?));
        Ok(p_x.f_reshape(size.as_slice())?)
    }

    /// Mish(GroupNorm(x)) for the four sweeps: the value ([`Mish::Fused`]'s bit for bit) and
    /// the tape with Mish's slope and curvature.
    ///
    /// [`Mish::Fused`]: super::Mish::Fused
    pub fn mish_forward_second(&self, x: &Tensor) -> Result<(Tensor, NormMishPass)> {
        let (normed, norm) = self.forward_taped(x)?;
        let parts = mish_parts(&normed, true)?;
        let curvature =
            parts.curvature.ok_or_else(|| Error::internal("group norm and Mish", "mish'' was not computed"))?;
        Ok((parts.value, NormMishPass { norm, slope: parts.slope, curvature }))
    }

    /// The input backward from g (the adjoint of Mish's output): (g_x, the adjoints kept).
    /// Also keeps q g, the factor of the tangent in the reverse's Mish term.
    pub fn mish_adjoints(&self, pass: &NormMishPass, g: &Tensor) -> Result<(Tensor, NormMishAdjoints)> {
        // Where the kernel declines (a GPU, float64) its fallback has g * slope already.
        let (g_x, g_norm) = self.slope_input_backward_parts(&pass.norm, &pass.slope, g)?;
        let g_norm = match g_norm {
            Some(g_norm) => g_norm,
            None => g.f_mul(&pass.slope)?,
        };
        let adjoints = NormMishAdjoints { curvature_g: pass.curvature.f_mul(g)?, g_norm };
        Ok((g_x, adjoints))
    }

    /// The tangent of Mish's output from ẋ.
    pub fn mish_tangent(&self, pass: &NormMishPass, x_dot: &Tensor) -> Result<(Tensor, GroupNormTangent)> {
        let norm = self.tangent(&pass.norm, x_dot)?;
        Ok((norm.y_dot.f_mul(&pass.slope)?, norm))
    }

    /// The reverse through Mish and the norm from p (the value adjoint of Mish's output).
    pub fn mish_second_backward(
        &self,
        pass: &NormMishPass,
        adjoints: &NormMishAdjoints,
        tangent: &GroupNormTangent,
        p: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<Tensor> {
        let p_norm = p.f_mul(&pass.slope)?.f_addcmul_(&adjoints.curvature_g, &tangent.y_dot)?;
        self.second_backward(&pass.norm, tangent, &adjoints.g_norm, &p_norm, grads)
    }
}

/// Mish(GroupNorm(x))'s forward for the four sweeps.
#[derive(Debug)]
pub struct NormMishPass {
    norm: GroupNormTape,
    slope: Tensor,
    curvature: Tensor,
}

/// The input backward's adjoint of the norm's output, and mish'' times Mish's output's.
#[derive(Debug)]
pub struct NormMishAdjoints {
    curvature_g: Tensor,
    g_norm: Tensor,
}

/// A [`Conv1dBlock`]'s sweeps: the forward's, the adjoints, the tangents.
#[derive(Debug)]
pub struct Conv1dBlockPass {
    input: Tensor,
    epilogue: NormMishPass,
}

#[derive(Debug)]
pub struct Conv1dBlockAdjoints {
    /// Of the convolution's output.
    g_conv: Tensor,
    epilogue: NormMishAdjoints,
}

#[derive(Debug)]
pub struct Conv1dBlockTangents {
    input: Tensor,
    norm: GroupNormTangent,
}

impl Conv1dBlock {
    pub fn forward_second(&self, x: &Tensor) -> Result<(Tensor, Conv1dBlockPass)> {
        let (y, epilogue) = self.norm.mish_forward_second(&self.conv.forward(x)?)?;
        Ok((y, Conv1dBlockPass { input: x.shallow_clone(), epilogue }))
    }

    pub fn adjoints(&self, pass: &Conv1dBlockPass, g: &Tensor) -> Result<(Tensor, Conv1dBlockAdjoints)> {
        let (g_conv, epilogue) = self.norm.mish_adjoints(&pass.epilogue, g)?;
        let g_x = self.conv.input_backward(&g_conv, pass.input.size()[2])?;
        Ok((g_x, Conv1dBlockAdjoints { g_conv, epilogue }))
    }

    pub fn tangent(&self, pass: &Conv1dBlockPass, x_dot: &Tensor) -> Result<(Tensor, Conv1dBlockTangents)> {
        let (y_dot, norm) = self.norm.mish_tangent(&pass.epilogue, &self.conv.tangent(x_dot)?)?;
        Ok((y_dot, Conv1dBlockTangents { input: x_dot.shallow_clone(), norm }))
    }

    pub fn second_backward(
        &self,
        pass: &Conv1dBlockPass,
        adjoints: &Conv1dBlockAdjoints,
        tangents: &Conv1dBlockTangents,
        p: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<Tensor> {
        let p_conv = self.norm.mish_second_backward(&pass.epilogue, &adjoints.epilogue, &tangents.norm, p, grads)?;
        self.conv.second_backward((&pass.input, &tangents.input), &adjoints.g_conv, &p_conv, grads)
    }
}

/// A [`ResidualTemporalBlock`]'s sweeps.
#[derive(Debug)]
pub struct ResidualPass {
    input: Tensor,
    blocks: [Conv1dBlockPass; 2],
}

#[derive(Debug)]
pub struct ResidualAdjoints {
    g_out: Tensor,
    blocks: [Conv1dBlockAdjoints; 2],
}

#[derive(Debug)]
pub struct ResidualTangents {
    input: Tensor,
    blocks: [Conv1dBlockTangents; 2],
}

impl ResidualTemporalBlock {
    /// The forward with [`Mish::Fused`](super::Mish::Fused)'s values; `time_act` is Mish of
    /// the time embedding (the same for every block, computed once by the caller).
    pub fn forward_second(&self, x: &Tensor, time_act: &Tensor) -> Result<(Tensor, ResidualPass)> {
        let time = self.time_linear.forward(time_act)?.f_unsqueeze(-1)?;
        let (h, first) = self.blocks[0].forward_second(x)?;
        let (h, second) = self.blocks[1].forward_second(&h.f_add(&time)?)?;
        let out = match &self.residual_conv {
            Some(conv) => h.f_add(&conv.forward(x)?)?,
            None => h.f_add(x)?,
        };
        Ok((out, ResidualPass { input: x.shallow_clone(), blocks: [first, second] }))
    }

    pub fn adjoints(&self, pass: &ResidualPass, g_out: &Tensor) -> Result<(Tensor, ResidualAdjoints)> {
        let (g_inner, second) = self.blocks[1].adjoints(&pass.blocks[1], g_out)?;
        let (g_x, first) = self.blocks[0].adjoints(&pass.blocks[0], &g_inner)?;
        let g_x = match &self.residual_conv {
            Some(conv) => g_x.f_add(&conv.input_backward(g_out, pass.input.size()[2])?)?,
            None => g_x.f_add(g_out)?,
        };
        Ok((g_x, ResidualAdjoints { g_out: g_out.shallow_clone(), blocks: [first, second] }))
    }

    pub fn tangent(&self, pass: &ResidualPass, x_dot: &Tensor) -> Result<(Tensor, ResidualTangents)> {
        let (h_dot, first) = self.blocks[0].tangent(&pass.blocks[0], x_dot)?;
        let (h_dot, second) = self.blocks[1].tangent(&pass.blocks[1], &h_dot)?;
        let out_dot = match &self.residual_conv {
            Some(conv) => h_dot.f_add(&conv.tangent(x_dot)?)?,
            None => h_dot.f_add(x_dot)?,
        };
        Ok((out_dot, ResidualTangents { input: x_dot.shallow_clone(), blocks: [first, second] }))
    }

    /// The reverse from p_out: pushes the block's parameters' gradients and returns (p_x, the
    /// adjoint of `time_act` from this block's time projection).
    pub fn second_backward(
        &self,
        sweeps: (&ResidualPass, &ResidualAdjoints, &ResidualTangents),
        p_out: &Tensor,
        time_act: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<(Tensor, Tensor)> {
        let (pass, adjoints, tangents) = sweeps;
        let p_inner =
            self.blocks[1].second_backward(&pass.blocks[1], &adjoints.blocks[1], &tangents.blocks[1], p_out, grads)?;
        // The time projection, added over the length: no tangent, an ordinary backward.
        let p_time = p_inner.f_sum_dim_intlist([2i64].as_slice(), false, None::<Kind>)?;
        let p_time_act = self.time_linear.backward(time_act, &p_time, grads)?;
        let p_x = self.blocks[0].second_backward(
            &pass.blocks[0],
            &adjoints.blocks[0],
            &tangents.blocks[0],
            &p_inner,
            grads,
        )?;
        let p_x = match &self.residual_conv {
            Some(conv) => {
                p_x.f_add(&conv.second_backward((&pass.input, &tangents.input), &adjoints.g_out, p_out, grads)?)?
            }
            None => p_x.f_add(p_out)?,
        };
        Ok((p_x, p_time_act))
    }
}

impl Downsample1d {
    pub fn tangent(&self, x_dot: &Tensor) -> Result<Tensor> {
        self.conv.tangent(x_dot)
    }

    /// The reverse of (y, ẏ) given the stage's input and its tangent, `g_y` and `p_y`.
    pub fn second_backward(
        &self,
        input: (&Tensor, &Tensor),
        g_y: &Tensor,
        p_y: &Tensor,
        grads: &mut ParamGrads,
    ) -> Result<Tensor> {
        self.conv.second_backward(input, g_y, p_y, grads)
    }
}

impl super::Linear {
    /// The ordinary backward of `y = input W^T + b` from y's adjoint: pushes dW and db,
    /// returns the input's adjoint. For the layers whose input does not depend on x (the time
    /// MLP, the blocks' time projections), where the pair (v, v̇) has no tangent.
    pub fn backward(&self, input: &Tensor, adjoint: &Tensor, grads: &mut ParamGrads) -> Result<Tensor> {
        self.param_grads(input, adjoint, grads)?;
        Ok(adjoint.f_mm(&self.weight)?)
    }

    /// [`Linear::backward`](super::Linear) without the input's adjoint.
    pub fn param_grads(&self, input: &Tensor, adjoint: &Tensor, grads: &mut ParamGrads) -> Result<()> {
        grads.push((self.weight.shallow_clone(), adjoint.f_tr()?.f_mm(input)?));
        grads.push((self.bias.shallow_clone(), sum_but_channels(adjoint)?));
        Ok(())
    }
}

/// What the time MLP's backward needs from its forward.
#[derive(Debug)]
pub struct TimeMlpPass {
    input: Tensor,
    hidden: Tensor,
    slope: Tensor,
}

impl super::TimeMlp {
    /// [`TimeMlp::forward`](super::TimeMlp::forward) with [`Mish::Fused`](super::Mish::Fused)
    /// (the same value bit for bit), keeping what [`TimeMlpPass`]'s backward needs.
    pub fn forward_kept(&self, t: &Tensor) -> Result<(Tensor, TimeMlpPass)> {
        let input = self.emb.forward(t)?;
        let parts = mish_parts(&self.first.forward(&input)?, false)?;
        let e = self.second.forward(&parts.value)?;
        Ok((e, TimeMlpPass { input, hidden: parts.value, slope: parts.slope }))
    }

    /// The parameters' gradients from the embedding's adjoint (e(t) does not depend on x: one
    /// ordinary backward).
    pub fn param_grads(&self, pass: &TimeMlpPass, adjoint: &Tensor, grads: &mut ParamGrads) -> Result<()> {
        let hidden = self.second.backward(&pass.hidden, adjoint, grads)?.f_mul(&pass.slope)?;
        self.first.param_grads(&pass.input, &hidden, grads)
    }
}
