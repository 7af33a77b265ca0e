//! Encode and Decode: images to latents and back through an uploaded autoencoder
//! ([`crate::engine::autoencoder`]), the latent space's doors (issue 37, item 3). The door
//! (`api::rewards`) hands over a request and gets back plain float32 values: it never touches a
//! tensor or a model's lock.
//!
//! - [`Latents::run`]: the one place an Encode or Decode request is validated, in this order:
//!   the model's name; the model (NOT_FOUND, or FAILED_PRECONDITION for another kind); the
//!   tensor (present, float32 or float64, shape `[B, *item]` with B >= 1 for the autoencoder's
//!   image or latent shape, every value finite and within float32); the answer's size (B
//!   outputs must fit `server.max_response_bytes`, RESOURCE_EXHAUSTED naming it and the
//!   largest batch that fits). Messages name the field (`images`, `latents`).
//! - Compute: one call is one pass, on the runtime's blocking pool under an inference slot
//!   (`engine.inference_workers`, shared with the Score/Gradient batcher and the sampling
//!   workers, so the three together cannot oversubscribe the CPU or the device), in the
//!   `latents` task group that shutdown waits for. No queue or batcher of its own: a call is
//!   already a batch of images, and a caller waiting for a slot holds only its request.
//! - The answer is checked finite on the host (an input in range whose output is not finite is
//!   refused as INVALID_ARGUMENT naming the input field, as Score refuses such an x).

use std::sync::Arc;

use relreward_proto::tensor;
use relreward_proto::v1 as pb;
use tokio::sync::Semaphore;

use crate::engine::autoencoder::Direction;
use crate::error::{Error, Result, brief};
use crate::fields::validate_name;
use crate::registry::ModelRegistry;
use crate::tasks::Tasks;

/// What a response message adds to its tensor's bytes (field tags, lengths, the shape), with
/// room to spare.
const RESPONSE_FRAMING_BYTES: u64 = 256;

/// An Encode or Decode answer: float32 values, row-major, of `shape`.
#[derive(Debug, Clone, PartialEq)]
pub struct Converted {
    pub shape: Vec<u64>,
    pub values: Vec<f32>,
}

/// The handle the door holds.
#[derive(Clone)]
pub struct Latents {
    inner: Arc<Inner>,
}

struct Inner {
    registry: ModelRegistry,
    slots: Arc<Semaphore>,
    max_response_bytes: u64,
    tasks: Tasks,
}

impl Latents {
    /// `slots`: the inference slots (shared with serving and sampling); `max_response_bytes`:
    /// `server.max_response_bytes`, which every answer must fit.
    pub fn new(registry: ModelRegistry, slots: Arc<Semaphore>, max_response_bytes: usize, tasks: Tasks) -> Self {
        Self { inner: Arc::new(Inner { registry, slots, max_response_bytes: max_response_bytes as u64, tasks }) }
    }

    /// Encodes images (`Direction::Encode`, the request's `images`) or decodes latents
    /// (`Direction::Decode`, `latents`) with autoencoder `model`; see the module doc for the
    /// checks and their order.
    pub async fn run(&self, direction: Direction, model: &str, input: Option<&pb::Tensor>) -> Result<Converted> {
        let field = match direction {
            Direction::Encode => "images",
            Direction::Decode => "latents",
        };
        validate_name("model", model)?;
        let autoencoder = self.inner.registry.get_autoencoder(model).await?;
        let manifest = &autoencoder.manifest;
        let (item, output, item_word) = match direction {
            Direction::Encode => (&manifest.image_shape, &manifest.latent_shape, "images"),
            Direction::Decode => (&manifest.latent_shape, &manifest.image_shape, "latents"),
        };
        let input = input.ok_or_else(|| Error::invalid(format!("{field}: missing")))?;
        let shape_ok = input.shape.len() == item.len() + 1
            && input.shape[0] >= 1
            && input.shape[1..].iter().zip(item.iter()).all(|(&a, &b)| a == b as u64);
        if !shape_ok {
            return Err(Error::invalid(format!(
                "{field}: shape {} but autoencoder '{model}' takes {item_word} of shape [B, {}] with B >= 1",
                brief(&input.shape),
                item.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")
            )));
        }
        let batch = input.shape[0];
        let values = tensor::decode_finite_f32(input).map_err(|e| Error::invalid(format!("{field}: {e}")))?;
        let per_item = output.iter().map(|&d| d as u64).product::<u64>().saturating_mul(4);
        let answer_bytes = per_item.saturating_mul(batch).saturating_add(RESPONSE_FRAMING_BYTES);
        let max = self.inner.max_response_bytes;
        if answer_bytes > max {
            let fits = max.saturating_sub(RESPONSE_FRAMING_BYTES) / per_item.max(1);
            return Err(Error::ResourceExhausted(format!(
                "{field}: the answer for {batch} {item_word} ({answer_bytes} bytes) would exceed \
                 server.max_response_bytes ({max}); send at most {fits} per call"
            )));
        }
        let token = self.inner.tasks.token().clone();
        let slot = tokio::select! {
            biased;
            () = token.cancelled() => None,
            permit = Arc::clone(&self.inner.slots).acquire_owned() => permit.ok(),
        }
        .ok_or_else(|| Error::Unavailable("the server is shutting down".into()))?;
        let rows = i64::try_from(batch).map_err(|_| Error::invalid(format!("{field}: {batch} items is too many")))?;
        let worker = Arc::clone(&autoencoder);
        let values = self
            .inner
            .tasks
            .spawn_blocking(move || {
                let _slot = slot;
                worker.lock().run(direction, &values, rows)
            })
            .await
            .map_err(|e| Error::internal("autoencoder task", e))??;
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(format!(
                "{field}: autoencoder '{model}''s {} of these {item_word} is not finite (output element {i}); \
                 nothing is answered",
                direction.method()
            )));
        }
        let mut shape = vec![batch];
        shape.extend(output.iter().map(|&d| d as u64));
        Ok(Converted { shape, values })
    }

    /// Shutdown, after the calls' grace: no call waits for a slot any more; waits at most
    /// `bound` for the passes under way (a pass cannot be interrupted).
    pub async fn stop(&self, bound: std::time::Duration) -> bool {
        self.inner.tasks.stop(bound).await
    }
}
