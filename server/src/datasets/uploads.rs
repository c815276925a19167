//! Uploads converted in the background. Converting a paper-size file (gigabytes) takes minutes; a client that waits
//! for the answer on one request times out while the server is still working, and its retry converted everything
//! again. An upload sent with `?background=true` is answered (202) as soon as its bytes are received and verified:
//! the conversion goes on in a task of this process, which heartbeats the upload's row (`uploads`) until it records
//! the answer or the error. Any replica answers `GET /v1/uploads/{upload}` from that row; a conversion whose heartbeat
//! stopped (the server was killed) is reported `interrupted`, and uploading the file again starts afresh. An upload
//! of bytes already being converted, or already converted, for the task follows that upload instead of starting
//! another.

use serde::Serialize;
use sqlx::Row;

use crate::datasets::db::{Db, now_ms, rfc3339_at_ms};
use crate::error::ApiError;

/// How often a converting server says it is still at work, and how old its last word may be before the upload is
/// reported interrupted.
pub const HEARTBEAT_MS: i64 = 1_000;
pub const STALE_MS: i64 = 10_000;

/// An upload as `GET /v1/uploads/{upload}` shows it.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct UploadView {
    pub id: String,
    pub task: String,
    /// sha256 of the uploaded bytes (before conversion).
    pub upload_sha256: String,
    pub file_name: String,
    pub byte_size: u64,
    /// `converting`, `done`, `failed`, or `interrupted` (its server stopped while converting: upload it again).
    pub state: String,
    /// The ingest's answer, once done (what a foreground upload answers).
    #[schema(value_type = Option<Object>)]
    pub result: Option<serde_json::Value>,
    /// Why it failed: the error document's code and message.
    #[schema(value_type = Option<Object>)]
    pub error: Option<serde_json::Value>,
    pub created_at: String,
    /// The converting server's last heartbeat, or when the upload ended.
    pub updated_at: String,
    /// Where to follow it.
    pub url: String,
}

fn view(row: &sqlx::any::AnyRow) -> Result<UploadView, ApiError> {
    let id: String = row.try_get("id")?;
    let state: String = row.try_get("state")?;
    let updated_ms: i64 = row.try_get("updated_ms")?;
    let state = if state == "converting" && now_ms() - updated_ms > STALE_MS {
        "interrupted".to_owned()
    } else {
        state
    };
    let result: Option<String> = row.try_get("result")?;
    let code: Option<String> = row.try_get("error_code")?;
    let message: Option<String> = row.try_get("error_message")?;
    Ok(UploadView {
        url: format!("/v1/uploads/{id}"),
        id,
        task: row.try_get("task")?,
        upload_sha256: row.try_get("upload_sha256")?,
        file_name: row.try_get("file_name")?,
        byte_size: row.try_get::<i64, _>("byte_size")? as u64,
        state,
        result: result
            .map(|r| serde_json::from_str(&r))
            .transpose()
            .map_err(ApiError::internal)?,
        error: code.map(|code| serde_json::json!({ "code": code, "message": message.unwrap_or_default() })),
        created_at: rfc3339_at_ms(row.try_get("created_ms")?),
        updated_at: rfc3339_at_ms(updated_ms),
    })
}

const COLUMNS: &str =
    "id, task, upload_sha256, file_name, byte_size, state, result, error_code, error_message, created_ms, updated_ms";

pub async fn get(db: &Db, id: &str) -> Result<UploadView, ApiError> {
    let row = sqlx::query(sqlx::AssertSqlSafe(format!(
        "SELECT {COLUMNS} FROM uploads WHERE id = $1"
    )))
    .bind(id)
    .fetch_optional(db.pool())
    .await?
    .ok_or_else(|| ApiError::NotFound(format!("no upload {id:?}")))?;
    view(&row)
}

/// The uploads of `task` with these bytes, newest first.
pub async fn find(db: &Db, task: &str, upload_sha256: &str) -> Result<Vec<UploadView>, ApiError> {
    let rows = sqlx::query(sqlx::AssertSqlSafe(format!(
        "SELECT {COLUMNS} FROM uploads WHERE task = $1 AND upload_sha256 = $2 ORDER BY created_ms DESC, id"
    )))
    .bind(task)
    .bind(upload_sha256)
    .fetch_all(db.pool())
    .await?;
    rows.iter().map(view).collect()
}

/// The upload a new one of the same bytes should follow: one converting (heartbeat fresh) or done.
pub async fn in_progress_or_done(db: &Db, task: &str, upload_sha256: &str) -> Result<Option<UploadView>, ApiError> {
    Ok(find(db, task, upload_sha256)
        .await?
        .into_iter()
        .find(|u| u.state == "converting" || u.state == "done"))
}

/// At start-up with the embedded SQLite database, which one process serves: a conversion recorded as under way was
/// this server's before it stopped, and is over. (Replicas sharing PostgreSQL tell a dead conversion by its
/// heartbeat instead.)
pub async fn recover(db: &Db) -> Result<u64, ApiError> {
    if db.backend() != dsrl_service::db::Backend::Sqlite {
        return Ok(0);
    }
    let done = sqlx::query(
        "UPDATE uploads SET state = 'failed', error_code = 'unavailable',
             error_message = 'the server restarted while converting this upload; upload the file again',
             updated_ms = $1
         WHERE state = 'converting'",
    )
    .bind(now_ms())
    .execute(db.pool())
    .await?;
    Ok(done.rows_affected())
}

/// Records a new upload being converted; returns its id.
pub async fn start(
    db: &Db,
    task: &str,
    upload_sha256: &str,
    file_name: &str,
    byte_size: u64,
) -> Result<String, ApiError> {
    let id = dsrl_service::secrets::random_hex().map_err(ApiError::internal)?[..24].to_owned();
    let now = now_ms();
    let mut tx = db.begin().await?;
    sqlx::query(
        "INSERT INTO uploads (id, task, upload_sha256, file_name, byte_size, state, created_ms, updated_ms)
         VALUES ($1, $2, $3, $4, $5, 'converting', $6, $6)",
    )
    .bind(&id)
    .bind(task)
    .bind(upload_sha256)
    .bind(file_name)
    .bind(byte_size as i64)
    .bind(now)
    .execute(&mut *tx)
    .await?;
    tx.commit().await?;
    Ok(id)
}

/// The converting server's word that it is still at work.
pub async fn heartbeat(db: &Db, id: &str) -> Result<(), ApiError> {
    sqlx::query("UPDATE uploads SET updated_ms = $2 WHERE id = $1 AND state = 'converting'")
        .bind(id)
        .bind(now_ms())
        .execute(db.pool())
        .await?;
    Ok(())
}

/// Records how the conversion ended: the ingest's answer, or the error.
pub async fn finish(db: &Db, id: &str, outcome: Result<serde_json::Value, &ApiError>) -> Result<(), ApiError> {
    let (state, result, code, message) = match outcome {
        Ok(result) => ("done", Some(result.to_string()), None, None),
        Err(e) => ("failed", None, Some(e.code().as_str().to_owned()), Some(e.to_string())),
    };
    let mut tx = db.begin().await?;
    sqlx::query(
        "UPDATE uploads SET state = $2, result = $3, error_code = $4, error_message = $5, updated_ms = $6
         WHERE id = $1",
    )
    .bind(id)
    .bind(state)
    .bind(result)
    .bind(code)
    .bind(message)
    .bind(now_ms())
    .execute(&mut *tx)
    .await?;
    tx.commit().await?;
    Ok(())
}
