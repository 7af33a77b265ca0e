//! DDPM ancestral sampling (the default) or DDIM ([`GuidedSampler::with_ddim`]) with
//! inpainting conditions and classifier guidance by a differentiable reward (REFERENCE
//! section 2; Diffuser's `p_sample_loop` with `n_step_guided_p_sample`).
//!
//! One sampling run, for t = T-1 down to 0, all batch elements at the same t:
//!
//! 1. (guidance only) `n_guide_steps` times: g = grad_x sum(rho(x, t)); if `scale_grad_by_std`,
//!    g *= exp(posterior_log_variance_clipped[t]) (the posterior VARIANCE, as Diffuser does
//!    despite the flag's name); g = 0 when t < t_stopgrad; x += omega g; re-apply conditions.
//! 2. x = mu(x, t) + [t > 0] exp(0.5 posterior_log_variance_clipped[t]) z, z ~ N(0, I);
//!    re-apply conditions.
//!
//! DDIM (see [`super::ddim`] for the step subset and coefficients) runs over its subset
//! t_1 > .. > t_n instead, one denoiser call per step: x0 and eps from the net, then
//! x = sqrt(a') x0 + sqrt(1 - a' - sigma^2) eps + sigma z (z drawn only when sigma > 0);
//! re-apply conditions. Guidance enters a DDIM step through eps, as Dhariwal & Nichol's
//! eq. 14 (their Algorithm 2) does: eps <- eps - omega sqrt(1 - abar_t) grad_x rho(x_t, t),
//! then x0 = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t) (clamped with clip_denoised). Why eps
//! and not Diffuser's x += omega g: a DDIM step is a deterministic map of (x0, eps), and
//! -eps / sqrt(1 - abar) is the score, so shifting eps is adding omega grad rho to the
//! score, i.e. sampling p(x) exp(omega rho(x)) whatever the step sizes; moving x by a fixed
//! omega g would act more or less strongly as the subset is coarser or finer. Hence one
//! gradient per step (n_guide_steps 1) and no variance scaling (scale_grad_by_std false): a
//! DDIM run refuses other values, naming them.
//!
//! x_T ~ N(0, I) with the conditions applied. All noise comes from the caller's
//! [`Rng`], never from libtorch's global generator, so a seed fixes the samples whatever other
//! threads do. The stream is consumed identically with and without guidance (x_T, then one
//! draw per step with t > 0), so guided and unguided runs with one seed share their noise.
//!
//! Denoiser calls run under no-grad; grad mode is switched on only around the reward's
//! gradient. With no reward, omega = 0 or n_guide_steps = 0 nothing is differentiated at all.
//! At steps with t < t_stopgrad, where g would be zeroed, the gradient is not computed: rho is
//! evaluated without grad only to report it (x is unchanged either way, exactly as in Diffuser).
//!
//! A conditional model samples through a [`Recipe`] ([`GuidedSampler::with_recipe`]; one
//! prompt per sample given to [`GuidedSampler::sample_prompted`]): every step asks the
//! recipe's run for the prediction (classifier-free and safety guidance, see
//! [`super::recipe`]) where an unconditional model is asked directly; everything else is the
//! same.
//!
//! Samples come back in normalized units; unnormalizing is the caller's job.

use tch::{Device, Kind, Tensor};

use super::ddim::{Ddim, coefs};
use super::diffusion::DiffusionModel;
use super::manifest::Space;
use super::recipe::{Predictor, Recipe, RecipeRun, check_conditions};
use super::rng::Rng;
use super::schedule::Table;
use crate::error::{Error, Result};

/// A differentiable scalar reward over normalized samples, for classifier guidance.
pub trait RewardFn {
    /// `x`: float32 `[B, *item_shape]` in the diffusion model's normalized units (a leaf that
    /// requires grad when guiding); `t`: int64 `[B]`. Returns `[B]` (or `[B, 1]`),
    /// differentiable with respect to `x`.
    fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor>;

    /// (rho(x, t), grad_x sum rho(x, t)), neither with a graph: what guidance needs at every
    /// guided step. By default autograd through [`RewardFn::rho`] ([`autograd_rho_and_grad`]);
    /// a reward with a gradient of its own overrides it (`RewardModel`: the native networks'
    /// closed forms and hand-written backwards, issue 38).
    fn rho_and_grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        autograd_rho_and_grad(&|x, t| self.rho(x, t), x, t)
    }
}

/// (rho(x, t), grad_x sum rho(x, t)) by autograd through `rho` on a detached copy of `x`, in
/// grad mode; FAILED_PRECONDITION when rho does not depend differentiably on x.
pub fn autograd_rho_and_grad(
    rho: &dyn Fn(&Tensor, &Tensor) -> Result<Tensor>,
    x: &Tensor,
    t: &Tensor,
) -> Result<(Tensor, Tensor)> {
    tch::with_grad(|| {
        let leaf = x.f_detach()?.f_set_requires_grad(true)?;
        let y = rho(&leaf, t)?;
        if !y.requires_grad() {
            return Err(Error::FailedPrecondition(
                "reward output does not depend differentiably on x (was it computed without grad?)".into(),
            ));
        }
        let total = y.f_sum(Kind::Float)?;
        let mut grads = Tensor::f_run_backward(&[&total], &[&leaf], false, false)
            .map_err(|e| Error::internal("gradient of the reward with respect to x", e))?;
        let grad = grads.pop().ok_or_else(|| Error::internal("reward gradient", "libtorch returned no gradient"))?;
        if !grad.defined() {
            return Err(Error::FailedPrecondition("reward output does not depend on x".into()));
        }
        Ok((y.f_detach()?, grad.f_detach()?))
    })
}

/// Inpainting: the observation part of transition `index` is fixed to `state`, either one
/// state `[obs_dim]` for every sample or one per sample `[n, obs_dim]` (normalized units).
#[derive(Debug)]
pub struct Condition {
    pub index: usize,
    pub state: Tensor,
}

/// Classifier guidance by `reward` (Diffuser's `n_step_guided_p_sample` parameters; its `scale`
/// is `omega`).
#[derive(Clone, Copy)]
pub struct Guidance<'a> {
    pub reward: &'a dyn RewardFn,
    pub omega: f64,
    pub n_guide_steps: usize,
    /// No guidance at steps t < t_stopgrad (t = T or more: no step is guided).
    pub t_stopgrad: usize,
    /// Multiply the gradient by the posterior variance at t.
    pub scale_grad_by_std: bool,
}

impl std::fmt::Debug for Guidance<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Guidance")
            .field("omega", &self.omega)
            .field("n_guide_steps", &self.n_guide_steps)
            .field("t_stopgrad", &self.t_stopgrad)
            .field("scale_grad_by_std", &self.scale_grad_by_std)
            .finish_non_exhaustive()
    }
}

/// What the per-step callback sees after the denoising step at `t` (conditions applied).
#[derive(Debug)]
pub struct Step<'a> {
    pub t: usize,
    /// x_{t-1} in Diffuser's indexing (the final samples when `t == 0`), `[n, *item_shape]`.
    pub x: &'a Tensor,
    /// rho at this step's last guide point, `[n]`; `None` without guidance.
    pub rewards: Option<&'a Tensor>,
}

/// The result of a sampling run.
#[derive(Debug)]
pub struct Sampled {
    /// `[n, *item_shape]`, normalized units.
    pub x: Tensor,
    /// With guidance: rho(x, 0) at the last step's final guide point, `[n]` (Diffuser's
    /// `values`, by which it ranks plans). `None` without guidance.
    pub rewards: Option<Tensor>,
}

/// Per-step callback; returning an error aborts the run with that error (e.g. cancellation).
pub type StepCallback<'c> = dyn FnMut(&Step<'_>) -> Result<()> + 'c;

/// Ancestral sampler for one diffusion model, with optional conditions and guidance.
#[derive(Debug)]
pub struct GuidedSampler<'a> {
    model: &'a DiffusionModel,
    conditions: Vec<Condition>,
    guidance: Option<Guidance<'a>>,
    /// DDIM instead of DDPM ancestral sampling.
    ddim: Option<Ddim>,
    /// A conditional model's recipe (None: an unconditional model, asked directly).
    recipe: Option<&'a Recipe>,
    device: Device,
}

/// Conditions checked and shaped for a batch of `n`: (index, state `[n, 1, obs_dim]`).
struct Prepared {
    rows: Vec<(i64, Tensor)>,
    action_dim: i64,
    obs_dim: i64,
}

impl Prepared {
    /// Overwrites x[:, i, action_dim:] with each condition's state, in place.
    fn apply(&self, x: &Tensor) -> Result<()> {
        for (i, state) in &self.rows {
            let mut view = x.f_narrow(1, *i, 1)?.f_narrow(2, self.action_dim, self.obs_dim)?;
            view.f_copy_(state)?;
        }
        Ok(())
    }
}

impl<'a> GuidedSampler<'a> {
    /// Plain sampling on the CPU; add conditions and guidance with the builder methods.
    pub fn new(model: &'a DiffusionModel) -> Self {
        Self { model, conditions: Vec::new(), guidance: None, ddim: None, recipe: None, device: Device::Cpu }
    }

    pub fn with_conditions(mut self, conditions: Vec<Condition>) -> Self {
        self.conditions = conditions;
        self
    }

    pub fn with_guidance(mut self, guidance: Guidance<'a>) -> Self {
        self.guidance = Some(guidance);
        self
    }

    /// Samples with DDIM over a subset of the model's steps instead of DDPM.
    pub fn with_ddim(mut self, ddim: Ddim) -> Self {
        self.ddim = Some(ddim);
        self
    }

    /// Samples a conditional model through `recipe` (validated by the caller against the
    /// model); prompts go to [`Self::sample_prompted`].
    pub fn with_recipe(mut self, recipe: &'a Recipe) -> Self {
        self.recipe = Some(recipe);
        self
    }

    /// The device the denoiser (and reward) run on.
    pub fn on_device(mut self, device: Device) -> Self {
        self.device = device;
        self
    }

    /// Draws `n` samples.
    pub fn sample(&self, n: usize, rng: &mut Rng) -> Result<Sampled> {
        self.sample_with(n, rng, &mut |_| Ok(()))
    }

    /// Draws `n` samples, calling `on_step` after every denoising step (t = T-1 down to 0).
    pub fn sample_with(&self, n: usize, rng: &mut Rng, on_step: &mut StepCallback<'_>) -> Result<Sampled> {
        self.sample_prompted(n, None, rng, on_step)
    }

    /// [`Self::sample_with`] for a conditional model: `prompts` holds each sample's condition
    /// (int64 labels `[n]` or float32 embeddings `[n, dim]`); with no recipe set, the plain
    /// conditional prediction is used.
    pub fn sample_prompted(
        &self,
        n: usize,
        prompts: Option<&Tensor>,
        rng: &mut Rng,
        on_step: &mut StepCallback<'_>,
    ) -> Result<Sampled> {
        if n == 0 {
            return Err(Error::invalid("n: at least one sample is needed"));
        }
        let guidance = self.checked_guidance()?;
        let prepared = self.prepare_conditions(n as i64)?;
        let plain = Recipe::conditional();
        let mut predictor = match (self.model.conditioning(), prompts) {
            (None, None) if self.recipe.is_none() => Predictor::Model(self.model),
            (None, _) => return Err(Error::invalid("prompts: the model is unconditional")),
            (Some(_), None) => return Err(Error::invalid("prompts: missing; the model is conditional")),
            (Some(c), Some(p)) => {
                check_conditions(p, c, "prompts", Some(n as i64))?;
                let recipe = self.recipe.unwrap_or(&plain);
                Predictor::Recipe(RecipeRun::new(self.model, recipe, &p.f_to_device(self.device)?)?)
            }
        };
        if let Some(ddim) = self.ddim {
            return self.sample_ddim(n, rng, on_step, ddim, &prepared, &mut predictor);
        }
        let model = self.model;
        let big_t = model.n_timesteps();
        let _no_grad = tch::no_grad_guard();
        let (shape, mut x) = self.initial_state(n, rng, &prepared)?;
        let mut last_rewards = None;
        for i in (0..big_t).rev() {
            let t = Tensor::f_full([n as i64], i as i64, (Kind::Int64, self.device))?;
            let log_var = model.schedule.get(Table::PosteriorLogVarianceClipped, i).unwrap_or(0.0);
            let mut rewards = None;
            if let Some(g) = &guidance {
                if i >= g.t_stopgrad {
                    // Diffuser multiplies by exp(log variance), i.e. the clipped variance.
                    let scale = if g.scale_grad_by_std { log_var.exp() } else { 1.0 };
                    for _ in 0..g.n_guide_steps {
                        let (y, grad) = reward_gradient(g.reward, &x, &t, n as i64)?;
                        let grad = if g.scale_grad_by_std { grad.f_mul_scalar(scale)? } else { grad };
                        x = x.f_add(&grad.f_mul_scalar(g.omega)?)?;
                        prepared.apply(&x)?;
                        rewards = Some(y);
                    }
                } else {
                    rewards = Some(reward_value(g.reward, &x, &t, n as i64)?);
                }
            }
            let mean = predictor.mean(&x, &t)?;
            x = if i > 0 {
                let noise = rng.randn(&shape, self.device);
                mean.f_add(&noise.f_mul_scalar((0.5 * log_var).exp())?)?
            } else {
                mean
            };
            prepared.apply(&x)?;
            on_step(&Step { t: i, x: &x, rewards: rewards.as_ref() })?;
            last_rewards = rewards;
        }
        Ok(Sampled { x, rewards: last_rewards })
    }

    /// The batch's shape and x_T: the run's first draw from `rng` (both samplers), with the
    /// conditions applied.
    fn initial_state(&self, n: usize, rng: &mut Rng, prepared: &Prepared) -> Result<(Vec<i64>, Tensor)> {
        let mut shape = vec![n as i64];
        shape.extend(self.model.item_shape());
        let x = rng.randn(&shape, self.device);
        prepared.apply(&x)?;
        Ok((shape, x))
    }

    /// DDIM over `ddim`'s subset (see the module's doc): the same noise stream layout as DDPM
    /// (x_T first, then one draw per step that adds noise).
    fn sample_ddim(
        &self,
        n: usize,
        rng: &mut Rng,
        on_step: &mut StepCallback<'_>,
        ddim: Ddim,
        prepared: &Prepared,
        predictor: &mut Predictor<'_>,
    ) -> Result<Sampled> {
        let guidance = self.checked_guidance()?;
        let model = self.model;
        let big_t = model.n_timesteps();
        ddim.check(big_t, "ddim")?;
        let abar = model.schedule.values(Table::AlphasCumprod);
        let clip = model.clip_denoised();
        let _no_grad = tch::no_grad_guard();
        let (shape, mut x) = self.initial_state(n, rng, prepared)?;
        let mut last_rewards = None;
        for i in ddim.timesteps(big_t) {
            let t = Tensor::f_full([n as i64], i as i64, (Kind::Int64, self.device))?;
            let c = coefs(abar[i], ddim.abar_prev(i, abar), ddim.eta);
            let pred = predictor.predict(&x, &t)?;
            let mut eps = model.eps_from_prediction(&x, &t, &pred)?;
            let mut rewards = None;
            let x0 = match &guidance {
                Some(g) if i >= g.t_stopgrad => {
                    let (y, grad) = reward_gradient(g.reward, &x, &t, n as i64)?;
                    rewards = Some(y);
                    eps = eps.f_sub(&grad.f_mul_scalar(g.omega * (1.0 - abar[i]).sqrt())?)?;
                    let x0 = model.x0_from_eps(&x, &t, &eps)?;
                    if clip { x0.f_clamp(-1.0, 1.0)? } else { x0 }
                }
                other => {
                    if let Some(g) = other {
                        rewards = Some(reward_value(g.reward, &x, &t, n as i64)?);
                    }
                    // Unguided: x0 straight from the net's output, as diffusers forms it
                    // (for x0 and v nets no round trip through eps).
                    model.x0_from_prediction(&x, &t, &pred, clip)?
                }
            };
            let mut next = x0.f_mul_scalar(c.x0_coef)?.f_add(&eps.f_mul_scalar(c.eps_coef)?)?;
            if c.sigma > 0.0 {
                let noise = rng.randn(&shape, self.device);
                next = next.f_add(&noise.f_mul_scalar(c.sigma)?)?;
            }
            x = next;
            prepared.apply(&x)?;
            on_step(&Step { t: i, x: &x, rewards: rewards.as_ref() })?;
            last_rewards = rewards;
        }
        Ok(Sampled { x, rewards: last_rewards })
    }

    /// The guidance that actually acts, after validation: `None` when there is nothing to
    /// differentiate (no reward, omega = 0 or no guide steps).
    fn checked_guidance(&self) -> Result<Option<Guidance<'a>>> {
        let Some(g) = self.guidance else { return Ok(None) };
        if !g.omega.is_finite() {
            return Err(Error::invalid(format!("guidance.omega: {} is not finite", g.omega)));
        }
        if self.ddim.is_some() && g.omega != 0.0 {
            // The module's doc says why DDIM guides once per step, through eps.
            if g.n_guide_steps > 1 {
                return Err(Error::invalid(format!(
                    "n_guide_steps: {} with DDIM; DDIM guides through eps once per step (omit it or set 1)",
                    g.n_guide_steps
                )));
            }
            if g.scale_grad_by_std {
                return Err(Error::invalid(
                    "scale_grad_by_std: not with DDIM, whose guidance scales the gradient by sqrt(1 - abar_t) through eps",
                ));
            }
        }
        Ok((g.omega != 0.0 && g.n_guide_steps > 0).then_some(g))
    }

    fn prepare_conditions(&self, n: i64) -> Result<Prepared> {
        let (horizon, action_dim, obs_dim) = match self.model.manifest.space {
            Space::Trajectory { horizon, action_dim, obs_dim } => (horizon, action_dim as i64, obs_dim as i64),
            Space::Sample { .. } => {
                if !self.conditions.is_empty() {
                    return Err(Error::invalid(
                        "conditions: only trajectory models can be conditioned (this model's space is a sample space)",
                    ));
                }
                return Ok(Prepared { rows: Vec::new(), action_dim: 0, obs_dim: 0 });
            }
        };
        let mut rows = Vec::with_capacity(self.conditions.len());
        for (k, c) in self.conditions.iter().enumerate() {
            if c.index >= horizon {
                return Err(Error::invalid(format!(
                    "conditions[{k}].index: {} is outside the horizon 0..{horizon}",
                    c.index
                )));
            }
            let size = c.state.size();
            let state = match size.as_slice() {
                [d] if *d == obs_dim => c.state.f_reshape([1, 1, obs_dim])?.f_expand([n, 1, obs_dim], false)?,
                [b, d] if *b == n && *d == obs_dim => c.state.f_reshape([n, 1, obs_dim])?,
                _ => {
                    return Err(Error::invalid(format!(
                        "conditions[{k}].state: expected [{obs_dim}] or [{n}, {obs_dim}] (obs_dim, or one state per sample), got {size:?}"
                    )));
                }
            };
            let state = state.f_detach()?.f_to_kind(Kind::Float)?.f_to_device(self.device)?;
            if state.f_isfinite()?.f_all()?.f_int64_value(&[])? == 0 {
                return Err(Error::invalid(format!("conditions[{k}].state: not finite")));
            }
            rows.push((c.index as i64, state));
        }
        Ok(Prepared { rows, action_dim, obs_dim })
    }
}

/// Plain ancestral sampling of `n` samples (no conditions, no guidance), on the CPU.
pub fn sample(model: &DiffusionModel, n: usize, rng: &mut Rng) -> Result<Tensor> {
    Ok(GuidedSampler::new(model).sample(n, rng)?.x)
}

/// rho's output as `[n]`, whatever of `[n]` / `[n, 1]` the reward returned.
fn reward_output(y: Tensor, n: i64) -> Result<Tensor> {
    let size = y.size();
    match size.as_slice() {
        [b] | [b, 1] if *b == n => Ok(y.f_reshape([n])?),
        _ => Err(Error::FailedPrecondition(format!("reward returned shape {size:?}; expected [{n}] or [{n}, 1]"))),
    }
}

/// (rho(x, t) as `[n]`, grad_x sum rho(x, t)): the reward's own gradient
/// ([`RewardFn::rho_and_grad`]).
fn reward_gradient(reward: &dyn RewardFn, x: &Tensor, t: &Tensor, n: i64) -> Result<(Tensor, Tensor)> {
    let (y, grad) = reward.rho_and_grad(x, t)?;
    if grad.size() != x.size() {
        return Err(Error::FailedPrecondition(format!(
            "reward gradient has shape {:?}; expected the samples' {:?}",
            grad.size(),
            x.size()
        )));
    }
    Ok((reward_output(y, n)?, grad))
}

/// rho(x, t) without grad (for reporting at unguided steps).
fn reward_value(reward: &dyn RewardFn, x: &Tensor, t: &Tensor, n: i64) -> Result<Tensor> {
    let y = tch::no_grad(|| reward.rho(x, t))?;
    Ok(reward_output(y, n)?.f_detach()?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::diffusion::testing::AnalyticGaussian;
    use crate::engine::manifest::{DiffusionManifest, Parametrization, ScheduleSpec};
    use crate::engine::normalizer::Normalizer;
    use crate::engine::schedule::Schedule;

    const T: usize = 50;

    fn model(space: Space, mean: &[f32]) -> DiffusionModel {
        let m = DiffusionManifest {
            parametrization: Parametrization::Epsilon,
            schedule: ScheduleSpec::Cosine { s: 0.008 },
            n_timesteps: T,
            clip_denoised: false,
            space,
            normalizer: Normalizer::Identity,
            architecture: None,
            conditioning: None,
        };
        let s = Schedule::new(&m.schedule, T).expect("schedule");
        let net = AnalyticGaussian::new(&s, mean, &m.space.item_shape(), false);
        DiffusionModel::new(m, Box::new(net)).expect("model")
    }

    fn sample_model() -> DiffusionModel {
        model(Space::Sample { shape: vec![3] }, &[1.0, -2.0, 0.5])
    }

    fn traj_model() -> DiffusionModel {
        // horizon 4, action_dim 1, obs_dim 2.
        model(Space::Trajectory { horizon: 4, action_dim: 1, obs_dim: 2 }, &[0.3; 12])
    }

    /// rho(x) = sum of w * x over each sample's elements.
    struct Linear(Tensor);
    impl RewardFn for Linear {
        fn rho(&self, x: &Tensor, _t: &Tensor) -> Result<Tensor> {
            Ok((x * &self.0).flatten(1, -1).sum_dim_intlist([1i64].as_slice(), false, Kind::Float))
        }
    }

    fn w3() -> Linear {
        Linear(Tensor::from_slice(&[1.0f32, 2.0, -1.0]))
    }

    fn guided(
        model: &DiffusionModel,
        reward: &dyn RewardFn,
        omega: f64,
        steps: usize,
        t_stopgrad: usize,
        scale: bool,
        seed: u64,
    ) -> Sampled {
        GuidedSampler::new(model)
            .with_guidance(Guidance { reward, omega, n_guide_steps: steps, t_stopgrad, scale_grad_by_std: scale })
            .sample(256, &mut Rng::new(seed))
            .expect("guided sample")
    }

    /// A native reward guides with its own gradient (`RewardModel::grad`: the MLPs' closed form,
    /// the convolutional rewards' hand-written backward) and samples what autograd through its
    /// rho samples, rewards included.
    #[test]
    fn native_rewards_guide_with_their_own_gradient_as_autograd_would() {
        use crate::engine::nets::{RewardArchitecture, RewardNet};
        use crate::engine::relative_reward::RewardManifest;
        use crate::engine::reward_model::RewardModel;
        /// The same reward without its own gradient: the default, autograd through rho.
        struct Autograd<'a>(&'a RewardModel);
        impl RewardFn for Autograd<'_> {
            fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
                self.0.rho(x, t)
            }
        }
        let traj = traj_model();
        for architecture in [
            RewardArchitecture::WindowedMlp { window: 2, hidden: vec![16, 8] },
            RewardArchitecture::ValueFunction { widths: vec![64] },
        ] {
            let dir = tempfile::tempdir().expect("tmp");
            let net = RewardNet::new(&architecture, &[4, 3], 0, Device::Cpu).expect("net");
            let path = dir.path().join("w.safetensors");
            net.save(&path).expect("save");
            let space = traj.manifest.space.clone();
            let manifest = RewardManifest::for_tests(architecture.clone(), space, Normalizer::Identity, T);
            let reward = RewardModel::load(manifest, &path, dir.path(), Device::Cpu).expect("load");
            // To float rounding relative to the values' scale: an entry near zero differs by
            // the rounding of the largest (elementwise relative tolerances fail there; the
            // ValueFunction's group norm over two values amplifies rounding to about 1e-5 of
            // the largest gradient entry across seeds).
            let close = |a: &Tensor, b: &Tensor| {
                let scale = b.abs().max().double_value(&[]).max(1e-3);
                (a - b).abs().max().double_value(&[]) <= 5e-5 * scale
            };
            // The guided step's gradient, at points of every scale and at several steps.
            let x = Tensor::randn([16, 4, 3], (Kind::Float, Device::Cpu)) * 2.0;
            let t = Tensor::arange(16, (Kind::Int64, Device::Cpu)) * 3;
            let (rho, grad) = reward_gradient(&reward, &x, &t, 16).expect("own gradient");
            let (own_rho, own_grad) = reward.grad(&x, &t).expect("grad");
            assert!(rho.equal(&own_rho) && grad.equal(&own_grad), "{architecture}: RewardModel::grad's, bit for bit");
            let (want_rho, want_grad) = reward_gradient(&Autograd(&reward), &x, &t, 16).expect("autograd");
            assert!(close(&rho, &want_rho) && close(&grad, &want_grad), "{architecture}: the guided step");
            // Whole runs for the windowed MLP. (The small ValueFunction's last group norm spans
            // two values, whose backward amplifies float rounding fed back through fifty guided
            // steps past any tolerance.)
            if matches!(architecture, RewardArchitecture::WindowedMlp { .. }) {
                let own = guided(&traj, &reward, 0.5, 2, 0, true, 8);
                let autograd = guided(&traj, &Autograd(&reward), 0.5, 2, 0, true, 8);
                let close = |a: &Tensor, b: &Tensor| a.allclose(b, 1e-4, 1e-5, false);
                assert!(close(&own.x, &autograd.x), "samples");
                assert!(close(&own.rewards.expect("rewards"), &autograd.rewards.expect("rewards")), "rewards");
                let unguided = guided(&traj, &reward, 0.0, 2, 0, true, 8);
                assert!(!close(&own.x, &unguided.x), "guidance moved the samples");
            }
        }
    }

    fn bitwise_equal(a: &Tensor, b: &Tensor) -> bool {
        a.size() == b.size() && a.eq_tensor(b).all().int64_value(&[]) == 1
    }

    #[test]
    fn same_seed_same_samples_different_seed_different() {
        let m = sample_model();
        let a = sample(&m, 64, &mut Rng::new(11)).expect("a");
        let b = sample(&m, 64, &mut Rng::new(11)).expect("b");
        let c = sample(&m, 64, &mut Rng::new(12)).expect("c");
        assert_eq!(a.size(), vec![64, 3]);
        assert!(bitwise_equal(&a, &b));
        assert!(!bitwise_equal(&a, &c));
        // The caller's generator advances, so consecutive runs differ.
        let mut rng = Rng::new(11);
        let first = sample(&m, 64, &mut rng).expect("first");
        let second = sample(&m, 64, &mut rng).expect("second");
        assert!(bitwise_equal(&first, &a) && !bitwise_equal(&first, &second));
    }

    #[test]
    fn zero_omega_and_full_stopgrad_equal_plain_sampling() {
        let m = sample_model();
        let plain = GuidedSampler::new(&m).sample(256, &mut Rng::new(5)).expect("plain");
        assert!(plain.rewards.is_none());
        let reward = w3();
        let zero = guided(&m, &reward, 0.0, 2, 0, false, 5);
        assert!(bitwise_equal(&plain.x, &zero.x) && zero.rewards.is_none());
        let stopped = guided(&m, &reward, 1.0, 2, T, true, 5);
        assert!(bitwise_equal(&plain.x, &stopped.x));
        // Rewards are still reported (rho at the last step's input).
        assert_eq!(stopped.rewards.expect("rewards").size(), vec![256]);
        let no_steps = guided(&m, &reward, 1.0, 0, 0, false, 5);
        assert!(bitwise_equal(&plain.x, &no_steps.x));
    }

    /// With the analytic model, mu(x + d) = mu(x) + sqrt(alpha_t) d, and guided and plain runs
    /// share their noise, so guided - plain = c w for every sample, with
    /// c = fold over t of sqrt(alpha_t) (c + [t >= t_stopgrad] n omega k_t), k_t = variance or 1.
    fn predicted_shift(m: &DiffusionModel, omega: f64, steps: usize, t_stopgrad: usize, scale: bool) -> f64 {
        let s = &m.schedule;
        let mut c = 0.0;
        for t in (0..T).rev() {
            let k = if scale { s.values(Table::PosteriorLogVarianceClipped)[t].exp() } else { 1.0 };
            let push = if t >= t_stopgrad { steps as f64 * omega * k } else { 0.0 };
            c = s.values(Table::Alphas)[t].sqrt() * (c + push);
        }
        c
    }

    #[test]
    fn linear_reward_shifts_samples_along_w_by_the_predicted_amount() {
        let m = sample_model();
        let reward = w3();
        let w = Tensor::from_slice(&[1.0f64, 2.0, -1.0]);
        let plain = GuidedSampler::new(&m).sample(256, &mut Rng::new(21)).expect("plain").x.to_kind(Kind::Double);
        let mut last = 0.0;
        for (omega, steps, t_stopgrad, scale) in
            [(0.01, 1, 0, false), (0.03, 1, 0, false), (0.03, 2, 3, false), (0.5, 2, 2, true), (-0.02, 1, 0, false)]
        {
            let g = guided(&m, &reward, omega, steps, t_stopgrad, scale, 21);
            let diff = g.x.to_kind(Kind::Double) - &plain;
            let c = predicted_shift(&m, omega, steps, t_stopgrad, scale);
            let want = &w * c;
            let err = (&diff - want.unsqueeze(0)).abs().max().double_value(&[]);
            assert!(
                err < 1e-4 * (1.0 + c.abs()),
                "omega {omega} steps {steps} stopgrad {t_stopgrad} scale {scale}: c {c}, err {err}"
            );
            // The mean moves along w: more for larger omega (same steps), backwards for omega < 0.
            let along = diff.mean_dim([0i64].as_slice(), false, Kind::Double).dot(&w).double_value(&[]);
            assert!((along - 6.0 * c).abs() < 1e-3 * (1.0 + c.abs()), "{along} vs {}", 6.0 * c);
            if (omega, steps) == (0.03, 1) {
                assert!(c > last && last > 0.0, "larger omega, larger shift: {c} vs {last}");
            }
            if omega < 0.0 {
                assert!(c < 0.0);
            }
            last = c;
            assert_eq!(g.rewards.expect("rewards").size(), vec![256]);
        }
    }

    #[test]
    fn conditions_hold_exactly_in_the_output_with_and_without_guidance() {
        let m = traj_model();
        let start = Tensor::from_slice(&[0.25f32, -0.75]);
        let goals = Tensor::from_slice(&(0..32).map(|i| i as f32 / 10.0).collect::<Vec<_>>()).reshape([16, 2]);
        let conditions = || {
            vec![
                Condition { index: 0, state: start.shallow_clone() },
                Condition { index: 3, state: goals.shallow_clone() },
            ]
        };
        let reward = Linear(Tensor::ones([4, 3], (Kind::Float, Device::Cpu)));
        let mut steps = Vec::new();
        for guide in [false, true] {
            let mut s = GuidedSampler::new(&m).with_conditions(conditions());
            if guide {
                s = s.with_guidance(Guidance {
                    reward: &reward,
                    omega: 0.1,
                    n_guide_steps: 2,
                    t_stopgrad: 1,
                    scale_grad_by_std: false,
                });
            }
            let out = s
                .sample_with(16, &mut Rng::new(3), &mut |step| {
                    steps.push(step.t);
                    // Conditions hold after every step, not only at the end.
                    let obs0 = step.x.narrow(1, 0, 1).narrow(2, 1, 2).reshape([16, 2]);
                    assert!(bitwise_equal(&obs0, &start.unsqueeze(0).expand([16, 2], false)));
                    assert_eq!(step.rewards.is_some(), guide);
                    Ok(())
                })
                .expect("sample");
            let x = out.x;
            assert_eq!(x.size(), vec![16, 4, 3]);
            let obs0 = x.narrow(1, 0, 1).narrow(2, 1, 2).reshape([16, 2]);
            let obs3 = x.narrow(1, 3, 1).narrow(2, 1, 2).reshape([16, 2]);
            assert!(bitwise_equal(&obs0, &start.unsqueeze(0).expand([16, 2], false)));
            assert!(bitwise_equal(&obs3, &goals));
            // Unconditioned entries are free.
            assert!(x.narrow(1, 1, 2).std(true).double_value(&[]) > 0.1);
        }
        let expected: Vec<usize> = (0..T).rev().chain((0..T).rev()).collect();
        assert_eq!(steps, expected);
    }

    #[test]
    fn a_failing_callback_aborts_the_run() {
        let m = sample_model();
        let mut calls = 0;
        let err = GuidedSampler::new(&m)
            .sample_with(4, &mut Rng::new(1), &mut |step| {
                calls += 1;
                if step.t == T - 3 { Err(Error::Unavailable("cancelled".into())) } else { Ok(()) }
            })
            .expect_err("aborted");
        assert!(matches!(err, Error::Unavailable(_)));
        assert_eq!(calls, 3);
    }

    mod ddim {
        use super::*;
        use crate::engine::ddim::{Ddim, Spacing};

        const MEAN: [f64; 3] = [1.0, -2.0, 0.5];

        fn run(m: &DiffusionModel, d: Ddim, guidance: Option<Guidance<'_>>, seed: u64) -> Result<Sampled> {
            let mut s = GuidedSampler::new(m).with_ddim(d);
            if let Some(g) = guidance {
                s = s.with_guidance(g);
            }
            s.sample(4, &mut Rng::new(seed))
        }

        fn trailing(n_steps: usize, eta: f64) -> Ddim {
            Ddim { n_steps, eta, spacing: Spacing::Trailing, set_alpha_to_one: true }
        }

        /// The analytic model's exact (x0, eps) at (x, t), by hand in f64.
        fn exact(m: &DiffusionModel, x: &Tensor, t: usize) -> (Tensor, Tensor) {
            let a = m.schedule.values(Table::AlphasCumprod)[t];
            let mean = Tensor::from_slice(&MEAN).unsqueeze(0);
            let x0 = x * a.sqrt() + &mean * (1.0 - a);
            let eps = (x - &mean * a.sqrt()) * (1.0 - a).sqrt();
            (x0, eps)
        }

        fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
            (a.to_kind(Kind::Double) - b.to_kind(Kind::Double)).abs().max().double_value(&[])
        }

        #[test]
        fn two_steps_equal_the_hand_computed_ddim_updates() {
            let m = sample_model();
            let abar = m.schedule.values(Table::AlphasCumprod).to_vec();
            // Leading, n = 2, T = 50: t = 25 -> 0, then 0 -> final (alpha one, no noise). (From
            // t = 49 the cosine schedule's abar is ~1e-5, and x0 = (x - sqrt(1 - abar) eps) /
            // sqrt(abar) in float32 would measure that division, not the step.)
            let leading = |eta| Ddim { spacing: Spacing::Leading, ..trailing(2, eta) };
            for eta in [0.0, 0.7] {
                let got = run(&m, leading(eta), None, 17).expect("ddim").x;
                let mut rng = Rng::new(17);
                let x_t = rng.randn(&[4, 3], Device::Cpu).to_kind(Kind::Double);
                let (a, ap) = (abar[25], abar[0]);
                let (x0, eps) = exact(&m, &x_t, 25);
                let var = (1.0 - ap) / (1.0 - a) * (1.0 - a / ap);
                let sigma = eta * var.sqrt();
                let mut x1 = x0 * ap.sqrt() + eps * (1.0 - ap - sigma * sigma).sqrt();
                if eta > 0.0 {
                    x1 += rng.randn(&[4, 3], Device::Cpu).to_kind(Kind::Double) * sigma;
                }
                let (want, _) = exact(&m, &x1, 0);
                assert!(max_diff(&got, &want) < 1e-5, "eta {eta}: {}", max_diff(&got, &want));
            }
            // eta > 0 draws noise, eta = 0 does not: the two differ.
            let a = run(&m, leading(0.0), None, 17).expect("a").x;
            let b = run(&m, leading(0.7), None, 17).expect("b").x;
            assert!(max_diff(&a, &b) > 1e-3);
        }

        #[test]
        fn every_parametrization_takes_the_same_ddim_path() {
            let build = |p: Parametrization| {
                let man = DiffusionManifest {
                    parametrization: p,
                    schedule: ScheduleSpec::Cosine { s: 0.008 },
                    n_timesteps: T,
                    clip_denoised: false,
                    space: Space::Sample { shape: vec![3] },
                    normalizer: Normalizer::Identity,
                    conditioning: None,
                    architecture: None,
                };
                let s = Schedule::new(&man.schedule, T).expect("schedule");
                let mean: Vec<f32> = MEAN.iter().map(|&v| v as f32).collect();
                DiffusionModel::new(man, Box::new(AnalyticGaussian::predicting(&s, &mean, &[3], p))).expect("model")
            };
            let d = Ddim { n_steps: 10, eta: 0.3, spacing: Spacing::Leading, set_alpha_to_one: false };
            let e = run(&build(Parametrization::Epsilon), d, None, 3).expect("eps").x;
            for p in [Parametrization::X0, Parametrization::V] {
                let o = run(&build(p), d, None, 3).expect("other").x;
                assert!(max_diff(&e, &o) < 1e-4, "{p:?}: {}", max_diff(&e, &o));
            }
        }

        #[test]
        fn guidance_shifts_eps_by_the_scaled_gradient() {
            // One trailing step from t = 49 to the end: x = x0(eps') with
            // eps' = eps - omega sqrt(1 - a) w, so guided - plain = omega (1 - a) / sqrt(a) w.
            let m = sample_model();
            let reward = w3();
            let a = m.schedule.values(Table::AlphasCumprod)[T - 1];
            let plain = run(&m, trailing(1, 0.0), None, 9).expect("plain");
            let g = |omega: f64, t_stopgrad: usize| Guidance {
                reward: &reward,
                omega,
                n_guide_steps: 1,
                t_stopgrad,
                scale_grad_by_std: false,
            };
            let guided = run(&m, trailing(1, 0.0), Some(g(0.02, 0)), 9).expect("guided");
            let w = Tensor::from_slice(&[1.0f64, 2.0, -1.0]).unsqueeze(0);
            let want = &w * (0.02 * (1.0 - a) / a.sqrt());
            let diff = guided.x.to_kind(Kind::Double) - plain.x.to_kind(Kind::Double);
            assert!(max_diff(&diff, &want.expand([4, 3], false)) < 1e-4 * (1.0 + want.abs().max().double_value(&[])));
            assert_eq!(guided.rewards.expect("rewards").size(), vec![4]);
            // t_stopgrad above the only step: unguided, rewards still reported.
            let stopped = run(&m, trailing(1, 0.0), Some(g(0.02, T)), 9).expect("stopped");
            assert!(bitwise_equal(&stopped.x, &plain.x) && stopped.rewards.is_some());
            // DDIM guides once per step through eps: other settings are refused by name.
            let err = run(&m, trailing(1, 0.0), Some(Guidance { n_guide_steps: 2, ..g(0.02, 0) }), 9)
                .expect_err("steps")
                .to_string();
            assert!(err.contains("n_guide_steps: 2 with DDIM"), "{err}");
            let err = run(&m, trailing(1, 0.0), Some(Guidance { scale_grad_by_std: true, ..g(0.02, 0) }), 9)
                .expect_err("scale")
                .to_string();
            assert!(err.contains("scale_grad_by_std"), "{err}");
            let err = run(&m, trailing(0, 0.0), None, 9).expect_err("n").to_string();
            assert!(err.contains("ddim.n_steps: 0"), "{err}");
        }

        #[test]
        fn ddim_calls_back_once_per_subset_step_and_keeps_conditions() {
            let m = traj_model();
            let start = Tensor::from_slice(&[0.25f32, -0.75]);
            let mut seen = Vec::new();
            let out = GuidedSampler::new(&m)
                .with_conditions(vec![Condition { index: 0, state: start.shallow_clone() }])
                .with_ddim(Ddim { n_steps: 5, eta: 1.0, spacing: Spacing::Leading, set_alpha_to_one: true })
                .sample_with(8, &mut Rng::new(2), &mut |s| {
                    seen.push(s.t);
                    Ok(())
                })
                .expect("sample");
            assert_eq!(seen, vec![40, 30, 20, 10, 0]);
            let obs0 = out.x.narrow(1, 0, 1).narrow(2, 1, 2).reshape([8, 2]);
            assert!(bitwise_equal(&obs0, &start.unsqueeze(0).expand([8, 2], false)));
        }
    }

    struct Detached;
    impl RewardFn for Detached {
        fn rho(&self, x: &Tensor, _t: &Tensor) -> Result<Tensor> {
            Ok(x.detach().sum_dim_intlist([1i64].as_slice(), false, Kind::Float))
        }
    }

    struct BadShape;
    impl RewardFn for BadShape {
        fn rho(&self, x: &Tensor, _t: &Tensor) -> Result<Tensor> {
            Ok(x.sum(Kind::Float))
        }
    }

    #[test]
    fn invalid_requests_are_rejected_before_sampling() {
        let traj = traj_model();
        let run = |conditions: Vec<Condition>| {
            GuidedSampler::new(&traj).with_conditions(conditions).sample(4, &mut Rng::new(1))
        };
        let err = run(vec![Condition { index: 4, state: Tensor::zeros([2], (Kind::Float, Device::Cpu)) }])
            .expect_err("index");
        assert!(err.to_string().contains("conditions[0].index: 4 is outside the horizon 0..4"), "{err}");
        let err =
            run(vec![Condition { index: 0, state: Tensor::zeros([3], (Kind::Float, Device::Cpu)) }]).expect_err("dim");
        assert!(err.to_string().contains("expected [2] or [4, 2]") && err.to_string().contains("[3]"), "{err}");
        let err = run(vec![Condition { index: 0, state: Tensor::from_slice(&[f32::NAN, 0.0]) }]).expect_err("nan");
        assert!(err.to_string().contains("not finite"), "{err}");
        let flat = sample_model();
        let err = GuidedSampler::new(&flat)
            .with_conditions(vec![Condition { index: 0, state: Tensor::zeros([2], (Kind::Float, Device::Cpu)) }])
            .sample(4, &mut Rng::new(1))
            .expect_err("sample space");
        assert!(err.to_string().contains("only trajectory models"), "{err}");
        assert!(sample(&flat, 0, &mut Rng::new(1)).is_err());
        let g = |reward: &dyn RewardFn, omega: f64| {
            GuidedSampler::new(&flat)
                .with_guidance(Guidance { reward, omega, n_guide_steps: 1, t_stopgrad: 0, scale_grad_by_std: false })
                .sample(4, &mut Rng::new(1))
        };
        assert!(matches!(g(&w3(), f64::NAN), Err(Error::InvalidArgument(_))));
        assert!(matches!(g(&Detached, 1.0), Err(Error::FailedPrecondition(_))));
        assert!(matches!(g(&BadShape, 1.0), Err(Error::FailedPrecondition(_))));
    }
}
