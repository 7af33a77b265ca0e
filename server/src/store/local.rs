//! Embedded blob store: directories under the data directory.
//!
//! Layout: `<data_dir>/blobs/<key>/...` for published files and `<data_dir>/staging/<uuid>/`
//! while being written. Publishing writes the blob's digest list ([`super::digests`]), fsyncs
//! every file, renames the staging directory into place (atomic on one filesystem) and fsyncs
//! the parent, so a published key is complete or absent, and carries the digest of each file.

use std::fs;
use std::path::{Path, PathBuf};

use async_trait::async_trait;

use super::{BlobStore, Staging};
use crate::error::{Error, Result};

pub struct LocalBlobs {
    blobs: PathBuf,
    staging: PathBuf,
}

impl LocalBlobs {
    pub fn open(data_dir: &Path) -> Result<Self> {
        let blobs = data_dir.join("blobs");
        let staging = data_dir.join("staging");
        for d in [&blobs, &staging] {
            fs::create_dir_all(d).map_err(|e| Error::internal(&format!("creating {}", d.display()), e))?;
        }
        Ok(Self { blobs, staging })
    }

    /// Maps a key to its directory, refusing anything that could leave the blob root.
    fn dir(&self, key: &str) -> Result<PathBuf> {
        let safe = !key.is_empty()
            && key.split('/').all(|part| {
                !part.is_empty() && part != "." && part != ".." && !part.contains('\\') && !part.contains('\0')
            });
        if !safe {
            return Err(Error::internal("blob store", format!("invalid key '{key}'")));
        }
        Ok(self.blobs.join(key))
    }
}

fn sync_dir(path: &Path) -> std::io::Result<()> {
    fs::File::open(path)?.sync_all()
}

#[async_trait]
impl BlobStore for LocalBlobs {
    fn staging(&self) -> Result<Staging> {
        let dir = self.staging.join(uuid::Uuid::new_v4().simple().to_string());
        fs::create_dir(&dir)?;
        Ok(Staging::new(dir))
    }

    async fn publish(&self, staging: Staging, key: &str) -> Result<()> {
        let target = self.dir(key)?;
        tokio::task::block_in_place(|| -> Result<()> {
            // Hashed here, after the writer closed its files, so the list covers exactly the
            // bytes that are published; the files are still in the page cache.
            super::digests::write_list(staging.path())?;
            for entry in fs::read_dir(staging.path())? {
                fs::File::open(entry?.path())?.sync_all()?;
            }
            let parent = target.parent().ok_or_else(|| Error::internal("blob store", "key without parent"))?;
            fs::create_dir_all(parent)?;
            fs::rename(staging.path(), &target)?;
            staging.disarm();
            sync_dir(parent)?;
            Ok(())
        })
    }

    async fn remove(&self, key: &str) -> Result<()> {
        let dir = self.dir(key)?;
        match tokio::task::block_in_place(|| fs::remove_dir_all(&dir)) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    async fn collectable_keys(&self, prefix: &str) -> Result<Vec<String>> {
        // One process owns the directory, so every key is collectable: nothing is between
        // publishing and recording while recovery runs. Keys are "<namespace>/<id>".
        let ns = prefix.trim_end_matches('/');
        let dir = self.dir(ns)?;
        let entries = match fs::read_dir(&dir) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(e.into()),
        };
        let mut keys = Vec::new();
        for entry in entries {
            let name = entry?.file_name();
            keys.push(format!("{ns}/{}", name.to_string_lossy()));
        }
        Ok(keys)
    }

    async fn local_dir(&self, key: &str) -> Result<PathBuf> {
        self.dir(key)
    }

    async fn clean_staging(&self) -> Result<usize> {
        let mut n = 0;
        for entry in fs::read_dir(&self.staging)? {
            let path = entry?.path();
            fs::remove_dir_all(&path).map_err(|e| Error::internal(&format!("removing {}", path.display()), e))?;
            n += 1;
        }
        Ok(n)
    }
}
