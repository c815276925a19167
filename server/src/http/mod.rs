//! The REST side of the server: routes, the admin check, downloads, metrics and the OpenAPI document.

pub mod auth;
pub mod failures;
pub mod html;
pub mod metrics;
pub mod openapi;

use axum::Router;
use axum::extract::DefaultBodyLimit;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::{get, post, put};

use crate::AppState;
use crate::{datasets, leaderboard, simulators};

pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(datasets::pages::index))
        .route("/tasks/{task}", get(datasets::pages::card))
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics::metrics))
        .route("/openapi.json", get(openapi_json))
        .route("/v1/server", get(datasets::rest::server_info))
        .route("/v1/simulators", get(simulators::list_simulators))
        .route("/v1/tasks", get(datasets::rest::list_tasks))
        .route("/v1/tasks/{task}", get(datasets::rest::get_task))
        .route(
            "/v1/datasets/{task}/versions",
            get(datasets::rest::list_versions).post(datasets::rest::ingest),
        )
        .route(
            "/v1/datasets/{task}/versions/{version}",
            get(datasets::rest::get_manifest),
        )
        .route(
            "/v1/datasets/{task}/versions/{version}/download",
            get(datasets::download::download),
        )
        .route(
            "/v1/datasets/{task}/versions/{version}/plot.svg",
            get(datasets::rest::get_plot),
        )
        .route(
            "/v1/datasets/{task}/versions/{version}/croissant.json",
            get(datasets::rest::get_croissant),
        )
        .route("/v1/datasets/{task}/tags/{tag}", put(datasets::rest::put_tag))
        .route("/v1/uploads", get(datasets::rest::find_uploads))
        .route("/v1/uploads/{upload}", get(datasets::rest::get_upload))
        // DSRL's own download URLs (`http://data.offline-saferl.org/download/{file}` in dsrl 0.1.0).
        .route("/download/{file}", get(datasets::dsrl_download::dsrl_download))
        .route("/v1/users", post(leaderboard::rest::create_user))
        .route(
            "/v1/submissions",
            post(leaderboard::rest::submit).layer(DefaultBodyLimit::max(
                state.leaderboard.config.max_submission_bytes as usize,
            )),
        )
        .route("/v1/submissions/{id}", get(leaderboard::rest::get_submission))
        .route(
            "/v1/submissions/{id}/cancel",
            post(leaderboard::rest::cancel_submission),
        )
        .route("/v1/leaderboard", get(leaderboard::rest::get_leaderboard))
        .route("/v1/leaderboard.csv", get(leaderboard::rest::leaderboard_csv))
        .route("/v1/leaderboard.parquet", get(leaderboard::rest::leaderboard_parquet))
        .route(
            "/v1/submissions/{id}/episodes.csv",
            get(leaderboard::rest::submission_episodes_csv),
        )
        .route(
            "/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.json",
            get(leaderboard::rest::episode_replay),
        )
        .route(
            "/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.gif",
            get(leaderboard::rest::episode_replay_gif),
        )
        .route("/v1/users/{name}/submissions", get(leaderboard::rest::user_submissions))
        .route("/users/{name}", get(leaderboard::rest::user_page))
        .route("/leaderboard", get(leaderboard::rest::leaderboard_page))
        .route("/leaderboard/agreement", get(leaderboard::rest::agreement_page))
        .route("/leaderboard/plots/{table}", get(leaderboard::rest::plot))
        .route("/submissions/{id}", get(leaderboard::rest::submission_page))
        .route(
            "/submissions/{id}/episodes/{threshold}/{episode}",
            get(leaderboard::rest::episode_page),
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
