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

use crate::EvaluationError;
use crate::in_workers::play_group_in_workers;
use crate::inference::{Player, PolicySource};
use dsrl_simulators::{PooledSession, Reply, SimulatorPool, StepResult, split_in_two};

/// One evaluated episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeScore {
    pub seed: u64,
    pub reward_return: f64,
    pub cost_return: f64,
    pub length: u32,
}

impl EpisodeScore {
    /// Each of `seeds` as an episode not played yet: no steps, no returns.
    pub(crate) fn unplayed(seeds: &[u64]) -> Vec<EpisodeScore> {
        seeds
            .iter()
            .map(|&seed| EpisodeScore {
                seed,
                reward_return: 0.0,
                cost_return: 0.0,
                length: 0,
            })
            .collect()
    }
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
    config
        .check_step_cost()
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
    let groups = seeds
        .chunks(session_run(seeds.len(), sessions))
        .map(|group| async move {
            match policy {
                // A submitted checkpoint acts inside the workers: the same episodes, without a round trip per step.
                PolicySource::Isolated(isolated) if isolated.act_in_workers => {
                    play_group_in_workers(
                        pool,
                        task,
                        isolated,
                        cost_threshold,
                        group,
                        envs_per_session.max(1),
                        progress,
                    )
                    .await
                }
                PolicySource::Isolated(_) | PolicySource::Local(_) => {
                    play_group(
                        pool,
                        task,
                        policy,
                        cost_threshold,
                        group,
                        envs_per_session.max(1),
                        progress,
                        None,
                    )
                    .await
                }
            }
        });
    let results = futures::future::try_join_all(groups).await?;
    Ok(results.into_iter().flatten().collect())
}

/// How many consecutive seeds each of `sessions` concurrent groups plays (the last may play fewer).
fn session_run(seeds: usize, sessions: usize) -> usize {
    seeds.div_ceil(sessions.max(1)).max(1)
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
///
/// With a `watcher`, the group is played only until the watched episode has ended, and that episode is recorded
/// step by step and drawn (see [`replay_episode`]); the requests for its frames go in the same ordered stream, so
/// the episodes played are the ones scoring played.
#[allow(clippy::too_many_arguments)]
async fn play_group(
    pool: &SimulatorPool,
    task: &Task,
    policy: PolicySource<'_>,
    cost_threshold: f64,
    seeds: &[u64],
    envs: usize,
    progress: &std::sync::atomic::AtomicU32,
    mut watcher: Option<&mut Watcher>,
) -> Result<Vec<EpisodeScore>, EvaluationError> {
    let k = seeds.len().min(envs);
    let mut rollout = Player::new(policy, cost_threshold, k).await?;
    for (env, &seed) in seeds[..k].iter().enumerate() {
        rollout.start_episode(env, seed).await?;
    }
    // Each group's environments (global numbers 0..k) and, in its session, environment `i` is `i - first[g]`.
    let (groups, mut sessions) = open_groups(pool, task, seeds, k).await?;
    let first: Vec<u32> = groups.iter().map(|g| g[0]).collect();
    let first_observations = sessions
        .iter()
        .flat_map(|s| s.initial_observations().iter().copied())
        .collect();
    let mut episodes = Episodes::new(seeds, k, sessions[0].spec().obs_dim as usize, first_observations);
    // Each group's environments still playing, and those it is resetting.
    let mut active: Vec<Vec<u32>> = groups;
    let mut resetting: Vec<Vec<u32>> = vec![Vec::new(); active.len()];
    let local = |g: usize, slots: &[u32]| -> Vec<u32> { slots.iter().map(|&i| i - first[g]).collect() };
    // The requests in flight, oldest first: (group, what was asked).
    let mut in_flight = std::collections::VecDeque::new();
    for (g, slots) in active.iter().enumerate() {
        if let Some(i) = episodes.watched_among(slots, watcher.as_deref()) {
            let w = watcher.as_deref().expect("an environment is watched");
            ask_frame(&mut sessions[g], local(g, &[i])[0], &w.options).await?;
            in_flight.push_back((g, Asked::Render));
        }
        send_actions(&mut sessions[g], &mut rollout, &episodes, slots, &local(g, slots)).await?;
        in_flight.push_back((g, Asked::Step));
    }
    while let Some((g, asked)) = in_flight.pop_front() {
        match (sessions[g].receive().await?, asked) {
            (Reply::Render(frames), Asked::Render) => {
                let w = watcher.as_deref_mut().ok_or_else(|| {
                    EvaluationError::Internal("a frame arrived for a replay that watches nothing".into())
                })?;
                w.frames.push(frames.frames);
                if w.ended {
                    // The watched episode is over and drawn: the rest of the group does not matter to it.
                    return Ok(episodes.scores);
                }
            }
            (Reply::Step(step), Asked::Step) => {
                rollout.observe(&active[g], &step.rewards, &step.costs).await?;
                let stepped = episodes.record_step(&active[g], &step, progress, watcher.as_deref_mut());
                // The rollout hears of the new episodes in the order the environments stand in the group.
                for &(i, seed) in &stepped.restarted {
                    rollout.start_episode(i as usize, seed).await?;
                }
                active[g] = stepped.still;
                if let (Some(i), Some(w)) = (stepped.draw, watcher.as_deref()) {
                    ask_frame(&mut sessions[g], local(g, &[i])[0], &w.options).await?;
                    in_flight.push_back((g, Asked::Render));
                    if w.ended {
                        continue;
                    }
                }
                if !stepped.restarted.is_empty() {
                    // The group's next step waits for these observations; the other group keeps the workers busy.
                    let (envs, reset_seeds): (Vec<u32>, Vec<u64>) = stepped.restarted.into_iter().unzip();
                    sessions[g].send_reset(&local(g, &envs), &reset_seeds).await?;
                    resetting[g] = envs;
                    in_flight.push_back((g, Asked::Reset));
                } else if !active[g].is_empty() {
                    let slots = local(g, &active[g]);
                    send_actions(&mut sessions[g], &mut rollout, &episodes, &active[g], &slots).await?;
                    in_flight.push_back((g, Asked::Step));
                }
            }
            (Reply::Reset { observations, .. }, Asked::Reset) => {
                let reset = std::mem::take(&mut resetting[g]);
                episodes.set_observations(&reset, &observations);
                if let Some(i) = episodes.watched_among(&reset, watcher.as_deref()) {
                    let w = watcher.as_deref().expect("an environment is watched");
                    ask_frame(&mut sessions[g], local(g, &[i])[0], &w.options).await?;
                    in_flight.push_back((g, Asked::Render));
                }
                active[g].extend(reset);
                active[g].sort_unstable();
                let slots = local(g, &active[g]);
                send_actions(&mut sessions[g], &mut rollout, &episodes, &active[g], &slots).await?;
                in_flight.push_back((g, Asked::Step));
            }
            _ => {
                return Err(EvaluationError::Internal(format!(
                    "simulator worker {} answered out of order",
                    sessions[g].worker()
                )));
            }
        }
    }
    // The last steps' rewards and costs still wait for a request to go with (see `Player::finish`).
    rollout.finish().await?;
    for session in sessions {
        session.close().await?;
    }
    Ok(episodes.scores)
}

/// The first `k` of `seeds` as two groups of environments (global numbers `0..k`, see [`split_in_two`]), each in a
/// session of its own opened with its environments' seeds, all opened at once.
pub(crate) async fn open_groups(
    pool: &SimulatorPool,
    task: &Task,
    seeds: &[u64],
    k: usize,
) -> Result<(Vec<Vec<u32>>, Vec<PooledSession>), EvaluationError> {
    let groups = split_in_two(k);
    let opens = groups.iter().map(|g| {
        pool.open(Open {
            task: task.id.to_string(),
            num_envs: g.len() as u32,
            seeds: g.iter().map(|&i| seeds[i as usize]).collect(),
            auto_reset: AutoReset::None as i32,
            controller: None,
        })
    });
    let sessions = futures::future::try_join_all(opens).await?;
    Ok((groups, sessions))
}

/// The episodes of one [`play_group`] as they stand between replies: the returns so far, the episode (index into
/// the seeds) each environment is playing, the next seed to hand out, and each environment's last observation
/// (`obs_dim` values a row, environments in their global order).
struct Episodes<'s> {
    seeds: &'s [u64],
    scores: Vec<EpisodeScore>,
    playing: Vec<usize>,
    next: usize,
    obs: Vec<f32>,
    obs_dim: usize,
}

/// What one step did to a group's environments, in the order they stand in the group.
struct Stepped {
    /// Those whose episode goes on.
    still: Vec<u32>,
    /// Those whose episode ended and that start another: each with the seed it was handed.
    restarted: Vec<(u32, u64)>,
    /// The watched environment, when this step is to be drawn (before its next request is sent).
    draw: Option<u32>,
}

impl<'s> Episodes<'s> {
    /// Environment `i` of the first `envs` starts with seed `i`, from row `i` of `obs`.
    fn new(seeds: &'s [u64], envs: usize, obs_dim: usize, obs: Vec<f32>) -> Episodes<'s> {
        Episodes {
            seeds,
            scores: EpisodeScore::unplayed(seeds),
            playing: (0..envs).collect(),
            next: envs,
            obs,
            obs_dim,
        }
    }

    /// The environment among `envs` that plays the watched episode, if any.
    fn watched_among(&self, envs: &[u32], watcher: Option<&Watcher>) -> Option<u32> {
        let w = watcher?;
        envs.iter().copied().find(|&i| self.playing[i as usize] == w.episode)
    }

    /// Rows of `observations` (in the order of `envs`) become those environments' last observations.
    fn set_observations(&mut self, envs: &[u32], observations: &[f32]) {
        let d = self.obs_dim;
        for (row, &i) in envs.iter().enumerate() {
            self.obs[i as usize * d..(i as usize + 1) * d].copy_from_slice(&observations[row * d..(row + 1) * d]);
        }
    }

    /// The last observations of `envs`, row after row: what the policy acts on.
    fn observations_of(&self, envs: &[u32]) -> Vec<f32> {
        let d = self.obs_dim;
        envs.iter()
            .flat_map(|&i| self.obs[i as usize * d..(i as usize + 1) * d].iter().copied())
            .collect()
    }

    /// Adds a step of `envs` (rows of `step` in their order) to their episodes' returns and keeps their
    /// observations; each environment whose episode ended takes the next unplayed seed, while there is one. The
    /// watched episode's rewards and costs are recorded, and whether this step is to be drawn.
    fn record_step(
        &mut self,
        envs: &[u32],
        step: &StepResult,
        progress: &std::sync::atomic::AtomicU32,
        mut watcher: Option<&mut Watcher>,
    ) -> Stepped {
        let mut stepped = Stepped {
            still: Vec::with_capacity(envs.len()),
            restarted: Vec::new(),
            draw: None,
        };
        self.set_observations(envs, &step.observations);
        for (row, &i) in envs.iter().enumerate() {
            let score = &mut self.scores[self.playing[i as usize]];
            // Sums in f64 of the f32 values the datasets store, as the normalization constants were computed.
            score.reward_return += f64::from(step.rewards[row] as f32);
            score.cost_return += f64::from(step.costs[row] as f32);
            score.length += 1;
            let length = score.length;
            let ended = step.terminated[row] || step.truncated[row];
            if let Some(w) = watcher.as_deref_mut()
                && self.playing[i as usize] == w.episode
            {
                w.rewards.push(step.rewards[row]);
                w.costs.push(step.costs[row]);
                w.ended = ended;
                if w.ended || length.is_multiple_of(w.options.stride) {
                    w.frame_steps.push(length);
                    stepped.draw = Some(i);
                }
            }
            if ended {
                progress.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
            if !ended {
                stepped.still.push(i);
            } else if self.next < self.seeds.len() {
                self.playing[i as usize] = self.next;
                stepped.restarted.push((i, self.seeds[self.next]));
                self.next += 1;
            }
        }
        stepped
    }
}

/// The policy's actions for environments `envs` (from their last observations), sent as their group's next step to
/// its session, where they are `local`.
async fn send_actions(
    session: &mut PooledSession,
    rollout: &mut Player<'_>,
    episodes: &Episodes<'_>,
    envs: &[u32],
    local: &[u32],
) -> Result<(), EvaluationError> {
    let actions = rollout.act(envs, &episodes.observations_of(envs)).await?;
    session.send_step(local, &actions).await
}

/// Asks for a frame of the watched environment (`env`, its number in the session) at the replay's size. The
/// answer comes back in the session's ordered stream, between the step answers around it.
async fn ask_frame(session: &mut PooledSession, env: u32, options: &WatchOptions) -> Result<(), EvaluationError> {
    session.send_render(&[env], options.width, options.height).await?;
    Ok(())
}

/// What a request in flight of [`play_group`] asked for.
#[derive(Debug, Clone, Copy)]
enum Asked {
    Step,
    Reset,
    Render,
}

/// How to draw a replayed episode: frames of `width` x `height` pixels after its reset, after every `stride`-th
/// step and after its last.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WatchOptions {
    pub stride: u32,
    pub width: u32,
    pub height: u32,
}

/// One episode played again and drawn ([`replay_episode`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    /// Its returns and length, computed as scoring computes them.
    pub score: EpisodeScore,
    /// Each step's reward and cost as the simulator reported them.
    pub rewards: Vec<f64>,
    pub costs: Vec<f64>,
    /// RGB frames (`height * width * 3` bytes each, rows top to bottom): the first after the reset, then one after
    /// each step of `frame_steps` (the step count, 1-based).
    pub frames: Vec<Vec<u8>>,
    pub frame_steps: Vec<u32>,
    pub options: WatchOptions,
}

/// The watched episode's record while [`play_group`] plays it.
struct Watcher {
    /// Its index among the group's seeds.
    episode: usize,
    options: WatchOptions,
    rewards: Vec<f64>,
    costs: Vec<f64>,
    frames: Vec<Vec<u8>>,
    frame_steps: Vec<u32>,
    ended: bool,
}

/// Plays episode `episode` (an index into `seeds`) again exactly as [`play_episodes`] with the same seeds and layout
/// played it, and draws it. The episode's environment may have played earlier episodes first (Bullet keeps motor
/// targets across a reset, so those shape it), so its group is replayed from the start, with the same sessions,
/// environments and request order, until the episode ends; frames are extra requests in the same stream and change
/// no simulator state. The recording's returns are therefore the scored episode's, which the caller can check.
#[allow(clippy::too_many_arguments)]
pub async fn replay_episode(
    pool: &SimulatorPool,
    task: &Task,
    policy: PolicySource<'_>,
    cost_threshold: f64,
    seeds: &[u64],
    envs_per_session: usize,
    sessions: usize,
    episode: usize,
    options: WatchOptions,
) -> Result<Recording, EvaluationError> {
    if episode >= seeds.len() {
        return Err(EvaluationError::NotFound(format!(
            "episode {episode} is not among the {} played at this threshold",
            seeds.len()
        )));
    }
    if options.stride == 0 {
        return Err(EvaluationError::InvalidArgument("a frame stride of 0 steps".into()));
    }
    let run = session_run(seeds.len(), sessions);
    let group = seeds
        .chunks(run)
        .nth(episode / run)
        .expect("the episode is among the seeds");
    let mut watcher = Watcher {
        episode: episode % run,
        options,
        rewards: Vec::new(),
        costs: Vec::new(),
        frames: Vec::new(),
        frame_steps: Vec::new(),
        ended: false,
    };
    let progress = std::sync::atomic::AtomicU32::new(0);
    let scores = play_group(
        pool,
        task,
        policy,
        cost_threshold,
        group,
        envs_per_session.max(1),
        &progress,
        Some(&mut watcher),
    )
    .await?;
    if !watcher.ended {
        return Err(EvaluationError::Internal(format!(
            "the replay of episode {episode} stopped before the episode ended"
        )));
    }
    Ok(Recording {
        score: scores[watcher.episode].clone(),
        rewards: watcher.rewards,
        costs: watcher.costs,
        frames: watcher.frames,
        frame_steps: watcher.frame_steps,
        options,
    })
}
