//! The schema's names and defaults as one JSON document, `proto/schema.json`, for what is not
//! Rust: the Python package's specs are tested against it (`client/python/tests/
//! test_specs_schema.py`), so their field names follow the Rust types. A test here keeps the
//! committed file equal to [`summary`]; `RELREWARD_BLESS=1 cargo test -p relreward-proto`
//! rewrites it after a deliberate change.

use serde_json::{Map, Value, json};

use super::job::request::ArchKind;
use super::job::{
    AmortisedTargets, DIFFUSION_OPTIMIZATION, DISCRIMINATOR_OPTIMIZATION, DiffusionJob, DiscriminatorJob, EvalPoint,
    KindDefaults, Optimization, REWARD_OPTIMIZATION, RewardAlgorithm, RewardArchitecture, RewardJob, Target,
};
use super::job::{
    DEFAULT_CLIP_DENOISED, DEFAULT_CONDITION_DROPOUT, DEFAULT_HORIZON, DEFAULT_N_TIMESTEPS, DEFAULT_NUM_CHAINS,
    DEFAULT_PARAMETRIZATION, DEFAULT_SCHEDULE,
};
use super::manifest::{Architecture, Conditioning, DiffusionManifest, Normalizer, Parametrization, Space};
use super::recipe::{PromptSet, RecipeSpec, SafetySpec};

/// The field names of a serialized value, in order.
fn fields(v: impl serde::Serialize) -> Value {
    let Ok(Value::Object(map)) = serde_json::to_value(v) else { return Value::Null };
    Value::Array(map.keys().map(|k| Value::String(k.clone())).collect())
}

fn optimization(d: KindDefaults) -> Value {
    json!(Optimization::from_proto(&Default::default(), d))
}

/// The document (see the module documentation).
pub fn summary() -> Value {
    let trajectory = Space::Trajectory { horizon: DEFAULT_HORIZON, action_dim: 2, obs_dim: 4 };
    let diffusion = DiffusionJob {
        dataset: String::new(),
        parametrization: DEFAULT_PARAMETRIZATION,
        schedule: DEFAULT_SCHEDULE,
        n_timesteps: DEFAULT_N_TIMESTEPS,
        horizon: DEFAULT_HORIZON,
        architecture: Architecture::default_for(true),
        action_weight: 1.0,
        clip_denoised: DEFAULT_CLIP_DENOISED,
        normalizer_datasets: Vec::new(),
        pooled_normalizer: false,
        conditional: true,
        condition_dropout: Some(DEFAULT_CONDITION_DROPOUT),
        num_classes: Some(10),
    };
    // Every optional field set, so that each is named.
    // Every field of a recipe set, so that each is named.
    let recipe = RecipeSpec {
        prompts: PromptSet::Labels(vec![0, 1]),
        guidance_scale: 3.0,
        safety: Some(SafetySpec {
            concept: PromptSet::Labels(vec![1]),
            scale: 1000.0,
            warmup_steps: 10,
            threshold: 0.01,
            momentum_scale: 0.3,
            momentum_beta: 0.4,
        }),
    };
    let reward = RewardJob {
        base_model: String::new(),
        expert_model: String::new(),
        architecture: RewardArchitecture::default_for(&trajectory),
        target: Target::Mean,
        eval_point: EvalPoint::XT,
        algorithm: RewardAlgorithm::ModelsOnly { num_chains: DEFAULT_NUM_CHAINS },
        rho_l2: 0.0,
        amortised_targets: Some(AmortisedTargets::DEFAULT),
        action_weight: 1.0,
        condition_weight: 1.0,
        inpaint_condition: true,
        base_recipe: Some(recipe.clone()),
        expert_recipe: Some(recipe),
    };
    let discriminator = DiscriminatorJob {
        base_dataset: String::new(),
        expert_dataset: String::new(),
        architecture: RewardArchitecture::default_for(&trajectory),
        diffusion_model: String::new(),
        inpaint_condition: true,
    };
    let manifest = DiffusionManifest {
        parametrization: Parametrization::X0,
        schedule: DEFAULT_SCHEDULE,
        n_timesteps: DEFAULT_N_TIMESTEPS,
        clip_denoised: false,
        space: trajectory,
        normalizer: Normalizer::Identity,
        architecture: Some(Architecture::default_for(true)),
        // Set so that the field is named (a temporal_unet takes none: not a valid manifest).
        conditioning: Some(Conditioning::Labels { num_classes: 11, null_class: Some(10) }),
    };
    let reward_architectures: Map<String, Value> =
        [ArchKind::WindowedMlp, ArchKind::ValueFunction, ArchKind::ConvEncoder, ArchKind::Mlp]
            .into_iter()
            .map(|k| (k.name().to_owned(), json!(RewardArchitecture::default_of(k))))
            .collect();
    // A UNet2D with every field unset, as the wire may carry one.
    let unet2d = Architecture::from_proto(crate::v1::diffusion_manifest::Architecture::Unet2d(Default::default()));
    json!({
        "manifest": { "fields": fields(&manifest) },
        "optimization": {
            "fields": fields(Optimization::from_proto(&Default::default(), DIFFUSION_OPTIMIZATION)),
            "defaults": {
                "diffusion": optimization(DIFFUSION_OPTIMIZATION),
                "reward": optimization(REWARD_OPTIMIZATION),
                "discriminator": optimization(DISCRIMINATOR_OPTIMIZATION),
            },
        },
        "diffusion": { "fields": fields(&diffusion), "defaults": diffusion },
        "reward": { "fields": fields(&reward), "defaults": reward },
        "discriminator": { "fields": fields(&discriminator), "defaults": discriminator },
        "schedules": ["linear", "cosine", "diffuser_cosine", "betas"],
        "cosine_s": super::manifest::DEFAULT_COSINE_S,
        "denoiser_architectures": {
            "temporal_unet": Architecture::default_for(true),
            "mlp": Architecture::default_for(false),
            "unet2d": unet2d,
        },
        "reward_architectures": reward_architectures,
        "amortised_targets": AmortisedTargets::DEFAULT,
    })
}

#[cfg(test)]
mod tests {
    use super::summary;

    #[test]
    fn the_committed_schema_summary_is_current() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("schema.json");
        let want = serde_json::to_string_pretty(&summary()).expect("json") + "\n";
        if std::env::var_os("RELREWARD_BLESS").is_some() {
            std::fs::write(&path, &want).expect("write proto/schema.json");
        }
        let have = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            have == want,
            "proto/schema.json is out of date with the Rust schema; rerun with RELREWARD_BLESS=1 \
             cargo test -p relreward-proto, and check client/python/src/relreward/specs.py follows"
        );
    }
}
