//! What the service leaves in its data directory, end to end: uploads, deletes, refusals,
//! restarts and crashes leave exactly the published files of what is stored, no stray blob
//! and nothing in staging; stored files hold exactly the uploaded bytes. These tests look at
//! the embedded store's files (`blobs/`, a black box: counts and digests), which only the
//! server's own tests may do; everything else in them goes through the API, as in tests/.
//! Datasets, models, then the server-wide limits (disk budget, upload quota, deadlines).

mod store_layout;

use std::sync::Arc;
use std::time::Duration;

use relreward_client::MemorySource;
use relreward_client::client::{DatasetUpload, UploadProgress};
use relreward_client::pb::{self, Dtype, upload_model_request::Message as ModelMessage};
use relreward_client::tensor::encode_f32;
use relreward_tests::dataset_upload::{chunk, commit, header, raw_upload, sha, small_upload};
use relreward_tests::model_upload::{self, ENABLE, T, fixtures, read, sample_manifest, upload_messages};
use relreward_tests::{Lines, TestServer, eventually, status_code, try_upload_lines};
use store_layout::StoreLayout;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

fn model_blobs(server: &TestServer) -> usize {
    server.blob_count("models")
}

// ---------------------------------------------------------------------------------------------
// Datasets

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
    let dir =
        std::fs::read_dir(server.blob_path("datasets")).expect("blobs").next().expect("one").expect("entry").path();
    let file = std::fs::read(dir.join("samples.npy")).expect("npy");
    let header_len = u16::from_le_bytes([file[8], file[9]]) as usize + 10;
    assert_eq!(sha(&[&file[header_len..]]), stored.sha256);
}

// ---------------------------------------------------------------------------------------------
// Models

#[tokio::test(flavor = "multi_thread")]
async fn upload_get_list_delete_and_restart() {
    let fx = fixtures();
    let mut server = TestServer::start_with_env(&[ENABLE]);
    let client = server.client().await;
    let gaussian = read(fx.path(), "gaussian.pt");

    let model = model_upload::raw_upload(
        &client,
        upload_messages(model_upload::header("gauss", Some(sample_manifest(&[3]))), &gaussian, None),
    )
    .await
    .expect("upload");
    assert_eq!(model.name, "gauss");
    assert_eq!(model.kind, pb::ModelKind::Diffusion as i32);
    assert_eq!(model.format, pb::ModelFormat::Torchscript as i32);
    assert_eq!(model.manifest, Some(sample_manifest(&[3])), "the manifest comes back as sent");
    assert_eq!(model.sha256, model_upload::sha(&gaussian));
    assert_eq!(model.size_bytes, gaussian.len() as u64);
    assert_eq!(model.parameter_count, 0, "the analytic model has buffers only");
    assert_eq!(model.description, "fixture gauss");
    assert!(matches!(
        model.provenance.as_ref().and_then(|p| p.source.as_ref()),
        Some(pb::provenance::Source::Uploaded(_))
    ));
    assert!(model.created_at.as_ref().is_some_and(|t| t.seconds > 1_600_000_000));
    assert!(model.reward.is_none());
    assert_eq!(client.get_model("gauss").await.expect("get"), model, "GetModel returns what the upload returned");

    // Stored with the module, as DownloadModel hands them out: the module byte for byte, and
    // the manifest in the engine's JSON form, equal to what the Python exporter wrote for the
    // same model.
    let out = tempfile::tempdir().expect("tempdir");
    let got = client.download_model("gauss", out.path(), false).await.expect("download");
    assert_eq!(got.files, [out.path().join("module.pt")]);
    assert_eq!(std::fs::read(got.weights()).expect("module"), gaussian);
    let stored: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&got.manifest_path).expect("manifest")).expect("json");
    let exported: serde_json::Value = serde_json::from_slice(&read(fx.path(), "gaussian.json")).expect("json");
    assert_eq!(stored, exported);

    // A second model through the client library's own uploader: a trajectory model with an
    // nn.Linear(3, 3), i.e. 12 parameters, and a limits normalizer.
    let mut manifest = sample_manifest(&[]);
    manifest.parametrization = pb::Parametrization::X0 as i32;
    manifest.clip_denoised = true;
    manifest.schedule = Some(pb::Schedule {
        kind: Some(pb::schedule::Kind::Betas(pb::schedule::ExplicitBetas { betas: vec![0.02; T as usize] })),
    });
    manifest.space = Some(pb::diffusion_manifest::Space::Trajectory(pb::diffusion_manifest::Trajectory {
        horizon: 4,
        action_dim: 1,
        obs_dim: 2,
    }));
    manifest.normalizer = Some(pb::Normalizer {
        kind: Some(pb::normalizer::Kind::Limits(pb::normalizer::Limits {
            min: vec![-1.0, 0.0, 2.0],
            max: vec![1.0, 5.0, 3.0],
        })),
    });
    let progress = Arc::new(UploadProgress::default());
    let linear = client
        .upload_model(model_upload::header("a-linear", Some(manifest.clone())), &fx.path().join("linear.pt"), progress)
        .await
        .expect("client upload");
    assert_eq!(linear.parameter_count, 12);
    assert_eq!(linear.manifest, Some(manifest));
    assert_eq!(linear.sha256, model_upload::sha(&read(fx.path(), "linear.pt")));

    // Listing: by name, paged, filtered by kind.
    assert_eq!(model_upload::names(&client).await, ["a-linear", "gauss"]);
    let first = client
        .models()
        .list_models(pb::ListModelsRequest {
            page: Some(pb::PageRequest { page_size: 1, page_token: String::new() }),
            kind: 0,
        })
        .await
        .expect("page 1")
        .into_inner();
    assert_eq!((first.models.len(), first.next_page_token.as_str()), (1, "after:a-linear"));
    let second = client
        .models()
        .list_models(pb::ListModelsRequest {
            page: Some(pb::PageRequest { page_size: 1, page_token: first.next_page_token }),
            kind: 0,
        })
        .await
        .expect("page 2")
        .into_inner();
    assert_eq!(second.models.iter().map(|m| m.name.as_str()).collect::<Vec<_>>(), ["gauss"]);
    assert!(second.next_page_token.is_empty());
    assert_eq!(client.list_models(pb::ModelKind::Diffusion).await.expect("diffusion").len(), 2);
    assert!(client.list_models(pb::ModelKind::Reward).await.expect("reward").is_empty());
    let err = client.models().list_models(pb::ListModelsRequest { page: None, kind: 42 }).await.expect_err("kind");
    assert_eq!(err.code(), Code::InvalidArgument);

    // Models survive a restart, byte for byte.
    server.restart();
    let client = server.client().await;
    assert_eq!(client.get_model("gauss").await.expect("after restart"), model);

    // Delete: gone from Get, List and disk; a second delete and unknown names are NOT_FOUND.
    client.delete_model("gauss").await.expect("delete");
    let err = client.models().get_model(pb::GetModelRequest { name: "gauss".into() }).await.expect_err("gone");
    assert_eq!(err.code(), Code::NotFound);
    let err = client.models().delete_model(pb::DeleteModelRequest { name: "gauss".into() }).await.expect_err("twice");
    assert_eq!(err.code(), Code::NotFound);
    assert_eq!(model_upload::names(&client).await, ["a-linear"]);
    assert_eq!(model_blobs(&server), 1);
    let err = client.models().get_model(pb::GetModelRequest { name: "Not/A/Name".into() }).await.expect_err("bad name");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().starts_with("name:"), "{}", err.message());

    // The name is free again.
    model_upload::raw_upload(
        &client,
        upload_messages(model_upload::header("gauss", Some(sample_manifest(&[3]))), &gaussian, None),
    )
    .await
    .expect("upload under a freed name");
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_uploads_get_their_status_and_store_nothing() {
    let fx = fixtures();
    let server = TestServer::start_with_env(&[ENABLE]);
    let client = server.client().await;
    let gaussian = read(fx.path(), "gaussian.pt");
    model_upload::raw_upload(
        &client,
        upload_messages(model_upload::header("good", Some(sample_manifest(&[3]))), &gaussian, None),
    )
    .await
    .expect("baseline upload");
    assert_eq!(model_blobs(&server), 1);

    let ok = || Some(sample_manifest(&[3]));
    let edit = |f: &dyn Fn(&mut pb::DiffusionManifest)| {
        let mut m = sample_manifest(&[3]);
        f(&mut m);
        Some(m)
    };
    let upload = |name: &str, manifest: Option<pb::DiffusionManifest>, file: &str| {
        upload_messages(model_upload::header(name, manifest), &read(fx.path(), file), None)
    };
    let mut no_commit = upload("fresh", ok(), "gaussian.pt");
    no_commit.pop();
    let mut chunk_first = upload("fresh", ok(), "gaussian.pt");
    chunk_first.swap(0, 1);
    let mut after_commit = upload("fresh", ok(), "gaussian.pt");
    after_commit.push(model_upload::msg(ModelMessage::Chunk(vec![0; 10])));
    let truncated = upload_messages(model_upload::header("fresh", ok()), &gaussian[..gaussian.len() / 2], None);
    let garbage = upload_messages(model_upload::header("fresh", ok()), b"this is not a TorchScript archive", None);
    let betas = |n: usize| {
        Some(pb::Schedule {
            kind: Some(pb::schedule::Kind::Betas(pb::schedule::ExplicitBetas { betas: vec![0.01; n] })),
        })
    };

    let cases: Vec<(&str, Vec<pb::UploadModelRequest>, Code, Vec<&str>)> = vec![
        (
            "wrong output shape",
            upload("fresh", ok(), "wrong_shape.pt"),
            Code::InvalidArgument,
            vec!["[2, 2]", "[2, 3]"],
        ),
        ("NaN output", upload("fresh", ok(), "nan.pt"), Code::InvalidArgument, vec!["module:", "NaN"]),
        (
            "module raises",
            upload("fresh", ok(), "raises.pt"),
            Code::InvalidArgument,
            vec!["module:", "deliberate failure: this module always raises"],
        ),
        (
            "manifest shape the module cannot handle",
            upload("fresh", Some(sample_manifest(&[4])), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["module:", "[2, 4]"],
        ),
        ("truncated file", truncated, Code::InvalidArgument, vec!["module: not a loadable TorchScript file"]),
        ("not a TorchScript file", garbage, Code::InvalidArgument, vec!["module: not a loadable TorchScript file"]),
        (
            "unknown schedule kind",
            upload("fresh", edit(&|m| m.schedule = Some(pb::Schedule { kind: None })), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest.schedule:"],
        ),
        (
            "missing schedule",
            upload("fresh", edit(&|m| m.schedule = None), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest.schedule: missing"],
        ),
        (
            "missing parametrization",
            upload("fresh", edit(&|m| m.parametrization = 0), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest.parametrization"],
        ),
        (
            "missing n_timesteps",
            upload("fresh", edit(&|m| m.n_timesteps = 0), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest.n_timesteps"],
        ),
        (
            "missing space",
            upload("fresh", edit(&|m| m.space = None), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest.space: missing"],
        ),
        (
            "missing normalizer",
            upload("fresh", edit(&|m| m.normalizer = None), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest.normalizer: missing"],
        ),
        (
            "missing manifest",
            upload("fresh", None, "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest: missing"],
        ),
        (
            "betas length mismatch",
            upload("fresh", edit(&|m| m.schedule = betas(7)), "gaussian.pt"),
            Code::InvalidArgument,
            vec!["header.manifest.schedule.betas: 7 values but n_timesteps is 50"],
        ),
        (
            "normalizer length mismatch",
            upload(
                "fresh",
                edit(&|m| {
                    m.normalizer = Some(pb::Normalizer {
                        kind: Some(pb::normalizer::Kind::Gaussian(pb::normalizer::Gaussian {
                            mean: vec![0.0],
                            std: vec![1.0],
                        })),
                    })
                }),
                "gaussian.pt",
            ),
            Code::InvalidArgument,
            vec!["header.manifest.normalizer.mean"],
        ),
        (
            "digest mismatch",
            upload_messages(
                model_upload::header("fresh", ok()),
                &gaussian,
                Some(&model_upload::sha(b"something else")),
            ),
            Code::InvalidArgument,
            vec!["commit.sha256"],
        ),
        ("duplicate name", upload("good", ok(), "gaussian.pt"), Code::AlreadyExists, vec!["header.name", "'good'"]),
        ("bad name", upload("Bad/Name", ok(), "gaussian.pt"), Code::InvalidArgument, vec!["header.name:"]),
        ("no commit", no_commit, Code::InvalidArgument, vec!["without a commit"]),
        ("chunk before header", chunk_first, Code::InvalidArgument, vec!["must be a header"]),
        ("message after commit", after_commit, Code::InvalidArgument, vec!["commit: must be the last message"]),
        ("empty stream", Vec::new(), Code::InvalidArgument, vec!["empty"]),
    ];
    for (what, msgs, code, needles) in cases {
        let err = model_upload::raw_upload(&client, msgs).await.expect_err(what);
        eprintln!("{what}: {:?} {}", err.code(), err.message());
        assert_eq!(err.code(), code, "{what}: {}", err.message());
        for needle in needles {
            assert!(err.message().contains(needle), "{what}: '{}' should contain '{needle}'", err.message());
        }
        assert!(!err.message().contains(&server.data_dir.display().to_string()), "{what}: leaks a path");
        assert_eq!(model_upload::names(&client).await, ["good"], "{what}: nothing registered");
        assert!(eventually(5, || server.staging_entries() == 0).await, "{what}: staging left behind");
        assert_eq!(model_blobs(&server), 1, "{what}: no model files published");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn uploads_are_off_by_default_and_bounded_in_size() {
    let fx = fixtures();
    let gaussian = read(fx.path(), "gaussian.pt");
    let msgs = || upload_messages(model_upload::header("gauss", Some(sample_manifest(&[3]))), &gaussian, None);

    let server = TestServer::start();
    let client = server.client().await;
    let err = model_upload::raw_upload(&client, msgs()).await.expect_err("disabled");
    assert_eq!(err.code(), Code::FailedPrecondition);
    assert!(err.message().contains("models.allow_torchscript_upload"), "{}", err.message());
    assert!(err.message().contains("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD"), "{}", err.message());
    assert!(model_upload::names(&client).await.is_empty());
    assert_eq!((server.staging_entries(), model_blobs(&server)), (0, 0));
    drop(server);

    let limit = (gaussian.len() / 2).to_string();
    let server = TestServer::start_with_env(&[ENABLE, ("RELREWARD__MODELS__MAX_UPLOAD_BYTES", &limit)]);
    let client = server.client().await;
    let err = model_upload::raw_upload(&client, msgs()).await.expect_err("too large");
    assert_eq!(err.code(), Code::ResourceExhausted);
    assert!(err.message().contains("models.max_upload_bytes"), "{}", err.message());
    assert!(model_upload::names(&client).await.is_empty());
    assert!(eventually(5, || server.staging_entries() == 0).await);
    assert_eq!(model_blobs(&server), 0);
}

#[tokio::test(flavor = "multi_thread")]
async fn uploads_count_against_the_disk_budget() {
    // A budget the metadata database alone nearly fills: a 2 MB module does not fit.
    let server = TestServer::start_with_env(&[ENABLE, ("RELREWARD__STORAGE__MAX_BYTES", "1000000")]);
    let client = server.client().await;
    let bytes = vec![7u8; 2_000_000];
    let err = model_upload::raw_upload(
        &client,
        upload_messages(model_upload::header("huge", Some(sample_manifest(&[3]))), &bytes, None),
    )
    .await
    .expect_err("beyond the disk budget");
    assert_eq!(err.code(), Code::ResourceExhausted, "{}", err.message());
    assert!(err.message().contains("storage.max_bytes") && err.message().contains("'huge'"), "{}", err.message());
    assert!(model_upload::names(&client).await.is_empty());
    assert!(eventually(5, || server.staging_entries() == 0).await, "the refused upload left staging files");
    assert_eq!(model_blobs(&server), 0);
}

// ---------------------------------------------------------------------------------------------
// Limits

/// 7000 episodes of 24 rows x (2 + 2 float32 + 1 bool) = 2 856 000 payload bytes.
const BIG: Lines =
    Lines { episodes: 7000, seed: 1, start: [(1.0, 0.0), (1.0, 0.0)], velocity: [(0.1, 0.0), (0.1, 0.0)] };

#[tokio::test(flavor = "multi_thread")]
async fn disk_budget_refuses_uploads_beyond_it_and_leaves_nothing_behind() {
    // Room for two BIG uploads and the metadata database, not three.
    let server = TestServer::start_with_env(&[("RELREWARD__STORAGE__MAX_BYTES", "7500000")]);
    let client = server.client().await;
    try_upload_lines(&client, "one", &BIG).await.expect("first upload fits");
    try_upload_lines(&client, "two", &BIG).await.expect("second upload fits");
    let err = try_upload_lines(&client, "three", &BIG).await.expect_err("third is beyond the budget");
    assert_eq!(status_code(&err), Some(Code::ResourceExhausted), "{err}");
    let msg = err.to_string();
    assert!(msg.contains("storage.max_bytes") && msg.contains("'three'"), "names the limit and the upload: {msg}");
    assert_eq!(server.staging_entries(), 0, "the refused upload left staging files");
    assert_eq!(server.dataset_blobs(), 2, "only the two stored datasets are on disk");
    let err = client.get_dataset("three").await.expect_err("not stored");
    assert_eq!(status_code(&err), Some(Code::NotFound));

    // Deleting one gives its room back.
    client.delete_dataset("one").await.expect("delete");
    try_upload_lines(&client, "three", &BIG).await.expect("fits after a delete");
    assert_eq!(server.dataset_blobs(), 2);
}

#[tokio::test(flavor = "multi_thread")]
async fn the_per_upload_quota_names_its_key() {
    let server = TestServer::start_with_env(&[("RELREWARD__DATASETS__MAX_UPLOAD_BYTES", "100000")]);
    let client = server.client().await;
    let err = try_upload_lines(&client, "big", &BIG).await.expect_err("beyond the quota");
    assert_eq!(status_code(&err), Some(Code::ResourceExhausted), "{err}");
    assert!(err.to_string().contains("datasets.max_upload_bytes"), "{err}");
    assert_eq!(server.staging_entries(), 0);
    assert_eq!(server.dataset_blobs(), 0);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_passed_deadline_is_deadline_exceeded_and_an_upload_leaves_nothing() {
    let server = TestServer::start();
    let client = server.client().await;
    // Connected before the timed call: the client's own timer for the deadline also runs
    // while it connects, which the server cannot see.
    client.list_datasets().await.expect("warm-up call");
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let header = pb::UploadHeader {
        name: "stalled".into(),
        kind: pb::DatasetKind::Samples as i32,
        arrays: vec![pb::ArraySpec { name: "samples".into(), dtype: pb::Dtype::Float32 as i32, shape: vec![4, 2] }],
        description: String::new(),
    };
    tx.send(pb::UploadDatasetRequest { message: Some(pb::upload_dataset_request::Message::Header(header)) })
        .await
        .expect("queue header");
    let mut request = tonic::Request::new(ReceiverStream::new(rx));
    request.set_timeout(Duration::from_millis(400));
    // The client then stalls (keeps `tx` open and sends nothing more).
    let err = client.datasets().upload_dataset(request).await.expect_err("the deadline passes");
    assert_eq!(err.code(), Code::DeadlineExceeded, "{err:?}");
    drop(tx);
    assert!(relreward_tests::eventually(5, || server.staging_entries() == 0).await, "staging left behind");
    assert_eq!(server.dataset_blobs(), 0);
}
