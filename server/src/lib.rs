//! The dsrl service: REST (axum) and gRPC (tonic) on one port over versioned Parquet datasets in an object store,
//! with metadata in SQLite. `run(listener, config, shutdown)` is the whole server, so tests run it on port 0.
//!
//! Layout: `config` (layered settings), `error` (one error type, one status table), `storage` (object store,
//! SQLite, the dataset service), `http` (REST routes), `grpc` (gRPC service), `starter` (datasets loaded at start),
//! `leaderboard` (submissions, the job queue and its runner). Playing policies on the simulators is
//! `dsrl-evaluation`'s.

pub mod config;
pub mod error;
pub mod grpc;
pub mod http;
pub mod leaderboard;
pub mod metrics;
pub mod starter;
pub mod storage;

use std::future::Future;
use std::sync::Arc;

use anyhow::Context;
use axum::Router;
use dsrl_proto::datasets::v1::dataset_service_server::DatasetServiceServer;
use dsrl_proto::leaderboard::v1::leaderboard_service_server::LeaderboardServiceServer;
use dsrl_suite::Catalog;
use tonic::server::NamedService;
use tower_http::trace::TraceLayer;

use crate::config::Config;
use crate::http::auth::AdminAuth;
use crate::leaderboard::Leaderboard;
use crate::metrics::Metrics;
use crate::storage::converter::Converter;
use crate::storage::datasets::{Datasets, DatasetsSetup};
use crate::storage::db::Db;
use dsrl_evaluation::simulators::SimulatorPool;

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
    let store = open_store(config)?;
    let catalog = open_catalog(config)?;
    let db = open_db(config).await?;
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
        local_objects: local_objects(config),
        tmp_dir: data_dir.join("tmp"),
        default_license: config.datasets.default_license.clone(),
        converter,
        metrics: metrics.clone(),
    })?;
    let auth = AdminAuth::load_or_create(config.auth.admin_token.as_deref(), &data_dir.join("admin-token"))?;
    if let Some(dir) = &config.datasets.starter_dir
        && dir.is_dir()
    {
        let created = starter::load(&datasets, dir).await?;
        tracing::info!(dir = %dir.display(), created, "starter datasets checked");
    }
    metrics.dataset_versions.set(datasets.db().version_count().await?);
    let simulators = Arc::new(SimulatorPool::start(&config.simulators));
    let leaderboard = Arc::new(Leaderboard::new(
        datasets.db().clone(),
        leaderboard_store,
        catalog,
        simulators.clone(),
        config.leaderboard.clone(),
        seed_secret(config)?,
        converter_program,
    ));
    leaderboard::runner::spawn(leaderboard.clone());
    Ok(AppState {
        leaderboard,
        simulators,
        datasets: Arc::new(datasets),
        auth: Arc::new(auth),
        metrics,
        max_upload_bytes: config.datasets.max_upload_bytes,
        dsrl_download_metadrive: config.datasets.dsrl_download_metadrive,
    })
}

/// The data folder (created when missing) and the object store in it or in S3.
fn open_store(config: &Config) -> anyhow::Result<Arc<dyn object_store::ObjectStore>> {
    let data_dir = &config.server.data_dir;
    std::fs::create_dir_all(data_dir).with_context(|| format!("creating {}", data_dir.display()))?;
    storage::objects::build(&config.storage, data_dir).context("opening the object store")
}

/// The local object store's folder, where finished files are renamed into place (`None` with S3).
fn local_objects(config: &Config) -> Option<std::path::PathBuf> {
    (config.storage.backend == config::StorageBackend::Local).then(|| config.server.data_dir.join("objects"))
}

/// The secret the held evaluation seeds derive from: configured, or generated once into the data folder.
fn seed_secret(config: &Config) -> anyhow::Result<String> {
    match &config.leaderboard.seed_secret {
        Some(secret) => Ok(secret.clone()),
        None => http::auth::load_or_generate_secret(
            &config.server.data_dir.join("evaluation-secret"),
            "evaluation seed secret",
        ),
    }
}

fn open_catalog(config: &Config) -> anyhow::Result<Arc<Catalog>> {
    let catalog = match &config.catalog.tasks {
        Some(path) => Catalog::load(path)?,
        None => Catalog::embedded()?,
    };
    tracing::info!(tasks = catalog.tasks().len(), "task catalog loaded");
    Ok(Arc::new(catalog))
}

/// The metadata database: the embedded SQLite file, or the shared one `database.url` names. Processes that share
/// a database must share their secrets too (the admin token, and the seed secret every evaluator derives the held
/// episodes from), so those must be configured rather than generated into one process's data folder.
async fn open_db(config: &Config) -> anyhow::Result<Db> {
    let db = match &config.database.url {
        None => Db::open(&config.server.data_dir.join("dsrl.sqlite3"))
            .await
            .context("opening the SQLite database")?,
        Some(url) => Db::connect(url, config.database.max_connections)
            .await
            .with_context(|| format!("connecting to the database at {}", config::redact_url(url)))?,
    };
    if db.backend() == storage::db::Backend::Postgres {
        anyhow::ensure!(
            config.auth.admin_token.is_some() && config.leaderboard.seed_secret.is_some(),
            "a shared PostgreSQL database needs auth.admin_token and leaderboard.seed_secret set \
             (DSRL__AUTH__ADMIN_TOKEN, DSRL__LEADERBOARD__SEED_SECRET), the same in every replica and evaluator: \
             generated ones would differ from process to process"
        );
    }
    tracing::info!(backend = ?db.backend(), "metadata database open");
    Ok(db)
}

/// The evaluator role (`dsrl-server evaluator`): a process that only claims leaderboard jobs from the shared
/// database and plays them on its simulator workers (`leaderboard.evaluators` at once, at least one), scaled apart
/// from the API replicas, which then run with `leaderboard.evaluators = 0`. It serves `/healthz` (database
/// reachable) and `/metrics` (the queue depth) for its probes and nothing else; it ingests no starter datasets.
/// `policy_program` is the `dsrl-server` binary submitted policies act in (`None`: in this process).
pub async fn run_evaluator(
    listener: tokio::net::TcpListener,
    config: Config,
    policy_program: Option<std::path::PathBuf>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let store = open_store(&config)?;
    let catalog = open_catalog(&config)?;
    let db = open_db(&config).await?;
    let simulators = Arc::new(SimulatorPool::start(&config.simulators));
    let mut leaderboard_config = config.leaderboard.clone();
    leaderboard_config.evaluators = leaderboard_config.evaluators.max(1);
    let leaderboard = Arc::new(Leaderboard::new(
        db,
        store,
        catalog,
        simulators,
        leaderboard_config,
        seed_secret(&config)?,
        policy_program,
    ));
    leaderboard::runner::spawn(leaderboard.clone());
    let metrics = Arc::new(Metrics::new());
    let probes = Router::new()
        .route(
            "/healthz",
            axum::routing::get({
                let leaderboard = leaderboard.clone();
                move || async move { http::database_health(&leaderboard.db).await }
            }),
        )
        .route(
            "/metrics",
            axum::routing::get(move || async move {
                http::metrics::refresh_queue_depth(&metrics, &leaderboard.db).await;
                metrics.render()
            }),
        )
        .fallback(http::not_found);
    axum::serve(listener, probes).with_graceful_shutdown(shutdown).await?;
    Ok(())
}

/// Applies the garbage-collection policy (`gc` in the configuration) to filtered versions: `dsrl-server gc`. Safe
/// while replicas serve the same database and store (see `Datasets::collect_garbage`).
pub async fn run_gc(config: &Config, dry_run: bool) -> anyhow::Result<storage::datasets::GcReport> {
    let store = open_store(config)?;
    let db = open_db(config).await?;
    // Its own temporary folder: a server on the same data folder clears `tmp` at start and owns what is in it.
    let tmp_dir = config.server.data_dir.join(format!("tmp-gc-{}", std::process::id()));
    let datasets = Datasets::new(DatasetsSetup {
        catalog: open_catalog(config)?,
        db,
        store,
        local_objects: local_objects(config),
        tmp_dir: tmp_dir.clone(),
        default_license: config.datasets.default_license.clone(),
        converter: Converter::InProcess,
        metrics: Arc::new(Metrics::new()),
    })?;
    let policy = storage::datasets::GcPolicy {
        max_idle: std::time::Duration::from_secs(config.gc.derived_max_idle_hours.saturating_mul(3600)),
        max_bytes: config.gc.derived_max_bytes,
    };
    let report = datasets.collect_garbage(&policy, dry_run).await;
    let _ = std::fs::remove_dir_all(&tmp_dir);
    Ok(report?)
}

/// REST and gRPC routes with metrics, request tracing, and panics turned into 500s.
pub fn app(state: AppState) -> Router {
    let grpc_service = DatasetServiceServer::new(grpc::DatasetGrpc::new(state.clone()));
    let grpc_path = format!("/{}/{{*method}}", DatasetServiceServer::<grpc::DatasetGrpc>::NAME);
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
    axum::serve(listener, app(state))
        .with_graceful_shutdown(shutdown)
        .await?;
    Ok(())
}
