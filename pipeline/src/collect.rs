//! Episodes of one sweep setting, stepped through a pooled simulator session.

use dsrl_evaluation::simulators::{SimulatorPool, StepResult};
use dsrl_proto::simulator::v1::{AutoReset, Controller, Idm, Open, controller};
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

/// Runs all episodes of `setting` on one worker session of up to `max_envs` environments (the IDM driver steers;
/// the dataset records the actions it applied). Episodes come back in episode-number order.
pub async fn collect_setting(
    pool: &SimulatorPool,
    recipe: &Recipe,
    setting: Setting,
    max_envs: u32,
    on_episode: impl Fn(),
) -> anyhow::Result<Vec<Episode>> {
    let seeds: Vec<u64> = (0..setting.episodes)
        .map(|e| recipe.episode_seed(setting.index, e))
        .collect();
    let k = setting.episodes.min(max_envs).max(1) as usize;
    let open = Open {
        task: recipe.task.clone(),
        num_envs: k as u32,
        seeds: seeds[..k].to_vec(),
        auto_reset: AutoReset::None as i32,
        controller: Some(Controller {
            kind: Some(controller::Kind::Idm(Idm {
                target_speed: setting.target_speed,
                acc_factor: setting.acc_factor,
            })),
        }),
    };
    let mut session = pool.open(open).await?;
    let (obs_dim, act_dim) = (session.spec().obs_dim as usize, session.spec().act_dim as usize);
    let mut last_obs: Vec<Vec<f32>> = session
        .initial_observations()
        .chunks(obs_dim)
        .map(<[f32]>::to_vec)
        .collect();
    // Which episode each env is playing (None: done, nothing left to start).
    let mut playing: Vec<Option<u32>> = (0..k as u32).map(Some).collect();
    let mut partial: Vec<TransitionChunk> = (0..k).map(|_| TransitionChunk::empty(obs_dim, act_dim)).collect();
    let mut next_episode = k as u32;
    let mut done: Vec<Episode> = Vec::with_capacity(setting.episodes as usize);
    while done.len() < setting.episodes as usize {
        let envs: Vec<u32> = (0..k as u32).filter(|&i| playing[i as usize].is_some()).collect();
        // Ignored while the controller drives, but the shape must be right.
        let actions = vec![0f32; envs.len() * act_dim];
        let step = session.step(&envs, &actions).await?;
        let (mut reset_envs, mut reset_seeds) = (Vec::new(), Vec::new());
        for (row, &env) in envs.iter().enumerate() {
            let i = env as usize;
            let chunk = &mut partial[i];
            record_step(chunk, &last_obs[i], &step, row);
            last_obs[i] = step.observations[row * obs_dim..(row + 1) * obs_dim].to_vec();
            if step.terminated[row] || step.truncated[row] {
                let number = playing[i].expect("stepped envs are playing");
                let transitions = std::mem::replace(chunk, TransitionChunk::empty(obs_dim, act_dim));
                done.push(Episode::from_chunk(
                    setting.index,
                    number,
                    seeds[number as usize],
                    transitions,
                ));
                on_episode();
                if next_episode < setting.episodes {
                    playing[i] = Some(next_episode);
                    reset_envs.push(env);
                    reset_seeds.push(seeds[next_episode as usize]);
                    next_episode += 1;
                } else {
                    playing[i] = None;
                }
            }
        }
        if !reset_envs.is_empty() {
            let observations = session.reset(&reset_envs, &reset_seeds).await?;
            for (row, &env) in reset_envs.iter().enumerate() {
                last_obs[env as usize] = observations[row * obs_dim..(row + 1) * obs_dim].to_vec();
            }
        }
    }
    session.close().await?;
    done.sort_by_key(|e| e.number);
    Ok(done)
}
