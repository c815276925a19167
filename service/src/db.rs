//! The metadata database through sqlx's `Any` driver: the embedded SQLite file (the default) or a PostgreSQL
//! server shared by several replicas, chosen by `database.url`. One set of queries serves both (numbered `$N`
//! parameters, `ON CONFLICT`, `RETURNING`); what differs is in `Backend`, in one place. Migrations per backend are
//! compiled in from `migrations/sqlite/` and `migrations/postgres/`. Runtime `query()` calls, so building needs no
//! database.

use std::path::Path;

use dsrl_suite::{TagName, TaskId, VersionId};
use sqlx::any::{AnyPoolOptions, AnyRow};
use sqlx::migrate::{Migration, MigrationType, Migrator};
use sqlx::{Any, AnyPool, Executor, Row, SqlSafeStr, Transaction};

/// The server's name for a hosted version row.
pub use dsrl_suite::HostedVersion as VersionRecord;

/// Which database holds the metadata. Every SQL difference between the two is a method here.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    Sqlite,
    Postgres,
}

impl Backend {
    fn of_url(url: &str) -> Result<Backend, sqlx::Error> {
        if url.starts_with("sqlite:") {
            Ok(Backend::Sqlite)
        } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Ok(Backend::Postgres)
        } else {
            Err(sqlx::Error::Configuration(
                format!("database.url must start with sqlite:, postgres:// or postgresql://, not {url:?}").into(),
            ))
        }
    }

    /// Joins a group's text values with commas.
    pub fn comma_list(self, column: &str) -> String {
        match self {
            Backend::Sqlite => format!("group_concat({column}, ',')"),
            Backend::Postgres => format!("string_agg({column}, ',')"),
        }
    }

    /// The column that orders dataset versions by creation (SQLite's rowid; PostgreSQL's identity column).
    pub fn creation_order(self) -> &'static str {
        match self {
            Backend::Sqlite => "rowid",
            Backend::Postgres => "seq",
        }
    }

    /// Appended to a subquery that picks a queued job: on PostgreSQL, concurrent evaluators skip rows another one
    /// is claiming instead of waiting for it (SQLite has one writer at a time, so nothing to skip). Only the rows of
    /// the table aliased `table` are locked.
    pub fn skip_locked(self, table: &str) -> String {
        match self {
            Backend::Sqlite => String::new(),
            Backend::Postgres => format!(" FOR UPDATE OF {table} SKIP LOCKED"),
        }
    }

    /// Appended to a SELECT of one row inside a transaction that later writes what depends on it: on PostgreSQL
    /// the row stays locked until the commit, so concurrent transactions on it run one after the other (SQLite
    /// already serializes writers).
    pub fn for_update(self) -> &'static str {
        match self {
            Backend::Sqlite => "",
            Backend::Postgres => " FOR UPDATE",
        }
    }

    fn migrations(self) -> &'static [(i64, &'static str, &'static str)] {
        match self {
            Backend::Sqlite => SQLITE_MIGRATIONS,
            Backend::Postgres => POSTGRES_MIGRATIONS,
        }
    }
}

/// When this process last saw the database fail for its storage (ms since the epoch; 0: never). See `connect`.
static STORAGE_FAILURE_AT_MS: std::sync::atomic::AtomicI64 = std::sync::atomic::AtomicI64::new(0);

/// Records a database error that says its storage failed (SQLite's READONLY, IOERR, FULL or CANTOPEN, or an I/O
/// error), so that no connection opened before it is handed out again. Every error that reaches a request passes
/// here (`From<sqlx::Error> for ApiError`), as do the health probe's.
pub fn note_failure(e: &sqlx::Error) {
    let storage = match e {
        sqlx::Error::Io(_) => true,
        sqlx::Error::Database(d) => d
            .code()
            .and_then(|c| c.parse::<i32>().ok())
            .is_some_and(|code| matches!(code & 0xff, 8 | 10 | 13 | 14)),
        _ => false,
    };
    if storage {
        STORAGE_FAILURE_AT_MS.store(now_ms(), std::sync::atomic::Ordering::Release);
    }
}

#[derive(Clone)]
pub struct Db {
    pool: AnyPool,
    backend: Backend,
    /// For the connections that hold advisory locks, opened apart from the pool (see `exclusively`).
    url: std::sync::Arc<str>,
}

impl Db {
    /// The embedded default: a SQLite file (created when missing).
    pub async fn open(path: &Path) -> Result<Db, sqlx::Error> {
        Db::connect(&format!("sqlite://{}?mode=rwc", path.display()), 8).await
    }

    /// Connects to `url` (`sqlite://PATH?mode=rwc` or `postgres://…`) and applies the backend's migrations. Replicas
    /// starting together are safe: sqlx takes an advisory lock around PostgreSQL migrations.
    pub async fn connect(url: &str, max_connections: u32) -> Result<Db, sqlx::Error> {
        sqlx::any::install_default_drivers();
        let backend = Backend::of_url(url)?;
        let pool = AnyPoolOptions::new()
            .max_connections(max_connections)
            .after_connect(move |conn, _| {
                Box::pin(async move {
                    if backend == Backend::Sqlite {
                        // WAL lets readers run beside the one writer; FULL syncs every commit; a writer waits for
                        // another instead of failing at once.
                        conn.execute(
                            "PRAGMA journal_mode = WAL; PRAGMA synchronous = FULL; PRAGMA foreign_keys = ON;
                             PRAGMA busy_timeout = 10000;",
                        )
                        .await?;
                        // SQLite opens a file it cannot open for writing (an unwritable or failing volume) read-only
                        // instead, and such a connection answers "attempt to write a readonly database" for its
                        // whole life. A write rolled back at once (nothing reaches the disk) tells: where it fails,
                        // the failure is noted, so `before_acquire` never hands this connection out again once it
                        // is back in the pool (it still serves the request at hand, which fails as it would).
                        if let Err(e) = conn
                            .execute("BEGIN; CREATE TABLE main.dsrl_write_check (x INTEGER); ROLLBACK;")
                            .await
                        {
                            note_failure(&e);
                            let _ = conn.execute("ROLLBACK").await;
                        }
                    }
                    Ok(())
                })
            })
            // A connection goes back to the pool only outside a transaction. When a statement, COMMIT or ROLLBACK
            // fails (an I/O error, a full disk), sqlx keeps its transaction depth above zero: handed out again, the
            // connection refused every later `begin` ("non-zero transaction depth") until the process restarted.
            // The ping first runs the rollback a dropped transaction queued; whatever is still open after it closes
            // the connection, and the pool opens a fresh one.
            .after_release(|conn, _| {
                Box::pin(async move {
                    sqlx::Connection::ping(conn).await?;
                    Ok(!sqlx::Connection::is_in_transaction(conn))
                })
            })
            // And none opened before this process last saw a write fail for its storage: SQLite reopens a file it
            // could not open read-write as read-only, and such a connection answered "attempt to write a readonly
            // database" long after the files were writable again. The opening time read back from the age can be
            // up to a millisecond late, so a connection opened in the millisecond of a failure counts as before it;
            // and for a minute after a failure a SQLite connection shows it can write (a write rolled back at once)
            // before it is handed out, which no clock race can fool.
            .before_acquire(move |conn, meta| {
                Box::pin(async move {
                    if sqlx::Connection::is_in_transaction(conn) {
                        return Ok(false);
                    }
                    let failed_ms = STORAGE_FAILURE_AT_MS.load(std::sync::atomic::Ordering::Acquire);
                    if failed_ms == 0 {
                        return Ok(true);
                    }
                    let opened_ms = now_ms() - meta.age.as_millis() as i64;
                    if opened_ms <= failed_ms + 1 {
                        return Ok(false);
                    }
                    if backend == Backend::Sqlite
                        && now_ms() - failed_ms < 60_000
                        && let Err(e) = conn
                            .execute("BEGIN; CREATE TABLE main.dsrl_write_check (x INTEGER); ROLLBACK;")
                            .await
                    {
                        note_failure(&e);
                        let _ = conn.execute("ROLLBACK").await;
                        return Ok(false);
                    }
                    Ok(true)
                })
            })
            .connect(url)
            .await?;
        migrator(backend).run(&pool).await?;
        Ok(Db {
            pool,
            backend,
            url: url.into(),
        })
    }

    pub fn pool(&self) -> &AnyPool {
        &self.pool
    }

    pub fn backend(&self) -> Backend {
        self.backend
    }

    pub async fn ping(&self) -> Result<(), sqlx::Error> {
        sqlx::query("SELECT 1").execute(&self.pool).await.map(|_| ())
    }

    /// Writes and commits one row: what `/healthz` asks of the database. A read (`ping`) succeeds on a database
    /// whose files cannot be written, where every submission and upload fails.
    pub async fn probe_write(&self) -> Result<(), sqlx::Error> {
        let result = async {
            let mut tx = self.begin().await?;
            sqlx::query(
                "INSERT INTO health_probe (id, probed_ms) VALUES (1, $1)
                 ON CONFLICT (id) DO UPDATE SET probed_ms = excluded.probed_ms",
            )
            .bind(now_ms())
            .execute(&mut *tx)
            .await?;
            tx.commit().await
        }
        .await;
        if let Err(e) = &result {
            note_failure(e);
        }
        result
    }

    /// A write transaction. On SQLite it takes the write lock at its start (`BEGIN IMMEDIATE`): a deferred one that
    /// reads first (quota counts, a lookup) and then writes must upgrade its read lock, and under WAL SQLite refuses
    /// that upgrade at once with SQLITE_BUSY when another writer went first — `busy_timeout` does not apply to it —
    /// so concurrent submissions got "database is locked". Taken at the start, the lock is waited for (up to
    /// `busy_timeout`) like any other.
    pub async fn begin(&self) -> Result<Transaction<'static, Any>, sqlx::Error> {
        match self.backend {
            Backend::Sqlite => self.pool.begin_with("BEGIN IMMEDIATE").await,
            Backend::Postgres => self.pool.begin().await,
        }
    }

    /// Runs `work` holding the lock named `key` across every process that shares this database, so that a
    /// derived object (an ingested version, a filtered version, an HDF5 export) is computed by one replica while
    /// the others wait and then find it.
    ///
    /// PostgreSQL: a session advisory lock on a connection of its own, opened for the work and closed after it.
    /// Not a pooled one: lock holders would otherwise take the pool's connections from the work inside them. A
    /// request dropped mid-work, or a replica that dies, releases the lock with the session. Derivations are
    /// expensive; one connection each costs nothing beside them.
    ///
    /// SQLite: one process serves the file, so the caller's in-process gate is the whole story.
    pub async fn exclusively<T, E: From<sqlx::Error>>(
        &self,
        key: &str,
        work: impl std::future::Future<Output = Result<T, E>>,
    ) -> Result<T, E> {
        if self.backend == Backend::Sqlite {
            return work.await;
        }
        let id = lock_id(key);
        let mut conn = <sqlx::AnyConnection as sqlx::Connection>::connect(&self.url).await?;
        // Wrapped in a SELECT of a number: the lock function returns `void`, which the Any driver cannot decode.
        sqlx::query("SELECT 1 FROM (SELECT pg_advisory_lock($1)) AS locked")
            .bind(id)
            .execute(&mut conn)
            .await?;
        let result = work.await;
        // Closing ends the session, and the lock with it.
        let _ = sqlx::Connection::close(conn).await;
        result
    }

    pub async fn version_count(&self) -> Result<i64, sqlx::Error> {
        sqlx::query("SELECT COUNT(*) FROM dataset_versions")
            .fetch_one(&self.pool)
            .await?
            .try_get(0)
    }

    /// Versions of `task` (or of every task), newest first, with their tags; filtered versions are not listed.
    pub async fn versions(&self, task: Option<&TaskId>) -> Result<Vec<VersionRecord>, sqlx::Error> {
        self.select_versions(task, None).await
    }

    /// The version a filter made from `parent`, if it was made before, and when it was last asked for
    /// (milliseconds since the epoch).
    pub async fn derivation(
        &self,
        task: &TaskId,
        parent: &str,
        filter: &str,
    ) -> Result<Option<(VersionId, i64)>, sqlx::Error> {
        let row = sqlx::query(
            "SELECT version, last_used_ms FROM dataset_derivations WHERE task = $1 AND parent = $2 AND filter = $3",
        )
        .bind(task.as_str())
        .bind(parent)
        .bind(filter)
        .fetch_optional(&self.pool)
        .await?;
        let last_used_ms = row.as_ref().map(|r| r.try_get::<i64, _>(1)).transpose()?;
        Ok(version_id(row)?.zip(last_used_ms))
    }

    /// Records that a filter's result was asked for now, unless that was recorded less than
    /// `DERIVATION_TOUCH_MS` ago (the caller skips the call then too), so a busy filtered version does not turn
    /// every request into a write.
    pub async fn touch_derivation(&self, task: &TaskId, parent: &str, filter: &str) -> Result<(), sqlx::Error> {
        sqlx::query(
            "UPDATE dataset_derivations SET last_used_ms = $4
             WHERE task = $1 AND parent = $2 AND filter = $3 AND last_used_ms < $4 - $5",
        )
        .bind(task.as_str())
        .bind(parent)
        .bind(filter)
        .bind(now_ms())
        .bind(DERIVATION_TOUCH_MS)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Filtered versions that garbage collection may remove, least recently used first: not tagged, and not the
    /// parent of another derivation (those go in a later pass, after their children).
    pub async fn collectable_derivations(&self) -> Result<Vec<DerivationRecord>, sqlx::Error> {
        let rows = sqlx::query(
            "SELECT d.task, d.parent, d.filter, d.version, v.byte_size + COALESCE(e.byte_size, 0), d.last_used_ms
             FROM dataset_derivations d JOIN dataset_versions v ON v.task = d.task AND v.version = d.version
                  LEFT JOIN dataset_hdf5_exports e ON e.task = d.task AND e.version = d.version
             WHERE v.derived
               AND NOT EXISTS (SELECT 1 FROM dataset_tags t WHERE t.task = d.task AND t.version = d.version)
               AND NOT EXISTS (SELECT 1 FROM dataset_derivations c WHERE c.task = d.task AND c.parent = d.version)
             ORDER BY d.last_used_ms, d.task, d.version",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(DerivationRecord {
                    task: r.try_get(0)?,
                    parent: r.try_get(1)?,
                    filter: r.try_get(2)?,
                    version: r.try_get(3)?,
                    byte_size: r.try_get::<i64, _>(4)? as u64,
                    last_used_ms: r.try_get(5)?,
                })
            })
            .collect()
    }

    /// Bytes of every filtered version, with its HDF5 export where one was made: both are derived, and removing the
    /// version removes its export (cast: PostgreSQL sums BIGINT to NUMERIC, which the Any driver cannot read).
    pub async fn derived_bytes(&self) -> Result<u64, sqlx::Error> {
        let row = sqlx::query(
            "SELECT CAST(COALESCE(SUM(v.byte_size + COALESCE(e.byte_size, 0)), 0) AS BIGINT)
             FROM dataset_versions v LEFT JOIN dataset_hdf5_exports e ON e.task = v.task AND e.version = v.version
             WHERE v.derived",
        )
        .fetch_one(&self.pool)
        .await?;
        Ok(row.try_get::<i64, _>(0)? as u64)
    }

    /// The HDF5 export of a version, if it was made before: (sha256 of its bytes, size).
    pub async fn hdf5_export(&self, task: &str, version: &str) -> Result<Option<(String, u64)>, sqlx::Error> {
        let row = sqlx::query("SELECT digest, byte_size FROM dataset_hdf5_exports WHERE task = $1 AND version = $2")
            .bind(task)
            .bind(version)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|r| Ok((r.try_get(0)?, r.try_get::<i64, _>(1)? as u64)))
            .transpose()
    }

    /// Records a version's HDF5 export (a second record of the same version keeps the first).
    pub async fn insert_hdf5_export(
        &self,
        task: &str,
        version: &str,
        digest: &str,
        byte_size: u64,
        now: &str,
    ) -> Result<(), sqlx::Error> {
        sqlx::query(
            "INSERT INTO dataset_hdf5_exports (task, version, digest, byte_size, created_at) VALUES ($1, $2, $3, $4, $5)
             ON CONFLICT (task, version) DO NOTHING",
        )
        .bind(task)
        .bind(version)
        .bind(digest)
        .bind(byte_size as i64)
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    pub async fn version(&self, task: &TaskId, version: &VersionId) -> Result<Option<VersionRecord>, sqlx::Error> {
        Ok(self.select_versions(Some(task), Some(version)).await?.pop())
    }

    async fn select_versions(
        &self,
        task: Option<&TaskId>,
        version: Option<&VersionId>,
    ) -> Result<Vec<VersionRecord>, sqlx::Error> {
        let sql = format!(
            "SELECT v.task, v.version, v.byte_size, v.episodes, v.transitions, v.observation_space, v.created_at,
                    (SELECT {tags} FROM (SELECT tag FROM dataset_tags t
                        WHERE t.task = v.task AND t.version = v.version ORDER BY tag) t) AS tags
             FROM dataset_versions v
             WHERE ($1 IS NULL OR v.task = $1) AND ($2 IS NULL OR v.version = $2)
               AND ($2 IS NOT NULL OR NOT v.derived)
             ORDER BY v.{order} DESC",
            tags = self.backend.comma_list("t.tag"),
            order = self.backend.creation_order(),
        );
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(task.map(|t| t.as_str()))
            .bind(version.map(|v| v.as_str()))
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(record).collect()
    }

    pub async fn tagged(&self, task: &TaskId, tag: &TagName) -> Result<Option<VersionId>, sqlx::Error> {
        let row = sqlx::query("SELECT version FROM dataset_tags WHERE task = $1 AND tag = $2")
            .bind(task.as_str())
            .bind(tag.as_str())
            .fetch_optional(&self.pool)
            .await?;
        version_id(row)
    }

    pub async fn manifest(&self, task: &TaskId, version: &VersionId) -> Result<Option<String>, sqlx::Error> {
        let row = sqlx::query("SELECT manifest FROM dataset_versions WHERE task = $1 AND version = $2")
            .bind(task.as_str())
            .bind(version.as_str())
            .fetch_optional(&self.pool)
            .await?;
        row.map(|r| r.try_get(0)).transpose()
    }
}

/// The SQL files of `migrations/sqlite/` and `migrations/postgres/`, compiled in (listed by hand; a test checks the
/// lists against the folders).
const SQLITE_MIGRATIONS: &[(i64, &str, &str)] = &[
    (
        20261122000001,
        "datasets",
        include_str!("../../migrations/sqlite/20261122000001_datasets.sql"),
    ),
    (
        20261122000002,
        "derivations",
        include_str!("../../migrations/sqlite/20261122000002_derivations.sql"),
    ),
    (
        20261122000003,
        "leaderboard",
        include_str!("../../migrations/sqlite/20261122000003_leaderboard.sql"),
    ),
    (
        20261123000001,
        "hdf5_exports",
        include_str!("../../migrations/sqlite/20261123000001_hdf5_exports.sql"),
    ),
    (
        20261124000001,
        "derivation_access",
        include_str!("../../migrations/sqlite/20261124000001_derivation_access.sql"),
    ),
    (
        20261126000001,
        "protocol",
        include_str!("../../migrations/sqlite/20261126000001_protocol.sql"),
    ),
    (
        20261126000002,
        "queue_operations",
        include_str!("../../migrations/sqlite/20261126000002_queue_operations.sql"),
    ),
    (
        20261128000001,
        "liveness",
        include_str!("../../migrations/sqlite/20261128000001_liveness.sql"),
    ),
    (
        20261128000002,
        "uploads",
        include_str!("../../migrations/sqlite/20261128000002_uploads.sql"),
    ),
    (
        20261128000003,
        "scored_by",
        include_str!("../../migrations/sqlite/20261128000003_scored_by.sql"),
    ),
];

const POSTGRES_MIGRATIONS: &[(i64, &str, &str)] = &[
    (
        20261124000001,
        "initial",
        include_str!("../../migrations/postgres/20261124000001_initial.sql"),
    ),
    (
        20261124000002,
        "derivation_access",
        include_str!("../../migrations/postgres/20261124000002_derivation_access.sql"),
    ),
    (
        20261126000001,
        "protocol",
        include_str!("../../migrations/postgres/20261126000001_protocol.sql"),
    ),
    (
        20261126000002,
        "queue_operations",
        include_str!("../../migrations/postgres/20261126000002_queue_operations.sql"),
    ),
    (
        20261128000001,
        "liveness",
        include_str!("../../migrations/postgres/20261128000001_liveness.sql"),
    ),
    (
        20261128000002,
        "uploads",
        include_str!("../../migrations/postgres/20261128000002_uploads.sql"),
    ),
    (
        20261128000003,
        "scored_by",
        include_str!("../../migrations/postgres/20261128000003_scored_by.sql"),
    ),
];

fn migrator(backend: Backend) -> Migrator {
    Migrator::with_migrations(
        backend
            .migrations()
            .iter()
            .map(|&(version, description, sql)| {
                Migration::new(
                    version,
                    description.into(),
                    MigrationType::Simple,
                    sql.into_sql_str(),
                    false,
                )
            })
            .collect(),
    )
}

/// A new version row; `false` when the version already existed (an identical ingest).
pub async fn insert_version(
    tx: &mut Transaction<'static, Any>,
    manifest: &dsrl_suite::Manifest,
    manifest_json: &str,
) -> Result<bool, sqlx::Error> {
    let done = sqlx::query(
        "INSERT INTO dataset_versions
            (task, version, byte_size, episodes, transitions, observation_space, created_at, manifest, derived)
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)
         ON CONFLICT (task, version) DO NOTHING",
    )
    .bind(manifest.task.as_str())
    .bind(manifest.version.as_str())
    .bind(manifest.byte_size as i64)
    .bind(manifest.episodes as i64)
    .bind(manifest.transitions as i64)
    .bind(manifest.observation_space.kind.as_str())
    .bind(&manifest.created_at)
    .bind(manifest_json)
    .bind(matches!(manifest.provenance, dsrl_suite::Provenance::Filter { .. }))
    .execute(&mut **tx)
    .await?;
    Ok(done.rows_affected() == 1)
}

/// Records that `filter` made `version` from `parent`.
pub async fn insert_derivation(
    tx: &mut Transaction<'static, Any>,
    task: &TaskId,
    parent: &str,
    filter: &str,
    version: &VersionId,
    now: &str,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO dataset_derivations (task, parent, filter, version, created_at, last_used_ms)
         VALUES ($1, $2, $3, $4, $5, $6)
         ON CONFLICT (task, parent, filter) DO NOTHING",
    )
    .bind(task.as_str())
    .bind(parent)
    .bind(filter)
    .bind(version.as_str())
    .bind(now)
    .bind(now_ms())
    .execute(&mut **tx)
    .await?;
    Ok(())
}

/// Points `tag` at `version`; with `only_if_absent`, leaves an existing tag alone. Returns whether it moved.
pub async fn set_tag(
    tx: &mut Transaction<'static, Any>,
    task: &TaskId,
    tag: &TagName,
    version: &VersionId,
    now: &str,
    only_if_absent: bool,
) -> Result<bool, sqlx::Error> {
    let sql = if only_if_absent {
        "INSERT INTO dataset_tags (task, tag, version, updated_at) VALUES ($1, $2, $3, $4)
         ON CONFLICT (task, tag) DO NOTHING"
    } else {
        "INSERT INTO dataset_tags (task, tag, version, updated_at) VALUES ($1, $2, $3, $4)
         ON CONFLICT (task, tag) DO UPDATE SET version = excluded.version, updated_at = excluded.updated_at
         WHERE dataset_tags.version != excluded.version"
    };
    let done = sqlx::query(sql)
        .bind(task.as_str())
        .bind(tag.as_str())
        .bind(version.as_str())
        .bind(now)
        .execute(&mut **tx)
        .await?;
    Ok(done.rows_affected() == 1)
}

/// A filtered version as garbage collection sees it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct DerivationRecord {
    pub task: String,
    pub parent: String,
    pub filter: String,
    pub version: String,
    /// The filtered version's bytes, with its HDF5 export's where one was made.
    pub byte_size: u64,
    pub last_used_ms: i64,
}

/// Removes a filtered version's rows (derivation, HDF5 export record, version) in one transaction, if it is still
/// collectable (untagged, nobody's parent). Returns the HDF5 export's digest when one was recorded, and whether
/// anything was removed.
pub async fn remove_derived(
    tx: &mut Transaction<'static, Any>,
    record: &DerivationRecord,
) -> Result<Option<Option<String>>, sqlx::Error> {
    let still = sqlx::query(
        "SELECT 1 FROM dataset_versions v
         WHERE v.task = $1 AND v.version = $2 AND v.derived
           AND NOT EXISTS (SELECT 1 FROM dataset_tags t WHERE t.task = v.task AND t.version = v.version)
           AND NOT EXISTS (SELECT 1 FROM dataset_derivations c WHERE c.task = v.task AND c.parent = v.version)",
    )
    .bind(&record.task)
    .bind(&record.version)
    .fetch_optional(&mut **tx)
    .await?;
    if still.is_none() {
        return Ok(None);
    }
    let export = sqlx::query("DELETE FROM dataset_hdf5_exports WHERE task = $1 AND version = $2 RETURNING digest")
        .bind(&record.task)
        .bind(&record.version)
        .fetch_optional(&mut **tx)
        .await?
        .map(|r| r.try_get::<String, _>(0))
        .transpose()?;
    sqlx::query("DELETE FROM dataset_derivations WHERE task = $1 AND version = $2")
        .bind(&record.task)
        .bind(&record.version)
        .execute(&mut **tx)
        .await?;
    sqlx::query("DELETE FROM dataset_versions WHERE task = $1 AND version = $2")
        .bind(&record.task)
        .bind(&record.version)
        .execute(&mut **tx)
        .await?;
    Ok(Some(export))
}

/// Whether any recorded HDF5 export still points at `digest` (exports are content-addressed, so two versions
/// could share one).
pub async fn hdf5_digest_in_use(tx: &mut Transaction<'static, Any>, digest: &str) -> Result<bool, sqlx::Error> {
    Ok(sqlx::query("SELECT 1 FROM dataset_hdf5_exports WHERE digest = $1")
        .bind(digest)
        .fetch_optional(&mut **tx)
        .await?
        .is_some())
}

/// How stale a derivation's last use may be before a request records it again (see `touch_derivation`).
pub const DERIVATION_TOUCH_MS: i64 = 60_000;

/// Now in UTC, to the second, as RFC 3339 (the timestamps the tables store).
pub fn now_rfc3339() -> String {
    let now = time::OffsetDateTime::now_utc()
        .replace_nanosecond(0)
        .expect("0 is a valid nanosecond");
    now.format(&time::format_description::well_known::Rfc3339)
        .expect("formattable")
}

/// A time in milliseconds since the Unix epoch as RFC 3339, to the second (heartbeats, estimates).
pub fn rfc3339_at_ms(ms: i64) -> String {
    time::OffsetDateTime::from_unix_timestamp(ms.div_euclid(1000))
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH)
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_default()
}

/// Now in milliseconds since the Unix epoch (last-use times, leases).
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// A lock name as PostgreSQL's 64-bit advisory lock key: the first 8 bytes of its sha256.
fn lock_id(key: &str) -> i64 {
    let digest = <sha2::Sha256 as sha2::Digest>::digest(key.as_bytes());
    i64::from_be_bytes(digest[..8].try_into().expect("8 bytes"))
}

/// The version id in the first column of an optional row.
fn version_id(row: Option<AnyRow>) -> Result<Option<VersionId>, sqlx::Error> {
    row.map(|r| {
        let v: String = r.try_get(0)?;
        v.parse()
            .map_err(|e: dsrl_suite::IdError| sqlx::Error::Decode(e.into()))
    })
    .transpose()
}

fn record(row: &AnyRow) -> Result<VersionRecord, sqlx::Error> {
    let tags: Option<String> = row.try_get("tags")?;
    Ok(VersionRecord {
        task: row.try_get("task")?,
        version: row.try_get("version")?,
        tags: tags
            .map(|t| t.split(',').map(str::to_owned).collect())
            .unwrap_or_default(),
        byte_size: row.try_get::<i64, _>("byte_size")? as u64,
        episodes: row.try_get::<i64, _>("episodes")? as u64,
        transitions: row.try_get::<i64, _>("transitions")? as u64,
        observation_space: row.try_get("observation_space")?,
        created_at: row.try_get("created_at")?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_migration_file_is_compiled_in() {
        for backend in [Backend::Sqlite, Backend::Postgres] {
            let folder = format!("{backend:?}").to_lowercase();
            let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../migrations")
                .join(&folder);
            let mut files: Vec<String> = std::fs::read_dir(dir)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .filter(|n| n.ends_with(".sql"))
                .collect();
            files.sort();
            let listed: Vec<String> = backend
                .migrations()
                .iter()
                .map(|(v, d, _)| format!("{v}_{d}.sql"))
                .collect();
            assert_eq!(files, listed, "{folder}");
        }
    }

    #[tokio::test]
    async fn migrations_apply_and_reapply() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("db.sqlite3");
        let db = Db::open(&path).await.unwrap();
        assert_eq!(db.version_count().await.unwrap(), 0);
        drop(db);
        // Opening again finds the migrations applied and the checksums unchanged.
        let db = Db::open(&path).await.unwrap();
        db.ping().await.unwrap();
    }
}
