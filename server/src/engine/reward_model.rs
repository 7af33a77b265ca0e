//! [`RewardModel`]: a stored reward (or discriminator) model as it is served: the function
//! rho with its manifest. rho is a trained network ([`RewardNet`], with for Algorithm 2 rewards
//! the per-step input standardisation it was trained under) or a bring-your-own TorchScript
//! module ([`TorchScriptReward`]); callers (Score, Gradient, guided sampling, OIP, export) use
//! this type alone and never ask which.
//!
//! Every method here takes `x` in the diffusion models' normalized units (what rho was trained
//! on, and what an uploaded module is called with); raw units are the serving layer's business
//! (the normalizer is affine, so the gradient with respect to raw inputs is this gradient times
//! [`crate::engine::normalizer::Normalizer::jacobian`]).
//!
//! Algorithm 2 rewards see `(x - input_mean[t]) / input_std[t]` rather than `x`; the tables are
//! applied here, inside rho, so that callers (Score, Gradient, guided sampling) all evaluate
//! and differentiate the same function of the normalized state.

use std::path::Path;

use tch::{Device, Kind, Tensor};

use super::manifest::RewardUploadManifest;
use super::nets::RewardNet;
use super::relative_reward::{RewardManifest, RewardSource, UploadedReward};
use super::sampling::{RewardFn, autograd_rho_and_grad};
use super::torchscript::TorchScriptReward;
use crate::error::{Error, Result};

/// Name of the per-step standardisation tables stored beside an Algorithm 2 reward's weights.
pub const STEP_NORM_FILE: &str = "step_norm.safetensors";

/// `input_mean` and `input_std`, `[T, *item_shape]`, indexed by time.
#[derive(Debug)]
struct StepNorm {
    mean: Tensor,
    std: Tensor,
}

/// What computes rho.
#[derive(Debug)]
enum Rho {
    Native { net: RewardNet, step_norm: Option<StepNorm> },
    TorchScript(TorchScriptReward),
}

#[derive(Debug)]
pub struct RewardModel {
    pub manifest: RewardManifest,
    rho: Rho,
}

impl RewardModel {
    /// Builds the model of a stored record from `manifest` and its file `path` (blocking):
    /// a native network's weights loaded strictly, with, when the manifest says so, the step
    /// standardisation tables from `dir`; or a bring-your-own module, loaded and validated
    /// again as at upload.
    pub fn load(manifest: RewardManifest, path: &Path, dir: &Path, device: Device) -> Result<Self> {
        match manifest.architecture {
            RewardSource::Native(_) => Self::load_native(manifest, path, dir, device),
            RewardSource::Uploaded(UploadedReward::Torchscript { signature }) => {
                let upload = RewardUploadManifest {
                    signature,
                    n_timesteps: manifest.n_timesteps,
                    space: manifest.space.clone(),
                    normalizer: manifest.normalizer.clone(),
                    base_model: manifest.base_model.clone(),
                };
                let module = TorchScriptReward::load_and_validate(path, &upload, device)?;
                Ok(Self { manifest, rho: Rho::TorchScript(module) })
            }
        }
    }

    fn load_native(manifest: RewardManifest, weights: &Path, dir: &Path, device: Device) -> Result<Self> {
        let RewardSource::Native(architecture) = &manifest.architecture else {
            return Err(Error::internal("reward loading", "not a native reward"));
        };
        let item_shape = manifest.space.item_shape();
        let net = RewardNet::load(architecture, &item_shape, weights, device)?;
        let step_norm = if manifest.step_normalization {
            let path = dir.join(STEP_NORM_FILE);
            let tables = Tensor::read_safetensors(&path)
                .map_err(|e| Error::DataLoss(format!("{STEP_NORM_FILE} is unreadable: {e}")))?;
            let find = |name: &str| -> Result<Tensor> {
                let t = tables
                    .iter()
                    .find(|(n, _)| n == name)
                    .map(|(_, t)| t.to_kind(Kind::Float).to_device(device))
                    .ok_or_else(|| Error::DataLoss(format!("{STEP_NORM_FILE} has no '{name}' table")))?;
                let mut want = vec![manifest.n_timesteps as i64];
                want.extend(&item_shape);
                if t.size() != want {
                    return Err(Error::DataLoss(format!(
                        "{STEP_NORM_FILE}: '{name}' has shape {:?}, expected {want:?}",
                        t.size()
                    )));
                }
                Ok(t)
            };
            Some(StepNorm { mean: find("input_mean")?, std: find("input_std")? })
        } else {
            None
        };
        Ok(Self { manifest, rho: Rho::Native { net, step_norm } })
    }

    /// Shape of one item, without the batch dimension.
    pub fn item_shape(&self) -> &[i64] {
        match &self.rho {
            Rho::Native { net, .. } => net.item_shape(),
            Rho::TorchScript(m) => m.item_shape(),
        }
    }

    pub fn n_timesteps(&self) -> usize {
        self.manifest.n_timesteps
    }

    /// Window length h of a windowed reward.
    pub fn window(&self) -> Option<usize> {
        match &self.rho {
            Rho::Native { net, .. } => net.window(),
            Rho::TorchScript(_) => None,
        }
    }

    pub fn parameter_count(&self) -> u64 {
        match &self.rho {
            Rho::Native { net, .. } => net.parameter_count(),
            Rho::TorchScript(m) => m.parameter_count(),
        }
    }

    /// Bytes the model holds in memory, for the registry's cache (parameters as float32 for a
    /// native network; a module's parameters at their own width).
    pub fn parameter_bytes(&self) -> u64 {
        match &self.rho {
            Rho::Native { net, .. } => net.parameter_count().saturating_mul(4),
            Rho::TorchScript(m) => m.parameter_bytes(),
        }
    }

    /// Another handle on this model for a serving thread's helper (a batch's rows split across
    /// threads): a native network shares its weights and tables ([`RewardNet::replica`]), a
    /// TorchScript module is shared ([`TorchScriptReward::replica`]).
    pub fn replica(&self) -> Result<Self> {
        match &self.rho {
            Rho::Native { net, step_norm } => Ok(Self {
                manifest: self.manifest.clone(),
                rho: Rho::Native {
                    net: net.replica()?,
                    step_norm: step_norm
                        .as_ref()
                        .map(|s| StepNorm { mean: s.mean.shallow_clone(), std: s.std.shallow_clone() }),
                },
            }),
            Rho::TorchScript(m) => Ok(Self { manifest: self.manifest.clone(), rho: Rho::TorchScript(m.replica()) }),
        }
    }

    /// The weights stop requiring gradients (a copy that is only evaluated and traced; the
    /// input gradient is unaffected). A module's parameters are left as they are: it is never
    /// traced (its file is its export).
    pub fn freeze(&mut self) {
        if let Rho::Native { net, .. } = &mut self.rho {
            net.weights_mut().var_store_mut().freeze();
        }
    }

    /// The batch size to evaluate `n` items at ([`RewardNet::padded_batch`]; a module's own
    /// `n`: what it computes is unknown, so padding might only add work, and the padded
    /// rows' zeros are not inputs its author promised to handle).
    pub fn padded_batch(&self, n: i64) -> i64 {
        match &self.rho {
            Rho::Native { net, .. } => net.padded_batch(n),
            Rho::TorchScript(_) => n,
        }
    }

    /// rho's input: `x` itself, or standardised per step for Algorithm 2 rewards.
    fn input(step_norm: Option<&StepNorm>, n_timesteps: usize, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        match step_norm {
            None => Ok(x.shallow_clone()),
            Some(s) => {
                let t = checked_t(t, n_timesteps)?;
                Ok(x.f_sub(&s.mean.f_index_select(0, &t)?)?.f_div(&s.std.f_index_select(0, &t)?)?)
            }
        }
    }

    /// rho(x, t), `[B]`; differentiable with respect to `x` when grad mode is on.
    pub fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        match &self.rho {
            Rho::Native { net, step_norm } => net.rho(&Self::input(step_norm.as_ref(), self.n_timesteps(), x, t)?, t),
            Rho::TorchScript(m) => m.rho(x, t),
        }
    }

    /// Per-window values `[B, H / h]` (`[B, 1]` for unwindowed architectures and modules).
    pub fn per_window(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        match &self.rho {
            Rho::Native { net, step_norm } => {
                net.per_window(&Self::input(step_norm.as_ref(), self.n_timesteps(), x, t)?, t)
            }
            Rho::TorchScript(m) => Ok(m.rho(x, t)?.f_unsqueeze(1)?),
        }
    }

    /// rho `[B]` and the per-window values from one pass (see `RewardNet::rho_and_windows`).
    pub fn rho_and_windows(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        match &self.rho {
            Rho::Native { net, step_norm } => {
                net.rho_and_windows(&Self::input(step_norm.as_ref(), self.n_timesteps(), x, t)?, t)
            }
            Rho::TorchScript(m) => {
                let rho = m.rho(x, t)?;
                let windows = rho.f_unsqueeze(1)?;
                Ok((rho, windows))
            }
        }
    }

    /// Per-step values `[B, H]` of a windowed reward.
    pub fn per_step(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        match &self.rho {
            Rho::Native { net, step_norm } => {
                net.per_step(&Self::input(step_norm.as_ref(), self.n_timesteps(), x, t)?, t)
            }
            Rho::TorchScript(m) => Err(Error::invalid(format!(
                "per-step values need a windowed reward (windowed_mlp); this one is a TorchScript module ({})",
                m.signature()
            ))),
        }
    }

    /// (rho `[B]`, grad_x rho with respect to normalized `x`), without autograd history. Works
    /// inside a no-grad region (a native network's gradient needs no graph; a module's
    /// backward enables grad mode locally).
    pub fn grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        match &self.rho {
            Rho::Native { net, step_norm } => {
                let (rho, grad) = net.grad(&Self::input(step_norm.as_ref(), self.n_timesteps(), x, t)?, t)?;
                match step_norm {
                    None => Ok((rho, grad)),
                    // d input / d x = 1 / input_std[t], elementwise.
                    Some(s) => Ok((rho, grad.f_div(&s.std.f_index_select(0, t)?)?)),
                }
            }
            // Autograd through the module, as PyTorch's `torch.autograd.grad(rho.sum(), x)`;
            // parameter gradients are not accumulated (only x is asked for).
            Rho::TorchScript(m) => tch::with_grad(|| {
                let x_req = x.f_detach_copy()?.f_set_requires_grad(true)?;
                let rho = m.rho(&x_req, t)?;
                let sum = rho.f_sum(None::<Kind>)?;
                let grad = Tensor::f_run_backward(&[&sum], &[&x_req], false, false)
                    .map_err(|e| Error::FailedPrecondition(format!("the TorchScript reward's backward failed: {e}")))?
                    .pop()
                    .filter(Tensor::defined);
                let grad = match grad {
                    Some(g) => g,
                    None => x_req.f_zeros_like()?,
                };
                Ok((rho.f_detach()?, grad))
            }),
        }
    }
}

/// `t` as an index into the step tables, range-checked (RewardNet checks shapes).
fn checked_t(t: &Tensor, n_timesteps: usize) -> Result<Tensor> {
    if t.kind() != Kind::Int64 || t.dim() != 1 {
        return Err(Error::invalid(format!("t: expected int64 [B], got {:?} {:?}", t.kind(), t.size())));
    }
    let big_t = n_timesteps as i64;
    if t.numel() > 0 && (t.min().int64_value(&[]) < 0 || t.max().int64_value(&[]) >= big_t) {
        return Err(Error::invalid(format!("t: values must lie in [0, {big_t})")));
    }
    Ok(t.shallow_clone())
}

impl RewardFn for RewardModel {
    fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        RewardModel::rho(self, x, t)
    }

    /// Guidance takes a native network's own gradient, as serving does (the closed form or
    /// hand-written backward); a module keeps autograd through its rho with guidance's checks
    /// (an output that does not depend on x is refused, not a zero gradient).
    fn rho_and_grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        match &self.rho {
            Rho::Native { .. } => self.grad(x, t),
            Rho::TorchScript(_) => autograd_rho_and_grad(&|x, t| self.rho(x, t), x, t),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::manifest::Space;
    use crate::engine::nets::RewardArchitecture;
    use crate::engine::normalizer::Normalizer;

    fn manifest(step_normalization: bool) -> RewardManifest {
        let architecture = RewardArchitecture::Mlp { hidden: vec![8] };
        let space = Space::Sample { shape: vec![3] };
        RewardManifest { step_normalization, ..RewardManifest::for_tests(architecture, space, Normalizer::Identity, 4) }
    }

    /// The step-standardised gradient equals autograd through the whole composite.
    #[test]
    fn step_normalized_gradient_is_the_chain_rule() {
        let dir = tempfile::tempdir().expect("tmp");
        let m = manifest(true);
        let net = RewardNet::new(&RewardArchitecture::Mlp { hidden: vec![8] }, &[3], 0, Device::Cpu).expect("net");
        net.save(&dir.path().join("w.safetensors")).expect("save");
        let mean = Tensor::randn([4, 3], (Kind::Float, Device::Cpu));
        let std = Tensor::rand([4, 3], (Kind::Float, Device::Cpu)) + 0.5;
        Tensor::write_safetensors(
            &[("input_mean", &mean), ("input_std", &std), ("target_std", &std)],
            dir.path().join(STEP_NORM_FILE),
        )
        .expect("tables");
        let model = RewardModel::load(m, &dir.path().join("w.safetensors"), dir.path(), Device::Cpu).expect("load");
        let x = Tensor::randn([5, 3], (Kind::Float, Device::Cpu));
        let t = Tensor::from_slice(&[0i64, 1, 2, 3, 1]);
        let (rho, grad) = model.grad(&x, &t).expect("grad");

        let xr = x.detach().set_requires_grad(true);
        let direct = net.rho(&((&xr - mean.index_select(0, &t)) / std.index_select(0, &t)), &t).expect("rho");
        let want = Tensor::run_backward(&[direct.sum(Kind::Float)], &[&xr], false, false);
        assert!(rho.allclose(&direct.detach(), 1e-6, 1e-6, false));
        assert!(grad.allclose(&want[0], 1e-5, 1e-6, false));
        assert!(model.rho(&x, &Tensor::from_slice(&[0i64, 1, 2, 3, 4])).is_err(), "t outside [0, T)");
    }

    #[test]
    fn missing_step_tables_are_data_loss() {
        let dir = tempfile::tempdir().expect("tmp");
        let m = manifest(true);
        let net = RewardNet::new(&RewardArchitecture::Mlp { hidden: vec![8] }, &[3], 0, Device::Cpu).expect("net");
        net.save(&dir.path().join("w.safetensors")).expect("save");
        match RewardModel::load(m, &dir.path().join("w.safetensors"), dir.path(), Device::Cpu) {
            Err(Error::DataLoss(msg)) => assert!(msg.contains(STEP_NORM_FILE), "{msg}"),
            other => panic!("expected DataLoss, got {other:?}"),
        }
    }
}
