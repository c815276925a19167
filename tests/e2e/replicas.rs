//! Beyond one machine, with real parts on loopback: PostgreSQL (Debian's server, started in a temporary folder) as
//! the shared metadata store and job queue, moto as the shared S3 bucket, two API replicas and two evaluator
//! processes. What one replica does, the other sees; derived versions are computed once across both; a replica or
//! an evaluator killed with SIGKILL loses nothing and leaves nothing half-visible.

use std::path::Path;
use std::time::Duration;

use dsrl_e2e::{Cli, Server, wait_for};

use crate::leaderboard::{TASK, train_bc};
use crate::services::{Moto, Postgres};
use crate::{block_on, get_json, s, sha256_file};

const ADMIN_TOKEN: &str = "e2e-admin-token-shared-by-replicas";
const SECRET: &str = "e2e-held-seed-secret";

/// What every process of one deployment shares: the database, the bucket, the secrets.
fn shared_env(pg: &Postgres, moto: &Moto, extra: &[(&str, &str)]) -> Vec<(String, String)> {
    let mut envs = moto.server_env("cluster");
    for (k, v) in [
        ("DSRL__DATABASE__URL", pg.url.as_str()),
        ("DSRL__AUTH__ADMIN_TOKEN", ADMIN_TOKEN),
        ("DSRL__LEADERBOARD__SEED_SECRET", SECRET),
    ]
    .into_iter()
    .chain(extra.iter().copied())
    {
        envs.push((k.to_owned(), v.to_owned()));
    }
    envs
}

fn start(dir: &Path, name: &str, args: &[&str], envs: &[(String, String)]) -> Server {
    let envs: Vec<(&str, &str)> = envs.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
    Server::start(&dir.join(name), args, &envs)
}

fn cli(server: &Server, cache: &Path) -> Cli {
    Cli {
        server: server.url.clone(),
        cache: cache.to_owned(),
        token: Some(ADMIN_TOKEN.to_owned()),
    }
}

/// `dsrl_filters_total{outcome=...}` of one replica.
fn filter_count(server: &Server, outcome: &str) -> u64 {
    let (url, outcome) = (server.url.clone(), outcome.to_owned());
    block_on(async move { crate::filters::filter_count(&url, &outcome).await })
}

#[test]
fn two_api_replicas_share_postgres_and_s3() {
    let dir = tempfile::tempdir().unwrap();
    let pg = Postgres::start();
    let moto = Moto::start("dsrl-replicas");
    // A small pool: derivations hold their locks on connections of their own, never the pool's (below).
    let envs = shared_env(
        &pg,
        &moto,
        &[
            ("DSRL__LEADERBOARD__EVALUATORS", "0"),
            ("DSRL__DATABASE__MAX_CONNECTIONS", "3"),
        ],
    );
    // Two replicas starting at once with the same starter dataset: the migrations run once (sqlx holds an advisory
    // lock around them), and the starter becomes one version (the ingest gate), whichever replica records it.
    let starters = dir.path().join("starters");
    let committed = dsrl_e2e::repo_root().join("data/starter/OfflineBallRun-v0");
    std::fs::create_dir_all(starters.join("OfflineBallRun-v0")).unwrap();
    for file in std::fs::read_dir(&committed).unwrap() {
        let file = file.unwrap().path();
        std::os::unix::fs::symlink(
            &file,
            starters.join("OfflineBallRun-v0").join(file.file_name().unwrap()),
        )
        .unwrap();
    }
    let starter_args = ["--starter-datasets", s(&starters)];
    let (mut a, b) = std::thread::scope(|scope| {
        let a = scope.spawn(|| start(dir.path(), "a", &starter_args, &envs));
        let b = scope.spawn(|| start(dir.path(), "b", &starter_args, &envs));
        (a.join().unwrap(), b.join().unwrap())
    });
    let starter_versions = get_json(&format!("{}/v1/datasets/OfflineBallRun-v0/versions", b.url));
    let listed = starter_versions["versions"].as_array().unwrap();
    assert_eq!(listed.len(), 1, "{starter_versions}");
    assert_eq!(listed[0]["tags"], serde_json::json!(["latest", "starter"]));
    let cli_a = cli(&a, &dir.path().join("cache-a"));
    let cli_b = cli(&b, &dir.path().join("cache-b"));

    // Ingest on A, fetch from B: the same bytes.
    let task = "OfflineMetadrive-easysparse-v0";
    let file = dir.path().join("md.parquet");
    let made = dsrl_e2e::make_dataset(task, 4, 22, &file);
    let version = made.version.to_string();
    let ingested = cli_a
        .run(&["--json", "admin", "ingest", "--task", task, s(&file)])
        .ok()
        .json();
    assert_eq!(ingested["version"]["version"], version.as_str());
    let fetched = cli_b.run(&["--json", "fetch", task]).ok().json();
    assert_eq!(fetched["version"], version.as_str(), "{fetched}");
    assert_eq!(sha256_file(Path::new(fetched["path"].as_str().unwrap())), version);
    assert_eq!(
        get_json(&format!("{}/v1/datasets/{task}/versions", b.url))["versions"][0]["version"],
        version.as_str()
    );

    // 50 concurrent requests for one filtered version that does not exist yet, split over both replicas: the
    // filter runs once in the whole deployment, and every request gets the same version.
    let filter = "obs_noise%3D0.1%2Cseed%3D3"; // obs_noise=0.1,seed=3
    let urls: Vec<String> = (0..50)
        .map(|i| {
            let replica = if i % 2 == 0 { &a } else { &b };
            format!("{}/v1/datasets/{task}/versions/latest?filter={filter}", replica.url)
        })
        .collect();
    let answers: Vec<serde_json::Value> = block_on(async move {
        let http = reqwest::Client::new();
        let requests = urls.iter().map(|url| {
            let http = http.clone();
            async move {
                let response = http.get(url).send().await.unwrap();
                let status = response.status();
                let body = response.text().await.unwrap();
                assert!(status.is_success(), "{url}: {status} {body}");
                serde_json::from_str::<serde_json::Value>(&body).unwrap()
            }
        });
        futures::future::join_all(requests).await
    });
    let derived = answers[0]["version"].as_str().unwrap().to_owned();
    assert_ne!(derived, version);
    assert!(answers.iter().all(|m| m["version"] == derived.as_str()));
    let computed = filter_count(&a, "computed") + filter_count(&b, "computed");
    let cached = filter_count(&a, "cached") + filter_count(&b, "cached");
    assert_eq!(computed, 1, "the filter ran {computed} times across the replicas");
    assert_eq!(cached, 49);

    // The same checkpoint submitted 8 times at once, half to each replica: the unique index lets one in, the
    // others are told it exists (not a check-then-insert race that lets two in).
    let user = cli_a
        .run(&["admin", "create-user", "alice"])
        .ok()
        .stdout
        .trim()
        .to_owned();
    let policy = crate::make_policy(&dir.path().join("policy"), "OfflineBallRun-v0", "target-cost-mlp", 5);
    let submitters: Vec<std::process::Child> = (0..8)
        .map(|i| {
            let replica = if i % 2 == 0 { &cli_a } else { &cli_b };
            replica
                .command(&[
                    "--json",
                    "submit",
                    s(&policy),
                    "--task",
                    "OfflineBallRun-v0",
                    "--name",
                    "dup",
                ])
                .env("DSRL_TOKEN", &user)
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let runs: Vec<dsrl_e2e::Run> = submitters
        .into_iter()
        .map(|c| dsrl_e2e::Run::from(c.wait_with_output().unwrap()))
        .collect();
    let accepted = runs.iter().filter(|r| r.code == 0).count();
    assert_eq!(accepted, 1, "{runs:?}");
    assert!(
        runs.iter()
            .filter(|r| r.code != 0)
            .all(|r| r.stderr.contains("already submitted") || r.stderr.contains("at the same time")),
        "{runs:?}"
    );

    // Six different filters at once on one replica with three pooled connections: every derivation holds its lock
    // while it computes, and the work inside still gets pooled connections.
    let urls: Vec<String> = (11..17)
        .map(|level| {
            format!(
                "{}/v1/datasets/{task}/versions/latest?filter=obs_noise%3D0.{level}",
                a.url
            )
        })
        .collect();
    let versions: Vec<String> = block_on(async move {
        let requests = urls.iter().map(|url| async move {
            let response = reqwest::get(url).await.unwrap();
            let status = response.status();
            let body = response.text().await.unwrap();
            assert!(status.is_success(), "{url}: {status} {body}");
            serde_json::from_str::<serde_json::Value>(&body).unwrap()["version"]
                .as_str()
                .unwrap()
                .to_owned()
        });
        futures::future::join_all(requests).await
    });
    assert_eq!(versions.iter().collect::<std::collections::BTreeSet<_>>().len(), 6);

    // Garbage collection of filtered versions while both replicas serve: the default policy keeps a version used
    // a moment ago; a zero size budget removes it (rows, then objects); asked for again, it is computed again, to
    // the same version.
    let gc = |extra: &[(&str, &str)], args: &[&str]| {
        let mut cmd = std::process::Command::new(dsrl_e2e::bin("dsrl-server"));
        cmd.arg("--data-dir").arg(dir.path().join("gc")).arg("gc").args(args);
        cmd.envs(envs.iter().map(|(k, v)| (k.as_str(), v.as_str())));
        cmd.envs(extra.iter().copied());
        let out = cmd.output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    let kept = gc(&[], &[]);
    assert_eq!(
        (kept["kept"].as_u64(), kept["removed"].as_array().unwrap().len()),
        (Some(7), 0),
        "{kept}"
    );
    let zero_budget = [("DSRL__GC__DERIVED_MAX_BYTES", "0")];
    let dry = gc(&zero_budget, &["--dry-run"]);
    assert_eq!(dry["removed"].as_array().unwrap().len(), 7, "{dry}");
    assert!(
        dry["removed"]
            .as_array()
            .unwrap()
            .iter()
            .any(|r| r["version"] == derived.as_str()),
        "{dry}"
    );
    let manifest_url = format!("{}/v1/datasets/{task}/versions/{derived}", b.url);
    let status_of = |url: &str| {
        let url = url.to_owned();
        block_on(async move { reqwest::get(url).await.unwrap().status().as_u16() })
    };
    assert_eq!(status_of(&manifest_url), 200, "a dry run removed something");
    let removed = gc(&zero_budget, &[]);
    assert_eq!(removed["removed"].as_array().unwrap().len(), 7, "{removed}");
    assert_eq!(removed["derived_bytes_after"], 0);
    assert_eq!(status_of(&manifest_url), 404);
    assert_eq!(
        status_of(&format!("{}/download", manifest_url.replace(&b.url, &a.url))),
        404
    );
    let again = get_json(&format!("{}/v1/datasets/{task}/versions/latest?filter={filter}", b.url));
    assert_eq!(again["version"], derived.as_str());
    assert_eq!(filter_count(&a, "computed") + filter_count(&b, "computed"), 8);
    assert_eq!(status_of(&format!("{manifest_url}/download")), 200);

    // A download cut by killing its replica (SIGKILL) resumes against the other.
    // Its own ~45 MB version: more than the loopback socket buffers hold, so the kill really cuts the transfer.
    let task = "OfflineMetadrive-easymean-v0";
    let file = dir.path().join("md-big.parquet");
    let version = dsrl_e2e::make_dataset(task, 30, 23, &file).version.to_string();
    cli_b.run(&["admin", "ingest", "--task", task, s(&file)]).ok();
    let cache = dir.path().join("cache-resume");
    let manifest = get_json(&format!("{}/v1/datasets/{task}/versions/{version}", a.url));
    let size = manifest["byte_size"].as_u64().unwrap();
    let part = cache
        .join(task)
        .join(&version)
        .join(format!("{}.part", manifest["file_name"].as_str().unwrap()));
    let mut download = cli(&a, &cache)
        .command(&["fetch", task, "--limit-rate", "1M"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let grew = wait_for(Duration::from_secs(60), || {
        std::fs::metadata(&part).is_ok_and(|m| m.len() >= 1 << 20)
    });
    assert!(grew, "the download from replica A never reached 1 MiB");
    a.kill();
    let _ = download.wait();
    let partial = std::fs::metadata(&part).unwrap().len();
    assert!(partial < size, "{partial} of {size}: the cut came too late");
    let resumed = cli(&b, &cache).run(&["--json", "fetch", task]).ok().json();
    let from = resumed["resumed_from"]
        .as_u64()
        .expect("the fetch from B resumed A's download");
    assert!(from >= 1 << 20 && from <= partial, "{from} vs {partial}");
    assert_eq!(sha256_file(&part.with_extension("")), version);

    // A replica killed mid-ingest (its upload converted, not yet recorded) leaves nothing visible on the other;
    // the same upload then succeeds there.
    a.restart();
    let cli_a = cli(&a, &dir.path().join("cache-a"));
    let task = "OfflineMetadrive-hardmean-v0";
    let file = dir.path().join("md-hard.parquet");
    let made = dsrl_e2e::make_dataset(task, 12, 12, &file);
    let tmp = a.data_dir.join("tmp");
    let mut child = cli_a
        .command(&["admin", "ingest", "--task", task, s(&file)])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let converting = wait_for(Duration::from_secs(60), || {
        std::fs::read_dir(&tmp).is_ok_and(|d| {
            d.flatten().any(|e| {
                e.file_name().to_string_lossy().starts_with("canonical-") && e.metadata().is_ok_and(|m| m.len() > 0)
            })
        })
    });
    assert!(converting, "the ingest on A never reached its conversion");
    a.kill();
    let _ = child.wait();
    let listed = get_json(&format!("{}/v1/datasets/{task}/versions", b.url));
    assert_eq!(
        listed["versions"],
        serde_json::json!([]),
        "half an ingest became visible: {listed}"
    );
    let out = cli_b
        .run(&["--json", "admin", "ingest", "--task", task, s(&file)])
        .ok()
        .json();
    assert_eq!(out["version"]["version"], made.version.as_str());
}

/// The job queue on PostgreSQL with the evaluators in their own processes: two API replicas that only queue
/// (`leaderboard.evaluators = 0`), and two `dsrl-evaluator` processes with their own simulator workers. The
/// evaluator playing a submission (the parent of its `play-policy` processes) is killed with SIGKILL; the other
/// takes the lapsed lease over and stores the same episodes an uninterrupted evaluation (SQLite, same secret)
/// stores.
#[test]
fn a_submission_survives_its_evaluator_killed_mid_job() {
    let dir = tempfile::tempdir().unwrap();
    let models = dir.path().join("models");
    train_bc(&models, "all", 0);
    let policy = models.join("bc-all");
    let worker = dsrl_e2e::bin("dsrl-sim-worker").display().to_string();
    let scoring = [
        ("DSRL__SIMULATORS__WORKER_BINARY", worker.as_str()),
        ("DSRL__LEADERBOARD__LEASE_SECONDS", "2"),
        ("DSRL__LEADERBOARD__EPISODES_PER_THRESHOLD", "10"),
        // The evaluator that holds the job is found by its `play-policy` children: the policy acts there, not in
        // the workers (the same episodes either way).
        ("DSRL__LEADERBOARD__ACT_IN_WORKERS_MAX_MULTIPLY_ADDS", "0"),
    ];

    // The reference: the same policy scored without interruption on the embedded default.
    let reference = {
        let mut envs: Vec<(&str, &str)> = scoring.to_vec();
        envs.extend([
            ("DSRL__SIMULATORS__LOCAL_WORKERS", "1"),
            ("DSRL__LEADERBOARD__SEED_SECRET", SECRET),
        ]);
        let home = tempfile::tempdir().unwrap();
        let flags = crate::leaderboard::hosting_the_starter(home.path());
        let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
        let env = crate::Env::with_kept(home, &flags, &envs);
        let user = crate::leaderboard::create_user(&env, "alice");
        let id = crate::leaderboard::submit(&env, &user, &policy, "BC-All").ok().json()["id"].clone();
        let done = crate::leaderboard::client(&env, &user, &["--json", "status", &id.to_string(), "--wait"])
            .ok()
            .json();
        assert_eq!(done["state"], "finished", "{done}");
        done
    };

    let pg = Postgres::start();
    let moto = Moto::start("dsrl-evaluators");
    let mut api_envs = scoring.to_vec();
    api_envs.push(("DSRL__LEADERBOARD__EVALUATORS", "0"));
    // The API replicas host the starter the policy was trained on (a submission must name a hosted version).
    let hosting = crate::leaderboard::hosting_the_starter(dir.path());
    let hosting: Vec<&str> = hosting.iter().map(String::as_str).collect();
    let api = start(dir.path(), "api-a", &hosting, &shared_env(&pg, &moto, &api_envs));
    let api_b = start(dir.path(), "api-b", &hosting, &shared_env(&pg, &moto, &api_envs));
    let mut evaluator_envs = scoring.to_vec();
    evaluator_envs.push(("DSRL__SIMULATORS__LOCAL_WORKERS", "1"));
    let evaluator_envs = shared_env(&pg, &moto, &evaluator_envs);
    let evaluator = |name: &str| {
        let envs: Vec<(&str, &str)> = evaluator_envs.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
        Server::evaluator(&dir.path().join(name), &envs)
    };
    let mut evaluators = [evaluator("evaluator-1"), evaluator("evaluator-2")];
    for evaluator in &evaluators {
        let health = block_on(reqwest::get(format!("{}/healthz", evaluator.url))).unwrap();
        assert_eq!(health.status(), 200);
    }

    let admin = cli(&api, &dir.path().join("cache"));
    let token = admin
        .run(&["admin", "create-user", "alice"])
        .ok()
        .stdout
        .trim()
        .to_owned();
    let submitted = dsrl_e2e::Run::from(
        admin
            .command(&["--json", "submit", "--task", TASK, "--name", "BC-All"])
            .arg(&policy)
            .env("DSRL_TOKEN", &token)
            .output()
            .unwrap(),
    )
    .ok()
    .json();
    let id = submitted["id"].clone();
    // Whichever evaluator claimed the job plays it in `play-policy` children: kill that one mid-job.
    let mut holder = None;
    let playing = wait_for(Duration::from_secs(180), || {
        let parents = play_policy_parents();
        holder = evaluators.iter().position(|e| parents.contains(&e.pid()));
        holder.is_some()
    });
    assert!(playing, "no evaluator started playing the job");
    let state = get_json(&format!("{}/v1/submissions/{id}", api_b.url))["state"].clone();
    assert_eq!(state, "running", "the job finished before the kill");
    evaluators[holder.unwrap()].kill();

    let done = dsrl_e2e::Run::from(
        cli(&api_b, &dir.path().join("cache-b"))
            .command(&["--json", "status", &id.to_string(), "--wait"])
            .env("DSRL_TOKEN", &token)
            .output()
            .unwrap(),
    )
    .ok()
    .json();
    assert_eq!(done["state"], "finished", "{done}");
    assert_eq!(done["attempts"], 2, "the second evaluator re-ran the job: {done}");
    assert_eq!(done["episodes"], reference["episodes"]);
    assert_eq!(done["normalized_reward"], reference["normalized_reward"]);
    assert_eq!(done["normalized_cost"], reference["normalized_cost"]);
}

/// The parent pids of the running `play-policy` processes (Linux /proc).
fn play_policy_parents() -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|entry| {
            let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
            let playing = cmdline.split(|&b| b == 0).any(|arg| arg == b"play-policy");
            if !playing {
                return None;
            }
            let status = std::fs::read_to_string(entry.path().join("status")).ok()?;
            status
                .lines()
                .find_map(|l| l.strip_prefix("PPid:")?.trim().parse().ok())
        })
        .collect()
}

/// The queue's guarantees on PostgreSQL under concurrency, through the server's own queue code: four evaluators
/// (separate connections, as separate processes would have) claim 200 jobs at once, and each job is claimed and
/// finished exactly once (`SKIP LOCKED`, finish only under the lease); eight concurrent submissions by one user
/// with a limit of 2 at once let exactly 2 in (the user's row is locked while the quota is checked).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_queue_keeps_its_guarantees_under_concurrent_evaluators() {
    use dsrl_leaderboard::queue::{self, NewSubmission, Quotas};
    use dsrl_leaderboard::users;
    use dsrl_service::db::Db;

    let pg = Postgres::start();
    let db = Db::connect(&pg.url, 8).await.unwrap();
    let user = users::create(&db, "bench").await.unwrap();
    let unlimited = Quotas {
        per_day: u32::MAX,
        concurrent: u32::MAX,
    };
    let jobs = 200;
    for i in 0..jobs {
        let digest = format!("{i:064x}");
        let new = NewSubmission {
            user_id: user.id,
            task: TASK,
            name: "job",
            checkpoint_sha256: &digest,
            checkpoints: &[],
            episodes_per_threshold: 20,
            dataset_version: None,
        };
        queue::insert(&db, new, &unlimited).await.unwrap();
    }
    assert_eq!(queue::depth(&db).await.unwrap(), jobs);
    let evaluators = (0..4).map(|e| {
        let url = pg.url.clone();
        tokio::spawn(async move {
            let db = Db::connect(&url, 2).await.unwrap();
            let owner = format!("evaluator-{e}");
            let mut claimed = Vec::new();
            while let Some(job) = queue::claim(&db, &owner, 60_000, 3).await.unwrap() {
                let scores = queue::Scores {
                    episodes: &[],
                    normalized_reward: 0.0,
                    normalized_cost: 0.0,
                    protocol_version: "p1.test",
                };
                assert!(
                    queue::finish(&db, job.id, &owner, &scores, dsrl_leaderboard::SCORER_BUILD)
                        .await
                        .unwrap()
                );
                claimed.push(job.id);
            }
            claimed
        })
    });
    let mut claimed: Vec<i64> = Vec::new();
    let mut per_evaluator = Vec::new();
    for evaluator in futures::future::join_all(evaluators).await {
        let ids = evaluator.unwrap();
        per_evaluator.push(ids.len());
        claimed.extend(ids);
    }
    claimed.sort();
    let before = claimed.len();
    claimed.dedup();
    assert_eq!(before, claimed.len(), "a job was claimed twice");
    assert_eq!(claimed.len() as i64, jobs, "{per_evaluator:?}");
    assert_eq!(queue::depth(&db).await.unwrap(), 0);

    // Eight connections opened first (opening one runs the migration check under a lock), then released together.
    let mut connections = Vec::new();
    for _ in 0..8 {
        connections.push(Db::connect(&pg.url, 1).await.unwrap());
    }
    let together = std::sync::Arc::new(tokio::sync::Barrier::new(8));
    let submissions = connections.into_iter().enumerate().map(|(i, db)| {
        let (together, user_id) = (together.clone(), user.id);
        tokio::spawn(async move {
            let limited = Quotas {
                per_day: u32::MAX,
                concurrent: 2,
            };
            let digest = format!("{:064x}", 1000 + i);
            let new = NewSubmission {
                user_id,
                task: TASK,
                name: "quota",
                checkpoint_sha256: &digest,
                checkpoints: &[],
                episodes_per_threshold: 20,
                dataset_version: None,
            };
            together.wait().await;
            queue::insert(&db, new, &limited).await.map_err(|e| e.to_string())
        })
    });
    let results: Vec<Result<i64, String>> = futures::future::join_all(submissions)
        .await
        .into_iter()
        .map(|r| r.unwrap())
        .collect();
    assert_eq!(results.iter().filter(|r| r.is_ok()).count(), 2, "{results:?}");
    assert!(
        results
            .iter()
            .filter_map(|r| r.as_ref().err())
            .all(|e| e.contains("queued or running")),
        "{results:?}"
    );
}

/// A managed PostgreSQL takes TLS: `database.url` carries libpq's `sslmode` and `sslrootcert`. Against a server that
/// rejects plaintext connections, `verify-full` with the server's CA connects (and migrates); plaintext is refused by
/// the server, and `verify-full` without the CA by the client.
#[tokio::test]
async fn postgres_over_tls_is_verified_and_plaintext_refused() {
    use dsrl_service::db::{Backend, Db};

    let (pg, ca) = Postgres::start_tls();
    let verified = format!("{}?sslmode=verify-full&sslrootcert={}", pg.url, ca.display());
    let db = Db::connect(&verified, 2).await.expect("a verified TLS connection");
    assert_eq!(db.backend(), Backend::Postgres);
    db.ping().await.unwrap();
    let plaintext = Db::connect(&format!("{}?sslmode=disable", pg.url), 2).await;
    let refused = plaintext.err().expect("plaintext must be refused").to_string();
    assert!(
        refused.contains("no encryption") || refused.contains("pg_hba"),
        "{refused}"
    );
    let unknown_ca = Db::connect(&format!("{}?sslmode=verify-full", pg.url), 2).await;
    assert!(
        unknown_ca.is_err(),
        "a server certificate from an unknown CA must not be accepted"
    );
}
