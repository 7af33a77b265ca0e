//! A sampling recipe: how a conditional diffusion model's denoising mean is formed, as data
//! (`relreward.v1.SamplingRecipe`, a Sample request's `prompts` / `guidance_scale` / `safety`,
//! and a reward job's `base_recipe` / `expert_recipe`). One definition for the wire, the stored
//! job spec and the checks; the server's `engine::recipe` does the arithmetic.
//!
//! - [`PromptSet`]: conditions as values: class labels, or embeddings of one width.
//! - [`SafetySpec`]: Safe Latent Diffusion's concept and settings (reward.proto's
//!   `SafetyGuidance` gives the formulas).
//! - [`RecipeSpec`]: a prompt set (each chain or sample draws one), the classifier-free guidance
//!   scale, and optional safety guidance.
//! - [`RecipeManifest`]: a named recipe's stored manifest (`ModelService.CreateRecipe`): the
//!   conditional model it samples, pinned by sha256, and its spec; also what a reward remembers
//!   of each side it was extracted from.
//!
//! Checks that need no model are here ([`RecipeSpec::from_proto`], messages naming the field);
//! [`PromptSet::check_against`] checks conditions against a model's conditioning.

use serde::{Deserialize, Serialize};

use super::manifest::Conditioning;
use super::{Invalid, invalid};
use crate::tensor;
use crate::v1 as pb;

/// Conditions as values (labels, or row-major embeddings of width `dim`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PromptSet {
    Labels(Vec<i64>),
    Embeddings { dim: usize, values: Vec<f32> },
}

impl PromptSet {
    pub fn len(&self) -> usize {
        match self {
            Self::Labels(l) => l.len(),
            Self::Embeddings { dim, values } => values.len() / (*dim).max(1),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// From a `Prompts` message: exactly one of labels and embeddings, embeddings `[dim]` or
    /// `[k, dim]` of finite values; `field` names it in messages.
    pub fn from_proto(p: &pb::Prompts, field: &str) -> Result<Self, Invalid> {
        if !p.dataset.is_empty() {
            // The server reads it (and replaces it by its conditions) where a recipe is stored.
            return invalid(format!(
                "{field}.dataset: a prompt dataset is read only where a recipe is stored (CreateRecipe, a reward \
                 job's base_recipe / expert_recipe); give labels or embeddings here"
            ));
        }
        match (p.labels.is_empty(), &p.embeddings) {
            (false, Some(_)) => invalid(format!("{field}: set labels or embeddings, not both")),
            (true, None) => invalid(format!("{field}: empty; give labels or embeddings")),
            (false, None) => Ok(Self::Labels(p.labels.clone())),
            (true, Some(e)) => {
                let dim = match e.shape.as_slice() {
                    [d] | [_, d] if *d >= 1 && e.shape.first().is_some_and(|&k| k >= 1) => *d as usize,
                    _ => {
                        return invalid(format!(
                            "{field}.embeddings: shape {:?}; expected [dim] or [k, dim], k and dim >= 1",
                            e.shape
                        ));
                    }
                };
                let values =
                    tensor::decode_finite_f32(e).map_err(|err| Invalid(format!("{field}.embeddings: {err}")))?;
                Ok(Self::Embeddings { dim, values })
            }
        }
    }

    pub fn to_proto(&self) -> pb::Prompts {
        match self {
            Self::Labels(l) => pb::Prompts { labels: l.clone(), ..Default::default() },
            Self::Embeddings { dim, values } => pb::Prompts {
                embeddings: Some(tensor::encode_f32(&[self.len() as u64, *dim as u64], values)),
                ..Default::default()
            },
        }
    }

    /// Checks the conditions against a model's conditioning: labels in its range, embeddings
    /// of its width; `model` and `field` are named in messages.
    pub fn check_against(&self, c: &Conditioning, field: &str, model: &str) -> Result<(), Invalid> {
        match (self, *c) {
            (Self::Labels(l), Conditioning::Labels { num_classes, .. }) => {
                if let Some((i, v)) = l.iter().enumerate().find(|(_, v)| !(0..num_classes as i64).contains(*v)) {
                    return invalid(format!(
                        "{field}.labels[{i}]: {v} is outside the labels 0..{num_classes} of model '{model}'"
                    ));
                }
                Ok(())
            }
            (Self::Embeddings { dim, .. }, Conditioning::Embedding { dim: want }) if *dim != want => invalid(format!(
                "{field}.embeddings: width {dim}, but model '{model}' takes embeddings of width {want}"
            )),
            (Self::Embeddings { .. }, Conditioning::Embedding { .. }) => Ok(()),
            (Self::Embeddings { .. }, Conditioning::Labels { num_classes, .. }) => invalid(format!(
                "{field}.embeddings: model '{model}' takes class labels (0..{num_classes}); set labels"
            )),
            (Self::Labels(_), Conditioning::Embedding { dim }) => {
                invalid(format!("{field}.labels: model '{model}' takes embeddings of width {dim}; set embeddings"))
            }
        }
    }
}

/// Safe Latent Diffusion's settings (reward.proto's `SafetyGuidance`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SafetySpec {
    pub concept: PromptSet,
    pub scale: f64,
    pub warmup_steps: usize,
    pub threshold: f64,
    pub momentum_scale: f64,
    pub momentum_beta: f64,
}

impl SafetySpec {
    pub fn from_proto(s: &pb::SafetyGuidance, field: &str) -> Result<Self, Invalid> {
        let concept = s
            .concept
            .as_ref()
            .ok_or_else(|| Invalid(format!("{field}.concept: missing; name the concept to steer away from")))?;
        let spec = Self {
            concept: PromptSet::from_proto(concept, &format!("{field}.concept"))?,
            scale: s.scale,
            warmup_steps: s.warmup_steps as usize,
            threshold: s.threshold,
            momentum_scale: s.momentum_scale,
            momentum_beta: s.momentum_beta,
        };
        spec.validate(field)?;
        Ok(spec)
    }

    pub fn validate(&self, field: &str) -> Result<(), Invalid> {
        for (name, v) in [("scale", self.scale), ("momentum_scale", self.momentum_scale)] {
            if !v.is_finite() || v < 0.0 {
                return invalid(format!("{field}.{name}: {v} must be finite and >= 0"));
            }
        }
        if !self.threshold.is_finite() {
            return invalid(format!("{field}.threshold: {} must be finite", self.threshold));
        }
        if !(0.0..1.0).contains(&self.momentum_beta) {
            return invalid(format!("{field}.momentum_beta: {} must be in [0, 1)", self.momentum_beta));
        }
        Ok(())
    }

    pub fn to_proto(&self) -> pb::SafetyGuidance {
        pb::SafetyGuidance {
            concept: Some(self.concept.to_proto()),
            scale: self.scale,
            warmup_steps: u32::try_from(self.warmup_steps).unwrap_or(u32::MAX),
            threshold: self.threshold,
            momentum_scale: self.momentum_scale,
            momentum_beta: self.momentum_beta,
        }
    }
}

/// Classifier-free guidance's scale when none is given: the conditional model alone.
pub const DEFAULT_GUIDANCE_SCALE: f64 = 1.0;

/// How a conditional model is sampled (module doc).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecipeSpec {
    /// The prompt set: each chain (or sample) draws one.
    pub prompts: PromptSet,
    pub guidance_scale: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safety: Option<SafetySpec>,
}

impl RecipeSpec {
    /// From a `SamplingRecipe` message; `field` names it in messages.
    pub fn from_proto(r: &pb::SamplingRecipe, field: &str) -> Result<Self, Invalid> {
        let prompts = r
            .prompts
            .as_ref()
            .ok_or_else(|| Invalid(format!("{field}.prompts: missing; give the prompt set the chains draw from")))?;
        let spec = Self {
            prompts: PromptSet::from_proto(prompts, &format!("{field}.prompts"))?,
            guidance_scale: r.guidance_scale.unwrap_or(DEFAULT_GUIDANCE_SCALE),
            safety: r.safety.as_ref().map(|s| SafetySpec::from_proto(s, &format!("{field}.safety"))).transpose()?,
        };
        spec.validate(field)?;
        Ok(spec)
    }

    pub fn validate(&self, field: &str) -> Result<(), Invalid> {
        check_guidance_scale(self.guidance_scale, &format!("{field}.guidance_scale"))?;
        if let Some(s) = &self.safety {
            s.validate(&format!("{field}.safety"))?;
        }
        Ok(())
    }

    /// Whether the unconditional prediction enters (so the model needs a null condition).
    pub fn needs_null(&self) -> bool {
        self.guidance_scale != 1.0 || self.safety.is_some()
    }

    /// Checks the recipe against model `model`'s conditioning (None: unconditional, refused).
    pub fn check_against(&self, c: Option<&Conditioning>, field: &str, model: &str) -> Result<(), Invalid> {
        let Some(c) = c else {
            return invalid(format!("{field}: model '{model}' is unconditional; a recipe needs a conditional model"));
        };
        self.prompts.check_against(c, &format!("{field}.prompts"), model)?;
        if let Some(s) = &self.safety {
            s.concept.check_against(c, &format!("{field}.safety.concept"), model)?;
        }
        if self.needs_null() && !c.has_null() {
            return invalid(format!(
                "{field}.guidance_scale: {}{} needs the unconditional prediction, but model '{model}' has no null condition",
                self.guidance_scale,
                if self.safety.is_some() { " with safety" } else { "" }
            ));
        }
        Ok(())
    }

    pub fn to_proto(&self) -> pb::SamplingRecipe {
        pb::SamplingRecipe {
            prompts: Some(self.prompts.to_proto()),
            guidance_scale: Some(self.guidance_scale),
            safety: self.safety.as_ref().map(SafetySpec::to_proto),
        }
    }
}

/// A recipe bound to its model: a named recipe's stored manifest (`recipe.json`), and a reward's
/// record of how a side was sampled (`Model.reward.base_recipe`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecipeManifest {
    /// The conditional diffusion model sampled.
    pub model: String,
    /// Its sha256 when the recipe was made: a model replaced under the same name is noticed.
    pub model_sha256: String,
    pub recipe: RecipeSpec,
    /// The stored dataset its prompt set was read from, if it came from one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prompt_dataset: Option<String>,
}

impl RecipeManifest {
    pub fn to_proto(&self) -> pb::RecipeInfo {
        pb::RecipeInfo {
            model: self.model.clone(),
            model_sha256: self.model_sha256.clone(),
            recipe: Some(self.recipe.to_proto()),
            prompt_dataset: self.prompt_dataset.clone().unwrap_or_default(),
        }
    }
}

/// A classifier-free guidance scale: finite, |s| <= 1e6 (the bound on guidance scales).
pub fn check_guidance_scale(s: f64, field: &str) -> Result<(), Invalid> {
    if !s.is_finite() || s.abs() > 1e6 {
        return invalid(format!("{field}: {s} must be finite, |s| <= 1e6"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(l: &[i64]) -> pb::Prompts {
        pb::Prompts { labels: l.to_vec(), ..Default::default() }
    }

    #[test]
    fn recipes_round_trip_and_name_the_field() {
        let r = pb::SamplingRecipe {
            prompts: Some(labels(&[0, 2])),
            guidance_scale: Some(3.0),
            safety: Some(pb::SafetyGuidance {
                concept: Some(labels(&[1])),
                scale: 1000.0,
                warmup_steps: 10,
                threshold: 0.01,
                momentum_scale: 0.3,
                momentum_beta: 0.4,
            }),
        };
        let spec = RecipeSpec::from_proto(&r, "spec.reward.expert_recipe").expect("valid");
        assert_eq!(spec.to_proto(), r);
        let c = Conditioning::Labels { num_classes: 3, null_class: Some(2) };
        spec.check_against(Some(&c), "r", "m").expect("fits");
        let no_null = Conditioning::Labels { num_classes: 3, null_class: None };
        let err = spec.check_against(Some(&no_null), "r", "m").expect_err("no null").0;
        assert!(err.starts_with("r.guidance_scale: 3 with safety needs"), "{err}");
        let small = Conditioning::Labels { num_classes: 2, null_class: Some(1) };
        let err = spec.check_against(Some(&small), "r", "m").expect_err("range").0;
        assert!(err.starts_with("r.prompts.labels[1]: 2 is outside"), "{err}");
        assert!(spec.check_against(None, "r", "m").expect_err("uncond").0.contains("unconditional"));
        let bad = pb::SamplingRecipe {
            safety: Some(pb::SafetyGuidance { momentum_beta: 1.0, ..r.safety.clone().expect("s") }),
            ..r.clone()
        };
        let err = RecipeSpec::from_proto(&bad, "x").expect_err("beta").0;
        assert!(err.starts_with("x.safety.momentum_beta: 1"), "{err}");
        let err = RecipeSpec::from_proto(&pb::SamplingRecipe { prompts: None, ..r.clone() }, "x").expect_err("p").0;
        assert!(err.starts_with("x.prompts: missing"), "{err}");
        let both = pb::Prompts {
            labels: vec![1],
            embeddings: Some(tensor::encode_f32(&[2], &[0.0, 1.0])),
            ..Default::default()
        };
        let err = PromptSet::from_proto(&both, "p").expect_err("both").0;
        assert!(err.contains("not both"), "{err}");
        let e = PromptSet::from_proto(
            &pb::Prompts { embeddings: Some(tensor::encode_f32(&[2, 3], &[0.5; 6])), ..Default::default() },
            "p",
        )
        .expect("embeddings");
        assert_eq!(e.len(), 2);
        let json = serde_json::to_string(&spec).expect("json");
        assert_eq!(serde_json::from_str::<RecipeSpec>(&json).expect("back"), spec);
    }
}
