//! The gRPC door: one tonic service per proto service, plus health and reflection.
//!
//! Handlers validate and convert wire types to domain types, call into `store` (and later
//! `engine`/`jobs`), and convert back. Status codes come only from `crate::error`.

pub mod convert;
pub mod datasets;
pub mod jobs;
pub mod models;
pub mod oip;
pub mod reflection;
pub mod rewards;

use relreward_proto::inference::grpc_inference_service_server::GrpcInferenceServiceServer;
use relreward_proto::v1::{
    dataset_service_server::DatasetServiceServer, job_service_server::JobServiceServer,
    model_service_server::ModelServiceServer, reward_service_server::RewardServiceServer,
};
use tonic::service::Routes;

use crate::config::Config;
use crate::jobs::JobManager;
use crate::latents::Latents;
use crate::sampling::Sampling;
use crate::serving::Serving;
use crate::store::Store;
use crate::tasks::Tasks;

/// Page size when a request leaves it at 0, and the cap on any page.
const DEFAULT_PAGE: usize = 100;
const MAX_PAGE: usize = 1000;

pub(crate) fn page_limit(requested: u32) -> usize {
    match requested as usize {
        0 => DEFAULT_PAGE,
        n => n.min(MAX_PAGE),
    }
}

/// The next message of a client-streaming upload with its oneof unwrapped by `inner`: a
/// message with nothing set is malformed, and a broken stream (the client went away, sent an
/// undecodable frame or one over the size limit) abandons the upload.
pub(crate) async fn next_upload<R, M>(
    stream: &mut tonic::Streaming<R>,
    inner: impl Fn(R) -> Option<M>,
) -> Result<Option<M>, crate::error::Error> {
    use crate::error::Error;
    match stream.message().await {
        Ok(Some(request)) => {
            inner(request).map(Some).ok_or_else(|| Error::invalid("message: none of header, chunk or commit is set"))
        }
        Ok(None) => Ok(None),
        Err(status) => Err(Error::from_inbound("upload stream", &status)),
    }
}

pub(crate) fn timestamp(ms: i64) -> prost_types::Timestamp {
    prost_types::Timestamp { seconds: ms.div_euclid(1000), nanos: (ms.rem_euclid(1000) * 1_000_000) as i32 }
}

/// Every relreward.v1 service, and the Open Inference Protocol's, with the configured message
/// limits and compression (gzip and deflate requests accepted; responses per
/// `server.response_compression`; a decompressed message is bounded by max_request_bytes too).
/// `streams`: the group GradientStream's tasks belong to.
pub fn routes(
    config: &Config,
    store: Store,
    job_manager: JobManager,
    serving: Serving,
    sampling: Sampling,
    latents: Latents,
    streams: Tasks,
) -> Routes {
    let registry = serving.registry().clone();
    let (max_in, max_out) = (config.server.max_request_bytes, config.server.max_response_bytes);
    let budget = crate::limits::DiskBudget::new(&config.storage.data_dir, config.storage.max_bytes);
    let datasets = DatasetServiceServer::new(datasets::Datasets::new(
        store.clone(),
        job_manager.clone(),
        config.datasets.max_upload_bytes,
        budget.clone(),
    ))
    .max_decoding_message_size(max_in)
    .max_encoding_message_size(max_out);
    let model_service = models::Models::new(
        store.clone(),
        registry.clone(),
        job_manager.clone(),
        config.models.clone(),
        budget,
        max_out,
    );
    let models =
        ModelServiceServer::new(model_service).max_decoding_message_size(max_in).max_encoding_message_size(max_out);
    let jobs = JobServiceServer::new(jobs::Jobs::new(store.clone(), job_manager))
        .max_decoding_message_size(max_in)
        .max_encoding_message_size(max_out);
    let inference = GrpcInferenceServiceServer::new(oip::Inference::new(serving.clone()))
        .max_decoding_message_size(max_in)
        .max_encoding_message_size(max_out);
    let rewards = RewardServiceServer::new(rewards::Rewards::new(serving, sampling, latents, streams))
        .max_decoding_message_size(max_in)
        .max_encoding_message_size(max_out);
    Routes::new(with_compression!(datasets, config))
        .add_service(with_compression!(models, config))
        .add_service(with_compression!(jobs, config))
        .add_service(with_compression!(rewards, config))
        .add_service(with_compression!(inference, config))
}

/// Service names registered with grpc.health.v1, besides "" for the whole server.
pub const SERVICE_NAMES: &[&str] = &[
    "relreward.v1.DatasetService",
    "relreward.v1.ModelService",
    "relreward.v1.JobService",
    "relreward.v1.RewardService",
    "inference.GRPCInferenceService",
];
