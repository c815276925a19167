//! REST routes of the leaderboard: users (admin), submissions (user tokens), the tables and the HTML page.

use axum::Json;
use axum::extract::{FromRequest, Multipart, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{Html, IntoResponse, Response};
use bytes::{Bytes, BytesMut};
use serde::Deserialize;

use crate::AppState;
use crate::error::ApiError;
use crate::leaderboard::queue::Canceller;
use crate::leaderboard::{SubmissionView, checkpoints, page, users};

#[derive(Deserialize, utoipa::ToSchema)]
pub struct NewUserRequest {
    /// 1-64 letters, digits, `.`, `_`, `-`.
    name: String,
}

/// `POST /v1/users` (admin): creates a user and returns its bearer token, shown this once. The token is checked
/// before the body is read, so an anonymous request learns only that it needs one.
#[utoipa::path(post, path = "/v1/users", tag = "leaderboard",
    request_body = NewUserRequest,
    security(("admin_token" = [])),
    responses(
        (status = 201, body = crate::leaderboard::users::NewUser, description = "The user and its bearer token, shown this once"),
        (status = 400, description = "The body is not {\"name\": NAME} with a valid name"),
        (status = 401, description = "No admin token"), (status = 403, description = "Not the admin token"),
        (status = 409, description = "A user of that name exists")))]
pub async fn create_user(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<impl IntoResponse, ApiError> {
    state.auth.check(&headers)?;
    let request: NewUserRequest = serde_json::from_slice(&body)
        .map_err(|e| ApiError::InvalidArgument(format!("the body must be JSON {{\"name\": NAME}}: {e}")))?;
    let user = users::create(&state.leaderboard.db, &request.name).await?;
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
///
/// The user is authenticated before the body is looked at. A file over its limit answers 413 with `Connection:
/// close`: the rest of the upload is not read, and a client reusing the connection (Python `requests`) must know.
#[utoipa::path(post, path = "/v1/submissions", tag = "leaderboard",
    request_body(content = SubmissionForm, content_type = "multipart/form-data",
        description = "Text fields task and name, and the checkpoint files as parts named by their paths"),
    security(("user_token" = [])),
    responses(
        (status = 202, body = SubmissionView, description = "Checked, stored and queued"),
        (status = 400, description = "The form or a checkpoint is malformed; the message names the problem"),
        (status = 401, description = "No user token, or one that belongs to no user"),
        (status = 404, description = "Unknown task"),
        (status = 409, description = "The same network was submitted before (the message names that submission)"),
        (status = 413, description = "A file is over its limit"),
        (status = 429, description = "Over the daily or concurrent quota")))]
pub async fn submit(State(state): State<AppState>, request: Request) -> Response {
    match receive_submission(&state, request).await {
        Ok(accepted) => accepted.into_response(),
        Err(e) => {
            // An upload refused for its size is not read to its end: say the connection closes. (Other errors
            // come before or after the body is read, and the connection stays usable.)
            let too_large = e.code() == crate::error::ErrorCode::PayloadTooLarge;
            let mut response = e.into_response();
            if too_large {
                response
                    .headers_mut()
                    .insert(header::CONNECTION, HeaderValue::from_static("close"));
            }
            response
        }
    }
}

async fn receive_submission(
    state: &AppState,
    request: Request,
) -> Result<(StatusCode, Json<SubmissionView>), ApiError> {
    let user = match users::authenticate(&state.leaderboard.db, request.headers()).await {
        Ok(user) => user,
        Err(e) => {
            // Refused before the body is read: read and discard it (bounded), or a client still sending the
            // checkpoint gets a broken pipe instead of this answer.
            crate::datasets::rest::linger(&mut request.into_body().into_data_stream()).await;
            return Err(e);
        }
    };
    let mut form = Multipart::from_request(request, state)
        .await
        .map_err(|e| ApiError::InvalidArgument(format!("the body must be multipart/form-data: {}", e.body_text())))?;
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

#[derive(Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct SubmissionQuery {
    /// Answer once the submission has ended (finished, failed or cancelled), or after this many seconds (at most
    /// 60) with its state then: a client waits for its score with one request instead of polling.
    wait: Option<String>,
}

/// `GET /v1/submissions/{id}[?wait=SECONDS]`: state, reason, scores and every episode.
#[utoipa::path(get, path = "/v1/submissions/{id}", tag = "leaderboard",
    params(("id" = String, Path, description = "Submission id (a number)"), SubmissionQuery),
    responses(
        (status = 200, body = SubmissionView),
        (status = 400, description = "Not a submission id, or a wait that is not 0-60 seconds"),
        (status = 404, description = "No such submission")))]
pub async fn get_submission(
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(query): Query<SubmissionQuery>,
) -> Result<impl IntoResponse, ApiError> {
    let id = submission_id(&id)?;
    if let Some(wait) = query.wait.as_deref() {
        let seconds = wait.parse().map_err(|_| crate::leaderboard::bad_wait(wait))?;
        state.leaderboard.wait_until_ended(id, seconds).await?;
    }
    Ok(Json(state.leaderboard.view(id).await?))
}

/// `GET /v1/submissions/{id}/episodes.csv`: every scored episode of a submission as CSV.
#[utoipa::path(get, path = "/v1/submissions/{id}/episodes.csv", tag = "leaderboard",
    params(("id" = String, Path, description = "Submission id (a number)")),
    responses(
        (status = 200, content_type = "text/csv", body = String,
         description = "cost_threshold, episode, reward_return, cost_return, length: one line per scored episode"),
        (status = 400, description = "Not a submission id"),
        (status = 404, description = "No such submission")))]
pub async fn submission_episodes_csv(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    let view = state.leaderboard.view(submission_id(&id)?).await?;
    let body = crate::leaderboard::export::episodes_csv(&view.episodes)?;
    Ok(([(header::CONTENT_TYPE, "text/csv; charset=utf-8")], body))
}

/// `GET /v1/leaderboard.csv`: the whole board (each task's entries and the paper's rows, each family's aggregate)
/// as one CSV table with the protocol version on every row.
#[utoipa::path(get, path = "/v1/leaderboard.csv", tag = "leaderboard",
    responses((status = 200, content_type = "text/csv", body = String,
        description = "One row per ranked entry, paper row and family entry (columns: protocol_version, scope, table, \
                       kind, rank, user, name, reference, normalized_reward, reward_low, reward_high, \
                       normalized_cost, cost_low, cost_high, safe, author_submissions_to_task, tasks, submission, \
                       dataset_version, finished_at)")))]
pub async fn leaderboard_csv(State(state): State<AppState>) -> Result<impl IntoResponse, ApiError> {
    let board = state.leaderboard.board(None).await?;
    let body = crate::leaderboard::export::csv(
        &crate::leaderboard::export::rows(&board),
        crate::leaderboard::export::BOARD_COLUMNS,
    )?;
    Ok((
        [
            (header::CONTENT_TYPE, "text/csv; charset=utf-8"),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"dsrl-leaderboard.csv\"",
            ),
        ],
        body,
    ))
}

/// `GET /v1/leaderboard.parquet`: the same table as `/v1/leaderboard.csv`, as Parquet.
#[utoipa::path(get, path = "/v1/leaderboard.parquet", tag = "leaderboard",
    responses((status = 200, content_type = "application/vnd.apache.parquet", body = Vec<u8>,
        description = "The board's rows as one Parquet file (the CSV's columns)")))]
pub async fn leaderboard_parquet(State(state): State<AppState>) -> Result<impl IntoResponse, ApiError> {
    let board = state.leaderboard.board(None).await?;
    let body = crate::leaderboard::export::parquet(&crate::leaderboard::export::rows(&board))?;
    Ok((
        [
            (header::CONTENT_TYPE, "application/vnd.apache.parquet"),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"dsrl-leaderboard.parquet\"",
            ),
        ],
        body,
    ))
}

/// `GET /v1/users/{name}/submissions`: every submission of a user, newest first.
#[utoipa::path(get, path = "/v1/users/{name}/submissions", tag = "leaderboard",
    params(("name" = String, Path, description = "User name")),
    responses(
        (status = 200, body = Vec<crate::leaderboard::UserSubmission>, description = "The user's submissions"),
        (status = 404, description = "No such user")))]
pub async fn user_submissions(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    Ok(Json(state.leaderboard.user_submissions(&name).await?))
}

/// `GET /users/{name}`: a user's page, every submission they made.
#[utoipa::path(get, path = "/users/{name}", tag = "leaderboard",
    params(("name" = String, Path, description = "User name")),
    responses(
        (status = 200, content_type = "text/html", body = String, description = "The user's page"),
        (status = 404, description = "No such user")))]
pub async fn user_page(State(state): State<AppState>, Path(name): Path<String>) -> Result<impl IntoResponse, ApiError> {
    let submissions = state.leaderboard.user_submissions(&name).await?;
    Ok((
        [(header::CACHE_CONTROL, "no-cache")],
        Html(page::render_user(&name, &submissions)),
    ))
}

/// `POST /v1/submissions/{id}/cancel` (the submitter's token, or the admin token for any submission).
#[utoipa::path(post, path = "/v1/submissions/{id}/cancel", tag = "leaderboard",
    params(("id" = String, Path, description = "Submission id (a number)")),
    security(("user_token" = []), ("admin_token" = [])),
    responses(
        (status = 200, body = SubmissionView, description = "Cancelled"),
        (status = 400, description = "Not a submission id, or the submission already ended"),
        (status = 401, description = "No token, or a user token that belongs to no user"),
        (status = 403, description = "The submission belongs to another user"),
        (status = 404, description = "No such submission")))]
pub async fn cancel_submission(
    State(state): State<AppState>,
    headers: HeaderMap,
    Path(id): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    let by = if state.auth.check(&headers).is_ok() {
        Canceller::Admin
    } else {
        Canceller::User(users::authenticate(&state.leaderboard.db, &headers).await?.id)
    };
    Ok(Json(state.leaderboard.cancel(by, submission_id(&id)?).await?))
}

#[derive(Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct BoardQuery {
    /// Only this task's table (an offline task id).
    task: Option<String>,
}

/// The multipart form of a submission (documentation type).
#[derive(utoipa::ToSchema)]
#[allow(dead_code)]
pub struct SubmissionForm {
    /// Offline task id.
    task: String,
    /// The entry's name (1-64 letters, digits, `.`, `_`, `-`).
    name: String,
    /// `policy.json` (at the top, or `<folder>/policy.json` per threshold).
    #[schema(rename = "policy.json", value_type = String, format = Binary)]
    policy_json: Vec<u8>,
    /// `policy.safetensors` (at the top, or `<folder>/policy.safetensors` per threshold).
    #[schema(rename = "policy.safetensors", value_type = String, format = Binary)]
    policy_safetensors: Vec<u8>,
}

/// `GET /v1/leaderboard[?task=T]`.
#[utoipa::path(get, path = "/v1/leaderboard", tag = "leaderboard",
    params(BoardQuery),
    responses(
        (status = 200, body = crate::leaderboard::Board, description = "Per-task tables and per-family aggregates"),
        (status = 400, description = "A malformed query"),
        (status = 404, description = "Unknown task")))]
pub async fn get_leaderboard(
    State(state): State<AppState>,
    Query(query): Query<BoardQuery>,
) -> Result<impl IntoResponse, ApiError> {
    Ok(Json(state.leaderboard.board(query.task.as_deref()).await?))
}

/// `GET /leaderboard[?task=T]`: the HTML page.
#[utoipa::path(get, path = "/leaderboard", tag = "leaderboard",
    params(BoardQuery),
    responses(
        (status = 200, content_type = "text/html", body = String, description = "The leaderboard page"),
        (status = 400, description = "A malformed query"),
        (status = 404, description = "Unknown task")))]
pub async fn leaderboard_page(
    State(state): State<AppState>,
    Query(query): Query<BoardQuery>,
) -> Result<impl IntoResponse, ApiError> {
    let board = state.leaderboard.board(query.task.as_deref()).await?;
    let queue = state.leaderboard.queue_summary().await?;
    Ok((
        [(header::CACHE_CONTROL, "no-cache")],
        Html(page::render(&board, &queue)),
    ))
}

/// `GET /leaderboard/agreement`: our reference entries against the paper's table, per family and per cell.
#[utoipa::path(get, path = "/leaderboard/agreement", tag = "leaderboard",
    responses(
        (status = 200, content_type = "text/html", body = String, description = "The agreement page")))]
pub async fn agreement_page(State(state): State<AppState>) -> Result<impl IntoResponse, ApiError> {
    let board = state.leaderboard.board(None).await?;
    Ok((
        [(header::CACHE_CONTROL, "no-cache")],
        Html(page::render_agreement(&board)),
    ))
}

/// `GET /leaderboard/plots/{table}.svg`: a task's or a family's entries (and a task's paper rows) on the
/// normalized cost–reward plane, with their intervals and the safe line, as on the page.
#[utoipa::path(get, path = "/leaderboard/plots/{table}", tag = "leaderboard",
    params(("table" = String, Path, description = "A task id or a family (bullet, safety-gymnasium, metadrive), \
        followed by .svg")),
    responses(
        (status = 200, content_type = "image/svg+xml", body = String, description = "The picture"),
        (status = 404, description = "No such task or family, or no .svg suffix")))]
pub async fn plot(State(state): State<AppState>, Path(table): Path<String>) -> Result<Response, ApiError> {
    let Some(name) = table.strip_suffix(".svg") else {
        return Err(ApiError::NotFound(format!(
            "{table}: plots are at /leaderboard/plots/<task or family>.svg"
        )));
    };
    let svg = if ["bullet", "safety-gymnasium", "metadrive"].contains(&name) {
        let board = state.leaderboard.board(None).await?;
        match board.families.iter().find(|f| f.family == name) {
            Some(family) => page::family_svg(family),
            // A family with no entries yet: an empty picture, not an error.
            None => dsrl_suite::plot::entries_svg(&format!("{name} (IQM over tasks)"), &[]),
        }
    } else {
        let board = state.leaderboard.board(Some(name)).await?;
        let table = board
            .tasks
            .first()
            .ok_or_else(|| ApiError::NotFound(format!("no table for {name}")))?;
        page::task_svg(table)
    }
    .map_err(ApiError::Internal)?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("image/svg+xml")),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        svg,
    )
        .into_response())
}

/// `GET /submissions/{id}`: a submission's page (per-threshold results), linked from the leaderboard page.
#[utoipa::path(get, path = "/submissions/{id}", tag = "leaderboard",
    params(("id" = String, Path, description = "Submission id (a number)")),
    responses(
        (status = 200, content_type = "text/html", body = String, description = "The submission's page"),
        (status = 400, description = "Not a submission id"),
        (status = 404, description = "No such submission")))]
pub async fn submission_page(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    let view = state.leaderboard.view(submission_id(&id)?).await?;
    Ok((
        [(header::CACHE_CONTROL, "no-cache")],
        Html(page::render_submission(&view)),
    ))
}

/// A scored episode named in a path: submission, cost threshold (as the episode table prints it), episode.
fn episode_path(id: &str, threshold: &str, episode: &str) -> Result<(i64, f64, u32), ApiError> {
    let threshold: f64 = threshold
        .parse()
        .map_err(|_| ApiError::InvalidArgument(format!("{threshold:?} is not a cost threshold (a number)")))?;
    let episode: u32 = episode
        .parse()
        .map_err(|_| ApiError::InvalidArgument(format!("{episode:?} is not an episode number")))?;
    Ok((submission_id(id)?, threshold, episode))
}

/// `GET /v1/submissions/{id}/episodes/{threshold}/{episode}/replay.json`: a scored episode played again from its
/// held seed and drawn. 200 with the replay (returns equal to the scored episode's, each step's reward and cost, the
/// animation's size and digest) once made; 202 while it waits (asking queues it; replays start only while no
/// submission waits or is scored).
#[utoipa::path(get, path = "/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.json", tag = "leaderboard",
    params(("id" = String, Path, description = "Submission id (a number)"),
        ("threshold" = String, Path, description = "One of the task's cost thresholds (20, 40, 80 ...)"),
        ("episode" = String, Path, description = "The episode's number at that threshold, from 0")),
    responses(
        (status = 200, body = crate::leaderboard::renders::EpisodeReplay, description = "The replay; its animation is replay.gif"),
        (status = 202, content_type = "application/json", body = Object, description = "{\"state\": \"queued\", \"ahead\": N}: queued behind N replays"),
        (status = 400, description = "Not a submission id, threshold or episode number"),
        (status = 404, description = "No such submission, threshold or episode; not scored; scored under another protocol; or its checkpoint is not held here"),
        (status = 500, description = "The replay failed; the message says why")))]
pub async fn episode_replay(
    State(state): State<AppState>,
    Path((id, threshold, episode)): Path<(String, String, String)>,
) -> Result<Response, ApiError> {
    use crate::leaderboard::renders::ReplayState;
    let (id, threshold, episode) = episode_path(&id, &threshold, &episode)?;
    Ok(match state.leaderboard.replay(id, threshold, episode).await? {
        ReplayState::Ready { replay, .. } => Json(replay).into_response(),
        ReplayState::Queued { ahead } => (
            StatusCode::ACCEPTED,
            [(header::RETRY_AFTER, HeaderValue::from_static("5"))],
            Json(serde_json::json!({"state": "queued", "ahead": ahead})),
        )
            .into_response(),
        ReplayState::Failed(reason) => return Err(ApiError::Internal(format!("the replay failed: {reason}"))),
    })
}

/// `GET /v1/submissions/{id}/episodes/{threshold}/{episode}/replay.gif`: the replay's animation (made first by a
/// request for replay.json).
#[utoipa::path(get, path = "/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.gif", tag = "leaderboard",
    params(("id" = String, Path, description = "Submission id (a number)"),
        ("threshold" = String, Path, description = "One of the task's cost thresholds"),
        ("episode" = String, Path, description = "The episode's number at that threshold, from 0")),
    responses(
        (status = 200, content_type = "image/gif", body = Vec<u8>, description = "A looping animated GIF"),
        (status = 400, description = "Not a submission id, threshold or episode number"),
        (status = 404, description = "Not replayed yet (GET replay.json queues it), or not replayable")))]
pub async fn episode_replay_gif(
    State(state): State<AppState>,
    Path((id, threshold, episode)): Path<(String, String, String)>,
) -> Result<impl IntoResponse, ApiError> {
    let (id, threshold, episode) = episode_path(&id, &threshold, &episode)?;
    let gif = state.leaderboard.replay_gif(id, threshold, episode).await?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("image/gif")),
            // A replay never changes once made.
            (
                header::CACHE_CONTROL,
                HeaderValue::from_static("public, max-age=86400, immutable"),
            ),
        ],
        gif,
    ))
}

/// `GET /submissions/{id}/episodes/{threshold}/{episode}`: the episode's page: its animation beside its
/// step-by-step reward and cost; while the replay waits, a note that reloads itself.
pub async fn episode_page(
    State(state): State<AppState>,
    Path((id, threshold, episode)): Path<(String, String, String)>,
) -> Result<impl IntoResponse, ApiError> {
    let (id, threshold, episode) = episode_path(&id, &threshold, &episode)?;
    let replay = state.leaderboard.replay(id, threshold, episode).await?;
    Ok((
        [(header::CACHE_CONTROL, "no-cache")],
        Html(page::render_episode(id, threshold, episode, &replay)),
    ))
}
