//! Building a job spec: `--config` with the flags on top, and the checks that name the flag or
//! field at fault.

use std::fmt::Display;
use std::path::Path;

use anyhow::{Context, Result, anyhow, bail};
use pb::job_spec::Kind;
use relreward_client::pb;

use relreward_proto::schema::job::DEFAULT_N_TIMESTEPS;
use relreward_proto::schema::manifest::Parametrization;

use super::config::{
    Algorithm, ArchKind, Architecture, DiscriminatorConfig, EvalPoint, RewardArchitecture, RewardConfig, Target,
    TrainConfig,
};
use super::flags::{AlgorithmArg, ArchArgs, TrainArgs, TrainDiffusionArgs, TrainDiscriminatorArgs, TrainRewardArgs};
use crate::UsageError;
use crate::manifest::read_file;

/// Reads the config file, if any (none: every field unset).
pub fn load_config(path: Option<&Path>) -> Result<TrainConfig> {
    path.map_or_else(|| Ok(TrainConfig::default()), read_file)
}

/// Reads `--config` (if any) and builds the spec.
pub fn diffusion_spec_from_args(args: &TrainDiffusionArgs) -> Result<pb::JobSpec> {
    diffusion_spec(load_config(args.job.config.as_deref())?, args)
}

/// Reads `--config` (if any) and builds the spec.
pub fn reward_spec_from_args(args: &TrainRewardArgs) -> Result<pb::JobSpec> {
    reward_spec(load_config(args.job.config.as_deref())?, args)
}

/// Reads `--config` (if any) and builds the spec.
pub fn discriminator_spec_from_args(args: &TrainDiscriminatorArgs) -> Result<pb::JobSpec> {
    discriminator_spec(load_config(args.job.config.as_deref())?, args)
}

/// The diffusion job spec: `config` with the flags of `args` on top. A missing output model or
/// dataset is a [`UsageError`].
pub fn diffusion_spec(config: TrainConfig, args: &TrainDiffusionArgs) -> Result<pb::JobSpec> {
    let common = Common::new(&config, &args.job, "diffusion")?;
    let d = config.diffusion.unwrap_or_default();
    let dataset =
        required(&args.dataset, d.dataset, "no dataset to train on", "--dataset NAME", "dataset", "diffusion")?;
    let n_timesteps = args.n_timesteps.or(d.n_timesteps);
    // The schema's checks of the file's schedule (the server's own), against the T the job
    // will have.
    let schedule = d
        .schedule
        .map(|s| {
            s.validate("diffusion.schedule", n_timesteps.map_or(DEFAULT_N_TIMESTEPS, |t| t as usize))?;
            Ok::<_, relreward_proto::schema::Invalid>(s.to_proto())
        })
        .transpose()
        .context("--config")?;
    let architecture = d.architecture.as_ref().map(Architecture::to_train_proto);
    Ok(common.spec(Kind::Diffusion(pb::TrainDiffusion {
        dataset,
        parametrization: d.parametrization.map_or(pb::Parametrization::Unspecified, Parametrization::to_proto) as i32,
        schedule,
        n_timesteps,
        horizon: args.horizon.or(d.horizon),
        architecture,
        action_weight: d.action_weight,
        clip_denoised: d.clip_denoised,
        pooled_normalizer: d.pooled_normalizer,
        conditional: d.conditional,
        condition_dropout: d.condition_dropout,
        num_classes: d.num_classes,
        normalizer_datasets: if args.normalizer_datasets.is_empty() {
            d.normalizer_datasets.unwrap_or_default()
        } else {
            args.normalizer_datasets.clone()
        },
    })))
}

/// The reward job spec: `config` with the flags of `args` on top. A missing output model, base
/// or expert model, or Algorithm 1 without a dataset, and flags that contradict each other are
/// [`UsageError`]s.
pub fn reward_spec(config: TrainConfig, args: &TrainRewardArgs) -> Result<pb::JobSpec> {
    let common = Common::new(&config, &args.job, "reward")?;
    let RewardConfig {
        base_model,
        expert_model,
        architecture,
        target,
        eval_point,
        algorithm,
        rho_l2,
        action_weight,
        condition_weight,
        inpaint_condition,
        base_recipe,
        expert_recipe,
    } = config.reward.unwrap_or_default();
    let base_model = required(&args.base, base_model, "no base model", "--base MODEL", "base_model", "reward")?;
    let expert_model =
        required(&args.expert, expert_model, "no expert model", "--expert MODEL", "expert_model", "reward")?;
    let algorithm = reward_algorithm(algorithm, args)?;
    let architecture = reward_architecture(architecture, &args.arch, "reward")?;
    let rho_l2 = flag_or_file(args.rho_l2, "--rho-l2", rho_l2, || "reward.rho_l2".into());
    let action_weight =
        flag_or_file(args.action_weight, "--action-weight", action_weight, || "reward.action_weight".into());
    let condition_weight = flag_or_file(args.condition_weight, "--condition-weight", condition_weight, || {
        "reward.condition_weight".into()
    });
    for (x, source) in [&rho_l2, &action_weight, &condition_weight].into_iter().flatten() {
        if !(x.is_finite() && *x >= 0.0) {
            return Err(source.invalid(format!("{} is not zero or positive", crate::output::given_num(*x))));
        }
    }
    Ok(common.spec(Kind::Reward(pb::TrainReward {
        base_model,
        expert_model,
        architecture,
        target: args.target.or(target).map_or(pb::RewardTarget::Unspecified, Target::to_proto) as i32,
        eval_point: args.eval_point.or(eval_point).map_or(pb::EvalPoint::Unspecified, EvalPoint::to_proto) as i32,
        algorithm: Some(algorithm),
        rho_l2: rho_l2.map(|(x, _)| x),
        amortised_targets: args.amortised.to_proto(),
        action_weight: action_weight.map(|(x, _)| x),
        condition_weight: condition_weight.map(|(x, _)| x),
        inpaint_condition: args.inpaint_condition.then_some(true).or(inpaint_condition),
        base_recipe: base_recipe.as_ref().map(relreward_proto::schema::recipe::RecipeSpec::to_proto),
        expert_recipe: expert_recipe.as_ref().map(relreward_proto::schema::recipe::RecipeSpec::to_proto),
    })))
}

/// The discriminator job spec: `config` with the flags of `args` on top. A missing output
/// model, dataset or diffusion model is a [`UsageError`].
pub fn discriminator_spec(config: TrainConfig, args: &TrainDiscriminatorArgs) -> Result<pb::JobSpec> {
    let common = Common::new(&config, &args.job, "discriminator")?;
    let DiscriminatorConfig { base_dataset, expert_dataset, architecture, diffusion_model, inpaint_condition } =
        config.discriminator.unwrap_or_default();
    let table = "discriminator";
    let base_dataset =
        required(&args.base_dataset, base_dataset, "no base dataset", "--base-dataset NAME", "base_dataset", table)?;
    let expert_dataset = required(
        &args.expert_dataset,
        expert_dataset,
        "no expert dataset",
        "--expert-dataset NAME",
        "expert_dataset",
        table,
    )?;
    let diffusion_model = required(
        &args.diffusion_model,
        diffusion_model,
        "no diffusion model to share the schedule and normalizer of",
        "--diffusion-model MODEL",
        "diffusion_model",
        table,
    )?;
    let architecture = reward_architecture(architecture, &args.arch, "discriminator")?;
    Ok(common.spec(Kind::Discriminator(pb::TrainDiscriminator {
        base_dataset,
        expert_dataset,
        architecture,
        diffusion_model,
        inpaint_condition: args.inpaint_condition.then_some(true).or(inpaint_condition),
    })))
}

/// The fields of every job spec: the output model, the seed and the optimisation settings.
struct Common {
    output_model: String,
    seed: Option<u64>,
    optimization: pb::Optimization,
}

impl Common {
    /// The shared fields of `config` with the flags on top, for `train {command}`. A table of
    /// another command in the file is an error; a missing output model is a [`UsageError`].
    fn new(config: &TrainConfig, args: &TrainArgs, command: &str) -> Result<Self> {
        let tables = [
            ("diffusion", config.diffusion.is_some()),
            ("reward", config.reward.is_some()),
            ("discriminator", config.discriminator.is_some()),
        ];
        if let Some((other, _)) = tables.iter().find(|(table, present)| *present && *table != command) {
            bail!("--config: the [{other}] table is for `train {other}`; `train {command}` reads [{command}]");
        }
        let output_model = args.name.clone().or_else(|| config.output_model.clone()).ok_or_else(|| {
            UsageError("the model to create is not named: pass --name MODEL (or output_model in --config)".into())
        })?;
        let o = config.optimization;
        let optimization = pb::Optimization {
            steps: args.steps.or(o.steps),
            batch_size: args.batch_size.or(o.batch_size),
            learning_rate: args.lr.or(o.learning_rate),
            grad_clip: o.grad_clip,
            ema_decay: o.ema_decay,
            ema_every: o.ema_every,
            ema_start: o.ema_start,
            checkpoint_every: o.checkpoint_every,
            eval_every: o.eval_every,
            log_every: o.log_every,
        };
        Ok(Self { output_model, seed: args.seed.or(config.seed), optimization })
    }

    fn spec(self, kind: Kind) -> pb::JobSpec {
        pb::JobSpec {
            output_model: self.output_model,
            seed: self.seed,
            optimization: Some(self.optimization),
            kind: Some(kind),
        }
    }
}

/// A name the job needs: the flag's, else the file's (`field` of `[table]`); neither is a
/// [`UsageError`] saying what is missing (`what`) and how to give it (`flag`, or the field).
fn required(
    flag: &Option<String>,
    file: Option<String>,
    what: &str,
    flag_usage: &str,
    field: &str,
    table: &str,
) -> Result<String> {
    flag.clone()
        .or(file)
        .ok_or_else(|| usage(format!("{what}: pass {flag_usage} (or {field} in --config's [{table}])")))
}

/// Where a value came from, to name it in an error.
enum Source {
    /// A flag: a bad value is a [`UsageError`].
    Flag(&'static str),
    /// A field of `--config`.
    File(String),
}

impl Source {
    fn invalid(&self, problem: impl Display) -> anyhow::Error {
        match self {
            Self::Flag(flag) => UsageError(format!("{flag}: {problem}")).into(),
            Self::File(field) => anyhow!("--config: {field}: {problem}"),
        }
    }
}

/// The flag's value, else the file's, with where it came from.
fn flag_or_file<T>(
    flag: Option<T>,
    flag_name: &'static str,
    file: Option<T>,
    field: impl FnOnce() -> String,
) -> Option<(T, Source)> {
    match (flag, file) {
        (Some(v), _) => Some((v, Source::Flag(flag_name))),
        (None, Some(v)) => Some((v, Source::File(field()))),
        (None, None) => None,
    }
}

fn usage(message: impl Into<String>) -> anyhow::Error {
    UsageError(message.into()).into()
}

/// The reward algorithm: `--algorithm`, else the one the flags imply (`--dataset`: 1,
/// `--num-chains`: 2), else the file's, else Algorithm 1. The file's datasets or chain count
/// are kept only when the file names the algorithm chosen.
fn reward_algorithm(file: Option<Algorithm>, args: &TrainRewardArgs) -> Result<pb::train_reward::Algorithm> {
    use pb::train_reward::{Algorithm as Proto, ModelsOnly, WithDataset};
    let datasets_flag = !args.datasets.is_empty();
    let chains_flag = args.num_chains.is_some();
    let which = match (args.algorithm, datasets_flag, chains_flag) {
        (Some(AlgorithmArg::WithDataset), _, true) => {
            return Err(usage("--num-chains is for --algorithm 2 (Algorithm 1 draws x_t from --dataset)"));
        }
        (Some(AlgorithmArg::ModelsOnly), true, _) => {
            return Err(usage("--dataset is for --algorithm 1 (Algorithm 2 uses the models alone)"));
        }
        (Some(which), _, _) => which,
        (None, true, true) => {
            return Err(usage(
                "--dataset (Algorithm 1) and --num-chains (Algorithm 2) exclude each other: pass one, or --algorithm",
            ));
        }
        (None, true, false) => AlgorithmArg::WithDataset,
        (None, false, true) => AlgorithmArg::ModelsOnly,
        (None, false, false) => match &file {
            Some(Algorithm::ModelsOnly { .. }) => AlgorithmArg::ModelsOnly,
            Some(Algorithm::WithDataset { .. }) | None => AlgorithmArg::WithDataset,
        },
    };
    match which {
        AlgorithmArg::WithDataset => {
            let datasets = match file {
                _ if datasets_flag => args.datasets.clone(),
                Some(Algorithm::WithDataset { datasets }) => datasets,
                _ => Vec::new(),
            };
            if datasets.is_empty() {
                return Err(usage(
                    "Algorithm 1 needs data: pass --dataset NAME, repeated for several (or algorithm = \
                     { kind = \"with_dataset\", datasets = [..] } in --config's [reward]), or --algorithm 2",
                ));
            }
            Ok(Proto::WithDataset(WithDataset { datasets }))
        }
        AlgorithmArg::ModelsOnly => {
            let from_file = match file {
                Some(Algorithm::ModelsOnly { num_chains }) => num_chains,
                _ => None,
            };
            let num_chains =
                flag_or_file(args.num_chains, "--num-chains", from_file, || "reward.algorithm.num_chains".into());
            if let Some((k, source)) = &num_chains
                && *k < 2
            {
                return Err(source.invalid(format!("{k} chains: at least 2 are needed (half follow each model)")));
            }
            Ok(Proto::ModelsOnly(ModelsOnly { num_chains: num_chains.map(|(k, _)| k) }))
        }
    }
}

/// The network of a reward or discriminator job (`table`: its config table): `--arch`, else the
/// file's kind, with `--window`, `--hidden` and `--widths` over the file's values (kept only when
/// the file names the same kind). None when neither names one.
fn reward_architecture(
    file: Option<RewardArchitecture>,
    args: &ArchArgs,
    table: &str,
) -> Result<Option<pb::RewardArchitecture>> {
    use ArchKind::{ConvEncoder, Mlp, ValueFunction, WindowedMlp};
    let shape_flags = [
        ("--window", args.window.is_some(), &[WindowedMlp][..]),
        ("--hidden", args.hidden.is_some(), &[WindowedMlp, Mlp][..]),
        ("--widths", args.widths.is_some(), &[ValueFunction, ConvEncoder][..]),
    ];
    let Some(kind) = args.arch.or(file.as_ref().map(RewardArchitecture::kind)) else {
        if let Some((flag, ..)) = shape_flags.iter().find(|(_, set, _)| *set) {
            return Err(usage(format!(
                "{flag} needs an architecture: pass --arch KIND (or architecture in --config's [{table}])"
            )));
        }
        return Ok(None);
    };
    if let Some((flag, _, kinds)) = shape_flags.iter().find(|(_, set, kinds)| *set && !kinds.contains(&kind)) {
        let fits: Vec<&str> = kinds.iter().map(|k| k.name()).collect();
        return Err(usage(format!(
            "{flag} is for --arch {}, and the architecture is {}",
            fits.join(" or "),
            kind.name()
        )));
    }
    let field = |name: &str| format!("{table}.architecture.{name}");
    let widths = |flag: &Option<Vec<u32>>, flag_name: &'static str, file: Vec<usize>, name: &str| {
        let (widths, source) = match flag {
            Some(widths) => (widths.iter().map(|&w| w as usize).collect::<Vec<_>>(), Source::Flag(flag_name)),
            None => (file, Source::File(field(name))),
        };
        match widths.iter().position(|&w| w == 0) {
            Some(i) => Err(source.invalid(format!("width {} of {widths:?} is 0", i + 1))),
            None => Ok(widths),
        }
    };
    // The file's network when it names this kind, else the kind's defaults (the schema's).
    let file = file.filter(|a| a.kind() == kind).unwrap_or_else(|| RewardArchitecture::default_of(kind));
    let architecture = match file {
        RewardArchitecture::WindowedMlp { window, hidden } => {
            let window = flag_or_file(args.window.map(|h| h as usize), "--window", Some(window), || field("window"));
            if let Some((0, source)) = &window {
                return Err(source.invalid("a window holds at least 1 transition"));
            }
            let hidden = widths(&args.hidden, "--hidden", hidden, "hidden")?;
            RewardArchitecture::WindowedMlp { window: window.map_or(0, |(h, _)| h), hidden }
        }
        RewardArchitecture::ValueFunction { widths: w } => {
            RewardArchitecture::ValueFunction { widths: widths(&args.widths, "--widths", w, "widths")? }
        }
        RewardArchitecture::ConvEncoder { widths: w } => {
            RewardArchitecture::ConvEncoder { widths: widths(&args.widths, "--widths", w, "widths")? }
        }
        RewardArchitecture::Mlp { hidden } => {
            RewardArchitecture::Mlp { hidden: widths(&args.hidden, "--hidden", hidden, "hidden")? }
        }
    };
    Ok(Some(architecture.to_proto()))
}
