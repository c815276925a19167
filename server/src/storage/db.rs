//! SQLite through sqlx: the connection pool, the migrations in `migrations/`, and the queries on dataset
//! versions and tags. Runtime `query()` calls, so building needs no database.

use std::path::Path;
use std::str::FromStr;

use dsrl_suite::{TagName, TaskId, VersionId};
use sqlx::migrate::{Migration, MigrationType, Migrator};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Row, SqlSafeStr, Sqlite, Transaction};

/// The server's name for a hosted version row.
pub use dsrl_suite::HostedVersion as VersionRecord;

#[derive(Clone)]
pub struct Db {
    pool: SqlitePool,
}

impl Db {
    pub async fn open(path: &Path) -> Result<Db, sqlx::Error> {
        let options = SqliteConnectOptions::from_str(&format!("sqlite://{}", path.display()))?
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Full)
            .foreign_keys(true)
            .busy_timeout(std::time::Duration::from_secs(10));
        let pool = SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(options)
            .await?;
        migrator().run(&pool).await?;
        Ok(Db { pool })
    }

    pub fn pool(&self) -> &SqlitePool {
        &self.pool
    }

    pub async fn ping(&self) -> Result<(), sqlx::Error> {
        sqlx::query("SELECT 1").execute(&self.pool).await.map(|_| ())
    }

    pub async fn begin(&self) -> Result<Transaction<'static, Sqlite>, sqlx::Error> {
        self.pool.begin().await
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

    /// The version a filter made from `parent`, if it was made before.
    pub async fn derivation(
        &self,
        task: &TaskId,
        parent: &str,
        filter: &str,
    ) -> Result<Option<VersionId>, sqlx::Error> {
        let row =
            sqlx::query("SELECT version FROM dataset_derivations WHERE task = ?1 AND parent = ?2 AND filter = ?3")
                .bind(task.as_str())
                .bind(parent)
                .bind(filter)
                .fetch_optional(&self.pool)
                .await?;
        version_id(row)
    }

    /// The HDF5 export of a version, if it was made before: (sha256 of its bytes, size).
    pub async fn hdf5_export(&self, task: &str, version: &str) -> Result<Option<(String, u64)>, sqlx::Error> {
        let row = sqlx::query("SELECT digest, byte_size FROM dataset_hdf5_exports WHERE task = ?1 AND version = ?2")
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
            "INSERT INTO dataset_hdf5_exports (task, version, digest, byte_size, created_at) VALUES (?1, ?2, ?3, ?4, ?5)
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
        let rows = sqlx::query(
            "SELECT v.task, v.version, v.byte_size, v.episodes, v.transitions, v.observation_space, v.created_at,
                    (SELECT group_concat(t.tag, ',') FROM (SELECT tag FROM dataset_tags t
                        WHERE t.task = v.task AND t.version = v.version ORDER BY tag) t) AS tags
             FROM dataset_versions v
             WHERE (?1 IS NULL OR v.task = ?1) AND (?2 IS NULL OR v.version = ?2)
               AND (?2 IS NOT NULL OR v.derived = 0)
             ORDER BY v.rowid DESC",
        )
        .bind(task.map(|t| t.as_str()))
        .bind(version.map(|v| v.as_str()))
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(record).collect()
    }

    pub async fn tagged(&self, task: &TaskId, tag: &TagName) -> Result<Option<VersionId>, sqlx::Error> {
        let row = sqlx::query("SELECT version FROM dataset_tags WHERE task = ?1 AND tag = ?2")
            .bind(task.as_str())
            .bind(tag.as_str())
            .fetch_optional(&self.pool)
            .await?;
        version_id(row)
    }

    pub async fn manifest(&self, task: &TaskId, version: &VersionId) -> Result<Option<String>, sqlx::Error> {
        let row = sqlx::query("SELECT manifest FROM dataset_versions WHERE task = ?1 AND version = ?2")
            .bind(task.as_str())
            .bind(version.as_str())
            .fetch_optional(&self.pool)
            .await?;
        row.map(|r| r.try_get(0)).transpose()
    }
}

/// The SQL files of `migrations/`, compiled in (listed by hand; a test checks the list against the folder).
const MIGRATIONS: &[(i64, &str, &str)] = &[
    (
        20261122000001,
        "datasets",
        include_str!("../../../migrations/20261122000001_datasets.sql"),
    ),
    (
        20261122000002,
        "derivations",
        include_str!("../../../migrations/20261122000002_derivations.sql"),
    ),
    (
        20261122000003,
        "leaderboard",
        include_str!("../../../migrations/20261122000003_leaderboard.sql"),
    ),
    (
        20261123000001,
        "hdf5_exports",
        include_str!("../../../migrations/20261123000001_hdf5_exports.sql"),
    ),
];

fn migrator() -> Migrator {
    Migrator::with_migrations(
        MIGRATIONS
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
    tx: &mut Transaction<'static, Sqlite>,
    manifest: &dsrl_suite::Manifest,
    manifest_json: &str,
) -> Result<bool, sqlx::Error> {
    let done = sqlx::query(
        "INSERT INTO dataset_versions
            (task, version, byte_size, episodes, transitions, observation_space, created_at, manifest, derived)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)
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
    tx: &mut Transaction<'static, Sqlite>,
    task: &TaskId,
    parent: &str,
    filter: &str,
    version: &VersionId,
    now: &str,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO dataset_derivations (task, parent, filter, version, created_at) VALUES (?1, ?2, ?3, ?4, ?5)
         ON CONFLICT (task, parent, filter) DO NOTHING",
    )
    .bind(task.as_str())
    .bind(parent)
    .bind(filter)
    .bind(version.as_str())
    .bind(now)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

/// Points `tag` at `version`; with `only_if_absent`, leaves an existing tag alone. Returns whether it moved.
pub async fn set_tag(
    tx: &mut Transaction<'static, Sqlite>,
    task: &TaskId,
    tag: &TagName,
    version: &VersionId,
    now: &str,
    only_if_absent: bool,
) -> Result<bool, sqlx::Error> {
    let sql = if only_if_absent {
        "INSERT INTO dataset_tags (task, tag, version, updated_at) VALUES (?1, ?2, ?3, ?4)
         ON CONFLICT (task, tag) DO NOTHING"
    } else {
        "INSERT INTO dataset_tags (task, tag, version, updated_at) VALUES (?1, ?2, ?3, ?4)
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

/// The version id in the first column of an optional row.
fn version_id(row: Option<sqlx::sqlite::SqliteRow>) -> Result<Option<VersionId>, sqlx::Error> {
    row.map(|r| {
        let v: String = r.try_get(0)?;
        v.parse()
            .map_err(|e: dsrl_suite::IdError| sqlx::Error::Decode(e.into()))
    })
    .transpose()
}

fn record(row: &sqlx::sqlite::SqliteRow) -> Result<VersionRecord, sqlx::Error> {
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
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../migrations");
        let mut files: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".sql"))
            .collect();
        files.sort();
        let listed: Vec<String> = MIGRATIONS.iter().map(|(v, d, _)| format!("{v}_{d}.sql")).collect();
        assert_eq!(files, listed);
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
