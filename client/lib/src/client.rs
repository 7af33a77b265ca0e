//! [`Client`]: one connection, typed access to every relreward.v1 service.
//!
//! The generated clients remain available (`client.datasets()`, ...) for callers that want the
//! raw RPCs; the helpers here add what every caller would otherwise rewrite: chunked uploads
//! with the digest computed on the fly, and listing through every page. Following a job's
//! events across reconnects is in [`crate::watch`].
//!
//! Reads and pure computations (health, Get/List, Score, Gradient) are retried for a few
//! seconds when they fail on the connection rather than in the server ([`idempotent`]): a call
//! that races a closing connection (a server's `max_connection_age` GOAWAY, a replica
//! restarting) then goes over a new one. Writes are never retried behind the caller's back.
//!
//! [`Client::connect_with`] takes [`ConnectOptions`]: a bearer token sent with every call
//! (servers with `security.tokens`) and TLS settings for `https://` endpoints (a CA file,
//! a client certificate for mutual TLS).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use relreward_proto::error_chain;
use relreward_proto::v1 as pb;
use sha2::{Digest, Sha256};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::{AsciiMetadataValue, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

use crate::retry::{Backoff, RetryPolicy, is_retryable};
use crate::upload::{UploadSource, row_bytes, rows_per_chunk, total_bytes};

/// Messages up to this size are accepted from the server (tensors in responses can be large).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;
/// Default payload carried by one upload chunk.
pub const DEFAULT_CHUNK_BYTES: u64 = 1 << 20;

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    // With the source's own causes: tonic's message alone is "transport error", which hides
    // a refused connection or a failed certificate check.
    #[error("cannot connect to {endpoint}: {}", error_chain(.source))]
    Connect { endpoint: String, source: tonic::transport::Error },
    #[error("{}: {}", code_name(.0.code()), .0.message())]
    Status(#[from] tonic::Status),
    #[error("reading upload data: {0}")]
    Io(#[from] std::io::Error),
    #[error("{}: {source}", .path.display())]
    File { path: PathBuf, source: std::io::Error },
    #[error("{0}")]
    Invalid(String),
}

/// The gRPC code in the spelling of the spec (`INVALID_ARGUMENT`), for messages.
pub fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}

/// What a dataset upload should create.
#[derive(Debug, Clone)]
pub struct DatasetUpload {
    pub name: String,
    pub kind: pb::DatasetKind,
    pub description: String,
    /// Target payload bytes per chunk message.
    pub chunk_bytes: u64,
}

/// Progress of an upload, shared with whoever displays it.
#[derive(Debug, Default)]
pub struct UploadProgress {
    pub total_bytes: AtomicU64,
    pub sent_bytes: AtomicU64,
}

/// How to reach a server beyond its address.
#[derive(Clone, Default)]
pub struct ConnectOptions {
    /// Sent as `authorization: Bearer <token>` with every call.
    pub token: Option<String>,
    /// Used for `https://` endpoints (and refused with `http://` ones, where it would be
    /// silently ignored).
    pub tls: Option<TlsOptions>,
}

impl std::fmt::Debug for ConnectOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the token itself.
        f.debug_struct("ConnectOptions").field("token", &self.token.as_ref().map(|_| "<set>")).finish_non_exhaustive()
    }
}

/// TLS settings, all PEM.
#[derive(Clone, Default)]
pub struct TlsOptions {
    /// CA certificate(s) the server's certificate must chain to; `None`: the system's roots.
    pub ca_certificate: Option<Vec<u8>>,
    /// Client certificate chain and private key, for servers that require mutual TLS.
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
    /// The name to check the server's certificate against, when it is not the endpoint's host.
    pub server_name: Option<String>,
}

impl TlsOptions {
    /// Reads the files: a CA certificate, and a client certificate with its key.
    pub fn from_files(
        ca_certificate: Option<&Path>,
        client_certificate: Option<(&Path, &Path)>,
        server_name: Option<String>,
    ) -> Result<Self, ClientError> {
        let read =
            |path: &Path| std::fs::read(path).map_err(|source| ClientError::File { path: path.to_owned(), source });
        let ca_certificate = ca_certificate.map(read).transpose()?;
        let identity = match client_certificate {
            Some((cert, key)) => Some((read(cert)?, read(key)?)),
            None => None,
        };
        Ok(Self { ca_certificate, identity, server_name })
    }
}

/// Adds the bearer token (if any) to every call made through a [`Client`].
#[derive(Clone, Default)]
pub struct Credentials {
    authorization: Option<AsciiMetadataValue>,
}

impl Credentials {
    pub fn new(token: Option<&str>) -> Result<Self, ClientError> {
        let authorization = match token {
            None => None,
            Some(token) => {
                let mut value: AsciiMetadataValue = MetadataValue::try_from(format!("Bearer {}", token.trim()))
                    .map_err(|_| ClientError::Invalid("token: not printable ASCII; copy it again".into()))?;
                // Kept out of debug output of the request.
                value.set_sensitive(true);
                Some(value)
            }
        };
        Ok(Self { authorization })
    }
}

impl Interceptor for Credentials {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.authorization {
            request.metadata_mut().insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// How long [`idempotent`] keeps trying: long enough to ride over a closing connection or a
/// replica restart, short enough that a server that is really gone is reported promptly.
const IDEMPOTENT_RETRY: RetryPolicy = RetryPolicy {
    initial_delay: Duration::from_millis(50),
    max_delay: Duration::from_secs(1),
    budget: Duration::from_secs(5),
};

/// Runs `call`, again (with backoff, within [`IDEMPOTENT_RETRY`]) while it fails on the
/// connection ([`is_retryable`]); errors the server chose are returned at once. Only for calls
/// that may safely run twice: a read or a pure computation whose answer may have been lost.
async fn idempotent<T, F, Fut>(call: F) -> Result<T, ClientError>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
{
    retry_connection_failures(IDEMPOTENT_RETRY, call).await
}

async fn retry_connection_failures<T, F, Fut>(policy: RetryPolicy, mut call: F) -> Result<T, ClientError>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
{
    let started = tokio::time::Instant::now();
    let mut backoff = Backoff::new(policy);
    loop {
        let status = match call().await {
            Ok(response) => return Ok(response.into_inner()),
            Err(status) => status,
        };
        match backoff.next_delay(started.elapsed()) {
            Some(delay) if is_retryable(&status) => tokio::time::sleep(delay).await,
            _ => return Err(status.into()),
        }
    }
}

/// What the typed service clients of a [`Client`] run on: its channel, with its credentials.
pub type Transport = InterceptedService<Channel, Credentials>;

#[derive(Clone)]
pub struct Client {
    channel: Channel,
    credentials: Credentials,
}

impl Client {
    /// Connects to `endpoint` (e.g. `http://127.0.0.1:50051`) without a token; an
    /// `https://` endpoint is verified against the system's roots.
    pub async fn connect(endpoint: &str) -> Result<Self, ClientError> {
        Self::connect_with(endpoint, &ConnectOptions::default()).await
    }

    /// Connects to `endpoint` with a token and TLS settings.
    pub async fn connect_with(endpoint: &str, options: &ConnectOptions) -> Result<Self, ClientError> {
        let connect_err = |source| ClientError::Connect { endpoint: endpoint.to_owned(), source };
        let credentials = Credentials::new(options.token.as_deref())?;
        let mut target = Endpoint::from_shared(endpoint.to_owned()).map_err(connect_err)?;
        let https = target.uri().scheme_str() == Some("https");
        match (&options.tls, https) {
            (tls, true) => {
                let tls = tls.clone().unwrap_or_default();
                let mut config = ClientTlsConfig::new();
                config = match tls.ca_certificate {
                    Some(pem) => config.ca_certificate(Certificate::from_pem(pem)),
                    None => config.with_native_roots(),
                };
                if let Some((cert, key)) = tls.identity {
                    config = config.identity(Identity::from_pem(cert, key));
                }
                if let Some(name) = tls.server_name {
                    config = config.domain_name(name);
                }
                target = target.tls_config(config).map_err(connect_err)?;
            }
            (Some(_), false) => {
                return Err(ClientError::Invalid(format!(
                    "TLS settings (CA or client certificate) were given but {endpoint} is not https://; use an \
                     https:// endpoint"
                )));
            }
            (None, false) => {}
        }
        let channel = target.connect().await.map_err(connect_err)?;
        Ok(Self { channel, credentials })
    }

    /// The bare channel: calls made on it carry no token (health needs none).
    pub fn channel(&self) -> Channel {
        self.channel.clone()
    }

    /// The channel with this client's credentials, for service clients built by hand (the
    /// Open Inference Protocol's, say).
    pub fn transport(&self) -> Transport {
        InterceptedService::new(self.channel.clone(), self.credentials.clone())
    }

    pub fn datasets(&self) -> pb::dataset_service_client::DatasetServiceClient<Transport> {
        pb::dataset_service_client::DatasetServiceClient::new(self.transport())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    pub fn models(&self) -> pb::model_service_client::ModelServiceClient<Transport> {
        pb::model_service_client::ModelServiceClient::new(self.transport())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    pub fn jobs(&self) -> pb::job_service_client::JobServiceClient<Transport> {
        pb::job_service_client::JobServiceClient::new(self.transport())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    pub fn rewards(&self) -> pb::reward_service_client::RewardServiceClient<Transport> {
        pb::reward_service_client::RewardServiceClient::new(self.transport())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    /// Overall serving status from `grpc.health.v1` (service name "" = the whole server).
    pub async fn health(&self) -> Result<tonic_health::pb::health_check_response::ServingStatus, ClientError> {
        let resp = idempotent(|| {
            let mut health = tonic_health::pb::health_client::HealthClient::new(self.transport());
            async move { health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await }
        })
        .await?;
        Ok(resp.status())
    }

    /// Uploads a dataset: header, every array in row chunks, then the sha256 of the payload.
    /// Reading happens on a blocking thread so large files never stall the runtime; `progress`
    /// is updated as chunks are handed to the transport.
    pub async fn upload_dataset<S: UploadSource>(
        &self,
        upload: DatasetUpload,
        source: S,
        progress: Arc<UploadProgress>,
    ) -> Result<pb::Dataset, ClientError> {
        let specs = source.arrays().to_vec();
        let total = total_bytes(&specs).map_err(|e| ClientError::Invalid(e.to_string()))?;
        progress.total_bytes.store(total, Ordering::Relaxed);
        let header = pb::UploadHeader {
            name: upload.name,
            kind: upload.kind as i32,
            arrays: specs,
            description: upload.description,
        };
        let (tx, rx) = mpsc::channel(4);
        let chunk_bytes = upload.chunk_bytes.max(1);
        let producer = tokio::task::spawn_blocking(move || produce(source, header, chunk_bytes, tx, &progress));
        let mut datasets = self.datasets();
        let rpc = datasets.upload_dataset(ReceiverStream::new(rx));
        finish_upload(tokio::join!(rpc, producer))
    }

    pub async fn get_dataset(&self, name: &str) -> Result<pb::Dataset, ClientError> {
        let req = pb::GetDatasetRequest { name: name.to_owned(), view: pb::DatasetView::Full as i32 };
        idempotent(|| {
            let (mut datasets, req) = (self.datasets(), req.clone());
            async move { datasets.get_dataset(req).await }
        })
        .await
    }

    /// Every dataset, following pagination to the end.
    pub async fn list_datasets(&self) -> Result<Vec<pb::Dataset>, ClientError> {
        all_pages(|page| async move {
            let req = pb::ListDatasetsRequest { page: Some(page), view: pb::DatasetView::Basic as i32 };
            let resp = idempotent(|| {
                let (mut datasets, req) = (self.datasets(), req.clone());
                async move { datasets.list_datasets(req).await }
            })
            .await?;
            Ok((resp.datasets, resp.next_page_token))
        })
        .await
    }

    pub async fn delete_dataset(&self, name: &str) -> Result<(), ClientError> {
        self.datasets().delete_dataset(pb::DeleteDatasetRequest { name: name.to_owned() }).await?;
        Ok(())
    }

    // -----------------------------------------------------------------------------------------
    // Models

    /// Registers the model file at `path`: `header` (name, manifest, description, format), the
    /// file's bytes in chunks of [`DEFAULT_CHUNK_BYTES`], then its sha256. A diffusion model's
    /// header carries `manifest`; a bring-your-own TorchScript reward's carries `reward` (a
    /// `RewardUploadManifest`, e.g. `relreward_proto::schema::manifest::RewardUploadManifest`'s
    /// `to_proto`) and no `manifest`. The file is read on a blocking thread; `progress` counts
    /// the bytes handed to the transport.
    pub async fn upload_model(
        &self,
        header: pb::UploadModelHeader,
        path: &Path,
        progress: Arc<UploadProgress>,
    ) -> Result<pb::Model, ClientError> {
        let (tx, rx) = mpsc::channel(4);
        let path = path.to_owned();
        let producer =
            tokio::task::spawn_blocking(move || produce_file(&path, header, DEFAULT_CHUNK_BYTES, tx, &progress));
        let mut models = self.models();
        let rpc = models.upload_model(ReceiverStream::new(rx));
        finish_upload(tokio::join!(rpc, producer))
    }

    pub async fn get_model(&self, name: &str) -> Result<pb::Model, ClientError> {
        idempotent(|| {
            let mut models = self.models();
            async move { models.get_model(pb::GetModelRequest { name: name.to_owned() }).await }
        })
        .await
    }

    /// Every model of `kind` (`ModelKind::Unspecified`: every model), following pagination.
    pub async fn list_models(&self, kind: pb::ModelKind) -> Result<Vec<pb::Model>, ClientError> {
        all_pages(|page| async move {
            let req = pb::ListModelsRequest { page: Some(page), kind: kind as i32 };
            let resp = idempotent(|| {
                let (mut models, req) = (self.models(), req.clone());
                async move { models.list_models(req).await }
            })
            .await?;
            Ok((resp.models, resp.next_page_token))
        })
        .await
    }

    /// Registers a named sampling recipe over a conditional diffusion model (not retried: a
    /// second attempt after a lost answer would meet ALREADY_EXISTS).
    pub async fn create_recipe(&self, req: pb::CreateRecipeRequest) -> Result<pb::Model, ClientError> {
        Ok(self.models().create_recipe(req).await?.into_inner())
    }

    pub async fn delete_model(&self, name: &str) -> Result<(), ClientError> {
        self.models().delete_model(pb::DeleteModelRequest { name: name.to_owned() }).await?;
        Ok(())
    }

    // -----------------------------------------------------------------------------------------
    // Jobs

    /// Queues a job. With a `job_id`, resubmitting the same spec returns the existing job.
    pub async fn submit_job(&self, spec: pb::JobSpec, job_id: Option<&str>) -> Result<pb::Job, ClientError> {
        let req = pb::SubmitJobRequest { spec: Some(spec), job_id: job_id.unwrap_or_default().to_owned() };
        Ok(self.jobs().submit_job(req).await?.into_inner())
    }

    pub async fn get_job(&self, id: &str) -> Result<pb::Job, ClientError> {
        idempotent(|| {
            let mut jobs = self.jobs();
            async move { jobs.get_job(pb::GetJobRequest { id: id.to_owned() }).await }
        })
        .await
    }

    /// Every job in `state` (`JobState::Unspecified`: every job), newest first, following
    /// pagination.
    pub async fn list_jobs(&self, state: pb::JobState) -> Result<Vec<pb::Job>, ClientError> {
        all_pages(|page| async move {
            let req = pb::ListJobsRequest { page: Some(page), state: state as i32 };
            let resp = idempotent(|| {
                let (mut jobs, req) = (self.jobs(), req.clone());
                async move { jobs.list_jobs(req).await }
            })
            .await?;
            Ok((resp.jobs, resp.next_page_token))
        })
        .await
    }

    pub async fn cancel_job(&self, id: &str) -> Result<pb::Job, ClientError> {
        Ok(self.jobs().cancel_job(pb::CancelJobRequest { id: id.to_owned() }).await?.into_inner())
    }

    /// The job's events from `from_seq` (0 or 1: from the first), then live ones until the job
    /// is finished. One stream, one connection: see [`Client::follow_job`] for a watch that
    /// survives reconnects.
    pub async fn watch_job(&self, id: &str, from_seq: u64) -> Result<tonic::Streaming<pb::JobEvent>, ClientError> {
        let req = pb::WatchJobRequest { id: id.to_owned(), from_seq };
        Ok(self.jobs().watch_job(req).await?.into_inner())
    }

    // -----------------------------------------------------------------------------------------
    // Rewards

    /// rho per item (and per window and per step when the request asks for them).
    pub async fn score(&self, request: pb::ScoreRequest) -> Result<pb::ScoreResponse, ClientError> {
        idempotent(|| {
            let (mut rewards, request) = (self.rewards(), request.clone());
            async move { rewards.score(request).await }
        })
        .await
    }

    /// grad_x rho(x_t, t) and rho for one batch.
    pub async fn gradient(&self, request: pb::GradientRequest) -> Result<pb::GradientResponse, ClientError> {
        idempotent(|| {
            let (mut rewards, request) = (self.rewards(), request.clone());
            async move { rewards.gradient(request).await }
        })
        .await
    }

    /// Opens a `GradientStream`: one stream per planner episode, one request per denoising
    /// step. Responses may come in any order; match them by `request_id`.
    pub async fn gradient_stream(&self) -> Result<GradientStream, ClientError> {
        let (sender, rx) = mpsc::channel(GRADIENT_STREAM_BUFFER);
        let responses = self.rewards().gradient_stream(ReceiverStream::new(rx)).await?.into_inner();
        Ok(GradientStream { sender, responses })
    }

    /// Samples from a base diffusion model, guided by a reward model when the request names one.
    /// Each sample arrives as its batch finishes, tagged with its `index`.
    pub async fn sample(
        &self,
        request: pb::SampleRequest,
    ) -> Result<tonic::Streaming<pb::SampleResponse>, ClientError> {
        Ok(self.rewards().sample(request).await?.into_inner())
    }

    // -----------------------------------------------------------------------------------------
    // Latents

    /// Images `[B, *image_shape]` to scaled latents through an autoencoder model, one batch per
    /// call (a computation: retried like Score). The answer must fit the server's
    /// `server.max_response_bytes`; split larger inputs.
    pub async fn encode(&self, request: pb::EncodeRequest) -> Result<pb::EncodeResponse, ClientError> {
        idempotent(|| {
            let (mut rewards, request) = (self.rewards(), request.clone());
            async move { rewards.encode(request).await }
        })
        .await
    }

    /// Scaled latents `[B, *latent_shape]` back to images through an autoencoder model.
    pub async fn decode(&self, request: pb::DecodeRequest) -> Result<pb::DecodeResponse, ClientError> {
        idempotent(|| {
            let (mut rewards, request) = (self.rewards(), request.clone());
            async move { rewards.decode(request).await }
        })
        .await
    }
}

/// Requests queued on a [`GradientStream`] before [`GradientStream::send`] waits.
const GRADIENT_STREAM_BUFFER: usize = 16;

/// Both ends of an open `GradientStream` call. Dropping the sender (or calling
/// [`GradientStream::close`]) ends the request side; the server then finishes the responses
/// still owed and ends the stream.
pub struct GradientStream {
    sender: mpsc::Sender<pb::GradientRequest>,
    responses: tonic::Streaming<pb::GradientResponse>,
}

impl GradientStream {
    /// Queues one request (waits while the buffer is full). Fails only when the call has
    /// ended; [`GradientStream::message`] then returns the status that ended it.
    pub async fn send(&self, request: pb::GradientRequest) -> Result<(), ClientError> {
        self.sender.send(request).await.map_err(|_| {
            ClientError::Invalid("the gradient stream has ended; read its responses for the reason".into())
        })
    }

    /// The next response, or `None` once the server has answered everything and the request
    /// side is closed. A failed request comes back as a response whose `error` is set (see
    /// [`stream_error_status`]); the stream goes on. An error here ends the call.
    pub async fn message(&mut self) -> Result<Option<pb::GradientResponse>, ClientError> {
        Ok(self.responses.message().await?)
    }

    /// Ends the request side and returns the response side alone.
    pub fn close(self) -> tonic::Streaming<pb::GradientResponse> {
        self.responses
    }

    /// A sender for other tasks (e.g. one per planner worker sharing the stream).
    pub fn sender(&self) -> mpsc::Sender<pb::GradientRequest> {
        self.sender.clone()
    }
}

/// The status a per-request `StreamError` on `GradientStream` stands for.
pub fn stream_error_status(error: &pb::StreamError) -> tonic::Status {
    tonic::Status::new(tonic::Code::from_i32(error.code), error.message.clone())
}

/// Every item of a paged listing: calls `page` with each page request (server default size)
/// until the server returns an empty next-page token.
async fn all_pages<T, F, Fut>(mut page: F) -> Result<Vec<T>, ClientError>
where
    F: FnMut(pb::PageRequest) -> Fut,
    Fut: std::future::Future<Output = Result<(Vec<T>, String), ClientError>>,
{
    let mut out = Vec::new();
    let mut token = String::new();
    loop {
        let (items, next) = page(pb::PageRequest { page_size: 0, page_token: token }).await?;
        out.extend(items);
        if next.is_empty() {
            return Ok(out);
        }
        token = next;
    }
}

/// What an upload's blocking reader task ended with.
type ReaderOutcome = Result<Result<(), ClientError>, tokio::task::JoinError>;

/// The outcome of an upload from its RPC and its reader task. A local read failure aborted the
/// stream (no commit was sent): report that, not the server's complaint about the missing
/// commit.
fn finish_upload<T>(
    (rpc, produced): (Result<tonic::Response<T>, tonic::Status>, ReaderOutcome),
) -> Result<T, ClientError> {
    match produced {
        Ok(Ok(())) => Ok(rpc?.into_inner()),
        Ok(Err(e)) => Err(e),
        Err(join) => Err(ClientError::Invalid(format!("upload reader crashed: {join}"))),
    }
}

/// Runs on a blocking thread: reads each array, sends row chunks, hashes as it goes, and sends
/// the commit only if everything was read. Returning early drops `tx` without a commit, which
/// the server treats as an abandoned upload.
fn produce<S: UploadSource>(
    mut source: S,
    header: pb::UploadHeader,
    chunk_bytes: u64,
    tx: mpsc::Sender<pb::UploadDatasetRequest>,
    progress: &UploadProgress,
) -> Result<(), ClientError> {
    use pb::upload_dataset_request::Message;
    let specs = header.arrays.clone();
    let send = |m: Message| tx.blocking_send(pb::UploadDatasetRequest { message: Some(m) }).is_ok();
    if !send(Message::Header(header)) {
        return Ok(()); // the RPC ended early; its status says why
    }
    let mut hasher = Sha256::new();
    for (i, spec) in specs.iter().enumerate() {
        let row = row_bytes(spec).map_err(|e| ClientError::Invalid(format!("array '{}': {e}", spec.name)))?;
        let rows_total = spec.shape.first().copied().unwrap_or(0);
        let step = rows_per_chunk(row, chunk_bytes);
        let mut reader = source.open(i)?;
        let mut done = 0u64;
        while done < rows_total {
            let rows = step.min(rows_total - done);
            let mut buf =
                vec![0u8; usize::try_from(rows * row).map_err(|_| ClientError::Invalid("chunk too large".into()))?];
            reader.read_exact(&mut buf)?;
            hasher.update(&buf);
            let mut shape = spec.shape.clone();
            shape[0] = rows;
            let n = buf.len() as u64;
            let chunk = pb::DatasetChunk {
                array: spec.name.clone(),
                data: Some(pb::Tensor { shape, dtype: spec.dtype, data: buf }),
            };
            if !send(Message::Chunk(chunk)) {
                return Ok(());
            }
            progress.sent_bytes.fetch_add(n, Ordering::Relaxed);
            done += rows;
        }
    }
    let sha256 = hex::encode(hasher.finalize());
    send(Message::Commit(pb::UploadCommit { sha256 }));
    Ok(())
}

/// Runs on a blocking thread: sends the header, the file at `path` in chunks, then the
/// commit with the file's sha256 (only if the whole file was read).
fn produce_file(
    path: &Path,
    header: pb::UploadModelHeader,
    chunk_bytes: u64,
    tx: mpsc::Sender<pb::UploadModelRequest>,
    progress: &UploadProgress,
) -> Result<(), ClientError> {
    use pb::upload_model_request::Message;
    let file_err = |source| ClientError::File { path: path.to_owned(), source };
    let file = std::fs::File::open(path).map_err(file_err)?;
    let len = file.metadata().map_err(file_err)?.len();
    progress.total_bytes.store(len, Ordering::Relaxed);
    let send = |m: Message| tx.blocking_send(pb::UploadModelRequest { message: Some(m) }).is_ok();
    if !send(Message::Header(header)) {
        return Ok(()); // the RPC ended early; its status says why
    }
    let mut hasher = Sha256::new();
    let mut reader = std::io::BufReader::new(file);
    loop {
        let mut buf = Vec::new();
        (&mut reader).take(chunk_bytes.max(1)).read_to_end(&mut buf).map_err(file_err)?;
        if buf.is_empty() {
            break;
        }
        hasher.update(&buf);
        let n = buf.len() as u64;
        if !send(Message::Chunk(buf)) {
            return Ok(());
        }
        progress.sent_bytes.fetch_add(n, Ordering::Relaxed);
    }
    let sha256 = hex::encode(hasher.finalize());
    send(Message::Commit(pb::UploadCommit { sha256 }));
    Ok(())
}

/// Lowercase hex sha256 of the concatenated raw bytes of `source`'s arrays: the digest an upload
/// of it commits with.
pub fn payload_sha256<S: UploadSource>(source: &mut S) -> std::io::Result<String> {
    let mut hasher = Sha256::new();
    let n = source.arrays().len();
    let mut buf = vec![0u8; 1 << 16];
    for i in 0..n {
        let mut r = source.open(i)?;
        loop {
            let k = r.read(&mut buf)?;
            if k == 0 {
                break;
            }
            hasher.update(&buf[..k]);
        }
    }
    Ok(hex::encode(hasher.finalize()))
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicU32;

    use super::*;

    /// [`IDEMPOTENT_RETRY`] scaled down a hundredfold, so the tests take milliseconds.
    const FAST: RetryPolicy = RetryPolicy {
        initial_delay: Duration::from_micros(500),
        max_delay: Duration::from_millis(10),
        budget: Duration::from_millis(50),
    };

    /// A status like the one tonic makes when the connection under a call closes.
    fn connection_closed() -> tonic::Status {
        let cause = std::io::Error::new(std::io::ErrorKind::ConnectionReset, "connection closed");
        tonic::Status::from_error(Box::new(cause))
    }

    #[tokio::test]
    async fn idempotent_calls_ride_over_a_closed_connection() {
        let calls = AtomicU32::new(0);
        let answer = retry_connection_failures(FAST, || {
            let n = calls.fetch_add(1, Ordering::SeqCst);
            async move { if n < 2 { Err(connection_closed()) } else { Ok(tonic::Response::new(n)) } }
        })
        .await;
        assert_eq!(answer.expect("third try"), 2);
        assert_eq!(calls.load(Ordering::SeqCst), 3);
    }

    #[tokio::test]
    async fn errors_the_server_chose_are_not_retried() {
        let calls = AtomicU32::new(0);
        let answer: Result<(), _> = retry_connection_failures(FAST, || {
            calls.fetch_add(1, Ordering::SeqCst);
            async { Err(tonic::Status::not_found("model \"m\" not found")) }
        })
        .await;
        assert!(matches!(answer, Err(ClientError::Status(s)) if s.code() == tonic::Code::NotFound));
        assert_eq!(calls.load(Ordering::SeqCst), 1);
    }

    #[tokio::test]
    async fn a_server_that_stays_away_is_reported_within_the_budget() {
        let calls = AtomicU32::new(0);
        let started = tokio::time::Instant::now();
        let answer: Result<(), _> = retry_connection_failures(FAST, || {
            calls.fetch_add(1, Ordering::SeqCst);
            async { Err(tonic::Status::unavailable("connection refused")) }
        })
        .await;
        assert!(matches!(answer, Err(ClientError::Status(s)) if s.code() == tonic::Code::Unavailable));
        let waited = started.elapsed();
        assert!(waited >= FAST.budget && waited < Duration::from_secs(2), "{waited:?}");
        assert!(calls.load(Ordering::SeqCst) > 3, "a few attempts with backoff");
    }
}
