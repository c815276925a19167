//! The protocol's error cases against a real worker: each must end the session with the documented code and a
//! message that says what was wrong, and must never leak environments.

use std::time::Duration;

use dsrl_proto::simulator::v1::{AutoReset, DType, DescribeRequest, Open, Step, Tensor, session_request};
use dsrl_simulators::session::{Reply, SimulatorSession};
use tonic::Code;

use crate::support::{Actions, Worker};

const TASK: &str = "SafetyBallRun-v0";

async fn expect_error(session: &mut SimulatorSession, kind: session_request::Kind, code: Code, needle: &str) {
    session.send_raw(kind).await.ok();
    let status = session.receive().await.expect_err("the worker accepted a bad request");
    assert_eq!(status.code(), code, "{status:?}");
    assert!(
        status.message().contains(needle),
        "message {:?} lacks {needle:?}",
        status.message()
    );
}

fn step(envs: Vec<u32>, dtype: DType, shape: Vec<u64>, data: Vec<u8>) -> session_request::Kind {
    session_request::Kind::Step(Step {
        envs,
        actions: Some(Tensor {
            dtype: dtype as i32,
            shape,
            data,
        }),
    })
}

#[tokio::test]
async fn unknown_tasks_are_not_found_with_suggestions() {
    let worker = Worker::start(&[]).await;
    let status = worker
        .client()
        .await
        .describe(DescribeRequest {
            task: "SafetyBalRun-v0".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert!(status.message().contains("SafetyBallRun-v0"), "{}", status.message());
    let open = Open {
        task: "OfflineBalRun-v0".into(),
        num_envs: 1,
        ..Default::default()
    };
    let status = SimulatorSession::open(worker.channel().await, open)
        .await
        .err()
        .expect("unknown task opened");
    assert_eq!(status.code(), Code::NotFound);
    assert!(status.message().contains("OfflineBallRun-v0"), "{}", status.message());
    // Offline ids are accepted and mean their simulator.
    let spec = worker
        .client()
        .await
        .describe(DescribeRequest {
            task: "OfflineBallRun-v0".into(),
        })
        .await
        .unwrap();
    assert_eq!(spec.get_ref().task, TASK);
    worker.wait_idle(Duration::from_secs(10)).await;
}

#[tokio::test]
async fn malformed_actions_are_invalid_argument() {
    let worker = Worker::start(&[]).await;
    let act_dim = 2u64; // SafetyBallRun-v0
    let f32s = |n: usize, v: f32| v.to_le_bytes().repeat(n);
    let cases = [
        (step(vec![], DType::Float32, vec![2, 3], f32s(6, 0.0)), "shape"),
        (step(vec![], DType::Float32, vec![4], f32s(4, 0.0)), "shape"),
        (
            step(vec![], DType::Float64, vec![2, act_dim], vec![0; 32]),
            "dtype FLOAT64",
        ),
        (step(vec![], DType::Float32, vec![2, act_dim], vec![0; 15]), "bytes"),
        (
            step(vec![5], DType::Float32, vec![1, act_dim], f32s(2, 0.0)),
            "out of range",
        ),
        (
            step(vec![1, 1], DType::Float32, vec![2, act_dim], f32s(4, 0.0)),
            "named twice",
        ),
        (
            step(vec![], DType::Float32, vec![2, act_dim], f32s(4, f32::NAN)),
            "finite",
        ),
        (
            step(vec![], DType::Float32, vec![2, act_dim], f32s(4, f32::NEG_INFINITY)),
            "finite",
        ),
        (
            session_request::Kind::Step(Step {
                envs: vec![],
                actions: None,
            }),
            "without actions",
        ),
    ];
    for (kind, needle) in cases {
        let (mut session, _) = worker.open(TASK, &[0, 1], AutoReset::None).await;
        expect_error(&mut session, kind, Code::InvalidArgument, needle).await;
    }
    worker.wait_idle(Duration::from_secs(10)).await;
}

#[tokio::test]
async fn out_of_bounds_actions_are_clipped_to_the_action_space() {
    let worker = Worker::start(&[]).await;
    let (mut clipped, _) = worker.open(TASK, &[3], AutoReset::None).await;
    let (mut bounded, _) = worker.open(TASK, &[3], AutoReset::None).await;
    let (low, high) = (clipped.spec().action_low.clone(), clipped.spec().action_high.clone());
    assert!(high.iter().all(|&h| h < 1e6));
    for i in 0..20 {
        let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
        let wild: Vec<f32> = low.iter().map(|_| sign * 1e6).collect();
        let edge: Vec<f32> = if sign > 0.0 {
            high.iter().map(|&h| h as f32).collect()
        } else {
            low.iter().map(|&l| l as f32).collect()
        };
        let a = clipped.step(&[], &wild).await.unwrap();
        let b = bounded.step(&[], &edge).await.unwrap();
        assert_eq!(a.applied_actions, edge, "the applied action is the clipped one");
        assert_eq!(a, b, "step {i}: an action beyond the bounds must act as the bound");
    }
}

#[tokio::test]
async fn stepping_a_finished_episode_is_failed_precondition_until_reset() {
    let worker = Worker::start(&[]).await;
    let (mut session, _) = worker.open(TASK, &[1], AutoReset::None).await;
    let spec = session.spec().clone();
    let mut actions = Actions::new(7);
    let mut steps = 0;
    loop {
        let out = session
            .step(&[], &actions.batch(&spec.action_low, &spec.action_high, 1))
            .await
            .unwrap();
        steps += 1;
        if out.terminated[0] || out.truncated[0] {
            break;
        }
        assert!(steps <= spec.max_episode_steps, "no episode end within the horizon");
    }
    // A reset makes the environment steppable again.
    let observations = session.reset(&[0], &[11]).await.unwrap();
    assert_eq!(observations.len(), spec.obs_dim as usize);
    session
        .step(&[], &actions.batch(&spec.action_low, &spec.action_high, 1))
        .await
        .unwrap();
    // Run to the end again, then step once more.
    loop {
        let out = session
            .step(&[], &actions.batch(&spec.action_low, &spec.action_high, 1))
            .await
            .unwrap();
        if out.terminated[0] || out.truncated[0] {
            break;
        }
    }
    let kind = session_request::Kind::Step(Step {
        envs: vec![],
        actions: Some(Tensor::from_f32(&[1, 2], &[0.0, 0.0])),
    });
    expect_error(&mut session, kind, Code::FailedPrecondition, "env 0 has finished").await;
    worker.wait_idle(Duration::from_secs(10)).await;
}

#[tokio::test]
async fn auto_reset_returns_the_final_observation_and_continues() {
    let worker = Worker::start(&[]).await;
    let (mut session, _) = worker.open(TASK, &[2, 3], AutoReset::SameStep).await;
    let spec = session.spec().clone();
    let mut actions = Actions::new(3);
    let mut ended = 0;
    for _ in 0..(2 * spec.max_episode_steps) {
        let out = session
            .step(&[], &actions.batch(&spec.action_low, &spec.action_high, 2))
            .await
            .unwrap();
        let finals = out.final_observations.expect("final observations with auto-reset");
        for k in 0..2 {
            let row = &finals[k * spec.obs_dim as usize..(k + 1) * spec.obs_dim as usize];
            if out.terminated[k] || out.truncated[k] {
                ended += 1;
                assert!(
                    row.iter().any(|&v| v != 0.0),
                    "finished env {k} without its last observation"
                );
            } else {
                assert!(row.iter().all(|&v| v == 0.0));
            }
        }
        if ended >= 2 {
            break;
        }
    }
    assert!(ended >= 2, "no automatic resets happened");
}

#[tokio::test]
async fn protocol_order_is_enforced_and_pipelined_requests_answer_in_order() {
    let worker = Worker::start(&[]).await;
    // The first request must be Open.
    let (requests, receiver) = tokio::sync::mpsc::channel(4);
    let mut client = worker.client().await;
    let call = client.session(tokio_stream::wrappers::ReceiverStream::new(receiver));
    requests
        .send(dsrl_proto::simulator::v1::SessionRequest {
            id: 1,
            kind: Some(session_request::Kind::Close(Default::default())),
        })
        .await
        .unwrap();
    let status = call.await.unwrap().into_inner().message().await.unwrap_err();
    assert_eq!(status.code(), Code::FailedPrecondition);
    assert!(status.message().contains("must be Open"));

    let (mut session, _) = worker.open(TASK, &[0, 1, 2], AutoReset::SameStep).await;
    for _ in 0..10 {
        session.send_step(&[2, 0], &[0.1, 0.1, -0.1, -0.1]).await.unwrap();
    }
    for _ in 0..10 {
        match session.receive().await.unwrap() {
            Reply::Step(out) => assert_eq!(out.envs, vec![2, 0]),
            other => panic!("expected a step, got {other:?}"),
        }
    }
    let open_again = session_request::Kind::Open(Open {
        task: TASK.into(),
        num_envs: 1,
        ..Default::default()
    });
    expect_error(&mut session, open_again, Code::FailedPrecondition, "already open").await;
}

#[tokio::test]
async fn batches_beyond_the_limits_are_resource_exhausted() {
    let worker = Worker::start(&["--max-envs-per-session", "4", "--max-envs", "6"]).await;
    let open = |k: u32| Open {
        task: TASK.into(),
        num_envs: k,
        ..Default::default()
    };
    let status = SimulatorSession::open(worker.channel().await, open(5))
        .await
        .err()
        .expect("5 > 4 opened");
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert!(status.message().contains("per session"), "{}", status.message());
    let (first, _) = SimulatorSession::open(worker.channel().await, open(4)).await.unwrap();
    let status = SimulatorSession::open(worker.channel().await, open(3))
        .await
        .err()
        .expect("4 + 3 > 6 opened");
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert!(status.message().contains("at most 6"), "{}", status.message());
    first.close().await.unwrap();
    worker.wait_idle(Duration::from_secs(10)).await;
    let (second, _) = SimulatorSession::open(worker.channel().await, open(4)).await.unwrap();
    second.close().await.unwrap();
}

#[tokio::test]
async fn a_client_that_disappears_leaks_no_session() {
    let worker = Worker::start(&[]).await;
    let (mut session, _) = worker.open(TASK, &[0, 1, 2], AutoReset::SameStep).await;
    session.step(&[], &[0.0; 6]).await.unwrap();
    // Leave requests in flight, then vanish without Close.
    for _ in 0..5 {
        session.send_step(&[], &[0.0; 6]).await.unwrap();
    }
    let busy = worker.health().await;
    assert_eq!((busy.sessions, busy.envs), (1, 3));
    drop(session);
    worker.wait_idle(Duration::from_secs(10)).await;
    // A MetaDrive session's environments are child processes: they go too. (The first one also starts
    // multiprocessing's resource tracker, which stays; count from after it.)
    let (first, _) = worker.open("SafeMetaDrive-easysparse-v0", &[0], AutoReset::None).await;
    first.close().await.unwrap();
    worker.wait_idle(Duration::from_secs(30)).await;
    let before = worker.child_processes();
    let (session, _) = worker
        .open("SafeMetaDrive-easysparse-v0", &[0, 1], AutoReset::None)
        .await;
    assert_eq!(worker.health().await.envs, 2);
    assert_eq!(
        worker.child_processes(),
        before + 2,
        "one process per MetaDrive environment"
    );
    drop(session);
    worker.wait_idle(Duration::from_secs(30)).await;
    assert_eq!(worker.child_processes(), before);
}
