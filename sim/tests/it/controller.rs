//! The built-in IDM driver of MetaDrive data collection: it drives instead of the client, reports what it applied,
//! and is as reproducible as everything else; other families refuse it. A reset can switch its settings.

use dsrl_proto::simulator::v1::{AutoReset, Controller, Idm, Open, controller};
use dsrl_proto::simulator_session::{SimulatorSession, StepResult};
use tonic::Code;

use crate::support::Worker;

fn idm_open(task: &str, seeds: Vec<u64>) -> Open {
    Open {
        task: task.into(),
        num_envs: seeds.len() as u32,
        seeds,
        auto_reset: AutoReset::None as i32,
        controller: Some(Controller {
            kind: Some(controller::Kind::Idm(Idm {
                target_speed: 13.0,
                acc_factor: 1.2,
            })),
        }),
    }
}

async fn drive(worker: &Worker, steps: usize) -> Vec<StepResult> {
    let (mut session, _) =
        SimulatorSession::open(worker.channel().await, idm_open("SafeMetaDrive-easysparse-v0", vec![3]))
            .await
            .unwrap();
    let mut out = Vec::new();
    for _ in 0..steps {
        // The client's actions are ignored while the controller drives.
        out.push(session.step(&[], &[-1.0, -1.0]).await.unwrap());
    }
    session.close().await.unwrap();
    out
}

#[tokio::test]
async fn the_idm_driver_drives_metadrive_reproducibly() {
    let worker = Worker::start(&[]).await;
    let a = drive(&worker, 60).await;
    let throttle: f32 = a.iter().map(|s| s.applied_actions[1]).sum();
    assert!(
        throttle > 10.0,
        "the IDM driver should accelerate (full brake was sent): {throttle}"
    );
    assert!(
        a.iter()
            .all(|s| s.applied_actions.iter().all(|v| (-1.0..=1.0).contains(v)))
    );
    assert!(
        a.iter().map(|s| s.rewards[0]).sum::<f64>() > 0.0,
        "driving forward earns reward"
    );
    let b = drive(&worker, 60).await;
    assert!(a == b, "the noisy IDM driver must be seeded by the episode seed");

    let status = SimulatorSession::open(worker.channel().await, idm_open("SafetyCarRun-v0", vec![0]))
        .await
        .err()
        .unwrap();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("only MetaDrive"), "{}", status.message());
    let mut bad = idm_open("SafeMetaDrive-easysparse-v0", vec![0]);
    bad.controller = Some(Controller {
        kind: Some(controller::Kind::Idm(Idm {
            target_speed: f64::NAN,
            acc_factor: 1.0,
        })),
    });
    let status = SimulatorSession::open(worker.channel().await, bad).await.err().unwrap();
    assert_eq!(status.code(), Code::InvalidArgument);
}

fn idm(target_speed: f64, acc_factor: f64) -> Controller {
    Controller {
        kind: Some(controller::Kind::Idm(Idm {
            target_speed,
            acc_factor,
        })),
    }
}

fn reward(steps: &[StepResult]) -> f64 {
    steps.iter().map(|s| s.rewards[0]).sum()
}

async fn steps(session: &mut SimulatorSession, n: usize) -> Vec<StepResult> {
    let mut out = Vec::new();
    for _ in 0..n {
        out.push(session.step(&[], &[0.0, 0.0]).await.unwrap());
    }
    out
}

#[tokio::test]
async fn a_reset_switches_the_driver_as_a_fresh_session_at_those_settings_would_drive() {
    let worker = Worker::start(&[]).await;
    // One environment plays 13 km/h, then is switched to 5 km/h on reset (the sweep's reuse of environments).
    let (mut reused, _) =
        SimulatorSession::open(worker.channel().await, idm_open("SafeMetaDrive-easysparse-v0", vec![3]))
            .await
            .unwrap();
    let fast = steps(&mut reused, 80).await;
    reused.reset_with(&[0], &[3], Some(idm(5.0, 0.6))).await.unwrap();
    let switched = steps(&mut reused, 80).await;
    reused.close().await.unwrap();
    // A fresh environment at 5 km/h.
    let mut open = idm_open("SafeMetaDrive-easysparse-v0", vec![3]);
    open.controller = Some(idm(5.0, 0.6));
    let (mut fresh, _) = SimulatorSession::open(worker.channel().await, open).await.unwrap();
    let slow = steps(&mut fresh, 80).await;
    fresh.close().await.unwrap();
    let (fast, switched, slow) = (reward(&fast), reward(&switched), reward(&slow));
    assert!(
        (fast - slow).abs() > 0.2 * slow.abs(),
        "13 and 5 km/h should earn different rewards: {fast} and {slow}"
    );
    assert!(
        (switched - slow).abs() <= 1e-3 * slow.abs(),
        "after the switch the driver should drive as a fresh one at 5 km/h: {switched} against {slow}"
    );

    // Only a driven session can switch, and the new settings are checked as an Open's are.
    let (mut client_driven, _) = worker.open("SafeMetaDrive-easysparse-v0", &[0], AutoReset::None).await;
    let status = client_driven
        .reset_with(&[0], &[1], Some(idm(5.0, 0.6)))
        .await
        .err()
        .unwrap();
    assert_eq!(status.code(), Code::FailedPrecondition, "{}", status.message());
    let (mut driven, _) =
        SimulatorSession::open(worker.channel().await, idm_open("SafeMetaDrive-easysparse-v0", vec![0]))
            .await
            .unwrap();
    let status = driven.reset_with(&[0], &[1], Some(idm(-1.0, 0.6))).await.err().unwrap();
    assert_eq!(status.code(), Code::InvalidArgument, "{}", status.message());
}
