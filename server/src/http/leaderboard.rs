//! REST routes of the leaderboard: users (admin), submissions (user tokens), the tables and the HTML page.

use axum::Json;
use axum::extract::{Multipart, Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{Html, IntoResponse};
use bytes::{Bytes, BytesMut};
use serde::Deserialize;

use crate::AppState;
use crate::error::ApiError;
use crate::leaderboard::{checkpoints, page, users};

#[derive(Deserialize)]
pub struct NewUserRequest {
    name: String,
}

/// `POST /v1/users` (admin): creates a user and returns its bearer token, shown this once.
pub async fn create_user(
    State(state): State<AppState>,
    headers: HeaderMap,
    Json(request): Json<NewUserRequest>,
) -> Result<impl IntoResponse, ApiError> {
    state.auth.check(&headers)?;
    let user = users::create(&state.leaderboard.pool, &request.name).await?;
    Ok((StatusCode::CREATED, Json(user)))
}

fn multipart_error(e: axum::extract::multipart::MultipartError) -> ApiError {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::InvalidArgument(format!("submission too large: {}", e.body_text()))
    } else {
        ApiError::InvalidArgument(format!("malformed multipart body: {}", e.body_text()))
    }
}

/// `POST /v1/submissions` (user token): multipart form with text fields `task` and `name` and the checkpoint
/// files, each a part named by its path (`policy.json`, `policy.safetensors`, or `<folder>/policy.json`, ...).
pub async fn submit(
    State(state): State<AppState>,
    headers: HeaderMap,
    mut form: Multipart,
) -> Result<impl IntoResponse, ApiError> {
    let user = users::authenticate(&state.leaderboard.pool, &headers).await?;
    let (mut task, mut name, mut files) = (None, None, Vec::<(String, Bytes)>::new());
    while let Some(mut field) = form.next_field().await.map_err(multipart_error)? {
        let field_name = field.name().unwrap_or_default().to_owned();
        match field_name.as_str() {
            "task" | "name" => {
                let text = field.text().await.map_err(multipart_error)?;
                if text.len() > 256 {
                    return Err(ApiError::InvalidArgument(format!("the {field_name} field is too long")));
                }
                *(if field_name == "task" { &mut task } else { &mut name }) = Some(text);
            }
            _ => {
                let limit = checkpoints::file_limit(&field_name).ok_or_else(|| {
                    ApiError::InvalidArgument(format!(
                        "unexpected part {field_name:?}: send task, name and the checkpoint files (policy.json, \
                         policy.safetensors, at the top or as <folder>/policy.json per threshold)"
                    ))
                })?;
                // Read with the file's limit, so a huge part is refused before it is held in memory.
                let mut bytes = BytesMut::new();
                while let Some(chunk) = field.chunk().await.map_err(multipart_error)? {
                    if (bytes.len() + chunk.len()) as u64 > limit {
                        return Err(ApiError::UploadTooLarge { limit });
                    }
                    bytes.extend_from_slice(&chunk);
                }
                files.push((field_name, bytes.freeze()));
            }
        }
    }
    let task = task.ok_or_else(|| ApiError::InvalidArgument("the form has no task field".into()))?;
    let name = name.ok_or_else(|| ApiError::InvalidArgument("the form has no name field".into()))?;
    let view = state.leaderboard.submit(&user, &task, &name, files).await?;
    Ok((StatusCode::ACCEPTED, Json(view)))
}

fn submission_id(id: &str) -> Result<i64, ApiError> {
    id.parse()
        .map_err(|_| ApiError::InvalidArgument(format!("{id:?} is not a submission id (a number)")))
}

/// `GET /v1/submissions/{id}`: state, reason, scores and every episode.
pub async fn get_submission(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    Ok(Json(state.leaderboard.view(submission_id(&id)?).await?))
}

/// `POST /v1/submissions/{id}/cancel` (the submitter's token).
pub async fn cancel_submission(
    State(state): State<AppState>,
    headers: HeaderMap,
    Path(id): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    let user = users::authenticate(&state.leaderboard.pool, &headers).await?;
    Ok(Json(state.leaderboard.cancel(&user, submission_id(&id)?).await?))
}

#[derive(Deserialize)]
pub struct BoardQuery {
    task: Option<String>,
}

/// `GET /v1/leaderboard[?task=T]`.
pub async fn get_leaderboard(
    State(state): State<AppState>,
    Query(query): Query<BoardQuery>,
) -> Result<impl IntoResponse, ApiError> {
    Ok(Json(state.leaderboard.board(query.task.as_deref()).await?))
}

/// `GET /leaderboard[?task=T]`: the HTML page.
pub async fn leaderboard_page(
    State(state): State<AppState>,
    Query(query): Query<BoardQuery>,
) -> Result<impl IntoResponse, ApiError> {
    let board = state.leaderboard.board(query.task.as_deref()).await?;
    Ok(([(header::CACHE_CONTROL, "no-cache")], Html(page::render(&board))))
}
