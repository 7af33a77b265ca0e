//! Load and soak test, loopback only and bounded in time: Score, GradientStream and Sample
//! clients, dataset uploads and deletes, and a training job, all at once against one server
//! with deliberately small queues, for `SOAK_SECS` seconds (60 by default; `tests/soak.sh`
//! runs it for 600).
//!
//! Asserts that overload shows only as RESOURCE_EXHAUSTED or DEADLINE_EXCEEDED, that the
//! server's resident memory stays flat (last quarter against first), and that the training
//! job ends exactly as the same job did on the idle server (jobs are seeded, and deterministic
//! with one intra-op thread). Prints the requests sent and their answers by status code.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use relreward_client::tensor::encode_f32;
use relreward_client::{Client, ClientError, pb};
use relreward_tests::{
    Lines, TestServer, TinyModels, rss_bytes, tiny_diffusion_spec, train_tiny_reward, try_upload_lines,
};
use tokio_stream::StreamExt;
use tonic::Code;

/// Answers by (call, status), shared by every client task.
#[derive(Default, Clone)]
struct Tally(Arc<Mutex<BTreeMap<(&'static str, String), u64>>>);

impl Tally {
    fn add(&self, call: &'static str, outcome: String) {
        *self.0.lock().expect("tally").entry((call, outcome)).or_default() += 1;
    }

    fn status(&self, call: &'static str, status: &tonic::Status) {
        self.add(call, outcome(status));
    }

    fn result<T>(&self, call: &'static str, result: &Result<T, ClientError>) {
        match result {
            Ok(_) => self.add(call, "OK".into()),
            Err(ClientError::Status(s)) => self.status(call, s),
            Err(e) => self.add(call, format!("CLIENT ERROR: {e}")),
        }
    }
}

/// The status name; tonic's client ends a call whose `grpc-timeout` passed on its own side as
/// CANCELLED "Timeout expired" (before the server's DEADLINE_EXCEEDED could arrive), which is
/// the same outcome seen from the client, so it is named as such.
fn outcome(status: &tonic::Status) -> String {
    if status.code() == Code::Cancelled && status.message() == "Timeout expired" {
        return "DEADLINE_EXCEEDED (client timer)".into();
    }
    relreward_client::client::code_name(status.code()).to_owned()
}

fn allowed(outcome: &str) -> bool {
    outcome == "OK" || outcome.starts_with("RESOURCE_EXHAUSTED") || outcome.starts_with("DEADLINE_EXCEEDED")
}

/// What a well-behaved client does when refused for overload: wait a little before the next
/// call, rather than spin on refusals (which would measure only how fast the server refuses).
async fn backoff(status: &tonic::Status) {
    if status.code() == Code::ResourceExhausted {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

fn job_spec(dataset: &str, output: &str) -> pb::JobSpec {
    let optimization = pb::Optimization {
        steps: Some(150),
        batch_size: Some(16),
        learning_rate: Some(1e-3),
        checkpoint_every: Some(50),
        log_every: Some(10),
        ..Default::default()
    };
    tiny_diffusion_spec(dataset, output, 11, optimization)
}

/// Submits `spec` and waits until the job ends; returns it and its output model.
async fn run_job(client: &Client, spec: pb::JobSpec, limit: Duration) -> (pb::Job, pb::Model) {
    let output = spec.output_model.clone();
    let job = client
        .jobs()
        .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() })
        .await
        .expect("submit")
        .into_inner();
    let started = Instant::now();
    loop {
        let got = client.get_job(&job.id).await.expect("get job");
        if got.state() == pb::JobState::Succeeded {
            return (got, client.get_model(&output).await.expect("output model"));
        }
        assert!(
            !matches!(got.state(), pb::JobState::Failed | pb::JobState::Cancelled),
            "job {} ended {:?}: {}",
            got.id,
            got.state(),
            got.error
        );
        assert!(started.elapsed() < limit, "job {} not done after {limit:?} (step {})", got.id, got.step);
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

fn x_for(m: &TinyModels, items: usize, seed: usize) -> pb::Tensor {
    let n = items * m.horizon * m.transition_dim;
    let values: Vec<f32> = (0..n).map(|i| (((i + seed) * 7919) % 1000) as f32 / 500.0 - 1.0).collect();
    encode_f32(&[items as u64, m.horizon as u64, m.transition_dim as u64], &values)
}

async fn score_client(client: Client, m: TinyModels, tally: Tally, stop: Instant, id: usize) {
    let mut i = 0;
    while Instant::now() < stop {
        let mut request = tonic::Request::new(pb::ScoreRequest {
            model: m.reward.clone(),
            x: Some(x_for(&m, 4, id * 1000 + i)),
            ..Default::default()
        });
        request.set_timeout(Duration::from_millis(300));
        match client.rewards().score(request).await {
            Ok(_) => tally.add("Score", "OK".into()),
            Err(s) => {
                tally.status("Score", &s);
                backoff(&s).await;
            }
        }
        i += 1;
    }
}

async fn gradient_stream_client(client: Client, m: TinyModels, tally: Tally, stop: Instant, id: usize) {
    let mut next_id = 0u64;
    while Instant::now() < stop {
        let mut stream = match client.gradient_stream().await {
            Ok(s) => s,
            Err(e) => {
                tally.result::<()>("GradientStream (open)", &Err(e));
                continue;
            }
        };
        // One planner episode: bursts of 8 denoising steps, all in flight at once.
        for _ in 0..10 {
            if Instant::now() >= stop {
                break;
            }
            for _ in 0..8 {
                next_id += 1;
                let request = pb::GradientRequest {
                    request_id: next_id,
                    model: m.reward.clone(),
                    x: Some(x_for(&m, 2, id * 100_000 + next_id as usize)),
                    t: vec![3],
                    ..Default::default()
                };
                if stream.send(request).await.is_err() {
                    break;
                }
            }
            for _ in 0..8 {
                match stream.message().await {
                    Ok(Some(response)) => match &response.error {
                        None => tally.add("GradientStream", "OK".into()),
                        Some(e) => {
                            let status = relreward_client::client::stream_error_status(e);
                            tally.status("GradientStream", &status);
                            backoff(&status).await;
                        }
                    },
                    Ok(None) => break,
                    Err(e) => {
                        tally.result::<()>("GradientStream (call)", &Err(e));
                        break;
                    }
                }
            }
        }
    }
}

async fn sample_client(client: Client, m: TinyModels, tally: Tally, stop: Instant) {
    let mut seed = 0;
    while Instant::now() < stop {
        seed += 1;
        let mut request = tonic::Request::new(pb::SampleRequest {
            model: m.base.clone(),
            n: 4,
            seed: Some(seed),
            ..Default::default()
        });
        request.set_timeout(Duration::from_secs(5));
        match client.rewards().sample(request).await {
            Ok(response) => {
                let mut stream = response.into_inner();
                let mut failed = None;
                while let Some(item) = stream.next().await {
                    if let Err(s) = item {
                        failed = Some(s);
                        break;
                    }
                }
                match failed {
                    None => tally.add("Sample", "OK".into()),
                    Some(s) => tally.status("Sample", &s),
                }
            }
            Err(s) => tally.status("Sample", &s),
        }
    }
}

async fn upload_client(client: Client, tally: Tally, stop: Instant) {
    let mut i = 0u64;
    while Instant::now() < stop {
        i += 1;
        let lines =
            Lines { episodes: 40, seed: i, start: [(2.0, -1.0), (2.0, -1.0)], velocity: [(0.2, -0.1), (0.2, -0.1)] };
        let name = format!("soak-upload-{i}");
        let uploaded = try_upload_lines(&client, &name, &lines).await;
        tally.result("UploadDataset", &uploaded);
        if uploaded.is_ok() {
            // Deleted again, so the data directory stays the same size however long this runs.
            tally.result("DeleteDataset", &client.delete_dataset(&name).await);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn overload_is_refused_cleanly_memory_stays_flat_and_jobs_are_unaffected() {
    let secs: u64 = std::env::var("SOAK_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(60);
    let server = TestServer::start_with_env(&[
        ("RELREWARD__SERVING__QUEUE_CAPACITY", "4"),
        ("RELREWARD__SERVING__MAX_BATCH", "16"),
        ("RELREWARD__ENGINE__INFERENCE_WORKERS", "1"),
        ("RELREWARD__LOG__LEVEL", "warn"),
    ]);
    let tmp = tempfile::tempdir().expect("tmp");
    let m = train_tiny_reward(&server, tmp.path());
    let client = server.client().await;

    // The reference: the job alone on the idle server.
    let idle_started = Instant::now();
    let (idle_job, idle_model) = run_job(&client, job_spec(&m.dataset, "soak-idle"), Duration::from_secs(600)).await;
    let idle_secs = idle_started.elapsed().as_secs_f64();

    let pid = server.pid().expect("server pid");
    let tally = Tally::default();
    let stop = Instant::now() + Duration::from_secs(secs);
    let mut tasks = tokio::task::JoinSet::new();
    // Each client on its own connection, as separate callers would be.
    for id in 0..3 {
        tasks.spawn(score_client(server.client().await, m.clone(), tally.clone(), stop, id));
    }
    for id in 0..2 {
        tasks.spawn(gradient_stream_client(server.client().await, m.clone(), tally.clone(), stop, id));
    }
    tasks.spawn(sample_client(server.client().await, m.clone(), tally.clone(), stop));
    tasks.spawn(upload_client(server.client().await, tally.clone(), stop));
    let rss = Arc::new(Mutex::new(Vec::new()));
    let sampler = {
        let rss = rss.clone();
        tokio::spawn(async move {
            while Instant::now() < stop {
                if let Some(bytes) = rss_bytes(pid) {
                    rss.lock().expect("rss").push(bytes);
                }
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
        })
    };
    // The same job again and again while the load lasts (at least once), each run compared
    // with the idle one; outputs are deleted so the data directory stays the same size.
    let (job_client, dataset) = (server.client().await, m.dataset.clone());
    let loaded = tokio::spawn(async move {
        let mut runs = Vec::new();
        while runs.is_empty() || Instant::now() < stop {
            let started = Instant::now();
            let output = format!("soak-loaded-{}", runs.len());
            let (job, model) = run_job(&job_client, job_spec(&dataset, &output), Duration::from_secs(600)).await;
            job_client.delete_model(&output).await.expect("delete job output");
            runs.push((job, model, started.elapsed().as_secs_f64()));
        }
        runs
    });

    while let Some(joined) = tasks.join_next().await {
        joined.expect("client task");
    }
    sampler.await.expect("sampler");
    let runs = loaded.await.expect("job task");

    let counts = tally.0.lock().expect("tally").clone();
    let total: u64 = counts.values().sum();
    let loaded_secs: Vec<String> = runs.iter().map(|(_, _, secs)| format!("{secs:.1}")).collect();
    eprintln!(
        "soak: {secs} s, {total} requests answered; job alone {idle_secs:.1} s, under load {} runs of {} s",
        runs.len(),
        loaded_secs.join(", ")
    );
    for ((call, outcome), n) in &counts {
        eprintln!("soak:   {call:<24} {outcome:<34} {n}");
    }
    let samples = rss.lock().expect("rss").clone();
    assert!(samples.len() >= 8, "too few memory samples: {}", samples.len());
    let quarter = samples.len() / 4;
    let mean = |s: &[u64]| s.iter().sum::<u64>() as f64 / s.len() as f64 / (1 << 20) as f64;
    let (first, last) = (mean(&samples[..quarter]), mean(&samples[samples.len() - quarter..]));
    let peak = *samples.iter().max().expect("samples") as f64 / (1 << 20) as f64;
    eprintln!("soak: RSS first quarter {first:.1} MiB, last quarter {last:.1} MiB, peak {peak:.1} MiB");
    eprintln!("soak: job alone: loss {}, weights sha256 {}", idle_job.loss, idle_model.sha256);

    let bad: Vec<_> = counts.iter().filter(|((_, outcome), _)| !allowed(outcome)).collect();
    assert!(bad.is_empty(), "errors other than RESOURCE_EXHAUSTED / DEADLINE_EXCEEDED: {bad:?}");
    for call in ["Score", "GradientStream", "Sample", "UploadDataset"] {
        let ok = counts.get(&(call, "OK".to_owned())).copied().unwrap_or(0);
        assert!(ok > 0, "no {call} succeeded under load: {counts:?}");
    }
    // Generous: the allocator keeps freed pages, and the job's tensors come and go.
    assert!(last <= first * 1.5 + 64.0, "memory grew from {first:.1} MiB to {last:.1} MiB");
    for (i, (job, model, _)) in runs.iter().enumerate() {
        assert_eq!(job.step, idle_job.step, "run {i}");
        assert_eq!(job.loss.to_bits(), idle_job.loss.to_bits(), "run {i}: final loss {} under load", job.loss);
        assert_eq!(model.sha256, idle_model.sha256, "run {i}: weights differ under load");
    }
    assert!(server.log().lines().all(|l| !l.contains("panicked")), "server log:\n{}", server.log());
}
