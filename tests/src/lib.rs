//! Support for the end-to-end tests: build and locate the real binaries, run a real `dsrl-server` process on a
//! loopback port, run the real `dsrl-client` CLI, make synthetic datasets, and find the pinned Python.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use dsrl_suite::catalog::{Catalog, ObservationSpace};
use dsrl_suite::convert::{Converted, write_canonical};
use dsrl_suite::synthetic::{SyntheticSpec, transitions};

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ is inside the repository")
        .to_path_buf()
}

/// The target folder of the running test binary (`target/<profile>`).
fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("current exe");
    exe.parent()
        .and_then(Path::parent)
        .expect("target/<profile>/deps/<test>")
        .to_path_buf()
}

/// Path of a workspace binary, built (once per test process) in the test's own profile so it is never stale.
pub fn bin(name: &str) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    BUILT.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut cmd = Command::new(cargo);
        cmd.args(["build", "--workspace", "--bins", "--quiet"])
            .current_dir(repo_root());
        if profile_dir().file_name().is_some_and(|n| n == "release") {
            cmd.arg("--release");
        }
        let status = cmd.status().expect("running cargo build");
        assert!(status.success(), "cargo build --workspace --bins failed");
    });
    let path = profile_dir().join(name);
    assert!(path.exists(), "{} is missing after cargo build", path.display());
    path
}

/// The Python of the pinned test environment (`scripts/setup-python.sh` makes it), or `$DSRL_TEST_PYTHON`.
pub fn python() -> PathBuf {
    let path = std::env::var_os("DSRL_TEST_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join(".venv/bin/python"));
    assert!(
        path.exists(),
        "{} not found: run scripts/setup-python.sh (scripts/test.sh does)",
        path.display()
    );
    path
}

/// Runs a script from `tests/python` with the pinned Python; panics with its output if it fails.
pub fn run_python(script: &str, args: &[&str]) -> String {
    let out = Command::new(python())
        .arg(repo_root().join("tests/python").join(script))
        .args(args)
        .output()
        .expect("running python");
    assert!(
        out.status.success(),
        "{script} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8")
}

/// Writes a synthetic dataset for `task` as canonical Parquet.
pub fn make_dataset(task: &str, episodes: usize, seed: u64, out: &Path) -> Converted {
    let catalog = Catalog::embedded().expect("catalog");
    let task = catalog.get(task).expect("task");
    let chunks = transitions(SyntheticSpec::for_task(task, episodes, seed));
    write_canonical(task, ObservationSpace::Simulator, chunks.map(Ok), vec![], out).expect("writing a dataset")
}

/// A `dsrl-server` (or `dsrl-evaluator`) process on a free loopback port, killed when dropped.
pub struct Server {
    program: &'static str,
    child: Child,
    pub url: String,
    pub data_dir: PathBuf,
    args: Vec<String>,
    envs: Vec<(String, String)>,
}

impl Server {
    /// Starts a server with its data under `data_dir`; `args` and `envs` are extra flags and environment.
    pub fn start(data_dir: &Path, args: &[&str], envs: &[(&str, &str)]) -> Server {
        let args: Vec<String> = args.iter().map(|s| s.to_string()).collect();
        let envs: Vec<(String, String)> = envs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        let (child, url) = spawn_server("dsrl-server", data_dir, &args, &envs);
        Server {
            program: "dsrl-server",
            child,
            url,
            data_dir: data_dir.to_owned(),
            args,
            envs,
        }
    }

    /// Starts a `dsrl-evaluator` process (it serves /healthz and /metrics on its port) with the given environment.
    pub fn evaluator(data_dir: &Path, envs: &[(&str, &str)]) -> Server {
        let envs: Vec<(String, String)> = envs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        let (child, url) = spawn_server("dsrl-evaluator", data_dir, &[], &envs);
        Server {
            program: "dsrl-evaluator",
            child,
            url,
            data_dir: data_dir.to_owned(),
            args: Vec::new(),
            envs,
        }
    }

    pub fn token(&self) -> String {
        std::fs::read_to_string(self.data_dir.join("admin-token"))
            .expect("admin token")
            .trim()
            .to_owned()
    }

    /// SIGKILL: the process gets no chance to clean up, as in a crash.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Kills the process and starts a new one on the same data (on a new port).
    pub fn restart(&mut self) {
        self.kill();
        let (child, url) = spawn_server(self.program, &self.data_dir, &self.args, &self.envs);
        self.child = child;
        self.url = url;
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// A CLI bound to this server, with its own cache folder.
    pub fn cli(&self, cache: &Path) -> Cli {
        Cli {
            server: self.url.clone(),
            cache: cache.to_owned(),
            token: Some(self.token()),
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}

fn spawn_server(program: &str, data_dir: &Path, args: &[String], envs: &[(String, String)]) -> (Child, String) {
    let mut cmd = Command::new(bin(program));
    cmd.arg("--listen").arg("127.0.0.1:0").arg("--data-dir").arg(data_dir);
    // Starter datasets are opt-in per test, never picked up from the working directory.
    if program == "dsrl-server" && !args.iter().any(|a| a == "--starter-datasets") {
        cmd.arg("--starter-datasets").arg(data_dir.join("no-starter-datasets"));
    }
    // The server's log goes to a file beside its data folder, for reading when a test fails.
    std::fs::create_dir_all(data_dir).expect("creating the data folder");
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(data_dir.with_extension("log"))
        .expect("opening the server log");
    // No simulator workers unless a test asks for them (tests/e2e/simulators.rs does); `envs` may override.
    cmd.env("DSRL__SIMULATORS__LOCAL_WORKERS", "0");
    // Nor the committed reference results (tests/e2e/reference.rs imports them); `envs` may override.
    if program == "dsrl-server" {
        cmd.env("DSRL__LEADERBOARD__IMPORT_REFERENCE_RESULTS", "false");
    }
    cmd.args(args)
        .envs(envs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .env("DSRL_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(log);
    let mut child = cmd.spawn().unwrap_or_else(|e| panic!("spawning {program}: {e}"));
    let stdout = child.stdout.take().expect("stdout");
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("reading the server's first line");
    // "dsrl-server listening on URL", "dsrl-evaluator listening on URL".
    let url = line
        .trim()
        .strip_prefix(&format!("{program} listening on "))
        .unwrap_or_else(|| panic!("unexpected first line from {program}: {line:?}"))
        .to_owned();
    (child, url)
}

/// The `dsrl-client` CLI with a server, a cache folder and an admin token.
#[derive(Debug, Clone)]
pub struct Cli {
    pub server: String,
    pub cache: PathBuf,
    pub token: Option<String>,
}

/// A finished CLI run.
#[derive(Debug)]
pub struct Run {
    pub code: i32,
    pub stdout: String,
    pub stderr: String,
}

impl From<Output> for Run {
    fn from(out: Output) -> Run {
        Run {
            code: out.status.code().unwrap_or(-1),
            stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
            stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        }
    }
}

impl Run {
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.stdout).unwrap_or_else(|e| panic!("stdout is not JSON ({e}): {self:?}"))
    }
    pub fn ok(self) -> Run {
        assert_eq!(self.code, 0, "dsrl-client failed: {self:?}");
        self
    }
}

impl Cli {
    pub fn command(&self, args: &[&str]) -> Command {
        let mut cmd = Command::new(bin("dsrl-client"));
        cmd.args(args)
            .env("DSRL_SERVER", &self.server)
            .env("DSRL_DATASET_DIR", &self.cache)
            .env_remove("DSRL_ADMIN_TOKEN")
            .env("HOME", self.cache.join("home")); // never read the developer's ~/.dsrl
        if let Some(t) = &self.token {
            cmd.env("DSRL_ADMIN_TOKEN", t);
        }
        cmd
    }

    pub fn run(&self, args: &[&str]) -> Run {
        Run::from(self.command(args).output().expect("running dsrl-client"))
    }
}

/// Polls `condition` every 20 ms until it holds or `timeout` passes.
pub fn wait_for(timeout: Duration, mut condition: impl FnMut() -> bool) -> bool {
    let start = Instant::now();
    while start.elapsed() < timeout {
        if condition() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    false
}
