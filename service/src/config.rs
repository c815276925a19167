//! Server configuration, layered: built-in defaults → TOML file → `DSRL__SECTION__KEY` environment variables →
//! command-line flags. The defaults are the embedded set-up: one SQLite file and a local object store under
//! `~/.dsrl/server`, the catalog compiled from `data/tasks.csv`, starter datasets from `data/starter`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use dsrl_simulators::SimulatorsConfig;
use figment::Figment;
use figment::providers::{Env, Format, Serialized, Toml};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub server: ServerConfig,
    pub catalog: CatalogConfig,
    pub datasets: DatasetsConfig,
    pub auth: AuthConfig,
    pub storage: StorageConfig,
    pub database: DatabaseConfig,
    pub gc: GcConfig,
    pub simulators: SimulatorsConfig,
    pub leaderboard: LeaderboardConfig,
}

/// Submissions and their evaluation (the paper's protocol: the task's three cost thresholds, 20 episodes each).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LeaderboardConfig {
    /// Jobs this server evaluates at once (0: it queues submissions but another server evaluates them).
    pub evaluators: u32,
    /// Episodes per cost threshold.
    pub episodes_per_threshold: u32,
    /// Environments per threshold while scoring: one session each, every environment playing
    /// `episodes_per_threshold / envs_per_session` episodes in turn (creating environments costs more than stepping).
    /// Part of the protocol version: on some tasks an environment's episode depends on the one it played before, so
    /// another layout scores other episodes.
    pub envs_per_session: u32,
    /// An evaluator's claim on a job lapses this long after its last heartbeat; another evaluator then re-runs it.
    pub lease_seconds: u64,
    /// A job claimed this many times without finishing fails.
    pub max_attempts: u32,
    /// Submissions one user may make in 24 hours.
    pub submissions_per_day: u32,
    /// Submissions one user may have queued or running at once.
    pub concurrent_submissions: u32,
    /// Largest accepted submission (all checkpoint files together), in bytes.
    pub max_submission_bytes: u64,
    /// The secret the held episode seeds derive from. Unset: generated once into `<data_dir>/evaluation-secret`.
    pub seed_secret: Option<String>,
    /// Address-space limit of the child process a submitted policy acts in (`dsrl-server play-policy`).
    pub policy_memory_limit_bytes: u64,
    /// Wall-clock budget of one evaluation (all thresholds); past it the submission fails with the reason.
    pub max_evaluation_seconds: u64,
    /// A job may run this many times its task's recent mean scoring time (at least `min_deadline_seconds`, at most
    /// `max_evaluation_seconds`) before it fails with the reason.
    pub deadline_factor: f64,
    pub min_deadline_seconds: u64,
    /// Every request to a submitted policy's process (load, act, observe) may use this many seconds of the
    /// process's CPU time; a process that uses more is stopped and its job fails with the reason (the checkpoint's
    /// fault). One that answers nothing within four times this on the clock while using less (starved by other work,
    /// or stopped) is stopped too, and its job goes back to the queue.
    pub policy_request_seconds: u64,
    /// A submitted policy whose forward pass costs at most this many multiply-adds per environment (its declared
    /// sizes, `Architecture::step_cost`) is scored acting inside the simulator workers (the simulator proto's `Act`
    /// and `Play`): the same episodes as acting in a policy process, with the server in the loop once an episode
    /// instead of once a step. A costlier one acts in a policy process, where its memory is capped and its CPU comes
    /// second to the simulators'; it gains little in the workers, where the forward pass is most of a step. 0: every
    /// policy acts in a policy process (replays always do).
    pub act_in_workers_max_multiply_adds: u64,
    /// The most multiply-adds a submission's scoring may take in all (its network's cost per action × the task's
    /// horizon × episodes per threshold × thresholds), checked before it is queued: a job's worst case is minutes.
    pub max_job_multiply_adds: u64,
    /// Import the committed reference results (`data/reference/results.jsonl`, compiled in) at start-up as the
    /// leaderboard's reference entries. Off on the server that scores them (`dsrl-admin reference`).
    pub import_reference_results: bool,
}

impl Default for LeaderboardConfig {
    fn default() -> Self {
        LeaderboardConfig {
            evaluators: 1,
            episodes_per_threshold: dsrl_evaluation::protocol::DEFAULT_EPISODES_PER_THRESHOLD,
            envs_per_session: dsrl_evaluation::protocol::DEFAULT_ENVS_PER_SESSION,
            lease_seconds: 60,
            max_attempts: 3,
            submissions_per_day: 10,
            concurrent_submissions: 2,
            max_submission_bytes: 3 * (64 << 20),
            seed_secret: None,
            policy_memory_limit_bytes: 4 << 30,
            max_evaluation_seconds: 3600,
            deadline_factor: 4.0,
            min_deadline_seconds: 600,
            policy_request_seconds: 30,
            // OSRL's MLP actors take well under a million; its CDT about 25 million.
            act_in_workers_max_multiply_adds: 10_000_000,
            // OSRL's CDT on a 1000-step task takes 1.5e12 (about 4 minutes on one core); FISOR at its published
            // settings (16 candidates × 5 denoising steps) up to 8.5e12 on MetaDrive (dsrl-leaderboard's
            // `the_default_budget_admits_fisor_at_its_published_settings_on_every_task`).
            max_job_multiply_adds: 10_000_000_000_000,
            import_reference_results: true,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    /// Address for REST and gRPC (one port).
    pub listen: SocketAddr,
    /// SQLite database, temporary files and (for the local backend) the object store live here.
    pub data_dir: PathBuf,
}

/// Where the metadata (versions, tags, derivations, users, the leaderboard's job queue) lives.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatabaseConfig {
    /// Unset: the embedded SQLite file `<data_dir>/dsrl.sqlite3`. `postgres://user:password@host/db`: a PostgreSQL
    /// server, which several replicas (and evaluators) can share. `sqlite://PATH?mode=rwc` names another file.
    pub url: Option<String>,
    /// Connections this process keeps open.
    pub max_connections: u32,
}

impl Default for DatabaseConfig {
    fn default() -> Self {
        DatabaseConfig {
            url: None,
            max_connections: 8,
        }
    }
}

/// Garbage collection of filtered versions (`dsrl-server gc`): they are derived, so removing one costs only its
/// recomputation when it is asked for again.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GcConfig {
    /// A filtered version nobody asked for in this many hours is removed.
    pub derived_max_idle_hours: u64,
    /// All filtered versions together may take this many bytes; past it the least recently used are removed. The
    /// server enforces it while it runs (after every new filtered version, and every `interval_seconds` for idle
    /// ones), never removing a version being downloaded; `dsrl-server gc` applies it from outside.
    pub derived_max_bytes: u64,
    pub interval_seconds: u64,
}

impl Default for GcConfig {
    fn default() -> Self {
        GcConfig {
            derived_max_idle_hours: 30 * 24,
            derived_max_bytes: 100 << 30,
            interval_seconds: 600,
        }
    }
}

/// `url` without its password, for logs and errors.
pub fn redact_url(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(scheme), Some(at)) if at > scheme => {
            let credentials = &url[scheme + 3..at];
            match credentials.find(':') {
                Some(colon) => format!("{}{}:***{}", &url[..scheme + 3], &credentials[..colon], &url[at..]),
                None => url.to_owned(),
            }
        }
        _ => url.to_owned(),
    }
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CatalogConfig {
    /// A tasks CSV in the layout of `data/tasks.csv`; unset means the copy compiled into the binary.
    pub tasks: Option<PathBuf>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetsConfig {
    /// Folder of starter datasets (`<task>/<file>.parquet|.hdf5`) ingested at start-up when missing.
    pub starter_dir: Option<PathBuf>,
    /// Largest accepted upload, in bytes; larger ones get 413.
    pub max_upload_bytes: u64,
    /// License recorded in manifests when an ingest names none.
    pub default_license: String,
    /// Address-space limit of the child process that parses an upload.
    pub converter_memory_limit_bytes: u64,
    /// Serve this server's MetaDrive data (the pinned simulator's 259 observation features) under DSRL's MetaDrive
    /// file names on `/download/{file}`, although DSRL's MetaDrive environments expect the paper's 261. Off: those
    /// names answer 404 with the reason.
    #[serde(default)]
    pub dsrl_download_metadrive: bool,
    /// Derived work (filtered versions, HDF5 exports) computed at once; more wait for a turn.
    pub max_concurrent_derivations: u32,
    /// Derived work waiting for a turn, past which a request that would start more is answered 503 with
    /// `Retry-After`.
    pub max_waiting_derivations: u32,
    /// Derived bytes that requests without a token may create per hour (a filter's cost is counted as its parent's
    /// size when it starts); past it they are answered 429 with `Retry-After`. Admin and user tokens are not limited.
    pub anonymous_derived_bytes_per_hour: u64,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuthConfig {
    /// Bearer token for admin operations. Unset: one is generated into `<data_dir>/admin-token` (mode 0600).
    pub admin_token: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StorageConfig {
    /// `local` (files under `<data_dir>/objects`) or `s3`.
    pub backend: StorageBackend,
    pub s3: S3Config,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StorageBackend {
    Local,
    S3,
}

/// S3 settings; credentials come from the standard `AWS_*` environment variables.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct S3Config {
    pub bucket: String,
    /// Key prefix inside the bucket.
    pub prefix: String,
    pub region: Option<String>,
    /// For S3-compatible services (MinIO, moto, Ceph): their URL.
    pub endpoint: Option<String>,
    /// Allow `http://` endpoints (tests and private networks).
    pub allow_http: bool,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            server: ServerConfig {
                listen: SocketAddr::from(([127, 0, 0, 1], 7070)),
                data_dir: PathBuf::from("~/.dsrl/server"),
            },
            catalog: CatalogConfig::default(),
            datasets: DatasetsConfig {
                starter_dir: Some(PathBuf::from("data/starter")),
                max_upload_bytes: 16 << 30,
                default_license: "CC-BY-4.0".to_owned(),
                converter_memory_limit_bytes: 8 << 30,
                dsrl_download_metadrive: false,
                max_concurrent_derivations: 2,
                max_waiting_derivations: 16,
                anonymous_derived_bytes_per_hour: 20 << 30,
            },
            auth: AuthConfig::default(),
            storage: StorageConfig {
                backend: StorageBackend::Local,
                s3: S3Config::default(),
            },
            database: DatabaseConfig::default(),
            gc: GcConfig::default(),
            simulators: SimulatorsConfig::default(),
            leaderboard: LeaderboardConfig::default(),
        }
    }
}

/// Values given on the command line; `None` leaves the lower layers' value.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Overrides {
    pub listen: Option<SocketAddr>,
    pub data_dir: Option<PathBuf>,
    pub catalog: Option<PathBuf>,
    pub starter_dir: Option<PathBuf>,
}

impl Config {
    /// Defaults → `file` (if given) → `DSRL__…` environment → `overrides`.
    pub fn load(file: Option<&Path>, overrides: &Overrides) -> Result<Config, Box<figment::Error>> {
        let mut figment = Figment::from(Serialized::defaults(Config::default()));
        if let Some(file) = file {
            figment = figment.merge(Toml::file_exact(file));
        }
        figment = figment.merge(Env::prefixed("DSRL__").split("__"));
        let mut flags = serde_json::Map::new();
        let mut set = |section: &str, key: &str, value: serde_json::Value| {
            flags
                .entry(section.to_owned())
                .or_insert_with(|| serde_json::Value::Object(Default::default()))
                .as_object_mut()
                .expect("section")
                .insert(key.to_owned(), value);
        };
        if let Some(v) = &overrides.listen {
            set("server", "listen", v.to_string().into());
        }
        if let Some(v) = &overrides.data_dir {
            set("server", "data_dir", v.display().to_string().into());
        }
        if let Some(v) = &overrides.catalog {
            set("catalog", "tasks", v.display().to_string().into());
        }
        if let Some(v) = &overrides.starter_dir {
            set("datasets", "starter_dir", v.display().to_string().into());
        }
        figment = figment.merge(Serialized::defaults(serde_json::Value::Object(flags)));
        let mut config: Config = figment.extract().map_err(Box::new)?;
        config.server.data_dir = expand_home(&config.server.data_dir);
        Ok(config)
    }
}

/// `~/x` → `$HOME/x`.
pub fn expand_home(path: &Path) -> PathBuf {
    match (path.strip_prefix("~"), std::env::var_os("HOME")) {
        (Ok(rest), Some(home)) => PathBuf::from(home).join(rest),
        _ => path.to_path_buf(),
    }
}

#[cfg(test)]
// figment's `Jail` API fixes the closure's error type.
#[allow(clippy::result_large_err)]
mod tests {
    use super::*;

    #[test]
    fn layers_apply_in_order() {
        figment::Jail::expect_with(|jail| {
            jail.create_file(
                "dsrl.toml",
                r#"
                [server]
                listen = "127.0.0.1:9000"
                data_dir = "/srv/a"
                [datasets]
                max_upload_bytes = 1000
                "#,
            )?;
            jail.set_env("DSRL__SERVER__DATA_DIR", "/srv/b");
            jail.set_env("DSRL__STORAGE__BACKEND", "s3");
            jail.set_env("DSRL__STORAGE__S3__BUCKET", "datasets");
            // A list in one variable, as deploy/k8s/cluster/config.yaml sets it.
            jail.set_env("DSRL__SIMULATORS__WORKER_SERVICES", r#"["dsrl-sim-workers:50051"]"#);
            jail.set_env("DSRL__DATABASE__URL", "postgres://dsrl@db:5432/dsrl");
            let c = Config::load(Some(Path::new("dsrl.toml")), &Overrides::default()).unwrap();
            assert_eq!(c.server.listen.port(), 9000); // file
            assert_eq!(c.server.data_dir, PathBuf::from("/srv/b")); // env beats file
            assert_eq!(c.datasets.max_upload_bytes, 1000);
            assert_eq!(c.storage.backend, StorageBackend::S3);
            assert_eq!(c.storage.s3.bucket, "datasets");
            assert_eq!(c.datasets.default_license, "CC-BY-4.0"); // default
            assert_eq!(c.simulators.worker_services, ["dsrl-sim-workers:50051"]);
            assert_eq!(c.database.url.as_deref(), Some("postgres://dsrl@db:5432/dsrl"));
            let flags = Overrides {
                data_dir: Some("/srv/c".into()),
                ..Default::default()
            };
            let c = Config::load(Some(Path::new("dsrl.toml")), &flags).unwrap();
            assert_eq!(c.server.data_dir, PathBuf::from("/srv/c")); // flag beats env
            Ok(())
        });
    }

    #[test]
    fn unknown_keys_and_bad_values_are_errors() {
        figment::Jail::expect_with(|jail| {
            jail.create_file("bad.toml", "[server]\nlisten_port = 3\n")?;
            let err = Config::load(Some(Path::new("bad.toml")), &Overrides::default()).unwrap_err();
            assert!(err.to_string().contains("listen_port"), "{err}");
            jail.create_file("bad2.toml", "[storage]\nbackend = \"gcs\"\n")?;
            assert!(Config::load(Some(Path::new("bad2.toml")), &Overrides::default()).is_err());
            assert!(Config::load(Some(Path::new("missing.toml")), &Overrides::default()).is_err());
            Ok(())
        });
    }

    #[test]
    fn the_documented_example_is_valid_and_matches_the_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/dsrl.toml");
        figment::Jail::expect_with(|_| {
            let c = Config::load(Some(&path), &Overrides::default()).unwrap();
            let mut defaults = Config::default();
            defaults.server.data_dir = expand_home(&defaults.server.data_dir);
            assert_eq!(c, defaults);
            Ok(())
        });
    }

    #[test]
    fn database_passwords_are_redacted() {
        assert_eq!(
            redact_url("postgres://dsrl:s3cret@db:5432/dsrl"),
            "postgres://dsrl:***@db:5432/dsrl"
        );
        assert_eq!(redact_url("postgres://dsrl@db/dsrl"), "postgres://dsrl@db/dsrl");
        assert_eq!(redact_url("sqlite:///x.db"), "sqlite:///x.db");
    }

    #[test]
    fn home_is_expanded() {
        let home = std::env::var("HOME").unwrap();
        assert_eq!(
            expand_home(Path::new("~/.dsrl/server")),
            PathBuf::from(home).join(".dsrl/server")
        );
        assert_eq!(expand_home(Path::new("/abs")), PathBuf::from("/abs"));
    }
}
