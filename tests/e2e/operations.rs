//! The leaderboard's operations, on real simulator workers with two episodes per threshold (the protocol's count
//! does not matter here, only the queue's behaviour): supervised evaluators, checked worker answers, policy
//! processes with deadlines, failures classified by whose they are, a fair queue that shows positions and
//! estimates, counts beside scores, and the board as data.

use std::time::Duration;

use crate::leaderboard::{TASK, client, create_user, submit, train_bc};
use crate::{Env, get_json, make_policy, s};

/// A scoring server for these tests: `workers` local simulator workers, two episodes per threshold, and `extra`.
fn ops_env(workers: &str, extra: &[(&str, &str)]) -> Env {
    let binary = dsrl_e2e::bin("dsrl-sim-worker").display().to_string();
    let mut envs = vec![
        ("DSRL__SIMULATORS__LOCAL_WORKERS", workers),
        ("DSRL__SIMULATORS__WORKER_BINARY", binary.as_str()),
        ("DSRL__LEADERBOARD__EPISODES_PER_THRESHOLD", "2"),
        ("DSRL__LEADERBOARD__ENVS_PER_SESSION", "2"),
        ("DSRL__LEADERBOARD__LEASE_SECONDS", "6"),
    ];
    envs.extend_from_slice(extra);
    let dir = tempfile::tempdir().unwrap();
    let flags = crate::leaderboard::hosting_the_starter(dir.path());
    let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
    Env::with_kept(dir, &flags, &envs)
}

fn status(env: &Env, id: &serde_json::Value) -> serde_json::Value {
    get_json(&format!("{}/v1/submissions/{id}", env.server.url))
}

fn wait_for_state(env: &Env, id: &serde_json::Value, states: &[&str], within: Duration) -> serde_json::Value {
    let mut last = serde_json::Value::Null;
    let reached = dsrl_e2e::wait_for(within, || {
        last = status(env, id);
        states.iter().any(|s| last["state"] == *s)
    });
    assert!(reached, "submission {id} never reached {states:?}: {last}");
    last
}

/// The pid of a `play-policy` child of the process `parent`.
fn policy_child(parent: u32) -> Option<u32> {
    std::fs::read_dir("/proc").ok()?.flatten().find_map(|entry| {
        let pid: u32 = entry.file_name().to_str()?.parse().ok()?;
        let stat = std::fs::read_to_string(entry.path().join("stat")).ok()?;
        let ppid: u32 = stat.rsplit(')').next()?.split_whitespace().nth(1)?.parse().ok()?;
        let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
        (ppid == parent && cmdline.windows(11).any(|w| w == b"play-policy")).then_some(pid)
    })
}

fn signal(pid: u32, signal: i32) {
    // SAFETY: kill(2) with a pid this test found among its server's children.
    assert_eq!(unsafe { libc_kill(pid as i32, signal) }, 0, "kill {pid}");
}

unsafe extern "C" {
    #[link_name = "kill"]
    fn libc_kill(pid: i32, sig: i32) -> i32;
}
const SIGKILL: i32 = 9;
const SIGSTOP: i32 = 19;

fn metric(env: &Env, name: &str) -> f64 {
    let text = crate::leaderboard::reqwest_text(&format!("{}/metrics", env.server.url));
    text.lines()
        .find(|l| l.starts_with(name) && l[name.len()..].starts_with(' '))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.0)
}

#[test]
fn a_panicking_evaluator_is_restarted_its_job_ends_with_the_reason_and_the_next_is_scored() {
    let models = tempfile::tempdir().unwrap();
    train_bc(models.path(), "all", 0);
    train_bc(models.path(), "safe", 0);
    // The test-only fault hook of debug builds: the evaluator that claims a submission of this name panics.
    let env = ops_env(
        "1",
        &[
            ("DSRL_TEST_PANIC_ON_NAME", "panic-me"),
            ("DSRL__LEADERBOARD__MAX_ATTEMPTS", "2"),
        ],
    );
    let alice = create_user(&env, "alice");
    let bad = submit(&env, &alice, &models.path().join("bc-all"), "panic-me")
        .ok()
        .json();
    let good = submit(&env, &alice, &models.path().join("bc-safe"), "BC-Safe")
        .ok()
        .json();
    let failed = wait_for_state(&env, &bad["id"], &["failed"], Duration::from_secs(120));
    let reason = failed["reason"].as_str().unwrap();
    assert!(reason.contains("test fault") && reason.contains("attempts"), "{failed}");
    assert_eq!(failed["failure"], "infrastructure", "{failed}");
    let done = wait_for_state(&env, &good["id"], &["finished"], Duration::from_secs(180));
    assert_eq!(done["episodes"].as_array().unwrap().len(), 6, "{done}");
    // Counted and shown, and running again.
    assert!(metric(&env, "dsrl_evaluator_restarts_total") >= 2.0);
    let health = get_json(&format!("{}/healthz", env.server.url));
    assert_eq!(health["status"], "ok", "{health}");
    let evaluator = &health["evaluators"][0];
    assert_eq!(evaluator["running"], true, "{health}");
    assert!(evaluator["restarts"].as_u64().unwrap() >= 2, "{health}");
    assert!(
        evaluator["last_panic"].as_str().unwrap().contains("test fault"),
        "{health}"
    );
}

#[test]
fn a_worker_answering_out_of_protocol_fails_the_job_as_infrastructure_and_it_may_be_submitted_again() {
    let models = tempfile::tempdir().unwrap();
    train_bc(models.path(), "all", 0);
    // A real worker with a test-only fault: its first answer to a step (or to a play, where the policy acts in the
    // worker) leaves out a row. `--exit-with-stdin`: dropping `worker` (a failed assertion too) closes its stdin, and
    // the worker exits rather than outliving the test.
    let mut worker = std::process::Command::new(dsrl_e2e::bin("dsrl-sim-worker"))
        .args([
            "--listen",
            "127.0.0.1:0",
            "--exit-with-stdin",
            "--inject-fault",
            "short-step-answers=1",
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .stdin(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(worker.stdout.take().unwrap()), &mut line).unwrap();
    let address = line.trim().rsplit(' ').next().unwrap().to_owned();
    let env = ops_env(
        "0",
        &[
            ("DSRL__SIMULATORS__REMOTE_WORKERS", &format!("[\"{address}\"]")),
            ("DSRL__LEADERBOARD__MAX_ATTEMPTS", "1"),
        ],
    );
    let alice = create_user(&env, "alice");
    let first = submit(&env, &alice, &models.path().join("bc-all"), "BC-All")
        .ok()
        .json();
    let failed = wait_for_state(&env, &first["id"], &["failed"], Duration::from_secs(120));
    let reason = failed["reason"].as_str().unwrap();
    assert!(
        reason.contains("out of protocol") && reason.contains("simulator worker remote-0"),
        "the reason names the fault and the worker: {failed}"
    );
    assert_eq!(failed["failure"], "infrastructure");
    // Not the checkpoint's fault: the same checkpoint may be submitted again, and it is scored.
    let again = submit(&env, &alice, &models.path().join("bc-all"), "BC-All")
        .ok()
        .json();
    let done = wait_for_state(&env, &again["id"], &["finished"], Duration::from_secs(180));
    assert_eq!(done["checkpoint_sha256"], failed["checkpoint_sha256"]);
    let _ = worker.kill();
    let _ = worker.wait();
}

#[test]
fn a_policy_process_starved_or_killed_from_outside_gives_its_job_back() {
    let models = tempfile::tempdir().unwrap();
    train_bc(models.path(), "all", 0);
    train_bc(models.path(), "safe", 1);
    // The BC networks act in policy processes (they would otherwise act in the workers), which this stops and kills.
    let env = ops_env(
        "1",
        &[
            ("DSRL__LEADERBOARD__POLICY_REQUEST_SECONDS", "3"),
            ("DSRL__LEADERBOARD__ACT_IN_WORKERS_MAX_MULTIPLY_ADDS", "0"),
        ],
    );
    let alice = create_user(&env, "alice");
    let stopped = submit(&env, &alice, &models.path().join("bc-all"), "BC-All")
        .ok()
        .json();
    wait_for_state(&env, &stopped["id"], &["running"], Duration::from_secs(120));
    let mut child = None;
    assert!(dsrl_e2e::wait_for(Duration::from_secs(30), || {
        child = policy_child(env.server.pid());
        child.is_some()
    }));
    // Stopped, as a process starved by other work (or in swap) is: it uses none of its 3 s of CPU time, so its
    // request ends on the clock, at four times the budget, and not as the checkpoint's fault. The job goes back to
    // the queue and a fresh policy process scores it.
    let started = std::time::Instant::now();
    signal(child.unwrap(), SIGSTOP);
    let done = wait_for_state(&env, &stopped["id"], &["finished", "failed"], Duration::from_secs(180));
    assert_eq!(done["state"], "finished", "{done}");
    assert_eq!(done["attempts"], 2, "scored again after the stopped process: {done}");
    assert!(started.elapsed() >= Duration::from_secs(12), "{:?}", started.elapsed());

    // Killed from outside: not the checkpoint's fault; the job goes back to the queue and is scored.
    let killed = submit(&env, &alice, &models.path().join("bc-safe"), "BC-Safe")
        .ok()
        .json();
    wait_for_state(&env, &killed["id"], &["running"], Duration::from_secs(120));
    let mut child = None;
    assert!(dsrl_e2e::wait_for(Duration::from_secs(30), || {
        child = policy_child(env.server.pid());
        child.is_some()
    }));
    signal(child.unwrap(), SIGKILL);
    let done = wait_for_state(&env, &killed["id"], &["finished", "failed"], Duration::from_secs(180));
    assert_eq!(done["state"], "finished", "{done}");
    assert_eq!(done["attempts"], 2, "re-run after the kill: {done}");
}

#[test]
fn the_queue_is_fair_shows_positions_and_counts_and_the_board_downloads_as_data() {
    let dir = tempfile::tempdir().unwrap();
    let env = ops_env("1", &[("DSRL__LEADERBOARD__CONCURRENT_SUBMISSIONS", "5")]);
    let (alice, bob) = (create_user(&env, "alice"), create_user(&env, "bob"));
    // Every policy is made first, so the four submissions follow each other closely.
    let policies: Vec<_> = [1, 2, 3, 9]
        .iter()
        .map(|&seed| make_policy(&dir.path().join(format!("p{seed}")), TASK, "target-cost-mlp", seed))
        .collect();
    // Alice queues three, then Bob one: Bob's waits behind at most the job being scored.
    let a: Vec<serde_json::Value> = (0..3)
        .map(|i| {
            submit(&env, &alice, &policies[i], &format!("alice-{}", i + 1))
                .ok()
                .json()
        })
        .collect();
    let b = submit(&env, &bob, &policies[3], "bob").ok().json();
    let queued = status(&env, &b["id"]);
    if queued["state"] == "queued" {
        // The CLI shows the queue place.
        let out = client(&env, &bob, &["status", &b["id"].to_string()]).ok();
        assert!(out.stdout.contains("queue position"), "{}", out.stdout);
    }
    let done: Vec<serde_json::Value> = a
        .iter()
        .chain([&b])
        .map(|s| wait_for_state(&env, &s["id"], &["finished"], Duration::from_secs(300)))
        .collect();
    assert!(done.iter().all(|d| d["author_submissions_to_task"].as_u64().is_some()));

    // Counts beside scores, on the table and on the user's page.
    let board = get_json(&format!("{}/v1/leaderboard?task={TASK}", env.server.url));
    // Its layout (2 environments per threshold) is part of its protocol: the same episodes on the default layout
    // would be another version.
    assert_eq!(board["protocol"]["envs_per_session"], 2);
    let catalog = dsrl_suite::Catalog::embedded().unwrap();
    assert_eq!(
        board["protocol"]["version"],
        dsrl_evaluation::protocol::current(&catalog, 2, 2).version
    );
    assert_ne!(
        board["protocol"]["version"],
        dsrl_evaluation::protocol::current(&catalog, 2, 5).version
    );
    let entries = board["tasks"][0]["entries"].as_array().unwrap();
    for e in entries {
        let expected = if e["user"] == "alice" { 3 } else { 1 };
        assert_eq!(e["author_submissions_to_task"], expected, "{e}");
    }
    let mine = get_json(&format!("{}/v1/users/alice/submissions", env.server.url));
    assert_eq!(mine.as_array().unwrap().len(), 3);
    let page = crate::leaderboard::reqwest_text(&format!("{}/users/alice", env.server.url));
    assert_eq!(page.matches("href=\"/submissions/").count(), 3, "{page}");

    // The board as data: CSV and Parquet read back by pyarrow hold every entry and the paper's rows.
    let csv = dir.path().join("board.csv");
    let parquet = dir.path().join("board.parquet");
    for (url, file) in [
        (format!("{}/v1/leaderboard.csv", env.server.url), &csv),
        (format!("{}/v1/leaderboard.parquet", env.server.url), &parquet),
    ] {
        let bytes = crate::block_on(async move { reqwest::get(url).await.unwrap().bytes().await.unwrap() });
        std::fs::write(file, bytes).unwrap();
    }
    let episodes = dir.path().join("episodes.csv");
    let url = format!("{}/v1/submissions/{}/episodes.csv", env.server.url, b["id"]);
    let bytes = crate::block_on(async move { reqwest::get(url).await.unwrap().bytes().await.unwrap() });
    std::fs::write(&episodes, bytes).unwrap();
    let out = std::process::Command::new(dsrl_e2e::python())
        .arg("-c")
        .arg(
            "import sys, json, pyarrow as pa, pyarrow.csv as c, pyarrow.parquet as p\n\
             text = c.ConvertOptions(column_types={'finished_at': pa.string()}, strings_can_be_null=True)\n\
             a = c.read_csv(sys.argv[1], convert_options=text).to_pylist()\n\
             b = p.read_table(sys.argv[2]).to_pylist()\n\
             e = c.read_csv(sys.argv[3]).to_pylist()\n\
             print(json.dumps({'csv': a, 'parquet': b, 'episodes': e}))",
        )
        .args([s(&csv), s(&parquet), s(&episodes)])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let read: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let (csv_rows, parquet_rows) = (read["csv"].as_array().unwrap(), read["parquet"].as_array().unwrap());
    // The two exports are the same table, cell for cell, as pyarrow reads them.
    assert_eq!(csv_rows.len(), parquet_rows.len());
    for (c, p) in csv_rows.iter().zip(parquet_rows) {
        assert_eq!(c, p, "a CSV row differs from its Parquet row");
    }
    let entries: Vec<&serde_json::Value> = csv_rows
        .iter()
        .filter(|r| r["scope"] == "task" && r["kind"] == "entry")
        .collect();
    assert_eq!(entries.len(), 4);
    assert_eq!(csv_rows.iter().filter(|r| r["kind"] == "paper").count(), 38 * 7);
    assert_eq!(csv_rows.iter().filter(|r| r["kind"] == "published").count(), 26);
    // Each entry row is the board's entry: its rank, scores, interval, verdict, dataset and the build that scored it.
    let board_entries = board["tasks"][0]["entries"].as_array().unwrap();
    for row in &entries {
        let entry = board_entries
            .iter()
            .find(|e| e["submission"] == row["submission"])
            .unwrap_or_else(|| panic!("{row} is not on the board"));
        assert_eq!(row["rank"], entry["rank"]);
        assert_eq!(row["normalized_reward"], entry["normalized_reward"]);
        assert_eq!(row["normalized_cost"], entry["normalized_cost"]);
        assert_eq!(row["reward_low"], entry["normalized_reward_interval"]["low"]);
        assert_eq!(row["cost_high"], entry["normalized_cost_interval"]["high"]);
        assert_eq!(row["safe"], entry["safe"]);
        assert_eq!(row["protocol_version"], board["protocol"]["version"]);
        let scored_by = row["scored_by"].as_str().unwrap_or_default();
        assert!(scored_by.starts_with("dsrl-leaderboard "), "{row}");
        assert_eq!(row["scored_by"], entry["scored_by"]);
    }
    // Bob's episodes, as the submission's JSON has them.
    let episodes = read["episodes"].as_array().unwrap();
    let view = status(&env, &b["id"]);
    assert_eq!(episodes.len(), 6, "2 episodes x 3 thresholds");
    for (row, e) in episodes.iter().zip(view["episodes"].as_array().unwrap()) {
        assert_eq!(row, e, "episodes.csv differs from the submission's episodes");
    }
    assert_eq!(view["scored_by"], entries[0]["scored_by"]);
    // Scored here, by this tree's scorer on workers that imported this tree's simulator Python: the build's own
    // label, with no mark for Python that differs from it (dsrl_leaderboard::scorer_build).
    assert_eq!(view["scored_by"], dsrl_leaderboard::SCORER_BUILD, "{view}");
}

/// The fair order, on a server without workers (nothing is claimed, so the order is seen whole): Alice queues three
/// jobs, then Bob one; Bob's is second in line (first in the second round would be FIFO's fourth), and Alice's third
/// waits behind both. A cancelled job leaves the line. The claim takes the head of this same order (the queue's
/// unit test claims through it).
#[test]
fn the_queue_serves_users_in_turn_not_first_come_first_served() {
    let dir = tempfile::tempdir().unwrap();
    let flags = crate::leaderboard::hosting_the_starter(dir.path());
    let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
    let env = Env::with_kept(dir, &flags, &[("DSRL__LEADERBOARD__CONCURRENT_SUBMISSIONS", "5")]);
    let (alice, bob) = (create_user(&env, "alice"), create_user(&env, "bob"));
    let policies = env.path("policies");
    let policy = |seed: u64| make_policy(&policies.join(format!("p{seed}")), TASK, "target-cost-mlp", seed);
    let a: Vec<serde_json::Value> = (1..=3)
        .map(|i| submit(&env, &alice, &policy(i), &format!("alice-{i}")).ok().json())
        .collect();
    let b = submit(&env, &bob, &policy(9), "bob").ok().json();
    let position = |s: &serde_json::Value| status(&env, &s["id"])["queue"]["position"].as_u64();
    assert_eq!(
        [position(&a[0]), position(&b), position(&a[1]), position(&a[2])],
        [Some(1), Some(2), Some(3), Some(4)],
        "round-robin over users: alice-1, bob, alice-2, alice-3"
    );
    // Cancelled, alice-1 leaves the line: alice-2 is now her first waiting job, in the first round with Bob's, and
    // neither user has been served, so the older goes first.
    client(&env, &alice, &["cancel", &a[0]["id"].to_string()]).ok();
    assert_eq!(
        [position(&a[1]), position(&b), position(&a[2])],
        [Some(1), Some(2), Some(3)]
    );
}
