//! A recipe run from start to dataset: an IDM sweep (settings in parallel over the worker pool, each finished
//! setting kept on disk) or an expert's training (saved periodically), so a killed run resumes where it stopped;
//! then the trajectory buffer and the final grid filter in a fixed order, and the canonical Parquet file with its
//! provenance.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use dsrl_pynumerics::pyrandom::PyRandom;
use dsrl_simulators::SimulatorPool;
use dsrl_simulators::SimulatorsConfig;
use dsrl_suite::catalog::{ObservationSpace, Task};
use dsrl_suite::collection::{Stored, TrajectoryBuffer, filter_points};
use dsrl_suite::convert::{Converted, ImportError, write_canonical};
use dsrl_suite::parquet_file::ParquetTransitions;
use dsrl_suite::transitions::TransitionChunk;
use dsrl_suite::{Catalog, Provenance};
use futures::StreamExt;
use indicatif::{ProgressBar, ProgressStyle};

use crate::collect::{Episode, collect_settings};
use crate::recipe::{Recipe, Setting};

/// This build of the pipeline: the crate's version and the commit it was built from (`-modified` where the sources
/// that shape the data differed from it: build.rs).
const CODE: &str = concat!(
    "dsrl-pipeline ",
    env!("CARGO_PKG_VERSION"),
    " (git ",
    env!("DSRL_BUILD_COMMIT"),
    ")"
);

/// The state folder's note of workers that ran other simulator Python than this build's (their versions, a line
/// each): its presence marks the data's code `-modified`.
const OTHER_PYTHON: &str = "other-simulator-python";

/// The first 12 hex digits of the digest of the `dsrl_sim` package this build was made with (build.rs).
fn simulator_python() -> &'static str {
    dsrl_suite::ids::short_hex(env!("DSRL_SIM_PYTHON_DIGEST"))
}

/// The code that made the data in `state_dir` (see `Run::code_version`).
fn code_version(state_dir: &Path) -> String {
    dsrl_simulators::mark_modified(CODE, state_dir.join(OTHER_PYTHON).exists())
}

pub struct Run {
    pub recipe: Recipe,
    pub recipe_path: PathBuf,
    /// How provenance names the recipe, where it is not the file itself (a full build's recipe is a committed
    /// recipe with some keys replaced by the plan).
    pub recipe_label: Option<String>,
    /// Where finished settings and the output live; a re-run with the same folder resumes.
    pub state_dir: PathBuf,
    /// Budget override: episodes per sweep setting (the recipe's by default).
    pub episodes_per_setting: Option<u32>,
    /// Budget override for expert recipes: environment steps to train for.
    pub budget_steps: Option<u64>,
    pub workers: u32,
    pub envs_per_session: u32,
    /// IDM sweeps: consecutive settings per session (blocks fixed by setting index, so resuming replays the same).
    pub settings_per_session: u32,
    /// IDM sweeps: let the worker's driver play whole episodes where the deal allows (see `collect_settings`).
    pub drive_episodes: bool,
    pub simulators: SimulatorsConfig,
    pub progress: bool,
    /// A bar the caller follows instead of one drawn on the terminal (`dsrl-admin build` reports its position).
    pub progress_bar: Option<ProgressBar>,
    /// Thin the result to at most this many episodes with the trajectory buffer's grid (starter datasets).
    pub max_episodes: Option<usize>,
    /// Where the output goes (default: the state folder).
    pub out_dir: Option<PathBuf>,
    /// Write the output in the compact form (committed starters; the ingested version is the canonical one).
    pub compact: bool,
    /// With `compact`: split the output into this many files of whole episodes (`<stem>.part-I-of-N.parquet`), for
    /// a starter larger than one committed file may be. 1 writes one file.
    pub parts: usize,
    /// The state folder of the build a recipe's `warm_start` names (default: `<state>/../<its task>`).
    pub warm_start_dir: Option<PathBuf>,
}

/// What a run produced.
pub struct Built {
    /// The dataset's file, or with parts the name they share (`files` are what was written).
    pub path: PathBuf,
    pub files: Vec<PathBuf>,
    pub converted: Converted,
    pub provenance: Provenance,
    pub collected: usize,
    pub after_buffer: usize,
}

fn setting_path(state: &Path, setting: &Setting) -> PathBuf {
    state.join("settings").join(format!("{:03}.parquet", setting.index))
}

/// Writes a finished setting atomically (temporary name, then rename), validated like any dataset.
fn save_setting(task: &Task, state: &Path, setting: &Setting, episodes: &[Episode]) -> anyhow::Result<()> {
    let path = setting_path(state, setting);
    let part = path.with_extension("parquet.part");
    // One episode copied at a time: the writer takes owned chunks, the caller keeps the episodes.
    let chunks = episodes.iter().map(|e| Ok::<_, ImportError>(e.transitions.clone()));
    write_canonical(task, ObservationSpace::Simulator, chunks, Vec::new(), &part)
        .with_context(|| format!("writing setting {}", setting.index))?;
    std::fs::rename(&part, &path)?;
    Ok(())
}

/// Reads a finished setting back, split into its episodes.
fn load_setting(recipe: &Recipe, state: &Path, setting: &Setting) -> anyhow::Result<Option<Vec<Episode>>> {
    let path = setting_path(state, setting);
    let Ok(file) = std::fs::File::open(&path) else {
        return Ok(None);
    };
    let mut all: Option<TransitionChunk> = None;
    for chunk in ParquetTransitions::open(file).with_context(|| format!("reading {}", path.display()))? {
        let mut chunk = chunk.with_context(|| format!("reading {}", path.display()))?;
        // Episode numbering is recomputed below; `append` joins only the DSRL columns.
        chunk.episode = None;
        chunk.step = None;
        match &mut all {
            Some(all) => all.append(&chunk),
            None => all = Some(chunk),
        }
    }
    let Some(mut all) = all else {
        return Ok(Some(Vec::new()));
    };
    let mut episodes = Vec::new();
    while !all.is_empty() {
        let end = (0..all.len())
            .find(|&i| all.is_done(i))
            .context("a stored setting ends mid-episode")?
            + 1;
        let number = episodes.len() as u32;
        let mut chunk = all.take_front(end);
        chunk.episode = None;
        chunk.step = None;
        episodes.push(Episode::from_chunk(
            setting.index,
            number,
            recipe.episode_seed(setting.index, number),
            chunk,
        ));
    }
    anyhow::ensure!(
        episodes.len() == setting.episodes as usize,
        "{} holds {} episodes, expected {}",
        path.display(),
        episodes.len(),
        setting.episodes
    );
    Ok(Some(episodes))
}

/// The recipe as provenance names it: `data/recipes/<task>.toml` for the repository's own, else the path given.
fn recipe_name(path: &Path, task: &Task) -> String {
    let default = Recipe::default_path(task.id.as_str());
    match (path.canonicalize(), default.canonicalize()) {
        (Ok(a), Ok(b)) if a == b => format!("data/recipes/{}.toml", task.id),
        _ => path.display().to_string(),
    }
}

impl Run {
    pub async fn execute(self, catalog: &Catalog) -> anyhow::Result<Built> {
        let started = Instant::now();
        let task = self.recipe.validate(catalog)?.clone();
        std::fs::create_dir_all(&self.state_dir)?;
        // A state folder belongs to one recipe and budget: refuse to mix runs.
        let mut identity =
            serde_json::json!({ "recipe": self.recipe, "episodes_per_setting": self.episodes_per_setting });
        if self.recipe.expert.is_some() {
            identity["budget_steps"] = serde_json::json!(self.budget_steps);
        }
        let identity_path = self.state_dir.join("run.json");
        match std::fs::read(&identity_path) {
            Ok(bytes) => {
                let stored: serde_json::Value = serde_json::from_slice(&bytes)?;
                anyhow::ensure!(
                    stored == identity,
                    "{} holds a run of another recipe or budget; use another --state folder",
                    self.state_dir.display()
                );
            }
            Err(_) => crate::write_atomically(&identity_path, &serde_json::to_vec_pretty(&identity)?)?,
        }

        let (buffered, collected, method) = if self.recipe.expert.is_some() {
            self.run_expert(&task).await?
        } else {
            self.run_sweep(&task).await?
        };
        self.write_dataset(&task, buffered, collected, method, started).await
    }

    fn progress_bar(&self, len: u64, template: &str) -> ProgressBar {
        let bar = match (&self.progress_bar, self.progress) {
            (Some(bar), _) => {
                bar.set_length(len);
                bar.clone()
            }
            (None, true) => ProgressBar::new(len),
            (None, false) => ProgressBar::hidden(),
        };
        bar.set_style(ProgressStyle::with_template(template).expect("template"));
        bar
    }

    /// Starts the run's own local workers and waits until they (and the configured remote ones) are healthy.
    async fn start_pool(&self) -> anyhow::Result<Arc<SimulatorPool>> {
        let pool = Arc::new(SimulatorPool::start(&SimulatorsConfig {
            local_workers: self.workers,
            ..self.simulators.clone()
        }));
        let wanted = (self.workers as usize + self.simulators.remote_workers.len()).max(1);
        anyhow::ensure!(
            pool.wait_healthy(wanted, std::time::Duration::from_secs(180)).await,
            "simulator workers did not become healthy: {:?}",
            pool.workers()
        );
        // Workers whose simulator Python is not this build's: the data is then not this commit's. Noted in the state
        // folder, so a build resumed later by a clean run still says so (`code_version`).
        let workers = pool.workers();
        if dsrl_simulators::label_with_workers_python(CODE, &workers, simulator_python()) != CODE {
            let versions: Vec<_> = workers.iter().filter_map(|w| w.version.clone()).collect();
            let note = format!("{}\n", versions.join("\n"));
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(self.state_dir.join(OTHER_PYTHON))?
                .write_all(note.as_bytes())?;
            tracing::warn!(
                ?versions,
                "the simulator workers run other Python than this build's: its data is marked -modified"
            );
        }
        Ok(pool)
    }

    /// The code that made the data: this crate's version and commit, `-modified` where its sources differed from the
    /// commit or a run of this build played on workers with other simulator Python (`OTHER_PYTHON`).
    fn code_version(&self) -> String {
        code_version(&self.state_dir)
    }

    /// The expert recipe: train (or resume) and return what the trajectory buffer kept, in its order.
    async fn run_expert(&self, task: &Task) -> anyhow::Result<(Vec<Episode>, usize, serde_json::Value)> {
        let expert = self.recipe.expert.as_ref().expect("checked by the caller");
        let budget = self.budget_steps.unwrap_or(expert.budget_steps);
        let bar = self.progress_bar(
            budget,
            "{msg} [{elapsed_precise}] {wide_bar} {pos}/{len} steps (eta {eta})",
        );
        bar.set_message(task.id.to_string());
        let root = self.state_dir.join("expert");
        let (warm_start, warm_record) = self.warm_start(&root)?;
        let pool = self.start_pool().await?;
        // One session per worker: every worker steps.
        let sessions = self.workers as usize + self.simulators.remote_workers.len();
        let training = crate::expert::train::Training {
            root: &root,
            budget,
            sessions,
            warm_start,
        };
        let collection = crate::expert::train::train(&pool, &self.recipe, task, training, &bar).await?;
        bar.finish();
        let seconds = |f: fn(&crate::expert::train::CollectLog) -> f64| -> f64 {
            collection.log.iter().map(f).sum::<f64>().round()
        };
        let mut details = serde_json::json!({
            "budget_steps": budget,
            "paper_steps": expert.cost_limit.paper_steps(),
            "budget_scale": budget as f64 / expert.cost_limit.paper_steps() as f64,
            "steps_trained": collection.steps,
            "collects": collection.log.len(),
            "final_lagrangian": collection.log.last().map(|l| l.lagrangian),
            "simulator_seconds": seconds(|l| l.simulator_seconds),
            "acting_seconds": seconds(|l| l.acting_seconds),
            "update_seconds": seconds(|l| l.update_seconds),
            "worker_idle_seconds": seconds(|l| l.worker_idle_seconds),
            "expert_policy": "expert/policy (policy.safetensors + policy.json)",
            "training_log": "expert/training.csv",
        });
        if let Some(record) = warm_record {
            details["warm_start"] = record;
        }
        let offered = collection.offered as usize;
        Ok((collection.episodes, offered, details))
    }

    /// The recipe's warm start: the source build's weights where this run starts from nothing, and the record the
    /// provenance keeps of them. The record is kept in `expert/warm_start.json` when the run starts, so a resumed
    /// run needs the source no more.
    fn warm_start(
        &self,
        root: &Path,
    ) -> anyhow::Result<(
        Option<crate::expert::train::WarmStartWeights>,
        Option<serde_json::Value>,
    )> {
        let Some(warm) = self.recipe.expert.as_ref().and_then(|e| e.warm_start.as_ref()) else {
            return Ok((None, None));
        };
        let record_path = root.join("warm_start.json");
        if crate::expert::train::has_save(root) {
            let record = std::fs::read(&record_path)
                .with_context(|| format!("{} is missing from a warm-started run", record_path.display()))?;
            return Ok((None, Some(serde_json::from_slice(&record)?)));
        }
        let source = match &self.warm_start_dir {
            Some(dir) => dir.clone(),
            None => self
                .state_dir
                .parent()
                .map_or_else(|| PathBuf::from(&warm.task), |p| p.join(&warm.task)),
        };
        anyhow::ensure!(
            source.canonicalize().ok() != self.state_dir.canonicalize().ok(),
            "the warm start's build and this run cannot share the state folder {}",
            source.display()
        );
        let weights = crate::expert::train::read_warm_start(&source, warm)?;
        std::fs::create_dir_all(root)?;
        crate::write_atomically(&record_path, &serde_json::to_vec_pretty(&weights.record)?)?;
        tracing::info!(from = %source.display(), task = %warm.task, "warm-starting the expert");
        let record = weights.record.clone();
        Ok((Some(weights), Some(record)))
    }

    /// The IDM sweep: every setting (resumed from disk when already finished), then the trajectory buffer over all
    /// episodes in a fixed order whatever finished first.
    async fn run_sweep(&self, task: &Task) -> anyhow::Result<(Vec<Episode>, usize, serde_json::Value)> {
        std::fs::create_dir_all(self.state_dir.join("settings"))?;
        let settings = self.recipe.settings(self.episodes_per_setting);
        let total: u64 = settings.iter().map(|s| u64::from(s.episodes)).sum();
        let mut finished: BTreeMap<usize, Vec<Episode>> = BTreeMap::new();
        for setting in &settings {
            if let Some(episodes) = load_setting(&self.recipe, &self.state_dir, setting)? {
                finished.insert(setting.index, episodes);
            }
        }
        let resumed: u64 = finished.values().map(|v| v.len() as u64).sum();
        let bar = self.progress_bar(
            total,
            "{msg} [{elapsed_precise}] {wide_bar} {pos}/{len} episodes (eta {eta})",
        );
        bar.set_message(task.id.to_string());
        bar.set_position(resumed);
        if resumed > 0 {
            tracing::info!(resumed, "resuming: finished settings found in the state folder");
        }

        // Blocks of consecutive settings, fixed by index whatever is resumed; one with any setting unsaved is
        // played again whole, so its episodes are those of an uninterrupted run.
        let block = self.settings_per_session.max(1) as usize;
        let todo: Vec<Vec<Setting>> = settings
            .chunks(block)
            .filter(|b| b.iter().any(|s| !finished.contains_key(&s.index)))
            .map(<[Setting]>::to_vec)
            .collect();
        if !todo.is_empty() {
            for s in todo.iter().flatten() {
                if let Some(replayed) = finished.remove(&s.index) {
                    bar.set_position(bar.position() - replayed.len() as u64);
                }
            }
            let pool = self.start_pool().await?;
            let wanted = (self.workers as usize + self.simulators.remote_workers.len()).max(1);
            let jobs = futures::stream::iter(todo.into_iter().map(|block| {
                let (pool, recipe, bar) = (pool.clone(), self.recipe.clone(), bar.clone());
                let (task, state) = (task.clone(), self.state_dir.clone());
                let (envs, drive) = (self.envs_per_session, self.drive_episodes);
                async move {
                    let episodes = collect_settings(&pool, &recipe, &block, envs, drive, || bar.inc(1)).await?;
                    let saved = tokio::task::spawn_blocking(move || {
                        for (setting, episodes) in block.iter().zip(&episodes) {
                            save_setting(&task, &state, setting, episodes)?;
                        }
                        anyhow::Ok(block.iter().map(|s| s.index).zip(episodes).collect::<Vec<_>>())
                    })
                    .await??;
                    anyhow::Ok(saved)
                }
            }))
            .buffer_unordered(wanted);
            futures::pin_mut!(jobs);
            while let Some(result) = jobs.next().await {
                finished.extend(result?);
            }
        }
        bar.finish();

        // Fixed order whatever finished first: settings by index, episodes by number.
        let mut buffer =
            TrajectoryBuffer::new(self.recipe.buffer_limits(), self.recipe.seed).map_err(anyhow::Error::msg)?;
        let mut collected = 0;
        for episode in finished.into_values().flatten() {
            collected += 1;
            buffer.offer(Stored {
                reward_return: episode.reward_return,
                cost_return: episode.cost_return,
                payload: episode,
            });
        }
        let mut details = serde_json::json!({
            "episodes_per_setting": self.episodes_per_setting.unwrap_or_else(|| self.recipe.settings(None)[0].episodes),
            "budget_scaled": self.episodes_per_setting.is_some(),
            "settings": settings.len(),
            "envs_per_session": self.envs_per_session,
        });
        // Only recorded where it departs from a fresh session per setting, so the provenance of such builds (the
        // committed starters') stays what it was.
        if self.settings_per_session > 1 {
            details["settings_per_session"] = self.settings_per_session.into();
        }
        Ok((
            buffer.into_episodes().into_iter().map(|s| s.payload).collect(),
            collected,
            details,
        ))
    }

    /// The final grid filter over the buffer's episodes, the optional starter thinning, the canonical Parquet file
    /// and its provenance.
    async fn write_dataset(
        &self,
        task: &Task,
        mut buffered: Vec<Episode>,
        collected: usize,
        method: serde_json::Value,
        started: Instant,
    ) -> anyhow::Result<Built> {
        let returns: Vec<(f64, f64)> = buffered.iter().map(|e| (e.reward_return, e.cost_return)).collect();
        let mut grid_random = PyRandom::seed(self.recipe.seed);
        // Positions in `buffered` of the episodes the final grid keeps, in its output order.
        let kept: Vec<usize> = self.recipe.final_grid().apply(&returns, &mut grid_random);
        anyhow::ensure!(
            !kept.is_empty(),
            "the final grid filter kept no episode (check final_grid against the returns)"
        );
        let after_grid = kept.len();
        let kept: Vec<usize> = match self.max_episodes {
            Some(n) if kept.len() > n => {
                // The same spread-preserving thinning as the buffer, seeded apart from it; file order is kept.
                let points: Vec<(f64, f64)> = kept.iter().map(|&i| returns[i]).collect();
                let mut chosen = filter_points(&points, n, &mut PyRandom::seed(self.recipe.seed.wrapping_add(1)));
                chosen.sort_unstable();
                chosen.into_iter().map(|i| kept[i]).collect()
            }
            _ => kept,
        };

        let cap = self.recipe.final_grid.cost_cap;
        let out_dir = self.out_dir.clone().unwrap_or_else(|| self.state_dir.clone());
        std::fs::create_dir_all(&out_dir)?;
        let path = out_dir.join(format!("{}-{cap}-{}.parquet", task.dataset_file_prefix, kept.len()));
        let part = path.with_extension("parquet.part");
        let (after_buffer, episodes_kept) = (buffered.len(), kept.len());
        // Kept episodes are taken out of `buffered`, not copied.
        let writing = Instant::now();
        let converted = {
            let (task, part) = (task.clone(), part.clone());
            tokio::task::spawn_blocking(move || {
                let chunks = kept
                    .iter()
                    .map(|&i| Ok::<_, ImportError>(std::mem::take(&mut buffered[i].transitions)));
                write_canonical(&task, ObservationSpace::Simulator, chunks, Vec::new(), &part)
            })
            .await??
        };
        let files = if self.compact {
            // The committed form of a starter: ingested, it gives the canonical file and its version id. A starter
            // over one file's budget is written in parts of whole episodes, joined back at ingest.
            let name = path
                .file_name()
                .and_then(|n| n.to_str())
                .context("output file name")?
                .to_owned();
            let files: Vec<PathBuf> = match self.parts {
                0 | 1 => vec![path.clone()],
                n => (1..=n)
                    .map(|i| out_dir.join(dsrl_suite::convert::part_file_name(&name, i, n)))
                    .collect(),
            };
            let scratch: Vec<PathBuf> = files.iter().map(|f| f.with_extension("parquet.compact")).collect();
            let (task, canonical, targets) = (task.clone(), part.clone(), scratch.clone());
            let episodes = converted.episode_index.clone();
            tokio::task::spawn_blocking(move || {
                dsrl_suite::convert::split_compact(&task, ObservationSpace::Simulator, &canonical, &episodes, &targets)
            })
            .await??;
            std::fs::remove_file(&part)?;
            for (from, to) in scratch.iter().zip(&files) {
                std::fs::rename(from, to)?;
            }
            files
        } else {
            std::fs::rename(&part, &path)?;
            vec![path.clone()]
        };
        let mut details = serde_json::json!({
            "recipe": self.recipe,
            "episodes_collected": collected,
            "episodes_after_buffer": after_buffer,
            "episodes_after_final_grid": after_grid,
            "episodes_kept": episodes_kept,
            "thinned_to": self.max_episodes,
            "transitions": converted.episode_index.iter().map(|e| u64::from(e.length)).sum::<u64>(),
            "workers": self.workers,
            "wall_seconds": started.elapsed().as_secs_f64().round(),
            "write_seconds": (writing.elapsed().as_secs_f64() * 10.0).round() / 10.0,
        });
        if let (Some(details), serde_json::Value::Object(method)) = (details.as_object_mut(), method) {
            details.extend(method);
        }
        let provenance = Provenance::Recipe {
            recipe: self
                .recipe_label
                .clone()
                .unwrap_or_else(|| recipe_name(&self.recipe_path, task)),
            seeds: vec![self.recipe.seed],
            // The commit as well as the version: see build.rs.
            code_version: self.code_version(),
            details,
        };
        // `<file>.provenance.json`: the name the server's starter loader reads beside a dataset.
        let provenance_path = PathBuf::from(format!("{}.provenance.json", path.display()));
        crate::write_atomically(&provenance_path, &serde_json::to_vec_pretty(&provenance)?)?;
        Ok(Built {
            path,
            files,
            converted,
            provenance,
            collected,
            after_buffer,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn synthetic_episode(task: &Task, setting: usize, number: u32, steps: usize) -> Episode {
        let (obs_dim, act_dim) = (task.obs_dim as usize, task.act_dim as usize);
        let mut chunk = TransitionChunk::empty(obs_dim, act_dim);
        for t in 0..steps {
            let v = (number as f32) + t as f32 * 1e-3;
            chunk.observations.extend(std::iter::repeat_n(v, obs_dim));
            chunk.next_observations.extend(std::iter::repeat_n(v + 1e-3, obs_dim));
            chunk.actions.extend(std::iter::repeat_n(0.5, act_dim));
            chunk.rewards.push(0.25 + number as f32);
            chunk.costs.push(if t % 7 == 0 { 1.0 } else { 0.0 });
            chunk.terminals.push(t + 1 == steps);
            chunk.timeouts.push(false);
        }
        Episode::from_chunk(setting, number, 0, chunk)
    }

    #[test]
    fn settings_saved_to_disk_read_back_as_the_same_episodes() {
        // Long MetaDrive-sized episodes, so the file is read back in several chunks.
        let catalog = Catalog::embedded().unwrap();
        let recipe = Recipe::load(&Recipe::committed_path("OfflineMetadrive-easysparse-v0")).unwrap();
        let task = recipe.validate(&catalog).unwrap();
        let setting = Setting {
            index: 3,
            acc_factor: 1.2,
            target_speed: 13.0,
            episodes: 12,
            maps: 1,
        };
        let episodes: Vec<Episode> = (0..12)
            .map(|n| synthetic_episode(task, 3, n, 900 + n as usize * 7))
            .collect();
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("settings")).unwrap();
        save_setting(task, dir.path(), &setting, &episodes).unwrap();
        let file = std::fs::File::open(setting_path(dir.path(), &setting)).unwrap();
        assert!(
            ParquetTransitions::open(file).unwrap().count() > 1,
            "the test needs a file read in several chunks"
        );
        let back = load_setting(&recipe, dir.path(), &setting).unwrap().unwrap();
        assert_eq!(back.len(), 12);
        for (a, b) in episodes.iter().zip(&back) {
            assert_eq!(a.transitions.len(), b.transitions.len());
            assert_eq!(a.transitions.observations, b.transitions.observations);
            assert_eq!((a.reward_return, a.cost_return), (b.reward_return, b.cost_return));
            assert_eq!(b.seed, recipe.episode_seed(3, b.number));
        }
        let missing = Setting { index: 4, ..setting };
        assert!(load_setting(&recipe, dir.path(), &missing).unwrap().is_none());
    }

    /// Data made on workers with other simulator Python (a run noted it in the state folder) is not the commit's:
    /// its code carries `-modified`, and only then.
    #[test]
    fn a_run_on_other_simulator_python_marks_the_code() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(code_version(dir.path()), CODE);
        assert!(CODE.starts_with("dsrl-pipeline ") && CODE.contains(" (git "), "{CODE}");
        std::fs::write(
            dir.path().join(OTHER_PYTHON),
            "dsrl-sim-worker 0.1.0 (dsrl_sim 000000000000)\n",
        )
        .unwrap();
        let marked = code_version(dir.path());
        assert!(marked.ends_with("-modified)"), "{marked}");
        assert_eq!(marked.matches("-modified").count(), 1, "{marked}");
    }
}
