//! `relreward.v1.JobService`: submit, get, list, cancel and watch training jobs.
//!
//! Converts the proto `JobSpec` into the stored, fully explicit `jobs::spec::JobSpec`, filling
//! every unset field with its documented default (jobs.proto), so a job's meaning never
//! depends on a later change of defaults.

use std::pin::Pin;

use futures::{Stream, StreamExt};
use relreward_proto::v1::{self as pb, job_service_server::JobService};
use tonic::{Request, Response, Status};

use super::{convert, page_limit, timestamp};
use crate::engine::manifest::{Architecture, DiffusionManifest, Parametrization, ScheduleSpec, Space};
use crate::engine::nets::reward::RewardArchitecture;
use crate::engine::relative_reward::{EvalPoint, Target};
use crate::engine::target_pool::AmortisedTargets;
use crate::error::Error;
use crate::fields::{self, validate_name, validate_names};
use crate::jobs::JobManager;
use crate::jobs::reward;
use crate::jobs::spec::{DiffusionJob, DiscriminatorJob, JobKind, JobSpec, Optimization, RewardAlgorithm, RewardJob};
use crate::store::{DatasetKind, JobEvent, JobEventKind, JobRecord, JobState, Store};

pub struct Jobs {
    store: Store,
    jobs: JobManager,
}

impl Jobs {
    pub fn new(store: Store, jobs: JobManager) -> Self {
        Self { store, jobs }
    }

    /// proto -> stored spec, with defaults. Needs the dataset's kind to pick the default
    /// architecture.
    async fn spec_from_proto(&self, spec: pb::JobSpec) -> Result<JobSpec, Error> {
        validate_spec_names(&spec)?;
        let kind =
            spec.kind.ok_or_else(|| Error::invalid("spec.kind: none of diffusion, reward or discriminator is set"))?;
        let o = spec.optimization.unwrap_or_default();
        match kind {
            pb::job_spec::Kind::Diffusion(d) => {
                let dataset = self.store.meta.get_dataset(&d.dataset).await?.ok_or_else(|| {
                    Error::NotFound(format!("spec.diffusion.dataset: dataset '{}' not found", d.dataset))
                })?;
                let architecture = match d.architecture {
                    Some(pb::train_diffusion::Architecture::TemporalUnet(u)) => convert::temporal_unet_from_proto(u),
                    Some(pb::train_diffusion::Architecture::Mlp(m)) => convert::mlp_from_proto(m),
                    Some(pb::train_diffusion::Architecture::Unet2d(u)) => convert::unet2d_from_proto(u),
                    None => match dataset.kind {
                        DatasetKind::Trajectories => {
                            Architecture::TemporalUnet { dim: 32, dim_mults: vec![1, 2, 4, 8] }
                        }
                        DatasetKind::Samples => Architecture::Mlp { hidden: vec![256, 256] },
                    },
                };
                // Checked here, where "unset" is still visible: the stored spec holds the
                // effective horizon (32 when unset), as resubmissions compare against it.
                if let (DatasetKind::Samples, Some(h)) = (dataset.kind, d.horizon) {
                    return Err(Error::invalid(format!(
                        "spec.diffusion.horizon: {h} applies to trajectories only (the sub-trajectory length); '{}' holds samples of a fixed shape",
                        dataset.name
                    )));
                }
                let job = DiffusionJob {
                    dataset: d.dataset,
                    // Unset: x0-prediction and Diffuser's cosine schedule, as Diffuser's configs.
                    parametrization: if d.parametrization == pb::Parametrization::Unspecified as i32 {
                        Parametrization::X0
                    } else {
                        convert::parametrization_from_proto(d.parametrization, "spec.diffusion.parametrization")?
                    },
                    schedule: match d.schedule {
                        None => ScheduleSpec::DiffuserCosine { s: 0.008 },
                        some => convert::schedule_from_proto(some, "spec.diffusion.schedule")?,
                    },
                    n_timesteps: d.n_timesteps.unwrap_or(20) as usize,
                    horizon: d.horizon.unwrap_or(32) as usize,
                    architecture,
                    action_weight: d.action_weight.unwrap_or(1.0),
                    clip_denoised: d.clip_denoised.unwrap_or(true),
                    normalizer_datasets: d.normalizer_datasets,
                    pooled_normalizer: d.pooled_normalizer.unwrap_or(false),
                };
                Ok(JobSpec {
                    output_model: spec.output_model,
                    seed: spec.seed.unwrap_or(0),
                    // Diffuser's configs: batch 32, learning rate 2e-4.
                    optimization: optimization(&o, 10_000, 32, 2e-4),
                    kind: JobKind::Diffusion(job),
                })
            }
            pb::job_spec::Kind::Reward(r) => {
                let base = self.store.meta.get_model(&r.base_model).await?.ok_or_else(|| {
                    Error::NotFound(format!("spec.reward.base_model: model '{}' not found", r.base_model))
                })?;
                let space: Space = serde_json::from_value::<DiffusionManifest>(base.manifest)
                    .map_err(|_| {
                        Error::invalid(format!("spec.reward.base_model: '{}' is not a diffusion model", r.base_model))
                    })?
                    .space;
                let architecture = reward_architecture(r.architecture, &space);
                let target =
                    match fields::known("spec.reward.target", r.target, "REWARD_TARGET_MEAN or REWARD_TARGET_SCORE")? {
                        pb::RewardTarget::Unspecified | pb::RewardTarget::Mean => Target::Mean,
                        pb::RewardTarget::Score => Target::Score,
                    };
                let eval_point = match fields::known(
                    "spec.reward.eval_point",
                    r.eval_point,
                    "EVAL_POINT_X_T or EVAL_POINT_MU_BASE",
                )? {
                    pb::EvalPoint::Unspecified | pb::EvalPoint::XT => EvalPoint::XT,
                    pb::EvalPoint::MuBase => EvalPoint::MuBase,
                };
                let algorithm = match r.algorithm {
                    Some(pb::train_reward::Algorithm::WithDataset(w)) => {
                        RewardAlgorithm::WithDataset { datasets: w.datasets }
                    }
                    Some(pb::train_reward::Algorithm::ModelsOnly(m)) => {
                        RewardAlgorithm::ModelsOnly { num_chains: m.num_chains.unwrap_or(1024) as usize }
                    }
                    None => {
                        return Err(Error::invalid(
                            "spec.reward.algorithm: set with_dataset (Algorithm 1) or models_only (Algorithm 2)",
                        ));
                    }
                };
                Ok(JobSpec {
                    output_model: spec.output_model,
                    seed: spec.seed.unwrap_or(0),
                    // The paper's maze reward nets: 100k steps, batch 256, learning rate 5e-5.
                    optimization: optimization(&o, 100_000, 256, 5e-5),
                    kind: JobKind::Reward(RewardJob {
                        base_model: r.base_model,
                        expert_model: r.expert_model,
                        architecture,
                        target,
                        eval_point,
                        algorithm,
                        rho_l2: r.rho_l2.unwrap_or(0.0),
                        action_weight: r.action_weight.unwrap_or(1.0),
                        condition_weight: r.condition_weight.unwrap_or(1.0),
                        inpaint_condition: r.inpaint_condition.unwrap_or(false),
                        amortised_targets: r.amortised_targets.map(|a| {
                            let d = AmortisedTargets::DEFAULT;
                            AmortisedTargets {
                                pool_size: a.pool_size.map_or(d.pool_size, |v| v as usize),
                                reuse: a.reuse.unwrap_or(d.reuse),
                                refresh_fraction: a.refresh_fraction.unwrap_or(d.refresh_fraction),
                            }
                        }),
                    }),
                })
            }
            pb::job_spec::Kind::Discriminator(d) => {
                let model = self.store.meta.get_model(&d.diffusion_model).await?.ok_or_else(|| {
                    Error::NotFound(format!(
                        "spec.discriminator.diffusion_model: model '{}' not found",
                        d.diffusion_model
                    ))
                })?;
                let space: Space = serde_json::from_value::<DiffusionManifest>(model.manifest)
                    .map_err(|_| {
                        Error::invalid(format!(
                            "spec.discriminator.diffusion_model: '{}' is not a diffusion model",
                            d.diffusion_model
                        ))
                    })?
                    .space;
                Ok(JobSpec {
                    output_model: spec.output_model,
                    seed: spec.seed.unwrap_or(0),
                    // The same settings as the reward it is compared with.
                    optimization: optimization(&o, 100_000, 256, 5e-5),
                    kind: JobKind::Discriminator(DiscriminatorJob {
                        base_dataset: d.base_dataset,
                        expert_dataset: d.expert_dataset,
                        architecture: reward_architecture(d.architecture, &space),
                        diffusion_model: d.diffusion_model,
                        inpaint_condition: d.inpaint_condition.unwrap_or(false),
                    }),
                })
            }
        }
    }
}

/// Every name a spec refers to, checked by the name rule before any lookup (a malformed name
/// is INVALID_ARGUMENT, never NOT_FOUND).
fn validate_spec_names(spec: &pb::JobSpec) -> Result<(), Error> {
    use pb::job_spec::Kind;
    validate_name("spec.output_model", &spec.output_model)?;
    match &spec.kind {
        None => Ok(()),
        Some(Kind::Diffusion(d)) => {
            validate_name("spec.diffusion.dataset", &d.dataset)?;
            validate_names("spec.diffusion.normalizer_datasets", &d.normalizer_datasets)
        }
        Some(Kind::Reward(r)) => {
            validate_name("spec.reward.base_model", &r.base_model)?;
            validate_name("spec.reward.expert_model", &r.expert_model)?;
            match &r.algorithm {
                Some(pb::train_reward::Algorithm::WithDataset(w)) => {
                    validate_names("spec.reward.with_dataset.datasets", &w.datasets)
                }
                _ => Ok(()),
            }
        }
        Some(Kind::Discriminator(d)) => {
            validate_name("spec.discriminator.base_dataset", &d.base_dataset)?;
            validate_name("spec.discriminator.expert_dataset", &d.expert_dataset)?;
            validate_name("spec.discriminator.diffusion_model", &d.diffusion_model)
        }
    }
}

/// The reward network from the wire; unset: the paper's default for the models' space, unset
/// widths: the paper's widths for that kind.
fn reward_architecture(a: Option<pb::RewardArchitecture>, space: &Space) -> RewardArchitecture {
    match a.and_then(|a| a.kind) {
        None => reward::default_architecture(space),
        Some(pb::reward_architecture::Kind::WindowedMlp(w)) => RewardArchitecture::WindowedMlp {
            window: w.window.unwrap_or(4) as usize,
            hidden: if w.hidden.is_empty() { vec![128, 64, 32] } else { to_usize(&w.hidden) },
        },
        Some(pb::reward_architecture::Kind::ValueFunction(v)) => RewardArchitecture::ValueFunction {
            widths: if v.widths.is_empty() { vec![64, 64, 128, 128] } else { to_usize(&v.widths) },
        },
        Some(pb::reward_architecture::Kind::ConvEncoder(c)) => RewardArchitecture::ConvEncoder {
            widths: if c.widths.is_empty() { vec![32, 64, 128, 256] } else { to_usize(&c.widths) },
        },
        Some(pb::reward_architecture::Kind::Mlp(m)) => RewardArchitecture::Mlp {
            hidden: if m.hidden.is_empty() { vec![128, 64, 32] } else { to_usize(&m.hidden) },
        },
    }
}

fn reward_architecture_to_proto(a: &RewardArchitecture) -> pb::RewardArchitecture {
    use pb::reward_architecture::{ConvEncoder, Kind, ValueFunction, WindowedMlp};
    let kind = match a {
        RewardArchitecture::WindowedMlp { window, hidden } => {
            Kind::WindowedMlp(WindowedMlp { window: Some(*window as u32), hidden: to_u32(hidden) })
        }
        RewardArchitecture::ValueFunction { widths } => Kind::ValueFunction(ValueFunction { widths: to_u32(widths) }),
        RewardArchitecture::ConvEncoder { widths } => Kind::ConvEncoder(ConvEncoder { widths: to_u32(widths) }),
        RewardArchitecture::Mlp { hidden } => Kind::Mlp(pb::Mlp { hidden: to_u32(hidden) }),
    };
    pb::RewardArchitecture { kind: Some(kind) }
}

fn to_usize(v: &[u32]) -> Vec<usize> {
    v.iter().map(|&x| x as usize).collect()
}

fn to_u32(v: &[usize]) -> Vec<u32> {
    v.iter().map(|&x| x as u32).collect()
}

/// Shared optimisation settings with a job kind's defaults for steps, batch size and learning
/// rate; the rest default as Diffuser's trainer (EMA 0.995 every 10 steps from step 2000).
fn optimization(o: &pb::Optimization, steps: u64, batch_size: u32, learning_rate: f64) -> Optimization {
    Optimization {
        steps: o.steps.unwrap_or(steps),
        batch_size: o.batch_size.unwrap_or(batch_size) as usize,
        learning_rate: o.learning_rate.unwrap_or(learning_rate),
        grad_clip: o.grad_clip,
        ema_decay: o.ema_decay.unwrap_or(0.995),
        ema_every: u64::from(o.ema_every.unwrap_or(10)),
        ema_start: o.ema_start.unwrap_or(2000),
        checkpoint_every: o.checkpoint_every.unwrap_or(1000),
        eval_every: o.eval_every.unwrap_or(500),
        log_every: o.log_every.unwrap_or(10),
    }
}

fn state_to_proto(s: JobState) -> pb::JobState {
    match s {
        JobState::Pending => pb::JobState::Pending,
        JobState::Running => pb::JobState::Running,
        JobState::Succeeded => pb::JobState::Succeeded,
        JobState::Failed => pb::JobState::Failed,
        JobState::Cancelled => pb::JobState::Cancelled,
    }
}

/// The stored spec back on the wire, with every default made explicit.
fn spec_to_proto(spec: &JobSpec) -> pb::JobSpec {
    let o = &spec.optimization;
    let kind = match &spec.kind {
        JobKind::Diffusion(d) => pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
            dataset: d.dataset.clone(),
            parametrization: convert::parametrization_to_proto(d.parametrization) as i32,
            schedule: Some(convert::schedule_to_proto(&d.schedule)),
            n_timesteps: Some(d.n_timesteps as u32),
            horizon: Some(d.horizon as u32),
            architecture: Some(match convert::architecture_to_proto(&d.architecture) {
                pb::diffusion_manifest::Architecture::TemporalUnet(u) => {
                    pb::train_diffusion::Architecture::TemporalUnet(u)
                }
                pb::diffusion_manifest::Architecture::Mlp(m) => pb::train_diffusion::Architecture::Mlp(m),
                pb::diffusion_manifest::Architecture::Unet2d(u) => pb::train_diffusion::Architecture::Unet2d(u),
            }),
            action_weight: Some(d.action_weight),
            clip_denoised: Some(d.clip_denoised),
            normalizer_datasets: d.normalizer_datasets.clone(),
            pooled_normalizer: Some(d.pooled_normalizer),
        }),
        JobKind::Reward(r) => pb::job_spec::Kind::Reward(pb::TrainReward {
            base_model: r.base_model.clone(),
            expert_model: r.expert_model.clone(),
            architecture: Some(reward_architecture_to_proto(&r.architecture)),
            target: match r.target {
                Target::Mean => pb::RewardTarget::Mean,
                Target::Score => pb::RewardTarget::Score,
            } as i32,
            eval_point: match r.eval_point {
                EvalPoint::XT => pb::EvalPoint::XT,
                EvalPoint::MuBase => pb::EvalPoint::MuBase,
            } as i32,
            algorithm: Some(match &r.algorithm {
                RewardAlgorithm::WithDataset { datasets } => {
                    pb::train_reward::Algorithm::WithDataset(pb::train_reward::WithDataset {
                        datasets: datasets.clone(),
                    })
                }
                RewardAlgorithm::ModelsOnly { num_chains } => {
                    pb::train_reward::Algorithm::ModelsOnly(pb::train_reward::ModelsOnly {
                        num_chains: Some(*num_chains as u32),
                    })
                }
            }),
            rho_l2: Some(r.rho_l2),
            action_weight: Some(r.action_weight),
            condition_weight: Some(r.condition_weight),
            inpaint_condition: Some(r.inpaint_condition),
            amortised_targets: r.amortised_targets.map(|a| pb::AmortisedTargets {
                pool_size: Some(a.pool_size as u32),
                reuse: Some(a.reuse),
                refresh_fraction: Some(a.refresh_fraction),
            }),
        }),
        JobKind::Discriminator(d) => pb::job_spec::Kind::Discriminator(pb::TrainDiscriminator {
            base_dataset: d.base_dataset.clone(),
            expert_dataset: d.expert_dataset.clone(),
            architecture: Some(reward_architecture_to_proto(&d.architecture)),
            diffusion_model: d.diffusion_model.clone(),
            inpaint_condition: Some(d.inpaint_condition),
        }),
    };
    pb::JobSpec {
        output_model: spec.output_model.clone(),
        seed: Some(spec.seed),
        optimization: Some(pb::Optimization {
            steps: Some(o.steps),
            batch_size: Some(o.batch_size as u32),
            learning_rate: Some(o.learning_rate),
            grad_clip: o.grad_clip,
            ema_decay: Some(o.ema_decay),
            ema_every: Some(o.ema_every as u32),
            ema_start: Some(o.ema_start),
            checkpoint_every: Some(o.checkpoint_every),
            eval_every: Some(o.eval_every),
            log_every: Some(o.log_every),
        }),
        kind: Some(kind),
    }
}

fn job_to_proto(r: &JobRecord) -> pb::Job {
    let spec = serde_json::from_value::<JobSpec>(r.spec.clone()).ok().map(|s| spec_to_proto(&s));
    pb::Job {
        id: r.id.clone(),
        spec,
        state: state_to_proto(r.state) as i32,
        step: r.step,
        total_steps: r.total_steps,
        loss: r.loss.unwrap_or(f64::NAN),
        error: r.error.clone(),
        created_at: Some(timestamp(r.created_at_ms)),
        started_at: r.started_at_ms.map(timestamp),
        finished_at: r.finished_at_ms.map(timestamp),
        last_seq: r.last_seq,
    }
}

fn event_to_proto(e: JobEvent) -> pb::JobEvent {
    use pb::job_event::{Checkpoint, Event, LogLine, Progress, StateChange};
    let event = match e.event {
        JobEventKind::State { state, message } => {
            Event::State(StateChange { state: state_to_proto(state) as i32, message })
        }
        JobEventKind::Progress {
            step,
            total_steps,
            loss,
            grad_norm,
            learning_rate,
            steps_per_second,
            eta_seconds,
            eval_loss,
        } => Event::Progress(Progress {
            step,
            total_steps,
            loss,
            grad_norm,
            learning_rate,
            steps_per_second,
            eta_seconds,
            eval_loss,
        }),
        JobEventKind::Checkpoint { step } => Event::Checkpoint(Checkpoint { step }),
        JobEventKind::Log { message } => Event::Log(LogLine { message }),
    };
    pb::JobEvent { seq: e.seq, time: Some(timestamp(e.time_ms)), event: Some(event) }
}

type EventStream = Pin<Box<dyn Stream<Item = Result<pb::JobEvent, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl JobService for Jobs {
    type WatchJobStream = EventStream;

    async fn submit_job(&self, request: Request<pb::SubmitJobRequest>) -> Result<Response<pb::Job>, Status> {
        let req = request.into_inner();
        if !req.job_id.is_empty() {
            validate_name("job_id", &req.job_id)?;
        }
        let spec = req.spec.ok_or_else(|| Error::invalid("spec: missing"))?;
        let spec = self.spec_from_proto(spec).await?;
        let id = (!req.job_id.is_empty()).then_some(req.job_id);
        let record = self.jobs.submit(id, spec).await?;
        Ok(Response::new(job_to_proto(&record)))
    }

    async fn get_job(&self, request: Request<pb::GetJobRequest>) -> Result<Response<pb::Job>, Status> {
        Ok(Response::new(job_to_proto(&self.jobs.get(&request.into_inner().id).await?)))
    }

    async fn list_jobs(&self, request: Request<pb::ListJobsRequest>) -> Result<Response<pb::ListJobsResponse>, Status> {
        let req = request.into_inner();
        let page = req.page.unwrap_or_default();
        let limit = page_limit(page.page_size);
        let after = fields::position_page_token(&page.page_token, "ListJobs")?;
        let states = "JOB_STATE_UNSPECIFIED (any), JOB_STATE_PENDING, _RUNNING, _SUCCEEDED, _FAILED or _CANCELLED";
        let state = match fields::known("state", req.state, states)? {
            pb::JobState::Unspecified => None,
            pb::JobState::Pending => Some(JobState::Pending),
            pb::JobState::Running => Some(JobState::Running),
            pb::JobState::Succeeded => Some(JobState::Succeeded),
            pb::JobState::Failed => Some(JobState::Failed),
            pb::JobState::Cancelled => Some(JobState::Cancelled),
        };
        let mut rows = self.jobs.list(state, after, limit + 1).await?;
        let next_page_token = if rows.len() > limit {
            rows.truncate(limit);
            rows.last().map(|(pos, _)| pos.to_string()).unwrap_or_default()
        } else {
            String::new()
        };
        let jobs = rows.iter().map(|(_, r)| job_to_proto(r)).collect();
        Ok(Response::new(pb::ListJobsResponse { jobs, next_page_token }))
    }

    async fn cancel_job(&self, request: Request<pb::CancelJobRequest>) -> Result<Response<pb::Job>, Status> {
        Ok(Response::new(job_to_proto(&self.jobs.cancel(&request.into_inner().id).await?)))
    }

    async fn watch_job(&self, request: Request<pb::WatchJobRequest>) -> Result<Response<Self::WatchJobStream>, Status> {
        let req = request.into_inner();
        let events = self.jobs.watch(&req.id, req.from_seq).await?;
        let stream = events.map(|e| e.map(event_to_proto).map_err(Status::from));
        Ok(Response::new(Box::pin(stream)))
    }
}
