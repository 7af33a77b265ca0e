//! `value_function { widths }` (locomotion rewards), item [H, D]: Diffuser's `ValueFunction`
//! (`diffuser/models/temporal.py`) with `widths` the channels after each level, i.e. Diffuser's
//! `[dim * m for m in dim_mults]`, and time width `widths[0]` (= Diffuser's `dim`, whose
//! `dim_mults` start at 1; the paper's (64, 64, 128, 128) is dim 64, dim_mults (1, 1, 2, 2)).
//! For dims = [D, *widths]: `blocks.{i}.0` = ResidualTemporalBlock(dims[i], dims[i + 1]),
//! `blocks.{i}.1` = ResidualTemporalBlock(dims[i + 1], dims[i + 1]), `blocks.{i}.2` =
//! Downsample1d on *every* level; `mid_block1` = ResidualTemporalBlock(w, w / 2),
//! `mid_down1` = Downsample1d(w / 2), `mid_block2` = ResidualTemporalBlock(w / 2, w / 4),
//! `mid_down2` = Downsample1d(w / 4) for w = widths[-1]; flatten [B, w / 4 * L] (channel-major)
//! and concatenate the time embedding; `final_block = Sequential(Linear(fc + d, fc / 2), Mish,
//! Linear(fc / 2, 1))` with fc = w / 4 * L. L is the length after the len(widths) + 2
//! downsamplings; the horizon must halve evenly through them (a power of two, or a multiple
//! of 2^(len(widths) + 2)), and then L = max(H / 2^(len(widths) + 2), 1) equals Diffuser's own
//! `fc_dim` bookkeeping, so Diffuser ValueFunction checkpoints load unchanged. (Diffuser's
//! bookkeeping and its actual lengths disagree for other horizons, where its forward fails.)
//! widths must be multiples of 8 (GroupNorm(8)), the last a multiple of 32 (w / 4 too).

use tch::Tensor;
use tch::nn;

use super::checks::{count, trajectory_shape, validate_widths};
use super::second_order::{AlignmentTerms, TimeSweep, top_forward, top_second_backward, top_tangent};
use crate::engine::nets::blocks::second_order::{ParamGrads, ResidualAdjoints, ResidualPass, ResidualTangents};
use crate::engine::nets::blocks::{
    Downsample1d, GROUPS, Linear, Mish, ResidualTemporalBlock, TEMPORAL_KERNEL, TimeMlp, total,
};
use crate::engine::nets::mlp::MAX_FEATURES;
use crate::error::{Error, Result};

/// The value function's hyperparameters: `final_length` is L, the horizon after every
/// downsampling.
#[derive(Debug, Clone)]
pub(super) struct ValueFunctionPlan {
    transition_dim: i64,
    widths: Vec<i64>,
    final_length: i64,
}

impl ValueFunctionPlan {
    pub(super) fn new(item_shape: &[i64], widths: &[usize]) -> Result<Self> {
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
        Ok(Self { transition_dim, widths, final_length: length })
    }

    pub(super) fn params(&self) -> u128 {
        ValueFunctionNet::params(self.transition_dim, &self.widths, self.final_length)
    }

    pub(super) fn build(&self, root: &nn::Path) -> Result<ValueFunctionNet> {
        ValueFunctionNet::new(root, self.transition_dim, &self.widths, self.final_length)
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
pub(super) struct ValueFunctionNet {
    time_mlp: TimeMlp,
    levels: Vec<ValueLevel>,
    mid_block1: ResidualTemporalBlock,
    mid_down1: Downsample1d,
    mid_block2: ResidualTemporalBlock,
    mid_down2: Downsample1d,
    final_first: Linear,
    pub(super) final_second: Linear,
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
    pub(super) fn forward(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let mut x = x.f_permute([0, 2, 1])?;
        let t_emb = self.time_mlp.forward(t, mish)?;
        for level in &self.levels {
            x = level.first.forward(&x, &t_emb, mish)?;
            x = level.second.forward(&x, &t_emb, mish)?;
            x = level.downsample.forward(&x)?;
        }
        x = self.mid_down1.forward(&self.mid_block1.forward(&x, &t_emb, mish)?)?;
        x = self.mid_down2.forward(&self.mid_block2.forward(&x, &t_emb, mish)?)?;
        let flat = x.f_flatten(1, -1)?;
        let h = self.final_first.forward(&Tensor::f_cat(&[&flat, &t_emb], 1)?)?;
        Ok(self.final_second.forward(&mish.forward(&h)?)?.f_squeeze_dim(1)?)
    }

    /// (rho [B], d sum(rho) / dx [B, H, D]) by a hand-written backward, without autograd:
    /// the forward keeps each block's tape (group-norm statistics, Mish slopes, lengths), the
    /// backward runs transposed convolutions, group-norm input backwards and slopes, in
    /// reverse. rho is [`ValueFunctionNet::forward`]'s with [`Mish::Fused`], bit for bit; the
    /// gradient is autograd's to float rounding (`tests.rs`). Call without a graph.
    pub(super) fn value_and_grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        let mut h = x.f_permute([0, 2, 1])?;
        let t_emb = self.time_mlp.forward(t, Mish::Fused)?;
        let mut tapes = Vec::with_capacity(self.levels.len());
        for level in &self.levels {
            let (a, first) = level.first.forward_taped(&h, &t_emb)?;
            let (b, second) = level.second.forward_taped(&a, &t_emb)?;
            h = level.downsample.forward(&b)?;
            tapes.push((first, second, b.size()[2]));
        }
        let (m1, mid1) = self.mid_block1.forward_taped(&h, &t_emb)?;
        let (m2, mid2) = self.mid_block2.forward_taped(&self.mid_down1.forward(&m1)?, &t_emb)?;
        let last = self.mid_down2.forward(&m2)?;
        let flat = last.f_flatten(1, -1)?;
        let pre = self.final_first.forward(&Tensor::f_cat(&[&flat, &t_emb], 1)?)?;
        let (act, act_tape) = Mish::forward_taped(&pre)?;
        let rho = self.final_second.forward(&act)?.f_squeeze_dim(1)?;

        // d sum(rho) / d act is the last layer's weight row for every sample.
        let g = act_tape.backward(&self.final_second.weight.f_expand_as(&act)?)?;
        let features = flat.size()[1];
        let g = g.f_matmul(&self.final_first.weight.f_narrow(1, 0, features)?)?.f_view(last.size().as_slice())?;
        let g = self.mid_down2.input_backward(&g, m2.size()[2])?;
        let g = self.mid_block2.input_backward(&mid2, &g)?;
        let g = self.mid_down1.input_backward(&g, m1.size()[2])?;
        let mut g = self.mid_block1.input_backward(&mid1, &g)?;
        for (level, (first, second, len)) in self.levels.iter().zip(tapes).rev() {
            g = level.downsample.input_backward(&g, len)?;
            g = level.second.input_backward(&second, &g)?;
            g = level.first.input_backward(&first, &g)?;
        }
        Ok((rho, g.f_permute([0, 2, 1])?.f_contiguous()?))
    }

    /// The network's layers after the time MLP in their order, up to the flattening.
    fn stages(&self) -> Vec<Stage<'_>> {
        let mut stages = Vec::with_capacity(3 * self.levels.len() + 4);
        for level in &self.levels {
            stages.extend([Stage::Block(&level.first), Stage::Block(&level.second), Stage::Down(&level.downsample)]);
        }
        stages.extend([
            Stage::Block(&self.mid_block1),
            Stage::Down(&self.mid_down1),
            Stage::Block(&self.mid_block2),
            Stage::Down(&self.mid_down2),
        ]);
        stages
    }

    /// The alignment loss and every parameter's gradient by the four sweeps of
    /// `blocks::second_order` (no autograd): `terms` gives the loss and its derivatives from
    /// (rho, grad_x rho) once the first two sweeps have them. Call without a graph.
    pub(super) fn alignment_grads(
        &self,
        x: &Tensor,
        t: &Tensor,
        terms: impl FnOnce(&Tensor, &Tensor) -> Result<AlignmentTerms>,
    ) -> Result<(Tensor, ParamGrads)> {
        let top_layers = (&self.final_first, &self.final_second);
        let mut time = TimeSweep::forward(&self.time_mlp, t)?;
        // 1. The forward.
        let stages = self.stages();
        let mut passes = Vec::with_capacity(stages.len());
        let mut h = x.f_permute([0, 2, 1])?;
        for stage in &stages {
            let (next, pass) = match stage {
                Stage::Block(block) => {
                    let (next, pass) = block.forward_second(&h, &time.act)?;
                    (next, StagePass::Block(pass))
                }
                Stage::Down(down) => (down.forward(&h)?, StagePass::Down(h.shallow_clone())),
            };
            passes.push(pass);
            h = next;
        }
        let last = h.size();
        let (rho, g_features, top) = top_forward(top_layers, &h.f_flatten(1, -1)?, &time.e)?;
        // 2. The input backward, keeping each stage's adjoints (in reverse order).
        let mut g = g_features.f_view(last.as_slice())?;
        let mut adjoints = Vec::with_capacity(stages.len());
        for (stage, pass) in stages.iter().zip(&passes).rev() {
            let (below, adjoint) = match (stage, pass) {
                (Stage::Block(block), StagePass::Block(pass)) => {
                    let (below, adjoint) = block.adjoints(pass, &g)?;
                    (below, StageAdjoint::Block(adjoint))
                }
                (Stage::Down(down), StagePass::Down(input)) => {
                    (down.input_backward(&g, input.size()[2])?, StageAdjoint::Down(g.shallow_clone()))
                }
                _ => return Err(mismatch()),
            };
            adjoints.push(adjoint);
            g = below;
        }
        adjoints.reverse();
        let grad = g.f_permute([0, 2, 1])?.f_contiguous()?;
        let AlignmentTerms { loss, r, p_rho } = terms(&rho, &grad)?;
        // 3. The tangent along r.
        let mut h_dot = r.f_permute([0, 2, 1])?;
        let mut tangents = Vec::with_capacity(stages.len());
        for (stage, pass) in stages.iter().zip(&passes) {
            let (next, tangent) = match (stage, pass) {
                (Stage::Block(block), StagePass::Block(pass)) => {
                    let (next, tangent) = block.tangent(pass, &h_dot)?;
                    (next, StageTangent::Block(tangent))
                }
                (Stage::Down(down), StagePass::Down(_)) => (down.tangent(&h_dot)?, StageTangent::Down(h_dot)),
                _ => return Err(mismatch()),
            };
            tangents.push(tangent);
            h_dot = next;
        }
        let top_dot = top_tangent(&self.final_first, &top, &h_dot.f_flatten(1, -1)?)?;
        // 4. The reverse of the pairs.
        let mut grads = ParamGrads::new();
        let (p_features, p_e) = top_second_backward(top_layers, &top, &top_dot, p_rho.as_ref(), &mut grads)?;
        let mut p = p_features.f_view(last.as_slice())?;
        for (((stage, pass), adjoint), tangent) in stages.iter().zip(&passes).zip(&adjoints).zip(&tangents).rev() {
            p = match (stage, pass, adjoint, tangent) {
                (
                    Stage::Block(block),
                    StagePass::Block(pass),
                    StageAdjoint::Block(adjoint),
                    StageTangent::Block(tangent),
                ) => {
                    let (below, from_time) =
                        block.second_backward((pass, adjoint, tangent), &p, &time.act, &mut grads)?;
                    time.add_act_adjoint(from_time)?;
                    below
                }
                (
                    Stage::Down(down),
                    StagePass::Down(input),
                    StageAdjoint::Down(g_out),
                    StageTangent::Down(input_dot),
                ) => down.second_backward((input, input_dot), g_out, &p, &mut grads)?,
                _ => return Err(mismatch()),
            };
        }
        time.backward(&self.time_mlp, p_e, &mut grads)?;
        Ok((loss, grads))
    }
}

/// One of the ValueFunction's layers between the time MLP and the flattening, with what each
/// sweep keeps of it.
enum Stage<'a> {
    Block(&'a ResidualTemporalBlock),
    Down(&'a Downsample1d),
}

enum StagePass {
    Block(ResidualPass),
    /// The downsampling's input.
    Down(Tensor),
}

enum StageAdjoint {
    Block(ResidualAdjoints),
    /// Of the downsampling's output.
    Down(Tensor),
}

enum StageTangent {
    Block(ResidualTangents),
    /// Of the downsampling's input.
    Down(Tensor),
}

fn mismatch() -> Error {
    Error::internal("value function sweeps", "a stage's records do not match its layer")
}
