//! Watching a scored episode. A request for an episode of a finished submission queues a replay: the episode is
//! played again on this server's pinned simulators from its held seed, with the submitted policy and the scoring
//! layout (`dsrl_evaluation::evaluator::replay_episode`), drawn without a display, encoded as an animated GIF and
//! kept in the object store with its step-by-step rewards and costs. Later requests are answered from the store.
//!
//! A replay never delays scoring: the renderer starts one only while no submission waits or is being scored (in any
//! process sharing the database), and drops one in progress, queueing it again, as soon as a submission arrives.
//! The renderer is one supervised task: a failed replay is logged, counted and answered with its reason; a panic
//! restarts the task (counted, shown in `/healthz`).

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use dsrl_evaluation::evaluator::{Recording, WatchOptions, replay_episode};
use dsrl_service::error::ApiError;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStoreExt, PutPayload};
use prometheus_client::metrics::counter::Counter;
use serde::{Deserialize, Serialize};

use crate::Leaderboard;
use crate::queue;
use crate::supervision::RendererState;

/// Frame sides in pixels: enough to see the agent and what it touches, ~10 KB a frame in a GIF.
pub const FRAME_SIDE: u32 = 128;
/// At most this many frames per episode: the stride between drawn steps is the task's horizon over this.
pub const MAX_FRAMES: u32 = 200;
/// Display time of a frame, in hundredths of a second.
const FRAME_DELAY_CS: u16 = 5;

/// One scored episode: a submission's `episode`-th episode at its task's `threshold_index`-th cost threshold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct EpisodeKey {
    pub submission: i64,
    pub threshold_index: usize,
    pub episode: u32,
}

impl EpisodeKey {
    fn object(&self, extension: &str) -> ObjectPath {
        ObjectPath::from(format!(
            "renders/{}/threshold-{}-episode-{}.{extension}",
            self.submission, self.threshold_index, self.episode
        ))
    }
}

/// A replayed episode as stored and served (`…/replay.json`); its animation is `…/replay.gif`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct EpisodeReplay {
    pub submission: i64,
    pub task: String,
    pub cost_threshold: f64,
    pub episode: u32,
    /// The protocol the submission was scored under, and so replayed under.
    pub protocol_version: String,
    /// The returns and length of the replay, computed as scoring computes them; equal to the scored episode's (the
    /// renderer checks it before it keeps a replay).
    pub reward_return: f64,
    pub cost_return: f64,
    pub length: u32,
    /// Each step's reward and cost as the simulator reported them.
    pub rewards: Vec<f64>,
    pub costs: Vec<f64>,
    /// The steps drawn after the reset's frame (1-based), one GIF frame each.
    pub frame_steps: Vec<u32>,
    pub frame_width: u32,
    pub frame_height: u32,
    pub gif_bytes: u64,
    pub gif_sha256: String,
    /// The server build that replayed it, and when.
    pub rendered_by: String,
    pub rendered_at: String,
}

/// Where a requested replay stands.
#[derive(Debug, Clone, PartialEq)]
pub enum ReplayState {
    /// Made: the record, and the key its animation is read with ([`Leaderboard::stored_gif`]).
    Ready {
        replay: Box<EpisodeReplay>,
        key: EpisodeKey,
    },
    /// Queued: `ahead` replays come first; none starts while submissions wait or are scored.
    Queued {
        ahead: usize,
    },
    Failed(String),
}

/// The replay queue, its failures and its counters.
#[derive(Default)]
pub struct Renders {
    queue: Mutex<VecDeque<EpisodeKey>>,
    failed: Mutex<HashMap<EpisodeKey, String>>,
    wake: tokio::sync::Notify,
    state: Mutex<RendererState>,
    /// `dsrl_replays_rendered_total`, `dsrl_replay_failures_total`, `dsrl_renderer_restarts_total`.
    pub rendered: Counter,
    pub failures: Counter,
    pub restarts: Counter,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A poisoned lock only means another thread panicked while holding it; the data are plain.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Renders {
    pub fn state(&self) -> RendererState {
        let mut state = lock(&self.state).clone();
        state.queued = lock(&self.queue).len();
        state
    }

    /// Queues `key` unless it is queued already; returns how many replays come before it.
    fn enqueue(&self, key: EpisodeKey) -> usize {
        let mut queue = lock(&self.queue);
        let ahead = match queue.iter().position(|k| *k == key) {
            Some(position) => position,
            None => {
                queue.push_back(key);
                queue.len() - 1
            }
        };
        drop(queue);
        self.wake.notify_one();
        ahead
    }
}

/// The stride between drawn steps for a task of `horizon` steps.
pub fn frame_stride(horizon: u32) -> u32 {
    horizon.div_ceil(MAX_FRAMES).max(1)
}

impl Leaderboard {
    /// Checks that `submission`'s `episode` at `cost_threshold` was scored here under the current protocol with a
    /// checkpoint this server holds; returns its key.
    async fn replayable(&self, submission: i64, cost_threshold: f64, episode: u32) -> Result<EpisodeKey, ApiError> {
        let row = queue::get(&self.db, submission).await?;
        let task = self.task(&row.task)?;
        let Some(threshold_index) = task.cost_thresholds.iter().position(|&t| t == cost_threshold) else {
            return Err(ApiError::NotFound(format!(
                "{} has no cost threshold {cost_threshold}; its thresholds: {:?}",
                task.id, task.cost_thresholds
            )));
        };
        if row.state != "finished" {
            return Err(ApiError::NotFound(format!(
                "submission {submission} is {}: only scored episodes can be watched",
                row.state
            )));
        }
        if episode >= row.episodes_per_threshold {
            return Err(ApiError::NotFound(format!(
                "submission {submission} played episodes 0 to {} at each threshold, not {episode}",
                row.episodes_per_threshold.saturating_sub(1)
            )));
        }
        if row.protocol_version.as_deref() != Some(self.protocol.version.as_str()) {
            return Err(ApiError::NotFound(format!(
                "submission {submission} was scored under protocol {}; this server plays protocol {}, whose \
                 simulators, seeds or layout may differ, so it cannot replay that episode",
                row.protocol_version.as_deref().unwrap_or("(none)"),
                self.protocol.version
            )));
        }
        if row.checkpoints.is_empty() || row.checkpoints.iter().any(|c| c.config_key.is_empty()) {
            return Err(ApiError::NotFound(format!(
                "submission {submission}'s checkpoint is not held by this server (an imported result): it cannot \
                 be replayed here"
            )));
        }
        Ok(EpisodeKey {
            submission,
            threshold_index,
            episode,
        })
    }

    /// Where the replay of an episode stands; queues it when it has not been made (or failed) yet.
    pub async fn replay(&self, submission: i64, cost_threshold: f64, episode: u32) -> Result<ReplayState, ApiError> {
        let key = self.replayable(submission, cost_threshold, episode).await?;
        if let Some(replay) = self.stored_replay(key).await? {
            return Ok(ReplayState::Ready {
                replay: Box::new(replay),
                key,
            });
        }
        if let Some(reason) = lock(&self.renders.failed).get(&key) {
            return Ok(ReplayState::Failed(reason.clone()));
        }
        Ok(ReplayState::Queued {
            ahead: self.renders.enqueue(key),
        })
    }

    /// The animation of a replay made already.
    pub async fn replay_gif(&self, submission: i64, cost_threshold: f64, episode: u32) -> Result<Bytes, ApiError> {
        let key = self.replayable(submission, cost_threshold, episode).await?;
        let Some(replay) = self.stored_replay(key).await? else {
            return Err(ApiError::NotFound(format!(
                "episode {episode} of submission {submission} at cost threshold {cost_threshold} has not been \
                 replayed yet: GET its replay.json to queue it"
            )));
        };
        self.stored_gif(key, &replay).await
    }

    /// The stored animation of a replay whose record is `replay`, checked against the record's size.
    pub async fn stored_gif(&self, key: EpisodeKey, replay: &EpisodeReplay) -> Result<Bytes, ApiError> {
        let gif = self.store.get(&key.object("gif")).await?.bytes().await?;
        if gif.len() as u64 != replay.gif_bytes {
            return Err(ApiError::Internal(format!(
                "the stored animation of {key:?} has {} bytes; its record says {}",
                gif.len(),
                replay.gif_bytes
            )));
        }
        Ok(gif)
    }

    /// The stored record of a replay, if one was made (the animation is written first, so a record means both).
    async fn stored_replay(&self, key: EpisodeKey) -> Result<Option<EpisodeReplay>, ApiError> {
        match self.store.get(&key.object("json")).await {
            Ok(found) => {
                let bytes = found.bytes().await?;
                let replay = serde_json::from_slice(&bytes)
                    .map_err(|e| ApiError::Internal(format!("the stored replay record of {key:?}: {e}")))?;
                Ok(Some(replay))
            }
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    /// Whether scoring needs the machine: a submission waits or is being scored.
    async fn scoring_busy(&self) -> Result<bool, ApiError> {
        Ok(queue::depth(&self.db).await? > 0 || !queue::running(&self.db).await?.is_empty())
    }

    /// Replays `key`, checks it against the scored episode and stores it.
    async fn render(&self, key: EpisodeKey) -> Result<(), ApiError> {
        // A test-only delay (`DSRL_TEST_REPLAY_DELAY_MS`, debug builds): holds a replay in progress long enough for
        // a test to submit a job under it and see the replay give way.
        #[cfg(debug_assertions)]
        if let Some(ms) = std::env::var("DSRL_TEST_REPLAY_DELAY_MS")
            .ok()
            .and_then(|v| v.parse().ok())
        {
            tokio::time::sleep(Duration::from_millis(ms)).await;
        }
        let row = queue::get(&self.db, key.submission).await?;
        let task = self.task(&row.task)?;
        let threshold = task.cost_thresholds[key.threshold_index];
        let scored = queue::episodes(&self.db, key.submission)
            .await?
            .into_iter()
            .find(|e| e.cost_threshold == threshold && e.episode == key.episode)
            .ok_or_else(|| ApiError::NotFound(format!("no scored episode {key:?}")))?;
        let record = row
            .checkpoints
            .iter()
            .find(|c| c.cost_threshold.is_none() || c.cost_threshold == Some(threshold))
            .ok_or_else(|| ApiError::Internal(format!("no checkpoint for threshold {threshold}")))?;
        let (config, weights) = self.load(record).await?;
        let seeds = self
            .seeds
            .seeds(task.id.as_str(), key.threshold_index, row.episodes_per_threshold);
        let options = WatchOptions {
            stride: frame_stride(task.max_episode_steps),
            width: FRAME_SIDE,
            height: FRAME_SIDE,
        };
        // The policy runs where scoring ran it.
        let policy =
            crate::runner::prepare_policy(self, config, weights).map_err(|e| ApiError::Internal(e.to_string()))?;
        let recording = replay_episode(
            &self.simulators,
            task,
            policy.source(),
            threshold,
            &seeds,
            self.config.envs_per_session as usize,
            1,
            key.episode as usize,
            options,
        )
        .await?;
        let score = &recording.score;
        if (score.reward_return, score.cost_return, score.length)
            != (scored.reward_return, scored.cost_return, scored.length)
        {
            return Err(ApiError::Internal(format!(
                "the replay of {key:?} returned reward {} and cost {} in {} steps; the scored episode {} and {} in {}: \
                 the simulators or the policy runtime changed under an unchanged protocol",
                score.reward_return,
                score.cost_return,
                score.length,
                scored.reward_return,
                scored.cost_return,
                scored.length
            )));
        }
        let gif = tokio::task::spawn_blocking(move || encode_gif(&recording).map(|gif| (gif, recording)))
            .await
            .map_err(ApiError::internal)?;
        let (gif, recording) = gif?;
        let replay = EpisodeReplay {
            submission: key.submission,
            task: task.id.to_string(),
            cost_threshold: threshold,
            episode: key.episode,
            protocol_version: self.protocol.version.clone(),
            reward_return: recording.score.reward_return,
            cost_return: recording.score.cost_return,
            length: recording.score.length,
            rewards: recording.rewards,
            costs: recording.costs,
            frame_steps: recording.frame_steps,
            frame_width: options.width,
            frame_height: options.height,
            gif_bytes: gif.len() as u64,
            gif_sha256: hex::encode(<sha2::Sha256 as sha2::Digest>::digest(&gif)),
            rendered_by: crate::scorer_build(&self.simulators.workers()),
            rendered_at: dsrl_service::db::now_rfc3339(),
        };
        self.store.put(&key.object("gif"), PutPayload::from(gif)).await?;
        let json = serde_json::to_vec(&replay).map_err(ApiError::internal)?;
        self.store.put(&key.object("json"), PutPayload::from(json)).await?;
        Ok(())
    }
}

/// The recording's frames as a looping animated GIF (each frame quantized to its own 256 colours).
pub fn encode_gif(recording: &Recording) -> Result<Vec<u8>, ApiError> {
    let (width, height) = (recording.options.width, recording.options.height);
    let (w, h) = (
        u16::try_from(width).map_err(ApiError::internal)?,
        u16::try_from(height).map_err(ApiError::internal)?,
    );
    let mut out = Vec::new();
    {
        let mut encoder = gif::Encoder::new(&mut out, w, h, &[]).map_err(ApiError::internal)?;
        encoder.set_repeat(gif::Repeat::Infinite).map_err(ApiError::internal)?;
        for frame in &recording.frames {
            if frame.len() != width as usize * height as usize * 3 {
                return Err(ApiError::Internal(format!(
                    "a frame of {} bytes is not {width} x {height} RGB",
                    frame.len()
                )));
            }
            let mut image = gif::Frame::from_rgb_speed(w, h, frame, 10);
            image.delay = FRAME_DELAY_CS;
            encoder.write_frame(&image).map_err(ApiError::internal)?;
        }
    }
    Ok(out)
}

/// Starts the supervised renderer; it runs until the runtime stops.
pub fn spawn(leaderboard: Arc<Leaderboard>) {
    tokio::spawn(async move {
        loop {
            lock(&leaderboard.renders.state).running = true;
            let run = tokio::spawn(renderer(leaderboard.clone())).await;
            let message = match run {
                Err(e) if e.is_panic() => crate::supervision::panic_message(e.into_panic()),
                // Returned or cancelled: the runtime is shutting down.
                _ => return,
            };
            tracing::error!(panic = %message, "the renderer panicked; starting it again");
            leaderboard.renders.restarts.inc();
            {
                let mut state = lock(&leaderboard.renders.state);
                state.running = false;
                state.replaying = None;
                state.restarts += 1;
                state.last_error = Some(message);
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
    });
}

/// How often the renderer looks at the scoring queue while it waits or replays.
const POLL: Duration = Duration::from_secs(1);

async fn renderer(leaderboard: Arc<Leaderboard>) {
    let renders = &leaderboard.renders;
    loop {
        let next = lock(&renders.queue).front().copied();
        let Some(key) = next else {
            let _ = tokio::time::timeout(Duration::from_secs(5), renders.wake.notified()).await;
            continue;
        };
        if leaderboard.scoring_busy().await.unwrap_or(true) {
            tokio::time::sleep(POLL).await;
            continue;
        }
        lock(&renders.state).replaying = Some(format!("{}/{}/{}", key.submission, key.threshold_index, key.episode));
        let busy = async {
            loop {
                tokio::time::sleep(POLL).await;
                if leaderboard.scoring_busy().await.unwrap_or(true) {
                    return;
                }
            }
        };
        let outcome = tokio::select! {
            result = leaderboard.render(key) => Some(result),
            () = busy => None,
        };
        let mut state = lock(&renders.state);
        state.replaying = None;
        match outcome {
            // Scoring needs the machine: the replay stays first in the queue and starts again later.
            None => {
                state.yielded += 1;
                tracing::info!(?key, "a replay gave way to scoring");
                continue;
            }
            Some(Ok(())) => {
                renders.rendered.inc();
                state.rendered += 1;
                tracing::info!(?key, "replayed and stored an episode");
            }
            Some(Err(e)) => {
                renders.failures.inc();
                state.failed += 1;
                state.last_error = Some(e.to_string());
                tracing::warn!(?key, error = %e, "a replay failed");
                lock(&renders.failed).insert(key, e.to_string());
            }
        }
        drop(state);
        lock(&renders.queue).retain(|k| *k != key);
    }
}

#[cfg(test)]
mod tests {
    use dsrl_evaluation::evaluator::EpisodeScore;

    use super::*;

    #[test]
    fn strides_keep_at_most_the_frame_budget() {
        assert_eq!(frame_stride(200), 1);
        assert_eq!(frame_stride(201), 2);
        assert_eq!(frame_stride(1000), 5);
        assert!(1000u32.div_ceil(frame_stride(1000)) <= MAX_FRAMES);
        assert_eq!(frame_stride(0), 1);
    }

    #[test]
    fn a_recording_encodes_as_a_looping_gif_with_one_frame_each() {
        let (width, height) = (16u32, 8u32);
        let frames: Vec<Vec<u8>> = (0..3u8)
            .map(|k| (0..width * height * 3).map(|i| (i as u8).wrapping_mul(k + 1)).collect())
            .collect();
        let recording = Recording {
            score: EpisodeScore {
                seed: 0,
                reward_return: 0.0,
                cost_return: 0.0,
                length: 2,
            },
            rewards: vec![0.0; 2],
            costs: vec![0.0; 2],
            frames: frames.clone(),
            frame_steps: vec![1, 2],
            options: WatchOptions {
                stride: 1,
                width,
                height,
            },
        };
        let gif = encode_gif(&recording).unwrap();
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options.read_info(gif.as_slice()).unwrap();
        assert_eq!((decoder.width(), decoder.height()), (16, 8));
        let mut decoded = 0;
        while let Some(frame) = decoder.read_next_frame().unwrap() {
            assert_eq!(frame.delay, FRAME_DELAY_CS);
            decoded += 1;
        }
        assert_eq!(decoded, frames.len());
        let mut bad = recording.clone();
        bad.frames[1].pop();
        assert!(encode_gif(&bad).is_err());
    }
}
