//! The serving layer in process, against a real store, registry and reward network: gradients
//! against finite differences in both units, the posterior-variance factor, batching that
//! returns each caller its own rows, load shedding, deadlines and cancellation.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tch::{Device, Kind, Tensor};
use tokio::sync::Semaphore;

use super::*;
use crate::config::{Config, Overrides};
use crate::engine::manifest::{RewardSignature, RewardUploadManifest, Space};
use crate::engine::nets::{RewardArchitecture, RewardNet};
use crate::engine::normalizer::{Normalize, Normalizer};
use crate::engine::relative_reward::{EvalPoint, Objective, RewardManifest, Target};
use crate::engine::reward_model::RewardModel;
use crate::store::digests::sha256_file;
use crate::store::{ModelFormat, ModelKind, ModelRecord, Provenance, Store};
use crate::tasks::Tasks;

const H: i64 = 8;
const D: i64 = 3;
const T: usize = 10;

fn windowed() -> RewardArchitecture {
    RewardArchitecture::WindowedMlp { window: 4, hidden: vec![16, 16] }
}

fn manifest() -> RewardManifest {
    manifest_with(windowed())
}

fn manifest_with(architecture: RewardArchitecture) -> RewardManifest {
    let space = Space::Trajectory { horizon: H as usize, action_dim: 1, obs_dim: 2 };
    // Different scales per coordinate, so raw and normalized gradients differ.
    let normalizer = Normalizer::Limits { min: vec![-2.0, 0.0, -10.0], max: vec![2.0, 1.0, 30.0] };
    RewardManifest {
        objective: Objective::alignment(Target::Mean, EvalPoint::XT, false),
        ..RewardManifest::for_tests(architecture, space, normalizer, T)
    }
}

/// What the fixture serves as "rho".
enum Served {
    /// A native reward network of this architecture, at its first weights.
    Native(RewardArchitecture),
    /// A bring-your-own TorchScript module of signature rho over the same space and normalizer.
    Module(PathBuf),
}

struct Fixture {
    _tmp: tempfile::TempDir,
    serving: Serving,
    metrics: Metrics,
    /// The same network, loaded privately, for reference values.
    reference: RewardModel,
}

async fn fixture(tune: impl FnOnce(&mut ServingConfig)) -> Fixture {
    fixture_with(Served::Native(windowed()), tune).await
}

async fn fixture_with(served: Served, tune: impl FnOnce(&mut ServingConfig)) -> Fixture {
    let tmp = tempfile::tempdir().expect("tempdir");
    let overrides = Overrides { data_dir: Some(tmp.path().join("data")), ..Overrides::default() };
    let env = config::Environment::with_prefix("RELREWARD").source(Some(HashMap::new()));
    let mut config = Config::load_with_env(None, &overrides, env).expect("config");
    tune(&mut config.serving);
    let store = Store::open(&config).await.expect("store");

    let (m, file, format) = match served {
        Served::Native(arch) => {
            let net = RewardNet::new(&arch, &[H, D], 0, Device::Cpu).expect("net");
            let weights = tmp.path().join("weights.safetensors");
            net.save(&weights).expect("save");
            (manifest_with(arch), weights, ModelFormat::Native)
        }
        Served::Module(path) => {
            let native = manifest();
            let upload = RewardUploadManifest {
                signature: RewardSignature::Rho,
                n_timesteps: T,
                space: native.space,
                normalizer: native.normalizer,
                base_model: String::new(),
            };
            (RewardManifest::uploaded(&upload), path, ModelFormat::Torchscript)
        }
    };
    register(&store, "rho", &file, format, ModelKind::Reward, serde_json::to_value(&m).expect("json")).await;
    // A diffusion record (never loaded: only its manifest's schedule is read) for the
    // posterior-variance factor.
    let diffusion = serde_json::json!({
        "parametrization": "epsilon",
        "schedule": {"kind": "cosine", "s": 0.008},
        "n_timesteps": T,
        "space": {"kind": "trajectory", "horizon": H, "action_dim": 1, "obs_dim": 2},
        "normalizer": {"kind": "identity"},
        "architecture": {"kind": "mlp", "hidden": [8]},
    });
    register(&store, "base", &file, ModelFormat::Native, ModelKind::Diffusion, diffusion).await;

    let registry = ModelRegistry::new(store.clone(), &config.models, Device::Cpu);
    let metrics = Metrics::new();
    let slots = Arc::new(Semaphore::new(2));
    let serving =
        Serving::new(registry, config.serving.clone(), slots, metrics.clone(), Tasks::detached_for_tests("serving"));
    let reference = RewardModel::load(m, &file, tmp.path(), Device::Cpu).expect("reference");
    Fixture { _tmp: tmp, serving, metrics, reference }
}

async fn register(
    store: &Store,
    name: &str,
    file: &Path,
    format: ModelFormat,
    kind: ModelKind,
    manifest: serde_json::Value,
) {
    let staging = store.blobs.staging().expect("staging");
    let stored = if format == ModelFormat::Torchscript { "module.pt" } else { "weights.safetensors" };
    let target = staging.path().join(stored);
    std::fs::copy(file, &target).expect("copy");
    let (sha256, size_bytes) = sha256_file(&target).expect("hash");
    let record = ModelRecord {
        name: name.into(),
        kind,
        format,
        manifest,
        parameter_count: 0,
        sha256,
        size_bytes,
        file: stored.into(),
        provenance: Provenance::Uploaded,
        created_at_ms: 0,
        description: String::new(),
        blob_key: String::new(),
    };
    store.commit_model(staging, record).await.expect("commit");
}

/// Deterministic inputs in raw units inside the normalizer's limits.
fn raw_items(b: usize, seed: u64) -> Vec<f32> {
    let (lo, hi) = ([-2.0f32, 0.0, -10.0], [2.0f32, 1.0, 30.0]);
    (0..b * (H * D) as usize)
        .map(|i| {
            let u = (((i as u64 + 1) * 2654435761 + seed * 97) % 1000) as f32 / 1000.0;
            let d = i % D as usize;
            lo[d] + u * (hi[d] - lo[d])
        })
        .collect()
}

fn score(values: Vec<f32>, b: usize, t: Vec<i64>, units: Units) -> Query {
    Query {
        shape: vec![b as i64, H, D],
        values,
        t,
        input_units: units,
        op: Op::Score { per_window: false, per_step: false },
        deadline: None,
    }
}

fn gradient(values: Vec<f32>, b: usize, t: Vec<i64>, units: Units, grad_units: Units) -> Query {
    Query { op: Op::Gradient { units: grad_units, omega: 1.0, variance_of: None }, ..score(values, b, t, units) }
}

fn to_vec(t: &Tensor) -> Vec<f32> {
    Vec::<f32>::try_from(&t.contiguous().view(-1)).expect("f32")
}

/// Central differences of Score agree with Gradient, with inputs and gradient both in raw
/// units and both in normalized units.
#[tokio::test(flavor = "multi_thread")]
async fn gradient_matches_finite_differences_of_score_in_both_units() {
    let f = fixture(|_| {}).await;
    let raw = raw_items(2, 1);
    let normalized = {
        let x = Tensor::from_slice(&raw).reshape([2, H, D]);
        to_vec(&manifest().normalizer.normalize(&x, 1))
    };
    for (units, x0, eps) in [(Units::Raw, &raw, 1e-2f32), (Units::Normalized, &normalized, 2e-3f32)] {
        let t = vec![3i64, 7];
        let answer = f.serving.query("rho", gradient(x0.clone(), 2, t.clone(), units, units)).await.expect("grad");
        let g = answer.gradient.as_ref().expect("gradient").values.clone();
        // Raw coordinate 2 spans 40 units: scale its step so every coordinate moves alike.
        let scale = |i: usize| if units == Units::Raw { [1.0f32, 0.25, 10.0][i % D as usize] } else { 1.0 };
        let mut worst = 0f32;
        for i in 0..x0.len() {
            let h = eps * scale(i);
            let (mut plus, mut minus) = (x0.clone(), x0.clone());
            plus[i] += h;
            minus[i] -= h;
            let up = f.serving.query("rho", score(plus, 2, t.clone(), units)).await.expect("score").rewards.values;
            let down = f.serving.query("rho", score(minus, 2, t.clone(), units)).await.expect("score").rewards.values;
            let item = i / (H * D) as usize;
            let fd = (up[item] - down[item]) / (2.0 * h);
            let err = (fd - g[i]).abs() / (1e-3 + g[i].abs());
            worst = worst.max(err);
            assert!(err < 3e-2, "{units:?}, coordinate {i}: finite difference {fd} vs gradient {}", g[i]);
        }
        eprintln!("{units:?}: worst relative error {worst:.2e}");
    }
    // The two units differ exactly by the normalizer's Jacobian (2 / (max - min)).
    let t = vec![5i64];
    let one = raw_items(1, 2);
    let g_raw = f.serving.query("rho", gradient(one.clone(), 1, t.clone(), Units::Raw, Units::Raw)).await.expect("g");
    let g_norm = f.serving.query("rho", gradient(one, 1, t, Units::Raw, Units::Normalized)).await.expect("g");
    let (g_raw, g_norm) = (g_raw.gradient.expect("g").values, g_norm.gradient.expect("g").values);
    for i in 0..g_raw.len() {
        let jac = [0.5f32, 2.0, 0.05][i % D as usize];
        assert!((g_raw[i] - g_norm[i] * jac).abs() <= 1e-6 * (1.0 + g_raw[i].abs()), "coordinate {i}");
    }
}

/// omega and the posterior variance of a named diffusion model scale the gradient per item.
#[tokio::test(flavor = "multi_thread")]
async fn omega_and_posterior_variance_scale_the_gradient_per_item() {
    let f = fixture(|_| {}).await;
    let x = raw_items(3, 3);
    let t = vec![0i64, 4, 9];
    let plain = f.serving.query("rho", gradient(x.clone(), 3, t.clone(), Units::Raw, Units::Raw)).await.expect("g");
    let mut q = gradient(x, 3, t.clone(), Units::Raw, Units::Raw);
    q.op = Op::Gradient { units: Units::Raw, omega: 0.3, variance_of: Some("base".into()) };
    let scaled = f.serving.query("rho", q).await.expect("scaled");
    let schedule = Schedule::new(&crate::engine::manifest::ScheduleSpec::Cosine { s: 0.008 }, T).expect("schedule");
    let tensor = |a: Answer| a.gradient.expect("g").to_tensor().expect("tensor");
    let (plain, scaled) = (tensor(plain), tensor(scaled));
    for (b, &ti) in t.iter().enumerate() {
        let factor = 0.3 * schedule.get(Table::PosteriorLogVarianceClipped, ti as usize).expect("t").exp();
        let want = plain.get(b as i64) * factor;
        assert!(scaled.get(b as i64).allclose(&want, 1e-5, 1e-9, false), "item {b} (t = {ti})");
    }
    // A diffusion model whose schedule has another T, or a reward model, is refused.
    let mut q = gradient(raw_items(1, 1), 1, vec![0], Units::Raw, Units::Raw);
    q.op = Op::Gradient { units: Units::Raw, omega: 1.0, variance_of: Some("rho".into()) };
    match f.serving.query("rho", q).await {
        Err(Error::FailedPrecondition(m)) => assert!(m.contains("scale_by_posterior_variance_of"), "{m}"),
        other => panic!("expected FailedPrecondition, got {other:?}"),
    }
}

/// Many concurrent callers with distinct inputs are merged into fewer passes, and each gets
/// exactly its own rows back.
#[tokio::test(flavor = "multi_thread")]
async fn concurrent_queries_are_merged_and_each_caller_gets_its_own_rows() {
    let merged = |c: &mut ServingConfig| c.max_delay_us = 50_000;
    merged_callers_get_their_own_rows(Served::Native(windowed()), merged, 1).await;
    // A convolutional reward: merged batches are padded to the next allowed size
    // (`RewardNet::padded_batch`), whose rows never reach a caller. Wide enough that its last
    // group norms span several values: over two (widths [32] here) the backward amplifies the
    // rounding that differs between batch sizes (oneDNN picks kernels per shape) past 1e-5.
    merged_callers_get_their_own_rows(
        Served::Native(RewardArchitecture::ValueFunction { widths: vec![128] }),
        merged,
        1,
    )
    .await;
}

/// A merged pass split across threads (`serving.pass_threads`: its rows in parts, each on its
/// own thread with its own handle on the weights) gives every caller its own rows, as one
/// thread does.
#[tokio::test(flavor = "multi_thread")]
async fn split_passes_give_each_caller_its_own_rows() {
    let split = |c: &mut ServingConfig| {
        c.max_delay_us = 50_000;
        c.pass_threads = 2;
        c.split_above_ms = 0.0;
    };
    let value_function = || Served::Native(RewardArchitecture::ValueFunction { widths: vec![128] });
    // Two rounds: a model's first pass is never split (nothing says yet what it costs).
    let f = merged_callers_get_their_own_rows(value_function(), split, 2).await;
    let text = f.metrics.render();
    assert!(metric(&text, "relreward_serving_split_passes_total{model=\"rho\"}") >= 1.0, "no pass was split\n{text}");
    // With one thread, none is.
    let one = |c: &mut ServingConfig| {
        split(c);
        c.pass_threads = 1;
    };
    let f = merged_callers_get_their_own_rows(value_function(), one, 2).await;
    assert!(!f.metrics.render().contains("relreward_serving_split_passes_total{"), "a pass was split on one thread");
    // A bring-your-own TorchScript module is split too, its helper sharing the loaded module.
    let modules = crate::engine::torchscript::tests::byo_fixtures();
    let f = merged_callers_get_their_own_rows(Served::Module(modules.path().join("scaled.pt")), split, 2).await;
    let text = f.metrics.render();
    assert!(
        metric(&text, "relreward_serving_split_passes_total{model=\"rho\"}") >= 1.0,
        "no module pass was split\n{text}"
    );
}

/// `rounds` times, 22 concurrent callers (Score and Gradient, 1 to 3 items each) check their
/// answers against the reference; the passes must have merged them.
async fn merged_callers_get_their_own_rows(
    served: Served,
    tune: impl FnOnce(&mut ServingConfig),
    rounds: usize,
) -> Fixture {
    let f = fixture_with(served, tune).await;
    // 21 and 22 items per kind: merged, neither is an allowed size, so the convolutional
    // reward's passes carry padding.
    let callers = 22usize;
    for _ in 0..rounds {
        merged_round(&f, callers).await;
    }
    let text = f.metrics.render();
    let batches = metric(&text, "relreward_serving_batch_items_count{model=\"rho\"}");
    assert!(
        batches < (rounds * callers) as f64 / 2.0,
        "{batches} passes for {rounds} x {callers} callers: not merged\n{text}"
    );
    f
}

async fn merged_round(f: &Fixture, callers: usize) {
    let mut tasks = Vec::new();
    for k in 0..callers {
        let serving = f.serving.clone();
        let b = 1 + k % 3;
        let x = raw_items(b, 100 + k as u64);
        let t: Vec<i64> = (0..b as i64).map(|i| (k as i64 + i) % T as i64).collect();
        tasks.push(tokio::spawn(async move {
            let q = if k % 2 == 0 {
                score(x.clone(), b, t.clone(), Units::Raw)
            } else {
                gradient(x.clone(), b, t.clone(), Units::Raw, Units::Normalized)
            };
            (x, t, serving.query("rho", q).await)
        }));
    }
    for (k, task) in tasks.into_iter().enumerate() {
        let (x, t, answer) = task.await.expect("task");
        let answer = answer.expect("answer");
        let b = t.len() as i64;
        let xn = manifest().normalizer.normalize(&Tensor::from_slice(&x).reshape([b, H, D]), 1);
        let tt = Tensor::from_slice(&t);
        let (want_rho, want_grad) = f.reference.grad(&xn, &tt).expect("reference");
        let rewards = answer.rewards.to_tensor().expect("tensor");
        assert!(rewards.allclose(&want_rho, 1e-5, 1e-6, false), "caller {k}: rewards are not its own");
        if let Some(g) = &answer.gradient {
            let g = g.to_tensor().expect("tensor");
            assert!(g.allclose(&want_grad, 1e-5, 1e-6, false), "caller {k}: gradient rows are not its own");
        }
    }
}

/// An overfull queue sheds load with RESOURCE_EXHAUSTED; the queries it accepted succeed.
#[tokio::test(flavor = "multi_thread")]
async fn an_overfull_queue_answers_resource_exhausted() {
    let f = fixture(|c| {
        c.queue_capacity = 2;
        c.max_delay_us = 300_000;
        c.max_batch = 1024;
    })
    .await;
    let mut tasks = Vec::new();
    for k in 0..8u64 {
        let serving = f.serving.clone();
        tasks.push(tokio::spawn(
            async move { serving.query("rho", score(raw_items(1, k), 1, vec![0], Units::Raw)).await },
        ));
    }
    let (mut ok, mut shed) = (0, 0);
    for task in tasks {
        match task.await.expect("task") {
            Ok(_) => ok += 1,
            Err(Error::ResourceExhausted(m)) => {
                assert!(m.contains("serving.queue_capacity"), "{m}");
                shed += 1;
            }
            Err(e) => panic!("unexpected error {e}"),
        }
    }
    assert!(shed >= 1 && ok >= 2 && ok + shed == 8, "ok {ok}, shed {shed}");
    assert_eq!(
        metric(&f.metrics.render(), "relreward_serving_dropped_total{model=\"rho\",reason=\"queue_full\"}"),
        shed as f64
    );
    // A query turned away by a full queue was never queued: only the accepted ones count.
    let stats = f.metrics.model_stats("rho").expect("statistics of rho");
    assert_eq!((stats.success.count, stats.fail.count), (ok, 0), "{stats:?}");
    // The server is healthy afterwards.
    f.serving.query("rho", score(raw_items(1, 9), 1, vec![0], Units::Raw)).await.expect("still serving");
}

/// A query whose deadline passes while it waits is answered DEADLINE_EXCEEDED and never
/// computed; a cancelled query (its future dropped) is skipped.
#[tokio::test(flavor = "multi_thread")]
async fn expired_and_cancelled_queries_cost_no_compute() {
    let f = fixture(|c| c.max_delay_us = 300_000).await;
    let mut q = score(raw_items(1, 1), 1, vec![0], Units::Raw);
    q.deadline = Some(Instant::now() + Duration::from_millis(30));
    match f.serving.query("rho", q).await {
        Err(Error::DeadlineExceeded(m)) => assert!(m.contains("not computed"), "{m}"),
        other => panic!("expected DeadlineExceeded, got {other:?}"),
    }
    let serving = f.serving.clone();
    let task = tokio::spawn(async move { serving.query("rho", score(raw_items(1, 2), 1, vec![0], Units::Raw)).await });
    tokio::time::sleep(Duration::from_millis(30)).await;
    task.abort();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let text = f.metrics.render();
    assert_eq!(metric(&text, "relreward_serving_dropped_total{model=\"rho\",reason=\"deadline\"}"), 1.0, "{text}");
    assert_eq!(metric(&text, "relreward_serving_dropped_total{model=\"rho\",reason=\"cancelled\"}"), 1.0, "{text}");
    assert_eq!(metric(&text, "relreward_serving_batch_items_count{model=\"rho\"}"), 0.0, "nothing was computed");
    // Both were queued, so both count as failures (Triton's REJECTED and CANCELED); a query
    // whose deadline had passed before it arrived was never queued and does not count.
    let mut late = score(raw_items(1, 3), 1, vec![0], Units::Raw);
    late.deadline = Some(Instant::now());
    match f.serving.query("rho", late).await {
        Err(Error::DeadlineExceeded(m)) => assert!(m.contains("before the query was queued"), "{m}"),
        other => panic!("expected DeadlineExceeded, got {other:?}"),
    }
    let stats = f.metrics.model_stats("rho").expect("statistics of rho");
    assert_eq!((stats.success.count, stats.fail.count), (0, 2), "{stats:?}");
    assert!(stats.fail.ns >= 30_000_000, "the deadline's wait is in the failures' duration: {stats:?}");
    assert_eq!((stats.inference_count, stats.execution_count), (0, 0));
}

/// Bad queries fail validation with named fields and never reach the batcher.
#[tokio::test(flavor = "multi_thread")]
async fn bad_queries_name_their_field_and_cost_nothing() {
    let f = fixture(|c| c.max_request_items = 4).await;
    let good = || score(raw_items(1, 1), 1, vec![0], Units::Raw);
    let cases: Vec<(Query, &str)> = vec![
        (Query { shape: vec![1, H, D + 1], ..good() }, "x: expected shape [B, 8, 3]"),
        (Query { shape: vec![H, D], ..good() }, "x: expected shape"),
        (Query { shape: vec![0, H, D], values: vec![], ..good() }, "B = 0"),
        (Query { shape: vec![5, H, D], values: raw_items(5, 1), ..good() }, "serving.max_request_items"),
        (Query { t: vec![T as i64], ..good() }, "t[0]: 10 is outside [0, 10)"),
        (
            Query {
                values: {
                    let mut v = raw_items(1, 1);
                    v[3] = f32::NAN;
                    v
                },
                ..good()
            },
            "x: element 3 is not finite",
        ),
        (Query { values: raw_items(1, 1)[1..].to_vec(), ..good() }, "do not fill the shape"),
        // The range check, on the query's own floats: as given, and after normalizing.
        (
            Query {
                values: {
                    let mut v = raw_items(1, 1);
                    v[5] = -2e4;
                    v
                },
                input_units: Units::Normalized,
                ..good()
            },
            "x: element 5 is -2e4 in the model's normalized units (as given",
        ),
        (
            Query {
                values: {
                    let mut v = raw_items(1, 1);
                    v[3] = 1e9;
                    v
                },
                ..good()
            },
            "x: element 3 is 5e8 in the model's normalized units (after normalizing the raw input)",
        ),
    ];
    for (q, want) in cases {
        match f.serving.query("rho", q).await {
            Err(Error::InvalidArgument(m)) => assert!(m.contains(want), "{m} should contain {want}"),
            other => panic!("expected InvalidArgument ({want}), got {other:?}"),
        }
    }
    match f.serving.query("missing", good()).await {
        Err(Error::NotFound(_)) => {}
        other => panic!("expected NotFound, got {other:?}"),
    }
    match f.serving.query("base", good()).await {
        Err(Error::FailedPrecondition(m)) => assert!(m.contains("not a reward"), "{m}"),
        other => panic!("expected FailedPrecondition, got {other:?}"),
    }
    assert_eq!(metric(&f.metrics.render(), "relreward_serving_batch_items_count{model=\"rho\"}"), 0.0);
    // Refused before they were queued: not in ModelStatistics (Triton does not count a request
    // that fails validation), nor in the queries counter.
    assert_eq!(f.metrics.model_stats("rho"), None, "validation refusals are not counted");
    assert!(!f.metrics.render().contains("relreward_serving_queries_total"), "{}", f.metrics.render());
}

/// One merged batch of gradient queries with different units and omegas: each caller's rows get
/// its own factors (applied on the host after the shared pass), checked against the reference
/// net's normalized gradient times omega and, for raw units, the normalizer's Jacobian.
#[tokio::test(flavor = "multi_thread")]
async fn mixed_units_and_omegas_in_one_batch_get_their_own_factors() {
    let f = fixture(|c| c.max_delay_us = 1_000_000).await;
    let cases = [(Units::Raw, 0.5), (Units::Normalized, 1.0), (Units::Raw, 1.0), (Units::Normalized, -2.0)];
    let mut tasks = Vec::new();
    for (k, &(units, omega)) in cases.iter().enumerate() {
        let serving = f.serving.clone();
        let x = raw_items(2, 7 + k as u64);
        let t = vec![k as i64, 9 - k as i64];
        tasks.push(tokio::spawn(async move {
            let mut q = gradient(x.clone(), 2, t.clone(), Units::Raw, units);
            q.op = Op::Gradient { units, omega, variance_of: None };
            (x, t, serving.query("rho", q).await)
        }));
    }
    for ((units, omega), task) in cases.into_iter().zip(tasks) {
        let (x, t, answer) = task.await.expect("task");
        let raw = Tensor::from_slice(&x).reshape([2, H, D]);
        let (_, grad) =
            f.reference.grad(&manifest().normalizer.normalize(&raw, 1), &Tensor::from_slice(&t)).expect("ref");
        let mut want = grad * omega;
        if units == Units::Raw {
            want *= manifest().normalizer.jacobian(&raw, 1);
        }
        let got = answer.expect("answer").gradient.expect("gradient").to_tensor().expect("tensor");
        assert!(got.allclose(&want.to_kind(Kind::Float), 1e-5, 1e-6, false), "{units:?}, omega {omega}");
    }
    let text = f.metrics.render();
    assert_eq!(metric(&text, "relreward_serving_batch_items_count{model=\"rho\"}"), 1.0, "one merged pass: {text}");
}

/// Per-window and per-step values of a windowed reward, batched like the rest.
#[tokio::test(flavor = "multi_thread")]
async fn per_window_and_per_step_values_come_back_per_item() {
    let f = fixture(|_| {}).await;
    let mut q = score(raw_items(2, 5), 2, vec![1, 2], Units::Raw);
    q.op = Op::Score { per_window: true, per_step: true };
    let a = f.serving.query("rho", q).await.expect("score");
    assert_eq!(a.per_window.as_ref().expect("windows").shape, [2, H / 4]);
    assert_eq!(a.per_step.as_ref().expect("steps").shape, [2, H]);
    let mean = a.per_window.expect("windows").to_tensor().expect("tensor").mean_dim(1, false, Kind::Float);
    assert!(
        mean.allclose(&a.rewards.to_tensor().expect("tensor"), 1e-5, 1e-6, false),
        "rho is the mean of the windows"
    );
}

/// The value of one sample line of the text exposition (0 when absent).
fn metric(text: &str, series: &str) -> f64 {
    text.lines().find_map(|l| l.strip_prefix(series).and_then(|v| v.trim().parse().ok())).unwrap_or(0.0)
}
