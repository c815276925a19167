//! Episodes of a block of sweep settings, played through one pooled simulator session: driven whole by the worker's
//! driver where the deal allows, stepped otherwise.

use dsrl_proto::simulator::v1::{AutoReset, Controller, Idm, Open, controller};
use dsrl_simulators::session::DrivenRest;
use dsrl_simulators::{PooledSession, SimulatorPool, StepResult};
use dsrl_suite::transitions::TransitionChunk;

use crate::recipe::{Recipe, Setting};

/// One finished episode with its returns (f64 sums of the stored f32 rewards and costs, as FSRL adds them).
#[derive(Debug, Clone)]
pub struct Episode {
    pub setting: usize,
    pub number: u32,
    pub seed: u64,
    pub transitions: TransitionChunk,
    pub reward_return: f64,
    pub cost_return: f64,
}

impl Episode {
    pub fn from_chunk(setting: usize, number: u32, seed: u64, transitions: TransitionChunk) -> Episode {
        let reward_return = transitions.rewards.iter().map(|&r| f64::from(r)).sum();
        let cost_return = transitions.costs.iter().map(|&c| f64::from(c)).sum();
        Episode {
            setting,
            number,
            seed,
            transitions,
            reward_return,
            cost_return,
        }
    }
}

/// Appends row `row` of a step's answer to an episode's transitions: the observation it was taken from, the next
/// one, the action the simulator applied (a controller's, or the policy's clipped), reward, cost, and how it ended.
pub fn record_step(chunk: &mut TransitionChunk, observation: &[f32], step: &StepResult, row: usize) {
    let (obs_dim, act_dim) = (observation.len(), step.applied_actions.len() / step.rewards.len());
    chunk.observations.extend_from_slice(observation);
    chunk
        .next_observations
        .extend_from_slice(&step.observations[row * obs_dim..(row + 1) * obs_dim]);
    chunk
        .actions
        .extend_from_slice(&step.applied_actions[row * act_dim..(row + 1) * act_dim]);
    chunk.rewards.push(step.rewards[row] as f32);
    chunk.costs.push(step.costs[row] as f32);
    chunk.terminals.push(step.terminated[row]);
    chunk.timeouts.push(step.truncated[row] && !step.terminated[row]);
}

/// An episode's transitions from its first observation and the rest its controller drove.
fn driven_chunk(first: &[f32], rest: &DrivenRest, obs_dim: usize, act_dim: usize) -> TransitionChunk {
    let steps = rest.rewards.len();
    let mut chunk = TransitionChunk::empty(obs_dim, act_dim);
    chunk.observations.extend_from_slice(first);
    chunk
        .observations
        .extend_from_slice(&rest.observations[..steps.saturating_sub(1) * obs_dim]);
    chunk.next_observations = rest.observations.clone();
    chunk.actions = rest.applied_actions.clone();
    chunk.rewards = rest.rewards.iter().map(|&r| r as f32).collect();
    chunk.costs = rest.costs.iter().map(|&c| c as f32).collect();
    // Only the last step ends the episode; stepping records the same flags.
    chunk.terminals = (0..steps).map(|t| t + 1 == steps && rest.terminated).collect();
    chunk.timeouts = (0..steps)
        .map(|t| t + 1 == steps && rest.truncated && !rest.terminated)
        .collect();
    chunk
}

/// The IDM driver of one sweep setting.
fn driver(setting: &Setting) -> Controller {
    Controller {
        kind: Some(controller::Kind::Idm(Idm {
            target_speed: setting.target_speed,
            acc_factor: setting.acc_factor,
            maps: setting.maps,
        })),
    }
}

/// Runs all episodes of `settings` (a block of the sweep) on one worker session of up to `max_envs` environments
/// (the IDM driver steers; the dataset records the actions it applied). Episodes are dealt in order, setting by
/// setting, to whichever environment finishes first (ties by environment index), and an environment that moves to
/// the next setting switches its driver on reset instead of being built again. The deal depends only on the
/// episodes, so a block gives the same episodes every time it runs; a block of one setting is a fresh session for
/// it. With `drive`, where every episode's environment is known before any is played (one environment, or all
/// episodes dealt at once), the worker's driver plays whole episodes instead (`drive_settings`): the same
/// episodes, one round trip per episode. Returns each setting's episodes in episode-number order.
pub async fn collect_settings(
    pool: &SimulatorPool,
    recipe: &Recipe,
    settings: &[Setting],
    max_envs: u32,
    drive: bool,
    on_episode: impl Fn(),
) -> anyhow::Result<Vec<Vec<Episode>>> {
    // Every (setting, episode) of the block, in the order they are dealt.
    let deal: Vec<(usize, u32)> = settings
        .iter()
        .enumerate()
        .flat_map(|(s, setting)| (0..setting.episodes).map(move |e| (s, e)))
        .collect();
    let seed_of = |(s, e): (usize, u32)| recipe.episode_seed(settings[s].index, e);
    let k = deal.len().min(max_envs as usize).max(1);
    let Some(first) = settings.first() else {
        return Ok(Vec::new());
    };
    let open = Open {
        task: recipe.task.clone(),
        num_envs: k as u32,
        seeds: deal[..k].iter().map(|&d| seed_of(d)).collect(),
        auto_reset: AutoReset::None as i32,
        controller: Some(driver(first)),
    };
    let mut session = pool.open(open).await?;
    let mut done: Vec<Vec<Episode>> = settings
        .iter()
        .map(|s| Vec::with_capacity(s.episodes as usize))
        .collect();
    let mut finish = |(s, number): (usize, u32), transitions: TransitionChunk| {
        done[s].push(Episode::from_chunk(
            settings[s].index,
            number,
            seed_of((s, number)),
            transitions,
        ));
        on_episode();
    };
    if drive && (k == 1 || deal.len() <= k) {
        // Every episode's environment is known before any is played (all dealt at once, or one environment for
        // all), so the worker's driver can play whole episodes: the same episodes as stepping, without a round trip
        // per step.
        drive_settings(&mut session, settings, &deal, k, &seed_of, &mut finish).await?;
    } else {
        step_settings(&mut session, settings, &deal, k, &seed_of, &mut finish).await?;
    }
    session.close().await?;
    for episodes in &mut done {
        episodes.sort_by_key(|e| e.number);
    }
    Ok(done)
}

/// `collect_settings` by stepping: episodes dealt to whichever environment finishes first, each step a round trip.
async fn step_settings(
    session: &mut PooledSession,
    settings: &[Setting],
    deal: &[(usize, u32)],
    k: usize,
    seed_of: &impl Fn((usize, u32)) -> u64,
    finish: &mut impl FnMut((usize, u32), TransitionChunk),
) -> anyhow::Result<()> {
    let (obs_dim, act_dim) = (session.spec().obs_dim as usize, session.spec().act_dim as usize);
    let mut last_obs: Vec<Vec<f32>> = session
        .initial_observations()
        .chunks(obs_dim)
        .map(<[f32]>::to_vec)
        .collect();
    // The setting whose driver each env has (all start with the first setting's) and what it is playing.
    let mut driving: Vec<usize> = vec![0; k];
    let mut playing: Vec<Option<(usize, u32)>> = deal[..k].iter().copied().map(Some).collect();
    // The first deal's envs already run their first episode, except where it belongs to a later setting.
    let mut starting: Vec<(u32, (usize, u32))> = (0..k as u32)
        .zip(deal[..k].iter().copied())
        .filter(|&(_, d)| d.0 != 0)
        .collect();
    let mut dealt = k;
    let mut partial: Vec<TransitionChunk> = (0..k).map(|_| TransitionChunk::empty(obs_dim, act_dim)).collect();
    let mut finished = 0;
    loop {
        // Start the dealt episodes, one reset per setting whose driver the envs switch to.
        let mut by_setting: Vec<usize> = starting.iter().map(|&(_, (s, _))| s).collect();
        by_setting.dedup();
        for s in by_setting {
            let (envs, seeds): (Vec<u32>, Vec<u64>) = starting
                .iter()
                .filter(|&&(_, d)| d.0 == s)
                .map(|&(i, d)| (i, seed_of(d)))
                .unzip();
            let switch = envs
                .iter()
                .any(|&i| driving[i as usize] != s)
                .then(|| driver(&settings[s]));
            let observations = session.reset_with(&envs, &seeds, switch).await?;
            for (row, &env) in envs.iter().enumerate() {
                last_obs[env as usize] = observations[row * obs_dim..(row + 1) * obs_dim].to_vec();
                driving[env as usize] = s;
            }
        }
        starting.clear();
        if finished == deal.len() {
            break;
        }
        let envs: Vec<u32> = (0..k as u32).filter(|&i| playing[i as usize].is_some()).collect();
        // Ignored while the controller drives, but the shape must be right.
        let actions = vec![0f32; envs.len() * act_dim];
        let step = session.step(&envs, &actions).await?;
        for (row, &env) in envs.iter().enumerate() {
            let i = env as usize;
            let chunk = &mut partial[i];
            record_step(chunk, &last_obs[i], &step, row);
            last_obs[i] = step.observations[row * obs_dim..(row + 1) * obs_dim].to_vec();
            if step.terminated[row] || step.truncated[row] {
                let played = playing[i].take().expect("stepped envs are playing");
                finish(
                    played,
                    std::mem::replace(chunk, TransitionChunk::empty(obs_dim, act_dim)),
                );
                finished += 1;
                if let Some(&next) = deal.get(dealt) {
                    playing[i] = Some(next);
                    starting.push((env, next));
                    dealt += 1;
                }
            }
        }
    }
    Ok(())
}

/// `collect_settings` where every episode's environment is known in advance: the first `k` episodes of `deal` on
/// environments `0..k` (driven together, their processes in parallel), then, with one environment, the rest one by
/// one on it. Each episode starts with a reset that switches the driver where the setting changes, as stepping does.
async fn drive_settings(
    session: &mut PooledSession,
    settings: &[Setting],
    deal: &[(usize, u32)],
    k: usize,
    seed_of: &impl Fn((usize, u32)) -> u64,
    finish: &mut impl FnMut((usize, u32), TransitionChunk),
) -> anyhow::Result<()> {
    let (obs_dim, act_dim) = (session.spec().obs_dim as usize, session.spec().act_dim as usize);
    let mut first: Vec<Vec<f32>> = session
        .initial_observations()
        .chunks(obs_dim)
        .map(<[f32]>::to_vec)
        .collect();
    // The setting whose driver each env has: all open with the first setting's.
    let mut driving = vec![0usize; k];
    let mut next = 0;
    while next < deal.len() {
        let wave: Vec<(u32, (usize, u32))> = (0..k as u32).zip(deal[next..].iter().copied()).collect();
        // Episodes past the first deal, or of another setting than the env drives, start with their own reset.
        for &(env, d) in &wave {
            if next > 0 || d.0 != driving[env as usize] {
                let switch = (d.0 != driving[env as usize]).then(|| driver(&settings[d.0]));
                first[env as usize] = session.reset_with(&[env], &[seed_of(d)], switch).await?;
                driving[env as usize] = d.0;
            }
        }
        let envs: Vec<u32> = wave.iter().map(|&(env, _)| env).collect();
        let driven = session.drive(&envs).await?;
        anyhow::ensure!(
            driven.len() == envs.len(),
            "the worker drove {} episodes for {} environments",
            driven.len(),
            envs.len()
        );
        for (&(env, played), rest) in wave.iter().zip(&driven) {
            let steps = rest.rewards.len();
            anyhow::ensure!(
                rest.env == env
                    && steps > 0
                    && rest.costs.len() == steps
                    && rest.observations.len() == steps * obs_dim
                    && rest.applied_actions.len() == steps * act_dim,
                "the worker's driven episode of env {env} is malformed (env {}, {steps} steps)",
                rest.env
            );
            finish(played, driven_chunk(&first[env as usize], rest, obs_dim, act_dim));
        }
        next += wave.len();
    }
    Ok(())
}
