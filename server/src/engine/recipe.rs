//! Sampling recipes: how a conditional model's prediction is formed at each denoising step from
//! its conditional and unconditional outputs. A [`Recipe`] (classifier-free guidance scale, and
//! optionally Safe Latent Diffusion's guidance away from a concept) is the rule; a [`RecipeRun`]
//! applies it to one batch of chains (their prompts, and SLD's momentum, which is state carried
//! from step to step). Samplers and Algorithm 2's chains ask a run for the prediction where
//! they would ask a model, so a recipe stands wherever a diffusion model stands.
//!
//! With pred(c) the prediction under each chain's prompt c, pred(null) under the null
//! condition and pred(S) under the safety concept (the mean over its conditions), all converted
//! to eps so that thresholds mean the same whatever the model predicts:
//!
//! ```text
//! classifier-free guidance (Ho & Salimans):  eps = eps(null) + s (eps(c) - eps(null))
//! Safe Latent Diffusion (Schramowski et al. 2023, section 3, eqs. 3-5 and momentum):
//!   eps   = eps(null) + s (eps(c) - eps(null) - gamma)
//!   gamma = mu * (eps(S) - eps(null)) + s_m nu,    nu <- beta_m nu + (1 - beta_m) gamma
//!   mu    = min(1, s_S |eps(c) - eps(S)|) where eps(c) - eps(S) < lambda, else 0 (elementwise)
//!   gamma acts only from step delta on (warm-up); nu accumulates from the first step
//! ```
//!
//! The paper's eq. 3 puts gamma inside the guidance scale's parentheses; diffusers'
//! `StableDiffusionPipelineSafe` subtracts it outside (unscaled). This follows the paper. The
//! combined eps goes back to the model's parametrization (x0 or v) for the sampler. Every
//! condition's pass is one batched call of the denoiser ([prompts; null; concept...] stacked).

use tch::{Kind, Tensor};

use relreward_proto::schema::recipe::{PromptSet, RecipeSpec};

use super::diffusion::DiffusionModel;
use super::manifest::Conditioning;
use crate::error::{Error, Result};

/// A prompt set (the schema's values) as a tensor: int64 `[k]` labels or float32 `[k, dim]`.
pub fn prompt_tensor(p: &PromptSet) -> Tensor {
    match p {
        PromptSet::Labels(l) => Tensor::from_slice(l),
        PromptSet::Embeddings { dim, values } => Tensor::from_slice(values).reshape([p.len() as i64, *dim as i64]),
    }
}

/// The engine's recipe for a recipe's settings (the schema's): its prompts are the caller's.
pub fn recipe_of(spec: &RecipeSpec) -> Recipe {
    Recipe {
        guidance_scale: spec.guidance_scale,
        safety: spec.safety.as_ref().map(|s| Safety {
            concept: prompt_tensor(&s.concept),
            scale: s.scale,
            warmup_steps: s.warmup_steps,
            threshold: s.threshold,
            momentum_scale: s.momentum_scale,
            momentum_beta: s.momentum_beta,
        }),
    }
}

/// Safe Latent Diffusion's settings (diffusers' names in parentheses).
#[derive(Debug)]
pub struct Safety {
    /// The unsafe concept: one or more conditions, int64 `[k]` labels or float32 `[k, dim]`.
    pub concept: Tensor,
    /// s_S (`sld_guidance_scale`), >= 0.
    pub scale: f64,
    /// delta (`sld_warmup_steps`): steps without safety guidance at the start of a run.
    pub warmup_steps: usize,
    /// lambda (`sld_threshold`).
    pub threshold: f64,
    /// s_m (`sld_momentum_scale`), >= 0.
    pub momentum_scale: f64,
    /// beta_m (`sld_mom_beta`), in [0, 1).
    pub momentum_beta: f64,
}

/// How a conditional model's prediction is formed (module doc).
#[derive(Debug)]
pub struct Recipe {
    /// s: 1 is the conditional prediction alone, 0 the unconditional one.
    pub guidance_scale: f64,
    pub safety: Option<Safety>,
}

impl Recipe {
    /// The conditional model as it is: pred(c), one call per step.
    pub fn conditional() -> Self {
        Self { guidance_scale: 1.0, safety: None }
    }

    /// Checks the settings against `model`; messages name `field` (the request's recipe).
    pub fn validate(&self, model: &DiffusionModel, field: &str) -> Result<()> {
        let Some(conditioning) = model.conditioning() else {
            return Err(Error::invalid(format!(
                "{field}: the model is unconditional; guidance_scale, prompts and safety need a conditional model"
            )));
        };
        let s = self.guidance_scale;
        if !s.is_finite() || s.abs() > 1e6 {
            return Err(Error::invalid(format!("{field}.guidance_scale: {s} must be finite, |s| <= 1e6")));
        }
        if self.needs_null() && !conditioning.has_null() {
            return Err(Error::invalid(format!(
                "{field}.guidance_scale: {s} needs the unconditional prediction, but the model has no null condition \
                 (its conditioning has no null_class); use guidance_scale 1 without safety"
            )));
        }
        if let Some(sld) = &self.safety {
            let f = format!("{field}.safety");
            for (name, v) in [("scale", sld.scale), ("momentum_scale", sld.momentum_scale)] {
                if !v.is_finite() || v < 0.0 {
                    return Err(Error::invalid(format!("{f}.{name}: {v} must be finite and >= 0")));
                }
            }
            if !sld.threshold.is_finite() {
                return Err(Error::invalid(format!("{f}.threshold: {} must be finite", sld.threshold)));
            }
            if !(0.0..1.0).contains(&sld.momentum_beta) {
                return Err(Error::invalid(format!("{f}.momentum_beta: {} must be in [0, 1)", sld.momentum_beta)));
            }
            check_conditions(&sld.concept, conditioning, &format!("{f}.concept"), None)?;
        }
        Ok(())
    }

    /// Whether the unconditional prediction enters (every recipe but the plain conditional one).
    fn needs_null(&self) -> bool {
        self.guidance_scale != 1.0 || self.safety.is_some()
    }
}

/// Checks conditions (`[k]` labels or `[k, dim]` embeddings, k >= 1, or exactly `[n]` /
/// `[n, dim]` when `n` is given) against the model's conditioning; messages name `field`.
pub fn check_conditions(c: &Tensor, conditioning: &Conditioning, field: &str, n: Option<i64>) -> Result<()> {
    let (size, kind) = (c.size(), c.f_kind()?);
    let count = size.first().copied().unwrap_or(0);
    if count < 1 || n.is_some_and(|n| n != count) {
        let want = n.map_or("at least one".to_string(), |n| n.to_string());
        return Err(Error::invalid(format!("{field}: {count} conditions given, {want} needed")));
    }
    match *conditioning {
        Conditioning::Labels { num_classes, .. } => {
            if size.len() != 1 || kind != Kind::Int64 {
                return Err(Error::invalid(format!(
                    "{field}: the model takes class labels (int64 [k]), got {kind:?} {size:?}"
                )));
            }
            let (lo, hi) = (c.f_min()?.f_int64_value(&[])?, c.f_max()?.f_int64_value(&[])?);
            if lo < 0 || hi >= num_classes as i64 {
                return Err(Error::invalid(format!(
                    "{field}: label {} is outside 0..{num_classes}",
                    if lo < 0 { lo } else { hi }
                )));
            }
        }
        Conditioning::Embedding { dim } => {
            if size.len() != 2 || size[1] != dim as i64 || kind != Kind::Float {
                return Err(Error::invalid(format!(
                    "{field}: the model takes float32 embeddings [k, {dim}], got {kind:?} {size:?}"
                )));
            }
            if c.f_isfinite()?.f_all()?.f_int64_value(&[])? != 1 {
                return Err(Error::invalid(format!("{field}: an embedding holds NaN or infinite values")));
            }
        }
    }
    Ok(())
}

/// A recipe applied to one batch of chains (module doc).
pub struct RecipeRun<'a> {
    model: &'a DiffusionModel,
    recipe: &'a Recipe,
    /// Every condition of a pass stacked: [prompts; null; concept_1; ..; concept_k], each `[B]`
    /// or `[B, dim]`, so one denoiser call serves them all (the null alone at scale 0 without
    /// safety).
    stacked: Tensor,
    batch: i64,
    /// SLD's momentum nu (None until the first safety step).
    momentum: Option<Tensor>,
    /// Steps taken so far (for the warm-up).
    step: usize,
}

impl<'a> RecipeRun<'a> {
    /// A run over `prompts` (one condition per chain, already checked by the caller against
    /// the model), on the prompts' device.
    pub fn new(model: &'a DiffusionModel, recipe: &'a Recipe, prompts: &Tensor) -> Result<Self> {
        let batch = prompts.size()[0];
        let device = prompts.device();
        // Scale 0 without safety is pred(null) alone: one pass over the null condition, not a
        // pass over the prompts whose result the scale would zero.
        let null_only = recipe.guidance_scale == 0.0 && recipe.safety.is_none();
        let mut parts = if null_only { Vec::new() } else { vec![prompts.shallow_clone()] };
        if recipe.needs_null() {
            parts.push(model.null_condition(batch, device, "recipe")?);
        }
        if let Some(sld) = &recipe.safety {
            let concept = sld.concept.f_to_device(device)?;
            for j in 0..concept.size()[0] {
                // One concept condition repeated over the batch: [B] or [B, dim].
                let one = concept.f_narrow(0, j, 1)?;
                let mut reps = vec![batch];
                reps.extend(std::iter::repeat_n(1, one.dim() - 1));
                parts.push(one.f_repeat(&reps)?);
            }
        }
        let stacked = if parts.len() == 1 { parts.swap_remove(0) } else { Tensor::f_cat(&parts, 0)? };
        Ok(Self { model, recipe, stacked, batch, momentum: None, step: 0 })
    }

    /// The recipe's prediction at (x, t) in the model's parametrization, `x` `[B, ..]` with
    /// the run's batch; advances the run by one step.
    pub fn predict(&mut self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let b = self.batch;
        if x.size().first() != Some(&b) {
            return Err(Error::internal("recipe run", format!("x has {:?} items, the run {b}", x.size().first())));
        }
        let step = self.step;
        self.step += 1;
        let s = self.recipe.guidance_scale;
        let passes = self.stacked.size()[0] / b;
        if passes == 1 {
            // The conditional model alone (scale 1), or the unconditional one (scale 0).
            return self.model.predict_given(x, t, Some(&self.stacked));
        }
        let mut reps = vec![passes];
        reps.extend(std::iter::repeat_n(1, x.dim() - 1));
        let xs = x.f_repeat(&reps)?;
        let ts = t.f_repeat([passes])?;
        let pred = self.model.predict_given(&xs, &ts, Some(&self.stacked))?;
        let eps = self.model.eps_from_prediction(&xs, &ts, &pred)?;
        let chunk = |i: i64| eps.f_narrow(0, i * b, b);
        let (eps_c, eps_null) = (chunk(0)?, chunk(1)?);
        let mut guidance = eps_c.f_sub(&eps_null)?;
        if let Some(sld) = &self.recipe.safety {
            let k = passes - 2;
            let mut eps_s = chunk(2)?;
            for j in 1..k {
                eps_s = eps_s.f_add(&chunk(2 + j)?)?;
            }
            if k > 1 {
                eps_s = eps_s.f_div_scalar(k as f64)?;
            }
            let diff = eps_c.f_sub(&eps_s)?;
            let scale = diff.f_abs()?.f_mul_scalar(sld.scale)?.f_clamp_max(1.0)?;
            let mu = scale.f_where_self(&diff.f_lt(sld.threshold)?, &scale.f_zeros_like()?)?;
            let mut gamma = mu.f_mul(&eps_s.f_sub(&eps_null)?)?;
            if let Some(nu) = &self.momentum {
                gamma = gamma.f_add(&nu.f_mul_scalar(sld.momentum_scale)?)?;
            }
            let nu = match &self.momentum {
                Some(nu) => nu.f_mul_scalar(sld.momentum_beta)?,
                None => gamma.f_zeros_like()?,
            };
            self.momentum = Some(nu.f_add(&gamma.f_mul_scalar(1.0 - sld.momentum_beta)?)?);
            if step >= sld.warmup_steps {
                guidance = guidance.f_sub(&gamma)?;
            }
        }
        let combined = eps_null.f_add(&guidance.f_mul_scalar(s)?)?;
        self.model.prediction_from_eps(x, t, &combined)
    }
}

/// Where a step's prediction comes from: the model itself (unconditional), or a recipe's run
/// over its batch's prompts. Samplers and Algorithm 2's chains step through one.
pub enum Predictor<'a> {
    Model(&'a DiffusionModel),
    Recipe(RecipeRun<'a>),
}

impl<'a> Predictor<'a> {
    /// `model` asked directly when `recipe` is None, else through a run over `prompts` (one
    /// condition per item, checked against the model).
    pub fn new(model: &'a DiffusionModel, recipe: Option<(&'a Recipe, &Tensor)>) -> Result<Self> {
        Ok(match recipe {
            None => Self::Model(model),
            Some((recipe, prompts)) => Self::Recipe(RecipeRun::new(model, recipe, prompts)?),
        })
    }

    /// The raw prediction at (x, t) (a recipe run advances by one step).
    pub fn predict(&mut self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        match self {
            Self::Model(m) => m.predict(x, t),
            Self::Recipe(run) => run.predict(x, t),
        }
    }

    /// The sampler's mean mu(x_t, t) from [`Self::predict`]: the posterior mean with x0_hat
    /// clamped as the manifest's `clip_denoised` says (what `DiffusionModel::model_mean` is
    /// for an unconditional model).
    pub fn mean(&mut self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let pred = self.predict(x, t)?;
        let model = match self {
            Self::Model(m) => *m,
            Self::Recipe(run) => run.model,
        };
        let x0 = model.x0_from_prediction(x, t, &pred, model.clip_denoised())?;
        model.q_posterior_mean(&x0, x, t)
    }
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;
    use crate::engine::denoiser::Denoiser;
    use crate::engine::manifest::{DiffusionManifest, Parametrization, ScheduleSpec, Space};
    use crate::engine::normalizer::Normalizer;

    /// eps(x, t, c) = 0.1 x + class_row[c] (+ 0.01 t): every class its own known offset.
    struct ByClass {
        rows: Tensor,
    }

    impl Denoiser for ByClass {
        fn forward(&self, x: &Tensor, t: &Tensor, cond: Option<&Tensor>) -> Result<Tensor> {
            let c = cond.expect("conditional");
            let t = t.to_kind(Kind::Float).unsqueeze(1) * 0.01;
            Ok(x * 0.1 + self.rows.index_select(0, c) + t)
        }
        fn parameter_count(&self) -> u64 {
            0
        }
    }

    fn model(parametrization: Parametrization, null: Option<usize>) -> DiffusionModel {
        let rows = Tensor::from_slice(&[0.5f32, -1.0, 2.0, 0.0, 0.3, 0.2, -0.4, 1.5]).reshape([4, 2]);
        let manifest = DiffusionManifest {
            parametrization,
            schedule: ScheduleSpec::Cosine { s: 0.008 },
            n_timesteps: 10,
            clip_denoised: false,
            space: Space::Sample { shape: vec![2] },
            normalizer: Normalizer::Identity,
            architecture: None,
            conditioning: Some(Conditioning::Labels { num_classes: 4, null_class: null }),
        };
        DiffusionModel::new(manifest, Box::new(ByClass { rows })).expect("model")
    }

    fn eps(m: &DiffusionModel, x: &Tensor, t: &Tensor, label: i64) -> Tensor {
        let c = Tensor::full([x.size()[0]], label, (Kind::Int64, Device::Cpu));
        let pred = m.predict_given(x, t, Some(&c)).expect("pred");
        m.eps_from_prediction(x, t, &pred).expect("eps")
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b).abs().max().double_value(&[])
    }

    /// Classifier-free guidance on an eps model and an x0 model: the formula, in eps.
    #[test]
    fn guidance_scale_is_ho_and_salimans_in_eps() {
        for p in [Parametrization::Epsilon, Parametrization::X0, Parametrization::V] {
            let m = model(p, Some(3));
            let x = Tensor::from_slice(&[0.2f32, -0.7, 1.1, 0.4]).reshape([2, 2]);
            let t = Tensor::from_slice(&[3i64, 8]);
            let prompts = Tensor::from_slice(&[1i64, 2]);
            let recipe = Recipe { guidance_scale: 3.0, safety: None };
            recipe.validate(&m, "recipe").expect("valid");
            let pred = RecipeRun::new(&m, &recipe, &prompts).expect("run").predict(&x, &t).expect("predict");
            let got = m.eps_from_prediction(&x, &t, &pred).expect("eps");
            let c = Tensor::cat(
                &[
                    eps(&m, &x.narrow(0, 0, 1), &t.narrow(0, 0, 1), 1),
                    eps(&m, &x.narrow(0, 1, 1), &t.narrow(0, 1, 1), 2),
                ],
                0,
            );
            let null = eps(&m, &x, &t, 3);
            let want = &null + (c - &null) * 3.0;
            assert!(max_diff(&got, &want) < 1e-5, "{p:?}: {got:?} vs {want:?}");
        }
    }

    /// Safe Latent Diffusion, three steps by hand (warm-up 1, momentum on, a threshold that
    /// switches some elements off), against the recipe.
    #[test]
    fn safety_guidance_follows_the_papers_equations_with_warmup_and_momentum() {
        let m = model(Parametrization::Epsilon, Some(3));
        let x = Tensor::from_slice(&[0.2f32, -0.7, 1.1, 0.4]).reshape([2, 2]);
        let prompts = Tensor::from_slice(&[0i64, 1]);
        let sld = Safety {
            concept: Tensor::from_slice(&[2i64]),
            scale: 0.6,
            warmup_steps: 1,
            threshold: 0.5,
            momentum_scale: 0.3,
            momentum_beta: 0.4,
        };
        let recipe = Recipe { guidance_scale: 2.0, safety: Some(sld) };
        recipe.validate(&m, "recipe").expect("valid");
        let mut run = RecipeRun::new(&m, &recipe, &prompts).expect("run");
        let mut nu = Tensor::zeros([2, 2], (Kind::Float, Device::Cpu));
        for step in 0..3 {
            let t = Tensor::from_slice(&[9 - step as i64, 9 - step as i64]);
            let got = run.predict(&x, &t).expect("predict");
            let c = Tensor::cat(
                &[
                    eps(&m, &x.narrow(0, 0, 1), &t.narrow(0, 0, 1), 0),
                    eps(&m, &x.narrow(0, 1, 1), &t.narrow(0, 1, 1), 1),
                ],
                0,
            );
            let (null, s) = (eps(&m, &x, &t, 3), eps(&m, &x, &t, 2));
            let diff: Vec<f32> = Vec::try_from((&c - &s).flatten(0, -1)).expect("diff");
            let mu: Vec<f32> = diff.iter().map(|d| if *d < 0.5 { (0.6 * d.abs()).min(1.0) } else { 0.0 }).collect();
            let mu = Tensor::from_slice(&mu).reshape([2, 2]);
            let gamma = mu * (&s - &null) + &nu * 0.3;
            nu = &nu * 0.4 + &gamma * 0.6;
            let gamma = if step >= 1 { gamma } else { gamma.zeros_like() };
            let want = &null + (c - &null - gamma) * 2.0;
            assert!(max_diff(&got, &want) < 1e-5, "step {step}: {got:?} vs {want:?}");
        }
    }

    #[test]
    fn recipes_are_refused_by_name() {
        let no_null = model(Parametrization::Epsilon, None);
        let err =
            Recipe { guidance_scale: 2.0, safety: None }.validate(&no_null, "r").expect_err("no null").to_string();
        assert!(err.contains("r.guidance_scale") && err.contains("null"), "{err}");
        assert!(Recipe::conditional().validate(&no_null, "r").is_ok());
        let m = model(Parametrization::Epsilon, Some(3));
        let bad = |sld: Safety| {
            Recipe { guidance_scale: 1.0, safety: Some(sld) }.validate(&m, "r").expect_err("bad").to_string()
        };
        let base = || Safety {
            concept: Tensor::from_slice(&[2i64]),
            scale: 1.0,
            warmup_steps: 0,
            threshold: 0.0,
            momentum_scale: 0.0,
            momentum_beta: 0.0,
        };
        assert!(bad(Safety { momentum_beta: 1.0, ..base() }).contains("r.safety.momentum_beta"));
        assert!(bad(Safety { scale: -1.0, ..base() }).contains("r.safety.scale"));
        assert!(bad(Safety { concept: Tensor::from_slice(&[7i64]), ..base() }).contains("r.safety.concept: label 7"));
        assert!(bad(Safety { concept: Tensor::from_slice(&[0.5f32]), ..base() }).contains("r.safety.concept"));
        let err = Recipe { guidance_scale: f64::NAN, safety: None }.validate(&m, "r").expect_err("nan").to_string();
        assert!(err.contains("r.guidance_scale"), "{err}");
    }
}
