//! `GET /v1/simulators`: the simulator worker pool as its supervisor sees it.

use axum::Json;
use axum::extract::State;
use serde::Serialize;

use crate::AppState;
use crate::simulators::WorkerStatus;

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct SimulatorPoolStatus {
    pub workers: Vec<WorkerStatus>,
}

#[utoipa::path(get, path = "/v1/simulators", tag = "simulators",
    responses((status = 200, body = SimulatorPoolStatus, description = "Every configured worker: health, load, restarts")))]
pub async fn list_simulators(State(state): State<AppState>) -> Json<SimulatorPoolStatus> {
    Json(SimulatorPoolStatus {
        workers: state.simulators.workers(),
    })
}
