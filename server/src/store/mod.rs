//! Durable state: metadata records and the files they describe.
//!
//! Two small interfaces keep the API layer independent of where things live:
//! - [`MetadataStore`]: records of datasets, models and jobs, transactional, and the job
//!   queue's leases. Embedded: SQLite ([`sqlite::SqliteMetadata`]); shared: PostgreSQL
//!   ([`postgres::PostgresMetadata`]).
//! - [`BlobStore`]: immutable file sets under a key, published atomically from a local staging
//!   directory. Embedded: a directory tree ([`local::LocalBlobs`]); shared: an S3-compatible
//!   object store with a local cache ([`s3::S3Blobs`]).
//!
//! `storage.backend` picks the pair: "embedded" (one process owns the data directory) or
//! "shared" (any number of serve and work processes, see docs/deployment.md).
//!
//! Job leases: a worker claims a job ([`MetadataStore::claim_job`]) for a lease it renews while
//! the job runs; every write of a running job's record names its lease owner and is refused
//! once another worker holds the lease, so a job is run by exactly one worker at a time, and
//! a job whose worker died is claimed again when its lease runs out.
//!
//! Visibility rule: a resource exists exactly when its metadata record exists. Files are
//! published first and the record inserted second; deletion removes the record first and the
//! files second. A crash between the two steps leaves only unreferenced files, which
//! [`Store::open`] removes at the next start, together with abandoned staging directories.
//!
//! Integrity rule: every published blob carries a digest list ([`digests`]), checked once each
//! time the resource is loaded (a dataset by a job, a model by the registry, a checkpoint on
//! resume). A mismatch is `Error::DataLoss` naming the resource; it is never served.
//! Checkpoints keep their predecessor until the next one is recorded, so a corrupt latest
//! checkpoint falls back to the previous one.

pub mod digests;
pub mod ingest;
pub mod local;
pub mod npy;
pub mod postgres;
mod records;
pub mod s3;
pub mod sqlite;

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Weak};
use std::time::Duration;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};

pub use self::records::{Named, NamedRecords};
use crate::config::Config;
use crate::error::{Error, Result};

/// Kind of dataset, as stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DatasetKind {
    Trajectories,
    Samples,
}

/// Per-coordinate statistics of one float array (population std).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArrayStats {
    #[serde(deserialize_with = "stored_floats")]
    pub min: Vec<f64>,
    #[serde(deserialize_with = "stored_floats")]
    pub max: Vec<f64>,
    #[serde(deserialize_with = "stored_floats")]
    pub mean: Vec<f64>,
    #[serde(deserialize_with = "stored_floats")]
    pub std: Vec<f64>,
}

/// Statistics as stored, a `null` read as NaN: JSON has no infinity, so a statistic that
/// overflowed (a float64 upload beyond float32's range, before ingestion refused those) was
/// written as `null`, and a strict read made the record, and every List that met it,
/// unreadable, its dataset impossible even to delete.
fn stored_floats<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Vec<f64>, D::Error> {
    let values: Vec<Option<f64>> = Deserialize::deserialize(d)?;
    Ok(values.into_iter().map(|v| v.unwrap_or(f64::NAN)).collect())
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArrayRecord {
    pub name: String,
    /// numpy dtype name ("float32", "bool", ...).
    pub dtype: String,
    pub shape: Vec<u64>,
    /// File name inside the dataset's blob (an .npy file).
    pub file: String,
    pub stats: Option<ArrayStats>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    pub count: u64,
    pub min_length: u64,
    pub max_length: u64,
    pub mean_length: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetRecord {
    pub name: String,
    pub kind: DatasetKind,
    pub num_rows: u64,
    pub arrays: Vec<ArrayRecord>,
    pub episodes: Option<EpisodeRecord>,
    /// Lowercase hex sha256 of the payload (arrays' raw bytes in order).
    pub sha256: String,
    pub size_bytes: u64,
    pub created_at_ms: i64,
    pub description: String,
    /// Where the files are in the [`BlobStore`].
    pub blob_key: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelKind {
    Diffusion,
    Reward,
    Discriminator,
    /// An uploaded TorchScript encoder/decoder between images and latents.
    Autoencoder,
    /// A named sampling recipe over a conditional diffusion model (JSON data).
    Recipe,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelFormat {
    /// A TorchScript module (code: only accepted when the server allows it).
    Torchscript,
    /// A built-in architecture with safetensors weights.
    Native,
    /// A sampling recipe: JSON data, no weights.
    Recipe,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "source", rename_all = "snake_case")]
pub enum Provenance {
    Uploaded,
    Trained { job_id: String, datasets: Vec<String>, models: Vec<String>, final_loss: f64 },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelRecord {
    pub name: String,
    pub kind: ModelKind,
    pub format: ModelFormat,
    /// The model's manifest as JSON (a diffusion manifest, or a reward model's); the store
    /// keeps it opaque, the engine gives it meaning.
    pub manifest: serde_json::Value,
    pub parameter_count: u64,
    /// Lowercase hex sha256 of `file`.
    pub sha256: String,
    pub size_bytes: u64,
    /// The weights or module file inside the blob.
    pub file: String,
    pub provenance: Provenance,
    pub created_at_ms: i64,
    pub description: String,
    pub blob_key: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Pending,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobState {
    /// Every state, in lifecycle order.
    pub const ALL: [JobState; 5] = [Self::Pending, Self::Running, Self::Succeeded, Self::Failed, Self::Cancelled];

    /// Terminal states have no way out.
    pub fn is_terminal(self) -> bool {
        matches!(self, Self::Succeeded | Self::Failed | Self::Cancelled)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::Pending => "pending",
            Self::Running => "running",
            Self::Succeeded => "succeeded",
            Self::Failed => "failed",
            Self::Cancelled => "cancelled",
        }
    }
}

/// Where a job's latest checkpoint is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointRef {
    pub blob_key: String,
    pub step: u64,
    /// The checkpoint before this one, kept (and referenced, so recovery does not collect it)
    /// until the next one is recorded: the fallback when this one turns out corrupt. Never
    /// itself has a `previous`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub previous: Option<Box<CheckpointRef>>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobRecord {
    pub id: String,
    /// "diffusion", "reward" or "discriminator".
    pub kind: String,
    /// The validated spec with defaults filled in, as JSON (opaque to the store).
    pub spec: serde_json::Value,
    pub state: JobState,
    pub step: u64,
    pub total_steps: u64,
    pub loss: Option<f64>,
    pub error: String,
    pub created_at_ms: i64,
    pub started_at_ms: Option<i64>,
    pub finished_at_ms: Option<i64>,
    /// Sequence number of the latest recorded event (0: none yet).
    pub last_seq: u64,
    pub checkpoint: Option<CheckpointRef>,
    /// Datasets and models the job reads (a model in use cannot be deleted).
    pub inputs: Vec<String>,
    pub output_model: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum JobEventKind {
    State {
        state: JobState,
        message: String,
    },
    Progress {
        step: u64,
        total_steps: u64,
        loss: f64,
        grad_norm: f64,
        learning_rate: f64,
        steps_per_second: f64,
        eta_seconds: f64,
        eval_loss: Option<f64>,
    },
    Checkpoint {
        step: u64,
    },
    Log {
        message: String,
    },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobEvent {
    pub seq: u64,
    pub time_ms: i64,
    pub event: JobEventKind,
}

/// What a lease renewal found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lease {
    /// Still this worker's; `cancel_requested` once someone asked for the job to stop.
    Held { cancel_requested: bool },
    /// Another worker holds it now, or the job is gone: stop without writing anything.
    Lost,
}

/// Metadata records. Implementations must make each call atomic.
#[async_trait]
pub trait MetadataStore: Send + Sync {
    /// The backend's dataset and model tables, from which the methods up to `delete_model`
    /// are provided.
    fn named_records(&self) -> &dyn NamedRecords;

    /// Inserts a new dataset; `Error::AlreadyExists` if the name is taken.
    async fn insert_dataset(&self, record: &DatasetRecord) -> Result<()> {
        self.named_records().insert_record(Named::Datasets, &record.name, &record.blob_key, record).await
    }
    async fn get_dataset(&self, name: &str) -> Result<Option<DatasetRecord>> {
        self.named_records().get_record(Named::Datasets, name).await
    }
    /// Datasets with names strictly after `after`, in name order, at most `limit`.
    async fn list_datasets(&self, after: &str, limit: usize) -> Result<Vec<DatasetRecord>> {
        self.named_records().list_records(Named::Datasets, after, limit).await
    }
    /// Removes the record and returns it, or `None` if there was none.
    async fn delete_dataset(&self, name: &str) -> Result<Option<DatasetRecord>> {
        self.named_records().delete_record(Named::Datasets, name).await
    }
    /// Every blob key some record refers to (for garbage collection).
    async fn referenced_blob_keys(&self) -> Result<HashSet<String>>;

    /// Inserts a new model; `Error::AlreadyExists` if the name is taken.
    async fn insert_model(&self, record: &ModelRecord) -> Result<()> {
        self.named_records().insert_record(Named::Models, &record.name, &record.blob_key, record).await
    }
    async fn get_model(&self, name: &str) -> Result<Option<ModelRecord>> {
        self.named_records().get_record(Named::Models, name).await
    }
    /// Models with names strictly after `after`, in name order, at most `limit`.
    async fn list_models(&self, after: &str, limit: usize) -> Result<Vec<ModelRecord>> {
        self.named_records().list_records(Named::Models, after, limit).await
    }
    async fn delete_model(&self, name: &str) -> Result<Option<ModelRecord>> {
        self.named_records().delete_record(Named::Models, name).await
    }

    /// Inserts a new job with its first events, in one transaction; `Error::AlreadyExists` if
    /// the id is taken.
    async fn insert_job(&self, record: &JobRecord, events: &[JobEvent]) -> Result<()>;
    async fn get_job(&self, id: &str) -> Result<Option<JobRecord>>;
    /// Jobs newest first, starting after the position `after` (0: from the newest); returns
    /// each record with its position for the next page.
    async fn list_jobs(&self, state: Option<JobState>, after: i64, limit: usize) -> Result<Vec<(i64, JobRecord)>>;
    /// Jobs in any of these states, oldest first (start-up recovery, in-use checks).
    async fn jobs_in_states(&self, states: &[JobState]) -> Result<Vec<JobRecord>>;
    /// How many jobs are in each state, every state listed (zero included); for the metrics
    /// endpoint, which asks at every scrape, so it must not read the records.
    async fn count_jobs_by_state(&self) -> Result<Vec<(JobState, u64)>>;
    /// Replaces the job record and appends events, in one transaction. `owner` is the lease
    /// holder writing (a worker running the job), or `None` for a write that needs the job
    /// unclaimed (cancelling a queued job). Refuses (`Error::FailedPrecondition`) a write by
    /// anyone else, and any way out of a terminal state. A terminal state releases the lease.
    async fn record_job(&self, record: &JobRecord, events: &[JobEvent], owner: Option<&str>) -> Result<()>;
    /// Leases the oldest job no live worker holds (PENDING, or RUNNING with a lapsed lease:
    /// its worker died) to `owner` for `lease`, and returns it; `None` when there is none.
    async fn claim_job(&self, owner: &str, lease: Duration) -> Result<Option<JobRecord>>;
    /// Extends `owner`'s lease on job `id` by `lease` from now.
    async fn renew_lease(&self, id: &str, owner: &str, lease: Duration) -> Result<Lease>;
    /// Gives `owner`'s lease on job `id` up, so another worker may claim it at once.
    async fn release_lease(&self, id: &str, owner: &str) -> Result<()>;
    /// Asks the worker running job `id` to cancel it (it sees this when renewing its lease).
    async fn request_cancel(&self, id: &str) -> Result<()>;
    /// A counter bumped by every model insert or delete, by any process (cache invalidation
    /// across replicas).
    async fn models_version(&self) -> Result<u64>;
    /// Events with seq >= from_seq, in order, at most `limit`.
    async fn job_events(&self, id: &str, from_seq: u64, limit: usize) -> Result<Vec<JobEvent>>;
}

/// Immutable file sets. Writers fill a local [`Staging`] directory and publish it under a key
/// in one atomic step; readers get a local path.
#[async_trait]
pub trait BlobStore: Send + Sync {
    /// A fresh, empty local staging directory, removed when dropped unless published.
    fn staging(&self) -> Result<Staging>;
    /// Makes the staged files visible under `key`, atomically and durably.
    async fn publish(&self, staging: Staging, key: &str) -> Result<()>;
    /// Removes the files under `key` (no error if absent).
    async fn remove(&self, key: &str) -> Result<()>;
    /// Keys under a prefix such as "datasets/" that garbage collection may remove when no
    /// record refers to them (with a shared store: only those older than a grace period, as
    /// another process may be between publishing and recording them).
    async fn collectable_keys(&self, prefix: &str) -> Result<Vec<String>>;
    /// A local directory holding the files of `key`.
    async fn local_dir(&self, key: &str) -> Result<PathBuf>;
    /// Removes staging directories left by a previous process.
    async fn clean_staging(&self) -> Result<usize>;
}

/// A staging directory that deletes itself unless it was published.
#[derive(Debug)]
pub struct Staging {
    dir: PathBuf,
    keep: bool,
}

impl Staging {
    pub fn new(dir: PathBuf) -> Self {
        Self { dir, keep: false }
    }

    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Called by a [`BlobStore`] once the directory has been moved away or copied.
    pub fn disarm(mut self) -> PathBuf {
        self.keep = true;
        std::mem::take(&mut self.dir)
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if !self.keep
            && !self.dir.as_os_str().is_empty()
            && let Err(e) = std::fs::remove_dir_all(&self.dir)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            tracing::warn!(dir = %self.dir.display(), error = %e, "could not remove staging directory; it will be removed at next start");
        }
    }
}

/// Every blob namespace; keys are "<namespace><id>".
pub const BLOB_NAMESPACES: [&str; 3] = ["datasets/", "models/", "checkpoints/"];

/// Hashes a dataset's payload as ingestion did and compares it with the record (blocking).
fn verify_payload(dir: &Path, record: &DatasetRecord, what: &str) -> Result<()> {
    use sha2::{Digest, Sha256};
    use std::io::Read;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    for array in &record.arrays {
        let dtype = relreward_proto::tensor::parse_dtype(&array.dtype)
            .ok_or_else(|| Error::DataLoss(format!("{what}: unknown stored dtype {}", array.dtype)))?;
        let header_len = npy::header(dtype, &array.shape).len();
        let mut file = std::fs::File::open(dir.join(&array.file)).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => Error::DataLoss(format!("{what}: stored file {} is missing", array.file)),
            _ => e.into(),
        })?;
        let mut skipped = 0;
        loop {
            let n = file.read(&mut buf)?;
            if n == 0 {
                break;
            }
            let skip = (header_len - skipped).min(n);
            skipped += skip;
            hasher.update(&buf[skip..n]);
        }
    }
    let actual = hex::encode(hasher.finalize());
    if actual != record.sha256 {
        return Err(Error::DataLoss(format!(
            "{what} is corrupt: its stored payload fails its integrity check (sha256 {actual}, recorded {})",
            record.sha256
        )));
    }
    Ok(())
}

/// The store the API layer talks to.
#[derive(Clone)]
pub struct Store {
    pub meta: Arc<dyn MetadataStore>,
    pub blobs: Arc<dyn BlobStore>,
    /// Bumped after every model record this process inserts or deletes, and, with the shared
    /// backend, whenever [`MetadataStore::models_version`] shows another process did, so caches
    /// keyed by model name can skip re-reading the record while it is unchanged (the serving
    /// hot path).
    models_generation: Arc<AtomicU64>,
    /// Held across "nothing uses this dataset or model" and its deletion, and across "this
    /// dataset or model exists" and the record that starts using it (a job, a recipe), so that
    /// within this process a deletion and a new use never interleave ([`Store::references`]).
    references: Arc<tokio::sync::Mutex<()>>,
    /// The embedded store's lock on its data directory (`relreward.lock`, held while any clone
    /// of this store lives; None for the shared backend).
    _owner: Option<Arc<std::fs::File>>,
}

/// How often a shared store looks for model changes made by other processes; a model deleted
/// or replaced elsewhere is served from cache at most this much longer.
const MODELS_VERSION_POLL: Duration = Duration::from_millis(500);

/// Takes the embedded store's exclusive lock on `dir` (an advisory lock on `dir/relreward.lock`,
/// released by the OS when the process ends, however it ends). The embedded store belongs to
/// one process: it breaks every job lease when it opens, so a second server on the same
/// directory would take over the first one's running jobs and both would write their
/// checkpoints and outputs. Refused with a message naming the setting instead.
fn lock_data_dir(dir: &std::path::Path) -> Result<std::fs::File> {
    let path = dir.join("relreward.lock");
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(|e| Error::internal(&format!("opening {}", path.display()), e))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => Err(Error::FailedPrecondition(format!(
            "storage.data_dir: {} is in use by another relreward-server (the embedded store is for one \
             process; run several servers with storage.backend = \"shared\")",
            dir.display()
        ))),
        Err(std::fs::TryLockError::Error(e)) => Err(Error::internal(&format!("locking {}", path.display()), e)),
    }
}

impl Store {
    /// Opens the configured backend and repairs what a crash may have left: abandoned staging
    /// directories and published files that no record refers to.
    pub async fn open(config: &Config) -> Result<Self> {
        let dir = &config.storage.data_dir;
        std::fs::create_dir_all(dir)
            .map_err(|e| Error::internal(&format!("creating data dir {}", dir.display()), e))?;
        let store = if config.storage.backend == "shared" {
            let meta = postgres::PostgresMetadata::connect(&config.storage.postgres).await?;
            let blobs = s3::S3Blobs::open(&config.storage.s3, dir).await?;
            let store = Self {
                meta: Arc::new(meta),
                blobs: Arc::new(blobs),
                models_generation: Arc::default(),
                references: Arc::default(),
                _owner: None,
            };
            store.follow_model_changes().await?;
            store
        } else {
            let owner = lock_data_dir(dir)?;
            let meta = sqlite::SqliteMetadata::open(&dir.join("metadata.sqlite3"))?;
            // One process owns the embedded store and it has just started: every job lease is
            // its predecessor's, so interrupted jobs can resume now rather than at lease expiry.
            let broken = meta.break_leases().await?;
            if broken > 0 {
                tracing::info!(jobs = broken, "jobs interrupted by the previous shutdown resume now");
            }
            let blobs = local::LocalBlobs::open(dir)?;
            Self {
                meta: Arc::new(meta),
                blobs: Arc::new(blobs),
                models_generation: Arc::default(),
                references: Arc::default(),
                _owner: Some(Arc::new(owner)),
            }
        };
        store.recover().await?;
        Ok(store)
    }

    /// Bumps the models generation whenever another process changed a model record, polling
    /// [`MetadataStore::models_version`] until the store is dropped.
    async fn follow_model_changes(&self) -> Result<()> {
        let meta = Arc::downgrade(&self.meta);
        let generation: Weak<AtomicU64> = Arc::downgrade(&self.models_generation);
        let mut seen = self.meta.models_version().await?;
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(MODELS_VERSION_POLL).await;
                let (Some(meta), Some(generation)) = (meta.upgrade(), generation.upgrade()) else { return };
                match meta.models_version().await {
                    Ok(version) if version != seen => {
                        seen = version;
                        generation.fetch_add(1, Ordering::SeqCst);
                    }
                    Ok(_) => {}
                    Err(e) => tracing::warn!(error = %e, "cannot read the models version; cached models may be stale"),
                }
            }
        });
        Ok(())
    }

    async fn recover(&self) -> Result<()> {
        let staged = self.blobs.clean_staging().await?;
        let referenced = self.meta.referenced_blob_keys().await?;
        let mut orphans = 0;
        for ns in BLOB_NAMESPACES {
            for key in self.blobs.collectable_keys(ns).await? {
                if !referenced.contains(&key) {
                    self.blobs.remove(&key).await?;
                    orphans += 1;
                }
            }
        }
        if staged + orphans > 0 {
            tracing::info!(staging_dirs = staged, orphaned_blobs = orphans, "removed leftovers of interrupted writes");
        }
        Ok(())
    }

    /// Publishes a finished ingest and records it, in that order. If the record cannot be
    /// inserted (for instance the name was taken meanwhile), the published files are removed.
    pub async fn commit_dataset(&self, staging: Staging, mut record: DatasetRecord) -> Result<DatasetRecord> {
        let key = format!("datasets/{}", uuid::Uuid::new_v4().simple());
        record.blob_key = key.clone();
        crate::fault::point("upload.before_publish");
        self.blobs.publish(staging, &key).await?;
        crate::fault::point("upload.after_publish");
        if let Err(e) = self.meta.insert_dataset(&record).await {
            if let Err(cleanup) = self.blobs.remove(&key).await {
                tracing::warn!(key, error = %cleanup, "could not remove files of a rejected dataset; removed at next start");
            }
            return Err(e);
        }
        Ok(record)
    }

    /// Publishes a model's staged files and records it (as [`Store::commit_dataset`]).
    pub async fn commit_model(&self, staging: Staging, mut record: ModelRecord) -> Result<ModelRecord> {
        let key = format!("models/{}", uuid::Uuid::new_v4().simple());
        record.blob_key = key.clone();
        crate::fault::point("model.before_publish");
        self.blobs.publish(staging, &key).await?;
        crate::fault::point("model.after_publish");
        if let Err(e) = self.meta.insert_model(&record).await {
            if let Err(cleanup) = self.blobs.remove(&key).await {
                tracing::warn!(key, error = %cleanup, "could not remove files of a rejected model; removed at next start");
            }
            return Err(e);
        }
        self.models_generation.fetch_add(1, Ordering::SeqCst);
        Ok(record)
    }

    /// Changes whenever a model record is inserted or deleted (see the field).
    pub fn models_generation(&self) -> u64 {
        self.models_generation.load(Ordering::SeqCst)
    }

    /// The lock every check of a reference and the write that acts on it take together: a
    /// model or dataset deleted while a job or recipe that names it is being created would
    /// leave that job or recipe pointing at nothing. It serialises within this process only;
    /// servers sharing one metadata store can still interleave (docs/architecture.md, "The model
    /// registry").
    pub async fn references(&self) -> tokio::sync::MutexGuard<'_, ()> {
        self.references.lock().await
    }

    /// Removes a model: record first, files second.
    pub async fn delete_model(&self, name: &str) -> Result<()> {
        let deleted = self.meta.delete_model(name).await;
        // Bumped even on error: the record may be gone although the call failed.
        self.models_generation.fetch_add(1, Ordering::SeqCst);
        let record = deleted?.ok_or_else(|| Error::NotFound(format!("model '{name}' not found")))?;
        if let Err(e) = self.blobs.remove(&record.blob_key).await {
            tracing::warn!(key = record.blob_key, error = %e, "could not remove model files; removed at next start");
        }
        Ok(())
    }

    /// Checks a stored dataset's files before a job reads them (blocking; once per load): its
    /// digest list when the blob has one, else the record's payload sha256 (the arrays' bytes
    /// after their `.npy` headers, in record order). `DataLoss` naming the dataset otherwise.
    pub fn verify_dataset(dir: &Path, record: &DatasetRecord) -> Result<()> {
        let what = format!("dataset '{}'", record.name);
        let result = match digests::verify_dir(dir, &what) {
            Ok(digests::Verified::Intact(_)) => Ok(()),
            Ok(digests::Verified::NoList) => verify_payload(dir, record, &what),
            Err(e) => Err(e),
        };
        if let Err(Error::DataLoss(m)) = &result {
            tracing::error!(dataset = record.name, blob = record.blob_key, "{m}");
        }
        result
    }

    /// Removes a dataset: record first (so it disappears atomically), files second.
    pub async fn delete_dataset(&self, name: &str) -> Result<()> {
        let record = self
            .meta
            .delete_dataset(name)
            .await?
            .ok_or_else(|| Error::NotFound(format!("dataset '{name}' not found")))?;
        if let Err(e) = self.blobs.remove(&record.blob_key).await {
            tracing::warn!(key = record.blob_key, error = %e, "could not remove dataset files; removed at next start");
        }
        Ok(())
    }
}
