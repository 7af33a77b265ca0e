//! The convolutional rewards' alignment gradients (`value_function`, `conv_encoder`) by the
//! four sweeps of `blocks::second_order` (forward, input backward, tangent along r, reverse of
//! the pair), without autograd's double backward: what both networks share, the loss's
//! derivatives ([`AlignmentTerms`]) and their top, Diffuser's `final_block =
//! Sequential(Linear(F + d, F / 2), Mish, Linear(F / 2, 1))` over the flattened features and
//! the time embedding e(t). Each network's file runs its own layers' sweeps around these.
//!
//! At the top, `pre = W_1 [f, e] + b_1`, `act = mish(pre)`, `rho = W_2 act + b_2` with
//! `s = mish'(pre)`, `q = mish''(pre)`: the input backward's adjoints `g_act = W_2`,
//! `g_pre = s g_act`, `g_f = g_pre W_1[:, :F]`; the tangent `pre_dot = ḟ W_1[:, :F]^T`,
//! `act_dot = s pre_dot`; the reverse from p_rho (the loss's own derivative along rho, zero
//! without rho's L2 penalty) and rho's tangent adjoint 1: `dW_2 = sum_b act_dot + p_rho^T act`,
//! `db_2 = sum p_rho`, `p_pre = s (p_rho W_2) + q pre_dot g_act`,
//! `dW_1 = [p_pre^T f + g_pre^T ḟ, p_pre^T e]`, `db_1 = sum p_pre`, and the adjoints of f and e
//! `p_pre W_1`.

use tch::{Kind, Tensor};

use crate::engine::nets::blocks::second_order::{ParamGrads, TimeMlpPass, sum_but_channels};
use crate::engine::nets::blocks::{Linear, TimeMlp, mish_parts};
use crate::error::{Error, Result};

/// The alignment loss at the pass's rho and input gradient, and its derivatives: `r` = d loss
/// / d grad (x's shape), `p_rho` = d loss / d rho [B] where the loss reads rho (its L2
/// penalty).
pub struct AlignmentTerms {
    pub loss: Tensor,
    pub r: Tensor,
    pub p_rho: Option<Tensor>,
}

/// The time embedding through the sweeps: e(t), which the top reads, and Mish(e), which every
/// block's time projection reads; neither depends on x, so the time MLP takes one ordinary
/// backward at the end, from the adjoints the blocks add up here.
pub(super) struct TimeSweep {
    pub(super) e: Tensor,
    pub(super) act: Tensor,
    slope: Tensor,
    pass: TimeMlpPass,
    act_adjoint: Option<Tensor>,
}

impl TimeSweep {
    pub(super) fn forward(time_mlp: &TimeMlp, t: &Tensor) -> Result<Self> {
        let (e, pass) = time_mlp.forward_kept(t)?;
        let parts = mish_parts(&e, false)?;
        Ok(Self { e, act: parts.value, slope: parts.slope, pass, act_adjoint: None })
    }

    /// Adds a block's adjoint of Mish(e).
    pub(super) fn add_act_adjoint(&mut self, adjoint: Tensor) -> Result<()> {
        self.act_adjoint = Some(match self.act_adjoint.take() {
            Some(sum) => sum.f_add(&adjoint)?,
            None => adjoint,
        });
        Ok(())
    }

    /// The time MLP's gradients from e's adjoint at the top and the blocks' of Mish(e).
    pub(super) fn backward(self, time_mlp: &TimeMlp, p_e: Tensor, grads: &mut ParamGrads) -> Result<()> {
        let p_e = match &self.act_adjoint {
            Some(p_act) => p_e.f_add(&p_act.f_mul(&self.slope)?)?,
            None => p_e,
        };
        time_mlp.param_grads(&self.pass, &p_e, grads)
    }
}

/// The top's forward for the sweeps.
pub(super) struct TopPass {
    features: Tensor,
    time_embedding: Tensor,
    act: Tensor,
    slope: Tensor,
    curvature: Tensor,
    g_pre: Tensor,
}

/// The top's tangent.
pub(super) struct TopTangent {
    features: Tensor,
    pre: Tensor,
    act: Tensor,
}

/// The top over `features` [B, F] and `e` [B, d]: (rho [B], d sum(rho) / d features, the pass).
/// rho is the networks' forward's with [`Mish::Fused`](crate::engine::nets::blocks::Mish::Fused)
/// bit for bit.
pub(super) fn top_forward(
    (first, second): (&Linear, &Linear),
    features: &Tensor,
    e: &Tensor,
) -> Result<(Tensor, Tensor, TopPass)> {
    let pre = first.forward(&Tensor::f_cat(&[features, e], 1)?)?;
    let parts = mish_parts(&pre, true)?;
    let curvature = parts.curvature.ok_or_else(|| Error::internal("reward top", "mish'' was not computed"))?;
    let rho = second.forward(&parts.value)?.f_squeeze_dim(1)?;
    let g_pre = second.weight.f_mul(&parts.slope)?;
    let g_features = g_pre.f_mm(&first.weight.f_narrow(1, 0, features.size()[1])?)?;
    let pass = TopPass {
        features: features.shallow_clone(),
        time_embedding: e.shallow_clone(),
        act: parts.value,
        slope: parts.slope,
        curvature,
        g_pre,
    };
    Ok((rho, g_features, pass))
}

/// The top's tangent from the features' tangent [B, F].
pub(super) fn top_tangent(first: &Linear, pass: &TopPass, features: &Tensor) -> Result<TopTangent> {
    let pre = features.f_mm(&first.weight.f_narrow(1, 0, features.size()[1])?.f_tr()?)?;
    let act = pre.f_mul(&pass.slope)?;
    Ok(TopTangent { features: features.shallow_clone(), pre, act })
}

/// The top's reverse: pushes its parameters' gradients, returns the adjoints (p_features [B, F],
/// p_e [B, d]).
pub(super) fn top_second_backward(
    (first, second): (&Linear, &Linear),
    pass: &TopPass,
    tangent: &TopTangent,
    p_rho: Option<&Tensor>,
    grads: &mut ParamGrads,
) -> Result<(Tensor, Tensor)> {
    let sum_rows = |t: &Tensor| t.f_sum_dim_intlist([0i64].as_slice(), true, None::<Kind>);
    let g_act = &second.weight;
    // p_pre's second-order part, q pre_dot g_act.
    let mut p_pre = pass.curvature.f_mul(&tangent.pre)?.f_mul(g_act)?;
    let mut dw2 = sum_rows(&tangent.act)?;
    let db2 = match p_rho {
        Some(p) => {
            let p = p.f_unsqueeze(1)?;
            dw2 = dw2.f_add(&p.f_tr()?.f_mm(&pass.act)?)?;
            p_pre = p_pre.f_add(&p.f_mm(g_act)?.f_mul(&pass.slope)?)?;
            sum_but_channels(&p)?
        }
        None => second.bias.f_zeros_like()?,
    };
    grads.push((second.weight.shallow_clone(), dw2));
    grads.push((second.bias.shallow_clone(), db2));
    let dw_features = p_pre.f_tr()?.f_mm(&pass.features)?.f_addmm_(&pass.g_pre.f_tr()?, &tangent.features)?;
    let dw_time = p_pre.f_tr()?.f_mm(&pass.time_embedding)?;
    grads.push((first.weight.shallow_clone(), Tensor::f_cat(&[&dw_features, &dw_time], 1)?));
    grads.push((first.bias.shallow_clone(), sum_but_channels(&p_pre)?));
    let p_input = p_pre.f_mm(&first.weight)?;
    let features = pass.features.size()[1];
    let p_e = p_input.f_narrow(1, features, p_input.size()[1] - features)?;
    Ok((p_input.f_narrow(1, 0, features)?, p_e))
}
