//! Adam and an exponential moving average of weights, owned by us rather than libtorch's C++
//! optimizer because a checkpoint must hold the optimizer moments (tch exposes no access to
//! them), and a resumed job must continue the exact same update sequence.
//!
//! Parameters are handled as `(name, tensor)` pairs sorted by name, so the order is stable
//! across processes and moments are saved under the parameter's own name.

use std::collections::HashMap;
use std::path::Path;

use tch::{Kind, Tensor, nn::VarStore};

use crate::error::{Error, Result};

/// The trainable parameters of a var store, sorted by name.
pub fn named_parameters(vs: &VarStore) -> Vec<(String, Tensor)> {
    let mut v: Vec<(String, Tensor)> = vs.variables().into_iter().filter(|(_, t)| t.requires_grad()).collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

/// What a training step hands the optimizer: a loss whose graph autograd differentiates, or a
/// loss with every parameter's gradient already computed (a reward's closed form,
/// `nets/reward/closed_form.rs`), which skips autograd.
pub enum StepLoss {
    Graph(Tensor),
    Computed {
        loss: Tensor,
        /// d loss / d parameter, by parameter name.
        grads: Vec<(String, Tensor)>,
    },
}

impl From<Tensor> for StepLoss {
    fn from(loss: Tensor) -> Self {
        Self::Graph(loss)
    }
}

/// Adam (Kingma & Ba) with PyTorch's update rule and defaults (betas 0.9, 0.999, eps 1e-8,
/// no weight decay), plus optional clipping of the global gradient norm.
///
/// Whether a step applies (its gradient finite) and how much clipping scales it are decided
/// on the host by default: the norm is read before the update is queued, which costs nothing
/// on the CPU. [`Adam::deciding_on_device`] decides both on the parameters' device instead (as
/// PyTorch's `capturable` Adam and GradScaler's `found_inf` do), so a step never makes the host
/// wait for a GPU: the same numbers (tested bit for bit on the CPU), the skip applied as a mask
/// and the step count kept on the device.
pub struct Adam {
    pub lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
    /// Updates applied so far (for bias correction), when decided on the host.
    steps: u64,
    /// Decided on the device: the count there and the constants the decisions pick from
    /// (`steps` is then unused).
    on_device: Option<OnDevice>,
    device: tch::Device,
    /// The moments of all parameters, one flat tensor each (None, as `flat_params`: the
    /// parameters differ in dtype or device, and every update goes parameter by parameter), and each parameter's
    /// moments as views into them (saved and loaded by name).
    flat: Option<(Tensor, Tensor)>,
    /// The parameters' own storage as one flat tensor, each parameter rebound to a view of it
    /// (`flatten_parameters`), so an update is one operation for all of them.
    flat_params: Option<Tensor>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
}

/// What [`Adam::deciding_on_device`] keeps on the parameters' device: the updates applied so
/// far (a 0-dim double), and the constants each step picks from, made once rather than per step
/// (on a GPU each would be an allocation and a fill).
struct OnDevice {
    steps: Tensor,
    /// 0 and 1 as 0-dim doubles.
    zero: Tensor,
    one: Tensor,
    beta2: Tensor,
    lr: Tensor,
    /// 1 - beta1 and 0 in the moments' kind (`lerp`'s weight must be of it).
    m_weight: Tensor,
    m_zero: Tensor,
    /// The last clip threshold and the 0-dim double holding it.
    clip: Option<(f64, Tensor)>,
}

/// One update's coefficients: numbers decided on the host, or 0-dim tensors on the device
/// that already fold in whether the step applies (a skipped step's are those of an update by
/// zero that leaves the moments as they were).
enum Coefficients {
    Host {
        /// Clipping's factor (1: none).
        scale: f64,
        step_size: f64,
        bc2_sqrt: f64,
    },
    Device {
        /// Clipping's factor; 0 for a skipped step.
        scale: Tensor,
        /// m's interpolation weight, 1 - beta1; 0 for a skipped step (in the parameters' kind,
        /// as `lerp` asks).
        m_weight: Tensor,
        /// v's decay, beta2; 1 for a skipped step.
        v_decay: Tensor,
        /// lr / (1 - beta1^steps); 0 for a skipped step.
        step_size: Tensor,
        /// sqrt(1 - beta2^steps); 1 for a skipped step.
        bc2_sqrt: Tensor,
    },
}

impl Adam {
    pub fn new(params: &[(String, Tensor)], lr: f64) -> Self {
        // Flat moments exactly where the parameters themselves could be flattened (one dtype
        // and device).
        let flat_params = flatten_parameters(params);
        let (flat, m, v) = match &flat_params {
            Some(all) => {
                let (m_flat, v_flat) = (all.zeros_like(), all.zeros_like());
                let views = |flat: &Tensor| pieces(flat, params);
                let (m, v) = (views(&m_flat), views(&v_flat));
                (Some((m_flat, v_flat)), m, v)
            }
            _ => {
                let zeros = || params.iter().map(|(_, p)| p.zeros_like().detach()).collect();
                (None, zeros(), zeros())
            }
        };
        let device = params.first().map_or(tch::Device::Cpu, |(_, p)| p.device());
        Self { lr, beta1: 0.9, beta2: 0.999, eps: 1e-8, steps: 0, on_device: None, device, flat, flat_params, m, v }
    }

    /// Decides each step's skip and clip on the parameters' device (`on`) or on the host.
    pub fn deciding_on_device(mut self, on: bool) -> Self {
        let steps = self.steps();
        let kind =
            self.flat.as_ref().map_or_else(|| self.m.first().map_or(Kind::Float, Tensor::kind), |(m, _)| m.kind());
        let scalar = |x: f64, kind: Kind| Tensor::scalar_tensor(x, (kind, self.device));
        self.on_device = on.then(|| OnDevice {
            steps: scalar(steps as f64, Kind::Double),
            zero: scalar(0.0, Kind::Double),
            one: scalar(1.0, Kind::Double),
            beta2: scalar(self.beta2, Kind::Double),
            lr: scalar(self.lr, Kind::Double),
            m_weight: scalar(1.0 - self.beta1, kind),
            m_zero: scalar(0.0, kind),
            clip: None,
        });
        self
    }

    /// Updates applied so far (read from the device when decided there).
    pub fn steps(&self) -> u64 {
        match &self.on_device {
            // A count of whole steps in a double: exact.
            Some(d) => d.steps.double_value(&[]) as u64,
            None => self.steps,
        }
    }

    /// Sets the count of updates applied (a checkpoint's, when resuming).
    pub fn set_steps(&mut self, steps: u64) {
        self.steps = steps;
        if let Some(d) = self.on_device.as_mut() {
            let _ = d.steps.fill_(steps as f64);
        }
    }

    /// Applies one update from the parameters' gradients, then zeroes them, and returns the
    /// global gradient norm before clipping (a 0-dim double on the parameters' device, not
    /// read). Parameters without a gradient are left alone.
    ///
    /// A gradient that is not finite (an inf or NaN from one batch: Adam's moments would turn
    /// it into NaN weights for good) applies nothing: the weights, the moments and the step
    /// count stay as they were, as PyTorch's GradScaler skips such a step; the caller sees the
    /// non-finite norm. Decided on the host, that reads the norm before the update is queued;
    /// decided on the device, nothing is read (docs/architecture.md, "What keeps a GPU busy").
    pub fn step(&mut self, params: &[(String, Tensor)], clip: Option<f64>) -> Tensor {
        let grads: Vec<Option<Tensor>> = params.iter().map(|(_, p)| Some(p.grad()).filter(Tensor::defined)).collect();
        let norm = self.apply(params, &grads, clip);
        zero_grads(params);
        norm
    }

    /// [`Adam::step`] from gradients computed without autograd (a [`StepLoss::Computed`]),
    /// matched to the parameters by name; a parameter without one is left alone.
    pub fn step_with(
        &mut self,
        params: &[(String, Tensor)],
        grads: Vec<(String, Tensor)>,
        clip: Option<f64>,
    ) -> Tensor {
        let mut by_name: HashMap<String, Tensor> = grads.into_iter().collect();
        let grads: Vec<Option<Tensor>> = params.iter().map(|(name, _)| by_name.remove(name)).collect();
        self.apply(params, &grads, clip)
    }

    /// The update of [`Adam::step`] with the gradients given, in the parameters' order.
    fn apply(&mut self, params: &[(String, Tensor)], grads: &[Option<Tensor>], clip: Option<f64>) -> Tensor {
        let _guard = tch::no_grad_guard();
        // Every parameter with a gradient and one flat set of moments: the update runs once over
        // all of them concatenated (the same elementwise operations on the same values, so the
        // same numbers; a few large operations where a small network's update was some ten
        // small ones per parameter).
        let flat_grad = match (&self.flat, grads.iter().all(Option::is_some)) {
            (Some(_), true) if !grads.is_empty() => {
                let pieces: Vec<Tensor> = grads.iter().flatten().map(|g| g.reshape([-1])).collect();
                Some(Tensor::cat(&pieces, 0))
            }
            _ => None,
        };
        let norm = match (&flat_grad, grads.iter().flatten().next()) {
            (Some(g), _) => g.square().sum(Kind::Double).sqrt(),
            (None, None) => Tensor::zeros([], (Kind::Double, self.device)),
            (None, Some(_)) => {
                let squares: Vec<Tensor> = grads.iter().flatten().map(|g| g.square().sum(Kind::Double)).collect();
                Tensor::stack(&squares, 0).sum(Kind::Double).sqrt()
            }
        };
        let Some(coefficients) = self.coefficients(&norm, clip) else {
            return norm;
        };
        if let (Some(g), Some((m, v))) = (flat_grad, self.flat.as_mut()) {
            let update = coefficients.update(&g, m, v, (self.beta1, self.beta2, self.eps));
            match self.flat_params.as_mut().filter(|flat| views_of(flat, params)) {
                Some(flat) => {
                    let _ = flat.g_add_(&update);
                }
                None => {
                    for ((_, p), u) in params.iter().zip(pieces(&update, params)) {
                        let _ = p.shallow_clone().g_add_(&u);
                    }
                }
            }
            return norm;
        }
        for (((_, p), g), (m, v)) in params.iter().zip(grads).zip(self.m.iter_mut().zip(self.v.iter_mut())) {
            let Some(g) = g else { continue };
            let update = coefficients.update(g, m, v, (self.beta1, self.beta2, self.eps));
            let _ = p.shallow_clone().g_add_(&update);
        }
        norm
    }

    /// This step's coefficients, counting it as applied; `None` when decided on the host that
    /// it applies nothing (its gradient not finite).
    fn coefficients(&mut self, norm: &Tensor, clip: Option<f64>) -> Option<Coefficients> {
        let (beta1, beta2) = (self.beta1, self.beta2);
        let Some(d) = self.on_device.as_mut() else {
            let norm = norm.double_value(&[]);
            if !norm.is_finite() {
                return None;
            }
            // torch.nn.utils.clip_grad_norm_: scale by max_norm / (norm + 1e-6) when above.
            let scale = match clip {
                Some(c) if norm > c => c / (norm + 1e-6),
                _ => 1.0,
            };
            self.steps += 1;
            let (bc1, bc2) = (1.0 - beta1.powf(self.steps as f64), 1.0 - beta2.powf(self.steps as f64));
            return Some(Coefficients::Host { scale, step_size: self.lr / bc1, bc2_sqrt: bc2.sqrt() });
        };
        // The host's formulas on 0-dim doubles, each picked by `where` between its value and
        // what leaves the moments unchanged (never multiplied by the 0/1 mask: a skipped first
        // step's lr / (1 - beta1^0) is an infinity, and 0 * inf a NaN).
        let applied = norm.isfinite();
        let _ = d.steps.g_add_(&applied.to_kind(Kind::Double));
        let scale = match clip {
            Some(c) => {
                // The clip as a tensor, made again only when it changes: c / (norm + 1e-6) is
                // then the host's division (a scalar numerator would be 1 / ((norm + 1e-6) / c)).
                let c_t = match &mut d.clip {
                    Some((held, t)) if *held == c => t.shallow_clone(),
                    slot => {
                        let t = Tensor::scalar_tensor(c, (Kind::Double, norm.device()));
                        *slot = Some((c, t.shallow_clone()));
                        t
                    }
                };
                (c_t / (norm + 1e-6)).where_self(&norm.gt(c), &d.one)
            }
            None => d.one.shallow_clone(),
        };
        let bc1: Tensor = 1.0 - Tensor::pow_scalar(beta1, &d.steps);
        let bc2: Tensor = 1.0 - Tensor::pow_scalar(beta2, &d.steps);
        Some(Coefficients::Device {
            scale: scale.where_self(&applied, &d.zero),
            m_weight: d.m_weight.where_self(&applied, &d.m_zero),
            v_decay: d.beta2.where_self(&applied, &d.one),
            step_size: (&d.lr / bc1).where_self(&applied, &d.zero),
            bc2_sqrt: bc2.sqrt().where_self(&applied, &d.one),
        })
    }

    /// The parameters' flat storage when they were flattened (see [`flatten_parameters`]) and
    /// still are views of it: what [`Ema::new`] averages in one operation.
    pub fn flat_params(&self, params: &[(String, Tensor)]) -> Option<&Tensor> {
        self.flat_params.as_ref().filter(|flat| views_of(flat, params))
    }

    /// Saves the moments as `<dir>/<file>` (safetensors, names "m.<param>" and "v.<param>").
    pub fn save(&self, params: &[(String, Tensor)], path: &Path) -> Result<()> {
        let mut named: Vec<(String, Tensor)> = Vec::with_capacity(2 * params.len());
        for ((name, _), (m, v)) in params.iter().zip(self.m.iter().zip(&self.v)) {
            // Saved from the CPU, so a checkpoint is the same file whatever device trained it.
            named.push((format!("m.{name}"), m.to_device(tch::Device::Cpu)));
            named.push((format!("v.{name}"), v.to_device(tch::Device::Cpu)));
        }
        Tensor::write_safetensors(&named, path).map_err(|e| Error::internal("writing optimizer state", e))
    }

    /// Restores moments saved by [`Adam::save`] for the same parameters; `steps` is restored
    /// by the caller from the checkpoint's state.
    pub fn load(&mut self, params: &[(String, Tensor)], path: &Path) -> Result<()> {
        let stored: HashMap<String, Tensor> = Tensor::read_safetensors(path)
            .map_err(|e| Error::DataLoss(format!("optimizer state unreadable: {e}")))?
            .into_iter()
            .collect();
        let _guard = tch::no_grad_guard();
        for ((name, p), (m, v)) in params.iter().zip(self.m.iter_mut().zip(self.v.iter_mut())) {
            for (prefix, slot) in [("m", m), ("v", v)] {
                let t = stored.get(&format!("{prefix}.{name}")).filter(|t| t.size() == p.size()).ok_or_else(|| {
                    Error::DataLoss(format!("optimizer state lacks {prefix}.{name} of shape {:?}", p.size()))
                })?;
                slot.copy_(t);
            }
        }
        Ok(())
    }
}

impl Coefficients {
    /// Updates the moments `m` and `v` in place from the gradient `g` and returns the step to
    /// add to the parameters.
    ///
    /// torch.optim.Adam's CPU update (`_single_tensor_adam`) op for op, so that the weights
    /// are bitwise those PyTorch would produce (server/tests/training_vs_pytorch.rs):
    ///   m.lerp_(g, 1 - beta1); v.mul_(beta2).addcmul_(g, g, value = 1 - beta2);
    ///   denom = (sqrt(v) / sqrt(bc2)).add_(eps); p.addcdiv_(m, denom, value = -lr / bc1).
    /// tch's addcmul_ / addcdiv_ take no `value`: scaling the first factor gives the same
    /// (value * t1) * t2 and (value * t1) / t2 that libtorch's kernels compute, and p + (value m)
    /// / denom is addcdiv's sum. In place, this makes four temporaries where the composed
    /// formula made eight: about 17 ms instead of 55 ms per update of the benchmark's
    /// 3.7M-parameter TemporalUnet (one thread, the same libtorch ops timed from Python), some
    /// 5% of a DDPM step. The device's coefficients are the same numbers as 0-dim tensors (a
    /// float op with a 0-dim double rounds it to float as it does a scalar).
    fn update(&self, g: &Tensor, m: &mut Tensor, v: &mut Tensor, (beta1, beta2, eps): (f64, f64, f64)) -> Tensor {
        match self {
            Self::Host { scale, step_size, bc2_sqrt } => {
                let g = if *scale == 1.0 { g.shallow_clone() } else { g * *scale };
                let _ = m.lerp_(&g, 1.0 - beta1);
                let _ = v.g_mul_scalar_(beta2).addcmul_(&(&g * (1.0 - beta2)), &g);
                let denom = v.sqrt().g_div_scalar_(*bc2_sqrt).g_add_scalar_(eps);
                (&*m * -*step_size).g_div_(&denom)
            }
            Self::Device { scale, m_weight, v_decay, step_size, bc2_sqrt } => {
                // A skipped step's gradient (inf or NaN somewhere) times its scale 0 is zeroed
                // whole, so that it adds nothing to v; a finite one is unchanged by both.
                let g = (g * scale).nan_to_num_(0.0, 0.0, 0.0);
                // (A no-op but where parameters of several kinds are updated one by one.)
                let _ = m.lerp_tensor_(&g, &m_weight.to_kind(m.kind()));
                let _ = v.g_mul_(v_decay).addcmul_(&(&g * (1.0 - beta2)), &g);
                let denom = v.sqrt().g_div_(bc2_sqrt).g_add_scalar_(eps);
                (&*m * -step_size).g_div_(&denom)
            }
        }
    }
}

/// Rebinds every parameter to a view of one new flat tensor holding their values, in order,
/// and returns it (what PyTorch's `flatten_parameters` and FSDP's flat parameter do): the
/// optimizer and the EMA then update all parameters in one operation each instead of one per
/// parameter, on a GPU one kernel launch instead of tens. Values, names, gradients and
/// autograd are unchanged (a parameter is still its own leaf). One thing differs: an update of
/// the flat tensor does not bump each parameter's version counter, so a graph kept across an
/// update would not notice it (as with PyTorch's flat parameters); the training loop builds
/// every graph after the previous update. `None` for parameters of different dtypes or
/// devices, or none.
pub fn flatten_parameters(params: &[(String, Tensor)]) -> Option<Tensor> {
    let (_, first) = params.first()?;
    if params.iter().any(|(_, p)| p.kind() != first.kind() || p.device() != first.device()) {
        return None;
    }
    let total: i64 = params.iter().map(|(_, p)| p.numel() as i64).sum();
    let _guard = tch::no_grad_guard();
    let flat = Tensor::empty([total], (first.kind(), first.device()));
    for ((_, p), view) in params.iter().zip(pieces(&flat, params)) {
        let mut view = view;
        view.copy_(p);
        p.shallow_clone().set_data(&view);
    }
    Some(flat)
}

/// Whether each parameter is still the view of `flat` that [`flatten_parameters`] made (a
/// caller may have rebound one since, e.g. converting the store's dtype).
fn views_of(flat: &Tensor, params: &[(String, Tensor)]) -> bool {
    let base = flat.data_ptr() as usize;
    let size = flat.kind().elt_size_in_bytes();
    let mut offset = 0usize;
    params.iter().all(|(_, p)| {
        let here = p.data_ptr() as usize == base + offset * size && p.is_contiguous();
        offset += p.numel();
        here
    }) && offset == flat.numel()
}

/// Views of a flat tensor shaped as each parameter, in order.
fn pieces(flat: &Tensor, params: &[(String, Tensor)]) -> Vec<Tensor> {
    let mut offset = 0i64;
    params
        .iter()
        .map(|(_, p)| {
            let n = p.numel() as i64;
            let view = flat.narrow(0, offset, n).view(p.size().as_slice());
            offset += n;
            view
        })
        .collect()
}

/// Global L2 norm of the parameters' current gradients.
pub fn grad_norm(params: &[(String, Tensor)]) -> f64 {
    let _guard = tch::no_grad_guard();
    params
        .iter()
        .map(|(_, p)| p.grad())
        .filter(Tensor::defined)
        .map(|g| g.square().sum(Kind::Double).double_value(&[]))
        .sum::<f64>()
        .sqrt()
}

/// Exponential moving average of weights as in Diffuser's trainer: before `start` the average
/// is reset to the current weights; from then on, every `every` steps,
/// ema = decay * ema + (1 - decay) * current.
pub struct Ema {
    pub decay: f64,
    pub every: u64,
    pub start: u64,
    /// The average of each parameter (views of `flat`'s second tensor when there is one).
    shadow: Vec<Tensor>,
    /// The parameters' flat storage (see [`flatten_parameters`]) and the average's, so an
    /// update is two operations instead of three per parameter.
    flat: Option<(Tensor, Tensor)>,
}

impl Ema {
    /// `flat`: the parameters' flat storage when they are views of one ([`Adam::flat_params`]).
    pub fn new(params: &[(String, Tensor)], decay: f64, every: u64, start: u64, flat: Option<&Tensor>) -> Self {
        let _guard = tch::no_grad_guard();
        let (shadow, flat) = match flat.filter(|flat| views_of(flat, params)) {
            Some(flat) => {
                let average = flat.detach().copy();
                (pieces(&average, params), Some((flat.shallow_clone(), average)))
            }
            None => (params.iter().map(|(_, p)| p.detach().copy()).collect(), None),
        };
        Self { decay, every, start, shadow, flat }
    }

    /// Call after optimisation step `step` (1-based) if it counts (its update applied and its
    /// loss was finite). `counts`: that decision as a 0-dim bool on the device, when Adam made
    /// it there ([`Adam::deciding_on_device`]); the average then moves only where it is true,
    /// with the same numbers.
    pub fn after_step(&mut self, params: &[(String, Tensor)], step: u64, counts: Option<&Tensor>) {
        if !step.is_multiple_of(self.every) {
            return;
        }
        let _guard = tch::no_grad_guard();
        let reset = step < self.start;
        // For a skipped step: ema = 1 ema + 0 current (or, before start, ema kept).
        let masked = counts.map(|counts| {
            let scalar = |x: f64| Tensor::scalar_tensor(x, (Kind::Double, counts.device()));
            let pick = |yes: f64, no: f64| scalar(yes).where_self(counts, &scalar(no));
            (counts, pick(self.decay, 1.0), pick(1.0 - self.decay, 0.0))
        });
        let average_into = |average: &mut Tensor, current: &Tensor| match (&masked, reset) {
            (None, true) => average.copy_(current),
            (Some((applied, _, _)), true) => average.copy_(&current.where_self(applied, average)),
            (None, false) => {
                let _ = average.g_mul_scalar_(self.decay).g_add_(&(current * (1.0 - self.decay)));
            }
            (Some((_, decay, rest)), false) => {
                let _ = average.g_mul_(decay).g_add_(&(current * rest));
            }
        };
        if let Some((current, average)) = self.flat.as_mut().filter(|(current, _)| views_of(current, params)) {
            average_into(average, current);
            return;
        }
        for ((_, p), s) in params.iter().zip(self.shadow.iter_mut()) {
            average_into(s, p);
        }
    }

    /// The averaged weights, by parameter name.
    pub fn named(&self, params: &[(String, Tensor)]) -> Vec<(String, Tensor)> {
        params.iter().zip(&self.shadow).map(|((n, _), s)| (n.clone(), s.shallow_clone())).collect()
    }

    pub fn load(&mut self, params: &[(String, Tensor)], path: &Path) -> Result<()> {
        let stored: HashMap<String, Tensor> = Tensor::read_safetensors(path)
            .map_err(|e| Error::DataLoss(format!("EMA weights unreadable: {e}")))?
            .into_iter()
            .collect();
        let _guard = tch::no_grad_guard();
        for ((name, p), s) in params.iter().zip(self.shadow.iter_mut()) {
            let t = stored
                .get(name)
                .filter(|t| t.size() == p.size())
                .ok_or_else(|| Error::DataLoss(format!("EMA weights lack {name} of shape {:?}", p.size())))?;
            s.copy_(t);
        }
        Ok(())
    }
}

fn zero_grads(params: &[(String, Tensor)]) {
    for (_, p) in params {
        let mut g = p.grad();
        if g.defined() {
            let _ = g.zero_();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, nn, nn::Module, nn::OptimizerConfig};

    fn setup(seed: i64) -> (VarStore, nn::Linear) {
        tch::manual_seed(seed);
        let vs = VarStore::new(Device::Cpu);
        let lin = nn::linear(vs.root() / "lin", 3, 2, Default::default());
        (vs, lin)
    }

    fn loss(lin: &nn::Linear) -> Tensor {
        let x = Tensor::from_slice(&[0.5f32, -1.0, 2.0, 1.5, 0.0, -0.5]).reshape([2, 3]);
        lin.forward(&x).square().sum(Kind::Float)
    }

    #[test]
    fn adam_matches_libtorch_adam() {
        let (vs_a, lin_a) = setup(3);
        // manual_seed is process-wide and tests run in parallel: copy instead of reseeding.
        let (mut vs_b, lin_b) = setup(3);
        vs_b.copy(&vs_a).expect("copy");
        let params = named_parameters(&vs_a);
        let mut ours = Adam::new(&params, 0.01);
        let mut theirs = nn::Adam::default().build(&vs_b, 0.01).expect("adam");
        for _ in 0..25 {
            loss(&lin_a).backward();
            let _ = ours.step(&params, None);
            theirs.zero_grad();
            loss(&lin_b).backward();
            theirs.step();
        }
        for (name, p) in &params {
            let q = &vs_b.variables()[name];
            assert!(p.allclose(q, 1e-6, 1e-6, false), "{name}: {p:?} vs {q:?}");
        }
    }

    /// Parameters flattened into one tensor (Adam's default) and parameters updated one by one
    /// (views broken by rebinding one, as converting a store would) give the same weights and
    /// the same average bit for bit; the network's own tensors see the flat updates.
    #[test]
    fn flat_parameters_update_as_the_per_parameter_path() {
        let (vs_a, lin_a) = setup(7);
        let (mut vs_b, lin_b) = setup(7);
        vs_b.copy(&vs_a).expect("copy");
        let (params_a, params_b) = (named_parameters(&vs_a), named_parameters(&vs_b));
        let mut adam_a = Adam::new(&params_a, 0.05);
        let flat = adam_a.flat_params(&params_a).expect("one dtype and device: flattened").shallow_clone();
        assert_eq!(flat.numel(), 3 * 2 + 2);
        let mut ema_a = Ema::new(&params_a, 0.9, 1, 2, Some(&flat));
        let mut adam_b = Adam::new(&params_b, 0.05);
        tch::no_grad(|| params_b[0].1.shallow_clone().set_data(&params_b[0].1.copy()));
        assert!(adam_b.flat_params(&params_b).is_none(), "a rebound parameter leaves the flat path");
        let mut ema_b = Ema::new(&params_b, 0.9, 1, 2, adam_b.flat_params(&params_b));
        for step in 1..=6 {
            loss(&lin_a).backward();
            let _ = adam_a.step(&params_a, None);
            ema_a.after_step(&params_a, step, None);
            loss(&lin_b).backward();
            let _ = adam_b.step(&params_b, None);
            ema_b.after_step(&params_b, step, None);
        }
        for (((name, a), (_, b)), ((_, ea), (_, eb))) in
            params_a.iter().zip(&params_b).zip(ema_a.named(&params_a).iter().zip(&ema_b.named(&params_b)))
        {
            assert!(a.equal(b), "{name}: {a:?} vs {b:?}");
            assert!(ea.equal(eb), "EMA of {name}");
        }
        assert!(lin_a.ws.equal(&vs_a.variables()["lin.weight"]), "the module sees the updated weights");
        assert!(adam_a.flat_params(&params_a).is_some(), "still flat after updates");
    }

    #[test]
    fn clipping_bounds_the_update_norm() {
        let (vs, lin) = setup(5);
        let params = named_parameters(&vs);
        loss(&lin).backward();
        let before = grad_norm(&params);
        let mut adam = Adam::new(&params, 0.1);
        let reported = adam.step(&params, Some(before / 10.0)).double_value(&[]);
        assert!((reported - before).abs() < 1e-9);
        assert_eq!(grad_norm(&params), 0.0, "gradients are zeroed after the step");
    }

    /// A step with an infinite or NaN gradient changes nothing (weights, moments, step count),
    /// so the next finite step is the one an optimizer that never saw it would take.
    #[test]
    fn a_non_finite_gradient_is_skipped_whole() {
        let (vs_a, lin_a) = setup(11);
        let (mut vs_b, lin_b) = setup(11);
        vs_b.copy(&vs_a).expect("copy");
        let (pa, pb) = (named_parameters(&vs_a), named_parameters(&vs_b));
        let (mut skipping, mut clean) = (Adam::new(&pa, 0.01), Adam::new(&pb, 0.01));
        for bad in [f64::INFINITY, f64::NAN] {
            (loss(&lin_a) * bad).backward();
            let norm = skipping.step(&pa, Some(1.0)).double_value(&[]);
            assert!(!norm.is_finite(), "{norm}");
            assert_eq!(grad_norm(&pa), 0.0, "gradients are zeroed after a skipped step");
        }
        assert_eq!(skipping.steps(), 0);
        for _ in 0..3 {
            loss(&lin_a).backward();
            loss(&lin_b).backward();
            let _ = (skipping.step(&pa, None), clean.step(&pb, None));
        }
        for ((_, a), (_, b)) in pa.iter().zip(&pb) {
            assert!(a.equal(b), "the skipped steps left a trace");
        }
    }

    /// Skip and clip decided on the device ([`Adam::deciding_on_device`]) give the weights,
    /// moments, step count and average of the host's decisions bit for bit, through clipped,
    /// unclipped, infinite and NaN steps (a skipped first step included), on the flat path and
    /// on the per-parameter one (a parameter without a gradient).
    #[test]
    fn deciding_on_the_device_updates_as_deciding_on_the_host() {
        for flat in [true, false] {
            let (vs_h, lin_h) = setup(13);
            let (mut vs_d, lin_d) = setup(13);
            vs_d.copy(&vs_h).expect("copy");
            let (ph, pd) = (named_parameters(&vs_h), named_parameters(&vs_d));
            let bias_before = pd[0].1.copy();
            let (mut host, mut device) = (Adam::new(&ph, 0.05), Adam::new(&pd, 0.05).deciding_on_device(true));
            let mut ema_h = Ema::new(&ph, 0.8, 2, 6, host.flat_params(&ph));
            let mut ema_d = Ema::new(&pd, 0.8, 2, 6, device.flat_params(&pd));
            // Flat: every gradient, one update over all; per parameter: the bias's left out.
            let step = |adam: &mut Adam, params: &[(String, Tensor)], clip| {
                if flat {
                    return adam.step(params, clip);
                }
                let grads = params[1..].iter().map(|(n, p)| (n.clone(), p.grad().copy())).collect();
                zero_grads(params);
                adam.step_with(params, grads, clip)
            };
            // Per step: the loss's factor (inf, NaN: a skipped step) and the clip.
            let schedule = [
                (f64::INFINITY, None),
                (1.0, Some(0.5)),
                (1.0, None),
                (f64::NAN, Some(1.0)),
                (2.0, Some(1e6)),
                (1.0, Some(0.1)),
                (f64::INFINITY, None),
                (0.5, None),
                (f64::NAN, None),
            ];
            let mut clipped = 0;
            for (i, (factor, clip)) in schedule.iter().cycle().take(40).enumerate() {
                let n = i as u64 + 1;
                (loss(&lin_h) * *factor).backward();
                let norm_h = step(&mut host, &ph, *clip).double_value(&[]);
                if norm_h.is_finite() {
                    ema_h.after_step(&ph, n, None);
                }
                clipped += usize::from(clip.is_some_and(|c| norm_h.is_finite() && norm_h > c));
                (loss(&lin_d) * *factor).backward();
                let norm_d = step(&mut device, &pd, *clip);
                ema_d.after_step(&pd, n, Some(&norm_d.isfinite()));
                let norm_d = norm_d.double_value(&[]);
                assert!(norm_h == norm_d || (norm_h.is_nan() && norm_d.is_nan()), "step {n}: {norm_h} vs {norm_d}");
                assert_eq!(host.steps(), device.steps(), "step {n}");
            }
            assert_eq!(host.steps(), 40 - 18, "18 of the 40 steps were not finite");
            assert!(clipped >= 5, "{clipped} steps clipped");
            for (((name, h), (_, d)), ((_, eh), (_, ed))) in
                ph.iter().zip(&pd).zip(ema_h.named(&ph).iter().zip(&ema_d.named(&pd)))
            {
                assert!(h.equal(d), "flat {flat}, {name}: {h:?} vs {d:?}");
                assert!(eh.equal(ed), "flat {flat}, EMA of {name}: {eh:?} vs {ed:?}");
            }
            for (a, b) in host.m.iter().zip(&device.m).chain(host.v.iter().zip(&device.v)) {
                assert!(a.equal(b), "flat {flat}: moments differ");
            }
            if !flat {
                assert_eq!(pd[0].0, "lin.bias");
                assert!(pd[0].1.equal(&bias_before), "the bias, without a gradient, moved");
            }
            // A resumed count reaches the device's.
            device.set_steps(7);
            assert_eq!(device.steps(), 7);
        }
    }

    #[test]
    fn moments_round_trip_through_safetensors() {
        let dir = tempfile::tempdir().expect("tmp");
        let (vs, lin) = setup(7);
        let params = named_parameters(&vs);
        let mut adam = Adam::new(&params, 0.01);
        loss(&lin).backward();
        let _ = adam.step(&params, None);
        adam.save(&params, &dir.path().join("adam.safetensors")).expect("save");
        let mut fresh = Adam::new(&params, 0.01);
        fresh.load(&params, &dir.path().join("adam.safetensors")).expect("load");
        for (a, b) in adam.m.iter().zip(&fresh.m).chain(adam.v.iter().zip(&fresh.v)) {
            assert!(a.equal(b));
        }
    }

    #[test]
    fn ema_resets_before_start_then_averages() {
        let (vs, _) = setup(9);
        let params = named_parameters(&vs);
        let mut ema = Ema::new(&params, 0.5, 1, 3, None);
        let set = |v: f32| {
            let _g = tch::no_grad_guard();
            for (_, p) in &params {
                let _ = p.shallow_clone().fill_(f64::from(v));
            }
        };
        set(1.0);
        ema.after_step(&params, 1, None); // before start: copy
        assert!(ema.named(&params).iter().all(|(_, s)| s.eq(1.0).all().int64_value(&[]) == 1));
        set(3.0);
        ema.after_step(&params, 3, None); // 0.5 * 1 + 0.5 * 3
        assert!(ema.named(&params).iter().all(|(_, s)| s.eq(2.0).all().int64_value(&[]) == 1));
    }

    /// Not a test: one Adam update at the training benchmark's TemporalUnet size (3.68M
    /// parameters in 40 tensors), one thread, best of five rounds of ten, without and with
    /// clipping (`cargo test --release -p relreward-server --lib time_adam -- --ignored
    /// --nocapture`).
    #[test]
    #[ignore]
    fn time_adam_at_the_temporal_unet_size() {
        tch::set_num_threads(1);
        let params: Vec<(String, Tensor)> = (0..40)
            .map(|i| {
                (format!("p{i:02}"), Tensor::randn([92_053], (Kind::Float, tch::Device::Cpu)).set_requires_grad(true))
            })
            .collect();
        let grads: Vec<(String, Tensor)> = params.iter().map(|(n, p)| (n.clone(), p.randn_like() * 1e-3)).collect();
        let mut adam = Adam::new(&params, 1e-4);
        for clip in [None, Some(1e-6)] {
            let mut step = || {
                let g = grads.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
                let _ = adam.step_with(&params, g, clip).double_value(&[]);
            };
            (0..5).for_each(|_| step());
            let best = (0..5)
                .map(|_| {
                    let start = std::time::Instant::now();
                    (0..10).for_each(|_| step());
                    start.elapsed().as_secs_f64() * 100.0
                })
                .fold(f64::INFINITY, f64::min);
            eprintln!("adam, 3.68M parameters, clip {clip:?}: {best:.2} ms");
        }
    }
}
