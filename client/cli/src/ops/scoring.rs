//! Scores from the server: [`ServerScorer`], the toolkit's [`Scorer`] over `Score` (a connected
//! client, a reward model, a diffusion time, the items), the checked float arrays of an answer,
//! and server errors labelled with the flag behind the field they name.

use std::ops::Range;

use anyhow::{Result, anyhow, bail};
use relreward_client::{Client, ClientError, pb, tensor};
use relreward_toolkit::eval::scorer::{BatchScores, Scorer};

use super::items::Items;

/// Requests in flight at once: one computing while the next travels.
pub const IN_FLIGHT: usize = 2;

/// float32 or float64 values of a response tensor (non-finite values are kept).
pub fn floats(t: Option<&pb::Tensor>, field: &str, shape: &[u64]) -> Result<Vec<f32>> {
    let t = t.ok_or_else(|| anyhow!("the server's answer has no {field}"))?;
    if t.shape != shape {
        bail!("the server's answer has {field} of shape {:?} where {shape:?} was expected", t.shape);
    }
    let mut out = Vec::with_capacity(t.data.len() / 4);
    tensor::for_each_float(t, |v| out.push(v as f32)).map_err(|e| anyhow!("the server's {field}: {e}"))?;
    Ok(out)
}

/// Mean, population standard deviation, min and max (`None` for no values).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Summary {
    pub mean: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
}

pub fn summarize(values: impl IntoIterator<Item = f64>) -> Option<Summary> {
    let (mut n, mut mean, mut m2) = (0u64, 0.0f64, 0.0f64);
    let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        n += 1;
        let delta = v - mean;
        mean += delta / n as f64;
        m2 += delta * (v - mean);
        min = min.min(v);
        max = max.max(v);
    }
    (n > 0).then(|| Summary { mean, std: (m2 / n as f64).sqrt(), min, max })
}

/// The flag behind a server error whose message starts with a request field (`t[0]: ..`,
/// `omega: ..`), from `fields`: (request field, flag as the user gave it).
pub fn flag_of(err: &ClientError, fields: &[(&str, String)]) -> Option<String> {
    let ClientError::Status(status) = err else { return None };
    let message = status.message();
    let end = message.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(message.len());
    let (field, rest) = message.split_at(end);
    if !rest.starts_with([':', '[', '.']) {
        return None;
    }
    fields.iter().find(|(f, _)| *f == field).map(|(_, flag)| flag.clone())
}

/// A failed request's error, labelled with the flag it concerns (see [`flag_of`]) and, when
/// the input took several requests and the fault may lie in the items, with the items sent.
pub fn request_error(
    err: ClientError,
    fields: &[(&str, String)],
    range: &Range<usize>,
    n: usize,
    several: bool,
) -> anyhow::Error {
    let flag = flag_of(&err, fields);
    let items = format!("items {}..{} of {n}", range.start, range.end);
    let label = match flag {
        Some(flag) if flag == "--input" && several => Some(format!("--input, {items}")),
        Some(flag) => Some(flag),
        None if several => Some(items),
        None => None,
    };
    let err = anyhow::Error::new(err);
    match label {
        Some(label) => err.context(label),
        None => err,
    }
}

/// Scores items of `items` with `model` at diffusion time `t` (raw units), one `Score` request
/// per batch; errors are labelled as [`request_error`] does, `flag` naming the items' file.
pub struct ServerScorer<'a> {
    pub client: &'a Client,
    pub model: &'a str,
    pub t: u32,
    pub items: &'a Items,
    /// Request fields and the flags that set them (see [`flag_of`]).
    pub fields: Vec<(&'static str, String)>,
    /// Whether the items take several requests (errors then name the items sent).
    pub several: bool,
}

impl Scorer for ServerScorer<'_> {
    type Error = anyhow::Error;

    async fn score(&self, range: Range<usize>, per_window: bool) -> Result<BatchScores> {
        let b = range.len() as u64;
        let request = pb::ScoreRequest {
            model: self.model.to_owned(),
            x: Some(self.items.batch(range.clone())),
            t: vec![self.t],
            input_units: pb::Units::Raw as i32,
            per_window,
            per_step: false,
        };
        let answer = self
            .client
            .score(request)
            .await
            .map_err(|e| request_error(e, &self.fields, &range, self.items.len(), self.several))?;
        let rewards = floats(answer.rewards.as_ref(), "rewards", &[b])?;
        let per_window = if per_window {
            let width = match answer.per_window.as_ref() {
                Some(t) if t.shape.len() == 2 && t.shape[1] > 0 => t.shape[1],
                other => bail!(
                    "the server's answer has no per-window values of shape [{b}, K] (got {:?})",
                    other.map(|t| &t.shape)
                ),
            };
            Some((width as usize, floats(answer.per_window.as_ref(), "per_window", &[b, width])?))
        } else {
            None
        };
        Ok(BatchScores { rewards, per_window })
    }
}
