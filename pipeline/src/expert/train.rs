//! Training an expert while collecting what it plays (spec 6.1): each collect plays one whole episode in each of
//! the recipe's environments with the current stochastic policy, offers every finished episode to the trajectory
//! buffer, then updates the policy against the cost limit of that point of the schedule.
//!
//! Every `checkpoint_every_collects` collects the sessions are closed and the whole state is saved (networks,
//! optimizer moments, the multiplier, the random state, the buffer and its episodes) into a new
//! `expert/ckpt-NNNNNN/` folder whose `state.json` is written last. Sessions are reopened after each save in an
//! uninterrupted run too, because a simulator's state cannot be saved: that way a run resumed from a save is
//! exactly the run that never stopped (Bullet environments carry state across resets within a session).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use dsrl_policy::noise::Noise;
use dsrl_proto::simulator::v1::{AutoReset, Open};
use dsrl_simulators::{PooledSession, Reply, SimulatorPool};
use dsrl_suite::catalog::{ObservationSpace, Task};
use dsrl_suite::collection::{BufferSnapshot, Stored, TrajectoryBuffer};
use dsrl_suite::convert::{ImportError, write_canonical};
use dsrl_suite::parquet_file::ParquetTransitions;
use dsrl_suite::transitions::TransitionChunk;
use indicatif::ProgressBar;
use serde::{Deserialize, Serialize};

use super::ppo::{Learner, LearnerState, Rollout, UpdateStats};
use crate::collect::{Episode, record_step};
use crate::recipe::{ExpertSettings, Recipe, WarmStart};

/// What the training left in its buffer, with the numbers provenance records.
pub struct ExpertCollection {
    /// The buffer's episodes in buffer order (`setting` = collect, `number` = environment).
    pub episodes: Vec<Episode>,
    pub offered: u64,
    pub steps: u64,
    pub log: Vec<CollectLog>,
}

/// One line of `expert/training.csv`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CollectLog {
    pub collect: u64,
    pub steps: u64,
    pub cost_limit: f64,
    pub mean_reward: f64,
    pub mean_cost: f64,
    pub lagrangian: f64,
    pub approx_kl: f64,
    pub std: f64,
    /// Waiting for the simulators (steps and resets).
    pub simulator_seconds: f64,
    /// The policy's forward passes while acting.
    pub acting_seconds: f64,
    pub update_seconds: f64,
    /// How long the workers had nothing to do, on average over the sessions: the collect's wall time less the
    /// time each session had a request in flight (steps, and resets waited for).
    #[serde(default)]
    pub worker_idle_seconds: f64,
    /// The actor's optimizer steps in the collect's update (fewer than passes x minibatches where the recipe's
    /// `target_kl` stopped it; 0 in logs written before this column).
    #[serde(default)]
    pub actor_steps: u32,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct State {
    collects: u64,
    steps: u64,
    noise: Noise,
    learner: LearnerState,
    buffer: BufferSnapshot,
    /// (collect, environment, seed) of each buffered episode, in buffer order.
    buffered: Vec<(u64, u32, u64)>,
    /// The task's action bound, known once a session has opened.
    #[serde(default)]
    max_action: Option<f64>,
    log: Vec<CollectLog>,
}

fn checkpoint_dirs(root: &Path) -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("ckpt-"))
                && p.join("state.json").is_file()
        })
        .collect();
    dirs.sort();
    dirs
}

fn save(
    root: &Path,
    task: &Task,
    state: &State,
    learner: &Learner,
    buffer: &TrajectoryBuffer<Episode>,
) -> anyhow::Result<()> {
    let dir = root.join(format!("ckpt-{:06}", state.collects));
    if dir.exists() {
        std::fs::remove_dir_all(&dir)?;
    }
    std::fs::create_dir_all(&dir)?;
    let tensors: HashMap<String, dsrl_policy::Tensor> = learner.tensors().into_iter().collect();
    dsrl_policy::candle_save(&tensors, &dir.join("state.safetensors"))?;
    if !buffer.episodes().is_empty() {
        let chunks = buffer
            .episodes()
            .iter()
            .map(|e| Ok::<_, ImportError>(e.payload.transitions.clone()));
        write_canonical(
            task,
            ObservationSpace::Simulator,
            chunks,
            Vec::new(),
            &dir.join("buffer.parquet"),
        )
        .context("saving the trajectory buffer")?;
    }
    // Written last, and whole (a kill between creating and filling it once left an empty state.json that the
    // resumed run could not read): a folder without it is an unfinished save and is ignored.
    crate::write_atomically(&dir.join("state.json"), &serde_json::to_vec(state)?)?;
    for old in checkpoint_dirs(root) {
        if old != dir {
            std::fs::remove_dir_all(old)?;
        }
    }
    write_log(root, &state.log)
}

fn write_log(root: &Path, log: &[CollectLog]) -> anyhow::Result<()> {
    let mut text = String::from(
        "collect,steps,cost_limit,mean_reward,mean_cost,lagrangian,approx_kl,std,simulator_seconds,acting_seconds,update_seconds,worker_idle_seconds,actor_steps\n",
    );
    for l in log {
        text.push_str(&format!(
            "{},{},{},{:.3},{:.3},{:.5},{:.6},{:.4},{:.3},{:.3},{:.3},{:.3},{}\n",
            l.collect,
            l.steps,
            l.cost_limit,
            l.mean_reward,
            l.mean_cost,
            l.lagrangian,
            l.approx_kl,
            l.std,
            l.simulator_seconds,
            l.acting_seconds,
            l.update_seconds,
            l.worker_idle_seconds,
            l.actor_steps
        ));
    }
    crate::write_atomically(&root.join("training.csv"), text.as_bytes())?;
    Ok(())
}

/// A save's state and learner tensors (not its buffered episodes), and the bytes of its tensor file.
fn load_learner(dir: &Path) -> anyhow::Result<(State, HashMap<String, dsrl_policy::Tensor>, Vec<u8>)> {
    let state: State = serde_json::from_slice(&std::fs::read(dir.join("state.json"))?)
        .with_context(|| format!("reading {}", dir.join("state.json").display()))?;
    let bytes = std::fs::read(dir.join("state.safetensors"))?;
    let tensors = dsrl_policy::checkpoint::parse_weights(&bytes)?;
    Ok((state, tensors, bytes))
}

/// A save as read back: the state, the learner's tensors and the buffered episodes.
type Saved = (State, HashMap<String, dsrl_policy::Tensor>, Vec<Episode>);

/// Reads the latest complete save: its state, tensors and buffered episodes.
fn load(root: &Path) -> anyhow::Result<Option<Saved>> {
    let Some(dir) = checkpoint_dirs(root).pop() else {
        return Ok(None);
    };
    let (state, tensors, _) = load_learner(&dir)?;
    let mut episodes = Vec::with_capacity(state.buffered.len());
    if !state.buffered.is_empty() {
        let path = dir.join("buffer.parquet");
        let mut all: Option<TransitionChunk> = None;
        for chunk in ParquetTransitions::open(std::fs::File::open(&path)?)? {
            let mut chunk = chunk.with_context(|| format!("reading {}", path.display()))?;
            chunk.episode = None;
            chunk.step = None;
            match &mut all {
                Some(all) => all.append(&chunk),
                None => all = Some(chunk),
            }
        }
        let all = all.context("the saved buffer is empty")?;
        // Episodes are copied out by offset: splitting from the front would move the rest once per episode.
        let mut start = 0;
        for &(collect, env, seed) in &state.buffered {
            let end = (start..all.len())
                .find(|&i| all.is_done(i))
                .context("the saved buffer ends mid-episode")?
                + 1;
            episodes.push(Episode::from_chunk(
                collect as usize,
                env,
                seed,
                all.rows(start, end - start),
            ));
            start = end;
        }
        anyhow::ensure!(
            start == all.len(),
            "the saved buffer holds more episodes than its state lists"
        );
    }
    Ok(Some((state, tensors, episodes)))
}

/// What a warm-started expert starts from (the recipe's `warm_start`): the source build's networks and
/// observation statistics, and what the provenance records of them.
pub struct WarmStartWeights {
    tensors: HashMap<String, dsrl_policy::Tensor>,
    observation_stats: Option<super::normalization::ObservationStats>,
    pub record: serde_json::Value,
}

/// Whether `root` (an expert folder) holds a save, so that a run there resumes rather than starts.
pub fn has_save(root: &Path) -> bool {
    !checkpoint_dirs(root).is_empty()
}

/// Reads the finished build in `source` (a state folder of `dsrl-admin collect`) that the recipe's `warm_start`
/// names: it must be a run of `warm.task` at `warm.budget_steps` that trained to the end.
pub fn read_warm_start(source: &Path, warm: &WarmStart) -> anyhow::Result<WarmStartWeights> {
    let missing = || {
        format!(
            "the recipe warm-starts from a finished {}-step build of {} and expects it in {}: build it there first \
             (BUDGET_STEPS={} data/build_datasets.sh {} with the same DSRL_COLLECT_DIR), or name its state folder \
             with --warm-start",
            warm.budget_steps,
            warm.task,
            source.display(),
            warm.budget_steps,
            warm.task
        )
    };
    let identity: serde_json::Value =
        serde_json::from_slice(&std::fs::read(source.join("run.json")).with_context(missing)?)
            .with_context(|| format!("reading {}", source.join("run.json").display()))?;
    let source_recipe: Recipe = serde_json::from_value(identity["recipe"].clone())
        .with_context(|| format!("{}: not an expert build's run.json", source.display()))?;
    let source_budget = identity["budget_steps"]
        .as_u64()
        .or(source_recipe.expert.as_ref().map(|e| e.budget_steps));
    anyhow::ensure!(
        source_recipe.task == warm.task && source_budget == Some(warm.budget_steps),
        "{} holds a build of {} at {} steps, not the warm start's {} at {} steps",
        source.display(),
        source_recipe.task,
        source_budget.map_or("unknown".to_owned(), |b| b.to_string()),
        warm.task,
        warm.budget_steps
    );
    // The latest save: the buffer the source kept is not needed.
    let dir = checkpoint_dirs(&source.join("expert")).pop().with_context(missing)?;
    let (state, tensors, bytes) = load_learner(&dir)?;
    anyhow::ensure!(
        state.steps >= warm.budget_steps,
        "{}: the build of {} has trained {} of its {} steps; finish it first ({})",
        source.display(),
        warm.task,
        state.steps,
        warm.budget_steps,
        missing()
    );
    use sha2::Digest;
    let sha256 = hex::encode(sha2::Sha256::digest(&bytes));
    // The networks only: the optimizers' moments belong to the other task's training.
    let tensors: HashMap<String, dsrl_policy::Tensor> = tensors
        .into_iter()
        .filter(|(name, _)| name.starts_with("actor.") || name.starts_with("critic."))
        .collect();
    Ok(WarmStartWeights {
        tensors,
        observation_stats: state.learner.observation_stats,
        record: serde_json::json!({
            "task": warm.task,
            "budget_steps": warm.budget_steps,
            "steps_trained": state.steps,
            "collects": state.collects,
            "recipe": source_recipe,
            "state_sha256": sha256,
        }),
    })
}

/// The action bound of a task whose actions lie in `[-m, m]` in every dimension (true of every Bullet and
/// Safety-Gymnasium task); the Gaussian actor's mean is `m·tanh(·)`.
fn symmetric_bound(session: &PooledSession) -> anyhow::Result<f64> {
    let spec = session.spec();
    let m = spec
        .action_high
        .first()
        .copied()
        .context("the task declares no action bounds")?;
    anyhow::ensure!(
        spec.action_high.iter().all(|&h| h == m) && spec.action_low.iter().all(|&l| l == -m),
        "{}: the expert needs symmetric action bounds, got {:?}..{:?}",
        spec.task,
        spec.action_low,
        spec.action_high
    );
    Ok(m)
}

struct Played {
    rollout: Rollout,
    /// One finished episode per environment, in environment order.
    episodes: Vec<TransitionChunk>,
    simulator_seconds: f64,
    acting_seconds: f64,
    /// Per session: how long it had a request in flight (its worker was busy or the answer on its way).
    busy_seconds: Vec<f64>,
}

/// Per session, the time it has at least one request in flight: what is not is time its worker sat idle.
struct Busy {
    in_flight: Vec<usize>,
    since: Vec<Instant>,
    seconds: Vec<f64>,
}

impl Busy {
    fn new(sessions: usize) -> Busy {
        Busy {
            in_flight: vec![0; sessions],
            since: vec![Instant::now(); sessions],
            seconds: vec![0.0; sessions],
        }
    }

    fn sent(&mut self, session: usize) {
        if self.in_flight[session] == 0 {
            self.since[session] = Instant::now();
        }
        self.in_flight[session] += 1;
    }

    fn answered(&mut self, session: usize) {
        self.in_flight[session] -= 1;
        if self.in_flight[session] == 0 {
            self.seconds[session] += self.since[session].elapsed().as_secs_f64();
        }
    }
}

/// Where environment `j` of a collect lives: `(session, index in the session)`, environments dealt out in order.
fn layout(envs: usize, sessions: usize) -> Vec<(usize, u32)> {
    let per = envs.div_ceil(sessions.max(1)).max(1);
    (0..envs).map(|j| (j / per, (j % per) as u32)).collect()
}

/// The sessions whose layout fixes the acting blocks (below): two, the number of workers every committed full build
/// ran with, so that their version ids hold.
const ACTING_LAYOUT_SESSIONS: usize = 2;

/// The acting blocks of `envs` environments: the contiguous runs of environments the policy acts on in one batch,
/// each session's first half and the rest in a layout over `ACTING_LAYOUT_SESSIONS` sessions, whatever the sessions
/// the run really has. A batch's number of rows picks gemm's kernels and so how a row's products round (an action
/// computed in a batch of 5 rows can differ in its last bit from the same computed in a batch of 3), so batches that
/// followed the sessions made the data depend on `--workers`; fixed blocks do not.
fn acting_blocks(envs: usize) -> Vec<Vec<usize>> {
    session_members(&layout(envs, ACTING_LAYOUT_SESSIONS))
        .iter()
        .flat_map(|members| {
            dsrl_simulators::split_in_two(members.len())
                .into_iter()
                .map(|half| half.iter().map(|&i| members[i as usize] as usize).collect())
        })
        .collect()
}

/// One step request in flight: a block's environments that live in one session, with what the policy sent them.
struct Request {
    block: usize,
    session: usize,
    envs: Vec<usize>,
    actions: Vec<f32>,
    log_probs: Vec<f32>,
}

/// Plays one episode in every environment from the observations `obs` (`[envs, obs_dim]`, global order).
///
/// The policy acts on fixed blocks of environments (`acting_blocks`), each block's step going to the sessions its
/// environments live in. The blocks' steps are pipelined: while a worker steps one block, the policy acts on
/// another's last observations, so the simulators do not wait for the round trip or for acting (BENCHMARKS.md). A
/// block acts again once every session has answered its last step; answers are handled in the order the requests
/// were sent, so the blocks act round-robin in block order and the policy draws its noise for the playing
/// environments in environment order. Neither the batches nor the noise depend on the sessions: the run does not
/// depend on `--workers`.
async fn play(
    sessions: &mut [PooledSession],
    layout: &[(usize, u32)],
    mut obs: Vec<f32>,
    learner: &Learner,
    noise: &mut Noise,
    obs_dim: usize,
    act_dim: usize,
) -> anyhow::Result<Played> {
    #[derive(Default)]
    struct Trace {
        chunk: Option<TransitionChunk>,
        actions: Vec<f32>,
        log_probs: Vec<f32>,
    }
    let total = layout.len();
    let mut traces: Vec<Trace> = (0..total)
        .map(|_| Trace {
            chunk: Some(TransitionChunk::empty(obs_dim, act_dim)),
            ..Trace::default()
        })
        .collect();
    // Each block's playing environments; the answers not yet in for its last step; those still playing after it.
    let mut blocks = acting_blocks(total);
    let mut unanswered = vec![0usize; blocks.len()];
    let mut still: Vec<Vec<usize>> = vec![Vec::new(); blocks.len()];
    let mut acting_seconds = 0.0;
    let mut busy = Busy::new(sessions.len());
    // The policy's actions for the block's playing environments, sent as their next step to the sessions they live
    // in (a block's environments are contiguous, and so are those of each session).
    let act = async |sessions: &mut [PooledSession],
                     block: usize,
                     envs: &[usize],
                     obs: &[f32],
                     noise: &mut Noise,
                     acting_seconds: &mut f64,
                     busy: &mut Busy|
           -> anyhow::Result<Vec<Request>> {
        let batch: Vec<f32> = envs
            .iter()
            .flat_map(|&j| obs[j * obs_dim..(j + 1) * obs_dim].iter().copied())
            .collect();
        let started = Instant::now();
        let (actions, log_probs) = learner.act(&batch, envs.len(), noise)?;
        *acting_seconds += started.elapsed().as_secs_f64();
        let mut requests = Vec::new();
        let mut from = 0;
        while from < envs.len() {
            let session = layout[envs[from]].0;
            let to = from + envs[from..].iter().take_while(|&&j| layout[j].0 == session).count();
            let local: Vec<u32> = envs[from..to].iter().map(|&j| layout[j].1).collect();
            let sent = &actions[from * act_dim..to * act_dim];
            sessions[session].send_step(&local, sent).await?;
            busy.sent(session);
            requests.push(Request {
                block,
                session,
                envs: envs[from..to].to_vec(),
                actions: sent.to_vec(),
                log_probs: log_probs[from..to].to_vec(),
            });
            from = to;
        }
        Ok(requests)
    };
    // Requests in flight, oldest first.
    let mut in_flight = std::collections::VecDeque::new();
    let started = Instant::now();
    for (b, envs) in blocks.iter().enumerate() {
        let requests = act(sessions, b, envs, &obs, noise, &mut acting_seconds, &mut busy).await?;
        unanswered[b] = requests.len();
        in_flight.extend(requests);
    }
    while let Some(request) = in_flight.pop_front() {
        let Request {
            block,
            session,
            envs,
            actions,
            log_probs,
        } = request;
        let Reply::Step(step) = sessions[session].receive().await? else {
            anyhow::bail!(
                "simulator worker {} answered a step out of order",
                sessions[session].worker()
            );
        };
        busy.answered(session);
        for (k, &j) in envs.iter().enumerate() {
            let next = &step.observations[k * obs_dim..(k + 1) * obs_dim];
            let trace = &mut traces[j];
            let chunk = trace.chunk.as_mut().expect("an active environment has a chunk");
            record_step(chunk, &obs[j * obs_dim..(j + 1) * obs_dim], &step, k);
            trace
                .actions
                .extend_from_slice(&actions[k * act_dim..(k + 1) * act_dim]);
            trace.log_probs.push(log_probs[k]);
            obs[j * obs_dim..(j + 1) * obs_dim].copy_from_slice(next);
            if !(step.terminated[k] || step.truncated[k]) {
                still[block].push(j);
            }
        }
        unanswered[block] -= 1;
        if unanswered[block] == 0 {
            // Every part of the block's step is in (in session order, so `still` is in environment order).
            blocks[block] = std::mem::take(&mut still[block]);
            if !blocks[block].is_empty() {
                let requests = act(
                    sessions,
                    block,
                    &blocks[block],
                    &obs,
                    noise,
                    &mut acting_seconds,
                    &mut busy,
                )
                .await?;
                unanswered[block] = requests.len();
                in_flight.extend(requests);
            }
        }
    }
    // Acting overlaps the simulators: what is left of the wall time is waiting for them.
    let simulator_seconds = started.elapsed().as_secs_f64() - acting_seconds;
    let mut rollout = Rollout {
        obs_dim,
        act_dim,
        ..Rollout::default()
    };
    let mut episodes = Vec::with_capacity(total);
    for trace in traces {
        let chunk = trace.chunk.expect("every environment played");
        rollout.observations.extend_from_slice(&chunk.observations);
        rollout.next_observations.extend_from_slice(&chunk.next_observations);
        rollout.actions.extend_from_slice(&trace.actions);
        rollout.log_probs.extend_from_slice(&trace.log_probs);
        rollout.rewards.extend(chunk.rewards.iter().map(|&r| f64::from(r)));
        rollout.costs.extend(chunk.costs.iter().map(|&c| f64::from(c)));
        rollout.terminated.extend_from_slice(&chunk.terminals);
        let n = chunk.len();
        rollout.episode_end.extend((0..n).map(|t| t + 1 == n));
        episodes.push(chunk);
    }
    Ok(Played {
        rollout,
        episodes,
        simulator_seconds,
        acting_seconds,
        busy_seconds: busy.seconds,
    })
}

/// Queues a reset of every environment of every session for collect `collect`; the caller receives the answers.
async fn send_resets(
    sessions: &mut [PooledSession],
    members: &[Vec<u32>],
    recipe: &Recipe,
    collect: u64,
) -> anyhow::Result<()> {
    for (session, envs) in sessions.iter_mut().zip(members) {
        let ids: Vec<u32> = (0..envs.len() as u32).collect();
        let seeds: Vec<u64> = envs.iter().map(|&j| env_seed(recipe, collect, j)).collect();
        session.send_reset(&ids, &seeds).await?;
    }
    Ok(())
}

/// The seed of environment `env` in collect `collect`: distinct across the run.
fn env_seed(recipe: &Recipe, collect: u64, env: u32) -> u64 {
    recipe.episode_seed(collect as usize, env)
}

/// Where and for how long an expert trains.
pub struct Training<'a> {
    /// The expert folder: saves, the training log and the final policy; a save there is resumed.
    pub root: &'a Path,
    /// Environment steps to train for.
    pub budget: u64,
    /// The environments are spread over up to this many sessions (one per worker); the result is the same for any
    /// number (the policy acts on fixed blocks of environments, `acting_blocks`).
    pub sessions: usize,
    /// The recipe's warm start, read by the caller; used only where the run starts (no save in `root`).
    pub warm_start: Option<WarmStartWeights>,
}

/// A learner's saved tensors, by name.
type Tensors = HashMap<String, dsrl_policy::Tensor>;

/// The state a run starts from: its last save in `root`, or a fresh start (the warm start's observation statistics
/// where there is one). Returns the state, the trajectory buffer and the saved learner's tensors (a resumed run).
fn resume_or_start(
    root: &Path,
    recipe: &Recipe,
    expert: &ExpertSettings,
    warm_start: Option<&WarmStartWeights>,
) -> anyhow::Result<(State, TrajectoryBuffer<Episode>, Option<Tensors>)> {
    let limits = recipe.buffer_limits();
    if let Some((state, tensors, episodes)) = load(root)? {
        let stored = episodes
            .into_iter()
            .map(|e| Stored {
                reward_return: e.reward_return,
                cost_return: e.cost_return,
                payload: e,
            })
            .collect();
        let buffer = TrajectoryBuffer::restore(limits, state.buffer.clone(), stored).map_err(anyhow::Error::msg)?;
        tracing::info!(
            collects = state.collects,
            steps = state.steps,
            "resuming the expert from its last save"
        );
        return Ok((state, buffer, Some(tensors)));
    }
    let buffer = TrajectoryBuffer::new(limits, recipe.seed).map_err(anyhow::Error::msg)?;
    let state = State {
        collects: 0,
        steps: 0,
        // Apart from the buffer's and the episode seeds' streams.
        noise: Noise::seeded(recipe.seed ^ 0x5EED_0FE7_BE57),
        learner: LearnerState {
            lagrangian: super::lagrangian::PidLagrangian::new(
                expert.lagrangian.kp,
                expert.lagrangian.ki,
                expert.lagrangian.kd,
            ),
            actor_steps: 0,
            critic_steps: 0,
            observation_stats: warm_start.and_then(|w| w.observation_stats.clone()),
        },
        buffer: buffer.snapshot(),
        buffered: Vec::new(),
        max_action: None,
        log: Vec::new(),
    };
    Ok((state, buffer, None))
}

/// The global environment numbers of each session, in order.
fn session_members(layout: &[(usize, u32)]) -> Vec<Vec<u32>> {
    let session_count = layout.last().map_or(0, |&(s, _)| s + 1);
    (0..session_count)
        .map(|s| {
            (0..layout.len() as u32)
                .filter(|&j| layout[j as usize].0 == s)
                .collect()
        })
        .collect()
}

/// Opens a segment's sessions, each environment seeded for collect `collects`.
async fn open_sessions(
    pool: &SimulatorPool,
    recipe: &Recipe,
    members: &[Vec<u32>],
    collects: u64,
) -> anyhow::Result<Vec<PooledSession>> {
    let opens = members.iter().map(|envs| {
        let seeds: Vec<u64> = envs.iter().map(|&j| env_seed(recipe, collects, j)).collect();
        pool.open(Open {
            task: recipe.task.clone(),
            num_envs: envs.len() as u32,
            seeds,
            auto_reset: AutoReset::None as i32,
            controller: None,
        })
    });
    Ok(futures::future::try_join_all(opens).await?)
}

/// Offers a collect's episodes to the trajectory buffer; returns their reward and cost returns.
fn offer_episodes(
    buffer: &mut TrajectoryBuffer<Episode>,
    episodes: Vec<TransitionChunk>,
    recipe: &Recipe,
    collects: u64,
) -> (Vec<f64>, Vec<f64>) {
    let mut rewards = Vec::with_capacity(episodes.len());
    let mut costs = Vec::with_capacity(episodes.len());
    for (j, chunk) in episodes.into_iter().enumerate() {
        let episode = Episode::from_chunk(collects as usize, j as u32, env_seed(recipe, collects, j as u32), chunk);
        costs.push(episode.cost_return);
        rewards.push(episode.reward_return);
        buffer.offer(Stored {
            reward_return: episode.reward_return,
            cost_return: episode.cost_return,
            payload: episode,
        });
    }
    (rewards, costs)
}

/// The final expert, also when a run stopped between its last save and this write.
fn write_final_policy(
    root: &Path,
    task: &Task,
    expert: &ExpertSettings,
    learner: Option<&Learner>,
    tensors: Option<Tensors>,
    state: &State,
) -> anyhow::Result<()> {
    let policy_dir = root.join("policy");
    match (learner, tensors, state.max_action) {
        (Some(learner), _, _) => learner.write_policy(&policy_dir, task.id.as_str())?,
        (None, Some(tensors), Some(max_action)) if !policy_dir.join("policy.json").is_file() => {
            Learner::restore(expert, max_action, &tensors, &state.learner)?
                .write_policy(&policy_dir, task.id.as_str())?
        }
        _ => {}
    }
    Ok(())
}

/// Trains the recipe's expert and returns what its trajectory buffer kept.
pub async fn train(
    pool: &SimulatorPool,
    recipe: &Recipe,
    task: &Task,
    training: Training<'_>,
    bar: &ProgressBar,
) -> anyhow::Result<ExpertCollection> {
    let Training {
        root,
        budget,
        sessions,
        warm_start,
    } = training;
    let expert: &ExpertSettings = recipe.expert.as_ref().context("the recipe has no expert section")?;
    std::fs::create_dir_all(root)?;
    let (obs_dim, act_dim) = (task.obs_dim as usize, task.act_dim as usize);
    let (mut state, mut buffer, mut tensors) = resume_or_start(root, recipe, expert, warm_start.as_ref())?;
    bar.set_length(budget);
    bar.set_position(state.steps.min(budget));
    let layout = layout(expert.envs as usize, sessions);
    let members = session_members(&layout);
    let mut learner: Option<Learner> = None;
    // Only a run that starts here takes the warm start; a resumed one has it in its save already.
    let mut warm = if tensors.is_none() {
        warm_start.map(|w| w.tensors)
    } else {
        None
    };
    while state.steps < budget {
        // A segment: fresh sessions, `checkpoint_every_collects` collects, a save.
        let mut sessions = open_sessions(pool, recipe, &members, state.collects).await?;
        let max_action = symmetric_bound(&sessions[0])?;
        state.max_action = Some(max_action);
        let learner = match &mut learner {
            Some(l) => l,
            None => learner.insert(match (tensors.take(), warm.take()) {
                (Some(t), _) => Learner::restore(expert, max_action, &t, &state.learner)?,
                (None, Some(w)) => {
                    Learner::warm_start(expert, max_action, &w, state.learner.observation_stats.clone())?
                }
                (None, None) => Learner::new(expert, obs_dim, act_dim, max_action, &mut state.noise)?,
            }),
        };
        let mut obs: Vec<f32> = sessions
            .iter()
            .flat_map(|s| s.initial_observations().to_vec())
            .collect();
        // Whether the next collect's resets are already with the workers.
        let mut resets_sent = false;
        for c in 0..expert.checkpoint_every_collects {
            if state.steps >= budget {
                break;
            }
            let reset_started = Instant::now();
            if c > 0 {
                obs.clear();
                if !resets_sent {
                    send_resets(&mut sessions, &members, recipe, state.collects).await?;
                }
                for session in sessions.iter_mut() {
                    let Reply::Reset { observations, .. } = session.receive().await? else {
                        anyhow::bail!("simulator worker {} answered a reset out of order", session.worker());
                    };
                    obs.extend(observations);
                }
            }
            let reset_seconds = reset_started.elapsed().as_secs_f64();
            let played = play(
                &mut sessions,
                &layout,
                obs.clone(),
                learner,
                &mut state.noise,
                obs_dim,
                act_dim,
            )
            .await?;
            let (rewards, costs) = offer_episodes(&mut buffer, played.episodes, recipe, state.collects);
            let cost_limit = expert.cost_limit_at(state.steps, budget);
            // The next collect's resets need no policy: the workers do them while the learner updates.
            resets_sent =
                c + 1 < expert.checkpoint_every_collects && state.steps + (played.rollout.len() as u64) < budget;
            if resets_sent {
                send_resets(&mut sessions, &members, recipe, state.collects + 1).await?;
            }
            let started = Instant::now();
            let stats: UpdateStats =
                tokio::task::block_in_place(|| learner.update(&played.rollout, &costs, cost_limit, &mut state.noise))?;
            let update_seconds = started.elapsed().as_secs_f64();
            state.steps += played.rollout.len() as u64;
            let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
            state.log.push(CollectLog {
                collect: state.collects,
                steps: state.steps,
                cost_limit,
                mean_reward: mean(&rewards),
                mean_cost: mean(&costs),
                lagrangian: stats.lagrangian,
                approx_kl: stats.approx_kl,
                std: stats.std,
                simulator_seconds: played.simulator_seconds + reset_seconds,
                acting_seconds: played.acting_seconds,
                update_seconds,
                worker_idle_seconds: (reset_started.elapsed().as_secs_f64()
                    - reset_seconds
                    - played.busy_seconds.iter().sum::<f64>() / played.busy_seconds.len().max(1) as f64)
                    .max(0.0),
                actor_steps: stats.actor_steps,
            });
            state.collects += 1;
            bar.set_position(state.steps.min(budget));
            bar.set_message(format!(
                "{} limit {cost_limit:.0} λ {:.2} R {:.0} C {:.1}",
                task.id,
                stats.lagrangian,
                mean(&rewards),
                mean(&costs)
            ));
        }
        for session in sessions {
            session.close().await?;
        }
        state.learner = learner.state();
        state.buffer = buffer.snapshot();
        state.buffered = buffer
            .episodes()
            .iter()
            .map(|e| (e.payload.setting as u64, e.payload.number, e.payload.seed))
            .collect();
        let (task, root) = (task.clone(), root.to_path_buf());
        tokio::task::block_in_place(|| save(&root, &task, &state, learner, &buffer))?;
    }
    write_final_policy(root, task, expert, learner.as_ref(), tensors, &state)?;
    write_log(root, &state.log)?;
    let (offered, _) = buffer.counts();
    Ok(ExpertCollection {
        episodes: buffer.into_episodes().into_iter().map(|s| s.payload).collect(),
        offered,
        steps: state.steps,
        log: state.log,
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn environments_are_dealt_to_sessions_in_order() {
        assert_eq!(super::layout(4, 1), vec![(0, 0), (0, 1), (0, 2), (0, 3)]);
        assert_eq!(super::layout(4, 2), vec![(0, 0), (0, 1), (1, 0), (1, 1)]);
        // 10 environments on 4 workers: sessions of 3, 3, 3 and 1; more workers than environments: one each.
        let ten = super::layout(10, 4);
        assert_eq!(ten.iter().filter(|(s, _)| *s == 3).count(), 1);
        assert_eq!(ten[9], (3, 0));
        assert_eq!(super::layout(2, 16), vec![(0, 0), (1, 0)]);
    }

    #[test]
    fn acting_blocks_are_the_halves_of_two_sessions_whatever_the_sessions() {
        // Ten environments: sessions of 5 in the two-session layout, each split into 3 and 2.
        assert_eq!(
            super::acting_blocks(10),
            vec![vec![0, 1, 2], vec![3, 4], vec![5, 6, 7], vec![8, 9]]
        );
        assert_eq!(super::acting_blocks(4), vec![vec![0], vec![1], vec![2], vec![3]]);
        assert_eq!(super::acting_blocks(1), vec![vec![0]]);
        // Every environment in exactly one block, in order.
        for envs in 1..40 {
            let flat: Vec<usize> = super::acting_blocks(envs).concat();
            assert_eq!(flat, (0..envs).collect::<Vec<_>>());
        }
    }
}
