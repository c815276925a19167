//! The evaluator process (`dsrl-evaluator`): it only claims leaderboard jobs from the shared database and plays
//! them on its simulator workers (`leaderboard.evaluators` at once, at least one), scaled apart from the API
//! replicas, which then run with `leaderboard.evaluators = 0`. It serves `/healthz` (the database is reachable) and
//! `/metrics` (the queue depth) for its probes and nothing else. It links neither the REST/gRPC API nor the dataset
//! storage: what it shares with the API replicas is `dsrl-service` (configuration, database, object store).

use std::future::Future;
use std::sync::Arc;

use axum::Router;
use axum::http::header;
use axum::response::IntoResponse;
use dsrl_service::config::Config;
use dsrl_service::error::ApiError;
use dsrl_simulators::SimulatorPool;
use prometheus_client::registry::Registry;

use crate::{Leaderboard, queue, runner};

/// Runs the evaluator until `shutdown`: claims and plays jobs, answers the probes on `listener`. `policy_program`
/// is the binary submitted policies act in (its hidden `play-policy` command; `None`: in this process).
pub async fn run(
    listener: tokio::net::TcpListener,
    config: Config,
    policy_program: Option<std::path::PathBuf>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let store = dsrl_service::open_store(&config)?;
    let catalog = dsrl_service::open_catalog(&config)?;
    let db = dsrl_service::open_db(&config).await?;
    let simulators = Arc::new(SimulatorPool::start(&config.simulators));
    let mut leaderboard_config = config.leaderboard.clone();
    leaderboard_config.evaluators = leaderboard_config.evaluators.max(1);
    let leaderboard = Leaderboard::new(
        db,
        store,
        catalog,
        simulators,
        leaderboard_config,
        dsrl_service::seed_secret(&config)?,
        policy_program,
    )?;
    let mut registry = Registry::with_prefix("dsrl");
    registry.register(
        "evaluator_restarts",
        "Evaluator tasks of this process started again after a panic",
        leaderboard.evaluators.restarts.clone(),
    );
    let leaderboard = Arc::new(leaderboard);
    runner::spawn(leaderboard.clone());
    let queue_depth = Arc::new(queue::register_depth_gauge(&mut registry));
    let registry = Arc::new(registry);
    let probes = Router::new()
        .route(
            "/healthz",
            axum::routing::get({
                let leaderboard = leaderboard.clone();
                move || async move {
                    let (healthy, health) = leaderboard.health().await;
                    let status = if healthy {
                        axum::http::StatusCode::OK
                    } else {
                        axum::http::StatusCode::SERVICE_UNAVAILABLE
                    };
                    (status, axum::Json(health))
                }
            }),
        )
        .route(
            "/metrics",
            axum::routing::get(move || async move {
                queue::refresh_depth_gauge(&queue_depth, &leaderboard.db).await;
                let mut text = String::new();
                prometheus_client::encoding::text::encode(&mut text, &registry).expect("writing to a String");
                ([(header::CONTENT_TYPE, dsrl_service::OPENMETRICS_CONTENT_TYPE)], text)
            }),
        )
        .fallback(|| async {
            ApiError::NotFound("an evaluator serves only /healthz and /metrics".into()).into_response()
        });
    axum::serve(listener, probes).with_graceful_shutdown(shutdown).await?;
    Ok(())
}
