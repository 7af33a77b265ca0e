//! Crash and corruption tests: the server aborts at a named point (`RELREWARD_FAULT`, the
//! server's `fault` module, as abrupt as kill -9) during an upload, a model registration, a
//! job and a checkpoint write, then restarts on the same data directory; and stored files get
//! bits flipped on disk. In every case nothing stored before is lost or altered (listings and
//! the digest of every stored file are compared before and after), nothing half-written stays
//! after the restart, and corrupt data is reported (DATA_LOSS naming it), never served.
//!
//! Each test prints one `FIGURE` line (run with `--nocapture`) for docs/reliability.md.

//!
//! These tests look at the data directory's files (a black box: digests and counts, `blobs/`
//! and `staging/`), which only the server's own tests may do; hence here, not in tests/.

mod store_layout;

use std::collections::BTreeMap;

use relreward_client::Client;
use relreward_client::pb::{self, job_event::Event};
use relreward_tests::{
    Lines, TestServer, eventually, final_state, flip_byte, ok, refused, tiny_diffusion_spec, train_tiny_reward,
    upload_lines, watch_all,
};
use store_layout::StoreLayout;

const FAULT: &str = "RELREWARD_FAULT";

const LINES: Lines =
    Lines { episodes: 20, seed: 7, start: [(2.0, -1.0), (2.0, -1.0)], velocity: [(0.2, -0.1), (0.2, -0.1)] };

/// 60 steps, a checkpoint every 20 (at 20 and 40; none at the last step).
const STEPS: u64 = 60;
const EVERY: u64 = 20;

fn spec(dataset: &str, output: &str) -> pb::JobSpec {
    let optimization = pb::Optimization {
        steps: Some(STEPS),
        batch_size: Some(8),
        checkpoint_every: Some(EVERY),
        log_every: Some(10),
        ..Default::default()
    };
    tiny_diffusion_spec(dataset, output, 3, optimization)
}

async fn submit(client: &Client, dataset: &str, output: &str, id: &str) {
    client.submit_job(spec(dataset, output), Some(id)).await.expect("submit");
}

/// State and log messages, in order.
fn messages(events: &[pb::JobEvent]) -> Vec<String> {
    events
        .iter()
        .filter_map(|e| match &e.event {
            Some(Event::State(s)) => Some(s.message.clone()),
            Some(Event::Log(l)) => Some(l.message.clone()),
            _ => None,
        })
        .collect()
}

/// The step the job resumed at after the restart (from its "resumed from the checkpoint at
/// step N" log line).
fn resumed_from(events: &[pb::JobEvent]) -> Option<u64> {
    messages(events).iter().rev().find_map(|m| m.strip_prefix("resumed from the checkpoint at step ")?.parse().ok())
}

/// What must survive a crash: every dataset, model and finished job as listed, and every
/// stored dataset and model file's digest.
#[derive(Debug, Clone, PartialEq)]
struct Snapshot {
    datasets: BTreeMap<String, (String, u64, u64)>,
    models: BTreeMap<String, (String, u64)>,
    finished_jobs: BTreeMap<String, (i32, u64, u64)>,
    files: BTreeMap<String, (String, u64)>,
}

async fn snapshot(server: &TestServer, client: &Client) -> Snapshot {
    let datasets = client.list_datasets().await.expect("datasets");
    let models = client.list_models(pb::ModelKind::Unspecified).await.expect("models");
    let jobs = client.list_jobs(pb::JobState::Unspecified).await.expect("jobs");
    let terminal = [pb::JobState::Succeeded, pb::JobState::Failed, pb::JobState::Cancelled];
    let mut files = server.blob_files("datasets");
    files.extend(server.blob_files("models"));
    Snapshot {
        datasets: datasets.into_iter().map(|d| (d.name, (d.sha256, d.size_bytes, d.num_rows))).collect(),
        models: models.into_iter().map(|m| (m.name, (m.sha256, m.size_bytes))).collect(),
        finished_jobs: jobs
            .into_iter()
            .filter(|j| terminal.contains(&j.state()))
            .map(|j| (j.id.clone(), (j.state, j.step, j.loss.to_bits())))
            .collect(),
        files,
    }
}

/// Asserts everything in `before` is in `after`, unchanged; returns the bytes lost (stored
/// files of `before` missing or altered in `after`), which the assertion makes 0.
fn assert_kept(before: &Snapshot, after: &Snapshot) -> u64 {
    let lost: u64 = before.files.iter().filter(|(k, v)| after.files.get(*k) != Some(*v)).map(|(_, v)| v.1).sum();
    for (name, d) in &before.datasets {
        assert_eq!(after.datasets.get(name), Some(d), "dataset '{name}' lost or altered");
    }
    for (name, m) in &before.models {
        assert_eq!(after.models.get(name), Some(m), "model '{name}' lost or altered");
    }
    for (id, j) in &before.finished_jobs {
        assert_eq!(after.finished_jobs.get(id), Some(j), "finished job '{id}' lost or altered");
    }
    assert_eq!(lost, 0, "stored files lost or altered");
    lost
}

/// Starts a server armed with `fault`.
async fn armed(fault: &str) -> (TestServer, Client) {
    let server = TestServer::start_with_env(&[(FAULT, fault)]);
    let client = server.client().await;
    (server, client)
}

/// Waits for the injected abort, checks the log names the point, and restarts disarmed.
async fn crash_and_restart(server: &mut TestServer, fault: &str) -> Client {
    assert!(server.wait_exit(120), "the server did not abort at {fault}; log:\n{}", server.log());
    let point = fault.split(':').next().unwrap_or(fault);
    assert!(server.log().contains(&format!("fault injected at {point}")), "log:\n{}", server.log());
    server.set_env(FAULT, None);
    server.restart();
    server.client().await
}

async fn upload_crash(fault: &str) {
    // The second upload aborts (at its commit, or mid-stream); the first is the data that must
    // survive.
    let (mut server, client) = armed(fault).await;
    upload_lines(&client, "kept", &LINES).await;
    let before = snapshot(&server, &client).await;
    let lines = Lines { seed: 8, ..LINES };
    // upload_lines panics on the dropped connection: its message in the output is expected.
    let crashed = tokio::spawn(async move { upload_lines(&client, "lost", &lines).await });
    let client = crash_and_restart(&mut server, fault).await;
    assert!(crashed.await.is_err(), "the interrupted upload reported success");

    let after = snapshot(&server, &client).await;
    assert!(!after.datasets.contains_key("lost"), "an interrupted upload became visible");
    assert_eq!((server.staging_entries(), server.blob_count("datasets")), (0, 1), "leftovers after the restart");
    let lost = assert_kept(&before, &after);
    // The name was never taken: the same upload now succeeds.
    upload_lines(&client, "lost", &Lines { seed: 8, ..LINES }).await;
    println!("FIGURE fault={fault} outcome=upload invisible, no leftovers, re-upload ok bytes_lost={lost}");
}

#[tokio::test(flavor = "multi_thread")]
async fn crash_in_the_middle_of_an_upload_stream_leaves_nothing() {
    // The client sends one chunk per array here (observations, actions, timeouts): chunks 1-3
    // are the kept upload's, chunk 4 the lost upload's observations. The server dies with
    // one array of three in staging.
    upload_crash("upload.chunk:4").await;
}

#[tokio::test(flavor = "multi_thread")]
async fn crash_during_upload_before_publish_leaves_nothing() {
    upload_crash("upload.before_publish:2").await;
}

#[tokio::test(flavor = "multi_thread")]
async fn crash_during_upload_after_publish_leaves_nothing() {
    upload_crash("upload.after_publish:2").await;
}

/// Aborts at the second arrival at a model-registration point (the second job's output; the
/// first job finished and registered its model), restarts, and the job registers it again.
async fn registration_crash(fault: &str) {
    let (mut server, client) = armed(fault).await;
    upload_lines(&client, "lines", &LINES).await;
    submit(&client, "lines", "first", "job-first").await;
    assert_eq!(final_state(&watch_all(&client, "job-first", 0).await), Some(pb::JobState::Succeeded));
    let before = snapshot(&server, &client).await;
    submit(&client, "lines", "second", "job-second").await;
    let client = crash_and_restart(&mut server, fault).await;

    let events = watch_all(&client, "job-second", 0).await;
    assert_eq!(final_state(&events), Some(pb::JobState::Succeeded), "{:?}", messages(&events));
    let after = snapshot(&server, &client).await;
    let lost = assert_kept(&before, &after);
    assert!(after.models.contains_key("second"));
    assert_eq!(server.blob_count("models"), 2, "one blob per model: the interrupted one was collected");
    assert_eq!(server.staging_entries(), 0);
    println!("FIGURE fault={fault} outcome=job resumed and registered its model once bytes_lost={lost}");
}

#[tokio::test(flavor = "multi_thread")]
async fn crash_during_model_registration_before_publish() {
    registration_crash("model.before_publish:2").await;
}

#[tokio::test(flavor = "multi_thread")]
async fn crash_during_model_registration_after_publish() {
    registration_crash("model.after_publish:2").await;
}

/// Runs a job on a server armed with `fault` (a checkpoint point), waits for the abort, lets
/// `damage` touch the data directory, restarts, and returns the job's events.
async fn job_crash(fault: &str, damage: impl FnOnce(&TestServer)) -> (TestServer, Client, Snapshot, Vec<pb::JobEvent>) {
    let (mut server, client) = armed(fault).await;
    upload_lines(&client, "lines", &LINES).await;
    let before = snapshot(&server, &client).await;
    submit(&client, "lines", "out", "job").await;
    assert!(server.wait_exit(120), "the server did not abort at {fault}; log:\n{}", server.log());
    damage(&server);
    let client = crash_and_restart(&mut server, fault).await;
    let events = watch_all(&client, "job", 0).await;
    (server, client, before, events)
}

/// The checkpoint directories on disk, as (step from state.json, directory), by step.
fn checkpoints(server: &TestServer) -> Vec<(u64, std::path::PathBuf)> {
    let mut out: Vec<(u64, std::path::PathBuf)> = std::fs::read_dir(server.blob_path("checkpoints"))
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| {
            let state: serde_json::Value =
                serde_json::from_slice(&std::fs::read(e.path().join("state.json")).expect("state.json"))
                    .expect("state json");
            (state["step"].as_u64().expect("step"), e.path())
        })
        .collect();
    out.sort();
    out
}

async fn assert_job_finished(server: &TestServer, client: &Client, before: &Snapshot, events: &[pb::JobEvent]) -> u64 {
    assert_eq!(final_state(events), Some(pb::JobState::Succeeded), "{:?}", messages(events));
    let job = client.get_job("job").await.expect("job");
    assert_eq!(job.step, STEPS);
    let after = snapshot(server, client).await;
    assert!(after.models.contains_key("out"));
    assert_eq!(server.staging_entries(), 0, "staging leftovers");
    // Released after the terminal state is recorded (record first, files second), so the
    // watcher may see the state a moment before the files go.
    let released = eventually(10, || server.blob_count("checkpoints") == 0).await;
    assert!(released, "a finished job's checkpoints are released");
    assert_kept(before, &after)
}

#[tokio::test(flavor = "multi_thread")]
async fn crash_during_a_job_resumes_from_its_checkpoint() {
    let fault = "checkpoint.after_record:2";
    let mut on_disk = Vec::new();
    let (server, client, before, events) = job_crash(fault, |s| on_disk = checkpoints(s)).await;
    // Both checkpoints were recorded (the latest and its fallback) when it died.
    assert_eq!(on_disk.iter().map(|c| c.0).collect::<Vec<_>>(), [EVERY, 2 * EVERY]);
    assert_eq!(resumed_from(&events), Some(2 * EVERY), "{:?}", messages(&events));
    let lost = assert_job_finished(&server, &client, &before, &events).await;
    println!("FIGURE fault={fault} outcome=resumed at step {} and succeeded bytes_lost={lost}", 2 * EVERY);
}

#[tokio::test(flavor = "multi_thread")]
async fn crash_during_a_checkpoint_write_keeps_the_previous_checkpoint() {
    for fault in ["checkpoint.before_publish:2", "checkpoint.after_publish:2"] {
        let (server, client, before, events) = job_crash(fault, |s| {
            // The second checkpoint is staged or published but not recorded.
            let published = checkpoints(s).iter().map(|c| c.0).collect::<Vec<_>>();
            if fault.starts_with("checkpoint.before_publish") {
                assert_eq!((published, s.staging_entries()), (vec![EVERY], 1));
            } else {
                assert_eq!(published, [EVERY, 2 * EVERY]);
            }
        })
        .await;
        assert_eq!(resumed_from(&events), Some(EVERY), "{fault}: {:?}", messages(&events));
        let lost = assert_job_finished(&server, &client, &before, &events).await;
        println!("FIGURE fault={fault} outcome=resumed at the previous checkpoint (step {EVERY}) bytes_lost={lost}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_corrupt_checkpoint_falls_back_to_the_previous_one() {
    let fault = "checkpoint.after_record:2";
    let (server, client, before, events) = job_crash(fault, |s| {
        let latest = checkpoints(s).pop().expect("a checkpoint");
        assert_eq!(latest.0, 2 * EVERY);
        flip_byte(&latest.1.join("weights.safetensors"), 1);
    })
    .await;
    let text = messages(&events).join("\n");
    assert!(text.contains(&format!("checkpoint at step {} is corrupt", 2 * EVERY)), "{text}");
    assert_eq!(resumed_from(&events), Some(EVERY), "{text}");
    assert!(server.log().contains("is corrupt"), "no log line");
    let lost = assert_job_finished(&server, &client, &before, &events).await;
    println!(
        "FIGURE fault={fault}+flip latest checkpoint outcome=fell back to step {EVERY}, succeeded bytes_lost={lost}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn a_job_whose_every_checkpoint_is_corrupt_fails_clearly() {
    let fault = "checkpoint.after_record:2";
    let (_server, client, _, events) = job_crash(fault, |s| {
        for (_, dir) in checkpoints(s) {
            flip_byte(&dir.join("adam.safetensors"), 3);
        }
    })
    .await;
    assert_eq!(final_state(&events), Some(pb::JobState::Failed));
    let job = client.get_job("job").await.expect("job");
    assert!(job.error.contains("is corrupt") && job.error.contains("adam.safetensors"), "{}", job.error);
    println!("FIGURE fault={fault}+flip both checkpoints outcome=job FAILED naming the corrupt checkpoint");
}

#[tokio::test(flavor = "multi_thread")]
async fn corrupt_models_and_datasets_are_reported_never_served() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let models = train_tiny_reward(&server, tmp.path());
    let client = server.client().await;
    let x = tmp.path().join("x.npz");
    let mut npz = relreward_toolkit::npz_write::NpzWriter::create(&x).expect("npz");
    let values: Vec<f32> = (0..2 * 8 * 4).map(|i| (i as f32 * 0.3).sin()).collect();
    npz.add_f32("x", &[2, 8, 4], &values).expect("x");
    npz.finish().expect("write npz");
    let x = x.to_str().expect("utf8");

    // The reward model's weights: found by the sha256 its record lists.
    let reward = client.get_model(&models.reward).await.expect("rw");
    let (file, _) = server
        .blob_files("models")
        .into_iter()
        .find(|(_, (sha, _))| *sha == reward.sha256)
        .expect("the reward model's stored file");
    flip_byte(&server.blob_path(&file), 100);
    for _ in 0..2 {
        // Twice: the second answer comes from the registry's memory of the corrupt blob.
        refused(&server, &["score", "--model", "rw", "--input", x], &["DATA_LOSS", "model 'rw'", "corrupt"]);
    }
    assert!(server.log().contains("model 'rw' is corrupt"), "no log line");
    // The other models are untouched and still served.
    ok(&server, &["sample", "--base", "base", "--n", "1", "--seed", "1"]);

    // A dataset: a job reading it fails, naming it.
    let (file, _) =
        server.blob_files("datasets").into_iter().find(|(k, _)| k.ends_with("observations.npy")).expect("obs");
    flip_byte(&server.blob_path(&file), 4);
    client.submit_job(spec("traj", "from-corrupt"), Some("corrupt-data")).await.expect("submit");
    let events = watch_all(&client, "corrupt-data", 0).await;
    assert_eq!(final_state(&events), Some(pb::JobState::Failed));
    let job = client.get_job("corrupt-data").await.expect("job");
    assert!(job.error.contains("dataset 'traj' is corrupt"), "{}", job.error);
    assert!(client.get_model("from-corrupt").await.is_err(), "nothing trained on corrupt data");
    println!("FIGURE fault=flip reward model byte outcome=Score DATA_LOSS x2, other models served");
    println!("FIGURE fault=flip dataset byte outcome=job FAILED naming dataset 'traj'");
}

/// The embedded store belongs to one process: a second server started on a data directory that
/// a live server holds stops at start with a message naming `storage.data_dir` (it would
/// otherwise break the first one's job leases and run its jobs beside it), and the first keeps
/// serving with its data intact. Once the first is gone (here: killed, so only the OS releases
/// the lock), a server opens the directory again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_server_on_a_held_data_directory_is_refused() {
    let mut server = TestServer::start();
    let client = server.client().await;
    upload_lines(&client, "held", &LINES).await;
    let mut second = std::process::Command::new(relreward_tests::bin("relreward-server"))
        .args(["--listen", "127.0.0.1:0", "--data-dir"])
        .arg(&server.data_dir)
        .env("RELREWARD__METRICS__LISTEN", "")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run a second server");
    // A second server that started would serve until stopped: give it 30 s to exit.
    let mut exited = None;
    for _ in 0..600 {
        exited = second.try_wait().expect("wait");
        if exited.is_some() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    if exited.is_none() {
        let _ = second.kill();
    }
    let second = second.wait_with_output().expect("second server's output");
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert!(exited.is_some() && !second.status.success(), "the second server started; stderr:\n{stderr}");
    assert!(
        stderr.contains("storage.data_dir") && stderr.contains("in use by another relreward-server"),
        "stderr does not name the setting:\n{stderr}"
    );
    let names = |c: &Client| {
        let c = c.clone();
        async move {
            let listed = c.datasets().list_datasets(pb::ListDatasetsRequest::default()).await.expect("list");
            listed.into_inner().datasets.into_iter().map(|d| d.name).collect::<Vec<_>>()
        }
    };
    assert_eq!(names(&client).await, ["held"], "the first server still serves its data");
    server.restart();
    assert_eq!(names(&server.client().await).await, ["held"], "a server opens the directory once it is free");
}
