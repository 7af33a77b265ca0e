//! The Prometheus endpoint end to end: calls made with the real client show up in a scrape of
//! the real server binary, by method and status code.

use std::net::SocketAddr;
use std::process::{Command, Stdio};

use relreward_tests::{TestServer, bin};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic::Code;

/// One HTTP/1.1 exchange on a fresh connection: (status line, headers, body).
async fn http(addr: SocketAddr, request: &str) -> (String, String, String) {
    let mut stream = tokio::net::TcpStream::connect(addr).await.expect("connect to the metrics endpoint");
    stream.write_all(request.as_bytes()).await.expect("send");
    let mut raw = String::new();
    stream.read_to_string(&mut raw).await.expect("read");
    let (head, body) = raw.split_once("\r\n\r\n").unwrap_or_else(|| panic!("no header end in {raw:?}"));
    let (status, headers) = head.split_once("\r\n").unwrap_or((head, ""));
    (status.to_owned(), headers.to_ascii_lowercase(), body.to_owned())
}

async fn scrape(addr: SocketAddr) -> String {
    let (status, headers, body) = http(addr, "GET /metrics HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n").await;
    assert_eq!(status, "HTTP/1.1 200 OK");
    assert!(headers.contains("content-type: text/plain; version=0.0.4"), "{headers}");
    body
}

/// The value of the sample line `name{labels}` (labels in Prometheus' sorted order).
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|l| l.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
}

fn calls(text: &str, method: &str, code: &str) -> Option<f64> {
    sample(text, &format!("relreward_grpc_requests_total{{code=\"{code}\",method=\"{method}\"}}"))
}

#[tokio::test(flavor = "multi_thread")]
async fn calls_are_counted_by_method_and_code() {
    let server = TestServer::start_with_env(&[("RELREWARD__METRICS__LISTEN", "127.0.0.1:0")]);
    let metrics = server.metrics_addr();
    let client = server.client().await;

    for _ in 0..3 {
        client.health().await.expect("health");
    }
    assert!(client.list_datasets().await.expect("list").is_empty());
    for _ in 0..2 {
        let missing = client.get_dataset("no-such-dataset").await.expect_err("missing");
        assert!(
            matches!(&missing, relreward_client::ClientError::Status(s) if s.code() == Code::NotFound),
            "{missing}"
        );
    }

    let text = scrape(metrics).await;
    assert_eq!(calls(&text, "grpc.health.v1.Health/Check", "OK"), Some(3.0), "{text}");
    assert_eq!(calls(&text, "relreward.v1.DatasetService/ListDatasets", "OK"), Some(1.0), "{text}");
    assert_eq!(calls(&text, "relreward.v1.DatasetService/GetDataset", "NOT_FOUND"), Some(2.0), "{text}");
    assert_eq!(calls(&text, "relreward.v1.DatasetService/GetDataset", "OK"), None, "{text}");
    assert!(text.contains("# TYPE relreward_grpc_request_seconds histogram"), "{text}");
    assert_eq!(
        sample(&text, "relreward_grpc_request_seconds_count{method=\"relreward.v1.DatasetService/GetDataset\"}"),
        Some(2.0),
        "{text}"
    );
    assert_eq!(
        sample(
            &text,
            "relreward_grpc_request_seconds_bucket{method=\"relreward.v1.DatasetService/GetDataset\",le=\"+Inf\"}"
        ),
        Some(2.0),
        "{text}"
    );
    // Scrape-time gauges: every job state (no jobs yet) and the models in memory.
    for state in ["pending", "running", "succeeded", "failed", "cancelled"] {
        assert_eq!(sample(&text, &format!("relreward_jobs{{state=\"{state}\"}}")), Some(0.0), "{state}: {text}");
    }
    assert_eq!(sample(&text, "relreward_loaded_models"), Some(0.0), "{text}");

    // A later scrape sees later calls.
    client.health().await.expect("health");
    let text = scrape(metrics).await;
    assert_eq!(calls(&text, "grpc.health.v1.Health/Check", "OK"), Some(4.0), "{text}");
}

#[tokio::test(flavor = "multi_thread")]
async fn other_paths_are_not_found_and_scrapes_may_overlap() {
    let server = TestServer::start_with_env(&[("RELREWARD__METRICS__LISTEN", "127.0.0.1:0")]);
    let metrics = server.metrics_addr();
    let (status, _, _) = http(metrics, "GET / HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n").await;
    assert_eq!(status, "HTTP/1.1 404 Not Found");
    let post = "POST /metrics/x HTTP/1.1\r\nHost: test\r\nContent-Length: 4\r\nConnection: close\r\n\r\nbody";
    let (status, _, _) = http(metrics, post).await;
    assert_eq!(status, "HTTP/1.1 404 Not Found");
    let scrapes = futures::future::join_all((0..8).map(|_| scrape(metrics))).await;
    assert!(scrapes.iter().all(|t| t.contains("relreward_loaded_models")));
    // The gRPC side is unaffected.
    server.client().await.health().await.expect("health");
}

#[test]
fn a_taken_metrics_port_fails_the_start_naming_the_key() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let addr = taken.local_addr().expect("addr").to_string();
    let data = tempfile::tempdir().expect("tmp");
    let out = Command::new(bin("relreward-server"))
        .args(["--listen", "127.0.0.1:0", "--data-dir"])
        .arg(data.path())
        .env("RELREWARD__METRICS__LISTEN", &addr)
        .stdin(Stdio::null())
        .output()
        .expect("run relreward-server");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("metrics.listen") && stderr.contains(&addr), "{stderr}");
}
