//! `relreward train diffusion|reward|discriminator` (specs built by [`super::train`]) and
//! `relreward job list|show|cancel|watch` (`job plot` is in [`super::eval`]).
//!
//! `job watch` (and `train ... --watch`) waits on [`relreward_cli::ops::jobs::wait`], shown as
//! [`super::watch`] shows a job: a progress bar and event lines, or JSON lines with `--json`.

use anyhow::Result;
use clap::{Subcommand, ValueEnum};
use relreward_cli::ops::jobs;
use relreward_client::{Client, pb};
use serde_json::{Map, Value, json};

use super::manifest::{architecture_json, manifest_architecture, parametrization_name, schedule_json, schedule_text};
use super::output::{eprint_line, fmt_short, key_values, or_dash, rfc3339, state_name, table, time_or_dash};
use super::train::{
    TrainArgs, TrainDiffusionArgs, TrainDiscriminatorArgs, TrainRewardArgs, diffusion_spec_from_args,
    discriminator_spec_from_args, reward_spec_from_args,
};
use super::watch::{JobView, print_line, state_label};
use super::{Ctx, Report};

#[derive(Debug, Subcommand)]
pub enum TrainCommand {
    /// Train a native diffusion model on a dataset (DDPM loss).
    Diffusion(TrainDiffusionArgs),
    /// Extract a relative reward rho from a base and an expert diffusion model (gradient
    /// alignment; Algorithm 1 on datasets, or Algorithm 2 from the models alone).
    Reward(TrainRewardArgs),
    /// Train the discriminator baseline: base vs expert dataset, binary cross-entropy.
    Discriminator(TrainDiscriminatorArgs),
}

#[derive(Debug, Subcommand)]
pub enum JobCommand {
    /// List jobs, newest first.
    List {
        /// Only jobs in this state.
        #[arg(long, value_enum)]
        state: Option<JobStateArg>,
    },
    /// Show a job: state, progress, loss, error, timestamps and spec.
    Show { id: String },
    /// Cancel a job (it stops at its next step).
    Cancel { id: String },
    /// Follow a job's progress until it finishes (exit 1 unless it succeeds).
    Watch {
        id: String,
        /// First event to show (default: from the first).
        #[arg(long, value_name = "N", default_value_t = 0)]
        from_seq: u64,
    },
    /// Draw a job's loss curve (and held-out loss) from its events as a PNG; optionally a
    /// histogram of a reward over the windows of datasets (see `super::eval`).
    Plot(super::eval::JobPlotArgs),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum JobStateArg {
    Pending,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobStateArg {
    fn to_proto(self) -> pb::JobState {
        match self {
            Self::Pending => pb::JobState::Pending,
            Self::Running => pb::JobState::Running,
            Self::Succeeded => pb::JobState::Succeeded,
            Self::Failed => pb::JobState::Failed,
            Self::Cancelled => pb::JobState::Cancelled,
        }
    }
}

pub async fn run_train(ctx: &Ctx, command: TrainCommand) -> Result<Report> {
    let (spec, job) = match &command {
        TrainCommand::Diffusion(args) => (diffusion_spec_from_args(args)?, &args.job),
        TrainCommand::Reward(args) => (reward_spec_from_args(args)?, &args.job),
        TrainCommand::Discriminator(args) => (discriminator_spec_from_args(args)?, &args.job),
    };
    submit(ctx, spec, job).await
}

pub async fn run(ctx: &Ctx, command: JobCommand) -> Result<Report> {
    match command {
        JobCommand::List { state } => list(ctx, state).await,
        JobCommand::Show { id } => show(ctx, &id).await,
        JobCommand::Cancel { id } => cancel(ctx, &id).await,
        JobCommand::Watch { id, from_seq } => {
            let client = ctx.connect().await?;
            watch(ctx, &client, &id, from_seq).await
        }
        JobCommand::Plot(args) => super::eval::job_plot(ctx, args).await,
    }
}

// ---------------------------------------------------------------------------------------------
// Commands

/// Submits `spec` (under `--job-id`, if given) and, with `--watch`, follows the job.
async fn submit(ctx: &Ctx, spec: pb::JobSpec, args: &TrainArgs) -> Result<Report> {
    let client = ctx.connect().await?;
    let job = client.submit_job(spec, args.job_id.as_deref()).await?;
    if !args.watch {
        let text = format!(
            "submitted job {} ({})\nfollow it with: relreward job watch {}\n",
            job.id,
            state_label(job.state()),
            job.id
        );
        return Ok(Report::ok(text, job_json(&job)));
    }
    let note = format!("submitted job {} ({})", job.id, state_label(job.state()));
    if ctx.json {
        eprint_line(&note);
    } else {
        print_line(&format!("{note}\n"));
    }
    watch(ctx, &client, &job.id, 0).await
}

async fn list(ctx: &Ctx, state: Option<JobStateArg>) -> Result<Report> {
    let state = state.map_or(pb::JobState::Unspecified, JobStateArg::to_proto);
    let jobs = ctx.connect().await?.list_jobs(state).await?;
    Ok(Report::ok(format_job_table(&jobs), Value::Array(jobs.iter().map(job_json).collect())))
}

async fn show(ctx: &Ctx, id: &str) -> Result<Report> {
    let job = ctx.connect().await?.get_job(id).await?;
    Ok(Report::ok(format_job(&job), job_json(&job)))
}

async fn cancel(ctx: &Ctx, id: &str) -> Result<Report> {
    let job = ctx.connect().await?.cancel_job(id).await?;
    let text = if job.state() == pb::JobState::Cancelled {
        format!("cancelled job {id}\n")
    } else {
        format!(
            "asked job {id} to stop; it is {} (watch it with: relreward job watch {id})\n",
            state_label(job.state())
        )
    };
    Ok(Report::ok(text, job_json(&job)))
}

/// Follows job `id` from event `from_seq` until it finishes: exit status 0 if it succeeded, an
/// error with its message (exit status 1) if it failed or was cancelled.
async fn watch(ctx: &Ctx, client: &Client, id: &str, from_seq: u64) -> Result<Report> {
    jobs::wait(&JobView::new(ctx.json, true), client, id, from_seq).await?;
    Ok(Report::streamed(format!("job {id} {}\n", state_label(pb::JobState::Succeeded))))
}

// ---------------------------------------------------------------------------------------------
// Output: JSON

/// A job as JSON:
///
/// ```json
/// {"id": "..", "state": "pending" | "running" | "succeeded" | "failed" | "cancelled",
///  "step": N, "total_steps": N, "loss": X | null, "error": "..",
///  "created_at": "RFC3339" | null, "started_at": .. | null, "finished_at": .. | null,
///  "last_seq": N, "spec": {see spec_json} | null}
/// ```
pub fn job_json(j: &pb::Job) -> Value {
    json!({
        "id": j.id,
        "state": state_name(j.state()),
        "step": j.step,
        "total_steps": j.total_steps,
        "loss": j.loss,
        "error": j.error,
        "created_at": j.created_at.as_ref().map(rfc3339),
        "started_at": j.started_at.as_ref().map(rfc3339),
        "finished_at": j.finished_at.as_ref().map(rfc3339),
        "last_seq": j.last_seq,
        "spec": j.spec.as_ref().map(spec_json),
    })
}

/// A job spec with the fields of the train config file: `output_model`, `seed` (null: server
/// default), `kind` ("diffusion" | "reward" | "discriminator" | null), `optimization` (every
/// field, null when unset), and an object under the kind's name with its fields.
pub fn spec_json(s: &pb::JobSpec) -> Value {
    use pb::job_spec::Kind;
    let o = s.optimization.unwrap_or_default();
    let mut out = Map::new();
    out.insert("output_model".into(), json!(s.output_model));
    out.insert("seed".into(), json!(s.seed));
    out.insert(
        "optimization".into(),
        json!({
            "steps": o.steps,
            "batch_size": o.batch_size,
            "learning_rate": o.learning_rate,
            "grad_clip": o.grad_clip,
            "ema_decay": o.ema_decay,
            "ema_every": o.ema_every,
            "ema_start": o.ema_start,
            "checkpoint_every": o.checkpoint_every,
            "eval_every": o.eval_every,
            "log_every": o.log_every,
        }),
    );
    let (kind, body) = match &s.kind {
        Some(Kind::Diffusion(d)) => ("diffusion", diffusion_json(d)),
        Some(Kind::Reward(r)) => ("reward", reward_json(r)),
        Some(Kind::Discriminator(d)) => ("discriminator", discriminator_json(d)),
        None => {
            out.insert("kind".into(), Value::Null);
            return Value::Object(out);
        }
    };
    out.insert("kind".into(), json!(kind));
    out.insert(kind.into(), body);
    Value::Object(out)
}

fn diffusion_json(d: &pb::TrainDiffusion) -> Value {
    json!({
        "dataset": d.dataset,
        "parametrization": parametrization_name(d.parametrization()),
        "schedule": schedule_json(d.schedule.as_ref()),
        "n_timesteps": d.n_timesteps,
        "horizon": d.horizon,
        "architecture": d.architecture.as_ref().map_or(Value::Null, |a| architecture_json(&manifest_architecture(a))),
        "action_weight": d.action_weight,
        "clip_denoised": d.clip_denoised,
        "pooled_normalizer": d.pooled_normalizer,
        "conditional": d.conditional,
        "condition_dropout": d.condition_dropout,
        "num_classes": d.num_classes,
    })
}

/// A sampling recipe in its stored (schema) form, or as the wire gave it when it does not parse.
fn recipe_json(r: &pb::SamplingRecipe) -> Value {
    relreward_proto::schema::recipe::RecipeSpec::from_proto(r, "recipe")
        .ok()
        .and_then(|spec| serde_json::to_value(spec).ok())
        .unwrap_or(Value::Null)
}

fn reward_architecture_json(a: Option<&pb::RewardArchitecture>) -> Value {
    use pb::reward_architecture::Kind;
    match a.and_then(|a| a.kind.as_ref()) {
        Some(Kind::WindowedMlp(w)) => json!({ "kind": "windowed_mlp", "window": w.window, "hidden": w.hidden }),
        Some(Kind::ValueFunction(v)) => json!({ "kind": "value_function", "widths": v.widths }),
        Some(Kind::ConvEncoder(c)) => json!({ "kind": "conv_encoder", "widths": c.widths }),
        Some(Kind::Mlp(m)) => json!({ "kind": "mlp", "hidden": m.hidden }),
        None => Value::Null,
    }
}

fn reward_json(r: &pb::TrainReward) -> Value {
    use pb::train_reward::Algorithm;
    json!({
        "base_model": r.base_model,
        "expert_model": r.expert_model,
        "architecture": reward_architecture_json(r.architecture.as_ref()),
        "target": match r.target() {
            pb::RewardTarget::Mean => json!("mean"),
            pb::RewardTarget::Score => json!("score"),
            pb::RewardTarget::Unspecified => Value::Null,
        },
        "eval_point": match r.eval_point() {
            pb::EvalPoint::XT => json!("x_t"),
            pb::EvalPoint::MuBase => json!("mu_base"),
            pb::EvalPoint::Unspecified => Value::Null,
        },
        "algorithm": match &r.algorithm {
            Some(Algorithm::WithDataset(w)) => json!({ "kind": "with_dataset", "datasets": w.datasets }),
            Some(Algorithm::ModelsOnly(m)) => json!({ "kind": "models_only", "num_chains": m.num_chains }),
            None => Value::Null,
        },
        "rho_l2": r.rho_l2,
        "action_weight": r.action_weight,
        "condition_weight": r.condition_weight,
        "inpaint_condition": r.inpaint_condition,
        "base_recipe": r.base_recipe.as_ref().map(recipe_json),
        "expert_recipe": r.expert_recipe.as_ref().map(recipe_json),
        "amortised_targets": r.amortised_targets.as_ref().map(|a| json!({
            "pool_size": a.pool_size, "reuse": a.reuse, "refresh_fraction": a.refresh_fraction
        })),
    })
}

fn discriminator_json(d: &pb::TrainDiscriminator) -> Value {
    json!({
        "base_dataset": d.base_dataset,
        "expert_dataset": d.expert_dataset,
        "architecture": reward_architecture_json(d.architecture.as_ref()),
        "diffusion_model": d.diffusion_model,
        "inpaint_condition": d.inpaint_condition,
    })
}

// ---------------------------------------------------------------------------------------------
// Output: text

/// What a spec asks for in one line: `diffusion on maze -> maze-expert; steps 1000, batch 32,
/// lr 0.0002, horizon 32, T 20, seed 3` (unset values are left out: server defaults).
fn spec_summary(s: &pb::JobSpec) -> String {
    use pb::job_spec::Kind;
    let what = match &s.kind {
        Some(Kind::Diffusion(d)) => format!("diffusion on {} -> {}", d.dataset, s.output_model),
        Some(Kind::Reward(r)) => format!("reward from {} vs {} -> {}", r.base_model, r.expert_model, s.output_model),
        Some(Kind::Discriminator(d)) => {
            format!("discriminator {} vs {} -> {}", d.base_dataset, d.expert_dataset, s.output_model)
        }
        None => format!("? -> {}", s.output_model),
    };
    let mut settings = Vec::new();
    if let Some(o) = &s.optimization {
        if let Some(v) = o.steps {
            settings.push(format!("steps {v}"));
        }
        if let Some(v) = o.batch_size {
            settings.push(format!("batch {v}"));
        }
        if let Some(v) = o.learning_rate {
            settings.push(format!("lr {v}"));
        }
    }
    if let Some(Kind::Diffusion(d)) = &s.kind {
        if let Some(p) = parametrization_name(d.parametrization()) {
            settings.push(p.to_owned());
        }
        if d.schedule.is_some() {
            settings.push(format!("schedule {}", schedule_text(d.schedule.as_ref())));
        }
        if let Some(v) = d.horizon {
            settings.push(format!("horizon {v}"));
        }
        if let Some(v) = d.n_timesteps {
            settings.push(format!("T {v}"));
        }
    }
    if let Some(v) = s.seed {
        settings.push(format!("seed {v}"));
    }
    if settings.is_empty() { what } else { format!("{what}; {}", settings.join(", ")) }
}

fn step_text(j: &pb::Job) -> String {
    if j.total_steps == 0 {
        return j.step.to_string();
    }
    format!("{}/{} ({:.1}%)", j.step, j.total_steps, 100.0 * j.step as f64 / j.total_steps as f64)
}

fn loss_text(loss: f64) -> String {
    if loss.is_nan() { "-".to_owned() } else { fmt_short(loss) }
}

/// `job show`.
fn format_job(j: &pb::Job) -> String {
    let fields = [
        ("id", j.id.clone()),
        ("state", state_label(j.state())),
        ("step", step_text(j)),
        ("loss", loss_text(j.loss)),
        ("error", or_dash(&j.error)),
        ("created", time_or_dash(j.created_at.as_ref())),
        ("started", time_or_dash(j.started_at.as_ref())),
        ("finished", time_or_dash(j.finished_at.as_ref())),
        ("events", j.last_seq.to_string()),
        ("spec", j.spec.as_ref().map_or_else(|| "-".to_owned(), spec_summary)),
    ];
    key_values(&fields, 0)
}

/// `job list`: one job per row.
fn format_job_table(jobs: &[pb::Job]) -> String {
    use pb::job_spec::Kind;
    if jobs.is_empty() {
        return "no jobs\n".to_owned();
    }
    let rows = jobs
        .iter()
        .map(|j| {
            let kind = match j.spec.as_ref().and_then(|s| s.kind.as_ref()) {
                Some(Kind::Diffusion(_)) => "diffusion",
                Some(Kind::Reward(_)) => "reward",
                Some(Kind::Discriminator(_)) => "discriminator",
                None => "-",
            };
            vec![
                j.id.clone(),
                state_label(j.state()),
                kind.to_owned(),
                j.spec.as_ref().map_or_else(|| "-".to_owned(), |s| or_dash(&s.output_model)),
                if j.total_steps == 0 { j.step.to_string() } else { format!("{}/{}", j.step, j.total_steps) },
                loss_text(j.loss),
                time_or_dash(j.created_at.as_ref()),
            ]
        })
        .collect();
    table(
        &["ID", "STATE", "KIND", "OUTPUT", "STEP", "LOSS", "CREATED"],
        &[false, false, false, false, true, true, false],
        rows,
        0,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ts(seconds: i64) -> Option<prost_types::Timestamp> {
        Some(prost_types::Timestamp { seconds, nanos: 250_000_000 })
    }

    fn job() -> pb::Job {
        pb::Job {
            id: "j1".into(),
            spec: Some(pb::JobSpec {
                output_model: "maze-expert".into(),
                seed: Some(3),
                optimization: Some(pb::Optimization {
                    steps: Some(1000),
                    batch_size: Some(32),
                    learning_rate: Some(2e-4),
                    ..Default::default()
                }),
                kind: Some(pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
                    dataset: "maze".into(),
                    parametrization: pb::Parametrization::X0 as i32,
                    horizon: Some(32),
                    n_timesteps: Some(20),
                    architecture: Some(pb::train_diffusion::Architecture::TemporalUnet(pb::TemporalUnet {
                        dim: Some(32),
                        dim_mults: vec![1, 2, 4, 8],
                    })),
                    ..Default::default()
                })),
            }),
            state: pb::JobState::Running as i32,
            step: 250,
            total_steps: 1000,
            loss: 0.0123,
            error: String::new(),
            created_at: ts(1_714_564_800),
            started_at: ts(1_714_564_801),
            finished_at: None,
            last_seq: 27,
        }
    }

    #[test]
    fn job_json_has_the_documented_shape() {
        let v = job_json(&job());
        assert_eq!(v["id"], "j1");
        assert_eq!(v["state"], "running");
        assert_eq!((v["step"].clone(), v["total_steps"].clone()), (json!(250), json!(1000)));
        assert_eq!(v["loss"], 0.0123);
        assert_eq!(v["created_at"], "2024-05-01T12:00:00Z");
        assert!(v["finished_at"].is_null());
        assert_eq!(v["last_seq"], 27);
        let spec = &v["spec"];
        assert_eq!(spec["output_model"], "maze-expert");
        assert_eq!(spec["seed"], 3);
        assert_eq!(spec["kind"], "diffusion");
        assert_eq!(spec["optimization"]["steps"], 1000);
        assert!(spec["optimization"]["grad_clip"].is_null());
        assert_eq!(spec["diffusion"]["dataset"], "maze");
        assert_eq!(spec["diffusion"]["parametrization"], "x0");
        assert!(spec["diffusion"]["schedule"].is_null());
        assert_eq!(
            spec["diffusion"]["architecture"],
            json!({"kind": "temporal_unet", "dim": 32, "dim_mults": [1, 2, 4, 8]})
        );
        assert_eq!(v.as_object().expect("object").len(), 11);

        let mut fresh = job();
        fresh.loss = f64::NAN;
        fresh.spec = None;
        let v = job_json(&fresh);
        assert!(v["loss"].is_null() && v["spec"].is_null());
    }

    #[test]
    fn reward_and_discriminator_specs_have_json_too() {
        let spec = pb::JobSpec {
            output_model: "r".into(),
            kind: Some(pb::job_spec::Kind::Reward(pb::TrainReward {
                base_model: "b".into(),
                expert_model: "e".into(),
                architecture: Some(pb::RewardArchitecture {
                    kind: Some(pb::reward_architecture::Kind::WindowedMlp(pb::reward_architecture::WindowedMlp {
                        window: Some(4),
                        hidden: vec![128, 64],
                    })),
                }),
                target: pb::RewardTarget::Score as i32,
                algorithm: Some(pb::train_reward::Algorithm::ModelsOnly(pb::train_reward::ModelsOnly {
                    num_chains: Some(8),
                })),
                ..Default::default()
            })),
            ..Default::default()
        };
        let v = spec_json(&spec);
        assert_eq!(v["kind"], "reward");
        assert_eq!(v["reward"]["architecture"], json!({"kind": "windowed_mlp", "window": 4, "hidden": [128, 64]}));
        assert_eq!(v["reward"]["target"], "score");
        assert!(v["reward"]["eval_point"].is_null());
        assert_eq!(v["reward"]["algorithm"], json!({"kind": "models_only", "num_chains": 8}));
        let spec = pb::JobSpec {
            kind: Some(pb::job_spec::Kind::Discriminator(pb::TrainDiscriminator {
                base_dataset: "a".into(),
                expert_dataset: "b".into(),
                ..Default::default()
            })),
            ..Default::default()
        };
        let v = spec_json(&spec);
        assert_eq!(
            (v["kind"].clone(), v["discriminator"]["expert_dataset"].clone()),
            (json!("discriminator"), json!("b"))
        );
        assert!(spec_json(&pb::JobSpec::default())["kind"].is_null());
    }

    #[test]
    fn text_output() {
        let text = format_job(&job());
        for needle in [
            "state     RUNNING",
            "step      250/1000 (25.0%)",
            "loss      0.01230",
            "error     -",
            "finished  -",
            "events    27",
            "diffusion on maze -> maze-expert; steps 1000, batch 32, lr 0.0002, x0, horizon 32, T 20, seed 3",
        ] {
            assert!(text.contains(needle), "missing {needle:?} in\n{text}");
        }
        let list = format_job_table(&[job()]);
        assert!(list.starts_with("ID"), "{list}");
        assert!(list.contains("j1  RUNNING  diffusion  maze-expert  250/1000"), "{list}");
        assert_eq!(format_job_table(&[]), "no jobs\n");
    }
}
