//! The `Simulator` gRPC service: task descriptions, sessions (one bidirectional stream each) and health.

use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

use dsrl_proto::simulator::v1 as pb;
use dsrl_proto::simulator::v1::{
    AutoReset, Closed, DType, DescribeRequest, Driven, DrivenEpisode, Frames, HealthRequest, HealthResponse,
    Observations, Opened, Reset, SessionRequest, SessionResponse, TaskSpec, Tensor, Transition, session_request,
    session_response, simulator_server::Simulator,
};
use dsrl_suite::catalog::{Catalog, Family};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

use crate::acting::Acting;
use crate::error::SimError;
use crate::python::{BatchShape, Controller, PyBatch, PythonHost, PythonThread};
use crate::session::{Limits, SessionState, check_open};

#[derive(Clone)]
pub struct SimulatorService {
    inner: Arc<Inner>,
}

struct Inner {
    host: Arc<PythonHost>,
    python: PythonThread,
    catalog: Catalog,
    limits: Limits,
    sessions: AtomicU32,
    envs: Arc<AtomicU32>,
    specs: Mutex<HashMap<String, TaskSpec>>,
}

/// Environments counted against the worker's capacity until dropped.
struct EnvReservation {
    count: u32,
    envs: Arc<AtomicU32>,
}

impl Drop for EnvReservation {
    fn drop(&mut self) {
        self.envs.fetch_sub(self.count, Ordering::SeqCst);
    }
}

/// An open batch: closed (on the Python thread) when the session ends for any reason, and only then are its
/// environments given back to the worker's capacity.
struct OpenBatch {
    batch: Option<Arc<PyBatch>>,
    reservation: Option<EnvReservation>,
    python: PythonThread,
}

impl Drop for OpenBatch {
    fn drop(&mut self) {
        let (Some(batch), reservation) = (self.batch.take(), self.reservation.take()) else {
            return;
        };
        self.python.spawn(move || {
            batch.close();
            drop(reservation);
        });
    }
}

impl SimulatorService {
    pub fn new(python: PythonThread, host: PythonHost, catalog: Catalog, limits: Limits) -> SimulatorService {
        SimulatorService {
            inner: Arc::new(Inner {
                host: Arc::new(host),
                python,
                catalog,
                limits,
                sessions: AtomicU32::new(0),
                envs: Arc::new(AtomicU32::new(0)),
                specs: Mutex::new(HashMap::new()),
            }),
        }
    }
}

impl Inner {
    /// The simulator id for a simulator id or an offline task id of the catalog.
    fn simulator_id(&self, task: &str) -> Result<String, SimError> {
        if let Some(t) = self
            .catalog
            .tasks()
            .iter()
            .find(|t| t.simulator_env_id == task || t.id.as_str() == task)
        {
            return Ok(t.simulator_env_id.clone());
        }
        // Suggest in the namespace the caller used: offline ids for `Offline...`, simulator ids otherwise.
        let offline = task.strip_prefix("Safety").map(|rest| format!("Offline{rest}"));
        let near = self.catalog.nearest(offline.as_deref().unwrap_or(task), 3);
        let suggestions = near
            .into_iter()
            .filter_map(|id| self.catalog.get(&id).ok())
            .map(|t| {
                if task.starts_with("Offline") {
                    t.id.as_str().to_owned()
                } else {
                    t.simulator_env_id.clone()
                }
            })
            .collect();
        Err(SimError::UnknownTask {
            id: task.to_owned(),
            suggestions,
        })
    }

    /// The built-in driver an `Open` asks for, if any: only MetaDrive tasks have one.
    fn controller(&self, sim_id: &str, controller: Option<&pb::Controller>) -> Result<Option<Controller>, SimError> {
        let Some(controller) = controller else { return Ok(None) };
        let Some(pb::controller::Kind::Idm(idm)) = &controller.kind else {
            return Err(SimError::InvalidArgument(
                "a controller must name its kind (idm)".into(),
            ));
        };
        let metadrive = self
            .catalog
            .tasks()
            .iter()
            .any(|t| t.simulator_env_id == sim_id && t.family == Family::MetaDrive);
        if !metadrive {
            return Err(SimError::InvalidArgument(format!(
                "{sim_id} has no IDM controller: only MetaDrive tasks do"
            )));
        }
        if !(idm.target_speed.is_finite()
            && idm.target_speed > 0.0
            && idm.acc_factor.is_finite()
            && idm.acc_factor >= 0.0)
        {
            return Err(SimError::InvalidArgument(format!(
                "IDM needs target_speed > 0 and acc_factor >= 0, got {} and {}",
                idm.target_speed, idm.acc_factor
            )));
        }
        // MetaDrive builds and keeps every map a session draws from (~1 s and some memory each).
        if idm.maps > pb::MAX_IDM_MAPS {
            return Err(SimError::InvalidArgument(format!(
                "IDM maps must be at most {}, got {}",
                pb::MAX_IDM_MAPS,
                idm.maps
            )));
        }
        Ok(Some(Controller::Idm {
            target_speed: idm.target_speed,
            acc_factor: idm.acc_factor,
            maps: idm.maps.max(1),
        }))
    }

    fn reserve(&self, count: u32) -> Result<EnvReservation, SimError> {
        let max = self.limits.max_envs;
        self.envs
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |used| {
                used.checked_add(count).filter(|&n| n <= max)
            })
            .map_err(|used| {
                SimError::ResourceExhausted(format!(
                    "this worker hosts {used} of at most {max} environments; {count} more do not fit"
                ))
            })?;
        Ok(EnvReservation {
            count,
            envs: self.envs.clone(),
        })
    }

    fn spec(&self, sim_id: &str, shape: &BatchShape) -> TaskSpec {
        TaskSpec {
            task: sim_id.to_owned(),
            family: shape.family.clone(),
            obs_dim: shape.obs_dim,
            act_dim: shape.act_dim,
            action_low: shape.action_low.clone(),
            action_high: shape.action_high.clone(),
            max_episode_steps: shape.max_episode_steps,
            simulator: shape.simulator.clone(),
            max_envs_per_session: self.limits.max_envs_per_session,
        }
    }
}

fn tensor(dtype: DType, shape: &[usize], data: Vec<u8>, width: usize, name: &str) -> Result<Tensor, SimError> {
    let want = shape.iter().product::<usize>() * width;
    if data.len() != want {
        return Err(SimError::Simulator(format!(
            "the simulator returned {} bytes of {name}, expected {want} for shape {shape:?}",
            data.len()
        )));
    }
    Ok(Tensor {
        dtype: dtype as i32,
        shape: shape.iter().map(|&d| d as u64).collect(),
        data,
    })
}

type Outbox = mpsc::Sender<Result<SessionResponse, Status>>;

async fn reply(outbox: &Outbox, id: u64, kind: session_response::Kind) -> Result<(), ()> {
    outbox
        .send(Ok(SessionResponse { id, kind: Some(kind) }))
        .await
        .map_err(|_| ())
}

/// One session, from `Open` to its end. Returns `Ok` when the client closed it or went away.
async fn run_session(
    inner: Arc<Inner>,
    inbound: &mut Streaming<SessionRequest>,
    outbox: &Outbox,
) -> Result<(), SimError> {
    let Ok(Some(first)) = inbound.message().await else {
        return Ok(());
    };
    let Some(session_request::Kind::Open(open)) = first.kind else {
        return Err(SimError::FailedPrecondition(
            "the first request of a session must be Open".into(),
        ));
    };
    let sim_id = inner.simulator_id(&open.task)?;
    let seeds = check_open(&open, inner.limits)?;
    let controller = inner.controller(&sim_id, open.controller.as_ref())?;
    let driven = controller;
    let reservation = inner.reserve(open.num_envs)?;
    let auto_reset = open.auto_reset == AutoReset::SameStep as i32;
    let k = seeds.len();
    let opening_seeds = seeds.clone();
    let host = inner.host.clone();
    let id = sim_id.clone();
    let (batch, shape, observations, build_cpu_seconds) = inner
        .python
        .run(move || {
            let (batch, shape) = host.open(&id, &seeds, auto_reset, controller)?;
            let all: Vec<u32> = (0..k as u32).collect();
            match batch
                .build_cpu_seconds()
                .and_then(|cpu| Ok((batch.reset(&all, &seeds, None)?, cpu)))
            {
                Ok((observations, cpu)) => Ok((batch, shape, observations, cpu)),
                Err(err) => {
                    batch.close();
                    Err(err)
                }
            }
        })
        .await??;
    let batch = Arc::new(batch);
    let _open = OpenBatch {
        batch: Some(batch.clone()),
        reservation: Some(reservation),
        python: inner.python.clone(),
    };
    let spec = inner.spec(&sim_id, &shape);
    let (obs_dim, act_dim) = (shape.obs_dim as usize, shape.act_dim as usize);
    let state = SessionState::new(obs_dim, act_dim, k, auto_reset);
    let opened_with = (opening_seeds, observations.clone());
    let observations = tensor(DType::Float32, &[k, obs_dim], observations, 4, "observations")?;
    tracing::info!(task = %sim_id, envs = k, auto_reset, build_cpu_seconds, "session opened");
    let opened = Opened {
        spec: Some(spec),
        observations: Some(observations),
    };
    if reply(outbox, first.id, session_response::Kind::Opened(opened))
        .await
        .is_err()
    {
        return Ok(());
    }
    // Requests are answered in order by jobs on the Python thread, submitted as soon as they arrive: a client
    // that pipelines keeps the simulator busy while earlier answers travel back. The session's rules are checked
    // inside each job (its state lives with the jobs), and after the first error no later job runs.
    let shape = Shape {
        obs_dim,
        act_dim,
        auto_reset,
        controlled: driven.is_some(),
    };
    let shared = Arc::new(Mutex::new(Jobs {
        state,
        failed: false,
        opened_with: Some(opened_with),
        acting: None,
    }));
    let (pending, mut answers) = mpsc::channel::<(u64, Answer)>(64);
    let (stop, mut stopped) = tokio::sync::oneshot::channel::<()>();
    // Set when the client leaves: a `Play` (many steps in one job) looks at it between steps.
    let client_gone = Arc::new(AtomicBool::new(false));
    let replies = outbox.clone();
    let forwarder = tokio::spawn(async move {
        while let Some((id, answer)) = answers.recv().await {
            let result = answer
                .await
                .unwrap_or_else(|_| Err(SimError::Simulator("a simulator call failed".into())));
            match result {
                Ok(kind) => {
                    if reply(&replies, id, kind).await.is_err() {
                        break;
                    }
                }
                Err(err) => {
                    tracing::info!(error = %err, "session ended with an error");
                    let _ = replies.send(Err(err.into())).await;
                    break;
                }
            }
        }
        let _ = stop.send(());
    });
    loop {
        let request = tokio::select! {
            message = inbound.message() => match message {
                Ok(Some(request)) => request,
                // End of stream or a broken connection: the client is gone, and a play in progress stops.
                Ok(None) | Err(_) => {
                    client_gone.store(true, Ordering::Relaxed);
                    break;
                }
            },
            _ = &mut stopped => break,
        };
        let (answer, answered) = tokio::sync::oneshot::channel();
        let closing = matches!(request.kind, Some(session_request::Kind::Close(_)));
        match request.kind {
            Some(session_request::Kind::Open(_)) => {
                let _ = answer.send(Err(SimError::FailedPrecondition("this session is already open".into())));
            }
            None => {
                let _ = answer.send(Err(SimError::InvalidArgument(
                    "a session request without a kind".into(),
                )));
            }
            Some(session_request::Kind::Close(_)) => {
                let _ = answer.send(Ok(session_response::Kind::Closed(Closed {})));
            }
            Some(kind) => {
                let switch = match &kind {
                    session_request::Kind::Reset(reset) => switch_driver(&inner, &sim_id, driven, reset),
                    session_request::Kind::Drive(_) if driven.is_none() => Err(SimError::FailedPrecondition(
                        "drive needs a session opened with a controller: without one, the client chooses the actions"
                            .into(),
                    )),
                    _ => Ok(None),
                };
                let (shared, batch, gone) = (shared.clone(), batch.clone(), client_gone.clone());
                inner.python.spawn(move || {
                    let mut jobs = shared.lock().expect("session state");
                    if jobs.failed {
                        return;
                    }
                    let result = switch.and_then(|switch| respond(kind, &mut jobs, &batch, shape, switch, &gone));
                    jobs.failed = result.is_err();
                    let _ = answer.send(result);
                });
            }
        }
        if pending.send((request.id, answered)).await.is_err() || closing {
            break;
        }
    }
    drop(pending);
    let _ = forwarder.await;
    Ok(())
}

/// The driver a `Reset` switches its environments to, checked as an `Open`'s is. Only a session opened with a
/// controller (`driven`) may switch: the client's own actions never silently give way to a driver. The maps are
/// built when the session opens, so a switch keeps them.
fn switch_driver(
    inner: &Inner,
    sim_id: &str,
    driven: Option<Controller>,
    reset: &Reset,
) -> Result<Option<Controller>, SimError> {
    let Some(controller) = reset.controller.as_ref() else {
        return Ok(None);
    };
    let Some(Controller::Idm { maps: opened, .. }) = driven else {
        return Err(SimError::FailedPrecondition(
            "a reset can switch the driver only in a session opened with a controller".into(),
        ));
    };
    let switch = inner.controller(sim_id, Some(controller))?;
    if let Some(Controller::Idm { maps, .. }) = switch
        && maps != opened
    {
        return Err(SimError::InvalidArgument(format!(
            "a switch cannot change the maps a session plays ({opened}) to {maps}: open another session"
        )));
    }
    Ok(switch)
}

type Answer = tokio::sync::oneshot::Receiver<Result<session_response::Kind, SimError>>;

/// A test-only fault (`dsrl-sim-worker --inject-fault short-step-answers=N`, hidden): the next N step answers of this
/// process leave out their last reward (a play's answer, its ended episodes), as a faulty worker might, so the tests
/// can check that the evaluators refuse such an answer instead of indexing past it.
static SHORT_STEP_ANSWERS: AtomicU32 = AtomicU32::new(0);

pub fn inject_short_step_answers(n: u32) {
    SHORT_STEP_ANSWERS.store(n, Ordering::SeqCst);
}

fn take_short_step_answer() -> bool {
    SHORT_STEP_ANSWERS
        .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
        .is_ok()
}

/// A session's rules and whether it has failed, owned by its jobs on the Python thread.
struct Jobs {
    state: SessionState,
    failed: bool,
    /// The seeds and observations the environments were opened with, kept until the first request: a policy
    /// (`Act`) can take over only from there.
    opened_with: Option<(Vec<u64>, Vec<u8>)>,
    /// The policy playing this session's environments, after an `Act`.
    acting: Option<Acting>,
}

#[derive(Clone, Copy)]
struct Shape {
    obs_dim: usize,
    act_dim: usize,
    auto_reset: bool,
    /// Opened with a built-in driver.
    controlled: bool,
}

/// Checks and answers one reset, step, drive, render, act or play (on the Python thread).
fn respond(
    kind: session_request::Kind,
    jobs: &mut Jobs,
    batch: &PyBatch,
    shape: Shape,
    switch: Option<Controller>,
    client_gone: &AtomicBool,
) -> Result<session_response::Kind, SimError> {
    let Shape {
        obs_dim,
        act_dim,
        auto_reset,
        controlled,
    } = shape;
    let opened_with = jobs.opened_with.take();
    let state = &mut jobs.state;
    if jobs.acting.is_some() && matches!(kind, session_request::Kind::Step(_) | session_request::Kind::Drive(_)) {
        return Err(SimError::FailedPrecondition(
            "this session's policy chooses the actions (Act): play its environments with Play".into(),
        ));
    }
    match kind {
        session_request::Kind::Act(act) => {
            if auto_reset || controlled {
                return Err(SimError::FailedPrecondition(
                    "a policy acts only in a session opened with AUTO_RESET_NONE and without a controller".into(),
                ));
            }
            let Some((seeds, observations)) = opened_with else {
                return Err(SimError::FailedPrecondition(
                    "Act must be the first request after Open (a session takes one policy, from its first episodes)"
                        .into(),
                ));
            };
            jobs.acting = Some(Acting::load(&act, state, &seeds, &observations)?);
            Ok(session_response::Kind::Act(pb::Acting {}))
        }
        session_request::Kind::Play(play) => {
            let acting = jobs
                .acting
                .as_mut()
                .ok_or_else(|| SimError::FailedPrecondition("play needs a policy: send Act right after Open".into()))?;
            let mut played = acting.play(&play, state, batch, client_gone)?;
            if take_short_step_answer() {
                played.ended.clear();
            }
            Ok(session_response::Kind::Play(played))
        }
        session_request::Kind::Reset(reset) => {
            let (envs, seeds) = state.check_reset(&reset)?;
            let observations = batch.reset(&envs, &seeds, switch)?;
            state.after_reset(&envs);
            if let Some(acting) = jobs.acting.as_mut() {
                acting.after_reset(&envs, &seeds, &observations)?;
            }
            let observations = tensor(DType::Float32, &[envs.len(), obs_dim], observations, 4, "observations")?;
            Ok(session_response::Kind::Reset(Observations {
                envs,
                observations: Some(observations),
            }))
        }
        session_request::Kind::Step(step) => {
            let (envs, actions) = state.check_step(&step)?;
            let out = batch.step(&envs, actions)?;
            state.after_step(&envs, &out.terminated, &out.truncated);
            let n = envs.len();
            let final_observations = if auto_reset {
                Some(tensor(
                    DType::Float32,
                    &[n, obs_dim],
                    out.final_observations,
                    4,
                    "final observations",
                )?)
            } else {
                None
            };
            Ok(session_response::Kind::Step(Transition {
                observations: Some(tensor(
                    DType::Float32,
                    &[n, obs_dim],
                    out.observations,
                    4,
                    "observations",
                )?),
                rewards: Some(if take_short_step_answer() && n > 0 {
                    tensor(
                        DType::Float64,
                        &[n - 1],
                        out.rewards[..(n - 1) * 8].to_vec(),
                        8,
                        "rewards",
                    )?
                } else {
                    tensor(DType::Float64, &[n], out.rewards, 8, "rewards")?
                }),
                costs: Some(tensor(DType::Float64, &[n], out.costs, 8, "costs")?),
                terminated: Some(tensor(DType::Bool, &[n], out.terminated, 1, "terminated")?),
                truncated: Some(tensor(DType::Bool, &[n], out.truncated, 1, "truncated")?),
                final_observations,
                applied_actions: Some(tensor(
                    DType::Float32,
                    &[n, act_dim],
                    out.applied_actions,
                    4,
                    "applied actions",
                )?),
                envs,
            }))
        }
        session_request::Kind::Drive(drive) => {
            let envs = state.check_drive(&drive)?;
            let driven = batch.drive(&envs)?;
            state.after_drive(&envs);
            let episodes = envs
                .iter()
                .zip(driven)
                .map(|(&env, out)| {
                    let steps = out.rewards.len() / 8;
                    Ok(DrivenEpisode {
                        env,
                        observations: Some(tensor(
                            DType::Float32,
                            &[steps, obs_dim],
                            out.observations,
                            4,
                            "observations",
                        )?),
                        applied_actions: Some(tensor(
                            DType::Float32,
                            &[steps, act_dim],
                            out.applied_actions,
                            4,
                            "applied actions",
                        )?),
                        rewards: Some(tensor(DType::Float64, &[steps], out.rewards, 8, "rewards")?),
                        costs: Some(tensor(DType::Float64, &[steps], out.costs, 8, "costs")?),
                        terminated: out.terminated,
                        truncated: out.truncated,
                    })
                })
                .collect::<Result<Vec<_>, SimError>>()?;
            if episodes.len() != envs.len() {
                return Err(SimError::Simulator(format!(
                    "the simulator drove {} episodes for {} environments",
                    episodes.len(),
                    envs.len()
                )));
            }
            Ok(session_response::Kind::Drive(Driven { episodes }))
        }
        session_request::Kind::Render(render) => {
            let envs = state.check_render(&render)?;
            let (width, height) = (render.width as usize, render.height as usize);
            let frames = batch.frames(&envs, render.width, render.height)?;
            let frames = tensor(DType::Uint8, &[envs.len(), height, width, 3], frames, 1, "frames")?;
            Ok(session_response::Kind::Render(Frames {
                envs,
                frames: Some(frames),
            }))
        }
        _ => Err(SimError::InvalidArgument(
            "not a reset, a step, a drive, a render, an act or a play".into(),
        )),
    }
}

type SessionStream = Pin<Box<dyn futures::Stream<Item = Result<SessionResponse, Status>> + Send>>;

#[tonic::async_trait]
impl Simulator for SimulatorService {
    async fn describe(&self, request: Request<DescribeRequest>) -> Result<Response<TaskSpec>, Status> {
        let inner = &self.inner;
        let sim_id = inner.simulator_id(&request.get_ref().task)?;
        if let Some(spec) = inner.specs.lock().expect("spec cache").get(&sim_id) {
            return Ok(Response::new(spec.clone()));
        }
        let reservation = inner.reserve(1)?;
        let host = inner.host.clone();
        let id = sim_id.clone();
        let shape = inner
            .python
            .run(move || {
                let (batch, shape) = host.open(&id, &[0], false, None)?;
                batch.close();
                drop(reservation);
                Ok::<_, SimError>(shape)
            })
            .await??;
        let spec = inner.spec(&sim_id, &shape);
        inner.specs.lock().expect("spec cache").insert(sim_id, spec.clone());
        Ok(Response::new(spec))
    }

    type SessionStream = SessionStream;

    async fn session(
        &self,
        request: Request<Streaming<SessionRequest>>,
    ) -> Result<Response<Self::SessionStream>, Status> {
        let mut inbound = request.into_inner();
        let (outbox, responses) = mpsc::channel(16);
        let inner = self.inner.clone();
        // Each Python call of the session is a job on the worker's Python thread (see python.rs).
        let session = async move {
            inner.sessions.fetch_add(1, Ordering::SeqCst);
            let result = run_session(inner.clone(), &mut inbound, &outbox).await;
            inner.sessions.fetch_sub(1, Ordering::SeqCst);
            if let Err(err) = result {
                tracing::info!(error = %err, "session ended with an error");
                let _ = outbox.send(Err(err.into())).await;
            }
        };
        tokio::spawn(session);
        Ok(Response::new(Box::pin(ReceiverStream::new(responses))))
    }

    async fn health(&self, _: Request<HealthRequest>) -> Result<Response<HealthResponse>, Status> {
        let inner = &self.inner;
        Ok(Response::new(HealthResponse {
            sessions: inner.sessions.load(Ordering::SeqCst),
            envs: inner.envs.load(Ordering::SeqCst),
            max_envs: inner.limits.max_envs,
            version: worker_version(inner.host.package_digest()),
        }))
    }
}

/// The version Health reports: the worker's, and the first 12 hex digits of the `dsrl_sim` package it imported
/// (which the scorer compares with its own, `dsrl_leaderboard::scorer_build`), e.g.
/// `dsrl-sim-worker 0.1.0 (dsrl_sim 0123456789ab)`.
pub fn worker_version(package_digest: &str) -> String {
    format!(
        "dsrl-sim-worker {} (dsrl_sim {})",
        env!("CARGO_PKG_VERSION"),
        &package_digest[..12.min(package_digest.len())]
    )
}
