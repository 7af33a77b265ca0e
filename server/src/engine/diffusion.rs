//! [`DiffusionModel`]: a denoiser network together with its manifest and schedule, and the
//! DDPM quantities built from its output: x0_hat, eps_hat, the posterior mean mu and variance,
//! the score, the forward process and the training loss.
//!
//! Conventions (docs/method.md section 2, Diffuser's): inputs are in normalized units, `x` is float32
//! `[B, *item_shape]` and `t` int64 `[B]` in `0..T` (`t = 0` is the last denoising step). Every
//! entry point validates shapes and `t` and answers `InvalidArgument` naming what was expected
//! and what was given, so no libtorch op downstream can fail on a caller's shape.
//!
//! Grad mode is the caller's: [`DiffusionModel::loss`] must be differentiable for training, and
//! frozen models are called under `tch::no_grad` by their users (sampler, reward trainer).
//!
//! Clipping: with `clip_denoised`, Diffuser clamps x0_hat to [-1, 1] before forming the
//! posterior mean. Clipping is therefore an explicit argument of [`DiffusionModel::x0_hat`] and
//! [`DiffusionModel::posterior_mean`]; [`DiffusionModel::model_mean`] applies the manifest's
//! choice and is what the sampler uses. `eps_hat` and `score` are never clipped: for an
//! x0-predicting net they are derived from its raw x0 prediction.

use tch::{Device, Kind, Tensor};

use super::denoiser::Denoiser;
use super::manifest::{Conditioning, DiffusionManifest, Parametrization, Space};
use super::nets::inputs::check_condition;
use super::schedule::{Schedule, Table};
use crate::error::{Error, Result};

pub struct DiffusionModel {
    pub manifest: DiffusionManifest,
    pub schedule: Schedule,
    net: Box<dyn Denoiser>,
}

impl std::fmt::Debug for DiffusionModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DiffusionModel")
            .field("manifest", &self.manifest)
            .field("parameters", &self.net.parameter_count())
            .finish_non_exhaustive()
    }
}

impl DiffusionModel {
    /// Validates the manifest and builds its schedule.
    pub fn new(manifest: DiffusionManifest, net: Box<dyn Denoiser>) -> Result<Self> {
        manifest.validate()?;
        let schedule = Schedule::new(&manifest.schedule, manifest.n_timesteps)?;
        Ok(Self { manifest, schedule, net })
    }

    /// Shape of one item, without the batch dimension.
    pub fn item_shape(&self) -> Vec<i64> {
        self.manifest.space.item_shape()
    }

    pub fn n_timesteps(&self) -> usize {
        self.schedule.n_timesteps()
    }

    pub fn parametrization(&self) -> Parametrization {
        self.manifest.parametrization
    }

    /// Whether the manifest asks for x0_hat to be clamped to [-1, 1] when sampling.
    pub fn clip_denoised(&self) -> bool {
        self.manifest.clip_denoised
    }

    pub fn net(&self) -> &dyn Denoiser {
        self.net.as_ref()
    }

    pub fn conditioning(&self) -> Option<&Conditioning> {
        self.manifest.conditioning.as_ref()
    }

    /// `n` copies of the model's null condition (the unconditional input of classifier-free
    /// guidance): its null label, or zero embeddings. A model without one refuses, naming
    /// `field`.
    pub fn null_condition(&self, n: i64, device: Device, field: &str) -> Result<Tensor> {
        match self.manifest.conditioning {
            None => Err(Error::invalid(format!("{field}: the model is unconditional"))),
            Some(Conditioning::Labels { null_class: Some(null), .. }) => {
                Ok(Tensor::f_full([n], null as i64, (Kind::Int64, device))?)
            }
            Some(Conditioning::Labels { null_class: None, num_classes }) => Err(Error::invalid(format!(
                "{field}: needs the unconditional prediction, but the model (labels 0..{num_classes}) has no null label"
            ))),
            Some(Conditioning::Embedding { dim }) => Ok(Tensor::f_zeros([n, dim as i64], (Kind::Float, device))?),
        }
    }

    /// Checks that `x` (named `name` in messages) is float32 `[B, *item_shape]` with B >= 1 and
    /// returns B.
    pub fn check_x(&self, x: &Tensor, name: &str) -> Result<i64> {
        let size = x.size();
        let item = self.item_shape();
        let kind = x.f_kind()?;
        let ok = size.len() == item.len() + 1 && size[1..] == item[..] && size[0] >= 1 && kind == Kind::Float;
        if !ok {
            return Err(Error::invalid(format!(
                "{name}: expected float32 [B, {}] with B >= 1, got {kind:?} {size:?}",
                item.iter().map(i64::to_string).collect::<Vec<_>>().join(", ")
            )));
        }
        Ok(size[0])
    }

    /// Checks `x` and that `t` is int64 `[B]` with values in `0..T`; returns B.
    pub fn check_xt(&self, x: &Tensor, t: &Tensor) -> Result<i64> {
        let b = self.check_x(x, "x")?;
        self.schedule.check_t(t, Some(b))?;
        Ok(b)
    }

    /// Checks that `other` (named `name`) has exactly `x`'s shape and is float32.
    fn check_same(x: &Tensor, other: &Tensor, name: &str) -> Result<()> {
        let kind = other.f_kind()?;
        if other.size() != x.size() || kind != Kind::Float {
            return Err(Error::invalid(format!(
                "{name}: expected float32 {:?} (the shape of x), got {kind:?} {:?}",
                x.size(),
                other.size()
            )));
        }
        Ok(())
    }

    fn coef(&self, table: Table, t: &Tensor, x: &Tensor) -> Result<Tensor> {
        Ok(self.schedule.extract(table, t, x.dim())?.f_to_device(x.device())?)
    }

    /// The network's raw output (eps, x0 or v, per the manifest's parametrization), in the
    /// caller's grad mode, for an unconditional model (a conditional one refuses: its callers
    /// go through [`Self::predict_given`] or a [`super::recipe::Recipe`]). A net whose output
    /// does not match its input's shape does not match its manifest: `FailedPrecondition`.
    pub fn predict(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.predict_given(x, t, None)
    }

    /// [`Self::predict`] under the condition `cond` of each item (a conditional model's int64
    /// labels `[B]` or float32 embeddings `[B, dim]`; `None` for an unconditional model).
    pub fn predict_given(&self, x: &Tensor, t: &Tensor, cond: Option<&Tensor>) -> Result<Tensor> {
        let b = self.check_xt(x, t)?;
        check_condition("model", cond, self.manifest.conditioning.as_ref(), b)?;
        let out = self.net.forward(x, t, cond)?;
        if out.size() != x.size() || out.f_kind()? != Kind::Float {
            return Err(Error::FailedPrecondition(format!(
                "denoiser returned {:?} {:?} for input float32 {:?}: the model does not match its manifest",
                out.f_kind()?,
                out.size(),
                x.size()
            )));
        }
        Ok(out)
    }

    /// x0 = sqrt(1 / abar_t) x_t - sqrt(1 / abar_t - 1) eps (no net call).
    pub fn x0_from_eps(&self, x_t: &Tensor, t: &Tensor, eps: &Tensor) -> Result<Tensor> {
        self.check_xt(x_t, t)?;
        Self::check_same(x_t, eps, "eps")?;
        let a = self.coef(Table::SqrtRecipAlphasCumprod, t, x_t)?;
        let b = self.coef(Table::SqrtRecipm1AlphasCumprod, t, x_t)?;
        Ok(x_t.f_mul(&a)?.f_sub(&eps.f_mul(&b)?)?)
    }

    /// eps = (sqrt(1 / abar_t) x_t - x0) / sqrt(1 / abar_t - 1), the inverse of
    /// [`Self::x0_from_eps`] (no net call). The denominator is positive: every beta is > 0.
    pub fn eps_from_x0(&self, x_t: &Tensor, t: &Tensor, x0: &Tensor) -> Result<Tensor> {
        self.check_xt(x_t, t)?;
        Self::check_same(x_t, x0, "x0")?;
        let a = self.coef(Table::SqrtRecipAlphasCumprod, t, x_t)?;
        let b = self.coef(Table::SqrtRecipm1AlphasCumprod, t, x_t)?;
        Ok(x_t.f_mul(&a)?.f_sub(x0)?.f_div(&b)?)
    }

    /// x0_hat from a raw net output `pred` at (x_t, t), clamped to [-1, 1] when `clip`.
    pub fn x0_from_prediction(&self, x_t: &Tensor, t: &Tensor, pred: &Tensor, clip: bool) -> Result<Tensor> {
        let x0 = match self.parametrization() {
            Parametrization::Epsilon => self.x0_from_eps(x_t, t, pred)?,
            Parametrization::X0 => {
                self.check_xt(x_t, t)?;
                Self::check_same(x_t, pred, "prediction")?;
                pred.shallow_clone()
            }
            Parametrization::V => self.x0_from_v(x_t, t, pred)?,
        };
        Ok(if clip { x0.f_clamp(-1.0, 1.0)? } else { x0 })
    }

    /// eps_hat from a raw net output `pred` at (x_t, t); never clipped.
    pub fn eps_from_prediction(&self, x_t: &Tensor, t: &Tensor, pred: &Tensor) -> Result<Tensor> {
        match self.parametrization() {
            Parametrization::Epsilon => {
                self.check_xt(x_t, t)?;
                Self::check_same(x_t, pred, "prediction")?;
                Ok(pred.shallow_clone())
            }
            Parametrization::X0 => self.eps_from_x0(x_t, t, pred),
            Parametrization::V => self.eps_from_v(x_t, t, pred),
        }
    }

    /// The raw prediction of the model's parametrization that corresponds to `eps` at
    /// (x_t, t): eps itself, x0 = [`Self::x0_from_eps`], or v from that x0 and eps (no net
    /// call). What a recipe combined in eps hands back to the sampler.
    pub fn prediction_from_eps(&self, x_t: &Tensor, t: &Tensor, eps: &Tensor) -> Result<Tensor> {
        match self.parametrization() {
            Parametrization::Epsilon => {
                self.check_xt(x_t, t)?;
                Self::check_same(x_t, eps, "eps")?;
                Ok(eps.shallow_clone())
            }
            Parametrization::X0 => self.x0_from_eps(x_t, t, eps),
            Parametrization::V => self.v_target(&self.x0_from_eps(x_t, t, eps)?, t, eps),
        }
    }

    /// x0 = sqrt(abar_t) x_t - sqrt(1 - abar_t) v (no net call). With x_t = sqrt(abar) x0 +
    /// sqrt(1 - abar) eps and v = sqrt(abar) eps - sqrt(1 - abar) x0 this is exact, and
    /// well-conditioned at every t (no division, unlike the eps -> x0 conversion).
    pub fn x0_from_v(&self, x_t: &Tensor, t: &Tensor, v: &Tensor) -> Result<Tensor> {
        self.check_xt(x_t, t)?;
        Self::check_same(x_t, v, "v")?;
        let a = self.coef(Table::SqrtAlphasCumprod, t, x_t)?;
        let b = self.coef(Table::SqrtOneMinusAlphasCumprod, t, x_t)?;
        Ok(x_t.f_mul(&a)?.f_sub(&v.f_mul(&b)?)?)
    }

    /// eps = sqrt(abar_t) v + sqrt(1 - abar_t) x_t (no net call).
    pub fn eps_from_v(&self, x_t: &Tensor, t: &Tensor, v: &Tensor) -> Result<Tensor> {
        self.check_xt(x_t, t)?;
        Self::check_same(x_t, v, "v")?;
        let a = self.coef(Table::SqrtAlphasCumprod, t, x_t)?;
        let b = self.coef(Table::SqrtOneMinusAlphasCumprod, t, x_t)?;
        Ok(v.f_mul(&a)?.f_add(&x_t.f_mul(&b)?)?)
    }

    /// The velocity target v = sqrt(abar_t) eps - sqrt(1 - abar_t) x0 (no net call).
    pub fn v_target(&self, x0: &Tensor, t: &Tensor, eps: &Tensor) -> Result<Tensor> {
        self.check_xt(x0, t)?;
        Self::check_same(x0, eps, "noise")?;
        let a = self.coef(Table::SqrtAlphasCumprod, t, x0)?;
        let b = self.coef(Table::SqrtOneMinusAlphasCumprod, t, x0)?;
        Ok(eps.f_mul(&a)?.f_sub(&x0.f_mul(&b)?)?)
    }

    /// Mean of q(x_{t-1} | x_t, x0) = coef1_t x0 + coef2_t x_t (no net call).
    pub fn q_posterior_mean(&self, x0: &Tensor, x_t: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.check_xt(x_t, t)?;
        Self::check_same(x_t, x0, "x0")?;
        let c1 = self.coef(Table::PosteriorMeanCoef1, t, x_t)?;
        let c2 = self.coef(Table::PosteriorMeanCoef2, t, x_t)?;
        Ok(x0.f_mul(&c1)?.f_add(&x_t.f_mul(&c2)?)?)
    }

    /// The net's estimate of x0 at (x_t, t); `clip` clamps it to [-1, 1] (pass
    /// [`Self::clip_denoised`] for the manifest's choice).
    pub fn x0_hat(&self, x: &Tensor, t: &Tensor, clip: bool) -> Result<Tensor> {
        let pred = self.predict(x, t)?;
        self.x0_from_prediction(x, t, &pred, clip)
    }

    /// The net's estimate of the noise at (x_t, t); never clipped.
    pub fn eps_hat(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let pred = self.predict(x, t)?;
        self.eps_from_prediction(x, t, &pred)
    }

    /// mu(x_t, t) = coef1 x0_hat + coef2 x_t, with x0_hat clamped when `clip`. Unclipped, this
    /// equals (x_t - beta_t / sqrt(1 - abar_t) eps_hat) / sqrt(alpha_t).
    pub fn posterior_mean(&self, x: &Tensor, t: &Tensor, clip: bool) -> Result<Tensor> {
        let x0 = self.x0_hat(x, t, clip)?;
        self.q_posterior_mean(&x0, x, t)
    }

    /// The sampler's mean: [`Self::posterior_mean`] with the manifest's `clip_denoised`.
    pub fn model_mean(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.posterior_mean(x, t, self.manifest.clip_denoised)
    }

    /// Score estimate s(x_t, t) = -eps_hat / sqrt(1 - abar_t).
    pub fn score(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let eps = self.eps_hat(x, t)?;
        let s = self.coef(Table::SqrtOneMinusAlphasCumprod, t, x)?;
        Ok(eps.f_div(&s)?.f_neg()?)
    }

    /// The score implied by a clean-data estimate x0 at (x_t, t): -eps / sqrt(1 - abar_t) with
    /// eps = [`Self::eps_from_x0`] (no net call; [`Self::score`] is this at x0_hat).
    pub fn score_from_x0(&self, x_t: &Tensor, t: &Tensor, x0: &Tensor) -> Result<Tensor> {
        let eps = self.eps_from_x0(x_t, t, x0)?;
        let s = self.coef(Table::SqrtOneMinusAlphasCumprod, t, x_t)?;
        Ok(eps.f_div(&s)?.f_neg()?)
    }

    /// Posterior variance beta_t (1 - abar_{t-1}) / (1 - abar_t) per batch element, `[B]`.
    pub fn posterior_variance(&self, t: &Tensor) -> Result<Tensor> {
        self.schedule.extract(Table::PosteriorVariance, t, 1)
    }

    /// log(max(posterior variance, 1e-20)) per batch element, `[B]`.
    pub fn posterior_log_variance(&self, t: &Tensor) -> Result<Tensor> {
        self.schedule.extract(Table::PosteriorLogVarianceClipped, t, 1)
    }

    /// Forward process: x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) noise.
    pub fn q_sample(&self, x0: &Tensor, t: &Tensor, noise: &Tensor) -> Result<Tensor> {
        self.check_xt(x0, t)?;
        Self::check_same(x0, noise, "noise")?;
        let a = self.coef(Table::SqrtAlphasCumprod, t, x0)?;
        let b = self.coef(Table::SqrtOneMinusAlphasCumprod, t, x0)?;
        Ok(x0.f_mul(&a)?.f_add(&noise.f_mul(&b)?)?)
    }

    /// The DDPM training loss at given (x0, t, noise): mean squared error between the net's
    /// prediction at x_t = q_sample(x0, t, noise) and its target (`noise` for eps models, `x0`
    /// for x0 models, v = sqrt(abar_t) noise - sqrt(1 - abar_t) x0 for v models, as diffusers'
    /// training scripts form it with `get_velocity`). Differentiable with respect to the net's parameters in grad mode.
    ///
    /// `action_weight = Some((w, action_dim))` is Diffuser's `action_weight`: the per-element
    /// weight of the first transition's action coordinates `[.., 0, :action_dim]` is `w`
    /// instead of 1, and the loss is the mean of weight * squared error over all elements
    /// (Diffuser's `WeightedL2` with `loss_discount = 1` and no per-dimension weights; its
    /// conditioning of x_t during training is not applied here). Trajectory models only.
    ///
    /// `cond`: each item's condition for a conditional model (the training labels, some
    /// replaced by the null label for classifier-free guidance), `None` otherwise.
    pub fn loss(
        &self,
        x0: &Tensor,
        t: &Tensor,
        noise: &Tensor,
        action_weight: Option<(f64, usize)>,
        cond: Option<&Tensor>,
    ) -> Result<Tensor> {
        let weights = match action_weight {
            None => None,
            Some((w, action_dim)) => {
                let Space::Trajectory { horizon, action_dim: ad, obs_dim } = self.manifest.space else {
                    return Err(Error::invalid("action_weight: only trajectory models have actions"));
                };
                let transition = ad + obs_dim;
                if !(w.is_finite() && w >= 0.0) || action_dim > transition {
                    return Err(Error::invalid(format!(
                        "action_weight: weight {} must be finite and >= 0 and action_dim {action_dim} at most the transition dim {transition}",
                        crate::fields::number(w)
                    )));
                }
                let weights = Tensor::f_ones([horizon as i64, transition as i64], (Kind::Float, x0.device()))?;
                let mut first = weights.f_narrow(0, 0, 1)?.f_narrow(1, 0, action_dim as i64)?;
                let _filled = first.f_fill_(w)?;
                Some(weights)
            }
        };
        let x_t = self.q_sample(x0, t, noise)?;
        let pred = self.predict_given(&x_t, t, cond)?;
        let target = match self.parametrization() {
            Parametrization::Epsilon => noise.shallow_clone(),
            Parametrization::X0 => x0.shallow_clone(),
            Parametrization::V => self.v_target(x0, t, noise)?,
        };
        let sq = pred.f_sub(&target)?.f_square()?;
        let sq = match weights {
            Some(w) => sq.f_mul(&w)?,
            None => sq,
        };
        Ok(sq.f_mean(Kind::Float)?)
    }
}

/// Test-only denoisers with exactly known outputs.
#[cfg(test)]
pub(crate) mod testing {
    use tch::{Kind, Tensor};

    use super::super::denoiser::Denoiser;
    use super::super::schedule::{Schedule, Table};
    use crate::error::Result;

    /// The exact denoiser for data x0 ~ N(mean, I) under the VP process: x_t ~ N(sqrt(abar_t)
    /// mean, I), so eps(x_t, t) = sqrt(1 - abar_t) (x_t - sqrt(abar_t) mean), and
    /// E[x0 | x_t] = sqrt(abar_t) x_t + (1 - abar_t) mean for the x0 parametrization.
    pub(crate) struct AnalyticGaussian {
        /// `[*item_shape]`.
        pub mean: Tensor,
        sqrt_abar: Tensor,
        one_minus_abar: Tensor,
        sqrt_one_minus_abar: Tensor,
        predict: super::super::manifest::Parametrization,
    }

    impl AnalyticGaussian {
        pub(crate) fn new(schedule: &Schedule, mean: &[f32], item_shape: &[i64], predict_x0: bool) -> Self {
            use super::super::manifest::Parametrization as P;
            Self::predicting(schedule, mean, item_shape, if predict_x0 { P::X0 } else { P::Epsilon })
        }

        /// The same exact denoiser with any parametrization's output (v from the exact eps
        /// and x0).
        pub(crate) fn predicting(
            schedule: &Schedule,
            mean: &[f32],
            item_shape: &[i64],
            predict: super::super::manifest::Parametrization,
        ) -> Self {
            let abar: Vec<f64> = schedule.values(Table::AlphasCumprod).to_vec();
            Self {
                mean: Tensor::from_slice(mean).reshape(item_shape),
                sqrt_abar: Tensor::from_slice(&abar).sqrt().to_kind(Kind::Float),
                one_minus_abar: Tensor::from_slice(&abar.iter().map(|a| 1.0 - a).collect::<Vec<_>>())
                    .to_kind(Kind::Float),
                sqrt_one_minus_abar: Tensor::from_slice(&abar.iter().map(|a| (1.0 - a).sqrt()).collect::<Vec<_>>())
                    .to_kind(Kind::Float),
                predict,
            }
        }
    }

    impl Denoiser for AnalyticGaussian {
        fn forward(&self, x: &Tensor, t: &Tensor, _cond: Option<&Tensor>) -> Result<Tensor> {
            let mut shape = vec![1i64; x.dim()];
            shape[0] = x.size()[0];
            let sa = self.sqrt_abar.index_select(0, t).reshape(&shape);
            use super::super::manifest::Parametrization as P;
            let x0 = &sa * x + self.one_minus_abar.index_select(0, t).reshape(&shape) * &self.mean;
            let sb = self.sqrt_one_minus_abar.index_select(0, t).reshape(&shape);
            let eps = &sb * (x - &sa * &self.mean);
            Ok(match self.predict {
                P::X0 => x0,
                P::Epsilon => eps,
                P::V => &sa * eps - sb * x0,
            })
        }

        fn parameter_count(&self) -> u64 {
            0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::testing::AnalyticGaussian;
    use super::*;
    use crate::engine::manifest::ScheduleSpec;
    use crate::engine::normalizer::Normalizer;
    use crate::engine::rng::Rng;

    fn manifest(parametrization: Parametrization, space: Space, clip: bool) -> DiffusionManifest {
        DiffusionManifest {
            parametrization,
            schedule: ScheduleSpec::Cosine { s: 0.008 },
            n_timesteps: 50,
            clip_denoised: clip,
            space,
            normalizer: Normalizer::Identity,
            architecture: None,
            conditioning: None,
        }
    }

    fn model(parametrization: Parametrization, mean: &[f32], clip: bool) -> DiffusionModel {
        let m = manifest(parametrization, Space::Trajectory { horizon: 4, action_dim: 1, obs_dim: 2 }, clip);
        let s = Schedule::new(&m.schedule, m.n_timesteps).expect("schedule");
        let net = AnalyticGaussian::predicting(&s, mean, &[4, 3], parametrization);
        DiffusionModel::new(m, Box::new(net)).expect("model")
    }

    const MEAN: [f32; 12] = [0.5, -1.0, 2.0, 0.0, 0.3, -0.2, 1.0, 1.0, -1.5, 0.7, 0.1, 0.9];

    fn inputs(seed: u64) -> (Tensor, Tensor) {
        let mut rng = Rng::new(seed);
        let x = rng.randn(&[6, 4, 3], tch::Device::Cpu) * 1.5;
        let t = Tensor::from_slice(&[0i64, 1, 7, 25, 48, 49]);
        (x, t)
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b).abs().max().double_value(&[])
    }

    /// Per-row scalar from a f64 table, as a [B, 1, 1] f64 tensor.
    fn per_t(t: &[i64], f: impl Fn(usize) -> f64) -> Tensor {
        let v: Vec<f64> = t.iter().map(|&i| f(i as usize)).collect();
        Tensor::from_slice(&v).reshape([t.len() as i64, 1, 1])
    }

    const TS: [i64; 6] = [0, 1, 7, 25, 48, 49];

    #[test]
    fn score_and_mean_follow_reference_formulas() {
        let m = model(Parametrization::Epsilon, &MEAN, false);
        let (x, t) = inputs(1);
        let eps = m.eps_hat(&x, &t).expect("eps").to_kind(Kind::Double);
        let s = &m.schedule;
        let v = |table: Table, i: usize| s.values(table)[i];
        // score = -eps / sqrt(1 - abar_t)
        let want = -&eps / per_t(&TS, |i| (1.0 - v(Table::AlphasCumprod, i)).sqrt());
        let got = m.score(&x, &t).expect("score").to_kind(Kind::Double);
        assert!(max_diff(&got, &want) < 1e-5 * (1.0 + want.abs().max().double_value(&[])));
        // mu = (x_t - beta_t / sqrt(1 - abar_t) eps) / sqrt(alpha_t)
        let xd = x.to_kind(Kind::Double);
        let k = per_t(&TS, |i| v(Table::Betas, i) / (1.0 - v(Table::AlphasCumprod, i)).sqrt());
        let want = (&xd - k * &eps) / per_t(&TS, |i| v(Table::Alphas, i).sqrt());
        let got = m.posterior_mean(&x, &t, false).expect("mu").to_kind(Kind::Double);
        assert!(max_diff(&got, &want) < 1e-4, "mu differs by {}", max_diff(&got, &want));
        // For Gaussian data the exact x0_hat is E[x0 | x_t] = sqrt(abar) x_t + (1 - abar) mean.
        let mean = Tensor::from_slice(&MEAN).reshape([1, 4, 3]).to_kind(Kind::Double);
        let want = per_t(&TS, |i| v(Table::SqrtAlphasCumprod, i)) * &xd
            + per_t(&TS, |i| 1.0 - v(Table::AlphasCumprod, i)) * mean;
        let got = m.x0_hat(&x, &t, false).expect("x0").to_kind(Kind::Double);
        // The eps -> x0 conversion divides by sqrt(abar) (large near t = T - 1) in float32.
        assert!(max_diff(&got, &want) < 1e-3, "x0_hat differs by {}", max_diff(&got, &want));
    }

    #[test]
    fn forward_process_inverts_exactly_with_the_true_noise() {
        let m = model(Parametrization::Epsilon, &MEAN, false);
        let (x0, t) = inputs(2);
        let noise = Rng::new(3).randn(&[6, 4, 3], tch::Device::Cpu);
        let x_t = m.q_sample(&x0, &t, &noise).expect("q_sample");
        let back = m.x0_from_eps(&x_t, &t, &noise).expect("x0");
        // Relative to sqrt(1 / abar) at the noisiest step (float32 arithmetic).
        let scale = m.schedule.values(Table::SqrtRecipAlphasCumprod)[49];
        assert!(max_diff(&back, &x0) < 1e-5 * scale, "{}", max_diff(&back, &x0));
        let eps = m.eps_from_x0(&x_t, &t, &x0).expect("eps");
        // eps = (x_t / sqrt(abar) - x0) / sqrt(1 / abar - 1): ill-conditioned only at t = 0.
        assert!(max_diff(&eps.narrow(0, 1, 5), &noise.narrow(0, 1, 5)) < 1e-3);
    }

    #[test]
    fn both_parametrizations_give_the_same_quantities() {
        let e = model(Parametrization::Epsilon, &MEAN, false);
        let (x, t) = inputs(4);
        let t = t.narrow(0, 1, 5);
        let x = x.narrow(0, 1, 5);
        for other in [Parametrization::X0, Parametrization::V] {
            let o = model(other, &MEAN, false);
            for (name, a, b) in [
                ("x0_hat", e.x0_hat(&x, &t, false), o.x0_hat(&x, &t, false)),
                ("eps_hat", e.eps_hat(&x, &t), o.eps_hat(&x, &t)),
                ("mu", e.posterior_mean(&x, &t, false), o.posterior_mean(&x, &t, false)),
            ] {
                let (a, b) = (a.expect(name), b.expect(name));
                assert!(max_diff(&a, &b) < 2e-3, "{other:?} {name}: {}", max_diff(&a, &b));
            }
        }
    }

    #[test]
    fn v_conversions_follow_the_definitions() {
        // v = sqrt(abar) eps - sqrt(1 - abar) x0; x0 = sqrt(abar) x_t - sqrt(1 - abar) v;
        // eps = sqrt(abar) v + sqrt(1 - abar) x_t, by hand in f64 against the float32 tables.
        let m = model(Parametrization::V, &MEAN, false);
        let (x0, t) = inputs(12);
        let noise = Rng::new(13).randn(&[6, 4, 3], tch::Device::Cpu);
        let x_t = m.q_sample(&x0, &t, &noise).expect("x_t");
        let v = m.v_target(&x0, &t, &noise).expect("v");
        let sa = per_t(&TS, |i| m.schedule.values(Table::AlphasCumprod)[i].sqrt());
        let sb = per_t(&TS, |i| (1.0 - m.schedule.values(Table::AlphasCumprod)[i]).sqrt());
        let (x0d, nd, xd) = (x0.to_kind(Kind::Double), noise.to_kind(Kind::Double), x_t.to_kind(Kind::Double));
        let want_v = &sa * &nd - &sb * &x0d;
        assert!(max_diff(&v.to_kind(Kind::Double), &want_v) < 1e-5);
        // Exact inverses, at every t (no division anywhere).
        assert!(max_diff(&m.x0_from_v(&x_t, &t, &v).expect("x0"), &x0) < 1e-5);
        assert!(max_diff(&m.eps_from_v(&x_t, &t, &v).expect("eps"), &noise) < 1e-5);
        let vd = v.to_kind(Kind::Double);
        let want_x0 = &sa * &xd - &sb * &vd;
        assert!(
            max_diff(&m.x0_from_prediction(&x_t, &t, &v, false).expect("x0").to_kind(Kind::Double), &want_x0) < 1e-5
        );
        let want_eps = &sa * &vd + &sb * &xd;
        assert!(max_diff(&m.eps_from_prediction(&x_t, &t, &v).expect("eps").to_kind(Kind::Double), &want_eps) < 1e-5);
        // The training loss regresses onto v.
        let want = (m.predict(&x_t, &t).expect("pred") - &v).square().mean(Kind::Float).double_value(&[]);
        assert!((m.loss(&x0, &t, &noise, None, None).expect("loss").double_value(&[]) - want).abs() < 1e-6);
    }

    #[test]
    fn mean_difference_is_score_difference_times_beta_over_sqrt_alpha() {
        // docs/method.md section 1: mu_expert - mu_base = beta_t / sqrt(alpha_t) (s_expert - s_base).
        let base = model(Parametrization::Epsilon, &[0.0; 12], false);
        let expert = model(Parametrization::Epsilon, &MEAN, false);
        let (x, t) = inputs(5);
        let dmu = expert.posterior_mean(&x, &t, false).expect("mu") - base.posterior_mean(&x, &t, false).expect("mu");
        let ds = expert.score(&x, &t).expect("s") - base.score(&x, &t).expect("s");
        let v = |table: Table, i: usize| base.schedule.values(table)[i];
        let k = per_t(&TS, |i| v(Table::Betas, i) / v(Table::Alphas, i).sqrt()).to_kind(Kind::Float);
        assert!(max_diff(&dmu, &(k * ds)) < 1e-4);
        // And it points toward the expert's mean (positive inner product with mean - 0).
        let mean = Tensor::from_slice(&MEAN).reshape([1, 4, 3]);
        let dot = (dmu * mean).sum_dim_intlist([1i64, 2].as_slice(), false, Kind::Float);
        assert!(dot.min().double_value(&[]) > 0.0);
    }

    #[test]
    fn clipping_is_explicit_and_model_mean_follows_the_manifest() {
        let clipped = model(Parametrization::Epsilon, &[3.0; 12], true);
        let (x, t) = inputs(6);
        let x0 = clipped.x0_hat(&x, &t, true).expect("x0");
        assert!(x0.abs().max().double_value(&[]) <= 1.0);
        assert!(clipped.x0_hat(&x, &t, false).expect("x0").abs().max().double_value(&[]) > 1.0);
        let mm = clipped.model_mean(&x, &t).expect("mean");
        assert!(max_diff(&mm, &clipped.posterior_mean(&x, &t, true).expect("mu")) == 0.0);
        assert!(max_diff(&mm, &clipped.posterior_mean(&x, &t, false).expect("mu")) > 0.0);
    }

    #[test]
    fn variances_are_per_batch_element() {
        let m = model(Parametrization::Epsilon, &MEAN, false);
        let (_, t) = inputs(7);
        let v = m.posterior_variance(&t).expect("var");
        let lv = m.posterior_log_variance(&t).expect("logvar");
        assert_eq!(v.size(), vec![6]);
        assert_eq!(v.double_value(&[0]), 0.0);
        assert!((lv.double_value(&[0]) - (1e-20f64).ln()).abs() < 1e-4);
        for (i, &ti) in TS.iter().enumerate().skip(1) {
            let want = m.schedule.values(Table::PosteriorVariance)[ti as usize];
            assert!((v.double_value(&[i as i64]) - want).abs() < 1e-6 * (1.0 + want));
            assert!((lv.double_value(&[i as i64]).exp() - want).abs() < 1e-5 * want);
        }
    }

    #[test]
    fn loss_matches_a_hand_computation_and_weights_the_first_action() {
        let m = model(Parametrization::Epsilon, &MEAN, false);
        let (x0, t) = inputs(8);
        let noise = Rng::new(9).randn(&[6, 4, 3], tch::Device::Cpu);
        let x_t = m.q_sample(&x0, &t, &noise).expect("x_t");
        let sq = (m.predict(&x_t, &t).expect("pred") - &noise).square();
        let plain = m.loss(&x0, &t, &noise, None, None).expect("loss").double_value(&[]);
        assert!((plain - sq.mean(Kind::Float).double_value(&[])).abs() < 1e-6);
        let same = m.loss(&x0, &t, &noise, Some((1.0, 1)), None).expect("loss").double_value(&[]);
        assert!((same - plain).abs() < 1e-6);
        let weighted = m.loss(&x0, &t, &noise, Some((10.0, 1)), None).expect("loss").double_value(&[]);
        let extra = 9.0 * sq.narrow(1, 0, 1).narrow(2, 0, 1).sum(Kind::Float).double_value(&[]) / sq.numel() as f64;
        assert!((weighted - (plain + extra)).abs() < 1e-5, "{weighted} vs {}", plain + extra);
        // x0 parametrization: the target is x0.
        let mx = model(Parametrization::X0, &MEAN, false);
        let want = (mx.predict(&x_t, &t).expect("pred") - &x0).square().mean(Kind::Float).double_value(&[]);
        assert!((mx.loss(&x0, &t, &noise, None, None).expect("loss").double_value(&[]) - want).abs() < 1e-6);
    }

    #[test]
    fn bad_inputs_name_expected_and_given_shapes() {
        let m = model(Parametrization::Epsilon, &MEAN, false);
        let (x, t) = inputs(10);
        let err = m.eps_hat(&x.narrow(2, 0, 2), &t).expect_err("shape").to_string();
        assert!(err.contains("expected float32 [B, 4, 3]") && err.contains("[6, 4, 2]"), "{err}");
        let err = m.eps_hat(&x.to_kind(Kind::Double), &t).expect_err("kind").to_string();
        assert!(err.contains("Double"), "{err}");
        let err = m.eps_hat(&x, &t.narrow(0, 0, 5)).expect_err("t len").to_string();
        assert!(err.contains("expected shape [6]"), "{err}");
        let err = m.eps_hat(&x, &(&t + 1)).expect_err("t range").to_string();
        assert!(err.contains("0..50") && err.contains("max 50"), "{err}");
        let err = m.q_sample(&x, &t, &x.narrow(1, 0, 3)).expect_err("noise").to_string();
        assert!(err.contains("noise: expected float32 [6, 4, 3]"), "{err}");
        let err = m.loss(&x, &t, &x, Some((1.0, 4)), None).expect_err("action_dim").to_string();
        assert!(err.contains("action_dim 4"), "{err}");
        let sample = {
            let man = manifest(Parametrization::Epsilon, Space::Sample { shape: vec![2] }, false);
            let s = Schedule::new(&man.schedule, man.n_timesteps).expect("schedule");
            DiffusionModel::new(man, Box::new(AnalyticGaussian::new(&s, &[0.0, 0.0], &[2], false))).expect("model")
        };
        let x2 = Tensor::zeros([6, 2], (Kind::Float, tch::Device::Cpu));
        let err = sample.loss(&x2, &t, &x2, Some((1.0, 1)), None).expect_err("sample").to_string();
        assert!(err.contains("only trajectory models"), "{err}");
    }

    struct WrongShape;
    impl Denoiser for WrongShape {
        fn forward(&self, x: &Tensor, _t: &Tensor, _cond: Option<&Tensor>) -> Result<Tensor> {
            Ok(x.narrow(0, 0, 1))
        }
        fn parameter_count(&self) -> u64 {
            0
        }
    }

    #[test]
    fn a_net_that_breaks_its_manifest_is_a_failed_precondition() {
        let man = manifest(Parametrization::Epsilon, Space::Sample { shape: vec![2] }, false);
        let m = DiffusionModel::new(man, Box::new(WrongShape)).expect("model");
        let x = Tensor::zeros([3, 2], (Kind::Float, tch::Device::Cpu));
        let t = Tensor::from_slice(&[0i64, 1, 2]);
        match m.eps_hat(&x, &t) {
            Err(Error::FailedPrecondition(msg)) => assert!(msg.contains("[1, 2]"), "{msg}"),
            other => panic!("expected FailedPrecondition, got {other:?}"),
        }
    }
}
