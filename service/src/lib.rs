//! What every dsrl service process shares: the API replicas (`dsrl-server`), the evaluators (`dsrl-evaluator`,
//! crate `dsrl-leaderboard`) and garbage collection all read one configuration, open the same metadata database
//! and object store, and report failures through one error type.
//!
//! `config` (layered settings), `error` (the error type and its one table to HTTP status and gRPC code), `db`
//! (SQLite or PostgreSQL, with their migrations), `objects` (the local or S3 object store), `secrets` (tokens and
//! secrets generated into the data folder). The functions below open each of them from the configuration, the
//! same way in every process.

pub mod config;
pub mod db;
pub mod error;
pub mod objects;
pub mod secrets;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use dsrl_suite::Catalog;

use crate::config::{Config, Overrides};
use crate::db::Db;

/// The options every service process takes (`dsrl-server`, `dsrl-evaluator`); they override the configuration.
#[derive(Debug, clap::Args)]
pub struct ProcessArgs {
    /// TOML configuration file.
    #[arg(long, env = "DSRL_CONFIG")]
    pub config: Option<PathBuf>,
    /// Address to listen on; port 0 picks a free port.
    #[arg(long)]
    pub listen: Option<SocketAddr>,
    /// Folder for the SQLite database, temporary files and the local object store.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// Task catalog CSV (default: the copy of data/tasks.csv compiled in).
    #[arg(long)]
    pub catalog: Option<PathBuf>,
    /// Log as JSON lines instead of text.
    #[arg(long)]
    pub log_json: bool,
}

impl ProcessArgs {
    /// The configuration: defaults, the file, the environment, then these options (and `starter_dir`).
    pub fn load_config(&self, starter_dir: Option<PathBuf>) -> anyhow::Result<Config> {
        let overrides = Overrides {
            listen: self.listen,
            data_dir: self.data_dir.clone(),
            catalog: self.catalog.clone(),
            starter_dir,
        };
        Ok(Config::load(self.config.as_deref(), &overrides)?)
    }
}

/// The data folder (created when missing) and the object store in it or in S3.
pub fn open_store(config: &Config) -> anyhow::Result<Arc<dyn object_store::ObjectStore>> {
    let data_dir = &config.server.data_dir;
    std::fs::create_dir_all(data_dir).with_context(|| format!("creating {}", data_dir.display()))?;
    objects::build(&config.storage, data_dir).context("opening the object store")
}

/// The local object store's folder, where finished files are renamed into place (`None` with S3).
pub fn local_objects(config: &Config) -> Option<std::path::PathBuf> {
    (config.storage.backend == config::StorageBackend::Local).then(|| config.server.data_dir.join("objects"))
}

/// The secret the held evaluation seeds derive from: configured, or generated once into the data folder.
pub fn seed_secret(config: &Config) -> anyhow::Result<String> {
    match &config.leaderboard.seed_secret {
        Some(secret) => Ok(secret.clone()),
        None => secrets::load_or_generate_secret(
            &config.server.data_dir.join("evaluation-secret"),
            "evaluation seed secret",
        ),
    }
}

pub fn open_catalog(config: &Config) -> anyhow::Result<Arc<Catalog>> {
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
pub async fn open_db(config: &Config) -> anyhow::Result<Db> {
    let db = match &config.database.url {
        None => Db::open(&config.server.data_dir.join("dsrl.sqlite3"))
            .await
            .context("opening the SQLite database")?,
        Some(url) => Db::connect(url, config.database.max_connections)
            .await
            .with_context(|| format!("connecting to the database at {}", config::redact_url(url)))?,
    };
    if db.backend() == db::Backend::Postgres {
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

/// The content type of every role's `/metrics` (Prometheus' OpenMetrics text).
pub const OPENMETRICS_CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// The health answer of every role (an API replica's `/healthz`, an evaluator's): the database answers.
pub async fn database_health(db: &Db) -> Result<&'static str, error::ApiError> {
    db.ping()
        .await
        .map_err(|e| error::ApiError::Unavailable(format!("database: {e}")))?;
    db.probe_write()
        .await
        .map_err(|e| error::ApiError::Unavailable(format!("database: reads answer, writes fail: {e}")))?;
    Ok("ok\n")
}

/// Logs to stderr, as text (coloured on a terminal) or JSON lines; the level comes from `DSRL_LOG`
/// (default `info`, with sqlx's per-query lines off).
pub fn init_logging(json: bool) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("DSRL_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,tower_http=info,sqlx=warn"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr);
    if json {
        builder.json().init();
    } else {
        builder.init();
    }
}

/// Resolves on Ctrl-C or SIGTERM (what Kubernetes sends before it kills a pod): servers stop accepting, finish
/// what is in flight, and return.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = terminate => {},
    }
}
