//! `windowed_mlp { window: h, hidden }` (maze rewards), item [H, D] with h dividing H. d = 32.
//! `net = Sequential(Linear(h D + 32, hidden[0]), Mish, ..., Linear(hidden[-1], 1))`
//! (`net.0.*`, `net.2.*`, ..., `net.{2 len(hidden)}.*`) scores one window: its h rows
//! flattened row-major ([row_k | row_k+1 | ...], each row [action | observation]) and
//! concatenated with the time embedding. The trajectory is split into H / h non-overlapping
//! windows (per-window values [B, H / h]); rho is their MEAN. Per-step values [B, H] score
//! the stride-1 window starting at each step k (rows k..k+h-1, the end padded by repeating
//! the last row), so per_step[:, j h] = per_window[:, j] and h = 1 gives g(s, a, t). The
//! weights depend on h and D only, so one file loads for any horizon divisible by h.

use tch::Tensor;
use tch::nn;

use super::checks::{to_i64, trajectory_shape, validate_hidden};
use super::mlp::MlpHead;
use crate::engine::nets::blocks::{Linear, Mish};
use crate::error::{Error, Result};

/// The windowed MLP's hyperparameters, checked against the trajectory's shape.
#[derive(Debug, Clone)]
pub(super) struct WindowedMlpPlan {
    horizon: i64,
    transition_dim: i64,
    window: i64,
    hidden: Vec<i64>,
}

impl WindowedMlpPlan {
    pub(super) fn new(item_shape: &[i64], window: usize, hidden: &[usize]) -> Result<Self> {
        let (horizon, transition_dim) = trajectory_shape(item_shape, "windowed_mlp")?;
        let window = to_i64(window, "architecture.window")?;
        if window <= 0 {
            return Err(Error::invalid(format!("architecture.window: {window} must be positive")));
        }
        if horizon % window != 0 {
            return Err(Error::invalid(format!(
                "architecture.window: horizon {horizon} is not divisible by window {window}"
            )));
        }
        let hidden = validate_hidden(hidden)?;
        Ok(Self { horizon, transition_dim, window, hidden })
    }

    pub(super) fn params(&self) -> u128 {
        MlpHead::params(self.transition_dim.saturating_mul(self.window), &self.hidden)
    }

    pub(super) fn build(&self, root: &nn::Path) -> Result<WindowedMlpNet> {
        Ok(WindowedMlpNet {
            horizon: self.horizon,
            transition_dim: self.transition_dim,
            window: self.window,
            head: MlpHead::new(root, self.window * self.transition_dim, &self.hidden)?,
        })
    }
}

/// The windowed MLP over trajectories [B, H, D].
#[derive(Debug)]
pub(super) struct WindowedMlpNet {
    horizon: i64,
    transition_dim: i64,
    pub(super) window: i64,
    pub(super) head: MlpHead,
}

impl WindowedMlpNet {
    /// [B, H / h]: one value per non-overlapping window.
    pub(super) fn per_window(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        self.head.forward(&self.rows(x)?, t, mish)
    }

    /// The head's rows: [B, H, D] -> [B, H / h, h, D] -> [B, H / h, h D]; no size names the
    /// batch, so a traced export (`engine::export`) serves any batch size.
    pub(super) fn rows(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_unflatten(1, [self.horizon / self.window, self.window])?.f_flatten(2, 3)?)
    }

    /// [B, H]: one value per stride-1 window starting at each step, the end padded by
    /// repeating the last row.
    pub(super) fn per_step(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let padded = if self.window > 1 {
            let last =
                x.f_narrow(1, self.horizon - 1, 1)?.f_expand([-1, self.window - 1, self.transition_dim], false)?;
            Tensor::f_cat(&[x, &last], 1)?
        } else {
            x.shallow_clone()
        };
        // [B, H, D, h] -> [B, H, h, D] -> [B, H, h D] (rows of each window in order).
        let windows = padded.f_unfold(1, self.window, 1)?.f_permute([0, 1, 3, 2])?.f_flatten(2, 3)?;
        self.head.forward(&windows, t, mish)
    }

    pub(super) fn output_layer(&self) -> Option<&Linear> {
        self.head.output_layer()
    }
}
