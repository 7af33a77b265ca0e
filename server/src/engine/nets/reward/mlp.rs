//! `mlp { hidden }` (flat samples), item [*shape]: the windowed MLP's layout over the whole
//! flattened sample, d = 32: `time_mlp` (`time_mlp.1.*`, `time_mlp.3.*`) and
//! `net = Sequential(Linear(n + 32, hidden[0]), Mish, ..., Linear(hidden[-1], 1))` (`net.0.*`,
//! `net.2.*`, ..., `net.{2 len(hidden)}.*`) for n the number of elements of an item.
//!
//! [`MlpHead`], the `time_mlp` + `net` pair scoring rows of features, is shared with
//! [`super::windowed_mlp`], whose rows are windows of a trajectory.

use tch::Tensor;
use tch::nn;

use super::checks::validate_hidden;
use crate::engine::nets::blocks::{Linear, Mish, TimeMlp};
use crate::engine::nets::mlp::{MLP_TIME_DIM, stack, stack_params};
use crate::error::{Error, Result};

/// The flat MLP's hyperparameters: `features` elements per item.
#[derive(Debug, Clone)]
pub(super) struct MlpPlan {
    features: i64,
    hidden: Vec<i64>,
}

impl MlpPlan {
    /// `features`: the item's element count, already checked positive and bounded.
    pub(super) fn new(features: i64, hidden: &[usize]) -> Result<Self> {
        Ok(Self { features, hidden: validate_hidden(hidden)? })
    }

    pub(super) fn params(&self) -> u128 {
        MlpHead::params(self.features, &self.hidden)
    }

    pub(super) fn build(&self, root: &nn::Path) -> Result<MlpNet> {
        Ok(MlpNet { head: MlpHead::new(root, self.features, &self.hidden)? })
    }
}

/// `time_mlp` + `net`: Linear/Mish layers over [..., features] concatenated with a 32-wide time
/// embedding, ending in one output.
#[derive(Debug)]
pub(super) struct MlpHead {
    pub(super) time_mlp: TimeMlp,
    /// Hidden layers (Mish after each), then the output layer.
    pub(super) layers: Vec<Linear>,
}

impl MlpHead {
    pub(super) fn params(features: i64, hidden: &[i64]) -> u128 {
        stack_params(features, hidden, 1)
    }

    pub(super) fn new(p: &nn::Path, features: i64, hidden: &[i64]) -> Result<Self> {
        let (time_mlp, layers) = stack(p, features, hidden, 1)?;
        Ok(Self { time_mlp, layers })
    }

    pub(super) fn output_layer(&self) -> Option<&Linear> {
        self.layers.last()
    }

    /// `features`: [B, N, F], `t`: float [B] -> [B, N] (one score per row, all rows of an item
    /// sharing its time embedding).
    pub(super) fn forward(&self, features: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let size = features.size();
        let rows = match size.as_slice() {
            &[_, rows, _] => rows,
            other => return Err(Error::internal("reward MLP", format!("features of shape {other:?}"))),
        };
        // -1 keeps the batch: no size in a traced export names it (`engine::export`).
        let t_emb = self.time_mlp.forward(t, mish)?.f_unsqueeze(1)?.f_expand([-1, rows, MLP_TIME_DIM], false)?;
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

/// The flat MLP over samples [B, *shape].
#[derive(Debug)]
pub(super) struct MlpNet {
    pub(super) head: MlpHead,
}

impl MlpNet {
    pub(super) fn forward(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        let flat = x.f_flatten(1, -1)?.f_unsqueeze(1)?;
        Ok(self.head.forward(&flat, t, mish)?.f_squeeze_dim(1)?)
    }

    pub(super) fn output_layer(&self) -> Option<&Linear> {
        self.head.output_layer()
    }
}
