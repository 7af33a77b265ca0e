//! Relative reward extraction end to end, checked against the closed form.
//!
//! Base N(0, I) and expert N(m, I) are exact (analytic) TorchScript eps-models on a cosine
//! schedule. For them the target is constant in x: with the score target sqrt(abar_t) m, with
//! the mean target (beta_t / sqrt(alpha_t)) sqrt(abar_t) m. The service trains rho from the
//! union of base and expert samples (Algorithm 1); the test then loads the registered reward
//! model with the engine and compares grad_x rho with the exact target at every t.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use relreward_client::client::{DatasetUpload, UploadProgress};
use relreward_client::pb::{self, job_event::Event};
use relreward_client::{Client, MemorySource};
use relreward_server::engine::manifest::ScheduleSpec;
use relreward_server::engine::nets::reward::{RewardArchitecture, RewardNet};
use relreward_server::engine::schedule::{Schedule, Table};
use relreward_tests::{TestServer, python, repo_root, wait_for_checkpoint};
use tch::{Device, Kind, Tensor};
use tokio_stream::StreamExt;

const T: usize = 20;
const M: [f32; 4] = [1.0, -0.5, 0.75, -1.25];

/// The exact model of N(mean, I); with `nan_beyond`, NaN at every item with an entry beyond it
/// (the script's --nan-beyond).
fn export(dir: &Path, name: &str, mean: &[f32], nan_beyond: Option<f32>) -> PathBuf {
    let out = dir.join(name);
    let mean = mean.iter().map(f32::to_string).collect::<Vec<_>>().join(",");
    let mut command = std::process::Command::new(python());
    command.arg(repo_root().join("tests/python/analytic_gaussian.py")).args([
        "--out",
        out.to_str().expect("utf8"),
        "--mean",
        &mean,
        "--schedule",
        "cosine",
        "--T",
        &T.to_string(),
    ]);
    if let Some(r) = nan_beyond {
        command.args(["--nan-beyond", &r.to_string()]);
    }
    let status = command.status().expect("python");
    assert!(status.success());
    out.join("model.pt")
}

fn manifest() -> pb::DiffusionManifest {
    pb::DiffusionManifest {
        parametrization: pb::Parametrization::Epsilon as i32,
        schedule: Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.008 })) }),
        n_timesteps: T as u32,
        clip_denoised: false,
        space: Some(pb::diffusion_manifest::Space::Sample(pb::diffusion_manifest::Sample {
            shape: vec![M.len() as u64],
        })),
        normalizer: Some(pb::Normalizer { kind: Some(pb::normalizer::Kind::Identity(pb::normalizer::Identity {})) }),
        architecture: None,
        conditioning: None,
    }
}

/// Deterministic standard normals (Box-Muller on a 64-bit LCG).
fn normals(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed;
    let mut u = || {
        s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    (0..n).map(|_| ((-2.0 * u().ln()).sqrt() * (std::f64::consts::TAU * u()).cos()) as f32).collect()
}

async fn upload_samples(client: &Client, name: &str, mean: &[f32], seed: u64) {
    let n = 4096;
    let d = mean.len();
    let values: Vec<f32> = normals(n * d, seed).iter().enumerate().map(|(i, z)| z + mean[i % d]).collect();
    let mut source = MemorySource::new();
    source.push_f32("samples", &[n as u64, d as u64], &values);
    let upload = DatasetUpload {
        name: name.into(),
        kind: pb::DatasetKind::Samples,
        description: String::new(),
        chunk_bytes: 1 << 20,
    };
    client.upload_dataset(upload, source, Arc::new(UploadProgress::default())).await.expect("dataset");
}

async fn upload_model(client: &Client, path: &Path, name: &str) {
    let header = pb::UploadModelHeader {
        name: name.into(),
        manifest: Some(manifest()),
        description: String::new(),
        format: 0,
        reward: None,
        autoencoder: None,
    };
    client.upload_model(header, path, Arc::new(UploadProgress::default())).await.expect("upload model");
}

/// Base and expert models plus their sample datasets on a fresh server.
async fn setup(server: &TestServer) -> Client {
    let client = server.client().await;
    let tmp = tempfile::tempdir().expect("tmp");
    for (name, mean) in [("base", vec![0.0f32; M.len()]), ("expert", M.to_vec())] {
        upload_model(&client, &export(tmp.path(), name, &mean, None), name).await;
    }
    upload_samples(&client, "base-samples", &[0.0; 4], 1).await;
    upload_samples(&client, "expert-samples", &M, 2).await;
    client
}

fn reward_spec(
    output: &str,
    target: pb::RewardTarget,
    eval_point: pb::EvalPoint,
    steps: u64,
    checkpoint_every: u64,
) -> pb::JobSpec {
    pb::JobSpec {
        output_model: output.into(),
        seed: Some(11),
        optimization: Some(pb::Optimization {
            steps: Some(steps),
            batch_size: Some(256),
            learning_rate: Some(3e-3),
            checkpoint_every: Some(checkpoint_every),
            eval_every: Some(200),
            log_every: Some(50),
            ema_decay: Some(0.9),
            ema_start: Some(steps / 2),
            ..Default::default()
        }),
        kind: Some(pb::job_spec::Kind::Reward(pb::TrainReward {
            base_model: "base".into(),
            expert_model: "expert".into(),
            architecture: Some(pb::RewardArchitecture {
                kind: Some(pb::reward_architecture::Kind::Mlp(pb::Mlp { hidden: vec![64, 64] })),
            }),
            target: target as i32,
            eval_point: eval_point as i32,
            algorithm: Some(pb::train_reward::Algorithm::WithDataset(pb::train_reward::WithDataset {
                datasets: vec!["base-samples".into(), "expert-samples".into()],
            })),
            rho_l2: None,
            amortised_targets: None,
            action_weight: None,
            condition_weight: None,
            inpaint_condition: None,
            base_recipe: None,
            expert_recipe: None,
        })),
    }
}

/// The discriminator baseline between the two sample datasets, with reward_spec's optimization.
fn discriminator_spec(output: &str, steps: u64, inpaint_condition: Option<bool>) -> pb::JobSpec {
    let mut spec = reward_spec(output, pb::RewardTarget::Mean, pb::EvalPoint::XT, steps, 1000);
    spec.kind = Some(pb::job_spec::Kind::Discriminator(pb::TrainDiscriminator {
        base_dataset: "base-samples".into(),
        expert_dataset: "expert-samples".into(),
        architecture: Some(pb::RewardArchitecture {
            kind: Some(pb::reward_architecture::Kind::Mlp(pb::Mlp { hidden: vec![64, 64] })),
        }),
        diffusion_model: "base".into(),
        inpaint_condition,
    }));
    spec
}

async fn wait_done(client: &Client, id: &str) -> Vec<pb::JobEvent> {
    let mut stream =
        client.jobs().watch_job(pb::WatchJobRequest { id: id.into(), from_seq: 0 }).await.expect("watch").into_inner();
    let mut events = Vec::new();
    while let Some(e) = tokio::time::timeout(Duration::from_secs(600), stream.next()).await.expect("in time") {
        events.push(e.expect("event"));
    }
    events
}

fn succeeded(events: &[pb::JobEvent]) -> bool {
    events.iter().any(|e| matches!(&e.event, Some(Event::State(s)) if s.state() == pb::JobState::Succeeded))
}

/// The blob directory holding a registered model's files (found by the weights' digest).
fn model_dir(server: &TestServer, model: &pb::Model) -> PathBuf {
    let dirs = std::fs::read_dir(server.data_dir.join("blobs/models")).expect("models");
    for d in dirs {
        let dir = d.expect("entry").path();
        let weights = dir.join("weights.safetensors");
        if weights.exists() && relreward_tests_sha(&weights) == model.sha256 {
            return dir;
        }
    }
    panic!("model files not found");
}

/// Loads the registered reward model with the engine.
fn load_reward(server: &TestServer, model: &pb::Model) -> RewardNet {
    let arch = RewardArchitecture::Mlp { hidden: vec![64, 64] };
    let weights = model_dir(server, model).join("weights.safetensors");
    RewardNet::load(&arch, &[M.len() as i64], &weights, Device::Cpu).expect("load reward")
}

fn relreward_tests_sha(path: &Path) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(std::fs::read(path).expect("read")))
}

/// The exact target at every t: constant in x, c_t m.
fn exact_targets(target: pb::RewardTarget) -> Vec<Tensor> {
    let schedule = Schedule::new(&ScheduleSpec::Cosine { s: 0.008 }, T).expect("schedule");
    let m = Tensor::from_slice(&M).to_kind(Kind::Double);
    (0..T)
        .map(|t| {
            let abar = schedule.values(Table::AlphasCumprod)[t];
            let scale = match target {
                pb::RewardTarget::Score => abar.sqrt(),
                _ => schedule.values(Table::Betas)[t] / schedule.values(Table::Alphas)[t].sqrt() * abar.sqrt(),
            };
            &m * scale
        })
        .collect()
}

/// x_t drawn from the union of the two marginals at t.
fn marginal_points(t: usize, n: usize) -> Tensor {
    let schedule = Schedule::new(&ScheduleSpec::Cosine { s: 0.008 }, T).expect("schedule");
    let abar = schedule.values(Table::AlphasCumprod)[t].sqrt();
    let z = Tensor::from_slice(&normals(n * M.len(), 100 + t as u64)).reshape([n as i64, M.len() as i64]);
    let shift = Tensor::from_slice(&M).unsqueeze(0) * abar;
    let half = Tensor::cat(
        &[
            Tensor::zeros([(n / 2) as i64, M.len() as i64], (Kind::Float, Device::Cpu)),
            shift.expand([(n / 2) as i64, M.len() as i64], false),
        ],
        0,
    );
    z + half
}

/// The analytic check: cosine > 0.98 for every t with a target norm at least 10% of the largest,
/// relative L2 error over all t below 10%, expert samples scoring above base samples.
fn check_recovery(reward: &RewardNet, target: pb::RewardTarget) {
    check_gradients(reward, &exact_targets(target), marginal_points);
    let n = 512;
    let t0 = Tensor::zeros([n as i64], (Kind::Int64, Device::Cpu));
    let base_x = Tensor::from_slice(&normals(n * M.len(), 7)).reshape([n as i64, M.len() as i64]);
    let expert_x = &base_x + Tensor::from_slice(&M).unsqueeze(0);
    let rb = reward.rho(&base_x, &t0).expect("rho").mean(Kind::Double).double_value(&[]);
    let re = reward.rho(&expert_x, &t0).expect("rho").mean(Kind::Double).double_value(&[]);
    assert!(re > rb, "expert samples must score higher: {re} vs {rb}");
}

/// grad_x rho at `points(t, n)` against the exact (constant) targets.
fn check_gradients(reward: &RewardNet, exact: &[Tensor], points: impl Fn(usize, usize) -> Tensor) {
    let norms: Vec<f64> = exact.iter().map(|e| e.norm().double_value(&[])).collect();
    let largest = norms.iter().copied().fold(0.0, f64::max);
    let n = 512;
    let (mut err2, mut ref2) = (0.0, 0.0);
    for (t, e) in exact.iter().enumerate() {
        let x = points(t, n);
        let tt = Tensor::full([n as i64], t as i64, (Kind::Int64, Device::Cpu));
        let (_, grad) = reward.grad(&x, &tt).expect("grad");
        let grad = grad.to_kind(Kind::Double);
        let e = e.unsqueeze(0);
        let cos = Tensor::cosine_similarity(&grad, &e, 1, 1e-12).mean(Kind::Double).double_value(&[]);
        if norms[t] >= 0.1 * largest {
            assert!(cos > 0.98, "t = {t}: mean cosine {cos} (target norm {})", norms[t]);
        }
        err2 += (&grad - &e).square().sum(Kind::Double).double_value(&[]);
        ref2 += e.square().sum(Kind::Double).double_value(&[]) * n as f64;
    }
    let rel = (err2 / ref2).sqrt();
    assert!(rel < 0.10, "relative L2 error {rel}");
}

#[tokio::test(flavor = "multi_thread")]
async fn gradient_alignment_recovers_the_analytic_reward_for_both_targets_and_eval_points() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let cases = [
        ("r-mean-xt", pb::RewardTarget::Mean, pb::EvalPoint::XT),
        ("r-score-xt", pb::RewardTarget::Score, pb::EvalPoint::XT),
        ("r-mean-mu", pb::RewardTarget::Mean, pb::EvalPoint::MuBase),
        ("r-score-mu", pb::RewardTarget::Score, pb::EvalPoint::MuBase),
    ];
    for (name, target, eval_point) in cases {
        let spec = reward_spec(name, target, eval_point, 1500, 1000);
        let job = client
            .jobs()
            .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: name.into() })
            .await
            .expect("submit")
            .into_inner();
        let events = wait_done(&client, &job.id).await;
        assert!(succeeded(&events), "{name}: {events:?}");
        let model =
            client.models().get_model(pb::GetModelRequest { name: name.into() }).await.expect("model").into_inner();
        assert_eq!(model.kind(), pb::ModelKind::Reward);
        let info = model.reward.as_ref().expect("reward info");
        assert_eq!((info.base_model.as_str(), info.expert_model.as_str()), ("base", "expert"));
        assert_eq!((info.architecture.as_str(), info.input_shape.as_slice()), ("mlp(hidden=[64, 64])", &[4u64][..]));
        check_recovery(&load_reward(&server, &model), target);
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn kill_9_during_a_reward_job_resumes_and_still_recovers_the_reward() {
    let mut server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let spec = reward_spec("r-crash", pb::RewardTarget::Mean, pb::EvalPoint::XT, 1500, 100);
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: "crash".into() }).await.expect("submit");
    wait_for_checkpoint(&client, "crash", 300).await;
    server.kill();
    server.restart();
    let client = server.client().await;
    let events = wait_done(&client, "crash").await;
    assert!(succeeded(&events));
    let resumed = events.iter().find_map(|e| match &e.event {
        Some(Event::State(s)) if s.message.starts_with("resumed at step") => Some(s.message.clone()),
        _ => None,
    });
    let resumed = resumed.expect("resumed");
    let at: u64 =
        resumed["resumed at step ".len()..].split_whitespace().next().and_then(|n| n.parse().ok()).expect("step");
    assert!(at >= 300, "resumed at {at}");
    // Issue 34, item 3: the state event names the step training resumes from (its checkpoint's,
    // as the runner's own log says), not the last progress step before the kill.
    let restored = events.iter().find_map(|e| match &e.event {
        Some(Event::Log(l)) => l.message.strip_prefix("resumed from the checkpoint at step ")?.parse::<u64>().ok(),
        _ => None,
    });
    assert_eq!(Some(at), restored, "{resumed}");
    let model =
        client.models().get_model(pb::GetModelRequest { name: "r-crash".into() }).await.expect("model").into_inner();
    check_recovery(&load_reward(&server, &model), pb::RewardTarget::Mean);
}

/// A training batch whose targets are not finite is skipped whole (the weights untouched), and
/// the job goes on; ten in a row fail it with a message that says what to change. The base
/// model here is the exact one except that it outputs NaN for items with an entry beyond a
/// radius (finite at the upload's probe, x = 0): beyond 4.5, about one batch in twenty has such
/// an item; beyond 0, every batch.
#[tokio::test(flavor = "multi_thread")]
async fn batches_with_non_finite_targets_are_skipped_and_a_run_of_them_fails_the_job() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let tmp = tempfile::tempdir().expect("tmp");
    let skipped = |events: &[pb::JobEvent]| {
        events
            .iter()
            .filter(|e| matches!(&e.event, Some(Event::Log(l)) if l.message.ends_with("not finite, update skipped")))
            .count()
    };
    let with_base = |name: &str, base: &str, steps: u64| {
        let mut spec = reward_spec(name, pb::RewardTarget::Mean, pb::EvalPoint::XT, steps, 1000);
        if let Some(pb::job_spec::Kind::Reward(r)) = spec.kind.as_mut() {
            r.base_model = base.into();
        }
        spec
    };

    upload_model(&client, &export(tmp.path(), "base-rare", &[0.0; 4], Some(4.5)), "base-rare").await;
    let spec = with_base("r-rare", "base-rare", 1500);
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: "rare".into() }).await.expect("submit");
    let events = wait_done(&client, "rare").await;
    assert!(succeeded(&events), "{events:?}");
    let n = skipped(&events);
    assert!((10..=300).contains(&n), "{n} skipped steps of 1500 (about 5% expected)");
    let model =
        client.models().get_model(pb::GetModelRequest { name: "r-rare".into() }).await.expect("model").into_inner();
    check_recovery(&load_reward(&server, &model), pb::RewardTarget::Mean);

    upload_model(&client, &export(tmp.path(), "base-bad", &[0.0; 4], Some(0.0)), "base-bad").await;
    let spec = with_base("r-bad", "base-bad", 200);
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: "bad".into() }).await.expect("submit");
    let events = wait_done(&client, "bad").await;
    let failed = events.iter().find_map(|e| match &e.event {
        Some(Event::State(s)) if s.state() == pb::JobState::Failed => Some(s.message.clone()),
        _ => None,
    });
    let failed = failed.unwrap_or_else(|| panic!("not failed: {events:?}"));
    assert!(
        failed.contains("training diverged at step 10") && failed.contains("spec.optimization.learning_rate"),
        "{failed}"
    );
    assert_eq!(skipped(&events), 9, "{events:?}");
    assert!(!events.iter().any(|e| matches!(e.event, Some(Event::Progress(_)))), "a skipped step reported progress");
    let missing = client.models().get_model(pb::GetModelRequest { name: "r-bad".into() }).await;
    assert_eq!(missing.expect_err("no model").code(), tonic::Code::NotFound);
}

/// `engine.step_checks = "device"` (the default on CUDA: Adam's skip and clip decided on the
/// device, the steps' losses read together where progress is reported) trains the same weights
/// and reports the same progress, skips and divergence as the host's checks, here on the CPU: a
/// job with rare non-finite batches, checkpoints and an evaluation, and a job that diverges
/// (its tenth non-finite step found after more were queued).
#[tokio::test(flavor = "multi_thread")]
async fn steps_checked_on_the_device_train_and_report_as_on_the_host() {
    let tmp = tempfile::tempdir().expect("tmp");
    let rare = export(tmp.path(), "base-rare", &[0.0; 4], Some(4.5));
    let bad = export(tmp.path(), "base-bad", &[0.0; 4], Some(0.0));
    let mut outcomes = Vec::new();
    for checks in ["host", "device"] {
        let server = TestServer::start_with_env(&[
            ("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true"),
            ("RELREWARD__ENGINE__STEP_CHECKS", checks),
        ]);
        let client = setup(&server).await;
        upload_model(&client, &rare, "base-rare").await;
        upload_model(&client, &bad, "base-bad").await;
        let mut figures = Vec::new();
        for (job, base, steps) in [("rare", "base-rare", 320), ("bad", "base-bad", 60)] {
            let mut spec = reward_spec(job, pb::RewardTarget::Mean, pb::EvalPoint::XT, steps, 150);
            if let Some(pb::job_spec::Kind::Reward(r)) = spec.kind.as_mut() {
                r.base_model = base.into();
            }
            // Progress every 50 steps (reward_spec's): on the device, up to 49 steps wait unread.
            if let Some(o) = spec.optimization.as_mut() {
                o.grad_clip = Some(5.0);
            }
            client
                .jobs()
                .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: job.into() })
                .await
                .expect("submit");
            let events = wait_done(&client, job).await;
            // Everything but the rates and times, in order.
            let seen: Vec<String> = events
                .iter()
                .filter_map(|e| match &e.event {
                    Some(Event::Progress(p)) => {
                        Some(format!("progress {} {:e} {:e} {:?}", p.step, p.loss, p.grad_norm, p.eval_loss))
                    }
                    Some(Event::Log(l)) if l.message.contains("not finite") => Some(l.message.clone()),
                    Some(Event::Checkpoint(c)) => Some(format!("checkpoint {}", c.step)),
                    // A running state's message names the worker, different per server.
                    Some(Event::State(s)) if s.state() == pb::JobState::Running => Some("Running".into()),
                    Some(Event::State(s)) => Some(format!("{:?} {}", s.state(), s.message)),
                    _ => None,
                })
                .collect();
            let model = client.models().get_model(pb::GetModelRequest { name: job.into() }).await;
            figures.push((seen, model.ok().map(|m| m.into_inner().sha256)));
        }
        // Read after the jobs: the start logs it after it begins to listen.
        let on_device = format!("step_checks_on_device={}", checks == "device");
        assert!(server.log().contains(&on_device), "{checks}: no '{on_device}' in the log:\n{}", server.log());
        outcomes.push(figures);
    }
    let (host, device) = (&outcomes[0], &outcomes[1]);
    let skips = host[0].0.iter().filter(|line| line.ends_with("update skipped")).count();
    assert!((3..=100).contains(&skips), "{skips} skipped steps of 320 (about 5% expected): {:?}", host[0].0);
    assert!(host[0].0.iter().any(|line| line == "checkpoint 300"), "{:?}", host[0].0);
    assert!(host[0].1.is_some() && host[1].1.is_none(), "the rare job registers its reward, the bad one nothing");
    assert!(host[1].0.iter().any(|line| line.contains("training diverged at step 10")), "{:?}", host[1].0);
    for (job, (h, d)) in ["rare", "bad"].iter().zip(host.iter().zip(device)) {
        assert_eq!(h.1, d.1, "{job}: the weights differ");
        assert_eq!(h.0.len(), d.0.len(), "{job}: {} events on the host, {} on the device", h.0.len(), d.0.len());
        for (a, b) in h.0.iter().zip(&d.0) {
            assert_eq!(a, b, "{job}");
        }
    }
}

/// Amortised targets (issue 21): a pool of 2048 triples, each used about 16 times, still
/// recovers the analytic reward, and a kill -9 in the middle resumes with the pool recomputed
/// from the seed (the job's refresh schedule continues where it was).
#[tokio::test(flavor = "multi_thread")]
async fn amortised_targets_recover_the_analytic_reward_across_a_kill_9() {
    let mut server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let mut spec = reward_spec("r-amortised", pb::RewardTarget::Mean, pb::EvalPoint::XT, 1500, 100);
    if let Some(pb::job_spec::Kind::Reward(r)) = spec.kind.as_mut() {
        r.amortised_targets =
            Some(pb::AmortisedTargets { pool_size: Some(2048), reuse: Some(4), refresh_fraction: None });
    }
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: "am".into() }).await.expect("submit");
    // The stored spec carries the filled-in defaults.
    let job = client.jobs().get_job(pb::GetJobRequest { id: "am".into() }).await.expect("job").into_inner();
    let Some(pb::job_spec::Kind::Reward(r)) = job.spec.and_then(|s| s.kind) else { panic!("reward spec") };
    assert_eq!(
        r.amortised_targets,
        Some(pb::AmortisedTargets { pool_size: Some(2048), reuse: Some(4), refresh_fraction: Some(0.25) })
    );
    let mut stream = client
        .jobs()
        .watch_job(pb::WatchJobRequest { id: "am".into(), from_seq: 0 })
        .await
        .expect("watch")
        .into_inner();
    while let Some(e) = stream.next().await {
        // Past several refreshes (an epoch is 2048 * 4 / 256 = 32 steps).
        if let Some(Event::Checkpoint(c)) = e.expect("event").event
            && c.step >= 300
        {
            break;
        }
    }
    drop(stream);
    server.kill();
    server.restart();
    let client = server.client().await;
    let events = wait_done(&client, "am").await;
    assert!(succeeded(&events), "{events:?}");
    let logged = |needle: &str| {
        events.iter().any(|e| match &e.event {
            Some(Event::Log(l)) => l.message.contains(needle),
            Some(Event::State(s)) => s.message.contains(needle),
            _ => false,
        })
    };
    assert!(logged("amortised targets: pool 2048, reuse 4, refresh fraction 0.25 (512 items every 32 steps)"));
    assert!(logged("resumed at step"));
    let model = client
        .models()
        .get_model(pb::GetModelRequest { name: "r-amortised".into() })
        .await
        .expect("model")
        .into_inner();
    check_recovery(&load_reward(&server, &model), pb::RewardTarget::Mean);
}

/// Bad settings are refused at submission, naming the field.
#[tokio::test(flavor = "multi_thread")]
async fn amortised_target_settings_are_checked_at_submission() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let cases = [
        (pb::AmortisedTargets { pool_size: Some(0), ..Default::default() }, "amortised_targets.pool_size"),
        (pb::AmortisedTargets { reuse: Some(0), ..Default::default() }, "amortised_targets.reuse"),
        (
            pb::AmortisedTargets { refresh_fraction: Some(1.5), ..Default::default() },
            "amortised_targets.refresh_fraction",
        ),
        (pb::AmortisedTargets { refresh_fraction: Some(f64::NAN), ..Default::default() }, "refresh_fraction"),
    ];
    for (i, (settings, field)) in cases.into_iter().enumerate() {
        let mut spec = reward_spec(&format!("bad-{i}"), pb::RewardTarget::Mean, pb::EvalPoint::XT, 10, 100);
        if let Some(pb::job_spec::Kind::Reward(r)) = spec.kind.as_mut() {
            r.amortised_targets = Some(settings);
        }
        let err = client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() }).await;
        let status = err.expect_err("refused");
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{}", status.message());
        assert!(status.message().contains(field), "{} should name {field}", status.message());
    }
    let mut spec = reward_spec("bad-alg2", pb::RewardTarget::Mean, pb::EvalPoint::XT, 10, 100);
    if let Some(pb::job_spec::Kind::Reward(r)) = spec.kind.as_mut() {
        r.algorithm = Some(pb::train_reward::Algorithm::ModelsOnly(pb::train_reward::ModelsOnly { num_chains: None }));
        r.amortised_targets = Some(pb::AmortisedTargets::default());
    }
    let status = client
        .jobs()
        .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() })
        .await
        .expect_err("refused");
    assert!(
        status.message().contains("spec.reward.amortised_targets: applies to with_dataset"),
        "{}",
        status.message()
    );
}

/// Options that need a trajectory's first action and observation are refused at submission,
/// naming the field, for models over fixed-shape samples; nothing is stored for them.
#[tokio::test(flavor = "multi_thread")]
async fn trajectory_only_options_are_refused_for_sample_models() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let reward = |edit: fn(&mut pb::TrainReward)| {
        let mut spec = reward_spec("opt", pb::RewardTarget::Mean, pb::EvalPoint::XT, 10, 100);
        if let Some(pb::job_spec::Kind::Reward(r)) = spec.kind.as_mut() {
            edit(r);
        }
        spec
    };
    let discriminator = discriminator_spec("opt", 10, Some(true));
    let cases = [
        (reward(|r| r.inpaint_condition = Some(true)), "spec.reward.inpaint_condition"),
        (reward(|r| r.action_weight = Some(10.0)), "spec.reward.action_weight"),
        (reward(|r| r.condition_weight = Some(0.0)), "condition_weight"),
        (discriminator, "spec.discriminator.inpaint_condition"),
    ];
    for (spec, field) in cases {
        let status = client
            .jobs()
            .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() })
            .await
            .expect_err("refused");
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{}", status.message());
        assert!(status.message().contains(field), "{} should name {field}", status.message());
        assert!(status.message().contains("only trajectory models"), "{}", status.message());
    }
    let jobs = client.jobs().list_jobs(pb::ListJobsRequest::default()).await.expect("list").into_inner();
    assert!(jobs.jobs.is_empty(), "refused specs stored jobs: {:?}", jobs.jobs);
}

#[tokio::test(flavor = "multi_thread")]
async fn algorithm_2_from_the_models_alone_recovers_the_same_reward() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let mut spec = reward_spec("r-alg2", pb::RewardTarget::Mean, pb::EvalPoint::XT, 1500, 1000);
    if let Some(pb::job_spec::Kind::Reward(r)) = spec.kind.as_mut() {
        r.algorithm =
            Some(pb::train_reward::Algorithm::ModelsOnly(pb::train_reward::ModelsOnly { num_chains: Some(2048) }));
    }
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: "alg2".into() }).await.expect("submit");
    let events = wait_done(&client, "alg2").await;
    assert!(succeeded(&events), "{events:?}");
    let model =
        client.models().get_model(pb::GetModelRequest { name: "r-alg2".into() }).await.expect("model").into_inner();
    // Algorithm 2's target x_{t-1}^expert - x_{t-1}^base is the mean target at the chain's x_t,
    // here standardised per step: rho sees (x - input_mean[t]) / input_std[t] and was fitted to
    // the target divided by target_std[t]. Check the gradient in those coordinates.
    let reward = load_reward(&server, &model);
    let dir = model_dir(&server, &model);
    let tables: std::collections::HashMap<String, Tensor> =
        Tensor::read_safetensors(dir.join("step_norm.safetensors")).expect("step norm").into_iter().collect();
    let target_std = tables["target_std"].to_kind(Kind::Double);
    assert_eq!(target_std.size(), vec![T as i64, M.len() as i64]);
    let exact: Vec<Tensor> =
        exact_targets(pb::RewardTarget::Mean).iter().enumerate().map(|(t, e)| e / target_std.get(t as i64)).collect();
    check_gradients(&reward, &exact, |t, n| {
        // Chain states standardise to roughly N(0, I); the target is constant, so any spread works.
        Tensor::from_slice(&normals(n * M.len(), 300 + t as u64)).reshape([n as i64, M.len() as i64])
    });
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).expect("manifest")).expect("json");
    assert_eq!(manifest["step_normalization"], true);
}

#[tokio::test(flavor = "multi_thread")]
async fn the_discriminator_baseline_separates_base_from_expert() {
    let server = TestServer::start_with_env(&[("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true")]);
    let client = setup(&server).await;
    let spec = discriminator_spec("disc", 800, None);
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: "disc".into() }).await.expect("submit");
    let events = wait_done(&client, "disc").await;
    assert!(succeeded(&events), "{events:?}");
    let model =
        client.models().get_model(pb::GetModelRequest { name: "disc".into() }).await.expect("model").into_inner();
    assert_eq!(model.kind(), pb::ModelKind::Discriminator);
    let net = load_reward(&server, &model);
    // Held-out draws at t = 0: the Bayes-optimal accuracy for N(0, I) vs N(m, I) is
    // Phi(|m| / 2) = 0.82 here.
    let n = 2048;
    let t0 = Tensor::zeros([n], (Kind::Int64, Device::Cpu));
    let base_x = Tensor::from_slice(&normals(n as usize * M.len(), 71)).reshape([n, M.len() as i64]);
    let expert_x = Tensor::from_slice(&normals(n as usize * M.len(), 72)).reshape([n, M.len() as i64])
        + Tensor::from_slice(&M).unsqueeze(0);
    let correct_base = net.rho(&base_x, &t0).expect("rho").lt(0.0).sum(Kind::Int64).int64_value(&[]);
    let correct_expert = net.rho(&expert_x, &t0).expect("rho").gt(0.0).sum(Kind::Int64).int64_value(&[]);
    let accuracy = (correct_base + correct_expert) as f64 / (2 * n) as f64;
    assert!(accuracy > 0.75, "accuracy {accuracy}");
}

/// The trained reward served over gRPC: Gradient agrees with finite differences of Score,
/// bad input gets its status, and guided sampling from the base model moves the samples
/// toward the expert mean as omega grows (with omega = 1 the guided base approximates the
/// expert, the paper's premise).
#[tokio::test(flavor = "multi_thread")]
async fn the_served_reward_differentiates_rejects_bad_input_and_guides_sampling_toward_the_expert() {
    let server = TestServer::start_with_env(&[
        ("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true"),
        ("RELREWARD__SERVING__MAX_REQUEST_ITEMS", "64"),
    ]);
    let client = setup(&server).await;
    let spec = reward_spec("r-serve", pb::RewardTarget::Mean, pb::EvalPoint::XT, 1500, 1000);
    client.jobs().submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: "serve".into() }).await.expect("submit");
    assert!(succeeded(&wait_done(&client, "serve").await));
    let mut rewards = client.rewards();
    let d = M.len();
    let tensor = |b: usize, v: &[f32]| relreward_client::tensor::encode_f32(&[b as u64, d as u64], v);
    let score =
        |x: pb::Tensor, t: Vec<u32>| pb::ScoreRequest { model: "r-serve".into(), x: Some(x), t, ..Default::default() };

    // Gradient vs central differences of Score (identity normalizer: raw = normalized).
    let x0 = normals(3 * d, 41);
    let t = vec![2u32, 9, 15];
    let grad = rewards
        .gradient(pb::GradientRequest {
            request_id: 7,
            model: "r-serve".into(),
            x: Some(tensor(3, &x0)),
            t: t.clone(),
            ..Default::default()
        })
        .await
        .expect("gradient")
        .into_inner();
    assert_eq!(grad.request_id, 7);
    let g = relreward_client::tensor::decode_finite_f32(grad.gradient.as_ref().expect("gradient")).expect("f32");
    let eps = 1e-2f32;
    for i in 0..x0.len() {
        let (mut up, mut down) = (x0.clone(), x0.clone());
        up[i] += eps;
        down[i] -= eps;
        let r = |x: Vec<f32>| {
            let mut rewards = rewards.clone();
            let req = score(tensor(3, &x), t.clone());
            async move {
                let resp = rewards.score(req).await.expect("score").into_inner();
                relreward_client::tensor::decode_finite_f32(resp.rewards.as_ref().expect("rewards")).expect("f32")
            }
        };
        let fd = (r(up).await[i / d] - r(down).await[i / d]) / (2.0 * eps);
        assert!((fd - g[i]).abs() < 2e-3 + 2e-2 * g[i].abs(), "coordinate {i}: finite difference {fd} vs {}", g[i]);
    }

    // Bad input: each gets its status, with the field named, and the server stays healthy.
    let int64 = pb::Tensor { shape: vec![1, d as u64], dtype: pb::Dtype::Int64 as i32, data: vec![0; 8 * d] };
    let mut nan = normals(d, 1);
    nan[2] = f32::NAN;
    let cases: Vec<(pb::ScoreRequest, tonic::Code, &str)> = vec![
        (score(tensor(1, &normals(d, 1)), vec![]), tonic::Code::Ok, ""),
        (
            score(relreward_client::tensor::encode_f32(&[1, d as u64 + 1], &normals(d + 1, 1)), vec![]),
            tonic::Code::InvalidArgument,
            "x: expected shape [B, 4]",
        ),
        (
            score(relreward_client::tensor::encode_f32(&[0, d as u64], &[]), vec![]),
            tonic::Code::InvalidArgument,
            "B = 0",
        ),
        (score(tensor(65, &normals(65 * d, 1)), vec![]), tonic::Code::InvalidArgument, "max_request_items"),
        (score(tensor(1, &normals(d, 1)), vec![T as u32]), tonic::Code::InvalidArgument, "t[0]: 20 is outside [0, 20)"),
        (score(tensor(1, &nan), vec![]), tonic::Code::InvalidArgument, "x: element 2 is not finite"),
        (score(int64, vec![]), tonic::Code::InvalidArgument, "x: dtype is int64 where float32 or float64"),
        (
            pb::ScoreRequest { model: "nope".into(), ..score(tensor(1, &normals(d, 1)), vec![]) },
            tonic::Code::NotFound,
            "'nope'",
        ),
        (
            pb::ScoreRequest { model: "base".into(), ..score(tensor(1, &normals(d, 1)), vec![]) },
            tonic::Code::FailedPrecondition,
            "not a reward",
        ),
        (
            pb::ScoreRequest { x: None, ..score(tensor(1, &normals(d, 1)), vec![]) },
            tonic::Code::InvalidArgument,
            "x: missing",
        ),
    ];
    for (req, code, message) in cases {
        match rewards.score(req).await {
            Ok(_) => assert_eq!(code, tonic::Code::Ok),
            Err(status) => {
                assert_eq!(status.code(), code, "{}", status.message());
                assert!(status.message().contains(message), "{} should contain {message}", status.message());
            }
        }
    }
    assert_eq!(client.health().await.expect("health"), tonic_health::pb::health_check_response::ServingStatus::Serving);

    // Guided sampling: the sample mean approaches the expert mean M as omega grows, and the
    // reported reward rises with it.
    let m = Tensor::from_slice(&M).to_kind(Kind::Double);
    let mut distances = Vec::new();
    let mut mean_rewards = Vec::new();
    for omega in [0.0, 0.25, 0.5, 1.0] {
        let req = pb::SampleRequest {
            model: "base".into(),
            reward_model: "r-serve".into(),
            omega,
            n: 512,
            seed: Some(3),
            ..Default::default()
        };
        let mut stream = rewards.sample(req).await.expect("sample").into_inner();
        let (mut xs, mut rs) = (Vec::new(), Vec::new());
        while let Some(item) = stream.next().await {
            let item = item.expect("sample item");
            xs.extend(relreward_client::tensor::decode_finite_f32(item.x.as_ref().expect("x")).expect("f32"));
            rs.push(item.reward.expect("reward reported"));
        }
        let x = Tensor::from_slice(&xs).reshape([512, d as i64]).to_kind(Kind::Double);
        let distance = (x.mean_dim(0, false, Kind::Double) - &m).norm().double_value(&[]);
        eprintln!(
            "omega {omega}: distance of the sample mean to the expert mean {distance:.3}, mean reward {:.4}",
            rs.iter().sum::<f64>() / rs.len() as f64
        );
        distances.push(distance);
        mean_rewards.push(rs.iter().sum::<f64>() / rs.len() as f64);
    }
    let norm_m = m.norm().double_value(&[]);
    assert!(distances[0] > 0.8 * norm_m, "unguided samples sit near the base mean: {distances:?}");
    assert!(distances.windows(2).all(|w| w[1] < w[0]), "distance must shrink as omega grows: {distances:?}");
    assert!(mean_rewards.windows(2).all(|w| w[1] > w[0]), "reward must grow with omega: {mean_rewards:?}");
    assert!(distances[3] < 0.25 * norm_m, "omega = 1 must land near the expert: {distances:?}");

    // GradientStream: one stream, many requests, answers matched by request_id and equal to
    // the unary answers; a bad request gets its error in its response and the stream goes on.
    let requests: Vec<pb::GradientRequest> = (0..20u64)
        .map(|id| pb::GradientRequest {
            request_id: 1000 + id,
            model: if id == 13 { "nope".into() } else { "r-serve".into() },
            x: Some(tensor(2, &normals(2 * d, 500 + id))),
            t: vec![(id % T as u64) as u32],
            ..Default::default()
        })
        .collect();
    let mut responses =
        rewards.gradient_stream(tokio_stream::iter(requests.clone())).await.expect("stream").into_inner();
    let mut seen = std::collections::HashMap::new();
    while let Some(r) = responses.next().await {
        let r = r.expect("stream message");
        seen.insert(r.request_id, r);
    }
    assert_eq!(seen.len(), requests.len(), "one response per request");
    for req in requests {
        let got = &seen[&req.request_id];
        if req.model == "nope" {
            let error = got.error.as_ref().expect("per-request error");
            assert_eq!(error.code, tonic::Code::NotFound as i32, "{}", error.message);
            continue;
        }
        let unary = rewards.gradient(req.clone()).await.expect("unary").into_inner();
        // Equal up to float rounding: the stream's requests were merged into other batches.
        let close = |a: &Option<pb::Tensor>, b: &Option<pb::Tensor>| {
            let a = relreward_client::tensor::decode_finite_f32(a.as_ref().expect("a")).expect("f32");
            let b = relreward_client::tensor::decode_finite_f32(b.as_ref().expect("b")).expect("f32");
            a.len() == b.len() && a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= 1e-6 + 1e-5 * y.abs())
        };
        assert!(close(&got.gradient, &unary.gradient), "request {}: streamed gradient differs", req.request_id);
        assert!(close(&got.rewards, &unary.rewards), "request {}: streamed rewards differ", req.request_id);
    }
}
