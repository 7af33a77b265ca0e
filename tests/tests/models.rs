//! The model registry end to end: TorchScript uploads through the real server binary, checked
//! against fixtures exported by `tests/python/export_models.py` (an exact Gaussian eps-model, a
//! linear model with known parameters, and modules that break their manifest in each way);
//! native weights; downloads; autoencoders with Encode and Decode.

use std::path::Path;
use std::process::Command;

use relreward_client::Client;
use relreward_client::pb::{self, upload_model_request::Message};
use relreward_tests::model_upload::{
    ENABLE, fixtures, header, names, raw_upload, read, sample_manifest, sha, upload_messages,
};
use relreward_tests::{TestServer, python, repo_root, stderr, train_tiny_reward};
use tonic::Code;

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
    // Registration refused after the conversion (the name is taken): the command fails and
    // leaves no weights at --out, nor a partial file beside it.
    let taken_out = path("taken.safetensors");
    let files_before = file_names(d);
    let mut args = vec!["model", "import"];
    let (npz, manifest_path) = (path("state_dict.npz"), path("manifest.toml"));
    args.extend([npz.as_str(), "--manifest", manifest_path.as_str(), "--dim", "8", "--dim-mults", "1,2"]);
    args.extend(["--prefix", "model.", "--out", taken_out.as_str(), "--name", "diffuser-native"]);
    let out = server.cli(&args);
    assert!(!out.status.success(), "a taken name");
    assert!(stderr(&out).contains("taken.safetensors was not written"), "{}", stderr(&out));
    assert_eq!(file_names(d), files_before, "--out was not written");

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
    let stored = client.download_model("diffuser-native", &d.join("stored"), false).await.expect("download");
    assert_eq!(std::fs::read(stored.weights()).expect("stored"), weights);

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
        reward: None,
        autoencoder: None,
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
    // refused naming the tensor and the index, not served.
    let mut poisoned = weights.clone();
    let end = poisoned.len();
    poisoned[end - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    let err =
        raw_upload(&client, upload_messages(header("n6", manifest.clone(), pb::ModelFormat::Native), &poisoned, None))
            .await
            .expect_err("NaN weights");
    assert_eq!(err.code(), Code::InvalidArgument, "{}", err.message());
    assert!(err.message().starts_with("chunk: the uploaded weights: tensor '"), "{}", err.message());
    assert!(err.message().contains("' holds a non-finite value (NaN) at index ["), "{}", err.message());
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
    // A name the server would refuse is refused first, and --out is never written (nor a
    // partial file beside it).
    let fresh = path("fresh.safetensors");
    let mut args = vec!["model", "import"];
    let (npz, manifest_path) = (path("state_dict.npz"), path("manifest.toml"));
    args.extend([npz.as_str(), "--manifest", manifest_path.as_str(), "--dim", "8", "--dim-mults", "1,2"]);
    args.extend(["--prefix", "model.", "--out", fresh.as_str(), "--name", "../x"]);
    let files_before = file_names(d);
    let out = server.cli(&args);
    assert_eq!(out.status.code(), Some(2), "a usage error: {}", stderr(&out));
    assert!(stderr(&out).contains("--name: \"../x\" is not a valid model name"), "{}", stderr(&out));
    assert_eq!(file_names(d), files_before, "--out was not written");
    assert_eq!(names(&client).await, vec!["diffuser-native".to_owned()], "nothing else was stored");

    let out = import(&server, "n6", &[]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("architecture: temporal_unet (dim 16, dim_mults [1, 2]) disagrees with --dim 8"),
        "{}",
        stderr(&out)
    );
}

/// Names of the files in `dir`, sorted.
fn file_names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("read dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// DownloadModel hands out what the store holds, checked: an uploaded module byte for byte
/// with its manifest, a trained reward's native weights with its manifest (what a PyTorch user
/// rebuilds the net from); through the client library and the CLI, which refuses to overwrite
/// without --force. An unknown name is NOT_FOUND naming the model, a malformed one
/// INVALID_ARGUMENT naming `name`.
#[tokio::test(flavor = "multi_thread")]
async fn download_returns_the_stored_files() {
    let fx = fixtures();
    let server = TestServer::start_with_env(&[ENABLE]);
    let client = server.client().await;
    let gaussian = read(fx.path(), "gaussian.pt");
    let uploaded = raw_upload(&client, upload_messages(header("gauss", Some(sample_manifest(&[3]))), &gaussian, None))
        .await
        .expect("upload");
    let out = tempfile::tempdir().expect("tempdir");

    // The uploaded module: the same bytes and digest, the record GetModel returns, the manifest.
    let dir = out.path().join("gauss");
    let got = client.download_model("gauss", &dir, false).await.expect("download");
    assert_eq!(got.model, uploaded);
    assert_eq!(got.weights(), dir.join("module.pt"));
    let bytes = std::fs::read(got.weights()).expect("module");
    assert_eq!((sha(&bytes), bytes.len() as u64), (uploaded.sha256.clone(), uploaded.size_bytes));
    assert_eq!(bytes, gaussian);
    let exported: serde_json::Value = serde_json::from_slice(&read(fx.path(), "gaussian.json")).expect("json");
    assert_eq!(serde_json::from_str::<serde_json::Value>(&got.manifest_json).expect("json"), exported);
    assert_eq!(file_names(&dir), ["manifest.json", "module.pt"], "the files and nothing else (no part files)");

    // An existing file is kept unless overwriting is asked for.
    std::fs::write(dir.join("module.pt"), b"mine").expect("write");
    let err = client.download_model("gauss", &dir, false).await.expect_err("exists");
    assert!(err.to_string().contains("module.pt: exists"), "{err}");
    assert_eq!(std::fs::read(dir.join("module.pt")).expect("kept"), b"mine");
    client.download_model("gauss", &dir, true).await.expect("overwrite");
    assert_eq!(std::fs::read(dir.join("module.pt")).expect("module"), gaussian);

    // Unknown and malformed names.
    let req = |name: &str| pb::DownloadModelRequest { name: name.into(), ..Default::default() };
    let err = client.models().download_model(req("no-such-model")).await.expect_err("unknown");
    assert_eq!(err.code(), Code::NotFound);
    assert!(err.message().starts_with("name:") && err.message().contains("'no-such-model'"), "{}", err.message());
    let err = client.models().download_model(req("Not A Name")).await.expect_err("malformed");
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().starts_with("name:"), "{}", err.message());
    assert!(client.download_model("no-such-model", &out.path().join("none"), false).await.is_err());
    assert!(!out.path().join("none").exists(), "a failed download leaves nothing behind");

    // The CLI writes the same files; again only with --force.
    let cli_dir = out.path().join("cli");
    let cli_dir_arg = cli_dir.to_str().expect("utf-8 path");
    let run = server.cli(&["--json", "model", "download", "gauss", "--out", cli_dir_arg]);
    assert!(run.status.success(), "model download failed:\n{}", stderr(&run));
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).expect("json");
    assert_eq!(report["model"]["sha256"], uploaded.sha256);
    assert_eq!(report["weights"], cli_dir.join("module.pt").to_str().expect("utf-8"));
    assert_eq!(std::fs::read(cli_dir.join("module.pt")).expect("module"), gaussian);
    assert_eq!(file_names(&cli_dir), ["manifest.json", "module.pt"]);
    let again = server.cli(&["model", "download", "gauss", "--out", cli_dir_arg]);
    assert!(!again.status.success() && stderr(&again).contains("--force"), "{}", stderr(&again));
    let forced = server.cli(&["model", "download", "gauss", "--out", cli_dir_arg, "--force"]);
    assert!(forced.status.success(), "{}", stderr(&forced));

    // A trained reward: its native weights and the manifest that rebuilds the net.
    let tiny = train_tiny_reward(&server, out.path());
    let reward = client.get_model(&tiny.reward).await.expect("reward");
    let got = client.download_model(&tiny.reward, &out.path().join("reward"), false).await.expect("download reward");
    assert_eq!(got.model, reward);
    assert_eq!(got.weights(), out.path().join("reward").join("weights.safetensors"));
    let bytes = std::fs::read(got.weights()).expect("weights");
    assert_eq!((sha(&bytes), bytes.len() as u64), (reward.sha256.clone(), reward.size_bytes));
    let manifest: serde_json::Value = serde_json::from_str(&got.manifest_json).expect("json");
    assert_eq!(manifest["architecture"], serde_json::json!({"kind": "windowed_mlp", "window": 4, "hidden": [16, 16]}));
    assert_eq!(manifest["space"]["horizon"], tiny.horizon);
    assert_eq!(manifest["n_timesteps"], tiny.n_timesteps);
    assert!(manifest["normalizer"]["kind"].is_string(), "{manifest}");
}

/// Scripts an autoencoder with PyTorch into `dir/ae.pt`: images [1, 4, 4] to latents [1, 2, 2]
/// by 2x2 average pooling times 3; latents back by nearest upsampling times 0.5.
const SCRIPT_AUTOENCODER: &str = r#"
import sys
import torch
import torch.nn.functional as F

class Pool(torch.nn.Module):
    @torch.jit.export
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x, 2) * 3.0
    @torch.jit.export
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return F.interpolate(z, scale_factor=2.0, mode="nearest") * 0.5

torch.jit.script(Pool()).save(sys.argv[1] + "/ae.pt")
"#;

/// An autoencoder end to end (issue 37, item 3): uploaded with `header.autoencoder` through the
/// client library, reported by GetModel and ListModels with its shapes and scaling, run by
/// Encode and Decode with diffusers' scaling ((encode(x) - shift) * scale, decode(z / scale +
/// shift)) against the analytic answer, by the CLI's `encode` / `decode` over .npz files (other
/// arrays copied), and refused by name: Encode of an unknown model NOT_FOUND, of a diffusion
/// model FAILED_PRECONDITION, of the wrong shape INVALID_ARGUMENT naming `images`; `model
/// export` of it FAILED_PRECONDITION. Deleted like any model.
#[tokio::test(flavor = "multi_thread")]
async fn autoencoders_upload_encode_and_decode() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    // From a file: torch.jit.script reads the module's source (`python -c` has none).
    std::fs::write(d.join("make_ae.py"), SCRIPT_AUTOENCODER).expect("script");
    let out = Command::new(python()).arg(d.join("make_ae.py")).arg(d).output().expect("python");
    assert!(out.status.success(), "scripting failed: {}", String::from_utf8_lossy(&out.stderr));
    let fx = fixtures();
    let server = TestServer::start_with_env(&[ENABLE]);
    let client = server.client().await;
    let manifest = pb::AutoencoderUploadManifest {
        image_shape: vec![1, 4, 4],
        latent_shape: vec![1, 2, 2],
        scaling_factor: Some(0.5),
        shift_factor: Some(0.25),
    };
    let ae_header = pb::UploadModelHeader {
        name: "ae".into(),
        autoencoder: Some(manifest),
        format: pb::ModelFormat::Torchscript as i32,
        ..Default::default()
    };
    let progress = std::sync::Arc::new(relreward_client::client::UploadProgress::default());
    let model = client.upload_model(ae_header, &d.join("ae.pt"), progress).await.expect("upload");
    assert_eq!((model.kind(), model.format()), (pb::ModelKind::Autoencoder, pb::ModelFormat::Torchscript));
    let info = model.autoencoder.clone().expect("autoencoder info");
    assert_eq!((info.image_shape, info.latent_shape), (vec![1, 4, 4], vec![1, 2, 2]));
    assert_eq!((info.scaling_factor, info.shift_factor), (0.5, 0.25));
    assert!(model.manifest.is_none() && model.reward.is_none());
    let listed = client.list_models(pb::ModelKind::Autoencoder).await.expect("list");
    assert_eq!(listed, vec![model.clone()]);

    // Two images 0..16 and 16..32: block means, times 3, then (z - 0.25) * 0.5.
    let x: Vec<f32> = (0..32).map(|i| i as f32).collect();
    let images = relreward_client::tensor::encode_f32(&[2, 1, 4, 4], &x);
    let req = pb::EncodeRequest { model: "ae".into(), images: Some(images.clone()) };
    let latents = client.encode(req).await.expect("encode").latents.expect("latents");
    assert_eq!(latents.shape, vec![2, 1, 2, 2]);
    let z = relreward_client::tensor::decode_finite_f32(&latents).expect("finite");
    let means = [2.5f32, 4.5, 10.5, 12.5, 18.5, 20.5, 26.5, 28.5];
    let want: Vec<f32> = means.iter().map(|m| (m * 3.0 - 0.25) * 0.5).collect();
    assert_eq!(z, want);
    let req = pb::DecodeRequest { model: "ae".into(), latents: Some(latents) };
    let back = client.decode(req).await.expect("decode").images.expect("images");
    assert_eq!(back.shape, vec![2, 1, 4, 4]);
    let back = relreward_client::tensor::decode_finite_f32(&back).expect("finite");
    // decode(z / 0.5 + 0.25) = (block mean * 3) * 0.5 at each of the block's four pixels.
    assert_eq!((back[0], back[5], back[2], back[31]), (3.75, 3.75, 6.75, 42.75));

    // The CLI over .npz files: the result under x, the labels copied.
    let npz = d.join("images.npz");
    relreward_tests::run_python(
        "import sys, numpy as np; np.savez(sys.argv[1], x=np.arange(32, dtype=np.float32).reshape(2, 1, 4, 4), \
         y=np.array([7, 9]))",
        &[npz.to_str().expect("utf-8")],
    );
    let (latents_npz, decoded_npz) = (d.join("latents.npz"), d.join("decoded.npz"));
    let out = server.cli(&[
        "encode",
        "--model",
        "ae",
        "--input",
        npz.to_str().expect("utf-8"),
        "--out",
        latents_npz.to_str().expect("utf-8"),
        "--batch",
        "1",
    ]);
    assert!(out.status.success(), "encode failed:\n{}", stderr(&out));
    let got = relreward_tests::np_load(&latents_npz);
    assert_eq!(relreward_tests::npz_shape(&got, "x"), vec![2, 1, 2, 2]);
    assert_eq!(relreward_tests::npz_values(&got, "x"), want.iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
    assert_eq!(relreward_tests::npz_values(&got, "y"), vec![7.0, 9.0]);
    let out = server.cli(&[
        "decode",
        "--model",
        "ae",
        "--input",
        latents_npz.to_str().expect("utf-8"),
        "--out",
        decoded_npz.to_str().expect("utf-8"),
    ]);
    assert!(out.status.success(), "decode failed:\n{}", stderr(&out));
    let got = relreward_tests::np_load(&decoded_npz);
    assert_eq!(relreward_tests::npz_values(&got, "x")[31], 42.75);
    let out =
        server.cli(&["encode", "--model", "ae", "--input", latents_npz.to_str().expect("utf-8"), "--out", "o.npz"]);
    assert!(!out.status.success() && stderr(&out).contains("takes images of shape [B, 1, 4, 4]"), "{}", stderr(&out));

    // Refusals, named.
    let gaussian = read(fx.path(), "gaussian.pt");
    raw_upload(&client, upload_messages(header("gauss", Some(sample_manifest(&[3]))), &gaussian, None))
        .await
        .expect("a diffusion model");
    let encode = |model: &str, images: pb::Tensor| pb::EncodeRequest { model: model.into(), images: Some(images) };
    let err = client.rewards().encode(encode("absent", images.clone())).await.expect_err("unknown");
    assert_eq!(err.code(), Code::NotFound, "{err:?}");
    let err = client.rewards().encode(encode("gauss", images.clone())).await.expect_err("wrong kind");
    assert_eq!(err.code(), Code::FailedPrecondition, "{err:?}");
    assert!(err.message().contains("is a diffusion model, not an autoencoder"), "{}", err.message());
    let flat = relreward_client::tensor::encode_f32(&[2, 16], &x);
    let err = client.rewards().encode(encode("ae", flat)).await.expect_err("wrong shape");
    assert_eq!(err.code(), Code::InvalidArgument, "{err:?}");
    assert!(err.message().starts_with("images: shape [2, 16]"), "{}", err.message());
    let out = server.cli(&["model", "export", "ae", "--out", d.join("export").to_str().expect("utf-8")]);
    assert!(!out.status.success() && stderr(&out).contains("is an autoencoder"), "{}", stderr(&out));

    // The Open Inference Protocol serves rewards: its repository index leaves the autoencoder
    // (and the diffusion model) out.
    let mut oip =
        relreward_proto::inference::grpc_inference_service_client::GrpcInferenceServiceClient::new(client.transport());
    let index = oip
        .repository_index(relreward_proto::inference::RepositoryIndexRequest {
            repository_name: String::new(),
            ready: false,
        })
        .await
        .expect("index")
        .into_inner()
        .models;
    assert!(index.is_empty(), "{index:?}");

    client.delete_model("ae").await.expect("delete");
    let err = client.rewards().encode(encode("ae", images)).await.expect_err("deleted");
    assert_eq!(err.code(), Code::NotFound, "{err:?}");
}
