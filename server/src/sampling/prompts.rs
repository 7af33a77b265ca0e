//! A Sample request's conditioning, checked against the model's manifest: `prompts` (one
//! condition per sample, or one for all), `guidance_scale` and `safety` (Safe Latent Diffusion's
//! concept and settings), into the schema's [`RecipeSpec`] (one definition with a reward job's
//! recipes) whose prompts are the n samples' own, and the engine's [`Recipe`]. A named recipe
//! (`model` names one) brings all three: sample i takes its prompt i mod k ([`plan_named`]).

use relreward_proto::schema::recipe::{
    DEFAULT_GUIDANCE_SCALE, PromptSet, RecipeManifest, RecipeSpec, SafetySpec, check_guidance_scale,
};
use relreward_proto::v1 as pb;
use tch::Tensor;

use crate::engine::manifest::Conditioning;
use crate::engine::nets::inputs::describe;
use crate::engine::recipe::{Recipe, prompt_tensor, recipe_of};
use crate::error::{Error, Result};

/// The conditioning of one Sample run: a recipe whose prompt set holds the n samples' prompts.
#[derive(Debug)]
pub(super) struct RecipePlan(RecipeSpec);

impl RecipePlan {
    /// The engine's recipe (its safety concept as a tensor).
    pub(super) fn recipe(&self) -> Recipe {
        recipe_of(&self.0)
    }

    /// The condition of sample `i`, as the wire reports it (one label, or one embedding `[dim]`).
    pub(super) fn prompt(&self, i: usize) -> pb::Prompts {
        match &self.0.prompts {
            PromptSet::Labels(l) => pb::Prompts { labels: vec![l[i]], ..Default::default() },
            PromptSet::Embeddings { dim, values } => pb::Prompts {
                embeddings: Some(relreward_proto::tensor::encode_f32(&[*dim as u64], &values[i * dim..(i + 1) * dim])),
                ..Default::default()
            },
        }
    }

    /// The prompts of samples `start..start + n`: int64 `[n]` or float32 `[n, dim]`.
    pub(super) fn prompts(&self, start: usize, n: usize) -> Tensor {
        prompt_tensor(&self.0.prompts).narrow(0, start as i64, n as i64)
    }
}

/// The request's conditioning for `n` samples of a model with `conditioning` (None:
/// unconditional, which refuses every conditioning field). Checks, in order: guidance_scale
/// (finite, |s| <= 1e6), prompts (present unless only the null condition is asked for; n or
/// one; in the model's labels or of its width), safety (its concept, scales, threshold, beta),
/// and the null condition where it is needed.
pub(super) fn plan(
    req: &pb::SampleRequest,
    conditioning: Option<&Conditioning>,
    n: usize,
) -> Result<Option<RecipePlan>> {
    let Some(conditioning) = conditioning else {
        if let Some(field) = recipe_field(req) {
            return Err(Error::invalid(format!(
                "{field}: model '{}' is unconditional (its manifest has no conditioning)",
                req.model
            )));
        }
        return Ok(None);
    };
    let guidance_scale = req.guidance_scale.unwrap_or(DEFAULT_GUIDANCE_SCALE);
    check_guidance_scale(guidance_scale, "guidance_scale")?;
    let prompts = match &req.prompts {
        // Checked against the model with the rest of the recipe below.
        Some(p) => PromptSet::from_proto(p, "prompts")?,
        // The unconditional prediction alone needs no prompt: the null condition for all.
        None if guidance_scale == 0.0 && req.safety.is_none() && conditioning.has_null() => null_prompt(conditioning),
        None => {
            return Err(Error::invalid(format!(
                "prompts: missing; model '{}' is conditional ({}): give labels or embeddings",
                req.model,
                describe(conditioning)
            )));
        }
    };
    if prompts.len() != 1 && prompts.len() != n {
        return Err(Error::invalid(format!(
            "prompts: {} conditions for n = {n} samples; give one per sample or one for all",
            prompts.len()
        )));
    }
    let safety = req.safety.as_ref().map(|s| SafetySpec::from_proto(s, "safety")).transpose()?;
    // Checked against the model before one condition is repeated n times: an embedding of the
    // wrong width would otherwise be copied n times first (a request's few megabytes, times n).
    let mut spec = RecipeSpec { prompts, guidance_scale, safety };
    spec.check_against(Some(conditioning), "", &req.model).map_err(|e| {
        // The request's fields are top-level ("guidance_scale", "safety.concept").
        Error::invalid(e.0.trim_start_matches('.').to_string())
    })?;
    spec.prompts = broadcast(spec.prompts, n);
    Ok(Some(RecipePlan(spec)))
}

/// The conditioning of `n` samples through named recipe `recipe` (which the request's `model`
/// names): the request must leave prompts, guidance_scale and safety to the recipe; sample i
/// takes the recipe's prompt i mod k, so a run covers the prompt set evenly and reproducibly.
pub(super) fn plan_named(req: &pb::SampleRequest, recipe: &RecipeManifest, n: usize) -> Result<RecipePlan> {
    if let Some(field) = recipe_field(req) {
        return Err(Error::invalid(format!(
            "{field}: model '{}' is a recipe over '{}' that brings its own prompts, guidance_scale and safety; \
             leave them unset, or sample '{}' with your own",
            req.model, recipe.model, recipe.model
        )));
    }
    let spec = &recipe.recipe;
    let k = spec.prompts.len().max(1);
    let prompts = match &spec.prompts {
        PromptSet::Labels(l) => PromptSet::Labels((0..n).map(|i| l[i % k]).collect()),
        PromptSet::Embeddings { dim, values } => PromptSet::Embeddings {
            dim: *dim,
            values: (0..n).flat_map(|i| values[(i % k) * dim..(i % k + 1) * dim].iter().copied()).collect(),
        },
    };
    Ok(RecipePlan(RecipeSpec { prompts, ..spec.clone() }))
}

/// The first of the request's recipe fields (prompts, guidance_scale, safety) that is set.
fn recipe_field(req: &pb::SampleRequest) -> Option<&'static str> {
    [
        (req.prompts.is_some(), "prompts"),
        (req.guidance_scale.is_some(), "guidance_scale"),
        (req.safety.is_some(), "safety"),
    ]
    .into_iter()
    .find_map(|(set, field)| set.then_some(field))
}

fn null_prompt(c: &Conditioning) -> PromptSet {
    match *c {
        Conditioning::Labels { null_class, .. } => PromptSet::Labels(vec![null_class.unwrap_or(0) as i64]),
        Conditioning::Embedding { dim } => PromptSet::Embeddings { dim, values: vec![0.0; dim] },
    }
}

/// One condition repeated to `n` (a request may give one for every sample).
fn broadcast(p: PromptSet, n: usize) -> PromptSet {
    if p.len() != 1 || n == 1 {
        return p;
    }
    match p {
        PromptSet::Labels(l) => PromptSet::Labels(vec![l[0]; n]),
        PromptSet::Embeddings { dim, values } => PromptSet::Embeddings { dim, values: values.repeat(n) },
    }
}
