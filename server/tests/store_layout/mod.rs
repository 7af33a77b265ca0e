//! The embedded store's files as a black box, for the server's own end-to-end tests: what
//! uploads, deletes, refusals and crashes leave under the data directory (`blobs/<namespace>/`
//! and `staging/`). Only the server crate's tests look there: everything else reaches models
//! and datasets through the API (`DownloadModel`, `GetDataset`), so the layout stays private
//! to `server/src/store`. Each test file takes it with `mod store_layout;`.
#![allow(dead_code)]

use std::collections::BTreeMap;

use relreward_tests::TestServer;
use sha2::{Digest, Sha256};

/// The published blobs and staging area of a [`TestServer`]'s data directory.
pub trait StoreLayout {
    /// Every published file under `blobs/<namespace>/`, as "namespace/key/file" -> (sha256,
    /// size).
    fn blob_files(&self, namespace: &str) -> BTreeMap<String, (String, u64)>;
    /// Published blob directories under `blobs/<namespace>/`.
    fn blob_count(&self, namespace: &str) -> usize;
    /// Published blob directories of datasets.
    fn dataset_blobs(&self) -> usize {
        self.blob_count("datasets")
    }
    /// The path of a published file (or blob directory) named as [`StoreLayout::blob_files`]
    /// names it ("namespace/key/file").
    fn blob_path(&self, file: &str) -> std::path::PathBuf;
}

impl StoreLayout for TestServer {
    fn blob_files(&self, namespace: &str) -> BTreeMap<String, (String, u64)> {
        let mut out = BTreeMap::new();
        let root = self.data_dir.join("blobs").join(namespace);
        for blob in std::fs::read_dir(&root).into_iter().flatten().flatten() {
            for file in std::fs::read_dir(blob.path()).into_iter().flatten().flatten() {
                let bytes = std::fs::read(file.path()).expect("read stored file");
                let name = format!(
                    "{namespace}/{}/{}",
                    blob.file_name().to_string_lossy(),
                    file.file_name().to_string_lossy()
                );
                out.insert(name, (hex::encode(Sha256::digest(&bytes)), bytes.len() as u64));
            }
        }
        out
    }

    fn blob_count(&self, namespace: &str) -> usize {
        std::fs::read_dir(self.data_dir.join("blobs").join(namespace)).map(|d| d.count()).unwrap_or(0)
    }

    fn blob_path(&self, file: &str) -> std::path::PathBuf {
        self.data_dir.join("blobs").join(file)
    }
}
