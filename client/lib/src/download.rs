//! Writing a `DownloadModel` stream into a directory, checked and all-or-nothing.
//!
//! [`Client::download_model`] (defined here, so that `client` does not import this module back)
//! opens the stream and hands it to
//! [`receive`]: the header names every file (name, size, sha256), then the files' bytes follow
//! in order. Each file goes to a hidden part file beside its target, hashed as it arrives; only
//! when every file has its declared size and digest (and the model file the record's) are the
//! part files renamed into place and `manifest.json` written. Any error, or a stream that ends
//! early, removes the part files ([`PartFiles`]), so a failed download leaves nothing behind.

use std::path::{Path, PathBuf};

use relreward_proto::v1 as pb;
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;
use tokio_stream::StreamExt;

use crate::client::{Client, ClientError};

/// Where the stored manifest goes, beside the files.
pub const MANIFEST_FILE: &str = "manifest.json";
/// The traced TorchScript module an export adds.
pub const EXPORT_FILE: &str = "module.pt";

impl Client {
    /// Downloads model `name` into `dir` (created if missing): its files under their stored
    /// names (the model file first: `module.pt` or `weights.safetensors`; a reward's
    /// `step_norm.safetensors` where it has one) and the stored manifest as `manifest.json`.
    /// Each file is checked against the size and sha256 the server declared (the model file
    /// against the record's too) before anything is put in place; a failed download leaves no
    /// file behind. Without `overwrite`, refuses when a target file exists. Not retried (a
    /// long stream; call again).
    pub async fn download_model(
        &self,
        name: &str,
        dir: &Path,
        overwrite: bool,
    ) -> Result<DownloadedModel, ClientError> {
        self.fetch_model(pb::DownloadModelRequest { name: name.to_owned(), torchscript: false }, dir, overwrite).await
    }

    /// [`Client::download_model`] plus the model as a TorchScript module, `module.pt`, traced
    /// by the server (see `DownloadModelRequest.torchscript`): for a reward or discriminator
    /// `forward(x raw, t) -> rho`, Score's values; for a native diffusion model the denoiser
    /// over normalized inputs. What a PyTorch user loads with `torch.jit.load`, beside the
    /// safetensors weights and `manifest.json`. A model stored as TorchScript is refused
    /// (FAILED_PRECONDITION): download it instead.
    pub async fn export_model(&self, name: &str, dir: &Path, overwrite: bool) -> Result<DownloadedModel, ClientError> {
        let got = self
            .fetch_model(pb::DownloadModelRequest { name: name.to_owned(), torchscript: true }, dir, overwrite)
            .await?;
        // A server from before the export ignores the request's `torchscript` and sends a
        // plain download: say so rather than report an export without its module.
        if !got.files.iter().any(|f| f.file_name().is_some_and(|n| n == EXPORT_FILE)) {
            return Err(ClientError::Invalid(format!(
                "the server sent no {EXPORT_FILE} (it predates model export); the plain download is in {}",
                dir.display()
            )));
        }
        Ok(got)
    }

    async fn fetch_model(
        &self,
        req: pb::DownloadModelRequest,
        dir: &Path,
        overwrite: bool,
    ) -> Result<DownloadedModel, ClientError> {
        let name = req.name.clone();
        let stream = self.models().download_model(req).await?;
        receive(stream.into_inner(), &name, dir, overwrite).await
    }
}

/// A model written by [`Client::download_model`](crate::Client::download_model).
#[derive(Debug, Clone)]
pub struct DownloadedModel {
    /// The model's record, as `GetModel` returns it.
    pub model: pb::Model,
    /// The stored manifest as JSON text (see `DownloadModelHeader.manifest_json`), also
    /// written to [`DownloadedModel::manifest_path`].
    pub manifest_json: String,
    /// Every file written, in the header's order: the model file first (its TorchScript
    /// module or safetensors weights), then any that belong with it.
    pub files: Vec<PathBuf>,
    pub manifest_path: PathBuf,
}

impl DownloadedModel {
    /// The model file: `module.pt` (TorchScript) or `weights.safetensors` (native).
    pub fn weights(&self) -> &Path {
        &self.files[0]
    }
}

/// Part files of a download in progress, removed when dropped unless [`PartFiles::publish`]
/// renamed them into place.
struct PartFiles(Vec<PathBuf>);

impl Drop for PartFiles {
    fn drop(&mut self) {
        for path in &self.0 {
            let _ = std::fs::remove_file(path);
        }
    }
}

/// A header's file name that is safe to join to the output directory: a plain name, not the
/// manifest's.
fn check_name(name: &str) -> Result<(), ClientError> {
    let plain = !name.is_empty() && name != "." && name != ".." && !name.contains(['/', '\\', '\0']);
    if !plain || name == MANIFEST_FILE {
        return Err(ClientError::Invalid(format!(
            "DownloadModel: the server named a file {name:?}, which is not a plain file name this client writes"
        )));
    }
    Ok(())
}

fn file_error(path: &Path) -> impl Fn(std::io::Error) -> ClientError + '_ {
    move |source| ClientError::File { path: path.to_owned(), source }
}

/// Receives a `DownloadModel` stream into `dir` (created if missing). Without `overwrite`,
/// refuses before writing anything when a target file exists.
pub(crate) async fn receive(
    mut stream: tonic::Streaming<pb::DownloadModelResponse>,
    name: &str,
    dir: &Path,
    overwrite: bool,
) -> Result<DownloadedModel, ClientError> {
    use pb::download_model_response::Message;
    let header = match stream.next().await.transpose()?.and_then(|m| m.message) {
        Some(Message::Header(h)) => h,
        Some(Message::Chunk(_)) | None => {
            return Err(ClientError::Invalid(format!(
                "DownloadModel '{name}': the stream did not start with a header"
            )));
        }
    };
    let model =
        header.model.clone().ok_or_else(|| ClientError::Invalid("DownloadModel: header.model missing".into()))?;
    let first = header.files.first().ok_or_else(|| ClientError::Invalid("DownloadModel: header.files empty".into()))?;
    if first.sha256 != model.sha256 || first.size_bytes != model.size_bytes {
        return Err(ClientError::Invalid(format!(
            "DownloadModel '{name}': the header's first file ({}, {} bytes, sha256 {}) is not the model's ({} bytes, sha256 {})",
            first.name, first.size_bytes, first.sha256, model.size_bytes, model.sha256
        )));
    }
    for (i, f) in header.files.iter().enumerate() {
        check_name(&f.name)?;
        if header.files[..i].iter().any(|g| g.name == f.name) {
            return Err(ClientError::Invalid(format!("DownloadModel: file {} listed twice", f.name)));
        }
    }
    tokio::fs::create_dir_all(dir).await.map_err(file_error(dir))?;
    let targets: Vec<PathBuf> = header.files.iter().map(|f| dir.join(&f.name)).collect();
    let manifest_path = dir.join(MANIFEST_FILE);
    if !overwrite {
        for path in targets.iter().chain([&manifest_path]) {
            if tokio::fs::try_exists(path).await.map_err(file_error(path))? {
                return Err(ClientError::Invalid(format!(
                    "{}: exists; nothing was downloaded (overwrite it with --force, or choose another directory)",
                    path.display()
                )));
            }
        }
    }
    let pid = std::process::id();
    let parts = PartFiles(header.files.iter().map(|f| dir.join(format!(".{}.{pid}.part", f.name))).collect());

    let mut chunks = 0usize;
    for (file, part) in header.files.iter().zip(&parts.0) {
        let mut out = tokio::fs::File::create(part).await.map_err(file_error(part))?;
        let mut hasher = Sha256::new();
        let mut left = file.size_bytes;
        while left > 0 {
            let bytes = match stream.next().await.transpose()?.and_then(|m| m.message) {
                Some(Message::Chunk(bytes)) => bytes,
                Some(Message::Header(_)) => {
                    return Err(ClientError::Invalid("DownloadModel: a second header".into()));
                }
                None => {
                    return Err(ClientError::Invalid(format!(
                        "DownloadModel '{name}': the stream ended {left} bytes before the end of {}; nothing was written",
                        file.name
                    )));
                }
            };
            chunks += 1;
            if bytes.len() as u64 > left {
                return Err(ClientError::Invalid(format!(
                    "DownloadModel '{name}': chunk {chunks} runs past the end of {} ({} bytes)",
                    file.name, file.size_bytes
                )));
            }
            left -= bytes.len() as u64;
            hasher.update(&bytes);
            out.write_all(&bytes).await.map_err(file_error(part))?;
        }
        out.sync_all().await.map_err(file_error(part))?;
        let sha256 = hex::encode(hasher.finalize());
        if !sha256.eq_ignore_ascii_case(&file.sha256) {
            return Err(ClientError::Invalid(format!(
                "DownloadModel '{name}': {} arrived with sha256 {sha256}, the server's is {}; nothing was written",
                file.name, file.sha256
            )));
        }
    }
    if stream.next().await.transpose()?.is_some() {
        return Err(ClientError::Invalid(format!("DownloadModel '{name}': bytes after the last file")));
    }

    // Everything arrived intact: put it in place (a rename within one directory).
    let mut manifest = header.manifest_json.clone();
    if !manifest.ends_with('\n') {
        manifest.push('\n');
    }
    let manifest_part = dir.join(format!(".{MANIFEST_FILE}.{pid}.part"));
    let mut parts = parts;
    parts.0.push(manifest_part.clone());
    tokio::fs::write(&manifest_part, manifest).await.map_err(file_error(&manifest_part))?;
    for (part, target) in parts.0.iter().zip(targets.iter().chain([&manifest_path])) {
        tokio::fs::rename(part, target).await.map_err(file_error(target))?;
    }
    parts.0.clear();
    Ok(DownloadedModel { model, manifest_json: header.manifest_json, files: targets, manifest_path })
}
