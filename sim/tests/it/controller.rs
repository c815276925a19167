//! The built-in IDM driver of MetaDrive data collection: it drives instead of the client, reports what it applied,
//! and is as reproducible as everything else; other families refuse it.

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
