//! `relreward.v1.JobService`: submit, get, list, cancel and watch training jobs.
//!
//! Converts the proto `JobSpec` into the stored, fully explicit `JobSpec` of the shared schema
//! (`relreward_proto::schema::job`, where every default is stated once), after looking up what
//! those defaults depend on, so a job's meaning never depends on a later change of defaults.

use std::pin::Pin;

use futures::{Stream, StreamExt};
use relreward_proto::v1::{self as pb, job_service_server::JobService};
use tonic::{Request, Response, Status};

use relreward_proto::schema::job::{Facts, JobSpec};

use super::{page_limit, timestamp};
use crate::engine::manifest::{DiffusionManifest, Space};
use crate::error::Error;
use crate::fields::{self, validate_name, validate_names};
use crate::jobs::JobManager;
use crate::store::{DatasetKind, JobEvent, JobEventKind, JobRecord, JobState, Store};

pub struct Jobs {
    store: Store,
    jobs: JobManager,
}

impl Jobs {
    pub fn new(store: Store, jobs: JobManager) -> Self {
        Self { store, jobs }
    }

    /// proto -> stored spec, with defaults (the shared schema's `JobSpec::from_proto`) after
    /// the lookups they depend on: the diffusion job's dataset kind, the space of the model a
    /// reward or discriminator job reads. A missing input is NOT_FOUND before any other check.
    async fn spec_from_proto(&self, mut spec: pb::JobSpec) -> Result<JobSpec, Error> {
        use pb::job_spec::Kind;
        validate_spec_names(&spec)?;
        // A recipe's prompt dataset is read now: the job keeps the conditions themselves.
        if let Some(Kind::Reward(r)) = spec.kind.as_mut() {
            for (side, recipe) in [("base", &mut r.base_recipe), ("expert", &mut r.expert_recipe)] {
                if let Some(p) = recipe.as_mut().and_then(|r| r.prompts.as_mut()) {
                    let field = format!("spec.reward.{side}_recipe.prompts");
                    crate::jobs::datasets::resolve_prompt_dataset(&self.store, p, &field).await?;
                }
            }
        }
        let facts = match &spec.kind {
            None => return Err(Error::invalid("spec.kind: none of diffusion, reward or discriminator is set")),
            Some(Kind::Diffusion(d)) => {
                let dataset = self.store.meta.get_dataset(&d.dataset).await?.ok_or_else(|| {
                    Error::NotFound(format!("spec.diffusion.dataset: dataset '{}' not found", d.dataset))
                })?;
                Facts::Dataset { name: dataset.name, trajectories: dataset.kind == DatasetKind::Trajectories }
            }
            Some(Kind::Reward(r)) => {
                Facts::Models { space: self.model_space("spec.reward.base_model", &r.base_model).await? }
            }
            Some(Kind::Discriminator(d)) => Facts::Models {
                space: self.model_space("spec.discriminator.diffusion_model", &d.diffusion_model).await?,
            },
        };
        Ok(JobSpec::from_proto(spec, &facts)?)
    }

    /// The item space of diffusion model `name` (or of a named recipe's model), named in
    /// errors as `field`.
    async fn model_space(&self, field: &str, name: &str) -> Result<Space, Error> {
        let (model, _) = crate::registry::resolve_sampled(&self.store, name).await.map_err(|e| match e {
            Error::NotFound(m) => Error::NotFound(format!("{field}: {m}")),
            Error::FailedPrecondition(m) => Error::invalid(format!("{field}: {m}")),
            other => other,
        })?;
        let manifest = serde_json::from_value::<DiffusionManifest>(model.manifest)
            .map_err(|e| Error::DataLoss(format!("{field}: model '{}': manifest unreadable: {e}", model.name)))?;
        Ok(manifest.space)
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

fn state_to_proto(s: JobState) -> pb::JobState {
    match s {
        JobState::Pending => pb::JobState::Pending,
        JobState::Running => pb::JobState::Running,
        JobState::Succeeded => pb::JobState::Succeeded,
        JobState::Failed => pb::JobState::Failed,
        JobState::Cancelled => pb::JobState::Cancelled,
    }
}

fn job_to_proto(r: &JobRecord) -> pb::Job {
    let spec = serde_json::from_value::<JobSpec>(r.spec.clone()).ok().map(|s| s.to_proto());
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
