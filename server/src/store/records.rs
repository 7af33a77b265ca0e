//! What both metadata backends share ([`super::sqlite`], [`super::postgres`]): the JSON record
//! format, the named-record tables, the indexed checkpoint keys, and the rules of a job record
//! write (terminal states, lease fencing), so the two stores cannot drift apart.

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
#[derive(Clone, Copy)]
pub(crate) enum Named {
    Datasets,
    Models,
}

impl Named {
    pub(crate) fn table(self) -> &'static str {
        match self {
            Self::Datasets => "datasets",
            Self::Models => "models",
        }
    }

    pub(crate) fn what(self) -> &'static str {
        match self {
            Self::Datasets => "dataset",
            Self::Models => "model",
        }
    }

    /// Model changes are counted (`MetadataStore::models_version`).
    pub(crate) fn counts_changes(self) -> bool {
        matches!(self, Self::Models)
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
