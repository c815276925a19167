//! The REST side of the server: routes, the admin check, downloads, metrics and the OpenAPI document.

pub mod auth;
pub mod browser;
pub mod datasets;
pub mod download;
pub mod dsrl_download;
pub mod failures;
pub mod html;
pub mod leaderboard;
pub mod metrics;
pub mod openapi;
pub mod simulators;

use axum::Router;
use axum::extract::DefaultBodyLimit;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::{get, post, put};

use crate::AppState;

pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(browser::index))
        .route("/tasks/{task}", get(browser::card))
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics::metrics))
        .route("/openapi.json", get(openapi_json))
        .route("/v1/server", get(datasets::server_info))
        .route("/v1/simulators", get(simulators::list_simulators))
        .route("/v1/tasks", get(datasets::list_tasks))
        .route("/v1/tasks/{task}", get(datasets::get_task))
        .route(
            "/v1/datasets/{task}/versions",
            get(datasets::list_versions).post(datasets::ingest),
        )
        .route("/v1/datasets/{task}/versions/{version}", get(datasets::get_manifest))
        .route(
            "/v1/datasets/{task}/versions/{version}/download",
            get(download::download),
        )
        .route(
            "/v1/datasets/{task}/versions/{version}/plot.svg",
            get(datasets::get_plot),
        )
        .route(
            "/v1/datasets/{task}/versions/{version}/croissant.json",
            get(datasets::get_croissant),
        )
        .route("/v1/datasets/{task}/tags/{tag}", put(datasets::put_tag))
        .route("/v1/uploads", get(datasets::find_uploads))
        .route("/v1/uploads/{upload}", get(datasets::get_upload))
        // DSRL's own download URLs (`http://data.offline-saferl.org/download/{file}` in dsrl 0.1.0).
        .route("/download/{file}", get(dsrl_download::dsrl_download))
        .route("/v1/users", post(leaderboard::create_user))
        .route(
            "/v1/submissions",
            post(leaderboard::submit).layer(DefaultBodyLimit::max(
                state.leaderboard.config.max_submission_bytes as usize,
            )),
        )
        .route("/v1/submissions/{id}", get(leaderboard::get_submission))
        .route("/v1/submissions/{id}/cancel", post(leaderboard::cancel_submission))
        .route("/v1/leaderboard", get(leaderboard::get_leaderboard))
        .route("/v1/leaderboard.csv", get(leaderboard::leaderboard_csv))
        .route("/v1/leaderboard.parquet", get(leaderboard::leaderboard_parquet))
        .route(
            "/v1/submissions/{id}/episodes.csv",
            get(leaderboard::submission_episodes_csv),
        )
        .route(
            "/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.json",
            get(leaderboard::episode_replay),
        )
        .route(
            "/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.gif",
            get(leaderboard::episode_replay_gif),
        )
        .route("/v1/users/{name}/submissions", get(leaderboard::user_submissions))
        .route("/users/{name}", get(leaderboard::user_page))
        .route("/leaderboard", get(leaderboard::leaderboard_page))
        .route("/leaderboard/agreement", get(leaderboard::agreement_page))
        .route("/leaderboard/plots/{table}", get(leaderboard::plot))
        .route("/submissions/{id}", get(leaderboard::submission_page))
        .route(
            "/submissions/{id}/episodes/{threshold}/{episode}",
            get(leaderboard::episode_page),
        )
        .layer(axum::middleware::map_response(html::defensive_headers))
        .with_state(state)
}

/// The database and this server's evaluators: 200 when the database answers and, where the server should evaluate
/// (`leaderboard.evaluators` > 0), at least one evaluator runs; 503 (`degraded`) otherwise.
#[utoipa::path(get, path = "/healthz", tag = "operations",
    responses((status = 200, body = crate::leaderboard::supervision::Health, description = "ok"),
        (status = 503, body = crate::leaderboard::supervision::Health,
         description = "Degraded: the database does not answer, or no evaluator runs where some should")))]
pub async fn healthz(State(state): State<AppState>) -> impl IntoResponse {
    let (healthy, health) = state.leaderboard.health().await;
    let status = if healthy {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    (status, axum::Json(health))
}

#[utoipa::path(get, path = "/openapi.json", tag = "operations",
    responses((status = 200, content_type = "application/json", body = Object, description = "This document")))]
pub async fn openapi_json() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "application/json")], openapi::json())
}

pub async fn not_found() -> impl IntoResponse {
    (
        StatusCode::NOT_FOUND,
        axum::Json(serde_json::json!({"error": {"code": "not_found", "message": "no such route; see /openapi.json"}})),
    )
}
