//! How a job being waited for is shown (`job watch`, `train --watch`, and the jobs `extract`
//! and `demo` train): a progress bar fed by the job's Progress events (step/total, loss, steps/s
//! and ETA as the server measured them), state changes, log lines and checkpoints above it,
//! reconnects noted (see [`relreward_client::watch`]); with `--json`, one JSON object per event
//! per line instead ([`event_json`]).

use std::cell::RefCell;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use relreward_cli::ops::Progress;
use relreward_client::pb;
use relreward_client::watch::WatchNotice;
use serde_json::{Map, Value, json};

use super::output::{
    bars_visible, eprint_line, fmt_short, human_duration, rfc3339, rfc3339_millis, state_name, write_stdout,
};

/// Jobs as `job watch` shows them, for operations that wait for jobs: event lines (JSON lines
/// with `--json`) above a progress bar, a fresh bar per job. Inside a pipeline
/// (`json_events: false`) `--json` shows nothing, so that stdout carries only the report.
pub struct JobView {
    json: bool,
    json_events: bool,
    view: RefCell<WatchView>,
}

impl JobView {
    pub fn new(json: bool, json_events: bool) -> Self {
        Self { json, json_events, view: RefCell::new(WatchView::new(json)) }
    }

    fn shows_events(&self) -> bool {
        !self.json || self.json_events
    }
}

impl Progress for JobView {
    fn quiet(&self) -> bool {
        self.json
    }

    fn stage(&self, text: &str) {
        if !self.json {
            eprint_line(&format!("==> {text}"));
        }
    }

    fn submitted(&self, job: &pb::Job) {
        *self.view.borrow_mut() = WatchView::new(self.json);
        if !self.json {
            print_line(&format!("submitted job {} ({})\n", job.id, state_label(job.state())));
        }
    }

    fn job_notice(&self, notice: WatchNotice<'_>) {
        if self.shows_events() {
            self.view.borrow_mut().notice(notice);
        }
    }

    fn job_done(&self) {
        self.view.borrow().finish();
    }
}

/// Renders watch notices: JSON lines, or text lines above a progress bar.
struct WatchView {
    json: bool,
    bar: ProgressBar,
    /// Whether a Progress event arrived (until then the bar is a spinner).
    progressed: bool,
}

impl WatchView {
    fn new(json: bool) -> Self {
        let target = if bars_visible(json) { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() };
        let style =
            ProgressStyle::with_template("{spinner} {msg}").unwrap_or_else(|_| ProgressStyle::default_spinner());
        let bar = ProgressBar::with_draw_target(Some(0), target).with_style(style);
        bar.set_message("waiting for progress");
        Self { json, bar, progressed: false }
    }

    fn notice(&mut self, notice: WatchNotice<'_>) {
        match notice {
            WatchNotice::Event(event) if self.json => {
                let mut line = event_json(event).to_string();
                line.push('\n');
                print_line(&line);
            }
            WatchNotice::Event(event) => self.show_event(event),
            WatchNotice::Reconnecting { error, from_seq, delay, attempt } => {
                let line = format!(
                    "connection lost ({}: {}); reconnecting in {} (attempt {attempt}, from event {from_seq})",
                    relreward_client::client::code_name(error.code()),
                    error.message(),
                    short_delay(delay)
                );
                self.bar.suspend(|| eprint_line(&line));
            }
            WatchNotice::Reconnected { from_seq } => {
                let line = format!("reconnected; resuming from event {from_seq}");
                self.bar.suspend(|| eprint_line(&line));
            }
        }
    }

    fn show_event(&mut self, event: &pb::JobEvent) {
        use pb::job_event::Event;
        let time = event.time.as_ref().map_or_else(|| "-".to_owned(), rfc3339);
        let line = match &event.event {
            Some(Event::Progress(p)) => {
                if !self.progressed {
                    self.progressed = true;
                    let style = ProgressStyle::with_template("{spinner} [{wide_bar}] {pos}/{len} {msg}")
                        .map(|s| s.progress_chars("=> "))
                        .unwrap_or_else(|_| ProgressStyle::default_bar());
                    self.bar.set_style(style);
                }
                self.bar.set_length(p.total_steps);
                self.bar.set_position(p.step);
                self.bar.set_message(progress_message(p));
                if !self.bar.is_hidden() {
                    return;
                }
                // No bar (not a terminal): one line per progress event, as the server logs them.
                format!("{time}  step {}/{}  {}", p.step, p.total_steps, progress_message(p))
            }
            Some(Event::State(s)) if s.message.is_empty() => format!("{time}  {}", state_label(s.state())),
            Some(Event::State(s)) => format!("{time}  {}: {}", state_label(s.state()), s.message),
            Some(Event::Checkpoint(c)) => format!("{time}  checkpoint at step {}", c.step),
            Some(Event::Log(l)) => format!("{time}  {}", l.message),
            None => return,
        };
        self.bar.suspend(|| print_line(&format!("{line}\n")));
    }

    fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// `loss 0.01234  eval 0.02000  41.3 steps/s  ETA 1m13s`.
fn progress_message(p: &pb::job_event::Progress) -> String {
    let mut parts = vec![format!("loss {}", fmt_short(p.loss))];
    if let Some(eval) = p.eval_loss {
        parts.push(format!("eval {}", fmt_short(eval)));
    }
    if p.steps_per_second > 0.0 && p.steps_per_second.is_finite() {
        parts.push(format!("{:.1} steps/s", p.steps_per_second));
    }
    parts.push(format!("ETA {}", human_duration(p.eta_seconds)));
    parts.join("  ")
}

/// `250 ms`, `1.5 s`.
fn short_delay(d: Duration) -> String {
    if d < Duration::from_secs(1) { format!("{} ms", d.as_millis()) } else { format!("{:.1} s", d.as_secs_f64()) }
}

/// Writes to stdout; a closed pipe is not an error (the watch goes on to set the exit status).
pub fn print_line(text: &str) {
    let _ = write_stdout(text);
}

/// `SUCCEEDED`, as the proto spells it, for text.
pub fn state_label(state: pb::JobState) -> String {
    state_name(state).to_ascii_uppercase()
}

/// One event as one line of `job watch --json`: `seq`, `time` (RFC 3339 with milliseconds, or
/// null), `type`, and the event's fields:
///
/// ```json
/// {"seq": 1, "time": "..", "type": "state", "state": "running", "message": ".."}
/// {"seq": 2, "time": "..", "type": "progress", "step": N, "total_steps": N, "loss": X,
///  "grad_norm": X, "learning_rate": X, "steps_per_second": X, "eta_seconds": X,
///  "eval_loss": X | null}
/// {"seq": 3, "time": "..", "type": "checkpoint", "step": N}
/// {"seq": 4, "time": "..", "type": "log", "message": ".."}
/// ```
pub fn event_json(e: &pb::JobEvent) -> Value {
    use pb::job_event::Event;
    let mut out = Map::new();
    out.insert("seq".into(), json!(e.seq));
    out.insert("time".into(), json!(e.time.as_ref().map(rfc3339_millis)));
    let fields = match &e.event {
        Some(Event::State(s)) => json!({ "type": "state", "state": state_name(s.state()), "message": s.message }),
        Some(Event::Progress(p)) => json!({
            "type": "progress",
            "step": p.step,
            "total_steps": p.total_steps,
            "loss": p.loss,
            "grad_norm": p.grad_norm,
            "learning_rate": p.learning_rate,
            "steps_per_second": p.steps_per_second,
            "eta_seconds": p.eta_seconds,
            "eval_loss": p.eval_loss,
        }),
        Some(Event::Checkpoint(c)) => json!({ "type": "checkpoint", "step": c.step }),
        Some(Event::Log(l)) => json!({ "type": "log", "message": l.message }),
        None => json!({ "type": null }),
    };
    if let Value::Object(fields) = fields {
        out.extend(fields);
    }
    Value::Object(out)
}

#[cfg(test)]
mod tests {
    use pb::job_event::{Checkpoint, Event, LogLine, Progress, StateChange};

    use super::*;

    fn ts(seconds: i64) -> Option<prost_types::Timestamp> {
        Some(prost_types::Timestamp { seconds, nanos: 250_000_000 })
    }

    #[test]
    fn events_are_one_flat_object_each() {
        let event = |seq, e| pb::JobEvent { seq, time: ts(1_714_564_800), event: Some(e) };
        let v = event_json(&event(
            1,
            Event::State(StateChange { state: pb::JobState::Running as i32, message: "started".into() }),
        ));
        assert_eq!(
            v,
            json!({"seq": 1, "time": "2024-05-01T12:00:00.250Z", "type": "state", "state": "running", "message": "started"})
        );
        let v = event_json(&event(
            2,
            Event::Progress(Progress {
                step: 10,
                total_steps: 100,
                loss: 0.5,
                grad_norm: 1.5,
                learning_rate: 2e-4,
                steps_per_second: 20.0,
                eta_seconds: 4.5,
                eval_loss: None,
            }),
        ));
        assert_eq!(
            v,
            json!({"seq": 2, "time": "2024-05-01T12:00:00.250Z", "type": "progress", "step": 10, "total_steps": 100,
                   "loss": 0.5, "grad_norm": 1.5, "learning_rate": 2e-4, "steps_per_second": 20.0,
                   "eta_seconds": 4.5, "eval_loss": null})
        );
        let v = event_json(&event(3, Event::Checkpoint(Checkpoint { step: 10 })));
        assert_eq!((v["type"].clone(), v["step"].clone()), (json!("checkpoint"), json!(10)));
        let v = event_json(&event(4, Event::Log(LogLine { message: "hello".into() })));
        assert_eq!((v["type"].clone(), v["message"].clone()), (json!("log"), json!("hello")));
        // One line each.
        assert!(!v.to_string().contains('\n'));
        let v = event_json(&pb::JobEvent { seq: 5, time: None, event: None });
        assert!(v["time"].is_null() && v["type"].is_null());
    }

    #[test]
    fn progress_lines_and_delays_read_short() {
        let p = Progress {
            step: 10,
            total_steps: 100,
            loss: 0.5,
            steps_per_second: 41.3,
            eta_seconds: 73.0,
            eval_loss: Some(0.25),
            ..Default::default()
        };
        assert_eq!(progress_message(&p), "loss 0.5000  eval 0.2500  41.3 steps/s  ETA 1m13s");
        assert_eq!(short_delay(Duration::from_millis(250)), "250 ms");
        assert_eq!(short_delay(Duration::from_millis(4000)), "4.0 s");
    }
}
