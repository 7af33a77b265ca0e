//! [`RewardModel`]: a stored reward (or discriminator) model as it is served: the network
//! rho_theta with its manifest, and for Algorithm 2 rewards the per-step input standardisation
//! it was trained under.
//!
//! Every method here takes `x` in the diffusion models' normalized units (what rho was trained
//! on); raw units are the serving layer's business (the normalizer is affine, so the gradient
//! with respect to raw inputs is this gradient times [`crate::engine::normalizer::Normalizer::jacobian`]).
//!
//! Algorithm 2 rewards see `(x - input_mean[t]) / input_std[t]` rather than `x`; the tables are
//! applied here, inside rho, so that callers (Score, Gradient, guided sampling) all evaluate
//! and differentiate the same function of the normalized state.

use std::path::Path;

use tch::{Device, Kind, Tensor};

use super::nets::RewardNet;
use super::relative_reward::RewardManifest;
use super::sampling::RewardFn;
use crate::error::{Error, Result};

/// Name of the per-step standardisation tables stored beside an Algorithm 2 reward's weights.
pub const STEP_NORM_FILE: &str = "step_norm.safetensors";

/// `input_mean` and `input_std`, `[T, *item_shape]`, indexed by time.
#[derive(Debug)]
struct StepNorm {
    mean: Tensor,
    std: Tensor,
}

#[derive(Debug)]
pub struct RewardModel {
    pub manifest: RewardManifest,
    net: RewardNet,
    step_norm: Option<StepNorm>,
}

impl RewardModel {
    /// Builds the network from `manifest` and loads `weights` (strictly) and, when the manifest
    /// says so, the step standardisation tables from `dir`. Blocking.
    pub fn load(manifest: RewardManifest, weights: &Path, dir: &Path, device: Device) -> Result<Self> {
        let item_shape = manifest.space.item_shape();
        let net = RewardNet::load(&manifest.architecture, &item_shape, weights, device)?;
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
        Ok(Self { manifest, net, step_norm })
    }

    /// Shape of one item, without the batch dimension.
    pub fn item_shape(&self) -> &[i64] {
        self.net.item_shape()
    }

    pub fn n_timesteps(&self) -> usize {
        self.manifest.n_timesteps
    }

    /// Window length h of a windowed reward.
    pub fn window(&self) -> Option<usize> {
        self.net.window()
    }

    pub fn parameter_count(&self) -> u64 {
        self.net.parameter_count()
    }

    /// The weights stop requiring gradients (a copy that is only evaluated and traced; the
    /// input gradient is unaffected).
    pub fn freeze(&mut self) {
        self.net.weights_mut().var_store_mut().freeze();
    }

    /// rho's input: `x` itself, or standardised per step for Algorithm 2 rewards.
    fn input(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        match &self.step_norm {
            None => Ok(x.shallow_clone()),
            Some(s) => {
                let t = self.checked_t(t)?;
                Ok(x.f_sub(&s.mean.f_index_select(0, &t)?)?.f_div(&s.std.f_index_select(0, &t)?)?)
            }
        }
    }

    /// `t` as an index into the step tables, range-checked (RewardNet checks shapes).
    fn checked_t(&self, t: &Tensor) -> Result<Tensor> {
        if t.kind() != Kind::Int64 || t.dim() != 1 {
            return Err(Error::invalid(format!("t: expected int64 [B], got {:?} {:?}", t.kind(), t.size())));
        }
        let big_t = self.manifest.n_timesteps as i64;
        if t.numel() > 0 && (t.min().int64_value(&[]) < 0 || t.max().int64_value(&[]) >= big_t) {
            return Err(Error::invalid(format!("t: values must lie in [0, {big_t})")));
        }
        Ok(t.shallow_clone())
    }

    /// rho(x, t), `[B]`; differentiable with respect to `x` when grad mode is on.
    pub fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.net.rho(&self.input(x, t)?, t)
    }

    /// Per-window values `[B, H / h]` (`[B, 1]` for unwindowed architectures).
    pub fn per_window(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.net.per_window(&self.input(x, t)?, t)
    }

    /// rho `[B]` and the per-window values from one pass (see `RewardNet::rho_and_windows`).
    pub fn rho_and_windows(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        self.net.rho_and_windows(&self.input(x, t)?, t)
    }

    /// Per-step values `[B, H]` of a windowed reward.
    pub fn per_step(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.net.per_step(&self.input(x, t)?, t)
    }

    /// (rho `[B]`, grad_x rho with respect to normalized `x`), without autograd history.
    pub fn grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        let (rho, grad) = self.net.grad(&self.input(x, t)?, t)?;
        match &self.step_norm {
            None => Ok((rho, grad)),
            // d input / d x = 1 / input_std[t], elementwise.
            Some(s) => Ok((rho, grad.f_div(&s.std.f_index_select(0, t)?)?)),
        }
    }
}

impl RewardFn for RewardModel {
    fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        RewardModel::rho(self, x, t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::manifest::Space;
    use crate::engine::nets::RewardArchitecture;
    use crate::engine::normalizer::Normalizer;
    use crate::engine::relative_reward::Objective;

    fn manifest(step_normalization: bool) -> RewardManifest {
        RewardManifest {
            architecture: RewardArchitecture::Mlp { hidden: vec![8] },
            space: Space::Sample { shape: vec![3] },
            normalizer: Normalizer::Identity,
            n_timesteps: 4,
            base_model: "b".into(),
            expert_model: "e".into(),
            datasets: vec![],
            objective: Objective::Discriminator,
            step_normalization,
            inpaint_condition: false,
            final_loss: 0.0,
            eval_loss: None,
        }
    }

    /// The step-standardised gradient equals autograd through the whole composite.
    #[test]
    fn step_normalized_gradient_is_the_chain_rule() {
        let dir = tempfile::tempdir().expect("tmp");
        let m = manifest(true);
        let net = RewardNet::new(&m.architecture, &[3], Device::Cpu).expect("net");
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
        let net = RewardNet::new(&m.architecture, &[3], Device::Cpu).expect("net");
        net.save(&dir.path().join("w.safetensors")).expect("save");
        match RewardModel::load(m, &dir.path().join("w.safetensors"), dir.path(), Device::Cpu) {
            Err(Error::DataLoss(msg)) => assert!(msg.contains(STEP_NORM_FILE), "{msg}"),
            other => panic!("expected DataLoss, got {other:?}"),
        }
    }
}
