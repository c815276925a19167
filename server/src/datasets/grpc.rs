//! The gRPC side: `dsrl.datasets.v1.DatasetService` over the same `Datasets` as REST, on the same port.
//! Transitions stream as Arrow IPC: the first chunk holds the schema, each later one a record batch of about
//! 1 MiB (well under gRPC's default 4 MiB message limit), the last one the end-of-stream marker.

use std::sync::Arc;

use arrow_ipc::writer::StreamWriter;
use dsrl_proto::datasets::v1 as pb;
use dsrl_proto::datasets::v1::dataset_service_server::DatasetService;
use futures::StreamExt;
use futures::stream::BoxStream;
use parquet::arrow::async_reader::ParquetRecordBatchStreamBuilder;
use tonic::{Request, Response, Status};

use crate::AppState;
use crate::datasets::db::VersionRecord;
use crate::datasets::objects;
use crate::error::ApiError;

/// Target size of one streamed record batch.
const STREAM_BATCH_BYTES: usize = 1 << 20;

pub struct DatasetGrpc {
    state: AppState,
}

impl DatasetGrpc {
    pub fn new(state: AppState) -> Self {
        DatasetGrpc { state }
    }

    /// Whether the request carries a token this server knows (its `authorization` metadata).
    async fn requester<T>(&self, request: &Request<T>) -> crate::datasets::service::Requester {
        let headers = request.metadata().clone().into_headers();
        crate::http::auth::requester(&self.state, &headers).await
    }
}

fn hosted(v: VersionRecord) -> pb::HostedVersion {
    pb::HostedVersion {
        version: v.version,
        tags: v.tags,
        byte_size: v.byte_size,
        episodes: v.episodes,
        transitions: v.transitions,
        observation_space: v.observation_space,
        created_at: v.created_at,
    }
}

fn task_message(task: &dsrl_suite::Task, versions: Vec<VersionRecord>) -> pb::Task {
    pb::Task {
        id: task.id.to_string(),
        family: task.family.as_str().to_owned(),
        simulator_env_id: task.simulator_env_id.clone(),
        max_episode_steps: task.max_episode_steps,
        obs_dim: task.obs_dim,
        obs_dim_paper: task.obs_dim_paper,
        act_dim: task.act_dim,
        min_episode_reward: task.min_episode_reward,
        max_episode_reward: task.max_episode_reward,
        min_episode_cost: task.min_episode_cost,
        max_episode_cost: task.max_episode_cost,
        cost_thresholds: task.cost_thresholds.clone(),
        paper_trajectories: task.paper_trajectories,
        paper_cost_cap: task.paper_cost_cap,
        dataset_file_prefix: task.dataset_file_prefix.clone(),
        versions: versions.into_iter().map(hosted).collect(),
    }
}

#[tonic::async_trait]
impl DatasetService for DatasetGrpc {
    async fn list_tasks(&self, _: Request<pb::ListTasksRequest>) -> Result<Response<pb::ListTasksResponse>, Status> {
        let tasks = self
            .state
            .datasets
            .catalog_with_versions()
            .await?
            .into_iter()
            .map(|(task, versions)| task_message(task, versions))
            .collect();
        Ok(Response::new(pb::ListTasksResponse { tasks }))
    }

    async fn list_versions(
        &self,
        request: Request<pb::ListVersionsRequest>,
    ) -> Result<Response<pb::ListVersionsResponse>, Status> {
        let (_, versions) = self.state.datasets.versions(&request.get_ref().task).await?;
        Ok(Response::new(pb::ListVersionsResponse {
            versions: versions.into_iter().map(hosted).collect(),
        }))
    }

    async fn get_manifest(
        &self,
        request: Request<pb::GetManifestRequest>,
    ) -> Result<Response<pb::GetManifestResponse>, Status> {
        let requester = self.requester(&request).await;
        let r = request.get_ref();
        let (_, record) = self
            .state
            .datasets
            .resolve_filtered(&r.task, &r.version, Some(&r.filter), requester)
            .await?;
        let manifest_json = self.state.datasets.manifest_json(&record).await?;
        Ok(Response::new(pb::GetManifestResponse {
            version: Some(hosted(record)),
            manifest_json,
        }))
    }

    type StreamTransitionsStream = BoxStream<'static, Result<pb::ArrowIpcChunk, Status>>;

    async fn stream_transitions(
        &self,
        request: Request<pb::StreamTransitionsRequest>,
    ) -> Result<Response<Self::StreamTransitionsStream>, Status> {
        let requester = self.requester(&request).await;
        let r = request.get_ref();
        let (task, record) = self
            .state
            .datasets
            .resolve_filtered(&r.task, &r.version, Some(&r.filter), requester)
            .await?;
        let serving = self.state.datasets.serving(&record);
        let obs_dim = if record.observation_space == "paper" {
            task.obs_dim_paper
        } else {
            task.obs_dim
        } as usize;
        let row_bytes = 4 * (2 * obs_dim + task.act_dim as usize + 4) + 2;
        let store = Arc::clone(self.state.datasets.store());
        let reader = objects::ParquetObject::new(
            store,
            objects::dataset_key(&record.task, &record.version),
            record.byte_size,
        );
        let batches = ParquetRecordBatchStreamBuilder::new(reader)
            .await
            .map_err(ApiError::internal)?
            .with_batch_size((STREAM_BATCH_BYTES / row_bytes).max(1))
            .build()
            .map_err(ApiError::internal)?;
        let schema = batches.schema().clone();
        let mut writer = StreamWriter::try_new(Vec::new(), &schema).map_err(ApiError::internal)?;
        let header = std::mem::take(writer.get_mut());
        let tail = futures::stream::unfold((batches, Some(writer)), |(mut batches, writer)| async move {
            let mut writer = writer?;
            let chunk = match batches.next().await {
                Some(Ok(batch)) => writer.write(&batch).map(|_| std::mem::take(writer.get_mut())),
                Some(Err(e)) => {
                    return Some((Err(Status::from(ApiError::internal(e))), (batches, None)));
                }
                None => {
                    let end = writer.finish().map(|_| std::mem::take(writer.get_mut()));
                    return Some((
                        end.map(|arrow_ipc| pb::ArrowIpcChunk { arrow_ipc })
                            .map_err(|e| ApiError::internal(e).into()),
                        (batches, None),
                    ));
                }
            };
            let item = chunk
                .map(|arrow_ipc| pb::ArrowIpcChunk { arrow_ipc })
                .map_err(|e| ApiError::internal(e).into());
            Some((item, (batches, Some(writer))))
        });
        let stream = futures::stream::once(async move { Ok(pb::ArrowIpcChunk { arrow_ipc: header }) })
            .chain(tail)
            .inspect(move |_| {
                let _ = &serving;
            });
        Ok(Response::new(stream.boxed()))
    }
}
