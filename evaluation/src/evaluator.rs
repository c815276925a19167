//! Scoring a policy on the real simulators: episodes from given seeds, played with the policy's deterministic
//! actions through the worker pool, batched `envs_per_session` to a session and the sessions run concurrently.
//! Every episode's reward and cost returns are kept; the normalized scores follow from the catalog (spec 4.1).
//!
//! This is the core the leaderboard's evaluator builds on (submissions, the durable queue and held seeds come
//! with it); `dsrl-admin evaluate` uses it to score the pipeline's experts.

use dsrl_policy::checkpoint::{Architecture, Conditioning, PolicyConfig};
use dsrl_proto::simulator::v1::{AutoReset, Open};
use dsrl_suite::catalog::Task;
use serde::{Deserialize, Serialize};

use crate::error::EvaluationError;
use crate::inference::{Player, PolicySource};
use crate::simulators::{PooledSession, Reply, SimulatorPool, split_in_two};

/// One evaluated episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeScore {
    pub seed: u64,
    pub reward_return: f64,
    pub cost_return: f64,
    pub length: u32,
}

/// Checks a policy's declared task and dimensions against the catalog's task; the message says what differs.
pub fn check_policy(task: &Task, config: &PolicyConfig) -> Result<(), EvaluationError> {
    if config.task != task.id.as_str() {
        return Err(EvaluationError::InvalidArgument(format!(
            "the policy was declared for {}, not {}",
            config.task, task.id
        )));
    }
    if (config.obs_dim, config.act_dim) != (task.obs_dim as usize, task.act_dim as usize) {
        return Err(EvaluationError::InvalidArgument(format!(
            "{} has observation dim {} and action dim {}; the policy declares {} and {}",
            task.id, task.obs_dim, task.act_dim, config.obs_dim, config.act_dim
        )));
    }
    if let Architecture::Cdt { episode_len, .. } = config.architecture
        && episode_len < task.max_episode_steps as usize
    {
        return Err(EvaluationError::InvalidArgument(format!(
            "{}'s episodes last up to {} steps; the cdt's timestep embedding covers episode_len = {episode_len}",
            task.id, task.max_episode_steps
        )));
    }
    // What one action may cost, from the declared sizes (a long CDT context once passed every other check and ate
    // the server's memory while it was scored).
    let input_dim = config.obs_dim + usize::from(matches!(config.conditioning, Conditioning::TargetCost));
    config
        .architecture
        .check_step_cost(input_dim, config.act_dim)
        .map_err(|e| EvaluationError::InvalidArgument(e.to_string()))?;
    if let Conditioning::ReturnsToGo { targets } = &config.conditioning {
        let covered: Vec<f64> = targets.iter().map(|t| t.cost_threshold).collect();
        if let Some(missing) = uncovered_thresholds(task, &covered) {
            return Err(EvaluationError::InvalidArgument(format!(
                "returns_to_go declares no target for cost threshold {missing} of {}",
                task.id
            )));
        }
    }
    Ok(())
}

/// The task's thresholds that `covered` lacks, listed (`"20, 40"`); `None` when it has them all.
pub fn uncovered_thresholds(task: &Task, covered: &[f64]) -> Option<String> {
    let missing: Vec<String> = task
        .cost_thresholds
        .iter()
        .filter(|k| !covered.contains(k))
        .map(|k| k.to_string())
        .collect();
    (!missing.is_empty()).then(|| missing.join(", "))
}

/// Plays one episode per seed with `policy`'s deterministic actions at `cost_threshold` (which a conditioned policy
/// reads; others ignore it); results come back in seed order.
///
/// The seeds are split into `sessions` contiguous runs, played concurrently, each in one session of at most
/// `envs_per_session` environments; an environment that finishes an episode is reset with its session's next
/// seed. Creating an environment costs more than many steps (~80 ms for a Bullet task), so fewer environments
/// playing several episodes each are faster. The layout is part of the result: Bullet keeps motor targets across
/// a reset, so an episode depends on the one its environment played before; the same seeds, `envs_per_session`
/// and `sessions` always give the same episodes.
pub async fn play_episodes(
    pool: &SimulatorPool,
    task: &Task,
    policy: PolicySource<'_>,
    cost_threshold: f64,
    seeds: &[u64],
    envs_per_session: usize,
    sessions: usize,
) -> Result<Vec<EpisodeScore>, EvaluationError> {
    let progress = std::sync::atomic::AtomicU32::new(0);
    play_episodes_counted(
        pool,
        task,
        policy,
        cost_threshold,
        seeds,
        envs_per_session,
        sessions,
        &progress,
    )
    .await
}

/// [`play_episodes`], adding one to `progress` as each episode ends (what the leaderboard shows while it scores).
#[allow(clippy::too_many_arguments)]
pub async fn play_episodes_counted(
    pool: &SimulatorPool,
    task: &Task,
    policy: PolicySource<'_>,
    cost_threshold: f64,
    seeds: &[u64],
    envs_per_session: usize,
    sessions: usize,
    progress: &std::sync::atomic::AtomicU32,
) -> Result<Vec<EpisodeScore>, EvaluationError> {
    let run = seeds.len().div_ceil(sessions.max(1)).max(1);
    let groups = seeds.chunks(run).map(|group| {
        play_group(
            pool,
            task,
            policy,
            cost_threshold,
            group,
            envs_per_session.max(1),
            progress,
        )
    });
    let results = futures::future::try_join_all(groups).await?;
    Ok(results.into_iter().flatten().collect())
}

/// Up to `envs` environments playing `seeds` in order: environment `i` starts with seed `i`, and each finished
/// environment takes the next unplayed seed. The policy's rollout is told of every episode start (its seed seeds
/// the policy's own draws) and of every step's reward and cost.
///
/// The environments form two groups (the first half and the second) whose steps are pipelined: while one group
/// steps, this side scores the other's last step and computes its next actions, so the simulators do not wait for
/// the round trip or the policy (BENCHMARKS.md, fixed-policy acting). Each group is a session of its own, so the
/// pool can place the two halves on different workers: a leaderboard job's three thresholds make six half-sessions,
/// which two workers share evenly, where three whole sessions left one worker with two of them. Each environment
/// is its simulator's own (MetaDrive's in a process of its own), so where a group runs does not change its
/// episodes. The answers are handled in the order the requests were sent (each group has one request in flight
/// at a time), which makes the episodes a function of the seeds and `envs` alone.
async fn play_group(
    pool: &SimulatorPool,
    task: &Task,
    policy: PolicySource<'_>,
    cost_threshold: f64,
    seeds: &[u64],
    envs: usize,
    progress: &std::sync::atomic::AtomicU32,
) -> Result<Vec<EpisodeScore>, EvaluationError> {
    let k = seeds.len().min(envs);
    let mut rollout = Player::new(policy, cost_threshold, k).await?;
    for (env, &seed) in seeds[..k].iter().enumerate() {
        rollout.start_episode(env, seed).await?;
    }
    // Each group's environments (global numbers 0..k) and, in its session, environment `i` is `i - first[g]`.
    let groups = split_in_two(k);
    let first: Vec<u32> = groups.iter().map(|g| g[0]).collect();
    let opens = groups.iter().map(|g| {
        pool.open(Open {
            task: task.id.to_string(),
            num_envs: g.len() as u32,
            seeds: g.iter().map(|&i| seeds[i as usize]).collect(),
            auto_reset: AutoReset::None as i32,
            controller: None,
        })
    });
    let mut sessions = futures::future::try_join_all(opens).await?;
    let obs_dim = sessions[0].spec().obs_dim as usize;
    let mut obs: Vec<f32> = sessions
        .iter()
        .flat_map(|s| s.initial_observations().iter().copied())
        .collect();
    let mut scores: Vec<EpisodeScore> = seeds
        .iter()
        .map(|&seed| EpisodeScore {
            seed,
            reward_return: 0.0,
            cost_return: 0.0,
            length: 0,
        })
        .collect();
    // The episode (index into `seeds`) each environment is playing; the next seed to hand out.
    let mut playing: Vec<usize> = (0..k).collect();
    let mut next = k;
    // Each group's environments still playing, and those it is resetting.
    let mut active: Vec<Vec<u32>> = groups;
    let mut resetting: Vec<Vec<u32>> = vec![Vec::new(); active.len()];
    let local = |g: usize, slots: &[u32]| -> Vec<u32> { slots.iter().map(|&i| i - first[g]).collect() };
    // The requests in flight, oldest first: (group, is a reset).
    let mut in_flight = std::collections::VecDeque::new();
    for (g, slots) in active.iter().enumerate() {
        send_actions(&mut sessions[g], &mut rollout, slots, &local(g, slots), &obs, obs_dim).await?;
        in_flight.push_back((g, false));
    }
    while let Some((g, is_reset)) = in_flight.pop_front() {
        match (sessions[g].receive().await?, is_reset) {
            (Reply::Step(step), false) => {
                let mut still = Vec::with_capacity(active[g].len());
                let mut reset_seeds = Vec::new();
                rollout.observe(&active[g], &step.rewards, &step.costs).await?;
                for (row, &i) in active[g].iter().enumerate() {
                    let score = &mut scores[playing[i as usize]];
                    // Sums in f64 of the f32 values the datasets store, as the normalization constants were computed.
                    score.reward_return += f64::from(step.rewards[row] as f32);
                    score.cost_return += f64::from(step.costs[row] as f32);
                    score.length += 1;
                    obs[i as usize * obs_dim..(i as usize + 1) * obs_dim]
                        .copy_from_slice(&step.observations[row * obs_dim..(row + 1) * obs_dim]);
                    let ended = step.terminated[row] || step.truncated[row];
                    if ended {
                        progress.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    }
                    if !ended {
                        still.push(i);
                    } else if next < seeds.len() {
                        playing[i as usize] = next;
                        resetting[g].push(i);
                        reset_seeds.push(seeds[next]);
                        rollout.start_episode(i as usize, seeds[next]).await?;
                        next += 1;
                    }
                }
                active[g] = still;
                if !resetting[g].is_empty() {
                    // The group's next step waits for these observations; the other group keeps the workers busy.
                    sessions[g].send_reset(&local(g, &resetting[g]), &reset_seeds).await?;
                    in_flight.push_back((g, true));
                } else if !active[g].is_empty() {
                    let slots = local(g, &active[g]);
                    send_actions(&mut sessions[g], &mut rollout, &active[g], &slots, &obs, obs_dim).await?;
                    in_flight.push_back((g, false));
                }
            }
            (Reply::Reset { observations, .. }, true) => {
                let reset = std::mem::take(&mut resetting[g]);
                for (row, &i) in reset.iter().enumerate() {
                    obs[i as usize * obs_dim..(i as usize + 1) * obs_dim]
                        .copy_from_slice(&observations[row * obs_dim..(row + 1) * obs_dim]);
                }
                active[g].extend(reset);
                active[g].sort_unstable();
                let slots = local(g, &active[g]);
                send_actions(&mut sessions[g], &mut rollout, &active[g], &slots, &obs, obs_dim).await?;
                in_flight.push_back((g, false));
            }
            _ => {
                return Err(EvaluationError::Internal(format!(
                    "simulator worker {} answered out of order",
                    sessions[g].worker()
                )));
            }
        }
    }
    for session in sessions {
        session.close().await?;
    }
    Ok(scores)
}

/// The policy's actions for environments `slots` (from their rows of `obs`), sent as their group's next step to
/// its session, where they are `local`.
async fn send_actions(
    session: &mut PooledSession,
    rollout: &mut Player<'_>,
    slots: &[u32],
    local: &[u32],
    obs: &[f32],
    obs_dim: usize,
) -> Result<(), EvaluationError> {
    let batch: Vec<f32> = slots
        .iter()
        .flat_map(|&i| obs[i as usize * obs_dim..(i as usize + 1) * obs_dim].iter().copied())
        .collect();
    let actions = rollout.act(slots, &batch).await?;
    session.send_step(local, &actions).await
}
