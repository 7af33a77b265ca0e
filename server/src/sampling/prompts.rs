//! A Sample request's conditioning, checked on host values against the model's manifest:
//! `prompts` (one condition per sample, or one for all), `guidance_scale` and `safety` (Safe
//! Latent Diffusion's concept and settings), into a [`RecipePlan`] the worker turns into the
//! engine's [`Recipe`] and per-batch prompt tensors.

use relreward_proto::tensor;
use relreward_proto::v1 as pb;
use tch::Tensor;

use crate::engine::manifest::Conditioning;
use crate::engine::recipe::{Recipe, Safety};
use crate::error::{Error, Result, brief};

/// Conditions as host values: labels, or embeddings of width `dim` (row-major).
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Conditions {
    Labels(Vec<i64>),
    Embeddings { dim: usize, values: Vec<f32> },
}

impl Conditions {
    fn len(&self) -> usize {
        match self {
            Self::Labels(l) => l.len(),
            Self::Embeddings { dim, values } => values.len() / dim.max(&1),
        }
    }

    /// Rows `start..start + n` as a tensor: int64 `[n]` or float32 `[n, dim]`.
    pub(super) fn tensor(&self, start: usize, n: usize) -> Tensor {
        match self {
            Self::Labels(l) => Tensor::from_slice(&l[start..start + n]),
            Self::Embeddings { dim, values } => {
                Tensor::from_slice(&values[start * dim..(start + n) * dim]).reshape([n as i64, *dim as i64])
            }
        }
    }

    /// One condition repeated to `n` (a request may give one for every sample).
    fn broadcast(self, n: usize) -> Self {
        if self.len() != 1 || n == 1 {
            return self;
        }
        match self {
            Self::Labels(l) => Self::Labels(vec![l[0]; n]),
            Self::Embeddings { dim, values } => Self::Embeddings { dim, values: values.repeat(n) },
        }
    }
}

/// The conditioning of one Sample run.
#[derive(Debug)]
pub(super) struct RecipePlan {
    /// One condition per sample (n of them).
    pub prompts: Conditions,
    pub guidance_scale: f64,
    pub safety: Option<(Conditions, pb::SafetyGuidance)>,
}

impl RecipePlan {
    /// The engine's recipe (the concept as a tensor).
    pub(super) fn recipe(&self) -> Recipe {
        Recipe {
            guidance_scale: self.guidance_scale,
            safety: self.safety.as_ref().map(|(concept, s)| Safety {
                concept: concept.tensor(0, concept.len()),
                scale: s.scale,
                warmup_steps: s.warmup_steps as usize,
                threshold: s.threshold,
                momentum_scale: s.momentum_scale,
                momentum_beta: s.momentum_beta,
            }),
        }
    }
}

/// The request's conditioning for `n` samples of a model with `conditioning` (None:
/// unconditional, which refuses every conditioning field). Checks, in order: prompts (present
/// unless guidance_scale is 0; n or one), guidance_scale (finite, |s| <= 1e6; the null
/// condition where it is needed), safety (its concept, scales, threshold, beta).
pub(super) fn plan(
    req: &pb::SampleRequest,
    conditioning: Option<&Conditioning>,
    n: usize,
) -> Result<Option<RecipePlan>> {
    let Some(conditioning) = conditioning else {
        for (set, field) in [
            (req.prompts.is_some(), "prompts"),
            (req.guidance_scale.is_some(), "guidance_scale"),
            (req.safety.is_some(), "safety"),
        ] {
            if set {
                return Err(Error::invalid(format!(
                    "{field}: model '{}' is unconditional (its manifest has no conditioning)",
                    req.model
                )));
            }
        }
        return Ok(None);
    };
    let guidance_scale = req.guidance_scale.unwrap_or(1.0);
    if !guidance_scale.is_finite() || guidance_scale.abs() > 1e6 {
        return Err(Error::invalid(format!("guidance_scale: {guidance_scale} must be finite, |s| <= 1e6")));
    }
    let prompts = match &req.prompts {
        Some(p) => conditions(p, conditioning, "prompts")?,
        // The unconditional model alone needs no prompt: the null condition for every sample.
        None if guidance_scale == 0.0 && req.safety.is_none() && conditioning.has_null() => {
            null_conditions(conditioning)
        }
        None => {
            return Err(Error::invalid(format!(
                "prompts: missing; model '{}' is conditional ({}): give labels or embeddings",
                req.model,
                crate::engine::nets::inputs::describe(conditioning)
            )));
        }
    };
    if prompts.len() != 1 && prompts.len() != n {
        return Err(Error::invalid(format!(
            "prompts: {} conditions for n = {n} samples; give one per sample or one for all",
            prompts.len()
        )));
    }
    let needs_null = guidance_scale != 1.0 || req.safety.is_some();
    if needs_null && !conditioning.has_null() {
        return Err(Error::invalid(format!(
            "guidance_scale: {guidance_scale}{} needs the unconditional prediction, but model '{}' has no null condition \
             (its conditioning has no null_class)",
            if req.safety.is_some() { " with safety" } else { "" },
            req.model
        )));
    }
    let safety = match &req.safety {
        None => None,
        Some(s) => {
            let concept = s
                .concept
                .as_ref()
                .ok_or_else(|| Error::invalid("safety.concept: missing; name the concept to steer away from"))?;
            let concept = conditions(concept, conditioning, "safety.concept")?;
            for (name, v) in [("scale", s.scale), ("momentum_scale", s.momentum_scale)] {
                if !v.is_finite() || v < 0.0 {
                    return Err(Error::invalid(format!("safety.{name}: {v} must be finite and >= 0")));
                }
            }
            if !s.threshold.is_finite() {
                return Err(Error::invalid(format!("safety.threshold: {} must be finite", s.threshold)));
            }
            if !(0.0..1.0).contains(&s.momentum_beta) {
                return Err(Error::invalid(format!("safety.momentum_beta: {} must be in [0, 1)", s.momentum_beta)));
            }
            Some((concept, s.clone()))
        }
    };
    Ok(Some(RecipePlan { prompts: prompts.broadcast(n), guidance_scale, safety }))
}

fn null_conditions(c: &Conditioning) -> Conditions {
    match *c {
        Conditioning::Labels { null_class, .. } => Conditions::Labels(vec![null_class.unwrap_or(0) as i64]),
        Conditioning::Embedding { dim } => Conditions::Embeddings { dim, values: vec![0.0; dim] },
    }
}

/// A `Prompts` message checked against the model's conditioning; messages name `field`.
fn conditions(p: &pb::Prompts, c: &Conditioning, field: &str) -> Result<Conditions> {
    match (*c, p.labels.is_empty(), &p.embeddings) {
        (_, false, Some(_)) => Err(Error::invalid(format!("{field}: set labels or embeddings, not both"))),
        (_, true, None) => Err(Error::invalid(format!("{field}: empty; give labels or embeddings"))),
        (Conditioning::Labels { num_classes, .. }, false, None) => {
            if let Some((i, l)) = p.labels.iter().enumerate().find(|(_, l)| !(0..num_classes as i64).contains(*l)) {
                return Err(Error::invalid(format!(
                    "{field}.labels[{i}]: {l} is outside the model's labels 0..{num_classes}"
                )));
            }
            Ok(Conditions::Labels(p.labels.clone()))
        }
        (Conditioning::Labels { num_classes, .. }, true, Some(_)) => Err(Error::invalid(format!(
            "{field}.embeddings: the model takes class labels (0..{num_classes}); set labels"
        ))),
        (Conditioning::Embedding { dim }, false, None) => {
            Err(Error::invalid(format!("{field}.labels: the model takes embeddings of width {dim}; set embeddings")))
        }
        (Conditioning::Embedding { dim }, true, Some(e)) => {
            let ok = matches!(e.shape.as_slice(), [d] if *d == dim as u64)
                || matches!(e.shape.as_slice(), [k, d] if *k >= 1 && *d == dim as u64);
            if !ok {
                return Err(Error::invalid(format!(
                    "{field}.embeddings: shape {} but the model takes [{dim}] or [k, {dim}]",
                    brief(&e.shape)
                )));
            }
            let values =
                tensor::decode_finite_f32(e).map_err(|err| Error::invalid(format!("{field}.embeddings: {err}")))?;
            Ok(Conditions::Embeddings { dim, values })
        }
    }
}
