//! A full build's record: what identifies the dataset it produced (the version id, the sha256 of the canonical
//! Parquet file), what it holds, how it was made and what it cost. The repository commits one per task under
//! `data/full/` (`<task>.json`, and `<task>.episodes.csv` with every episode's length and returns), so anyone can
//! rebuild a task and check the bytes, and a build that differs is told where.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// Where the repository keeps the records.
pub const RECORDS_DIR: &str = "data/full";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BuildRecord {
    pub task: String,
    /// sha256 of the canonical Parquet file: the version id every dsrl server gives it.
    pub version: String,
    /// The file's name (`<prefix>-<cost cap>-<episodes>.parquet`, DSRL's naming) and size.
    pub file_name: String,
    pub bytes: u64,
    pub trajectories: u64,
    pub transitions: u64,
    /// Lowest and highest episode return.
    pub reward_return: [f64; 2],
    pub cost_return: [f64; 2],
    /// The paper's count, for the comparison.
    pub paper_trajectories: u64,
    /// The recipe and the plan keys that replaced some of its values.
    pub recipe: String,
    pub plan: serde_json::Value,
    pub seed: u64,
    /// `budget_steps` (expert recipes) or `episodes_per_setting` and `settings` (IDM sweeps).
    pub budget: serde_json::Value,
    /// What the collection offered and kept: collected, after the trajectory buffer, after the final grid.
    pub episodes_collected: u64,
    pub episodes_after_buffer: u64,
    /// The build's code: `dsrl-pipeline <version> (git <commit>[-modified])`.
    pub code_version: String,
    pub compute: super::compute::Compute,
    /// Where the build's time went, from its provenance (seconds): the simulators, the policy's forward passes
    /// while acting, the learner's updates (expert recipes), and writing the dataset.
    #[serde(default)]
    pub time_split: serde_json::Value,
    /// When the build finished (RFC 3339, UTC).
    pub finished_at: String,
    /// What the task's gap record estimated the whole build would cost before it was built, where it had a
    /// measured cost: kept so the gaps' budgets can be held against what builds then cost (`data/README.md`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimate: Option<Estimate>,
}

/// A gap record's estimate of a whole build: its measured CPU cost per unit (a trial's or a partial build's) times
/// the units the recipe plans.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub cpu_seconds_per_unit: f64,
    /// `steps` or `episodes`.
    pub unit: String,
    pub planned: u64,
    /// `cpu_seconds_per_unit × planned`, in core-hours to a tenth.
    pub core_hours: f64,
    /// The CPU the cost was measured on.
    pub cpu: String,
}

impl Estimate {
    /// The estimate a gap record makes, where it measured a cost.
    pub fn of_gap(gap: &super::Progress) -> Option<Estimate> {
        let cost = gap.cpu_seconds_per_unit?;
        Some(Estimate {
            cpu_seconds_per_unit: cost,
            unit: gap.unit.clone(),
            planned: gap.planned,
            core_hours: gap.remaining_core_hours_for(gap.planned)?,
            cpu: gap.cpu.clone(),
        })
    }
}

/// One line of `<task>.episodes.csv`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EpisodeLine {
    pub episode: u64,
    pub length: u32,
    pub reward_return: f32,
    pub cost_return: f32,
}

pub fn record_path(dir: &Path, task: &str) -> PathBuf {
    dir.join(format!("{task}.json"))
}

pub fn episodes_path(dir: &Path, task: &str) -> PathBuf {
    dir.join(format!("{task}.episodes.csv"))
}

/// Reads a task's committed record, `None` when there is none.
pub fn read(dir: &Path, task: &str) -> anyhow::Result<Option<(BuildRecord, Vec<EpisodeLine>)>> {
    let path = record_path(dir, task);
    let bytes = match std::fs::read(&path) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => anyhow::bail!("reading {}: {e}", path.display()),
    };
    let record: BuildRecord = serde_json::from_slice(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let episodes_file = episodes_path(dir, task);
    let mut reader =
        csv::Reader::from_path(&episodes_file).map_err(|e| anyhow::anyhow!("{}: {e}", episodes_file.display()))?;
    let episodes = reader
        .deserialize()
        .collect::<Result<Vec<EpisodeLine>, _>>()
        .map_err(|e| anyhow::anyhow!("{}: {e}", episodes_file.display()))?;
    Ok(Some((record, episodes)))
}

/// Writes a record and its episodes (each file whole: a temporary name, then a rename).
pub fn write(dir: &Path, record: &BuildRecord, episodes: &[EpisodeLine]) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut json = serde_json::to_vec_pretty(record)?;
    json.push(b'\n');
    crate::write_atomically(&record_path(dir, &record.task), &json)?;
    let mut writer = csv::Writer::from_writer(Vec::new());
    for e in episodes {
        writer.serialize(e)?;
    }
    crate::write_atomically(&episodes_path(dir, &record.task), &writer.into_inner()?)?;
    Ok(())
}

/// What differs between a build and its committed record, for a person: the counts, the return ranges, and the
/// first episode whose length or returns differ. Empty when the version ids agree.
pub fn differences(
    built: &BuildRecord,
    built_episodes: &[EpisodeLine],
    committed: &BuildRecord,
    committed_episodes: &[EpisodeLine],
) -> Vec<String> {
    if built.version == committed.version {
        return Vec::new();
    }
    let mut lines = vec![format!(
        "version {} where the committed record has {}",
        built.version, committed.version
    )];
    let mut compare = |what: &str, a: String, b: String| {
        if a != b {
            lines.push(format!("{what}: {a} here, {b} committed"));
        }
    };
    compare(
        "trajectories",
        built.trajectories.to_string(),
        committed.trajectories.to_string(),
    );
    compare(
        "transitions",
        built.transitions.to_string(),
        committed.transitions.to_string(),
    );
    compare(
        "reward returns",
        format!("{:?}", built.reward_return),
        format!("{:?}", committed.reward_return),
    );
    compare(
        "cost returns",
        format!("{:?}", built.cost_return),
        format!("{:?}", committed.cost_return),
    );
    compare("code", built.code_version.clone(), committed.code_version.clone());
    compare("CPU", built.compute.cpu.clone(), committed.compute.cpu.clone());
    if built.compute.cpu != committed.compute.cpu {
        // Which kernels the committed build ran on, where its record names them (`... AVX2 kernels)`).
        let here = dsrl_policy::matrix_kernels();
        let theirs = ["AVX-512", "AVX2", "baseline"]
            .into_iter()
            .find(|k| committed.compute.cpu.contains(&format!("{k} kernels")));
        match theirs {
            Some(theirs) if theirs != here => lines.push(format!(
                "the committed build ran on {theirs} matrix kernels, this one on {here}: kernels that add in another \
                 order give another build, equally valid (data/README.md: what a version id depends on)"
            )),
            Some(_) => {}
            None => lines.push(format!(
                "the committed record does not name its CPU's matrix kernels; this build ran on {here} (other kernels \
                 give another build, equally valid: data/README.md, what a version id depends on)"
            )),
        }
    }
    match built_episodes.iter().zip(committed_episodes).find(|(a, b)| a != b) {
        Some((a, b)) => lines.push(format!(
            "first differing episode: {} (length {}, reward {}, cost {} here; length {}, reward {}, cost {} committed)",
            a.episode, a.length, a.reward_return, a.cost_return, b.length, b.reward_return, b.cost_return
        )),
        None if built_episodes.len() != committed_episodes.len() => lines.push(format!(
            "the first {} episodes agree; the build has {} and the record {}",
            built_episodes.len().min(committed_episodes.len()),
            built_episodes.len(),
            committed_episodes.len()
        )),
        None => lines.push(
            "every episode's length and returns agree: the rows differ within episodes (observations or actions)"
                .into(),
        ),
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(version: &str, trajectories: u64) -> BuildRecord {
        BuildRecord {
            task: "OfflineBallRun-v0".into(),
            version: version.into(),
            file_name: "SafetyBallRun-v0-80-3.parquet".into(),
            bytes: 10,
            trajectories,
            transitions: 300,
            reward_return: [1.0, 2.0],
            cost_return: [0.0, 5.0],
            paper_trajectories: 940,
            recipe: "data/recipes/OfflineBallRun-v0.toml".into(),
            plan: serde_json::json!({}),
            seed: 0,
            budget: serde_json::json!({"budget_steps": 300}),
            episodes_collected: 3,
            episodes_after_buffer: 3,
            code_version: "dsrl-pipeline 0.1.0 (git abc)".into(),
            compute: super::super::compute::Compute::default(),
            time_split: serde_json::json!({}),
            finished_at: "2026-11-28T00:00:00Z".into(),
            estimate: None,
        }
    }

    fn line(episode: u64, reward: f32) -> EpisodeLine {
        EpisodeLine {
            episode,
            length: 100,
            reward_return: reward,
            cost_return: 1.0,
        }
    }

    #[test]
    fn a_record_round_trips_and_a_different_build_is_told_where_it_differs() {
        let dir = tempfile::tempdir().unwrap();
        let episodes = [line(0, 1.0), line(1, 2.0), line(2, 1.5)];
        write(dir.path(), &record("a".repeat(64).as_str(), 3), &episodes).unwrap();
        let (back, back_episodes) = read(dir.path(), "OfflineBallRun-v0").unwrap().unwrap();
        assert_eq!(back, record("a".repeat(64).as_str(), 3));
        assert_eq!(back_episodes, episodes);
        assert!(read(dir.path(), "OfflineCarRun-v0").unwrap().is_none());

        assert!(differences(&back, &episodes, &back, &episodes).is_empty());
        let other = record(&"b".repeat(64), 3);
        let changed = [line(0, 1.0), line(1, 2.5), line(2, 1.5)];
        let said = differences(&other, &changed, &back, &episodes).join("\n");
        assert!(said.contains(&format!("version {}", "b".repeat(64))), "{said}");
        assert!(
            said.contains("first differing episode: 1 (length 100, reward 2.5"),
            "{said}"
        );
        assert!(!said.contains("trajectories"), "{said}");
        let fewer = record(&"c".repeat(64), 2);
        let said = differences(&fewer, &episodes[..2], &back, &episodes).join("\n");
        assert!(said.contains("trajectories: 2 here, 3 committed"), "{said}");
        assert!(
            said.contains("the first 2 episodes agree; the build has 2 and the record 3"),
            "{said}"
        );
    }
}
