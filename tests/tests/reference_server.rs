//! The serving benchmark's baseline, `bench/reference/grpc_server.py` (a researcher's Python
//! gRPC server around the PyTorch reference nets), computes the same gradients and rho as
//! relreward on the same stored weights, so `tests/bench/serving.sh` compares speed on
//! identical work. Both servers get the same requests, unary and streamed, over every option
//! the benchmark uses (normalized units, per-item t, omega) and raw units too.

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use relreward_client::tensor::{decode_finite_f32, encode_f32, encode_f64};
use relreward_client::{Client, pb};
use relreward_tests::{TestServer, TinyModels, python, repo_root, train_tiny_reward};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

/// Tolerance on every gradient and rho element, relative to the largest magnitude of the
/// same tensor (elementwise relative error is meaningless for entries that round to ~0).
const RTOL: f32 = 1e-5;

/// The Python reference server, killed on drop.
struct ReferenceServer {
    child: Child,
    endpoint: String,
}

impl ReferenceServer {
    /// Serves `models` on a free loopback port, from the same weights relreward serves,
    /// downloaded through its API (`DownloadModel`) into `dir/NAME`.
    async fn start(server: &TestServer, dir: &std::path::Path, models: &[&str]) -> Self {
        let client = server.client().await;
        for m in models {
            client.download_model(m, &dir.join(m), false).await.expect("download the reward");
        }
        let mut cmd = Command::new(python());
        cmd.arg(repo_root().join("bench/reference/grpc_server.py"))
            .args(["--listen", "127.0.0.1:0", "--threads", "1", "--models-dir"])
            .arg(dir)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        for m in models {
            cmd.args(["--model", m]);
        }
        let mut child = cmd.spawn().expect("spawn grpc_server.py");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut lines = BufReader::new(stdout).lines();
            let _ = tx.send(lines.next().and_then(Result::ok));
            for _ in lines {}
        });
        let line = rx.recv_timeout(Duration::from_secs(120)).ok().flatten();
        let Some(addr) = line.as_deref().and_then(|l| l.strip_prefix("reference grpc_server listening on ")) else {
            let _ = child.kill();
            let mut err = String::new();
            if let Some(mut e) = child.stderr.take() {
                let _ = std::io::Read::read_to_string(&mut e, &mut err);
            }
            panic!("grpc_server.py did not start (first line {line:?}):\n{err}");
        };
        let endpoint = format!("http://{addr}");
        Self { child, endpoint }
    }
}

impl Drop for ReferenceServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn connect(endpoint: &str) -> Client {
    for _ in 0..100 {
        if let Ok(c) = Client::connect(endpoint).await {
            return c;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("cannot connect to {endpoint}");
}

/// Deterministic values in [-1.5, 1.5): inside and a little outside the normalized range.
fn values(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 11) as f64 / (1u64 << 53) as f64 * 3.0 - 1.5) as f32
        })
        .collect()
}

/// The requests both servers answer: every unit combination, per-item / broadcast / absent t,
/// omega set and unset, float32 and float64 inputs, one and several items.
fn requests(m: &TinyModels) -> Vec<pb::GradientRequest> {
    let item = [m.horizon as u64, m.transition_dim as u64];
    let per_item = m.horizon * m.transition_dim;
    let x32 = |b: u64, seed| encode_f32(&[b, item[0], item[1]], &values(b as usize * per_item, seed));
    let (raw, norm) = (pb::Units::Raw as i32, pb::Units::Normalized as i32);
    let last = m.n_timesteps as u32 - 1;
    let request = |id, x, t: Vec<u32>, input_units, gradient_units, omega| pb::GradientRequest {
        request_id: id,
        model: m.reward.clone(),
        x: Some(x),
        t,
        input_units,
        gradient_units,
        omega,
        scale_by_posterior_variance_of: String::new(),
    };
    let x64 =
        encode_f64(&[2, item[0], item[1]], &values(2 * per_item, 9).iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
    vec![
        // The benchmark's request: normalized units, per-item t, omega.
        request(1, x32(5, 1), vec![0, 3, last, 5, 1], norm, norm, Some(0.3)),
        request(2, x32(1, 2), vec![0], norm, norm, None),
        // Raw units both ways, t broadcast.
        request(3, x32(4, 3), vec![7], raw, raw, None),
        // Raw input, normalized gradient, no t (0 for all), the default units spelled unspecified.
        request(4, x32(3, 4), vec![], pb::Units::Unspecified as i32, norm, Some(-2.0)),
        // Normalized input, raw gradient, float64 x.
        request(5, x64, vec![2, last], norm, pb::Units::Unspecified as i32, Some(1.5)),
    ]
}

/// max |got - want| <= RTOL * max |want|, and `want` is not all zeros (a test on zeros would
/// pass for any broken gradient).
#[track_caller]
fn assert_close(what: &str, got: &pb::Tensor, want: &pb::Tensor) {
    assert_eq!(got.shape, want.shape, "{what}: shapes differ");
    let (got, want) = (decode_finite_f32(got).expect("got"), decode_finite_f32(want).expect("want"));
    let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.0, "{what}: the reference answered all zeros");
    let worst = got.iter().zip(&want).map(|(g, w)| (g - w).abs()).fold(0f32, f32::max);
    assert!(worst <= RTOL * scale, "{what}: max |relreward - reference| = {worst:e} > {RTOL:e} x {scale:e}");
}

#[track_caller]
fn assert_same_answer(what: &str, relreward: &pb::GradientResponse, reference: &pb::GradientResponse) {
    assert_eq!(relreward.error, None, "{what}: relreward failed");
    assert_eq!(reference.error, None, "{what}: the reference failed");
    assert_eq!(relreward.request_id, reference.request_id, "{what}: request ids");
    let (g, r) = (relreward.gradient.as_ref().expect("gradient"), reference.gradient.as_ref().expect("gradient"));
    assert_close(&format!("{what}: gradient"), g, r);
    let (g, r) = (relreward.rewards.as_ref().expect("rewards"), reference.rewards.as_ref().expect("rewards"));
    assert_close(&format!("{what}: rho"), g, r);
}

#[tokio::test(flavor = "multi_thread")]
async fn unary_gradients_match_relreward() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let models = train_tiny_reward(&server, tmp.path());
    let reference = ReferenceServer::start(&server, &tmp.path().join("models"), &[&models.reward]).await;
    let mut ours = server.client().await.rewards();
    let mut theirs = connect(&reference.endpoint).await.rewards();
    let all = requests(&models);
    for req in &all {
        let what = format!("request {}", req.request_id);
        let a = ours.gradient(req.clone()).await.unwrap_or_else(|e| panic!("{what}: relreward: {e}")).into_inner();
        let b = theirs.gradient(req.clone()).await.unwrap_or_else(|e| panic!("{what}: reference: {e}")).into_inner();
        assert_same_answer(&what, &a, &b);
    }
    // The options change the answer, so agreeing on them is not vacuous: omega scales the
    // gradient (request 1 at omega 1 vs 0.3), raw units change it (requests 2 in raw units).
    let mut unit_omega = all[0].clone();
    unit_omega.omega = None;
    let scaled = ours.gradient(all[0].clone()).await.expect("scaled").into_inner();
    let unit = theirs.gradient(unit_omega).await.expect("unit").into_inner();
    let (s, u) = (
        decode_finite_f32(scaled.gradient.as_ref().expect("g")).expect("s"),
        decode_finite_f32(unit.gradient.as_ref().expect("g")).expect("u"),
    );
    for (s, u) in s.iter().zip(&u) {
        assert!((s - 0.3 * u).abs() <= 1e-5 * u.abs().max(1e-3), "omega 0.3: {s} vs 0.3 x {u}");
    }
    let mut raw = all[1].clone();
    raw.input_units = pb::Units::Raw as i32;
    raw.gradient_units = pb::Units::Raw as i32;
    let a = ours.gradient(raw.clone()).await.expect("raw").into_inner();
    let b = theirs.gradient(raw).await.expect("raw").into_inner();
    assert_same_answer("request 2 in raw units", &a, &b);
    assert_ne!(a.gradient, ours.gradient(all[1].clone()).await.expect("norm").into_inner().gradient);
}

/// Sends every request of `requests(..)` plus one malformed one on one GradientStream, all at
/// once, and returns the responses by request_id.
async fn stream_all(client: &Client, reqs: Vec<pb::GradientRequest>) -> HashMap<u64, pb::GradientResponse> {
    let n = reqs.len();
    let (tx, rx) = tokio::sync::mpsc::channel(n);
    for r in reqs {
        tx.send(r).await.expect("queue");
    }
    drop(tx);
    let mut responses = client.rewards().gradient_stream(ReceiverStream::new(rx)).await.expect("stream").into_inner();
    let mut out = HashMap::new();
    while let Some(r) = responses.next().await {
        let r = r.expect("the stream ends cleanly");
        assert!(out.insert(r.request_id, r).is_none(), "one response per request");
    }
    assert_eq!(out.len(), n, "every request answered");
    out
}

#[tokio::test(flavor = "multi_thread")]
async fn streamed_gradients_match_relreward_and_errors_stay_in_the_stream() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let models = train_tiny_reward(&server, tmp.path());
    let reference = ReferenceServer::start(&server, &tmp.path().join("models"), &[&models.reward]).await;
    let mut reqs = requests(&models);
    // A wrong item shape in the middle of the stream: answered with its error, the requests
    // after it still answered.
    let bad = pb::GradientRequest {
        request_id: 99,
        model: models.reward.clone(),
        x: Some(encode_f32(&[1, 3, 4], &[0.0; 12])),
        ..Default::default()
    };
    reqs.insert(2, bad);
    let ours = stream_all(&server.client().await, reqs.clone()).await;
    let theirs = stream_all(&connect(&reference.endpoint).await, reqs.clone()).await;
    for req in reqs.iter().filter(|r| r.request_id != 99) {
        let id = req.request_id;
        assert_same_answer(&format!("streamed request {id}"), &ours[&id], &theirs[&id]);
    }
    for (who, answers) in [("relreward", &ours), ("reference", &theirs)] {
        let error = answers[&99].error.as_ref().unwrap_or_else(|| panic!("{who}: the bad request succeeded"));
        assert_eq!(Code::from_i32(error.code), Code::InvalidArgument, "{who}: {error:?}");
        assert!(error.message.starts_with("x: expected shape [B, 8, 4]"), "{who}: {}", error.message);
    }
}
