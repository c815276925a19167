//! The server's simulator worker pool with real `dsrl-sim-worker` processes: start-up and status, replacement of a
//! killed worker, fast failure of its sessions, placement by load, remote workers, and no orphans.

use std::time::Duration;

use dsrl_proto::simulator::v1::{AutoReset, Open};
use dsrl_simulators::SimulatorPool;
use dsrl_simulators::SimulatorsConfig;

use crate::{Env, get_json, get_json_with_token};

fn worker_binary() -> String {
    dsrl_e2e::bin("dsrl-sim-worker").display().to_string()
}

fn alive(pid: u32) -> bool {
    // A killed child stays a zombie until reaped; count those as gone.
    std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|stat| !stat.contains(") Z "))
}

fn pool_config(local: u32, remote: Vec<String>) -> SimulatorsConfig {
    SimulatorsConfig {
        local_workers: local,
        worker_binary: Some(worker_binary().into()),
        remote_workers: remote,
        health_interval_ms: 200,
        request_timeout_s: 60,
        ..SimulatorsConfig::default()
    }
}

/// A worker started apart from any pool (as one on another machine would be), killed when dropped; its address.
async fn start_worker(args: &[&str]) -> (tokio::process::Child, String) {
    let mut worker = tokio::process::Command::new(worker_binary())
        .args(["--listen", "127.0.0.1:0", "--exit-with-stdin"])
        .args(args)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut lines = tokio::io::AsyncBufReadExt::lines(tokio::io::BufReader::new(worker.stdout.take().unwrap()));
    let address = loop {
        let line = lines.next_line().await.unwrap().expect("the worker exited");
        if let Some(a) = line.strip_prefix("dsrl-sim-worker listening on ") {
            break a.to_owned();
        }
    };
    tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
    (worker, address)
}

fn open(task: &str, k: u32) -> Open {
    Open {
        task: task.into(),
        num_envs: k,
        seeds: vec![],
        auto_reset: AutoReset::SameStep as i32,
        controller: None,
    }
}

#[test]
fn the_server_supervises_its_workers_and_takes_them_down_with_it() {
    let binary = worker_binary();
    let mut env = Env::with(
        &[],
        &[
            ("DSRL__SIMULATORS__LOCAL_WORKERS", "1"),
            ("DSRL__SIMULATORS__WORKER_BINARY", &binary),
        ],
    );
    let status = |env: &Env| {
        get_json_with_token(&format!("{}/v1/simulators", env.server.url), &env.server.token())["workers"][0].clone()
    };
    assert!(
        dsrl_e2e::wait_for(Duration::from_secs(120), || status(&env)["healthy"] == true),
        "{}",
        status(&env)
    );
    // Without the admin token: the summary only, no pids or addresses (an outside probe flagged them).
    let public = get_json(&format!("{}/v1/simulators", env.server.url));
    assert_eq!(public["healthy_workers"], 1, "{public}");
    assert_eq!(public["workers_total"], 1, "{public}");
    assert!(public["free_envs"].as_u64().unwrap() > 0, "{public}");
    assert!(public.get("workers").is_none(), "{public}");
    // Any other token (a user's, a wrong one) gets the same public view, not an error.
    let wrong = get_json_with_token(&format!("{}/v1/simulators", env.server.url), "not-the-admin-token");
    assert_eq!(wrong, public, "{wrong}");
    let first = status(&env);
    assert_eq!(first["kind"], "local");
    assert_eq!(first["restarts"], 0);
    assert!(first["max_envs"].as_u64().unwrap() > 0);
    let pid = first["pid"].as_u64().unwrap() as u32;

    crate::kill_hard(pid);
    let replaced = dsrl_e2e::wait_for(Duration::from_secs(120), || {
        let s = status(&env);
        s["healthy"] == true && s["restarts"] == 1 && s["pid"].as_u64() != Some(u64::from(pid))
    });
    assert!(replaced, "the killed worker was not replaced: {}", status(&env));

    // A server killed outright leaves no worker behind (they exit when their stdin closes).
    let worker = status(&env)["pid"].as_u64().unwrap() as u32;
    env.server.kill();
    assert!(
        dsrl_e2e::wait_for(Duration::from_secs(20), || !alive(worker)),
        "worker {worker} outlived its server"
    );
}

#[tokio::test]
async fn sessions_fail_fast_when_their_worker_dies_and_the_pool_recovers() {
    let pool = SimulatorPool::start(&pool_config(1, vec![]));
    assert!(
        pool.wait_healthy(1, Duration::from_secs(120)).await,
        "{:?}",
        pool.workers()
    );
    let mut session = pool.open(open("OfflineBallRun-v0", 2)).await.unwrap();
    assert_eq!(session.worker(), "local-0");
    assert_eq!(
        session.initial_observations().len(),
        2 * session.spec().obs_dim as usize
    );
    session.step(&[], &[0.0; 4]).await.unwrap();

    crate::kill_hard(pool.workers()[0].pid.unwrap());
    let started = std::time::Instant::now();
    let err = session
        .step(&[], &[0.0; 4])
        .await
        .expect_err("a step on a dead worker succeeded");
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "failing took {:?}",
        started.elapsed()
    );
    let message = err.to_string();
    assert!(message.contains("simulator worker local-0"), "{message}");

    let recovered = tokio::time::timeout(Duration::from_secs(120), async {
        loop {
            let w = &pool.workers()[0];
            if w.healthy && w.restarts == 1 {
                return;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    assert!(recovered.is_ok(), "no replacement: {:?}", pool.workers());
    let mut again = pool.open(open("SafetyBallRun-v0", 1)).await.unwrap();
    again.step(&[], &[0.1, 0.1]).await.unwrap();
    again.close().await.unwrap();
}

#[tokio::test]
async fn sessions_spread_over_local_and_remote_workers_by_load() {
    // A worker started by hand stands in for one on another machine.
    let (_remote, address) = start_worker(&["--max-envs", "8"]).await;

    let pool = SimulatorPool::start(&pool_config(1, vec![address.clone()]));
    assert!(
        pool.wait_healthy(2, Duration::from_secs(120)).await,
        "{:?}",
        pool.workers()
    );
    let remote_status = pool.workers().into_iter().find(|w| w.kind == "remote").unwrap();
    assert_eq!(remote_status.address.as_deref(), Some(address.as_str()));
    assert_eq!(remote_status.max_envs, 8);

    let a = pool.open(open("SafetyCarRun-v0", 4)).await.unwrap();
    let b = pool.open(open("SafetyCarRun-v0", 4)).await.unwrap();
    assert_ne!(
        a.worker(),
        b.worker(),
        "two sessions went to one worker while the other was idle"
    );
    // The remote worker (8 envs) is now half full; more than it has left must go elsewhere or fail clearly.
    let c = pool.open(open("SafetyCarRun-v0", 6)).await.unwrap();
    assert_eq!(c.worker(), "local-0");
    for s in [a, b, c] {
        s.close().await.unwrap();
    }

    // Concurrent opens (an evaluation opens its three threshold sessions at once) spread over both workers:
    // capacity is reserved at placement, not counted only after each open returns (before, all four saw the same
    // load and went to one worker). The closes above reach the counts at the next health check.
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let opens = (0..4).map(|_| pool.open(open("SafetyCarRun-v0", 2)));
    let sessions = futures::future::try_join_all(opens).await.unwrap();
    let on_remote = sessions.iter().filter(|s| s.worker() != "local-0").count();
    let placed: Vec<String> = sessions.iter().map(|s| s.worker().to_owned()).collect();
    assert!((1..=3).contains(&on_remote), "all on one worker: {placed:?}");
    for s in sessions {
        s.close().await.unwrap();
    }

    let empty = SimulatorPool::start(&pool_config(0, vec![]));
    let err = empty
        .open(open("SafetyCarRun-v0", 1))
        .await
        .err()
        .expect("opened without workers");
    assert!(err.to_string().contains("no simulator workers are configured"), "{err}");
}

/// Workers behind a service name are found by resolving it (here `localhost:PORT` through the system resolver, as a
/// Kubernetes headless Service name would be) and used like any other.
#[tokio::test]
async fn workers_behind_a_service_name_are_discovered() {
    let (_worker, address) = start_worker(&[]).await;
    let port = address.rsplit(':').next().unwrap();
    let config = SimulatorsConfig {
        worker_services: vec![format!("localhost:{port}")],
        discovery_interval_ms: 200,
        ..pool_config(0, vec![])
    };
    let pool = SimulatorPool::start(&config);
    assert!(
        pool.wait_healthy(1, Duration::from_secs(60)).await,
        "{:?}",
        pool.workers()
    );
    let found = pool.workers().into_iter().find(|w| w.healthy).unwrap();
    assert_eq!(found.kind, "discovered");
    assert_eq!(found.address.as_deref(), Some(address.as_str()));
    let session = pool.open(open("SafetyCarRun-v0", 2)).await.unwrap();
    assert_eq!(session.worker(), format!("localhost:{port}@{address}"));
    session.close().await.unwrap();
}
