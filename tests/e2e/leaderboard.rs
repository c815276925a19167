//! The leaderboard end to end: users and tokens, submissions checked and deduped and held to quotas (a server
//! without simulator workers, so submissions stay queued), malformed CDT declarations refused with the reason, and a
//! BC-All / BC-Safe pair trained by `dsrl-train` on the committed BallRun starter plus an (untrained) CDT, submitted,
//! scored on real simulator workers with held seeds and ranked; a server killed in the middle of an evaluation
//! re-runs the job after restart to exactly the same episodes.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use crate::{Env, block_on, get_json, s};

pub(crate) const TASK: &str = "OfflineBallRun-v0";
const SECRET: &str = "e2e-held-seed-secret";

pub(crate) fn starter() -> PathBuf {
    dsrl_e2e::repo_root().join("data/starter/OfflineBallRun-v0/SafetyBallRun-v0-80-1132.parquet")
}

/// Trains BC (a few hundred steps: the test needs real checkpoints, not good ones) into `out`.
pub(crate) fn train_bc(out: &Path, mode: &str, seed: u64) {
    let status = Command::new(dsrl_e2e::bin("dsrl-train"))
        .args([
            "bc",
            "--task",
            TASK,
            "--mode",
            mode,
            "--steps",
            "300",
            "--seed",
            &seed.to_string(),
        ])
        .arg("--dataset")
        .arg(starter())
        .arg("--out")
        .arg(out)
        .env_remove("DSRL_SERVER")
        .status()
        .unwrap();
    assert!(status.success(), "dsrl-train bc --mode {mode} failed");
}

/// Creates a user through the CLI and returns its token.
pub(crate) fn create_user(env: &Env, name: &str) -> String {
    let mut cli = env.cli.clone();
    cli.token = Some(env.server.token());
    let run = cli.run(&["admin", "create-user", name]).ok();
    run.stdout.trim().to_owned()
}

/// The CLI as the user holding `token`.
pub(crate) fn client(env: &Env, token: &str, args: &[&str]) -> dsrl_e2e::Run {
    dsrl_e2e::Run::from(env.cli.command(args).env("DSRL_TOKEN", token).output().unwrap())
}

pub(crate) fn submit(env: &Env, token: &str, dir: &Path, name: &str) -> dsrl_e2e::Run {
    client(
        env,
        token,
        &["--json", "submit", s(dir), "--task", TASK, "--name", name],
    )
}

/// A copy of a checkpoint folder with its policy.json changed by `edit`.
pub(crate) fn variant(from: &Path, to: &Path, edit: impl Fn(&mut serde_json::Value)) {
    std::fs::create_dir_all(to).unwrap();
    std::fs::copy(from.join("policy.safetensors"), to.join("policy.safetensors")).unwrap();
    let mut config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(from.join("policy.json")).unwrap()).unwrap();
    edit(&mut config);
    std::fs::write(to.join("policy.json"), serde_json::to_vec(&config).unwrap()).unwrap();
}

/// Files under `dir` (recursively; none when it does not exist).
fn walk_count(dir: &std::path::Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    entries
        .flatten()
        .map(|e| {
            let path = e.path();
            if path.is_dir() { walk_count(&path) } else { 1 }
        })
        .sum()
}

/// POSTs a multipart submission built by hand; returns the status, the error code and its message.
fn post_parts(url: &str, token: &str, parts: Vec<(&str, Vec<u8>)>) -> (u16, String, String) {
    let (url, token) = (format!("{url}/v1/submissions"), token.to_owned());
    let parts: Vec<(String, Vec<u8>)> = parts.into_iter().map(|(n, b)| (n.to_owned(), b)).collect();
    block_on(async move {
        let mut form = reqwest::multipart::Form::new()
            .percent_encode_noop()
            .text("task", TASK)
            .text("name", "hostile");
        for (name, bytes) in parts {
            form = form.part(name.clone(), reqwest::multipart::Part::bytes(bytes).file_name(name));
        }
        let response = reqwest::Client::new()
            .post(&url)
            .bearer_auth(&token)
            .multipart(form)
            .send()
            .await
            .unwrap();
        let status = response.status().as_u16();
        let body: serde_json::Value = response.json().await.unwrap_or_default();
        (
            status,
            body["error"]["code"].as_str().unwrap_or_default().to_owned(),
            body["error"]["message"].as_str().unwrap_or_default().to_owned(),
        )
    })
}

#[test]
fn submissions_are_checked_deduped_and_held_to_quotas() {
    let dir = tempfile::tempdir().unwrap();
    let flags = hosting_the_starter(dir.path());
    let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
    let env = Env::with_kept(
        dir,
        &flags,
        &[
            ("DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY", "3"),
            ("DSRL__LEADERBOARD__CONCURRENT_SUBMISSIONS", "2"),
        ],
    );
    let models = env.path("models");
    train_bc(&models, "all", 0);
    let bc_all = models.join("bc-all");

    let alice = create_user(&env, "alice");
    assert!(alice.starts_with("dsrl_"), "{alice}");
    let mut admin = env.cli.clone();
    admin.token = Some(env.server.token());
    assert_eq!(admin.run(&["admin", "create-user", "alice"]).code, 6, "a second alice");
    let mut anonymous = env.cli.clone();
    anonymous.token = None;
    assert_eq!(
        anonymous.run(&["admin", "create-user", "bob"]).code,
        2,
        "no admin token"
    );

    // Tokens: none is a usage error, a wrong one is refused.
    let run = env.cli.run(&["submit", s(&bc_all), "--task", TASK, "--name", "BC-All"]);
    assert_eq!(run.code, 2, "{run:?}");
    let run = submit(&env, "dsrl_not-a-token", &bc_all, "BC-All");
    assert_eq!(run.code, 7, "{run:?}");

    let first = submit(&env, &alice, &bc_all, "BC-All").ok().json();
    assert_eq!(first["state"], "queued");
    assert_eq!(first["attempts"], 0);
    assert_eq!(first["checkpoints"][0]["architecture"], "mlp_actor");
    let first_id = first["id"].as_i64().unwrap();

    // The same network again, with its JSON reformatted and a different training note: a duplicate.
    variant(&bc_all, &env.path("same"), |c| {
        c["training"] = serde_json::json!({"note": "resubmitted"})
    });
    let run = submit(&env, &alice, &env.path("same"), "BC-All-again");
    assert_eq!(run.code, 6, "{run:?}");
    assert!(run.stdout.contains(&format!("submission {first_id}")), "{run:?}");

    // Different networks (another max action) are new entries, up to the concurrency quota.
    let other = |i: u32| {
        let dir = env.path(&format!("variant-{i}"));
        variant(&bc_all, &dir, |c| {
            c["architecture"]["max_action"] = serde_json::json!(1.0 - f64::from(i) / 100.0)
        });
        dir
    };
    let second = submit(&env, &alice, &other(1), "BC-All-scaled").ok().json();
    let run = submit(&env, &alice, &other(2), "BC-All-scaled-2");
    assert_eq!(run.code, 6, "{run:?}");
    assert!(
        run.stdout.contains("resource_exhausted") && run.stdout.contains("at once"),
        "{run:?}"
    );
    // Cancelling frees a slot, and cancelled work does not count toward the day's quota: with the first queued and
    // two cancelled, a fourth of the day's three is accepted.
    let cancelled = client(&env, &alice, &["--json", "cancel", &second["id"].to_string()])
        .ok()
        .json();
    assert_eq!(cancelled["state"], "cancelled");
    let run = client(&env, &alice, &["cancel", &second["id"].to_string()]);
    assert_eq!(run.code, 6, "cancelling twice: {run:?}");
    let third = submit(&env, &alice, &other(2), "BC-All-scaled-2").ok().json();
    client(&env, &alice, &["cancel", &third["id"].to_string()]).ok();
    let fourth = submit(&env, &alice, &other(3), "BC-All-scaled-3").ok().json();
    assert_eq!(
        fourth["state"], "queued",
        "cancelled submissions were counted toward the day: {fourth}"
    );
    client(&env, &alice, &["cancel", &fourth["id"].to_string()]).ok();
    // Only the submitter cancels.
    let bob = create_user(&env, "bob");
    let run = client(&env, &bob, &["--json", "cancel", &first_id.to_string()]);
    assert_eq!(run.code, 7, "{run:?}");
    // It says what is wrong (it used to say the token was "not valid for admin operations").
    assert!(run.stdout.contains("belongs to another user"), "{run:?}");

    // Malformed and hostile checkpoints are 400s (413 over a file's limit) that say what is wrong.
    let config = std::fs::read(bc_all.join("policy.json")).unwrap();
    let weights = std::fs::read(bc_all.join("policy.safetensors")).unwrap();
    let url = &env.server.url;
    let mut wrong_task: serde_json::Value = serde_json::from_slice(&config).unwrap();
    wrong_task["task"] = "OfflineCarRun-v0".into();
    let mut wrong_dims: serde_json::Value = serde_json::from_slice(&config).unwrap();
    wrong_dims["obs_dim"] = 9.into();
    // A safetensors header that declares a terabyte-long header.
    let mut huge_header = (1u64 << 40).to_le_bytes().to_vec();
    huge_header.extend_from_slice(b"{}");
    type Parts<'a> = Vec<(&'a str, Vec<u8>)>;
    // Each case: what is wrong, the parts, and the status and words of the refusal.
    let cases: Vec<(&str, Parts, u16, &str)> = vec![
        (
            "no weights",
            vec![("policy.json", config.clone())],
            400,
            "policy.safetensors is missing",
        ),
        (
            "a stray file",
            vec![("policy.json", config.clone()), ("model.pt", b"x".to_vec())],
            400,
            "unexpected part \"model.pt\"",
        ),
        (
            "path escape",
            vec![("../policy.json", config.clone())],
            400,
            "unexpected part \"../policy.json\"",
        ),
        (
            "weights are not safetensors",
            vec![
                ("policy.json", config.clone()),
                ("policy.safetensors", b"garbage".to_vec()),
            ],
            400,
            "shorter than its 8-byte header length",
        ),
        (
            "a header length past the end",
            vec![("policy.json", config.clone()), ("policy.safetensors", huge_header)],
            400,
            "its header declares 1099511627776 bytes, more than the 262144 allowed",
        ),
        (
            "truncated weights",
            vec![
                ("policy.json", config.clone()),
                ("policy.safetensors", weights[..weights.len() / 2].to_vec()),
            ],
            400,
            "do not hold them inside the 136464 data bytes",
        ),
        (
            "declared for another task",
            vec![
                ("policy.json", serde_json::to_vec(&wrong_task).unwrap()),
                ("policy.safetensors", weights.clone()),
            ],
            400,
            "declared for OfflineCarRun-v0, not OfflineBallRun-v0",
        ),
        (
            "wrong dims",
            vec![
                ("policy.json", serde_json::to_vec(&wrong_dims).unwrap()),
                ("policy.safetensors", weights.clone()),
            ],
            400,
            "has observation dim 7 and action dim 2; the policy declares 9 and 2",
        ),
        (
            "policy.json over its limit",
            vec![("policy.json", vec![b' '; 70_000])],
            413,
            "the limit is 65536 bytes",
        ),
    ];
    let stored = |dir: &std::path::Path| walk_count(&dir.join("objects").join("submissions"));
    let before = stored(&env.server.data_dir);
    let listed_before = get_json(&format!("{url}/v1/users/alice/submissions"));
    for (what, parts, status, says) in cases {
        let (got, code, message) = post_parts(url, &alice, parts);
        assert_eq!(got, status, "{what}: {code} {message}");
        let expected_code = if status == 413 {
            "payload_too_large"
        } else {
            "invalid_argument"
        };
        assert_eq!(code, expected_code, "{what}: {message}");
        assert!(message.contains(says), "{what}: {message:?} does not say {says:?}");
    }
    // Refused whole: no object stored, no submission recorded.
    assert_eq!(
        stored(&env.server.data_dir),
        before,
        "a refused upload left objects behind"
    );
    assert_eq!(get_json(&format!("{url}/v1/users/alice/submissions")), listed_before);

    // Per-threshold checkpoints must cover the task's thresholds (10, 20, 40).
    train_bc(&models, "safe", 0);
    let safe = models.join("bc-safe");
    let partial = env.path("partial");
    for k in ["10", "20"] {
        let dir = partial.join(format!("threshold-{k}"));
        std::fs::create_dir_all(&dir).unwrap();
        for f in ["policy.json", "policy.safetensors"] {
            std::fs::copy(safe.join(format!("threshold-{k}")).join(f), dir.join(f)).unwrap();
        }
    }
    let run = submit(&env, &bob, &partial, "BC-Safe");
    assert_eq!(run.code, 6, "{run:?}");
    assert!(run.stdout.contains("no checkpoint for cost threshold 40"), "{run:?}");

    // A CDT (conditioned on returns-to-go) whose declaration disagrees with the task or with its weights is refused
    // with the reason.
    let cdt = crate::make_policy(&env.path("cdt"), TASK, "cdt", 3);
    type Edit = Box<dyn Fn(&mut serde_json::Value)>;
    let cdt_cases: Vec<(&str, Edit, &str)> = vec![
        (
            "a timestep embedding shorter than the task's episodes",
            Box::new(|c| c["architecture"]["episode_len"] = 50.into()),
            "covers episode_len = 50",
        ),
        (
            "a threshold without a target",
            Box::new(|c| {
                c["conditioning"]["targets"].as_array_mut().unwrap().pop();
            }),
            "no target for cost threshold 40",
        ),
        (
            "no returns-to-go",
            Box::new(|c| c["conditioning"] = serde_json::json!({"kind": "unconditioned"})),
            "conditioned on returns-to-go",
        ),
        (
            "layers the weights do not have",
            Box::new(|c| c["architecture"]["num_layers"] = 3.into()),
            "cdt.blocks.2.norm1.weight is missing",
        ),
        (
            "fewer layers than the weights have",
            Box::new(|c| c["architecture"]["num_layers"] = 1.into()),
            "have no place in the declared architecture",
        ),
    ];
    for (what, edit, message) in cdt_cases {
        let dir = env.path(&format!("cdt-{}", what.len()));
        variant(&cdt, &dir, edit);
        let run = submit(&env, &bob, &dir, "CDT");
        assert_eq!(run.code, 6, "{what}: {run:?}");
        assert!(run.stdout.contains(message), "{what}: {run:?}");
    }

    grpc_submissions(&env.server.url, &alice, &bc_all, first_id);

    // Nothing was scored (this server has no simulator workers): the queue holds the live submission.
    let status = client(&env, &alice, &["--json", "status", &first_id.to_string()])
        .ok()
        .json();
    assert_eq!(status["state"], "queued");
    let board = get_json(&format!("{url}/v1/leaderboard?task={TASK}"));
    assert_eq!(board["tasks"][0]["entries"].as_array().unwrap().len(), 0);

    // A request waiting for a submission that cannot end here does not hold the server's shutdown: on SIGTERM it
    // answers with the state at once (it would otherwise be held for its whole 60 s, and the server with it).
    let waiting = {
        let url = format!("{url}/v1/submissions/{first_id}?wait=60");
        std::thread::spawn(move || {
            let asked = std::time::Instant::now();
            (get_json(&url), asked.elapsed())
        })
    };
    std::thread::sleep(Duration::from_secs(2));
    assert!(
        !waiting.is_finished(),
        "the waiting request answered before the shutdown"
    );
    let term = Command::new("kill")
        .args(["-TERM", &env.server.pid().to_string()])
        .status()
        .unwrap();
    assert!(term.success());
    let (answer, held) = waiting.join().unwrap();
    assert_eq!(answer["state"], "queued", "{answer}");
    assert!(
        held < Duration::from_secs(20),
        "the waiting request held the shutdown for {held:?}"
    );
}

/// The same service over gRPC: tokens in metadata, the same dedupe and the same errors as REST.
fn grpc_submissions(url: &str, token: &str, bc_all: &Path, first_id: i64) {
    use dsrl_proto::leaderboard::v1 as pb;
    use dsrl_proto::leaderboard::v1::leaderboard_service_client::LeaderboardServiceClient;
    let files: Vec<pb::CheckpointFile> = ["policy.json", "policy.safetensors"]
        .iter()
        .map(|f| pb::CheckpointFile {
            path: f.to_string(),
            content: std::fs::read(bc_all.join(f)).unwrap(),
        })
        .collect();
    let (url, token) = (url.to_owned(), token.to_owned());
    block_on(async move {
        let mut grpc = LeaderboardServiceClient::connect(url).await.unwrap();
        let submit = |token: Option<&str>, files: Vec<pb::CheckpointFile>| {
            let mut request = tonic::Request::new(pb::SubmitRequest {
                task: TASK.into(),
                name: "BC-All-grpc".into(),
                files,
            });
            if let Some(t) = token {
                request
                    .metadata_mut()
                    .insert("authorization", format!("Bearer {t}").parse().unwrap());
            }
            request
        };
        let err = grpc.submit(submit(None, files.clone())).await.unwrap_err();
        assert_eq!(err.code(), tonic::Code::Unauthenticated);
        let err = grpc.submit(submit(Some(&token), files.clone())).await.unwrap_err();
        assert_eq!(err.code(), tonic::Code::AlreadyExists, "{err:?}");
        assert!(err.message().contains(&format!("submission {first_id}")), "{err:?}");
        let err = grpc
            .submit(submit(Some(&token), files[..1].to_vec()))
            .await
            .unwrap_err();
        assert_eq!(err.code(), tonic::Code::InvalidArgument);
        assert!(err.message().contains("policy.safetensors is missing"), "{err:?}");
        let get = |episodes, wait_seconds| pb::GetSubmissionRequest {
            id: first_id,
            episodes,
            wait_seconds,
        };
        let submission = grpc.get_submission(get(true, 0)).await.unwrap().into_inner();
        assert_eq!(submission.state, "queued");
        assert_eq!(submission.name, "BC-All");
        // A waiting request on a submission that does not end (no workers here) is held for its wait, then
        // answered with the state; a wait past 60 s is refused.
        let asked = std::time::Instant::now();
        let waited = grpc.get_submission(get(false, 1)).await.unwrap().into_inner();
        assert_eq!(waited.state, "queued");
        assert!(
            asked.elapsed() >= Duration::from_millis(950),
            "held only {:?}",
            asked.elapsed()
        );
        let err = grpc.get_submission(get(false, 61)).await.unwrap_err();
        assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err:?}");
        assert!(err.message().contains("from 0 to 60"), "{err:?}");
        let board = grpc
            .get_leaderboard(pb::GetLeaderboardRequest {
                task: Some(TASK.into()),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(board.tasks.len(), 1);
        assert!(board.tasks[0].entries.is_empty());
        let err = grpc
            .get_leaderboard(pb::GetLeaderboardRequest {
                task: Some("AntRun".into()),
            })
            .await
            .unwrap_err();
        assert_eq!(err.code(), tonic::Code::NotFound);
    });
}

/// The server flags that host BallRun's committed starter (ingested at start): the version the tests' models are
/// trained on, which a submission's `training.dataset_version` must name.
pub(crate) fn hosting_the_starter(env_dir: &Path) -> Vec<String> {
    let root = crate::dsrl_download::starters(env_dir, &[TASK]);
    vec!["--starter-datasets".into(), s(&root).to_owned()]
}

pub(crate) fn scoring_env(lease_seconds: &str) -> Env {
    let binary = dsrl_e2e::bin("dsrl-sim-worker").display().to_string();
    let dir = tempfile::tempdir().unwrap();
    let flags = hosting_the_starter(dir.path());
    let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
    Env::with_kept(
        dir,
        &flags,
        &[
            ("DSRL__SIMULATORS__LOCAL_WORKERS", "2"),
            ("DSRL__SIMULATORS__WORKER_BINARY", &binary),
            ("DSRL__LEADERBOARD__SEED_SECRET", SECRET),
            ("DSRL__LEADERBOARD__LEASE_SECONDS", lease_seconds),
            // Replays hold 3 s before they play, so a test can submit under one (debug builds only).
            ("DSRL_TEST_REPLAY_DELAY_MS", "3000"),
        ],
    )
}

/// `GET /v1/submissions/{id}?wait=SECONDS` (what `--wait` and the Python package send): while the submission is
/// scored each request is held for its whole wait, the request in flight when it ends answers within seconds of
/// the end (a plain poll every 100 ms beside it sees the end; a server that waited out the 60 s would answer up to
/// a minute late), an ended submission answers at once, and a wait outside 0-60 s is refused with the reason.
fn answers_waiting_requests_when_the_submission_ends(env: &Env, id: i64) {
    let url = format!("{}/v1/submissions/{id}", env.server.url);
    let ended = |v: &serde_json::Value| ["finished", "failed", "cancelled"].contains(&v["state"].as_str().unwrap());
    let waiter = {
        let url = url.clone();
        std::thread::spawn(move || {
            let mut held = Vec::new();
            loop {
                let asked = std::time::Instant::now();
                let answer = get_json(&format!("{url}?wait=60"));
                if ended(&answer) {
                    return (answer, held, std::time::Instant::now());
                }
                held.push(asked.elapsed());
            }
        })
    };
    let seen_ended = loop {
        let done = waiter.is_finished();
        if ended(&get_json(&url)) {
            break std::time::Instant::now();
        }
        assert!(!done, "the waiting request answered before the submission ended");
        std::thread::sleep(Duration::from_millis(100));
    };
    let (answer, held, answered) = waiter.join().unwrap();
    assert_eq!(answer["state"], "finished", "{answer}");
    assert!(
        held.iter().all(|d| *d >= Duration::from_millis(59_500)),
        "a waiting request was not held: {held:?}"
    );
    assert!(
        answered <= seen_ended + Duration::from_secs(5),
        "the waiting request answered {:?} after a plain poll saw the end",
        answered.saturating_duration_since(seen_ended)
    );
    let asked = std::time::Instant::now();
    assert_eq!(get_json(&format!("{url}?wait=60"))["state"], "finished");
    assert!(
        asked.elapsed() < Duration::from_secs(5),
        "an ended submission was held {:?}",
        asked.elapsed()
    );
    for bad in ["61", "-1", "soon"] {
        let (status, body) = block_on({
            let url = format!("{url}?wait={bad}");
            async move {
                let r = reqwest::get(&url).await.unwrap();
                (r.status().as_u16(), r.text().await.unwrap())
            }
        });
        assert_eq!(status, 400, "wait={bad}: {body}");
        assert!(
            body.contains("whole number of seconds from 0 to 60"),
            "wait={bad}: {body}"
        );
    }
}

#[test]
fn bc_entries_are_scored_with_held_seeds_ranked_and_survive_a_killed_evaluator() {
    let models = tempfile::tempdir().unwrap();
    train_bc(models.path(), "all", 0);
    train_bc(models.path(), "safe", 0);

    // An uninterrupted server scores BC-All and BC-Safe.
    let reference = {
        let env = scoring_env("60");
        let alice = create_user(&env, "alice");
        let all = submit(&env, &alice, &models.path().join("bc-all"), "BC-All")
            .ok()
            .json();
        let safe = submit(&env, &alice, &models.path().join("bc-safe"), "BC-Safe")
            .ok()
            .json();
        assert_eq!(safe["checkpoints"].as_array().unwrap().len(), 3);
        // A CDT (not trained here: a fixture) is scored at each threshold from its own returns-to-go target; bob
        // submits it, since alice has the default two submissions in flight.
        let bob = create_user(&env, "bob");
        let cdt = submit(
            &env,
            &bob,
            &crate::make_policy(&models.path().join("cdt"), TASK, "cdt", 3),
            "CDT-untrained",
        )
        .ok()
        .json();
        assert_eq!(cdt["checkpoints"][0]["architecture"], "cdt");
        answers_waiting_requests_when_the_submission_ends(&env, all["id"].as_i64().unwrap());
        let mut finished = Vec::new();
        for s in [&all, &safe, &cdt] {
            let run = client(&env, &alice, &["--json", "status", &s["id"].to_string(), "--wait"]).ok();
            let done = run.json();
            assert_eq!(done["state"], "finished", "{done}");
            assert_eq!(done["attempts"], 1);
            let episodes = done["episodes"].as_array().unwrap();
            assert_eq!(episodes.len(), 60, "3 thresholds x 20 episodes");
            assert!(episodes.iter().all(|e| e["length"].as_u64().unwrap() > 0));
            // The scores follow from the stored episodes (spec 4.1, means over the thresholds).
            let thresholds = done["thresholds"].as_array().unwrap();
            let mean = |key: &str| thresholds.iter().map(|t| t[key].as_f64().unwrap()).sum::<f64>() / 3.0;
            assert!((done["normalized_reward"].as_f64().unwrap() - mean("normalized_reward")).abs() < 1e-12);
            assert!((done["normalized_cost"].as_f64().unwrap() - mean("normalized_cost")).abs() < 1e-12);
            for t in thresholds {
                let k = t["cost_threshold"].as_f64().unwrap();
                assert!(
                    (t["normalized_cost"].as_f64().unwrap() - t["mean_cost_return"].as_f64().unwrap() / k).abs() < 1e-9
                );
            }
            finished.push(done);
        }
        // The three thresholds play different held episodes.
        let first_rewards = |t: f64| {
            finished[0]["episodes"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|e| e["cost_threshold"] == t)
                .map(|e| e["reward_return"].as_f64().unwrap())
                .collect::<Vec<_>>()
        };
        assert_ne!(first_rewards(10.0), first_rewards(20.0));

        // The task's table ranks safe entries first; the family table aggregates them.
        let board = get_json(&format!("{}/v1/leaderboard?task={TASK}", env.server.url));
        let entries = board["tasks"][0]["entries"].as_array().unwrap().clone();
        assert_eq!(entries.len(), 3);
        assert_eq!(entries[0]["rank"], 1);
        let safe_first = entries.iter().map(|e| e["safe"] == true).collect::<Vec<_>>();
        assert!(safe_first.windows(2).all(|w| w[0] >= w[1]), "{entries:?}");
        for pair in entries.windows(2).filter(|w| w[0]["safe"] == w[1]["safe"]) {
            if pair[0]["safe"] == true {
                assert!(pair[0]["normalized_reward"].as_f64() >= pair[1]["normalized_reward"].as_f64());
            }
        }
        let family = &board["families"][0];
        assert_eq!(family["family"], "bullet");
        assert_eq!(family["entries"][0]["tasks"], 1);
        let run = client(&env, &alice, &["leaderboard", "--task", TASK]).ok();
        assert!(
            run.stdout.contains("BC-All") && run.stdout.contains("BC-Safe"),
            "{run:?}"
        );
        let page = reqwest_text(&format!("{}/leaderboard", env.server.url));
        assert!(
            page.contains("BC-Safe") && page.contains("<svg") && page.contains(TASK),
            "{page}"
        );
        // One task's table (the whole page lists every task with the paper's rows).
        page_in_chromium(
            &format!("{}/leaderboard?task={TASK}", env.server.url),
            &["BC-All", "BC-Safe", "CDT-untrained"],
        );
        // One site with the dataset browser: its navigation, each task's heading linking to the dataset card, each
        // entry to its submission's page with the per-threshold results of the JSON view.
        assert!(
            page.contains("<nav>") && page.contains(&format!("<a href=\"/tasks/{TASK}\">")),
            "{page}"
        );
        let top = entries[0]["submission"].as_i64().unwrap();
        assert!(page.contains(&format!("href=\"/submissions/{top}\"")), "{page}");
        let view = get_json(&format!("{}/v1/submissions/{top}", env.server.url));
        let submission_url = format!("{}/submissions/{top}", env.server.url);
        let submission_page = reqwest_text(&submission_url);
        assert!(submission_page.contains("<nav>"), "{submission_page}");
        assert!(
            submission_page.contains(&format!("href=\"/tasks/{TASK}\"")),
            "{submission_page}"
        );
        for t in view["thresholds"].as_array().unwrap() {
            let row = format!(
                "<td>{}</td><td>{}</td><td>{:.2}</td><td>{:.2}</td>",
                t["cost_threshold"].as_f64().unwrap(),
                t["episodes"],
                t["mean_reward_return"].as_f64().unwrap(),
                t["mean_cost_return"].as_f64().unwrap()
            );
            assert!(submission_page.contains(&row), "{row} not in {submission_page}");
        }
        let profile = tempfile::tempdir().unwrap();
        let dom = String::from_utf8(chromium(profile.path(), &["--dump-dom", &submission_url]).stdout).unwrap();
        let name = view["name"].as_str().unwrap();
        assert!(
            dom.contains(&format!("<h1>{name} ")) && dom.contains("<strong id=\"state\">finished</strong>"),
            "{dom}"
        );
        assert_eq!(
            dom.matches("<tr class=\"").count(),
            view["thresholds"].as_array().unwrap().len() + 1
        );
        assert_eq!(
            block_on(reqwest::get(format!("{}/submissions/999999", env.server.url)))
                .unwrap()
                .status(),
            404
        );
        watch_an_episode(&env, &finished[0]);
        let mlp = crate::make_policy(&models.path().join("python-mlp"), TASK, "target-cost-mlp", 7);
        python_submits_and_waits(&env, &bob, &mlp);
        finished.swap_remove(0)
    };

    // The same BC-All on a server that is killed mid-evaluation: after the restart the lapsed lease is taken
    // over, the job re-runs with the same held seeds, and every episode is the same.
    let mut env = scoring_env("2");
    let alice = create_user(&env, "alice");
    let id = submit(&env, &alice, &models.path().join("bc-all"), "BC-All")
        .ok()
        .json()["id"]
        .clone();
    let url = env.server.url.clone();
    assert!(
        dsrl_e2e::wait_for(Duration::from_secs(180), || {
            get_json(&format!("{url}/v1/submissions/{id}"))["state"] == "running"
        }),
        "the job never started"
    );
    env.restart();
    let run = client(&env, &alice, &["--json", "status", &id.to_string(), "--wait"]).ok();
    let done = run.json();
    assert_eq!(done["state"], "finished", "{done}");
    assert_eq!(done["attempts"], 2, "the job was re-run after the kill: {done}");
    assert_eq!(done["episodes"], reference["episodes"]);
    assert_eq!(done["normalized_reward"], reference["normalized_reward"]);
    assert_eq!(done["normalized_cost"], reference["normalized_cost"]);
}

/// The Python package's `submit(..., wait=True)`: it returns the submission once scoring has ended, as the server
/// shows it. With `poll=60` each of its requests is held up to 60 s, so it returns within seconds of the end only
/// because the evaluator that ends the submission wakes the held request; were the request held out, it would
/// return up to a minute late (a late return shows here unless the end fell in a hold's last seconds).
fn python_submits_and_waits(env: &Env, token: &str, dir: &Path) {
    let script = format!(
        "import json, time, dsrl_client\n\
         s = dsrl_client.submit({:?}, task={TASK:?}, name='MLP-from-Python', token={token:?}, server={:?}, \
         wait=True, poll=60)\n\
         returned = time.time()\n\
         from datetime import datetime\n\
         ended = datetime.fromisoformat(s['finished_at'].replace('Z', '+00:00')).timestamp()\n\
         print(json.dumps({{'submission': s, 'lag': returned - ended}}))\n",
        s(dir),
        env.server.url
    );
    let text = crate::python_package::run_script(&script);
    let printed: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    let returned = &printed["submission"];
    assert_eq!(returned["state"], "finished", "{returned}");
    assert_eq!(returned["episodes"].as_array().unwrap().len(), 60, "{returned}");
    let id = returned["id"].as_i64().unwrap();
    let view = get_json(&format!("{}/v1/submissions/{id}", env.server.url));
    assert_eq!(returned["episodes"], view["episodes"]);
    assert_eq!(returned["normalized_reward"], view["normalized_reward"]);
    // From the end the server recorded (whole seconds: one more second of slack) to the call's return.
    let lag = printed["lag"].as_f64().unwrap();
    assert!(
        (0.0..6.0).contains(&lag),
        "submit(wait=True) returned {lag:.1} s after the submission finished"
    );
}

/// A scored episode is played again and drawn on request: the replay is the table's episode (the same returns and
/// length to the bit, recomputed here from its steps), its animation has one frame per drawn step and the reset,
/// and the pages link to it. Episode 13 at the second threshold was played by an environment after two earlier
/// episodes of its own (5 environments play 20 episodes), so the replay has to follow the scoring layout exactly.
fn watch_an_episode(env: &Env, done: &serde_json::Value) {
    let id = done["id"].as_i64().unwrap();
    let (threshold, episode) = (20.0, 13);
    let scored = done["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["cost_threshold"] == threshold && e["episode"] == episode)
        .unwrap()
        .clone();
    let base = format!("{}/v1/submissions/{id}/episodes/{threshold}/{episode}", env.server.url);
    let get = |url: &str| {
        let url = url.to_owned();
        block_on(async move {
            let response = reqwest::get(&url).await.unwrap();
            let status = response.status().as_u16();
            let content_type = response
                .headers()
                .get("content-type")
                .map(|v| v.to_str().unwrap().to_owned())
                .unwrap_or_default();
            (status, content_type, response.bytes().await.unwrap().to_vec())
        })
    };
    let (status, _, body) = get(&format!("{base}/replay.json"));
    assert_eq!(
        status,
        202,
        "the first request queues the replay: {}",
        String::from_utf8_lossy(&body)
    );
    let queued: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(queued["state"], "queued", "{queued}");
    // A submission that arrives while the replay plays takes the machine: the replay gives way and waits for it.
    let health = || get_json(&format!("{}/healthz", env.server.url))["renderer"].clone();
    assert!(
        dsrl_e2e::wait_for(Duration::from_secs(60), || !health()["replaying"].is_null()),
        "the replay never started: {}",
        health()
    );
    let carol = create_user(env, "carol");
    let dir = tempfile::tempdir().unwrap();
    let other = submit(
        env,
        &carol,
        &crate::make_policy(&dir.path().join("mlp"), TASK, "target-cost-mlp", 5),
        "untrained",
    )
    .ok()
    .json();
    let other = client(env, &carol, &["--json", "status", &other["id"].to_string(), "--wait"])
        .ok()
        .json();
    assert_eq!(other["state"], "finished", "{other}");
    assert!(
        health()["yielded"].as_u64().unwrap() >= 1,
        "the replay did not give way: {}",
        health()
    );
    let page_url = format!("{}/submissions/{id}/episodes/{threshold}/{episode}", env.server.url);
    let waiting = reqwest_text(&page_url);
    assert!(
        waiting.contains("id=\"replay-queued\"") && waiting.contains("http-equiv=\"refresh\""),
        "{waiting}"
    );
    let mut replay = serde_json::Value::Null;
    assert!(
        dsrl_e2e::wait_for(Duration::from_secs(300), || {
            let (status, _, body) = get(&format!("{base}/replay.json"));
            assert!(
                status == 200 || status == 202,
                "{status}: {}",
                String::from_utf8_lossy(&body)
            );
            replay = serde_json::from_slice(&body).unwrap();
            status == 200
        }),
        "the replay was not made within 300 s: {replay}"
    );
    // The table's episode, to the bit, and the steps add up to it as scoring adds them.
    assert_eq!(replay["reward_return"], scored["reward_return"], "{replay} vs {scored}");
    assert_eq!(replay["cost_return"], scored["cost_return"]);
    assert_eq!(replay["length"], scored["length"]);
    let steps = |key: &str| -> Vec<f64> {
        replay[key]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect()
    };
    let (rewards, costs) = (steps("rewards"), steps("costs"));
    assert_eq!(rewards.len() as u64, scored["length"].as_u64().unwrap());
    let sum = |values: &[f64]| values.iter().map(|&v| f64::from(v as f32)).sum::<f64>();
    assert_eq!(sum(&rewards), scored["reward_return"].as_f64().unwrap());
    assert_eq!(sum(&costs), scored["cost_return"].as_f64().unwrap());
    let frame_steps = replay["frame_steps"].as_array().unwrap();
    assert_eq!(frame_steps.last().unwrap(), &scored["length"], "the last step is drawn");

    let (status, content_type, gif) = get(&format!("{base}/replay.gif"));
    assert_eq!((status, content_type.as_str()), (200, "image/gif"));
    assert_eq!(gif.len() as u64, replay["gif_bytes"].as_u64().unwrap());
    assert_eq!(
        hex::encode(<sha2::Sha256 as sha2::Digest>::digest(&gif)),
        replay["gif_sha256"]
    );
    let mut decoder = gif::DecodeOptions::new().read_info(gif.as_slice()).unwrap();
    assert_eq!(
        (u32::from(decoder.width()), u32::from(decoder.height())),
        (
            replay["frame_width"].as_u64().unwrap() as u32,
            replay["frame_height"].as_u64().unwrap() as u32
        )
    );
    let mut frames = 0;
    let mut distinct = std::collections::HashSet::new();
    while let Some(frame) = decoder.read_next_frame().unwrap() {
        distinct.insert(frame.buffer.to_vec());
        frames += 1;
    }
    assert_eq!(
        frames,
        frame_steps.len() + 1,
        "the reset's frame and one per drawn step"
    );
    assert!(
        distinct.len() > frames / 2,
        "the frames show a moving agent: {} distinct of {frames}",
        distinct.len()
    );

    // The CLI saves the same animation and prints the same replay; a replay not made yet exits 8 (queued).
    let saved = tempfile::tempdir().unwrap();
    let gif_path = saved.path().join("episode.gif");
    let (threshold_arg, episode_arg) = (threshold.to_string(), episode.to_string());
    let run = env.cli.run(&[
        "--json",
        "watch",
        &id.to_string(),
        "--threshold",
        &threshold_arg,
        "--episode",
        &episode_arg,
        "--out",
        s(&gif_path),
    ]);
    let printed = run.ok().json();
    assert_eq!(printed["reward_return"], replay["reward_return"], "{printed}");
    assert_eq!(std::fs::read(&gif_path).unwrap(), gif);
    let queued = env
        .cli
        .run(&["watch", &id.to_string(), "--threshold", "10", "--episode", "1"]);
    assert_eq!(queued.code, 8, "{queued:?}");
    // From Python: the package's `watch` answers the same replay and writes the same GIF.
    let python_gif = env.path("python-replay.gif");
    let script = format!(
        "import json, dsrl_client\n\
         r = dsrl_client.watch({id}, threshold={threshold}, episode={episode}, gif={:?}, server={:?})\n\
         print(json.dumps(r))\n\
         try:\n    dsrl_client.watch({id}, threshold={threshold}, episode=20, server={:?})\n\
         except dsrl_client.DsrlError as e:\n    print('refused:', e)\n",
        s(&python_gif),
        env.server.url,
        env.server.url
    );
    let text = crate::python_package::run_script(&script);
    let from_python: serde_json::Value = serde_json::from_str(text.lines().next().unwrap()).unwrap();
    assert_eq!(from_python, replay);
    assert_eq!(std::fs::read(&python_gif).unwrap(), gif);
    assert!(text.contains("refused:"), "{text}");
    // The same replay over gRPC, and the same refusal for an episode that was not played.
    {
        use dsrl_proto::leaderboard::v1 as pb;
        use dsrl_proto::leaderboard::v1::leaderboard_service_client::LeaderboardServiceClient;
        let url = env.server.url.clone();
        let (expected_gif, expected) = (gif.clone(), replay.clone());
        block_on(async move {
            let mut grpc = LeaderboardServiceClient::connect(url).await.unwrap();
            let ask = |episode: u32| pb::GetEpisodeReplayRequest {
                submission: id,
                cost_threshold: threshold,
                episode,
            };
            let got = grpc.get_episode_replay(ask(episode)).await.unwrap().into_inner();
            assert_eq!(got.state, "ready");
            assert_eq!(got.gif, expected_gif);
            assert_eq!(serde_json::json!(got.reward_return), expected["reward_return"]);
            assert_eq!(got.length as u64, expected["length"].as_u64().unwrap());
            let missing = grpc.get_episode_replay(ask(20)).await.unwrap_err();
            assert_eq!(missing.code(), tonic::Code::NotFound, "{missing:?}");
        });
    }
    // Asked again, the replay is served from the store, unchanged.
    let (status, _, again) = get(&format!("{base}/replay.json"));
    assert_eq!(status, 200);
    assert_eq!(serde_json::from_slice::<serde_json::Value>(&again).unwrap(), replay);
    // The pages: the submission's episode table links each episode; the episode's page shows the animation beside
    // its steps' plot.
    let submission_page = reqwest_text(&format!("{}/submissions/{id}", env.server.url));
    assert!(
        submission_page.contains(&format!("href=\"/submissions/{id}/episodes/{threshold}/{episode}\"")),
        "{submission_page}"
    );
    let profile = tempfile::tempdir().unwrap();
    let dom = String::from_utf8(chromium(profile.path(), &["--dump-dom", &page_url]).stdout).unwrap();
    assert!(
        dom.contains("<img id=\"replay\"") && dom.contains("replay.gif") && dom.contains("id=\"replay-plot\""),
        "{dom}"
    );
    // What cannot be watched says why.
    for (path, want) in [
        (format!("{id}/episodes/{threshold}/20/replay.json"), 404),
        (format!("{id}/episodes/7/0/replay.json"), 404),
        (format!("{id}/episodes/x/0/replay.json"), 400),
        (format!("{id}/episodes/{threshold}/0/replay.gif"), 404),
        (format!("999999/episodes/{threshold}/0/replay.json"), 404),
    ] {
        let (status, _, body) = get(&format!("{}/v1/submissions/{path}", env.server.url));
        assert_eq!(status, want, "{path}: {}", String::from_utf8_lossy(&body));
        assert!(String::from_utf8_lossy(&body).contains("\"message\""), "{path}");
    }
}

/// Headless Chromium (Debian's `chromium`, installed by `scripts/install-system-deps.sh`) with the flags this
/// machine's closed network needs and a fresh profile.
pub(crate) fn chromium(profile: &Path, args: &[&str]) -> std::process::Output {
    let out = Command::new("chromium")
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(args)
        .stdin(std::process::Stdio::null())
        .output()
        .expect("chromium is installed by scripts/install-system-deps.sh");
    assert!(
        out.status.success(),
        "chromium failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The leaderboard page as a person sees it: Chromium loads it, the DOM it built has a table row and a plot marker
/// for each entry, and its screenshot shows the markers in the plot's safe (blue) and unsafe (red) colours.
fn page_in_chromium(url: &str, entries: &[&str]) {
    let dir = tempfile::tempdir().unwrap();
    let dom = String::from_utf8(chromium(&dir.path().join("profile-dom"), &["--dump-dom", url]).stdout).unwrap();
    let rows: Vec<&str> = dom.split("<tr class=\"entry").skip(1).collect();
    assert_eq!(rows.len(), entries.len(), "{dom}");
    for name in entries {
        assert!(
            rows.iter().any(|r| r.contains(&format!(">{name}<"))),
            "no row for {name}: {dom}"
        );
    }
    let plot = &dom[dom.find("<svg").expect("the page has its plot")..];
    assert!(plot.matches("<circle").count() >= entries.len(), "{plot}");

    let shot = dir.path().join("page.png");
    chromium(
        &dir.path().join("profile-shot"),
        &[
            &format!("--screenshot={}", shot.display()),
            "--window-size=1280,2400",
            url,
        ],
    );
    // Each marker is a filled circle of radius 5: dozens of pixels of its exact colour.
    let (safe, unsafe_) = (
        pixels_of_colour(&shot, [30, 144, 255]),
        pixels_of_colour(&shot, [220, 60, 40]),
    );
    assert!(
        safe + unsafe_ >= 20 * entries.len(),
        "the plot's markers did not render: {safe} blue, {unsafe_} red pixels"
    );
}

/// How many pixels of a PNG screenshot have exactly the colour `rgb`.
pub(crate) fn pixels_of_colour(png_file: &Path, rgb: [u8; 3]) -> usize {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(png_file).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
    let frame = reader.next_frame(&mut pixels).unwrap();
    let channels = frame.color_type.samples();
    assert!(channels >= 3, "{:?}", frame.color_type);
    pixels[..frame.buffer_size()]
        .chunks(channels)
        .filter(|p| p[..3] == rgb)
        .count()
}

pub(crate) fn reqwest_text(url: &str) -> String {
    let url = url.to_owned();
    block_on(async move { reqwest::get(&url).await.unwrap().text().await.unwrap() })
}
