//! `dsrl-client`: list the DSRL tasks, fetch verified datasets into the local cache, inspect and verify them.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand, ValueEnum};
use dsrl_client::api::{DEFAULT_SERVER, IngestOptions};
use dsrl_client::error::exit;
use dsrl_client::out;
use dsrl_client::{Cache, Client, ClientError, FetchOptions};
use indicatif::ProgressBar;

const EXIT_CODES: &str = "\
Exit codes:
  0  success
  1  other failure (local I/O, unexpected server answer)
  2  usage error
  3  integrity: a download did not match its sha256, or verify found (and removed) corrupt files
  4  not found: unknown task, version or tag
  5  server unreachable or failing (5xx); an interrupted download is kept and resumes on the next fetch
  6  rejected by the server: invalid (400, 413, 416), a duplicate submission (409), over quota (429)
  7  missing or wrong token (401, 403)
  8  queued, not done yet (watch without --wait): run it again

Environment:
  DSRL_SERVER        server URL (default http://127.0.0.1:7070)
  DSRL_DATASET_DIR   cache root (default ~/.dsrl/datasets)
  DSRL_ADMIN_TOKEN   admin token for `admin` commands
  DSRL_TOKEN         user token for `submit` and `cancel`";

/// Offline safe-RL datasets from a dsrl server: the 38 DSRL tasks, verified and resumable downloads into a
/// local cache laid out so DSRL/OSRL code finds the files.
#[derive(Debug, Parser)]
#[command(version, after_help = EXIT_CODES)]
struct Cli {
    /// Server URL.
    #[arg(long, global = true, env = "DSRL_SERVER", default_value = DEFAULT_SERVER)]
    server: String,
    /// Cache root [default: $DSRL_DATASET_DIR or ~/.dsrl/datasets].
    #[arg(long, global = true)]
    cache_dir: Option<PathBuf>,
    /// Print machine-readable JSON on stdout (errors too, as {"error": ...}).
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// List all tasks with their constants and hosted versions.
    List,
    /// Show a version's manifest: counts, return ranges, spaces, provenance.
    Show {
        task: String,
        /// Version id (sha256) or tag.
        #[arg(long, default_value = "latest")]
        version: String,
        /// Also print the episode index (one line per episode).
        #[arg(long)]
        episodes: bool,
        /// Show the version a DSRL post-process filter makes (repeatable, joined with commas), e.g. noise=0.05.
        #[arg(long = "filter", value_name = "KEY=VALUE")]
        filters: Vec<String>,
        /// Also save the cost-reward return plot (SVG) to this file.
        #[arg(long, value_name = "FILE")]
        plot: Option<PathBuf>,
    },
    /// Download a version into the cache (verified by sha256, resumable) and print its path.
    Fetch {
        task: String,
        /// Version id (sha256) or tag. A version id already in the cache needs no server.
        #[arg(long, default_value = "latest")]
        version: String,
        /// parquet, or hdf5 for DSRL's layout (load it with get_dataset(h5path=...)).
        #[arg(long, value_enum, default_value = "parquet")]
        format: Format,
        /// Cap the download speed, e.g. 500K, 20M (bytes per second).
        #[arg(long, value_parser = parse_rate)]
        limit_rate: Option<u64>,
        /// Fetch the version a DSRL post-process filter makes from it, computed on the server (repeatable, joined
        /// with commas): noise=0.05 (the paper's noise level = outliers_percent), density=0.5, seed=1,
        /// obs_noise=0.1, discard=tempting|low-reward, inpaint=pcmin:pcmax:prmin:prmax, epsilon=E, target_cost=K.
        #[arg(long = "filter", value_name = "KEY=VALUE")]
        filters: Vec<String>,
    },
    /// Re-hash every cached file; report and remove corrupt ones.
    Verify,
    /// Submit a policy to the leaderboard: DIR holds policy.json + policy.safetensors (one checkpoint scored at
    /// each of the task's three cost thresholds), or one subfolder per threshold whose policy.json declares
    /// conditioning {"kind": "per_threshold", "cost_threshold": K}. The server checks it, queues it, and scores
    /// it on the simulators with seeds it never shows: 20 episodes per threshold. Prints the submission id.
    Submit {
        dir: PathBuf,
        #[arg(long)]
        task: String,
        /// The entry's name on the leaderboard (letters, digits, . _ -), e.g. BC-Safe.
        #[arg(long)]
        name: String,
        /// User token [default: $DSRL_TOKEN].
        #[arg(long, env = "DSRL_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// Wait until the submission is scored (or fails) and print the result.
        #[arg(long)]
        wait: bool,
    },
    /// A submission's state (queued, running, finished, failed, cancelled), reason and scores.
    Status {
        id: i64,
        /// Also print every evaluated episode.
        #[arg(long)]
        episodes: bool,
        /// Wait until it is scored, fails or is cancelled.
        #[arg(long)]
        wait: bool,
    },
    /// Watch a scored episode: the server plays it again from its held seed with the submitted policy, draws it
    /// and keeps it (the first request queues the replay; replays wait while submissions are scored). Saves the
    /// animated GIF and prints the replay's returns (the scored episode's) and where its page is.
    Watch {
        /// The submission id.
        id: i64,
        /// One of the task's cost thresholds, as `status --episodes` prints it (e.g. 20).
        #[arg(long)]
        threshold: f64,
        /// The episode's number at that threshold, from 0.
        #[arg(long, default_value_t = 0)]
        episode: u32,
        /// Where to save the GIF [default: submission-ID-threshold-K-episode-E.gif].
        #[arg(long)]
        out: Option<PathBuf>,
        /// Wait until the replay is made (otherwise a queued replay says so and exits 8).
        #[arg(long)]
        wait: bool,
    },
    /// Cancel one of your queued or running submissions.
    Cancel {
        id: i64,
        /// User token [default: $DSRL_TOKEN].
        #[arg(long, env = "DSRL_TOKEN", hide_env_values = true)]
        token: Option<String>,
    },
    /// The leaderboard: each family's entries (interquartile mean across tasks, 95% bootstrap interval) and each
    /// task's table (safe entries by normalized reward, then unsafe ones).
    Leaderboard {
        #[arg(long)]
        task: Option<String>,
    },
    /// Operations that need the admin token.
    Admin(AdminArgs),
}

#[derive(Debug, Args)]
struct AdminArgs {
    /// Admin bearer token [default: $DSRL_ADMIN_TOKEN, else ~/.dsrl/server/admin-token for a loopback server].
    #[arg(long, global = true, env = "DSRL_ADMIN_TOKEN", hide_env_values = true)]
    token: Option<String>,
    #[command(subcommand)]
    command: AdminCommand,
}

#[derive(Debug, Subcommand)]
enum AdminCommand {
    /// Create a leaderboard user and print its bearer token (shown only this once).
    CreateUser { name: String },
    /// Upload a Parquet or DSRL HDF5 file as a new version of TASK (identical data is a no-op).
    Ingest {
        #[arg(long)]
        task: String,
        file: PathBuf,
        /// Named tag to point at the version (repeatable); `latest` moves automatically.
        #[arg(long = "tag")]
        tags: Vec<String>,
        /// `paper` for MetaDrive files in the paper's 261-feature observation space.
        #[arg(long)]
        observation_space: Option<String>,
        #[arg(long)]
        license: Option<String>,
        /// Recipe provenance JSON file (`{"kind": "recipe", ...}`) for data built by a recipe.
        #[arg(long)]
        provenance: Option<PathBuf>,
        /// Leave `latest` where it is (the new version gets only the tags named).
        #[arg(long)]
        keep_latest: bool,
    },
    /// Point TAG of TASK at VERSION.
    Tag {
        #[arg(long)]
        task: String,
        #[arg(long)]
        version: String,
        tag: String,
    },
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Format {
    Parquet,
    Hdf5,
}

fn parse_rate(s: &str) -> Result<u64, String> {
    let s = s.trim();
    let (digits, unit) = match s.char_indices().find(|(_, c)| !c.is_ascii_digit() && *c != '.') {
        Some((i, _)) => s.split_at(i),
        None => (s, ""),
    };
    let value: f64 = digits
        .parse()
        .map_err(|_| format!("invalid rate {s:?}: expected e.g. 500K or 20M"))?;
    let factor = match unit.to_ascii_uppercase().as_str() {
        "" | "B" => 1.0,
        "K" | "KB" => 1024.0,
        "M" | "MB" => 1024.0 * 1024.0,
        "G" | "GB" => 1024.0 * 1024.0 * 1024.0,
        _ => return Err(format!("invalid rate unit {unit:?}: use K, M or G")),
    };
    // A float-to-integer cast saturates: refuse what is not a finite positive number of at most 1 TB/s first.
    if !(value.is_finite() && value > 0.0 && value * factor <= 1e12) {
        return Err(format!(
            "invalid rate {s:?}: expected a positive rate of at most 1T per second"
        ));
    }
    let rate = (value * factor) as u64;
    if rate == 0 {
        return Err("the rate must be positive".into());
    }
    Ok(rate)
}

#[tokio::main]
async fn main() -> ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_env("DSRL_LOG").unwrap_or_else(|_| "warn".into()))
        .with_writer(std::io::stderr)
        .init();
    let json = cli.json;
    match run(cli).await {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            if json {
                out!("{}", e.to_json());
            }
            eprintln!("dsrl-client: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}

fn print_json(value: &impl serde::Serialize) {
    out!("{}", serde_json::to_string_pretty(value).expect("serializable"));
}

async fn run(cli: Cli) -> Result<u8, ClientError> {
    let cache = Cache::new(cli.cache_dir.clone().unwrap_or_else(Cache::default_root));
    let client = Client::new(&cli.server)?;
    match cli.command {
        Command::List => {
            let tasks = client.tasks().await?;
            if cli.json {
                print_json(&tasks);
            } else {
                print_tasks(&tasks);
            }
        }
        Command::Show {
            task,
            version,
            episodes,
            filters,
            plot,
        } => {
            let filter = joined(&filters);
            let (manifest, raw) = client.manifest(&task, &version, filter.as_deref()).await?;
            if let Some(path) = &plot {
                // The plot of the version asked for: with a filter, the parent with the filter's decisions marked.
                let svg = client.plot_svg(&task, &version, filter.as_deref()).await?;
                std::fs::write(path, svg).map_err(ClientError::io(format!("writing {}", path.display())))?;
                if !cli.json {
                    eprintln!("plot saved to {}", path.display());
                }
            }
            if cli.json {
                out!("{raw}");
                return Ok(exit::OK);
            }
            print_manifest(&manifest, episodes);
        }
        Command::Fetch {
            task,
            version,
            format,
            limit_rate,
            filters,
        } => {
            let options = FetchOptions {
                hdf5: matches!(format, Format::Hdf5),
                filter: joined(&filters),
                limit_rate,
                progress: !cli.json,
            };
            let outcome = cache.fetch(&client, &task, &version, &options).await?;
            report_fetch(&outcome, cli.json);
        }
        Command::Verify => {
            let report = tokio::task::spawn_blocking(move || cache.verify(!cli.json))
                .await
                .map_err(|e| ClientError::Protocol(format!("verify task: {e}")))??;
            return Ok(report_verify(&report, cli.json));
        }
        Command::Submit {
            dir,
            task,
            name,
            token,
            wait,
        } => {
            let client = client.with_token(token);
            let submission = client.submit(&dir, &task, &name).await?;
            let id = submission["id"].as_i64().unwrap_or_default();
            if wait {
                let done = wait_for_submission(&client, id, cli.json).await?;
                return Ok(report_submission(&done, cli.json, false));
            }
            if cli.json {
                print_json(&submission);
            } else {
                eprintln!("submission {id} queued; follow it with `dsrl-client status {id} --wait`");
                out!("{id}");
            }
        }
        Command::Status { id, episodes, wait } => {
            let submission = if wait {
                wait_for_submission(&client, id, cli.json).await?
            } else {
                client.submission(id).await?
            };
            return Ok(report_submission(&submission, cli.json, episodes));
        }
        Command::Watch {
            id,
            threshold,
            episode,
            out,
            wait,
        } => return watch_episode(&client, cli.json, (id, threshold, episode), out, wait).await,
        Command::Cancel { id, token } => {
            let submission = client.with_token(token).cancel(id).await?;
            return Ok(report_submission(&submission, cli.json, false));
        }
        Command::Leaderboard { task } => {
            let board = client.leaderboard(task.as_deref()).await?;
            if cli.json {
                print_json(&board);
            } else {
                print_board(&board);
            }
        }
        Command::Admin(admin) => return run_admin(client, &cli.server, cli.json, admin).await,
    }
    Ok(exit::OK)
}

/// `fetch`'s answer: the path on standard output, how it got there on standard error (or all of it as JSON).
fn report_fetch(outcome: &dsrl_client::cache::FetchOutcome, json: bool) {
    if json {
        print_json(outcome);
        return;
    }
    let mut how = if outcome.downloaded_bytes == 0 && outcome.resumed_from.is_none() {
        "cache hit".to_owned()
    } else if let Some(offset) = outcome.resumed_from {
        format!(
            "resumed at byte {offset}, {} bytes downloaded",
            outcome.downloaded_bytes
        )
    } else {
        format!("{} bytes downloaded", outcome.downloaded_bytes)
    };
    if outcome.converted {
        how.push_str(", converted to DSRL HDF5");
    }
    how.push_str(&format!(", {:.2} s", outcome.seconds));
    eprintln!(
        "{} {} verified ({how})",
        outcome.task,
        dsrl_suite::ids::short_hex(&outcome.version)
    );
    out!("{}", outcome.path.display());
}

/// `verify`'s answer; the exit code is INTEGRITY when a file was corrupt or missing.
fn report_verify(report: &dsrl_client::cache::VerifyReport, json: bool) -> u8 {
    if json {
        print_json(report);
    } else {
        for f in &report.files {
            if f.status != "ok" {
                out!("{} {} (removed)", f.status.to_uppercase(), f.path.display());
            }
        }
        for p in &report.partial {
            out!("PARTIAL {} (kept; the next fetch resumes it)", p.display());
        }
        out!(
            "{} files checked, {} corrupt or missing, {} partial, {} bytes hashed",
            report.files.len(),
            report.corrupt(),
            report.partial.len(),
            report.bytes_hashed
        );
    }
    if report.corrupt() > 0 {
        exit::INTEGRITY
    } else {
        exit::OK
    }
}

/// `list`'s table: one line per task with its constants and its `latest` version.
fn print_tasks(tasks: &[dsrl_client::api::TaskEntry]) {
    out!(
        "{:<40} {:<13} {:>5} {:>4} {:>3} {:>21} {:>10} {:<9} latest",
        "TASK",
        "FAMILY",
        "STEPS",
        "OBS",
        "ACT",
        "REWARD RANGE",
        "COST MAX",
        "THRESH."
    );
    for t in tasks {
        let k = &t.task;
        let thresholds: Vec<String> = k.cost_thresholds.iter().map(|c| format!("{c}")).collect();
        let latest = t
            .versions
            .iter()
            .find(|v| v.tags.iter().any(|tag| tag == "latest"))
            .map(|v| format!("{} ({} episodes)", dsrl_suite::ids::short_hex(&v.version), v.episodes))
            .unwrap_or_else(|| "-".into());
        out!(
            "{:<40} {:<13} {:>5} {:>4} {:>3} {:>10.2}..{:<9.2} {:>10.2} {:<9} {latest}",
            k.id.as_str(),
            k.family.as_str(),
            k.max_episode_steps,
            k.obs_dim,
            k.act_dim,
            k.min_episode_reward,
            k.max_episode_reward,
            k.max_episode_cost,
            thresholds.join("/")
        );
    }
    let hosted = tasks.iter().filter(|t| !t.versions.is_empty()).count();
    out!("{} tasks, {hosted} with hosted versions", tasks.len());
}

/// `show`'s text: the manifest's fields, how the version is hosted, and with `episodes` its episode index.
fn print_manifest(m: &dsrl_suite::manifest::Manifest, episodes: bool) {
    out!("task              {}", m.task);
    out!("version           {}", m.version);
    out!(
        "file              {} ({} bytes, {})",
        m.file_name,
        m.byte_size,
        m.format
    );
    out!("episodes          {}", m.episodes);
    out!("transitions       {}", m.transitions);
    out!(
        "observations      {} features ({} space)",
        m.observation_space.dim,
        m.observation_space.kind.as_str()
    );
    out!("actions           {} features", m.action_space.dim);
    out!("reward return     {} .. {}", m.reward_return.min, m.reward_return.max);
    out!("cost return       {} .. {}", m.cost_return.min, m.cost_return.max);
    out!("license           {}", m.license);
    out!("created           {}", m.created_at);
    out!(
        "provenance        {}",
        serde_json::to_string(&m.provenance).expect("serializable")
    );
    if let Some(h) = &m.hosting {
        out!(
            "hosted as         {} ({} of the paper's {} trajectories)",
            h.kind,
            h.trajectories,
            h.paper_trajectories
        );
        if let Some(notice) = &h.notice {
            out!("notice            {notice}");
        }
    }
    if episodes {
        out!(
            "\n{:>8} {:>10} {:>7} {:>14} {:>12}",
            "EPISODE",
            "START",
            "LENGTH",
            "REWARD RETURN",
            "COST RETURN"
        );
        for (i, e) in m.episode_index.iter().enumerate() {
            out!(
                "{i:>8} {:>10} {:>7} {:>14} {:>12}",
                e.start,
                e.length,
                e.reward_return,
                e.cost_return
            );
        }
    }
}

/// `admin ...`: the commands that need the server's admin token.
async fn run_admin(client: Client, server: &str, json: bool, admin: AdminArgs) -> Result<u8, ClientError> {
    let token = admin.token.or_else(|| local_admin_token(server));
    let client = client.with_token(token);
    match admin.command {
        AdminCommand::Ingest {
            task,
            file,
            tags,
            observation_space,
            license,
            provenance,
            keep_latest,
        } => {
            let provenance_json = match provenance {
                Some(p) => {
                    Some(std::fs::read_to_string(&p).map_err(ClientError::io(format!("reading {}", p.display())))?)
                }
                None => None,
            };
            let size = std::fs::metadata(&file).map(|m| m.len()).unwrap_or(0);
            let bar = Client::upload_bar(size, !json);
            let b = bar.clone();
            let options = IngestOptions {
                tags,
                observation_space,
                license,
                provenance_json: provenance_json.map(|p| p.trim().replace('\n', " ")),
                keep_latest,
            };
            let result = client.ingest(&task, &file, &options, move |n| b.set_position(n)).await;
            bar.finish_and_clear();
            let result = result?;
            if json {
                print_json(&result);
            } else {
                let what = if result.created {
                    "created"
                } else {
                    "unchanged (identical data already hosted)"
                };
                out!(
                    "{} {} {what}: {} episodes, {} transitions, tags [{}]",
                    result.task,
                    result.version.version,
                    result.version.episodes,
                    result.version.transitions,
                    result.version.tags.join(", ")
                );
            }
        }
        AdminCommand::CreateUser { name } => {
            let user = client.create_user(&name).await?;
            if json {
                print_json(&user);
            } else {
                eprintln!("created user {name}; its token (shown only now):");
                out!("{}", user["token"].as_str().unwrap_or_default());
            }
        }
        AdminCommand::Tag { task, version, tag } => {
            let v = client.tag(&task, &tag, &version).await?;
            if json {
                print_json(&v);
            } else {
                out!("{task} {tag} -> {} (tags [{}])", v.version, v.tags.join(", "));
            }
        }
    }
    Ok(exit::OK)
}

const ENDED: [&str; 3] = ["finished", "failed", "cancelled"];

/// Polls a submission until it ends, with a spinner showing its state.
/// `watch`: the replay of one scored episode, waited for with `wait`, its GIF saved to `out`.
async fn watch_episode(
    client: &Client,
    json: bool,
    (id, threshold, episode): (i64, f64, u32),
    out: Option<PathBuf>,
    wait: bool,
) -> Result<u8, ClientError> {
    let spinner = if json || !wait {
        ProgressBar::hidden()
    } else {
        ProgressBar::new_spinner()
    };
    let replay = loop {
        match client.episode_replay(id, threshold, episode).await? {
            Some(replay) => break replay,
            None if wait => {
                spinner.set_message(format!("episode {episode} at threshold {threshold}: replay queued"));
                spinner.tick();
                tokio::time::sleep(std::time::Duration::from_secs(2)).await;
            }
            None => {
                if json {
                    print_json(&serde_json::json!({"state": "queued"}));
                } else {
                    out!("the replay is queued (it waits while submissions are scored); run again, or add --wait");
                }
                return Ok(exit::PENDING);
            }
        }
    };
    spinner.finish_and_clear();
    let gif = client.episode_replay_gif(id, threshold, episode).await?;
    let path =
        out.unwrap_or_else(|| PathBuf::from(format!("submission-{id}-threshold-{threshold}-episode-{episode}.gif")));
    std::fs::write(&path, &gif).map_err(ClientError::io(format!("writing {}", path.display())))?;
    if json {
        let mut replay = replay;
        replay["gif_path"] = serde_json::json!(path.display().to_string());
        print_json(&replay);
    } else {
        out!(
            "{} episode {episode} at cost threshold {threshold}: reward return {}, cost return {}, {} steps; \
             {} frames saved to {} (page: /submissions/{id}/episodes/{threshold}/{episode})",
            replay["task"].as_str().unwrap_or_default(),
            number(&replay["reward_return"]),
            number(&replay["cost_return"]),
            replay["length"],
            replay["frame_steps"].as_array().map_or(0, |f| f.len() + 1),
            path.display()
        );
    }
    Ok(exit::OK)
}

/// Waits for the submission to end: each request asks the server to answer when it ends or after a few seconds
/// (then the spinner shows its progress and the next request waits again).
async fn wait_for_submission(client: &Client, id: i64, quiet: bool) -> Result<serde_json::Value, ClientError> {
    let spinner = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new_spinner()
    };
    let mut submission = client.submission(id).await?;
    loop {
        let state = submission["state"].as_str().unwrap_or_default().to_owned();
        if ENDED.contains(&state.as_str()) {
            spinner.finish_and_clear();
            return Ok(submission);
        }
        spinner.set_message(format!("submission {id}: {state} (attempt {})", submission["attempts"]));
        spinner.tick();
        submission = client.submission_when_ended(id, WAIT_SECONDS).await?;
    }
}

/// How long one `--wait` request lets the server hold it (the spinner's update period).
const WAIT_SECONDS: u32 = 5;

fn number(value: &serde_json::Value) -> String {
    value.as_f64().map_or_else(|| "–".to_owned(), |x| format!("{x:.3}"))
}

/// Prints a submission; the exit code is FAILURE for a failed one.
fn report_submission(s: &serde_json::Value, json: bool, episodes: bool) -> u8 {
    let state = s["state"].as_str().unwrap_or_default();
    if json {
        print_json(s);
    } else {
        out!(
            "submission {}: {} {:?} by {}: {state} (attempts {})",
            s["id"],
            s["task"].as_str().unwrap_or_default(),
            s["name"].as_str().unwrap_or_default(),
            s["user"].as_str().unwrap_or_default(),
            s["attempts"]
        );
        if let Some(reason) = s["reason"].as_str() {
            out!("  reason: {reason}");
        }
        let q = &s["queue"];
        if q.is_object() {
            out!(
                "  queue position {} ({} jobs ahead, {} being scored); estimated start {}, finish {}",
                q["position"],
                q["jobs_ahead"].as_array().map_or(0, Vec::len),
                q["running"],
                q["estimated_start"].as_str().unwrap_or("unknown"),
                q["estimated_finish"].as_str().unwrap_or("unknown")
            );
            if let Some(why) = q["estimate_unknown"].as_str() {
                out!("  (estimates unknown: {why})");
            }
        }
        let p = &s["progress"];
        if p.is_object() {
            out!(
                "  scoring: {} of {} episodes done, evaluator {}, last heartbeat {}",
                p["episodes_done"],
                p["episodes_total"],
                p["evaluator"].as_str().unwrap_or("?"),
                p["last_heartbeat"].as_str().unwrap_or("?")
            );
            if p["heartbeat_stale"] == true {
                out!("  the evaluator's heartbeat is stale: it has probably stopped; the job returns to the queue");
            }
        }
        if let Some(n) = s["author_submissions_to_task"].as_u64() {
            out!("  {n} submission(s) by this user to this task");
        }
        if state == "finished" {
            out!(
                "  normalized reward {}, normalized cost {} ({})",
                number(&s["normalized_reward"]),
                number(&s["normalized_cost"]),
                if s["safe"] == true { "safe" } else { "unsafe" }
            );
        }
        for t in s["thresholds"].as_array().into_iter().flatten() {
            out!(
                "  threshold {}: {} episodes, mean reward return {}, mean cost return {}, normalized reward {}, \
                 normalized cost {}",
                t["cost_threshold"],
                t["episodes"],
                number(&t["mean_reward_return"]),
                number(&t["mean_cost_return"]),
                number(&t["normalized_reward"]),
                number(&t["normalized_cost"])
            );
        }
        if episodes {
            for e in s["episodes"].as_array().into_iter().flatten() {
                out!(
                    "    threshold {} episode {}: reward {}, cost {}, length {}",
                    e["cost_threshold"],
                    e["episode"],
                    number(&e["reward_return"]),
                    number(&e["cost_return"]),
                    e["length"]
                );
            }
        }
    }
    if state == "failed" { exit::FAILURE } else { exit::OK }
}

fn print_board(board: &serde_json::Value) {
    for family in board["families"].as_array().into_iter().flatten() {
        out!(
            "{} (interquartile mean across tasks, 95% bootstrap interval)",
            family["family"].as_str().unwrap_or_default()
        );
        let ranked = family["entries"].as_array().into_iter().flatten();
        let partial = family["partial"].as_array().into_iter().flatten();
        for e in ranked.chain(partial) {
            let (r, c) = (&e["normalized_reward"], &e["normalized_cost"]);
            let rank = e["rank"]
                .as_u64()
                .map_or_else(|| "  –".to_owned(), |r| format!("{r:>3}"));
            out!(
                "  {}. {} ({}): reward {} [{}, {}], cost {} [{}, {}], safe on {} of {} tasks",
                rank,
                e["name"].as_str().unwrap_or_default(),
                e["user"].as_str().unwrap_or_default(),
                number(&r["estimate"]),
                number(&r["low"]),
                number(&r["high"]),
                number(&c["estimate"]),
                number(&c["low"]),
                number(&c["high"]),
                e["safe_tasks"],
                e["tasks"]
            );
        }
    }
    for table in board["tasks"].as_array().into_iter().flatten() {
        out!("{}", table["task"].as_str().unwrap_or_default());
        let entries = table["entries"].as_array().cloned().unwrap_or_default();
        if entries.is_empty() {
            out!("  no scored entries yet");
        }
        for e in entries {
            out!(
                "  {:>3}. {} ({}): normalized reward {}, normalized cost {}{} [submission {}]",
                e["rank"],
                e["name"].as_str().unwrap_or_default(),
                e["user"].as_str().unwrap_or_default(),
                number(&e["normalized_reward"]),
                number(&e["normalized_cost"]),
                if e["safe"] == true { "" } else { " UNSAFE" },
                e["submission"]
            );
        }
    }
}

/// Repeated `--filter` values as one filter string.
fn joined(filters: &[String]) -> Option<String> {
    (!filters.is_empty()).then(|| filters.join(","))
}

/// For a server on loopback, the token a local `dsrl-server` with default settings generated.
fn local_admin_token(server: &str) -> Option<String> {
    let host = server.split("://").nth(1)?.split(['/', ':']).next()?;
    if !matches!(host, "127.0.0.1" | "localhost" | "[") {
        return None;
    }
    let home = std::env::var_os("HOME")?;
    let token = std::fs::read_to_string(PathBuf::from(home).join(".dsrl/server/admin-token")).ok()?;
    Some(token.trim().to_owned()).filter(|t| !t.is_empty())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates() {
        assert_eq!(parse_rate("500").unwrap(), 500);
        assert_eq!(parse_rate("2K").unwrap(), 2048);
        assert_eq!(parse_rate("1.5M").unwrap(), 1_572_864);
        assert!(parse_rate("0").is_err());
        assert!(parse_rate("5X").is_err());
        assert!(parse_rate("fast").is_err());
    }

    #[test]
    fn cli_parses() {
        Cli::command_for_test();
    }

    impl Cli {
        fn command_for_test() {
            use clap::CommandFactory;
            Cli::command().debug_assert();
        }
    }
}
