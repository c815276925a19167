//! The dsrl service's API: REST (axum) and gRPC (tonic) on one port over versioned Parquet datasets in an object
//! store, with metadata in SQLite or PostgreSQL. `build_state` + `app` are the whole server, so tests run it on
//! port 0.
//!
//! Layout, by feature, each with its REST routes, gRPC service and pages: `datasets` (the dataset service over the
//! object store and the database, uploads, downloads, DSRL's legacy URLs, the browser, the starters loaded at start),
//! `leaderboard` (over the `dsrl-leaderboard` crate, where submissions, the job queue, the evaluators and the
//! replays live), `simulators` (the pool's status); `http` holds what every route shares (the router, the admin
//! check, the page layout, failures, `/metrics`, the OpenAPI document). Configuration, the error
//! type and the database are `dsrl-service`'s, shared with the evaluator process; playing policies on the
//! simulators is `dsrl-evaluation`'s.

pub mod datasets;
pub mod http;
pub mod leaderboard;
pub mod metrics;
pub mod simulators;

// The configuration and the error type are shared with the evaluators; re-exported at the paths the API uses.
pub use dsrl_service::{config, error};

use std::future::Future;
use std::sync::Arc;

use axum::Router;
use dsrl_proto::datasets::v1::dataset_service_server::DatasetServiceServer;
use dsrl_proto::leaderboard::v1::leaderboard_service_server::LeaderboardServiceServer;
use tonic::server::NamedService;
use tower_http::trace::TraceLayer;

use crate::config::Config;
use crate::datasets::converter::Converter;
use crate::datasets::service::{Datasets, DatasetsSetup};
use crate::http::auth::AdminAuth;
use crate::leaderboard::Leaderboard;
use crate::metrics::Metrics;
use dsrl_simulators::SimulatorPool;

/// What every handler shares.
#[derive(Clone)]
pub struct AppState {
    pub datasets: Arc<Datasets>,
    pub auth: Arc<AdminAuth>,
    pub metrics: Arc<Metrics>,
    pub max_upload_bytes: u64,
    /// Serve the 259-feature MetaDrive data under DSRL's 261-feature file names (`/download/{file}`).
    pub dsrl_download_metadrive: bool,
    pub simulators: Arc<SimulatorPool>,
    pub leaderboard: Arc<Leaderboard>,
}

/// Opens storage, loads the catalog and the starter datasets: everything the server needs before it listens.
/// `converter` says where uploads are parsed (the `dsrl-server` binary uses a child process).
pub async fn build_state(config: &Config, converter: Converter) -> anyhow::Result<AppState> {
    let data_dir = &config.server.data_dir;
    let store = dsrl_service::open_store(config)?;
    let catalog = dsrl_service::open_catalog(config)?;
    let db = dsrl_service::open_db(config).await?;
    let leaderboard_store = store.clone();
    let metrics = Arc::new(Metrics::new());
    // Submitted policies act in child processes of the same binary as uploads are converted in (see `inference`).
    let converter_program = match &converter {
        Converter::Subprocess { program, .. } => Some(program.clone()),
        Converter::InProcess => None,
    };
    let datasets = Datasets::new(DatasetsSetup {
        catalog: catalog.clone(),
        db,
        store,
        local_objects: dsrl_service::local_objects(config),
        tmp_dir: data_dir.join("tmp"),
        default_license: config.datasets.default_license.clone(),
        converter,
        metrics: metrics.clone(),
        limits: derived_limits(config),
    })?;
    let interrupted = datasets::uploads::recover(datasets.db()).await?;
    if interrupted > 0 {
        tracing::warn!(
            interrupted,
            "background uploads were being converted when the server stopped; marked failed"
        );
    }
    let auth = AdminAuth::load_or_create(config.auth.admin_token.as_deref(), &data_dir.join("admin-token"))?;
    if let Some(dir) = &config.datasets.starter_dir
        && dir.is_dir()
    {
        let created = datasets::starter::load(&datasets, dir).await?;
        tracing::info!(dir = %dir.display(), created, "starter datasets checked");
    }
    metrics.dataset_versions.set(datasets.db().version_count().await?);
    let simulators = Arc::new(SimulatorPool::start(&config.simulators));
    let mut leaderboard = Leaderboard::new(
        datasets.db().clone(),
        leaderboard_store,
        catalog,
        simulators.clone(),
        config.leaderboard.clone(),
        dsrl_service::seed_secret(config)?,
        converter_program,
    )?;
    leaderboard.evaluators.restarts = metrics.evaluator_restarts.clone();
    leaderboard.renders.rendered = metrics.replays_rendered.clone();
    leaderboard.renders.failures = metrics.replay_failures.clone();
    leaderboard.renders.restarts = metrics.renderer_restarts.clone();
    let leaderboard = Arc::new(leaderboard);
    leaderboard.import_reference_results().await?;
    leaderboard::runner::spawn(leaderboard.clone());
    leaderboard::renders::spawn(leaderboard.clone());
    let datasets = Arc::new(datasets);
    spawn_derived_gc(datasets.clone(), config.gc.interval_seconds, metrics.clone());
    Ok(AppState {
        leaderboard,
        simulators,
        datasets,
        auth: Arc::new(auth),
        metrics,
        max_upload_bytes: config.datasets.max_upload_bytes,
        dsrl_download_metadrive: config.datasets.dsrl_download_metadrive,
    })
}

/// Applies the derived-data policy every `interval_seconds` while the server runs (idle filtered versions, the size
/// budget), each run in a task of its own: a run that fails or panics is logged and counted
/// (`dsrl_gc_runs_total{outcome="failed"}`), and the next runs on time.
fn spawn_derived_gc(datasets: Arc<Datasets>, interval_seconds: u64, metrics: Arc<Metrics>) {
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(std::time::Duration::from_secs(interval_seconds.max(1)));
        tick.tick().await;
        loop {
            tick.tick().await;
            let this = datasets.clone();
            let run = tokio::spawn(async move {
                let policy = this.limits().gc.clone();
                this.collect_garbage(&policy, false).await
            });
            let outcome = match run.await {
                Ok(Ok(report)) => {
                    if !report.removed.is_empty() {
                        tracing::info!(
                            removed = report.removed.len(),
                            bytes = report.derived_bytes_after,
                            "derived data collected"
                        );
                    }
                    "ok"
                }
                Ok(Err(e)) => {
                    tracing::error!(error = %e, "collecting derived data");
                    "failed"
                }
                Err(e) => {
                    tracing::error!(error = %e, "collecting derived data panicked");
                    "failed"
                }
            };
            metrics.gc_runs.get_or_create(&metrics::OutcomeLabels { outcome }).inc();
        }
    });
}

/// The limits on derived work and data from the configuration (`datasets.*_derivations`, the anonymous budget, and
/// `gc`'s policy, which the server also applies while it runs).
fn derived_limits(config: &Config) -> datasets::service::DerivedLimits {
    datasets::service::DerivedLimits {
        max_concurrent: config.datasets.max_concurrent_derivations,
        max_waiting: config.datasets.max_waiting_derivations,
        anonymous_bytes_per_hour: config.datasets.anonymous_derived_bytes_per_hour,
        gc: datasets::service::GcPolicy {
            max_idle: std::time::Duration::from_secs(config.gc.derived_max_idle_hours.saturating_mul(3600)),
            max_bytes: config.gc.derived_max_bytes,
        },
    }
}

/// Applies the garbage-collection policy (`gc` in the configuration) to filtered versions: `dsrl-server gc`. Safe
/// while replicas serve the same database and store (see `Datasets::collect_garbage`).
pub async fn run_gc(config: &Config, dry_run: bool) -> anyhow::Result<datasets::service::GcReport> {
    let store = dsrl_service::open_store(config)?;
    let db = dsrl_service::open_db(config).await?;
    // Its own temporary folder: a server on the same data folder clears `tmp` at start and owns what is in it.
    let tmp_dir = config.server.data_dir.join(format!("tmp-gc-{}", std::process::id()));
    let datasets = Datasets::new(DatasetsSetup {
        catalog: dsrl_service::open_catalog(config)?,
        db,
        store,
        local_objects: dsrl_service::local_objects(config),
        tmp_dir: tmp_dir.clone(),
        default_license: config.datasets.default_license.clone(),
        converter: Converter::InProcess,
        metrics: Arc::new(Metrics::new()),
        limits: derived_limits(config),
    })?;
    let policy = datasets::service::GcPolicy {
        max_idle: std::time::Duration::from_secs(config.gc.derived_max_idle_hours.saturating_mul(3600)),
        max_bytes: config.gc.derived_max_bytes,
    };
    let report = datasets.collect_garbage(&policy, dry_run).await;
    let _ = std::fs::remove_dir_all(&tmp_dir);
    Ok(report?)
}

/// REST and gRPC routes with metrics, request tracing, and panics turned into 500s.
pub fn app(state: AppState) -> Router {
    let grpc_service = DatasetServiceServer::new(datasets::grpc::DatasetGrpc::new(state.clone()));
    let grpc_path = format!(
        "/{}/{{*method}}",
        DatasetServiceServer::<datasets::grpc::DatasetGrpc>::NAME
    );
    // A submission arrives in one message: allow its size (the files' own limits are checked in the handler).
    let leaderboard_service = LeaderboardServiceServer::new(leaderboard::grpc::LeaderboardGrpc::new(state.clone()))
        .max_decoding_message_size(state.leaderboard.config.max_submission_bytes as usize + (1 << 20));
    let leaderboard_path = format!(
        "/{}/{{*method}}",
        LeaderboardServiceServer::<leaderboard::grpc::LeaderboardGrpc>::NAME
    );
    let routes = http::router(state.clone())
        .route_service(&grpc_path, grpc_service)
        .route_service(&leaderboard_path, leaderboard_service);
    with_layers(routes, state)
}

/// What every route goes through: the JSON 404 fallback, failures in the one error shape and panics turned into
/// counted 500s / INTERNAL (innermost, so the metrics middleware sees and counts the 500), metrics, tracing. Public so that a test can route
/// a deliberately panicking handler through the same layers.
pub fn with_layers(routes: Router, state: AppState) -> Router {
    routes
        .fallback(http::not_found)
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            http::failures::catch,
        ))
        .layer(axum::middleware::from_fn_with_state(state, http::metrics::track))
        .layer(TraceLayer::new_for_http())
}

/// Serves until `shutdown` completes, then finishes the requests in flight. Uploads are converted in-process
/// here (the test binary cannot be re-run as a converter); the `dsrl-server` binary isolates them.
pub async fn run(
    listener: tokio::net::TcpListener,
    config: Config,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let state = build_state(&config, Converter::InProcess).await?;
    serve_until(listener, state, shutdown).await?;
    Ok(())
}

/// Serves `state` on `listener` until `shutdown` completes, then finishes the requests in flight. Requests waiting
/// for a submission to end answer at once then, instead of holding the shutdown for their whole wait.
pub async fn serve_until(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let leaderboard = state.leaderboard.clone();
    axum::serve(listener, app(state))
        .with_graceful_shutdown(async move {
            shutdown.await;
            leaderboard.close_waits();
        })
        .await
}
