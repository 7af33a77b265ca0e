//! The transport, end to end: compression on every service (tonic clients, and grpcio and
//! tritonclient through tests/python/transport_probe.py), HTTP/2 flow control with a stalled
//! GradientStream on a shared connection, oversized request metadata refused on its call alone,
//! reflection's in-stream errors (v1 and v1alpha), and the shutdown drain (health NOT_SERVING while still serving, then the graceful close).

use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use relreward_client::pb;
use relreward_client::tensor::encode_f32;
use relreward_proto::inference::{self as oip, grpc_inference_service_client::GrpcInferenceServiceClient};
use relreward_proto::v1::{
    dataset_service_client::DatasetServiceClient, job_service_client::JobServiceClient,
    model_service_client::ModelServiceClient, reward_service_client::RewardServiceClient,
};
use relreward_tests::{TestServer, python, repo_root, rss_bytes, train_tiny_reward};
use serde_json::Value;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::codec::CompressionEncoding::{Deflate, Gzip};
use tonic::transport::{Channel, Endpoint};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

async fn channel(server: &TestServer) -> Channel {
    for _ in 0..100 {
        if let Ok(c) = Endpoint::from_shared(server.endpoint()).expect("endpoint").connect().await {
            return c;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("cannot connect to {}; log:\n{}", server.endpoint(), server.log())
}

/// The `grpc-encoding` a response came with ("identity" when none).
fn encoding_of<T>(response: &tonic::Response<T>) -> String {
    response.metadata().get("grpc-encoding").and_then(|v| v.to_str().ok()).unwrap_or("identity").to_owned()
}

/// tests/python/transport_probe.py's JSON answer.
fn probe(args: &[&str]) -> Value {
    let out = Command::new(python())
        .arg(repo_root().join("tests/python/transport_probe.py"))
        .args(args)
        .output()
        .expect("python");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "transport_probe.py {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("not JSON ({e}): {stdout}"))
}

/// The float32 values of a tensor (empty when absent).
fn floats(t: Option<&pb::Tensor>) -> Vec<f32> {
    t.map(|t| t.data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
        .unwrap_or_default()
}

fn x_values(n: usize) -> Vec<f32> {
    (0..n).map(|i| ((i * 37) % 101) as f32 / 50.0 - 1.0).collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn compressed_calls_are_answered_on_every_service() {
    let server = TestServer::start();
    let dir = tempfile::tempdir().expect("tempdir");
    let m = train_tiny_reward(&server, dir.path());
    let channel = channel(&server).await;
    let (h, d) = (m.horizon, m.transition_dim);
    let x = encode_f32(&[3, h as u64, d as u64], &x_values(3 * h * d));
    let gradient = pb::GradientRequest { model: m.reward.clone(), x: Some(x), ..Default::default() };

    // relreward.v1.RewardService: the same gradient, whatever the compression, and the
    // response compressed with the request's algorithm.
    let plain = RewardServiceClient::new(channel.clone()).gradient(gradient.clone()).await.expect("plain gradient");
    assert_eq!(encoding_of(&plain), "identity");
    for encoding in [Gzip, Deflate] {
        let mut rewards =
            RewardServiceClient::new(channel.clone()).send_compressed(encoding).accept_compressed(encoding);
        let response = rewards.gradient(gradient.clone()).await.unwrap_or_else(|s| panic!("{encoding:?}: {s:?}"));
        assert_eq!(encoding_of(&response), encoding.to_string(), "response compressed like the request");
        assert_eq!(response.get_ref(), plain.get_ref(), "{encoding:?}: same answer as uncompressed");

        // GradientStream: every request answered, in-stream.
        let requests: Vec<_> = (1..=3).map(|id| pb::GradientRequest { request_id: id, ..gradient.clone() }).collect();
        let mut stream =
            rewards.gradient_stream(tokio_stream::iter(requests)).await.expect("gradient stream").into_inner();
        let mut ids = Vec::new();
        while let Some(r) = stream.message().await.expect("stream message") {
            assert!(r.error.is_none(), "{r:?}");
            // Batched with its neighbours, so equal up to float rounding.
            let (got, want) = (floats(r.gradient.as_ref()), floats(plain.get_ref().gradient.as_ref()));
            assert_eq!(got.len(), want.len());
            assert!(got.iter().zip(&want).all(|(a, b)| (a - b).abs() <= 1e-6 + 1e-4 * b.abs()), "{got:?} vs {want:?}");
            ids.push(r.request_id);
        }
        ids.sort_unstable();
        assert_eq!(ids, [1, 2, 3]);
    }
    // A client that accepts gzip but sends plain requests (as grpcio does on every call) gets
    // plain responses under the default server.response_compression = "request".
    let response = RewardServiceClient::new(channel.clone())
        .accept_compressed(Gzip)
        .accept_compressed(Deflate)
        .gradient(gradient.clone())
        .await
        .expect("accept-only gradient");
    assert_eq!(encoding_of(&response), "identity");

    // A compressed bomb: 20 MiB of zeros squeezed into a few kB is still over
    // server.max_request_bytes (16 MiB) once decompressed.
    let zeros = encode_f32(&[5 << 18, 1, 4], &vec![0.0; 5 << 20]);
    let bomb = pb::GradientRequest { model: m.reward.clone(), x: Some(zeros), ..Default::default() };
    let status = RewardServiceClient::new(channel.clone())
        .send_compressed(Gzip)
        .gradient(bomb)
        .await
        .expect_err("decompressed beyond the limit");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");

    // DatasetService, ModelService, JobService.
    let mut datasets = DatasetServiceClient::new(channel.clone()).send_compressed(Gzip).accept_compressed(Gzip);
    let list = datasets.list_datasets(pb::ListDatasetsRequest::default()).await.expect("list datasets");
    assert_eq!(encoding_of(&list), "gzip");
    assert!(list.get_ref().datasets.iter().any(|d| d.name == m.dataset), "{:?}", list.get_ref());
    let got = datasets
        .get_dataset(pb::GetDatasetRequest { name: m.dataset.clone(), ..Default::default() })
        .await
        .expect("get dataset");
    assert_eq!(got.get_ref().name, m.dataset);
    let mut models = ModelServiceClient::new(channel.clone()).send_compressed(Deflate).accept_compressed(Deflate);
    let list = models.list_models(pb::ListModelsRequest::default()).await.expect("list models");
    assert_eq!(encoding_of(&list), "deflate");
    assert_eq!(list.get_ref().models.len(), 3, "{:?}", list.get_ref());
    let mut jobs = JobServiceClient::new(channel.clone()).send_compressed(Gzip).accept_compressed(Gzip);
    let list = jobs.list_jobs(pb::ListJobsRequest::default()).await.expect("list jobs");
    assert_eq!(list.get_ref().jobs.len(), 3, "{:?}", list.get_ref());

    // The Open Inference Protocol.
    let mut inference = GrpcInferenceServiceClient::new(channel.clone()).send_compressed(Gzip).accept_compressed(Gzip);
    let live = inference.server_live(oip::ServerLiveRequest {}).await.expect("server live");
    assert!(live.get_ref().live);
    assert_eq!(encoding_of(&live), "gzip");
    let meta = inference
        .model_metadata(oip::ModelMetadataRequest { name: m.reward.clone(), version: String::new() })
        .await
        .expect("model metadata");
    assert_eq!(meta.get_ref().name, m.reward);

    // Health.
    let mut health = HealthClient::new(channel.clone()).send_compressed(Gzip).accept_compressed(Gzip);
    let answer = health.check(HealthCheckRequest { service: String::new() }).await.expect("health");
    assert_eq!(answer.get_ref().status(), ServingStatus::Serving);
    assert_eq!(encoding_of(&answer), "gzip");

    // The client library, unchanged: no compression either way.
    let client = server.client().await;
    assert!(client.list_datasets().await.expect("client library").iter().any(|d| d.name == m.dataset));

    // grpcio channels created with compression, and tritonclient's compression_algorithm.
    let report = probe(&["compression", "--url", &server.addr.to_string()]);
    for name in ["gzip", "deflate"] {
        let r = &report[name];
        assert_eq!(r["health"], 1, "{name}: Health/Check SERVING: {r}");
        assert_eq!(r["health_reward_service"], 1, "{name}: {r}");
        assert_eq!(r["server_live"], true, "{name}: ServerLive: {r}");
        // The request was decoded: the model's absence is the answer, not the compression.
        assert_eq!(r["infer"], "StatusCode.NOT_FOUND", "{name}: tritonclient infer: {r}");
    }
}

/// `server.response_compression`: "accepted" compresses whenever the client accepts it, "off"
/// never (compressed requests are still accepted).
#[tokio::test(flavor = "multi_thread")]
async fn response_compression_follows_its_setting() {
    let check = HealthCheckRequest::default();
    let accepted = TestServer::start_with_env(&[("RELREWARD__SERVER__RESPONSE_COMPRESSION", "accepted")]);
    let ch = channel(&accepted).await;
    let answer = HealthClient::new(ch.clone()).accept_compressed(Gzip).check(check.clone()).await.expect("health");
    assert_eq!(encoding_of(&answer), "gzip", "accepted: compressed for a client that only accepts gzip");
    let answer = HealthClient::new(ch).check(check.clone()).await.expect("health");
    assert_eq!(encoding_of(&answer), "identity", "accepted: plain for a client that accepts nothing");

    let off = TestServer::start_with_env(&[("RELREWARD__SERVER__RESPONSE_COMPRESSION", "off")]);
    let ch = channel(&off).await;
    let mut datasets = DatasetServiceClient::new(ch).send_compressed(Deflate).accept_compressed(Deflate);
    let list = datasets.list_datasets(pb::ListDatasetsRequest::default()).await.expect("compressed request accepted");
    assert_eq!(encoding_of(&list), "identity", "off: never compressed");
}

#[tokio::test(flavor = "multi_thread")]
async fn reflection_answers_failed_lookups_in_stream() {
    let server = TestServer::start();
    let url = server.addr.to_string();
    for compression in ["none", "gzip"] {
        let report = probe(&["reflection", "--url", &url, "--compression", compression]);
        for version in ["v1", "v1alpha"] {
            let r = &report[version];
            let answers = r["answers"].as_array().unwrap_or_else(|| panic!("{version}: {r}"));
            assert_eq!(answers.len(), 8, "{version} ({compression}): every request answered on one stream: {r}");
            assert_eq!(r["ended"], "OK", "{version}: {r}");
            let not_found = |i: usize, what: &str| {
                let a = &answers[i];
                assert_eq!(a["kind"], "error_response", "{version}: {what}: {a}");
                assert_eq!(a["error_code"], 5, "{version}: {what}: NOT_FOUND: {a}");
                assert!(!a["error_message"].as_str().unwrap_or_default().is_empty(), "{a}");
                assert_eq!(a["valid_host"], "probe", "{a}");
            };
            not_found(0, "unknown symbol");
            assert_eq!(answers[0]["original"], "file_containing_symbol", "the request echoed");
            for i in [1, 7] {
                let services = answers[i]["services"].as_array().unwrap_or_else(|| panic!("{}", answers[i]));
                for name in [
                    "relreward.v1.RewardService",
                    "relreward.v1.DatasetService",
                    "inference.GRPCInferenceService",
                    "grpc.health.v1.Health",
                    "grpc.reflection.v1.ServerReflection",
                    "grpc.reflection.v1alpha.ServerReflection",
                ] {
                    assert!(services.iter().any(|s| s == name), "{version}: list_services lacks {name}: {services:?}");
                }
            }
            let files = &answers[2]["files"];
            assert_eq!(files[0]["package"], "relreward.v1", "{version}: {}", answers[2]);
            assert!(files[0]["services"].as_array().is_some_and(|s| s.iter().any(|s| s == "RewardService")), "{files}");
            // With the file it imports, so that the answer alone builds the descriptors.
            assert!(
                files.as_array().is_some_and(|f| f.iter().any(|f| f["name"] == "relreward/v1/tensor.proto")),
                "{files}"
            );
            not_found(3, "unknown file");
            not_found(4, "extension");
            not_found(5, "extension numbers of an unknown type");
            assert_eq!(answers[6]["kind"], "all_extension_numbers_response", "{}", answers[6]);
            assert_eq!(answers[6]["base_type_name"], "relreward.v1.GradientRequest");
        }
    }
}

/// A GradientStream that never reads its responses, on the one connection a tonic Channel
/// holds: once its responses back up, the server stops reading its requests (backpressure),
/// and their unread data must not block the connection's other calls.
#[tokio::test(flavor = "multi_thread")]
async fn a_stalled_gradient_stream_does_not_stall_its_connection() {
    let server = TestServer::start();
    let pid = server.pid().expect("pid");
    // The client's own windows: a large connection window, so the client is never the
    // bottleneck for the other calls' responses; a small stream window, so the stalled
    // stream's (small, error) responses back up after a few hundred.
    let channel = Endpoint::from_shared(server.endpoint())
        .expect("endpoint")
        .initial_connection_window_size(64 << 20)
        .initial_stream_window_size(64 << 10)
        .connect()
        .await
        .expect("connect");
    let mut health = HealthClient::new(channel.clone());
    health.check(HealthCheckRequest::default()).await.expect("health before");
    let rss_before = rss_bytes(pid).expect("rss");

    // 64 KiB requests to a model that does not exist: each is answered at once with an
    // in-stream NOT_FOUND, and nobody reads the answers.
    const ITEM_FLOATS: usize = 16 << 10;
    const MAX_REQUESTS: usize = 6000;
    let (tx, rx) = tokio::sync::mpsc::channel::<pb::GradientRequest>(1);
    let taken = Arc::new(AtomicUsize::new(0));
    let producer = {
        let taken = Arc::clone(&taken);
        tokio::spawn(async move {
            let x = encode_f32(&[1, 4096, 4], &x_values(ITEM_FLOATS));
            for id in 0..MAX_REQUESTS as u64 {
                let request = pb::GradientRequest {
                    request_id: id,
                    model: "no-such-model".into(),
                    x: Some(x.clone()),
                    ..Default::default()
                };
                if tx.send(request).await.is_err() {
                    return;
                }
                taken.fetch_add(1, Ordering::Relaxed);
            }
        })
    };
    let stalled = RewardServiceClient::new(channel.clone())
        .max_encoding_message_size(usize::MAX)
        .gradient_stream(ReceiverStream::new(rx))
        .await
        .expect("gradient stream opened");
    // Stalled: the client stops taking requests because the server stopped reading them.
    let started = Instant::now();
    let taken_at_stall = until_stalled(&taken, MAX_REQUESTS).await;
    let rss_stalled = rss_bytes(pid).expect("rss");
    eprintln!(
        "stalled after {taken_at_stall} requests ({} MiB sent) in {:.1} s",
        (taken_at_stall * ITEM_FLOATS * 4) >> 20,
        started.elapsed().as_secs_f64()
    );

    // The same connection still serves its other calls: health, a unary call to each of two
    // services.
    let within = Duration::from_secs(3);
    let answer = tokio::time::timeout(within, health.check(HealthCheckRequest::default()))
        .await
        .expect("Health/Check not answered within 3 s on the stalled stream's connection")
        .expect("health");
    assert_eq!(answer.get_ref().status(), ServingStatus::Serving);
    let mut rewards = RewardServiceClient::new(channel.clone());
    let unary = pb::GradientRequest {
        model: "no-such-model".into(),
        x: Some(encode_f32(&[1, 8, 4], &x_values(32))),
        ..Default::default()
    };
    let status = tokio::time::timeout(within, rewards.gradient(unary))
        .await
        .expect("Gradient not answered within 3 s")
        .expect_err("no such model");
    assert_eq!(status.code(), Code::NotFound, "{status:?}");
    tokio::time::timeout(
        within,
        DatasetServiceClient::new(channel.clone()).list_datasets(pb::ListDatasetsRequest::default()),
    )
    .await
    .expect("ListDatasets not answered within 3 s")
    .expect("list datasets");

    // Memory stays bounded while the stream stays stalled: unread data is capped by the
    // stream window, and the server holds what it has not sent.
    let taken_at_stall = until_stalled(&taken, MAX_REQUESTS).await.max(taken_at_stall);
    let mut rss_max = rss_stalled;
    for _ in 0..10 {
        tokio::time::sleep(Duration::from_millis(200)).await;
        rss_max = rss_max.max(rss_bytes(pid).expect("rss"));
    }
    assert_eq!(taken.load(Ordering::Relaxed), taken_at_stall, "still stalled");
    eprintln!(
        "server RSS: {} MiB before, {} MiB at the stall, at most {} MiB while stalled",
        rss_before >> 20,
        rss_stalled >> 20,
        rss_max >> 20
    );
    assert!(rss_max < rss_before + (256 << 20), "RSS grew from {rss_before} to {rss_max} bytes");
    assert!(rss_max < rss_stalled + (16 << 20), "RSS kept growing while stalled: {rss_stalled} -> {rss_max}");
    drop(stalled);
    producer.abort();
}

/// Request metadata over `server.max_metadata_bytes` (64 KiB) is refused on its call alone,
/// RESOURCE_EXHAUSTED naming the setting, while a GradientStream open on the same connection
/// goes on answering; metadata under it (32 KiB, over hyper's 16 KiB default) is served. Before
/// the limit, 16-64 KiB got HTTP 431 (UNKNOWN at the client) and about 100 KB a GOAWAY that
/// ended every call on the connection.
#[tokio::test(flavor = "multi_thread")]
async fn oversized_metadata_is_refused_on_its_call_alone() {
    let server = TestServer::start();
    let channel = channel(&server).await;
    let mut rewards = RewardServiceClient::new(channel.clone());
    let (tx, rx) = tokio::sync::mpsc::channel::<pb::GradientRequest>(4);
    let mut stream = rewards.gradient_stream(ReceiverStream::new(rx)).await.expect("stream opened").into_inner();
    answered_in_stream(&tx, &mut stream, 1).await;

    let with_metadata = |bytes: usize| {
        let mut call = tonic::Request::new(pb::ListDatasetsRequest::default());
        let pad = tonic::metadata::MetadataValue::try_from("x".repeat(bytes)).expect("ascii");
        call.metadata_mut().insert("x-pad", pad);
        call
    };
    let mut datasets = DatasetServiceClient::new(channel.clone());
    datasets.list_datasets(with_metadata(32 << 10)).await.expect("32 KiB of metadata is served");
    for bytes in [100_000, 200_000, 900_000] {
        let status = datasets.list_datasets(with_metadata(bytes)).await.expect_err("over the limit");
        assert_eq!(status.code(), Code::ResourceExhausted, "{bytes} bytes: {status:?}");
        assert!(status.message().contains("server.max_metadata_bytes = 65536"), "{}", status.message());
        // The connection and its open stream go on.
        answered_in_stream(&tx, &mut stream, 10 + bytes as u64).await;
    }
    datasets.list_datasets(pb::ListDatasetsRequest::default()).await.expect("the connection serves on");
    let mut health = HealthClient::new(channel);
    health.check(HealthCheckRequest::default()).await.expect("health on the same connection");
}

/// Sends request `id` (for a model that does not exist) on an open GradientStream and checks
/// that it is answered, in-stream.
async fn answered_in_stream(
    tx: &tokio::sync::mpsc::Sender<pb::GradientRequest>,
    stream: &mut tonic::Streaming<pb::GradientResponse>,
    id: u64,
) {
    let request = pb::GradientRequest {
        request_id: id,
        model: "no-such-model".into(),
        x: Some(encode_f32(&[1, 8, 4], &x_values(32))),
        ..Default::default()
    };
    tx.send(request).await.expect("stream open");
    let answer = stream.message().await.expect("stream alive").expect("an answer");
    assert_eq!(answer.request_id, id);
    assert!(answer.error.is_some(), "no such model, answered in-stream: {answer:?}");
}

/// Waits until `taken` has not moved for 2 s; returns it.
async fn until_stalled(taken: &AtomicUsize, max: usize) -> usize {
    let started = Instant::now();
    let mut last = (taken.load(Ordering::Relaxed), Instant::now());
    loop {
        tokio::time::sleep(Duration::from_millis(100)).await;
        let now = taken.load(Ordering::Relaxed);
        if now != last.0 {
            last = (now, Instant::now());
        } else if last.1.elapsed() > Duration::from_secs(2) {
            return now;
        }
        assert!(now < max, "{now} requests taken and the stream never stalled");
        assert!(started.elapsed() < Duration::from_secs(120), "no stall in 120 s ({now} requests)");
    }
}

/// One Health/Check every ~20 ms on one connection; the answers, with when they came.
async fn poll_health(
    channel: Channel,
    services: [&'static str; 2],
    until: Duration,
) -> Vec<(Duration, Result<ServingStatus, Code>)> {
    let mut health = HealthClient::new(channel);
    let start = Instant::now();
    let mut out = Vec::new();
    let mut failures = 0;
    for i in 0.. {
        let service = services[i % 2].to_owned();
        let answer = tokio::time::timeout(Duration::from_secs(1), health.check(HealthCheckRequest { service })).await;
        let answer = match answer {
            Ok(Ok(r)) => Ok(r.get_ref().status()),
            Ok(Err(s)) => Err(s.code()),
            Err(_) => Err(Code::DeadlineExceeded),
        };
        failures = if answer.is_err() { failures + 1 } else { 0 };
        out.push((start.elapsed(), answer));
        if failures >= 5 || start.elapsed() > until {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    out
}

#[tokio::test(flavor = "multi_thread")]
async fn shutdown_reports_not_serving_through_the_drain_then_closes() {
    const DRAIN: Duration = Duration::from_secs(2);
    let mut server = TestServer::start_with_env(&[
        ("RELREWARD__SERVER__SHUTDOWN_DRAIN_SECS", "2"),
        ("RELREWARD__OIP_HTTP__LISTEN", "127.0.0.1:0"),
    ]);
    let channel = channel(&server).await;
    let endpoint = server.endpoint();
    // The OIP over HTTP's readiness follows health: 200, then 503 through the drain.
    let ready_url = format!("{}/v2/health/ready", server.oip_http_url());
    let http_ready = move || {
        let out = std::process::Command::new("curl")
            .args(["-s", "-o", "/dev/null", "-w", "%{http_code}", "--max-time", "5", &ready_url])
            .output()
            .expect("curl");
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    assert_eq!(http_ready(), "200");
    let poller = tokio::spawn(poll_health(channel, ["", "relreward.v1.RewardService"], Duration::from_secs(30)));
    tokio::time::sleep(Duration::from_millis(300)).await;

    let signalled = Instant::now();
    let stopped = tokio::task::spawn_blocking(move || {
        let clean = server.terminate();
        (clean, server)
    });
    // Mid-drain, a new connection and a new call are still served.
    tokio::time::sleep(DRAIN / 2).await;
    let fresh = Endpoint::from_shared(endpoint).expect("endpoint").connect().await.expect("new connection mid-drain");
    DatasetServiceClient::new(fresh)
        .list_datasets(pb::ListDatasetsRequest::default())
        .await
        .expect("a new call mid-drain is answered");
    assert_eq!(tokio::task::spawn_blocking(http_ready.clone()).await.expect("curl"), "503", "HTTP readiness mid-drain");

    let (clean, server) = stopped.await.expect("terminate");
    let took = signalled.elapsed();
    let answers = poller.await.expect("poller");
    assert!(clean, "graceful shutdown exits 0; log:\n{}", server.log());
    // Nothing in flight: the drain, then a prompt close (shutdown_grace_secs is 10 s).
    assert!(
        took >= DRAIN - Duration::from_millis(200) && took < DRAIN + Duration::from_secs(5),
        "exited after {took:?}"
    );

    let serving = answers.iter().take_while(|(_, a)| *a == Ok(ServingStatus::Serving)).count();
    let not_serving: Vec<_> =
        answers[serving..].iter().take_while(|(_, a)| *a == Ok(ServingStatus::NotServing)).collect();
    let rest = &answers[serving + not_serving.len()..];
    let summary = format!(
        "{serving} SERVING, {} NOT_SERVING, then {:?}",
        not_serving.len(),
        rest.iter().map(|(t, a)| (t.as_millis(), *a)).take(5).collect::<Vec<_>>()
    );
    assert!(serving > 0, "{summary}");
    // About DRAIN / 20 ms answers; a slow machine gets fewer.
    assert!(not_serving.len() >= 10, "NOT_SERVING answers before the connection went away: {summary}");
    let span =
        not_serving.last().map(|l| l.0).unwrap_or_default() - not_serving.first().map(|f| f.0).unwrap_or_default();
    assert!(span >= DRAIN - Duration::from_millis(500), "NOT_SERVING for only {span:?}: {summary}");
    assert!(!rest.is_empty() && rest.iter().all(|(_, a)| a.is_err()), "after the drain the connection goes: {summary}");
    eprintln!("{summary}; exited {took:?} after SIGTERM");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_second_signal_cuts_the_drain_short() {
    let mut server = TestServer::start_with_env(&[("RELREWARD__SERVER__SHUTDOWN_DRAIN_SECS", "60")]);
    let mut health = HealthClient::new(channel(&server).await);
    let pid = server.pid().expect("pid").to_string();
    assert!(Command::new("kill").args(["-TERM", &pid]).status().expect("kill").success());
    let mut status = ServingStatus::Serving;
    for _ in 0..100 {
        status = health.check(HealthCheckRequest::default()).await.expect("served during the drain").get_ref().status();
        if status == ServingStatus::NotServing {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(status, ServingStatus::NotServing);
    // The harness's terminate is the second SIGTERM; it waits up to 15 s, far below the drain.
    let started = Instant::now();
    assert!(server.terminate(), "exits 0 on the second signal; log:\n{}", server.log());
    assert!(started.elapsed() < Duration::from_secs(5), "took {:?}", started.elapsed());
}
