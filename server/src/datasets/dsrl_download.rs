//! DSRL's own download URLs: `GET /download/{file}` answers the file names of DSRL's `DATASET_URLS`
//! (`{SimulatorEnvId}-{cost cap}-{n}.hdf5`, the paper's names), so that an unmodified `pip install dsrl` whose dead
//! host (`data.offline-saferl.org`) is pointed at this server gets datasets again.
//!
//! The name picks the task; the answer is that task's `latest` version in DSRL's HDF5 layout — our rebuilt data,
//! not the paper's file, so the trajectory count rarely matches the name's `{n}` (`X-Dsrl-Version` and
//! `X-Dsrl-Episodes` say what was served). The HDF5 is converted once per version and stored content-addressed;
//! it streams with `Content-Length`, `ETag` (its sha256), `Range` and `HEAD`. A task with nothing hosted answers
//! 404 with the JSON error, never an empty body, because DSRL keeps whatever file it downloaded as the dataset.
//! DSRL's MetaDrive environments expect the paper's 261 features; ours have the pinned simulator's 259, so the
//! MetaDrive names answer 404 with that reason unless the operator opts in (`datasets.dsrl_download_metadrive`).

use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::Response;
use dsrl_suite::Task;
use dsrl_suite::catalog::Family;

use crate::AppState;
use crate::datasets::download::serve_hdf5_export;
use crate::error::ApiError;

/// DSRL's file name for a task: `{prefix}-{cap}-{n}.hdf5` with the paper's cap and trajectory count.
pub fn dsrl_file_name(task: &Task) -> String {
    format!("{}.hdf5", task.dataset_file_stem(u64::from(task.paper_trajectories)))
}

/// DSRL's file of the paper's dataset, in DSRL's HDF5 layout from this server's latest version of the task.
#[utoipa::path(get, path = "/download/{file}", tag = "datasets",
    params(("file" = String, Path, pattern = r"^[A-Za-z0-9_.-]+\.hdf5$",
        example = "SafetyBallRun-v0-80-940.hdf5",
        description = "A file name of DSRL's DATASET_URLS, e.g. SafetyCarCircle-v0-100-1450.hdf5")),
    responses(
        (status = 200, content_type = "application/x-hdf5", body = Vec<u8>,
            description = "The task's latest version in DSRL's HDF5 layout (X-Dsrl-Version names it)"),
        (status = 206, content_type = "application/x-hdf5", body = Vec<u8>, description = "The requested range"),
        (status = 304, description = "Not modified (If-None-Match)"),
        (status = 404, description = "Not one of DSRL's file names, no hosted version, or a MetaDrive name \
            while this server does not serve 259-feature data under the paper's 261-feature names"),
        (status = 416, description = "Range not satisfiable"),
        (status = 429, description = "The anonymous derivation budget of the hour is spent: send a token, or retry after Retry-After"),
        (status = 503, description = "Too much derivation work waiting: retry after Retry-After")))]
pub async fn dsrl_download(
    State(state): State<AppState>,
    Path(file): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let catalog = &state.datasets.catalog;
    let task = catalog
        .tasks()
        .iter()
        .find(|t| dsrl_file_name(t) == file)
        .ok_or_else(|| {
            ApiError::NotFound(format!(
                "{file} is not one of DSRL's dataset files (DATASET_URLS of dsrl 0.1.0, e.g. {}); \
                 this route serves those names only",
                catalog.tasks().first().map(dsrl_file_name).unwrap_or_default()
            ))
        })?;
    if task.family == Family::MetaDrive && !state.dsrl_download_metadrive && task.obs_dim != task.obs_dim_paper {
        return Err(ApiError::NotFound(format!(
            "{file}: DSRL's MetaDrive environment expects the paper's {} observation features, and this server's \
             MetaDrive data has the pinned simulator's {}; the operator can serve it anyway \
             (datasets.dsrl_download_metadrive = true), or fetch it with dsrl-client",
            task.obs_dim_paper, task.obs_dim
        )));
    }
    let (_, record) = state.datasets.resolve(task.id.as_str(), "latest").await?;
    let requester = crate::http::auth::requester(&state, &headers).await;
    let mut response_headers = HeaderMap::new();
    let value = |v: &str| HeaderValue::from_str(v).map_err(ApiError::internal);
    // `latest` can move to a new version.
    response_headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response_headers.insert("x-dsrl-task", value(task.id.as_str())?);
    response_headers.insert("x-dsrl-episodes", HeaderValue::from(record.episodes));
    serve_hdf5_export(&state, &record, &headers, requester, &file, response_headers).await
}
