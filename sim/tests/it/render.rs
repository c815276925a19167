//! Drawing environments (`Render`) on each family's renderer without a display: MuJoCo through EGL, pybullet's
//! software renderer, MetaDrive's top-down view. A frame is the size asked for and shows something that moves, and
//! drawing changes no episode: the same seeds and actions give the same steps with a frame after every step as
//! without any.

use dsrl_proto::simulator::v1::{AutoReset, Render, session_request};
use dsrl_simulators::session::StepResult;
use tonic::Code;

use crate::support::{Actions, Worker};

/// `steps` steps of two environments; with `draw`, env 1 is drawn at `width` x `height` after the open and after
/// every step. Returns the steps and the frames.
async fn play(worker: &Worker, task: &str, steps: usize, draw: Option<(u32, u32)>) -> (Vec<StepResult>, Vec<Vec<u8>>) {
    let (mut session, _) = worker.open(task, &[5, 6], AutoReset::SameStep).await;
    let spec = session.spec().clone();
    let mut actions = Actions::new(7);
    let (mut out, mut frames) = (Vec::new(), Vec::new());
    if let Some((w, h)) = draw {
        frames.push(session.render(&[1], w, h).await.unwrap().frames);
    }
    for _ in 0..steps {
        let batch = actions.batch(&spec.action_low, &spec.action_high, 2);
        out.push(session.step(&[], &batch).await.unwrap());
        if let Some((w, h)) = draw {
            let drawn = session.render(&[1], w, h).await.unwrap();
            assert_eq!((drawn.envs.as_slice(), drawn.width, drawn.height), (&[1u32][..], w, h));
            assert_eq!(drawn.frames.len(), (w * h * 3) as usize);
            frames.push(drawn.frames);
        }
    }
    session.close().await.unwrap();
    (out, frames)
}

async fn check(task: &str, steps: usize) {
    let worker = Worker::start(&[]).await;
    let (plain, _) = play(&worker, task, steps, None).await;
    let (drawn, frames) = play(&worker, task, steps, Some((64, 48))).await;
    assert!(plain == drawn, "{task}: drawing changed the episode");
    assert_eq!(frames.len(), steps + 1);
    let first = &frames[0];
    assert!(first.iter().any(|&p| p != first[0]), "{task}: a frame of one colour");
    let distinct: std::collections::HashSet<&Vec<u8>> = frames.iter().collect();
    assert!(distinct.len() > 1, "{task}: every frame is the same");
}

#[tokio::test]
async fn bullet_frames_leave_episodes_unchanged() {
    check("SafetyCarCircle-v0", 20).await;
}

#[tokio::test]
async fn safety_gymnasium_frames_leave_episodes_unchanged() {
    check("SafetyPointGoal1-v0", 20).await;
}

#[tokio::test]
async fn metadrive_frames_leave_episodes_unchanged() {
    check("SafeMetaDrive-easymean-v0", 20).await;
}

#[tokio::test]
async fn frames_outside_the_limits_are_invalid_argument() {
    let worker = Worker::start(&[]).await;
    for (render, needle) in [
        (
            Render {
                envs: vec![],
                width: 1024,
                height: 64,
            },
            "width of 1024",
        ),
        (
            Render {
                envs: vec![],
                width: 64,
                height: 8,
            },
            "height of 8",
        ),
        (
            Render {
                envs: vec![3],
                width: 64,
                height: 64,
            },
            "out of range",
        ),
    ] {
        let (mut session, _) = worker.open("SafetyBallRun-v0", &[1, 2], AutoReset::None).await;
        session.send_raw(session_request::Kind::Render(render)).await.unwrap();
        let status = session.receive().await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert!(status.message().contains(needle), "{status:?}");
    }
}
