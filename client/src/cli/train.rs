//! `train diffusion|reward|discriminator`: the job spec from a TOML config file (the proto's
//! fields) and flags. Every command shares the top-level fields, `[optimization]`, the flags
//! that set them ([`TrainArgs`]) and the merging rules; each reads its own table:
//!
//! ```toml
//! output_model = "maze-expert"      # --name
//! seed = 0                          # --seed
//! [optimization]                    # steps (--steps), batch_size (--batch-size),
//! steps = 1000                      # learning_rate (--lr), grad_clip, ema_decay, ema_every,
//! batch_size = 32                   # ema_start, checkpoint_every, eval_every, log_every
//!
//! [diffusion]                       # train diffusion
//! dataset = "maze-umaze-base"       # --dataset
//! horizon = 32                      # --horizon
//! n_timesteps = 20                  # --n-timesteps
//! parametrization = "x0"
//! schedule = { kind = "cosine" }
//! architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 2, 4, 8] }
//! # or architecture = { kind = "mlp", hidden = [256, 256] }
//! action_weight = 10.0
//! clip_denoised = true
//!
//! [reward]                          # train reward
//! base_model = "maze-base"          # --base
//! expert_model = "maze-expert"      # --expert
//! algorithm = { kind = "with_dataset", datasets = ["maze-umaze-base"] }  # --algorithm 1 --dataset D
//! # or algorithm = { kind = "models_only", num_chains = 512 }           # --algorithm 2 --num-chains K
//! target = "score"                  # --target mean|score
//! eval_point = "mu_base"            # --eval-point x_t|mu_base
//! rho_l2 = 0.0                      # --rho-l2
//! architecture = { kind = "windowed_mlp", window = 4, hidden = [128, 64, 32] }
//! # or { kind = "value_function", widths = [..] }, { kind = "conv_encoder", widths = [..] },
//! # { kind = "mlp", hidden = [..] }  (--arch, --window, --hidden, --widths)
//!
//! [discriminator]                   # train discriminator
//! base_dataset = "maze-umaze-base"  # --base-dataset
//! expert_dataset = "maze-expert"    # --expert-dataset
//! diffusion_model = "maze-base"     # --diffusion-model
//! architecture = { kind = "value_function", widths = [32, 64] }  # as in [reward]
//! ```
//!
//! Flags override the file; whatever neither sets stays unset, and the server fills in the
//! paper's defaults. A file with another command's table is refused.
//!
//! The reward algorithm is `--algorithm` if given, else the one its flags imply (`--dataset`:
//! 1, `--num-chains`: 2), else the file's, else Algorithm 1. The reward architecture is `--arch`
//! if given, else the file's; `--window`, `--hidden` and `--widths` adjust it, and the file's
//! widths are kept only when the file names the same kind.

use std::fmt::Display;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, ValueEnum};
use pb::job_spec::Kind;
use relreward_client::pb;
use serde::Deserialize;

use super::UsageError;
use super::manifest::{Parametrization, Schedule, read_file};

// ---------------------------------------------------------------------------------------------
// The config file

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub output_model: Option<String>,
    pub seed: Option<u64>,
    #[serde(default)]
    pub optimization: OptimizationConfig,
    pub diffusion: Option<DiffusionConfig>,
    pub reward: Option<RewardConfig>,
    pub discriminator: Option<DiscriminatorConfig>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OptimizationConfig {
    pub steps: Option<u64>,
    pub batch_size: Option<u32>,
    pub learning_rate: Option<f64>,
    pub grad_clip: Option<f64>,
    pub ema_decay: Option<f64>,
    pub ema_every: Option<u32>,
    pub ema_start: Option<u64>,
    pub checkpoint_every: Option<u64>,
    pub eval_every: Option<u64>,
    pub log_every: Option<u64>,
}

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionConfig {
    pub dataset: Option<String>,
    pub parametrization: Option<Parametrization>,
    pub schedule: Option<Schedule>,
    pub n_timesteps: Option<u32>,
    pub horizon: Option<u32>,
    pub architecture: Option<Architecture>,
    pub action_weight: Option<f64>,
    pub clip_denoised: Option<bool>,
    pub normalizer_datasets: Option<Vec<String>>,
}

/// The denoiser of a diffusion job.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Architecture {
    TemporalUnet {
        dim: Option<u32>,
        #[serde(default)]
        dim_mults: Vec<u32>,
    },
    Mlp {
        #[serde(default)]
        hidden: Vec<u32>,
    },
}

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardConfig {
    pub base_model: Option<String>,
    pub expert_model: Option<String>,
    pub architecture: Option<RewardArchitecture>,
    pub target: Option<Target>,
    pub eval_point: Option<EvalPoint>,
    pub algorithm: Option<Algorithm>,
    pub rho_l2: Option<f64>,
}

#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiscriminatorConfig {
    pub base_dataset: Option<String>,
    pub expert_dataset: Option<String>,
    pub architecture: Option<RewardArchitecture>,
    pub diffusion_model: Option<String>,
}

/// The network rho(x, t) of a reward or discriminator job; empty widths are left to the server.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RewardArchitecture {
    WindowedMlp {
        window: Option<u32>,
        #[serde(default)]
        hidden: Vec<u32>,
    },
    ValueFunction {
        #[serde(default)]
        widths: Vec<u32>,
    },
    ConvEncoder {
        #[serde(default)]
        widths: Vec<u32>,
    },
    Mlp {
        #[serde(default)]
        hidden: Vec<u32>,
    },
}

impl RewardArchitecture {
    fn kind(&self) -> ArchKind {
        match self {
            Self::WindowedMlp { .. } => ArchKind::WindowedMlp,
            Self::ValueFunction { .. } => ArchKind::ValueFunction,
            Self::ConvEncoder { .. } => ArchKind::ConvEncoder,
            Self::Mlp { .. } => ArchKind::Mlp,
        }
    }

    /// `kind` with every field unset.
    fn unset(kind: ArchKind) -> Self {
        match kind {
            ArchKind::WindowedMlp => Self::WindowedMlp { window: None, hidden: Vec::new() },
            ArchKind::ValueFunction => Self::ValueFunction { widths: Vec::new() },
            ArchKind::ConvEncoder => Self::ConvEncoder { widths: Vec::new() },
            ArchKind::Mlp => Self::Mlp { hidden: Vec::new() },
        }
    }

    fn into_proto(self) -> pb::RewardArchitecture {
        use pb::reward_architecture::{ConvEncoder, Kind, ValueFunction, WindowedMlp};
        let kind = match self {
            Self::WindowedMlp { window, hidden } => Kind::WindowedMlp(WindowedMlp { window, hidden }),
            Self::ValueFunction { widths } => Kind::ValueFunction(ValueFunction { widths }),
            Self::ConvEncoder { widths } => Kind::ConvEncoder(ConvEncoder { widths }),
            Self::Mlp { hidden } => Kind::Mlp(pb::Mlp { hidden }),
        };
        pb::RewardArchitecture { kind: Some(kind) }
    }
}

/// How a reward job gets its x_t.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Algorithm {
    WithDataset {
        #[serde(default)]
        datasets: Vec<String>,
    },
    ModelsOnly {
        num_chains: Option<u32>,
    },
}

/// What grad rho is aligned with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// mu_expert - mu_base (the server's default).
    Mean,
    /// s_expert - s_base.
    Score,
}

impl Target {
    fn to_proto(self) -> pb::RewardTarget {
        match self {
            Self::Mean => pb::RewardTarget::Mean,
            Self::Score => pb::RewardTarget::Score,
        }
    }
}

/// Where grad rho is evaluated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, ValueEnum)]
pub enum EvalPoint {
    /// At x_t, as in the paper's formula (the server's default).
    #[serde(rename = "x_t")]
    #[value(name = "x_t")]
    XT,
    /// At mu_base(x_t, t), as in the authors' code.
    #[serde(rename = "mu_base")]
    #[value(name = "mu_base")]
    MuBase,
}

impl EvalPoint {
    fn to_proto(self) -> pb::EvalPoint {
        match self {
            Self::XT => pb::EvalPoint::XT,
            Self::MuBase => pb::EvalPoint::MuBase,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Flags

/// Flags every train command takes: the output model, the config file, the optimisation
/// settings, the seed, the job id and `--watch`.
#[derive(Debug, Clone, Default, Args)]
pub struct TrainArgs {
    /// Name of the model the job registers [or output_model in --config].
    #[arg(long, value_name = "MODEL")]
    pub name: Option<String>,
    /// TOML file with the job spec's fields (output_model, seed, [optimization] and the
    /// command's table: [diffusion], [reward] or [discriminator]).
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Optimisation steps.
    #[arg(long)]
    pub steps: Option<u64>,
    #[arg(long)]
    pub batch_size: Option<u32>,
    /// Learning rate.
    #[arg(long, value_name = "X")]
    pub lr: Option<f64>,
    /// Seed of every random choice of the job.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Client-chosen job id: resubmitting the same spec under it returns the existing job.
    #[arg(long)]
    pub job_id: Option<String>,
    /// Watch the job's progress until it finishes.
    #[arg(long)]
    pub watch: bool,
}

/// The network of a reward or discriminator job.
#[derive(Debug, Clone, Default, Args)]
pub struct ArchArgs {
    /// The network [or architecture.kind in --config].
    #[arg(long, value_enum, value_name = "KIND")]
    pub arch: Option<ArchKind>,
    /// windowed_mlp: transitions per window.
    #[arg(long, value_name = "H")]
    pub window: Option<u32>,
    /// windowed_mlp, mlp: hidden layer widths.
    #[arg(long, value_name = "N,N,..", value_delimiter = ',')]
    pub hidden: Option<Vec<u32>>,
    /// value_function, conv_encoder: layer widths.
    #[arg(long, value_name = "N,N,..", value_delimiter = ',')]
    pub widths: Option<Vec<u32>>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ArchKind {
    /// MLP over windows of H transitions, averaged.
    #[value(name = "windowed_mlp")]
    WindowedMlp,
    /// Diffuser's ValueFunction temporal convolutions.
    #[value(name = "value_function")]
    ValueFunction,
    /// 2D convolutions over [C, H, W] latents.
    #[value(name = "conv_encoder")]
    ConvEncoder,
    /// MLP over the whole sample.
    #[value(name = "mlp")]
    Mlp,
}

impl ArchKind {
    fn name(self) -> &'static str {
        match self {
            Self::WindowedMlp => "windowed_mlp",
            Self::ValueFunction => "value_function",
            Self::ConvEncoder => "conv_encoder",
            Self::Mlp => "mlp",
        }
    }
}

/// `--algorithm 1|2`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum AlgorithmArg {
    /// x_t from the forward process on the --dataset samples.
    #[value(name = "1")]
    WithDataset,
    /// Pairs generated by --num-chains chains from noise, half following each model.
    #[value(name = "2")]
    ModelsOnly,
}

/// `relreward train diffusion` flags.
#[derive(Debug, Clone, Default, Args)]
pub struct TrainDiffusionArgs {
    /// The dataset to train on [or diffusion.dataset in --config].
    #[arg(long, value_name = "DATASET")]
    pub dataset: Option<String>,
    /// Sub-trajectory length H.
    #[arg(long)]
    pub horizon: Option<u32>,
    /// Number of diffusion steps T.
    #[arg(long)]
    pub n_timesteps: Option<u32>,
    /// Also compute the normalizer over this dataset (repeatable): give a base and an expert
    /// model the same ones so that a reward can be extracted between them
    /// [or diffusion.normalizer_datasets in --config].
    #[arg(long = "normalizer-dataset", value_name = "DATASET")]
    pub normalizer_datasets: Vec<String>,
    #[command(flatten)]
    pub job: TrainArgs,
}

/// `relreward train reward` flags.
#[derive(Debug, Clone, Default, Args)]
pub struct TrainRewardArgs {
    /// The base diffusion model [or reward.base_model in --config].
    #[arg(long, value_name = "MODEL")]
    pub base: Option<String>,
    /// The expert diffusion model [or reward.expert_model in --config].
    #[arg(long, value_name = "MODEL")]
    pub expert: Option<String>,
    /// Algorithm 1's data; repeat it for the union of several datasets
    /// [or reward.algorithm.datasets in --config].
    #[arg(long = "dataset", value_name = "DATASET")]
    pub datasets: Vec<String>,
    /// Where x_t comes from [default: 1, or what the other flags or --config imply].
    #[arg(long, value_enum)]
    pub algorithm: Option<AlgorithmArg>,
    /// Algorithm 2's number of chains K.
    #[arg(long, value_name = "K")]
    pub num_chains: Option<u32>,
    /// What grad rho is aligned with.
    #[arg(long, value_enum)]
    pub target: Option<Target>,
    /// Where grad rho is evaluated.
    #[arg(long, value_enum)]
    pub eval_point: Option<EvalPoint>,
    #[command(flatten)]
    pub arch: ArchArgs,
    /// Weight of the rho^2 regularizer (0: off).
    #[arg(long, value_name = "X")]
    pub rho_l2: Option<f64>,
    #[command(flatten)]
    pub job: TrainArgs,
}

/// `relreward train discriminator` flags.
#[derive(Debug, Clone, Default, Args)]
pub struct TrainDiscriminatorArgs {
    /// Dataset of the base behaviour [or discriminator.base_dataset in --config].
    #[arg(long, value_name = "DATASET")]
    pub base_dataset: Option<String>,
    /// Dataset of the expert behaviour [or discriminator.expert_dataset in --config].
    #[arg(long, value_name = "DATASET")]
    pub expert_dataset: Option<String>,
    /// Diffusion model whose schedule and normalizer the discriminator shares
    /// [or discriminator.diffusion_model in --config].
    #[arg(long, value_name = "MODEL")]
    pub diffusion_model: Option<String>,
    #[command(flatten)]
    pub arch: ArchArgs,
    #[command(flatten)]
    pub job: TrainArgs,
}

// ---------------------------------------------------------------------------------------------
// Building the spec

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
    let dataset = args.dataset.clone().or(d.dataset).ok_or_else(|| {
        UsageError("no dataset to train on: pass --dataset NAME (or dataset in --config's [diffusion])".into())
    })?;
    let schedule = d.schedule.map(|s| s.to_proto("diffusion.schedule")).transpose().context("--config")?;
    let architecture = d.architecture.map(|a| match a {
        Architecture::TemporalUnet { dim, dim_mults } => {
            pb::train_diffusion::Architecture::TemporalUnet(pb::TemporalUnet { dim, dim_mults })
        }
        Architecture::Mlp { hidden } => pb::train_diffusion::Architecture::Mlp(pb::Mlp { hidden }),
    });
    Ok(common.spec(Kind::Diffusion(pb::TrainDiffusion {
        dataset,
        parametrization: d.parametrization.map_or(pb::Parametrization::Unspecified, Parametrization::to_proto) as i32,
        schedule,
        n_timesteps: args.n_timesteps.or(d.n_timesteps),
        horizon: args.horizon.or(d.horizon),
        architecture,
        action_weight: d.action_weight,
        clip_denoised: d.clip_denoised,
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
    let RewardConfig { base_model, expert_model, architecture, target, eval_point, algorithm, rho_l2 } =
        config.reward.unwrap_or_default();
    let base_model =
        args.base.clone().or(base_model).ok_or_else(|| {
            UsageError("no base model: pass --base MODEL (or base_model in --config's [reward])".into())
        })?;
    let expert_model = args.expert.clone().or(expert_model).ok_or_else(|| {
        UsageError("no expert model: pass --expert MODEL (or expert_model in --config's [reward])".into())
    })?;
    let algorithm = reward_algorithm(algorithm, args)?;
    let architecture = reward_architecture(architecture, &args.arch, "reward")?;
    let rho_l2 = flag_or_file(args.rho_l2, "--rho-l2", rho_l2, || "reward.rho_l2".into());
    if let Some((x, source)) = &rho_l2
        && !(x.is_finite() && *x >= 0.0)
    {
        return Err(source.invalid(format!("{x} is not zero or positive")));
    }
    Ok(common.spec(Kind::Reward(pb::TrainReward {
        base_model,
        expert_model,
        architecture,
        target: args.target.or(target).map_or(pb::RewardTarget::Unspecified, Target::to_proto) as i32,
        eval_point: args.eval_point.or(eval_point).map_or(pb::EvalPoint::Unspecified, EvalPoint::to_proto) as i32,
        algorithm: Some(algorithm),
        rho_l2: rho_l2.map(|(x, _)| x),
    })))
}

/// The discriminator job spec: `config` with the flags of `args` on top. A missing output
/// model, dataset or diffusion model is a [`UsageError`].
pub fn discriminator_spec(config: TrainConfig, args: &TrainDiscriminatorArgs) -> Result<pb::JobSpec> {
    let common = Common::new(&config, &args.job, "discriminator")?;
    let DiscriminatorConfig { base_dataset, expert_dataset, architecture, diffusion_model } =
        config.discriminator.unwrap_or_default();
    let base_dataset = args.base_dataset.clone().or(base_dataset).ok_or_else(|| {
        UsageError("no base dataset: pass --base-dataset NAME (or base_dataset in --config's [discriminator])".into())
    })?;
    let expert_dataset = args.expert_dataset.clone().or(expert_dataset).ok_or_else(|| {
        UsageError(
            "no expert dataset: pass --expert-dataset NAME (or expert_dataset in --config's [discriminator])".into(),
        )
    })?;
    let diffusion_model = args.diffusion_model.clone().or(diffusion_model).ok_or_else(|| {
        UsageError(
            "no diffusion model to share the schedule and normalizer of: pass --diffusion-model MODEL \
             (or diffusion_model in --config's [discriminator])"
                .into(),
        )
    })?;
    let architecture = reward_architecture(architecture, &args.arch, "discriminator")?;
    Ok(common.spec(Kind::Discriminator(pb::TrainDiscriminator {
        base_dataset,
        expert_dataset,
        architecture,
        diffusion_model,
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
    let widths = |flag: &Option<Vec<u32>>, flag_name: &'static str, file: Vec<u32>, name: &str| {
        let (widths, source) = match flag {
            Some(widths) => (widths.clone(), Source::Flag(flag_name)),
            None => (file, Source::File(field(name))),
        };
        match widths.iter().position(|&w| w == 0) {
            Some(i) => Err(source.invalid(format!("width {} of {widths:?} is 0", i + 1))),
            None => Ok(widths),
        }
    };
    let file = file.filter(|a| a.kind() == kind).unwrap_or_else(|| RewardArchitecture::unset(kind));
    let architecture = match file {
        RewardArchitecture::WindowedMlp { window, hidden } => {
            let window = flag_or_file(args.window, "--window", window, || field("window"));
            if let Some((0, source)) = &window {
                return Err(source.invalid("a window holds at least 1 transition"));
            }
            let hidden = widths(&args.hidden, "--hidden", hidden, "hidden")?;
            RewardArchitecture::WindowedMlp { window: window.map(|(h, _)| h), hidden }
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
    Ok(Some(architecture.into_proto()))
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::super::manifest::parse_text;
    use super::*;

    const CONFIG: &str = r#"
        output_model = "from-file"
        seed = 3

        [optimization]
        steps = 1000
        batch_size = 32
        learning_rate = 2e-4
        ema_decay = 0.995

        [diffusion]
        dataset = "maze"
        horizon = 32
        n_timesteps = 20
        parametrization = "x0"
        schedule = { kind = "cosine" }
        architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 2, 4, 8] }
        action_weight = 10
        clip_denoised = true
    "#;

    const REWARD_CONFIG: &str = r#"
        output_model = "maze-reward"
        seed = 5

        [optimization]
        steps = 100000
        batch_size = 256
        learning_rate = 5e-5
        grad_clip = 1.0

        [reward]
        base_model = "maze-base"
        expert_model = "maze-expert"
        architecture = { kind = "windowed_mlp", window = 4, hidden = [128, 64, 32] }
        algorithm = { kind = "with_dataset", datasets = ["maze-a", "maze-b"] }
        target = "score"
        eval_point = "mu_base"
        rho_l2 = 0.01
    "#;

    const DISCRIMINATOR_CONFIG: &str = r#"
        output_model = "maze-disc"

        [optimization]
        steps = 2000

        [discriminator]
        base_dataset = "maze-a"
        expert_dataset = "maze-b"
        diffusion_model = "maze-base"
        architecture = { kind = "value_function", widths = [32, 64] }
    "#;

    fn config(text: &str) -> TrainConfig {
        parse_text(text, Path::new("train.toml")).unwrap_or_else(|e| panic!("{e:#}"))
    }

    fn job(name: &str) -> TrainArgs {
        TrainArgs { name: Some(name.into()), ..Default::default() }
    }

    fn diffusion(spec: &pb::JobSpec) -> &pb::TrainDiffusion {
        match &spec.kind {
            Some(Kind::Diffusion(d)) => d,
            other => panic!("not a diffusion job: {other:?}"),
        }
    }

    fn reward(spec: &pb::JobSpec) -> &pb::TrainReward {
        match &spec.kind {
            Some(Kind::Reward(r)) => r,
            other => panic!("not a reward job: {other:?}"),
        }
    }

    fn discriminator(spec: &pb::JobSpec) -> &pb::TrainDiscriminator {
        match &spec.kind {
            Some(Kind::Discriminator(d)) => d,
            other => panic!("not a discriminator job: {other:?}"),
        }
    }

    /// The message of a [`UsageError`] (panics on any other error).
    fn usage_error(result: Result<pb::JobSpec>) -> String {
        let err = result.expect_err("a usage error");
        match err.downcast_ref::<UsageError>() {
            Some(e) => e.0.clone(),
            None => panic!("not a usage error: {err:#}"),
        }
    }

    /// The message of an error that is not a [`UsageError`].
    fn config_error(result: Result<pb::JobSpec>) -> String {
        let err = result.expect_err("an error");
        assert!(err.downcast_ref::<UsageError>().is_none(), "a usage error: {err:#}");
        format!("{err:#}")
    }

    fn windowed(window: Option<u32>, hidden: &[u32]) -> Option<pb::RewardArchitecture> {
        Some(pb::RewardArchitecture {
            kind: Some(pb::reward_architecture::Kind::WindowedMlp(pb::reward_architecture::WindowedMlp {
                window,
                hidden: hidden.to_vec(),
            })),
        })
    }

    fn value_function(widths: &[u32]) -> Option<pb::RewardArchitecture> {
        Some(pb::RewardArchitecture {
            kind: Some(pb::reward_architecture::Kind::ValueFunction(pb::reward_architecture::ValueFunction {
                widths: widths.to_vec(),
            })),
        })
    }

    fn mlp(hidden: &[u32]) -> Option<pb::RewardArchitecture> {
        Some(pb::RewardArchitecture {
            kind: Some(pb::reward_architecture::Kind::Mlp(pb::Mlp { hidden: hidden.to_vec() })),
        })
    }

    fn with_dataset(datasets: &[&str]) -> Option<pb::train_reward::Algorithm> {
        Some(pb::train_reward::Algorithm::WithDataset(pb::train_reward::WithDataset {
            datasets: datasets.iter().map(|d| (*d).to_owned()).collect(),
        }))
    }

    fn models_only(num_chains: Option<u32>) -> Option<pb::train_reward::Algorithm> {
        Some(pb::train_reward::Algorithm::ModelsOnly(pb::train_reward::ModelsOnly { num_chains }))
    }

    // -----------------------------------------------------------------------------------------
    // train diffusion

    #[test]
    fn the_config_file_fills_the_spec() {
        let spec = diffusion_spec(config(CONFIG), &TrainDiffusionArgs::default()).expect("spec");
        assert_eq!(spec.output_model, "from-file");
        assert_eq!(spec.seed, Some(3));
        let o = spec.optimization.expect("optimization");
        assert_eq!(
            (o.steps, o.batch_size, o.learning_rate, o.ema_decay),
            (Some(1000), Some(32), Some(2e-4), Some(0.995))
        );
        assert_eq!((o.grad_clip, o.ema_every, o.log_every), (None, None, None));
        let d = diffusion(&spec);
        assert_eq!(d.dataset, "maze");
        assert_eq!((d.horizon, d.n_timesteps, d.action_weight), (Some(32), Some(20), Some(10.0)));
        assert_eq!(d.parametrization(), pb::Parametrization::X0);
        assert_eq!(d.clip_denoised, Some(true));
        assert_eq!(
            d.schedule,
            Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.0 })) })
        );
        assert_eq!(
            d.architecture,
            Some(pb::train_diffusion::Architecture::TemporalUnet(pb::TemporalUnet {
                dim: Some(32),
                dim_mults: vec![1, 2, 4, 8]
            }))
        );
    }

    #[test]
    fn flags_override_the_file() {
        let args = TrainDiffusionArgs {
            dataset: Some("other".into()),
            horizon: Some(64),
            n_timesteps: Some(100),
            normalizer_datasets: vec!["a".into(), "b".into()],
            job: TrainArgs {
                name: Some("from-flag".into()),
                steps: Some(50),
                batch_size: Some(8),
                lr: Some(1e-3),
                seed: Some(9),
                ..Default::default()
            },
        };
        let spec = diffusion_spec(config(CONFIG), &args).expect("spec");
        assert_eq!((spec.output_model.as_str(), spec.seed), ("from-flag", Some(9)));
        let o = spec.optimization.expect("optimization");
        assert_eq!((o.steps, o.batch_size, o.learning_rate), (Some(50), Some(8), Some(1e-3)));
        assert_eq!(o.ema_decay, Some(0.995), "what no flag sets comes from the file");
        let d = diffusion(&spec);
        assert_eq!((d.dataset.as_str(), d.horizon, d.n_timesteps), ("other", Some(64), Some(100)));
        assert_eq!(d.normalizer_datasets, ["a", "b"]);
        assert_eq!(d.parametrization(), pb::Parametrization::X0);
    }

    #[test]
    fn unset_fields_stay_unset() {
        let args = TrainDiffusionArgs { dataset: Some("d".into()), job: job("m"), ..Default::default() };
        let spec = diffusion_spec(TrainConfig::default(), &args).expect("spec");
        assert_eq!(spec.seed, None);
        assert_eq!(spec.optimization, Some(pb::Optimization::default()));
        let d = diffusion(&spec);
        assert_eq!(
            d,
            &pb::TrainDiffusion { dataset: "d".into(), ..Default::default() },
            "parametrization UNSPECIFIED, no schedule, no architecture, no T or H"
        );
        // An MLP with no widths leaves them to the server as well.
        let spec = diffusion_spec(config("[diffusion]\narchitecture = { kind = \"mlp\" }"), &args).expect("spec");
        assert_eq!(diffusion(&spec).architecture, Some(pb::train_diffusion::Architecture::Mlp(pb::Mlp::default())));
    }

    #[test]
    fn missing_names_are_usage_errors() {
        let err = usage_error(diffusion_spec(TrainConfig::default(), &TrainDiffusionArgs::default()));
        assert!(err.contains("--name"), "{err}");
        let args = TrainDiffusionArgs { job: job("m"), ..Default::default() };
        let err = usage_error(diffusion_spec(TrainConfig::default(), &args));
        assert!(err.contains("--dataset"), "{err}");
    }

    #[test]
    fn config_errors_name_the_field_or_line() {
        let parse = |text: &str| parse_text::<TrainConfig>(text, Path::new("train.toml")).map(|_| ());
        let err = parse("[optimization]\nstep = 10").expect_err("typo");
        assert!(err.to_string().contains("unknown field `step`") && err.to_string().contains("line 2"), "{err}");
        let err = parse("[diffusion]\narchitecture = { kind = \"resnet\" }").expect_err("bad kind");
        assert!(err.to_string().contains("unknown variant `resnet`"), "{err}");
        let err = parse("[optimization]\nsteps = -1").expect_err("negative");
        assert!(err.to_string().contains("line 2"), "{err}");
        let bad_s = config("[diffusion]\nschedule = { kind = \"cosine\", s = 2 }");
        let args = TrainDiffusionArgs { dataset: Some("d".into()), job: job("m"), ..Default::default() };
        let err = config_error(diffusion_spec(bad_s, &args));
        assert!(err.contains("diffusion.schedule.s"), "{err}");
        // Another command's table is a mistake, not something to ignore.
        let err = config_error(diffusion_spec(config(REWARD_CONFIG), &args));
        assert!(err.contains("[reward]") && err.contains("`train reward`") && err.contains("[diffusion]"), "{err}");
    }

    #[test]
    fn a_config_file_is_read_from_disk() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("train.toml");
        std::fs::write(&path, CONFIG).expect("write");
        let args = TrainDiffusionArgs {
            job: TrainArgs { config: Some(path.clone()), steps: Some(7), ..Default::default() },
            ..Default::default()
        };
        let spec = diffusion_spec_from_args(&args).expect("spec");
        assert_eq!(spec.optimization.and_then(|o| o.steps), Some(7));
        let args = TrainDiffusionArgs {
            job: TrainArgs { config: Some(dir.path().join("missing.toml")), ..Default::default() },
            ..Default::default()
        };
        let err = format!("{:#}", diffusion_spec_from_args(&args).expect_err("missing"));
        assert!(err.contains("missing.toml"), "{err}");
    }

    // -----------------------------------------------------------------------------------------
    // train reward

    #[test]
    fn reward_config_file_fills_the_spec() {
        let spec = reward_spec(config(REWARD_CONFIG), &TrainRewardArgs::default()).expect("spec");
        assert_eq!((spec.output_model.as_str(), spec.seed), ("maze-reward", Some(5)));
        let o = spec.optimization.expect("optimization");
        assert_eq!(
            (o.steps, o.batch_size, o.learning_rate, o.grad_clip),
            (Some(100_000), Some(256), Some(5e-5), Some(1.0))
        );
        assert_eq!(
            reward(&spec),
            &pb::TrainReward {
                base_model: "maze-base".into(),
                expert_model: "maze-expert".into(),
                architecture: windowed(Some(4), &[128, 64, 32]),
                target: pb::RewardTarget::Score as i32,
                eval_point: pb::EvalPoint::MuBase as i32,
                algorithm: with_dataset(&["maze-a", "maze-b"]),
                rho_l2: Some(0.01),
            }
        );
        // Algorithm 2 from the file, with its chain count.
        let text = "[reward]\nbase_model = \"b\"\nexpert_model = \"e\"\n\
                    algorithm = { kind = \"models_only\", num_chains = 512 }";
        let spec = reward_spec(config(text), &TrainRewardArgs { job: job("r"), ..Default::default() }).expect("spec");
        assert_eq!(reward(&spec).algorithm, models_only(Some(512)));
    }

    #[test]
    fn reward_flags_override_the_file() {
        let args = TrainRewardArgs {
            base: Some("b2".into()),
            expert: Some("e2".into()),
            datasets: vec!["d1".into(), "d2".into(), "d3".into()],
            target: Some(Target::Mean),
            eval_point: Some(EvalPoint::XT),
            arch: ArchArgs { hidden: Some(vec![16, 16]), ..Default::default() },
            rho_l2: Some(0.0),
            job: TrainArgs {
                name: Some("r2".into()),
                steps: Some(10),
                batch_size: Some(4),
                lr: Some(1e-3),
                seed: Some(1),
                ..Default::default()
            },
            ..Default::default()
        };
        let spec = reward_spec(config(REWARD_CONFIG), &args).expect("spec");
        assert_eq!((spec.output_model.as_str(), spec.seed), ("r2", Some(1)));
        let o = spec.optimization.expect("optimization");
        assert_eq!((o.steps, o.batch_size, o.learning_rate), (Some(10), Some(4), Some(1e-3)));
        assert_eq!(o.grad_clip, Some(1.0), "what no flag sets comes from the file");
        let r = reward(&spec);
        assert_eq!((r.base_model.as_str(), r.expert_model.as_str()), ("b2", "e2"));
        assert_eq!((r.target(), r.eval_point(), r.rho_l2), (pb::RewardTarget::Mean, pb::EvalPoint::XT, Some(0.0)));
        assert_eq!(r.algorithm, with_dataset(&["d1", "d2", "d3"]), "--dataset replaces the file's list");
        assert_eq!(r.architecture, windowed(Some(4), &[16, 16]), "--hidden keeps the file's window");

        // --window over the file's windowed_mlp; --arch of another kind drops the file's widths.
        let args = TrainRewardArgs { arch: ArchArgs { window: Some(8), ..Default::default() }, ..Default::default() };
        let spec = reward_spec(config(REWARD_CONFIG), &args).expect("spec");
        assert_eq!(reward(&spec).architecture, windowed(Some(8), &[128, 64, 32]));
        let args = TrainRewardArgs {
            arch: ArchArgs { arch: Some(ArchKind::Mlp), ..Default::default() },
            ..Default::default()
        };
        let spec = reward_spec(config(REWARD_CONFIG), &args).expect("spec");
        assert_eq!(reward(&spec).architecture, mlp(&[]));
        let args = TrainRewardArgs {
            arch: ArchArgs { arch: Some(ArchKind::ValueFunction), widths: Some(vec![8, 16]), ..Default::default() },
            ..Default::default()
        };
        let spec = reward_spec(config(REWARD_CONFIG), &args).expect("spec");
        assert_eq!(reward(&spec).architecture, value_function(&[8, 16]));
    }

    #[test]
    fn the_reward_algorithm_follows_the_flags() {
        let spec = |text: &str, args: TrainRewardArgs| reward_spec(config(text), &args);
        // The file says Algorithm 1: --num-chains switches to 2, as does --algorithm 2.
        let args = TrainRewardArgs { num_chains: Some(64), ..Default::default() };
        assert_eq!(reward(&spec(REWARD_CONFIG, args).expect("spec")).algorithm, models_only(Some(64)));
        let args = TrainRewardArgs { algorithm: Some(AlgorithmArg::ModelsOnly), ..Default::default() };
        assert_eq!(reward(&spec(REWARD_CONFIG, args).expect("spec")).algorithm, models_only(None));
        // The file says Algorithm 2: --dataset switches to 1; --num-chains overrides K.
        let file = "output_model = \"r\"\n[reward]\nbase_model = \"b\"\nexpert_model = \"e\"\n\
                    algorithm = { kind = \"models_only\", num_chains = 512 }";
        let args = TrainRewardArgs { datasets: vec!["d".into()], ..Default::default() };
        assert_eq!(reward(&spec(file, args).expect("spec")).algorithm, with_dataset(&["d"]));
        let args = TrainRewardArgs { num_chains: Some(8), ..Default::default() };
        assert_eq!(reward(&spec(file, args).expect("spec")).algorithm, models_only(Some(8)));
        let args = TrainRewardArgs { algorithm: Some(AlgorithmArg::ModelsOnly), ..Default::default() };
        assert_eq!(reward(&spec(file, args).expect("spec")).algorithm, models_only(Some(512)));
        // --algorithm 1 over the file's Algorithm 2 needs datasets from the flags.
        let args = TrainRewardArgs { algorithm: Some(AlgorithmArg::WithDataset), ..Default::default() };
        let err = usage_error(spec(file, args));
        assert!(err.contains("--dataset"), "{err}");
        // No file: --algorithm 2 alone leaves K to the server.
        let args = TrainRewardArgs {
            base: Some("b".into()),
            expert: Some("e".into()),
            algorithm: Some(AlgorithmArg::ModelsOnly),
            job: job("r"),
            ..Default::default()
        };
        assert_eq!(reward(&spec("", args).expect("spec")).algorithm, models_only(None));
    }

    #[test]
    fn unset_reward_fields_stay_unset() {
        let args = TrainRewardArgs {
            base: Some("b".into()),
            expert: Some("e".into()),
            datasets: vec!["d".into()],
            job: job("r"),
            ..Default::default()
        };
        let spec = reward_spec(TrainConfig::default(), &args).expect("spec");
        assert_eq!(spec.seed, None);
        assert_eq!(spec.optimization, Some(pb::Optimization::default()));
        assert_eq!(
            reward(&spec),
            &pb::TrainReward {
                base_model: "b".into(),
                expert_model: "e".into(),
                algorithm: with_dataset(&["d"]),
                ..Default::default()
            },
            "no architecture, target and eval point UNSPECIFIED, no rho_l2"
        );
        // A kind with no widths leaves them to the server too.
        let args = TrainRewardArgs {
            arch: ArchArgs { arch: Some(ArchKind::WindowedMlp), ..Default::default() },
            ..args.clone()
        };
        assert_eq!(
            reward(&reward_spec(TrainConfig::default(), &args).expect("spec")).architecture,
            windowed(None, &[])
        );
    }

    #[test]
    fn missing_reward_inputs_name_their_flag() {
        let full = TrainRewardArgs {
            base: Some("b".into()),
            expert: Some("e".into()),
            datasets: vec!["d".into()],
            job: job("r"),
            ..Default::default()
        };
        let cases = [
            ("--name", TrainRewardArgs { job: TrainArgs::default(), ..full.clone() }),
            ("--base", TrainRewardArgs { base: None, ..full.clone() }),
            ("--expert", TrainRewardArgs { expert: None, ..full.clone() }),
            ("--dataset", TrainRewardArgs { datasets: Vec::new(), ..full.clone() }),
        ];
        for (flag, args) in cases {
            let err = usage_error(reward_spec(TrainConfig::default(), &args));
            assert!(err.contains(flag), "{flag}: {err}");
        }
        // An empty dataset list in the file is no dataset.
        let text = "[reward]\nalgorithm = { kind = \"with_dataset\", datasets = [] }";
        let err = usage_error(reward_spec(config(text), &TrainRewardArgs { datasets: Vec::new(), ..full }));
        assert!(err.contains("--dataset"), "{err}");
    }

    #[test]
    fn bad_reward_values_are_refused() {
        let full = TrainRewardArgs {
            base: Some("b".into()),
            expert: Some("e".into()),
            datasets: vec!["d".into()],
            job: job("r"),
            ..Default::default()
        };
        let arch = |arch: ArchArgs| TrainRewardArgs { arch, ..full.clone() };
        let usage_cases = [
            (
                "--num-chains",
                TrainRewardArgs { algorithm: Some(AlgorithmArg::WithDataset), num_chains: Some(8), ..full.clone() },
            ),
            ("--dataset", TrainRewardArgs { algorithm: Some(AlgorithmArg::ModelsOnly), ..full.clone() }),
            ("exclude each other", TrainRewardArgs { num_chains: Some(8), ..full.clone() }),
            ("--num-chains: 1 chains", TrainRewardArgs { datasets: Vec::new(), num_chains: Some(1), ..full.clone() }),
            ("--rho-l2: -1", TrainRewardArgs { rho_l2: Some(-1.0), ..full.clone() }),
            ("--rho-l2: NaN", TrainRewardArgs { rho_l2: Some(f64::NAN), ..full.clone() }),
            ("--window needs an architecture", arch(ArchArgs { window: Some(4), ..Default::default() })),
            ("--hidden needs an architecture", arch(ArchArgs { hidden: Some(vec![8]), ..Default::default() })),
            (
                "--window is for --arch windowed_mlp, and the architecture is mlp",
                arch(ArchArgs { arch: Some(ArchKind::Mlp), window: Some(4), ..Default::default() }),
            ),
            (
                "--widths is for --arch value_function or conv_encoder",
                arch(ArchArgs { arch: Some(ArchKind::WindowedMlp), widths: Some(vec![8]), ..Default::default() }),
            ),
            (
                "--hidden is for --arch windowed_mlp or mlp",
                arch(ArchArgs { arch: Some(ArchKind::ConvEncoder), hidden: Some(vec![8]), ..Default::default() }),
            ),
            (
                "--window: a window",
                arch(ArchArgs { arch: Some(ArchKind::WindowedMlp), window: Some(0), ..Default::default() }),
            ),
            (
                "--hidden: width 2 of [8, 0] is 0",
                arch(ArchArgs { arch: Some(ArchKind::Mlp), hidden: Some(vec![8, 0]), ..Default::default() }),
            ),
        ];
        for (needle, args) in usage_cases {
            let err = usage_error(reward_spec(TrainConfig::default(), &args));
            assert!(err.contains(needle), "{needle:?} not in {err:?}");
        }
        // A flag that does not fit the file's architecture is refused as well.
        let err = usage_error(reward_spec(
            config(REWARD_CONFIG),
            &TrainRewardArgs { arch: ArchArgs { widths: Some(vec![8]), ..Default::default() }, ..Default::default() },
        ));
        assert!(err.contains("the architecture is windowed_mlp"), "{err}");

        // Bad values in the file name their field (and are not usage errors).
        let file_cases = [
            ("rho_l2 = -0.5", "--config: reward.rho_l2: -0.5"),
            ("algorithm = { kind = \"models_only\", num_chains = 0 }", "reward.algorithm.num_chains: 0 chains"),
            ("architecture = { kind = \"windowed_mlp\", window = 0 }", "reward.architecture.window"),
            ("architecture = { kind = \"conv_encoder\", widths = [0] }", "reward.architecture.widths: width 1"),
        ];
        let models_only = TrainRewardArgs { datasets: Vec::new(), ..full.clone() };
        for (line, needle) in file_cases {
            let args = if line.contains("models_only") { &models_only } else { &full };
            let err = config_error(reward_spec(config(&format!("[reward]\n{line}")), args));
            assert!(err.contains(needle), "{needle:?} not in {err:?}");
        }
    }

    #[test]
    fn reward_config_errors_name_the_field_or_line() {
        let parse = |text: &str| {
            let err = parse_text::<TrainConfig>(text, Path::new("train.toml")).expect_err(text);
            err.to_string()
        };
        let cases = [
            ("[reward]\nbase = \"b\"", "unknown field `base`"),
            ("[reward]\n\ntarget = \"median\"", "unknown variant `median`"),
            ("[reward]\neval_point = \"xt\"", "unknown variant `xt`"),
            ("[reward]\nalgorithm = { kind = \"algorithm_3\" }", "unknown variant `algorithm_3`"),
            ("[reward]\nalgorithm = { kind = \"models_only\", num_chains = -1 }", "line 2"),
            ("[reward]\nalgorithm = { kind = \"models_only\", datasets = [\"d\"] }", "unknown field `datasets`"),
            ("[reward]\narchitecture = { kind = \"windowed_mlp\", widths = [8] }", "unknown field `widths`"),
            ("[reward]\narchitecture = { kind = \"windowed_mlp\", window = \"four\" }", "line 2"),
            ("[reward]\nrho_l2 = \"small\"", "line 2"),
        ];
        for (text, needle) in cases {
            let err = parse(text);
            assert!(err.contains(needle), "{needle:?} not in {err:?}");
        }
        assert!(parse("[reward]\n\ntarget = \"median\"").contains("line 3"));
        let err = config_error(reward_spec(config(CONFIG), &TrainRewardArgs::default()));
        assert!(err.contains("[diffusion]") && err.contains("`train reward` reads [reward]"), "{err}");
    }

    #[test]
    fn a_reward_config_is_read_from_disk() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("reward.toml");
        std::fs::write(&path, REWARD_CONFIG).expect("write");
        let args = TrainRewardArgs {
            target: Some(Target::Mean),
            job: TrainArgs { config: Some(path), ..Default::default() },
            ..Default::default()
        };
        let spec = reward_spec_from_args(&args).expect("spec");
        assert_eq!(reward(&spec).target(), pb::RewardTarget::Mean);
        assert_eq!(reward(&spec).base_model, "maze-base");
    }

    // -----------------------------------------------------------------------------------------
    // train discriminator

    #[test]
    fn discriminator_config_file_fills_the_spec() {
        let spec = discriminator_spec(config(DISCRIMINATOR_CONFIG), &TrainDiscriminatorArgs::default()).expect("spec");
        assert_eq!((spec.output_model.as_str(), spec.seed), ("maze-disc", None));
        assert_eq!(spec.optimization, Some(pb::Optimization { steps: Some(2000), ..Default::default() }));
        assert_eq!(
            discriminator(&spec),
            &pb::TrainDiscriminator {
                base_dataset: "maze-a".into(),
                expert_dataset: "maze-b".into(),
                architecture: value_function(&[32, 64]),
                diffusion_model: "maze-base".into(),
            }
        );
    }

    #[test]
    fn discriminator_flags_override_the_file() {
        let args = TrainDiscriminatorArgs {
            base_dataset: Some("a2".into()),
            expert_dataset: Some("b2".into()),
            diffusion_model: Some("m2".into()),
            arch: ArchArgs { widths: Some(vec![16]), ..Default::default() },
            job: TrainArgs { name: Some("d2".into()), lr: Some(1e-4), seed: Some(2), ..Default::default() },
        };
        let spec = discriminator_spec(config(DISCRIMINATOR_CONFIG), &args).expect("spec");
        assert_eq!((spec.output_model.as_str(), spec.seed), ("d2", Some(2)));
        assert_eq!(
            spec.optimization,
            Some(pb::Optimization { steps: Some(2000), learning_rate: Some(1e-4), ..Default::default() })
        );
        assert_eq!(
            discriminator(&spec),
            &pb::TrainDiscriminator {
                base_dataset: "a2".into(),
                expert_dataset: "b2".into(),
                architecture: value_function(&[16]),
                diffusion_model: "m2".into(),
            }
        );
        let args = TrainDiscriminatorArgs {
            arch: ArchArgs { arch: Some(ArchKind::WindowedMlp), window: Some(2), ..Default::default() },
            ..Default::default()
        };
        let spec = discriminator_spec(config(DISCRIMINATOR_CONFIG), &args).expect("spec");
        assert_eq!(discriminator(&spec).architecture, windowed(Some(2), &[]));
    }

    #[test]
    fn unset_discriminator_fields_stay_unset_and_missing_ones_are_named() {
        let full = TrainDiscriminatorArgs {
            base_dataset: Some("a".into()),
            expert_dataset: Some("b".into()),
            diffusion_model: Some("m".into()),
            job: job("d"),
            ..Default::default()
        };
        let spec = discriminator_spec(TrainConfig::default(), &full).expect("spec");
        assert_eq!(spec.seed, None);
        assert_eq!(spec.optimization, Some(pb::Optimization::default()));
        assert_eq!(discriminator(&spec).architecture, None);
        let cases = [
            ("--name", TrainDiscriminatorArgs { job: TrainArgs::default(), ..full.clone() }),
            ("--base-dataset", TrainDiscriminatorArgs { base_dataset: None, ..full.clone() }),
            ("--expert-dataset", TrainDiscriminatorArgs { expert_dataset: None, ..full.clone() }),
            ("--diffusion-model", TrainDiscriminatorArgs { diffusion_model: None, ..full.clone() }),
        ];
        for (flag, args) in cases {
            let err = usage_error(discriminator_spec(TrainConfig::default(), &args));
            assert!(err.contains(flag), "{flag}: {err}");
        }
    }

    #[test]
    fn bad_discriminator_values_are_refused() {
        let args =
            TrainDiscriminatorArgs { arch: ArchArgs { window: Some(4), ..Default::default() }, ..Default::default() };
        let err = usage_error(discriminator_spec(config(DISCRIMINATOR_CONFIG), &args));
        assert!(err.contains("--window is for --arch windowed_mlp, and the architecture is value_function"), "{err}");
        let args = TrainDiscriminatorArgs {
            arch: ArchArgs { widths: Some(vec![4]), ..Default::default() },
            ..Default::default()
        };
        let text = DISCRIMINATOR_CONFIG.replace("architecture = { kind = \"value_function\", widths = [32, 64] }", "");
        let err = usage_error(discriminator_spec(config(&text), &args));
        assert!(err.contains("--widths needs an architecture") && err.contains("[discriminator]"), "{err}");
        let text = DISCRIMINATOR_CONFIG.replace("[32, 64]", "[32, 0]");
        let err = config_error(discriminator_spec(config(&text), &TrainDiscriminatorArgs::default()));
        assert!(err.contains("discriminator.architecture.widths: width 2"), "{err}");
        // Config errors name the field or line; a reward table is refused.
        let err = parse_text::<TrainConfig>("[discriminator]\nbase_model = \"b\"", Path::new("t.toml"))
            .expect_err("unknown field")
            .to_string();
        assert!(err.contains("unknown field `base_model`") && err.contains("line 2"), "{err}");
        let err = config_error(discriminator_spec(config(REWARD_CONFIG), &TrainDiscriminatorArgs::default()));
        assert!(err.contains("[reward]") && err.contains("`train discriminator` reads [discriminator]"), "{err}");
    }
}
