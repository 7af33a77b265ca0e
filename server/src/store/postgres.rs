//! Shared metadata store and job queue: PostgreSQL (`storage.backend = "shared"`).
//!
//! The same tables as the embedded SQLite store (records as JSON text next to their indexed
//! keys), so both backends keep one record format. Differences that matter:
//! - migrations run at start inside one transaction holding an advisory lock, so replicas
//!   starting together apply each migration exactly once;
//! - job claims use `SELECT ... FOR UPDATE SKIP LOCKED`: concurrent workers never wait on
//!   each other's candidate rows and never claim the same job;
//! - lease times are the database's clock (`now()`), never a worker's, so clock skew between
//!   nodes cannot shorten or stretch a lease;
//! - TLS as the URL's `sslmode` says (prefer, require, disable), through rustls: the server's
//!   certificate is always verified, against `storage.postgres.ca_file` or the system's roots,
//!   and its name against the URL's host (libpq's verify-full), since a TLS connection whose
//!   peer is not checked protects the password from no one who can intercept it.

use std::collections::HashSet;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod, Runtime};
use tokio_postgres::Transaction;
use tokio_postgres::config::SslMode;
use tokio_postgres::error::SqlState;
use tokio_postgres_rustls::MakeRustlsConnect;

use super::records::{Named, NamedRecords, check_transition, checkpoint_keys, decode, encode, seq_i64};
use super::{JobEvent, JobRecord, JobState, Lease, MetadataStore};
use crate::config::PostgresConfig;
use crate::error::{Error, Result, error_chain};

/// Schema migrations, applied in order; `relreward_schema.version` records how many ran.
const MIGRATIONS: &[&str] = &["CREATE TABLE datasets (
        name TEXT PRIMARY KEY,
        blob_key TEXT NOT NULL,
        record TEXT NOT NULL
    );
    CREATE TABLE models (
        name TEXT PRIMARY KEY,
        blob_key TEXT NOT NULL,
        record TEXT NOT NULL
    );
    CREATE TABLE jobs (
        seq BIGSERIAL PRIMARY KEY,
        id TEXT UNIQUE NOT NULL,
        state TEXT NOT NULL,
        checkpoint_key TEXT,
        previous_checkpoint_key TEXT,
        record TEXT NOT NULL,
        lease_owner TEXT,
        lease_expires TIMESTAMPTZ,
        cancel_requested BOOLEAN NOT NULL DEFAULT FALSE
    );
    CREATE INDEX jobs_by_state ON jobs (state, seq);
    CREATE TABLE job_events (
        job_id TEXT NOT NULL,
        seq BIGINT NOT NULL,
        event TEXT NOT NULL,
        PRIMARY KEY (job_id, seq)
    );
    CREATE TABLE counters (name TEXT PRIMARY KEY, value BIGINT NOT NULL);
    INSERT INTO counters (name, value) VALUES ('models', 0);"];

/// How long start-up waits for the database (a pod may start before it).
const CONNECT_PATIENCE: Duration = Duration::from_secs(60);

pub struct PostgresMetadata {
    pool: Pool,
}

impl PostgresMetadata {
    /// Connects (retrying while the database is not up yet) and runs pending migrations.
    pub async fn connect(config: &PostgresConfig) -> Result<Self> {
        let pg: tokio_postgres::Config = config
            .url
            .parse()
            .map_err(|e| Error::internal("storage.postgres.url", format!("not a valid PostgreSQL URL: {e}")))?;
        let tls = tls_connector(config)?;
        let manager = Manager::from_config(pg, tls, ManagerConfig { recycling_method: RecyclingMethod::Fast });
        let pool = Pool::builder(manager)
            .max_size(config.pool_size)
            .runtime(Runtime::Tokio1)
            .create_timeout(Some(Duration::from_secs(10)))
            .wait_timeout(Some(Duration::from_secs(30)))
            .build()
            .map_err(|e| Error::internal("metadata database pool", e))?;
        let store = Self { pool };
        let started = tokio::time::Instant::now();
        loop {
            match store.pool.get().await {
                Ok(_) => break,
                Err(e) => {
                    let failure = first_connection_failure(e);
                    if failure.is_fatal() || started.elapsed() >= CONNECT_PATIENCE {
                        return Err(Error::Unavailable(failure.message()));
                    }
                    tracing::warn!("waiting for the metadata database: {}", failure.message());
                    tokio::time::sleep(Duration::from_secs(2)).await;
                }
            }
        }
        let version = store.migrate().await?;
        tracing::info!(schema_version = version, "metadata database ready (PostgreSQL)");
        Ok(store)
    }

    async fn migrate(&self) -> Result<usize> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        // One migrator at a time across every replica; released at commit.
        tx.execute("SELECT pg_advisory_xact_lock(hashtext('relreward-migrations'))", &[]).await?;
        tx.batch_execute("CREATE TABLE IF NOT EXISTS relreward_schema (version INTEGER NOT NULL)").await?;
        let version: i32 = match tx.query_opt("SELECT version FROM relreward_schema", &[]).await? {
            Some(row) => row.get(0),
            None => {
                tx.execute("INSERT INTO relreward_schema (version) VALUES (0)", &[]).await?;
                0
            }
        };
        let version = usize::try_from(version).unwrap_or(usize::MAX);
        if version > MIGRATIONS.len() {
            return Err(Error::internal(
                "metadata database",
                format!(
                    "schema version {version} is newer than this server ({}); refusing to touch it",
                    MIGRATIONS.len()
                ),
            ));
        }
        for sql in &MIGRATIONS[version..] {
            tx.batch_execute(sql).await?;
        }
        let now = i32::try_from(MIGRATIONS.len()).unwrap_or(i32::MAX);
        tx.execute("UPDATE relreward_schema SET version = $1", &[&now]).await?;
        tx.commit().await?;
        Ok(MIGRATIONS.len())
    }

    async fn client(&self) -> Result<deadpool_postgres::Object> {
        self.pool.get().await.map_err(|e| Error::Unavailable(format!("metadata database unreachable: {e}")))
    }
}

/// Why the first connection failed: worth waiting for (the database is starting, the network
/// is not up yet) or not (settings a retry cannot change).
enum FirstConnection {
    Waiting(String),
    Tls(String),
    Refused(String),
}

impl FirstConnection {
    fn is_fatal(&self) -> bool {
        !matches!(self, Self::Waiting(_))
    }

    fn message(&self) -> String {
        match self {
            Self::Waiting(m) => format!("metadata database unreachable: {m}"),
            Self::Tls(m) => format!(
                "TLS to the metadata database failed: {m} (storage.postgres.ca_file must hold the CA that signed the \
                 database server's certificate, or be empty to use the system's roots; the certificate must name \
                 the host in storage.postgres.url; sslmode=disable there turns TLS off)"
            ),
            Self::Refused(m) => {
                format!("the metadata database refused the connection: {m} (check storage.postgres.url)")
            }
        }
    }
}

fn first_connection_failure(e: deadpool_postgres::PoolError) -> FirstConnection {
    let text = error_chain(&e);
    let deadpool_postgres::PoolError::Backend(backend) = &e else { return FirstConnection::Waiting(text) };
    // Class 28: authentication (bad password, no pg_hba.conf entry, TLS required);
    // 3D000: no such database. A retry gives the same answer.
    if let Some(code) = backend.code().map(SqlState::code)
        && (code.starts_with("28") || code == SqlState::INVALID_CATALOG_NAME.code())
    {
        return FirstConnection::Refused(text);
    }
    if text.contains("TLS handshake") || text.contains("does not support TLS") {
        return FirstConnection::Tls(text);
    }
    FirstConnection::Waiting(text)
}

/// What connections to the database go through: TLS per the URL's `sslmode`, verified against
/// `storage.postgres.ca_file` or the system's roots.
pub fn tls_connector(config: &PostgresConfig) -> Result<MakeRustlsConnect> {
    let mode = match config.url.parse::<tokio_postgres::Config>() {
        Ok(pg) => pg.get_ssl_mode(),
        Err(_) => SslMode::Prefer,
    };
    Ok(MakeRustlsConnect::new(tls_config(&config.ca_file, mode)?))
}

/// The rustls settings for connections to the database: roots from `ca_file` (PEM), or the
/// system's when it is empty. Not needed with `sslmode=disable`, so missing system roots only
/// matter when TLS may be used.
fn tls_config(ca_file: &str, mode: SslMode) -> Result<rustls::ClientConfig> {
    let key = "storage.postgres.ca_file";
    let mut roots = rustls::RootCertStore::empty();
    if ca_file.is_empty() {
        let found = rustls_native_certs::load_native_certs();
        let (added, _) = roots.add_parsable_certificates(found.certs);
        if added == 0 && mode != SslMode::Disable {
            tracing::warn!(
                "no trusted root certificates found on this system: TLS to the metadata database will fail unless \
                 {key} is set"
            );
        }
    } else {
        for cert in read_pem_certificates(Path::new(ca_file)).map_err(|m| Error::internal(key, m))? {
            roots.add(cert).map_err(|e| Error::internal(key, format!("{ca_file}: {e}")))?;
        }
    }
    // ring, named explicitly: rustls refuses to guess when a dependency enables another provider.
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| Error::internal("TLS to the metadata database", e))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(config)
}

/// Every certificate in the PEM file at `path`; at least one.
fn read_pem_certificates(path: &Path) -> std::result::Result<Vec<rustls::pki_types::CertificateDer<'static>>, String> {
    use rustls::pki_types::pem::PemObject;
    let shown = path.display();
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
    let certs = rustls::pki_types::CertificateDer::pem_slice_iter(&bytes)
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| format!("{shown} is not PEM: {e}"))?;
    if certs.is_empty() {
        return Err(format!("{shown} holds no certificate (expected PEM, -----BEGIN CERTIFICATE-----)"));
    }
    Ok(certs)
}

fn is_unique_violation(e: &tokio_postgres::Error) -> bool {
    e.code() == Some(&SqlState::UNIQUE_VIOLATION)
}

fn lease_secs(lease: Duration) -> f64 {
    lease.as_secs_f64()
}

/// Counts a model change (`MetadataStore::models_version`) in the same transaction.
async fn bump_counter(kind: Named, tx: &Transaction<'_>) -> Result<()> {
    if kind.counts_changes() {
        tx.execute("UPDATE counters SET value = value + 1 WHERE name = 'models'", &[]).await?;
    }
    Ok(())
}

#[async_trait]
impl NamedRecords for PostgresMetadata {
    async fn insert_named(&self, kind: Named, name: &str, blob_key: &str, json: String) -> Result<()> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        let sql = format!("INSERT INTO {} (name, blob_key, record) VALUES ($1, $2, $3)", kind.table());
        match tx.execute(&sql, &[&name, &blob_key, &json]).await {
            Ok(_) => {}
            Err(e) if is_unique_violation(&e) => {
                return Err(Error::AlreadyExists(format!("{} '{name}' already exists", kind.what())));
            }
            Err(e) => return Err(e.into()),
        }
        bump_counter(kind, &tx).await?;
        tx.commit().await?;
        Ok(())
    }

    async fn get_named(&self, kind: Named, name: &str) -> Result<Option<String>> {
        let client = self.client().await?;
        let sql = format!("SELECT record FROM {} WHERE name = $1", kind.table());
        let row = client.query_opt(&sql, &[&name]).await?;
        Ok(row.map(|r| r.get::<_, String>(0)))
    }

    async fn list_named(&self, kind: Named, after: &str, limit: usize) -> Result<Vec<String>> {
        let client = self.client().await?;
        // COLLATE "C": byte order, the order names sort in with the embedded store too.
        let sql = format!(
            "SELECT record FROM {} WHERE name COLLATE \"C\" > $1 ORDER BY name COLLATE \"C\" LIMIT $2",
            kind.table()
        );
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let rows = client.query(&sql, &[&after, &limit]).await?;
        Ok(rows.iter().map(|r| r.get::<_, String>(0)).collect())
    }

    async fn delete_named(&self, kind: Named, name: &str) -> Result<Option<String>> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        let sql = format!("DELETE FROM {} WHERE name = $1 RETURNING record", kind.table());
        let Some(row) = tx.query_opt(&sql, &[&name]).await? else { return Ok(None) };
        let json = row.get::<_, String>(0);
        bump_counter(kind, &tx).await?;
        tx.commit().await?;
        Ok(Some(json))
    }
}

async fn insert_events(tx: &Transaction<'_>, id: &str, events: &[JobEvent]) -> Result<()> {
    for event in events {
        tx.execute(
            "INSERT INTO job_events (job_id, seq, event) VALUES ($1, $2, $3)",
            &[&id, &seq_i64(event.seq), &encode(event)?],
        )
        .await?;
    }
    Ok(())
}

#[async_trait]
impl MetadataStore for PostgresMetadata {
    fn named_records(&self) -> &dyn NamedRecords {
        self
    }

    async fn referenced_blob_keys(&self) -> Result<HashSet<String>> {
        let client = self.client().await?;
        let rows = client
            .query(
                "SELECT blob_key FROM datasets UNION SELECT blob_key FROM models
                 UNION SELECT checkpoint_key FROM jobs WHERE checkpoint_key IS NOT NULL
                 UNION SELECT previous_checkpoint_key FROM jobs WHERE previous_checkpoint_key IS NOT NULL",
                &[],
            )
            .await?;
        Ok(rows.iter().map(|r| r.get::<_, String>(0)).collect())
    }

    async fn insert_job(&self, record: &JobRecord, events: &[JobEvent]) -> Result<()> {
        let json = encode(record)?;
        let (ckpt, previous) = checkpoint_keys(record);
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        match tx
            .execute(
                "INSERT INTO jobs (id, state, checkpoint_key, previous_checkpoint_key, record) VALUES ($1, $2, $3, $4, $5)",
                &[&record.id, &record.state.as_str(), &ckpt, &previous, &json],
            )
            .await
        {
            Ok(_) => {}
            Err(e) if is_unique_violation(&e) => {
                return Err(Error::AlreadyExists(format!("job '{}' already exists", record.id)));
            }
            Err(e) => return Err(e.into()),
        }
        insert_events(&tx, &record.id, events).await?;
        tx.commit().await?;
        Ok(())
    }

    async fn get_job(&self, id: &str) -> Result<Option<JobRecord>> {
        let client = self.client().await?;
        let row = client.query_opt("SELECT record FROM jobs WHERE id = $1", &[&id]).await?;
        row.map(|r| decode(r.get::<_, &str>(0))).transpose()
    }

    async fn list_jobs(&self, state: Option<JobState>, after: i64, limit: usize) -> Result<Vec<(i64, JobRecord)>> {
        let client = self.client().await?;
        let after = if after <= 0 { i64::MAX } else { after };
        let state = state.map(JobState::as_str);
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let rows = client
            .query(
                "SELECT seq, record FROM jobs WHERE seq < $1 AND ($2::TEXT IS NULL OR state = $2)
                 ORDER BY seq DESC LIMIT $3",
                &[&after, &state, &limit],
            )
            .await?;
        rows.iter().map(|r| Ok((r.get::<_, i64>(0), decode(r.get::<_, &str>(1))?))).collect()
    }

    async fn jobs_in_states(&self, states: &[JobState]) -> Result<Vec<JobRecord>> {
        let client = self.client().await?;
        let wanted: Vec<&str> = states.iter().map(|s| s.as_str()).collect();
        let rows = client.query("SELECT record FROM jobs WHERE state = ANY($1) ORDER BY seq", &[&wanted]).await?;
        rows.iter().map(|r| decode(r.get::<_, &str>(0))).collect()
    }

    async fn count_jobs_by_state(&self) -> Result<Vec<(JobState, u64)>> {
        let client = self.client().await?;
        let rows = client.query("SELECT state, COUNT(*) FROM jobs GROUP BY state", &[]).await?;
        let mut counts: Vec<(JobState, u64)> = JobState::ALL.iter().map(|s| (*s, 0)).collect();
        for row in rows {
            let (state, n): (&str, i64) = (row.get(0), row.get(1));
            if let Some(entry) = counts.iter_mut().find(|(s, _)| s.as_str() == state) {
                entry.1 = u64::try_from(n).unwrap_or(0);
            }
        }
        Ok(counts)
    }

    async fn record_job(&self, record: &JobRecord, events: &[JobEvent], owner: Option<&str>) -> Result<()> {
        let json = encode(record)?;
        let (ckpt, previous) = checkpoint_keys(record);
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        // FOR UPDATE: the check and the write see the same lease holder.
        let row = tx.query_opt("SELECT state, lease_owner FROM jobs WHERE id = $1 FOR UPDATE", &[&record.id]).await?;
        let Some(row) = row else {
            return Err(Error::NotFound(format!("job '{}' not found", record.id)));
        };
        let (current, holder): (&str, Option<&str>) = (row.get(0), row.get(1));
        check_transition(&record.id, current, record.state, holder, owner)?;
        tx.execute(
            "UPDATE jobs SET state = $2, checkpoint_key = $3, previous_checkpoint_key = $4, record = $5,
             lease_owner = CASE WHEN $6 THEN NULL ELSE lease_owner END,
             lease_expires = CASE WHEN $6 THEN NULL ELSE lease_expires END
             WHERE id = $1",
            &[&record.id, &record.state.as_str(), &ckpt, &previous, &json, &record.state.is_terminal()],
        )
        .await?;
        insert_events(&tx, &record.id, events).await?;
        tx.commit().await?;
        Ok(())
    }

    async fn claim_job(&self, owner: &str, lease: Duration) -> Result<Option<JobRecord>> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        let row = tx
            .query_opt(
                "SELECT id, record FROM jobs WHERE state IN ('pending', 'running')
                 AND (lease_owner IS NULL OR lease_expires < now())
                 ORDER BY seq LIMIT 1 FOR UPDATE SKIP LOCKED",
                &[],
            )
            .await?;
        let Some(row) = row else { return Ok(None) };
        let (id, json): (&str, &str) = (row.get(0), row.get(1));
        tx.execute(
            "UPDATE jobs SET lease_owner = $2, lease_expires = now() + make_interval(secs => $3) WHERE id = $1",
            &[&id, &owner, &lease_secs(lease)],
        )
        .await?;
        let record = decode(json)?;
        tx.commit().await?;
        Ok(Some(record))
    }

    async fn renew_lease(&self, id: &str, owner: &str, lease: Duration) -> Result<Lease> {
        let client = self.client().await?;
        let row = client
            .query_opt(
                "UPDATE jobs SET lease_expires = now() + make_interval(secs => $3)
                 WHERE id = $1 AND lease_owner = $2 RETURNING cancel_requested",
                &[&id, &owner, &lease_secs(lease)],
            )
            .await?;
        Ok(row.map_or(Lease::Lost, |r| Lease::Held { cancel_requested: r.get(0) }))
    }

    async fn release_lease(&self, id: &str, owner: &str) -> Result<()> {
        let client = self.client().await?;
        client
            .execute(
                "UPDATE jobs SET lease_owner = NULL, lease_expires = NULL WHERE id = $1 AND lease_owner = $2",
                &[&id, &owner],
            )
            .await?;
        Ok(())
    }

    async fn request_cancel(&self, id: &str) -> Result<()> {
        let client = self.client().await?;
        client.execute("UPDATE jobs SET cancel_requested = TRUE WHERE id = $1", &[&id]).await?;
        Ok(())
    }

    async fn models_version(&self) -> Result<u64> {
        let client = self.client().await?;
        let row = client.query_one("SELECT value FROM counters WHERE name = 'models'", &[]).await?;
        Ok(u64::try_from(row.get::<_, i64>(0)).unwrap_or(0))
    }

    async fn job_events(&self, id: &str, from_seq: u64, limit: usize) -> Result<Vec<JobEvent>> {
        let client = self.client().await?;
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let rows = client
            .query(
                "SELECT event FROM job_events WHERE job_id = $1 AND seq >= $2 ORDER BY seq LIMIT $3",
                &[&id, &seq_i64(from_seq), &limit],
            )
            .await?;
        rows.iter().map(|r| decode(r.get::<_, &str>(0))).collect()
    }
}
