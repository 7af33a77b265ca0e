//! From recordings to served rewards and their evaluation (`relreward extract`; `relreward demo`
//! runs it on the data it generates).
//!
//! One base dataset and one or more expert datasets, as canonical `.npz` files ([`files`]
//! converts HDF5 and Minari recordings), then, against a running server, [`pipeline`]:
//! 1. profiles each file and derives the sizes ([`relreward_toolkit::profile`]: the horizon
//!    from how far the agent moves per row, capped by the episode lengths), `--config` on top
//!    ([`sizes`]), and resolves what the evaluation will read besides the rows (walls, each
//!    expert's goal: [`resolve_evaluation`]), so that a run that would fail at step 5 fails
//!    here, before anything is uploaded or trained;
//! 2. uploads each dataset, or reuses it: names carry a fingerprint of the file's bytes, so a
//!    second run finds its datasets (and, names carrying a fingerprint of the sizes too, its
//!    models and rewards) and continues where the first stopped;
//! 3. trains a base and one expert diffusion model per expert dataset under one normalizer
//!    (computed over every dataset of the run), waiting on each job's watch;
//! 4. extracts a reward per expert (Algorithm 1 by default, or 2), and optionally the
//!    discriminator baseline of the same network;
//! 5. evaluates each ([`super::evaluate`]): discriminability with both classes' reward
//!    histograms, the loss curve, and when the maze's walls are known the reward heatmap with
//!    goal recovery, twice: over base sub-trajectories (the paper's) and at rest (the reward
//!    of staying at each position; docs/results.md, issue 19).
//!
//! [`report`] writes `report.md` and `report.json` from the typed results.

pub mod files;
pub mod report;
pub mod sizes;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use relreward_client::Client;
use relreward_toolkit::profile::{self, DataProfile};
use relreward_toolkit::trajectories::Trajectories;
use serde::Serialize;

use self::files::file_fingerprint;
use self::sizes::{Size, Sizes, Sizing};
use super::datasets::upload_or_reuse;
use super::evaluate::Scoring;
use super::evaluate::discriminate::{DiscriminateInput, discriminate};
use super::evaluate::heatmap::{Heatmap, HeatmapInput, Probe, heatmap};
use super::evaluate::plot::{JobPlotInput, job_plot};
use super::jobs::train_and_wait;
use super::{Progress, Silent};
use crate::UsageError;
use crate::train::config::ArchKind;
use crate::train::flags::{
    AlgorithmArg, AmortisedArgs, ArchArgs, TrainArgs, TrainDiffusionArgs, TrainDiscriminatorArgs, TrainRewardArgs,
};
use crate::train::{diffusion_spec_from_args, discriminator_spec_from_args, reward_spec_from_args};

/// What [`pipeline`] runs on: canonical `.npz` files and their labels.
#[derive(Debug, Clone)]
pub struct Inputs {
    pub base: PathBuf,
    pub experts: Vec<PathBuf>,
    /// One label per expert (names, pictures).
    pub labels: Vec<String>,
    /// One goal position per expert, when known.
    pub goals: Vec<Option<(f64, f64)>>,
    pub walls: Option<PathBuf>,
    pub out: PathBuf,
    /// Prefix of the server-side names of the run's datasets and models.
    pub prefix: String,
    pub algorithm: AlgorithmArg,
    pub discriminator: bool,
    pub seed: u64,
    /// Amortised targets for Algorithm 1's reward jobs (unset: per-step targets).
    pub amortised: AmortisedArgs,
}

/// What [`pipeline`] made: server names, the data's profiles, the sizes, one result per expert.
#[derive(Debug, Clone)]
pub struct Extracted {
    pub base_model: String,
    pub expert_models: Vec<String>,
    pub rewards: Vec<String>,
    pub experts: Vec<ExpertResult>,
    pub profiles: Vec<DataProfile>,
    pub sizes: Sizes,
}

/// One expert's reward (and discriminator) with its evaluation: a row of `report.json`.
#[derive(Debug, Clone, Serialize)]
pub struct ExpertResult {
    #[serde(flatten)]
    pub reward: ModelEvaluation,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub discriminator: Option<ModelEvaluation>,
    pub label: String,
    pub expert_data: String,
    pub sizes: Sizes,
}

/// One model's evaluation: discriminability, its pictures, and the maze measures when the
/// walls are known.
#[derive(Debug, Clone, Serialize)]
pub struct ModelEvaluation {
    /// `reward` or `discriminator`.
    pub kind: &'static str,
    pub model: String,
    pub balanced_accuracy: f64,
    pub auc: f64,
    pub expert_scores_higher: bool,
    pub histogram: String,
    pub loss_plot: String,
    #[serde(flatten)]
    pub maze: Option<MazeEvaluation>,
}

/// The heatmap over base sub-trajectories, and at rest.
#[derive(Debug, Clone, Serialize)]
pub struct MazeEvaluation {
    pub heatmap: String,
    /// The goal measured against (`--goal`, else the expert file's constant `goals`).
    pub goal: (f64, f64),
    pub argmax_cell: Option<(i64, i64)>,
    pub distance_cells: Option<f64>,
    pub goal_recovered: Option<bool>,
    #[serde(flatten)]
    pub at_rest: AtRest,
}

/// The at-rest heatmap, or why the data could not be probed at rest (states that are more than
/// a position and its velocities).
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum AtRest {
    Probed {
        heatmap_at_rest: String,
        argmax_cell_at_rest: Option<(i64, i64)>,
        distance_cells_at_rest: Option<f64>,
        goal_recovered_at_rest: Option<bool>,
    },
    Refused {
        at_rest_refused: String,
    },
}

impl ExpertResult {
    /// Whether the paper's heatmap recovered the goal (`None`: no walls or no goal).
    pub fn goal_recovered(&self) -> Option<bool> {
        self.reward.maze.as_ref().and_then(|m| m.goal_recovered)
    }

    /// Whether the at-rest heatmap recovered the goal (`None`: not probed, or no goal).
    pub fn goal_recovered_at_rest(&self) -> Option<bool> {
        match self.reward.maze.as_ref().map(|m| &m.at_rest) {
            Some(AtRest::Probed { goal_recovered_at_rest, .. }) => *goal_recovered_at_rest,
            _ => None,
        }
    }

    /// The maze cell of the paper's heatmap's maximum.
    pub fn argmax_cell(&self) -> Option<(i64, i64)> {
        self.reward.maze.as_ref().and_then(|m| m.argmax_cell)
    }

    /// The maze cell of the at-rest heatmap's maximum.
    pub fn argmax_cell_at_rest(&self) -> Option<(i64, i64)> {
        match self.reward.maze.as_ref().map(|m| &m.at_rest) {
            Some(AtRest::Probed { argmax_cell_at_rest, .. }) => *argmax_cell_at_rest,
            _ => None,
        }
    }
}

/// A path as report text.
pub fn path_str(p: &Path) -> String {
    p.to_string_lossy().into_owned()
}

/// Steps 1 to 5 of the module docs over canonical `.npz` inputs.
pub async fn pipeline(progress: &dyn Progress, client: &Client, inputs: &Inputs, sizing: Sizing) -> Result<Extracted> {
    client.health().await.context("the server is not answering health checks")?;
    let out = &inputs.out;

    // ---- sizes from the data
    let mut profiles = Vec::new();
    let (mut base_obs_dim, mut base_act_dim) = (0, 0);
    for path in std::iter::once(&inputs.base).chain(&inputs.experts) {
        let p = path.clone();
        let (profile, obs_dim, act_dim) =
            tokio::task::spawn_blocking(move || -> Result<(DataProfile, usize, usize)> {
                let t = Trajectories::from_npz(&p)?;
                Ok((profile::profile(&t.observations, t.obs_dim, &t.episodes()), t.obs_dim, t.act_dim))
            })
            .await??;
        if profiles.is_empty() {
            (base_obs_dim, base_act_dim) = (obs_dim, act_dim);
        } else if (obs_dim, act_dim) != (base_obs_dim, base_act_dim) {
            // One normalizer and one pair of models per expert: the rows must be alike. Said
            // now, before anything is uploaded or trained.
            return Err(UsageError(format!(
                "{}: rows of {obs_dim} observation and {act_dim} action values, but the base data ({}) has \
                 {base_obs_dim} and {base_act_dim}; base and expert recordings must come from the same environment",
                path.display(),
                inputs.base.display()
            ))
            .into());
        }
        profiles.push(profile);
    }
    // What the evaluation reads besides the rows (walls, goals), resolved now: a run that
    // would fail at its evaluation fails here, before anything is uploaded or trained.
    let evaluation = {
        let i = inputs.clone();
        tokio::task::spawn_blocking(move || resolve_evaluation(&i, base_obs_dim)).await??
    };
    let sizes = match sizing {
        Sizing::Fixed(s) => s,
        Sizing::Derive { size, config } => {
            let mut s = Sizes::preset(size);
            if size != Size::Full {
                let (h, w) = profile::derive_window(&profiles);
                (s.horizon, s.window) = (h as u32, w as u32);
            }
            if let Some(path) = &config {
                s.apply_config(path)?;
            }
            s.check().map_err(UsageError)?;
            s
        }
    };
    progress.stage(&format!(
        "sizes: horizon {} (reward window {}), T = {}, {} diffusion steps, {} reward steps; mean motion per row {:.4}",
        sizes.horizon,
        sizes.window,
        sizes.n_timesteps,
        sizes.diffusion_steps,
        sizes.reward_steps,
        profiles.iter().map(|p| p.displacement_per_row).sum::<f64>() / profiles.len().max(1) as f64
    ));

    // ---- upload or reuse
    let prefix = &inputs.prefix;
    let mut datasets = Vec::new();
    for (path, label) in
        std::iter::once((&inputs.base, &"base".to_owned())).chain(inputs.experts.iter().zip(&inputs.labels))
    {
        let p = path.clone();
        let fp = tokio::task::spawn_blocking(move || file_fingerprint(&p)).await??;
        let name = format!("{prefix}-{label}-{fp}");
        upload_or_reuse(progress, client, path, &name).await?;
        datasets.push(name);
    }
    let (base_ds, expert_ds) = (&datasets[0], &datasets[1..]);

    // ---- diffusion models: one base, one per expert, one normalizer over every dataset.
    let fp = sizes.diffusion_fingerprint();
    let mut diffusion = toml::Table::new();
    let mut table = toml::Table::new();
    table.insert("horizon".into(), toml::Value::Integer(i64::from(sizes.horizon)));
    table.insert("n_timesteps".into(), toml::Value::Integer(i64::from(sizes.n_timesteps)));
    table.insert("architecture".into(), sizes.diffusion_architecture.clone());
    diffusion.insert("diffusion".into(), toml::Value::Table(table));
    let config_path = out.join("diffusion.toml");
    std::fs::write(&config_path, toml::to_string(&diffusion)?)?;
    // Model names: the dataset's (with its content fingerprint) and the sizes' fingerprint.
    let model_name = |ds: &str| format!("{}-m{fp}", ds.chars().take(64 - 10).collect::<String>());
    let base_model = model_name(base_ds);
    let expert_models: Vec<String> = expert_ds.iter().map(|d| model_name(d)).collect();
    let jobs: Vec<(&String, &String)> =
        std::iter::once((&base_model, base_ds)).chain(expert_models.iter().zip(expert_ds)).collect();
    let diffusion_batch = batch_size(sizes.diffusion_batch, "diffusion_batch")?;
    for (i, (model, ds)) in jobs.iter().enumerate() {
        if client.get_model(model).await.is_ok() {
            progress.stage(&format!("reusing diffusion model {model}"));
            continue;
        }
        progress.stage(&format!(
            "training diffusion model {} of {}: {model} ({} steps)",
            i + 1,
            jobs.len(),
            sizes.diffusion_steps
        ));
        let args = TrainDiffusionArgs {
            dataset: Some((*ds).clone()),
            normalizer_datasets: datasets.clone(),
            job: TrainArgs {
                name: Some((*model).clone()),
                config: Some(config_path.clone()),
                steps: Some(sizes.diffusion_steps),
                batch_size: Some(diffusion_batch),
                seed: Some(inputs.seed + i as u64),
                job_id: Some((*model).clone()),
                ..TrainArgs::default()
            },
            ..TrainDiffusionArgs::default()
        };
        train_and_wait(progress, client, diffusion_spec_from_args(&args)?, model).await?;
    }

    // ---- rewards (and discriminators)
    let algorithm = match inputs.algorithm {
        AlgorithmArg::WithDataset => "1",
        AlgorithmArg::ModelsOnly => "2",
    };
    let reward_batch = batch_size(sizes.reward_batch, "reward_batch")?;
    // Both networks: a windowed MLP of the run's window and widths, the run's steps and batch.
    let net = ArchArgs {
        arch: Some(ArchKind::WindowedMlp),
        window: Some(sizes.window),
        hidden: Some(sizes.reward_hidden.clone()),
        widths: None,
    };
    let job = |name: &str, seed: u64| TrainArgs {
        name: Some(name.to_owned()),
        steps: Some(sizes.reward_steps),
        batch_size: Some(reward_batch),
        lr: Some(sizes.reward_lr),
        seed: Some(seed),
        job_id: Some(name.to_owned()),
        ..TrainArgs::default()
    };
    // Rewards and discriminators: named by every size, the reward's own included.
    let fp = sizes.fingerprint();
    let amortised = inputs.amortised.to_proto().is_some();
    let mut rewards = Vec::new();
    let mut discriminators = Vec::new();
    for (k, label) in inputs.labels.iter().enumerate() {
        // Amortised targets are a different recipe: a name of their own, so a rerun without
        // them never reuses an amortised reward (and the reverse).
        let recipe = if !amortised || inputs.algorithm != AlgorithmArg::WithDataset { "" } else { "a" };
        let reward = format!("{prefix}-r{algorithm}{recipe}-{label}-{fp}");
        let reward = reward.chars().take(64).collect::<String>();
        if client.get_model(&reward).await.is_ok() {
            progress.stage(&format!("reusing reward {reward}"));
        } else {
            progress.stage(&format!(
                "extracting reward {} of {} (Algorithm {algorithm}): {reward} ({} steps)",
                k + 1,
                inputs.labels.len(),
                sizes.reward_steps
            ));
            let mut args = TrainRewardArgs {
                base: Some(base_model.clone()),
                expert: Some(expert_models[k].clone()),
                arch: net.clone(),
                job: job(&reward, inputs.seed + 100 + k as u64),
                ..TrainRewardArgs::default()
            };
            if inputs.algorithm == AlgorithmArg::WithDataset {
                args.datasets = vec![base_ds.clone(), expert_ds[k].clone()];
                args.amortised = inputs.amortised.clone();
            } else {
                (args.algorithm, args.num_chains) = (Some(AlgorithmArg::ModelsOnly), Some(sizes.num_chains));
            }
            train_and_wait(progress, client, reward_spec_from_args(&args)?, &reward).await?;
        }
        rewards.push(reward);
        if inputs.discriminator {
            let disc = format!("{prefix}-d-{label}-{fp}").chars().take(64).collect::<String>();
            if client.get_model(&disc).await.is_ok() {
                progress.stage(&format!("reusing discriminator {disc}"));
            } else {
                progress.stage(&format!("training discriminator {} of {}: {disc}", k + 1, inputs.labels.len()));
                let args = TrainDiscriminatorArgs {
                    base_dataset: Some(base_ds.clone()),
                    expert_dataset: Some(expert_ds[k].clone()),
                    diffusion_model: Some(base_model.clone()),
                    arch: net.clone(),
                    job: job(&disc, inputs.seed + 200 + k as u64),
                    ..TrainDiscriminatorArgs::default()
                };
                train_and_wait(progress, client, discriminator_spec_from_args(&args)?, &disc).await?;
            }
            discriminators.push(disc);
        }
    }

    // ---- evaluation
    let mut experts = Vec::new();
    for (k, label) in inputs.labels.iter().enumerate() {
        progress.stage(&format!("evaluating reward {} of {} ({label})", k + 1, inputs.labels.len()));
        let maze = evaluation.walls.as_deref().zip(evaluation.goals[k]);
        let reward = evaluate_model(client, inputs, &sizes, k, &rewards[k], maze, "reward").await?;
        let discriminator = match discriminators.get(k) {
            Some(disc) => Some(evaluate_model(client, inputs, &sizes, k, disc, None, "discriminator").await?),
            None => None,
        };
        experts.push(ExpertResult {
            reward,
            discriminator,
            label: label.clone(),
            expert_data: path_str(&inputs.experts[k]),
            sizes: sizes.clone(),
        });
    }
    Ok(Extracted { base_model, expert_models, rewards, experts, profiles, sizes })
}

/// What the evaluation reads besides the rows, resolved by [`resolve_evaluation`].
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluationInputs {
    /// The file holding the maze's walls (`--walls`, else the base file when it holds them);
    /// `None`: no maze, so no heatmap and no goal needed.
    pub walls: Option<PathBuf>,
    /// One goal per expert: `Some` for every expert whenever `walls` is.
    pub goals: Vec<Option<(f64, f64)>>,
}

/// Resolves and checks, from the local files alone, everything the evaluation will read
/// besides the rows, so that [`pipeline`] fails before its first upload rather than after all
/// its training (issue 34): the walls (`--walls` must hold them; else the base file's, which
/// must be well formed), and with walls, a position in the base rows (2 coordinates or more)
/// and one goal per expert: `--goal`, else the expert file's `goals` when they hold one
/// constant goal. An expert file converted by `extract` (HDF5, Minari, `--absorbing`) keeps
/// its input's `goals` ([`Trajectories::write_npz`]), so the rule is the same for every input.
/// Errors are usage errors naming the flag and the file.
pub fn resolve_evaluation(inputs: &Inputs, base_obs_dim: usize) -> Result<EvaluationInputs> {
    let walls = match &inputs.walls {
        Some(w) => {
            relreward_toolkit::npz::walls_from_npz(w).with_context(|| format!("--walls {}", w.display()))?.ok_or_else(
                || UsageError(format!("--walls {}: no 'walls', 'wall_map' or 'maze_map' array", w.display())),
            )?;
            Some(w.clone())
        }
        None => relreward_toolkit::npz::walls_from_npz(&inputs.base)
            .with_context(|| format!("--base {}: maze walls", inputs.base.display()))?
            .map(|_| inputs.base.clone()),
    };
    let Some(walls) = walls else {
        // No maze: the evaluation is discriminability alone, which needs no goal.
        return Ok(EvaluationInputs { walls: None, goals: inputs.goals.clone() });
    };
    if base_obs_dim < 2 {
        return Err(UsageError(format!(
            "--base {}: observations have {base_obs_dim} coordinate(s); the maze heatmap (walls in {}) needs a \
             position, 2",
            inputs.base.display(),
            walls.display()
        ))
        .into());
    }
    let mut goals = Vec::new();
    for (k, path) in inputs.experts.iter().enumerate() {
        if let Some(g) = inputs.goals.get(k).copied().flatten() {
            goals.push(Some(g));
            continue;
        }
        let why = match super::evaluate::constant_goal(path) {
            Ok(Some(g)) => {
                goals.push(Some(g));
                continue;
            }
            Ok(None) => match relreward_toolkit::npz::npz_array_shape(path, "goals") {
                Ok(Some(_)) => "its 'goals' are not one constant goal".to_owned(),
                _ => "it has no 'goals' array".to_owned(),
            },
            Err(e) => format!("{e:#}"),
        };
        return Err(UsageError(format!(
            "--goal: expert {} ({}) has no goal for the maze heatmap (walls in {}): {why}; give --goal X,Y once per \
             --expert, in order",
            k + 1,
            path.display(),
            walls.display()
        ))
        .into());
    }
    Ok(EvaluationInputs { walls: Some(walls), goals })
}

/// A batch size as the job spec takes it.
fn batch_size(batch: u64, field: &str) -> Result<u32> {
    u32::try_from(batch).map_err(|_| UsageError(format!("[extract] {field} = {batch} is too large")).into())
}

/// Discriminability with histograms, the loss curve and (with walls) the heatmaps of one
/// model. Runs silently: the pipeline's stages say what is going on.
async fn evaluate_model(
    client: &Client,
    inputs: &Inputs,
    sizes: &Sizes,
    k: usize,
    model: &str,
    maze: Option<(&Path, (f64, f64))>,
    kind: &'static str,
) -> Result<ModelEvaluation> {
    let out = &inputs.out;
    let scoring = Scoring { seed: inputs.seed, ..Scoring::new(model) };
    let hist_png = out.join(format!("hist-{model}.png"));
    let mut input = DiscriminateInput::new(scoring.clone(), inputs.base.clone(), inputs.experts[k].clone());
    (input.max_windows, input.hist_out) = (sizes.max_windows.min(20_000), Some(hist_png.clone()));
    let measured = discriminate(&Silent, client, &input).await?;
    let loss_png = out.join(format!("loss-{model}.png"));
    let plot = JobPlotInput { id: model.to_owned(), out: loss_png.clone(), histogram: None };
    job_plot(&Silent, client, &plot).await.with_context(|| format!("plotting the loss of {model}"))?;
    let mut evaluation = ModelEvaluation {
        kind,
        model: model.to_owned(),
        balanced_accuracy: measured.balanced_accuracy(),
        auc: measured.result.test_auc,
        expert_scores_higher: measured.expert_scores_higher(),
        histogram: path_str(&hist_png),
        loss_plot: path_str(&loss_png),
        maze: None,
    };
    let Some((walls, goal)) = maze else { return Ok(evaluation) };
    let heat_png = out.join(format!("heatmap-{model}.png"));
    let mut input = HeatmapInput::new(scoring, inputs.base.clone(), heat_png.clone());
    (input.walls, input.max_windows) = (Some(walls.to_owned()), sizes.max_windows);
    // Resolved (and checked) before any training: resolve_evaluation.
    input.goal = Some(goal);
    let base: Heatmap = heatmap(&Silent, client, &input).await?;
    // The same maze scored at rest: the reward of staying at each position. Reported beside
    // the paper's heatmap, never instead of it; data whose states are more than a position and
    // its velocities cannot be probed (the refusal is reported).
    let rest_png = out.join(format!("heatmap-at-rest-{model}.png"));
    (input.out, input.probe) = (rest_png.clone(), Probe::AtRest);
    let at_rest = match heatmap(&Silent, client, &input).await {
        Ok(rest) => AtRest::Probed {
            heatmap_at_rest: path_str(&rest_png),
            argmax_cell_at_rest: rest.argmax_cell(),
            distance_cells_at_rest: rest.distance_cells,
            goal_recovered_at_rest: rest.goal_recovered,
        },
        Err(e) if e.downcast_ref::<UsageError>().is_some() => AtRest::Refused { at_rest_refused: e.to_string() },
        Err(e) => return Err(e),
    };
    evaluation.maze = Some(MazeEvaluation {
        heatmap: path_str(&heat_png),
        goal,
        argmax_cell: base.argmax_cell(),
        distance_cells: base.distance_cells,
        goal_recovered: base.goal_recovered,
        at_rest,
    });
    Ok(evaluation)
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    fn evaluation(maze: Option<MazeEvaluation>) -> ModelEvaluation {
        ModelEvaluation {
            kind: "reward",
            model: "r".into(),
            balanced_accuracy: 0.75,
            auc: f64::NAN,
            expert_scores_higher: true,
            histogram: "h.png".into(),
            loss_plot: "l.png".into(),
            maze,
        }
    }

    /// report.json's rows keep the keys they always had: maze measures only with walls, the
    /// at-rest ones or the refusal, a discriminator only when trained; non-numbers as null.
    #[test]
    fn rows_serialize_flat_with_the_keys_of_what_was_measured() {
        let refused = MazeEvaluation {
            heatmap: "m.png".into(),
            goal: (3.0, 3.0),
            argmax_cell: Some((1, 2)),
            distance_cells: Some(0.5),
            goal_recovered: Some(true),
            at_rest: AtRest::Refused { at_rest_refused: "no".into() },
        };
        let row = ExpertResult {
            reward: evaluation(Some(refused)),
            discriminator: Some(evaluation(None)),
            label: "e0".into(),
            expert_data: "e.npz".into(),
            sizes: Sizes::preset(Size::Tiny),
        };
        let v = serde_json::to_value(&row).expect("json");
        assert_eq!((v["argmax_cell"].clone(), v["auc"].clone()), (json!([1, 2]), json!(null)));
        assert_eq!((v["goal_recovered"].clone(), v["at_rest_refused"].clone()), (json!(true), json!("no")));
        assert!(v.get("heatmap_at_rest").is_none() && v.get("maze").is_none() && v.get("at_rest").is_none());
        assert_eq!(v["discriminator"]["balanced_accuracy"], 0.75);
        assert!(v["discriminator"].get("heatmap").is_none());
        assert_eq!((row.goal_recovered(), row.goal_recovered_at_rest()), (Some(true), None));
        let probed = AtRest::Probed {
            heatmap_at_rest: "a.png".into(),
            argmax_cell_at_rest: None,
            distance_cells_at_rest: None,
            goal_recovered_at_rest: Some(false),
        };
        let v = serde_json::to_value(&probed).expect("json");
        assert_eq!(v["argmax_cell_at_rest"], json!(null));
        assert_eq!(v["goal_recovered_at_rest"], json!(false));
        let plain = ExpertResult { discriminator: None, ..row };
        assert!(serde_json::to_value(&plain).expect("json").get("discriminator").is_none());
    }
}
