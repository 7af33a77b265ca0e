//! Command-line flags, their validation, and the loopback-only rule for `--endpoint`.

use std::net::IpAddr;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::{Parser, ValueEnum};
use tonic::codegen::http::Uri;

/// Closed-loop load on RewardService.Gradient / GradientStream: each client has its own
/// connection and exactly one request in flight, as a planner that needs the gradient of
/// denoising step k before it sends step k+1.
///
/// Inputs are deterministic pseudo-random values in [-1, 1], different per client, sent and
/// answered in normalized units (the diffusion models' space, where a planner works).
/// Only loopback endpoints are accepted: the load generator runs beside the server and shares
/// its CPUs, which every report says.
#[derive(Debug, Parser)]
#[command(name = "relreward-loadgen", version)]
pub struct Args {
    /// Server address; its host must be a loopback address (127.0.0.0/8, ::1) or `localhost`.
    /// Repeat it for several replicas: client i connects to the (i mod n)-th, a client-side
    /// round-robin over connections.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub endpoint: Vec<String>,

    /// Reward model to query.
    #[arg(long)]
    pub model: String,

    /// Shape of one item, e.g. 64,6 for [H, D] (default: the model's input_shape from GetModel).
    #[arg(long, value_name = "N,N,..", value_parser = parse_shape)]
    pub shape: Option<ItemShape>,

    /// Items per request.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub batch: u32,

    /// Diffusion time of every item.
    #[arg(long, default_value_t = 0)]
    pub t: u32,

    /// Concurrent clients, each with its own connection and one request in flight.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub clients: u32,

    /// unary: one Gradient call per request; stream: one GradientStream per client.
    #[arg(long, value_enum, default_value_t = Mode::Unary)]
    pub mode: Mode,

    /// Recorded requests per client (after the warmup).
    #[arg(long, conflicts_with = "duration", value_parser = clap::value_parser!(u64).range(1..))]
    pub requests: Option<u64>,

    /// Recorded seconds (after the warmup) [default: 10 unless --requests is given].
    #[arg(long, value_parser = parse_seconds)]
    pub duration: Option<f64>,

    /// Seconds of load before recording starts (not recorded).
    #[arg(long, default_value_t = 1.0, value_parser = parse_seconds)]
    pub warmup: f64,

    /// Seconds a client waits for one response before counting it as an error (DEADLINE_EXCEEDED).
    #[arg(long, default_value_t = 30.0, value_parser = parse_seconds)]
    pub timeout: f64,

    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,

    /// Also sample this process's resident set size (the server's PID, read from
    /// /proc/PID/status) during the load, and report its growth and slope.
    #[arg(long, value_name = "PID")]
    pub rss_pid: Option<u32>,

    /// Seconds between two RSS samples (with --rss-pid).
    #[arg(long, default_value_t = 1.0, requires = "rss_pid", value_parser = parse_seconds)]
    pub rss_every: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Unary,
    Stream,
}

/// When recording stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Stop {
    /// This many recorded requests per client.
    Requests(u64),
    /// After this long.
    Duration(Duration),
}

const DEFAULT_DURATION_SECS: f64 = 10.0;

impl Args {
    pub fn stop(&self) -> Stop {
        match (self.requests, self.duration) {
            (Some(n), _) => Stop::Requests(n),
            (None, d) => Stop::Duration(Duration::from_secs_f64(d.unwrap_or(DEFAULT_DURATION_SECS))),
        }
    }
}

/// The shape of one item (a newtype so that clap takes `64,6` as one value, not a list).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ItemShape(pub Vec<u64>);

/// `64,6` -> `[64, 6]`; every dimension positive.
fn parse_shape(s: &str) -> Result<ItemShape, String> {
    let dims = s
        .split(',')
        .map(|d| match d.trim().parse::<u64>() {
            Ok(0) => Err(format!("dimension 0 in `{s}`: every dimension must be positive")),
            Ok(n) => Ok(n),
            Err(_) => Err(format!("`{d}` in `{s}` is not a dimension (expected e.g. 64,6)")),
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(ItemShape(dims))
}

/// Non-negative, finite seconds, at most a day (every loop here stops by itself).
fn parse_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if x.is_finite() && (0.0..=86_400.0).contains(&x) => Ok(x),
        _ => Err(format!("`{s}` is not a number of seconds between 0 and 86400")),
    }
}

/// Refuses every endpoint that is not plain `http://` to a loopback host: an IP literal in
/// 127.0.0.0/8 or ::1 (also as IPv4-mapped ::ffff:127.x.y.z), or the name `localhost`, which
/// must resolve to loopback addresses only ([`check_resolved`]). This tool generates load and
/// must never point it at another machine.
pub fn check_loopback(endpoint: &str) -> Result<Uri> {
    let refuse = |why: &str| {
        anyhow::anyhow!(
            "refusing endpoint `{endpoint}`: {why}; relreward-loadgen only targets loopback \
             (http://127.0.0.1:PORT, http://[::1]:PORT or http://localhost:PORT)"
        )
    };
    let uri: Uri = endpoint.parse().map_err(|e| refuse(&format!("not a URI ({e})")))?;
    match uri.scheme_str() {
        Some("http") => {}
        Some(other) => return Err(refuse(&format!("scheme `{other}` (expected http)"))),
        None => return Err(refuse("no scheme (expected http://)")),
    }
    let host = uri.host().ok_or_else(|| refuse("no host"))?;
    if host.eq_ignore_ascii_case("localhost") {
        return Ok(uri);
    }
    let literal = host.strip_prefix('[').and_then(|h| h.strip_suffix(']')).unwrap_or(host);
    let ip: IpAddr =
        literal.parse().map_err(|_| refuse(&format!("host `{host}` is neither an IP address nor localhost")))?;
    if !is_loopback(ip) {
        return Err(refuse(&format!("{ip} is not a loopback address")));
    }
    Ok(uri)
}

fn is_loopback(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => v4.is_loopback(),
        IpAddr::V6(v6) => v6.is_loopback() || v6.to_ipv4_mapped().is_some_and(|v4| v4.is_loopback()),
    }
}

/// For `localhost`: every address it resolves to must be loopback (a hosts file could say
/// otherwise). IP literals were checked by [`check_loopback`] already.
pub async fn check_resolved(uri: &Uri) -> Result<()> {
    let host = uri.host().unwrap_or_default();
    if !host.eq_ignore_ascii_case("localhost") {
        return Ok(());
    }
    let port = uri.port_u16().unwrap_or(80);
    let addrs: Vec<_> =
        tokio::net::lookup_host((host, port)).await.with_context(|| format!("cannot resolve `{host}`"))?.collect();
    if addrs.is_empty() {
        bail!("`{host}` resolves to no address");
    }
    if let Some(bad) = addrs.iter().find(|a| !is_loopback(a.ip())) {
        bail!("refusing endpoint: `{host}` resolves to {}, which is not a loopback address", bad.ip());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Args, clap::Error> {
        Args::try_parse_from(std::iter::once("relreward-loadgen").chain(args.iter().copied()))
    }

    #[test]
    fn loopback_endpoints_are_accepted() {
        for ok in [
            "http://127.0.0.1:50051",
            "http://127.0.0.1",
            "http://127.255.3.4:1",
            "http://localhost:6000",
            "http://LocalHost:6000",
            "http://[::1]:50051",
            "http://[::ffff:127.0.0.1]:50051",
        ] {
            assert!(check_loopback(ok).is_ok(), "{ok} should be accepted");
        }
    }

    #[test]
    fn other_endpoints_are_refused() {
        for bad in [
            "http://10.0.0.1:50051",
            "http://192.168.1.2:50051",
            "http://0.0.0.0:50051",
            "http://[::]:50051",
            "http://[2001:db8::1]:50051",
            "http://[::ffff:10.0.0.1]:50051",
            "http://example.com:50051",
            "http://localhost.example.com:50051",
            "http://127.0.0.1.example.com:50051",
            "https://127.0.0.1:50051",
            "127.0.0.1:50051",
            "http://",
            "not a uri",
        ] {
            let err = check_loopback(bad).expect_err(bad).to_string();
            assert!(err.contains("refusing endpoint") && err.contains("loopback"), "{bad}: {err}");
        }
    }

    #[test]
    fn refusal_names_the_address() {
        let err = check_loopback("http://10.1.2.3:50051").expect_err("refused").to_string();
        assert!(err.contains("10.1.2.3 is not a loopback address"), "{err}");
    }

    #[tokio::test]
    async fn localhost_resolves_to_loopback() {
        let uri = check_loopback("http://localhost:50051").expect("accepted");
        check_resolved(&uri).await.expect("localhost is loopback here");
    }

    #[test]
    fn defaults() {
        let a = parse(&["--model", "m"]).expect("parses");
        assert_eq!(a.endpoint, ["http://127.0.0.1:50051"]);
        assert_eq!((a.batch, a.t, a.clients, a.mode, a.json), (1, 0, 1, Mode::Unary, false));
        assert_eq!(a.shape, None);
        assert_eq!(a.warmup, 1.0);
        assert_eq!(a.stop(), Stop::Duration(Duration::from_secs(10)));
    }

    #[test]
    fn every_flag() {
        let a = parse(&[
            "--endpoint",
            "http://127.0.0.1:7000",
            "--model",
            "maze-reward",
            "--shape",
            "64, 6",
            "--batch",
            "8",
            "--t",
            "5",
            "--clients",
            "64",
            "--mode",
            "stream",
            "--requests",
            "2000",
            "--warmup",
            "0.5",
            "--json",
        ])
        .expect("parses");
        assert_eq!(a.endpoint, ["http://127.0.0.1:7000"]);
        assert_eq!(a.model, "maze-reward");
        assert_eq!(a.shape, Some(ItemShape(vec![64, 6])));
        assert_eq!((a.batch, a.t, a.clients, a.mode), (8, 5, 64, Mode::Stream));
        assert_eq!(a.stop(), Stop::Requests(2000));
        assert_eq!(a.warmup, 0.5);
        assert!(a.json);
        assert_eq!((a.rss_pid, a.rss_every), (None, 1.0));
        let r = parse(&["--model", "m", "--rss-pid", "42", "--rss-every", "0.5"]).expect("parses");
        assert_eq!((r.rss_pid, r.rss_every), (Some(42), 0.5));
        let d = parse(&["--model", "m", "--duration", "2.5"]).expect("parses");
        assert_eq!(d.stop(), Stop::Duration(Duration::from_secs_f64(2.5)));
    }

    #[test]
    fn bad_flags_are_refused() {
        for bad in [
            &["--shape", "64,6"][..],                                // no --model
            &["--model", "m", "--shape", "64,0"],                    // zero dimension
            &["--model", "m", "--shape", "64,x"],                    // not a number
            &["--model", "m", "--shape", ""],                        // empty
            &["--model", "m", "--batch", "0"],                       // no items
            &["--model", "m", "--clients", "0"],                     // no clients
            &["--model", "m", "--mode", "bidi"],                     // unknown mode
            &["--model", "m", "--requests", "0"],                    // nothing to do
            &["--model", "m", "--requests", "5", "--duration", "3"], // both stops
            &["--model", "m", "--duration", "-1"],                   // negative
            &["--model", "m", "--duration", "inf"],                  // unbounded
            &["--model", "m", "--warmup", "NaN"],                    // not a number
            &["--model", "m", "--rss-every", "2"],                   // sampling what?
            &["--model", "m", "--rss-pid", "x"],                     // not a PID
        ] {
            assert!(parse(bad).is_err(), "{bad:?} should be refused");
        }
    }
}
