//! Images to latents and back through an autoencoder model, over local `.npz` files (`relreward
//! encode` and `relreward decode`; the server's Encode and Decode, issue 37 item 3).
//!
//! The input array (`x` by default) is read whole, checked against the model's shape
//! (`[B, *image_shape]` to encode, `[B, *latent_shape]` to decode) before anything is sent,
//! and sent in requests of at most `batch` items, lowered so that neither a request nor its
//! answer carries more than [`MAX_REQUEST_BYTES`](super::items::MAX_REQUEST_BYTES) (half the
//! server's default request limit, an eighth of its response limit). The output `.npz` holds the
//! result under `out_key` (`x` by default, so that a file of latents uploads as a samples
//! dataset as it is) and every other array of the input copied unchanged (labels stay beside
//! their items); it is written to a temporary file and renamed into place only when complete.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use relreward_client::{Client, pb, tensor};
use relreward_toolkit::npz::{npz_keys, read_numbers};
use relreward_toolkit::npz_write::NpzWriter;
use serde::Serialize;

use super::items::MAX_REQUEST_BYTES;

/// Which way.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// Images to latents.
    Encode,
    /// Latents to images.
    Decode,
}

/// One conversion of a file.
#[derive(Debug, Clone)]
pub struct Conversion {
    /// The autoencoder model.
    pub model: String,
    pub direction: Direction,
    pub input: PathBuf,
    /// The input's array.
    pub key: String,
    pub out: PathBuf,
    /// The output's array.
    pub out_key: String,
    /// Items per request, before the size bound.
    pub batch: u64,
}

/// What a conversion did.
#[derive(Debug, Clone, Serialize)]
pub struct Converted {
    pub model: String,
    pub direction: Direction,
    pub input: PathBuf,
    pub out: PathBuf,
    pub key: String,
    pub out_key: String,
    pub items: u64,
    pub input_shape: Vec<u64>,
    pub output_shape: Vec<u64>,
    pub requests: usize,
    /// Other arrays of the input copied into the output.
    pub copied: Vec<String>,
}

/// Reads, converts in batches and writes; see the module doc. `on_batch` is told the items
/// done and the items in all after each request (a progress bar).
pub async fn convert(client: &Client, c: &Conversion, mut on_batch: impl FnMut(u64, u64)) -> Result<Converted> {
    let model = client.get_model(&c.model).await.with_context(|| format!("--model {}", c.model))?;
    let Some(info) = model.autoencoder.as_ref().filter(|_| model.kind() == pb::ModelKind::Autoencoder) else {
        bail!("--model {}: is not an autoencoder (relreward model list --kind autoencoder)", c.model);
    };
    let (item, output, what) = match c.direction {
        Direction::Encode => (&info.image_shape, &info.latent_shape, "images"),
        Direction::Decode => (&info.latent_shape, &info.image_shape, "latents"),
    };
    let (shape, values) = read_numbers(&c.input, &c.key)
        .with_context(|| format!("--input {}", c.input.display()))?
        .ok_or_else(|| anyhow!("--input {}: no array '{}' (choose one with --key)", c.input.display(), c.key))?;
    if shape.len() != item.len() + 1 || shape[1..] != item[..] {
        bail!(
            "--input {}: '{}' has shape {shape:?}, but autoencoder '{}' takes {what} of shape [B, {}]",
            c.input.display(),
            c.key,
            c.model,
            item.iter().map(u64::to_string).collect::<Vec<_>>().join(", ")
        );
    }
    let n = shape[0];
    if n == 0 {
        bail!("--input {}: '{}' holds no {what}", c.input.display(), c.key);
    }
    let mut narrowed = Vec::with_capacity(values.len());
    for (i, &v) in values.iter().enumerate() {
        if !v.is_finite() || tensor::beyond_f32(v) {
            bail!("--input {}: '{}' element {i} ({v:e}) is not a finite float32", c.input.display(), c.key);
        }
        narrowed.push(v as f32);
    }
    let in_len = item.iter().product::<u64>() as usize;
    let out_len = output.iter().product::<u64>() as usize;
    let per_item = 4 * in_len.max(out_len) as u64;
    let batch = c.batch.clamp(1, (MAX_REQUEST_BYTES / per_item.max(1)).max(1)) as usize;
    let mut result = Vec::with_capacity(n as usize * out_len);
    let mut requests = 0;
    for start in (0..n as usize).step_by(batch) {
        let end = (start + batch).min(n as usize);
        let mut batch_shape = vec![(end - start) as u64];
        batch_shape.extend_from_slice(item);
        let input = tensor::encode_f32(&batch_shape, &narrowed[start * in_len..end * in_len]);
        let label = || format!("--input {}, {what} {start}..{end} of {n}", c.input.display());
        let answer = match c.direction {
            Direction::Encode => {
                let req = pb::EncodeRequest { model: c.model.clone(), images: Some(input) };
                client.encode(req).await.with_context(label)?.latents
            }
            Direction::Decode => {
                let req = pb::DecodeRequest { model: c.model.clone(), latents: Some(input) };
                client.decode(req).await.with_context(label)?.images
            }
        };
        let answer = answer.ok_or_else(|| anyhow!("{}: the server answered no tensor", label()))?;
        let got = tensor::decode_finite_f32(&answer).with_context(label)?;
        if got.len() != (end - start) * out_len {
            bail!("{}: the server answered {} values, expected {}", label(), got.len(), (end - start) * out_len);
        }
        result.extend_from_slice(&got);
        requests += 1;
        on_batch(end as u64, n);
    }
    let mut output_shape = vec![n];
    output_shape.extend_from_slice(output);
    let copied = write(c, &output_shape, &result)?;
    Ok(Converted {
        model: c.model.clone(),
        direction: c.direction,
        input: c.input.clone(),
        out: c.out.clone(),
        key: c.key.clone(),
        out_key: c.out_key.clone(),
        items: n,
        input_shape: shape,
        output_shape,
        requests,
        copied,
    })
}

/// The output archive: the result, then the input's other arrays (an `.npy` input has none).
fn write(c: &Conversion, shape: &[u64], values: &[f32]) -> Result<Vec<String>> {
    let context = || format!("--out {}", c.out.display());
    let mut writer = NpzWriter::create(&c.out).with_context(context)?;
    writer.add_f32(&c.out_key, shape, values).with_context(context)?;
    let copied: Vec<String> = if is_npy(&c.input) {
        Vec::new()
    } else {
        let keys = npz_keys(&c.input).with_context(|| format!("--input {}", c.input.display()))?;
        keys.into_iter().filter(|k| *k != c.key && *k != c.out_key).collect()
    };
    if !copied.is_empty() {
        writer
            .copy_members(&c.input, |name| copied.iter().any(|k| k == name).then(|| name.to_owned()))
            .with_context(context)?;
    }
    writer.finish().with_context(context)?;
    Ok(copied)
}

fn is_npy(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy"))
}
