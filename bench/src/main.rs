//! `relreward-loadgen`: closed-loop load on relreward's serving endpoints, loopback only.
//!
//! Module map:
//! - [`args`]: flags, their validation, and the loopback-only rule for `--endpoint`.
//! - [`load`]: the clients (one connection and one request in flight each), the measurement
//!   window, HDR histograms of latency merged across clients.
//! - [`report`]: the report as text or one JSON object.
//! - [`rss`]: the server's resident set size sampled during the load (`--rss-pid`).
//!
//! Depends on the client library only, never on the server: it must not link libtorch.

mod args;
mod load;
mod report;
mod rss;

use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Parser;
use relreward_client::Client;
use relreward_proto::v1::GetModelRequest;

use crate::args::Args;
use crate::load::Plan;
use crate::report::Report;

fn main() -> ExitCode {
    let args = Args::parse();
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("relreward-loadgen: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(args)) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("relreward-loadgen: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Exit status: success when at least one request succeeded (errors are in the report).
async fn run(args: Args) -> Result<ExitCode> {
    for endpoint in &args.endpoint {
        let uri = args::check_loopback(endpoint)?;
        args::check_resolved(&uri).await?;
    }
    let item_shape = match &args.shape {
        Some(shape) => shape.0.clone(),
        None => input_shape(&args.endpoint[0], &args.model).await?,
    };
    let plan = Plan {
        model: args.model.clone(),
        mode: args.mode,
        clients: args.clients,
        batch: args.batch,
        item_shape,
        t: args.t,
        warmup: Duration::from_secs_f64(args.warmup),
        stop: args.stop(),
        timeout: Duration::from_secs_f64(args.timeout),
    };
    let sampler =
        args.rss_pid.map(|pid| rss::RssSampler::start(pid, Duration::from_secs_f64(args.rss_every))).transpose()?;
    let totals = load::run(&args.endpoint, plan.clone()).await?;
    let mut report = Report::new(&args.endpoint.join(","), &plan, &totals);
    if let Some(sampler) = sampler {
        report.rss = Some(sampler.finish(totals.measure_start).await?);
    }
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print!("{}", report.to_text());
    }
    if report.requests == 0 {
        eprintln!("relreward-loadgen: no request succeeded");
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}

/// The reward model's item shape, from ModelService.GetModel (`reward.input_shape`).
async fn input_shape(endpoint: &str, model: &str) -> Result<Vec<u64>> {
    let client = Client::connect(endpoint).await?;
    let record = client
        .models()
        .get_model(GetModelRequest { name: model.to_owned() })
        .await
        .with_context(|| format!("cannot get model `{model}` (pass --shape to skip this)"))?
        .into_inner();
    match record.reward {
        Some(info) if !info.input_shape.is_empty() => Ok(info.input_shape),
        _ => bail!("model `{model}` is not a reward model with an input shape (pass --shape)"),
    }
}
