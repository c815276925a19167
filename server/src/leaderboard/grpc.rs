//! `dsrl.leaderboard.v1.LeaderboardService`: the same operations as the REST routes, over the same `Leaderboard`.

use bytes::Bytes;
use dsrl_proto::leaderboard::v1 as pb;
use dsrl_proto::leaderboard::v1::leaderboard_service_server::LeaderboardService;
use tonic::{Request, Response, Status};

use super::reference::{ReferenceRecord, TrainingData};
use super::{Board, SubmissionView, checkpoints, users};
use crate::AppState;
use crate::error::ApiError;

pub struct LeaderboardGrpc {
    state: AppState,
}

impl LeaderboardGrpc {
    pub fn new(state: AppState) -> Self {
        LeaderboardGrpc { state }
    }

    async fn user<T>(&self, request: &Request<T>) -> Result<users::User, ApiError> {
        let headers = request.metadata().clone().into_headers();
        users::authenticate(&self.state.leaderboard.db, &headers).await
    }
}

fn submission(view: SubmissionView, with_episodes: bool) -> pb::Submission {
    pb::Submission {
        id: view.id,
        task: view.task,
        name: view.name,
        user: view.user,
        state: view.state,
        reason: view.reason,
        attempts: view.attempts,
        checkpoint_sha256: view.checkpoint_sha256,
        created_at: view.created_at,
        started_at: view.started_at,
        finished_at: view.finished_at,
        episodes_per_threshold: view.episodes_per_threshold,
        normalized_reward: view.normalized_reward,
        normalized_cost: view.normalized_cost,
        safe: view.safe,
        thresholds: view
            .thresholds
            .into_iter()
            .map(|t| pb::ThresholdResult {
                cost_threshold: t.cost_threshold,
                episodes: t.episodes as u32,
                mean_reward_return: t.mean_reward_return,
                mean_cost_return: t.mean_cost_return,
                normalized_reward: t.normalized_reward,
                normalized_cost: t.normalized_cost,
                safe: t.safe,
            })
            .collect(),
        episodes: if with_episodes {
            view.episodes
                .into_iter()
                .map(|e| pb::Episode {
                    cost_threshold: e.cost_threshold,
                    episode: e.episode,
                    reward_return: e.reward_return,
                    cost_return: e.cost_return,
                    length: e.length,
                })
                .collect()
        } else {
            Vec::new()
        },
        protocol_version: view.protocol_version,
        dataset_version: view.dataset_version,
        reference: view.reference.map(reference),
        scored_by: view.scored_by,
    }
}

fn reference(r: ReferenceRecord) -> pb::ReferenceRecord {
    pb::ReferenceRecord {
        method: r.method,
        seed: r.seed,
        steps: r.training.steps,
        batch_size: r.training.batch_size as u32,
        models: r.training.models,
        training_seconds: r.training.seconds,
        training_cpu_seconds: r.training.cpu_seconds,
        osrl_steps: r.training.osrl_steps,
        osrl_batch_size: r.training.osrl_batch_size as u32,
        code_commit: r.code_commit,
        dataset: match r.dataset {
            TrainingData::Starter => "starter",
            TrainingData::FullBuild => "full_build",
        }
        .to_owned(),
    }
}

fn interval(i: dsrl_scoring::leaderboard::Interval) -> pb::Interval {
    pb::Interval {
        estimate: i.estimate,
        low: i.low,
        high: i.high,
        confidence: i.confidence,
        resamples: i.resamples,
        seed: i.seed,
    }
}

fn board(board: Board) -> pb::Leaderboard {
    pb::Leaderboard {
        tasks: board
            .tasks
            .into_iter()
            .map(|t| pb::TaskTable {
                task: t.task,
                family: t.family.to_owned(),
                cost_thresholds: t.cost_thresholds,
                entries: t
                    .entries
                    .into_iter()
                    .map(|e| pb::TaskEntry {
                        rank: e.rank as u32,
                        submission: e.submission,
                        user: e.user,
                        name: e.name,
                        normalized_reward: e.normalized_reward,
                        normalized_cost: e.normalized_cost,
                        safe: e.safe,
                        protocol_version: e.protocol_version,
                        dataset_version: e.dataset_version,
                        reference: e.reference.map(reference),
                        normalized_reward_interval: Some(interval(e.normalized_reward_interval)),
                        normalized_cost_interval: Some(interval(e.normalized_cost_interval)),
                        scored_by: e.scored_by,
                        interval_covers: e.interval_covers,
                        training_seeds: e
                            .training_seeds
                            .into_iter()
                            .map(|s| pb::SeedRun {
                                submission: s.submission,
                                seed: s.seed,
                                normalized_reward: s.normalized_reward,
                                normalized_cost: s.normalized_cost,
                                safe: s.safe,
                            })
                            .collect(),
                    })
                    .collect(),
                earlier_protocol_entries: t.earlier_protocol_entries as u32,
                paper: t
                    .paper
                    .into_iter()
                    .map(|p| pb::PaperRow {
                        method: p.method,
                        normalized_reward: p.normalized_reward,
                        normalized_cost: p.normalized_cost,
                        safe: p.safe,
                    })
                    .collect(),
                published: t
                    .published
                    .into_iter()
                    .map(|p| pb::PublishedRow {
                        method: p.method,
                        normalized_reward: p.normalized_reward,
                        normalized_cost: p.normalized_cost,
                        safe: p.safe,
                        citation: p.citation,
                        protocol: p.protocol,
                    })
                    .collect(),
                agreement: t
                    .agreement
                    .into_iter()
                    .map(|a| pb::Agreement {
                        task: a.task,
                        method: a.method,
                        seeds: a.seeds as u32,
                        normalized_reward: a.normalized_reward,
                        normalized_cost: a.normalized_cost,
                        paper_normalized_reward: a.paper_normalized_reward,
                        paper_normalized_cost: a.paper_normalized_cost,
                        safe: a.safe,
                        paper_safe: a.paper_safe,
                        verdict_agrees: a.verdict_agrees,
                    })
                    .collect(),
            })
            .collect(),
        families: board
            .families
            .into_iter()
            .map(|f| {
                let entry = |e: crate::leaderboard::FamilyEntry| pb::FamilyEntry {
                    rank: e.rank.map(|r| r as u32),
                    user: e.user,
                    name: e.name,
                    tasks: e.tasks as u32,
                    safe_tasks: e.safe_tasks as u32,
                    normalized_reward: Some(interval(e.normalized_reward)),
                    normalized_cost: Some(interval(e.normalized_cost)),
                    reference: e.reference,
                    training_seeds: e.training_seeds as u32,
                };
                pb::FamilyTable {
                    family: f.family.to_owned(),
                    entries: f.entries.into_iter().map(entry).collect(),
                    tasks: f.tasks as u32,
                    partial: f.partial.into_iter().map(entry).collect(),
                }
            })
            .collect(),
        protocol: Some(pb::Protocol {
            version: board.protocol.version,
            rules: board.protocol.rules,
            tasks: board.protocol.tasks as u32,
            catalog_sha256: board.protocol.catalog_sha256,
            simulator_pins_sha256: board.protocol.simulator_pins_sha256,
            episodes_per_threshold: board.protocol.episodes_per_threshold,
            envs_per_session: board.protocol.envs_per_session,
            held_seeds: board.protocol.held_seeds,
            scorer_revision: board.protocol.scorer_revision,
        }),
        paper_label: board.paper_label.to_owned(),
        agreement: board.agreement.into_iter().map(agreement_summary).collect(),
        agreement_by_method: board.agreement_by_method.into_iter().map(agreement_summary).collect(),
    }
}

fn agreement_summary(a: dsrl_scoring::reference::AgreementSummary) -> pb::AgreementSummary {
    pb::AgreementSummary {
        scope: a.scope,
        cells: a.cells as u32,
        agreeing: a.agreeing as u32,
        share: a.share,
        mean_abs_reward_difference: a.mean_abs_reward_difference,
        mean_abs_cost_difference: a.mean_abs_cost_difference,
        chance_share: a.chance_share,
        all_unsafe_share: a.all_unsafe_share,
        bc_safe_rule_share: a.bc_safe_rule_share,
    }
}

#[tonic::async_trait]
impl LeaderboardService for LeaderboardGrpc {
    async fn submit(&self, request: Request<pb::SubmitRequest>) -> Result<Response<pb::Submission>, Status> {
        let user = self.user(&request).await?;
        let request = request.into_inner();
        let mut files = Vec::with_capacity(request.files.len());
        for file in request.files {
            // The message size limit bounds the whole request; each file still has its own limit.
            if let Some(limit) = checkpoints::file_limit(&file.path)
                && file.content.len() as u64 > limit
            {
                return Err(ApiError::UploadTooLarge { limit }.into());
            }
            files.push((file.path, Bytes::from(file.content)));
        }
        let view = self
            .state
            .leaderboard
            .submit(&user, &request.task, &request.name, files)
            .await?;
        Ok(Response::new(submission(view, false)))
    }

    async fn get_submission(
        &self,
        request: Request<pb::GetSubmissionRequest>,
    ) -> Result<Response<pb::Submission>, Status> {
        let request = request.into_inner();
        if request.wait_seconds > 0 {
            self.state
                .leaderboard
                .wait_until_ended(request.id, request.wait_seconds)
                .await?;
        }
        let view = self.state.leaderboard.view(request.id).await?;
        Ok(Response::new(submission(view, request.episodes)))
    }

    async fn cancel_submission(
        &self,
        request: Request<pb::CancelSubmissionRequest>,
    ) -> Result<Response<pb::Submission>, Status> {
        let headers = request.metadata().clone().into_headers();
        let by = if self.state.auth.check(&headers).is_ok() {
            crate::leaderboard::queue::Canceller::Admin
        } else {
            crate::leaderboard::queue::Canceller::User(self.user(&request).await?.id)
        };
        let view = self.state.leaderboard.cancel(by, request.into_inner().id).await?;
        Ok(Response::new(submission(view, false)))
    }

    async fn get_episode_replay(
        &self,
        request: Request<pb::GetEpisodeReplayRequest>,
    ) -> Result<Response<pb::EpisodeReplay>, Status> {
        use crate::leaderboard::renders::ReplayState;
        let r = request.into_inner();
        let leaderboard = &self.state.leaderboard;
        let replay = match leaderboard.replay(r.submission, r.cost_threshold, r.episode).await? {
            ReplayState::Queued { ahead } => pb::EpisodeReplay {
                state: "queued".into(),
                ahead: u32::try_from(ahead).unwrap_or(u32::MAX),
                ..Default::default()
            },
            ReplayState::Failed(reason) => {
                return Err(ApiError::Internal(format!("the replay failed: {reason}")).into());
            }
            ReplayState::Ready { replay, key } => {
                let gif = leaderboard.stored_gif(key, &replay).await?;
                pb::EpisodeReplay {
                    state: "ready".into(),
                    ahead: 0,
                    task: replay.task,
                    reward_return: replay.reward_return,
                    cost_return: replay.cost_return,
                    length: replay.length,
                    rewards: replay.rewards,
                    costs: replay.costs,
                    frame_steps: replay.frame_steps,
                    frame_width: replay.frame_width,
                    frame_height: replay.frame_height,
                    gif: gif.to_vec(),
                    gif_sha256: replay.gif_sha256,
                    protocol_version: replay.protocol_version,
                    rendered_by: replay.rendered_by,
                    rendered_at: replay.rendered_at,
                }
            }
        };
        Ok(Response::new(replay))
    }

    async fn get_leaderboard(
        &self,
        request: Request<pb::GetLeaderboardRequest>,
    ) -> Result<Response<pb::Leaderboard>, Status> {
        let task = request.into_inner().task;
        Ok(Response::new(board(
            self.state.leaderboard.board(task.as_deref()).await?,
        )))
    }
}
