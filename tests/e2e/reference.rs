//! The leaderboard of record on a fresh server: the paper's rows for all 38 tasks, the committed reference results
//! imported as ranked reference entries that carry the protocol version they were scored under, and the agreement
//! with the paper equal to what the results file gives.

use dsrl_leaderboard::reference::{TrainingData, entry_name, method_label};
use dsrl_scoring::paper::{PAPER_METHODS, PaperResults};
use dsrl_scoring::reference::{ReferenceEntry, agreement, read_results, scored_entries, summarize};
use dsrl_suite::Catalog;

use crate::{Env, get_json};

// Run by `hosted::the_default_server_hosts_every_starter_to_the_bar_and_shows_the_leaderboard_of_record`, on the
// one default server the read-only checks share.

/// On `env`'s server (reference import on): the paper's rows, the reference entries, the agreement, the pages; then
/// a restart imports nothing twice.
pub(crate) fn the_papers_rows_and_the_reference_entries_are_shown_under_their_protocol(env: &mut Env) {
    let catalog = Catalog::embedded().unwrap();
    let paper = PaperResults::embedded(&catalog).unwrap();
    let read = |path: &str| {
        let file = dsrl_e2e::repo_root().join(path);
        read_results(&std::fs::read_to_string(&file).unwrap(), &catalog).unwrap()
    };
    // The starter-trained entries and those trained on the full builds, each with its kind.
    let starter_entries = read("data/reference/results.jsonl");
    let full_build_entries = read("data/reference/full_builds.jsonl");
    let entries: Vec<(TrainingData, &ReferenceEntry)> = starter_entries
        .iter()
        .map(|e| (TrainingData::Starter, e))
        .chain(full_build_entries.iter().map(|e| (TrainingData::FullBuild, e)))
        .collect();
    let protocol = dsrl_evaluation::protocol::current(&catalog, 20, 5);
    let current: Vec<(TrainingData, &ReferenceEntry)> = entries
        .iter()
        .copied()
        .filter(|(_, e)| e.protocol_version == protocol.version)
        .collect();
    assert!(
        current.iter().any(|(kind, _)| *kind == TrainingData::FullBuild),
        "a fresh server shows entries trained on the full builds"
    );
    assert!(
        !current.is_empty(),
        "a fresh server shows reference entries of protocol {}",
        protocol.version
    );

    let board = get_json(&format!("{}/v1/leaderboard", env.server.url));
    assert_eq!(board["protocol"]["version"], protocol.version.as_str());
    assert_eq!(board["protocol"]["episodes_per_threshold"], 20);
    assert_eq!(board["protocol"]["envs_per_session"], 5);
    let tables = board["tasks"].as_array().unwrap();
    assert_eq!(tables.len(), 38, "every task has a table: the paper's rows at least");
    for (table, task) in tables.iter().zip(catalog.tasks()) {
        let id = task.id.as_str();
        assert_eq!(table["task"], id);
        let rows = table["paper"].as_array().unwrap();
        let methods: Vec<&str> = rows.iter().map(|r| r["method"].as_str().unwrap()).collect();
        assert_eq!(methods, PAPER_METHODS, "{id}");
        for row in rows {
            let expected = paper.get(id, row["method"].as_str().unwrap()).unwrap();
            assert_eq!(row["normalized_reward"].as_f64().unwrap(), expected.normalized_reward);
            assert_eq!(row["normalized_cost"].as_f64().unwrap(), expected.normalized_cost);
            assert_eq!(row["safe"], expected.safe);
        }
        // The rows methods beyond the paper publish for the task, each with its citation and protocol.
        let published = dsrl_scoring::published::PublishedResults::embedded(&catalog).unwrap();
        let expected = published.for_task(id);
        assert_eq!(table["published"], serde_json::to_value(&expected).unwrap(), "{id}");
        // Every reference entry of the current protocol is in its task's table with its record; a method's several
        // training seeds (same budget and dataset) are one row, the mean over them with an interval over seeds and
        // episodes, each seed reachable from it; the scores are the file's episodes scored.
        let listed: Vec<&serde_json::Value> = table["entries"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|e| !e["reference"].is_null())
            .collect();
        // Tasks the reference sweep has not reached yet have none (data/reference/README.md counts them).
        // Starter-trained and full-build entries of a method are apart: their datasets differ.
        let expected: Vec<_> = current.iter().filter(|(_, e)| e.task == id).collect();
        let mut groups: Vec<(TrainingData, Vec<&ReferenceEntry>)> = Vec::new();
        for (kind, e) in expected {
            let same = |o: &ReferenceEntry| {
                o.method == e.method
                    && o.training.steps == e.training.steps
                    && o.training.batch_size == e.training.batch_size
                    && o.dataset_version == e.dataset_version
            };
            match groups.iter_mut().find(|(k, g)| k == kind && same(g[0])) {
                Some((_, g)) => g.push(e),
                None => groups.push((*kind, vec![e])),
            }
        }
        assert_eq!(listed.len(), groups.len(), "{id}: one row per method's seeds");
        for (kind, group) in groups {
            let e = group[0];
            let dataset = serde_json::to_value(kind).unwrap();
            let shown = if group.len() == 1 {
                let name = entry_name(&e.method, e.seed, kind);
                let shown = listed
                    .iter()
                    .find(|l| l["name"] == name.as_str())
                    .unwrap_or_else(|| panic!("{id}: {name} is not shown"));
                assert_eq!(shown["interval_covers"], "episodes", "{id}: {name}");
                assert!(shown["training_seeds"].as_array().unwrap().is_empty());
                assert_eq!(shown["reference"]["seed"], e.seed);
                assert_eq!(shown["reference"]["code_commit"], e.code_commit.as_str());
                shown
            } else {
                let shown = listed
                    .iter()
                    .find(|l| l["reference"]["method"] == e.method.as_str() && l["reference"]["dataset"] == dataset)
                    .unwrap_or_else(|| panic!("{id}: {}'s seeds ({}) are not one row", e.method, kind.as_str()));
                assert!(
                    shown["name"]
                        .as_str()
                        .unwrap()
                        .starts_with(&method_label(&e.method, kind)),
                    "{id}: {}",
                    shown["name"]
                );
                assert_eq!(shown["interval_covers"], "training seeds and episodes");
                let runs = shown["training_seeds"].as_array().unwrap();
                assert_eq!(runs.len(), group.len(), "{id} {}", e.method);
                for member in &group {
                    let run = runs
                        .iter()
                        .find(|r| r["seed"] == member.seed)
                        .unwrap_or_else(|| panic!("{id} {} seed {} is not reachable", e.method, member.seed));
                    let score = member.score(task).unwrap();
                    assert_eq!(run["normalized_cost"].as_f64().unwrap(), score.cost);
                    // Each seed's own page.
                    let page = crate::leaderboard::reqwest_text(&format!(
                        "{}/submissions/{}",
                        env.server.url,
                        run["submission"].as_i64().unwrap()
                    ));
                    assert!(page.contains(&e.method), "{id} {} seed {}", e.method, member.seed);
                }
                shown
            };
            let score = dsrl_scoring::reference::mean_over_seeds(
                group
                    .iter()
                    .map(|m| m.score(task).unwrap())
                    .collect::<Vec<_>>()
                    .into_iter(),
            );
            assert_eq!(shown["user"], dsrl_leaderboard::users::REFERENCE_USER);
            assert_eq!(shown["protocol_version"], protocol.version.as_str());
            assert_eq!(shown["dataset_version"], e.dataset_version.as_str());
            assert_eq!(shown["reference"]["method"], e.method.as_str());
            assert_eq!(shown["reference"]["dataset"], dataset);
            assert_eq!(shown["reference"]["training"]["steps"], e.training.steps);
            assert!((shown["normalized_reward"].as_f64().unwrap() - score.reward).abs() < 1e-12);
            assert!((shown["normalized_cost"].as_f64().unwrap() - score.cost).abs() < 1e-12);
            let interval = &shown["normalized_cost_interval"];
            assert!(
                interval["low"].as_f64().unwrap() <= score.cost && score.cost <= interval["high"].as_f64().unwrap()
            );
        }
        let earlier = entries
            .iter()
            .filter(|(_, e)| e.task == id && e.protocol_version != protocol.version)
            .count();
        assert_eq!(table["earlier_protocol_entries"], earlier, "{id}");
    }

    // The agreement figures are what the results files give, each file's entries apart from the other's.
    let cells = agreement(
        &catalog,
        &paper,
        &scored_entries(&starter_entries, &catalog, &protocol.version),
    );
    let full_build_cells = agreement(
        &catalog,
        &paper,
        &scored_entries(&full_build_entries, &catalog, &protocol.version),
    );
    assert!(!cells.is_empty() && !full_build_cells.is_empty());
    for (key, cells) in [("agreement", &cells), ("full_build_agreement", &full_build_cells)] {
        assert_eq!(board[key], serde_json::to_value(summarize(&catalog, cells)).unwrap());
        assert_eq!(
            board[format!("{key}_by_method")],
            serde_json::to_value(dsrl_scoring::reference::summarize_by_method(cells)).unwrap()
        );
        for table in tables {
            let task_cells: Vec<_> = cells.iter().filter(|c| c.task == table["task"]).collect();
            assert_eq!(table[key], serde_json::to_value(&task_cells).unwrap());
        }
    }

    // The pages: every task's paper rows, and the summary.
    let page = crate::leaderboard::reqwest_text(&format!("{}/leaderboard", env.server.url));
    assert_eq!(page.matches("<tr class=\"paper-row\">").count(), 38 * 7);
    // FISOR's table: 26 rows, each with its source beside it.
    assert_eq!(page.matches("<tr class=\"published-row\">").count(), 26);
    assert!(
        page.contains("ICLR 2024, Table 1"),
        "the published rows name their source"
    );
    assert!(page.contains(&format!("Protocol <strong>{}</strong>", protocol.version)));
    let summary = crate::leaderboard::reqwest_text(&format!("{}/leaderboard/agreement", env.server.url));
    let overall = summarize(&catalog, &cells).pop().unwrap();
    assert!(
        summary.contains(&format!(
            "<td>{} of {} ({:.0}%)</td>",
            overall.agreeing,
            overall.cells,
            100.0 * overall.share.unwrap()
        )),
        "{summary}"
    );
    // The trivial rules beside the agreement, on both pages, and the per-method table.
    for text in [&page, &summary] {
        assert!(
            text.contains(&format!(
                "<td class=\"baseline\">{:.0}%</td>",
                100.0 * overall.bc_safe_rule_share.unwrap()
            )),
            "the BC-Safe rule's share is shown"
        );
    }
    assert!(summary.contains("<table id=\"agreement-by-method\">"));
    // The full-build entries' agreement, apart, on both pages.
    let full = summarize(&catalog, &full_build_cells).pop().unwrap();
    for text in [&page, &summary] {
        assert!(text.contains("<table id=\"full-build-agreement\">"));
        assert!(text.contains(&format!(
            "<td>{} of {} ({:.0}%)</td>",
            full.agreeing,
            full.cells,
            100.0 * full.share.unwrap()
        )));
    }
    assert_eq!(
        summary.matches("<tr class=\"agrees\">").count(),
        overall.agreeing + full.agreeing
    );

    // Family tables rank only entries scored on every task of the family; the others are listed apart.
    for family in board["families"].as_array().unwrap() {
        let tasks = family["tasks"].as_u64().unwrap();
        let name = family["family"].as_str().unwrap();
        assert_eq!(
            tasks as usize,
            catalog.tasks().iter().filter(|t| t.family.suite() == name).count()
        );
        for (i, e) in family["entries"].as_array().unwrap().iter().enumerate() {
            assert_eq!(e["tasks"].as_u64().unwrap(), tasks, "{name}: {}", e["name"]);
            assert_eq!(e["rank"], i + 1);
        }
        for e in family["partial"].as_array().unwrap() {
            assert!(e["tasks"].as_u64().unwrap() < tasks);
            assert!(e["rank"].is_null());
        }
        // A reference method is one row over its training seeds.
        let names: Vec<&str> = family["entries"]
            .as_array()
            .unwrap()
            .iter()
            .chain(family["partial"].as_array().unwrap())
            .filter(|e| e["reference"] == true)
            .map(|e| e["name"].as_str().unwrap())
            .collect();
        let mut unique = names.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), names.len(), "{name}: {names:?}");
        let methods: Vec<String> = dsrl_scoring::reference::REFERENCE_METHODS
            .iter()
            .flat_map(|m| [TrainingData::Starter, TrainingData::FullBuild].map(|kind| method_label(m, kind)))
            .collect();
        assert!(names.iter().all(|n| methods.iter().any(|m| m == n)), "{names:?}");
    }

    // The pictures, by URL: a task's entries with the paper's rows (hollow squares), a family's aggregates.
    let svg = crate::leaderboard::reqwest_text(&format!("{}/leaderboard/plots/OfflineBallRun-v0.svg", env.server.url));
    assert!(
        svg.starts_with("<svg") && svg.contains("paper CPQ"),
        "{}",
        &svg[..svg.len().min(300)]
    );
    let svg = crate::leaderboard::reqwest_text(&format!("{}/leaderboard/plots/bullet.svg", env.server.url));
    assert!(svg.starts_with("<svg") && svg.contains("BC-Safe"));
    let url = format!("{}/leaderboard/plots/OfflineNope-v0.svg", env.server.url);
    let status = crate::block_on(async move { reqwest::get(&url).await.unwrap().status() });
    assert_eq!(status, 404);

    // A restart imports nothing twice; an entry whose record changed in the file (its checkpoints reproduced by
    // another commit: same digest, same scoring) is brought up to the file's record. Here the server's copy of one
    // record is made an older one, as a server that imported an earlier file would hold.
    // One whose method has a single seed on its task (a row of its own).
    let (task, kind, e) = current
        .iter()
        .filter(|(kind, e)| {
            current
                .iter()
                .filter(|(k, o)| k == kind && o.task == e.task && o.method == e.method)
                .count()
                == 1
        })
        .map(|(kind, e)| (catalog.get(&e.task).unwrap(), *kind, *e))
        .next()
        .unwrap();
    let row = |board: &serde_json::Value| {
        let table = board["tasks"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["task"] == task.id.as_str())
            .unwrap();
        let name = entry_name(&e.method, e.seed, kind);
        table["entries"]
            .as_array()
            .unwrap()
            .iter()
            .find(|r| r["name"] == name.as_str())
            .unwrap()
            .clone()
    };
    let id = row(&board)["submission"].as_i64().unwrap();
    let older = dsrl_leaderboard::reference::ReferenceRecord {
        method: e.method.clone(),
        seed: e.seed,
        training: e.training.clone(),
        code_commit: "000000000000-modified".into(),
        scoring: e.scoring.clone(),
        dataset: kind,
    };
    let db_file = env.server.data_dir.join("dsrl.sqlite3");
    crate::block_on(async move {
        let db = dsrl_service::db::Db::open(&db_file).await.unwrap();
        let older = serde_json::to_string(&older).unwrap();
        dsrl_leaderboard::queue::set_reference(&db, id, &older).await.unwrap();
    });
    let tampered = get_json(&format!("{}/v1/leaderboard", env.server.url));
    assert_eq!(row(&tampered)["reference"]["code_commit"], "000000000000-modified");
    env.restart();
    let again = get_json(&format!("{}/v1/leaderboard", env.server.url));
    let count = |b: &serde_json::Value| {
        b["tasks"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t["entries"].as_array().unwrap().len())
            .sum::<usize>()
    };
    assert_eq!(count(&again), count(&board));
    assert_eq!(row(&again)["reference"]["code_commit"], e.code_commit.as_str());
    assert_eq!(row(&again)["submission"], id, "updated in place, not imported again");
    let groups: std::collections::BTreeSet<(&str, &str, u64, &str)> = current
        .iter()
        .map(|(kind, e)| (e.task.as_str(), e.method.as_str(), e.training.steps, kind.as_str()))
        .collect();
    assert_eq!(count(&board), groups.len());
}
