//! Shared blob store: an S3-compatible object store with a local cache
//! (`storage.backend = "shared"`).
//!
//! Layout: `<prefix><key>/<file>` per published file, e.g. `models/3f2a.../weights.safetensors`,
//! and `<prefix><key>/SHA256SUMS`, the blob's digest list, uploaded last. Locally:
//! `<data_dir>/staging/<uuid>/` while being written (as with the embedded store) and
//! `<data_dir>/cache/<key>/` for blobs this node published or downloaded.
//!
//! Atomic visibility holds as on local disk: a resource exists when its metadata record
//! exists, and the record is inserted only after every object was uploaded. A crash halfway
//! leaves unreferenced objects, collected at a later start once older than
//! `storage.s3.orphan_grace_secs` (a younger one may belong to an upload in flight in another
//! process). Blobs are immutable, so a cached copy never goes stale; a download is checked
//! against its digest list before it enters the cache, and loaders check it again once per
//! load, as on local disk. The cache is emptied at start (a pod's local disk is scratch) and
//! kept under `storage.s3.cache_max_bytes` by evicting the least recently used blobs, never one
//! used within `storage.s3.cache_hold_secs` (whoever asked for it may still be reading it).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use futures::{StreamExt, TryStreamExt};
use object_store::aws::AmazonS3Builder;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use tokio::io::AsyncWriteExt;

use super::digests::{self, DIGEST_FILE};
use super::{BlobStore, Staging};
use crate::config::S3Config;
use crate::error::{Error, Result};

/// How long start-up waits for the object store (a pod may start before it).
const CONNECT_PATIENCE: Duration = Duration::from_secs(60);

pub struct S3Blobs {
    store: Arc<dyn ObjectStore>,
    /// Empty, or ends with '/'.
    prefix: String,
    bucket: String,
    staging: PathBuf,
    cache: Cache,
    grace: Duration,
}

/// This node's copies of blobs under `dir/<key>/`, bounded in bytes.
///
/// The index is the truth about what is cached (the directory is emptied at start): a copy is
/// entered once complete and verified, and leaves by a rename into a trash name made under the
/// index's lock, so a caller is never handed a directory that is being deleted.
struct Cache {
    dir: PathBuf,
    /// 0: no bound.
    max_bytes: u64,
    hold: Duration,
    index: Mutex<CacheIndex>,
}

#[derive(Default)]
struct CacheIndex {
    /// Size and last use of each cached blob.
    entries: HashMap<String, (u64, Instant)>,
    total_bytes: u64,
}

impl Cache {
    fn path(&self, key: &str) -> PathBuf {
        self.dir.join(key)
    }

    fn index(&self) -> std::sync::MutexGuard<'_, CacheIndex> {
        // The index holds plain numbers: a panic elsewhere cannot leave it half-updated.
        self.index.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The cached copy of `key`, marked as used now; `None` when there is none.
    fn get(&self, key: &str) -> Option<PathBuf> {
        let mut index = self.index();
        let entry = index.entries.get_mut(key)?;
        entry.1 = Instant::now();
        Some(self.path(key))
    }

    /// Enters the complete copy of `key` (already at its path), then evicts least recently
    /// used blobs beyond the bound, except `key` and those used within the hold.
    fn insert(&self, key: &str, bytes: u64) {
        let mut trash = Vec::new();
        {
            let mut index = self.index();
            if let Some((old, _)) = index.entries.insert(key.to_owned(), (bytes, Instant::now())) {
                index.total_bytes -= old;
            }
            index.total_bytes += bytes;
            if self.max_bytes > 0 && index.total_bytes > self.max_bytes {
                let mut by_age: Vec<(Instant, String, u64)> = index
                    .entries
                    .iter()
                    .filter(|(k, (_, used))| k.as_str() != key && used.elapsed() >= self.hold)
                    .map(|(k, (b, used))| (*used, k.clone(), *b))
                    .collect();
                by_age.sort();
                for (_, victim, victim_bytes) in by_age {
                    if index.total_bytes <= self.max_bytes {
                        break;
                    }
                    let to = self.dir.join(format!(".evicted-{}", uuid::Uuid::new_v4().simple()));
                    if let Err(e) = std::fs::rename(self.path(&victim), &to) {
                        tracing::warn!(key = victim, error = %e, "cannot evict a cached blob");
                        continue;
                    }
                    index.entries.remove(&victim);
                    index.total_bytes -= victim_bytes;
                    trash.push((victim, victim_bytes, to));
                }
            }
        }
        for (victim, victim_bytes, to) in trash {
            tracing::info!(
                key = victim,
                bytes = victim_bytes,
                "evicted from the blob cache (storage.s3.cache_max_bytes)"
            );
            if let Err(e) = std::fs::remove_dir_all(&to) {
                tracing::warn!(path = %to.display(), error = %e, "cannot delete an evicted blob");
            }
        }
    }

    /// Forgets `key` (its blob was removed); the caller deletes the directory.
    fn forget(&self, key: &str) {
        let mut index = self.index();
        if let Some((bytes, _)) = index.entries.remove(key) {
            index.total_bytes -= bytes;
        }
    }

    /// Bytes the cache holds, as the index counts them.
    fn total_bytes(&self) -> u64 {
        self.index().total_bytes
    }
}

/// Total size of the files in `dir` (a blob's directory is flat).
fn dir_bytes(dir: &Path) -> std::io::Result<u64> {
    let mut total = 0;
    for entry in std::fs::read_dir(dir)? {
        total += entry?.metadata()?.len();
    }
    Ok(total)
}

fn s3_error(context: &str, e: object_store::Error) -> Error {
    match e {
        object_store::Error::NotFound { .. } => Error::DataLoss(format!("{context}: missing from the object store")),
        other => Error::Unavailable(format!("object store: {context}: {other}")),
    }
}

impl S3Blobs {
    /// Connects (retrying while the object store is not up yet), checks the bucket can be
    /// listed, and empties the local cache.
    pub async fn open(config: &S3Config, data_dir: &Path) -> Result<Self> {
        // Environment first (AWS_* variables, instance credentials), then the configured keys.
        let mut builder = AmazonS3Builder::from_env()
            .with_bucket_name(&config.bucket)
            .with_region(&config.region)
            .with_allow_http(config.allow_http);
        if !config.endpoint.is_empty() {
            builder = builder.with_endpoint(&config.endpoint);
        }
        if !config.access_key_id.is_empty() {
            builder =
                builder.with_access_key_id(&config.access_key_id).with_secret_access_key(&config.secret_access_key);
        }
        let store = builder.build().map_err(|e| Error::internal("storage.s3", e))?;
        let prefix = match config.prefix.trim_end_matches('/') {
            "" => String::new(),
            p => format!("{p}/"),
        };
        let staging = data_dir.join("staging");
        let cache = data_dir.join("cache");
        if cache.exists() {
            std::fs::remove_dir_all(&cache)
                .map_err(|e| Error::internal(&format!("emptying the blob cache {}", cache.display()), e))?;
        }
        for d in [&staging, &cache] {
            std::fs::create_dir_all(d).map_err(|e| Error::internal(&format!("creating {}", d.display()), e))?;
        }
        let blobs = Self {
            store: Arc::new(store),
            prefix,
            bucket: config.bucket.clone(),
            staging,
            cache: Cache {
                dir: cache,
                max_bytes: config.cache_max_bytes,
                hold: Duration::from_secs(config.cache_hold_secs),
                index: Mutex::default(),
            },
            grace: Duration::from_secs(config.orphan_grace_secs),
        };
        let started = tokio::time::Instant::now();
        loop {
            let probe = ObjectPath::from(blobs.prefix.as_str());
            match blobs.store.list_with_delimiter(Some(&probe)).await {
                Ok(_) => break,
                Err(e) if started.elapsed() < CONNECT_PATIENCE => {
                    tracing::warn!(bucket = blobs.bucket, error = %e, "waiting for the object store");
                    tokio::time::sleep(Duration::from_secs(2)).await;
                }
                Err(e) => {
                    return Err(Error::Unavailable(format!(
                        "storage.s3: cannot list bucket '{}' (does it exist, and may these credentials read it?): {e}",
                        blobs.bucket
                    )));
                }
            }
        }
        tracing::info!(bucket = blobs.bucket, prefix = blobs.prefix, "blob store ready (S3-compatible)");
        Ok(blobs)
    }

    /// Bytes held in this node's blob cache.
    pub fn cached_bytes(&self) -> u64 {
        self.cache.total_bytes()
    }

    /// Refuses keys that could escape their directory in the cache.
    fn check_key(key: &str) -> Result<()> {
        let safe = !key.is_empty()
            && key.split('/').all(|part| {
                !part.is_empty() && part != "." && part != ".." && !part.contains('\\') && !part.contains('\0')
            });
        if safe { Ok(()) } else { Err(Error::internal("blob store", format!("invalid key '{key}'"))) }
    }

    fn object(&self, key: &str, file: &str) -> ObjectPath {
        ObjectPath::from(format!("{}{key}/{file}", self.prefix))
    }

    fn dir_prefix(&self, key: &str) -> ObjectPath {
        ObjectPath::from(format!("{}{key}", self.prefix))
    }

    /// Every object of blob `key`, by file name.
    async fn objects(&self, key: &str) -> Result<Vec<(String, ObjectPath)>> {
        let listed: Vec<_> = self
            .store
            .list(Some(&self.dir_prefix(key)))
            .try_collect()
            .await
            .map_err(|e| s3_error(&format!("listing blob {key}"), e))?;
        Ok(listed
            .into_iter()
            .filter_map(|meta| {
                let name = meta.location.filename()?.to_owned();
                Some((name, meta.location))
            })
            .collect())
    }

    async fn upload(&self, path: &Path, to: &ObjectPath) -> Result<()> {
        let mut file = tokio::fs::File::open(path).await?;
        // Multipart above its buffer (10 MiB), a single PUT below: large datasets stream.
        let mut writer = object_store::buffered::BufWriter::new(Arc::clone(&self.store), to.clone());
        let copied = tokio::io::copy(&mut file, &mut writer).await;
        if let Err(e) = copied {
            let _ = writer.abort().await;
            return Err(Error::Unavailable(format!("object store: uploading {to}: {e}")));
        }
        writer.shutdown().await.map_err(|e| Error::Unavailable(format!("object store: uploading {to}: {e}")))?;
        Ok(())
    }

    async fn download(&self, key: &str, into: &Path) -> Result<()> {
        let objects = self.objects(key).await?;
        if !objects.iter().any(|(name, _)| name == DIGEST_FILE) {
            // The list goes up last: without it the blob is incomplete (or was never published).
            return Err(Error::DataLoss(format!("blob {key} is incomplete in the object store (no {DIGEST_FILE})")));
        }
        for (name, location) in objects {
            let mut out = tokio::fs::File::create(into.join(&name)).await?;
            let mut stream =
                self.store.get(&location).await.map_err(|e| s3_error(&format!("reading {location}"), e))?.into_stream();
            while let Some(chunk) = stream.next().await {
                out.write_all(&chunk.map_err(|e| s3_error(&format!("reading {location}"), e))?).await?;
            }
            out.sync_all().await?;
        }
        Ok(())
    }
}

#[async_trait]
impl BlobStore for S3Blobs {
    fn staging(&self) -> Result<Staging> {
        let dir = self.staging.join(uuid::Uuid::new_v4().simple().to_string());
        std::fs::create_dir(&dir)?;
        Ok(Staging::new(dir))
    }

    async fn publish(&self, staging: Staging, key: &str) -> Result<()> {
        Self::check_key(key)?;
        tokio::task::block_in_place(|| digests::write_list(staging.path()))?;
        let mut files: Vec<String> = std::fs::read_dir(staging.path())?
            .map(|e| e.map(|e| e.file_name().to_string_lossy().into_owned()))
            .collect::<std::io::Result<_>>()?;
        // The digest list last: its presence marks a complete upload.
        files.sort_by_key(|name| (name == DIGEST_FILE, name.clone()));
        for name in &files {
            if let Err(e) = self.upload(&staging.path().join(name), &self.object(key, name)).await {
                // Best effort; what stays is unreferenced and collected later.
                let _ = self.remove(key).await;
                return Err(e);
            }
        }
        // This node has the files already: keep them as its cached copy.
        let cached = self.cache.path(key);
        if let Some(parent) = cached.parent() {
            std::fs::create_dir_all(parent)?;
        }
        if std::fs::rename(staging.path(), &cached).is_ok() {
            staging.disarm();
            // Off the async workers: an eviction may delete gigabytes.
            tokio::task::block_in_place(|| dir_bytes(&cached).map(|bytes| self.cache.insert(key, bytes)))?;
        }
        Ok(())
    }

    async fn remove(&self, key: &str) -> Result<()> {
        Self::check_key(key)?;
        for (_, location) in self.objects(key).await? {
            match self.store.delete(&location).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(s3_error(&format!("deleting {location}"), e)),
            }
        }
        self.cache.forget(key);
        let cached = self.cache.path(key);
        match tokio::task::block_in_place(|| std::fs::remove_dir_all(&cached)) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    async fn collectable_keys(&self, prefix: &str) -> Result<Vec<String>> {
        let listed: Vec<_> = self
            .store
            .list(Some(&ObjectPath::from(format!("{}{}", self.prefix, prefix.trim_end_matches('/')))))
            .try_collect()
            .await
            .map_err(|e| s3_error(&format!("listing {prefix}"), e))?;
        // A key's age is its newest object's: an upload in flight keeps adding objects.
        let mut newest: std::collections::BTreeMap<String, i64> = std::collections::BTreeMap::new();
        for meta in listed {
            let full = meta.location.to_string();
            let Some(rest) = full.strip_prefix(&self.prefix) else { continue };
            let mut parts = rest.splitn(3, '/');
            let (Some(ns), Some(id), Some(_file)) = (parts.next(), parts.next(), parts.next()) else { continue };
            let at = meta.last_modified.timestamp_millis();
            let entry = newest.entry(format!("{ns}/{id}")).or_insert(at);
            *entry = (*entry).max(at);
        }
        let cutoff = crate::store::ingest::now_ms() - i64::try_from(self.grace.as_millis()).unwrap_or(i64::MAX);
        Ok(newest.into_iter().filter(|(_, at)| *at < cutoff).map(|(key, _)| key).collect())
    }

    async fn local_dir(&self, key: &str) -> Result<PathBuf> {
        Self::check_key(key)?;
        if let Some(cached) = self.cache.get(key) {
            return Ok(cached);
        }
        let cached = self.cache.path(key);
        let partial = self.cache.dir.join(format!(".partial-{}", uuid::Uuid::new_v4().simple()));
        tokio::fs::create_dir_all(&partial).await?;
        let fetched = async {
            self.download(key, &partial).await?;
            tokio::task::block_in_place(|| digests::verify_dir(&partial, &format!("blob {key}")))?;
            if let Some(parent) = cached.parent() {
                tokio::fs::create_dir_all(parent).await?;
            }
            Ok::<_, Error>(())
        }
        .await;
        if let Err(e) = fetched {
            let _ = std::fs::remove_dir_all(&partial);
            return Err(e);
        }
        // Another task may have fetched the same blob meanwhile: its copy is as good.
        if std::fs::rename(&partial, &cached).is_err() {
            let _ = std::fs::remove_dir_all(&partial);
            if !cached.is_dir() {
                return Err(Error::internal(
                    "blob cache",
                    format!("cannot place {key} in {}", self.cache.dir.display()),
                ));
            }
        }
        // Off the async workers: an eviction may delete gigabytes.
        tokio::task::block_in_place(|| dir_bytes(&cached).map(|bytes| self.cache.insert(key, bytes)))?;
        Ok(cached)
    }

    async fn clean_staging(&self) -> Result<usize> {
        let mut n = 0;
        for entry in std::fs::read_dir(&self.staging)? {
            let path = entry?.path();
            std::fs::remove_dir_all(&path).map_err(|e| Error::internal(&format!("removing {}", path.display()), e))?;
            n += 1;
        }
        Ok(n)
    }
}
