//! The network inside a diffusion model: whatever maps (x_t, t) to a prediction of eps or x0.
//!
//! Implementations: TorchScript modules (`torchscript.rs`) and the native architectures
//! (`nets/`). The DDPM math in `diffusion.rs` only ever sees this trait.

use tch::{Device, Kind, Tensor};

use super::manifest::Conditioning;
use crate::error::{Error, Result};

pub trait Denoiser: Send {
    /// `x`: float32 `[B, *item_shape]` in normalized units; `t`: int64 `[B]` in `0..T`;
    /// `cond`: the condition of each item for a conditional model (the manifest's
    /// `conditioning`: int64 labels `[B]` or float32 embeddings `[B, dim]`), `None` for an
    /// unconditional one. Returns the network's raw prediction, the same shape as `x`. Must be
    /// differentiable with respect to the parameters when called with grad mode on (training),
    /// and is called under `no_grad` for frozen models.
    fn forward(&self, x: &Tensor, t: &Tensor, cond: Option<&Tensor>) -> Result<Tensor>;

    /// Number of scalar parameters (for listings).
    fn parameter_count(&self) -> u64;
}

/// The inputs an upload's validation forward runs on: zeros `[2, *item_shape]` with
/// `t = [0, T - 1]`, the two ends of the schedule, so that a network that breaks at either end
/// (NaN weights, a time embedding that overflows) is refused at upload rather than served.
pub struct ValidationProbe {
    pub x: Tensor,
    pub t: Tensor,
    /// For a conditional model: the null condition where it has one, else label 0 or the zero
    /// vector, for both items.
    pub cond: Option<Tensor>,
    /// `x`'s shape, for messages.
    pub shape: Vec<i64>,
    /// `T - 1`, for messages.
    pub last: i64,
}

impl ValidationProbe {
    pub fn new(
        item_shape: &[i64],
        n_timesteps: usize,
        conditioning: Option<&Conditioning>,
        device: Device,
    ) -> Result<Self> {
        let last = i64::try_from(n_timesteps.saturating_sub(1))
            .map_err(|_| Error::invalid(format!("manifest.n_timesteps: {n_timesteps} is too large")))?;
        let mut shape = vec![2i64];
        shape.extend_from_slice(item_shape);
        let x = Tensor::f_zeros(shape.as_slice(), (Kind::Float, device))?;
        let t = Tensor::f_from_slice(&[0i64, last])?.f_to_device(device)?;
        let cond = conditioning.map(|c| probe_condition(c, 2, device)).transpose()?;
        Ok(Self { x, t, cond, shape, last })
    }

    /// Refuses an output with a NaN or an infinity, naming `what` ran on the probe.
    pub fn check_finite(&self, out: &Tensor, what: &str) -> Result<()> {
        if out.f_isfinite()?.f_all()?.f_int64_value(&[])? == 1 {
            return Ok(());
        }
        Err(Error::invalid(format!(
            "{what} on zeros {:?} with t = [0, {}] returned NaN or infinite values",
            self.shape, self.last
        )))
    }
}

/// `n` copies of a conditional model's null condition (label 0 or zeros where it has none):
/// what an upload's validation forward runs on.
fn probe_condition(c: &Conditioning, n: i64, device: Device) -> Result<Tensor> {
    Ok(match *c {
        Conditioning::Labels { null_class, .. } => {
            Tensor::f_full([n], null_class.unwrap_or(0) as i64, (Kind::Int64, device))?
        }
        Conditioning::Embedding { dim } => Tensor::f_zeros([n, dim as i64], (Kind::Float, device))?,
    })
}
