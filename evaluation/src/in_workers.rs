//! Scoring with the policy acting inside the simulator workers (`Act` and `Play` in the simulator proto): the same
//! episodes as [`crate::evaluator`]'s `play_group`, with the server in the loop once an episode instead of once a
//! step (BENCHMARKS.md, scoring).
//!
//! What makes the episodes the same is the order in which the two groups of a threshold draw seeds. `play_group`
//! keeps one request in flight per group and handles the answers in the order the requests were sent, so the
//! groups' requests alternate (the first group's n-th request before the second's n-th), resets counting as
//! requests, until a group has nothing left to play; an environment whose episode ends takes the next seed when
//! the step that ended it is handled. Here each group's session plays until a step ends one of its episodes, and
//! the evaluator numbers that step among the group's requests as `play_group` would have. An end is handed its
//! seeds once every request before it in that order is known: the other group has nothing left, or its own next
//! end, or the first request of what it is playing now, comes later. Between ends nothing passes between the groups,
//! so each session plays on without the server.
//!
//! The policy's checks in the worker are those of the server's policy process, but for the memory cap: there the
//! checkpoint's declared sizes bound what it may hold (`check_step_cost`, the format's weight limit), where the
//! policy process also has an address-space limit.

use dsrl_simulators::{PlayedEpisode, PooledSession, Reply, SimulatorPool};
use dsrl_suite::catalog::Task;

use crate::EvaluationError;
use crate::evaluator::{EpisodeScore, open_groups};
use crate::inference::IsolatedPolicy;

/// One group's place in the order of requests.
struct Group {
    /// The environments (global numbers) still playing, increasing; in its session, environment `i` is
    /// `i - first`.
    active: Vec<u32>,
    first: u32,
    /// The number (from 1) of the first request of what the group is playing now, when it is playing.
    playing_from: Option<u64>,
    /// An end the group reached and waits on: the number of the step that ended it, and the episodes it ended.
    ended_at: Option<(u64, Vec<PlayedEpisode>)>,
    /// Answers still due before the next `Played`: a reset sent with the play.
    resets_due: usize,
}

impl Group {
    /// The position of its next event in the order of requests, for the group numbered `g`: its waiting end, or
    /// the first request of what it plays; `None` when it has nothing left to play.
    fn next_position(&self, g: usize) -> Option<(u64, usize)> {
        match (&self.ended_at, self.playing_from) {
            (Some((step, _)), _) => Some((*step, g)),
            (None, Some(from)) => Some((from, g)),
            (None, None) => None,
        }
    }

    fn local(&self, envs: &[u32]) -> Vec<u32> {
        envs.iter().map(|&i| i - self.first).collect()
    }
}

/// Plays `seeds` as `play_group` does with `envs` environments in two groups, `policy` acting in the workers.
pub(crate) async fn play_group_in_workers(
    pool: &SimulatorPool,
    task: &Task,
    policy: &IsolatedPolicy,
    cost_threshold: f64,
    seeds: &[u64],
    envs: usize,
    progress: &std::sync::atomic::AtomicU32,
) -> Result<Vec<EpisodeScore>, EvaluationError> {
    let k = seeds.len().min(envs);
    let (layout, mut sessions) = open_groups(pool, task, seeds, k).await?;
    let act_cpu_seconds = policy.request_timeout.as_secs_f64();
    for session in &mut sessions {
        session
            .send_act(&policy.config, &policy.weights, cost_threshold, act_cpu_seconds)
            .await?;
    }
    for session in &mut sessions {
        match session.receive().await? {
            Reply::Acting => {}
            _ => return Err(out_of_order(session)),
        }
    }
    let mut scores = EpisodeScore::unplayed(seeds);
    // The episode (index into the seeds) each environment plays, and the next seed to hand out.
    let mut playing: Vec<usize> = (0..k).collect();
    let mut next = k;
    let mut groups: Vec<Group> = layout
        .into_iter()
        .map(|active| Group {
            first: active[0],
            active,
            playing_from: Some(1),
            ended_at: None,
            resets_due: 0,
        })
        .collect();
    for (g, group) in groups.iter().enumerate() {
        sessions[g].send_play(&group.local(&group.active)).await?;
    }
    // The first event in the order of requests, among the groups that still play.
    while let Some((_, g)) = groups
        .iter()
        .enumerate()
        .filter_map(|(g, group)| group.next_position(g))
        .min()
    {
        let Some((step, ended)) = groups[g].ended_at.take() else {
            // Its session is still playing: what it reaches decides what comes next.
            receive_end(&mut sessions[g], &mut groups[g]).await?;
            continue;
        };
        // Every request before this end is known: its episodes take the next seeds, in the group's order.
        let group = &mut groups[g];
        let mut restarted = Vec::new();
        for episode in ended {
            let i = episode.env + group.first;
            let e = playing[i as usize];
            scores[e] = EpisodeScore {
                seed: seeds[e],
                reward_return: episode.reward_return,
                cost_return: episode.cost_return,
                length: episode.length,
            };
            progress.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            group.active.retain(|&a| a != i);
            if next < seeds.len() {
                playing[i as usize] = next;
                restarted.push((i, seeds[next]));
                next += 1;
            }
        }
        let mut from = step + 1;
        if !restarted.is_empty() {
            let (envs, reset_seeds): (Vec<u32>, Vec<u64>) = restarted.into_iter().unzip();
            sessions[g].send_reset(&group.local(&envs), &reset_seeds).await?;
            group.resets_due += 1;
            group.active.extend(envs);
            group.active.sort_unstable();
            from += 1;
        }
        if group.active.is_empty() {
            group.playing_from = None;
        } else {
            sessions[g].send_play(&group.local(&group.active)).await?;
            group.playing_from = Some(from);
        }
    }
    for session in sessions {
        session.close().await?;
    }
    Ok(scores)
}

/// Waits for the end the group's session is playing towards (after the answers to any reset sent before it).
async fn receive_end(session: &mut PooledSession, group: &mut Group) -> Result<(), EvaluationError> {
    let from = group.playing_from.expect("the group is playing");
    loop {
        match session.receive().await? {
            Reply::Reset { .. } if group.resets_due > 0 => group.resets_due -= 1,
            Reply::Played(played) if group.resets_due == 0 => {
                group.ended_at = Some((from + u64::from(played.steps) - 1, played.ended));
                group.playing_from = None;
                return Ok(());
            }
            _ => return Err(out_of_order(session)),
        }
    }
}

fn out_of_order(session: &PooledSession) -> EvaluationError {
    EvaluationError::Internal(format!("simulator worker {} answered out of order", session.worker()))
}
