//! The model registry end to end: TorchScript uploads through the real server binary, checked
//! against fixtures exported by `tests/python/export_models.py` (an exact Gaussian eps-model, a
//! linear model with known parameters, and modules that break their manifest in each way).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use relreward_client::Client;
use relreward_client::client::UploadProgress;
use relreward_client::pb::{self, upload_model_request::Message};
use relreward_tests::{TestServer, eventually, python, repo_root, stderr};
use sha2::{Digest, Sha256};
use tonic::Code;

const ENABLE: (&str, &str) = ("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true");
/// The Gaussian fixture: data N(MEAN, I), cosine schedule, T = 50.
const MEAN: &str = "1,-2,0.5";
const T: u32 = 50;

/// Exports the fixtures into a fresh directory.
fn fixtures() -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = Command::new(python())
        .arg(repo_root().join("tests/python/export_models.py"))
        .args(["--out", dir.path().to_str().expect("utf-8 path"), "--mean", MEAN, "--T", &T.to_string()])
        .output()
        .expect("run export_models.py");
    assert!(out.status.success(), "export_models.py failed: {}", String::from_utf8_lossy(&out.stderr));
    dir
}

fn read(dir: &Path, name: &str) -> Vec<u8> {
    std::fs::read(dir.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn sha(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// The manifest of the Gaussian fixture: eps, cosine (s = 0.008), T = 50, samples [3], identity.
fn sample_manifest(shape: &[u64]) -> pb::DiffusionManifest {
    pb::DiffusionManifest {
        parametrization: pb::Parametrization::Epsilon as i32,
        schedule: Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.008 })) }),
        n_timesteps: T,
        clip_denoised: false,
        space: Some(pb::diffusion_manifest::Space::Sample(pb::diffusion_manifest::Sample { shape: shape.to_vec() })),
        normalizer: Some(pb::Normalizer { kind: Some(pb::normalizer::Kind::Identity(pb::normalizer::Identity {})) }),
        architecture: None,
    }
}

fn header(name: &str, manifest: Option<pb::DiffusionManifest>) -> pb::UploadModelHeader {
    pb::UploadModelHeader { name: name.into(), manifest, description: format!("fixture {name}"), format: 0 }
}

fn msg(m: Message) -> pb::UploadModelRequest {
    pb::UploadModelRequest { message: Some(m) }
}

/// Header, the bytes in 1000-byte chunks, and a commit with `digest` (the bytes' sha256 when
/// `None`).
fn upload_messages(header: pb::UploadModelHeader, bytes: &[u8], digest: Option<&str>) -> Vec<pb::UploadModelRequest> {
    let mut msgs = vec![msg(Message::Header(header))];
    msgs.extend(bytes.chunks(1000).map(|c| msg(Message::Chunk(c.to_vec()))));
    let digest = digest.map_or_else(|| sha(bytes), str::to_owned);
    msgs.push(msg(Message::Commit(pb::UploadCommit { sha256: digest })));
    msgs
}

async fn raw_upload(client: &Client, msgs: Vec<pb::UploadModelRequest>) -> Result<pb::Model, tonic::Status> {
    client.models().upload_model(tokio_stream::iter(msgs)).await.map(|r| r.into_inner())
}

async fn names(client: &Client) -> Vec<String> {
    client.list_models(pb::ModelKind::Unspecified).await.expect("list").into_iter().map(|m| m.name).collect()
}

fn model_blobs(server: &TestServer) -> usize {
    std::fs::read_dir(server.data_dir.join("blobs/models")).map(|d| d.count()).unwrap_or(0)
}

fn model_dirs(server: &TestServer) -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(server.data_dir.join("blobs/models"))
        .map(|d| d.map(|e| e.expect("entry").path()).collect())
        .unwrap_or_default();
    dirs.sort();
    dirs
}

#[tokio::test(flavor = "multi_thread")]
async fn upload_get_list_delete_and_restart() {
    let fx = fixtures();
    let mut server = TestServer::start_with_env(&[ENABLE]);
    let client = server.client().await;
    let gaussian = read(fx.path(), "gaussian.pt");

    let model = raw_upload(&client, upload_messages(header("gauss", Some(sample_manifest(&[3]))), &gaussian, None))
        .await
        .expect("upload");
    assert_eq!(model.name, "gauss");
    assert_eq!(model.kind, pb::ModelKind::Diffusion as i32);
    assert_eq!(model.format, pb::ModelFormat::Torchscript as i32);
    assert_eq!(model.manifest, Some(sample_manifest(&[3])), "the manifest comes back as sent");
    assert_eq!(model.sha256, sha(&gaussian));
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

    // Stored beside the module: the manifest in the engine's JSON form, equal to what the
    // Python exporter wrote for the same model.
    let dirs = model_dirs(&server);
    assert_eq!(dirs.len(), 1);
    assert_eq!(std::fs::read(dirs[0].join("module.pt")).expect("module"), gaussian);
    let stored: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dirs[0].join("manifest.json")).expect("manifest")).expect("json");
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
        .upload_model(header("a-linear", Some(manifest.clone())), &fx.path().join("linear.pt"), progress)
        .await
        .expect("client upload");
    assert_eq!(linear.parameter_count, 12);
    assert_eq!(linear.manifest, Some(manifest));
    assert_eq!(linear.sha256, sha(&read(fx.path(), "linear.pt")));

    // Listing: by name, paged, filtered by kind.
    assert_eq!(names(&client).await, ["a-linear", "gauss"]);
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
    assert_eq!(names(&client).await, ["a-linear"]);
    assert_eq!(model_blobs(&server), 1);
    let err = client.models().get_model(pb::GetModelRequest { name: "Not/A/Name".into() }).await.expect_err("bad name");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().starts_with("name:"), "{}", err.message());

    // The name is free again.
    raw_upload(&client, upload_messages(header("gauss", Some(sample_manifest(&[3]))), &gaussian, None))
        .await
        .expect("upload under a freed name");
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_uploads_get_their_status_and_store_nothing() {
    let fx = fixtures();
    let server = TestServer::start_with_env(&[ENABLE]);
    let client = server.client().await;
    let gaussian = read(fx.path(), "gaussian.pt");
    raw_upload(&client, upload_messages(header("good", Some(sample_manifest(&[3]))), &gaussian, None))
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
        upload_messages(header(name, manifest), &read(fx.path(), file), None)
    };
    let mut no_commit = upload("fresh", ok(), "gaussian.pt");
    no_commit.pop();
    let mut chunk_first = upload("fresh", ok(), "gaussian.pt");
    chunk_first.swap(0, 1);
    let mut after_commit = upload("fresh", ok(), "gaussian.pt");
    after_commit.push(msg(Message::Chunk(vec![0; 10])));
    let truncated = upload_messages(header("fresh", ok()), &gaussian[..gaussian.len() / 2], None);
    let garbage = upload_messages(header("fresh", ok()), b"this is not a TorchScript archive", None);
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
            upload_messages(header("fresh", ok()), &gaussian, Some(&sha(b"something else"))),
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
        let err = raw_upload(&client, msgs).await.expect_err(what);
        eprintln!("{what}: {:?} {}", err.code(), err.message());
        assert_eq!(err.code(), code, "{what}: {}", err.message());
        for needle in needles {
            assert!(err.message().contains(needle), "{what}: '{}' should contain '{needle}'", err.message());
        }
        assert!(!err.message().contains(&server.data_dir.display().to_string()), "{what}: leaks a path");
        assert_eq!(names(&client).await, ["good"], "{what}: nothing registered");
        assert!(eventually(5, || server.staging_entries() == 0).await, "{what}: staging left behind");
        assert_eq!(model_blobs(&server), 1, "{what}: no model files published");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn uploads_are_off_by_default_and_bounded_in_size() {
    let fx = fixtures();
    let gaussian = read(fx.path(), "gaussian.pt");
    let msgs = || upload_messages(header("gauss", Some(sample_manifest(&[3]))), &gaussian, None);

    let server = TestServer::start();
    let client = server.client().await;
    let err = raw_upload(&client, msgs()).await.expect_err("disabled");
    assert_eq!(err.code(), Code::FailedPrecondition);
    assert!(err.message().contains("models.allow_torchscript_upload"), "{}", err.message());
    assert!(err.message().contains("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD"), "{}", err.message());
    assert!(names(&client).await.is_empty());
    assert_eq!((server.staging_entries(), model_blobs(&server)), (0, 0));
    drop(server);

    let limit = (gaussian.len() / 2).to_string();
    let server = TestServer::start_with_env(&[ENABLE, ("RELREWARD__MODELS__MAX_UPLOAD_BYTES", &limit)]);
    let client = server.client().await;
    let err = raw_upload(&client, msgs()).await.expect_err("too large");
    assert_eq!(err.code(), Code::ResourceExhausted);
    assert!(err.message().contains("models.max_upload_bytes"), "{}", err.message());
    assert!(names(&client).await.is_empty());
    assert!(eventually(5, || server.staging_entries() == 0).await);
    assert_eq!(model_blobs(&server), 0);
}

#[tokio::test(flavor = "multi_thread")]
async fn uploads_count_against_the_disk_budget() {
    // A budget the metadata database alone nearly fills: a 2 MB module does not fit.
    let server = TestServer::start_with_env(&[ENABLE, ("RELREWARD__STORAGE__MAX_BYTES", "1000000")]);
    let client = server.client().await;
    let bytes = vec![7u8; 2_000_000];
    let err = raw_upload(&client, upload_messages(header("huge", Some(sample_manifest(&[3]))), &bytes, None))
        .await
        .expect_err("beyond the disk budget");
    assert_eq!(err.code(), Code::ResourceExhausted, "{}", err.message());
    assert!(err.message().contains("storage.max_bytes") && err.message().contains("'huge'"), "{}", err.message());
    assert!(names(&client).await.is_empty());
    assert!(eventually(5, || server.staging_entries() == 0).await, "the refused upload left staging files");
    assert_eq!(model_blobs(&server), 0);
}

/// Native weights: a Diffuser TemporalUnet built in PyTorch (`export_diffuser_temporal.py`),
/// converted and registered in one command by `relreward model import --name` on a server that
/// refuses TorchScript (native weights are data, never code). GetModel reports the native
/// format and the architecture; the stored file is the imported one, byte for byte; the model
/// samples, and is served again after a restart. (That these weights give the PyTorch module's
/// outputs, loaded the way the registry loads them, is server/tests/diffuser_import.rs.)
/// Refusals name the field or the tensor, and store nothing.
#[tokio::test(flavor = "multi_thread")]
async fn native_weights_register_through_model_import() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let out = Command::new(python())
        .arg(repo_root().join("tests/python/export_diffuser_temporal.py"))
        .arg(d)
        .output()
        .expect("run export_diffuser_temporal.py");
    assert!(out.status.success(), "export failed: {}", String::from_utf8_lossy(&out.stderr));
    std::fs::write(
        d.join("manifest.toml"),
        "parametrization = \"x0\"\nn_timesteps = 20\nclip_denoised = true\nschedule = { kind = \"diffuser_cosine\" }\n\
         space = { kind = \"trajectory\", horizon = 8, action_dim = 2, obs_dim = 3 }\n",
    )
    .expect("manifest");
    let path = |name: &str| d.join(name).to_str().expect("utf-8 path").to_owned();

    let mut server = TestServer::start();
    let client = server.client().await;
    let import = |server: &TestServer, name: &str, extra: &[&str]| {
        let mut args = vec!["--json", "model", "import"];
        let (npz, manifest, weights) = (path("state_dict.npz"), path("manifest.toml"), path("weights.safetensors"));
        args.extend([npz.as_str(), "--manifest", manifest.as_str(), "--dim", "8", "--dim-mults", "1,2"]);
        args.extend(["--prefix", "model.", "--out", weights.as_str(), "--name", name]);
        args.extend(extra);
        server.cli(&args)
    };
    let out = import(&server, "diffuser-native", &["--description", "imported"]);
    assert!(out.status.success(), "import --name failed:\n{}\n{}", stderr(&out), server.log());
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    assert_eq!(report["model"]["name"], "diffuser-native");

    let model = client.get_model("diffuser-native").await.expect("get");
    assert_eq!(model.format, pb::ModelFormat::Native as i32);
    assert_eq!(model.kind, pb::ModelKind::Diffusion as i32);
    assert_eq!(model.description, "imported");
    let manifest = model.manifest.expect("manifest");
    assert_eq!(
        manifest.architecture,
        Some(pb::diffusion_manifest::Architecture::TemporalUnet(pb::TemporalUnet {
            dim: Some(8),
            dim_mults: vec![1, 2]
        }))
    );
    assert_eq!(model.parameter_count, report["parameters"].as_u64().expect("parameters"));
    let weights = std::fs::read(d.join("weights.safetensors")).expect("weights");
    assert_eq!(model.sha256, sha(&weights));
    let dirs = model_dirs(&server);
    assert_eq!(std::fs::read(dirs[0].join("weights.safetensors")).expect("stored"), weights);

    let sample = |client: Client| async move {
        let req = pb::SampleRequest { model: "diffuser-native".into(), n: 2, seed: Some(3), ..Default::default() };
        let mut stream = client.rewards().sample(req).await.expect("sample").into_inner();
        let mut items = Vec::new();
        while let Some(item) = tokio_stream::StreamExt::next(&mut stream).await {
            let x = item.expect("item").x.expect("x");
            assert_eq!(x.shape, vec![8, 5]);
            items.push(relreward_client::tensor::decode_finite_f32(&x).expect("finite"));
        }
        assert_eq!(items.len(), 2);
        items
    };
    let before = sample(client.clone()).await;
    server.restart();
    let client = server.client().await;
    assert_eq!(sample(client.clone()).await, before, "the same weights are served after a restart");

    // Refusals. The manifest must name an architecture for native weights, and only then.
    let header = |name: &str, manifest: pb::DiffusionManifest, format: pb::ModelFormat| pb::UploadModelHeader {
        name: name.into(),
        manifest: Some(manifest),
        description: String::new(),
        format: format as i32,
    };
    let mut bare = manifest.clone();
    bare.architecture = None;
    let err = raw_upload(&client, upload_messages(header("n1", bare, pb::ModelFormat::Native), &weights, None))
        .await
        .expect_err("no architecture");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().starts_with("header.manifest.architecture: missing"), "{}", err.message());
    let err = raw_upload(
        &client,
        upload_messages(header("n2", manifest.clone(), pb::ModelFormat::Torchscript), &weights, None),
    )
    .await
    .expect_err("torchscript with an architecture");
    assert_eq!(err.code(), Code::FailedPrecondition, "TorchScript stays disabled: {}", err.message());
    // Weights of another architecture: the strict load names the tensors.
    let mut wider = manifest.clone();
    wider.architecture = Some(pb::diffusion_manifest::Architecture::TemporalUnet(pb::TemporalUnet {
        dim: Some(16),
        dim_mults: vec![1, 2],
    }));
    let err = raw_upload(&client, upload_messages(header("n3", wider, pb::ModelFormat::Native), &weights, None))
        .await
        .expect_err("mis-shaped");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(
        err.message().starts_with("chunk: the uploaded weights do not fit header.manifest.architecture"),
        "{}",
        err.message()
    );
    assert!(err.message().contains("has shape"), "{}", err.message());
    // Bytes that are not safetensors at all.
    let err = raw_upload(
        &client,
        upload_messages(header("n4", manifest.clone(), pb::ModelFormat::Native), b"not weights", None),
    )
    .await
    .expect_err("garbage");
    assert_eq!(err.code(), Code::InvalidArgument, "{}", err.message());
    assert!(err.message().starts_with("chunk:"), "{}", err.message());
    let err = raw_upload(
        &client,
        upload_messages(header("n5", manifest.clone(), pb::ModelFormat::Native), &weights, None)
            .into_iter()
            .map(|mut m| {
                if let Some(Message::Header(h)) = &mut m.message {
                    h.format = 7;
                }
                m
            })
            .collect(),
    )
    .await
    .expect_err("unknown format");
    assert!(err.message().starts_with("header.format: unknown value 7"), "{}", err.message());
    // Weights of the right shapes with a NaN in them (the last float of the data section):
    // refused by the validation forward, not served.
    let mut poisoned = weights.clone();
    let end = poisoned.len();
    poisoned[end - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    let err =
        raw_upload(&client, upload_messages(header("n6", manifest.clone(), pb::ModelFormat::Native), &poisoned, None))
            .await
            .expect_err("NaN weights");
    assert_eq!(err.code(), Code::InvalidArgument, "{}", err.message());
    assert!(err.message().starts_with("chunk: the uploaded weights' forward"), "{}", err.message());
    assert!(err.message().contains("NaN"), "{}", err.message());
    assert_eq!(names(&client).await, vec!["diffuser-native".to_owned()], "nothing else was stored");
    assert_eq!(server.staging_entries(), 0, "no staging left behind");
    // The CLI names a manifest architecture that disagrees with the flags, before any work.
    std::fs::write(
        d.join("manifest.toml"),
        format!(
            "{}architecture = {{ kind = \"temporal_unet\", dim = 16, dim_mults = [1, 2] }}\n",
            std::fs::read_to_string(d.join("manifest.toml")).expect("read")
        ),
    )
    .expect("manifest");
    let out = import(&server, "n6", &[]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("architecture: temporal_unet (dim 16, dim_mults [1, 2]) disagrees with --dim 8"),
        "{}",
        stderr(&out)
    );
}
