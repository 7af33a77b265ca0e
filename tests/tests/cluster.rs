//! The shared backend across processes: two serving replicas and two workers on loopback,
//! against a real PostgreSQL and a real S3-protocol server started by `tests/cluster/infra.sh`
//! (`make test-cluster` runs both; the test is ignored by a plain `cargo test`, which has no
//! database to talk to).
//!
//! Asserts: an upload through one replica is visible through the other; N submitted jobs each
//! run exactly once (one "started" event, no resume); kill -9 of the worker running a job
//! makes the other worker resume it from its checkpoint; a reward trained by a worker is
//! served by both replicas with bit-identical outputs; nothing is lost (every record on both
//! replicas, every stored blob complete and matching its digest list in the bucket).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use relreward_client::pb::{self, job_event::Event};
use relreward_client::tensor::encode_f32;
use relreward_tests::{
    Lines, TestServer, eventually, final_state, tiny_diffusion_spec, train_tiny_reward, upload_lines, watch_all,
};
use tokio_stream::StreamExt;

const LINES: Lines =
    Lines { episodes: 20, seed: 11, start: [(2.0, -1.0), (2.0, -1.0)], velocity: [(0.2, -0.1), (0.2, -0.1)] };

/// The infrastructure `tests/cluster/infra.sh start` wrote to its env file.
struct Infra {
    pg_url: String,
    /// The CA of the database server's certificate (it takes TLS connections only).
    pg_ca: String,
    s3_endpoint: String,
    bucket: String,
    region: String,
    key: String,
    secret: String,
    /// The S3 server's directory for the bucket (s3s-fs keeps objects as files).
    bucket_dir: PathBuf,
}

fn var(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| {
        panic!("{name} is not set: run this test through `make test-cluster` (tests/cluster/run.sh)")
    })
}

impl Infra {
    fn from_env() -> Self {
        let bucket = var("RELREWARD_TEST_S3_BUCKET");
        Self {
            pg_url: var("RELREWARD_TEST_PG_URL"),
            pg_ca: var("RELREWARD_TEST_PG_CA"),
            s3_endpoint: var("RELREWARD_TEST_S3_ENDPOINT"),
            region: var("RELREWARD_TEST_S3_REGION"),
            key: var("RELREWARD_TEST_S3_ACCESS_KEY_ID"),
            secret: var("RELREWARD_TEST_S3_SECRET_ACCESS_KEY"),
            bucket_dir: PathBuf::from(var("RELREWARD_TEST_S3_ROOT")).join(&bucket),
            bucket,
        }
    }

    fn start(&self, role: &str) -> TestServer {
        self.start_with(role, &[])
    }

    fn start_with(&self, role: &str, extra: &[(&str, &str)]) -> TestServer {
        let mut env = vec![
            ("RELREWARD__SERVER__ROLE", role),
            ("RELREWARD__STORAGE__BACKEND", "shared"),
            ("RELREWARD__STORAGE__POSTGRES__URL", &self.pg_url),
            ("RELREWARD__STORAGE__POSTGRES__CA_FILE", &self.pg_ca),
            ("RELREWARD__STORAGE__S3__ENDPOINT", &self.s3_endpoint),
            ("RELREWARD__STORAGE__S3__BUCKET", &self.bucket),
            ("RELREWARD__STORAGE__S3__REGION", &self.region),
            ("RELREWARD__STORAGE__S3__ACCESS_KEY_ID", &self.key),
            ("RELREWARD__STORAGE__S3__SECRET_ACCESS_KEY", &self.secret),
            ("RELREWARD__STORAGE__S3__ALLOW_HTTP", "true"),
            // Short leases and polls, so a dead worker's job moves within seconds.
            ("RELREWARD__JOBS__LEASE_SECS", "3"),
            ("RELREWARD__JOBS__POLL_MS", "200"),
        ];
        env.extend_from_slice(extra);
        TestServer::start_with_env(&env)
    }
}

fn optimization(steps: u64, checkpoint_every: u64) -> pb::Optimization {
    pb::Optimization {
        steps: Some(steps),
        batch_size: Some(8),
        checkpoint_every: Some(checkpoint_every),
        log_every: Some(10),
        ..Default::default()
    }
}

fn states(events: &[pb::JobEvent]) -> Vec<String> {
    events
        .iter()
        .filter_map(|e| match &e.event {
            Some(Event::State(s)) if s.state() == pb::JobState::Running => Some(s.message.clone()),
            _ => None,
        })
        .collect()
}

/// The worker name ("host/pid/suffix") a RUNNING state message names, and its pid.
fn worker_of(message: &str) -> (String, u32) {
    let name = message.rsplit(" on ").next().expect("a worker name").to_owned();
    let pid = name.split('/').nth(1).and_then(|p| p.parse().ok()).unwrap_or_else(|| panic!("no pid in '{name}'"));
    (name, pid)
}

/// Every object file under the bucket directory, grouped by blob key ("models/<id>").
fn bucket_blobs(dir: &Path) -> BTreeMap<String, Vec<PathBuf>> {
    let mut blobs = BTreeMap::new();
    for ns in ["datasets", "models", "checkpoints"] {
        for blob in std::fs::read_dir(dir.join(ns)).into_iter().flatten().flatten() {
            let files: Vec<PathBuf> = std::fs::read_dir(blob.path())
                .into_iter()
                .flatten()
                .flatten()
                .map(|f| f.path())
                .filter(|p| p.is_file())
                .collect();
            // s3s-fs leaves a key's directory behind when its last object is deleted; S3 has
            // no directories, so an empty one is no blob.
            if !files.is_empty() {
                blobs.insert(format!("{ns}/{}", blob.file_name().to_string_lossy()), files);
            }
        }
    }
    blobs
}

/// A blob is whole when its SHA256SUMS names exactly its other files with their digests.
fn blob_is_whole(files: &[PathBuf]) -> Result<(), String> {
    use sha2::{Digest, Sha256};
    let sums = files.iter().find(|p| p.ends_with("SHA256SUMS")).ok_or("no SHA256SUMS")?;
    let text = std::fs::read_to_string(sums).map_err(|e| e.to_string())?;
    let mut listed = 0;
    for line in text.lines() {
        let (digest, name) = line.split_once("  ").ok_or_else(|| format!("bad line '{line}'"))?;
        let file = files.iter().find(|p| p.file_name().is_some_and(|n| n == name)).ok_or(format!("{name} missing"))?;
        let bytes = std::fs::read(file).map_err(|e| e.to_string())?;
        if hex::encode(Sha256::digest(&bytes)) != digest {
            return Err(format!("{name} does not match its digest"));
        }
        listed += 1;
    }
    if listed + 1 != files.len() {
        return Err(format!("{} files, {listed} listed", files.len()));
    }
    Ok(())
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs PostgreSQL and an S3 server: run with `make test-cluster`"]
async fn two_replicas_and_two_workers_share_one_store() {
    let infra = Infra::from_env();
    let serve = [infra.start("serve"), infra.start("serve")];
    let mut work = [infra.start("work"), infra.start("work")];
    let a = serve[0].client().await;
    let b = serve[1].client().await;

    // 1. An upload through one replica is visible through the other.
    upload_lines(&a, "lines", &LINES).await;
    let (via_a, via_b) = (a.get_dataset("lines").await.expect("A"), b.get_dataset("lines").await.expect("B"));
    assert_eq!(via_a, via_b, "the same record through both replicas");
    assert_eq!(via_b.num_rows, 20 * 24);
    println!("FIGURE upload through A visible through B: {} rows, sha256 {}", via_b.num_rows, via_b.sha256);

    // 2. N jobs submitted through both replicas each run exactly once.
    const N: usize = 4;
    for i in 0..N {
        let client = if i % 2 == 0 { &a } else { &b };
        let spec = tiny_diffusion_spec("lines", &format!("m{i}"), i as u64, optimization(30, 10));
        client.submit_job(spec, Some(&format!("once-{i}"))).await.expect("submit");
    }
    let mut ran_on = BTreeMap::new();
    for i in 0..N {
        // Watched through the replica that did not take the submission.
        let client = if i % 2 == 0 { &b } else { &a };
        let events = watch_all(client, &format!("once-{i}"), 0).await;
        assert_eq!(final_state(&events), Some(pb::JobState::Succeeded), "once-{i}: {events:?}");
        let running = states(&events);
        assert_eq!(running.len(), 1, "once-{i} ran exactly once: {running:?}");
        assert!(running[0].starts_with("started on "), "{running:?}");
        *ran_on.entry(worker_of(&running[0]).0).or_insert(0) += 1;
    }
    println!("FIGURE {N} jobs, each run once; per worker: {ran_on:?}");
    for i in 0..N {
        assert!(b.get_model(&format!("m{i}")).await.is_ok(), "model m{i} registered once, visible on B");
    }

    // 3. kill -9 of the worker running a job: the other worker resumes it from its checkpoint.
    let spec = tiny_diffusion_spec("lines", "long", 9, optimization(1500, 100));
    a.submit_job(spec, Some("long")).await.expect("submit long");
    let mut stream = b.watch_job("long", 0).await.expect("watch long");
    let (mut victim, mut checkpoint) = (None, 0);
    while let Some(e) = stream.next().await {
        match e.expect("event").event {
            Some(Event::State(s)) if s.state() == pb::JobState::Running => victim = Some(worker_of(&s.message)),
            Some(Event::Checkpoint(c)) => {
                checkpoint = c.step;
                if checkpoint >= 200 {
                    break;
                }
            }
            Some(Event::State(s)) if s.state() != pb::JobState::Pending => panic!("long ended early: {s:?}"),
            _ => {}
        }
    }
    drop(stream);
    let (victim_name, victim_pid) = victim.expect("the job started");
    let index = work.iter().position(|w| w.pid() == Some(victim_pid)).expect("the victim is one of the workers");
    work[index].kill();
    let survivor_pid = work[1 - index].pid().expect("the other worker runs");
    let events = watch_all(&a, "long", 0).await;
    assert_eq!(final_state(&events), Some(pb::JobState::Succeeded), "{events:?}");
    let running = states(&events);
    assert_eq!(running.len(), 2, "started once, resumed once: {running:?}");
    let resumed = &running[1];
    assert!(resumed.starts_with("resumed at step "), "{resumed}");
    // The step the runner restarted from (the record's step may be past it: progress after the
    // last checkpoint is recorded, then lost with the worker).
    let at: u64 = events
        .iter()
        .find_map(|e| match &e.event {
            Some(Event::Log(l)) => l.message.strip_prefix("resumed from the checkpoint at step ")?.parse().ok(),
            _ => None,
        })
        .unwrap_or_else(|| panic!("no resume log line: {events:?}"));
    let (heir, heir_pid) = worker_of(resumed);
    assert_eq!(heir_pid, survivor_pid, "resumed by the other worker ({heir}), not {victim_name}");
    assert!(at >= checkpoint, "resumed at {at}, checkpoint seen {checkpoint}");
    assert_eq!(at % 100, 0, "a checkpoint step");
    let progress: Vec<u64> = events
        .iter()
        .skip_while(|e| !matches!(&e.event, Some(Event::Log(l)) if l.message.starts_with("resumed from")))
        .filter_map(|e| match &e.event {
            Some(Event::Progress(p)) => Some(p.step),
            _ => None,
        })
        .collect();
    assert!(progress.iter().all(|s| *s > at), "training went on from the checkpoint: {progress:?}");
    assert_eq!(progress.last(), Some(&1500));
    println!(
        "FIGURE kill -9 of {victim_name} after the checkpoint at step {checkpoint}: resumed at step {at} on {heir}"
    );

    // 4. A reward trained by the workers is served by both replicas, bit for bit.
    let tmp = tempfile::tempdir().expect("tmp");
    let m = train_tiny_reward(&serve[0], tmp.path());
    let (h, d) = (m.horizon, m.transition_dim);
    let x: Vec<f32> = (0..3 * h * d).map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0).collect();
    let request = pb::ScoreRequest {
        model: m.reward.clone(),
        x: Some(encode_f32(&[3, h as u64, d as u64], &x)),
        ..Default::default()
    };
    let (score_a, score_b) = (a.score(request.clone()).await.expect("A"), b.score(request).await.expect("B"));
    assert_eq!(score_a.rewards, score_b.rewards, "identical rewards from both replicas");
    let gradient = pb::GradientRequest {
        model: m.reward.clone(),
        x: Some(encode_f32(&[3, h as u64, d as u64], &x)),
        ..Default::default()
    };
    let (grad_a, grad_b) = (a.gradient(gradient.clone()).await.expect("A"), b.gradient(gradient).await.expect("B"));
    assert_eq!(grad_a.gradient, grad_b.gradient, "identical gradients from both replicas");
    println!("FIGURE reward '{}' trained by a worker: Score and Gradient bit-identical on both replicas", m.reward);

    // 5. Nothing lost: both replicas list the same records; every blob in the bucket is whole
    // and referenced. The killed worker may have left a half-uploaded checkpoint (no digest
    // list, no record): start-up garbage collection removes such objects once older than
    // storage.s3.orphan_grace_secs, which a replica started with a grace of 0 shows.
    let (datasets_a, datasets_b) = (a.list_datasets().await.expect("A"), b.list_datasets().await.expect("B"));
    assert_eq!(datasets_a, datasets_b);
    let models_a = a.list_models(pb::ModelKind::Unspecified).await.expect("A");
    assert_eq!(models_a, b.list_models(pb::ModelKind::Unspecified).await.expect("B"));
    let expected_models = N + 1 + 3; // m0..m3, long, base, expert, rw
    assert_eq!(models_a.len(), expected_models, "{:?}", models_a.iter().map(|m| &m.name).collect::<Vec<_>>());
    let leftovers: Vec<String> = bucket_blobs(&infra.bucket_dir)
        .into_iter()
        .filter(|(_, files)| blob_is_whole(files).is_err())
        .map(|(key, _)| key)
        .collect();
    assert!(leftovers.iter().all(|k| k.starts_with("checkpoints/")), "only an interrupted checkpoint: {leftovers:?}");
    // Plus one planted by hand (s3s-fs serves plain files), so collection is always exercised.
    let planted = infra.bucket_dir.join("checkpoints/0000feed");
    std::fs::create_dir_all(&planted).expect("plant");
    std::fs::write(planted.join("weights.safetensors"), b"half an upload").expect("plant");
    let collector = infra.start_with("serve", &[("RELREWARD__STORAGE__S3__ORPHAN_GRACE_SECS", "0")]);
    let collected = eventually(30, || collector.log().contains("removed leftovers of interrupted writes")).await;
    assert!(collected, "the orphans were not collected; log:\n{}", collector.log());
    assert!(!planted.join("weights.safetensors").exists(), "the planted orphan is gone");
    let blobs = bucket_blobs(&infra.bucket_dir);
    for (key, files) in &blobs {
        blob_is_whole(files).unwrap_or_else(|e| panic!("blob {key} in the bucket is not whole: {e}"));
    }
    let count = |ns: &str| blobs.keys().filter(|k| k.starts_with(ns)).count();
    assert_eq!(count("models/"), expected_models, "one blob per model: {blobs:?}");
    assert_eq!(count("datasets/"), datasets_a.len(), "one blob per dataset");
    assert_eq!(count("checkpoints/"), 0, "finished jobs keep no checkpoints");
    println!(
        "FIGURE nothing lost: {} datasets, {} models, every blob whole; bytes lost 0; interrupted uploads \
         collected: {}",
        datasets_a.len(),
        models_a.len(),
        leftovers.len()
    );
}
