//! What both metadata backends share ([`super::sqlite`], [`super::postgres`]): the JSON record
//! format, the named-record tables ([`Named`], and [`NamedRecords`], the four operations a
//! backend implements once for datasets and models alike), the indexed checkpoint keys, and
//! the rules of a job record write (terminal states, lease fencing), so the two stores cannot
//! drift apart.

use async_trait::async_trait;

use super::{JobRecord, JobState};
use crate::error::{Error, Result};

pub(crate) fn decode<T: serde::de::DeserializeOwned>(json: &str) -> Result<T> {
    serde_json::from_str(json).map_err(|e| Error::DataLoss(format!("a stored record is unreadable: {e}")))
}

/// An event sequence number as the databases store it (BIGINT / INTEGER, signed 64 bits):
/// saturating, so a number past i64::MAX (a client's `from_seq`) means "after every event"
/// rather than wrapping to a negative one, which would mean "from the first".
pub(crate) fn seq_i64(seq: u64) -> i64 {
    i64::try_from(seq).unwrap_or(i64::MAX)
}

pub(crate) fn encode<T: serde::Serialize>(value: &T) -> Result<String> {
    serde_json::to_string(value).map_err(|e| Error::internal("encoding record", e))
}

/// The tables of named records (name, blob_key, record): datasets and models share their
/// insert, get, list and delete.
#[derive(Debug, Clone, Copy)]
pub enum Named {
    Datasets,
    Models,
}

impl Named {
    pub fn table(self) -> &'static str {
        match self {
            Self::Datasets => "datasets",
            Self::Models => "models",
        }
    }

    pub fn what(self) -> &'static str {
        match self {
            Self::Datasets => "dataset",
            Self::Models => "model",
        }
    }

    /// Model changes are counted (`MetadataStore::models_version`).
    pub fn counts_changes(self) -> bool {
        matches!(self, Self::Models)
    }
}

/// A backend's named-record tables, over encoded records (JSON text): each operation is one
/// transaction, and inserts and deletes of models bump the models counter in it
/// ([`Named::counts_changes`]). [`super::MetadataStore`]'s dataset and model methods are
/// provided from these (encoding and decoding the records), so the backends write them once.
#[async_trait]
pub trait NamedRecords: Send + Sync {
    /// Inserts a record; `Error::AlreadyExists` (naming [`Named::what`]) if the name is taken.
    async fn insert_named(&self, kind: Named, name: &str, blob_key: &str, json: String) -> Result<()>;
    async fn get_named(&self, kind: Named, name: &str) -> Result<Option<String>>;
    /// Records with names strictly after `after`, in byte order of the names, at most `limit`.
    async fn list_named(&self, kind: Named, after: &str, limit: usize) -> Result<Vec<String>>;
    /// Removes the record and returns it, or `None` if there was none.
    async fn delete_named(&self, kind: Named, name: &str) -> Result<Option<String>>;
}

/// The named-record operations on records rather than their JSON text.
impl dyn NamedRecords + '_ {
    pub async fn insert_record<T: serde::Serialize>(
        &self,
        kind: Named,
        name: &str,
        blob_key: &str,
        record: &T,
    ) -> Result<()> {
        let json = encode(record)?;
        self.insert_named(kind, name, blob_key, json).await
    }

    pub async fn get_record<T: serde::de::DeserializeOwned>(&self, kind: Named, name: &str) -> Result<Option<T>> {
        self.get_named(kind, name).await?.as_deref().map(decode).transpose()
    }

    pub async fn list_records<T: serde::de::DeserializeOwned>(
        &self,
        kind: Named,
        after: &str,
        limit: usize,
    ) -> Result<Vec<T>> {
        self.list_named(kind, after, limit).await?.iter().map(|json| decode(json)).collect()
    }

    pub async fn delete_record<T: serde::de::DeserializeOwned>(&self, kind: Named, name: &str) -> Result<Option<T>> {
        self.delete_named(kind, name).await?.as_deref().map(decode).transpose()
    }
}

/// The blob keys of a job's latest and previous checkpoints (the indexed columns).
pub(crate) fn checkpoint_keys(record: &JobRecord) -> (Option<String>, Option<String>) {
    let latest = record.checkpoint.as_ref();
    let previous = latest.and_then(|c| c.previous.as_ref()).map(|p| p.blob_key.clone());
    (latest.map(|c| c.blob_key.clone()), previous)
}

/// The rules every backend applies to a job record write (see `MetadataStore::record_job`):
/// `holder` is the current lease owner, `writer` who writes.
pub(crate) fn check_transition(
    id: &str,
    current: &str,
    next: JobState,
    holder: Option<&str>,
    writer: Option<&str>,
) -> Result<()> {
    let terminal = ["succeeded", "failed", "cancelled"].contains(&current);
    if terminal && current != next.as_str() {
        return Err(Error::FailedPrecondition(format!(
            "job '{id}' is {current}, a terminal state; it cannot become {}",
            next.as_str()
        )));
    }
    if holder != writer && !terminal {
        return Err(Error::FailedPrecondition(match (holder, writer) {
            (Some(h), Some(_)) => format!("job '{id}' is now run by {h}: this worker's lease on it was lost"),
            (Some(h), None) => format!("job '{id}' was taken by worker {h}"),
            (None, _) => format!("job '{id}' is not leased to this worker"),
        }));
    }
    Ok(())
}
