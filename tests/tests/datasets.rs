//! Dataset upload end to end: the real server binary, the real client library and CLI. (What
//! uploads, deletes and refusals leave on disk is server/tests/stored_files.rs.)

use relreward_client::pb::{self, Dtype};
use relreward_client::tensor::encode_f32;
use relreward_tests::dataset_upload::{chunk, header, raw_upload, small_upload};
use relreward_tests::{TestServer, eventually, python};
use tonic::Code;

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

/// Class labels of a samples dataset (issue 37): stored with statistics (max, what conditional
/// training reads its class count from), and refused by the server itself, naming the row or the
/// field, when a client sends a negative label, a float array as labels, or labels alone.
#[tokio::test(flavor = "multi_thread")]
async fn sample_labels_are_stored_and_checked_by_the_server() {
    use relreward_tests::dataset_upload::{commit, sha};
    let server = TestServer::start();
    let client = server.client().await;
    let samples = encode_f32(&[4, 1, 2, 2], &[0.5; 16]);
    let int64 = |v: &[i64]| pb::Tensor {
        shape: vec![v.len() as u64],
        dtype: Dtype::Int64 as i32,
        data: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    };
    let upload = |name: &str, labels: pb::Tensor, dtype: Dtype| {
        let digest = sha(&[&samples.data, &labels.data]);
        vec![
            header(
                name,
                pb::DatasetKind::Samples,
                &[("samples", Dtype::Float32, &[4, 1, 2, 2]), ("labels", dtype, &[4])],
            ),
            chunk("samples", samples.clone()),
            chunk("labels", labels),
            commit(&digest),
        ]
    };
    let ds = raw_upload(&client, upload("labelled", int64(&[0, 3, 1, 2]), Dtype::Int64)).await.expect("labels");
    let labels = ds.arrays.iter().find(|a| a.spec.as_ref().is_some_and(|s| s.name == "labels")).expect("labels");
    assert_eq!(labels.stats.as_ref().map(|s| s.max.clone()), Some(vec![3.0]));

    let err = raw_upload(&client, upload("negative", int64(&[0, -1, 1, 2]), Dtype::Int64)).await.expect_err("-1");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().contains("label -1 at row 1"), "{}", err.message());
    let err = raw_upload(&client, upload("floats", encode_f32(&[4], &[0.0; 4]), Dtype::Float32)).await.expect_err("f");
    assert!(err.message().contains("class labels must be int32, int64 or uint8"), "{}", err.message());
    let alone = vec![header("alone", pb::DatasetKind::Samples, &[("labels", Dtype::Int64, &[4])])];
    let err = raw_upload(&client, alone).await.expect_err("labels alone");
    assert!(err.message().contains("a samples dataset needs 'samples'"), "{}", err.message());
    assert_eq!(client.list_datasets().await.expect("list").len(), 1, "only the valid upload is stored");
}

/// A header's shapes are the client's: they are checked whole (row count, elements per row,
/// quota) before the server allocates anything for them; a float64 value beyond float32's range
/// is refused, where its square would have made a statistic no record can hold (and every List
/// call fail); a description is bounded as a model's is. After each refusal the server answers and lists.
#[tokio::test(flavor = "multi_thread")]
async fn upload_headers_values_and_descriptions_are_bounded_before_anything_is_stored() {
    use relreward_tests::dataset_upload::{commit, sha};
    let server = TestServer::start();
    let client = server.client().await;
    // A row beyond an item's bound (its statistics alone would be 32 TiB), and a payload beyond
    // the quota whose rows are small.
    let wide: &[u64] = &[1, 1 << 40];
    let err = raw_upload(&client, vec![header("wide", pb::DatasetKind::Samples, &[("samples", Dtype::Float32, wide)])])
        .await
        .expect_err("a 4 TiB row");
    assert_eq!(err.code(), Code::InvalidArgument, "{}", err.message());
    assert!(err.message().contains("elements per row, more than the 16777216"), "{}", err.message());
    let long: &[u64] = &[1 << 40, 4];
    let err = raw_upload(&client, vec![header("long", pb::DatasetKind::Samples, &[("samples", Dtype::Float32, long)])])
        .await
        .expect_err("16 TiB of rows");
    assert_eq!(err.code(), Code::ResourceExhausted, "{}", err.message());
    assert!(err.message().contains("datasets.max_upload_bytes"), "{}", err.message());
    let empty: &[u64] = &[0, 4];
    let err =
        raw_upload(&client, vec![header("none", pb::DatasetKind::Samples, &[("samples", Dtype::Float32, empty)])])
            .await
            .expect_err("no rows");
    assert!(err.message().contains("N = 0 rows"), "{}", err.message());
    let obs: &[u64] = &[3, 1 << 40];
    let err = raw_upload(
        &client,
        vec![header(
            "wide-obs",
            pb::DatasetKind::Trajectories,
            &[("observations", Dtype::Float32, obs), ("actions", Dtype::Float32, &[3, 1])],
        )],
    )
    .await
    .expect_err("wide observations");
    assert_eq!(err.code(), Code::InvalidArgument, "{}", err.message());

    // Float64 samples [4, 2], 0.25 but for `value` at row 2, coordinate 1.
    let far = |name: &str, value: f64| {
        let mut values = vec![0.25f64; 8];
        values[5] = value;
        let samples = relreward_client::tensor::encode_f64(&[4, 2], &values);
        let digest = sha(&[&samples.data]);
        vec![
            header(name, pb::DatasetKind::Samples, &[("samples", Dtype::Float64, &[4, 2])]),
            chunk("samples", samples),
            commit(&digest),
        ]
    };
    for (value, needle) in [(1e300, "1e300 at row 2, coordinate 1 is outside float32's range"), (-4e38, "-4e38")] {
        let err = raw_upload(&client, far("far", value)).await.expect_err("beyond float32");
        assert_eq!(err.code(), Code::InvalidArgument);
        assert!(err.message().contains(needle), "{}", err.message());
    }
    // float32's own largest value is a value like any other.
    raw_upload(&client, far("edge", f32::MAX as f64)).await.expect("float32's largest value");

    let mut long = small_upload("described");
    if let Some(pb::upload_dataset_request::Message::Header(h)) = long[0].message.as_mut() {
        h.description = "d".repeat(4097);
    }
    let err = raw_upload(&client, long).await.expect_err("a long description");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().contains("header.description: 4097 bytes, at most 4096"), "{}", err.message());
    let listed = client.list_datasets().await.expect("list");
    assert_eq!(listed.iter().map(|d| d.name.as_str()).collect::<Vec<_>>(), ["edge"]);
}

/// DeleteDataset and a SubmitJob that reads the same dataset, sent together: one of the two is
/// refused every time (the job sees no dataset, or the deletion sees the job), never both
/// accepted with the job left reading a dataset that is gone (`Store::references`).
#[tokio::test(flavor = "multi_thread")]
async fn a_deletion_and_a_job_on_the_same_dataset_never_both_succeed() {
    use relreward_tests::{Lines, upload_lines};
    let server = TestServer::start();
    let client = server.client().await;
    let lines = Lines { episodes: 2, seed: 3, start: [(1.0, 0.0), (1.0, 0.0)], velocity: [(0.1, 0.0), (0.1, 0.0)] };
    let long = pb::Optimization { steps: Some(1_000_000), log_every: Some(1_000_000), ..Default::default() };
    let (mut deleted, mut submitted) = (0, 0);
    for i in 0..8 {
        let name = format!("race-{i}");
        upload_lines(&client, &name, &lines).await;
        let spec = relreward_tests::tiny_diffusion_spec(&name, &format!("out-{i}"), 0, long);
        let (delete, submit) = tokio::join!(client.delete_dataset(&name), client.submit_job(spec, None));
        match (delete, submit) {
            (Ok(()), Ok(job)) => panic!("round {i}: the dataset was deleted and job {} accepted on it", job.id),
            (Ok(()), Err(e)) => {
                assert_eq!(relreward_tests::status_code(&e), Some(Code::NotFound), "round {i}: {e}");
                deleted += 1;
            }
            (Err(e), Ok(job)) => {
                assert_eq!(relreward_tests::status_code(&e), Some(Code::FailedPrecondition), "round {i}: {e}");
                client.cancel_job(&job.id).await.expect("cancel");
                submitted += 1;
            }
            (Err(d), Err(s)) => panic!("round {i}: both refused: {d}; {s}"),
        }
    }
    assert_eq!(deleted + submitted, 8);
}
