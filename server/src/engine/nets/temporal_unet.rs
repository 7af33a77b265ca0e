//! Diffuser's `TemporalUnet` (`diffuser/models/temporal.py`, without attention): a 1D U-Net that
//! convolves along the horizon of a trajectory [B, H, D] with the transition features as
//! channels.
//!
//! Structure, for dims = [D, dim * m for m in dim_mults] and levels (in, out) = consecutive pairs:
//! - `time_mlp`: sinusoidal(dim) -> Linear(dim, 4 dim) -> Mish -> Linear(4 dim, dim);
//! - `downs.{i}`: ResidualTemporalBlock(in, out) at `.0`, ResidualTemporalBlock(out, out) at `.1`,
//!   (`.2` is Diffuser's attention slot, an identity here), Downsample1d at `.3` except on the
//!   last level; each level's output is kept as a skip connection;
//! - `mid_block1`, `mid_block2` at the deepest width;
//! - `ups.{i}` over the levels reversed *excluding the first*: concatenate the most recent skip,
//!   ResidualTemporalBlock(2 out, in) at `.0`, ResidualTemporalBlock(in, in) at `.1`, and
//!   Upsample1d at `.3` on *every* up level. Diffuser's `is_last` test there can never be true,
//!   so the upsamplings (levels - 1 of them) exactly undo the downsamplings, and the first level's
//!   skip is never consumed. Both quirks are kept so that Diffuser checkpoints load unchanged;
//! - `final_conv`: Conv1dBlock(dim * dim_mults[0], dim, 5) at `.0`, Conv1d(dim, D, 1) at `.1`.
//!   (Diffuser writes Conv1dBlock(dim, dim), which only works for dim_mults[0] = 1; both agree
//!   there.)

use tch::Tensor;
use tch::nn::Path;

use super::blocks::{
    Conv1d, Conv1dBlock, Downsample1d, Mish, ResidualTemporalBlock, TEMPORAL_KERNEL, TimeMlp, Upsample1d, conv_params,
    total,
};
use crate::error::{Error, Result};

/// Levels beyond this would need horizons of 2^15 and more; the bound also keeps the
/// divisibility arithmetic far from overflow.
pub const MAX_LEVELS: usize = 16;
/// Upper bound on any channel width (dim * mult), far above practical networks; it keeps the
/// width arithmetic (4 dim, 2 width) well inside i64. The real size guard is the parameter
/// budget checked by the caller.
pub const MAX_WIDTH: i64 = 1 << 20;

#[derive(Debug)]
struct DownLevel {
    first: ResidualTemporalBlock,
    second: ResidualTemporalBlock,
    downsample: Option<Downsample1d>,
}

#[derive(Debug)]
struct UpLevel {
    first: ResidualTemporalBlock,
    second: ResidualTemporalBlock,
    upsample: Upsample1d,
}

#[derive(Debug)]
pub struct TemporalUnet {
    horizon: i64,
    transition_dim: i64,
    time_mlp: TimeMlp,
    downs: Vec<DownLevel>,
    mid_block1: ResidualTemporalBlock,
    mid_block2: ResidualTemporalBlock,
    ups: Vec<UpLevel>,
    final_block: Conv1dBlock,
    final_conv: Conv1d,
}

/// Channel widths [D, dim * m...]; call only after [`TemporalUnet::validate`].
fn widths(transition_dim: i64, dim: i64, dim_mults: &[i64]) -> Vec<i64> {
    std::iter::once(transition_dim).chain(dim_mults.iter().map(|m| dim * m)).collect()
}

impl TemporalUnet {
    /// Checks the hyperparameters; errors name the manifest field at fault.
    pub fn validate(horizon: i64, transition_dim: i64, dim: i64, dim_mults: &[i64]) -> Result<()> {
        if transition_dim <= 0 {
            return Err(Error::invalid(format!(
                "space: transition dim (action_dim + obs_dim) {transition_dim} must be positive"
            )));
        }
        if dim <= 0 || dim % 8 != 0 {
            return Err(Error::invalid(format!(
                "architecture.dim: {dim} must be a positive multiple of 8 (GroupNorm with 8 groups)"
            )));
        }
        if dim_mults.is_empty() || dim_mults.len() > MAX_LEVELS || dim_mults.iter().any(|&m| m <= 0) {
            return Err(Error::invalid(format!(
                "architecture.dim_mults: {dim_mults:?} must hold 1 to {MAX_LEVELS} positive multipliers"
            )));
        }
        if dim_mults.iter().any(|&m| dim.checked_mul(m).is_none_or(|w| w > MAX_WIDTH)) {
            return Err(Error::invalid(format!(
                "architecture.dim_mults: {dim_mults:?} times dim {dim} exceeds the maximum width {MAX_WIDTH}"
            )));
        }
        let factor = 1i64 << (dim_mults.len() - 1);
        if horizon <= 0 || horizon % factor != 0 {
            return Err(Error::invalid(format!(
                "space.horizon: {horizon} must be a positive multiple of 2^(levels - 1) = {factor} for dim_mults {dim_mults:?}"
            )));
        }
        Ok(())
    }

    /// Number of parameters the network will have, computed without allocating; call after
    /// [`Self::validate`].
    pub fn params(transition_dim: i64, dim: i64, dim_mults: &[i64]) -> u128 {
        let dims = widths(transition_dim, dim, dim_mults);
        let levels = dims.len() - 1;
        let mut parts = vec![TimeMlp::params(dim, 4 * dim, dim)];
        for (i, pair) in dims.windows(2).enumerate() {
            let (w_in, w_out) = (pair[0], pair[1]);
            parts.push(ResidualTemporalBlock::params(w_in, w_out, dim, TEMPORAL_KERNEL));
            parts.push(ResidualTemporalBlock::params(w_out, w_out, dim, TEMPORAL_KERNEL));
            if i + 1 < levels {
                parts.push(Downsample1d::params(w_out));
            }
        }
        let mid = dims[levels];
        parts.push(ResidualTemporalBlock::params(mid, mid, dim, TEMPORAL_KERNEL));
        parts.push(ResidualTemporalBlock::params(mid, mid, dim, TEMPORAL_KERNEL));
        for pair in dims[1..].windows(2).rev() {
            let (w_in, w_out) = (pair[0], pair[1]);
            parts.push(ResidualTemporalBlock::params(2 * w_out, w_in, dim, TEMPORAL_KERNEL));
            parts.push(ResidualTemporalBlock::params(w_in, w_in, dim, TEMPORAL_KERNEL));
            parts.push(Upsample1d::params(w_in));
        }
        parts.push(Conv1dBlock::params(dims[1], dim, TEMPORAL_KERNEL));
        parts.push(conv_params(dim, transition_dim, 1));
        total(&parts)
    }

    /// Registers the parameters under `p` (the root of the model's `VarStore` for checkpoints
    /// that load in PyTorch as `TemporalUnet.state_dict()`).
    pub fn new(p: &Path, horizon: i64, transition_dim: i64, dim: i64, dim_mults: &[i64]) -> Result<Self> {
        Self::validate(horizon, transition_dim, dim, dim_mults)?;
        let dims = widths(transition_dim, dim, dim_mults);
        let levels = dims.len() - 1;
        let block =
            |path: Path, w_in: i64, w_out: i64| ResidualTemporalBlock::new(&path, w_in, w_out, dim, TEMPORAL_KERNEL);

        let time_mlp = TimeMlp::new(&(p / "time_mlp"), dim, 4 * dim, dim)?;
        let mut downs = Vec::with_capacity(levels);
        for (i, pair) in dims.windows(2).enumerate() {
            let (w_in, w_out) = (pair[0], pair[1]);
            let level = p / "downs" / i;
            downs.push(DownLevel {
                first: block(&level / "0", w_in, w_out)?,
                second: block(&level / "1", w_out, w_out)?,
                downsample: if i + 1 < levels { Some(Downsample1d::new(&(&level / "3"), w_out)?) } else { None },
            });
        }
        let mid = dims[levels];
        let mid_block1 = block(p / "mid_block1", mid, mid)?;
        let mid_block2 = block(p / "mid_block2", mid, mid)?;
        let mut ups = Vec::with_capacity(levels.saturating_sub(1));
        for (i, pair) in dims[1..].windows(2).rev().enumerate() {
            let (w_in, w_out) = (pair[0], pair[1]);
            let level = p / "ups" / i;
            ups.push(UpLevel {
                first: block(&level / "0", 2 * w_out, w_in)?,
                second: block(&level / "1", w_in, w_in)?,
                upsample: Upsample1d::new(&(&level / "3"), w_in)?,
            });
        }
        let final_path = p / "final_conv";
        Ok(Self {
            horizon,
            transition_dim,
            time_mlp,
            downs,
            mid_block1,
            mid_block2,
            ups,
            final_block: Conv1dBlock::new(&(&final_path / "0"), dims[1], dim, TEMPORAL_KERNEL)?,
            final_conv: Conv1d::new(&(&final_path / "1"), dim, transition_dim, 1, 1, 0)?,
        })
    }

    pub fn horizon(&self) -> i64 {
        self.horizon
    }

    pub fn transition_dim(&self) -> i64 {
        self.transition_dim
    }

    /// `x`: float [B, H, D]; `t`: float [B] (the diffusion step, as Diffuser feeds it to the
    /// sinusoidal embedding). Returns [B, H, D].
    pub fn forward(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let mut x = x.f_permute([0, 2, 1])?;
        let t_emb = self.time_mlp.forward(t, Mish::Fused)?;
        let mut skips = Vec::with_capacity(self.downs.len());
        for level in &self.downs {
            x = level.first.forward(&x, &t_emb, Mish::Fused)?;
            x = level.second.forward(&x, &t_emb, Mish::Fused)?;
            skips.push(x.shallow_clone());
            if let Some(down) = &level.downsample {
                x = down.forward(&x)?;
            }
        }
        x = self.mid_block1.forward(&x, &t_emb, Mish::Fused)?;
        x = self.mid_block2.forward(&x, &t_emb, Mish::Fused)?;
        for level in &self.ups {
            let skip =
                skips.pop().ok_or_else(|| Error::internal("TemporalUnet", "more up levels than skip connections"))?;
            x = Tensor::f_cat(&[&x, &skip], 1)?;
            x = level.first.forward(&x, &t_emb, Mish::Fused)?;
            x = level.second.forward(&x, &t_emb, Mish::Fused)?;
            x = level.upsample.forward(&x)?;
        }
        let x = self.final_conv.forward(&self.final_block.forward(&x, Mish::Fused)?)?;
        Ok(x.f_permute([0, 2, 1])?)
    }
}
