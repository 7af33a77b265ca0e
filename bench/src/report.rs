//! The report: what was run, what came back, as text or one JSON object.

use std::collections::BTreeMap;

use serde::Serialize;

use crate::args::{Mode, Stop};
use crate::load::{Plan, Totals};
use crate::rss::RssReport;

/// Said in every report: the figures are not the server's alone.
pub const SHARED_CPU_NOTE: &str = "the load generator ran on the server's machine (loopback only) and shared its CPUs \
                                   with the server, so the server had less than all of them";

#[derive(Debug, Serialize)]
pub struct Report {
    pub endpoint: String,
    pub model: String,
    pub mode: Mode,
    pub clients: u32,
    pub batch: u32,
    pub item_shape: Vec<u64>,
    pub t: u32,
    pub warmup_s: f64,
    /// Set in duration mode.
    pub duration_s: Option<f64>,
    /// Set in requests mode.
    pub requests_per_client: Option<u64>,
    /// Successful recorded requests.
    pub requests: u64,
    pub items: u64,
    /// Failed recorded requests by gRPC code.
    pub errors: BTreeMap<&'static str, u64>,
    pub elapsed_s: f64,
    pub requests_per_s: f64,
    pub items_per_s: f64,
    /// Latency of successful requests, send to answer, in milliseconds (absent without any).
    pub latency_ms: Option<Latency>,
    /// CPUs of the machine that both the server and the load generator ran on.
    pub cpus: usize,
    pub note: &'static str,
    /// The server's RSS during the load (with `--rss-pid`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rss: Option<RssReport>,
}

#[derive(Debug, Serialize)]
pub struct Latency {
    pub p50: f64,
    pub p90: f64,
    pub p99: f64,
    pub max: f64,
    pub mean: f64,
}

impl Report {
    pub fn new(endpoint: &str, plan: &Plan, totals: &Totals) -> Self {
        let secs = totals.elapsed.as_secs_f64();
        let per_s = |n: u64| if secs > 0.0 { n as f64 / secs } else { 0.0 };
        let h = &totals.latency_us;
        let ms = |us: u64| us as f64 / 1000.0;
        let latency = (!h.is_empty()).then(|| Latency {
            p50: ms(h.value_at_quantile(0.50)),
            p90: ms(h.value_at_quantile(0.90)),
            p99: ms(h.value_at_quantile(0.99)),
            max: ms(h.max()),
            mean: h.mean() / 1000.0,
        });
        let (duration_s, requests_per_client) = match plan.stop {
            Stop::Duration(d) => (Some(d.as_secs_f64()), None),
            Stop::Requests(n) => (None, Some(n)),
        };
        Self {
            endpoint: endpoint.to_owned(),
            model: plan.model.clone(),
            mode: plan.mode,
            clients: plan.clients,
            batch: plan.batch,
            item_shape: plan.item_shape.clone(),
            t: plan.t,
            warmup_s: plan.warmup.as_secs_f64(),
            duration_s,
            requests_per_client,
            requests: totals.requests,
            items: totals.items,
            errors: totals.errors.clone(),
            elapsed_s: secs,
            requests_per_s: per_s(totals.requests),
            items_per_s: per_s(totals.items),
            latency_ms: latency,
            cpus: std::thread::available_parallelism().map_or(1, |n| n.get()),
            note: SHARED_CPU_NOTE,
            rss: None,
        }
    }

    pub fn error_count(&self) -> u64 {
        self.errors.values().sum()
    }

    pub fn to_text(&self) -> String {
        let mode = match self.mode {
            Mode::Unary => "unary Gradient",
            Mode::Stream => "GradientStream",
        };
        let window = match (self.duration_s, self.requests_per_client) {
            (Some(d), _) => format!("{d} s"),
            (None, Some(n)) => format!("{n} requests per client"),
            (None, None) => String::new(),
        };
        let errors = if self.errors.is_empty() {
            "0".to_owned()
        } else {
            let by_code: Vec<String> = self.errors.iter().map(|(code, n)| format!("{code} {n}")).collect();
            format!("{} ({})", self.error_count(), by_code.join(", "))
        };
        let latency = match &self.latency_ms {
            Some(l) => format!(
                "p50 {:.3} ms, p90 {:.3} ms, p99 {:.3} ms, max {:.3} ms (mean {:.3} ms)",
                l.p50, l.p90, l.p99, l.max, l.mean
            ),
            None => "no successful request".to_owned(),
        };
        let rss = match &self.rss {
            None => String::new(),
            Some(r) => {
                let slope = |s: Option<f64>| s.map_or("n/a".to_owned(), |s| format!("{s:+.1} KiB/min"));
                format!(
                    "\x20 rss         pid {}: {} KiB at the window's start, {} KiB at the end ({:+} KiB), max {} KiB, \
                     peak (VmHWM) {} KiB; slope {} (second half {}), {} samples every {} s\n",
                    r.pid,
                    r.start_kib,
                    r.end_kib,
                    r.growth_kib,
                    r.max_kib,
                    r.peak_kib,
                    slope(r.slope_kib_per_min),
                    slope(r.slope_second_half_kib_per_min),
                    r.samples.len(),
                    r.every_s
                )
            }
        };
        format!(
            "relreward-loadgen: {mode} on {endpoint}, model {model}, {clients} client(s) x batch {batch}, item \
             {shape:?}, t {t}; {window} after {warmup} s warmup\n\
             \x20 requests    {requests}\n\
             \x20 items       {items}\n\
             \x20 errors      {errors}\n\
             \x20 elapsed     {elapsed:.3} s\n\
             \x20 throughput  {rps:.1} requests/s, {ips:.1} items/s\n\
             \x20 latency     {latency}\n\
             {rss}\
             note: {note} ({cpus} CPUs).\n",
            endpoint = self.endpoint,
            model = self.model,
            clients = self.clients,
            batch = self.batch,
            shape = self.item_shape,
            t = self.t,
            warmup = self.warmup_s,
            requests = self.requests,
            items = self.items,
            elapsed = self.elapsed_s,
            rps = self.requests_per_s,
            ips = self.items_per_s,
            note = SHARED_CPU_NOTE,
            cpus = self.cpus,
        )
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use hdrhistogram::Histogram;

    use super::*;

    #[test]
    fn figures_and_both_formats() {
        let mut h = Histogram::<u64>::new_with_bounds(1, 3_600_000_000, 3).expect("bounds");
        for us in 1..=1000 {
            h.record(us * 10).expect("in range");
        }
        let totals = Totals {
            latency_us: h,
            requests: 1000,
            items: 8000,
            errors: BTreeMap::from([("UNAVAILABLE", 2)]),
            elapsed: Duration::from_secs(4),
            measure_start: std::time::Instant::now(),
        };
        let plan = Plan {
            model: "maze-reward".into(),
            mode: Mode::Stream,
            clients: 8,
            batch: 8,
            item_shape: vec![64, 6],
            t: 0,
            warmup: Duration::from_secs(1),
            stop: Stop::Duration(Duration::from_secs(4)),
            timeout: Duration::from_secs(30),
        };
        let r = Report::new("http://127.0.0.1:1", &plan, &totals);
        assert_eq!(r.requests_per_s, 250.0);
        assert_eq!(r.items_per_s, 2000.0);
        let l = r.latency_ms.as_ref().expect("latency");
        assert!((l.p50 - 5.0).abs() < 0.01 && (l.p99 - 9.9).abs() < 0.01 && (l.max - 10.0).abs() < 0.01, "{l:?}");
        let json: serde_json::Value = serde_json::from_str(&serde_json::to_string(&r).expect("json")).expect("parse");
        assert_eq!(json["mode"], "stream");
        assert_eq!(json["errors"]["UNAVAILABLE"], 2);
        assert_eq!(json["requests_per_client"], serde_json::Value::Null);
        let text = r.to_text();
        assert!(text.contains("errors      2 (UNAVAILABLE 2)"), "{text}");
        assert!(text.contains("shared its CPUs"), "{text}");
    }
}
