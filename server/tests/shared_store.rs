//! The shared backend's two stores on their own, against the real PostgreSQL and S3-protocol
//! server that `tests/cluster/infra.sh` starts (`make test-cluster` runs these; a plain
//! `cargo test` has neither, so they are ignored there).
//!
//! PostgreSQL: concurrent claims never hand one job to two workers (`FOR UPDATE SKIP LOCKED`);
//! a lapsed lease moves to another worker and the old owner's writes are refused; cancellation
//! requests travel with the lease; the models version counts model changes. Each test works
//! in a schema of its own.
//!
//! S3: a blob published by one node is downloaded by another, byte for byte; a corrupted
//! object is reported as DATA_LOSS, never cached; garbage collection respects the grace
//! period; removal deletes every object.

use std::collections::HashSet;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use relreward_server::config::{PostgresConfig, S3Config};
use relreward_server::error::Error;
use relreward_server::store::postgres::{self, PostgresMetadata};
use relreward_server::store::s3::S3Blobs;
use relreward_server::store::{
    BlobStore, JobEvent, JobEventKind, JobRecord, JobState, Lease, MetadataStore, ModelFormat, ModelKind, ModelRecord,
    Provenance,
};

fn var(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| panic!("{name} is not set: run these tests through `make test-cluster`"))
}

/// The test database's settings: the server takes TCP connections over TLS only, with a
/// certificate from the CA in RELREWARD_TEST_PG_CA.
fn pg_config(url: String) -> PostgresConfig {
    PostgresConfig { url, pool_size: 16, ca_file: var("RELREWARD_TEST_PG_CA") }
}

/// `url` with `param` added to its query string.
fn with_param(url: &str, param: &str) -> String {
    let sep = if url.contains('?') { '&' } else { '?' };
    format!("{url}{sep}{param}")
}

/// A direct connection through the store's own TLS connector, for set-up and inspection.
async fn direct_client(config: &PostgresConfig) -> tokio_postgres::Client {
    let tls = postgres::tls_connector(config).expect("connector");
    let (client, connection) = tokio_postgres::connect(&config.url, tls).await.expect("connect");
    tokio::spawn(connection);
    client
}

/// A metadata store in a fresh schema (search_path set through the connection options).
async fn fresh_metadata() -> PostgresMetadata {
    let url = var("RELREWARD_TEST_PG_URL");
    let schema = format!("t{}", &uuid::Uuid::new_v4().simple().to_string()[..12]);
    let client = direct_client(&pg_config(url.clone())).await;
    client.batch_execute(&format!("CREATE SCHEMA {schema}")).await.expect("schema");
    let url = with_param(&url, &format!("options=-c%20search_path%3D{schema}"));
    PostgresMetadata::connect(&pg_config(url)).await.expect("metadata store")
}

fn job(id: &str, state: JobState, last_seq: u64) -> JobRecord {
    JobRecord {
        id: id.into(),
        kind: "diffusion".into(),
        spec: serde_json::json!({}),
        state,
        step: 0,
        total_steps: 10,
        loss: None,
        error: String::new(),
        created_at_ms: 0,
        started_at_ms: None,
        finished_at_ms: None,
        last_seq,
        checkpoint: None,
        inputs: vec![],
        output_model: "m".into(),
    }
}

fn event(seq: u64, state: JobState) -> JobEvent {
    JobEvent { seq, time_ms: 0, event: JobEventKind::State { state, message: String::new() } }
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs PostgreSQL: run with `make test-cluster`"]
async fn concurrent_claims_hand_each_job_to_exactly_one_worker() {
    let db = Arc::new(fresh_metadata().await);
    const JOBS: usize = 40;
    for i in 0..JOBS {
        db.insert_job(&job(&format!("j{i:02}"), JobState::Pending, 1), &[event(1, JobState::Pending)])
            .await
            .expect("insert");
    }
    let mut workers = tokio::task::JoinSet::new();
    for w in 0..8 {
        let db = Arc::clone(&db);
        workers.spawn(async move {
            let mut mine = Vec::new();
            while let Some(record) = db.claim_job(&format!("w{w}"), Duration::from_secs(60)).await.expect("claim") {
                mine.push(record.id);
            }
            mine
        });
    }
    let mut claimed = Vec::new();
    while let Some(mine) = workers.join_next().await {
        claimed.extend(mine.expect("worker"));
    }
    let unique: HashSet<_> = claimed.iter().collect();
    assert_eq!(claimed.len(), JOBS, "every job claimed once: {claimed:?}");
    assert_eq!(unique.len(), JOBS, "no job claimed twice");
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs PostgreSQL: run with `make test-cluster`"]
async fn a_lapsed_lease_moves_and_fences_the_old_owner() {
    let db = fresh_metadata().await;
    db.insert_job(&job("j", JobState::Pending, 1), &[event(1, JobState::Pending)]).await.expect("insert");
    let short = Duration::from_millis(800);
    assert!(db.claim_job("w1", short).await.expect("claim").is_some());
    assert_eq!(db.claim_job("w2", short).await.expect("claim"), None, "held by w1");
    db.record_job(&job("j", JobState::Running, 2), &[event(2, JobState::Running)], Some("w1")).await.expect("w1");
    let stranger = db.record_job(&job("j", JobState::Running, 3), &[event(3, JobState::Running)], Some("w2")).await;
    assert!(matches!(stranger, Err(Error::FailedPrecondition(_))), "{stranger:?}");

    tokio::time::sleep(Duration::from_millis(1200)).await;
    let taken = db.claim_job("w2", Duration::from_secs(60)).await.expect("claim").expect("lapsed: claimable");
    assert_eq!((taken.state, taken.last_seq), (JobState::Running, 2), "w2 resumes what w1 recorded");
    assert_eq!(db.renew_lease("j", "w1", short).await.expect("renew"), Lease::Lost);
    let late = db.record_job(&job("j", JobState::Running, 3), &[event(3, JobState::Running)], Some("w1")).await;
    assert!(matches!(late, Err(Error::FailedPrecondition(_))), "the old owner is fenced off: {late:?}");
    // A queued-job cancel (no owner) is refused too while a worker holds the job.
    let cancel = db.record_job(&job("j", JobState::Cancelled, 3), &[event(3, JobState::Cancelled)], None).await;
    assert!(matches!(cancel, Err(Error::FailedPrecondition(_))), "{cancel:?}");

    db.request_cancel("j").await.expect("request");
    assert_eq!(
        db.renew_lease("j", "w2", Duration::from_secs(60)).await.expect("renew"),
        Lease::Held { cancel_requested: true }
    );
    db.record_job(&job("j", JobState::Cancelled, 3), &[event(3, JobState::Cancelled)], Some("w2")).await.expect("w2");
    assert_eq!(db.claim_job("w3", short).await.expect("claim"), None, "terminal: never claimed again");
    let seqs: Vec<u64> = db.job_events("j", 1, 100).await.expect("events").iter().map(|e| e.seq).collect();
    assert_eq!(seqs, [1, 2, 3], "refused writes left no events");

    db.release_lease("j", "w2").await.expect("release of a finished job is harmless");
    let before = db.models_version().await.expect("version");
    let model = ModelRecord {
        name: "m".into(),
        kind: ModelKind::Reward,
        format: ModelFormat::Native,
        manifest: serde_json::json!({}),
        parameter_count: 1,
        sha256: String::new(),
        size_bytes: 0,
        file: "weights.safetensors".into(),
        provenance: Provenance::Uploaded,
        created_at_ms: 0,
        description: String::new(),
        blob_key: "models/x".into(),
    };
    db.insert_model(&model).await.expect("model");
    assert!(matches!(db.insert_model(&model).await, Err(Error::AlreadyExists(_))));
    db.delete_model("m").await.expect("delete");
    assert_eq!(db.models_version().await.expect("version"), before + 2, "insert and delete each counted once");
}

fn s3_config(prefix: &str, grace_secs: u64) -> S3Config {
    S3Config {
        endpoint: var("RELREWARD_TEST_S3_ENDPOINT"),
        bucket: var("RELREWARD_TEST_S3_BUCKET"),
        region: var("RELREWARD_TEST_S3_REGION"),
        prefix: prefix.into(),
        access_key_id: var("RELREWARD_TEST_S3_ACCESS_KEY_ID"),
        secret_access_key: var("RELREWARD_TEST_S3_SECRET_ACCESS_KEY"),
        allow_http: true,
        orphan_grace_secs: grace_secs,
        cache_max_bytes: 0,
        cache_hold_secs: 60,
    }
}

fn read(dir: &Path, file: &str) -> Vec<u8> {
    std::fs::read(dir.join(file)).unwrap_or_else(|e| panic!("{}: {e}", dir.join(file).display()))
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs an S3 server: run with `make test-cluster`"]
async fn blobs_travel_between_nodes_whole_or_not_at_all() {
    let prefix = format!("test-{}/", &uuid::Uuid::new_v4().simple().to_string()[..8]);
    let nodes = tempfile::tempdir().expect("tmp");
    let writer = S3Blobs::open(&s3_config(&prefix, 3600), &nodes.path().join("a")).await.expect("node a");
    let staging = writer.staging().expect("staging");
    let big: Vec<u8> = (0..12_000_000u32).map(|i| (i * 7919 % 251) as u8).collect(); // multipart
    std::fs::write(staging.path().join("weights.bin"), &big).expect("write");
    std::fs::write(staging.path().join("manifest.json"), b"{}").expect("write");
    writer.publish(staging, "models/k1").await.expect("publish");

    // Another node downloads it: identical bytes, digest list included.
    let reader = S3Blobs::open(&s3_config(&prefix, 3600), &nodes.path().join("b")).await.expect("node b");
    let dir = reader.local_dir("models/k1").await.expect("download");
    assert_eq!(read(&dir, "weights.bin"), big);
    assert_eq!(read(&dir, "manifest.json"), b"{}");
    assert!(dir.join("SHA256SUMS").exists());

    // Fresh keys are not collectable until the grace period has passed.
    assert!(reader.collectable_keys("models/").await.expect("list").is_empty(), "within the grace period");
    let impatient = S3Blobs::open(&s3_config(&prefix, 0), &nodes.path().join("c")).await.expect("node c");
    assert_eq!(impatient.collectable_keys("models/").await.expect("list"), ["models/k1"]);

    // Bytes flipped in the bucket: a node without a cached copy refuses it (and caches nothing).
    let object = Path::new(&var("RELREWARD_TEST_S3_ROOT"))
        .join(var("RELREWARD_TEST_S3_BUCKET"))
        .join(&prefix)
        .join("models/k1/manifest.json");
    std::fs::write(&object, b"[]").expect("corrupt the stored object");
    let err = impatient.local_dir("models/k1").await.expect_err("corrupt");
    assert!(matches!(&err, Error::DataLoss(m) if m.contains("manifest.json")), "{err:?}");
    assert!(!nodes.path().join("c/cache/models/k1").exists(), "nothing cached");

    // Removal deletes every object: no node can fetch it any more.
    writer.remove("models/k1").await.expect("remove");
    let gone = impatient.local_dir("models/k1").await.expect_err("removed");
    assert!(matches!(gone, Error::DataLoss(_)), "{gone:?}");
    assert!(impatient.collectable_keys("models/").await.expect("list").is_empty());
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs PostgreSQL: run with `make test-cluster`"]
async fn tls_to_the_database_is_verified_and_bad_settings_fail_fast() {
    // The store connects (the server refuses plaintext TCP), and the session is encrypted.
    let url = var("RELREWARD_TEST_PG_URL");
    PostgresMetadata::connect(&pg_config(url.clone())).await.expect("TLS with the test CA");
    let require = pg_config(with_param(&url, "sslmode=require"));
    let client = direct_client(&require).await;
    let row = client.query_one("SELECT ssl FROM pg_stat_ssl WHERE pid = pg_backend_pid()", &[]).await.expect("ssl");
    assert!(row.get::<_, bool>(0), "pg_stat_ssl: the connection is not encrypted");

    // Settings a retry cannot mend fail at once (not after the 60 s wait for a database that
    // is starting), with a message that says what to change.
    let cases = [
        // The system's roots do not hold the test CA: the certificate is not trusted.
        (PostgresConfig { ca_file: String::new(), ..pg_config(url.clone()) }, "storage.postgres.ca_file"),
        // Plaintext is refused by the server (hostssl): an authentication-class error.
        (pg_config(with_param(&url, "sslmode=disable")), "refused the connection"),
        (pg_config(url.replacen("://relreward:", "://relreward:x", 1)), "password authentication failed"),
    ];
    for (config, expected) in cases {
        let started = std::time::Instant::now();
        let Err(e) = PostgresMetadata::connect(&config).await else { panic!("{config:?} connected") };
        let text = e.to_string();
        assert!(matches!(e, Error::Unavailable(_)), "{text}");
        assert!(text.contains(expected), "{config:?}: {text}");
        assert!(!text.contains(&var("RELREWARD_TEST_PG_URL")), "the message shows the password: {text}");
        assert!(started.elapsed() < Duration::from_secs(15), "{config:?} took {:?}", started.elapsed());
    }

    // A CA file that cannot be used names its key.
    let dir = tempfile::tempdir().expect("tmp");
    let not_pem = dir.path().join("ca.pem");
    std::fs::write(&not_pem, "not a certificate").expect("write");
    for ca_file in [not_pem.display().to_string(), dir.path().join("missing.pem").display().to_string()] {
        let config = PostgresConfig { ca_file, ..pg_config(url.clone()) };
        let Err(e) = PostgresMetadata::connect(&config).await else { panic!("{config:?} connected") };
        assert!(format!("{e:#}").contains("storage.postgres.ca_file"), "{e:#}");
    }
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "needs the S3-protocol server: run with `make test-cluster`"]
async fn the_blob_cache_stays_under_its_bound_least_recently_used_first() {
    let prefix = format!("test-{}/", &uuid::Uuid::new_v4().simple().to_string()[..8]);
    let nodes = tempfile::tempdir().expect("tmp");
    let writer = S3Blobs::open(&s3_config(&prefix, 3600), &nodes.path().join("a")).await.expect("node a");
    const MB: usize = 1 << 20;
    for (i, key) in ["models/k1", "models/k2", "models/k3"].into_iter().enumerate() {
        let staging = writer.staging().expect("staging");
        std::fs::write(staging.path().join("weights.bin"), vec![i as u8; MB]).expect("write");
        writer.publish(staging, key).await.expect("publish");
    }
    assert!(writer.cached_bytes() > 3 * MB as u64, "the publisher keeps its copies (no bound)");

    // Room for two blobs, nothing held: the least recently used goes first.
    let cached = |node: &str, key: &str| nodes.path().join(node).join("cache").join(key).is_dir();
    let config = S3Config { cache_max_bytes: (5 * MB / 2) as u64, cache_hold_secs: 0, ..s3_config(&prefix, 3600) };
    let reader = S3Blobs::open(&config, &nodes.path().join("b")).await.expect("node b");
    reader.local_dir("models/k1").await.expect("k1");
    reader.local_dir("models/k2").await.expect("k2");
    assert!(cached("b", "models/k1") && cached("b", "models/k2"));
    let dir = reader.local_dir("models/k3").await.expect("k3");
    assert_eq!(read(&dir, "weights.bin"), vec![2u8; MB]);
    assert!(!cached("b", "models/k1") && cached("b", "models/k2") && cached("b", "models/k3"), "k1 was the oldest");
    assert!(reader.cached_bytes() <= config.cache_max_bytes);
    // A use refreshes a blob: k2 is now newer than k3, so k3 makes room for k1.
    reader.local_dir("models/k2").await.expect("k2 from the cache");
    let dir = reader.local_dir("models/k1").await.expect("k1 again");
    assert_eq!(read(&dir, "weights.bin"), vec![0u8; MB], "downloaded again, whole");
    assert!(cached("b", "models/k1") && cached("b", "models/k2") && !cached("b", "models/k3"));
    let leftovers: Vec<_> = std::fs::read_dir(nodes.path().join("b/cache"))
        .expect("cache dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|name| name.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "evicted or partial copies left behind: {leftovers:?}");

    // Blobs in use (within the hold) are never evicted, even beyond the bound.
    let config = S3Config { cache_max_bytes: MB as u64, cache_hold_secs: 3600, ..s3_config(&prefix, 3600) };
    let holder = S3Blobs::open(&config, &nodes.path().join("c")).await.expect("node c");
    let first = holder.local_dir("models/k1").await.expect("k1");
    holder.local_dir("models/k2").await.expect("k2");
    assert_eq!(read(&first, "weights.bin"), vec![0u8; MB], "a held blob stays readable");
    assert!(cached("c", "models/k1") && cached("c", "models/k2"));

    // Removal forgets the cached copy too.
    writer.remove("models/k2").await.expect("remove");
    reader.remove("models/k2").await.expect("remove on the reader (objects already gone)");
    assert!(!cached("b", "models/k2"));
    assert!(reader.cached_bytes() < 2 * MB as u64);
    for key in ["models/k1", "models/k3"] {
        writer.remove(key).await.expect("clean up");
    }
}
