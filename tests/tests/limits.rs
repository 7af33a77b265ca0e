//! Server-wide limits, end to end: connections (`server.max_connections`), calls per connection
//! (`server.max_concurrent_streams`) and deadlines (`serving.default_deadline_ms`). The limits
//! whose test also checks what is left on disk (the disk budget, the per-upload quota, an
//! upload whose deadline passes) are in server/tests/stored_files.rs.

use std::time::Duration;

use relreward_client::tensor::encode_f32;
use relreward_client::{Client, pb};
use relreward_tests::{TestServer, status_code, train_tiny_reward};
use tonic::Code;

/// Whether a fresh connection gets a ListDatasets answered. The raw RPC, one attempt: the
/// client's own retry of reads would hide how soon the server refuses.
async fn served(server: &TestServer) -> Result<Client, String> {
    let client = Client::connect(&server.endpoint()).await.map_err(|e| e.to_string())?;
    let mut datasets = client.datasets();
    let list = datasets.list_datasets(pb::ListDatasetsRequest::default());
    match tokio::time::timeout(Duration::from_secs(5), list).await {
        Ok(Ok(_)) => Ok(client),
        Ok(Err(e)) => Err(relreward_client::ClientError::from(e).to_string()),
        Err(_) => Err("no answer in 5 s".into()),
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn connections_beyond_the_maximum_are_refused_until_one_closes() {
    let server = TestServer::start_with_env(&[("RELREWARD__SERVER__MAX_CONNECTIONS", "2")]);
    let first = served(&server).await.expect("first connection");
    let second = served(&server).await.expect("second connection");
    let started = std::time::Instant::now();
    let err = served(&server).await.err().expect("a third connection must be refused");
    // Refused at once (closed by the server), not left to time out.
    assert!(started.elapsed() < Duration::from_secs(4), "refusal took {:?}: {err}", started.elapsed());
    // The connections admitted keep working.
    first.list_datasets().await.expect("first still served");
    second.list_datasets().await.expect("second still served");

    drop(first);
    let mut third = None;
    for _ in 0..100 {
        if let Ok(c) = served(&server).await {
            third = Some(c);
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(third.is_some(), "the slot of a closed connection never came back");
    assert!(server.log().contains("server.max_connections"), "the refusal is logged with its key");
}

#[tokio::test(flavor = "multi_thread")]
async fn calls_beyond_the_stream_limit_wait_for_a_free_stream() {
    let server = TestServer::start_with_env(&[("RELREWARD__SERVER__MAX_CONCURRENT_STREAMS", "1")]);
    let client = server.client().await;
    // An open GradientStream holds the connection's one stream.
    let stream = client.gradient_stream().await.expect("open stream");
    let waiting = tokio::time::timeout(Duration::from_millis(700), client.list_datasets()).await;
    assert!(waiting.is_err(), "a second call on the connection was not held back: {waiting:?}");
    // Per connection: another connection is served meanwhile.
    let other = Client::connect(&server.endpoint()).await.expect("connect");
    other.list_datasets().await.expect("another connection has its own streams");
    // Ending the stream frees the slot.
    let mut responses = stream.close();
    while responses.message().await.expect("stream ends cleanly").is_some() {}
    tokio::time::timeout(Duration::from_secs(5), client.list_datasets())
        .await
        .expect("served once the stream ended")
        .expect("list");
}

#[tokio::test(flavor = "multi_thread")]
async fn unary_serving_calls_without_a_deadline_get_the_default_one() {
    // Batches wait 300 ms for company; the default deadline of 100 ms passes in the queue.
    let server = TestServer::start_with_env(&[
        ("RELREWARD__SERVING__MAX_DELAY_US", "300000"),
        ("RELREWARD__SERVING__DEFAULT_DEADLINE_MS", "100"),
    ]);
    let tmp = tempfile::tempdir().expect("tmp");
    let m = train_tiny_reward(&server, tmp.path());
    let client = server.client().await;
    let x = encode_f32(&[1, m.horizon as u64, m.transition_dim as u64], &vec![0.1; m.horizon * m.transition_dim]);
    let score = pb::ScoreRequest { model: m.reward.clone(), x: Some(x), ..Default::default() };

    let err = client.score(score.clone()).await.expect_err("the default deadline passes in the queue");
    assert_eq!(status_code(&err), Some(Code::DeadlineExceeded), "{err}");

    // A caller's own deadline wins over the default.
    let mut request = tonic::Request::new(score);
    request.set_timeout(Duration::from_secs(10));
    let answer = client.rewards().score(request).await.expect("own deadline of 10 s").into_inner();
    assert!(answer.rewards.is_some());
}

/// A grpc.health.v1 Watch stream on `channel`: it stays open until the server ends it.
async fn health_watch(channel: tonic::transport::Channel) -> tonic::Streaming<tonic_health::pb::HealthCheckResponse> {
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    let mut health = HealthClient::new(channel);
    let request = HealthCheckRequest { service: String::new() };
    let mut watch = health.watch(request).await.expect("watch").into_inner();
    assert!(watch.message().await.expect("first status").is_some());
    watch
}

#[tokio::test(flavor = "multi_thread")]
async fn old_connections_are_sent_away_and_clients_reconnect() {
    // Control: with no maximum age (the default) a quiet stream stays open.
    let server = TestServer::start();
    let mut watch = health_watch(server.client().await.channel()).await;
    assert!(tokio::time::timeout(Duration::from_secs(3), watch.message()).await.is_err(), "still open after 3 s");
    drop(server);

    // With a 1 s age and 1 s of grace, the server ends the connection and the stream on it.
    let server = TestServer::start_with_env(&[
        ("RELREWARD__SERVER__MAX_CONNECTION_AGE_SECS", "1"),
        ("RELREWARD__SERVER__MAX_CONNECTION_AGE_GRACE_SECS", "1"),
    ]);
    let client = server.client().await;
    let mut watch = health_watch(client.channel()).await;
    let started = std::time::Instant::now();
    let ended = tokio::time::timeout(Duration::from_secs(20), watch.message()).await;
    assert!(ended.is_ok(), "the old connection was not closed within 20 s");
    assert!(!matches!(ended, Ok(Ok(Some(_)))), "no status change was expected: {ended:?}");
    assert!(started.elapsed() < Duration::from_secs(10), "closed after age + grace, not later");
    // The same client's next call goes over a new connection (to any replica), at once: the
    // client retries a read that raced the close, so the caller sees no error.
    for _ in 0..3 {
        client.health().await.expect("a call after the GOAWAY goes over a new connection");
        client.list_datasets().await.expect("and so does a list");
    }
}
