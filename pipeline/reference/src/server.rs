//! The private scoring server a phase starts when no `--server` is given: a `dsrl-server` on the embedded defaults
//! and the committed starters, its state under `<state>/server` (its own held-seed secret, kept between runs), the
//! committed reference results not imported (it scores them), quotas and the evaluation deadline lifted. It is
//! stopped when the phase ends, however it ends: dropped, or with this process (the kernel's parent-death signal).

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use anyhow::Context;
use dsrl_client::api::Client;
use tokio::io::AsyncBufReadExt;
use tokio::process::{Child, ChildStdout, Command};

/// The user the private server's submissions are made as.
pub const USER: &str = "reference-trainer";

/// How long a simulator request may take: a sweep is a batch job at low priority beside other work, where building
/// MetaDrive's scenes for a session has taken past a public server's 120 s; a slow scoring is fine, a failed one
/// costs a rerun. `DSRL_REFERENCE_REQUEST_TIMEOUT_S` overrides it.
const REQUEST_TIMEOUT_S: u64 = 900;
/// Every start of the private server claims again the jobs it left running, and a public server fails a job on its
/// third claim: here a stopped and resumed run is the usual cause, not a job that kills its evaluator.
const MAX_ATTEMPTS: u32 = 10;

pub struct PrivateServer {
    pub url: String,
    /// A user's token on it (kept in `<state>/user-token`).
    pub token: String,
    /// Its admin token (`<state>/server/admin-token`), for hosting the full builds.
    pub admin_token: String,
    _child: Child,
    /// Held open: the server's first line was read from it, and a closed pipe would fail its later writes.
    _stdout: ChildStdout,
}

impl PrivateServer {
    pub async fn start(binary: &Path, state: &Path, repo: &Path, evaluators: u32) -> anyhow::Result<PrivateServer> {
        let data = state.join("server");
        std::fs::create_dir_all(&data)?;
        let log_path = state.join("server.log");
        let log = std::fs::OpenOptions::new().create(true).append(true).open(&log_path)?;
        let timeout = std::env::var("DSRL_REFERENCE_REQUEST_TIMEOUT_S").unwrap_or(REQUEST_TIMEOUT_S.to_string());
        let mut command = Command::new(binary);
        command
            .arg("--listen")
            .arg("127.0.0.1:0")
            .arg("--starter-datasets")
            .arg(repo.join("data/starter"))
            .env("DSRL__SERVER__DATA_DIR", &data)
            // No evaluation deadline to speak of (a day): it scores our own checkpoints at the lowest priority,
            // beside other work that can starve it for minutes, and a slow machine is not the checkpoint's fault.
            .env("DSRL__LEADERBOARD__DEADLINE_FACTOR", "1000")
            .env("DSRL__LEADERBOARD__MAX_EVALUATION_SECONDS", "86400")
            .env("DSRL__LEADERBOARD__IMPORT_REFERENCE_RESULTS", "false")
            .env("DSRL__LEADERBOARD__EVALUATORS", evaluators.to_string())
            .env("DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY", "1000000")
            .env("DSRL__LEADERBOARD__CONCURRENT_SUBMISSIONS", "1000000")
            .env("DSRL__LEADERBOARD__MAX_ATTEMPTS", MAX_ATTEMPTS.to_string())
            .env("DSRL__SIMULATORS__REQUEST_TIMEOUT_S", timeout)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log);
        let mut child = crate::training::spawn_supervised(&mut command)
            .with_context(|| format!("starting {}", binary.display()))?;
        let mut stdout = child.stdout.take().context("the server's stdout")?;
        // "dsrl-server listening on URL", its first line once it listens.
        let mut reader = tokio::io::BufReader::new(&mut stdout);
        let mut line = String::new();
        let read = tokio::time::timeout(Duration::from_secs(600), reader.read_line(&mut line)).await;
        let url = match read {
            Ok(Ok(n)) if n > 0 => line
                .trim()
                .strip_prefix("dsrl-server listening on ")
                .map(str::to_owned)
                .with_context(|| format!("unexpected first line from the scoring server: {line:?}"))?,
            _ => anyhow::bail!("the scoring server did not start; see {}", log_path.display()),
        };
        eprintln!(
            "started a private scoring server on {url} (state in {}, log {})",
            data.display(),
            log_path.display()
        );
        let admin_token = read_token(&data.join("admin-token"))?;
        let token = user_token(&url, state, &admin_token).await?;
        Ok(PrivateServer {
            url,
            token,
            admin_token,
            _child: child,
            _stdout: stdout,
        })
    }
}

fn read_token(path: &Path) -> anyhow::Result<String> {
    Ok(std::fs::read_to_string(path)
        .with_context(|| format!("reading {}", path.display()))?
        .trim()
        .to_owned())
}

/// The user's token: kept from an earlier run, or made now (written under a temporary name first, so a run killed
/// meanwhile leaves no empty token behind).
async fn user_token(url: &str, state: &Path, admin_token: &str) -> anyhow::Result<String> {
    let path: PathBuf = state.join("user-token");
    match read_token(&path) {
        Ok(token) if !token.is_empty() => return Ok(token),
        _ => {}
    }
    let admin = Client::new(url)?.with_token(Some(admin_token.to_owned()));
    let user = admin.create_user(USER).await?;
    let token = user["token"]
        .as_str()
        .context("the server's new user has no token")?
        .to_owned();
    dsrl_pipeline::write_atomically(&path, token.as_bytes())?;
    Ok(token)
}
