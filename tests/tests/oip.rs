//! The Open Inference Protocol (KServe v2 / Triton gRPC) endpoint, end to end.
//!
//! A tiny base and expert diffusion model and a reward model between them are trained on a
//! trajectory dataset (a few steps each: the numbers only have to be numbers). Then:
//! - Python's stock `tritonclient.grpc` (tests/python/oip_client.py) asks liveness, readiness
//!   and metadata and infers `reward` and `grad_x`; its answers must equal the native
//!   RewardService's Score and Gradient on the same input bit for bit, and relreward's
//!   `inference` descriptors must match the ones shipped inside tritonclient field for field.
//!   It also reads the model's config, statistics and the repository index with tritonclient's
//!   own stubs (protobuf and JSON), which proves those answers wire-compatible too.
//! - Bad requests through the generated Rust client get the native API's status codes
//!   (NOT_FOUND, FAILED_PRECONDITION, INVALID_ARGUMENT naming the input), as do a few through
//!   tritonclient, and the server answers normally afterwards.
//! - ModelConfig reports the model and the serving settings; ModelStatistics counts exactly
//!   the calls made (successes and failures); RepositoryIndex lists the reward model READY and
//!   no diffusion model; `t` given once (shape [1] or []) or as [B, 1] gives the same numbers
//!   as one per item.
//! - RPCs of the protocol that relreward leaves out answer UNIMPLEMENTED.
//! - The same protocol over HTTP/JSON (`oip_http.listen`, KServe v2 REST): `tritonclient.http`
//!   (tests/python/oip_http_client.py), with binary and JSON tensors, compressed bodies, and
//!   `curl`, answers exactly as gRPC does (which equals the native API, above); refusals carry
//!   the HTTP status of the gRPC code and a JSON error naming the field.

use std::time::Duration;

use relreward_client::pb::{self, job_event::Event};
use relreward_client::{Client, tensor};
use relreward_proto::inference::grpc_inference_service_client::GrpcInferenceServiceClient;
use relreward_proto::inference::model_infer_request::{InferInputTensor, InferRequestedOutputTensor};
use relreward_proto::inference::{self as oip, InferTensorContents};
use relreward_tests::{Lines, TestServer, python, repo_root, upload_lines};
use tokio_stream::StreamExt;
use tonic::Code;
use tonic::transport::Channel;

const HORIZON: u32 = 8;
/// observations (2) and actions (2).
const DIM: usize = 4;
const T: u32 = 10;
/// serving.max_request_items for this server, so that "too many items" is cheap to send.
const MAX_ITEMS: usize = 16;

/// Straight-line trajectories (see [`Lines`]): x0 in [-2, 2), y0 in [1, 7), vx in [-0.2, 0.2),
/// vy in [-0.1, 0.1), 64 episodes.
const LINES: Lines =
    Lines { episodes: 64, seed: 99, start: [(4.0, -2.0), (6.0, 1.0)], velocity: [(0.4, -0.2), (0.2, -0.1)] };

fn optimization(steps: u64) -> Option<pb::Optimization> {
    Some(pb::Optimization {
        steps: Some(steps),
        batch_size: Some(16),
        learning_rate: Some(1e-3),
        checkpoint_every: Some(1000),
        eval_every: Some(1000),
        log_every: Some(10),
        ..Default::default()
    })
}

fn diffusion_spec(output: &str, seed: u64) -> pb::JobSpec {
    pb::JobSpec {
        output_model: output.into(),
        seed: Some(seed),
        optimization: optimization(10),
        kind: Some(pb::job_spec::Kind::Diffusion(pb::TrainDiffusion {
            dataset: "lines".into(),
            horizon: Some(HORIZON),
            n_timesteps: Some(T),
            parametrization: pb::Parametrization::Epsilon as i32,
            architecture: Some(pb::train_diffusion::Architecture::TemporalUnet(pb::TemporalUnet {
                dim: Some(8),
                dim_mults: vec![1, 2],
            })),
            ..Default::default()
        })),
    }
}

fn reward_spec() -> pb::JobSpec {
    pb::JobSpec {
        output_model: "lines-reward".into(),
        seed: Some(5),
        optimization: optimization(10),
        kind: Some(pb::job_spec::Kind::Reward(pb::TrainReward {
            base_model: "lines-base".into(),
            expert_model: "lines-expert".into(),
            algorithm: Some(pb::train_reward::Algorithm::WithDataset(pb::train_reward::WithDataset {
                datasets: vec!["lines".into()],
            })),
            ..Default::default()
        })),
    }
}

async fn train(client: &Client, spec: pb::JobSpec) {
    let job = client
        .jobs()
        .submit_job(pb::SubmitJobRequest { spec: Some(spec), job_id: String::new() })
        .await
        .expect("submit")
        .into_inner();
    let mut stream = client
        .jobs()
        .watch_job(pb::WatchJobRequest { id: job.id.clone(), from_seq: 0 })
        .await
        .expect("watch")
        .into_inner();
    let mut last = None;
    while let Some(e) = tokio::time::timeout(Duration::from_secs(120), stream.next()).await.expect("event in time") {
        if let Some(Event::State(s)) = e.expect("event").event {
            last = Some(s);
        }
    }
    let last = last.expect("a state event");
    assert_eq!(last.state(), pb::JobState::Succeeded, "job {}: {last:?}", job.id);
}

/// A server with the dataset "lines", diffusion models "lines-base" and "lines-expert" and the
/// reward model "lines-reward" between them.
async fn setup() -> (TestServer, Client) {
    let server = TestServer::start_with_env(&[
        ("RELREWARD__SERVING__MAX_REQUEST_ITEMS", &MAX_ITEMS.to_string()),
        ("RELREWARD__OIP_HTTP__LISTEN", "127.0.0.1:0"),
        ("RELREWARD__METRICS__LISTEN", "127.0.0.1:0"),
    ]);
    let client = server.client().await;
    upload_lines(&client, "lines", &LINES).await;
    let (base, expert) = (diffusion_spec("lines-base", 1), diffusion_spec("lines-expert", 2));
    tokio::join!(train(&client, base), train(&client, expert));
    train(&client, reward_spec()).await;
    (server, client)
}

async fn inference(server: &TestServer) -> GrpcInferenceServiceClient<Channel> {
    GrpcInferenceServiceClient::connect(server.endpoint()).await.expect("connect")
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

fn f32_le(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn raw_f32(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn raw_i64(values: &[i64]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// Native Score and Gradient (raw units, the defaults) of `x` `[B, H, D]` at `t`.
async fn native(client: &Client, x: &[f32], t: &[i64]) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let shape = [t.len() as u64, u64::from(HORIZON), DIM as u64];
    let t: Vec<u32> = t.iter().map(|&v| u32::try_from(v).expect("t")).collect();
    let score = client
        .rewards()
        .score(pb::ScoreRequest {
            model: "lines-reward".into(),
            x: Some(tensor::encode_f32(&shape, x)),
            t: t.clone(),
            ..Default::default()
        })
        .await
        .expect("native score")
        .into_inner();
    let gradient = client
        .rewards()
        .gradient(pb::GradientRequest {
            model: "lines-reward".into(),
            x: Some(tensor::encode_f32(&shape, x)),
            t,
            ..Default::default()
        })
        .await
        .expect("native gradient")
        .into_inner();
    let decode = |t: Option<pb::Tensor>| tensor::decode_finite_f32(&t.expect("tensor")).expect("finite float32");
    let g = gradient.gradient.expect("gradient");
    assert_eq!(g.shape, shape, "native gradient shape");
    (decode(score.rewards), decode(gradient.rewards), decode(Some(g)))
}

fn u32s(v: &serde_json::Value) -> Vec<u32> {
    v.as_array().expect("array").iter().map(|b| b.as_u64().expect("u32") as u32).collect()
}

/// (a) tritonclient against the native API, and the descriptors against tritonclient's.
async fn tritonclient_matches_native(server: &TestServer, client: &Client) {
    let tmp = tempfile::tempdir().expect("tmp");
    let descriptor = tmp.path().join("inference_descriptor.bin");
    std::fs::write(&descriptor, relreward_proto::INFERENCE_FILE_DESCRIPTOR_SET).expect("descriptor");
    let out = std::process::Command::new(python())
        .arg(repo_root().join("tests/python/oip_client.py"))
        .args(["--url", &server.addr.to_string(), "--model", "lines-reward", "--diffusion-model", "lines-base"])
        .arg("--out")
        .arg(tmp.path().join("oip.npz"))
        .arg("--descriptor")
        .arg(&descriptor)
        .output()
        .expect("python");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "oip_client.py failed:\n{stderr}\nserver log:\n{}", server.log());
    assert!(tmp.path().join("oip.npz").exists());
    let s: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON summary");

    let descriptor = &s["descriptor"];
    assert!(descriptor["fields_and_methods_compared"].as_u64().expect("count") > 60, "{descriptor}");
    assert_eq!(descriptor["mismatches"], serde_json::json!([]), "wire compatibility with tritonclient");

    for (key, want) in [
        ("server_live", true),
        ("server_ready", true),
        ("model_ready", true),
        ("model_ready_version_1", true),
        ("unknown_model_ready", false),
        ("diffusion_model_ready", false),
    ] {
        assert_eq!(s[key], want, "{key}");
    }
    assert_eq!(s["server_metadata"]["name"], "relreward");
    assert_eq!(s["server_metadata"]["version"], env!("CARGO_PKG_VERSION"));
    let meta = &s["model_metadata"];
    assert_eq!(meta["name"], "lines-reward");
    assert_eq!(meta["versions"], serde_json::json!(["1"]));
    // as_json renders int64 as strings (proto3 JSON).
    let io = |list: &serde_json::Value| -> Vec<(String, String, Vec<String>)> {
        list.as_array()
            .expect("tensors")
            .iter()
            .map(|t| {
                let shape = t["shape"].as_array().expect("shape").iter().map(|d| d.to_string().replace('"', ""));
                (t["name"].as_str().expect("name").into(), t["datatype"].as_str().expect("dt").into(), shape.collect())
            })
            .collect()
    };
    let dims = |d: &[&str]| d.iter().map(|s| (*s).to_owned()).collect::<Vec<_>>();
    let (h, d) = (HORIZON.to_string(), DIM.to_string());
    assert_eq!(
        io(&meta["inputs"]),
        [("x".into(), "FP32".into(), dims(&["-1", &h, &d])), ("t".into(), "INT64".into(), dims(&["-1"]))]
    );
    assert_eq!(
        io(&meta["outputs"]),
        [("reward".into(), "FP32".into(), dims(&["-1"])), ("grad_x".into(), "FP32".into(), dims(&["-1", &h, &d]))]
    );

    let r = &s["response"];
    assert_eq!(
        (r["id"].as_str(), r["model_name"].as_str(), r["model_version"].as_str()),
        (Some("req-7"), Some("lines-reward"), Some("1"))
    );
    assert_eq!(s["reward_only_outputs"], serde_json::json!(["reward"]));
    assert_eq!(s["default_outputs"], serde_json::json!(["reward", "grad_x"]));

    let arrays = &s["arrays"];
    let x: Vec<f32> = u32s(&arrays["x"]["bits"]).into_iter().map(f32::from_bits).collect();
    let t: Vec<i64> = arrays["t"]["bits"].as_array().expect("t").iter().map(|v| v.as_i64().expect("i64")).collect();
    let b = t.len();
    assert!(b > 1 && t.iter().any(|&v| v > 0), "a batch over several diffusion steps: {t:?}");
    assert_eq!(arrays["grad_x"]["shape"], serde_json::json!([b, HORIZON, DIM]));
    let (score, gradient_rewards, gradient) = native(client, &x, &t).await;
    assert_eq!(u32s(&arrays["reward_only"]["bits"]), bits(&score), "OIP reward (score path) vs native Score");
    assert_eq!(u32s(&arrays["reward"]["bits"]), bits(&gradient_rewards), "OIP reward (gradient path) vs native");
    assert_eq!(u32s(&arrays["grad_x"]["bits"]), bits(&gradient), "OIP grad_x vs native Gradient");
    assert_eq!(u32s(&arrays["grad_x_default"]["bits"]), bits(&gradient), "no outputs named: both");
    for (a, b) in score.iter().zip(&gradient_rewards) {
        assert!((a - b).abs() <= 1e-6 * a.abs().max(1.0), "Score {a} vs Gradient's rewards {b}");
    }
    assert!(gradient.iter().any(|g| *g != 0.0), "a gradient that is not all zeros");

    let status = |k: &str| s["errors"][k]["status"].as_str().expect("status").to_owned();
    let message = |k: &str| s["errors"][k]["message"].as_str().expect("message").to_owned();
    assert_eq!(status("x_fp64"), "StatusCode.INVALID_ARGUMENT", "{}", message("x_fp64"));
    assert!(message("x_fp64").contains("x: datatype") && message("x_fp64").contains("FP32"), "{}", message("x_fp64"));
    assert_eq!(status("unknown_model"), "StatusCode.NOT_FOUND");
    assert_eq!(status("diffusion_model"), "StatusCode.FAILED_PRECONDITION");
    assert_eq!(status("unknown_output"), "StatusCode.INVALID_ARGUMENT");
    for (rpc, code) in [
        ("config_unknown_model", "NOT_FOUND"),
        ("config_diffusion_model", "FAILED_PRECONDITION"),
        ("config_unknown_version", "NOT_FOUND"),
        ("statistics_unknown_model", "NOT_FOUND"),
        ("statistics_diffusion_model", "FAILED_PRECONDITION"),
        ("load_model", "UNIMPLEMENTED"),
        ("shared_memory_status", "UNIMPLEMENTED"),
        ("log_settings", "UNIMPLEMENTED"),
    ] {
        assert_eq!(status(rpc), format!("StatusCode.{code}"), "{rpc}: {}", message(rpc));
    }
    assert_eq!(s["after_errors_equal"], true);

    // ModelConfig, as tritonclient's ModelConfig message and as JSON.
    let (h, d) = (i64::from(HORIZON), DIM as i64);
    assert_eq!(
        s["model_config_proto"],
        serde_json::json!({
            "name": "lines-reward",
            "max_batch_size": MAX_ITEMS,
            "inputs": [["x", "TYPE_FP32", [h, d], [], false], ["t", "TYPE_INT64", [1], [], true]],
            "outputs": [["reward", "TYPE_FP32", [1], []], ["grad_x", "TYPE_FP32", [h, d], []]],
            "scheduling": "dynamic_batching",
            "preferred_batch_size": [MAX_ITEMS],
            "version_policy": "specific",
        })
    );
    let config = &s["model_config"];
    assert_eq!(
        (config["name"].as_str(), config["platform"].as_str()),
        (Some("lines-reward"), Some("relreward_native"))
    );
    assert_eq!(config["input"][0]["dims"], serde_json::json!([h.to_string(), d.to_string()]), "{config}");
    assert_eq!(config["input"][1]["reshape"], serde_json::json!({}), "t: one scalar per item: {config}");
    assert!(config["input"][0].get("reshape").is_none(), "{config}");
    assert_eq!(config["parameters"]["n_timesteps"]["string_value"], T.to_string(), "{config}");

    // Statistics: the three inferences above (one success each, B items each), no failure
    // (the bad requests were refused before reaching the model, or were for other models).
    let delta = &s["statistics_delta"];
    assert_eq!((delta["name"].as_str(), delta["version"].as_str()), (Some("lines-reward"), Some("1")));
    assert_eq!((delta["success"].as_u64(), delta["fail"].as_u64()), (Some(3), Some(0)), "{delta}");
    assert_eq!(delta["inference_count"].as_u64(), Some(3 * b as u64), "{delta}");
    assert_eq!(delta["compute_infer"].as_u64(), Some(3), "{delta}");
    assert_eq!(delta["success_ns_grew"], true);
    let now_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).expect("clock").as_millis();
    let last = u128::from(delta["last_inference_ms"].as_u64().expect("ms"));
    assert!(last <= now_ms && last + 600_000 > now_ms, "last_inference {last} vs now {now_ms}");
    assert_eq!(s["statistics_json"]["model_stats"][0]["name"], "lines-reward");
    let count = s["statistics_json"]["model_stats"][0]["inference_count"].as_str().expect("uint64 as a JSON string");
    assert!(count.parse::<u64>().expect("count") >= 3 * b as u64);
    let all: Vec<&str> = s["statistics_all_json"]["model_stats"]
        .as_array()
        .expect("all stats")
        .iter()
        .map(|m| m["name"].as_str().expect("name"))
        .collect();
    assert_eq!(all, ["lines-reward"], "only reward models with statistics");

    // The repository: the reward model, not the diffusion models.
    assert_eq!(s["repository_index"], serde_json::json!([["lines-reward", "1", "READY", ""]]));
    assert_eq!(
        s["repository_index_json"],
        serde_json::json!({"models": [{"name": "lines-reward", "version": "1", "state": "READY"}]})
    );
}

fn x_input(shape: &[i64]) -> InferInputTensor {
    InferInputTensor { name: "x".into(), datatype: "FP32".into(), shape: shape.to_vec(), ..Default::default() }
}

fn t_input(shape: &[i64]) -> InferInputTensor {
    InferInputTensor { name: "t".into(), datatype: "INT64".into(), shape: shape.to_vec(), ..Default::default() }
}

fn infer_request(inputs: Vec<InferInputTensor>, raw: Vec<Vec<u8>>) -> oip::ModelInferRequest {
    oip::ModelInferRequest {
        model_name: "lines-reward".into(),
        inputs,
        raw_input_contents: raw.into_iter().map(Into::into).collect(),
        ..Default::default()
    }
}

/// A batch of `b` items inside the data's range, and its diffusion steps.
fn batch(b: usize) -> (Vec<f32>, Vec<i64>) {
    let x = (0..b * HORIZON as usize * DIM).map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0).collect();
    let t = (0..b as i64).map(|i| i % i64::from(T)).collect();
    (x, t)
}

/// The generated Rust client: raw and typed inputs, missing t, and every bad input.
async fn rust_client_and_bad_inputs(server: &TestServer, client: &Client) {
    let mut oip = inference(server).await;
    let b = 3usize;
    let shape = [b as i64, i64::from(HORIZON), DIM as i64];
    let (x, t) = batch(b);
    let (score, _, gradient) = native(client, &x, &t).await;

    // Raw contents, t before x, outputs in the order asked.
    let mut req = infer_request(vec![t_input(&[b as i64]), x_input(&shape)], vec![raw_i64(&t), raw_f32(&x)]);
    req.outputs = ["grad_x", "reward"]
        .into_iter()
        .map(|n| InferRequestedOutputTensor { name: n.into(), ..Default::default() })
        .collect();
    req.id = "abc".into();
    let resp = oip.model_infer(req).await.expect("infer raw").into_inner();
    assert_eq!((resp.id.as_str(), resp.model_name.as_str(), resp.model_version.as_str()), ("abc", "lines-reward", "1"));
    let names: Vec<&str> = resp.outputs.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, ["grad_x", "reward"]);
    assert_eq!((resp.outputs[0].datatype.as_str(), resp.outputs[0].shape.as_slice()), ("FP32", shape.as_slice()));
    assert_eq!((resp.outputs[1].datatype.as_str(), resp.outputs[1].shape.as_slice()), ("FP32", &[b as i64][..]));
    assert_eq!(bits(&f32_le(&resp.raw_output_contents[0])), bits(&gradient));

    // Typed contents, reward only (a Score).
    let mut xi = x_input(&shape);
    xi.contents = Some(InferTensorContents { fp32_contents: x.clone(), ..Default::default() });
    let mut ti = t_input(&[b as i64]);
    ti.contents = Some(InferTensorContents { int64_contents: t.clone(), ..Default::default() });
    let mut req = infer_request(vec![xi, ti], vec![]);
    req.outputs = vec![InferRequestedOutputTensor { name: "reward".into(), ..Default::default() }];
    let resp = oip.model_infer(req).await.expect("infer typed").into_inner();
    assert_eq!(resp.outputs.len(), 1);
    assert_eq!(bits(&f32_le(&resp.raw_output_contents[0])), bits(&score));

    // t left out means t = 0 for every item.
    let (score0, _, _) = native(client, &x, &[0; 3]).await;
    let req = infer_request(vec![x_input(&shape)], vec![raw_f32(&x)]);
    let resp = oip.model_infer(req).await.expect("infer without t").into_inner();
    let reward = resp.outputs.iter().position(|o| o.name == "reward").expect("reward");
    assert_eq!(bits(&f32_le(&resp.raw_output_contents[reward])), bits(&score0));

    // Bad requests: (request, code, what the message must contain).
    let good = || infer_request(vec![x_input(&shape), t_input(&[b as i64])], vec![raw_f32(&x), raw_i64(&t)]);
    let mut cases: Vec<(&str, oip::ModelInferRequest, Code, Vec<String>)> = Vec::new();
    let mut r = good();
    r.model_name = "no-such-model".into();
    cases.push(("unknown model", r, Code::NotFound, vec!["no-such-model".into()]));
    let mut r = good();
    r.model_name = "lines-base".into();
    cases.push(("diffusion model", r, Code::FailedPrecondition, vec!["lines-base".into()]));
    let mut r = good();
    r.model_version = "2".into();
    cases.push(("unknown version", r, Code::NotFound, vec!["version".into()]));
    let mut r = good();
    r.inputs[0].datatype = "FP64".into();
    r.raw_input_contents[0] = x.iter().flat_map(|v| f64::from(*v).to_le_bytes()).collect::<Vec<u8>>().into();
    cases.push(("x as FP64", r, Code::InvalidArgument, vec!["x: datatype".into(), "FP64".into(), "FP32".into()]));
    let mut r = good();
    r.inputs[1].datatype = "INT32".into();
    r.raw_input_contents[1] = t.iter().flat_map(|v| (*v as i32).to_le_bytes()).collect::<Vec<u8>>().into();
    cases.push(("t as INT32", r, Code::InvalidArgument, vec!["t: datatype".into(), "INT64".into()]));
    let wrong = [b as i64, i64::from(HORIZON) + 1, DIM as i64];
    let (x_wrong, _) = batch(b + 1);
    let r = infer_request(
        vec![x_input(&wrong), t_input(&[b as i64])],
        vec![raw_f32(&x_wrong[..b * (HORIZON as usize + 1) * DIM]), raw_i64(&t)],
    );
    cases.push(("wrong shape", r, Code::InvalidArgument, vec![format!("[B, {HORIZON}, {DIM}]"), format!("{wrong:?}")]));
    let mut r = good();
    r.raw_input_contents[0] = raw_f32(&x[..x.len() - 1]).into();
    cases.push(("short x", r, Code::InvalidArgument, vec!["x: raw_input_contents".into(), "bytes".into()]));
    let mut r = good();
    r.inputs[1].shape = vec![b as i64 - 1];
    r.raw_input_contents[1] = raw_i64(&t[..b - 1]).into();
    cases.push(("t for fewer items", r, Code::InvalidArgument, vec![format!("t: expected shape [{b}]")]));
    let mut r = good();
    r.inputs.push(InferInputTensor { name: "y".into(), datatype: "FP32".into(), shape: vec![1], ..Default::default() });
    r.raw_input_contents.push(raw_f32(&[0.0]).into());
    cases.push(("unknown input", r, Code::InvalidArgument, vec!["unknown input 'y'".into()]));
    let mut r = good();
    r.inputs.push(x_input(&shape));
    r.raw_input_contents.push(raw_f32(&x).into());
    cases.push(("duplicate x", r, Code::InvalidArgument, vec!["'x'".into(), "more than once".into()]));
    let mut r = good();
    r.outputs = vec![InferRequestedOutputTensor { name: "value".into(), ..Default::default() }];
    cases.push(("unknown output", r, Code::InvalidArgument, vec!["unknown output 'value'".into()]));
    let mut r = good();
    r.inputs.remove(0);
    r.raw_input_contents.remove(0);
    cases.push(("x missing", r, Code::InvalidArgument, vec!["'x'".into(), "missing".into()]));
    for (what, bad) in [("NaN", f32::NAN), ("Inf", f32::INFINITY)] {
        let mut x_bad = x.clone();
        x_bad[5] = bad;
        let r = infer_request(vec![x_input(&shape), t_input(&[b as i64])], vec![raw_f32(&x_bad), raw_i64(&t)]);
        cases.push((what, r, Code::InvalidArgument, vec!["x: element 5 is not finite".into()]));
    }
    let r =
        infer_request(vec![x_input(&[0, i64::from(HORIZON), DIM as i64]), t_input(&[0])], vec![Vec::new(), Vec::new()]);
    cases.push(("B = 0", r, Code::InvalidArgument, vec!["B = 0".into()]));
    for bad_t in [i64::from(T), -1] {
        let mut t_bad = t.clone();
        t_bad[1] = bad_t;
        let r = infer_request(vec![x_input(&shape), t_input(&[b as i64])], vec![raw_f32(&x), raw_i64(&t_bad)]);
        cases.push(("t out of range", r, Code::InvalidArgument, vec![format!("t[1]: {bad_t} is outside [0, {T})")]));
    }
    let big = MAX_ITEMS + 1;
    let (x_big, t_big) = batch(big);
    let r = infer_request(
        vec![x_input(&[big as i64, i64::from(HORIZON), DIM as i64]), t_input(&[big as i64])],
        vec![raw_f32(&x_big), raw_i64(&t_big)],
    );
    cases.push(("B above the limit", r, Code::InvalidArgument, vec!["max_request_items".into()]));
    let mut r = good();
    r.raw_input_contents.pop();
    cases.push(("raw for one of two inputs", r, Code::InvalidArgument, vec!["raw_input_contents: 1 entries".into()]));
    let mut r = good();
    r.inputs[0].shape = vec![-3, i64::from(HORIZON), DIM as i64];
    cases.push(("negative dimension", r, Code::InvalidArgument, vec!["negative dimension".into()]));

    for (what, request, code, needles) in cases {
        let err = oip.model_infer(request).await.expect_err(what);
        assert_eq!(err.code(), code, "{what}: {}", err.message());
        for n in needles {
            assert!(err.message().contains(&n), "{what}: {:?} does not mention {n:?}", err.message());
        }
    }

    // Metadata and readiness of what is not a servable model.
    let err = oip
        .model_metadata(oip::ModelMetadataRequest { name: "no-such-model".into(), version: String::new() })
        .await
        .expect_err("metadata of an unknown model");
    assert_eq!(err.code(), Code::NotFound);
    let err = oip
        .model_metadata(oip::ModelMetadataRequest { name: "lines-expert".into(), version: String::new() })
        .await
        .expect_err("metadata of a diffusion model");
    assert_eq!(err.code(), Code::FailedPrecondition);
    for (name, version, want) in
        [("lines-reward", "", true), ("lines-reward", "2", false), ("lines-base", "", false), ("Bad Name!", "", false)]
    {
        let ready = oip
            .model_ready(oip::ModelReadyRequest { name: name.into(), version: version.into() })
            .await
            .expect("model ready")
            .into_inner()
            .ready;
        assert_eq!(ready, want, "ModelReady({name:?}, {version:?})");
    }

    // Still serving, with the same numbers.
    let resp = oip.model_infer(good()).await.expect("infer after errors").into_inner();
    let g = resp.outputs.iter().position(|o| o.name == "grad_x").expect("grad_x");
    assert_eq!(bits(&f32_le(&resp.raw_output_contents[g])), bits(&gradient));
    assert!(!server.log().contains("panicked"), "server log:\n{}", server.log());
}

async fn statistics(oip: &mut GrpcInferenceServiceClient<Channel>, name: &str) -> oip::ModelStatistics {
    let mut all = oip
        .model_statistics(oip::ModelStatisticsRequest { name: name.into(), version: String::new() })
        .await
        .expect("statistics")
        .into_inner()
        .model_stats;
    assert_eq!(all.len(), 1, "one model asked for: {all:?}");
    all.remove(0)
}

fn durations(s: &oip::ModelStatistics) -> [(u64, u64); 4] {
    let i = s.inference_stats.expect("inference_stats");
    [i.success, i.fail, i.queue, i.compute_infer].map(|d| {
        let d = d.unwrap_or_default();
        (d.count, d.ns)
    })
}

/// ModelConfig, ModelStatistics and RepositoryIndex through the generated Rust client, and
/// `t` given once for every item.
async fn config_statistics_and_index(server: &TestServer, client: &Client) {
    let mut oip = inference(server).await;

    // ModelConfig.
    let config = oip
        .model_config(oip::ModelConfigRequest { name: "lines-reward".into(), version: "1".into() })
        .await
        .expect("config")
        .into_inner()
        .config
        .expect("config");
    let (h, d) = (i64::from(HORIZON), DIM as i64);
    assert_eq!((config.name.as_str(), config.platform.as_str()), ("lines-reward", "relreward_native"));
    assert_eq!(config.max_batch_size, MAX_ITEMS as i32, "serving.max_request_items");
    let inputs: Vec<_> = config
        .input
        .iter()
        .map(|i| (i.name.as_str(), i.data_type(), i.dims.clone(), i.reshape.clone().map(|r| r.shape), i.optional))
        .collect();
    assert_eq!(
        inputs,
        [
            ("x", oip::DataType::TypeFp32, vec![h, d], None, false),
            ("t", oip::DataType::TypeInt64, vec![1], Some(vec![]), true)
        ]
    );
    let outputs: Vec<_> = config
        .output
        .iter()
        .map(|o| (o.name.as_str(), o.data_type(), o.dims.clone(), o.reshape.clone().map(|r| r.shape)))
        .collect();
    assert_eq!(
        outputs,
        [
            ("reward", oip::DataType::TypeFp32, vec![1], Some(vec![])),
            ("grad_x", oip::DataType::TypeFp32, vec![h, d], None)
        ]
    );
    let Some(oip::model_config::SchedulingChoice::DynamicBatching(batching)) = &config.scheduling_choice else {
        panic!("dynamic batching: {config:?}")
    };
    // Defaults: max_batch 256 (capped by max_request_items), max_delay_us 0, queue_capacity
    // 1024, default_deadline_ms 30000.
    assert_eq!(batching.preferred_batch_size, [MAX_ITEMS as i32]);
    assert_eq!(batching.max_queue_delay_microseconds, 0);
    let policy = batching.default_queue_policy.expect("queue policy");
    assert_eq!(
        (policy.max_queue_size, policy.default_timeout_microseconds, policy.allow_timeout_override),
        (1024, 30_000_000, true)
    );
    assert_eq!(policy.timeout_action(), oip::model_queue_policy::TimeoutAction::Reject);
    assert_eq!(
        config.version_policy.and_then(|p| p.policy_choice),
        Some(oip::model_version_policy::PolicyChoice::Specific(oip::model_version_policy::Specific {
            versions: vec![1]
        }))
    );
    assert_eq!(config.parameters["n_timesteps"].string_value, T.to_string());
    for (name, version, code) in [
        ("no-such-model", "", Code::NotFound),
        ("lines-base", "", Code::FailedPrecondition),
        ("lines-reward", "2", Code::NotFound),
        ("Bad Name!", "", Code::InvalidArgument),
    ] {
        let err = oip
            .model_config(oip::ModelConfigRequest { name: name.into(), version: version.into() })
            .await
            .expect_err("config of what is not a servable model");
        assert_eq!(err.code(), code, "ModelConfig({name:?}, {version:?}): {}", err.message());
        let meta = oip
            .model_metadata(oip::ModelMetadataRequest { name: name.into(), version: version.into() })
            .await
            .expect_err("metadata of what is not a servable model");
        assert_eq!(meta.code(), code, "ModelConfig answers as ModelMetadata does");
    }

    // t once for every item ([1] or a scalar) or as [B, 1]: the numbers of t per item.
    let b = 3usize;
    let shape = [b as i64, h, d];
    let (x, _) = batch(b);
    let (_, _, gradient) = native(client, &x, &[4; 3]).await;
    let (score, _, _) = native(client, &x, &[4; 3]).await;
    for t_shape in [&[1][..], &[][..], &[b as i64, 1][..]] {
        let t: Vec<i64> = vec![4; t_shape.iter().product::<i64>() as usize];
        let req = infer_request(vec![x_input(&shape), t_input(t_shape)], vec![raw_f32(&x), raw_i64(&t)]);
        let resp = oip.model_infer(req).await.expect("t broadcast").into_inner();
        let out = |n: &str| f32_le(&resp.raw_output_contents[resp.outputs.iter().position(|o| o.name == n).expect(n)]);
        assert_eq!(bits(&out("grad_x")), bits(&gradient), "t shape {t_shape:?}");
        let mut req = infer_request(vec![x_input(&shape), t_input(t_shape)], vec![raw_f32(&x), raw_i64(&t)]);
        req.outputs = vec![InferRequestedOutputTensor { name: "reward".into(), ..Default::default() }];
        let resp = oip.model_infer(req).await.expect("t broadcast, score").into_inner();
        assert_eq!(bits(&f32_le(&resp.raw_output_contents[0])), bits(&score), "t shape {t_shape:?}");
    }

    // ModelStatistics: exactly the calls made from here on.
    let before = statistics(&mut oip, "lines-reward").await;
    assert_eq!((before.name.as_str(), before.version.as_str()), ("lines-reward", "1"));
    let (x, t) = batch(b);
    let good = || infer_request(vec![x_input(&shape), t_input(&[b as i64])], vec![raw_f32(&x), raw_i64(&t)]);
    let successes = 4;
    for i in 0..successes {
        let mut req = good();
        if i % 2 == 1 {
            req.outputs = vec![InferRequestedOutputTensor { name: "reward".into(), ..Default::default() }];
        }
        oip.model_infer(req).await.expect("infer");
    }
    // Refused by validation against the model (t out of range, too many items, non-finite x,
    // a deadline that passed before the query was queued): answered with their errors but not
    // counted, as Triton does not count a request that fails validation before its scheduler
    // accepted it.
    let mut t_bad = t.clone();
    t_bad[0] = i64::from(T);
    let big = MAX_ITEMS + 1;
    let (x_big, t_big) = batch(big);
    let mut x_nan = x.clone();
    x_nan[1] = f32::NAN;
    let refused = [
        infer_request(vec![x_input(&shape), t_input(&[b as i64])], vec![raw_f32(&x), raw_i64(&t_bad)]),
        infer_request(
            vec![x_input(&[big as i64, h, d]), t_input(&[big as i64])],
            vec![raw_f32(&x_big), raw_i64(&t_big)],
        ),
        infer_request(vec![x_input(&shape), t_input(&[b as i64])], vec![raw_f32(&x_nan), raw_i64(&t)]),
    ];
    for req in refused {
        assert_eq!(oip.model_infer(req).await.expect_err("refused").code(), Code::InvalidArgument);
    }
    let mut expired = tonic::Request::new(good());
    expired.metadata_mut().insert("grpc-timeout", "1n".parse().expect("ascii"));
    let err = oip.model_infer(expired).await.expect_err("an expired deadline");
    // tonic's client may end the call on its own timer first (CANCELLED "Timeout expired").
    assert!(
        err.code() == Code::DeadlineExceeded || (err.code() == Code::Cancelled && err.message() == "Timeout expired"),
        "{err:?}"
    );
    // Refused before reaching a model (malformed message, unknown model or version): not counted.
    let mut fp64 = good();
    fp64.inputs[0].datatype = "FP64".into();
    let mut unknown = good();
    unknown.model_name = "no-such-model".into();
    let mut version = good();
    version.model_version = "2".into();
    for req in [fp64, unknown, version] {
        oip.model_infer(req).await.expect_err("refused before the model");
    }
    let after = statistics(&mut oip, "lines-reward").await;
    let ([s0, f0, q0, c0], [s1, f1, q1, c1]) = (durations(&before), durations(&after));
    assert_eq!(s1.0 - s0.0, successes, "success count");
    assert_eq!(f1, f0, "requests refused before they were queued are not failures: {before:?} -> {after:?}");
    assert!(s1.1 > s0.1, "durations grow: {before:?} -> {after:?}");
    assert_eq!(after.inference_count - before.inference_count, successes * b as u64, "items of the successes");
    // Sequential calls: each query is its own batch, computed once.
    assert_eq!(after.execution_count - before.execution_count, successes);
    assert_eq!((q1.0 - q0.0, c1.0 - c0.0), (successes, successes), "queue and compute per computed query");
    assert!(c1.1 > c0.1);
    assert!(after.last_inference >= before.last_inference && after.last_inference > 0);
    // The native API's queries count for the same model.
    native(client, &x, &t).await;
    let native_after = statistics(&mut oip, "lines-reward").await;
    assert_eq!(durations(&native_after)[0].0 - s1.0, 2, "a native Score and Gradient");

    for (name, version, code) in [
        ("no-such-model", "", Code::NotFound),
        ("lines-base", "", Code::FailedPrecondition),
        ("lines-reward", "2", Code::NotFound),
    ] {
        let err = oip
            .model_statistics(oip::ModelStatisticsRequest { name: name.into(), version: version.into() })
            .await
            .expect_err("statistics of what is not a servable model");
        assert_eq!(err.code(), code, "ModelStatistics({name:?}, {version:?}): {}", err.message());
    }
    let all = oip
        .model_statistics(oip::ModelStatisticsRequest::default())
        .await
        .expect("all statistics")
        .into_inner()
        .model_stats;
    let names: Vec<&str> = all.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["lines-reward"], "models with statistics, no diffusion model");

    // RepositoryIndex: the reward model READY; diffusion models are not listed.
    for ready in [false, true] {
        let index = oip
            .repository_index(oip::RepositoryIndexRequest { repository_name: String::new(), ready })
            .await
            .expect("index")
            .into_inner()
            .models;
        let index: Vec<_> = index.iter().map(|m| (m.name.as_str(), m.version.as_str(), m.state.as_str())).collect();
        assert_eq!(index, [("lines-reward", "1", "READY")], "ready = {ready}");
    }
    let err = oip
        .repository_index(oip::RepositoryIndexRequest { repository_name: "other".into(), ready: false })
        .await
        .expect_err("unknown repository");
    assert_eq!(err.code(), Code::NotFound);
}

/// Encodes and decodes messages without fields (the empty protobuf encoding), for calling a
/// method that has no generated client.
#[derive(Default)]
struct EmptyCodec;

impl tonic::codec::Codec for EmptyCodec {
    type Encode = ();
    type Decode = ();
    type Encoder = EmptyCodec;
    type Decoder = EmptyCodec;

    fn encoder(&mut self) -> Self::Encoder {
        EmptyCodec
    }

    fn decoder(&mut self) -> Self::Decoder {
        EmptyCodec
    }
}

impl tonic::codec::Encoder for EmptyCodec {
    type Item = ();
    type Error = tonic::Status;

    fn encode(&mut self, (): (), _dst: &mut tonic::codec::EncodeBuf<'_>) -> Result<(), tonic::Status> {
        Ok(())
    }
}

impl tonic::codec::Decoder for EmptyCodec {
    type Item = ();
    type Error = tonic::Status;

    fn decode(&mut self, _src: &mut tonic::codec::DecodeBuf<'_>) -> Result<Option<()>, tonic::Status> {
        Ok(Some(()))
    }
}

/// (c) Methods of the protocol that relreward leaves out, called on the raw channel.
async fn unimplemented_rpcs(server: &TestServer) {
    let channel = Channel::from_shared(server.endpoint()).expect("endpoint").connect().await.expect("connect");
    let methods = ["ModelStreamInfer", "RepositoryModelLoad", "SystemSharedMemoryStatus", "LogSettings"]
        .map(|m| format!("/inference.GRPCInferenceService/{m}"));
    // A service that does not exist at all is answered the same way.
    for method in methods.iter().map(String::as_str).chain(["/nope.v1.Service/Call"]) {
        let mut grpc = tonic::client::Grpc::new(channel.clone());
        grpc.ready().await.expect("ready");
        let path = tonic::codegen::http::uri::PathAndQuery::try_from(method).expect("path");
        let err = grpc.unary(tonic::Request::new(()), path, EmptyCodec).await.expect_err(method);
        assert_eq!(err.code(), Code::Unimplemented, "{method}: {err:?}");
        // Named, with where to find what is served (tonic's own answer has no message).
        assert!(err.message().contains(&format!("'{method}' is not a method")), "{method}: {err:?}");
        assert!(err.message().contains("reflection"), "{method}: {err:?}");
    }
}

/// (e) The OIP over HTTP/JSON: tritonclient.http, urllib and curl (oip_http_client.py).
async fn http_answers_as_grpc(server: &TestServer, client: &Client) {
    let url = server.oip_http_url();
    assert!(url.starts_with("http://"), "{url}");
    let out = std::process::Command::new(python())
        .arg(repo_root().join("tests/python/oip_http_client.py"))
        .args(["--http", &url, "--grpc", &server.addr.to_string()])
        .args(["--model", "lines-reward", "--diffusion-model", "lines-base"])
        .output()
        .expect("python");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "oip_http_client.py failed:\n{stderr}\nserver log:\n{}", server.log());
    let s: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON summary");

    for (key, want) in [
        ("server_live", true),
        ("server_ready", true),
        ("model_ready", true),
        ("model_ready_version_1", true),
        ("model_ready_version_2", false),
        ("unknown_model_ready", false),
        ("diffusion_model_ready", false),
        ("config_grpc_equal", true),
        ("curl_same", true),
        ("after_refusals_same", true),
    ] {
        assert_eq!(s[key], want, "{key}");
    }
    assert_eq!(
        s["server_metadata"],
        serde_json::json!({"name": "relreward", "version": env!("CARGO_PKG_VERSION"), "extensions": ["binary_tensor_data"]})
    );
    let (h, d) = (i64::from(HORIZON), DIM as i64);
    assert_eq!(
        s["model_metadata"],
        serde_json::json!({
            "name": "lines-reward", "versions": ["1"], "platform": "relreward_native",
            "inputs": [{"name": "x", "datatype": "FP32", "shape": [-1, h, d]}, {"name": "t", "datatype": "INT64", "shape": [-1]}],
            "outputs": [{"name": "reward", "datatype": "FP32", "shape": [-1]}, {"name": "grad_x", "datatype": "FP32", "shape": [-1, h, d]}],
        })
    );
    let config = &s["model_config"];
    assert_eq!(config["max_batch_size"], MAX_ITEMS);
    assert_eq!(
        config["input"][0],
        serde_json::json!({"name": "x", "data_type": "TYPE_FP32", "dims": [h, d], "optional": false})
    );
    assert_eq!(config["input"][1]["reshape"], serde_json::json!({"shape": []}));
    assert_eq!(config["dynamic_batching"]["default_queue_policy"]["timeout_action"], "REJECT");
    let index = s["repository_index"].as_array().expect("index");
    assert_eq!(index.len(), 1, "reward models only: {index:?}");
    assert_eq!(index[0]["name"], "lines-reward");
    assert_eq!(index[0]["state"], "READY");

    // gRPC's answer is the native API's (checked in (a)); here, against native directly too.
    let x: Vec<f32> = u32s(&s["x"]).into_iter().map(f32::from_bits).collect();
    let t: Vec<i64> = s["t"].as_array().expect("t").iter().map(|v| v.as_i64().expect("i64")).collect();
    let (_, gradient_rewards, gradient) = native(client, &x, &t).await;
    assert_eq!(u32s(&s["reward"]), bits(&gradient_rewards), "OIP reward vs native");
    assert_eq!(u32s(&s["grad_x"]), bits(&gradient), "OIP grad_x vs native Gradient");
    for form in ["binary", "json", "mixed", "unnamed", "gzip", "deflate"] {
        assert_eq!(s["same_as_grpc"][form], true, "{form} over HTTP differs from gRPC");
    }
    assert_eq!(
        s["json_response"],
        serde_json::json!({"model_name": "lines-reward", "model_version": "1", "id": "req-1"})
    );
    assert_eq!(s["json_output_keys"], serde_json::json!(["data", "datatype", "name", "shape"]));
    assert_eq!(s["curl_outputs"], serde_json::json!(["reward"]));

    // Refusals: tritonclient's exceptions (HTTP status, JSON error) ...
    let refusal = |k: &str| {
        let r = &s["refusals"][k];
        (r["status"].as_str().unwrap_or("none").to_owned(), r["message"].as_str().unwrap_or("").to_owned())
    };
    for (key, status, needle) in [
        ("unknown_model", "404", "no-such-model"),
        ("diffusion_model", "409", "diffusion"),
        ("fp64", "400", "x: datatype"),
        ("t_shape", "400", "t: expected shape"),
        ("metadata_unknown_version", "404", "version"),
    ] {
        let (got, message) = refusal(key);
        assert_eq!(got, status, "{key}: {message}");
        assert!(message.contains(needle), "{key}: {message}");
    }
    // ... and plain HTTP's.
    for (key, status, needle) in [
        ("malformed_json", 400, "request body: not a KServe v2 inference request"),
        ("unknown_field", 400, "unknown field `outptus`"),
        ("short_data", 400, "x: data holds 1 values"),
        ("beyond_f32", 400, "x: data[0] (1e39) is outside float32's range"),
        ("unknown_route", 404, "no endpoint"),
        ("wrong_method", 405, "takes POST"),
        ("unsupported_encoding", 415, "Content-Encoding"),
        ("bad_gzip", 400, "cannot be decompressed"),
    ] {
        let r = &s["raw"][key];
        assert_eq!(r[0], status, "{key}: {r}");
        let message = r[1]["error"].as_str().unwrap_or_else(|| panic!("{key}: no JSON error: {r}"));
        assert!(message.contains(needle), "{key}: {message}");
    }
    assert_eq!(s["raw"]["index_ready"][0], 200);
    assert_eq!(s["raw"]["live"][0], 200);

    // Requests are counted by route and status in the Prometheus metrics.
    let scrape = std::process::Command::new("curl")
        .args(["-sS", &format!("http://{}/metrics", server.metrics_addr())])
        .output()
        .expect("curl");
    let text = String::from_utf8_lossy(&scrape.stdout);
    let count = |route: &str, status: u16| {
        let prefix = format!("relreward_oip_http_requests_total{{route=\"{route}\",status=\"{status}\"}} ");
        text.lines().find_map(|l| l.strip_prefix(&prefix)).map_or(0, |v| v.parse::<u64>().expect("count"))
    };
    assert!(count("infer", 200) >= 8, "{text}");
    assert_eq!(count("unknown", 404), 1, "{text}");
    assert_eq!(count("infer", 405), 1, "{text}");

    // The HTTP inferences count in the model's statistics like gRPC's.
    let stats = &s["statistics"]["model_stats"][0];
    assert_eq!(stats["name"], "lines-reward");
    assert!(stats["inference_stats"]["success"]["count"].as_u64().expect("count") >= 8, "{stats}");
}

#[tokio::test(flavor = "multi_thread")]
async fn open_inference_protocol_serves_rewards_like_the_native_api() {
    let (server, client) = setup().await;
    let mut oip = inference(&server).await;
    assert!(oip.server_live(oip::ServerLiveRequest {}).await.expect("live").into_inner().live);
    assert!(oip.server_ready(oip::ServerReadyRequest {}).await.expect("ready").into_inner().ready);
    let meta = oip.server_metadata(oip::ServerMetadataRequest {}).await.expect("server metadata").into_inner();
    assert_eq!((meta.name.as_str(), meta.version.as_str()), ("relreward", env!("CARGO_PKG_VERSION")));
    assert!(meta.extensions.is_empty());

    tritonclient_matches_native(&server, &client).await;
    rust_client_and_bad_inputs(&server, &client).await;
    config_statistics_and_index(&server, &client).await;
    unimplemented_rpcs(&server).await;
    // Last: its inferences add to the statistics counted exactly above.
    http_answers_as_grpc(&server, &client).await;

    // Health knows the service by its name.
    let mut health = tonic_health::pb::health_client::HealthClient::new(client.channel());
    let status = health
        .check(tonic_health::pb::HealthCheckRequest { service: "inference.GRPCInferenceService".into() })
        .await
        .expect("health")
        .into_inner()
        .status();
    assert_eq!(status, tonic_health::pb::health_check_response::ServingStatus::Serving);
}
