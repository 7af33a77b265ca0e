//! Building model uploads for the end-to-end tests (here and in server/tests/): the fixtures
//! exported by `tests/python/export_models.py` (an exact Gaussian eps-model, a linear model with
//! known parameters, and modules that break their manifest in each way), their manifests, and
//! upload streams sent raw, so that malformed ones can be built too.

use std::path::Path;
use std::process::Command;

use relreward_client::Client;
use relreward_client::pb::{self, upload_model_request::Message};
use sha2::{Digest, Sha256};

use crate::{python, repo_root};

/// The server setting that allows TorchScript uploads (off by default: a module is code).
pub const ENABLE: (&str, &str) = ("RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD", "true");
/// The Gaussian fixture: data N(MEAN, I), cosine schedule, T = 50.
pub const MEAN: &str = "1,-2,0.5";
pub const T: u32 = 50;

/// Exports the fixtures into a fresh directory.
pub fn fixtures() -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = Command::new(python())
        .arg(repo_root().join("tests/python/export_models.py"))
        .args(["--out", dir.path().to_str().expect("utf-8 path"), "--mean", MEAN, "--T", &T.to_string()])
        .output()
        .expect("run export_models.py");
    assert!(out.status.success(), "export_models.py failed: {}", String::from_utf8_lossy(&out.stderr));
    dir
}

pub fn read(dir: &Path, name: &str) -> Vec<u8> {
    std::fs::read(dir.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"))
}

pub fn sha(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// The manifest of the Gaussian fixture: eps, cosine (s = 0.008), T = 50, samples [3], identity.
pub fn sample_manifest(shape: &[u64]) -> pb::DiffusionManifest {
    pb::DiffusionManifest {
        parametrization: pb::Parametrization::Epsilon as i32,
        schedule: Some(pb::Schedule { kind: Some(pb::schedule::Kind::Cosine(pb::schedule::Cosine { s: 0.008 })) }),
        n_timesteps: T,
        clip_denoised: false,
        space: Some(pb::diffusion_manifest::Space::Sample(pb::diffusion_manifest::Sample { shape: shape.to_vec() })),
        normalizer: Some(pb::Normalizer { kind: Some(pb::normalizer::Kind::Identity(pb::normalizer::Identity {})) }),
        architecture: None,
        conditioning: None,
    }
}

pub fn header(name: &str, manifest: Option<pb::DiffusionManifest>) -> pb::UploadModelHeader {
    pb::UploadModelHeader {
        name: name.into(),
        manifest,
        description: format!("fixture {name}"),
        format: 0,
        reward: None,
        autoencoder: None,
    }
}

pub fn msg(m: Message) -> pb::UploadModelRequest {
    pb::UploadModelRequest { message: Some(m) }
}

/// Header, the bytes in 1000-byte chunks, and a commit with `digest` (the bytes' sha256 when
/// `None`).
pub fn upload_messages(
    header: pb::UploadModelHeader,
    bytes: &[u8],
    digest: Option<&str>,
) -> Vec<pb::UploadModelRequest> {
    let mut msgs = vec![msg(Message::Header(header))];
    msgs.extend(bytes.chunks(1000).map(|c| msg(Message::Chunk(c.to_vec()))));
    let digest = digest.map_or_else(|| sha(bytes), str::to_owned);
    msgs.push(msg(Message::Commit(pb::UploadCommit { sha256: digest })));
    msgs
}

pub async fn raw_upload(client: &Client, msgs: Vec<pb::UploadModelRequest>) -> Result<pb::Model, tonic::Status> {
    client.models().upload_model(tokio_stream::iter(msgs)).await.map(|r| r.into_inner())
}

pub async fn names(client: &Client) -> Vec<String> {
    client.list_models(pb::ModelKind::Unspecified).await.expect("list").into_iter().map(|m| m.name).collect()
}
