//! `inference.GRPCInferenceService`: the KServe Open Inference Protocol v2 (Triton's gRPC
//! API), so that generic clients such as Python's `tritonclient.grpc` score and differentiate
//! reward models with no relreward-specific code. It is a second door onto [`Serving`], which
//! validates, batches and computes exactly as for the native RewardService, so both protocols
//! give the same numbers for the same input.
//!
//! A reward (or discriminator) model, version "1", takes
//! - `x`: FP32 `[B, *item_shape]` (`[B, H, D]` trajectories, or `[B, *shape]` samples), in the
//!   dataset's raw units (the native API's default);
//! - `t`: INT64, the diffusion step per item, shape `[B]` (or `[B, 1]`, the shape ModelConfig's
//!   dims `[1]` describe), or one step for every item, shape `[1]` or `[]` (optional: missing
//!   means 0 for every item);
//!
//! and offers
//! - `reward`: FP32 `[B]`, rho(x, t);
//! - `grad_x`: FP32 `[B, *item_shape]`, grad_x rho in raw units (omega 1, no variance scaling).
//!
//! Requesting `grad_x` (or no outputs at all, which means both) runs a gradient query, else a
//! score query. Inputs come in `raw_input_contents` (what tritonclient sends) or in the typed
//! `contents` fields; outputs always go in `raw_output_contents` (what tritonclient reads).
//! Every malformed request is INVALID_ARGUMENT naming the input and what was expected, checked
//! before any model compute; unknown models are NOT_FOUND and diffusion models
//! FAILED_PRECONDITION, as on the native API.
//!
//! Besides inference:
//! - ModelMetadata and ModelConfig describe a model; ModelConfig in Triton's terms:
//!   `max_batch_size` is `serving.max_request_items` (the most items one request may carry),
//!   dims are per item, `t` and `reward` are dims `[1]` reshaped to `[]` (one scalar per item),
//!   `t` is optional, and `dynamic_batching` is the batcher's settings (`preferred_batch_size`
//!   `serving.max_batch`, `max_queue_delay_microseconds` `serving.max_delay_us`, a queue of
//!   `serving.queue_capacity` requests that rejects on timeout, `serving.default_deadline_ms`
//!   unless the call carries `grpc-timeout`); its `parameters` say `n_timesteps`, the
//!   `base_model` and `expert_model` it was extracted from and, for a side sampled through a
//!   sampling recipe (named or the job's own), `base_recipe` / `expert_recipe` as JSON (model,
//!   model_sha256, recipe). Both answer NOT_FOUND for an unknown model or version and
//!   FAILED_PRECONDITION for a diffusion model (or a recipe).
//! - ModelStatistics: per model, what serving counted since the server started
//!   ([`crate::metrics::ModelStats`]: Score and Gradient of the native API count too). With a
//!   name, that model (zeros before its first query); without, every reward model in the store
//!   that has statistics.
//! - RepositoryIndex: every reward and discriminator model in the store, version "1", READY
//!   when ModelReady would say so (it loads and passes its integrity check; so the index may
//!   load models), else UNAVAILABLE with the reason. Diffusion models, autoencoders and recipes
//!   are not listed: this endpoint never serves them. `ready` keeps the READY ones only.
//!
//! The protocol's other RPCs (ModelStreamInfer, RepositoryModelLoad and RepositoryModelUnload
//! (models load on demand), the system and CUDA shared-memory RPCs, TraceSetting and
//! LogSettings) are not in `proto/inference/grpc_service.proto` and are answered UNIMPLEMENTED
//! by tonic.

use std::collections::{HashMap, HashSet};

use prost::bytes::Bytes;
use relreward_proto::inference::{
    self as pb, InferParameter, grpc_inference_service_server::GrpcInferenceService,
    model_infer_request::InferInputTensor, model_infer_response::InferOutputTensor,
    model_metadata_response::TensorMetadata, repository_index_response::ModelIndex,
};

use tonic::{Request, Response, Status};
use tracing::Instrument;

use crate::error::{Error, Result, brief, quote};
use crate::metrics::{CountNs, ModelStats};
use crate::serving::{self, HostTensor, Op, Query, Serving, Units};
use crate::store::ModelKind;
use relreward_proto::schema::recipe::RecipeManifest;

/// The one version every model has.
const VERSION: &str = "1";
const PLATFORM: &str = "relreward_native";
/// ModelConfig's backend.
const BACKEND: &str = "relreward";
const X: &str = "x";
const T: &str = "t";
const REWARD: &str = "reward";
const GRAD_X: &str = "grad_x";
const FP32: &str = "FP32";
const INT64: &str = "INT64";
/// RepositoryIndex states.
const READY: &str = "READY";
const UNAVAILABLE: &str = "UNAVAILABLE";
/// Store records read per page while building the repository index.
const INDEX_PAGE: usize = 256;
/// Parameters that ask the server to read or write shared memory, which it does not offer.
const SHARED_MEMORY: &[&str] = &["shared_memory_region", "shared_memory_byte_size", "shared_memory_offset"];

pub struct Inference {
    serving: Serving,
}

impl Inference {
    pub fn new(serving: Serving) -> Self {
        Self { serving }
    }
}

/// Only version "1" exists; empty means the server's choice (that one).
fn check_version(name: &str, version: &str) -> Result<()> {
    if version.is_empty() || version == VERSION {
        Ok(())
    } else {
        Err(Error::NotFound(format!(
            "model {} has no version {} (its only version is \"{VERSION}\")",
            quote(name),
            quote(version)
        )))
    }
}

fn refuse_shared_memory(what: &str, parameters: &HashMap<String, InferParameter>) -> Result<()> {
    match SHARED_MEMORY.iter().find(|k| parameters.contains_key(**k)) {
        Some(k) => Err(Error::invalid(format!(
            "{what}: parameter '{k}': shared memory is not supported; send the data in the request"
        ))),
        None => Ok(()),
    }
}

/// The element count of `shape`, refusing negative dimensions and overflow.
fn element_count(name: &str, shape: &[i64]) -> Result<usize> {
    shape.iter().try_fold(1usize, |n, &d| {
        let d = usize::try_from(d)
            .map_err(|_| Error::invalid(format!("{name}: shape {} has a negative dimension", brief(&shape))))?;
        n.checked_mul(d).ok_or_else(|| Error::invalid(format!("{name}: shape {} has too many elements", brief(&shape))))
    })
}

/// The little-endian elements of `raw`, which must hold exactly `count` of `N` bytes each.
fn from_raw<const N: usize, V>(
    name: &str,
    datatype: &str,
    shape: &[i64],
    count: usize,
    raw: &[u8],
    decode: impl Fn([u8; N]) -> V,
) -> Result<Vec<V>> {
    if Some(raw.len()) != count.checked_mul(N) {
        return Err(Error::invalid(format!(
            "{name}: raw_input_contents has {} bytes but {datatype} shape {} needs {count} x {N} = {} bytes",
            raw.len(),
            brief(&shape),
            count.saturating_mul(N)
        )));
    }
    Ok(raw.chunks_exact(N).map(|c| decode(c.try_into().unwrap_or([0; N]))).collect())
}

/// Typed contents must hold exactly `count` values in the field for the datatype.
fn from_contents<V: Clone>(name: &str, field: &str, shape: &[i64], count: usize, values: &[V]) -> Result<Vec<V>> {
    if values.len() != count {
        return Err(Error::invalid(format!(
            "{name}: contents.{field} holds {} values but shape {} needs {count}",
            values.len(),
            brief(&shape)
        )));
    }
    Ok(values.to_vec())
}

/// `x` and `t` of a ModelInferRequest, checked against the protocol (names, datatypes, byte
/// counts) but not yet against the model (Serving::prepare does that).
#[derive(Debug, PartialEq)]
struct Inputs {
    x_shape: Vec<i64>,
    x: Vec<f32>,
    /// Empty when `t` is not given: 0 for every item.
    t: Vec<i64>,
}

fn parse_inputs(req: &pb::ModelInferRequest) -> Result<Inputs> {
    let raw = &req.raw_input_contents;
    if !raw.is_empty() && raw.len() != req.inputs.len() {
        return Err(Error::invalid(format!(
            "raw_input_contents: {} entries for {} inputs (give one per input, in the order of inputs, or none)",
            raw.len(),
            req.inputs.len()
        )));
    }
    let mut x: Option<(Vec<i64>, Vec<f32>)> = None;
    let mut t: Option<(Vec<i64>, Vec<i64>)> = None;
    for (i, input) in req.inputs.iter().enumerate() {
        let InferInputTensor { name, datatype, shape, parameters, contents } = input;
        let (want, seen) = match name.as_str() {
            X => (FP32, x.is_some()),
            T => (INT64, t.is_some()),
            other => {
                return Err(Error::invalid(format!(
                    "inputs[{i}]: unknown input {}; reward models take {X} ({FP32}) and {T} ({INT64})",
                    quote(other)
                )));
            }
        };
        if seen {
            return Err(Error::invalid(format!("inputs[{i}]: input '{name}' is given more than once")));
        }
        refuse_shared_memory(name, parameters)?;
        if datatype != want {
            return Err(Error::invalid(format!(
                "{name}: datatype {} is not accepted; expected {want}",
                quote(datatype)
            )));
        }
        let count = element_count(name, shape)?;
        let raw = raw.get(i);
        if raw.is_some() && contents.is_some() {
            return Err(Error::invalid(format!("{name}: data given both in contents and in raw_input_contents")));
        }
        let contents = contents.clone().unwrap_or_default();
        if name == X {
            let values = match raw {
                Some(raw) => from_raw(name, want, shape, count, raw, f32::from_le_bytes)?,
                None => from_contents(name, "fp32_contents", shape, count, &contents.fp32_contents)?,
            };
            x = Some((shape.clone(), values));
        } else {
            let values = match raw {
                Some(raw) => from_raw(name, want, shape, count, raw, i64::from_le_bytes)?,
                None => from_contents(name, "int64_contents", shape, count, &contents.int64_contents)?,
            };
            t = Some((shape.clone(), values));
        }
    }
    let (x_shape, x) = x.ok_or_else(|| Error::invalid(format!("inputs: input '{X}' ({FP32} [B, ...]) is missing")))?;
    let t = match (t, x_shape.first()) {
        (None, _) => Vec::new(),
        (Some((shape, values)), Some(&b)) => {
            // One step per item ([B], or [B, 1] as ModelConfig's dims [1] describe), or one
            // step for every item ([1] or a scalar), which Serving broadcasts.
            let per_item = shape == [b] || shape == [b, 1];
            let broadcast = shape.is_empty() || shape == [1];
            if !(per_item || broadcast) {
                return Err(Error::invalid(format!(
                    "{T}: expected shape [{b}] or [{b}, 1] (one diffusion step per item of {X}, whose shape is \
                     {}), or [1] or [] (one step for every item), got {}",
                    brief(&x_shape),
                    brief(&shape)
                )));
            }
            values
        }
        // x without a batch dimension: Serving::prepare reports x's shape.
        (Some((_, values)), None) => values,
    };
    Ok(Inputs { x_shape, x, t })
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Output {
    Reward,
    GradX,
}

impl Output {
    fn name(self) -> &'static str {
        match self {
            Self::Reward => REWARD,
            Self::GradX => GRAD_X,
        }
    }
}

/// The requested outputs in order; none named means both.
fn parse_outputs(req: &pb::ModelInferRequest) -> Result<Vec<Output>> {
    if req.outputs.is_empty() {
        return Ok(vec![Output::Reward, Output::GradX]);
    }
    let mut outputs = Vec::with_capacity(req.outputs.len());
    for (i, requested) in req.outputs.iter().enumerate() {
        let output = match requested.name.as_str() {
            REWARD => Output::Reward,
            GRAD_X => Output::GradX,
            other => {
                return Err(Error::invalid(format!(
                    "outputs[{i}]: unknown output {}; reward models offer {REWARD} and {GRAD_X}",
                    quote(other)
                )));
            }
        };
        if outputs.contains(&output) {
            return Err(Error::invalid(format!(
                "outputs[{i}]: output '{}' is requested more than once",
                requested.name
            )));
        }
        refuse_shared_memory(&requested.name, &requested.parameters)?;
        outputs.push(output);
    }
    Ok(outputs)
}

/// A float tensor of the answer as an FP32 output: its shape and little-endian bytes.
fn fp32_output(name: &str, t: &HostTensor) -> Result<(InferOutputTensor, Bytes)> {
    let bytes: Vec<u8> = t.values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let meta = InferOutputTensor {
        name: name.to_owned(),
        datatype: FP32.to_owned(),
        shape: t.shape.clone(),
        ..Default::default()
    };
    Ok((meta, Bytes::from(bytes)))
}

fn tensor_metadata(name: &str, datatype: &str, shape: Vec<i64>) -> TensorMetadata {
    TensorMetadata { name: name.to_owned(), datatype: datatype.to_owned(), shape }
}

/// One scalar per item, in Triton's terms: dims `[1]`, which the model sees as `[]`.
fn scalar_reshape() -> Option<pb::ModelTensorReshape> {
    Some(pb::ModelTensorReshape { shape: Vec::new() })
}

fn duration(d: CountNs) -> Option<pb::StatisticDuration> {
    Some(pb::StatisticDuration { count: d.count, ns: d.ns })
}

fn model_statistics(name: String, s: &ModelStats) -> pb::ModelStatistics {
    pb::ModelStatistics {
        name,
        version: VERSION.to_owned(),
        last_inference: s.last_inference_ms,
        inference_count: s.inference_count,
        execution_count: s.execution_count,
        inference_stats: Some(pb::InferStatistics {
            success: duration(s.success),
            fail: duration(s.fail),
            queue: duration(s.queue),
            compute_input: duration(CountNs::default()),
            compute_infer: duration(s.compute_infer),
            compute_output: duration(CountNs::default()),
            cache_hit: duration(CountNs::default()),
            cache_miss: duration(CountNs::default()),
        }),
        ..Default::default()
    }
}

/// The repository's own error for a repository name other than its one, unnamed, repository.
fn check_repository(name: &str) -> Result<()> {
    if name.is_empty() {
        Ok(())
    } else {
        Err(Error::NotFound(format!(
            "repository {}: relreward has one model repository, the model store; leave repository_name empty",
            quote(name)
        )))
    }
}

impl Inference {
    pub(crate) async fn infer(
        &self,
        req: pb::ModelInferRequest,
        deadline: Option<std::time::Instant>,
    ) -> Result<pb::ModelInferResponse> {
        check_version(&req.model_name, &req.model_version)?;
        let inputs = parse_inputs(&req)?;
        let outputs = parse_outputs(&req)?;
        let op = if outputs.contains(&Output::GradX) {
            Op::Gradient { units: Units::Raw, omega: 1.0, variance_of: None }
        } else {
            Op::Score { per_window: false, per_step: false }
        };
        let query =
            Query { shape: inputs.x_shape, values: inputs.x, t: inputs.t, input_units: Units::Raw, op, deadline };
        let answer = self.serving.query(&req.model_name, query).await?;
        let mut response = pb::ModelInferResponse {
            model_name: req.model_name,
            model_version: VERSION.to_owned(),
            id: req.id,
            ..Default::default()
        };
        for output in outputs {
            let tensor = match output {
                Output::Reward => &answer.rewards,
                Output::GradX => answer
                    .gradient
                    .as_ref()
                    .ok_or_else(|| Error::internal("inference", "a gradient query answered without a gradient"))?,
            };
            let (meta, bytes) = fp32_output(output.name(), tensor)?;
            response.outputs.push(meta);
            response.raw_output_contents.push(bytes);
        }
        Ok(response)
    }

    pub(crate) async fn metadata(&self, req: pb::ModelMetadataRequest) -> Result<pb::ModelMetadataResponse> {
        check_version(&req.name, &req.version)?;
        let model = self.serving.reward(&req.name).await?;
        let batched = |item: &[i64]| std::iter::once(-1).chain(item.iter().copied()).collect::<Vec<_>>();
        Ok(pb::ModelMetadataResponse {
            name: req.name,
            versions: vec![VERSION.to_owned()],
            platform: PLATFORM.to_owned(),
            inputs: vec![tensor_metadata(X, FP32, batched(&model.item_shape)), tensor_metadata(T, INT64, vec![-1])],
            outputs: vec![
                tensor_metadata(REWARD, FP32, vec![-1]),
                tensor_metadata(GRAD_X, FP32, batched(&model.item_shape)),
            ],
        })
    }

    pub(crate) async fn config(&self, req: pb::ModelConfigRequest) -> Result<pb::ModelConfigResponse> {
        check_version(&req.name, &req.version)?;
        let model = self.serving.reward(&req.name).await?;
        let serving = self.serving.config();
        let int32 = |what: &str, v: usize| {
            i32::try_from(v).map_err(|e| Error::internal(&format!("ModelConfig: serving.{what} = {v}"), e))
        };
        let max_batch_size = int32("max_request_items", serving.max_request_items)?;
        let preferred = int32("max_batch", serving.max_batch.min(serving.max_request_items))?;
        let max_queue_size = u32::try_from(serving.queue_capacity).map_err(|e| {
            Error::internal(&format!("ModelConfig: serving.queue_capacity = {}", serving.queue_capacity), e)
        })?;
        let input =
            |name: &str, data_type: pb::DataType, dims: Vec<i64>, scalar: bool, optional: bool| pb::ModelInput {
                name: name.to_owned(),
                data_type: data_type as i32,
                dims,
                reshape: if scalar { scalar_reshape() } else { None },
                optional,
            };
        let output = |name: &str, dims: Vec<i64>, scalar: bool| pb::ModelOutput {
            name: name.to_owned(),
            data_type: pb::DataType::TypeFp32 as i32,
            dims,
            reshape: if scalar { scalar_reshape() } else { None },
        };
        let item = model.item_shape.clone();
        // Provenance beside T: the models (or recipes) it was extracted from and, for a side
        // sampled through a recipe, the recipe as JSON (model, its sha256, prompts, guidance).
        let recipe = |r: &Option<RecipeManifest>| {
            r.as_ref().map(|r| serde_json::to_string(r).map_err(|e| Error::internal("ModelConfig: a recipe", e)))
        };
        let m = &model.manifest;
        let parameters = [
            ("n_timesteps", Some(Ok(m.n_timesteps.to_string()))),
            ("base_model", (!m.base_model.is_empty()).then(|| Ok(m.base_model.clone()))),
            ("expert_model", (!m.expert_model.is_empty()).then(|| Ok(m.expert_model.clone()))),
            ("base_recipe", recipe(&m.base_recipe)),
            ("expert_recipe", recipe(&m.expert_recipe)),
        ]
        .into_iter()
        .filter_map(|(k, v)| v.map(|v| v.map(|v| (k.to_owned(), pb::ModelParameter { string_value: v }))))
        .collect::<Result<_>>()?;
        let config = pb::ModelConfig {
            name: req.name,
            platform: PLATFORM.to_owned(),
            backend: BACKEND.to_owned(),
            version_policy: Some(pb::ModelVersionPolicy {
                policy_choice: Some(pb::model_version_policy::PolicyChoice::Specific(
                    pb::model_version_policy::Specific { versions: vec![1] },
                )),
            }),
            max_batch_size,
            input: vec![
                input(X, pb::DataType::TypeFp32, item.clone(), false, false),
                input(T, pb::DataType::TypeInt64, vec![1], true, true),
            ],
            output: vec![output(REWARD, vec![1], true), output(GRAD_X, item, false)],
            scheduling_choice: Some(pb::model_config::SchedulingChoice::DynamicBatching(pb::ModelDynamicBatching {
                preferred_batch_size: vec![preferred],
                max_queue_delay_microseconds: serving.max_delay_us,
                preserve_ordering: false,
                default_queue_policy: Some(pb::ModelQueuePolicy {
                    timeout_action: pb::model_queue_policy::TimeoutAction::Reject as i32,
                    default_timeout_microseconds: serving.default_deadline_ms.saturating_mul(1000),
                    allow_timeout_override: true,
                    max_queue_size,
                }),
            })),
            parameters,
        };
        Ok(pb::ModelConfigResponse { config: Some(config) })
    }

    pub(crate) async fn statistics(&self, req: pb::ModelStatisticsRequest) -> Result<pb::ModelStatisticsResponse> {
        check_version(if req.name.is_empty() { "any model" } else { &req.name }, &req.version)?;
        let metrics = self.serving.metrics();
        if !req.name.is_empty() {
            self.serving.reward(&req.name).await?;
            let stats = metrics.model_stats(&req.name).unwrap_or_default();
            return Ok(pb::ModelStatisticsResponse { model_stats: vec![model_statistics(req.name, &stats)] });
        }
        // Statistics outlive a deleted model (they are kept by name): list those in the store.
        let stored: HashSet<String> = self.reward_models().await?.into_iter().collect();
        let model_stats = metrics
            .all_model_stats()
            .into_iter()
            .filter(|(name, _)| stored.contains(name))
            .map(|(name, stats)| model_statistics(name, &stats))
            .collect();
        Ok(pb::ModelStatisticsResponse { model_stats })
    }

    /// Names of the reward and discriminator models in the store, in the store's name order.
    async fn reward_models(&self) -> Result<Vec<String>> {
        let registry = self.serving.registry();
        let mut names = Vec::new();
        let mut after = String::new();
        loop {
            let page = registry.list_records(&after, INDEX_PAGE).await?;
            let done = page.len() < INDEX_PAGE;
            if let Some(last) = page.last() {
                after.clone_from(&last.name);
            }
            names.extend(
                page.into_iter()
                    .filter(|r| matches!(r.kind, ModelKind::Reward | ModelKind::Discriminator))
                    .map(|r| r.name),
            );
            if done {
                return Ok(names);
            }
        }
    }

    pub(crate) async fn index(&self, req: pb::RepositoryIndexRequest) -> Result<pb::RepositoryIndexResponse> {
        check_repository(&req.repository_name)?;
        let mut models = Vec::new();
        for name in self.reward_models().await? {
            let (state, reason) = match self.serving.reward(&name).await {
                Ok(_) => (READY, String::new()),
                // Deleted since the listing.
                Err(Error::NotFound(_)) => continue,
                Err(e @ (Error::FailedPrecondition(_) | Error::InvalidArgument(_) | Error::DataLoss(_))) => {
                    (UNAVAILABLE, e.to_string())
                }
                Err(e) => return Err(e),
            };
            if req.ready && state != READY {
                continue;
            }
            models.push(ModelIndex { name, version: VERSION.to_owned(), state: state.to_owned(), reason });
        }
        Ok(pb::RepositoryIndexResponse { models })
    }

    /// Ready iff the registry can load `name` as a reward or discriminator model.
    pub(crate) async fn ready(&self, req: pb::ModelReadyRequest) -> Result<bool> {
        if check_version(&req.name, &req.version).is_err() {
            return Ok(false);
        }
        match self.serving.reward(&req.name).await {
            Ok(_) => Ok(true),
            Err(Error::NotFound(_) | Error::FailedPrecondition(_) | Error::InvalidArgument(_) | Error::DataLoss(_)) => {
                Ok(false)
            }
            Err(e) => Err(e),
        }
    }
}

fn span(method: &'static str, model: &str) -> tracing::Span {
    tracing::info_span!("oip", method, model)
}

#[tonic::async_trait]
impl GrpcInferenceService for Inference {
    async fn server_live(
        &self,
        _request: Request<pb::ServerLiveRequest>,
    ) -> Result<Response<pb::ServerLiveResponse>, Status> {
        Ok(Response::new(pb::ServerLiveResponse { live: true }))
    }

    async fn server_ready(
        &self,
        _request: Request<pb::ServerReadyRequest>,
    ) -> Result<Response<pb::ServerReadyResponse>, Status> {
        Ok(Response::new(pb::ServerReadyResponse { ready: true }))
    }

    async fn model_ready(
        &self,
        request: Request<pb::ModelReadyRequest>,
    ) -> Result<Response<pb::ModelReadyResponse>, Status> {
        let req = request.into_inner();
        let span = span("ModelReady", &req.name);
        let ready = self.ready(req).instrument(span).await?;
        Ok(Response::new(pb::ModelReadyResponse { ready }))
    }

    async fn server_metadata(
        &self,
        _request: Request<pb::ServerMetadataRequest>,
    ) -> Result<Response<pb::ServerMetadataResponse>, Status> {
        Ok(Response::new(pb::ServerMetadataResponse {
            name: "relreward".to_owned(),
            version: env!("CARGO_PKG_VERSION").to_owned(),
            extensions: Vec::new(),
        }))
    }

    async fn model_metadata(
        &self,
        request: Request<pb::ModelMetadataRequest>,
    ) -> Result<Response<pb::ModelMetadataResponse>, Status> {
        let req = request.into_inner();
        let span = span("ModelMetadata", &req.name);
        Ok(Response::new(self.metadata(req).instrument(span).await?))
    }

    async fn model_infer(
        &self,
        request: Request<pb::ModelInferRequest>,
    ) -> Result<Response<pb::ModelInferResponse>, Status> {
        let deadline = serving::deadline_of(request.metadata());
        let req = request.into_inner();
        let span = span("ModelInfer", &req.model_name);
        Ok(Response::new(self.infer(req, deadline).instrument(span).await?))
    }

    async fn model_config(
        &self,
        request: Request<pb::ModelConfigRequest>,
    ) -> Result<Response<pb::ModelConfigResponse>, Status> {
        let req = request.into_inner();
        let span = span("ModelConfig", &req.name);
        Ok(Response::new(self.config(req).instrument(span).await?))
    }

    async fn model_statistics(
        &self,
        request: Request<pb::ModelStatisticsRequest>,
    ) -> Result<Response<pb::ModelStatisticsResponse>, Status> {
        let req = request.into_inner();
        let span = span("ModelStatistics", &req.name);
        Ok(Response::new(self.statistics(req).instrument(span).await?))
    }

    async fn repository_index(
        &self,
        request: Request<pb::RepositoryIndexRequest>,
    ) -> Result<Response<pb::RepositoryIndexResponse>, Status> {
        let req = request.into_inner();
        let span = span("RepositoryIndex", &req.repository_name);
        Ok(Response::new(self.index(req).instrument(span).await?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relreward_proto::inference::InferTensorContents;
    use relreward_proto::inference::model_infer_request::InferRequestedOutputTensor;

    fn input(name: &str, datatype: &str, shape: &[i64]) -> InferInputTensor {
        InferInputTensor { name: name.into(), datatype: datatype.into(), shape: shape.to_vec(), ..Default::default() }
    }

    fn raw_f32(v: &[f32]) -> Bytes {
        Bytes::from(v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>())
    }

    fn raw_i64(v: &[i64]) -> Bytes {
        Bytes::from(v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>())
    }

    fn request(inputs: Vec<InferInputTensor>, raw: Vec<Bytes>) -> pb::ModelInferRequest {
        pb::ModelInferRequest { model_name: "m".into(), inputs, raw_input_contents: raw, ..Default::default() }
    }

    fn err(req: &pb::ModelInferRequest) -> String {
        match parse_inputs(req).expect_err("bad input") {
            Error::InvalidArgument(m) => m,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn raw_and_typed_inputs_decode_alike() {
        let x = [1.0f32, -2.5, 3.0, 4.0];
        let raw =
            request(vec![input("t", INT64, &[2]), input("x", FP32, &[2, 2])], vec![raw_i64(&[3, 4]), raw_f32(&x)]);
        let want = Inputs { x_shape: vec![2, 2], x: x.to_vec(), t: vec![3, 4] };
        assert_eq!(parse_inputs(&raw).expect("raw"), want);
        let mut tx = input("t", INT64, &[2]);
        tx.contents = Some(InferTensorContents { int64_contents: vec![3, 4], ..Default::default() });
        let mut xx = input("x", FP32, &[2, 2]);
        xx.contents = Some(InferTensorContents { fp32_contents: x.to_vec(), ..Default::default() });
        assert_eq!(parse_inputs(&request(vec![xx, tx], vec![])).expect("typed"), want);
        // One t for every item (Serving broadcasts it), or one per item as [B, 1].
        for (shape, t) in [(&[1][..], &[7][..]), (&[][..], &[7][..]), (&[2, 1][..], &[3, 4][..])] {
            let req = request(vec![input("x", FP32, &[2, 2]), input("t", INT64, shape)], vec![raw_f32(&x), raw_i64(t)]);
            assert_eq!(parse_inputs(&req).expect("t shape").t, t, "t shape {shape:?}");
        }
        // t is optional.
        let only_x = request(vec![input("x", FP32, &[2, 2])], vec![raw_f32(&x)]);
        assert!(parse_inputs(&only_x).expect("x only").t.is_empty());
    }

    #[test]
    fn malformed_inputs_name_the_input() {
        let x = raw_f32(&[0.0; 4]);
        let e = err(&request(vec![input("x", "FP64", &[2, 2])], vec![x.clone()]));
        assert!(e.contains("x: datatype 'FP64'") && e.contains("expected FP32"), "{e}");
        let e = err(&request(vec![input("x", FP32, &[2, 2]), input("t", "INT32", &[2])], vec![x.clone(), x.clone()]));
        assert!(e.contains("t: datatype 'INT32'") && e.contains("expected INT64"), "{e}");
        let e = err(&request(vec![input("x", FP32, &[2, 3])], vec![x.clone()]));
        assert!(e.contains("x: raw_input_contents has 16 bytes") && e.contains("24 bytes"), "{e}");
        let e = err(&request(vec![input("y", FP32, &[2, 2])], vec![x.clone()]));
        assert!(e.contains("unknown input 'y'"), "{e}");
        let e = err(&request(vec![input("x", FP32, &[2, 2]), input("x", FP32, &[2, 2])], vec![x.clone(), x.clone()]));
        assert!(e.contains("more than once"), "{e}");
        let e = err(&request(vec![input("x", FP32, &[2, 2]), input("t", INT64, &[1])], vec![x.clone()]));
        assert!(e.contains("raw_input_contents: 1 entries for 2 inputs"), "{e}");
        let e = err(&request(vec![input("t", INT64, &[2])], vec![raw_i64(&[0, 0])]));
        assert!(e.contains("'x'") && e.contains("missing"), "{e}");
        let e = err(&request(
            vec![input("x", FP32, &[2, 2]), input("t", INT64, &[3])],
            vec![x.clone(), raw_i64(&[0, 1, 2])],
        ));
        assert!(e.contains("t: expected shape [2] or [2, 1]") && e.contains("got [3]"), "{e}");
        let e = err(&request(
            vec![input("x", FP32, &[2, 2]), input("t", INT64, &[1, 2])],
            vec![x.clone(), raw_i64(&[0, 1])],
        ));
        assert!(e.contains("got [1, 2]"), "{e}");
        let e = err(&request(vec![input("x", FP32, &[-2, 2])], vec![x.clone()]));
        assert!(e.contains("negative dimension"), "{e}");
        let e = err(&request(vec![input("x", FP32, &[i64::MAX, i64::MAX, 4])], vec![x.clone()]));
        assert!(e.contains("too many elements"), "{e}");
        let e = err(&request(vec![input("x", FP32, &[2, 2])], vec![]));
        assert!(e.contains("contents.fp32_contents holds 0 values"), "{e}");
        let mut shm = input("x", FP32, &[2, 2]);
        shm.parameters.insert("shared_memory_region".into(), InferParameter::default());
        assert!(err(&request(vec![shm], vec![x])).contains("shared memory"));
    }

    #[test]
    fn outputs_default_to_both_and_are_checked() {
        let mut req = request(vec![], vec![]);
        assert_eq!(parse_outputs(&req).expect("default"), [Output::Reward, Output::GradX]);
        let named = |n: &str| InferRequestedOutputTensor { name: n.into(), ..Default::default() };
        req.outputs = vec![named("grad_x")];
        assert_eq!(parse_outputs(&req).expect("grad"), [Output::GradX]);
        req.outputs = vec![named("reward"), named("reward")];
        assert!(parse_outputs(&req).expect_err("dup").to_string().contains("more than once"));
        req.outputs = vec![named("value")];
        assert!(parse_outputs(&req).expect_err("unknown").to_string().contains("unknown output 'value'"));
    }

    #[test]
    fn versions() {
        assert!(check_version("m", "").is_ok() && check_version("m", "1").is_ok());
        assert!(matches!(check_version("m", "2"), Err(Error::NotFound(_))));
    }
}
