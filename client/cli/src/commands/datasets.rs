//! `relreward dataset upload|list|show|delete`.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use relreward_cli::ops::datasets::{self, OpenedFile, kind_name};
use relreward_client::client::{MAX_MESSAGE_BYTES, UploadProgress};
use relreward_client::{Client, pb, tensor};
use serde_json::{Value, json};
use tokio::sync::oneshot;

use super::output::{
    byte_progress_bar, drive_progress, eprint_line, fmt_fixed, fmt_num, human_bytes, key_values, rfc3339, table,
};
use super::{Ctx, Report};

/// Largest `--chunk-bytes`: half the message size limit leaves room for framing.
const MAX_CHUNK_BYTES: u64 = (MAX_MESSAGE_BYTES / 2) as u64;
/// Coordinates per statistics table shown without `--all`.
const STATS_ROWS: usize = 20;

#[derive(Debug, Subcommand)]
pub enum DatasetCommand {
    /// Upload an .npz archive, .npy file, D4RL HDF5 file or Minari dataset as a new dataset.
    Upload(UploadArgs),
    /// List every dataset.
    List,
    /// Show a dataset: arrays, episodes, digest and per-coordinate statistics.
    Show {
        name: String,
        /// Show every coordinate's statistics, not only the first ones.
        #[arg(long)]
        all: bool,
    },
    /// Delete a dataset.
    Delete { name: String },
}

#[derive(Debug, Args)]
pub struct UploadArgs {
    /// The .npz archive, .npy file, D4RL-layout HDF5 file, or Minari dataset (its
    /// main_data.hdf5 or its directory). Rules for episodes, dict observations and walls:
    /// docs/data-formats.md.
    file: PathBuf,
    /// Dataset name: [a-z0-9][a-z0-9._-]{0,63}.
    #[arg(long)]
    name: String,
    /// Default: trajectories for an .npz holding 'observations', otherwise samples.
    #[arg(long, value_enum)]
    kind: Option<KindArg>,
    /// Samples only: the .npz array to upload (default: 'samples', or the only array).
    #[arg(long)]
    key: Option<String>,
    #[arg(long, default_value = "")]
    description: String,
    /// Payload bytes per upload message, e.g. 1048576, 512KiB or 4MiB.
    #[arg(long, value_parser = parse_byte_size, default_value = "1MiB")]
    chunk_bytes: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum KindArg {
    Trajectories,
    Samples,
}

pub async fn run(ctx: &Ctx, command: DatasetCommand) -> Result<Report> {
    match command {
        DatasetCommand::Upload(args) => upload(ctx, args).await,
        DatasetCommand::List => list(ctx).await,
        DatasetCommand::Show { name, all } => show(ctx, &name, all).await,
        DatasetCommand::Delete { name } => delete(ctx, &name).await,
    }
}

// ---------------------------------------------------------------------------------------------
// Commands

async fn upload(ctx: &Ctx, args: UploadArgs) -> Result<Report> {
    let UploadArgs { file, name, kind, key, description, chunk_bytes } = args;
    let kind = kind.map(|k| match k {
        KindArg::Trajectories => pb::DatasetKind::Trajectories,
        KindArg::Samples => pb::DatasetKind::Samples,
    });
    // Reading headers (or a whole HDF5 file) touches the disk: keep it off the runtime.
    let opened = tokio::task::spawn_blocking(move || datasets::open_file(&file, kind, key.as_deref()))
        .await
        .context("reading the file crashed")??;
    for note in &opened.notes {
        eprint_line(&format!("note: {note}"));
    }
    send(ctx, &name, opened, &description, chunk_bytes).await
}

/// Sends one upload with a progress bar and reports the stored dataset.
async fn send(ctx: &Ctx, name: &str, file: OpenedFile, description: &str, chunk_bytes: u64) -> Result<Report> {
    let client = ctx.connect().await?;
    let progress = Arc::new(UploadProgress::default());
    let bar = byte_progress_bar(ctx.json);
    let (done_tx, done_rx) = oneshot::channel();
    let ticker = tokio::spawn(drive_progress(bar.clone(), Arc::clone(&progress), done_rx));
    let started = Instant::now();
    let result = datasets::upload(&client, name, file, description, chunk_bytes, Arc::clone(&progress)).await;
    let _ = done_tx.send(());
    let _ = ticker.await;
    bar.finish_and_clear();
    let dataset = result?;
    if !bar.is_hidden() {
        let secs = started.elapsed().as_secs_f64();
        let sent = progress.sent_bytes.load(Ordering::Relaxed);
        eprint_line(&format!("uploaded {} in {secs:.1} s", human_bytes(sent)));
    }
    let dataset = with_stats(&client, dataset).await;
    Ok(Report::ok(format_dataset(&dataset, false), dataset_json(&dataset)))
}

async fn list(ctx: &Ctx) -> Result<Report> {
    let datasets = ctx.connect().await?.list_datasets().await?;
    Ok(Report::ok(format_dataset_table(&datasets), Value::Array(datasets.iter().map(dataset_json).collect())))
}

async fn show(ctx: &Ctx, name: &str, all: bool) -> Result<Report> {
    let dataset = ctx.connect().await?.get_dataset(name).await?;
    Ok(Report::ok(format_dataset(&dataset, all), dataset_json(&dataset)))
}

async fn delete(ctx: &Ctx, name: &str) -> Result<Report> {
    ctx.connect().await?.delete_dataset(name).await?;
    Ok(Report::ok(format!("deleted {name}\n"), json!({ "deleted": name })))
}

// ---------------------------------------------------------------------------------------------
// Upload helpers

/// The dataset with statistics: an upload's answer may leave them out, so fetch the full view
/// then (keeping the answer if that fails).
async fn with_stats(client: &Client, dataset: pb::Dataset) -> pb::Dataset {
    let missing = dataset
        .arrays
        .iter()
        .any(|a| a.stats.is_none() && a.spec.as_ref().is_some_and(|s| matches!(dtype_of(s), "float32" | "float64")));
    if !missing {
        return dataset;
    }
    client.get_dataset(&dataset.name).await.unwrap_or(dataset)
}

/// `--chunk-bytes`: a count of bytes with an optional binary suffix (`K`, `KiB`, `M`, `MiB`).
fn parse_byte_size(text: &str) -> Result<u64, String> {
    let text = text.trim();
    let split = text.find(|c: char| !c.is_ascii_digit()).unwrap_or(text.len());
    let (digits, unit) = text.split_at(split);
    let invalid = || format!("'{text}' is not a byte count (e.g. 1048576, 512KiB, 4MiB)");
    let n: u64 = digits.parse().map_err(|_| invalid())?;
    let unit_bytes: u64 = match unit.trim() {
        "" | "B" => 1,
        "K" | "k" | "KiB" | "kiB" => 1 << 10,
        "M" | "m" | "MiB" => 1 << 20,
        _ => return Err(invalid()),
    };
    let bytes = n.checked_mul(unit_bytes).ok_or_else(invalid)?;
    if bytes == 0 || bytes > MAX_CHUNK_BYTES {
        return Err(format!("must be between 1 byte and {} MiB", MAX_CHUNK_BYTES >> 20));
    }
    Ok(bytes)
}

// ---------------------------------------------------------------------------------------------
// Output: JSON

/// A dataset as JSON:
///
/// ```json
/// {"name": "..", "kind": "trajectories" | "samples", "num_rows": N, "sha256": "..",
///  "size_bytes": N, "created_at": "RFC3339" | null, "description": "..",
///  "episodes": {"count": N, "min_length": N, "max_length": N, "mean_length": X} | null,
///  "arrays": [{"name": "..", "dtype": "float32", "shape": [..],
///              "stats": {"min": [..], "max": [..], "mean": [..], "std": [..]} | null}]}
/// ```
///
/// Non-finite numbers are written as `null`.
pub fn dataset_json(d: &pb::Dataset) -> Value {
    json!({
        "name": d.name,
        "kind": kind_name(d.kind()),
        "num_rows": d.num_rows,
        "sha256": d.sha256,
        "size_bytes": d.size_bytes,
        "created_at": d.created_at.as_ref().map(rfc3339),
        "description": d.description,
        "episodes": d.episodes.as_ref().map(|e| json!({
            "count": e.count,
            "min_length": e.min_length,
            "max_length": e.max_length,
            "mean_length": e.mean_length,
        })),
        "arrays": d.arrays.iter().map(array_json).collect::<Vec<_>>(),
    })
}

fn array_json(a: &pb::ArrayInfo) -> Value {
    let spec = a.spec.clone().unwrap_or_default();
    json!({
        "name": spec.name,
        "dtype": dtype_of(&spec),
        "shape": spec.shape,
        "stats": a.stats.as_ref().map(|s| json!({
            "min": s.min,
            "max": s.max,
            "mean": s.mean,
            "std": s.std,
        })),
    })
}

// ---------------------------------------------------------------------------------------------
// Output: text

fn dtype_of(spec: &pb::ArraySpec) -> &'static str {
    tensor::dtype_name(pb::Dtype::try_from(spec.dtype).unwrap_or(pb::Dtype::Unspecified))
}

/// `dataset show`: a key/value block, the arrays, then one statistics table per float array.
fn format_dataset(d: &pb::Dataset, all: bool) -> String {
    let mut fields: Vec<(&str, String)> =
        vec![("name", d.name.clone()), ("kind", kind_name(d.kind()).to_owned()), ("rows", d.num_rows.to_string())];
    if let Some(e) = &d.episodes {
        fields.push((
            "episodes",
            format!(
                "{} (length min {}, max {}, mean {})",
                e.count,
                e.min_length,
                e.max_length,
                fmt_fixed(e.mean_length, 1)
            ),
        ));
    }
    fields.push(("size", format!("{} ({} bytes)", human_bytes(d.size_bytes), d.size_bytes)));
    fields.push(("sha256", d.sha256.clone()));
    fields.push(("created", d.created_at.as_ref().map_or_else(|| "-".to_owned(), rfc3339)));
    fields.push(("description", if d.description.is_empty() { "-".to_owned() } else { d.description.clone() }));
    let mut out = key_values(&fields, 0);

    out.push_str("\narrays\n");
    let rows = d
        .arrays
        .iter()
        .map(|a| {
            let spec = a.spec.clone().unwrap_or_default();
            vec![spec.name.clone(), dtype_of(&spec).to_owned(), format!("{:?}", spec.shape)]
        })
        .collect();
    out.push_str(&table(&["NAME", "DTYPE", "SHAPE"], &[false, false, false], rows, 2));

    for a in &d.arrays {
        if let (Some(spec), Some(stats)) = (&a.spec, &a.stats) {
            out.push('\n');
            out.push_str(&format_stats(spec, stats, all));
        }
    }
    out
}

/// Per-coordinate statistics of one array: index, min, max, mean, std.
fn format_stats(spec: &pb::ArraySpec, stats: &pb::ArrayStats, all: bool) -> String {
    let count = stats.min.len();
    let shown = if all { count } else { count.min(STATS_ROWS) };
    let trailing = spec.shape.get(1..).unwrap_or(&[]);
    let value = |v: &[f64], i: usize| fmt_num(v.get(i).copied().unwrap_or(f64::NAN));
    let rows = (0..shown)
        .map(|i| {
            vec![
                coord_label(i, trailing),
                value(&stats.min, i),
                value(&stats.max, i),
                value(&stats.mean, i),
                value(&stats.std, i),
            ]
        })
        .collect();
    let plural = if count == 1 { "" } else { "s" };
    let mut out = format!("statistics of {} ({count} coordinate{plural})\n", spec.name);
    out.push_str(&table(&["COORD", "MIN", "MAX", "MEAN", "STD"], &[true, true, true, true, true], rows, 2));
    if shown < count {
        out.push_str(&format!("  ... {} more (--all shows every coordinate; --json has them all)\n", count - shown));
    }
    out
}

/// A coordinate's label: its flat index for `[N, D]` arrays, its index tuple for `[N, C, H, W]`.
fn coord_label(flat: usize, trailing: &[u64]) -> String {
    if trailing.len() <= 1 || trailing.contains(&0) {
        return flat.to_string();
    }
    let mut rest = flat as u64;
    let mut index: Vec<String> = trailing
        .iter()
        .rev()
        .map(|&d| {
            let i = rest % d;
            rest /= d;
            i.to_string()
        })
        .collect();
    index.reverse();
    format!("({})", index.join(", "))
}

/// `dataset list`: one dataset per row.
fn format_dataset_table(datasets: &[pb::Dataset]) -> String {
    if datasets.is_empty() {
        return "no datasets\n".to_owned();
    }
    let rows = datasets
        .iter()
        .map(|d| {
            vec![
                d.name.clone(),
                kind_name(d.kind()).to_owned(),
                d.num_rows.to_string(),
                d.episodes.as_ref().map_or_else(|| "-".to_owned(), |e| e.count.to_string()),
                human_bytes(d.size_bytes),
                d.created_at.as_ref().map_or_else(|| "-".to_owned(), rfc3339),
            ]
        })
        .collect();
    table(&["NAME", "KIND", "ROWS", "EPISODES", "SIZE", "CREATED"], &[false, false, true, true, true, false], rows, 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_dataset() -> pb::Dataset {
        pb::Dataset {
            name: "hopper".into(),
            kind: pb::DatasetKind::Trajectories as i32,
            num_rows: 4,
            arrays: vec![
                pb::ArrayInfo {
                    spec: Some(pb::ArraySpec {
                        name: "observations".into(),
                        dtype: pb::Dtype::Float32 as i32,
                        shape: vec![4, 2],
                    }),
                    stats: Some(pb::ArrayStats {
                        min: vec![0.0, -1.0],
                        max: vec![1.0, 1e9],
                        mean: vec![0.5, f64::NAN],
                        std: vec![0.25, 2e-7],
                    }),
                },
                pb::ArrayInfo {
                    spec: Some(pb::ArraySpec {
                        name: "terminals".into(),
                        dtype: pb::Dtype::Bool as i32,
                        shape: vec![4],
                    }),
                    stats: None,
                },
            ],
            episodes: Some(pb::EpisodeInfo { count: 2, min_length: 1, max_length: 3, mean_length: 2.0 }),
            sha256: "ab".repeat(32),
            size_bytes: 36,
            created_at: Some(prost_types::Timestamp { seconds: 1_714_564_800, nanos: 5 }),
            description: "test".into(),
        }
    }

    #[test]
    fn dataset_json_has_the_documented_shape() {
        let v = dataset_json(&sample_dataset());
        assert_eq!(v["name"], "hopper");
        assert_eq!(v["kind"], "trajectories");
        assert_eq!(v["num_rows"], 4);
        assert_eq!(v["sha256"], "ab".repeat(32));
        assert_eq!(v["size_bytes"], 36);
        assert_eq!(v["created_at"], "2024-05-01T12:00:00Z");
        assert_eq!(v["description"], "test");
        assert_eq!(v["episodes"], json!({"count": 2, "min_length": 1, "max_length": 3, "mean_length": 2.0}));
        let arrays = v["arrays"].as_array().expect("arrays");
        assert_eq!(arrays.len(), 2);
        assert_eq!(arrays[0]["name"], "observations");
        assert_eq!(arrays[0]["dtype"], "float32");
        assert_eq!(arrays[0]["shape"], json!([4, 2]));
        assert_eq!(arrays[0]["stats"]["min"], json!([0.0, -1.0]));
        assert_eq!(arrays[0]["stats"]["mean"], json!([0.5, null]));
        assert_eq!(arrays[1]["dtype"], "bool");
        assert!(arrays[1]["stats"].is_null());
        assert_eq!(v.as_object().expect("object").len(), 9);

        let mut samples = sample_dataset();
        samples.kind = pb::DatasetKind::Samples as i32;
        samples.episodes = None;
        samples.created_at = None;
        let v = dataset_json(&samples);
        assert_eq!(v["kind"], "samples");
        assert!(v["episodes"].is_null() && v["created_at"].is_null());
    }

    #[test]
    fn text_output_shows_every_field() {
        let text = format_dataset(&sample_dataset(), false);
        for needle in [
            "hopper",
            "trajectories",
            "2 (length min 1, max 3, mean 2.0)",
            "36 B (36 bytes)",
            "2024-05-01T12:00:00Z",
            "observations  float32  [4, 2]",
            "terminals     bool     [4]",
            "statistics of observations (2 coordinates)",
            "1.0000e9",
            "nan",
        ] {
            assert!(text.contains(needle), "missing {needle:?} in\n{text}");
        }
        let list = format_dataset_table(&[sample_dataset()]);
        assert!(list.starts_with("NAME"), "{list}");
        assert!(list.contains("hopper  trajectories"), "{list}");
        assert_eq!(format_dataset_table(&[]), "no datasets\n");
    }

    #[test]
    fn long_statistics_are_cut_unless_all() {
        let n = STATS_ROWS + 5;
        let spec = pb::ArraySpec { name: "samples".into(), dtype: pb::Dtype::Float32 as i32, shape: vec![3, n as u64] };
        let stats = pb::ArrayStats { min: vec![0.0; n], max: vec![1.0; n], mean: vec![0.5; n], std: vec![0.1; n] };
        let cut = format_stats(&spec, &stats, false);
        assert!(cut.contains("... 5 more"), "{cut}");
        assert_eq!(cut.lines().count(), 2 + STATS_ROWS + 1);
        let full = format_stats(&spec, &stats, true);
        assert_eq!(full.lines().count(), 2 + n);
    }

    #[test]
    fn coordinates_of_image_like_samples_are_index_tuples() {
        assert_eq!(coord_label(5, &[7]), "5");
        assert_eq!(coord_label(5, &[2, 3]), "(1, 2)");
        assert_eq!(coord_label(7, &[2, 2, 2]), "(1, 1, 1)");
        assert_eq!(coord_label(3, &[0, 2]), "3");
    }

    #[test]
    fn byte_sizes() {
        assert_eq!(parse_byte_size("1048576"), Ok(1 << 20));
        assert_eq!(parse_byte_size("512KiB"), Ok(512 << 10));
        assert_eq!(parse_byte_size("4M"), Ok(4 << 20));
        assert!(parse_byte_size("0").is_err());
        assert!(parse_byte_size("1GiB").is_err());
        assert!(parse_byte_size("lots").is_err());
        assert!(parse_byte_size("99999999999999999999M").is_err());
    }
}
