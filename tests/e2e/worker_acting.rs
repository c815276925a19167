//! A policy acting inside real `dsrl-sim-worker` processes (the simulator proto's `Act` and `Play`): the session's
//! rules, a checkpoint the worker refuses, and scoring in the workers giving the very episodes that acting through
//! the server's policy process gives: on a task whose episodes end at different steps, and on a Bullet task whose
//! episodes all end together and depend on the episode their environment played before (Bullet keeps motor
//! targets across a reset), so that a seed handed to another environment than the relayed scoring's changes an
//! episode.

use std::sync::atomic::AtomicU32;
use std::time::Duration;

use bytes::Bytes;
use dsrl_evaluation::evaluator::play_episodes_counted;
use dsrl_evaluation::inference::{IsolatedPolicy, PolicySource};
use dsrl_proto::simulator::v1::{AutoReset, Open};
use dsrl_simulators::{PooledSession, Reply, SimulatorPool, SimulatorsConfig};
use dsrl_suite::catalog::Catalog;

/// Hopper falls after a varying number of steps under an untrained policy: episodes of different lengths.
const TASK: &str = "OfflineHopperVelocityGymnasium-v1";

async fn pool(workers: u32) -> SimulatorPool {
    let pool = SimulatorPool::start(&SimulatorsConfig {
        local_workers: workers,
        worker_binary: Some(dsrl_e2e::bin("dsrl-sim-worker")),
        health_interval_ms: 200,
        request_timeout_s: 60,
        ..SimulatorsConfig::default()
    });
    assert!(
        pool.wait_healthy(workers as usize, Duration::from_secs(120)).await,
        "{:?}",
        pool.workers()
    );
    pool
}

fn checkpoint(dir: &std::path::Path, task: &str, arch: &str) -> (Bytes, Bytes) {
    let out = crate::make_policy(&dir.join(format!("{task}-{arch}")), task, arch, 3);
    (
        std::fs::read(out.join("policy.json")).unwrap().into(),
        std::fs::read(out.join("policy.safetensors")).unwrap().into(),
    )
}

async fn session(pool: &SimulatorPool, k: u32) -> PooledSession {
    pool.open(Open {
        task: TASK.into(),
        num_envs: k,
        seeds: vec![],
        auto_reset: AutoReset::None as i32,
        controller: None,
    })
    .await
    .unwrap()
}

#[tokio::test]
async fn a_session_plays_its_policy_by_its_rules() {
    let pool = pool(1).await;
    let dir = tempfile::tempdir().unwrap();
    let (config, weights) = checkpoint(dir.path(), TASK, "caps");

    // Played: each answer is one end; the episodes that end are among those played, with their whole length.
    let mut s = session(&pool, 3).await;
    s.send_act(&config, &weights, 20.0, 30.0).await.unwrap();
    assert_eq!(s.receive().await.unwrap(), Reply::Acting);
    s.send_play(&[]).await.unwrap();
    let Reply::Played(played) = s.receive().await.unwrap() else {
        panic!("a play not answered with Played")
    };
    assert!(played.steps > 0 && !played.ended.is_empty(), "{played:?}");
    for e in &played.ended {
        assert!(
            e.env < 3 && e.length == played.steps && e.cost_return >= 0.0,
            "{played:?}"
        );
    }
    // An ended environment must be reset before it plays again; a reset starts its next episode.
    let ended: Vec<u32> = played.ended.iter().map(|e| e.env).collect();
    s.send_play(&ended).await.unwrap();
    let err = s.receive().await.unwrap_err().to_string();
    assert!(err.contains("reset it before playing it"), "{err}");

    // The session's policy chooses the actions: a step of the client's own is refused.
    let mut s = session(&pool, 1).await;
    s.send_act(&config, &weights, 20.0, 30.0).await.unwrap();
    s.send_step(&[0], &[0.0, 0.0, 0.0]).await.unwrap();
    assert_eq!(s.receive().await.unwrap(), Reply::Acting);
    let err = s.receive().await.unwrap_err().to_string();
    assert!(err.contains("play its environments with Play"), "{err}");

    // A play without a policy, and a policy that comes after the first episode began.
    let mut s = session(&pool, 1).await;
    s.send_play(&[]).await.unwrap();
    let err = s.receive().await.unwrap_err().to_string();
    assert!(err.contains("play needs a policy"), "{err}");
    let mut s = session(&pool, 1).await;
    s.send_reset(&[0], &[5]).await.unwrap();
    s.send_act(&config, &weights, 20.0, 30.0).await.unwrap();
    assert!(matches!(s.receive().await.unwrap(), Reply::Reset { .. }));
    let err = s.receive().await.unwrap_err().to_string();
    assert!(err.contains("Act must be the first request after Open"), "{err}");

    // Checkpoints the worker refuses: another task's dimensions, weights that are not safetensors, and a forward
    // pass over its CPU budget (the checkpoint's doing: INVALID_ARGUMENT, not the worker's).
    let (other, other_weights) = checkpoint(dir.path(), "OfflineBallRun-v0", "caps");
    let refusals: [(&[u8], &[u8], f64, &str); 3] = [
        (&other, &other_weights, 30.0, "observation dim"),
        (&config, b"not safetensors", 30.0, "weights"),
        (&config, &weights, 1e-9, "CPU time for one forward pass"),
    ];
    for (config, weights, budget, expected) in refusals {
        let mut s = session(&pool, 2).await;
        s.send_act(config, weights, 20.0, budget).await.unwrap();
        s.send_play(&[]).await.unwrap();
        let err = match s.receive().await {
            Ok(Reply::Acting) => s.receive().await.unwrap_err(),
            Ok(other) => panic!("{other:?}"),
            Err(e) => e,
        };
        assert!(
            matches!(err, dsrl_simulators::SimulatorError::InvalidArgument(_)),
            "{expected}: {err:?}"
        );
        assert!(err.to_string().contains(expected), "{expected}: {err}");
    }
}

#[tokio::test]
async fn scoring_in_the_workers_plays_the_episodes_the_policy_process_plays() {
    let pool = pool(2).await;
    let catalog = Catalog::embedded().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let seeds: Vec<u64> = (0..20).map(|i| 1000 + 7 * i).collect();
    // A memoryless network, one that hears every step's cost (CAPS) and one with a context of past steps (CDT);
    // whether a task's episodes end at different steps.
    let cases = [
        (TASK, "target-cost-mlp", true),
        (TASK, "caps", true),
        (TASK, "cdt", true),
        ("OfflineCarCircle-v0", "caps", false),
    ];
    for (task, arch, varied) in cases {
        let task = catalog.get(task).unwrap();
        let (config, weights) = checkpoint(dir.path(), task.id.as_str(), arch);
        let policy = |act_in_workers| IsolatedPolicy {
            program: dsrl_e2e::bin("dsrl-server"),
            memory_limit_bytes: 4 << 30,
            request_timeout: Duration::from_secs(30),
            act_in_workers,
            config: config.clone(),
            weights: weights.clone(),
        };
        let (in_workers, relayed) = (policy(true), policy(false));
        let (progress, relayed_progress) = (AtomicU32::new(0), AtomicU32::new(0));
        let (a, b) = futures::future::join(
            play_episodes_counted(
                &pool,
                task,
                PolicySource::Isolated(&in_workers),
                40.0,
                &seeds,
                5,
                1,
                &progress,
            ),
            play_episodes_counted(
                &pool,
                task,
                PolicySource::Isolated(&relayed),
                40.0,
                &seeds,
                5,
                1,
                &relayed_progress,
            ),
        )
        .await;
        let (a, b) = (a.unwrap(), b.unwrap());
        assert_eq!(
            a, b,
            "{arch} on {}: acting in the workers played other episodes",
            task.id
        );
        assert_eq!(progress.into_inner(), 20, "{arch} on {}", task.id);
        let lengths: std::collections::BTreeSet<u32> = a.iter().map(|e| e.length).collect();
        assert_eq!(
            lengths.len() > 1,
            varied,
            "{arch} on {}: episode lengths {lengths:?}",
            task.id
        );
    }
}
