//! `GET /v1/simulators`: the simulator worker pool as its supervisor sees it. Anyone sees a summary (how many
//! workers are healthy, the free capacity); the per-worker detail (pids, addresses, errors) is for the admin
//! token only, since it tells an attacker what to aim at.

use axum::Json;
use axum::extract::State;
use axum::http::HeaderMap;
use serde::Serialize;

use crate::AppState;
use crate::error::ApiError;
use dsrl_simulators::WorkerStatus;

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct SimulatorPoolStatus {
    /// Workers configured (local and remote).
    pub workers_total: u32,
    /// Workers that answered their last health check.
    pub healthy_workers: u32,
    /// Environments the healthy workers can still open, and their total.
    pub free_envs: u32,
    pub max_envs: u32,
    /// Every worker's health, load, pid or address and restarts: present only with the admin token.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub workers: Option<Vec<WorkerStatus>>,
}

#[utoipa::path(get, path = "/v1/simulators", tag = "simulators",
    params(("Authorization" = Option<String>, Header, description = "Bearer <admin token>: adds each worker's detail")),
    responses(
        (status = 200, body = SimulatorPoolStatus, description = "The pool's summary (to anyone but the admin: a user's token, another token or none); with the admin token, every worker's health, load, pid or address and restarts")))]
pub async fn list_simulators(
    State(state): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<SimulatorPoolStatus>, ApiError> {
    // The detail for the admin token; the public summary for everyone else (a user's token is not a mistake here:
    // the leaderboard's users hold one and see what anyone sees).
    let detail = state.auth.check(&headers).is_ok();
    let workers = state.simulators.workers();
    let healthy: Vec<&WorkerStatus> = workers.iter().filter(|w| w.healthy).collect();
    Ok(Json(SimulatorPoolStatus {
        workers_total: workers.len() as u32,
        healthy_workers: healthy.len() as u32,
        free_envs: healthy.iter().map(|w| w.max_envs.saturating_sub(w.envs)).sum(),
        max_envs: healthy.iter().map(|w| w.max_envs).sum(),
        workers: detail.then_some(workers),
    }))
}
