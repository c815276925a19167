//! The leaderboard of record on a fresh server: the paper's rows for all 38 tasks, the committed reference results
//! imported as ranked reference entries that carry the protocol version they were scored under, and the agreement
//! with the paper equal to what the results file gives.

use dsrl_suite::Catalog;
use dsrl_suite::paper::{PAPER_METHODS, PaperResults};
use dsrl_suite::reference::{agreement, read_results, scored_entries, summarize};

use crate::{Env, get_json};

// Run by `hosted::the_default_server_hosts_every_starter_to_the_bar_and_shows_the_leaderboard_of_record`, on the
// one default server the read-only checks share.

/// On `env`'s server (reference import on): the paper's rows, the reference entries, the agreement, the pages; then
/// a restart imports nothing twice.
pub(crate) fn the_papers_rows_and_the_reference_entries_are_shown_under_their_protocol(env: &mut Env) {
    let catalog = Catalog::embedded().unwrap();
    let paper = PaperResults::embedded(&catalog).unwrap();
    let file = dsrl_e2e::repo_root().join("data/reference/results.jsonl");
    let entries = read_results(&std::fs::read_to_string(&file).unwrap(), &catalog).unwrap();
    let protocol = dsrl_evaluation::protocol::current(&catalog, 20, 5);
    let current: Vec<_> = entries
        .iter()
        .filter(|e| e.protocol_version == protocol.version)
        .collect();
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
        // Every reference entry of the current protocol is in its task's table, ranked, with its record; the scores
        // are the file's episodes scored.
        let listed: Vec<&serde_json::Value> = table["entries"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|e| !e["reference"].is_null())
            .collect();
        // Tasks the reference sweep has not reached yet have none (data/reference/README.md counts them).
        let expected: Vec<_> = current.iter().filter(|e| e.task == id).collect();
        assert_eq!(listed.len(), expected.len(), "{id}");
        for e in expected {
            let name = dsrl_leaderboard::reference::entry_name(&e.method, e.seed);
            let shown = listed
                .iter()
                .find(|l| l["name"] == name.as_str())
                .unwrap_or_else(|| panic!("{id}: {name} is not shown"));
            let score = e.score(task).unwrap();
            assert_eq!(shown["user"], dsrl_leaderboard::users::REFERENCE_USER);
            assert_eq!(shown["protocol_version"], protocol.version.as_str());
            assert_eq!(shown["dataset_version"], e.dataset_version.as_str());
            assert_eq!(shown["reference"]["method"], e.method.as_str());
            assert_eq!(shown["reference"]["seed"], e.seed);
            assert_eq!(shown["reference"]["training"]["steps"], e.training.steps);
            assert_eq!(shown["reference"]["code_commit"], e.code_commit.as_str());
            assert_eq!(shown["normalized_reward"].as_f64().unwrap(), score.reward);
            assert_eq!(shown["normalized_cost"].as_f64().unwrap(), score.cost);
            let interval = &shown["normalized_cost_interval"];
            assert!(
                interval["low"].as_f64().unwrap() <= score.cost && score.cost <= interval["high"].as_f64().unwrap()
            );
        }
        let earlier = entries
            .iter()
            .filter(|e| e.task == id && e.protocol_version != protocol.version)
            .count();
        assert_eq!(table["earlier_protocol_entries"], earlier, "{id}");
    }

    // The agreement figures are what the results file gives.
    let cells = agreement(&catalog, &paper, &scored_entries(&entries, &catalog, &protocol.version));
    assert!(!cells.is_empty());
    assert_eq!(
        board["agreement"],
        serde_json::to_value(summarize(&catalog, &cells)).unwrap()
    );
    for table in tables {
        let task_cells: Vec<_> = cells.iter().filter(|c| c.task == table["task"]).collect();
        assert_eq!(table["agreement"], serde_json::to_value(&task_cells).unwrap());
    }

    // The pages: every task's paper rows, and the summary.
    let page = crate::leaderboard::reqwest_text(&format!("{}/leaderboard", env.server.url));
    assert_eq!(page.matches("<tr class=\"paper-row\">").count(), 38 * 7);
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
    assert_eq!(summary.matches("<tr class=\"agrees\">").count(), overall.agreeing);

    // A restart imports nothing twice; an entry whose record changed in the file (its checkpoints reproduced by
    // another commit: same digest, same scoring) is brought up to the file's record. Here the server's copy of one
    // record is made an older one, as a server that imported an earlier file would hold.
    let (task, e) = current
        .iter()
        .map(|e| (catalog.get(&e.task).unwrap(), e))
        .next()
        .unwrap();
    let row = |board: &serde_json::Value| {
        let table = board["tasks"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["task"] == task.id.as_str())
            .unwrap();
        let name = dsrl_leaderboard::reference::entry_name(&e.method, e.seed);
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
    assert_eq!(count(&board), current.len());
}
