//! The board as data: every row of the tables (each task's ranked entries and the paper's rows, each family's
//! aggregate) as one flat table with the protocol version, written as CSV or Parquet; and a submission's episodes as
//! CSV. The columns are `BoardRow`'s fields, in order.

use std::sync::Arc;

use arrow_array::{ArrayRef, BooleanArray, Float64Array, Int64Array, RecordBatch, StringArray, UInt64Array};
use arrow_schema::{DataType, Field, Schema};
use serde::Serialize;

use super::Board;
use super::queue::EpisodeRow;
use dsrl_service::error::ApiError;

/// One row of the exported board.
#[derive(Debug, Clone, Serialize)]
pub struct BoardRow {
    pub protocol_version: String,
    /// `task` or `family`.
    pub scope: &'static str,
    /// The task id, or the family.
    pub table: String,
    /// `entry` (ranked, scored here), or `paper` (the paper's self-reported row, unranked).
    pub kind: &'static str,
    pub rank: Option<u64>,
    pub user: String,
    pub name: String,
    pub reference: bool,
    pub normalized_reward: f64,
    pub reward_low: Option<f64>,
    pub reward_high: Option<f64>,
    pub normalized_cost: f64,
    pub cost_low: Option<f64>,
    pub cost_high: Option<f64>,
    pub safe: bool,
    /// Submissions the author made to the task (task rows); tasks the entry was scored on (family rows).
    pub author_submissions_to_task: Option<u64>,
    pub tasks: Option<u64>,
    pub submission: Option<i64>,
    pub dataset_version: Option<String>,
    pub finished_at: Option<String>,
}

pub fn rows(board: &Board) -> Vec<BoardRow> {
    let version = board.protocol.version.clone();
    let mut rows = Vec::new();
    for t in &board.tasks {
        for e in &t.entries {
            rows.push(BoardRow {
                protocol_version: version.clone(),
                scope: "task",
                table: t.task.clone(),
                kind: "entry",
                rank: Some(e.rank as u64),
                user: e.user.clone(),
                name: e.name.clone(),
                reference: e.reference.is_some(),
                normalized_reward: e.normalized_reward,
                reward_low: Some(e.normalized_reward_interval.low),
                reward_high: Some(e.normalized_reward_interval.high),
                normalized_cost: e.normalized_cost,
                cost_low: Some(e.normalized_cost_interval.low),
                cost_high: Some(e.normalized_cost_interval.high),
                safe: e.safe,
                author_submissions_to_task: Some(u64::from(e.author_submissions_to_task)),
                tasks: None,
                submission: Some(e.submission),
                dataset_version: e.dataset_version.clone(),
                finished_at: e.finished_at.clone(),
            });
        }
        for p in &t.paper {
            rows.push(BoardRow {
                protocol_version: version.clone(),
                scope: "task",
                table: t.task.clone(),
                kind: "paper",
                rank: None,
                user: "paper".into(),
                name: p.method.clone(),
                reference: false,
                normalized_reward: p.normalized_reward,
                reward_low: None,
                reward_high: None,
                normalized_cost: p.normalized_cost,
                cost_low: None,
                cost_high: None,
                safe: p.safe,
                author_submissions_to_task: None,
                tasks: None,
                submission: None,
                dataset_version: None,
                finished_at: None,
            });
        }
    }
    for f in &board.families {
        for e in &f.entries {
            rows.push(BoardRow {
                protocol_version: version.clone(),
                scope: "family",
                table: f.family.to_owned(),
                kind: "entry",
                rank: Some(e.rank as u64),
                user: e.user.clone(),
                name: e.name.clone(),
                reference: e.reference,
                normalized_reward: e.normalized_reward.estimate,
                reward_low: Some(e.normalized_reward.low),
                reward_high: Some(e.normalized_reward.high),
                normalized_cost: e.normalized_cost.estimate,
                cost_low: Some(e.normalized_cost.low),
                cost_high: Some(e.normalized_cost.high),
                safe: e.normalized_cost.estimate <= 1.0,
                author_submissions_to_task: None,
                tasks: Some(e.tasks as u64),
                submission: None,
                dataset_version: None,
                finished_at: None,
            });
        }
    }
    rows
}

/// The rows as CSV with a header line.
pub fn csv(rows: &[impl Serialize]) -> Result<Vec<u8>, ApiError> {
    let mut writer = csv::Writer::from_writer(Vec::new());
    for row in rows {
        writer.serialize(row).map_err(ApiError::internal)?;
    }
    writer.into_inner().map_err(ApiError::internal)
}

/// The rows as one Parquet file (zstd).
pub fn parquet(rows: &[BoardRow]) -> Result<Vec<u8>, ApiError> {
    let text = |f: fn(&BoardRow) -> Option<String>| {
        Arc::new(StringArray::from(rows.iter().map(f).collect::<Vec<_>>())) as ArrayRef
    };
    let float = |f: fn(&BoardRow) -> Option<f64>| {
        Arc::new(Float64Array::from(rows.iter().map(f).collect::<Vec<_>>())) as ArrayRef
    };
    let unsigned = |f: fn(&BoardRow) -> Option<u64>| {
        Arc::new(UInt64Array::from(rows.iter().map(f).collect::<Vec<_>>())) as ArrayRef
    };
    let columns: Vec<(&str, DataType, bool, ArrayRef)> = vec![
        (
            "protocol_version",
            DataType::Utf8,
            false,
            text(|r| Some(r.protocol_version.clone())),
        ),
        ("scope", DataType::Utf8, false, text(|r| Some(r.scope.to_owned()))),
        ("table", DataType::Utf8, false, text(|r| Some(r.table.clone()))),
        ("kind", DataType::Utf8, false, text(|r| Some(r.kind.to_owned()))),
        ("rank", DataType::UInt64, true, unsigned(|r| r.rank)),
        ("user", DataType::Utf8, false, text(|r| Some(r.user.clone()))),
        ("name", DataType::Utf8, false, text(|r| Some(r.name.clone()))),
        (
            "reference",
            DataType::Boolean,
            false,
            Arc::new(BooleanArray::from(rows.iter().map(|r| r.reference).collect::<Vec<_>>())),
        ),
        (
            "normalized_reward",
            DataType::Float64,
            false,
            float(|r| Some(r.normalized_reward)),
        ),
        ("reward_low", DataType::Float64, true, float(|r| r.reward_low)),
        ("reward_high", DataType::Float64, true, float(|r| r.reward_high)),
        (
            "normalized_cost",
            DataType::Float64,
            false,
            float(|r| Some(r.normalized_cost)),
        ),
        ("cost_low", DataType::Float64, true, float(|r| r.cost_low)),
        ("cost_high", DataType::Float64, true, float(|r| r.cost_high)),
        (
            "safe",
            DataType::Boolean,
            false,
            Arc::new(BooleanArray::from(rows.iter().map(|r| r.safe).collect::<Vec<_>>())),
        ),
        (
            "author_submissions_to_task",
            DataType::UInt64,
            true,
            unsigned(|r| r.author_submissions_to_task),
        ),
        ("tasks", DataType::UInt64, true, unsigned(|r| r.tasks)),
        (
            "submission",
            DataType::Int64,
            true,
            Arc::new(Int64Array::from(rows.iter().map(|r| r.submission).collect::<Vec<_>>())),
        ),
        (
            "dataset_version",
            DataType::Utf8,
            true,
            text(|r| r.dataset_version.clone()),
        ),
        ("finished_at", DataType::Utf8, true, text(|r| r.finished_at.clone())),
    ];
    let schema = Arc::new(Schema::new(
        columns
            .iter()
            .map(|(name, kind, nullable, _)| Field::new(*name, kind.clone(), *nullable))
            .collect::<Vec<_>>(),
    ));
    let batch =
        RecordBatch::try_new(schema.clone(), columns.into_iter().map(|c| c.3).collect()).map_err(ApiError::internal)?;
    let props = parquet::file::properties::WriterProperties::builder()
        .set_compression(parquet::basic::Compression::ZSTD(Default::default()))
        .build();
    let mut writer =
        parquet::arrow::ArrowWriter::try_new(Vec::new(), schema, Some(props)).map_err(ApiError::internal)?;
    writer.write(&batch).map_err(ApiError::internal)?;
    writer.into_inner().map_err(ApiError::internal)
}

/// A submission's episodes as CSV: cost_threshold, episode, reward_return, cost_return, length.
pub fn episodes_csv(episodes: &[EpisodeRow]) -> Result<Vec<u8>, ApiError> {
    csv(episodes)
}
