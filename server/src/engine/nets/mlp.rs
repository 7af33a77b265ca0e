//! An MLP denoiser for samples of any shape [B, *shape] (flat vectors, small latents, short
//! trajectories): the sample is flattened to n features, concatenated with a learned time
//! embedding, passed through Linear + Mish hidden layers, and projected back to n features.
//!
//! PyTorch layout (and parameter names):
//! - `time_mlp = Sequential(SinusoidalPosEmb(32), Linear(32, 128), Mish, Linear(128, 32))`
//!   (`time_mlp.1.*`, `time_mlp.3.*`), the TemporalUnet's time MLP at a fixed width of 32;
//! - `net = Sequential(Linear(n + 32, h0), Mish, Linear(h0, h1), Mish, ..., Linear(h_last, n))`
//!   (`net.0.*`, `net.2.*`, ..., `net.{2 len(hidden)}.*`).
//!
//! The time width is fixed rather than tied to `hidden[0]` so that small hidden widths (the
//! sinusoidal embedding needs at least 4 features) and wide ones behave alike.

use tch::Tensor;
use tch::nn::Path;

use super::blocks::{Linear, Mish, TimeMlp, linear_params, total};
use crate::error::{Error, Result};

/// Width of the MLP denoiser's time embedding.
pub const MLP_TIME_DIM: i64 = 32;
/// Hidden width of the time MLP (4x, as in the TemporalUnet).
pub const MLP_TIME_HIDDEN: i64 = 4 * MLP_TIME_DIM;
/// Bounds on the hidden layers, far above practical sizes; they keep the arithmetic in i64.
pub const MAX_LAYERS: usize = 64;
pub const MAX_HIDDEN: i64 = 1 << 20;
pub const MAX_FEATURES: i64 = 1 << 40;

/// Parameters of `time_mlp` + `net` with `outputs` outputs (module docs), computed without
/// allocating: the layout this denoiser and the reward MLPs (`reward::mlp::MlpHead`) share.
pub(crate) fn stack_params(features: i64, hidden: &[i64], outputs: i64) -> u128 {
    let mut parts = vec![TimeMlp::params(MLP_TIME_DIM, MLP_TIME_HIDDEN, MLP_TIME_DIM)];
    let mut width_in = features.saturating_add(MLP_TIME_DIM);
    for &h in hidden {
        parts.push(linear_params(width_in, h));
        width_in = h;
    }
    parts.push(linear_params(width_in, outputs));
    total(&parts)
}

/// `time_mlp` and the `net` layers (hidden layers, then the output layer of `outputs`) under
/// `p`, with PyTorch's names (module docs).
pub(crate) fn stack(p: &Path, features: i64, hidden: &[i64], outputs: i64) -> Result<(TimeMlp, Vec<Linear>)> {
    let time_mlp = TimeMlp::new(&(p / "time_mlp"), MLP_TIME_DIM, MLP_TIME_HIDDEN, MLP_TIME_DIM)?;
    let net = p / "net";
    let mut layers = Vec::with_capacity(hidden.len() + 1);
    let mut width_in = features + MLP_TIME_DIM;
    for (i, &h) in hidden.iter().enumerate() {
        layers.push(Linear::new(&(&net / (2 * i)), width_in, h)?);
        width_in = h;
    }
    layers.push(Linear::new(&(&net / (2 * hidden.len())), width_in, outputs)?);
    Ok((time_mlp, layers))
}

#[derive(Debug)]
pub struct MlpDenoiser {
    features: i64,
    time_mlp: TimeMlp,
    /// Hidden layers followed by the output layer (Mish between consecutive layers).
    layers: Vec<Linear>,
}

impl MlpDenoiser {
    /// Checks the hyperparameters; errors name the manifest field at fault.
    pub fn validate(features: i64, hidden: &[i64]) -> Result<()> {
        if features <= 0 || features > MAX_FEATURES {
            return Err(Error::invalid(format!("space: {features} features per sample must be in 1..={MAX_FEATURES}")));
        }
        if hidden.is_empty() || hidden.len() > MAX_LAYERS || hidden.iter().any(|&h| h <= 0 || h > MAX_HIDDEN) {
            return Err(Error::invalid(format!(
                "architecture.hidden: {hidden:?} must hold 1 to {MAX_LAYERS} widths in 1..={MAX_HIDDEN}"
            )));
        }
        Ok(())
    }

    /// Number of parameters, computed without allocating; call after [`Self::validate`].
    pub fn params(features: i64, hidden: &[i64]) -> u128 {
        stack_params(features, hidden, features)
    }

    /// `features`: n = the product of the sample shape.
    pub fn new(p: &Path, features: i64, hidden: &[i64]) -> Result<Self> {
        Self::validate(features, hidden)?;
        let (time_mlp, layers) = stack(p, features, hidden, features)?;
        Ok(Self { features, time_mlp, layers })
    }

    pub fn features(&self) -> i64 {
        self.features
    }

    /// `x`: float [B, *shape] with prod(shape) = n; `t`: float [B]. Returns x's shape.
    pub fn forward(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        // Batch-agnostic shapes (flatten / unflatten): a traced export serves any batch size.
        let shape = x.size();
        let flat = x.f_flatten(1, -1)?;
        let mut h = Tensor::f_cat(&[&flat, &self.time_mlp.forward(t, Mish::Fused)?], 1)?;
        let last = self.layers.len().saturating_sub(1);
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.forward(&h)?;
            if i < last {
                h = Mish::Fused.forward(&h)?;
            }
        }
        Ok(h.f_unflatten(1, &shape[1..])?)
    }
}
