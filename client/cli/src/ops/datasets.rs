//! Datasets from files: a recordings file opened as an upload (`.npz`/`.npy` as they are, D4RL
//! HDF5 and Minari recordings converted in memory; the reader chosen by the file's signature,
//! docs/data-formats.md), sent with the client's chunked, digest-checked upload, or reused when
//! a dataset of that name already exists.

use std::io::{self, Read};
use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use relreward_client::client::{DatasetUpload, UploadProgress};
use relreward_client::{Client, MemorySource, UploadSource, pb};
use relreward_toolkit::npz::{self, NpzSource};

use super::Progress;

/// Payload bytes per upload message unless asked otherwise (`dataset upload --chunk-bytes`).
pub const DEFAULT_CHUNK_BYTES: u64 = 1 << 20;

/// Where an opened file's arrays come from: the file itself, or its conversion in memory.
pub enum FileSource {
    Npz(NpzSource),
    Converted(MemorySource),
}

impl UploadSource for FileSource {
    fn arrays(&self) -> &[pb::ArraySpec] {
        match self {
            Self::Npz(s) => s.arrays(),
            Self::Converted(s) => s.arrays(),
        }
    }

    fn open(&mut self, index: usize) -> io::Result<Box<dyn Read + '_>> {
        match self {
            Self::Npz(s) => s.open(index),
            Self::Converted(s) => s.open(index),
        }
    }
}

/// A file ready to upload: its arrays, the kind of dataset they make, and what the user should
/// know about arrays left out or renamed (one line each).
pub struct OpenedFile {
    pub source: FileSource,
    pub kind: pb::DatasetKind,
    pub notes: Vec<String>,
}

/// Opens `file` as the requested kind (or the detected one: a `key` means samples). HDF5 files
/// and Minari datasets are read whole (on the calling thread: call it off the runtime).
pub fn open_file(file: &Path, kind: Option<pb::DatasetKind>, key: Option<&str>) -> Result<OpenedFile> {
    if relreward_toolkit::hdf5::is_hdf5(file) {
        if kind == Some(pb::DatasetKind::Samples) || key.is_some() {
            bail!("--kind samples / --key: an HDF5 file or Minari dataset uploads as trajectories");
        }
        let shown = file.display().to_string();
        let t = relreward_toolkit::hdf5::read_hdf5(file)?;
        let mut notes = Vec::new();
        if !t.ignored.is_empty() {
            let keys = t.ignored.iter().map(|k| format!("'{k}'")).collect::<Vec<_>>().join(", ");
            notes.push(format!("{shown}: not uploading {keys} (not part of a trajectories dataset)"));
        }
        notes.extend(t.notes.iter().map(|note| format!("{shown}: {note}")));
        let source = FileSource::Converted(t.upload_source());
        return Ok(OpenedFile { source, kind: pb::DatasetKind::Trajectories, notes });
    }
    let kind = match (kind, key) {
        (Some(kind), _) => kind,
        (None, Some(_)) => pb::DatasetKind::Samples,
        (None, None) => match npz::detect_kind(file)? {
            pb::DatasetKind::Trajectories => pb::DatasetKind::Trajectories,
            _ => pb::DatasetKind::Samples,
        },
    };
    let source = match (kind, key) {
        (pb::DatasetKind::Trajectories, Some(key)) => bail!(
            "--key {key}: --key selects the array of a samples upload; trajectories always use \
             'observations' and 'actions'"
        ),
        (pb::DatasetKind::Trajectories, None) => npz::trajectories_from_npz(file)?,
        (_, key) => npz::samples_from_npz_or_npy(file, key)?,
    };
    let mut notes = Vec::new();
    let ignored = source.ignored_keys();
    if !ignored.is_empty() {
        let keys = ignored.iter().map(|k| format!("'{k}'")).collect::<Vec<_>>().join(", ");
        notes.push(format!("not uploading {keys} (not part of a {} dataset)", kind_name(source.kind())));
    }
    if source.kind() == pb::DatasetKind::Trajectories {
        notes.extend(source.renamed().iter().map(|(from, to)| format!("uploading '{from}' as '{to}'")));
    }
    Ok(OpenedFile { kind: source.kind(), source: FileSource::Npz(source), notes })
}

/// `trajectories`, `samples`.
pub fn kind_name(kind: pb::DatasetKind) -> &'static str {
    match kind {
        pb::DatasetKind::Trajectories => "trajectories",
        pb::DatasetKind::Samples => "samples",
        pb::DatasetKind::Unspecified => "unspecified",
    }
}

/// Uploads an opened file as dataset `name`, counting bytes in `progress`.
pub async fn upload(
    client: &Client,
    name: &str,
    file: OpenedFile,
    description: &str,
    chunk_bytes: u64,
    progress: Arc<UploadProgress>,
) -> Result<pb::Dataset> {
    let request =
        DatasetUpload { name: name.to_owned(), kind: file.kind, description: description.to_owned(), chunk_bytes };
    Ok(client.upload_dataset(request, file.source, progress).await?)
}

/// Whether [`upload_or_reuse`] found the dataset or sent it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Provenance {
    Reused,
    Uploaded,
}

/// Dataset `name` if the server has it, else `path` uploaded under that name (notes about the
/// file on stderr, as `dataset upload` prints them; no progress bar). Names that carry a
/// fingerprint of the file's bytes make this "upload once".
pub async fn upload_or_reuse(progress: &dyn Progress, client: &Client, path: &Path, name: &str) -> Result<Provenance> {
    if client.get_dataset(name).await.is_ok() {
        progress.stage(&format!("reusing dataset {name}"));
        return Ok(Provenance::Reused);
    }
    progress.stage(&format!("uploading {} as {name}", path.display()));
    let file = path.to_owned();
    let opened = tokio::task::spawn_blocking(move || open_file(&file, None, None))
        .await
        .context("reading the file crashed")?
        .with_context(|| format!("uploading {}", path.display()))?;
    for note in &opened.notes {
        crate::output::eprint_line(&format!("note: {note}"));
    }
    upload(client, name, opened, "", DEFAULT_CHUNK_BYTES, Arc::default())
        .await
        .with_context(|| format!("uploading {}", path.display()))?;
    Ok(Provenance::Uploaded)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_implies_samples_and_conflicts_with_trajectories() {
        let dir = tempfile::tempdir().expect("tempdir");
        let missing = dir.path().join("missing.npz");
        let err = open_file(&missing, Some(pb::DatasetKind::Trajectories), Some("k")).err().expect("must fail");
        assert!(err.to_string().contains("--key"), "{err}");
    }
}
