//! `dsrl.leaderboard.v1.LeaderboardService`: the same operations as the REST routes, over the same `Leaderboard`.

use bytes::Bytes;
use dsrl_proto::leaderboard::v1 as pb;
use dsrl_proto::leaderboard::v1::leaderboard_service_server::LeaderboardService;
use tonic::{Request, Response, Status};

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
    }
}

fn interval(i: dsrl_suite::leaderboard::Interval) -> pb::Interval {
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
                    })
                    .collect(),
            })
            .collect(),
        families: board
            .families
            .into_iter()
            .map(|f| pb::FamilyTable {
                family: f.family.to_owned(),
                entries: f
                    .entries
                    .into_iter()
                    .map(|e| pb::FamilyEntry {
                        rank: e.rank as u32,
                        user: e.user,
                        name: e.name,
                        tasks: e.tasks as u32,
                        safe_tasks: e.safe_tasks as u32,
                        normalized_reward: Some(interval(e.normalized_reward)),
                        normalized_cost: Some(interval(e.normalized_cost)),
                    })
                    .collect(),
            })
            .collect(),
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
        let view = self.state.leaderboard.view(request.id).await?;
        Ok(Response::new(submission(view, request.episodes)))
    }

    async fn cancel_submission(
        &self,
        request: Request<pb::CancelSubmissionRequest>,
    ) -> Result<Response<pb::Submission>, Status> {
        let user = self.user(&request).await?;
        let view = self.state.leaderboard.cancel(&user, request.into_inner().id).await?;
        Ok(Response::new(submission(view, false)))
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
