//! Deterministic synthetic datasets in a task's shape, for tests and benchmarks only: they exercise every code
//! path (early terminations, time-limit truncations, spread cost and reward returns) without a simulator.
//! They are never benchmark data.

use crate::catalog::Task;
use crate::transitions::TransitionChunk;

/// SplitMix64: tiny, seedable, and stable across versions, which is what reproducible fixtures need.
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Shape of a synthetic dataset.
#[derive(Debug, Clone, Copy)]
pub struct SyntheticSpec {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub horizon: u32,
    pub episodes: usize,
    /// Rows per yielded chunk.
    pub chunk_rows: usize,
    pub seed: u64,
    /// Cost returns of full-length episodes spread over about `0..max_cost_return`.
    pub max_cost_return: f32,
    /// Reward returns of full-length episodes spread over about this range, rising with cost like the paper's
    /// reward-cost frontier.
    pub reward_return_range: (f32, f32),
}

impl SyntheticSpec {
    pub fn for_task(task: &Task, episodes: usize, seed: u64) -> Self {
        SyntheticSpec {
            obs_dim: task.obs_dim as usize,
            act_dim: task.act_dim as usize,
            horizon: task.max_episode_steps,
            episodes,
            chunk_rows: 4096,
            seed,
            max_cost_return: (task.max_episode_cost * 1.1) as f32,
            reward_return_range: (task.min_episode_reward as f32, (task.max_episode_reward * 1.1) as f32),
        }
    }
}

/// Yields the dataset in chunks of about `chunk_rows` rows. Every 5th episode terminates early; the others are
/// truncated at the horizon. Each episode draws an "aggressiveness" that sets both its cost rate and its reward
/// level, so returns spread over the task's ranges with a rising frontier.
pub fn transitions(spec: SyntheticSpec) -> impl Iterator<Item = TransitionChunk> {
    let mut rng = SplitMix64::new(spec.seed);
    let mut episode = 0usize;
    let mut step = 0u32;
    let mut length = 0u32;
    let mut cost_rate = 0.0f32;
    let mut reward_scale = 0.0f32;
    let mut obs: Vec<f32> = Vec::new();
    std::iter::from_fn(move || {
        if episode >= spec.episodes {
            return None;
        }
        let mut chunk = TransitionChunk::empty(spec.obs_dim, spec.act_dim);
        while chunk.len() < spec.chunk_rows && episode < spec.episodes {
            if step == 0 {
                length = if episode % 5 == 4 {
                    1 + (rng.next_u64() % spec.horizon as u64) as u32
                } else {
                    spec.horizon
                };
                let aggressiveness = rng.next_f32();
                cost_rate = (aggressiveness * spec.max_cost_return / spec.horizon as f32).min(1.0);
                let (lo, hi) = spec.reward_return_range;
                let level = (0.15 + 0.85 * aggressiveness) * (0.7 + 0.3 * rng.next_f32());
                reward_scale = 2.0 * (lo + (hi - lo) * level) / spec.horizon as f32;
                obs = (0..spec.obs_dim).map(|_| rng.next_f32() * 2.0 - 1.0).collect();
            }
            let next: Vec<f32> = obs.iter().map(|v| v + (rng.next_f32() - 0.5) * 0.1).collect();
            chunk.observations.extend_from_slice(&obs);
            chunk.next_observations.extend_from_slice(&next);
            chunk
                .actions
                .extend((0..spec.act_dim).map(|_| rng.next_f32() * 2.0 - 1.0));
            chunk.rewards.push(rng.next_f32() * reward_scale);
            chunk.costs.push(if rng.next_f32() < cost_rate { 1.0 } else { 0.0 });
            let last = step + 1 == length;
            let terminal = last && length < spec.horizon;
            chunk.terminals.push(terminal);
            chunk.timeouts.push(last && !terminal);
            obs = next;
            if last {
                episode += 1;
                step = 0;
            } else {
                step += 1;
            }
        }
        Some(chunk)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_data_and_episodes_close() {
        let spec = SyntheticSpec {
            obs_dim: 3,
            act_dim: 2,
            horizon: 50,
            episodes: 12,
            chunk_rows: 64,
            seed: 7,
            max_cost_return: 20.0,
            reward_return_range: (0.0, 100.0),
        };
        let a: Vec<_> = transitions(spec).collect();
        let b: Vec<_> = transitions(spec).collect();
        assert_eq!(a, b);
        let dones: usize = a.iter().map(|c| (0..c.len()).filter(|&i| c.is_done(i)).count()).sum();
        assert_eq!(dones, 12);
        let last = a.last().unwrap();
        assert!(last.is_done(last.len() - 1));
        let c: Vec<_> = transitions(SyntheticSpec { seed: 8, ..spec }).collect();
        assert_ne!(a, c);
    }
}
