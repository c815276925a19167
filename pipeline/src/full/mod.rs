//! `dsrl-admin build`: the full builds, every task's dataset at the paper's size, as `data/full_builds.toml` plans
//! them, each checked against its committed identity (`data/full/<task>.json`).
//!
//! Each task is built in a child process of its own (`dsrl-admin build-task`, hidden), in a state folder of its
//! own under the root (`~/.dsrl/full/<task>`): a recipe run that resumes where it stopped after a kill at any
//! point (`crate::build::Run`), with its compute counted over its process tree (`compute.rs`). The parent runs
//! `--jobs` of them at once, draws a progress bar per task from what the children report, compares each result
//! with the committed record (`record.rs`), and, as asked, writes the records (`--record`) and uploads the builds
//! to a server (`--server`), tagged `full` and made `latest`.

pub mod compute;
pub mod plan;
pub mod record;
pub mod table;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use dsrl_client::api::{Client, IngestOptions};
use dsrl_simulators::SimulatorsConfig;
use dsrl_suite::Catalog;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use tokio::io::AsyncBufReadExt;

use self::plan::Plan;
use self::record::{BuildRecord, EpisodeLine, Estimate};
use crate::build::Run;

/// The tag a server gives an uploaded full build (besides `latest`).
pub const FULL_TAG: &str = dsrl_suite::TagName::FULL;

/// What the parent asks of one `dsrl-admin build`.
#[derive(Debug, Clone)]
pub struct BuildOptions {
    pub plan: PathBuf,
    pub recipes: PathBuf,
    pub records: PathBuf,
    pub root: PathBuf,
    pub tasks: Vec<String>,
    pub jobs: usize,
    pub workers: u32,
    /// How many times a task whose child fails is started again (it resumes from its state folder).
    pub retries: u32,
    pub record: bool,
    pub server: Option<String>,
    pub token: Option<String>,
    pub progress: bool,
}

/// How one task's build ended.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    pub task: String,
    pub version: Option<String>,
    pub trajectories: Option<u64>,
    /// `matches`, `differs` (a failure), `no committed record`, or `failed`.
    pub check: String,
    /// What differs from the committed record, or why the build failed.
    pub details: Vec<String>,
    /// The record was written into the records folder (`--record`).
    pub recorded: bool,
    /// The server's manifest URL of the upload (`--server`).
    pub uploaded: Option<String>,
    /// Why each earlier run of the task's build stopped, where it had to be started again (`--retries`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub retried_after: Vec<String>,
}

impl Outcome {
    pub fn ok(&self) -> bool {
        self.check == "matches" || self.check == "no committed record"
    }
}

/// A line a child writes on its standard output.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum ChildReport {
    Progress { position: u64, length: u64, unit: String },
    Finished { version: String },
}

/// `<state>/record.json` and `<state>/record.episodes.csv`: what a finished build in `state` produced.
fn state_record(state: &Path, task: &str) -> anyhow::Result<Option<(BuildRecord, Vec<EpisodeLine>)>> {
    let dir = state.join("record");
    record::read(&dir, task)
}

/// Whether the build in state folder `state` has finished (its record is written last).
pub fn finished(state: &Path, task: &str) -> anyhow::Result<bool> {
    Ok(state_record(state, task)?.is_some())
}

/// Runs the builds: every task in order, `jobs` at a time, a warm start's source finished before the task that
/// starts from it. Returns each task's outcome; a failed task does not stop the others.
pub async fn build(options: &BuildOptions) -> anyhow::Result<Vec<Outcome>> {
    let plan = Plan::load(&options.plan)?;
    let order = plan.order(&options.tasks, &options.recipes)?;
    // Every recipe is checked before anything starts: a typo fails now, not hours in.
    let catalog = Catalog::embedded()?;
    let mut sources = std::collections::HashMap::new();
    for task in &order {
        let recipe = plan.recipe(task, &options.recipes)?;
        recipe.validate(&catalog)?;
        if let Some(source) = recipe.expert.as_ref().and_then(|e| e.warm_start.as_ref()) {
            sources.insert(task.clone(), source.task.clone());
        }
    }
    let client = match &options.server {
        Some(server) => {
            let client = Client::new(server)?.with_token(options.token.clone());
            let info = client.server_info().await?;
            anyhow::ensure!(
                info.admin,
                "{server}: uploading needs its admin token (--token or DSRL_ADMIN_TOKEN)"
            );
            Some(client)
        }
        None => None,
    };
    std::fs::create_dir_all(options.root.join("logs"))?;
    let multi = if options.progress {
        MultiProgress::new()
    } else {
        MultiProgress::with_draw_target(indicatif::ProgressDrawTarget::hidden())
    };
    let mut outcomes: Vec<Outcome> = Vec::new();
    let mut waiting: Vec<String> = order.clone();
    let mut running = tokio::task::JoinSet::new();
    let jobs = options.jobs.max(1);
    loop {
        // Start what may start: a free slot, and a warm start's source finished (or failed: then this fails too).
        let mut i = 0;
        while running.len() < jobs && i < waiting.len() {
            let task = waiting[i].clone();
            if let Some(source) = sources.get(&task) {
                match outcomes.iter().find(|o| &o.task == source) {
                    // The source is waiting or being built (the order puts it first).
                    None => {
                        i += 1;
                        continue;
                    }
                    Some(o) if !o.ok() => {
                        waiting.remove(i);
                        outcomes.push(Outcome {
                            task,
                            version: None,
                            trajectories: None,
                            check: "failed".into(),
                            details: vec![format!("its warm start's source, {source}, did not build")],
                            recorded: false,
                            uploaded: None,
                            retried_after: Vec::new(),
                        });
                        continue;
                    }
                    Some(_) => {}
                }
            }
            waiting.remove(i);
            let bar = multi.add(ProgressBar::new(0));
            bar.set_style(
                ProgressStyle::with_template("{msg:40} [{elapsed_precise}] {wide_bar} {pos}/{len} (eta {eta})")
                    .expect("template"),
            );
            bar.set_message(task.clone());
            let options = options.clone();
            running.spawn(async move {
                let mut retried_after = Vec::new();
                let result = loop {
                    match run_child(&options, &task, &bar).await {
                        Err(e) if retried_after.len() < options.retries as usize => {
                            // A transient stop (a worker that died or timed out, a suspended machine) costs only
                            // what the child did since its last save: the next run resumes from there.
                            let why = format!("{e:#}");
                            bar.suspend(
                                || tracing::warn!(task = %task, error = %why, "the build stopped; starting it again"),
                            );
                            retried_after.push(why);
                            tokio::time::sleep(RETRY_PAUSE).await;
                        }
                        other => break other,
                    }
                };
                bar.finish();
                (task, result, retried_after)
            });
        }
        let Some(done) = running.join_next().await else {
            break;
        };
        let (task, result, retried_after) = done?;
        let mut outcome = match result {
            Ok(()) => settle(options, &task, client.as_ref()).await,
            Err(e) => Err(e),
        }
        .unwrap_or_else(|e| Outcome {
            task: task.clone(),
            version: None,
            trajectories: None,
            check: "failed".into(),
            details: vec![format!("{e:#}")],
            recorded: false,
            uploaded: None,
            retried_after: Vec::new(),
        });
        outcome.retried_after = retried_after;
        multi.suspend(|| eprintln!("{}", describe(&outcome)));
        outcomes.push(outcome);
    }
    Ok(outcomes)
}

/// One line for a person.
pub fn describe(outcome: &Outcome) -> String {
    let mut line = format!(
        "{}: {}{}",
        outcome.task,
        outcome.check,
        outcome
            .version
            .as_deref()
            .map(|v| format!(" (version {v}, {} trajectories)", outcome.trajectories.unwrap_or(0)))
            .unwrap_or_default()
    );
    for detail in &outcome.details {
        line.push_str("\n  ");
        line.push_str(detail);
    }
    for (i, why) in outcome.retried_after.iter().enumerate() {
        line.push_str(&format!(
            "\n  run {} stopped and the build was started again: {why}",
            i + 1
        ));
    }
    if outcome.recorded {
        line.push_str("\n  record written");
    }
    if let Some(url) = &outcome.uploaded {
        line.push_str(&format!("\n  uploaded: {url}"));
    }
    line
}

/// The binary this process runs, for its children: on Linux `/proc/self/exe`, which still names it after a rebuild
/// replaced the file (the path `current_exe` gives then names nothing, and every later task failed to start with
/// "No such file or directory"); a child so started runs the parent's own code.
fn own_binary() -> std::io::Result<std::path::PathBuf> {
    let running = std::path::Path::new("/proc/self/exe");
    if running.exists() {
        Ok(running.to_path_buf())
    } else {
        std::env::current_exe()
    }
}

/// How long a failed task's build waits before it is started again (a worker's port and processes go first).
const RETRY_PAUSE: Duration = Duration::from_secs(5);

/// How often a build whose bar is hidden prints a line of its progress instead.
const PLAIN_PROGRESS_EVERY: Duration = Duration::from_secs(300);

/// Runs `dsrl-admin build-task` for `task` and follows its reports on `bar`; its log goes to `<root>/logs/`.
async fn run_child(options: &BuildOptions, task: &str, bar: &ProgressBar) -> anyhow::Result<()> {
    let log_path = options.root.join("logs").join(format!("{task}.log"));
    let log = std::fs::OpenOptions::new().create(true).append(true).open(&log_path)?;
    let mut command = tokio::process::Command::new(own_binary()?);
    command
        .arg("build-task")
        .arg("--task")
        .arg(task)
        .arg("--plan")
        .arg(&options.plan)
        .arg("--recipes")
        .arg(&options.recipes)
        .arg("--state")
        .arg(options.root.join(task))
        .arg("--workers")
        .arg(options.workers.to_string())
        .env("DSRL_LOG", std::env::var("DSRL_LOG").unwrap_or_else(|_| "info".into()))
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(log)
        .kill_on_drop(true);
    // The build dies with this process, however it ends (a SIGKILL runs no destructor): an orphan would go on
    // writing the state folder that the next run resumes.
    // SAFETY: prctl is async-signal-safe and touches nothing of the parent.
    unsafe {
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = command.spawn()?;
    let stdout = child.stdout.take().expect("piped");
    let mut lines = tokio::io::BufReader::new(stdout).lines();
    // Where no bar is drawn (a log file, --json), a plain line now and then says how far the build is.
    let mut said = std::time::Instant::now();
    while let Some(line) = lines.next_line().await? {
        match serde_json::from_str::<ChildReport>(&line) {
            Ok(ChildReport::Progress { position, length, unit }) => {
                bar.set_length(length);
                bar.set_position(position);
                bar.set_message(format!("{task} ({unit})"));
                if bar.is_hidden() && said.elapsed() >= PLAIN_PROGRESS_EVERY && length > 0 {
                    said = std::time::Instant::now();
                    eprintln!(
                        "{} {task}: {position} of {length} {unit} ({:.0}%)",
                        now_rfc3339(),
                        100.0 * position as f64 / length as f64
                    );
                }
            }
            Ok(ChildReport::Finished { .. }) => {}
            Err(_) => tracing::debug!(task, line, "unexpected line from a build"),
        }
    }
    let status = child.wait().await?;
    if !status.success() {
        let text = std::fs::read_to_string(&log_path).unwrap_or_default();
        let tail: Vec<&str> = text.lines().rev().take(5).collect();
        anyhow::bail!(
            "the build stopped ({status}); the end of {}:\n    {}",
            log_path.display(),
            tail.into_iter().rev().collect::<Vec<_>>().join("\n    ")
        );
    }
    Ok(())
}

/// After a child finished: compares its record with the committed one, writes it (`--record`) and uploads the
/// build (`--server`).
async fn settle(options: &BuildOptions, task: &str, client: Option<&Client>) -> anyhow::Result<Outcome> {
    let state = options.root.join(task);
    let (mut built, episodes) = state_record(&state, task)?
        .ok_or_else(|| anyhow::anyhow!("the build finished without its record in {}", state.display()))?;
    let committed = record::read(&options.records, task)?;
    // What the gap record estimated this build would cost; a rebuild keeps the estimate its committed record has.
    built.estimate = read_progress(&options.records, task)?
        .as_ref()
        .and_then(Estimate::of_gap)
        .or_else(|| committed.as_ref().and_then(|(c, _)| c.estimate.clone()));
    let (check, details) = match &committed {
        None => ("no committed record".to_owned(), Vec::new()),
        Some((committed, committed_episodes)) => {
            let differences = record::differences(&built, &episodes, committed, committed_episodes);
            if differences.is_empty() {
                ("matches".to_owned(), Vec::new())
            } else {
                ("differs".to_owned(), differences)
            }
        }
    };
    let mut outcome = Outcome {
        task: task.to_owned(),
        version: Some(built.version.clone()),
        trajectories: Some(built.trajectories),
        check,
        details,
        recorded: false,
        uploaded: None,
        retried_after: Vec::new(),
    };
    if options.record {
        record::write(&options.records, &built, &episodes)?;
        // A finished build has no gap left: its gap record goes.
        remove_progress(&options.records, task)?;
        outcome.recorded = true;
    }
    if let Some(client) = client {
        let file = state.join(&built.file_name);
        // One line: it travels in a header.
        let provenance: serde_json::Value =
            serde_json::from_slice(&std::fs::read(format!("{}.provenance.json", file.display()))?)?;
        let provenance = serde_json::to_string(&provenance)?;
        let ingested = client
            .ingest(
                task,
                &file,
                &IngestOptions {
                    // `latest` named too: an identical upload (a rebuild) moves only the tags it names.
                    tags: vec![FULL_TAG.to_owned(), "latest".to_owned()],
                    provenance_json: Some(provenance),
                    ..IngestOptions::default()
                },
                |_| {},
            )
            .await?;
        outcome.uploaded = Some(ingested.manifest_url);
    }
    Ok(outcome)
}

/// Where a task's full build stands: finished (in the state folder), committed (the records hold its finished
/// build, made elsewhere; this root holds none of it), partial (with what it has done, at what measured rate, and what is
/// left), or not started. A committed gap record (`<task>.progress.json`) that got further than the state folder,
/// or as far with a measured cost, stands for the task (`keep_recorded`). `dsrl-admin build --status` prints these;
/// with `--record` the unfinished ones are kept beside the records as `<task>.progress.json`, the measured numbers
/// of a gap.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    pub task: String,
    /// `finished`, `committed`, `partial` or `not started`.
    pub state: String,
    /// Environment steps (expert recipes) or episodes (IDM sweeps) done, of those planned.
    pub done: u64,
    pub planned: u64,
    pub unit: String,
    /// Units per second of collection and updates, measured on this build (the expert's log: simulator, acting and
    /// update seconds; a sweep: its compute's wall time), and the hours the rest would take at that rate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rate_per_second: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub remaining_hours: Option<f64>,
    /// CPU seconds of the build's whole process tree per unit done (`compute.json`, where every unit done was
    /// counted), and the core-hours the rest would take at that cost. Unlike the rate above, this does not depend on
    /// what else the machine ran meanwhile (a build at the lowest priority beside other work takes longer, not more
    /// CPU), so it is the budget that closes the gap: on N free cores, about core-hours / N hours.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpu_seconds_per_unit: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub remaining_core_hours: Option<f64>,
    /// The compute counted so far, where the build was run by `dsrl-admin build`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub compute: Option<compute::Compute>,
    /// The CPU the rate was measured on: the one the build's compute names, else this machine's.
    pub cpu: String,
}

/// `x` rounded to three significant digits: a CPU cost per step is a few ten-thousandths of a second, which four
/// decimals would have cut to one digit (0.000265 to 0.0003, a 13% error in every budget made from it).
fn three_significant_digits(x: f64) -> f64 {
    if x == 0.0 || !x.is_finite() {
        return x;
    }
    let scale = 10f64.powi(2 - x.abs().log10().floor() as i32);
    (x * scale).round() / scale
}

/// Core-hours for `units` at `cpu_seconds_per_unit`, to a tenth.
fn core_hours(units: u64, cpu_seconds_per_unit: f64) -> f64 {
    (units as f64 * cpu_seconds_per_unit / 3600.0 * 10.0).round() / 10.0
}

impl Progress {
    /// The core-hours `units` more would take at this build's measured CPU cost, where it has one.
    pub fn remaining_core_hours_for(&self, units: u64) -> Option<f64> {
        self.cpu_seconds_per_unit.map(|c| core_hours(units, c))
    }
}

/// Each task's state, in the plan's order: its state folder under the root, else its committed build record, else
/// the better of its state folder and its committed gap record.
pub fn status(options: &BuildOptions) -> anyhow::Result<Vec<Progress>> {
    let mut out = Vec::new();
    for local in local_status(options)? {
        let committed_build = record::record_path(&options.records, &local.task).exists();
        out.push(if local.state == "finished" {
            local
        } else if committed_build && local.done == 0 {
            Progress {
                state: "committed".into(),
                done: local.planned,
                rate_per_second: None,
                remaining_hours: None,
                cpu_seconds_per_unit: None,
                remaining_core_hours: None,
                compute: None,
                ..local
            }
        } else {
            let recorded = read_progress(&options.records, &local.task)?;
            keep_recorded(local, recorded)
        });
    }
    Ok(out)
}

/// Which numbers stand for an unfinished build: the committed gap record where it got further than the state folder
/// (on another machine, before this one's state was lost) or as far with a measured cost (`scripts/measure-gaps.sh`),
/// else the state folder's. A fresh state folder must not erase measured numbers; a kept record takes the CPU cost
/// this state folder measured where it has none, applied to what it has left.
pub fn keep_recorded(local: Progress, recorded: Option<Progress>) -> Progress {
    let Some(mut kept) =
        recorded.filter(|r| r.done > local.done || (r.done == local.done && local.cpu_seconds_per_unit.is_none()))
    else {
        return local;
    };
    tracing::info!(
        task = %local.task,
        "the committed gap record stands: {} {} done there, {} here",
        kept.done,
        kept.unit,
        local.done
    );
    if kept.cpu_seconds_per_unit.is_none()
        && let Some(c) = local.cpu_seconds_per_unit
    {
        kept.cpu_seconds_per_unit = Some(c);
        kept.remaining_core_hours = local.remaining_core_hours_for(kept.planned.saturating_sub(kept.done));
        if let Some(compute) = kept.compute.as_mut() {
            let said = format!(
                "the CPU cost per unit was measured on {} over the first {} {} of a fresh start",
                local.cpu, local.done, local.unit
            );
            compute.note = add_note(&compute.note, &said);
        }
    }
    kept
}

/// `note` with `said` added (`; ` between them), unless it says it already: recording twice adds nothing.
fn add_note(note: &str, said: &str) -> String {
    if note.split("; ").any(|n| n == said) {
        return note.to_owned();
    }
    [note, said]
        .into_iter()
        .filter(|n| !n.is_empty())
        .collect::<Vec<_>>()
        .join("; ")
}

/// A gap record that takes a trial build's measured CPU cost (`scripts/measure-gaps.sh` runs the trials): the
/// committed record where it did something, with the trial's cost applied to what it has left; else a record that
/// says "not started", with the cost applied to the whole budget. The trial's progress is not the build's (its state
/// is not kept), so only its cost goes in. `None` where the trial did too little to have a cost.
pub fn trial_record(trial: &Progress, recorded: Option<Progress>) -> Option<Progress> {
    let cost = trial.cpu_seconds_per_unit?;
    let said = format!(
        "the CPU cost per unit was measured on {} by a trial of the build's first {} {} (not kept)",
        trial.cpu, trial.done, trial.unit
    );
    let mut record = match recorded.filter(|r| r.done > 0) {
        Some(mut r) => {
            let compute = r.compute.get_or_insert_with(|| compute::Compute {
                cpu: trial.cpu.clone(),
                ..Default::default()
            });
            compute.note = add_note(&compute.note, &said);
            r
        }
        None => Progress {
            task: trial.task.clone(),
            state: "not started".into(),
            done: 0,
            planned: trial.planned,
            unit: trial.unit.clone(),
            rate_per_second: None,
            remaining_hours: None,
            cpu_seconds_per_unit: None,
            remaining_core_hours: None,
            compute: trial.compute.clone().map(|c| compute::Compute { note: said, ..c }),
            cpu: trial.cpu.clone(),
        },
    };
    record.cpu_seconds_per_unit = Some(cost);
    record.remaining_core_hours = Some(core_hours(record.planned.saturating_sub(record.done), cost));
    Some(record)
}

/// Each task's state in its state folder under `root` alone, in the plan's order (`--status --trial`).
pub fn local_status(options: &BuildOptions) -> anyhow::Result<Vec<Progress>> {
    let plan = Plan::load(&options.plan)?;
    let mut out = Vec::new();
    for task in plan.order(&options.tasks, &options.recipes)? {
        let recipe = plan.recipe(&task, &options.recipes)?;
        let state = options.root.join(&task);
        let compute: Option<compute::Compute> = std::fs::read(state.join("compute.json"))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok());
        let finished = state_record(&state, &task)?.is_some();
        let (done, planned, unit, rate) = match (&recipe.expert, &recipe.idm_sweep) {
            (Some(expert), _) => {
                let log = std::fs::read_to_string(state.join("expert/training.csv")).unwrap_or_default();
                let (mut steps, mut seconds) = (0u64, 0.0f64);
                for line in log.lines().skip(1) {
                    let f: Vec<&str> = line.split(',').collect();
                    steps = f.get(1).and_then(|v| v.parse().ok()).unwrap_or(steps);
                    seconds += [8, 9, 10]
                        .iter()
                        .filter_map(|&i| f.get(i).and_then(|v| v.parse::<f64>().ok()))
                        .sum::<f64>();
                }
                let rate = (seconds > 0.0).then(|| steps as f64 / seconds);
                (steps, expert.budget_steps, "steps", rate)
            }
            (None, Some(sweep)) => {
                let settings = std::fs::read_dir(state.join("settings"))
                    .map(|d| {
                        d.flatten()
                            .filter(|e| e.path().extension().is_some_and(|x| x == "parquet"))
                            .count()
                    })
                    .unwrap_or(0) as u64;
                let episodes = settings * u64::from(sweep.episodes_per_setting);
                let rate = compute
                    .as_ref()
                    .filter(|c| c.wall_seconds > 0.0)
                    .map(|c| episodes as f64 / c.wall_seconds);
                let planned = recipe.settings(None).len() as u64 * u64::from(sweep.episodes_per_setting);
                (episodes, planned, "episodes", rate)
            }
            (None, None) => (0, 0, "steps", None),
        };
        let done = if finished { planned.max(done) } else { done };
        // Only where the CPU count covers every unit done: a build begun before its CPU time was measured says so
        // in the note, and its CPU per unit would be too low.
        let cpu_per_unit = compute
            .as_ref()
            .filter(|c| c.note.is_empty() && c.cpu_seconds > 0.0 && done > 0 && !finished)
            .map(|c| c.cpu_seconds / done as f64);
        out.push(Progress {
            task,
            state: if finished {
                "finished"
            } else if done > 0 {
                "partial"
            } else {
                "not started"
            }
            .into(),
            done,
            planned,
            unit: unit.into(),
            rate_per_second: rate.map(|r| (r * 100.0).round() / 100.0),
            remaining_hours: rate
                .filter(|r| *r > 0.0 && !finished)
                .map(|r| ((planned.saturating_sub(done)) as f64 / r / 3600.0 * 10.0).round() / 10.0),
            cpu_seconds_per_unit: cpu_per_unit.map(three_significant_digits),
            remaining_core_hours: cpu_per_unit.map(|c| core_hours(planned.saturating_sub(done), c)),
            cpu: compute
                .as_ref()
                .filter(|c| !c.cpu.is_empty())
                .map_or_else(compute::cpu_name, |c| c.cpu.clone()),
            compute,
        });
    }
    Ok(out)
}

/// `<records>/<task>.progress.json`: an unfinished build's measured numbers, committed as the record of its gap.
pub fn progress_path(records: &Path, task: &str) -> PathBuf {
    records.join(format!("{task}.progress.json"))
}

/// A task's committed gap record, `None` when it has none.
pub fn read_progress(records: &Path, task: &str) -> anyhow::Result<Option<Progress>> {
    let path = progress_path(records, task);
    match std::fs::read(&path) {
        Ok(bytes) => Ok(Some(
            serde_json::from_slice(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?,
        )),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => anyhow::bail!("reading {}: {e}", path.display()),
    }
}

/// Writes a task's gap record (whole: a temporary name, then a rename).
pub fn write_progress(records: &Path, progress: &Progress) -> anyhow::Result<()> {
    std::fs::create_dir_all(records)?;
    let mut bytes = serde_json::to_vec_pretty(progress)?;
    bytes.push(b'\n');
    crate::write_atomically(&progress_path(records, &progress.task), &bytes)?;
    Ok(())
}

/// Removes a task's gap record (a finished build has no gap), where there is one.
pub fn remove_progress(records: &Path, task: &str) -> anyhow::Result<()> {
    let path = progress_path(records, task);
    match std::fs::remove_file(&path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => anyhow::bail!("removing {}: {e}", path.display()),
        _ => Ok(()),
    }
}

/// What `build-task` is given: one task's full build in its state folder.
#[derive(Debug, Clone)]
pub struct TaskBuild {
    pub task: String,
    pub plan: PathBuf,
    pub recipes: PathBuf,
    pub state: PathBuf,
    pub workers: u32,
}

/// The child's work: builds (or resumes) one task, reporting progress as JSON lines on stdout, and leaves its
/// record in `<state>/record/`. A state folder whose record names a file that is there is already finished.
pub async fn build_task(args: &TaskBuild) -> anyhow::Result<()> {
    let plan = Plan::load(&args.plan)?;
    let recipe = plan.recipe(&args.task, &args.recipes)?;
    let catalog = Catalog::embedded()?;
    let task = recipe.validate(&catalog)?.clone();
    if let Some((done, _)) = state_record(&args.state, &args.task)?
        && std::fs::metadata(args.state.join(&done.file_name)).is_ok_and(|m| m.len() == done.bytes)
    {
        report(&ChildReport::Finished { version: done.version });
        return Ok(());
    }
    std::fs::create_dir_all(&args.state)?;
    let _lock = lock(&args.state)?;
    let meter = Arc::new(compute::Meter::start(&args.state, args.workers)?);
    let saving = meter.clone().keep_saving(Duration::from_secs(10));
    let bar = ProgressBar::hidden();
    let ticking = {
        let bar = bar.clone();
        let unit = if recipe.expert.is_some() { "steps" } else { "episodes" };
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(Duration::from_secs(2)).await;
                report(&ChildReport::Progress {
                    position: bar.position(),
                    length: bar.length().unwrap_or(0),
                    unit: unit.into(),
                });
            }
        })
    };
    let run = Run {
        recipe: recipe.clone(),
        recipe_path: args.recipes.join(format!("{}.toml", args.task)),
        recipe_label: Some(plan.recipe_name(&args.task)),
        state_dir: args.state.clone(),
        episodes_per_setting: None,
        budget_steps: None,
        workers: args.workers.max(1),
        envs_per_session: 4,
        settings_per_session: 1,
        drive_episodes: true,
        simulators: SimulatorsConfig::default(),
        progress: false,
        progress_bar: Some(bar),
        max_episodes: None,
        out_dir: None,
        compact: false,
        parts: 1,
        warm_start_dir: None,
    };
    let built = run.execute(&catalog).await;
    ticking.abort();
    saving.abort();
    let built = built?;
    let compute = meter.save()?;
    let episodes: Vec<EpisodeLine> = built
        .converted
        .episode_index
        .iter()
        .enumerate()
        .map(|(i, e)| EpisodeLine {
            episode: i as u64,
            length: e.length,
            reward_return: e.reward_return,
            cost_return: e.cost_return,
        })
        .collect();
    let range = |f: fn(&EpisodeLine) -> f32| -> [f64; 2] {
        let values = episodes.iter().map(|e| f64::from(f(e)));
        [
            values.clone().fold(f64::INFINITY, f64::min),
            values.fold(f64::NEG_INFINITY, f64::max),
        ]
    };
    let budget = match (&recipe.expert, &recipe.idm_sweep) {
        (Some(expert), _) => serde_json::json!({ "budget_steps": expert.budget_steps }),
        (None, Some(sweep)) => serde_json::json!({
            "episodes_per_setting": sweep.episodes_per_setting,
            "settings": recipe.settings(None).len(),
            "maps": sweep.maps,
        }),
        (None, None) => serde_json::Value::Null,
    };
    let record = BuildRecord {
        task: args.task.clone(),
        version: built.converted.version.to_string(),
        file_name: built
            .path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        bytes: built.converted.byte_size,
        trajectories: episodes.len() as u64,
        transitions: episodes.iter().map(|e| u64::from(e.length)).sum(),
        reward_return: range(|e| e.reward_return),
        cost_return: range(|e| e.cost_return),
        paper_trajectories: u64::from(task.paper_trajectories),
        recipe: format!("data/recipes/{}.toml", args.task),
        plan: serde_json::to_value(&plan.entry(&args.task)?.overrides)?,
        seed: recipe.seed,
        budget,
        episodes_collected: built.collected as u64,
        episodes_after_buffer: built.after_buffer as u64,
        code_version: match &built.provenance {
            dsrl_suite::Provenance::Recipe { code_version, .. } => code_version.clone(),
            _ => String::new(),
        },
        compute,
        time_split: match &built.provenance {
            dsrl_suite::Provenance::Recipe { details, .. } => {
                let keys = ["simulator_seconds", "acting_seconds", "update_seconds", "write_seconds"];
                keys.iter()
                    .filter_map(|k| details.get(*k).map(|v| (k.to_string(), v.clone())))
                    .collect::<serde_json::Map<_, _>>()
                    .into()
            }
            _ => serde_json::json!({}),
        },
        finished_at: now_rfc3339(),
        estimate: None,
    };
    record::write(&args.state.join("record"), &record, &episodes)?;
    report(&ChildReport::Finished {
        version: record.version,
    });
    Ok(())
}

/// Holds `<state>/lock` (an exclusive `flock`) for as long as the returned file lives: two builds writing one
/// state folder would corrupt it, so the second is refused.
fn lock(state: &Path) -> anyhow::Result<std::fs::File> {
    use std::os::fd::AsRawFd;
    let path = state.join("lock");
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)?;
    // SAFETY: flock on a descriptor this function owns.
    if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
        anyhow::bail!(
            "another build is working in {} (it holds {})",
            state.display(),
            path.display()
        );
    }
    Ok(file)
}

/// Now in UTC, to the second.
pub fn now_rfc3339() -> String {
    time::OffsetDateTime::now_utc()
        .replace_nanosecond(0)
        .ok()
        .and_then(|t| t.format(&time::format_description::well_known::Rfc3339).ok())
        .unwrap_or_default()
}

fn report(line: &ChildReport) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{}", serde_json::to_string(line).expect("serializable"));
    let _ = out.flush();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cpu_cost_keeps_three_significant_digits() {
        assert_eq!(three_significant_digits(0.000265_4), 0.000265);
        assert_eq!(three_significant_digits(10.4487), 10.4);
        assert_eq!(three_significant_digits(0.0), 0.0);
    }

    fn progress(task: &str, done: u64, cost: Option<f64>) -> Progress {
        Progress {
            task: task.into(),
            state: if done > 0 { "partial" } else { "not started" }.into(),
            done,
            planned: 1_000_000,
            unit: "steps".into(),
            rate_per_second: None,
            remaining_hours: None,
            cpu_seconds_per_unit: cost,
            remaining_core_hours: cost.map(|c| core_hours(1_000_000 - done, c)),
            compute: None,
            cpu: "test CPU".into(),
        }
    }

    #[test]
    fn a_gap_record_that_got_further_stands_and_takes_the_fresh_cost() {
        // The record got further elsewhere and has no cost; the fresh state measured one: both are kept.
        let kept = keep_recorded(progress("t", 1000, Some(0.0036)), Some(progress("t", 500_000, None)));
        assert_eq!(kept.done, 500_000);
        assert_eq!(kept.cpu_seconds_per_unit, Some(0.0036));
        assert_eq!(
            kept.remaining_core_hours,
            Some(0.5),
            "500,000 steps at 0.0036 CPU s = 0.5 core-hours"
        );
        // As far with a cost (a trial) against a state folder without one: the record stands.
        let kept = keep_recorded(progress("t", 0, None), Some(progress("t", 0, Some(0.01))));
        assert_eq!(kept.cpu_seconds_per_unit, Some(0.01));
        // The state folder got further: it stands.
        let local = keep_recorded(progress("t", 600_000, None), Some(progress("t", 500_000, Some(0.01))));
        assert_eq!((local.done, local.cpu_seconds_per_unit), (600_000, None));
        assert_eq!(keep_recorded(progress("t", 5, None), None).done, 5);
    }

    #[test]
    fn a_trial_gives_a_gap_record_its_cost_and_nothing_else() {
        let trial = Progress {
            compute: Some(compute::Compute {
                cpu_seconds: 300.0,
                cpu: "test CPU".into(),
                ..Default::default()
            }),
            ..progress("t", 100_000, Some(0.003))
        };
        // No record: "not started", the cost over the whole budget (1,000,000 steps at 0.003 s = 0.8 core-hours).
        let fresh = trial_record(&trial, None).unwrap();
        assert_eq!((fresh.state.as_str(), fresh.done), ("not started", 0));
        assert_eq!(fresh.remaining_core_hours, Some(0.8));
        assert!(
            fresh
                .compute
                .unwrap()
                .note
                .contains("a trial of the build's first 100000 steps")
        );
        // A committed partial build keeps its progress and gains the cost over what it has left.
        let partial = trial_record(&trial, Some(progress("t", 400_000, None))).unwrap();
        assert_eq!((partial.done, partial.remaining_core_hours), (400_000, Some(0.5)));
        // Too little done to have a cost: nothing to record.
        assert!(trial_record(&progress("t", 0, None), None).is_none());
        // Recorded twice, the record says it once.
        let again = trial_record(&trial, Some(partial.clone())).unwrap();
        assert_eq!(again.compute.unwrap().note, partial.compute.unwrap().note);
    }

    #[test]
    fn status_names_a_build_committed_from_elsewhere_and_a_kept_gap_record() {
        let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let records = tempfile::tempdir().unwrap();
        let root = tempfile::tempdir().unwrap();
        let built = "OfflineBallRun-v0";
        let gap = "OfflineCarRun-v0";
        for file in [
            record::record_path(records.path(), built),
            record::episodes_path(records.path(), built),
        ] {
            std::fs::copy(repo.join("data/full").join(file.file_name().unwrap()), &file).unwrap();
        }
        let recorded = Progress {
            planned: 1_000_000,
            ..progress(gap, 250_000, Some(0.002))
        };
        std::fs::write(
            progress_path(records.path(), gap),
            serde_json::to_vec(&recorded).unwrap(),
        )
        .unwrap();
        let options = BuildOptions {
            plan: repo.join("data/full_builds.toml"),
            recipes: repo.join("data/recipes"),
            records: records.path().to_owned(),
            root: root.path().to_owned(),
            tasks: vec![built.into(), gap.into(), "OfflineDroneRun-v0".into()],
            jobs: 1,
            workers: 1,
            retries: 0,
            record: false,
            server: None,
            token: None,
            progress: false,
        };
        let listed = status(&options).unwrap();
        let by_task = |t: &str| listed.iter().find(|p| p.task == t).unwrap();
        let status_of =
            |options: &BuildOptions, t: &str| status(options).unwrap().into_iter().find(|p| p.task == t).unwrap();
        assert_eq!(by_task(built).state, "committed");
        assert_eq!(by_task(built).done, by_task(built).planned);
        assert_eq!((by_task(gap).state.as_str(), by_task(gap).done), ("partial", 250_000));
        assert_eq!(by_task("OfflineDroneRun-v0").state, "not started");
        // A committed build being built again here shows how far it got.
        let expert = root.path().join(built).join("expert");
        std::fs::create_dir_all(&expert).unwrap();
        std::fs::write(expert.join("training.csv"), "collect,steps\n1,4000\n").unwrap();
        let again = status_of(&options, built);
        assert_eq!((again.state.as_str(), again.done), ("partial", 4000));
        // The CPU its numbers were measured on is the one its compute names, not the machine reading them.
        let measured = compute::Compute {
            cpu: "the CPU that ran it".into(),
            ..Default::default()
        };
        std::fs::write(
            root.path().join(built).join("compute.json"),
            serde_json::to_vec(&measured).unwrap(),
        )
        .unwrap();
        assert_eq!(status_of(&options, built).cpu, "the CPU that ran it");
    }
}
