//! The MLP head's input gradient and the alignment loss's parameter gradient written out by
//! hand (issue 38), for the windowed MLP and the flat MLP: a few large matrix products instead
//! of autograd's double backward, whose graph of small operations is what a reward step costs
//! at the maze's sizes.
//!
//! The head scores rows: `u = [z, e(t)]` (a row's F features and the item's time embedding),
//! `a_1 = W_1 u + b_1`, `h_k = mish(a_k)`, `a_{k+1} = W_{k+1} h_k + b_{k+1}`, and
//! `out = W_L h_{L-1} + b_L`; an item's rho is `c` times the sum of its rows' outputs (the
//! windowed MLP's mean over its N windows: c = 1 / N; the flat MLP has one row, c = 1). With
//! `s_k = mish'(a_k)` and `q_k = mish''(a_k)`:
//!
//! - input gradient (one backward): `g_{L-1} = c W_L`, `d_k = s_k * g_k`,
//!   `g_{k-1} = d_k W_k`, and d rho / d z = `d_1 W_1[:, :F]`;
//! - parameter gradient of a loss L(grad) with `r = dL / d grad` (and, for rho's L2 penalty,
//!   `p_out = dL / d out` per row): L's derivative along the parameters is that of
//!   `S = sum r . grad`, which is c times the forward-mode derivative of `out` along r. The
//!   tangent pass `ȧ_1 = r W_1[:, :F]^T`, `ḣ_k = s_k * ȧ_k`, `ȧ_{k+1} = ḣ_k W_{k+1}^T`, and
//!   its reverse: the tangent adjoint of `ȧ_k` is `d_k` again, the primal adjoint
//!   `p_k = g_k * ȧ_k * q_k + s_k * (p_{k+1} W_{k+1})` (the last term from p_out at the top),
//!   and `dW_k = d_k^T ḣ_{k-1} + p_k^T h_{k-1}`, `db_k = sum p_k`, with `ḣ_0 = [r, 0]` and
//!   `h_0 = u`; the time embedding's adjoint `sum over rows of p_1 W_1[:, F:]` goes back
//!   through the time MLP (one ordinary backward: e(t) does not depend on x).
//!
//! Mish's derivatives: with `T = tanh(softplus(a))` and `σ = sigmoid(a)`,
//! `mish' = T + a (1 - T²) σ` and `mish'' = (1 - T²) σ (2 + a (1 - σ - 2 T σ))`, all from one
//! exp (`blocks::mish_parts`); above 20, where T rounds to 1 in float32, mish' is 1 and mish'' is
//! negligible (under 4e-17 |a|), as the training pass's `Mish::TwiceDifferentiable` has them.
//! `reward/tests.rs` checks both against autograd to 1e-5 on every architecture it applies to.

use tch::{Kind, Tensor};

use super::mlp::MlpHead;
use crate::engine::nets::blocks::second_order::{ParamGrads, TimeMlpPass};
use crate::engine::nets::blocks::{Mish, mish_parts};
use crate::engine::nets::kernels::MishParts;
use crate::engine::nets::mlp::MLP_TIME_DIM;
use crate::error::{Error, Result};

/// One pass of the head over `R = B N` rows with what the backward passes need.
pub(super) struct HeadPass {
    rows_per_item: i64,
    features: i64,
    /// e(t), [B, 32], and (training pass only) what the time MLP's backward needs.
    time_embedding: Tensor,
    time: Option<TimeMlpPass>,
    /// Each layer's row input ([R, width]): `z` (the first layer's input is `[z, e(t)]`, each
    /// row with its item's e(t)), then `h_1 .. h_{L-1}`.
    inputs: Vec<Tensor>,
    /// `s_k` and `q_k` (the latter only for the training pass), k = 1 .. L-1.
    slopes: Vec<Tensor>,
    curvatures: Vec<Tensor>,
    /// `g_k` (adjoint of h_k) and `d_k = s_k g_k`, k = 1 .. L-1.
    adjoints: Vec<Tensor>,
    deltas: Vec<Tensor>,
    /// One output per row, [B, N]: the same operations as [`MlpHead::forward`] with fused Mish,
    /// so the same numbers bit for bit (rho served with a gradient equals rho scored alone).
    pub(super) out: Tensor,
    /// d (c sum of an item's outputs) / d z per row, [R, F].
    pub(super) grad: Tensor,
}

impl MlpHead {
    /// The forward pass and the input gradient of rho (the mean of an item's row outputs), by
    /// hand. `features` [B, N, F], `t` [B] in the weights' float dtype; `second`: also keep
    /// mish'' and the time MLP's slope for [`MlpHead::alignment_grads`].
    pub(super) fn pass(&self, features: &Tensor, t: &Tensor, second: bool) -> Result<HeadPass> {
        let size = features.size();
        let &[_, rows, width] = size.as_slice() else {
            return Err(Error::internal("reward MLP", format!("features of shape {size:?}")));
        };
        let hidden = self.layers.len().saturating_sub(1);
        if hidden == 0 {
            return Err(Error::internal("reward MLP", "a head without hidden layers"));
        }
        let c = 1.0 / rows as f64;
        // The forward's operations in its order (MlpHead::forward, TimeMlp::forward with fused
        // Mish), keeping what the backward passes read; the time MLP's only for training.
        let (e, time) = if second {
            let (e, time) = self.time_mlp.forward_kept(t)?;
            (e, Some(time))
        } else {
            (self.time_mlp.forward(t, Mish::Fused)?, None)
        };
        let t_emb = e.f_unsqueeze(1)?.f_expand([-1, rows, MLP_TIME_DIM], false)?;
        let mut a = self.layers[0].forward(&Tensor::f_cat(&[features, &t_emb], 2)?)?;
        let mut inputs = vec![features.f_flatten(0, 1)?];
        let (mut slopes, mut curvatures) = (Vec::with_capacity(hidden), Vec::with_capacity(hidden));
        for k in 0..hidden {
            let MishParts { value, slope, curvature } = mish_parts(&a, second)?;
            slopes.push(slope.f_flatten(0, 1)?);
            curvatures.extend(curvature.map(|q| q.f_flatten(0, 1)).transpose()?);
            // The next pre-activation; after the last hidden layer, the output [B, N, 1].
            a = self.layers[k + 1].forward(&value)?;
            inputs.push(value.f_flatten(0, 1)?);
        }
        let out = a.f_squeeze_dim(-1)?;
        // Backward from c: g_{L-1} = c W_L (one row, broadcast), d_k = s_k g_k, g_{k-1} = d_k W_k.
        // adjoints[k], deltas[k]: of the k-th hidden layer's output h (inputs[k + 1]) and its
        // pre-activation (the output of layers[k]).
        let (mut adjoints, mut deltas) = (Vec::with_capacity(hidden), Vec::with_capacity(hidden));
        let mut g = self.layers[hidden].weight.f_mul_scalar(c)?;
        for k in (0..hidden).rev() {
            let d = slopes[k].f_mul(&g)?;
            let below = if k > 0 { Some(d.f_mm(&self.layers[k].weight)?) } else { None };
            adjoints.push(g);
            deltas.push(d);
            match below {
                Some(b) => g = b,
                None => break,
            }
        }
        adjoints.reverse();
        deltas.reverse();
        let grad = deltas[0].f_mm(&self.layers[0].weight.f_narrow(1, 0, width)?)?;
        Ok(HeadPass {
            rows_per_item: rows,
            features: width,
            time_embedding: e,
            time,
            inputs,
            slopes,
            curvatures,
            adjoints,
            deltas,
            out,
            grad,
        })
    }

    /// Every parameter's gradient of a loss of the pass's input gradient (module doc): `r`
    /// [R, F] is dL / d grad, `p_out` [R] dL / d out where the loss also reads the outputs.
    /// Pairs of (parameter, gradient) in no particular order.
    pub(super) fn alignment_grads(&self, pass: &HeadPass, r: &Tensor, p_out: Option<&Tensor>) -> Result<ParamGrads> {
        let layers = &self.layers;
        let hidden = layers.len() - 1;
        let (true, Some(time)) = (pass.curvatures.len() == hidden, &pass.time) else {
            return Err(Error::internal("reward MLP", "alignment gradients need the training pass (mish'')"));
        };
        let width = pass.features;
        let sum_rows = |t: &Tensor, keep: bool| t.f_sum_dim_intlist([0i64].as_slice(), keep, None::<Kind>);
        // Tangent pass along r: ȧ_1 = r W_1[:, :F]^T, ḣ_k = s_k ȧ_k, ȧ_{k+1} = ḣ_k W_{k+1}^T.
        let (mut a_dots, mut h_dots) = (Vec::with_capacity(hidden), Vec::with_capacity(hidden));
        let mut a_dot = r.f_mm(&layers[0].weight.f_narrow(1, 0, width)?.f_tr()?)?;
        for k in 0..hidden {
            let h_dot = pass.slopes[k].f_mul(&a_dot)?;
            // The output layer's tangent is not needed: dW_L takes ḣ_{L-1} itself.
            if k + 1 < hidden {
                let next = h_dot.f_mm(&layers[k + 1].weight.f_tr()?)?;
                a_dots.push(std::mem::replace(&mut a_dot, next));
            } else {
                a_dots.push(std::mem::replace(&mut a_dot, Tensor::new()));
            }
            h_dots.push(h_dot);
        }
        let mut grads = Vec::with_capacity(2 * layers.len() + 4);
        // The output layer: dW_L = c sum_rows ḣ_{L-1} + p_out^T h_{L-1}; db_L = sum p_out.
        let last = &layers[hidden];
        let c = 1.0 / pass.rows_per_item as f64;
        let mut dw = sum_rows(&h_dots[hidden - 1], true)?.f_mul_scalar(c)?;
        // The primal adjoint of the layer below's output, from p_out.
        let mut p_above = None;
        let db = match p_out {
            Some(p) => {
                let p = p.f_unsqueeze(1)?;
                dw = dw.f_add(&p.f_tr()?.f_mm(&pass.inputs[hidden])?)?;
                p_above = Some(p.f_mm(&last.weight)?);
                sum_rows(&p, false)?
            }
            None => last.bias.f_zeros_like()?,
        };
        grads.push((last.weight.shallow_clone(), dw));
        grads.push((last.bias.shallow_clone(), db));
        let mut p_first = Tensor::new();
        for k in (0..hidden).rev() {
            // p_k = g_k ȧ_k q_k + s_k (p_{k+1} W_{k+1}).
            let mut p = pass.adjoints[k].f_mul(&a_dots[k])?.f_mul(&pass.curvatures[k])?;
            if let Some(above) = &p_above {
                p = p.f_add(&pass.slopes[k].f_mul(above)?)?;
            }
            let layer = &layers[k];
            if k > 0 {
                let dw = p.f_tr()?.f_mm(&pass.inputs[k])?.f_addmm_(&pass.deltas[k].f_tr()?, &h_dots[k - 1])?;
                p_above = Some(p.f_mm(&layer.weight)?);
                grads.push((layer.weight.shallow_clone(), dw));
                grads.push((layer.bias.shallow_clone(), sum_rows(&p, false)?));
            } else {
                p_first = p;
            }
        }
        // The first layer's two column blocks: z's (with the tangent ḣ_0 = r) and e's, whose
        // rows share an item's e: p_1 summed over an item's rows, once per item.
        let first = &layers[0];
        let batch = pass.time_embedding.size()[0];
        let p_item = p_first.f_view([batch, pass.rows_per_item, -1])?.f_sum_dim_intlist(
            [1i64].as_slice(),
            false,
            None::<Kind>,
        )?;
        let dw_z = p_first.f_tr()?.f_mm(&pass.inputs[0])?.f_addmm_(&pass.deltas[0].f_tr()?, r)?;
        let dw_e = p_item.f_tr()?.f_mm(&pass.time_embedding)?;
        grads.push((first.weight.shallow_clone(), Tensor::f_cat(&[&dw_z, &dw_e], 1)?));
        grads.push((first.bias.shallow_clone(), sum_rows(&p_item, false)?));
        // The time embedding's adjoint back through the time MLP.
        let adj_e = p_item.f_mm(&first.weight.f_narrow(1, width, first.weight.size()[1] - width)?)?;
        self.time_mlp.param_grads(time, &adj_e, &mut grads)?;
        Ok(grads)
    }
}
