//! `dsrl-admin import-dsrl DIR`: hosts the DSRL files a researcher kept (DSRL 0.1.0's released HDF5 files, or a
//! mirror's) in one step. Every file in DIR named as one of DSRL's `DATASET_URLS` (`<prefix>-<cost cap>-<count>.hdf5`,
//! the names `dsrl_suite::Task::dataset_file_stem` gives) is ingested through the server's own validation, checked
//! against the catalog (the task the name maps to, its dimensions, the cost cap in the name, the trajectory count in
//! the name against the file's episodes), and tagged with a stable tag (`dsrl-0.1.0`) without moving `latest` unless
//! asked. MetaDrive files with the paper's 261 observation features are labelled as the paper's observation space
//! (they are never `latest`). A file already imported (same name, size and modification time, recorded in
//! `<DIR>/.dsrl-import.json`) is not uploaded again, so a killed import resumes where it stopped.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use dsrl_client::api::{Client, IngestOptions};
use dsrl_suite::catalog::{Catalog, Family, ObservationSpace, Task};
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};

/// What the import of one file ended in.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Imported {
    pub file: String,
    pub task: String,
    pub version: Option<String>,
    /// `imported`, `present` (done by an earlier run), or `refused` with the reason.
    pub outcome: String,
    pub reason: Option<String>,
    pub observation_space: Option<String>,
}

/// The state file: file name → (size, modified seconds, version) of each file imported.
#[derive(Debug, Default, Serialize, Deserialize)]
struct State {
    done: BTreeMap<String, (u64, u64, String)>,
}

const STATE_FILE: &str = ".dsrl-import.json";

pub struct ImportOptions {
    pub tag: String,
    /// Move `latest` to the imported versions (simulator space only).
    pub latest: bool,
}

/// The task a DSRL file name names, if it is one of DSRL's names: (task, the cost cap and count the name says).
pub fn task_of<'a>(catalog: &'a Catalog, file_name: &str) -> Option<(&'a Task, String, u64)> {
    let stem = file_name.strip_suffix(".hdf5")?;
    let (rest, count) = stem.rsplit_once('-')?;
    let (prefix, cap) = rest.rsplit_once('-')?;
    let count: u64 = count.parse().ok()?;
    let task = catalog.tasks().iter().find(|t| t.dataset_file_prefix == prefix)?;
    Some((task, cap.to_owned(), count))
}

/// The observation space of an observation width: the simulator's, or (MetaDrive) the paper's 261 features;
/// `None` for a width neither has.
fn observation_space(task: &Task, width: u64) -> Option<ObservationSpace> {
    if width == u64::from(task.obs_dim) {
        Some(ObservationSpace::Simulator)
    } else if task.family == Family::MetaDrive && width == u64::from(task.obs_dim_paper) {
        Some(ObservationSpace::Paper)
    } else {
        None
    }
}

fn stamp(path: &Path) -> anyhow::Result<(u64, u64)> {
    let meta = std::fs::metadata(path)?;
    let modified = meta
        .modified()?
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    Ok((meta.len(), modified))
}

/// Imports every DSRL-named file in `dir` into the server `client` talks to (with an admin token).
pub async fn import(client: &Client, dir: &Path, options: &ImportOptions) -> anyhow::Result<Vec<Imported>> {
    let catalog = Catalog::embedded()?;
    let state_path = dir.join(STATE_FILE);
    let mut state: State = match std::fs::read(&state_path) {
        Ok(bytes) => serde_json::from_slice(&bytes).with_context(|| format!("reading {}", state_path.display()))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => State::default(),
        Err(e) => return Err(e.into()),
    };
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "hdf5"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{} holds no .hdf5 file", dir.display());
    }
    let overall = ProgressBar::new(files.len() as u64);
    overall.set_style(ProgressStyle::with_template("importing {pos}/{len} files {wide_bar} {msg}").expect("template"));
    let mut report = Vec::new();
    for path in files {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        overall.set_message(name.clone());
        let result = import_one(client, &catalog, &path, &name, options, &mut state).await;
        let entry = match result {
            Ok(entry) => entry,
            Err(e) => Imported {
                file: name.clone(),
                task: task_of(&catalog, &name)
                    .map(|(t, ..)| t.id.to_string())
                    .unwrap_or_default(),
                version: None,
                outcome: "refused".into(),
                reason: Some(format!("{e:#}")),
                observation_space: None,
            },
        };
        if entry.outcome == "imported" {
            let tmp = state_path.with_extension("json.tmp");
            std::fs::write(&tmp, serde_json::to_vec_pretty(&state)?)?;
            std::fs::rename(&tmp, &state_path)?;
        }
        overall.inc(1);
        report.push(entry);
    }
    overall.finish_and_clear();
    Ok(report)
}

async fn import_one(
    client: &Client,
    catalog: &Catalog,
    path: &Path,
    name: &str,
    options: &ImportOptions,
    state: &mut State,
) -> anyhow::Result<Imported> {
    let Some((task, cap, count)) = task_of(catalog, name) else {
        bail!("{name} is not one of DSRL's file names (<prefix>-<cost cap>-<count>.hdf5 of a catalog task)");
    };
    let expected_cap = format!("{}", task.paper_cost_cap);
    if cap != expected_cap {
        bail!(
            "{name}: cost cap {cap} in the name, but {}'s released file has {expected_cap}",
            task.id
        );
    }
    let (size, modified) = stamp(path)?;
    if let Some((s, m, version)) = state.done.get(name)
        && (*s, *m) == (size, modified)
    {
        return Ok(Imported {
            file: name.to_owned(),
            task: task.id.to_string(),
            version: Some(version.clone()),
            outcome: "present".into(),
            reason: None,
            observation_space: None,
        });
    }
    // Checked before anything is uploaded: the shapes and the done flags only.
    let owned = path.to_owned();
    let (_, width, episodes) = tokio::task::spawn_blocking(move || dsrl_suite::hdf5_file::summarize(&owned))
        .await?
        .with_context(|| format!("reading {name} as a DSRL HDF5 file"))?;
    let Some(space) = observation_space(task, width) else {
        bail!(
            "{name}: its observations have {width} features; {} has {} (and, MetaDrive only, the paper's {})",
            task.id,
            task.obs_dim,
            task.obs_dim_paper
        );
    };
    if episodes != count {
        bail!("{name}: the name says {count} trajectories, the file holds {episodes}");
    }
    let bar = ProgressBar::new(size);
    bar.set_style(
        ProgressStyle::with_template("  uploading {msg} [{bar:30}] {bytes}/{total_bytes} {binary_bytes_per_sec}")
            .expect("template")
            .progress_chars("=> "),
    );
    bar.set_message(name.to_owned());
    let b = bar.clone();
    let ingest_options = IngestOptions {
        tags: vec![options.tag.clone()],
        observation_space: (space == ObservationSpace::Paper).then(|| "paper".to_owned()),
        keep_latest: !options.latest,
        ..IngestOptions::default()
    };
    let result = client
        .ingest(task.id.as_str(), path, &ingest_options, move |n| b.set_position(n))
        .await;
    bar.finish_and_clear();
    let result = result.map_err(|e| anyhow::anyhow!("{name}: {e}"))?;
    state
        .done
        .insert(name.to_owned(), (size, modified, result.version.version.clone()));
    Ok(Imported {
        file: name.to_owned(),
        task: task.id.to_string(),
        version: Some(result.version.version),
        outcome: "imported".into(),
        reason: None,
        observation_space: Some(space.as_str().to_owned()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dsrl_names_map_to_their_tasks() {
        let catalog = Catalog::embedded().unwrap();
        for task in catalog.tasks() {
            let name = format!("{}.hdf5", task.dataset_file_stem(u64::from(task.paper_trajectories)));
            let (found, cap, count) = task_of(&catalog, &name).unwrap();
            assert_eq!(found.id, task.id, "{name}");
            assert_eq!(
                (cap, count),
                (format!("{}", task.paper_cost_cap), u64::from(task.paper_trajectories))
            );
        }
        assert!(task_of(&catalog, "SafetyBallRun-v0-80.hdf5").is_none());
        assert!(task_of(&catalog, "NotATask-v0-80-940.hdf5").is_none());
        assert!(task_of(&catalog, "SafetyBallRun-v0-80-940.parquet").is_none());
    }
}
