//! What `score`, `grad` and `sample` do with the server's answers: checked float arrays,
//! summaries, the `--out` archive, progress bars, errors labelled with the flag they concern,
//! and the request loop and report that `score` and `grad` share.

use std::ops::Range;
use std::path::Path;

use anyhow::{Context, Result, anyhow, bail};
use futures::StreamExt;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use relreward_client::{ClientError, pb, tensor};
use relreward_toolkit::npz_write::NpzWriter;
use serde_json::{Value, json};

use super::input::{InputArgs, Items};
use crate::commands::output::{bars_visible, check_out_file, fmt_num, key_values};
use crate::commands::{Ctx, Report};

/// Requests in flight at once: one computing while the next travels.
pub(crate) const IN_FLIGHT: usize = 2;

/// float32 or float64 values of a response tensor (non-finite values are kept).
pub(crate) fn floats(t: Option<&pb::Tensor>, field: &str, shape: &[u64]) -> Result<Vec<f32>> {
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

pub(crate) fn summary_json(s: Option<Summary>) -> Value {
    s.map_or(Value::Null, |s| json!({ "mean": s.mean, "std": s.std, "min": s.min, "max": s.max }))
}

pub(crate) fn summary_text(s: Option<Summary>) -> String {
    s.map_or_else(
        || "-".to_owned(),
        |s| format!("mean {}  std {}  min {}  max {}", fmt_num(s.mean), fmt_num(s.std), fmt_num(s.min), fmt_num(s.max)),
    )
}

/// Arrays for `--out`, in the order they are written.
#[derive(Debug, Default)]
pub(crate) struct OutArrays {
    pub(crate) f32s: Vec<(&'static str, Vec<u64>, Vec<f32>)>,
    pub(crate) i64s: Vec<(&'static str, Vec<u64>, Vec<i64>)>,
}

impl OutArrays {
    fn shapes_json(&self) -> Value {
        let mut map = serde_json::Map::new();
        for (name, shape, _) in &self.f32s {
            map.insert((*name).to_owned(), json!(shape));
        }
        for (name, shape, _) in &self.i64s {
            map.insert((*name).to_owned(), json!(shape));
        }
        Value::Object(map)
    }

    fn shapes_text(&self) -> String {
        let f = self.f32s.iter().map(|(n, s, _)| format!("{n} {s:?}"));
        let i = self.i64s.iter().map(|(n, s, _)| format!("{n} {s:?}"));
        f.chain(i).collect::<Vec<_>>().join(", ")
    }

    /// Writes the arrays to `out` when given; returns their shapes as JSON and as text.
    pub(crate) async fn write_to(self, out: Option<&Path>) -> Result<(Value, String)> {
        let shapes = (self.shapes_json(), self.shapes_text());
        if let Some(out) = out {
            self.write(out).await?;
        }
        Ok(shapes)
    }

    /// Writes the arrays to `path` (on a blocking thread).
    async fn write(self, path: &Path) -> Result<()> {
        let dest = path.to_owned();
        tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            let mut w = NpzWriter::create(&dest)?;
            for (name, shape, values) in &self.f32s {
                w.add_f32(name, shape, values)?;
            }
            for (name, shape, values) in &self.i64s {
                w.add_i64(name, shape, values)?;
            }
            w.finish()?;
            Ok(())
        })
        .await
        .context("writing the output crashed")?
        .map_err(|e| anyhow!("--out {}: {e}", path.display()))
    }
}

/// Refuses an `--out` whose directory does not exist before any work is done.
pub(crate) fn check_out(out: Option<&Path>) -> Result<()> {
    if let Some(out) = out {
        check_out_file("--out", out)?;
    }
    Ok(())
}

/// A count progress bar on stderr, hidden with `--json` or off a terminal.
pub(crate) fn item_bar(json: bool, total: u64, what: &str) -> ProgressBar {
    let target = if bars_visible(json) { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() };
    let template =
        format!("{{spinner}} {{elapsed_precise}} [{{wide_bar}}] {{pos}}/{{len}} {what} {{per_sec}} ETA {{eta}}");
    let style = ProgressStyle::with_template(&template)
        .map(|s| s.progress_chars("=> "))
        .unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::with_draw_target(Some(total), target).with_style(style)
}

/// The flag behind a server error whose message starts with a request field (`t[0]: ..`,
/// `omega: ..`), from `fields`: (request field, flag as the user gave it).
pub(crate) fn flag_of(err: &ClientError, fields: &[(&str, String)]) -> Option<String> {
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
pub(crate) fn request_error(
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

/// Request fields of Score and Gradient and the flags that set them.
pub(crate) fn query_fields(input: &InputArgs, t: u32) -> Vec<(&'static str, String)> {
    vec![
        ("model", format!("--model {}", input.model)),
        ("x", "--input".to_owned()),
        ("t", format!("--t {t}")),
        ("input_units", "--units".to_owned()),
    ]
}

/// Sends a request per range of items, `send(index, range)`, at most [`IN_FLIGHT`] at a time,
/// and hands each answer in order to `take` with its item count; a failed request's error is
/// labelled as [`request_error`] does. A bar on stderr counts the items answered.
pub(crate) async fn query_batches<A, F>(
    ctx: &Ctx,
    ranges: &[Range<usize>],
    fields: &[(&str, String)],
    send: impl Fn(usize, Range<usize>) -> F,
    mut take: impl FnMut(u64, A) -> Result<()>,
) -> Result<()>
where
    F: std::future::Future<Output = Result<A, ClientError>>,
{
    let n = ranges.last().map_or(0, |r| r.end);
    let several = ranges.len() > 1;
    let bar = item_bar(ctx.json, n as u64, "items");
    let requests = ranges.iter().enumerate().map(|(i, range)| send(i, range.clone()));
    let mut answers = futures::stream::iter(requests).buffered(IN_FLIGHT);
    let mut next = ranges.iter();
    while let Some(answer) = answers.next().await {
        let range = next.next().ok_or_else(|| anyhow!("more answers than requests"))?;
        let b = range.len() as u64;
        let answer = answer.map_err(|e| request_error(e, fields, range, n, several))?;
        take(b, answer)?;
        bar.inc(b);
    }
    bar.finish_and_clear();
    Ok(())
}

/// The output of `score` and `grad`: `reward` [N], then `more` arrays, then `window_start` [N]
/// for windows cut from trajectories, written to `--out` when given; the report's fields are
/// model, items, t and reward, then `more_text`, then out, and its JSON document has the
/// fields both commands share plus those of `more_json` (an object).
pub(crate) async fn query_report(
    input: &InputArgs,
    items: &Items,
    t: u32,
    rewards: Vec<f32>,
    more: Vec<(&'static str, Vec<u64>, Vec<f32>)>,
    more_text: Vec<(&'static str, String)>,
    more_json: Value,
) -> Result<Report> {
    let n = items.len();
    let item_shape = items.item_shape();
    let summary = summarize(rewards.iter().map(|&v| f64::from(v)));
    let mut arrays = OutArrays::default();
    arrays.f32s.push(("reward", vec![n as u64], rewards));
    arrays.f32s.extend(more);
    if let Items::Windows(w) = items {
        arrays.i64s.push(("window_start", vec![n as u64], w.starts.iter().map(|&s| s as i64).collect()));
    }
    let (shapes_json, shapes_text) = arrays.write_to(input.out.as_deref()).await?;

    let mut fields = vec![
        ("model", input.model.clone()),
        ("items", format!("{n} ({}, each {item_shape:?})", items.describe())),
        ("t", t.to_string()),
        ("reward", summary_text(summary)),
    ];
    fields.extend(more_text);
    if let Some(out) = &input.out {
        fields.push(("out", format!("{} ({shapes_text})", out.display())));
    }
    let mut json = json!({
        "model": input.model,
        "input": input.input.display().to_string(),
        "source": items.source_json(),
        "count": n,
        "item_shape": item_shape,
        "t": t,
        "units": input.units.name(),
        "reward": summary_json(summary),
        "out": input.out.as_ref().map(|p| p.display().to_string()),
        "arrays": shapes_json,
    });
    if let (Some(doc), Value::Object(more)) = (json.as_object_mut(), more_json) {
        doc.extend(more);
    }
    Ok(Report::ok(key_values(&fields, 0), json))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn server_errors_name_the_flag_of_the_field_they_name() {
        let fields = vec![("t", "--t 100".to_owned()), ("x", "--input".to_owned()), ("omega", "--omega 2".to_owned())];
        let status = |m: &str| ClientError::Status(tonic::Status::invalid_argument(m));
        assert_eq!(flag_of(&status("t[0]: 100 is outside [0, 10)"), &fields).as_deref(), Some("--t 100"));
        assert_eq!(flag_of(&status("omega: inf is not finite"), &fields).as_deref(), Some("--omega 2"));
        assert_eq!(flag_of(&status("x.shape: no"), &fields).as_deref(), Some("--input"));
        assert_eq!(flag_of(&status("tx: other"), &fields), None);
        assert_eq!(flag_of(&status("the server is busy"), &fields), None);
        assert_eq!(flag_of(&ClientError::Invalid("t: local".into()), &fields), None);
        // The label and the status, as `relreward` prints them (without the status's sources).
        let text = |e: anyhow::Error| e.chain().take(2).map(ToString::to_string).collect::<Vec<_>>().join(": ");
        let r = 16..32;
        assert_eq!(
            text(request_error(status("t[0]: bad"), &fields, &r, 40, true)),
            "--t 100: INVALID_ARGUMENT: t[0]: bad"
        );
        assert!(
            text(request_error(status("x: bad"), &fields, &r, 40, true)).starts_with("--input, items 16..32 of 40: ")
        );
        assert!(text(request_error(status("busy"), &fields, &r, 40, true)).starts_with("items 16..32 of 40: "));
        let plain = request_error(status("busy"), &fields, &r, 40, false);
        assert_eq!(plain.to_string(), "INVALID_ARGUMENT: busy");
    }
}
