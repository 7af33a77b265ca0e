//! `relreward.v1.RewardService`: Score, Gradient and GradientStream over [`Serving`] (which
//! validates, in [`crate::serving::query`], then batches and computes), Sample over
//! [`Sampling`] (validated there, computed by its workers, its samples streamed back as host
//! rows), and Encode and Decode over [`Latents`] (validated there, one pass under an inference
//! slot, host values back). The handlers only convert between the wire and those three: no
//! tensor, no model lock, and every task they start belongs to the server's `streams` group
//! ([`Tasks`]).

use std::pin::Pin;

use futures::stream::FuturesUnordered;
use futures::{Stream, StreamExt};
use relreward_proto::tensor;
use relreward_proto::v1::{self as pb, reward_service_server::RewardService};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status, Streaming};

use crate::engine::autoencoder::Direction;
use crate::error::{Error, Result};
use crate::latents::{Converted, Latents};
use crate::sampling::{SampleRow, Sampling};
use crate::serving::{self, Answer, HostTensor, Query, Serving};
use crate::tasks::Tasks;

/// Responses buffered per GradientStream before the server waits for the client to read.
const STREAM_BUFFER: usize = 64;

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

pub struct Rewards {
    serving: Serving,
    sampling: Sampling,
    latents: Latents,
    /// GradientStream's tasks: cancelled when the listener closes (see [`serve_stream`]).
    streams: Tasks,
}

impl Rewards {
    pub fn new(serving: Serving, sampling: Sampling, latents: Latents, streams: Tasks) -> Self {
        Self { serving, sampling, latents, streams }
    }
}

async fn answer_gradient(
    serving: &Serving,
    req: &pb::GradientRequest,
    deadline: Option<std::time::Instant>,
) -> Result<pb::GradientResponse> {
    let answer = serving.query(&req.model, Query::gradient(req, deadline)?).await?;
    let gradient = answer.gradient.as_ref().map(host_f32).transpose()?;
    Ok(pb::GradientResponse {
        request_id: req.request_id,
        gradient,
        rewards: Some(host_f32(&answer.rewards)?),
        error: None,
    })
}

fn score_response(answer: &Answer) -> Result<pb::ScoreResponse> {
    Ok(pb::ScoreResponse {
        rewards: Some(host_f32(&answer.rewards)?),
        per_window: answer.per_window.as_ref().map(host_f32).transpose()?,
        per_step: answer.per_step.as_ref().map(host_f32).transpose()?,
    })
}

fn sample_response(item_shape: &[i64], row: SampleRow) -> Result<pb::SampleResponse> {
    Ok(pb::SampleResponse {
        index: row.index,
        x: Some(f32_tensor(item_shape, &row.x)?),
        x_normalized: Some(f32_tensor(item_shape, &row.x_normalized)?),
        reward: row.reward,
        prompt: row.prompt,
    })
}

/// An Encode or Decode answer on the wire.
fn converted(c: Converted) -> pb::Tensor {
    tensor::encode_f32(&c.shape, &c.values)
}

/// A float32 wire tensor from host values (Score and Gradient answers).
fn host_f32(h: &HostTensor) -> Result<pb::Tensor> {
    f32_tensor(&h.shape, &h.values)
}

/// A float32 wire tensor of `shape` from row-major host values: one copy into the wire's
/// little-endian bytes, no libtorch call.
fn f32_tensor(shape: &[i64], values: &[f32]) -> Result<pb::Tensor> {
    let shape: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let mut data = Vec::with_capacity(values.len() * 4);
    for v in values {
        data.extend_from_slice(&v.to_le_bytes());
    }
    tensor::from_raw(&shape, pb::Dtype::Float32, data).map_err(|e| Error::internal("encoding a result tensor", e))
}

/// One GradientStream: answers every request as soon as its batch is done (in any order,
/// matched by request_id); a failed request gets its error in its response and the stream
/// goes on. A frame that cannot be read (undecodable, or over the size limit) ends the stream
/// with INVALID_ARGUMENT (RESOURCE_EXHAUSTED) once the requests before it are answered. When
/// the client goes away, queries still queued are skipped. When `stop` is cancelled (the
/// listener closes at shutdown), no more requests are read: those in flight are answered,
/// then the stream ends UNAVAILABLE, so the client reconnects elsewhere.
async fn serve_stream(
    serving: Serving,
    mut inbound: Streaming<pb::GradientRequest>,
    deadline: Option<std::time::Instant>,
    tx: mpsc::Sender<Result<pb::GradientResponse, Status>>,
    stop: CancellationToken,
) {
    let mut in_flight = FuturesUnordered::new();
    let mut inbound_open = true;
    // Why the inbound stream broke, if it did: the stream then ends with this status once
    // the requests in flight are answered, never with OK.
    let mut broken: Option<Status> = None;
    loop {
        tokio::select! {
            message = inbound.message(), if inbound_open => match message {
                Ok(Some(req)) => {
                    let serving = serving.clone();
                    in_flight.push(async move {
                        match answer_gradient(&serving, &req, deadline).await {
                            Ok(response) => response,
                            Err(e) => {
                                let status = Status::from(e);
                                pb::GradientResponse {
                                    request_id: req.request_id,
                                    error: Some(pb::StreamError {
                                        code: status.code() as i32,
                                        message: status.message().to_owned(),
                                    }),
                                    ..Default::default()
                                }
                            }
                        }
                    });
                }
                Ok(None) => inbound_open = false,
                Err(status) => {
                    // A broken inbound stream (an undecodable frame, one over the size
                    // limit, or the client gone): answer what is in flight if anyone still
                    // listens, accept nothing more, end with the error.
                    tracing::debug!(error = %status, "GradientStream: inbound stream ended with an error");
                    inbound_open = false;
                    broken = Some(Error::from_inbound("request stream", &status).into());
                }
            },
            () = stop.cancelled(), if inbound_open => {
                inbound_open = false;
                broken = Some(Error::Unavailable("the server is shutting down; reconnect to go on".into()).into());
            }
            Some(response) = in_flight.next(), if !in_flight.is_empty() => {
                if tx.send(Ok(response)).await.is_err() {
                    return;
                }
            }
            () = tx.closed() => return,
        }
        if !inbound_open && in_flight.is_empty() {
            if let Some(status) = broken {
                let _ = tx.send(Err(status)).await;
            }
            return;
        }
    }
}

#[tonic::async_trait]
impl RewardService for Rewards {
    type GradientStreamStream = BoxStream<pb::GradientResponse>;
    type SampleStream = BoxStream<pb::SampleResponse>;

    async fn score(&self, request: Request<pb::ScoreRequest>) -> Result<Response<pb::ScoreResponse>, Status> {
        let deadline = serving::deadline_of(request.metadata());
        let req = request.into_inner();
        let answer = self.serving.query(&req.model, Query::score(&req, deadline)?).await?;
        Ok(Response::new(score_response(&answer)?))
    }

    async fn gradient(&self, request: Request<pb::GradientRequest>) -> Result<Response<pb::GradientResponse>, Status> {
        let deadline = serving::deadline_of(request.metadata());
        let req = request.into_inner();
        Ok(Response::new(answer_gradient(&self.serving, &req, deadline).await?))
    }

    /// See [`serve_stream`].
    async fn gradient_stream(
        &self,
        request: Request<Streaming<pb::GradientRequest>>,
    ) -> Result<Response<Self::GradientStreamStream>, Status> {
        let deadline = serving::deadline_of(request.metadata());
        let (tx, rx) = mpsc::channel(STREAM_BUFFER);
        let stop = self.streams.token().clone();
        self.streams.spawn(serve_stream(self.serving.clone(), request.into_inner(), deadline, tx, stop));
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    /// Streams each sample as its batch finishes, with its reward rho(x, 0) when a reward
    /// model is given (guiding when omega != 0). A bad request is refused before the stream
    /// starts; a run that fails ends the stream with its error. Stops early when the client
    /// goes away.
    async fn sample(&self, request: Request<pb::SampleRequest>) -> Result<Response<Self::SampleStream>, Status> {
        let run = self.sampling.submit(&request.into_inner()).await?;
        let item_shape = run.item_shape;
        let responses =
            run.rows.map(move |row| -> Result<pb::SampleResponse, Status> { Ok(sample_response(&item_shape, row?)?) });
        Ok(Response::new(Box::pin(responses)))
    }

    async fn encode(&self, request: Request<pb::EncodeRequest>) -> Result<Response<pb::EncodeResponse>, Status> {
        let req = request.into_inner();
        let out = self.latents.run(Direction::Encode, &req.model, req.images.as_ref()).await?;
        Ok(Response::new(pb::EncodeResponse { latents: Some(converted(out)) }))
    }

    async fn decode(&self, request: Request<pb::DecodeRequest>) -> Result<Response<pb::DecodeResponse>, Status> {
        let req = request.into_inner();
        let out = self.latents.run(Direction::Decode, &req.model, req.latents.as_ref()).await?;
        Ok(Response::new(pb::DecodeResponse { images: Some(converted(out)) }))
    }
}
