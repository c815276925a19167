use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use crate::session::{DrivenRest, Reply, SimulatorSession, StepResult};
use dsrl_proto::simulator::v1::{Controller, TaskSpec};
use tonic::{Code, Status};

use crate::error::SimulatorError;

/// A session's place among its worker's open sessions. A worker answers the calls of all its sessions one after
/// another on its one Python thread, so a call waits behind the other sessions' calls: its deadline is the
/// configured one for each session open there, and a busy machine slows evaluations instead of interrupting them
/// (a worker that stops answering altogether is found by the pool's health checks and replaced).
pub(super) struct WorkerLoad(Arc<AtomicUsize>);

impl WorkerLoad {
    pub(super) fn join(open_sessions: &Arc<AtomicUsize>) -> WorkerLoad {
        open_sessions.fetch_add(1, Ordering::AcqRel);
        WorkerLoad(open_sessions.clone())
    }

    /// The deadline of one call: `per_session` for each session open on the worker (at least one).
    pub(super) fn deadline(&self, per_session: Duration) -> Duration {
        per_session * self.0.load(Ordering::Acquire).max(1) as u32
    }
}

impl Drop for WorkerLoad {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A session on one pool worker. Every call has a deadline, and errors name the worker, so a worker that dies or
/// hangs fails its sessions clearly instead of stalling an evaluation.
pub struct PooledSession {
    session: SimulatorSession,
    initial_observations: Vec<f32>,
    worker: String,
    per_session: Duration,
    load: WorkerLoad,
}

impl PooledSession {
    pub(super) fn new(
        session: SimulatorSession,
        observations: Vec<f32>,
        worker: String,
        per_session: Duration,
        load: WorkerLoad,
    ) -> Self {
        PooledSession {
            session,
            initial_observations: observations,
            worker,
            per_session,
            load,
        }
    }

    /// This call's deadline, from the sessions open on the worker now.
    fn timeout(&self) -> Duration {
        self.load.deadline(self.per_session)
    }

    /// A worker's status as this server's error: the worker's own verdicts keep their meaning; a broken stream
    /// means the worker died.
    pub(super) fn error(worker: &str, status: Status) -> SimulatorError {
        let message = format!("simulator worker {worker}: {}", status.message());
        match status.code() {
            Code::NotFound => SimulatorError::NotFound(message),
            Code::InvalidArgument | Code::FailedPrecondition | Code::OutOfRange => {
                SimulatorError::InvalidArgument(message)
            }
            Code::ResourceExhausted | Code::Unavailable => SimulatorError::Unavailable(message),
            Code::Internal => SimulatorError::Internal(message),
            _ => SimulatorError::Unavailable(format!(
                "simulator worker {worker} failed during the session: {}",
                status.message()
            )),
        }
    }

    pub fn worker(&self) -> &str {
        &self.worker
    }

    pub fn spec(&self) -> &TaskSpec {
        self.session.spec()
    }

    /// The observations of the K environments as the session opened (`[K * obs_dim]`).
    pub fn initial_observations(&self) -> &[f32] {
        &self.initial_observations
    }

    pub async fn step(&mut self, envs: &[u32], actions: &[f32]) -> Result<StepResult, SimulatorError> {
        let timeout = self.timeout();
        let worker = self.worker.clone();
        let call = self.session.step(envs, actions);
        deadline(&worker, timeout, "step", call).await
    }

    pub async fn reset(&mut self, envs: &[u32], seeds: &[u64]) -> Result<Vec<f32>, SimulatorError> {
        self.reset_with(envs, seeds, None).await
    }

    /// A reset that also switches the environments' built-in driver (sessions opened with a controller only).
    pub async fn reset_with(
        &mut self,
        envs: &[u32],
        seeds: &[u64],
        controller: Option<Controller>,
    ) -> Result<Vec<f32>, SimulatorError> {
        let timeout = self.timeout();
        let worker = self.worker.clone();
        let call = self.session.reset_with(envs, seeds, controller);
        deadline(&worker, timeout, "reset", call).await
    }

    /// The controller plays the rest of each named environment's episode inside the worker (a session opened with a
    /// controller only): one answer per episode instead of one per step. The deadline holds for the whole drive.
    pub async fn drive(&mut self, envs: &[u32]) -> Result<Vec<DrivenRest>, SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        deadline(&worker, timeout, "drive", self.session.drive(envs)).await
    }

    /// Queues a step without waiting for its result, so the worker can step it while the caller acts on another
    /// group of the session's environments; [`Self::receive`] returns the answers in the order they were sent.
    pub async fn send_step(&mut self, envs: &[u32], actions: &[f32]) -> Result<(), SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        deadline(&worker, timeout, "step", self.session.send_step(envs, actions)).await?;
        Ok(())
    }

    /// Queues a reset without waiting for its observations (see [`Self::send_step`]).
    pub async fn send_reset(&mut self, envs: &[u32], seeds: &[u64]) -> Result<(), SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        deadline(&worker, timeout, "reset", self.session.send_reset(envs, seeds)).await?;
        Ok(())
    }

    /// Queues a render of the named environments (see `Render` in the simulator proto) without waiting for it.
    pub async fn send_render(&mut self, envs: &[u32], width: u32, height: u32) -> Result<(), SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        let call = self.session.send_render(envs, width, height);
        deadline(&worker, timeout, "render", call).await?;
        Ok(())
    }

    /// Queues an `Act` (see `SimulatorSession::send_act`): the session's policy plays its environments from here on.
    pub async fn send_act(
        &mut self,
        config: &[u8],
        weights: &[u8],
        cost_threshold: f64,
        act_cpu_seconds: f64,
    ) -> Result<(), SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        let call = self.session.send_act(config, weights, cost_threshold, act_cpu_seconds);
        deadline(&worker, timeout, "act", call).await?;
        Ok(())
    }

    /// Queues a `Play` of the named environments: the session's policy steps them inside the worker until one of
    /// their episodes ends. Its answer's deadline, like a drive's, holds for all the steps.
    pub async fn send_play(&mut self, envs: &[u32]) -> Result<(), SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        deadline(&worker, timeout, "play", self.session.send_play(envs)).await?;
        Ok(())
    }

    /// The answer to the oldest request sent with [`Self::send_step`], [`Self::send_reset`] or
    /// [`Self::send_render`].
    pub async fn receive(&mut self) -> Result<Reply, SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        deadline(&worker, timeout, "queued request", self.session.receive()).await
    }

    pub async fn close(self) -> Result<(), SimulatorError> {
        let (timeout, worker) = (self.timeout(), self.worker.clone());
        deadline(&worker, timeout, "close", self.session.close()).await
    }
}

async fn deadline<T>(
    worker: &str,
    timeout: Duration,
    what: &str,
    call: impl Future<Output = Result<T, Status>>,
) -> Result<T, SimulatorError> {
    match tokio::time::timeout(timeout, call).await {
        Ok(result) => result.map_err(|status| PooledSession::error(worker, status)),
        Err(_) => Err(SimulatorError::Unavailable(format!(
            "simulator worker {worker} did not answer a {what} within {timeout:?}"
        ))),
    }
}

/// Environments `0..k` as two pipelined groups, the first half and the rest (one group when `k` is 1).
pub fn split_in_two(k: usize) -> Vec<Vec<u32>> {
    let half = k.div_ceil(2) as u32;
    [(0..half).collect::<Vec<u32>>(), (half..k as u32).collect()]
        .into_iter()
        .filter(|g| !g.is_empty())
        .collect()
}

#[cfg(test)]
mod tests {
    #[test]
    fn environments_split_into_two_pipelined_groups() {
        assert_eq!(super::split_in_two(1), vec![vec![0]]);
        assert_eq!(super::split_in_two(2), vec![vec![0], vec![1]]);
        assert_eq!(super::split_in_two(5), vec![vec![0, 1, 2], vec![3, 4]]);
        assert!(super::split_in_two(0).is_empty());
    }
}
