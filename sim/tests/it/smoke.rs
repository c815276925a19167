//! One task per family through the protocol: the spaces match the catalog, the pinned simulator answers, and the
//! step outputs are well formed.

use dsrl_proto::simulator::v1::AutoReset;
use dsrl_suite::catalog::Catalog;

use crate::support::{Actions, Worker};

async fn smoke(offline_id: &str, simulator: &str, steps: usize) {
    let catalog = Catalog::embedded().unwrap();
    let task = catalog.get(offline_id).unwrap();
    let worker = Worker::start(&[]).await;
    let (mut session, first) = worker.open(offline_id, &[0, 1], AutoReset::SameStep).await;
    let spec = session.spec().clone();
    assert_eq!(spec.task, task.simulator_env_id);
    assert_eq!(spec.simulator, simulator);
    assert_eq!((spec.obs_dim, spec.act_dim), (task.obs_dim, task.act_dim));
    assert_eq!(spec.max_episode_steps, task.max_episode_steps);
    assert_eq!(first.len(), 2 * task.obs_dim as usize);
    let mut actions = Actions::new(1);
    let (mut rewards, mut last) = (Vec::new(), first.clone());
    for _ in 0..steps {
        let out = session
            .step(&[], &actions.batch(&spec.action_low, &spec.action_high, 2))
            .await
            .unwrap();
        assert_eq!(out.observations.len(), 2 * task.obs_dim as usize);
        assert!(out.observations.iter().all(|v| v.is_finite()));
        assert!(out.rewards.iter().all(|r| r.is_finite()));
        assert!(out.costs.iter().all(|&c| c >= 0.0 && c.is_finite()));
        assert_eq!(
            (out.rewards.len(), out.terminated.len(), out.truncated.len()),
            (2, 2, 2)
        );
        rewards.extend(out.rewards.iter().copied());
        last = out.observations;
    }
    // The simulator moved: the observations changed and the rewards are not one constant.
    assert_ne!(last, first, "{offline_id}: the observations never changed");
    rewards.sort_by(f64::total_cmp);
    rewards.dedup();
    assert!(rewards.len() > 1, "{offline_id}: every reward was {rewards:?}");
    session.close().await.unwrap();
}

#[tokio::test]
async fn bullet_safety_gym_steps() {
    smoke("OfflineDroneRun-v0", "bullet-safety-gym 1.4.0", 200).await;
}

#[tokio::test]
async fn safety_gymnasium_steps() {
    smoke("OfflinePointGoal1Gymnasium-v0", "safety-gymnasium 1.0.0", 200).await;
}

#[tokio::test]
async fn metadrive_steps() {
    smoke("OfflineMetadrive-easysparse-v0", "metadrive-simulator 0.4.3", 100).await;
}
