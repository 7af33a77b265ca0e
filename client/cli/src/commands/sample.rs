//! `relreward sample`: samples of a base diffusion model, guided by a reward model or not, with
//! inpainting conditions (one Sample stream).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use relreward_client::{ClientError, pb, tensor};
use serde_json::{Value, json};

use relreward_cli::ops::scoring::{flag_of, floats, summarize};
use relreward_cli::output::{item_bar, key_values};

use super::rewards::{OutArrays, check_out, summary_json, summary_text};
use super::{Ctx, Report, UsageError};

#[derive(Debug, Clone, Args)]
pub struct SampleArgs {
    /// Base diffusion model.
    #[arg(long, value_name = "B")]
    pub base: String,
    /// Reward model that guides the sampler (needs --scale).
    #[arg(long, value_name = "R")]
    pub reward: Option<String>,
    /// Guidance scale omega (0: no guidance, the reward of each sample is still reported).
    #[arg(long, value_name = "W", allow_negative_numbers = true)]
    pub scale: Option<f64>,
    /// Guided sampling: no guidance at diffusion times below K [default: the server's].
    #[arg(long, value_name = "K", allow_negative_numbers = true)]
    pub t_stopgrad: Option<u32>,
    /// Guided sampling: gradient steps per denoising step [default: the server's].
    #[arg(long, value_name = "N", allow_negative_numbers = true)]
    pub n_guide_steps: Option<u32>,
    /// Guided sampling: scale the gradient by the posterior variance.
    #[arg(long)]
    pub scale_grad_by_std: bool,
    /// Inpainting: the observation at horizon index INDEX, in raw units (repeatable).
    #[arg(long = "condition", value_name = "INDEX=v1,v2,..", value_parser = parse_condition, allow_hyphen_values = true)]
    pub conditions: Vec<ConditionArg>,
    /// Number of samples.
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..), allow_negative_numbers = true)]
    pub n: u32,
    /// Seed of the sampler's noise [default: the server picks one].
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    pub seed: Option<u64>,
    /// Samples denoised together [default: all of them, up to the server's limit].
    #[arg(long, value_name = "M", value_parser = clap::value_parser!(u32).range(1..), allow_negative_numbers = true)]
    pub batch_size: Option<u32>,
    /// Write the samples to this .npz file.
    #[arg(long, value_name = "FILE.npz")]
    pub out: Option<PathBuf>,
    /// The sampler: ddpm (all T steps, the default) or ddim (--steps, --eta, --timestep-spacing).
    #[arg(long, value_name = "NAME", default_value = "ddpm", value_parser = ["ddpm", "ddim"])]
    pub sampler: String,
    /// DDIM: denoising steps, 1 to T [default: T].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..), allow_negative_numbers = true)]
    pub steps: Option<u32>,
    /// DDIM: eta in [0, 1] (0: deterministic) [default: 0].
    #[arg(long, value_name = "E", allow_negative_numbers = true)]
    pub eta: Option<f64>,
    /// DDIM: how the steps are spaced over 0..T, as diffusers names it [default: leading].
    #[arg(long, value_name = "S", value_parser = ["leading", "trailing", "linspace"])]
    pub timestep_spacing: Option<String>,
    /// DDIM: the last step ends at abar_0 instead of 1 (diffusers' set_alpha_to_one = false).
    #[arg(long)]
    pub no_alpha_to_one: bool,
    #[command(flatten)]
    pub recipe: RecipeFlags,
}

/// How a conditional model is sampled, as flags (`sample`, `model recipe`).
#[derive(Debug, Clone, Args)]
pub struct RecipeFlags {
    /// Conditional models: the class label of every sample, or one per sample (L1,L2,..); for
    /// `model recipe`, the prompt set (sample i takes label i mod k).
    #[arg(long, value_name = "L[,L..]", value_delimiter = ',', allow_negative_numbers = true)]
    pub labels: Vec<i64>,
    /// Conditional models: classifier-free guidance scale s [default: 1, the conditional model alone].
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    pub guidance_scale: Option<f64>,
    /// Conditional models: Safe Latent Diffusion's guidance away from these class labels.
    #[arg(long, value_name = "L[,L..]", value_delimiter = ',', allow_negative_numbers = true)]
    pub safety_concept: Vec<i64>,
    /// With --safety-concept: diffusers' preset of warm-up, scale, threshold and momentum.
    #[arg(long, value_name = "NAME", default_value = "medium", value_parser = ["weak", "medium", "strong", "max"])]
    pub safety_preset: String,
}

impl RecipeFlags {
    /// --labels as prompts (None when not given).
    pub fn prompts(&self) -> Option<pb::Prompts> {
        (!self.labels.is_empty()).then(|| pb::Prompts { labels: self.labels.clone(), ..Default::default() })
    }

    /// --safety-concept with --safety-preset (None without a concept).
    pub fn safety(&self) -> Option<pb::SafetyGuidance> {
        (!self.safety_concept.is_empty()).then(|| safety_preset(&self.safety_preset, &self.safety_concept))
    }

    /// Which flag sets each of Sample's request fields (the server's messages name the field).
    pub fn fields(&self) -> Vec<(&'static str, String)> {
        vec![
            ("prompts", "--labels".to_owned()),
            (
                "guidance_scale",
                self.guidance_scale.map_or_else(|| "--guidance-scale".to_owned(), |v| format!("--guidance-scale {v}")),
            ),
            ("safety", format!("--safety-concept with --safety-preset {}", self.safety_preset)),
        ]
    }
}

/// diffusers' Safe Stable Diffusion presets: (warmup_steps, scale, threshold, momentum_scale,
/// momentum_beta), as the Python client's `SAFETY_PRESETS`.
fn safety_preset(name: &str, concept: &[i64]) -> pb::SafetyGuidance {
    let (warmup_steps, scale, threshold, momentum_scale, momentum_beta) = match name {
        "weak" => (15, 20.0, 0.0, 0.0, 0.0),
        "strong" => (7, 2000.0, 0.025, 0.5, 0.7),
        "max" => (0, 5000.0, 1.0, 0.5, 0.7),
        _ => (10, 1000.0, 0.01, 0.3, 0.4),
    };
    pb::SafetyGuidance {
        concept: Some(pb::Prompts { labels: concept.to_vec(), ..Default::default() }),
        scale,
        warmup_steps,
        threshold,
        momentum_scale,
        momentum_beta,
    }
}

/// `--sampler ddim` with its options as the request's `ddim`; DDIM's flags without it are a
/// usage error (they would be ignored).
fn ddim_request(args: &SampleArgs) -> Result<Option<pb::Ddim>, UsageError> {
    if args.sampler != "ddim" {
        let given = [
            ("--steps", args.steps.is_some()),
            ("--eta", args.eta.is_some()),
            ("--timestep-spacing", args.timestep_spacing.is_some()),
            ("--no-alpha-to-one", args.no_alpha_to_one),
        ];
        if let Some((flag, _)) = given.iter().find(|(_, set)| *set) {
            return Err(UsageError(format!("{flag} only applies to DDIM: add --sampler ddim")));
        }
        return Ok(None);
    }
    let spacing = match args.timestep_spacing.as_deref() {
        None | Some("leading") => pb::TimestepSpacing::Leading,
        Some("trailing") => pb::TimestepSpacing::Trailing,
        Some("linspace") => pb::TimestepSpacing::Linspace,
        Some(other) => {
            return Err(UsageError(format!("--timestep-spacing {other}: expected leading, trailing or linspace")));
        }
    };
    Ok(Some(pb::Ddim {
        n_steps: args.steps.unwrap_or(0),
        eta: args.eta.unwrap_or(0.0),
        timestep_spacing: spacing as i32,
        set_alpha_to_one: args.no_alpha_to_one.then_some(false),
    }))
}

/// `--condition INDEX=v1,v2,..`.
#[derive(Debug, Clone, PartialEq)]
pub struct ConditionArg {
    pub index: u32,
    pub state: Vec<f64>,
}

impl ConditionArg {
    fn text(&self) -> String {
        let values: Vec<String> = self.state.iter().map(f64::to_string).collect();
        format!("{}={}", self.index, values.join(","))
    }
}

fn parse_condition(text: &str) -> Result<ConditionArg, String> {
    let usage = "expected INDEX=v1,v2,.. (a horizon index and the observation there, e.g. 0=1.5,2,0,0)";
    let (index, values) = text.split_once('=').ok_or_else(|| usage.to_owned())?;
    let index = index.trim().parse::<u32>().map_err(|_| format!("'{index}' is not a horizon index; {usage}"))?;
    let state = values
        .split(',')
        .map(|v| match v.trim().parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(x),
            _ => Err(format!("'{v}' is not a finite number; {usage}")),
        })
        .collect::<Result<Vec<f64>, String>>()?;
    Ok(ConditionArg { index, state })
}

/// Checks the guidance flags together: `--reward` and `--scale` come as a pair, and the
/// guidance settings need them.
fn check_guidance(args: &SampleArgs) -> Result<(), UsageError> {
    match (&args.reward, args.scale) {
        (Some(r), None) => {
            return Err(UsageError(format!(
                "--reward {r} needs --scale W, the guidance scale omega (e.g. --scale 0.1)"
            )));
        }
        (None, Some(_)) => {
            return Err(UsageError(
                "--scale needs --reward R: the guidance scale multiplies that reward model's gradient".into(),
            ));
        }
        (Some(_), Some(w)) if !w.is_finite() => {
            return Err(UsageError(format!("--scale {w}: must be a finite number")));
        }
        _ => {}
    }
    if args.reward.is_none() {
        let given = [
            ("--t-stopgrad", args.t_stopgrad.is_some()),
            ("--n-guide-steps", args.n_guide_steps.is_some()),
            ("--scale-grad-by-std", args.scale_grad_by_std),
        ];
        if let Some((flag, _)) = given.iter().find(|(_, set)| *set) {
            return Err(UsageError(format!("{flag} only applies to guided sampling: give --reward R and --scale W")));
        }
    }
    if args.reward.as_deref() == Some("") {
        return Err(UsageError("--reward: needs a reward model name".into()));
    }
    Ok(())
}

/// Checks `--condition`s against the base model's trajectory space (horizon, obs_dim).
fn check_conditions(base: &pb::Model, conditions: &[ConditionArg]) -> Result<()> {
    use pb::diffusion_manifest::Space;
    if base.kind() != pb::ModelKind::Diffusion {
        bail!(
            "--base {}: is not a diffusion model; sampling needs one (relreward model list --kind diffusion)",
            base.name
        );
    }
    if conditions.is_empty() {
        return Ok(());
    }
    let space = base.manifest.as_ref().and_then(|m| m.space.as_ref());
    let Some(Space::Trajectory(traj)) = space else {
        bail!(
            "--condition {}: model '{}' samples fixed-shape items, not trajectories; conditions fix an observation \
             at a horizon index",
            conditions[0].text(),
            base.name
        );
    };
    for c in conditions {
        if c.index >= traj.horizon {
            bail!(
                "--condition {}: index {} is outside model '{}''s horizon 0..{}",
                c.text(),
                c.index,
                base.name,
                traj.horizon
            );
        }
        if c.state.len() != traj.obs_dim as usize {
            bail!(
                "--condition {}: {} values but model '{}' has obs_dim {}",
                c.text(),
                c.state.len(),
                base.name,
                traj.obs_dim
            );
        }
    }
    Ok(())
}

/// Request fields of Sample and the flags that set them.
fn sample_fields(args: &SampleArgs) -> Vec<(&'static str, String)> {
    let opt = |flag: &str, v: Option<String>| v.map_or_else(|| flag.to_owned(), |v| format!("{flag} {v}"));
    vec![
        ("model", format!("--base {}", args.base)),
        ("reward_model", opt("--reward", args.reward.clone())),
        ("omega", opt("--scale", args.scale.map(|w| w.to_string()))),
        ("n_guide_steps", opt("--n-guide-steps", args.n_guide_steps.map(|v| v.to_string()))),
        ("t_stopgrad", opt("--t-stopgrad", args.t_stopgrad.map(|v| v.to_string()))),
        ("scale_grad_by_std", "--scale-grad-by-std".to_owned()),
        ("conditions", "--condition".to_owned()),
        ("n", format!("--n {}", args.n)),
        ("batch_size", opt("--batch-size", args.batch_size.map(|v| v.to_string()))),
        ("ddim.n_steps", opt("--steps", args.steps.map(|v| v.to_string()))),
        ("ddim.eta", opt("--eta", args.eta.map(|v| v.to_string()))),
        ("ddim.timestep_spacing", opt("--timestep-spacing", args.timestep_spacing.clone())),
        ("ddim", "--sampler ddim".to_owned()),
    ]
    .into_iter()
    .chain(args.recipe.fields())
    .collect()
}

/// "ddpm", or "ddim, N steps (leading), eta E".
fn sampler_text(args: &SampleArgs) -> String {
    if args.sampler != "ddim" {
        return args.sampler.clone();
    }
    format!(
        "ddim, {} steps ({}), eta {}",
        args.steps.map_or_else(|| "T".to_owned(), |s| s.to_string()),
        args.timestep_spacing.as_deref().unwrap_or("leading"),
        args.eta.unwrap_or(0.0)
    )
}

/// One sample as it arrived: raw values, normalized values and its reward (guided sampling).
type Sampled = (Vec<f32>, Vec<f32>, Option<f64>);

pub async fn sample(ctx: &Ctx, args: SampleArgs) -> Result<Report> {
    check_guidance(&args)?;
    let ddim = ddim_request(&args)?;
    check_out(args.out.as_deref())?;
    let client = ctx.connect().await?;
    let base = client.get_model(&args.base).await.with_context(|| format!("--base {}", args.base))?;
    check_conditions(&base, &args.conditions)?;
    let guided = args.reward.is_some();
    let request = pb::SampleRequest {
        model: args.base.clone(),
        reward_model: args.reward.clone().unwrap_or_default(),
        omega: args.scale.unwrap_or(0.0),
        n_guide_steps: args.n_guide_steps,
        t_stopgrad: args.t_stopgrad,
        scale_grad_by_std: args.scale_grad_by_std,
        conditions: args
            .conditions
            .iter()
            .map(|c| pb::Condition {
                index: c.index,
                state: Some(tensor::encode_f64(&[c.state.len() as u64], &c.state)),
            })
            .collect(),
        input_units: pb::Units::Raw as i32,
        n: args.n,
        seed: args.seed,
        batch_size: args.batch_size.unwrap_or(0),
        ddim,
        prompts: args.recipe.prompts(),
        guidance_scale: args.recipe.guidance_scale,
        safety: args.recipe.safety(),
    };
    let n = args.n as usize;
    let bar = item_bar(ctx.json, n as u64, "samples");
    let fields = sample_fields(&args);
    let labelled = |e: ClientError| match flag_of(&e, &fields) {
        Some(flag) => anyhow::Error::new(e).context(flag),
        None => anyhow::Error::new(e),
    };
    let mut stream = client.sample(request).await.map_err(labelled)?;
    let mut shape: Option<Vec<u64>> = None;
    let mut x: Vec<Option<Sampled>> = vec![None; n];
    while let Some(item) = stream.message().await.map_err(|e| labelled(e.into()))? {
        let i = item.index as usize;
        if i >= n || x[i].is_some() {
            bail!("the server sent sample {i} {}", if i >= n { "beyond --n" } else { "twice" });
        }
        let got = item.x.as_ref().map(|t| t.shape.clone()).unwrap_or_default();
        let shape = shape.get_or_insert(got);
        let raw = floats(item.x.as_ref(), "x", shape)?;
        let normalized = floats(item.x_normalized.as_ref(), "x_normalized", shape)?;
        if guided && item.reward.is_none() {
            bail!("the server sent sample {i} without its reward");
        }
        x[i] = Some((raw, normalized, item.reward));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let missing = x.iter().filter(|v| v.is_none()).count();
    if missing > 0 {
        bail!("the server's stream ended after {} of {n} samples", n - missing);
    }
    let shape = shape.unwrap_or_default();
    let (mut raw, mut normalized, mut rewards) = (Vec::new(), Vec::new(), Vec::new());
    for (r, z, reward) in x.into_iter().flatten() {
        raw.extend(r);
        normalized.extend(z);
        rewards.extend(reward);
    }
    let summary = guided.then(|| summarize(rewards.iter().copied())).flatten();
    let mut full = vec![n as u64];
    full.extend(&shape);
    let mut arrays = OutArrays::default();
    arrays.f32s.push(("x", full.clone(), raw));
    arrays.f32s.push(("x_normalized", full, normalized));
    if guided {
        arrays.f32s.push(("reward", vec![n as u64], rewards.iter().map(|&r| r as f32).collect()));
    }
    let (shapes_json, shapes_text) = arrays.write_to(args.out.as_deref()).await?;

    let mut fields = vec![
        ("base", args.base.clone()),
        ("samples", format!("{n}, each {shape:?}")),
        ("seed", args.seed.map_or_else(|| "-".to_owned(), |s| s.to_string())),
        ("sampler", sampler_text(&args)),
    ];
    if let (Some(r), Some(w)) = (&args.reward, args.scale) {
        fields.push(("guidance", format!("{r}, scale {w}")));
        fields.push(("reward", summary_text(summary)));
    }
    if let Some(out) = &args.out {
        fields.push(("out", format!("{} ({shapes_text})", out.display())));
    }
    let json = json!({
        "base": args.base,
        "reward_model": args.reward,
        "scale": args.scale,
        "t_stopgrad": args.t_stopgrad,
        "n_guide_steps": args.n_guide_steps,
        "scale_grad_by_std": args.scale_grad_by_std,
        "conditions": args.conditions.iter().map(|c| json!({ "index": c.index, "state": c.state })).collect::<Vec<_>>(),
        "sampler": args.sampler,
        "steps": args.steps,
        "eta": args.eta,
        "timestep_spacing": args.timestep_spacing,
        "count": n,
        "shape": shape,
        "seed": args.seed,
        "reward": if guided { summary_json(summary) } else { Value::Null },
        "out": args.out.as_ref().map(|p| p.display().to_string()),
        "arrays": shapes_json,
    });
    Ok(Report::ok(key_values(&fields, 0), json))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conditions_parse_and_summaries_are_population_statistics() {
        assert_eq!(parse_condition("3=1.5,-2,0").expect("ok"), ConditionArg { index: 3, state: vec![1.5, -2.0, 0.0] });
        assert!(parse_condition("3").is_err());
        assert!(parse_condition("x=1").is_err());
        assert!(parse_condition("-1=1").is_err());
        assert!(parse_condition("0=1,,2").is_err());
        assert!(parse_condition("0=nan").is_err());
        assert_eq!(ConditionArg { index: 2, state: vec![1.5, -2.0] }.text(), "2=1.5,-2");
        let s = summarize([1.0, 2.0, 3.0, 4.0]).expect("values");
        assert_eq!((s.mean, s.min, s.max), (2.5, 1.0, 4.0));
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-12);
        assert_eq!(summarize(std::iter::empty()), None);
        assert_eq!(summary_json(None), Value::Null);
    }
}
