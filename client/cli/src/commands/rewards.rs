//! What `relreward score`, `grad` and `sample` (the RewardService from the command line, one
//! module per command: [`super::score`], [`super::grad`], [`super::sample`]) share: the flags of
//! their inputs ([`InputArgs`], [`UnitsArg`]), the request loop, the `--out` archive, and the
//! report `score` and `grad` print.
//!
//! Inputs of `score` and `grad` (`--input`) are read whole into memory:
//! - an array of items `[B, *item_shape]` (`x` by default, another with `--key`; float32 or
//!   float64), whose item shape must be the reward model's `input_shape`;
//! - or a D4RL-style trajectories archive (`observations`, `actions`, optional `terminals`,
//!   `timeouts`, `episode_starts`), cut into the model's `[H, D]` windows
//!   (`ops::items::Windows`): rows are `[action | observation]` as in Diffuser, a window is H
//!   consecutive rows of one episode, and windows start every `--stride` rows.
//!
//! Items are read by [`relreward_cli::ops::items`] and go to the server in requests of `--batch`
//! (two in flight), lowered when needed so that one request stays under
//! [`relreward_cli::ops::items::MAX_REQUEST_BYTES`]. Results are written with `--out` as an `.npz`
//! ([`relreward_toolkit::npz_write`]) and summarised as text or, with `--json`, one document.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow};
use clap::{Args, ValueEnum};
use futures::StreamExt;
use relreward_cli::ops::items::{Items, ItemsQuery};
use relreward_cli::ops::scoring::{IN_FLIGHT, Summary, request_error, summarize};
use relreward_cli::output::{check_out_file, fmt_num, item_bar, key_values};
use relreward_client::{ClientError, pb};
use relreward_toolkit::npz_write::NpzWriter;
use serde_json::{Value, json};

use super::{Ctx, Report};

/// Units of inputs and gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum UnitsArg {
    /// The dataset's units.
    Raw,
    /// The diffusion models' normalized units.
    Normalized,
}

impl UnitsArg {
    pub(crate) fn to_proto(self) -> pb::Units {
        match self {
            Self::Raw => pb::Units::Raw,
            Self::Normalized => pb::Units::Normalized,
        }
    }

    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Raw => "raw",
            Self::Normalized => "normalized",
        }
    }
}

/// What `score` and `grad` read and where they send it.
#[derive(Debug, Clone, Args)]
pub struct InputArgs {
    /// Reward (or discriminator) model.
    #[arg(long, value_name = "R")]
    pub model: String,
    /// .npz holding `x` [B, H, D] (or [B, ...] samples), a D4RL-style trajectories .npz
    /// (observations, actions, terminals/timeouts) cut into the model's windows, or an .npy.
    #[arg(long, value_name = "FILE.npz")]
    pub input: PathBuf,
    /// The array of --input holding the items [default: x; an archive holding 'observations'
    /// is read as trajectories].
    #[arg(long, value_name = "KEY")]
    pub key: Option<String>,
    /// Trajectories: rows between the starts of consecutive windows [default: 1].
    #[arg(long, value_name = "S", value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub stride: Option<u64>,
    /// Units of the input values.
    #[arg(long, value_enum, value_name = "UNITS", default_value_t = UnitsArg::Raw)]
    pub units: UnitsArg,
    /// Items per request.
    #[arg(long, value_name = "N", default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..), allow_negative_numbers = true)]
    pub batch: u64,
    /// Write the results to this .npz file.
    #[arg(long, value_name = "OUT.npz")]
    pub out: Option<PathBuf>,
}

impl InputArgs {
    /// The items these flags ask for.
    pub fn query(&self) -> ItemsQuery {
        ItemsQuery { model: self.model.clone(), input: self.input.clone(), key: self.key.clone(), stride: self.stride }
    }
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
        "source": items.source(),
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
    use relreward_cli::ops::scoring::flag_of;

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
