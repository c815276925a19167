//! REST handlers for the catalog and dataset versions: list tasks, list versions, read a manifest, ingest an
//! upload (admin), move a tag (admin). Downloads are in `download.rs`.

use axum::Json;
use axum::body::Body;
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use dsrl_suite::{ObservationSpace, Provenance, TagName, Task};
use futures::StreamExt;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;

use crate::AppState;
use crate::datasets::db::VersionRecord;
use crate::datasets::service::{IngestRequest, LatestPolicy};
use crate::datasets::uploads::{self, UploadView};
use crate::error::ApiError;
use crate::metrics::OutcomeLabels;

/// Header carrying the provenance of data built by a recipe (JSON, `{"kind": "recipe", ...}`).
pub const PROVENANCE_HEADER: &str = "dsrl-provenance";

#[derive(Serialize, utoipa::ToSchema)]
pub struct TaskEntry {
    #[serde(flatten)]
    pub task: Task,
    /// Hosted versions, newest first.
    pub versions: Vec<VersionRecord>,
}

#[derive(Serialize, utoipa::ToSchema)]
pub struct TaskList {
    pub tasks: Vec<TaskEntry>,
}

#[derive(Serialize, utoipa::ToSchema)]
pub struct VersionList {
    pub task: String,
    pub versions: Vec<VersionRecord>,
}

#[derive(Serialize, utoipa::ToSchema)]
pub struct IngestResponse {
    /// `false`: identical data was already hosted, nothing was stored.
    pub created: bool,
    pub task: String,
    pub version: VersionRecord,
    /// Tags moved to this version by the request.
    pub moved_tags: Vec<String>,
    pub manifest_url: String,
    pub download_url: String,
}

#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
pub struct IngestParams {
    /// The uploaded file's name, recorded in the provenance.
    pub filename: Option<String>,
    /// Comma-separated tags to point at the version besides `latest`.
    pub tags: Option<String>,
    /// `simulator` (default) or `paper` (MetaDrive files with the paper's 261 features; never tagged latest).
    pub observation_space: Option<String>,
    /// License to record; the server's default otherwise.
    pub license: Option<String>,
    /// `false`: leave `latest` where it is (default `true`: a new version becomes `latest`).
    pub latest: Option<bool>,
    /// `true`: answer 202 as soon as the upload is received and verified, and convert it in the background;
    /// `GET /v1/uploads/{id}` follows it. An upload of bytes already being converted (or converted) for the task
    /// follows that one instead of converting again. For files whose conversion outlasts a client's patience.
    pub background: Option<bool>,
}

/// What a client needs to know before uploading.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ServerInfo {
    pub name: &'static str,
    pub version: &'static str,
    /// Largest accepted upload, in bytes.
    pub max_upload_bytes: u64,
    /// Whether the request carried the admin token (any other token, or none, gets the same answer with `false`).
    pub admin: bool,
}

#[utoipa::path(get, path = "/v1/server", tag = "server",
    responses((status = 200, body = ServerInfo)))]
pub async fn server_info(State(state): State<AppState>, headers: HeaderMap) -> Result<Json<ServerInfo>, ApiError> {
    // The public view for any caller, whatever token it carries (a user's token is no reason to refuse it);
    // `admin` says whether the token is the admin token.
    let admin = headers.contains_key(header::AUTHORIZATION) && state.auth.check(&headers).is_ok();
    Ok(Json(ServerInfo {
        name: "dsrl",
        version: env!("CARGO_PKG_VERSION"),
        max_upload_bytes: state.max_upload_bytes,
        admin,
    }))
}

/// Query of the version endpoints.
#[derive(Debug, Default, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
pub struct VersionQuery {
    /// A DSRL post-process filter, e.g. `noise=0.05` (outliers_percent), `density=0.5,seed=1`, `obs_noise=0.1`,
    /// `discard=tempting`, `epsilon=-20,target_cost=10`. The answer is about the filtered version, computed once
    /// and cached; an invalid filter is a 400 that lists the valid keys and ranges.
    pub filter: Option<String>,
}

impl VersionQuery {
    pub fn from(query: Result<Query<VersionQuery>, QueryRejection>) -> Result<VersionQuery, ApiError> {
        query
            .map(|Query(q)| q)
            .map_err(|e| ApiError::InvalidArgument(e.body_text()))
    }
}

#[derive(Debug, Deserialize, utoipa::ToSchema)]
pub struct TagRequest {
    /// Version id (sha256) the tag should point at.
    pub version: String,
}

#[utoipa::path(get, path = "/v1/tasks", tag = "catalog",
    responses((status = 200, description = "All tasks with constants and hosted versions", body = TaskList)))]
pub async fn list_tasks(State(state): State<AppState>) -> Result<Json<TaskList>, ApiError> {
    let tasks = state
        .datasets
        .catalog_with_versions()
        .await?
        .into_iter()
        .map(|(task, versions)| TaskEntry {
            task: task.clone(),
            versions,
        })
        .collect();
    Ok(Json(TaskList { tasks }))
}

#[utoipa::path(get, path = "/v1/tasks/{task}", tag = "catalog",
    params(("task" = String, Path, description = "Offline task id, e.g. OfflineAntRun-v0")),
    responses((status = 200, body = TaskEntry), (status = 404, description = "Unknown task; nearest ids suggested")))]
pub async fn get_task(State(state): State<AppState>, Path(task): Path<String>) -> Result<Json<TaskEntry>, ApiError> {
    let (task, versions) = state.datasets.versions(&task).await?;
    Ok(Json(TaskEntry {
        task: task.clone(),
        versions,
    }))
}

#[utoipa::path(get, path = "/v1/datasets/{task}/versions", tag = "datasets",
    params(("task" = String, Path)),
    responses((status = 200, body = VersionList), (status = 404, description = "Unknown task; nearest ids suggested")))]
pub async fn list_versions(
    State(state): State<AppState>,
    Path(task): Path<String>,
) -> Result<Json<VersionList>, ApiError> {
    let (task, versions) = state.datasets.versions(&task).await?;
    Ok(Json(VersionList {
        task: task.id.to_string(),
        versions,
    }))
}

#[utoipa::path(get, path = "/v1/datasets/{task}/versions/{version}", tag = "datasets",
    params(("task" = String, Path), ("version" = String, Path, description = "Version id (sha256) or tag such as latest"), VersionQuery),
    responses((status = 200, description = "The version's manifest (of the filtered version with ?filter=)", body = dsrl_suite::Manifest),
        (status = 400, description = "An invalid version reference or filter, or a filter this dataset cannot satisfy"),
        (status = 404, description = "Unknown task or version"),
        (status = 429, description = "The anonymous derivation budget of the hour is spent: send a token, or retry after Retry-After"),
        (status = 503, description = "Too much derivation work waiting: retry after Retry-After")))]
pub async fn get_manifest(
    State(state): State<AppState>,
    Path((task, reference)): Path<(String, String)>,
    query: Result<Query<VersionQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let query = VersionQuery::from(query)?;
    let requester = crate::http::auth::requester(&state, &headers).await;
    let (_, record) = state
        .datasets
        .resolve_filtered(&task, &reference, query.filter.as_deref(), requester)
        .await?;
    let json = state.datasets.manifest_json(&record).await?;
    let etag = HeaderValue::from_str(&format!("\"{}\"", record.version)).map_err(ApiError::internal)?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("application/json")),
            (header::ETAG, etag),
        ],
        json,
    )
        .into_response())
}

#[utoipa::path(get, path = "/v1/datasets/{task}/versions/{version}/croissant.json", tag = "datasets",
    params(("task" = String, Path), ("version" = String, Path, description = "Version id (sha256) or tag")),
    responses((status = 200, description = "The version described in Croissant 1.0 (JSON-LD): its Parquet file's \
            URL and sha256, the columns as typed fields, the license, how it was built", content_type = "application/ld+json"),
        (status = 400, description = "An invalid version reference"), (status = 404, description = "Unknown task or version")))]
pub async fn get_croissant(
    State(state): State<AppState>,
    Path((task, reference)): Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let (task, record) = state.datasets.resolve(&task, &reference).await?;
    let manifest = state.datasets.manifest(&record).await?;
    // Absolute URLs as the client reached this server (behind a proxy, its Host header).
    let host = headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .filter(|h| h.bytes().all(|b| b.is_ascii_graphic()))
        .unwrap_or("localhost");
    let document = dsrl_suite::croissant::describe(&manifest, task, &format!("http://{host}"));
    let body = serde_json::to_string_pretty(&document).map_err(ApiError::internal)?;
    Ok((
        [(header::CONTENT_TYPE, HeaderValue::from_static("application/ld+json"))],
        body,
    )
        .into_response())
}

#[utoipa::path(get, path = "/v1/datasets/{task}/versions/{version}/plot.svg", tag = "datasets",
    params(("task" = String, Path), ("version" = String, Path), VersionQuery),
    responses((status = 200, description = "Cost-reward return scatter with the task's cost thresholds; with ?filter=, \
        removed trajectories in gray and relabelled outliers in red", content_type = "image/svg+xml"),
        (status = 400, description = "An invalid version reference or filter"), (status = 404, description = "Unknown task or version"),
        (status = 429, description = "The anonymous derivation budget of the hour is spent: send a token, or retry after Retry-After"),
        (status = 503, description = "Too much derivation work waiting: retry after Retry-After")))]
pub async fn get_plot(
    State(state): State<AppState>,
    Path((task, reference)): Path<(String, String)>,
    query: Result<Query<VersionQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    let query = VersionQuery::from(query)?;
    let svg = state
        .datasets
        .plot_svg(&task, &reference, query.filter.as_deref())
        .await?;
    Ok(([(header::CONTENT_TYPE, HeaderValue::from_static("image/svg+xml"))], svg).into_response())
}

#[utoipa::path(post, path = "/v1/datasets/{task}/versions", tag = "datasets",
    params(("task" = String, Path), IngestParams),
    request_body(content = Vec<u8>, description = "A Parquet file or a DSRL HDF5 file", content_type = "application/octet-stream"),
    security(("admin_token" = [])),
    responses(
        (status = 201, description = "A new version was stored", body = IngestResponse),
        (status = 200, description = "Identical data was already hosted", body = IngestResponse),
        (status = 202, description = "With background=true: received; converting in the background (Location: the \
            upload to follow)", body = UploadView),
        (status = 400, description = "The file is not a valid dataset for the task; the message names the first problem (row, column)"),
        (status = 401, description = "No admin token"), (status = 403, description = "Not the admin token"),
        (status = 404, description = "Unknown task"), (status = 413, description = "Over the upload limit")))]
pub async fn ingest(
    State(state): State<AppState>,
    Path(task): Path<String>,
    params: Result<Query<IngestParams>, QueryRejection>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let mut stream = body.into_data_stream();
    let received = match state.auth.check(&headers) {
        Ok(()) => match params {
            Ok(Query(params)) => receive(&state, task, params, &headers, &mut stream).await,
            Err(e) => Err(ApiError::InvalidArgument(e.body_text())),
        },
        Err(e) => Err(e),
    };
    let received = match received {
        Ok(received) => received,
        Err(e) => {
            count_ingest(&state, &Err(()));
            linger(&mut stream).await;
            return Err(e);
        }
    };
    if received.background {
        return in_background(state, received).await;
    }
    let result = convert(&state, received).await;
    count_ingest(&state, &result.as_ref().map(|r| r.created).map_err(|_| ()));
    let response = result?;
    let status = if response.created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    Ok((status, Json(response)).into_response())
}

fn count_ingest(state: &AppState, outcome: &Result<bool, ()>) {
    let outcome = match outcome {
        Ok(true) => "created",
        Ok(false) => "unchanged",
        Err(()) => "rejected",
    };
    state.metrics.ingests.get_or_create(&OutcomeLabels { outcome }).inc();
    if outcome == "created" {
        state.metrics.dataset_versions.inc();
    }
}

/// Answers 202 for a received upload and converts it in a task of this process, which heartbeats the upload's row
/// and records the answer or the error there; an upload of the same bytes already converting or done is followed
/// instead.
async fn in_background(state: AppState, received: Received) -> Result<Response, ApiError> {
    let db = state.datasets.db().clone();
    let view = match uploads::in_progress_or_done(&db, &received.task, &received.upload_sha256).await? {
        Some(existing) => existing,
        None => {
            let id = uploads::start(
                &db,
                &received.task,
                &received.upload_sha256,
                &received.file_name,
                received.byte_size,
            )
            .await?;
            let (task_db, task_id) = (db.clone(), id.clone());
            tokio::spawn(async move {
                let beating = {
                    let (db, id) = (task_db.clone(), task_id.clone());
                    tokio::spawn(async move {
                        loop {
                            tokio::time::sleep(std::time::Duration::from_millis(uploads::HEARTBEAT_MS as u64)).await;
                            if let Err(e) = uploads::heartbeat(&db, &id).await {
                                tracing::warn!(upload = %id, error = %e, "upload heartbeat");
                            }
                        }
                    })
                };
                let result = convert(&state, received).await;
                beating.abort();
                count_ingest(&state, &result.as_ref().map(|r| r.created).map_err(|_| ()));
                let recorded = match &result {
                    Ok(response) => match serde_json::to_value(response) {
                        Ok(value) => uploads::finish(&task_db, &task_id, Ok(value)).await,
                        Err(e) => uploads::finish(&task_db, &task_id, Err(&ApiError::internal(e))).await,
                    },
                    Err(e) => uploads::finish(&task_db, &task_id, Err(e)).await,
                };
                match (&result, recorded) {
                    (_, Err(e)) => tracing::error!(upload = %task_id, error = %e, "recording how an upload ended"),
                    (Err(e), Ok(())) => tracing::warn!(upload = %task_id, error = %e, "a background upload failed"),
                    (Ok(r), Ok(())) => {
                        tracing::info!(upload = %task_id, version = %r.version.version, "a background upload finished")
                    }
                }
            });
            uploads::get(&db, &id).await?
        }
    };
    let location = HeaderValue::from_str(&view.url).map_err(ApiError::internal)?;
    Ok((StatusCode::ACCEPTED, [(header::LOCATION, location)], Json(view)).into_response())
}

#[utoipa::path(get, path = "/v1/uploads/{upload}", tag = "datasets",
    params(("upload" = String, Path, description = "The upload's id, from the 202 of a background upload")),
    security(("admin_token" = [])),
    responses((status = 200, body = UploadView, description = "The upload: converting, done (with the ingest's \
            answer), failed (with the error) or interrupted"),
        (status = 401, description = "No admin token"), (status = 403, description = "Not the admin token"),
        (status = 404, description = "No such upload")))]
pub async fn get_upload(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Json<UploadView>, ApiError> {
    state.auth.check(&headers)?;
    Ok(Json(uploads::get(state.datasets.db(), &id).await?))
}

#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
pub struct UploadQuery {
    pub task: String,
    /// sha256 of the uploaded bytes.
    pub sha256: String,
}

#[derive(Serialize, utoipa::ToSchema)]
pub struct UploadList {
    pub uploads: Vec<UploadView>,
}

#[utoipa::path(get, path = "/v1/uploads", tag = "datasets",
    params(UploadQuery),
    security(("admin_token" = [])),
    responses((status = 200, body = UploadList, description = "The uploads of these bytes for the task, newest \
            first: what a client resuming an upload looks for before sending the file again"),
        (status = 400, description = "A missing or unknown query parameter"),
        (status = 401, description = "No admin token"), (status = 403, description = "Not the admin token")))]
pub async fn find_uploads(
    State(state): State<AppState>,
    query: Result<Query<UploadQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Json<UploadList>, ApiError> {
    state.auth.check(&headers)?;
    let Query(query) = query.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    Ok(Json(UploadList {
        uploads: uploads::find(state.datasets.db(), &query.task, &query.sha256).await?,
    }))
}

/// How long, and how many bytes, a rejected upload is still read (and discarded) before the error is sent.
const LINGER_TIME: std::time::Duration = std::time::Duration::from_secs(2);
const LINGER_BYTES: u64 = 64 << 20;

/// Reads and discards what is left of a rejected upload, within bounds, as nginx's lingering close does: an
/// HTTP/1.1 client that is still sending when the server answers and closes gets a broken pipe instead of the
/// answer. Bounded, so a client that keeps sending cannot hold the connection.
pub(crate) async fn linger(stream: &mut axum::body::BodyDataStream) {
    let mut drained = 0u64;
    let _ = tokio::time::timeout(LINGER_TIME, async {
        while let Some(Ok(chunk)) = stream.next().await {
            drained += chunk.len() as u64;
            if drained > LINGER_BYTES {
                break;
            }
        }
    })
    .await;
}

/// An upload received whole: spooled to a temporary file, hashed, its size checked, its parameters parsed.
struct Received {
    task: String,
    request: IngestRequest,
    upload_sha256: String,
    file_name: String,
    byte_size: u64,
    background: bool,
}

async fn receive(
    state: &AppState,
    task: String,
    params: IngestParams,
    headers: &HeaderMap,
    stream: &mut axum::body::BodyDataStream,
) -> Result<Received, ApiError> {
    let task_id = state.datasets.task(&task)?.id.to_string();
    let limit = state.max_upload_bytes;
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit) {
        return Err(ApiError::UploadTooLarge { limit });
    }
    let observation_space = match params.observation_space.as_deref() {
        None => ObservationSpace::Simulator,
        Some(s) => s.parse().map_err(ApiError::InvalidArgument)?,
    };
    let tags = params
        .tags
        .as_deref()
        .unwrap_or("")
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<TagName>()
                .map_err(|e| ApiError::InvalidArgument(e.to_string()))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let recipe = match headers.get(PROVENANCE_HEADER) {
        None => None,
        Some(v) => {
            let p: Provenance = serde_json::from_slice(v.as_bytes())
                .map_err(|e| ApiError::InvalidArgument(format!("{PROVENANCE_HEADER} header: {e}")))?;
            if !matches!(p, Provenance::Recipe { .. }) {
                return Err(ApiError::InvalidArgument(format!(
                    "{PROVENANCE_HEADER} header: only recipe provenance can be declared; imports are recorded by the \
                     server"
                )));
            }
            Some(p)
        }
    };
    if let Some(license) = &params.license
        && (license.is_empty() || license.len() > 128)
    {
        return Err(ApiError::InvalidArgument("license must have 1-128 characters".into()));
    }
    let file_name = params.filename.clone().unwrap_or_else(|| "upload".to_owned());

    // Stream the body to a temporary file, hashing it and enforcing the size limit as it arrives.
    let upload = state.datasets.temp_file("upload");
    let mut file = tokio::io::BufWriter::with_capacity(
        1 << 20,
        tokio::fs::File::create(upload.path())
            .await
            .map_err(ApiError::internal)?,
    );
    let mut hasher = Sha256::new();
    let mut received = 0u64;
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| ApiError::InvalidUpload(format!("the upload was interrupted: {e}")))?;
        received += chunk.len() as u64;
        if received > limit {
            return Err(ApiError::UploadTooLarge { limit });
        }
        hasher.update(&chunk);
        file.write_all(&chunk).await.map_err(ApiError::internal)?;
    }
    file.flush().await.map_err(ApiError::internal)?;
    drop(file);
    if received == 0 {
        return Err(ApiError::InvalidUpload("the upload is empty".into()));
    }
    if declared.is_some_and(|n| n != received) {
        return Err(ApiError::InvalidUpload(format!(
            "received {received} bytes but Content-Length said {declared:?}"
        )));
    }
    let upload_sha256 = hex::encode(hasher.finalize());
    Ok(Received {
        task: task_id.clone(),
        upload_sha256: upload_sha256.clone(),
        file_name: file_name.clone(),
        byte_size: received,
        background: params.background == Some(true),
        request: IngestRequest {
            task: task_id,
            upload,
            upload_sha256,
            file_name,
            observation_space,
            tags,
            license: params.license,
            recipe,
            latest: if params.latest == Some(false) {
                LatestPolicy::Keep
            } else {
                LatestPolicy::Move
            },
        },
    })
}

/// Converts and stores a received upload: the ingest's answer.
async fn convert(state: &AppState, received: Received) -> Result<IngestResponse, ApiError> {
    let task_id = received.task;
    let outcome = state.datasets.ingest(received.request).await?;
    let version = outcome.version.version.clone();
    Ok(IngestResponse {
        created: outcome.created,
        manifest_url: format!("/v1/datasets/{task_id}/versions/{version}"),
        download_url: format!("/v1/datasets/{task_id}/versions/{version}/download"),
        task: task_id,
        version: outcome.version,
        moved_tags: outcome.moved_tags,
    })
}

#[utoipa::path(put, path = "/v1/datasets/{task}/tags/{tag}", tag = "datasets",
    params(("task" = String, Path), ("tag" = String, Path)),
    request_body = TagRequest,
    security(("admin_token" = [])),
    responses((status = 200, body = VersionRecord), (status = 400, description = "An invalid tag name or body"),
        (status = 401, description = "No admin token"), (status = 403, description = "Not the admin token"),
        (status = 404, description = "Unknown task or version")))]
pub async fn put_tag(
    State(state): State<AppState>,
    Path((task, tag)): Path<(String, String)>,
    headers: HeaderMap,
    request: Result<Json<TagRequest>, JsonRejection>,
) -> Result<Json<VersionRecord>, ApiError> {
    state.auth.check(&headers)?;
    let Json(request) = request.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    Ok(Json(state.datasets.tag(&task, &tag, &request.version).await?))
}
