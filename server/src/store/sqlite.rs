//! Embedded metadata store: one SQLite file in the data directory.
//!
//! Records are stored as JSON documents next to their indexed key, so adding a field to a
//! record needs no migration. WAL mode with synchronous=FULL: a committed transaction survives
//! power loss. rusqlite is blocking, so every call runs on the blocking pool.

use std::collections::HashSet;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use async_trait::async_trait;
use rusqlite::{Connection, OptionalExtension, params};

use super::records::{Named, NamedRecords, check_transition, checkpoint_keys, decode, encode, seq_i64};
use super::{JobEvent, JobRecord, JobState, Lease, MetadataStore};
use crate::error::{Error, Result};
use crate::store::ingest::now_ms;

/// Schema migrations, applied in order; `PRAGMA user_version` records how many ran.
const MIGRATIONS: &[&str] = &[
    "CREATE TABLE datasets (
        name TEXT PRIMARY KEY NOT NULL,
        blob_key TEXT NOT NULL,
        record TEXT NOT NULL
    ) STRICT;",
    "CREATE TABLE models (
        name TEXT PRIMARY KEY NOT NULL,
        blob_key TEXT NOT NULL,
        record TEXT NOT NULL
    ) STRICT;
    CREATE TABLE jobs (
        seq INTEGER PRIMARY KEY AUTOINCREMENT,
        id TEXT UNIQUE NOT NULL,
        state TEXT NOT NULL,
        checkpoint_key TEXT,
        record TEXT NOT NULL
    ) STRICT;
    CREATE INDEX jobs_by_state ON jobs (state);
    CREATE TABLE job_events (
        job_id TEXT NOT NULL,
        seq INTEGER NOT NULL,
        event TEXT NOT NULL,
        PRIMARY KEY (job_id, seq)
    ) STRICT, WITHOUT ROWID;",
    // A job's previous checkpoint is kept as a fallback (see `CheckpointRef::previous`);
    // its key is a column so recovery's garbage collection sees it without decoding records.
    "ALTER TABLE jobs ADD COLUMN previous_checkpoint_key TEXT;",
    // Job leases (see `MetadataStore::claim_job`) and the models change counter.
    "ALTER TABLE jobs ADD COLUMN lease_owner TEXT;
    ALTER TABLE jobs ADD COLUMN lease_expires_ms INTEGER;
    ALTER TABLE jobs ADD COLUMN cancel_requested INTEGER NOT NULL DEFAULT 0;
    CREATE TABLE counters (name TEXT PRIMARY KEY NOT NULL, value INTEGER NOT NULL) STRICT;
    INSERT INTO counters (name, value) VALUES ('models', 0);",
];

pub struct SqliteMetadata {
    conn: Arc<Mutex<Connection>>,
}

impl SqliteMetadata {
    pub fn open(path: &Path) -> Result<Self> {
        let conn = Connection::open(path)?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "FULL")?;
        conn.busy_timeout(std::time::Duration::from_secs(5))?;
        migrate(&conn)?;
        Ok(Self { conn: Arc::new(Mutex::new(conn)) })
    }

    /// Drops every job lease: only right after opening, when this process owns the file and
    /// whoever held a lease (its predecessor) is gone.
    pub async fn break_leases(&self) -> Result<u64> {
        self.with_conn(|c| {
            let n = c.execute(
                "UPDATE jobs SET lease_owner = NULL, lease_expires_ms = NULL WHERE lease_owner IS NOT NULL",
                [],
            )?;
            Ok(n as u64)
        })
        .await
    }

    /// Runs `f` with the connection on the blocking pool.
    async fn with_conn<T: Send + 'static>(
        &self,
        f: impl FnOnce(&mut Connection) -> Result<T> + Send + 'static,
    ) -> Result<T> {
        let conn = Arc::clone(&self.conn);
        tokio::task::spawn_blocking(move || {
            let mut guard = conn.lock().map_err(|_| Error::internal("metadata database", "lock poisoned"))?;
            f(&mut guard)
        })
        .await
        .map_err(|e| Error::internal("metadata task", e))?
    }
}

fn migrate(conn: &Connection) -> Result<()> {
    let version: i64 = conn.pragma_query_value(None, "user_version", |r| r.get(0))?;
    let version = usize::try_from(version).unwrap_or(usize::MAX);
    if version > MIGRATIONS.len() {
        return Err(Error::internal(
            "metadata database",
            format!("schema version {version} is newer than this server ({}); refusing to touch it", MIGRATIONS.len()),
        ));
    }
    for (i, sql) in MIGRATIONS.iter().enumerate().skip(version) {
        conn.execute_batch(&format!("BEGIN; {sql} PRAGMA user_version = {}; COMMIT;", i + 1))?;
    }
    Ok(())
}

/// Counts a model change (`MetadataStore::models_version`) in the same transaction.
fn bump_counter(kind: Named, tx: &rusqlite::Transaction<'_>) -> Result<()> {
    if kind.counts_changes() {
        tx.execute("UPDATE counters SET value = value + 1 WHERE name = 'models'", [])?;
    }
    Ok(())
}

#[async_trait]
impl NamedRecords for SqliteMetadata {
    async fn insert_named(&self, kind: Named, name: &str, blob_key: &str, json: String) -> Result<()> {
        let (name, key) = (name.to_owned(), blob_key.to_owned());
        self.with_conn(move |c| {
            let tx = c.transaction()?;
            let sql = format!("INSERT INTO {} (name, blob_key, record) VALUES (?1, ?2, ?3)", kind.table());
            match tx.execute(&sql, params![name, key, json]) {
                Ok(_) => {}
                Err(e) if is_constraint(&e) => {
                    return Err(Error::AlreadyExists(format!("{} '{name}' already exists", kind.what())));
                }
                Err(e) => return Err(e.into()),
            }
            bump_counter(kind, &tx)?;
            tx.commit()?;
            Ok(())
        })
        .await
    }

    async fn get_named(&self, kind: Named, name: &str) -> Result<Option<String>> {
        let name = name.to_owned();
        self.with_conn(move |c| {
            let sql = format!("SELECT record FROM {} WHERE name = ?1", kind.table());
            Ok(c.query_row(&sql, [name], |r| r.get(0)).optional()?)
        })
        .await
    }

    async fn list_named(&self, kind: Named, after: &str, limit: usize) -> Result<Vec<String>> {
        let after = after.to_owned();
        self.with_conn(move |c| {
            let sql = format!("SELECT record FROM {} WHERE name > ?1 ORDER BY name LIMIT ?2", kind.table());
            let mut stmt = c.prepare(&sql)?;
            let rows = stmt.query_map(params![after, limit as i64], |r| r.get::<_, String>(0))?;
            Ok(rows.collect::<Result<Vec<_>, _>>()?)
        })
        .await
    }

    async fn delete_named(&self, kind: Named, name: &str) -> Result<Option<String>> {
        let name = name.to_owned();
        self.with_conn(move |c| {
            let tx = c.transaction()?;
            let select = format!("SELECT record FROM {} WHERE name = ?1", kind.table());
            let json: Option<String> = tx.query_row(&select, [&name], |r| r.get(0)).optional()?;
            let Some(json) = json else { return Ok(None) };
            tx.execute(&format!("DELETE FROM {} WHERE name = ?1", kind.table()), [&name])?;
            bump_counter(kind, &tx)?;
            tx.commit()?;
            Ok(Some(json))
        })
        .await
    }
}

fn lease_ms(lease: Duration) -> i64 {
    i64::try_from(lease.as_millis()).unwrap_or(i64::MAX)
}

fn is_constraint(e: &rusqlite::Error) -> bool {
    matches!(e, rusqlite::Error::SqliteFailure(f, _) if f.code == rusqlite::ErrorCode::ConstraintViolation)
}

#[async_trait]
impl MetadataStore for SqliteMetadata {
    fn named_records(&self) -> &dyn NamedRecords {
        self
    }

    async fn referenced_blob_keys(&self) -> Result<HashSet<String>> {
        self.with_conn(|c| {
            let mut stmt = c.prepare(
                "SELECT blob_key FROM datasets UNION SELECT blob_key FROM models
                 UNION SELECT checkpoint_key FROM jobs WHERE checkpoint_key IS NOT NULL
                 UNION SELECT previous_checkpoint_key FROM jobs WHERE previous_checkpoint_key IS NOT NULL",
            )?;
            let keys = stmt.query_map([], |r| r.get::<_, String>(0))?;
            Ok(keys.collect::<Result<HashSet<_>, _>>()?)
        })
        .await
    }

    async fn insert_job(&self, record: &JobRecord, events: &[JobEvent]) -> Result<()> {
        let json = encode(record)?;
        let events: Vec<(u64, String)> = events.iter().map(|e| Ok((e.seq, encode(e)?))).collect::<Result<_>>()?;
        let (id, state) = (record.id.clone(), record.state.as_str());
        let (ckpt, previous) = checkpoint_keys(record);
        self.with_conn(move |c| {
            let tx = c.transaction()?;
            match tx.execute(
                "INSERT INTO jobs (id, state, checkpoint_key, previous_checkpoint_key, record) VALUES (?1, ?2, ?3, ?4, ?5)",
                params![id, state, ckpt, previous, json],
            ) {
                Ok(_) => {}
                Err(e) if is_constraint(&e) => return Err(Error::AlreadyExists(format!("job '{id}' already exists"))),
                Err(e) => return Err(e.into()),
            }
            for (seq, event) in &events {
                tx.execute(
                    "INSERT INTO job_events (job_id, seq, event) VALUES (?1, ?2, ?3)",
                    params![id, seq_i64(*seq), event],
                )?;
            }
            tx.commit()?;
            Ok(())
        })
        .await
    }

    async fn get_job(&self, id: &str) -> Result<Option<JobRecord>> {
        let id = id.to_owned();
        self.with_conn(move |c| {
            let json: Option<String> =
                c.query_row("SELECT record FROM jobs WHERE id = ?1", [id], |r| r.get(0)).optional()?;
            json.as_deref().map(decode).transpose()
        })
        .await
    }

    async fn list_jobs(&self, state: Option<JobState>, after: i64, limit: usize) -> Result<Vec<(i64, JobRecord)>> {
        let state = state.map(JobState::as_str);
        self.with_conn(move |c| {
            let after = if after <= 0 { i64::MAX } else { after };
            let mut stmt = c.prepare(
                "SELECT seq, record FROM jobs WHERE seq < ?1 AND (?2 IS NULL OR state = ?2) ORDER BY seq DESC LIMIT ?3",
            )?;
            let rows = stmt.query_map(params![after, state, limit as i64], |r| {
                Ok((r.get::<_, i64>(0)?, r.get::<_, String>(1)?))
            })?;
            rows.map(|r| {
                let (seq, json) = r?;
                Ok((seq, decode(&json)?))
            })
            .collect()
        })
        .await
    }

    async fn jobs_in_states(&self, states: &[JobState]) -> Result<Vec<JobRecord>> {
        let wanted: Vec<&'static str> = states.iter().map(|s| s.as_str()).collect();
        self.with_conn(move |c| {
            let mut stmt = c.prepare("SELECT state, record FROM jobs ORDER BY seq")?;
            let rows = stmt.query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, String>(1)?)))?;
            let mut out = Vec::new();
            for row in rows {
                let (state, json) = row?;
                if wanted.contains(&state.as_str()) {
                    out.push(decode(&json)?);
                }
            }
            Ok(out)
        })
        .await
    }

    async fn count_jobs_by_state(&self) -> Result<Vec<(JobState, u64)>> {
        self.with_conn(|c| {
            // Answered from the jobs_by_state index alone.
            let mut stmt = c.prepare("SELECT state, COUNT(*) FROM jobs GROUP BY state")?;
            let rows = stmt.query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))?;
            let mut counts: Vec<(JobState, u64)> = JobState::ALL.iter().map(|s| (*s, 0)).collect();
            for row in rows {
                let (state, n) = row?;
                if let Some(entry) = counts.iter_mut().find(|(s, _)| s.as_str() == state) {
                    entry.1 = u64::try_from(n).unwrap_or(0);
                }
            }
            Ok(counts)
        })
        .await
    }

    async fn record_job(&self, record: &JobRecord, events: &[JobEvent], owner: Option<&str>) -> Result<()> {
        let json = encode(record)?;
        let events: Vec<(u64, String)> = events.iter().map(|e| Ok((e.seq, encode(e)?))).collect::<Result<_>>()?;
        let (id, state) = (record.id.clone(), record.state);
        let (ckpt, previous) = checkpoint_keys(record);
        let owner = owner.map(str::to_owned);
        self.with_conn(move |c| {
            let tx = c.transaction()?;
            let current: Option<(String, Option<String>)> = tx
                .query_row("SELECT state, lease_owner FROM jobs WHERE id = ?1", [&id], |r| Ok((r.get(0)?, r.get(1)?)))
                .optional()?;
            let Some((current, holder)) = current else {
                return Err(Error::NotFound(format!("job '{id}' not found")));
            };
            check_transition(&id, &current, state, holder.as_deref(), owner.as_deref())?;
            // A terminal state ends the lease.
            let keep_lease = if state.is_terminal() { None } else { holder };
            tx.execute(
                "UPDATE jobs SET state = ?2, checkpoint_key = ?3, previous_checkpoint_key = ?4, record = ?5,
                 lease_owner = ?6, lease_expires_ms = CASE WHEN ?6 IS NULL THEN NULL ELSE lease_expires_ms END
                 WHERE id = ?1",
                params![id, state.as_str(), ckpt, previous, json, keep_lease],
            )?;
            for (seq, event) in &events {
                tx.execute(
                    "INSERT INTO job_events (job_id, seq, event) VALUES (?1, ?2, ?3)",
                    params![id, seq_i64(*seq), event],
                )?;
            }
            tx.commit()?;
            Ok(())
        })
        .await
    }

    async fn claim_job(&self, owner: &str, lease: Duration) -> Result<Option<JobRecord>> {
        let owner = owner.to_owned();
        self.with_conn(move |c| {
            let now = now_ms();
            let tx = c.transaction_with_behavior(rusqlite::TransactionBehavior::Immediate)?;
            let found: Option<(String, String)> = tx
                .query_row(
                    "SELECT id, record FROM jobs WHERE state IN ('pending', 'running')
                     AND (lease_owner IS NULL OR lease_expires_ms < ?1) ORDER BY seq LIMIT 1",
                    [now],
                    |r| Ok((r.get(0)?, r.get(1)?)),
                )
                .optional()?;
            let Some((id, json)) = found else { return Ok(None) };
            tx.execute(
                "UPDATE jobs SET lease_owner = ?2, lease_expires_ms = ?3 WHERE id = ?1",
                params![id, owner, now.saturating_add(lease_ms(lease))],
            )?;
            tx.commit()?;
            decode(&json).map(Some)
        })
        .await
    }

    async fn renew_lease(&self, id: &str, owner: &str, lease: Duration) -> Result<Lease> {
        let (id, owner) = (id.to_owned(), owner.to_owned());
        self.with_conn(move |c| {
            let expires = now_ms().saturating_add(lease_ms(lease));
            let n = c.execute(
                "UPDATE jobs SET lease_expires_ms = ?3 WHERE id = ?1 AND lease_owner = ?2",
                params![id, owner, expires],
            )?;
            if n == 0 {
                return Ok(Lease::Lost);
            }
            let cancel: bool = c.query_row("SELECT cancel_requested FROM jobs WHERE id = ?1", [&id], |r| r.get(0))?;
            Ok(Lease::Held { cancel_requested: cancel })
        })
        .await
    }

    async fn release_lease(&self, id: &str, owner: &str) -> Result<()> {
        let (id, owner) = (id.to_owned(), owner.to_owned());
        self.with_conn(move |c| {
            c.execute(
                "UPDATE jobs SET lease_owner = NULL, lease_expires_ms = NULL WHERE id = ?1 AND lease_owner = ?2",
                params![id, owner],
            )?;
            Ok(())
        })
        .await
    }

    async fn request_cancel(&self, id: &str) -> Result<()> {
        let id = id.to_owned();
        self.with_conn(move |c| {
            c.execute("UPDATE jobs SET cancel_requested = 1 WHERE id = ?1", [id])?;
            Ok(())
        })
        .await
    }

    async fn models_version(&self) -> Result<u64> {
        self.with_conn(|c| {
            let v: i64 = c.query_row("SELECT value FROM counters WHERE name = 'models'", [], |r| r.get(0))?;
            Ok(u64::try_from(v).unwrap_or(0))
        })
        .await
    }

    async fn job_events(&self, id: &str, from_seq: u64, limit: usize) -> Result<Vec<JobEvent>> {
        let id = id.to_owned();
        self.with_conn(move |c| {
            let mut stmt =
                c.prepare("SELECT event FROM job_events WHERE job_id = ?1 AND seq >= ?2 ORDER BY seq LIMIT ?3")?;
            let rows = stmt.query_map(params![id, seq_i64(from_seq), limit as i64], |r| r.get::<_, String>(0))?;
            rows.map(|r| decode(&r?)).collect()
        })
        .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::JobEventKind;

    fn job(state: JobState, last_seq: u64) -> JobRecord {
        JobRecord {
            id: "j".into(),
            kind: "diffusion".into(),
            spec: serde_json::json!({}),
            state,
            step: 0,
            total_steps: 10,
            loss: None,
            error: String::new(),
            created_at_ms: 0,
            started_at_ms: None,
            finished_at_ms: None,
            last_seq,
            checkpoint: None,
            inputs: vec![],
            output_model: "m".into(),
        }
    }

    fn event(seq: u64, state: JobState) -> JobEvent {
        JobEvent { seq, time_ms: 0, event: JobEventKind::State { state, message: String::new() } }
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn jobs_keep_their_events_and_never_leave_a_terminal_state() {
        let dir = tempfile::tempdir().expect("tmp");
        let db = SqliteMetadata::open(&dir.path().join("m.sqlite3")).expect("open");
        db.insert_job(&job(JobState::Pending, 1), &[event(1, JobState::Pending)]).await.expect("insert");
        let dup = db.insert_job(&job(JobState::Pending, 1), &[event(1, JobState::Pending)]).await;
        assert!(matches!(dup, Err(Error::AlreadyExists(_))));
        let claimed = db.claim_job("w1", Duration::from_secs(60)).await.expect("claim").expect("a job");
        assert_eq!(claimed.id, "j");
        assert_eq!(db.claim_job("w2", Duration::from_secs(60)).await.expect("claim"), None, "leased to w1");
        let stranger = db.record_job(&job(JobState::Running, 2), &[event(2, JobState::Running)], Some("w2")).await;
        assert!(matches!(stranger, Err(Error::FailedPrecondition(_))), "{stranger:?}");
        db.record_job(&job(JobState::Running, 2), &[event(2, JobState::Running)], Some("w1")).await.expect("running");
        db.record_job(&job(JobState::Succeeded, 3), &[event(3, JobState::Succeeded)], Some("w1")).await.expect("done");
        let back = db.record_job(&job(JobState::Running, 4), &[event(4, JobState::Running)], None).await;
        assert!(matches!(back, Err(Error::FailedPrecondition(_))), "{back:?}");
        let events = db.job_events("j", 1, 100).await.expect("events");
        assert_eq!(events.iter().map(|e| e.seq).collect::<Vec<_>>(), vec![1, 2, 3], "the refused update wrote nothing");
        assert_eq!(db.get_job("j").await.expect("get").expect("some").state, JobState::Succeeded);
        // Reopening keeps everything (schema migrations are idempotent).
        drop(db);
        let db = SqliteMetadata::open(&dir.path().join("m.sqlite3")).expect("reopen");
        assert_eq!(db.job_events("j", 2, 100).await.expect("events").len(), 2);
    }

    /// A record whose statistics overflowed (written before ingestion refused values beyond
    /// float32's range: an infinite std became JSON `null`) reads, lists and deletes.
    #[tokio::test(flavor = "multi_thread")]
    async fn a_dataset_whose_statistics_overflowed_is_still_read_and_deleted() {
        use crate::store::{ArrayRecord, ArrayStats, DatasetKind, DatasetRecord};
        let dir = tempfile::tempdir().expect("tmp");
        let db = SqliteMetadata::open(&dir.path().join("m.sqlite3")).expect("open");
        let stats = ArrayStats { min: vec![0.25], max: vec![1e300], mean: vec![2.5e299], std: vec![f64::INFINITY] };
        let record = DatasetRecord {
            name: "far".into(),
            kind: DatasetKind::Samples,
            num_rows: 4,
            arrays: vec![ArrayRecord {
                name: "samples".into(),
                dtype: "float64".into(),
                shape: vec![4, 1],
                file: "samples.npy".into(),
                stats: Some(stats),
            }],
            episodes: None,
            sha256: "0".repeat(64),
            size_bytes: 32,
            created_at_ms: 0,
            description: String::new(),
            blob_key: "k".into(),
        };
        db.insert_dataset(&record).await.expect("insert");
        let read = db.get_dataset("far").await.expect("readable").expect("stored");
        let stats = read.arrays[0].stats.as_ref().expect("stats");
        assert_eq!((stats.min[0], stats.max[0]), (0.25, 1e300));
        assert!(stats.std[0].is_nan(), "the lost value reads as NaN: {:?}", stats.std);
        assert_eq!(db.list_datasets("", 10).await.expect("listed").len(), 1);
        assert!(db.delete_dataset("far").await.expect("deleted").is_some());
        assert!(db.get_dataset("far").await.expect("read").is_none());
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn leases_lapse_renew_release_and_carry_cancellation() {
        let dir = tempfile::tempdir().expect("tmp");
        let db = SqliteMetadata::open(&dir.path().join("m.sqlite3")).expect("open");
        db.insert_job(&job(JobState::Pending, 1), &[event(1, JobState::Pending)]).await.expect("insert");
        let short = Duration::from_millis(50);
        assert!(db.claim_job("w1", short).await.expect("claim").is_some());
        assert_eq!(db.renew_lease("j", "w1", short).await.expect("renew"), Lease::Held { cancel_requested: false });
        assert_eq!(db.renew_lease("j", "w2", short).await.expect("renew"), Lease::Lost);
        tokio::time::sleep(Duration::from_millis(80)).await;
        // Lapsed: another worker takes the job over, and the first one's lease is gone.
        assert!(db.claim_job("w2", Duration::from_secs(60)).await.expect("claim").is_some());
        assert_eq!(db.renew_lease("j", "w1", short).await.expect("renew"), Lease::Lost);
        db.request_cancel("j").await.expect("cancel");
        assert_eq!(
            db.renew_lease("j", "w2", Duration::from_secs(60)).await.expect("renew"),
            Lease::Held { cancel_requested: true }
        );
        db.release_lease("j", "w2").await.expect("release");
        assert!(db.claim_job("w3", Duration::from_secs(60)).await.expect("claim").is_some(), "released: claimable");
        assert_eq!(db.break_leases().await.expect("break"), 1);
        assert!(db.claim_job("w4", Duration::from_secs(60)).await.expect("claim").is_some());
        assert_eq!(db.models_version().await.expect("version"), 0);
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn jobs_are_counted_by_state_with_zeros() {
        let dir = tempfile::tempdir().expect("tmp");
        let db = SqliteMetadata::open(&dir.path().join("m.sqlite3")).expect("open");
        for (id, state) in [("a", JobState::Pending), ("b", JobState::Pending), ("c", JobState::Failed)] {
            let record = JobRecord { id: id.into(), ..job(state, 1) };
            db.insert_job(&record, &[event(1, state)]).await.expect("insert");
        }
        let counts = db.count_jobs_by_state().await.expect("count");
        assert_eq!(
            counts,
            vec![
                (JobState::Pending, 2),
                (JobState::Running, 0),
                (JobState::Succeeded, 0),
                (JobState::Failed, 1),
                (JobState::Cancelled, 0)
            ]
        );
    }
}
