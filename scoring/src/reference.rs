//! The leaderboard's reference results as data: one line of `data/reference/results.jsonl` per reference entry (a
//! method trained by `dsrl-train` on a hosted dataset and scored by a dsrl leaderboard), with everything needed to
//! check or reproduce it — the training budget and seed, the dataset version it was trained on, the code commit,
//! the checkpoint's digest, the protocol version it was scored under, and every scored episode. The documents'
//! reference tables are generated from this file and the server imports it; scores are always computed from the
//! episodes (never stored beside them), so the file cannot disagree with itself.
//!
//! `agreement` compares the entries with the paper's table (`paper`): per (task, method) the difference in
//! normalized reward and cost and whether the safe/unsafe verdicts agree, and the share of agreeing verdicts per
//! family and overall: the benchmark's fidelity figure.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::leaderboard::entry_score;
use crate::paper::{PAPER_METHODS, PaperResults};
use dsrl_suite::catalog::{Catalog, Family, Task};
use dsrl_suite::score::{EpisodeResult, NormalizedScore};

/// The methods reference entries are trained with: OSRL's seven, then CAPS, FISOR and LSPC (beyond the paper).
pub const REFERENCE_METHODS: [&str; 10] = [
    "BC-All",
    "BC-Safe",
    "CDT",
    "BCQ-Lag",
    "BEAR-Lag",
    "CPQ",
    "COptiDICE",
    "CAPS",
    "FISOR",
    "LSPC",
];

/// OSRL's training budget for `method` on `task`: gradient steps per model and batch size (spec 5.4–5.8: 100,000
/// steps, MetaDrive 200,000, BEAR-Lag 300,000 outside MetaDrive; batch 512, CDT 2048). CAPS: its own paper's 100,000
/// steps at batch 512; FISOR and LSPC: their code's 1,000,000 steps, at batch 2048 (FISOR's actor: two halves of
/// 1024) and 1024.
pub fn osrl_budget(method: &str, task: &Task) -> Option<(u64, usize)> {
    let metadrive = task.family == Family::MetaDrive;
    let base = if metadrive { 200_000 } else { 100_000 };
    Some(match method {
        "BC-All" | "BC-Safe" | "BCQ-Lag" | "CPQ" | "COptiDICE" => (base, 512),
        "BEAR-Lag" => (if metadrive { 200_000 } else { 300_000 }, 512),
        "CDT" => (base, 2048),
        "CAPS" => (100_000, 512),
        "FISOR" => (1_000_000, 2048),
        "LSPC" => (1_000_000, 1024),
        _ => return None,
    })
}

/// How an entry was trained.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainingBudget {
    /// Gradient steps per model.
    pub steps: u64,
    pub batch_size: usize,
    /// Models trained: 1, or one per cost threshold for the per-threshold methods.
    pub models: u32,
    /// Wall-clock seconds of training, all models together, each on one thread.
    pub seconds: f64,
    /// CPU seconds of training (each model's training thread, user + system), all models together: the compute,
    /// whatever else shared the machine.
    pub cpu_seconds: f64,
    /// The CPU the models were trained on (model name, AVX-512 or not), as their training records name it: CPU
    /// seconds are comparable only on one CPU. Absent for entries trained before the records named it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpu: Option<String>,
    /// OSRL's steps and batch size for the method on the task, for the fraction of its budget.
    pub osrl_steps: u64,
    pub osrl_batch_size: usize,
}

impl TrainingBudget {
    /// The fraction of OSRL's training samples (steps × batch) this budget used.
    pub fn fraction_of_osrl(&self) -> f64 {
        (self.steps as f64 * self.batch_size as f64) / (self.osrl_steps as f64 * self.osrl_batch_size as f64)
    }

    /// CPU seconds OSRL's full budget would take at this entry's measured compute per sample (one thread per model).
    pub fn osrl_cpu_seconds(&self) -> f64 {
        self.cpu_seconds / self.fraction_of_osrl()
    }
}

/// Where and when an entry was scored.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScoringRecord {
    /// The submission id on the leaderboard that scored it.
    pub submission: i64,
    pub started_at: String,
    pub finished_at: String,
    /// Wall-clock seconds from claim to result.
    pub seconds: f64,
    /// The build that scored it (`dsrl-leaderboard <version> (git <commit>[-modified])`); absent for entries scored
    /// before builds were recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub build: Option<String>,
}

/// One reference entry: one line of the results file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceEntry {
    pub task: String,
    /// One of `REFERENCE_METHODS`.
    pub method: String,
    /// The training seed (initialization and batch sampling).
    pub seed: u64,
    pub training: TrainingBudget,
    /// The dataset version (sha256) every model of the entry was trained on.
    pub dataset_version: String,
    /// The git commit `dsrl-train` was built from (`-modified` when its sources differed).
    pub code_commit: String,
    /// The leaderboard's digest of the checkpoints (its dedupe key).
    pub checkpoint_sha256: String,
    /// The protocol version the entry was scored under.
    pub protocol_version: String,
    pub scoring: ScoringRecord,
    /// Every scored episode, by threshold and episode index.
    pub episodes: Vec<EpisodeResult>,
}

impl ReferenceEntry {
    /// Normalized reward and cost as the leaderboard computes them from the episodes.
    pub fn score(&self, task: &Task) -> Option<NormalizedScore> {
        entry_score(task, &self.episodes)
    }

    /// The key that makes an entry unique in the file.
    pub fn key(&self) -> (String, usize, u64) {
        (self.task.clone(), method_index(&self.method), self.seed)
    }
}

fn method_index(method: &str) -> usize {
    REFERENCE_METHODS
        .iter()
        .position(|m| *m == method)
        .unwrap_or(usize::MAX)
}

#[derive(Debug, thiserror::Error)]
pub enum ReferenceError {
    #[error("reference results line {line}: {message}")]
    Invalid { line: usize, message: String },
}

/// Reads a results file (JSON Lines; blank lines skipped), checked against `catalog`: known tasks and methods,
/// one entry per (task, method, seed), episodes only at the task's thresholds, every number finite.
pub fn read_results(text: &str, catalog: &Catalog) -> Result<Vec<ReferenceEntry>, ReferenceError> {
    let mut entries: Vec<ReferenceEntry> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let invalid = |message: String| ReferenceError::Invalid { line: i + 1, message };
        let entry: ReferenceEntry = serde_json::from_str(line).map_err(|e| invalid(e.to_string()))?;
        let task = catalog.get(&entry.task).map_err(|e| invalid(e.to_string()))?;
        if method_index(&entry.method) == usize::MAX {
            return Err(invalid(format!(
                "unknown method {:?}; reference methods are {}",
                entry.method,
                REFERENCE_METHODS.join(", ")
            )));
        }
        if entry.episodes.is_empty() {
            return Err(invalid("no episodes".into()));
        }
        if let Some(e) = entry.episodes.iter().find(|e| {
            !(task.cost_thresholds.contains(&e.cost_threshold)
                && e.reward_return.is_finite()
                && e.cost_return.is_finite())
        }) {
            return Err(invalid(format!(
                "episode {} at threshold {} is not a finite episode at one of {}'s thresholds",
                e.episode, e.cost_threshold, task.id
            )));
        }
        if entries.iter().any(|other| other.key() == entry.key()) {
            return Err(invalid(format!(
                "{} {} seed {} appears twice",
                entry.task, entry.method, entry.seed
            )));
        }
        entries.push(entry);
    }
    Ok(entries)
}

/// The file's text for `entries`: one line each, ordered by task id, method (`REFERENCE_METHODS` order) and seed,
/// so a re-run that changes one entry changes one line.
pub fn write_results(entries: &[ReferenceEntry]) -> String {
    let mut sorted: Vec<&ReferenceEntry> = entries.iter().collect();
    sorted.sort_by_key(|e| e.key());
    sorted
        .iter()
        .map(|e| serde_json::to_string(e).expect("a reference entry serializes") + "\n")
        .collect()
}

/// `entries` with `entry` in place of the one of the same (task, method, seed), or added.
pub fn upsert(entries: &mut Vec<ReferenceEntry>, entry: ReferenceEntry) {
    entries.retain(|e| e.key() != entry.key());
    entries.push(entry);
}

/// One scored reference entry, as the agreement needs it (from the file or from a server's tables).
#[derive(Debug, Clone, PartialEq)]
pub struct ScoredEntry {
    pub task: String,
    pub method: String,
    pub score: NormalizedScore,
}

/// `entries` of the current `protocol_version`, scored.
pub fn scored_entries(entries: &[ReferenceEntry], catalog: &Catalog, protocol_version: &str) -> Vec<ScoredEntry> {
    entries
        .iter()
        .filter(|e| e.protocol_version == protocol_version)
        .filter_map(|e| {
            let task = catalog.get(&e.task).ok()?;
            Some(ScoredEntry {
                task: e.task.clone(),
                method: e.method.clone(),
                score: e.score(task)?,
            })
        })
        .collect()
}

/// Our result against the paper's for one (task, method).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Agreement {
    pub task: String,
    pub method: String,
    /// Our entries (training seeds) averaged, as the paper averages its seeds.
    pub seeds: usize,
    pub normalized_reward: f64,
    pub normalized_cost: f64,
    pub paper_normalized_reward: f64,
    pub paper_normalized_cost: f64,
    /// Ours minus the paper's.
    pub reward_difference: f64,
    pub cost_difference: f64,
    pub safe: bool,
    pub paper_safe: bool,
    pub verdict_agrees: bool,
}

/// The share of agreeing verdicts over a family (`bullet`, `safety-gymnasium`, `metadrive`) or `all`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AgreementSummary {
    pub scope: String,
    /// (task, method) cells with both our entry and the paper's.
    pub cells: usize,
    pub agreeing: usize,
    /// `agreeing / cells`; `None` with no cells.
    pub share: Option<f64>,
    /// Mean absolute differences in normalized reward and cost.
    pub mean_abs_reward_difference: Option<f64>,
    pub mean_abs_cost_difference: Option<f64>,
    /// What trivial rules would agree on over the same cells, for scale: the share expected by chance from the two
    /// tables' safe rates (ours `s`, the paper's `p`: `s·p + (1−s)(1−p)`), and the shares of "every method unsafe"
    /// and "BC-Safe safe, every other method unsafe". `None` with no cells.
    pub chance_share: Option<f64>,
    pub all_unsafe_share: Option<f64>,
    pub bc_safe_rule_share: Option<f64>,
}

/// The benchmark's fidelity goal: at least this share of (task, method) verdicts agreeing with the paper's (and
/// more than any trivial rule's).
pub const FIDELITY_GOAL: f64 = 0.8;

/// The verdict of the trivial rule "BC-Safe is safe, every other method is unsafe".
fn bc_safe_rule(method: &str) -> bool {
    method == "BC-Safe"
}

/// The agreement over `cells`, with the trivial rules' beside it, named `scope`.
pub fn summary_of(scope: &str, cells: &[&Agreement]) -> AgreementSummary {
    let n = cells.len();
    let share = |count: usize| (n > 0).then(|| count as f64 / n as f64);
    let mean = |f: fn(&Agreement) -> f64| (n > 0).then(|| cells.iter().map(|c| f(c).abs()).sum::<f64>() / n as f64);
    let agreeing = cells.iter().filter(|c| c.verdict_agrees).count();
    let ours_safe = share(cells.iter().filter(|c| c.safe).count());
    let paper_safe = share(cells.iter().filter(|c| c.paper_safe).count());
    AgreementSummary {
        scope: scope.to_owned(),
        cells: n,
        agreeing,
        share: share(agreeing),
        mean_abs_reward_difference: mean(|c| c.reward_difference),
        mean_abs_cost_difference: mean(|c| c.cost_difference),
        chance_share: ours_safe.zip(paper_safe).map(|(s, p)| s * p + (1.0 - s) * (1.0 - p)),
        all_unsafe_share: share(cells.iter().filter(|c| !c.paper_safe).count()),
        bc_safe_rule_share: share(cells.iter().filter(|c| bc_safe_rule(&c.method) == c.paper_safe).count()),
    }
}

/// The mean of one (task, method)'s scores over its training seeds, as the paper averages its seeds: what our
/// verdict on a cell is taken from. Called with at least one score (none gives NaN).
pub fn mean_over_seeds(scores: impl ExactSizeIterator<Item = NormalizedScore> + Clone) -> NormalizedScore {
    let n = scores.len() as f64;
    NormalizedScore {
        reward: scores.clone().map(|s| s.reward).sum::<f64>() / n,
        cost: scores.map(|s| s.cost).sum::<f64>() / n,
    }
}

/// Every (task, method) that both our entries and the paper's table have, in catalog then method order. Our
/// verdict uses the benchmark's rule (normalized cost at most 1) on the mean over seeds.
pub fn agreement(catalog: &Catalog, paper: &PaperResults, ours: &[ScoredEntry]) -> Vec<Agreement> {
    let mut cells = Vec::new();
    for task in catalog.tasks() {
        for method in PAPER_METHODS {
            let Some(row) = paper.get(task.id.as_str(), method) else {
                continue;
            };
            let seeds: Vec<&ScoredEntry> = ours
                .iter()
                .filter(|e| e.task == task.id.as_str() && e.method == method)
                .collect();
            if seeds.is_empty() {
                continue;
            }
            let mean = mean_over_seeds(seeds.iter().map(|e| e.score));
            let (reward, cost, safe) = (mean.reward, mean.cost, mean.is_safe());
            cells.push(Agreement {
                task: task.id.to_string(),
                method: method.to_owned(),
                seeds: seeds.len(),
                normalized_reward: reward,
                normalized_cost: cost,
                paper_normalized_reward: row.normalized_reward,
                paper_normalized_cost: row.normalized_cost,
                reward_difference: reward - row.normalized_reward,
                cost_difference: cost - row.normalized_cost,
                safe,
                paper_safe: row.safe,
                verdict_agrees: safe == row.safe,
            });
        }
    }
    cells
}

/// Per family (the paper's three) and over all cells.
pub fn summarize(catalog: &Catalog, cells: &[Agreement]) -> Vec<AgreementSummary> {
    let mut scopes: BTreeMap<&str, Vec<&Agreement>> = BTreeMap::new();
    for scope in ["bullet", "safety-gymnasium", "metadrive"] {
        scopes.insert(scope, Vec::new());
    }
    for cell in cells {
        if let Ok(task) = catalog.get(&cell.task) {
            scopes.entry(task.family.suite()).or_default().push(cell);
        }
    }
    let mut out: Vec<AgreementSummary> = ["bullet", "safety-gymnasium", "metadrive"]
        .iter()
        .map(|scope| summary_of(scope, &scopes[scope]))
        .collect();
    let all: Vec<&Agreement> = cells.iter().collect();
    out.push(summary_of("all", &all));
    out
}

/// Per method (the paper's, in its order), over every task: which methods our entries reproduce.
pub fn summarize_by_method(cells: &[Agreement]) -> Vec<AgreementSummary> {
    PAPER_METHODS
        .iter()
        .filter_map(|method| {
            let of: Vec<&Agreement> = cells.iter().filter(|c| c.method == *method).collect();
            (!of.is_empty()).then(|| summary_of(method, &of))
        })
        .collect()
}

/// A made-up reference entry on `task` for tests: two episodes at each of the task's thresholds, each with the given
/// returns; its checkpoint digest names the method and seed, its protocol version is `p1.x`. Never a result.
pub fn synthetic_entry(task: &Task, method: &str, seed: u64, reward_return: f64, cost_return: f64) -> ReferenceEntry {
    let episodes = task
        .cost_thresholds
        .iter()
        .flat_map(|&k| {
            (0..2).map(move |i| EpisodeResult {
                cost_threshold: k,
                episode: i,
                reward_return,
                cost_return,
                length: 10,
            })
        })
        .collect();
    ReferenceEntry {
        task: task.id.to_string(),
        method: method.into(),
        seed,
        training: TrainingBudget {
            steps: 10,
            batch_size: 512,
            models: 1,
            seconds: 1.0,
            cpu_seconds: 1.0,
            cpu: None,
            osrl_steps: 100_000,
            osrl_batch_size: 512,
        },
        dataset_version: "0".repeat(64),
        code_commit: "abc".into(),
        checkpoint_sha256: format!("{}{method}{seed}", task.id),
        protocol_version: "p1.x".into(),
        scoring: ScoringRecord {
            submission: 1,
            started_at: "a".into(),
            finished_at: "b".into(),
            seconds: 1.0,
            build: None,
        },
        episodes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(task: &str, method: &str, seed: u64, cost: f64) -> ReferenceEntry {
        let catalog = Catalog::embedded().unwrap();
        synthetic_entry(catalog.get(task).unwrap(), method, seed, 100.0, cost)
    }

    #[test]
    fn the_file_round_trips_in_a_fixed_order_and_refuses_duplicates() {
        let catalog = Catalog::embedded().unwrap();
        let mut entries = vec![
            entry("OfflineCarRun-v0", "CPQ", 0, 0.0),
            entry("OfflineBallRun-v0", "CDT", 1, 0.0),
            entry("OfflineBallRun-v0", "BC-All", 0, 0.0),
        ];
        let text = write_results(&entries);
        let read = read_results(&text, &catalog).unwrap();
        assert_eq!(
            read.iter()
                .map(|e| (e.task.as_str(), e.method.as_str()))
                .collect::<Vec<_>>(),
            [
                ("OfflineBallRun-v0", "BC-All"),
                ("OfflineBallRun-v0", "CDT"),
                ("OfflineCarRun-v0", "CPQ")
            ]
        );
        upsert(&mut entries, entry("OfflineCarRun-v0", "CPQ", 0, 5.0));
        assert_eq!(entries.len(), 3);
        let twice = format!("{text}{}", text.lines().next().unwrap());
        assert!(
            read_results(&twice, &catalog)
                .unwrap_err()
                .to_string()
                .contains("twice")
        );
        let mut wrong = entry("OfflineBallRun-v0", "BC-All", 0, 0.0);
        wrong.episodes[0].cost_threshold = 15.0;
        let e = read_results(&write_results(&[wrong]), &catalog).unwrap_err();
        assert!(e.to_string().contains("thresholds"), "{e}");
    }

    #[test]
    fn agreement_averages_seeds_and_compares_verdicts() {
        let catalog = Catalog::embedded().unwrap();
        let paper = PaperResults::embedded(&catalog).unwrap();
        // BallRun's thresholds are 10, 20, 40: cost 5 at each is 0.5, 0.25, 0.125 (mean 0.29); cost 50 is unsafe.
        let entries = [
            entry("OfflineBallRun-v0", "BC-All", 0, 5.0),
            entry("OfflineBallRun-v0", "BC-All", 1, 50.0),
            entry("OfflineBallRun-v0", "BC-Safe", 0, 5.0),
            entry("OfflineBallRun-v0", "CAPS", 0, 5.0),
        ];
        let scored = scored_entries(&entries, &catalog, "p1.x");
        assert_eq!(scored.len(), 4);
        assert!(scored_entries(&entries, &catalog, "p1.other").is_empty());
        let cells = agreement(&catalog, &paper, &scored);
        // CAPS is not in the paper.
        assert_eq!(cells.len(), 2);
        let all = &cells[0];
        assert_eq!((all.method.as_str(), all.seeds), ("BC-All", 2));
        let expected_cost = ((5.0 / 10.0 + 5.0 / 20.0 + 5.0 / 40.0) / 3.0 + (5.0 + 2.5 + 1.25) / 3.0) / 2.0;
        assert!((all.normalized_cost - expected_cost).abs() < 1e-12);
        let paper_row = paper.get("OfflineBallRun-v0", "BC-All").unwrap();
        assert_eq!(all.verdict_agrees, all.safe == paper_row.safe);
        assert_eq!(all.cost_difference, all.normalized_cost - paper_row.normalized_cost);
        let summary = summarize(&catalog, &cells);
        let bullet = summary.iter().find(|s| s.scope == "bullet").unwrap();
        let overall = summary.iter().find(|s| s.scope == "all").unwrap();
        assert_eq!((bullet.cells, overall.cells), (2, 2));
        assert_eq!(bullet.agreeing, cells.iter().filter(|c| c.verdict_agrees).count());
        let metadrive = summary.iter().find(|s| s.scope == "metadrive").unwrap();
        assert_eq!((metadrive.cells, metadrive.share), (0, None));
    }

    /// The agreement and its trivial baselines on a hand-made table, the answers counted by hand below.
    #[test]
    fn agreement_and_its_baselines_on_a_hand_made_table() {
        // (method, ours safe, paper safe), on Bullet tasks unless marked.
        let cell = |task: &str, method: &str, safe: bool, paper_safe: bool| Agreement {
            task: task.to_owned(),
            method: method.to_owned(),
            seeds: 1,
            normalized_reward: 0.5,
            normalized_cost: if safe { 0.5 } else { 2.0 },
            paper_normalized_reward: 0.25,
            paper_normalized_cost: if paper_safe { 0.75 } else { 1.5 },
            reward_difference: 0.25,
            cost_difference: if safe { 0.5 } else { 2.0 } - if paper_safe { 0.75 } else { 1.5 },
            safe,
            paper_safe,
            verdict_agrees: safe == paper_safe,
        };
        let cells = [
            cell("OfflineBallRun-v0", "BC-Safe", true, true),
            cell("OfflineBallRun-v0", "BC-All", true, false),
            cell("OfflineBallRun-v0", "CPQ", false, false),
            cell("OfflineCarRun-v0", "BC-Safe", false, true),
            cell("OfflineCarRun-v0", "CPQ", false, true),
            cell("OfflinePointGoal1Gymnasium-v0", "BC-Safe", true, false),
        ];
        let catalog = Catalog::embedded().unwrap();
        let summaries = summarize(&catalog, &cells);
        let get = |scope: &str| summaries.iter().find(|s| s.scope == scope).unwrap().clone();
        let (bullet, gymnasium, all) = (get("bullet"), get("safety-gymnasium"), get("all"));
        // Bullet: 5 cells; verdicts agree on BallRun's BC-Safe and CPQ: 2 of 5.
        assert_eq!((bullet.cells, bullet.agreeing, bullet.share), (5, 2, Some(0.4)));
        // Ours safe on 2 of 5, the paper's on 3 of 5: chance = 0.4·0.6 + 0.6·0.4 = 0.48.
        assert!((bullet.chance_share.unwrap() - 0.48).abs() < 1e-12);
        // "All unsafe" agrees where the paper is unsafe: BallRun's BC-All and CPQ, 2 of 5.
        assert_eq!(bullet.all_unsafe_share, Some(0.4));
        // "BC-Safe safe, the rest unsafe": BallRun BC-Safe, BC-All and CPQ, CarRun BC-Safe; not CarRun CPQ: 4 of 5.
        assert_eq!(bullet.bc_safe_rule_share, Some(0.8));
        // Safety-Gymnasium: one cell, BC-Safe safe where the paper's is unsafe.
        assert_eq!((gymnasium.cells, gymnasium.agreeing), (1, 0));
        assert_eq!(
            (
                gymnasium.chance_share,
                gymnasium.all_unsafe_share,
                gymnasium.bc_safe_rule_share
            ),
            (Some(0.0), Some(1.0), Some(0.0))
        );
        // All 6: 2 agree; ours safe 3/6, the paper's 3/6: chance 0.5; all unsafe 3/6; the BC-Safe rule 4/6.
        assert_eq!((all.cells, all.agreeing), (6, 2));
        assert!((all.chance_share.unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(all.all_unsafe_share, Some(0.5));
        assert!((all.bc_safe_rule_share.unwrap() - 4.0 / 6.0).abs() < 1e-12);
        // |Δ cost| over Bullet: 0.25, 1.0, 0.5, 1.25, 1.25 → 4.25 / 5.
        assert!((bullet.mean_abs_cost_difference.unwrap() - 0.85).abs() < 1e-12);
        // Per method: BC-Safe 1 of 3, BC-All 0 of 1, CPQ 1 of 2, in the paper's method order.
        let methods = summarize_by_method(&cells);
        let by: Vec<(&str, usize, usize)> = methods
            .iter()
            .map(|m| (m.scope.as_str(), m.cells, m.agreeing))
            .collect();
        assert_eq!(by, [("BC-All", 1, 0), ("BC-Safe", 3, 1), ("CPQ", 2, 1)]);
    }
}
