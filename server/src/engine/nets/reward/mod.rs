//! The relative reward network rho_theta(x, t): a scalar per item whose input gradient is
//! trained to match the difference of two diffusion models (Algorithm 1 of "Extracting Reward
//! Functions from Diffusion Models"). [`RewardNet`] owns its variables ([`Weights`]), validates
//! its architecture against the item shape before allocating, computes rho, its input gradient
//! (for guidance), training's alignment loss with every parameter's gradient (without
//! autograd) and the input gradient with a differentiable graph (autograd's double backward,
//! the reference the tests hold training's gradients to), and stores its weights as strict
//! safetensors under PyTorch module names (the independent PyTorch implementation is
//! `relreward_dev.reward_nets` in `dev/python`, which `tests/python/reward_nets_reference.py`
//! drives for the tests).
//!
//! Module map, one file per architecture ([`RewardArchitecture`]), each with its hyperparameter
//! checks, parameter count, layers (with their PyTorch names) and forward pass:
//! - `architecture`: [`RewardArchitecture`] and the validated plan that dispatches to
//!   (with the checks they share in `checks`):
//! - `windowed_mlp`: `windowed_mlp { window, hidden }` (maze rewards), rho the mean over
//!   non-overlapping windows of a trajectory [H, D], with per-window and per-step values;
//! - `value_function`: `value_function { widths }` (locomotion rewards), Diffuser's
//!   ValueFunction over a trajectory [H, D];
//! - `conv_encoder`: `conv_encoder { widths }` (image-like latents [C, H, W]), strided 2D
//!   convolutions and global pooling;
//! - `mlp`: `mlp { hidden }` (flat samples of any shape), and the MLP head the windowed
//!   MLP shares;
//! - `closed_form`: that head's input gradient and training gradient written out by hand
//!   ([`RewardNet::grad`], [`RewardNet::alignment_gradients`]), so serving and training the
//!   two MLP rewards skip autograd (and training its double backward);
//! - `second_order`: what the convolutional rewards' training gradients share (the loss's
//!   derivatives, the final block's sweeps) around their layers' sweeps
//!   (`blocks::second_order`), so they train without autograd too.
//!
//! Every activation is Mish (smooth, as the double backward and the paper's existence theorem
//! want), every time embedding is Diffuser's
//! `Sequential(SinusoidalPosEmb(d), Linear(d, 4 d), Mish, Linear(4 d, d))` under `time_mlp.1.*`
//! and `time_mlp.3.*`, fed the diffusion step t as a float.
//!
//! All forward passes use tch's fallible operations: bad shapes are errors, never panics.
//! Mish is [`Mish::Fused`] (libtorch's op, or the hand-fused kernel where nothing is
//! differentiated) except in `grad_create_graph`, the pass autograd differentiates twice
//! ([`Mish::TwiceDifferentiable`]).

mod architecture;
mod checks;
mod closed_form;
mod conv_encoder;
mod mlp;
mod second_order;
#[cfg(test)]
mod tests;
mod value_function;
mod windowed_mlp;

use std::path::Path;

use tch::{Device, Kind, Tensor};

pub use self::architecture::RewardArchitecture;
use self::architecture::{Network, Plan};
use self::second_order::AlignmentTerms;
use super::blocks::Mish;
use super::inputs::check_inputs;
use super::weights::{Start, Weights};
use crate::error::{Error, Result};

/// An alignment loss with its parameter gradients computed without autograd
/// ([`RewardNet::alignment_gradients`]): no autograd graph behind either.
#[derive(Debug)]
pub struct AlignmentGradients {
    /// The loss, a scalar.
    pub loss: Tensor,
    /// d loss / d parameter, by the parameters' names in the network's `VarStore`.
    pub grads: Vec<(String, Tensor)>,
}

/// A relative reward network rho_theta(x, t) with its variables.
#[derive(Debug)]
pub struct RewardNet {
    weights: Weights,
    network: Network,
    architecture: RewardArchitecture,
    item_shape: Vec<i64>,
}

impl RewardNet {
    /// Validates the architecture against the item shape and returns the number of parameters
    /// the network would have, without allocating it. Errors name the field at fault.
    pub fn planned_parameter_count(architecture: &RewardArchitecture, item_shape: &[i64]) -> Result<u64> {
        Plan::new(architecture, item_shape)?.params()
    }

    /// A freshly initialised network (PyTorch's default initialisation, drawn from `seed`) on
    /// `device`, for items of `item_shape` ([H, D] for trajectories, the sample shape
    /// otherwise).
    pub fn new(architecture: &RewardArchitecture, item_shape: &[i64], seed: u64, device: Device) -> Result<Self> {
        Self::build(architecture, item_shape, Start::Seeded(seed), device)
    }

    fn build(architecture: &RewardArchitecture, item_shape: &[i64], start: Start, device: Device) -> Result<Self> {
        let plan = Plan::new(architecture, item_shape)?;
        let (weights, network) = Weights::build(device, plan.params()?, "RewardNet", start, |root| plan.build(root))?;
        Ok(Self { weights, network, architecture: architecture.clone(), item_shape: item_shape.to_vec() })
    }

    /// Builds the network and loads its weights from a safetensors file (strictly, see
    /// [`Weights::load_strict`]).
    pub fn load(architecture: &RewardArchitecture, item_shape: &[i64], path: &Path, device: Device) -> Result<Self> {
        let net = Self::build(architecture, item_shape, Start::Replaced, device)?;
        net.weights.load_strict(path)?;
        Ok(net)
    }

    /// Another handle on this network for another thread: the same architecture over the same
    /// weight storage (no copy; [`Weights::share_storage_of`]). libtorch reads a tensor from
    /// several threads safely; tch's handles are not `Sync`, hence one per thread. Only for
    /// evaluation: a trainer's updates through one handle would be seen by all.
    pub fn replica(&self) -> Result<Self> {
        let mut net =
            Self::build(&self.architecture, &self.item_shape, Start::Replaced, self.weights.var_store().device())?;
        net.weights.share_storage_of(&self.weights)?;
        Ok(net)
    }

    /// Writes every weight to `path` atomically (see [`Weights::save_atomic`]).
    pub fn save(&self, path: &Path) -> Result<()> {
        self.weights.save_atomic(path)
    }

    /// The variables: names, loading, the `VarStore` a trainer optimises.
    pub fn weights(&self) -> &Weights {
        &self.weights
    }

    /// Mutable access for a trainer (e.g. `double()` for precise checks); changing the set of
    /// variables breaks the network.
    pub fn weights_mut(&mut self) -> &mut Weights {
        &mut self.weights
    }

    pub fn parameter_count(&self) -> u64 {
        self.weights.parameter_count()
    }

    pub fn architecture(&self) -> &RewardArchitecture {
        &self.architecture
    }

    /// Shape of one item, without the batch dimension.
    pub fn item_shape(&self) -> &[i64] {
        &self.item_shape
    }

    /// E.g. "windowed_mlp(h=4, hidden=[128, 64, 32])".
    pub fn describe(&self) -> String {
        self.architecture.to_string()
    }

    /// Whether per-step values exist (windowed architectures).
    pub fn is_windowed(&self) -> bool {
        matches!(self.network, Network::WindowedMlp(_))
    }

    /// Window length h of the windowed MLP (`None` for the other architectures).
    pub fn window(&self) -> Option<usize> {
        match &self.network {
            Network::WindowedMlp(net) => Some(net.window as usize),
            _ => None,
        }
    }

    /// The batch size to evaluate `n` items at: `n`, except for the convolutional rewards on
    /// the CPU, padded up to the next of 1, 2, 3, 4, 6, 8, 12, 16, 24, ... (powers of two and
    /// one and a half times them). oneDNN compiles a kernel for every convolution shape it
    /// meets, batch size included, and keeps the last 1024: a dynamic batcher passing every
    /// size from 1 to 256 compiled kernels all the time (an eighth of the ValueFunction's
    /// serving thread, measured with perf). TF Serving's `allowed_batch_sizes` is the same
    /// remedy; at most a third of a padded pass is padding.
    pub fn padded_batch(&self, n: i64) -> i64 {
        let compiled = matches!(self.network, Network::ValueFunction(_) | Network::ConvEncoder(_));
        if !compiled || self.weights.var_store().device() != tch::Device::Cpu || n <= 4 {
            return n;
        }
        let power = 1i64 << (63 - n.leading_zeros());
        if n == power {
            n
        } else if n <= power + power / 2 {
            power + power / 2
        } else {
            power * 2
        }
    }

    /// The dtype of the weights (float32 unless the store was converted); inputs must match.
    pub fn kind(&self) -> Kind {
        let output = match &self.network {
            Network::WindowedMlp(net) => net.output_layer(),
            Network::Mlp(net) => net.output_layer(),
            Network::ValueFunction(net) => Some(&net.final_second),
            Network::ConvEncoder(net) => Some(&net.final_second),
        };
        output.map_or(Kind::Float, |layer| layer.weight.kind())
    }

    /// rho(x, t): `x` [B, *item_shape] in the weights' dtype, `t` int64 [B] -> [B].
    /// Differentiable with respect to `x` and the parameters when grad mode is on.
    pub fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let t = self.check_inputs(x, t)?;
        self.rho_unchecked(x, &t, Mish::Fused)
    }

    /// Per-window values: [B, H / h] for the windowed MLP (rho is their mean); [B, 1] = rho
    /// for the other architectures.
    pub fn per_window(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let t = self.check_inputs(x, t)?;
        match &self.network {
            Network::WindowedMlp(net) => net.per_window(x, &t, Mish::Fused),
            _ => Ok(self.rho_unchecked(x, &t, Mish::Fused)?.f_unsqueeze(1)?),
        }
    }

    /// (rho [B], per-window values) from one pass: for the windowed MLP rho is the mean of the
    /// windows it has just computed (the same numbers as [`RewardNet::rho`] and
    /// [`RewardNet::per_window`] called apart, at the cost of one of them).
    pub fn rho_and_windows(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        let t = self.check_inputs(x, t)?;
        match &self.network {
            Network::WindowedMlp(net) => {
                let windows = net.per_window(x, &t, Mish::Fused)?;
                Ok((windows.f_mean_dim([1i64].as_slice(), false, None::<Kind>)?, windows))
            }
            _ => {
                let rho = self.rho_unchecked(x, &t, Mish::Fused)?;
                let windows = rho.f_unsqueeze(1)?;
                Ok((rho, windows))
            }
        }
    }

    /// Per-step values [B, H] of the windowed MLP: the window starting at each step (the end
    /// padded by repeating the last row). InvalidArgument for other architectures.
    pub fn per_step(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let Network::WindowedMlp(net) = &self.network else {
            return Err(Error::invalid(format!(
                "per-step values need a windowed reward (windowed_mlp); this one is {}",
                self.describe()
            )));
        };
        let t = self.check_inputs(x, t)?;
        net.per_step(x, &t, Mish::Fused)
    }

    /// (rho [B], grad_x of sum(rho), the shape of `x`), both without autograd history and
    /// without autograd: works inside a no-grad region, accumulates no parameter gradient.
    /// The MLP rewards take the closed form (`closed_form.rs`: one forward keeping Mish's
    /// slopes, one backward of a few matrix products), the convolutional ones a hand-written
    /// backward over their blocks' tapes (`blocks/mod.rs`: transposed convolutions, group-norm
    /// input backwards, Mish slopes). Either way rho is the forward's bit for bit (Score's
    /// answer) and the gradient autograd's to float rounding (`tests.rs`).
    pub fn grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        let t = self.check_inputs(x, t)?;
        let _no_graph = tch::no_grad_guard();
        match &self.network {
            Network::ValueFunction(net) => return net.value_and_grad(x, &t),
            Network::ConvEncoder(net) => return net.value_and_grad(x, &t),
            Network::WindowedMlp(_) | Network::Mlp(_) => {}
        }
        let (head, features) =
            self.head_rows(x)?.ok_or_else(|| Error::internal("reward gradient", "an MLP reward without its head"))?;
        let pass = head.pass(&features, &t, false)?;
        // As rho_unchecked: the mean of the windows, or the flat MLP's one row.
        let rho = match &self.network {
            Network::WindowedMlp(_) => pass.out.f_mean_dim([1i64].as_slice(), false, None::<Kind>)?,
            _ => pass.out.f_squeeze_dim(1)?,
        };
        Ok((rho, pass.grad.f_view(x.size().as_slice())?))
    }

    /// The MLP head and its rows [B, N, F] for the architectures with a closed form; `None`
    /// for the convolutional ones.
    fn head_rows(&self, x: &Tensor) -> Result<Option<(&mlp::MlpHead, Tensor)>> {
        Ok(match &self.network {
            Network::WindowedMlp(net) => Some((&net.head, net.rows(x)?)),
            Network::Mlp(net) => Some((&net.head, x.f_flatten(1, -1)?.f_unsqueeze(1)?)),
            Network::ValueFunction(_) | Network::ConvEncoder(_) => None,
        })
    }

    /// grad_x of sum(rho) WITH its graph (create_graph): a loss computed from it (with grad mode
    /// on) backpropagates to the parameters through the double backward of Algorithm 1. The
    /// graph is built from a detached copy of `x`, so no gradient flows back into `x`. The one
    /// pass differentiated twice, hence [`Mish::TwiceDifferentiable`] (the fused op's second
    /// derivative is NaN for inputs above about 88.7; `blocks/mod.rs`).
    pub fn grad_create_graph(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let t = self.check_inputs(x, t)?;
        tch::with_grad(|| {
            let x_req = x.f_detach_copy()?.f_set_requires_grad(true)?;
            let rho = self.rho_unchecked(&x_req, &t, Mish::TwiceDifferentiable)?;
            input_gradient_with_graph(&rho, &x_req)
        })
    }

    /// Algorithm 1's alignment loss at (`point`, `t`) against `target` (entry `weights`, rho's
    /// L2 penalty `rho_l2`) with every parameter's gradient, without autograd: the MLP heads
    /// in closed form (`closed_form.rs`), the convolutional rewards by the four sweeps of
    /// `blocks::second_order` (`second_order.rs`, each network's `alignment_grads`). The loss
    /// equals [`super::super::relative_reward::alignment_loss`]'s value; the gradients equal its
    /// double backward to float rounding (`tests.rs`).
    pub fn alignment_gradients(
        &self,
        point: &Tensor,
        t: &Tensor,
        target: &Tensor,
        weights: Option<&Tensor>,
        rho_l2: f64,
    ) -> Result<AlignmentGradients> {
        let t = self.check_inputs(point, t)?;
        let _no_graph = tch::no_grad_guard();
        let terms = |rho: &Tensor, grad: &Tensor| alignment_terms(rho, grad, target, weights, rho_l2);
        let (loss, grads) = match &self.network {
            Network::ValueFunction(net) => net.alignment_grads(point, &t, terms)?,
            Network::ConvEncoder(net) => net.alignment_grads(point, &t, terms)?,
            Network::WindowedMlp(_) | Network::Mlp(_) => {
                let (head, features) = self
                    .head_rows(point)?
                    .ok_or_else(|| Error::internal("reward closed form", "an MLP reward without its head"))?;
                let pass = head.pass(&features, &t, true)?;
                // rho is the mean of an item's rows' outputs (one row for the flat MLP).
                let rows = pass.out.size()[1];
                let rho = pass.out.f_mean_dim([1i64].as_slice(), false, None::<Kind>)?;
                let grad = pass.grad.f_view(point.size().as_slice())?;
                let AlignmentTerms { loss, r, p_rho } = terms(&rho, &grad)?;
                let r = r.f_view(pass.grad.size().as_slice())?;
                let p_out = p_rho
                    .map(|p| -> Result<Tensor> {
                        Ok(p.f_div_scalar(rows as f64)?.f_unsqueeze(1)?.f_expand_as(&pass.out)?.f_reshape([-1])?)
                    })
                    .transpose()?;
                (loss, head.alignment_grads(&pass, &r, p_out.as_ref())?)
            }
        };
        let names: std::collections::HashMap<usize, String> =
            self.weights.var_store().variables().into_iter().map(|(name, v)| (v.data_ptr() as usize, name)).collect();
        let grads = grads
            .into_iter()
            .map(|(param, grad)| {
                names
                    .get(&(param.data_ptr() as usize))
                    .map(|name| (name.clone(), grad))
                    .ok_or_else(|| Error::internal("reward alignment gradients", "a gradient of an unknown parameter"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(AlignmentGradients { loss, grads })
    }

    fn rho_unchecked(&self, x: &Tensor, t: &Tensor, mish: Mish) -> Result<Tensor> {
        match &self.network {
            Network::WindowedMlp(net) => {
                Ok(net.per_window(x, t, mish)?.f_mean_dim([1i64].as_slice(), false, None::<Kind>)?)
            }
            Network::Mlp(net) => net.forward(x, t, mish),
            Network::ValueFunction(net) => net.forward(x, t, mish),
            Network::ConvEncoder(net) => net.forward(x, t, mish),
        }
    }

    /// Checks x [B >= 1, *item_shape] (the weights' dtype) and t int64 [B]; returns t as the
    /// weights' float dtype for the time embedding.
    fn check_inputs(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let kind = self.kind();
        check_inputs("reward", x, t, &self.item_shape, kind)?;
        Ok(t.f_to_kind(kind)?)
    }
}

/// mean_batch sum(weights * (grad - target)^2): the alignment term of Algorithm 1's loss
/// (`relative_reward::alignment_loss`, which re-exports this), the loss training reports
/// ([`RewardNet::alignment_gradients`]) and the held-out loss a job reports (from a grad
/// computed without a graph).
pub fn alignment_error(grad: &Tensor, target: &Tensor, weights: Option<&Tensor>) -> Result<Tensor> {
    mean_weighted_square(&grad.f_sub(target)?, weights)
}

/// mean_batch sum(weights * diff^2), diff = grad - target: [`alignment_error`]'s arithmetic,
/// for [`alignment_terms`], which needs diff for r too.
fn mean_weighted_square(diff: &Tensor, weights: Option<&Tensor>) -> Result<Tensor> {
    let squared = diff.f_square()?;
    let squared = match weights {
        Some(w) => squared.f_mul(w)?,
        None => squared,
    };
    // In the inputs' dtype (float32 in training; float64 where a test checks derivations).
    Ok(squared.f_flatten(1, -1)?.f_sum_dim_intlist([1i64].as_slice(), false, None::<Kind>)?.f_mean(None::<Kind>)?)
}

/// The alignment loss at rho [B] and grad (x's shape), by [`alignment_error`]'s arithmetic
/// (the loss every path reports; grad - target computed once for it and r), with
/// r = d loss / d grad = 2 w (grad - target) / B and, under rho's L2 penalty,
/// d loss / d rho = 2 l2 rho / B.
fn alignment_terms(
    rho: &Tensor,
    grad: &Tensor,
    target: &Tensor,
    weights: Option<&Tensor>,
    rho_l2: f64,
) -> Result<AlignmentTerms> {
    let batch = grad.size()[0] as f64;
    let diff = grad.f_sub(target)?;
    let mut loss = mean_weighted_square(&diff, weights)?;
    let mut r = diff.f_mul_scalar(2.0 / batch)?;
    if let Some(w) = weights {
        r = r.f_mul_(w)?;
    }
    let p_rho = if rho_l2 > 0.0 {
        loss = loss.f_add(&rho.f_square()?.f_mean(None::<Kind>)?.f_mul_scalar(rho_l2)?)?;
        Some(rho.f_mul_scalar(2.0 * rho_l2 / batch)?)
    } else {
        None
    };
    Ok(AlignmentTerms { loss, r, p_rho })
}

/// d sum(rho) / d x_req with its differentiable graph (PyTorch's
/// `autograd.grad(rho.sum(), x, create_graph = True)`).
fn input_gradient_with_graph(rho: &Tensor, x_req: &Tensor) -> Result<Tensor> {
    let sum = rho.f_sum(None::<Kind>)?;
    let grad = Tensor::f_run_backward(&[&sum], &[x_req], true, true)?
        .pop()
        .ok_or_else(|| Error::internal("reward gradient", "autograd returned no gradient"))?;
    if grad.defined() { Ok(grad) } else { Ok(x_req.f_zeros_like()?) }
}
