//! `relreward score`, `grad` and `sample` end to end: a tiny dataset with known episodes is
//! uploaded, a base and an expert diffusion model and a windowed reward are trained for a few
//! steps with the CLI, and the serving commands are checked through the files they write (read
//! back with numpy), their JSON summaries and their errors. The typed `GradientStream` helper
//! is checked against unary Gradient on the same server.

use std::path::Path;

use relreward_client::client::stream_error_status;
use relreward_client::pb;
use relreward_client::tensor::{decode_finite_f32, encode_f32};
use relreward_tests::{
    TestServer, np_load, npz_shape as shape, npz_values as values, ok, ok_json, refused, run_python, train_models,
};

/// Rows per episode of the trajectories file. With the horizon H = 8: 23 + 0 + 33 + 5 + 18 = 79
/// windows at stride 1 and 12 + 0 + 17 + 3 + 9 = 41 at stride 2.
const EPISODES: [usize; 5] = [30, 5, 40, 12, 25];
const H: usize = 8;
const D: usize = 4;

/// Writes `traj.npz` (D4RL keys; the first episode ends at a terminal, the others at timeouts),
/// `x.npz` (`x` [5, H, D] float64) and `first.npz` (`x`: the windows of the first episode as
/// Diffuser builds them, [action | observation] rows).
const MAKE_INPUTS: &str = r#"
import sys
import numpy as np
out, lengths, H = sys.argv[1], [int(v) for v in sys.argv[2].split(",")], int(sys.argv[3])
rng = np.random.default_rng(0)
n = sum(lengths)
t = np.arange(n, dtype=np.float32)
obs = np.stack([np.sin(t / 7), np.cos(t / 5)], axis=1).astype(np.float32) + 0.1 * rng.normal(size=(n, 2)).astype(np.float32)
act = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)
ends = np.cumsum(lengths) - 1
terminals = np.zeros(n, dtype=bool)
timeouts = np.zeros(n, dtype=bool)
terminals[ends[0]] = True
timeouts[ends[1:]] = True
np.savez(f"{out}/traj.npz", observations=obs, actions=act, terminals=terminals, timeouts=timeouts,
         rewards=np.zeros(n, dtype=np.float32))
np.savez(f"{out}/x.npz", x=rng.normal(size=(5, H, 4)))
rows = np.concatenate([act, obs], axis=1)
first = np.stack([rows[s:s + H] for s in range(lengths[0] - H + 1)])
np.savez(f"{out}/first.npz", x=first.astype(np.float32))
"#;

fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol * (1.0 + x.abs().max(y.abs())))
}

#[tokio::test(flavor = "multi_thread")]
async fn score_grad_and_sample_commands_write_npz_files_numpy_reads() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let dir = tmp.path();
    let path = |name: &str| dir.join(name).to_str().expect("utf8").to_owned();
    let lengths = EPISODES.map(|l| l.to_string()).join(",");
    run_python(MAKE_INPUTS, &[dir.to_str().expect("utf8"), &lengths, &H.to_string()]);

    // ---- a dataset, two diffusion models and a reward, each in a few steps.
    ok(&server, &["dataset", "upload", &path("traj.npz"), "--name", "traj"]);
    train_models(&server, dir, "traj", "traj", &["--steps", "8", "--batch-size", "8"]);

    // ---- plain sampling: x [3, H, D] in raw units, deterministic for a seed.
    let s1 = path("s1.npz");
    let summary = ok_json(&server, &["sample", "--base", "base", "--n", "3", "--seed", "1", "--out", &s1]);
    assert_eq!(summary["count"], 3);
    assert_eq!(summary["shape"], serde_json::json!([H, D]));
    assert_eq!(summary["out"], s1.as_str());
    let a = np_load(Path::new(&s1));
    assert_eq!(shape(&a, "x"), [3, H as u64, D as u64]);
    assert_eq!(shape(&a, "x_normalized"), [3, H as u64, D as u64]);
    assert_eq!(a["x"]["dtype"], "float32");
    assert!(a.get("reward").is_none(), "no reward without a reward model");
    let s2 = path("s2.npz");
    ok(&server, &["sample", "--base", "base", "--n", "3", "--seed", "1", "--out", &s2]);
    let b = np_load(Path::new(&s2));
    assert_eq!(values(&a, "x"), values(&b, "x"), "same seed, same samples");
    let s3 = path("s3.npz");
    ok(&server, &["sample", "--base", "base", "--n", "3", "--seed", "2", "--out", &s3]);
    assert_ne!(values(&a, "x"), values(&np_load(Path::new(&s3)), "x"), "another seed, other samples");
    // An inpainting condition (raw units) is what the sample holds at that index.
    let sc = path("cond.npz");
    ok(
        &server,
        &[
            "sample",
            "--base",
            "base",
            "--n",
            "2",
            "--seed",
            "4",
            "--condition",
            "0=0.25,-0.5",
            "--batch-size",
            "1",
            "--out",
            &sc,
        ],
    );
    let cond = values(&np_load(Path::new(&sc)), "x");
    for item in 0..2 {
        let row = &cond[item * H * D..item * H * D + D];
        assert!(close(&row[2..], &[0.25, -0.5], 1e-4), "condition not applied: {row:?}");
    }
    // Text summary without --out.
    let text = ok(&server, &["sample", "--base", "base", "--n", "2", "--seed", "1"]);
    assert!(text.contains("samples") && text.contains("[8, 4]"), "{text}");

    // ---- flags the CLI refuses, naming the flag.
    refused(&server, &["sample", "--base", "base", "--reward", "rw"], &["--scale"]);
    refused(&server, &["sample", "--base", "base", "--scale", "0.1"], &["--reward"]);
    refused(&server, &["sample", "--base", "base", "--t-stopgrad", "2"], &["--t-stopgrad", "--reward"]);
    refused(&server, &["sample", "--base", "base", "--n", "0"], &["--n"]);
    refused(&server, &["sample", "--base", "base", "--condition", "0=1"], &["--condition", "obs_dim 2"]);
    refused(&server, &["sample", "--base", "base", "--condition", "99=1,2"], &["--condition", "horizon"]);
    refused(&server, &["sample", "--base", "base", "--condition", "zero=1,2"], &["--condition"]);
    refused(&server, &["sample", "--base", "rw"], &["--base"]);
    refused(&server, &["sample", "--base", "missing"], &["NOT_FOUND"]);
    let x = path("x.npz");
    refused(&server, &["score", "--model", "rw", "--input", &x, "--batch", "0"], &["--batch"]);
    refused(&server, &["score", "--model", "rw", "--input", &x, "--units", "kelvin"], &["--units"]);
    refused(&server, &["score", "--model", "rw", "--input", &path("missing.npz")], &["--input"]);
    refused(&server, &["score", "--model", "rw", "--input", &x, "--key", "nope"], &["--key nope", "'x'"]);
    refused(&server, &["score", "--model", "rw", "--input", &x, "--stride", "2"], &["--stride"]);
    refused(&server, &["score", "--model", "rw", "--input", &x, "--out", &path("no/such/dir/o.npz")], &["--out"]);
    refused(&server, &["score", "--model", "base", "--input", &x], &["--model base", "diffusion"]);
    refused(&server, &["score", "--model", "missing", "--input", &x], &["NOT_FOUND"]);
    refused(&server, &["grad", "--model", "rw", "--input", &x], &["--t"]);
    refused(&server, &["grad", "--model", "rw", "--input", &x, "--t", "1", "--omega", "nan"], &["--omega"]);
    refused(&server, &["score", "--model", "rw", "--input", &x, "--t", "1000"], &["INVALID_ARGUMENT", "t"]);

    // ---- score an array of items.
    let so = path("score.npz");
    let summary = ok_json(
        &server,
        &["score", "--model", "rw", "--input", &x, "--per-window", "--per-step", "--t", "3", "--out", &so],
    );
    assert_eq!(summary["count"], 5);
    for field in ["mean", "std", "min", "max"] {
        assert!(summary["reward"][field].is_number(), "{summary}");
    }
    let scored = np_load(Path::new(&so));
    assert_eq!(shape(&scored, "reward"), [5]);
    assert_eq!(scored["reward"]["dtype"], "float32");
    assert_eq!(shape(&scored, "per_window"), [5, (H / 4) as u64]);
    assert_eq!(shape(&scored, "per_step"), [5, H as u64]);
    let mean = values(&scored, "reward").iter().sum::<f64>() / 5.0;
    assert!((mean - summary["reward"]["mean"].as_f64().expect("mean")).abs() < 1e-5);
    let text = ok(&server, &["score", "--model", "rw", "--input", &x]);
    assert!(text.contains("reward") && text.contains("mean") && text.contains('5'), "{text}");

    // ---- gradients: grad_x has the input's shape; its rewards are Score's at the same t.
    let go = path("grad.npz");
    let summary = ok_json(&server, &["grad", "--model", "rw", "--input", &x, "--t", "3", "--out", &go]);
    assert!(summary["gradient_norm"]["mean"].is_number(), "{summary}");
    let grads = np_load(Path::new(&go));
    assert_eq!(shape(&grads, "grad_x"), [5, H as u64, D as u64]);
    assert_eq!(shape(&grads, "reward"), [5]);
    assert!(close(&values(&grads, "reward"), &values(&scored, "reward"), 1e-4));
    // omega scales the gradient.
    let g2 = path("grad2.npz");
    ok(&server, &["grad", "--model", "rw", "--input", &x, "--t", "3", "--omega", "2", "--batch", "2", "--out", &g2]);
    let doubled: Vec<f64> = values(&grads, "grad_x").iter().map(|g| 2.0 * g).collect();
    assert!(close(&values(&np_load(Path::new(&g2)), "grad_x"), &doubled, 1e-4));
    let text = ok(&server, &["grad", "--model", "rw", "--input", &x, "--t", "3"]);
    assert!(text.contains("|grad_x|"), "{text}");

    // ---- a trajectories file is cut into windows inside episodes.
    let traj = path("traj.npz");
    let windows: usize = EPISODES.iter().map(|&l| (l + 1).saturating_sub(H)).sum();
    let to = path("traj-score.npz");
    let summary = ok_json(&server, &["score", "--model", "rw", "--input", &traj, "--batch", "16", "--out", &to]);
    assert_eq!(summary["count"], windows);
    assert_eq!(summary["source"]["episodes"], EPISODES.len());
    let traj_scores = np_load(Path::new(&to));
    assert_eq!(shape(&traj_scores, "reward"), [windows as u64]);
    assert_eq!(shape(&traj_scores, "window_start"), [windows as u64]);
    // The first episode's windows score as numpy's windows of [action | observation] rows.
    let fo = path("first-score.npz");
    ok(&server, &["score", "--model", "rw", "--input", &path("first.npz"), "--out", &fo]);
    let first = values(&np_load(Path::new(&fo)), "reward");
    assert_eq!(first.len(), EPISODES[0] + 1 - H);
    assert!(close(&values(&traj_scores, "reward")[..first.len()], &first, 1e-4));
    let strided: usize = EPISODES.iter().map(|&l| (l + 1).saturating_sub(H).div_ceil(2)).sum();
    let summary = ok_json(&server, &["score", "--model", "rw", "--input", &traj, "--stride", "2"]);
    assert_eq!(summary["count"], strided);
    let summary = ok_json(&server, &["grad", "--model", "rw", "--input", &traj, "--t", "1"]);
    assert_eq!(summary["count"], windows);

    // ---- guided sampling writes the reward of each sample.
    let gs = path("guided.npz");
    let guided = ["sample", "--base", "base", "--reward", "rw", "--scale", "0.1", "--n", "3", "--seed", "1"];
    let summary = ok_json(&server, &[&guided[..], &["--out", &gs]].concat());
    assert!(summary["reward"]["mean"].is_number(), "{summary}");
    let g = np_load(Path::new(&gs));
    assert_eq!(shape(&g, "x"), [3, H as u64, D as u64]);
    assert_eq!(shape(&g, "reward"), [3]);
    let gs2 = path("guided2.npz");
    ok(&server, &[&guided[..], &["--out", &gs2]].concat());
    assert_eq!(values(&g, "x"), values(&np_load(Path::new(&gs2)), "x"), "guided sampling is seeded too");

    // ---- the typed GradientStream helper: answers matched by id, errors per request.
    let client = server.client().await;
    let items: Vec<f32> = (0..2 * H * D).map(|i| (i as f32 * 0.37).sin()).collect();
    let x = encode_f32(&[2, H as u64, D as u64], &items);
    let request = |id: u64, t: u32| pb::GradientRequest {
        request_id: id,
        model: "rw".into(),
        x: Some(x.clone()),
        t: vec![t],
        ..Default::default()
    };
    let mut stream = client.gradient_stream().await.expect("open stream");
    for (id, t) in [(7, 2), (9, 5), (11, 10_000)] {
        stream.send(request(id, t)).await.expect("send");
    }
    let mut answers = std::collections::HashMap::new();
    for _ in 0..3 {
        let answer = stream.message().await.expect("message").expect("an answer per request");
        answers.insert(answer.request_id, answer);
    }
    let mut rest = stream.close();
    assert!(rest.message().await.expect("end").is_none(), "the stream ends once the requests do");
    let bad = answers[&11].error.as_ref().expect("t out of range is an error for request 11");
    assert_eq!(stream_error_status(bad).code(), tonic::Code::InvalidArgument, "{bad:?}");
    for (id, t) in [(7, 2), (9, 5)] {
        let streamed = &answers[&id];
        assert!(streamed.error.is_none(), "{:?}", streamed.error);
        let unary = client.gradient(request(id, t)).await.expect("unary");
        assert_eq!(unary.request_id, id);
        let a = decode_finite_f32(streamed.gradient.as_ref().expect("gradient")).expect("finite");
        let b = decode_finite_f32(unary.gradient.as_ref().expect("gradient")).expect("finite");
        let (a, b): (Vec<f64>, Vec<f64>) =
            (a.into_iter().map(f64::from).collect(), b.into_iter().map(f64::from).collect());
        assert!(close(&a, &b, 1e-5), "request {id}: stream and unary gradients differ");
    }
}
