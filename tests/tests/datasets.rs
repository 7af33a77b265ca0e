//! Dataset upload end to end: the real server binary, the real client library and CLI.

use std::sync::Arc;

use relreward_client::client::{DatasetUpload, UploadProgress};
use relreward_client::pb::{self, Dtype, upload_dataset_request::Message};
use relreward_client::tensor::encode_f32;
use relreward_client::{Client, MemorySource};
use relreward_tests::{TestServer, eventually, python};
use sha2::{Digest, Sha256};
use tonic::Code;

fn header(name: &str, kind: pb::DatasetKind, arrays: &[(&str, Dtype, &[u64])]) -> pb::UploadDatasetRequest {
    let arrays = arrays
        .iter()
        .map(|(n, d, s)| pb::ArraySpec { name: (*n).into(), dtype: *d as i32, shape: s.to_vec() })
        .collect();
    msg(Message::Header(pb::UploadHeader { name: name.into(), kind: kind as i32, arrays, description: String::new() }))
}

fn chunk(array: &str, t: pb::Tensor) -> pb::UploadDatasetRequest {
    msg(Message::Chunk(pb::DatasetChunk { array: array.into(), data: Some(t) }))
}

fn commit(sha256: &str) -> pb::UploadDatasetRequest {
    msg(Message::Commit(pb::UploadCommit { sha256: sha256.into() }))
}

fn msg(m: Message) -> pb::UploadDatasetRequest {
    pb::UploadDatasetRequest { message: Some(m) }
}

fn sha(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update(p);
    }
    hex::encode(h.finalize())
}

fn flags(v: &[u8]) -> pb::Tensor {
    pb::Tensor { shape: vec![v.len() as u64], dtype: Dtype::Bool as i32, data: v.to_vec() }
}

async fn raw_upload(client: &Client, msgs: Vec<pb::UploadDatasetRequest>) -> Result<pb::Dataset, tonic::Status> {
    client.datasets().upload_dataset(tokio_stream::iter(msgs)).await.map(|r| r.into_inner())
}

/// A valid 6-row trajectory upload: observations [6, 3], actions [6, 2], terminals [6].
fn small_upload(name: &str) -> Vec<pb::UploadDatasetRequest> {
    let obs: Vec<f32> = (0..18).map(|i| i as f32 * 0.5).collect();
    let act: Vec<f32> = (0..12).map(|i| (i as f32 - 6.0) / 6.0).collect();
    let o1 = encode_f32(&[4, 3], &obs[..12]);
    let o2 = encode_f32(&[2, 3], &obs[12..]);
    let a = encode_f32(&[6, 2], &act);
    let t = flags(&[0, 0, 1, 0, 0, 1]);
    let digest = sha(&[&o1.data, &o2.data, &a.data, &t.data]);
    vec![
        header(
            name,
            pb::DatasetKind::Trajectories,
            &[
                ("observations", Dtype::Float32, &[6, 3]),
                ("actions", Dtype::Float32, &[6, 2]),
                ("terminals", Dtype::Bool, &[6]),
            ],
        ),
        chunk("observations", o1),
        chunk("observations", o2),
        chunk("actions", a),
        chunk("terminals", t),
        commit(&digest),
    ]
}

#[tokio::test(flavor = "multi_thread")]
async fn health_reports_serving_and_score_names_a_missing_model() {
    let server = TestServer::start();
    let client = server.client().await;
    assert_eq!(client.health().await.expect("health"), tonic_health_status_serving());
    let out = server.cli(&["health"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "SERVING");

    let err = client
        .rewards()
        .score(pb::ScoreRequest { model: "r".into(), ..Default::default() })
        .await
        .expect_err("no such model");
    assert_eq!(err.code(), Code::InvalidArgument, "x is checked before the model is looked up");
    assert!(err.message().contains("x: missing"), "{}", err.message());
}

fn tonic_health_status_serving() -> tonic_health::pb::health_check_response::ServingStatus {
    tonic_health::pb::health_check_response::ServingStatus::Serving
}

#[tokio::test(flavor = "multi_thread")]
async fn upload_get_list_delete_with_exact_statistics() {
    let server = TestServer::start();
    let client = server.client().await;
    let ds = raw_upload(&client, small_upload("small")).await.expect("upload");
    assert_eq!(ds.name, "small");
    assert_eq!(ds.num_rows, 6);
    let ep = ds.episodes.expect("episodes");
    assert_eq!((ep.count, ep.min_length, ep.max_length), (2, 3, 3));

    let got = client.get_dataset("small").await.expect("get");
    assert_eq!(got, ds, "GetDataset returns what the upload returned");
    let obs = got.arrays.iter().find(|a| a.spec.as_ref().is_some_and(|s| s.name == "observations")).expect("obs");
    let stats = obs.stats.as_ref().expect("stats");
    // Column j holds 0.5 * (3 i + j) for i in 0..6: mean 0.5 (7.5 + j), population std 0.5 * 3 * sqrt(35/12).
    for j in 0..3 {
        let mean = 0.5 * (7.5 + j as f64);
        let std = 1.5 * (35.0f64 / 12.0).sqrt();
        assert!((stats.mean[j] - mean).abs() < 1e-12, "mean[{j}] = {}", stats.mean[j]);
        assert!((stats.std[j] - std).abs() < 1e-12, "std[{j}] = {}", stats.std[j]);
        assert_eq!(stats.min[j], 0.5 * j as f64);
        assert_eq!(stats.max[j], 0.5 * (15 + j) as f64);
    }
    let terminals =
        got.arrays.iter().find(|a| a.spec.as_ref().is_some_and(|s| s.name == "terminals")).expect("terminals");
    assert!(terminals.stats.is_none(), "flags carry no statistics");

    let listed = client.list_datasets().await.expect("list");
    assert_eq!(listed.len(), 1);
    assert!(listed[0].arrays.iter().all(|a| a.stats.is_none()), "listings use the basic view");

    // The stored files are plain .npy with exactly the uploaded bytes.
    assert_eq!(server.dataset_blobs(), 1);
    client.delete_dataset("small").await.expect("delete");
    assert!(client.get_dataset("small").await.expect_err("gone").to_string().contains("NOT_FOUND"));
    assert_eq!(server.dataset_blobs(), 0);
    let err = client.delete_dataset("small").await.expect_err("twice");
    assert!(err.to_string().starts_with("NOT_FOUND"), "{err}");
}

#[tokio::test(flavor = "multi_thread")]
async fn listing_pages_through_every_dataset() {
    let server = TestServer::start();
    let client = server.client().await;
    for i in 0..5 {
        raw_upload(&client, small_upload(&format!("d{i}"))).await.expect("upload");
    }
    let mut names = Vec::new();
    let mut token = String::new();
    let mut pages = 0;
    loop {
        let req = pb::ListDatasetsRequest { page: Some(pb::PageRequest { page_size: 2, page_token: token }), view: 0 };
        let resp = client.datasets().list_datasets(req).await.expect("list").into_inner();
        pages += 1;
        names.extend(resp.datasets.into_iter().map(|d| d.name));
        if resp.next_page_token.is_empty() {
            break;
        }
        token = resp.next_page_token;
    }
    assert_eq!(names, ["d0", "d1", "d2", "d3", "d4"]);
    assert_eq!(pages, 3);
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_inputs_get_clear_errors_and_store_nothing() {
    let server = TestServer::start_with_env(&[("RELREWARD__DATASETS__MAX_UPLOAD_BYTES", "100000")]);
    let client = server.client().await;
    let baseline = raw_upload(&client, small_upload("baseline")).await.expect("baseline upload");

    let good = small_upload("fresh");
    let with = |i: usize, m: pb::UploadDatasetRequest| {
        let mut v = good.clone();
        v[i] = m;
        v
    };
    let obs6 = |vals: &[f32]| chunk("observations", encode_f32(&[vals.len() as u64 / 3, 3], vals));
    let mut nan = vec![0.0f32; 12];
    nan[7] = f32::NAN;
    let mut inf = vec![0.0f32; 12];
    inf[3] = f32::NEG_INFINITY;
    let mut wrong_bytes = encode_f32(&[4, 3], &[0.0; 12]);
    wrong_bytes.data.truncate(40);
    let unknown_dtype = pb::Tensor { shape: vec![4, 3], dtype: 42, data: vec![0; 48] };
    let big_rows = 100_000u64;

    let cases: Vec<(&str, Vec<pb::UploadDatasetRequest>, Code, &str)> = vec![
        ("NaN value", with(1, obs6(&nan)), Code::InvalidArgument, "row 2, coordinate 1 is not finite"),
        ("infinite value", with(1, obs6(&inf)), Code::InvalidArgument, "row 1, coordinate 0 is not finite"),
        (
            "shape inconsistent across chunks",
            with(2, chunk("observations", encode_f32(&[1, 2], &[0.0; 2]))),
            Code::InvalidArgument,
            "inconsistent with the header's [rows, 3]",
        ),
        ("wrong byte count", with(1, chunk("observations", wrong_bytes)), Code::InvalidArgument, "40 bytes"),
        (
            "unknown chunk dtype",
            with(1, chunk("observations", unknown_dtype)),
            Code::InvalidArgument,
            "unknown dtype 42",
        ),
        (
            "dtype differs from header",
            with(
                3,
                chunk("actions", pb::Tensor { shape: vec![6, 2], dtype: Dtype::Float64 as i32, data: vec![0; 96] }),
            ),
            Code::InvalidArgument,
            "float64 but the header declared float32",
        ),
        (
            "unknown dtype in header",
            with(
                0,
                header(
                    "fresh",
                    pb::DatasetKind::Trajectories,
                    &[("observations", Dtype::Unspecified, &[6, 3]), ("actions", Dtype::Float32, &[6, 2])],
                ),
            ),
            Code::InvalidArgument,
            "header.arrays[0] ('observations').dtype",
        ),
        (
            "empty data",
            vec![
                header(
                    "fresh",
                    pb::DatasetKind::Trajectories,
                    &[("observations", Dtype::Float32, &[0, 3]), ("actions", Dtype::Float32, &[0, 2])],
                ),
                commit(&sha(&[])),
            ],
            Code::InvalidArgument,
            "N = 0 rows",
        ),
        ("digest mismatch", with(5, commit(&"0".repeat(64))), Code::InvalidArgument, "digest mismatch"),
        ("malformed digest", with(5, commit("abc")), Code::InvalidArgument, "not 64 hex digits"),
        (
            "upper-case name",
            with(0, header("Fresh", pb::DatasetKind::Trajectories, &[])),
            Code::InvalidArgument,
            "header.name",
        ),
        (
            "path traversal name",
            with(0, header("../etc", pb::DatasetKind::Trajectories, &[])),
            Code::InvalidArgument,
            "header.name",
        ),
        (
            "name too long",
            with(0, header(&"a".repeat(65), pb::DatasetKind::Trajectories, &[])),
            Code::InvalidArgument,
            "header.name",
        ),
        ("duplicate name", small_upload("baseline"), Code::AlreadyExists, "dataset 'baseline' already exists"),
        (
            "payload above quota",
            vec![header("fresh", pb::DatasetKind::Samples, &[("samples", Dtype::Float32, &[big_rows, 4])])],
            Code::ResourceExhausted,
            "exceeds the upload quota of 100000 bytes",
        ),
        ("missing commit", good[..5].to_vec(), Code::InvalidArgument, "without a commit"),
        (
            "chunk before header",
            good[1..].to_vec(),
            Code::InvalidArgument,
            "first message of an upload must be a header",
        ),
        (
            "rows missing at commit",
            {
                let mut v = good.clone();
                v.remove(2);
                v
            },
            Code::InvalidArgument,
            "incomplete",
        ),
        ("too many rows", with(2, obs6(&[0.0; 9])), Code::InvalidArgument, "would make 7 but the header declared 6"),
        (
            "arrays out of order",
            {
                let mut v = good.clone();
                v.swap(2, 3);
                v
            },
            Code::InvalidArgument,
            "arrays are sent whole, in header order",
        ),
        (
            "unknown array name",
            with(
                0,
                header(
                    "fresh",
                    pb::DatasetKind::Trajectories,
                    &[("observations", Dtype::Float32, &[6, 3]), ("rewards", Dtype::Float32, &[6])],
                ),
            ),
            Code::InvalidArgument,
            "('rewards').name: not an array",
        ),
        (
            "missing actions",
            with(0, header("fresh", pb::DatasetKind::Trajectories, &[("observations", Dtype::Float32, &[6, 3])])),
            Code::InvalidArgument,
            "needs 'actions'",
        ),
        (
            "leading dimensions differ",
            with(
                0,
                header(
                    "fresh",
                    pb::DatasetKind::Trajectories,
                    &[("observations", Dtype::Float32, &[6, 3]), ("actions", Dtype::Float32, &[5, 2])],
                ),
            ),
            Code::InvalidArgument,
            "share the leading dimension",
        ),
        (
            "unset kind",
            with(0, header("fresh", pb::DatasetKind::Unspecified, &[])),
            Code::InvalidArgument,
            "header.kind",
        ),
        ("empty stream", vec![], Code::InvalidArgument, "empty"),
        (
            "message with nothing set",
            vec![pb::UploadDatasetRequest { message: None }],
            Code::InvalidArgument,
            "none of header, chunk or commit",
        ),
        (
            "message after commit",
            {
                let mut v = good.clone();
                v.push(commit("x"));
                v
            },
            Code::InvalidArgument,
            "must be the last message",
        ),
    ];

    for (what, msgs, code, needle) in cases {
        let err = raw_upload(&client, msgs).await.expect_err(what);
        assert_eq!(err.code(), code, "{what}: {}", err.message());
        assert!(err.message().contains(needle), "{what}: message {:?} should contain {needle:?}", err.message());
        // The store is exactly as it was: one dataset, unchanged, and no leftovers.
        let listed = client.list_datasets().await.expect("list");
        assert_eq!(listed.iter().map(|d| d.name.as_str()).collect::<Vec<_>>(), ["baseline"], "{what}");
        assert!(eventually(5, || server.staging_entries() == 0).await, "{what}: staging not cleaned");
        assert_eq!(server.dataset_blobs(), 1, "{what}: stray blob");
    }
    assert_eq!(client.get_dataset("baseline").await.expect("baseline"), baseline);

    for (what, name) in [("get", "Bad/Name"), ("delete", "..")] {
        let err = if what == "get" {
            client.datasets().get_dataset(pb::GetDatasetRequest { name: name.into(), view: 0 }).await.expect_err(what)
        } else {
            client.datasets().delete_dataset(pb::DeleteDatasetRequest { name: name.into() }).await.expect_err(what)
        };
        assert_eq!(err.code(), Code::InvalidArgument, "{what}");
        assert!(err.message().starts_with("name:"), "{what}: {}", err.message());
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn interrupted_upload_leaves_nothing_and_kill_9_leftovers_are_cleaned_at_start() {
    let mut server = TestServer::start();
    let client = server.client().await;

    // A client that goes away mid-upload: send a header and half the data, then drop the stream.
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    let mut datasets = client.datasets();
    let call =
        tokio::spawn(async move { datasets.upload_dataset(tokio_stream::wrappers::ReceiverStream::new(rx)).await });
    let n = 20_000u64;
    tx.send(header("partial", pb::DatasetKind::Samples, &[("samples", Dtype::Float32, &[n, 8])])).await.expect("send");
    tx.send(chunk("samples", encode_f32(&[n / 2, 8], &vec![1.0; (n / 2 * 8) as usize]))).await.expect("send");
    assert!(eventually(10, || server.staging_entries() == 1).await, "the upload should be staging");
    call.abort();
    drop(tx);
    assert!(eventually(10, || server.staging_entries() == 0).await, "staging removed when the client left");
    assert!(client.list_datasets().await.expect("list").is_empty());

    // The same interrupted by a crash of the server: leftovers go at the next start.
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    let mut datasets = client.datasets();
    let _call =
        tokio::spawn(async move { datasets.upload_dataset(tokio_stream::wrappers::ReceiverStream::new(rx)).await });
    tx.send(header("partial", pb::DatasetKind::Samples, &[("samples", Dtype::Float32, &[n, 8])])).await.expect("send");
    tx.send(chunk("samples", encode_f32(&[n / 2, 8], &vec![1.0; (n / 2 * 8) as usize]))).await.expect("send");
    assert!(eventually(10, || server.staging_entries() == 1).await);
    server.kill();
    assert_eq!(server.staging_entries(), 1, "a killed server cannot clean up");
    server.restart();
    let client = server.client().await;
    assert!(client.list_datasets().await.expect("list").is_empty());
    assert_eq!(server.staging_entries(), 0, "cleaned at start");
}

#[tokio::test(flavor = "multi_thread")]
async fn datasets_survive_restarts_and_crashes() {
    let mut server = TestServer::start();
    let client = server.client().await;
    let mut source = MemorySource::new();
    let n = 50_000usize;
    let samples: Vec<f32> = (0..n * 4).map(|i| ((i * 7919) % 1000) as f32 / 100.0).collect();
    source.push_f32("samples", &[n as u64, 2, 2], &samples);
    let upload = DatasetUpload {
        name: "latents".into(),
        kind: pb::DatasetKind::Samples,
        description: "persistence".into(),
        chunk_bytes: 64 << 10,
    };
    let progress = Arc::new(UploadProgress::default());
    let stored = client.upload_dataset(upload, source, Arc::clone(&progress)).await.expect("upload");
    assert_eq!(progress.sent_bytes.load(std::sync::atomic::Ordering::Relaxed), (n * 16) as u64);
    assert_eq!(stored.sha256, sha(&[&encode_f32(&[n as u64 * 4], &samples).data]));

    assert!(server.terminate(), "graceful shutdown exits 0");
    server.restart();
    let client = server.client().await;
    assert_eq!(client.get_dataset("latents").await.expect("after restart"), stored);

    server.kill();
    server.restart();
    let client = server.client().await;
    assert_eq!(client.get_dataset("latents").await.expect("after kill -9"), stored);

    // The stored file is an .npy whose payload is exactly the uploaded bytes.
    let dir = std::fs::read_dir(server.data_dir.join("blobs/datasets"))
        .expect("blobs")
        .next()
        .expect("one")
        .expect("entry")
        .path();
    let file = std::fs::read(dir.join("samples.npy")).expect("npy");
    let header_len = u16::from_le_bytes([file[8], file[9]]) as usize + 10;
    assert_eq!(sha(&[&file[header_len..]]), stored.sha256);
}

#[tokio::test(flavor = "multi_thread")]
async fn cli_uploads_a_million_transitions_matching_numpy() {
    let server = TestServer::start();
    let tmp = tempfile::tempdir().expect("tmp");
    let npz = tmp.path().join("maze.npz");
    let expected_path = tmp.path().join("expected.json");
    let status = std::process::Command::new(python())
        .arg(relreward_tests::repo_root().join("tests/python/make_dataset.py"))
        .args(["--rows", "1000000", "--seed", "7"])
        .arg("--out")
        .arg(&npz)
        .arg("--expected")
        .arg(&expected_path)
        .status()
        .expect("python");
    assert!(status.success());
    let expected: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&expected_path).expect("json")).expect("parse");

    let out = server.cli(&["--json", "dataset", "upload", npz.to_str().expect("utf8"), "--name", "maze-1m"]);
    assert!(out.status.success(), "upload failed: {}", String::from_utf8_lossy(&out.stderr));
    let out = server.cli(&["--json", "dataset", "show", "maze-1m"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let shown: serde_json::Value = serde_json::from_slice(&out.stdout).expect("show --json");

    assert_eq!(shown["kind"], "trajectories");
    assert_eq!(shown["num_rows"], expected["num_rows"]);
    assert_eq!(shown["sha256"], expected["sha256"], "digest computed independently by numpy");
    assert_eq!(shown["size_bytes"], expected["size_bytes"]);
    for key in ["count", "min_length", "max_length"] {
        assert_eq!(shown["episodes"][key], expected["episodes"][key], "episodes.{key}");
    }
    let names: Vec<&str> =
        shown["arrays"].as_array().expect("arrays").iter().map(|a| a["name"].as_str().expect("name")).collect();
    assert_eq!(names, ["observations", "actions", "terminals", "timeouts"], "extra npz keys are not uploaded");
    for array in ["observations", "actions"] {
        let got = shown["arrays"].as_array().expect("arrays").iter().find(|a| a["name"] == array).expect(array);
        for stat in ["min", "max", "mean", "std"] {
            let g = got["stats"][stat].as_array().expect(stat);
            let e = expected["stats"][array][stat].as_array().expect(stat);
            assert_eq!(g.len(), e.len());
            for (j, (g, e)) in g.iter().zip(e).enumerate() {
                let (g, e) = (g.as_f64().expect("f64"), e.as_f64().expect("f64"));
                // min/max are exact; mean/std agree to float64 rounding of a million-term sum.
                let tol = if matches!(stat, "min" | "max") { 0.0 } else { 1e-9 * e.abs().max(1.0) };
                assert!((g - e).abs() <= tol, "{array}.{stat}[{j}]: server {g} vs numpy {e}");
            }
        }
    }

    // The human-readable forms work too.
    let out = server.cli(&["dataset", "show", "maze-1m"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success()
            && text.contains("observations")
            && text.contains(expected["sha256"].as_str().expect("sha")),
        "{text}"
    );
    let out = server.cli(&["dataset", "upload", npz.to_str().expect("utf8"), "--name", "maze-1m"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("ALREADY_EXISTS"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = server.cli(&["dataset", "delete", "maze-1m"]);
    assert!(out.status.success());
    let out = server.cli(&["dataset", "show", "maze-1m"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("NOT_FOUND"));
}
