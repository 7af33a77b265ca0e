//! Resident set size of another process (the server under load), sampled from
//! `/proc/PID/status` while the load runs: the memory half of the serving benchmark, which
//! asks whether a server's RSS grows under sustained GradientStream load.
//!
//! Samples are taken every `--rss-every` seconds from the start of the warmup to the end of the
//! load, timed relative to the start of the measurement window (warmup samples have t < 0).
//! Growth and slopes are computed over the window only: the warmup is where allocators and
//! per-connection buffers reach their steady size, which is not a leak.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde::Serialize;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// What the report says about the sampled process.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct RssReport {
    pub pid: u32,
    pub every_s: f64,
    /// `[seconds since the measurement window started, VmRSS KiB]`.
    pub samples: Vec<(f64, u64)>,
    /// Last sample at or before the window's start (the first sample when there is none).
    pub start_kib: u64,
    pub end_kib: u64,
    pub max_kib: u64,
    /// `end_kib - start_kib`.
    pub growth_kib: i64,
    /// Least-squares slope over the window's samples, KiB per minute (None with < 2 samples).
    pub slope_kib_per_min: Option<f64>,
    /// The same over the window's second half: a steady server has ~0 here even when the
    /// first half still settles.
    pub slope_second_half_kib_per_min: Option<f64>,
    /// VmHWM (the process's peak RSS since it started) at the end.
    pub peak_kib: u64,
}

/// A running sampler; [`RssSampler::finish`] stops it and summarises.
pub struct RssSampler {
    pid: u32,
    every: Duration,
    stop: oneshot::Sender<()>,
    task: JoinHandle<Result<Vec<(Instant, u64)>>>,
}

/// VmRSS and VmHWM of `pid`, in KiB.
pub fn read_status(pid: u32) -> Result<(u64, u64)> {
    let path = format!("/proc/{pid}/status");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("cannot read {path} (is process {pid} running?)"))?;
    parse_status(&text).with_context(|| format!("{path} has no VmRSS/VmHWM lines"))
}

fn parse_status(text: &str) -> Option<(u64, u64)> {
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|rest| rest.trim().strip_suffix("kB"))
            .and_then(|v| v.trim().parse::<u64>().ok())
    };
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

impl RssSampler {
    /// Checks that `pid` can be read, then samples it every `every` until finished.
    pub fn start(pid: u32, every: Duration) -> Result<Self> {
        if every.is_zero() {
            bail!("--rss-every must be positive");
        }
        let first = read_status(pid)?.0;
        let (stop, mut stopped) = oneshot::channel();
        let task = tokio::spawn(async move {
            let mut samples = vec![(Instant::now(), first)];
            let mut tick = tokio::time::interval(every);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            tick.tick().await; // the first tick is immediate: that sample is `first`
            loop {
                tokio::select! {
                    _ = &mut stopped => break,
                    _ = tick.tick() => samples.push((Instant::now(), read_status(pid)?.0)),
                }
            }
            samples.push((Instant::now(), read_status(pid)?.0));
            Ok(samples)
        });
        Ok(Self { pid, every, stop, task })
    }

    /// Stops sampling and summarises the samples against the measurement window starting at
    /// `window_start`.
    pub async fn finish(self, window_start: Instant) -> Result<RssReport> {
        let _ = self.stop.send(());
        let samples = self.task.await.context("the RSS sampler failed")??;
        let peak_kib = read_status(self.pid)?.1;
        let samples: Vec<(f64, u64)> = samples
            .iter()
            .map(|&(at, kib)| {
                let t = if at >= window_start {
                    (at - window_start).as_secs_f64()
                } else {
                    -(window_start - at).as_secs_f64()
                };
                (t, kib)
            })
            .collect();
        Ok(summarise(self.pid, self.every.as_secs_f64(), samples, peak_kib))
    }
}

fn summarise(pid: u32, every_s: f64, samples: Vec<(f64, u64)>, peak_kib: u64) -> RssReport {
    let window: Vec<(f64, u64)> = samples.iter().copied().filter(|&(t, _)| t >= 0.0).collect();
    let start_kib = samples.iter().rev().find(|&&(t, _)| t <= 0.0).or(samples.first()).map_or(0, |s| s.1);
    let end_kib = samples.last().map_or(0, |s| s.1);
    let max_kib = samples.iter().map(|s| s.1).max().unwrap_or(0);
    let half = window.last().map_or(0.0, |s| s.0) / 2.0;
    let second_half: Vec<(f64, u64)> = window.iter().copied().filter(|&(t, _)| t >= half).collect();
    RssReport {
        pid,
        every_s,
        start_kib,
        end_kib,
        max_kib,
        growth_kib: end_kib as i64 - start_kib as i64,
        slope_kib_per_min: slope(&window).map(|s| s * 60.0),
        slope_second_half_kib_per_min: slope(&second_half).map(|s| s * 60.0),
        // The kernel raises VmHWM lazily (RSS counters are batched per CPU), so a VmRSS sample
        // can read above it: the peak is at least the largest sample.
        peak_kib: peak_kib.max(max_kib),
        samples,
    }
}

/// Least-squares slope of kib over t (per second); None with fewer than two distinct times.
fn slope(points: &[(f64, u64)]) -> Option<f64> {
    let n = points.len() as f64;
    if points.len() < 2 {
        return None;
    }
    let mean_t = points.iter().map(|p| p.0).sum::<f64>() / n;
    let mean_y = points.iter().map(|p| p.1 as f64).sum::<f64>() / n;
    let sxx: f64 = points.iter().map(|p| (p.0 - mean_t).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mean_t) * (p.1 as f64 - mean_y)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_lines_parse() {
        let text = "Name:\trelreward-serv\nVmPeak:\t 1000 kB\nVmHWM:\t  170000 kB\nVmRSS:\t  165288 kB\nThreads:\t7\n";
        assert_eq!(parse_status(text), Some((165_288, 170_000)));
        assert_eq!(parse_status("Name:\tx\n"), None);
    }

    #[test]
    fn slopes_are_least_squares_per_minute() {
        // 1 KiB per second for 10 s, after a warmup sample at t = -1.
        let mut samples = vec![(-1.0, 500)];
        samples.extend((0..=10).map(|s| (f64::from(s), 1000 + s as u64)));
        let r = summarise(1, 1.0, samples, 2000);
        assert_eq!((r.start_kib, r.end_kib, r.max_kib, r.growth_kib, r.peak_kib), (1000, 1010, 1010, 10, 2000));
        assert!((r.slope_kib_per_min.expect("slope") - 60.0).abs() < 1e-9);
        assert!((r.slope_second_half_kib_per_min.expect("slope") - 60.0).abs() < 1e-9);
        let flat = summarise(1, 1.0, vec![(0.0, 7), (1.0, 7), (2.0, 7)], 7);
        assert_eq!((flat.growth_kib, flat.slope_kib_per_min), (0, Some(0.0)));
        assert_eq!(summarise(1, 1.0, vec![(0.0, 7)], 7).slope_kib_per_min, None);
    }

    #[tokio::test]
    async fn samples_this_process() {
        let sampler = RssSampler::start(std::process::id(), Duration::from_millis(10)).expect("own status");
        let start = Instant::now();
        tokio::time::sleep(Duration::from_millis(60)).await;
        let r = sampler.finish(start).await.expect("report");
        assert!(r.samples.len() >= 3, "{r:?}");
        assert!(r.end_kib > 0 && r.peak_kib >= r.max_kib, "{r:?}");
    }

    #[test]
    fn a_missing_process_is_an_error() {
        assert!(read_status(u32::MAX).is_err());
    }
}
