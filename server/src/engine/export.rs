//! Models out as TorchScript: a stored native network traced into a module a PyTorch user
//! loads with `torch.jit.load`, no relreward needed (`DownloadModel` with `torchscript`).
//!
//! - A reward or discriminator becomes `forward(x, t) -> rho`: `x` float32 `[B, *item_shape]`
//!   in the dataset's **raw** units (the normalizer, and an Algorithm 2 reward's per-step
//!   standardisation, are inside), `t` int64 `[B]`, rho float32 `[B]`: Score's numbers, and
//!   `torch.autograd.grad` through it gives Gradient's raw-unit gradient.
//! - A native diffusion model becomes `forward(x, t) -> prediction`: the denoiser network
//!   itself over **normalized** inputs, eps or x0 as its manifest's parametrization says (the
//!   convention of a TorchScript upload, so the export uploads back as one).
//!
//! Tracing records the operations one forward pass runs, with the weights as constants. Two
//! rules make the record the function: no size that names the batch in the nets' shape
//! arithmetic (flatten, unflatten, -1), so the graph serves any batch size; and no tensor
//! built from host values inside the pass (the tracer records its factory call, not its
//! data), so constants such as the normalizer's are made before tracing, and the hand-fused
//! kernels (`nets::kernels`, whose results are host data to the tracer) are switched off for
//! the traced pass, which then records libtorch's own operations. [`trace`] checks
//! the saved module on a second batch size and other inputs before it leaves, so a net that
//! ever broke a rule fails the export instead of handing out a wrong module.

use std::cell::RefCell;
use std::path::Path;

use tch::{CModule, Device, Kind, Tensor};

use super::denoiser::Denoiser;
use super::manifest::Conditioning;
use super::nets::kernels;
use super::normalizer::Normalize;
use super::reward_model::RewardModel;
use crate::error::{Error, Result};

/// Batch sizes of the traced pass and of the check: distinct, and neither 1 (a 1 could hide
/// a broadcast that only works for one item).
const TRACE_BATCH: i64 = 2;
const CHECK_BATCH: i64 = 3;
/// How far the loaded module may stray from the network it was traced from (float32 reruns
/// of the same operations; only the order of a reduction can differ).
const CHECK_TOLERANCE: f64 = 1e-5;

/// The raw-unit reward rho(x, t) of `model`, traced and saved to `out`. The model's weights
/// must not require gradients (see [`RewardModel::freeze`]): a traced constant cannot.
pub fn trace_reward(model: &RewardModel, out: &Path) -> Result<()> {
    let manifest = &model.manifest;
    let dims = manifest.space.normalizer_dims();
    // The normalizer's offset and scale as tensors made before tracing: a tensor built from
    // host values inside the traced pass is recorded as an empty factory call (zeros) without
    // its data. unnormalize(0) is the offset exactly, the Jacobian the scale, so (x - offset)
    // * scale is `normalize`'s float32 arithmetic.
    let mut probe_shape = vec![1];
    probe_shape.extend_from_slice(model.item_shape());
    let probe = Tensor::f_zeros(&probe_shape, (Kind::Float, Device::Cpu))?;
    let offset = manifest.normalizer.unnormalize(&probe, dims);
    let scale = manifest.normalizer.jacobian(&probe, dims);
    let forward = |x: &Tensor, t: &Tensor, _: Option<&Tensor>| model.rho(&x.f_sub(&offset)?.f_mul(&scale)?, t);
    trace("RewardRho", model.item_shape(), model.n_timesteps(), None, &forward, out)
}

/// The denoiser network over normalized inputs, traced and saved to `out` (see the module doc):
/// `forward(x, t)`, or `forward(x, t, cond)` for a conditional model (the upload contract).
pub fn trace_denoiser(
    net: &dyn Denoiser,
    item_shape: &[i64],
    n_timesteps: usize,
    conditioning: Option<&Conditioning>,
    out: &Path,
) -> Result<()> {
    trace("Denoiser", item_shape, n_timesteps, conditioning, &|x, t, c| net.forward(x, t, c), out)
}

/// A traced pass: (x, t) and, for a conditional network, its condition.
type Forward<'a> = dyn Fn(&Tensor, &Tensor, Option<&Tensor>) -> Result<Tensor> + 'a;

/// A condition per item, deterministic like [`inputs`]: labels cycling through the classes, or
/// embeddings of a sine ramp.
fn condition(c: &Conditioning, batch: i64, phase: f64) -> Result<Tensor> {
    Ok(match *c {
        Conditioning::Labels { num_classes, .. } => {
            let labels: Vec<i64> = (0..batch).map(|i| (i + phase as i64) % num_classes as i64).collect();
            Tensor::from_slice(&labels)
        }
        Conditioning::Embedding { dim } => Tensor::f_arange(batch * dim as i64, (Kind::Float, Device::Cpu))?
            .f_mul_scalar(0.3)?
            .f_add_scalar(phase)?
            .f_sin()?
            .f_reshape([batch, dim as i64])?,
    })
}

/// Inputs for `batch` items, deterministic and without touching libtorch's global generator
/// (jobs may be drawing from it): x = sin of a ramp, inside [-1, 1] like every fitted
/// normalizer's range; t spread over 0..T.
fn inputs(item_shape: &[i64], n_timesteps: usize, batch: i64, phase: f64) -> Result<(Tensor, Tensor)> {
    let mut shape = vec![batch];
    shape.extend_from_slice(item_shape);
    let numel: i64 = shape.iter().product();
    let x = Tensor::f_arange(numel, (Kind::Float, Device::Cpu))?.f_mul_scalar(0.7)?.f_add_scalar(phase)?.f_sin()?;
    let last = n_timesteps.saturating_sub(1) as i64;
    let t: Vec<i64> = (0..batch).map(|i| i * last / (batch - 1).max(1)).collect();
    Ok((x.f_reshape(&shape)?, Tensor::from_slice(&t)))
}

fn trace(
    name: &str,
    item_shape: &[i64],
    n_timesteps: usize,
    conditioning: Option<&Conditioning>,
    forward: &Forward<'_>,
    out: &Path,
) -> Result<()> {
    // libtorch's operations only, so that the tracer records the whole pass (module doc).
    kernels::with_libtorch_ops(|| {
        let (x, t) = inputs(item_shape, n_timesteps, TRACE_BATCH, 0.0)?;
        let cond = conditioning.map(|c| condition(c, TRACE_BATCH, 0.0)).transpose()?;
        // The pass once outside the tracer, so that an error is ours (with its message) and the
        // traced pass below can only repeat a pass that worked.
        let _ = forward(&x, &t, cond.as_ref())?;
        let failed = RefCell::new(None);
        let mut closure = |inputs: &[Tensor]| match forward(&inputs[0], &inputs[1], inputs.get(2)) {
            Ok(y) => vec![y],
            Err(e) => {
                *failed.borrow_mut() = Some(e);
                Vec::new()
            }
        };
        let mut traced_inputs = vec![x, t];
        traced_inputs.extend(cond);
        let traced = CModule::create_by_tracing(name, "forward", &traced_inputs, &mut closure);
        if let Some(e) = failed.into_inner() {
            return Err(e);
        }
        let module = traced.map_err(|e| Error::internal("tracing the export", e))?;
        module.save(out).map_err(|e| Error::internal("saving the traced export", e))?;

        // The file as a user will load it, on a batch size it was not traced with.
        let loaded = CModule::load(out).map_err(|e| Error::internal("loading the traced export back", e))?;
        let (x, t) = inputs(item_shape, n_timesteps, CHECK_BATCH, 1.0)?;
        let cond = conditioning.map(|c| condition(c, CHECK_BATCH, 1.0)).transpose()?;
        let want = tch::no_grad(|| forward(&x, &t, cond.as_ref()))?;
        let mut check_inputs = vec![&x, &t];
        check_inputs.extend(cond.as_ref());
        let got = tch::no_grad(|| loaded.forward_ts(&check_inputs)).map_err(|e| {
            Error::internal("checking the traced export", format!("it does not run on a batch of {CHECK_BATCH}: {e}"))
        })?;
        let err = if got.size() == want.size() {
            got.f_sub(&want)?.f_abs()?.f_max()?.double_value(&[])
        } else {
            f64::INFINITY
        };
        if err.is_nan() || err > CHECK_TOLERANCE {
            return Err(Error::internal(
                "checking the traced export",
                format!(
                    "on a batch of {CHECK_BATCH} it gives {:?} differing by {err} from the network's {:?}",
                    got.size(),
                    want.size()
                ),
            ));
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::manifest::{Architecture, Space};
    use crate::engine::nets::NativeDenoiser;

    /// A frozen float32 CPU network is the case where `Mish::Fused` would take the hand-fused
    /// kernel; traced, the module must still compute the network (the kernel's result would
    /// be recorded as a constant) on a batch size it was not traced with.
    #[test]
    fn traced_native_denoisers_compute_the_network() {
        let cases = [
            (Architecture::Mlp { hidden: vec![16, 8] }, Space::Sample { shape: vec![3, 2] }),
            (
                Architecture::TemporalUnet { dim: 8, dim_mults: vec![1, 2] },
                Space::Trajectory { horizon: 8, action_dim: 2, obs_dim: 3 },
            ),
        ];
        for (architecture, space) in cases {
            let mut net = NativeDenoiser::new(&architecture, &space, None, 0, Device::Cpu).expect("network");
            net.freeze();
            let dir = tempfile::tempdir().expect("tmp");
            let out = dir.path().join("model.pt");
            let item_shape = net.item_shape().to_vec();
            trace_denoiser(&net, &item_shape, 10, None, &out).expect("traced, saved and checked");
            let loaded = CModule::load(&out).expect("load");
            let (x, t) = inputs(&item_shape, 10, 5, 2.0).expect("inputs");
            let want = tch::no_grad(|| net.forward(&x, &t, None)).expect("network");
            let got = tch::no_grad(|| loaded.forward_ts(&[&x, &t])).expect("module");
            let diff = (&got - &want).abs().max().double_value(&[]);
            assert!(diff < 1e-5, "{architecture:?}: the module differs from the network by {diff}");
        }
    }
}
