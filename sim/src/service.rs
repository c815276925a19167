//! The `Simulator` gRPC service: task descriptions, sessions (one bidirectional stream each) and health.

use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

use dsrl_proto::simulator::v1 as pb;
use dsrl_proto::simulator::v1::{
    AutoReset, Closed, DType, DescribeRequest, HealthRequest, HealthResponse, Observations, Opened, SessionRequest,
    SessionResponse, TaskSpec, Tensor, Transition, session_request, session_response, simulator_server::Simulator,
};
use dsrl_suite::catalog::{Catalog, Family};
use pyo3::Python;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

use crate::error::SimError;
use crate::python::{BatchShape, Controller, PyBatch, PythonHost};
use crate::session::{Limits, SessionState, check_open};

#[derive(Clone)]
pub struct SimulatorService {
    inner: Arc<Inner>,
}

struct Inner {
    host: Arc<PythonHost>,
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

/// An open batch: closed (on a blocking thread, as Python work is) when the session ends for any reason, and only
/// then are its environments given back to the worker's capacity.
struct OpenBatch {
    batch: Option<Arc<PyBatch>>,
    reservation: Option<EnvReservation>,
}

impl Drop for OpenBatch {
    fn drop(&mut self) {
        let (Some(batch), reservation) = (self.batch.take(), self.reservation.take()) else {
            return;
        };
        let close = move || {
            batch.close();
            drop(reservation);
        };
        match tokio::runtime::Handle::try_current() {
            Ok(runtime) => drop(runtime.spawn_blocking(close)),
            Err(_) => close(),
        }
    }
}

impl SimulatorService {
    pub fn new(host: PythonHost, catalog: Catalog, limits: Limits) -> SimulatorService {
        SimulatorService {
            inner: Arc::new(Inner {
                host: Arc::new(host),
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
        Ok(Some(Controller::Idm {
            target_speed: idm.target_speed,
            acc_factor: idm.acc_factor,
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

async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T, SimError> + Send + 'static,
) -> Result<T, SimError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| SimError::Simulator(format!("simulator call panicked: {e}")))?
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
    let reservation = inner.reserve(open.num_envs)?;
    let auto_reset = open.auto_reset == AutoReset::SameStep as i32;
    let k = seeds.len();
    let host = inner.host.clone();
    // This runs on the session's own thread (see `session`), so Python is called directly.
    let (batch, shape, observations) = {
        let (batch, shape) = host.open(&sim_id, &seeds, auto_reset, controller)?;
        let all: Vec<u32> = (0..k as u32).collect();
        match batch.reset(&all, &seeds) {
            Ok(observations) => (batch, shape, observations),
            Err(err) => {
                batch.close();
                return Err(err);
            }
        }
    };
    let batch = Arc::new(batch);
    let _open = OpenBatch {
        batch: Some(batch.clone()),
        reservation: Some(reservation),
    };
    let spec = inner.spec(&sim_id, &shape);
    let (obs_dim, act_dim) = (shape.obs_dim as usize, shape.act_dim as usize);
    let mut state = SessionState::new(obs_dim, act_dim, k, auto_reset);
    let observations = tensor(DType::Float32, &[k, obs_dim], observations, 4, "observations")?;
    tracing::info!(task = %sim_id, envs = k, auto_reset, "session opened");
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
    loop {
        let request = match inbound.message().await {
            Ok(Some(request)) => request,
            // End of stream or a broken connection: the client is gone.
            Ok(None) | Err(_) => return Ok(()),
        };
        let kind = match request.kind {
            Some(session_request::Kind::Open(_)) => {
                return Err(SimError::FailedPrecondition("this session is already open".into()));
            }
            Some(session_request::Kind::Close(_)) => {
                let _ = reply(outbox, request.id, session_response::Kind::Closed(Closed {})).await;
                return Ok(());
            }
            Some(session_request::Kind::Reset(reset)) => {
                let (envs, seeds) = state.check_reset(&reset)?;
                let observations = batch.reset(&envs, &seeds)?;
                state.after_reset(&envs);
                let observations = tensor(DType::Float32, &[envs.len(), obs_dim], observations, 4, "observations")?;
                session_response::Kind::Reset(Observations {
                    envs,
                    observations: Some(observations),
                })
            }
            Some(session_request::Kind::Step(step)) => {
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
                session_response::Kind::Step(Transition {
                    observations: Some(tensor(
                        DType::Float32,
                        &[n, obs_dim],
                        out.observations,
                        4,
                        "observations",
                    )?),
                    rewards: Some(tensor(DType::Float64, &[n], out.rewards, 8, "rewards")?),
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
                })
            }
            None => return Err(SimError::InvalidArgument("a session request without a kind".into())),
        };
        if reply(outbox, request.id, kind).await.is_err() {
            return Ok(());
        }
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
        let shape = blocking(move || {
            let (batch, shape) = host.open(&id, &[0], false, None)?;
            batch.close();
            drop(reservation);
            Ok(shape)
        })
        .await?;
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
        // A session lives on its own blocking thread and calls Python directly: a step then costs one thread
        // wake-up each way (connection task -> session thread -> connection task) instead of also hopping through
        // an executor task and the blocking pool, which measurably slowed small batches (BENCHMARKS.md).
        let runtime = tokio::runtime::Handle::current();
        let session = async move {
            inner.sessions.fetch_add(1, Ordering::SeqCst);
            let result = run_session(inner.clone(), &mut inbound, &outbox).await;
            inner.sessions.fetch_sub(1, Ordering::SeqCst);
            if let Err(err) = result {
                tracing::info!(error = %err, "session ended with an error");
                let _ = outbox.send(Err(err.into())).await;
            }
        };
        // The thread keeps one Python thread state for the whole session (attached once, then detached while it
        // waits): re-attaching it for each call is cheap, where a fresh state per call cost ~25 us.
        tokio::task::spawn_blocking(move || Python::attach(|py| py.detach(|| runtime.block_on(session))));
        Ok(Response::new(Box::pin(ReceiverStream::new(responses))))
    }

    async fn health(&self, _: Request<HealthRequest>) -> Result<Response<HealthResponse>, Status> {
        let inner = &self.inner;
        Ok(Response::new(HealthResponse {
            sessions: inner.sessions.load(Ordering::SeqCst),
            envs: inner.envs.load(Ordering::SeqCst),
            max_envs: inner.limits.max_envs,
            version: concat!("dsrl-sim-worker ", env!("CARGO_PKG_VERSION")).to_owned(),
        }))
    }
}
