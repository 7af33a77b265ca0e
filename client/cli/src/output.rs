//! Output shared by every command: JSON documents, aligned tables and key/value blocks,
//! number, size, time and duration formats, byte progress bars, and terminal writes that never
//! panic.

use std::io::{self, IsTerminal, Write};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use relreward_client::client::UploadProgress;
use relreward_client::pb;
use serde_json::{Value, json};
use tokio::sync::oneshot;

use crate::UsageError;

// ---------------------------------------------------------------------------------------------
// JSON

/// A pretty-printed document and a newline.
pub fn json_text(value: &Value) -> String {
    let mut text = serde_json::to_string_pretty(value).unwrap_or_else(|_| value.to_string());
    text.push('\n');
    text
}

/// `{"kind": "limits", "min": [..], "max": [..]}`, `{"kind": "gaussian", "mean": [..], "std":
/// [..]}` or `{"kind": "identity"}` (also for an absent normalizer, which means identity).
pub fn normalizer_json(n: Option<&pb::Normalizer>) -> Value {
    use pb::normalizer::Kind;
    match n.and_then(|n| n.kind.as_ref()) {
        Some(Kind::Limits(l)) => json!({ "kind": "limits", "min": l.min, "max": l.max }),
        Some(Kind::Gaussian(g)) => json!({ "kind": "gaussian", "mean": g.mean, "std": g.std }),
        Some(Kind::Identity(_)) | None => json!({ "kind": "identity" }),
    }
}

/// A normalizer in a few words: `limits (6 coordinates)`.
pub fn normalizer_text(n: Option<&pb::Normalizer>) -> String {
    use pb::normalizer::Kind;
    let (kind, len) = match n.and_then(|n| n.kind.as_ref()) {
        Some(Kind::Limits(l)) => ("limits", l.min.len()),
        Some(Kind::Gaussian(g)) => ("gaussian", g.mean.len()),
        Some(Kind::Identity(_)) | None => return "identity".to_owned(),
    };
    format!("{kind} ({len} coordinate{})", if len == 1 { "" } else { "s" })
}

// ---------------------------------------------------------------------------------------------
// Text

/// `key  value` lines with the values aligned.
pub fn key_values(fields: &[(&str, String)], indent: usize) -> String {
    let width = fields.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    let mut out = String::new();
    for (key, value) in fields {
        out.push_str(&format!("{:indent$}{key:<width$}  {value}\n", ""));
    }
    out
}

/// Aligned columns separated by two spaces; `right[i]` right-aligns column `i`.
pub fn table(headers: &[&str], right: &[bool], rows: Vec<Vec<String>>, indent: usize) -> String {
    let mut widths: Vec<usize> = headers.iter().map(|h| h.chars().count()).collect();
    for row in &rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let header_row: Vec<String> = headers.iter().map(|h| (*h).to_owned()).collect();
    let mut out = String::new();
    for row in std::iter::once(&header_row).chain(&rows) {
        let cells: Vec<String> = row
            .iter()
            .zip(&widths)
            .enumerate()
            .map(
                |(i, (cell, &w))| {
                    if right.get(i).copied().unwrap_or(false) { format!("{cell:>w$}") } else { format!("{cell:<w$}") }
                },
            )
            .collect();
        out.push_str(&" ".repeat(indent));
        out.push_str(cells.join("  ").trim_end());
        out.push('\n');
    }
    out
}

/// `-` for an empty string.
pub fn or_dash(s: &str) -> String {
    if s.is_empty() { "-".to_owned() } else { s.to_owned() }
}

/// A timestamp, or `-`.
pub fn time_or_dash(ts: Option<&prost_types::Timestamp>) -> String {
    ts.map_or_else(|| "-".to_owned(), rfc3339)
}

/// A statistic: fixed notation for ordinary magnitudes, scientific otherwise.
pub fn fmt_num(v: f64) -> String {
    if v.is_nan() {
        "nan".to_owned()
    } else if v.is_infinite() {
        if v > 0.0 { "inf".to_owned() } else { "-inf".to_owned() }
    } else if v == 0.0 {
        "0".to_owned()
    } else if (1e-3..1e6).contains(&v.abs()) {
        format!("{v:.6}")
    } else {
        format!("{v:.4e}")
    }
}

/// A number the user gave, echoed in a message (the rule the server's refusals share).
pub use relreward_client::given_number as given_num;

/// A fraction as a percentage with two decimals.
pub fn percent(v: f64) -> String {
    if v.is_finite() { format!("{:.2}%", 100.0 * v) } else { "-".to_owned() }
}

/// A tail fraction as a percentage: `1`, `0.5`.
pub fn fmt_p(p: f64) -> String {
    let text = format!("{:.3}", 100.0 * p);
    text.trim_end_matches('0').trim_end_matches('.').to_owned()
}

pub fn fmt_fixed(v: f64, decimals: usize) -> String {
    if v.is_finite() { format!("{v:.decimals$}") } else { fmt_num(v) }
}

/// A loss or learning rate: four significant digits (`0.01234`, `2.000e-4`).
pub fn fmt_short(v: f64) -> String {
    if !v.is_finite() || v == 0.0 {
        fmt_num(v)
    } else if (1e-3..1e4).contains(&v.abs()) {
        let digits = (3 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
        format!("{v:.digits$}")
    } else {
        format!("{v:.3e}")
    }
}

/// `1.5 MiB`; exact below 1 KiB.
pub fn human_bytes(n: u64) -> String {
    const UNITS: [&str; 6] = ["KiB", "MiB", "GiB", "TiB", "PiB", "EiB"];
    if n < 1024 {
        return format!("{n} B");
    }
    let mut value = n as f64 / 1024.0;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    format!("{value:.1} {}", UNITS[unit])
}

/// `1h02m03s`, `4m05s`, `7s`; `-` for a negative or non-finite count.
pub fn human_duration(seconds: f64) -> String {
    if !seconds.is_finite() || seconds < 0.0 {
        return "-".to_owned();
    }
    let s = seconds.round().min(u64::MAX as f64) as u64;
    let (h, m, s) = (s / 3600, s % 3600 / 60, s % 60);
    if h > 0 {
        format!("{h}h{m:02}m{s:02}s")
    } else if m > 0 {
        format!("{m}m{s:02}s")
    } else {
        format!("{s}s")
    }
}

/// RFC 3339 in UTC with whole seconds, e.g. `2024-05-01T12:00:00Z`.
pub fn rfc3339(ts: &prost_types::Timestamp) -> String {
    let days = ts.seconds.div_euclid(86_400);
    let secs = ts.seconds.rem_euclid(86_400);
    let (year, month, day) = civil_from_days(days);
    format!("{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z", secs / 3600, secs % 3600 / 60, secs % 60)
}

/// RFC 3339 in UTC with milliseconds, e.g. `2024-05-01T12:00:00.250Z` (event times).
pub fn rfc3339_millis(ts: &prost_types::Timestamp) -> String {
    let whole = rfc3339(ts);
    let millis = ts.nanos.clamp(0, 999_999_999) / 1_000_000;
    match whole.strip_suffix('Z') {
        Some(base) => format!("{base}.{millis:03}Z"),
        None => whole,
    }
}

/// Proleptic Gregorian date of a day count since 1970-01-01 (H. Hinnant's algorithm).
fn civil_from_days(days: i64) -> (i64, i64, i64) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    (year, month, day)
}

// ---------------------------------------------------------------------------------------------
// Upload progress

/// Whether progress bars should be drawn: not with `--json`, and only on a terminal.
pub fn bars_visible(json: bool) -> bool {
    !json && io::stderr().is_terminal()
}

/// A byte progress bar on stderr, hidden when stderr is not a terminal or with `--json`.
pub fn byte_progress_bar(json: bool) -> ProgressBar {
    let target = if bars_visible(json) { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() };
    let style = ProgressStyle::with_template(
        "{spinner} {elapsed_precise} [{wide_bar}] {binary_bytes}/{binary_total_bytes} \
         {binary_bytes_per_sec} ETA {eta} {msg}",
    )
    .map(|s| s.progress_chars("=> "))
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::with_draw_target(Some(0), target).with_style(style)
}

/// Copies `progress` into `bar` every 100 ms until `done` fires (or its sender is dropped).
pub async fn drive_progress(bar: ProgressBar, progress: Arc<UploadProgress>, mut done: oneshot::Receiver<()>) {
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    loop {
        tokio::select! {
            _ = &mut done => break,
            _ = tick.tick() => update_bar(&bar, &progress),
        }
    }
    update_bar(&bar, &progress);
}

fn update_bar(bar: &ProgressBar, progress: &UploadProgress) {
    let total = progress.total_bytes.load(Ordering::Relaxed);
    let sent = progress.sent_bytes.load(Ordering::Relaxed).min(total);
    bar.set_length(total);
    bar.set_position(sent);
    if total > 0 && sent == total && bar.message().is_empty() {
        bar.set_message("verifying");
    }
}

/// A count progress bar on stderr, hidden with `--json` or off a terminal.
pub fn item_bar(json: bool, total: u64, what: &str) -> ProgressBar {
    let target = if bars_visible(json) { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() };
    let template =
        format!("{{spinner}} {{elapsed_precise}} [{{wide_bar}}] {{pos}}/{{len}} {what} {{per_sec}} ETA {{eta}}");
    let style = ProgressStyle::with_template(&template)
        .map(|s| s.progress_chars("=> "))
        .unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::with_draw_target(Some(total), target).with_style(style)
}

// ---------------------------------------------------------------------------------------------
// Terminal I/O that never panics

pub fn write_stdout(text: &str) -> io::Result<()> {
    let mut out = io::stdout().lock();
    out.write_all(text.as_bytes())?;
    out.flush()
}

pub fn eprint_line(line: &str) {
    let _ = writeln!(io::stderr().lock(), "{line}");
}

/// Refuses an output file given as `flag` that names no file or lies in a directory that does
/// not exist, before any work is done (`score`, `grad`, `sample`, `maze generate`, `eval`).
pub fn check_out_file(flag: &str, out: &Path) -> Result<(), UsageError> {
    if out.file_name().is_none() || out.is_dir() {
        return Err(UsageError(format!("{flag} {}: not a file name", out.display())));
    }
    let dir = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(UsageError(format!("{flag} {}: directory {} does not exist", out.display(), dir.display())));
    }
    Ok(())
}

/// A job state's name in JSON and in `--state` (`succeeded`): here, not with the job commands,
/// because `job list|show|watch` and `job plot` (in `eval`) both print it.
pub fn state_name(state: pb::JobState) -> &'static str {
    match state {
        pb::JobState::Pending => "pending",
        pb::JobState::Running => "running",
        pb::JobState::Succeeded => "succeeded",
        pb::JobState::Failed => "failed",
        pb::JobState::Cancelled => "cancelled",
        pb::JobState::Unspecified => "unspecified",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timestamps_are_rfc3339_utc() {
        let at = |seconds| rfc3339(&prost_types::Timestamp { seconds, nanos: 0 });
        assert_eq!(at(0), "1970-01-01T00:00:00Z");
        assert_eq!(at(951_782_400), "2000-02-29T00:00:00Z");
        assert_eq!(at(1_709_251_199), "2024-02-29T23:59:59Z");
        assert_eq!(at(-1), "1969-12-31T23:59:59Z");
        assert_eq!(at(253_402_300_799), "9999-12-31T23:59:59Z");
        // Absurd values format without panicking.
        let _ = at(i64::MAX);
        let _ = at(i64::MIN);
        let ms = rfc3339_millis(&prost_types::Timestamp { seconds: 1_714_564_800, nanos: 250_999_999 });
        assert_eq!(ms, "2024-05-01T12:00:00.250Z");
        let _ = rfc3339_millis(&prost_types::Timestamp { seconds: 0, nanos: -5 });
    }

    #[test]
    fn numbers_sizes_and_durations() {
        assert_eq!(fmt_num(0.0), "0");
        assert_eq!(fmt_num(-1.5), "-1.500000");
        assert_eq!(fmt_num(1e-9), "1.0000e-9");
        assert_eq!(fmt_num(f64::NEG_INFINITY), "-inf");
        assert_eq!(fmt_short(0.012346), "0.01235");
        assert_eq!(fmt_short(1.5), "1.500");
        assert_eq!(fmt_short(2e-4), "2.000e-4");
        assert_eq!(fmt_short(f64::NAN), "nan");
        assert_eq!(human_bytes(1023), "1023 B");
        assert_eq!(human_bytes(1536), "1.5 KiB");
        assert_eq!(human_bytes(u64::MAX), "16.0 EiB");
        assert_eq!(human_duration(7.4), "7s");
        assert_eq!(human_duration(245.0), "4m05s");
        assert_eq!(human_duration(3723.0), "1h02m03s");
        assert_eq!(human_duration(f64::INFINITY), "-");
        assert_eq!(human_duration(-1.0), "-");
    }

    #[test]
    fn normalizers() {
        use pb::normalizer::{Kind, Limits};
        let limits = pb::Normalizer { kind: Some(Kind::Limits(Limits { min: vec![0.0, 1.0], max: vec![1.0, 2.0] })) };
        assert_eq!(normalizer_json(Some(&limits)), json!({"kind": "limits", "min": [0.0, 1.0], "max": [1.0, 2.0]}));
        assert_eq!(normalizer_json(None), json!({"kind": "identity"}));
        assert_eq!(normalizer_text(Some(&limits)), "limits (2 coordinates)");
        assert_eq!(normalizer_text(None), "identity");
    }
}
