//! A policy acting inside the worker (`Act`, then `Play` in the simulator proto). Scoring a submission through the
//! server costs a round trip per step: the worker's answer wakes the server, the server asks the policy process
//! for the next actions and sends them back, and on a machine whose cores the workers share with the server, each
//! of those wake-ups takes time from the simulators (BENCHMARKS.md, scoring). Here the worker's Python thread asks
//! the policy itself between two steps, and the server hears from the session once an episode ends.
//!
//! The episodes are those stepping would have played: the same policy code acts on the same batch of environments
//! (those named, in their order) with the same observations, and hears the same rewards and costs; the returns are
//! summed in the order the server's evaluator sums them.
//!
//! A checkpoint is checked here as the server checks it before queueing it (format, dimensions, what one action may
//! cost), so its memory and its work per step are bounded by the format's limits; each forward pass is also held
//! to the CPU time the `Act` allows, measured on this thread's own clock. No participant code runs: a checkpoint is
//! weights and a declared architecture.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use dsrl_policy::acting::{Policy, Rollout};
use dsrl_policy::checkpoint;
use dsrl_proto::simulator::v1::{Act, Play, Played, PlayedEpisode};

use crate::error::SimError;
use crate::python::PyBatch;
use crate::session::SessionState;

/// One environment's episode as far as it has been played here.
#[derive(Debug, Clone, Copy, Default)]
struct Sums {
    reward_return: f64,
    cost_return: f64,
    length: u32,
}

/// A session's policy and what it knows of each environment.
pub struct Acting {
    rollout: Rollout<'static>,
    /// The last observation of every environment, row after row.
    observations: Vec<f32>,
    sums: Vec<Sums>,
    act_cpu: Duration,
}

fn refused(what: &str, e: impl std::fmt::Display) -> SimError {
    SimError::InvalidArgument(format!("{what}: {e}"))
}

impl Acting {
    /// Loads `act`'s checkpoint for a session whose environments were just reset with `seeds` to `observations`.
    pub fn load(act: &Act, state: &SessionState, seeds: &[u64], observations: &[u8]) -> Result<Acting, SimError> {
        let config = checkpoint::parse_config(&act.config).map_err(|e| refused("the policy's config", e))?;
        if (config.obs_dim, config.act_dim) != (state.obs_dim, state.act_dim) {
            return Err(SimError::InvalidArgument(format!(
                "the policy declares observation dim {} and action dim {}; this session's task has {} and {}",
                config.obs_dim, config.act_dim, state.obs_dim, state.act_dim
            )));
        }
        config.check_step_cost().map_err(|e| refused("the policy", e))?;
        if !(act.act_cpu_seconds.is_finite() && act.act_cpu_seconds > 0.0) {
            return Err(SimError::InvalidArgument(format!(
                "act_cpu_seconds must be a positive number of seconds, not {}",
                act.act_cpu_seconds
            )));
        }
        let tensors = checkpoint::parse_weights(&act.weights).map_err(|e| refused("the policy's weights", e))?;
        let policy = Policy::load(&config, &tensors).map_err(|e| refused("the policy", e))?;
        let k = state.num_envs();
        let mut rollout = Arc::new(policy)
            .shared_rollout(act.cost_threshold, k)
            .map_err(|e| refused("the policy", e))?;
        for (env, &seed) in seeds.iter().enumerate() {
            rollout.start_episode(env, seed).map_err(|e| refused("the policy", e))?;
        }
        Ok(Acting {
            rollout,
            observations: f32s(observations),
            sums: vec![Sums::default(); k],
            act_cpu: Duration::from_secs_f64(act.act_cpu_seconds),
        })
    }

    /// `envs` were reset with `seeds` to `observations`: each starts an episode.
    pub fn after_reset(&mut self, envs: &[u32], seeds: &[u64], observations: &[u8]) -> Result<(), SimError> {
        let d = self.obs_dim();
        let observations = f32s(observations);
        for (row, (&env, &seed)) in envs.iter().zip(seeds).enumerate() {
            let i = env as usize;
            self.observations[i * d..(i + 1) * d].copy_from_slice(&observations[row * d..(row + 1) * d]);
            self.sums[i] = Sums::default();
            self.rollout
                .start_episode(i, seed)
                .map_err(|e| refused("the policy", e))?;
        }
        Ok(())
    }

    fn obs_dim(&self) -> usize {
        self.observations.len() / self.sums.len().max(1)
    }

    /// Plays `play`'s environments until a step ends one of their episodes (see `Play` in the proto).
    /// Stops with an error, between two steps, once `client_gone` is set (the session's client left: a cancelled
    /// scoring frees the worker within a step).
    pub fn play(
        &mut self,
        play: &Play,
        state: &mut SessionState,
        batch: &PyBatch,
        client_gone: &AtomicBool,
    ) -> Result<Played, SimError> {
        let mut envs = state.check_play(play)?;
        // The rollout's slots are in increasing order; the request's order is the batch's, so it must be too.
        if envs.windows(2).any(|w| w[0] >= w[1]) {
            return Err(SimError::InvalidArgument(format!(
                "play names environments {envs:?}: name them in increasing order"
            )));
        }
        let d = self.obs_dim();
        let mut steps = 0u32;
        loop {
            if client_gone.load(Ordering::Relaxed) {
                return Err(SimError::FailedPrecondition(
                    "the session's client left during a play".into(),
                ));
            }
            let observations: Vec<f32> = envs
                .iter()
                .flat_map(|&i| self.observations[i as usize * d..(i as usize + 1) * d].iter().copied())
                .collect();
            let started = thread_cpu_time();
            let actions = self
                .rollout
                .act(&envs, &observations)
                .map_err(|e| refused("evaluating the policy", e))?;
            let used = thread_cpu_time().saturating_sub(started);
            if used > self.act_cpu {
                // Debug-formatted durations pick their unit (s, ms, µs), so a limit far under a millisecond reads
                // as what it is rather than as "0.000 s".
                return Err(SimError::InvalidArgument(format!(
                    "the policy took {used:?} of CPU time for one forward pass of {} environments; the limit is {:?}",
                    envs.len(),
                    self.act_cpu
                )));
            }
            let actions: Vec<u8> = actions.iter().flat_map(|a| a.to_le_bytes()).collect();
            let out = batch.step(&envs, &actions)?;
            state.after_step(&envs, &out.terminated, &out.truncated);
            steps += 1;
            let (rewards, costs) = (f64s(&out.rewards), f64s(&out.costs));
            let next = f32s(&out.observations);
            if rewards.len() != envs.len() || costs.len() != envs.len() || next.len() != envs.len() * d {
                return Err(SimError::Simulator(format!(
                    "a step of {} environments returned {} rewards, {} costs and {} observation values",
                    envs.len(),
                    rewards.len(),
                    costs.len(),
                    next.len()
                )));
            }
            self.rollout
                .observe(&envs, &rewards, &costs)
                .map_err(|e| refused("the policy", e))?;
            let mut ended = Vec::new();
            let mut still = Vec::with_capacity(envs.len());
            for (row, &env) in envs.iter().enumerate() {
                let i = env as usize;
                self.observations[i * d..(i + 1) * d].copy_from_slice(&next[row * d..(row + 1) * d]);
                let sums = &mut self.sums[i];
                // As the server's evaluator sums them: in f64, of the f32 values the datasets store.
                sums.reward_return += f64::from(rewards[row] as f32);
                sums.cost_return += f64::from(costs[row] as f32);
                sums.length += 1;
                if out.terminated.get(row) == Some(&1) || out.truncated.get(row) == Some(&1) {
                    ended.push(PlayedEpisode {
                        env,
                        reward_return: sums.reward_return,
                        cost_return: sums.cost_return,
                        length: sums.length,
                    });
                } else {
                    still.push(env);
                }
            }
            if !ended.is_empty() {
                return Ok(Played { steps, ended });
            }
            envs = still;
        }
    }
}

fn f32s(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
        .collect()
}

fn f64s(bytes: &[u8]) -> Vec<f64> {
    bytes
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
        .collect()
}

/// The CPU time this thread has used (the kernel's per-thread clock): what a forward pass costs, whatever else the
/// machine runs.
fn thread_cpu_time() -> Duration {
    let mut now = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime only writes the timespec it is given, which lives on this stack.
    let ok = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut now) } == 0;
    if ok {
        Duration::new(now.tv_sec as u64, now.tv_nsec as u32)
    } else {
        Duration::ZERO
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_thread_clock_counts_this_threads_work_only() {
        let before = thread_cpu_time();
        let mut x = 0u64;
        for i in 0..20_000_000u64 {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(i);
        }
        std::hint::black_box(x);
        let busy = thread_cpu_time() - before;
        assert!(busy > Duration::ZERO, "work took no CPU time");
        let before = thread_cpu_time();
        std::thread::sleep(Duration::from_millis(50));
        assert!(
            thread_cpu_time() - before < Duration::from_millis(25),
            "sleeping counted as CPU time"
        );
    }
}
