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
//! action_weight = 10.0              # --action-weight (trajectory models; first action)
//! condition_weight = 0.0            # --condition-weight (first observation)
//! inpaint_condition = true          # --inpaint-condition (first observation clean in x_t)
//! architecture = { kind = "windowed_mlp", window = 4, hidden = [128, 64, 32] }
//! # or { kind = "value_function", widths = [..] }, { kind = "conv_encoder", widths = [..] },
//! # { kind = "mlp", hidden = [..] }  (--arch, --window, --hidden, --widths)
//!
//! [discriminator]                   # train discriminator
//! base_dataset = "maze-umaze-base"  # --base-dataset
//! expert_dataset = "maze-expert"    # --expert-dataset
//! diffusion_model = "maze-base"     # --diffusion-model
//! inpaint_condition = true          # --inpaint-condition
//! architecture = { kind = "value_function", widths = [32, 64] }  # as in [reward]
//! ```
//!
//! Flags override the file; whatever neither sets stays unset, and the server fills in the
//! paper's defaults. A nested document (an architecture, a schedule) is read with the shared
//! schema's defaults for what it leaves out, the same the server would give. A file with
//! another command's table is refused.
//!
//! The reward algorithm is `--algorithm` if given, else the one its flags imply (`--dataset`:
//! 1, `--num-chains`: 2), else the file's, else Algorithm 1. The reward architecture is `--arch`
//! if given, else the file's; `--window`, `--hidden` and `--widths` adjust it, and the file's
//! widths are kept only when the file names the same kind.
//!
//! The file's types are the shared schema's (`relreward_proto::schema::job::request`, re-exported
//! by [`config`]), the flags are in [`flags`], and the merging in [`spec`].

pub mod config;
pub mod flags;
pub mod spec;

pub use flags::{TrainArgs, TrainDiffusionArgs, TrainDiscriminatorArgs, TrainRewardArgs};
pub use spec::{diffusion_spec_from_args, discriminator_spec_from_args, reward_spec_from_args};

#[cfg(test)]
mod tests {
    use std::path::Path;

    use anyhow::Result;
    use pb::job_spec::Kind;
    use relreward_client::pb;

    use super::super::UsageError;
    use super::super::manifest::parse_text;
    use super::config::{ArchKind, EvalPoint, Target, TrainConfig};
    use super::flags::{AlgorithmArg, ArchArgs};
    use super::spec::{diffusion_spec, discriminator_spec, reward_spec};
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
        action_weight = 10.0
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
        // A nested document's omitted field is read with the schema's default (cosine s).
        assert_eq!(
            d.schedule,
            Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.008 })) })
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
        // An MLP with no widths gets the schema's (the server's) default widths.
        let spec = diffusion_spec(config("[diffusion]\narchitecture = { kind = \"mlp\" }"), &args).expect("spec");
        assert_eq!(
            diffusion(&spec).architecture,
            Some(pb::train_diffusion::Architecture::Mlp(pb::Mlp { hidden: vec![256, 256] }))
        );
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
                amortised_targets: None,
                action_weight: Some(10.0),
                condition_weight: None,
                inpaint_condition: None,
                base_recipe: None,
                expert_recipe: None,
            }
        );
        // Algorithm 2 from the file, with its chain count.
        let text = "[reward]\nbase_model = \"b\"\nexpert_model = \"e\"\n\
                    algorithm = { kind = \"models_only\", num_chains = 512 }";
        let spec = reward_spec(config(text), &TrainRewardArgs { job: job("r"), ..Default::default() }).expect("spec");
        assert_eq!(reward(&spec).algorithm, models_only(Some(512)));
        // Algorithm 2 with two recipes of a conditional model (Safe Latent Diffusion's setting).
        let text = "[reward]\nbase_model = \"m\"\nexpert_model = \"m\"\n\
                    algorithm = { kind = \"models_only\" }\n\
                    base_recipe = { prompts = { labels = [0, 3] }, guidance_scale = 3.0 }\n\
                    [reward.expert_recipe]\nprompts = { labels = [0, 3] }\nguidance_scale = 3.0\n\
                    safety = { concept = { labels = [3] }, scale = 2000.0, warmup_steps = 7, threshold = 0.025, \
                    momentum_scale = 0.5, momentum_beta = 0.7 }";
        let spec = reward_spec(config(text), &TrainRewardArgs { job: job("r"), ..Default::default() }).expect("spec");
        let r = reward(&spec);
        assert_eq!(r.base_recipe.as_ref().and_then(|b| b.prompts.as_ref()).map(|p| p.labels.clone()), Some(vec![0, 3]));
        let safety = r.expert_recipe.as_ref().and_then(|e| e.safety.as_ref()).expect("safety");
        assert_eq!((safety.warmup_steps, safety.scale), (7, 2000.0));
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

        // Amortised targets: off without the flags; any one flag turns them on, the rest left
        // to the server's defaults; `demo` passes the same flags on.
        assert_eq!(r.amortised_targets, None);
        let amortised = super::flags::AmortisedArgs { amortised_reuse: Some(8), ..Default::default() };
        let args = TrainRewardArgs { amortised: amortised.clone(), ..Default::default() };
        let spec = reward_spec(config(REWARD_CONFIG), &args).expect("spec");
        assert_eq!(
            reward(&spec).amortised_targets,
            Some(pb::AmortisedTargets { pool_size: None, reuse: Some(8), refresh_fraction: None })
        );
        assert_eq!(amortised.to_argv(), ["--amortised-reuse", "8"]);

        // --window over the file's windowed_mlp; --arch of another kind drops the file's widths.
        let args = TrainRewardArgs { arch: ArchArgs { window: Some(8), ..Default::default() }, ..Default::default() };
        let spec = reward_spec(config(REWARD_CONFIG), &args).expect("spec");
        assert_eq!(reward(&spec).architecture, windowed(Some(8), &[128, 64, 32]));
        let args = TrainRewardArgs {
            arch: ArchArgs { arch: Some(ArchKind::Mlp), ..Default::default() },
            ..Default::default()
        };
        let spec = reward_spec(config(REWARD_CONFIG), &args).expect("spec");
        assert_eq!(reward(&spec).architecture, mlp(&[128, 64, 32]), "the kind's defaults, from the schema");
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
        // A kind with no widths gets that kind's defaults (the schema's, as the server's).
        let args = TrainRewardArgs {
            arch: ArchArgs { arch: Some(ArchKind::WindowedMlp), ..Default::default() },
            ..args.clone()
        };
        assert_eq!(
            reward(&reward_spec(TrainConfig::default(), &args).expect("spec")).architecture,
            windowed(Some(4), &[128, 64, 32])
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
            ("--action-weight: -2", TrainRewardArgs { action_weight: Some(-2.0), ..full.clone() }),
            ("--condition-weight: inf", TrainRewardArgs { condition_weight: Some(f64::INFINITY), ..full.clone() }),
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
            ("condition_weight = -1.0", "--config: reward.condition_weight: -1"),
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
                inpaint_condition: None,
            }
        );
    }

    #[test]
    fn discriminator_flags_override_the_file() {
        let args = TrainDiscriminatorArgs {
            base_dataset: Some("a2".into()),
            expert_dataset: Some("b2".into()),
            diffusion_model: Some("m2".into()),
            inpaint_condition: true,
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
                inpaint_condition: Some(true),
            }
        );
        let args = TrainDiscriminatorArgs {
            arch: ArchArgs { arch: Some(ArchKind::WindowedMlp), window: Some(2), ..Default::default() },
            ..Default::default()
        };
        let spec = discriminator_spec(config(DISCRIMINATOR_CONFIG), &args).expect("spec");
        assert_eq!(discriminator(&spec).architecture, windowed(Some(2), &[128, 64, 32]));
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
