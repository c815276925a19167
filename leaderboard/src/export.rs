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
    /// `entry` (ranked, scored here), `paper` (the paper's self-reported row, unranked), or `published` (a row a
    /// method beyond the paper publishes, unranked).
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
    /// The build that scored the entry (task rows), where recorded.
    pub scored_by: Option<String>,
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
                scored_by: e.scored_by.clone(),
                finished_at: e.finished_at.clone(),
            });
        }
        // The self-reported rows: the paper's, then those of methods beyond it (each unranked, without intervals).
        let paper = t
            .paper
            .iter()
            .map(|p| ("paper", &p.method, p.normalized_reward, p.normalized_cost, p.safe));
        let published = t
            .published
            .iter()
            .map(|p| ("published", &p.method, p.normalized_reward, p.normalized_cost, p.safe));
        for (kind, method, normalized_reward, normalized_cost, safe) in paper.chain(published) {
            rows.push(BoardRow {
                protocol_version: version.clone(),
                scope: "task",
                table: t.task.clone(),
                kind,
                rank: None,
                user: kind.into(),
                name: method.clone(),
                reference: false,
                normalized_reward,
                reward_low: None,
                reward_high: None,
                normalized_cost,
                cost_low: None,
                cost_high: None,
                safe,
                author_submissions_to_task: None,
                tasks: None,
                submission: None,
                dataset_version: None,
                scored_by: None,
                finished_at: None,
            });
        }
    }
    for f in &board.families {
        // Partial entries (scored on some of the family's tasks) follow the ranked ones, without a rank.
        for e in f.entries.iter().chain(&f.partial) {
            rows.push(BoardRow {
                protocol_version: version.clone(),
                scope: "family",
                table: f.family.to_owned(),
                kind: if e.rank.is_some() { "entry" } else { "partial entry" },
                rank: e.rank.map(|r| r as u64),
                user: e.user.clone(),
                name: e.name.clone(),
                reference: e.reference,
                normalized_reward: e.normalized_reward.estimate,
                reward_low: Some(e.normalized_reward.low),
                reward_high: Some(e.normalized_reward.high),
                normalized_cost: e.normalized_cost.estimate,
                cost_low: Some(e.normalized_cost.low),
                cost_high: Some(e.normalized_cost.high),
                safe: dsrl_suite::score::is_safe(e.normalized_cost.estimate),
                author_submissions_to_task: None,
                tasks: Some(e.tasks as u64),
                submission: None,
                dataset_version: None,
                scored_by: None,
                finished_at: None,
            });
        }
    }
    rows
}

/// The exported board's columns, in `BoardRow`'s field order (a test holds the two together).
pub const BOARD_COLUMNS: &[&str] = &[
    "protocol_version",
    "scope",
    "table",
    "kind",
    "rank",
    "user",
    "name",
    "reference",
    "normalized_reward",
    "reward_low",
    "reward_high",
    "normalized_cost",
    "cost_low",
    "cost_high",
    "safe",
    "author_submissions_to_task",
    "tasks",
    "submission",
    "dataset_version",
    "scored_by",
    "finished_at",
];

/// A submission's episode columns, in `EpisodeRow`'s field order.
pub const EPISODE_COLUMNS: &[&str] = &["cost_threshold", "episode", "reward_return", "cost_return", "length"];

/// The rows as CSV: the header line always (an empty table is a header alone, not an empty file), then one line
/// per row with its fields in `columns`' order. Text cells a spreadsheet would read as a formula (starting with
/// `=`, `+`, `-`, `@`, a tab or CR) get a leading `'`, OWASP's rule; numbers are written as they are, so a
/// negative score stays a number.
pub fn csv(rows: &[impl Serialize], columns: &[&str]) -> Result<Vec<u8>, ApiError> {
    let mut writer = csv::Writer::from_writer(Vec::new());
    writer.write_record(columns).map_err(ApiError::internal)?;
    for row in rows {
        let value = serde_json::to_value(row).map_err(ApiError::internal)?;
        let record: Vec<String> = columns
            .iter()
            .map(|c| match &value[*c] {
                serde_json::Value::Null => String::new(),
                serde_json::Value::String(text) => neutralized(text),
                other => other.to_string(),
            })
            .collect();
        writer.write_record(&record).map_err(ApiError::internal)?;
    }
    writer.into_inner().map_err(ApiError::internal)
}

/// A text cell as a spreadsheet may open it: one that starts like a formula is prefixed with `'`.
pub fn neutralized(text: &str) -> String {
    if text.starts_with(['=', '+', '-', '@', '\t', '\r']) {
        format!("'{text}")
    } else {
        text.to_owned()
    }
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
        ("scored_by", DataType::Utf8, true, text(|r| r.scored_by.clone())),
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
    csv(episodes, EPISODE_COLUMNS)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The header `csv::Writer` derives from a row's serde fields.
    fn serde_header(row: &impl Serialize) -> Vec<String> {
        let mut writer = csv::Writer::from_writer(Vec::new());
        writer.serialize(row).unwrap();
        let text = String::from_utf8(writer.into_inner().unwrap()).unwrap();
        text.lines().next().unwrap().split(',').map(str::to_owned).collect()
    }

    fn board_row(name: &str, dataset_version: Option<&str>) -> BoardRow {
        BoardRow {
            protocol_version: "p1".into(),
            scope: "task",
            table: "OfflineBallRun-v0".into(),
            kind: "entry",
            rank: Some(1),
            user: "alice".into(),
            name: name.into(),
            reference: false,
            normalized_reward: -0.25,
            reward_low: Some(-0.5),
            reward_high: None,
            normalized_cost: 0.5,
            cost_low: Some(0.25),
            cost_high: Some(0.75),
            safe: true,
            author_submissions_to_task: Some(2),
            tasks: None,
            submission: Some(7),
            dataset_version: dataset_version.map(str::to_owned),
            scored_by: Some("dsrl-leaderboard 0.1.0 (git abc)".into()),
            finished_at: None,
        }
    }

    #[test]
    fn the_column_lists_are_the_rows_fields_in_order() {
        assert_eq!(serde_header(&board_row("a", None)), BOARD_COLUMNS);
        let episode = EpisodeRow {
            cost_threshold: 10.0,
            episode: 0,
            reward_return: 1.0,
            cost_return: 2.0,
            length: 3,
        };
        assert_eq!(serde_header(&episode), EPISODE_COLUMNS);
    }

    #[test]
    fn formulas_in_text_cells_are_neutralized_and_numbers_kept() {
        let rows = [board_row("=HYPERLINK(\"http://evil.example\")", Some("@SUM(A1)"))];
        let text = String::from_utf8(csv(&rows, BOARD_COLUMNS).unwrap()).unwrap();
        let mut reader = csv::Reader::from_reader(text.as_bytes());
        let header = reader.headers().unwrap().clone();
        let row = reader.records().next().unwrap().unwrap();
        let cell = |name: &str| row[header.iter().position(|h| h == name).unwrap()].to_owned();
        assert_eq!(cell("name"), "'=HYPERLINK(\"http://evil.example\")");
        assert_eq!(cell("dataset_version"), "'@SUM(A1)");
        assert_eq!(cell("normalized_reward"), "-0.25");
        assert_eq!(cell("reward_low"), "-0.5");
        assert_eq!(cell("reward_high"), "");
        assert_eq!(cell("safe"), "true");
        for (text, want) in [
            ("-x", "'-x"),
            ("+x", "'+x"),
            ("\tx", "'\tx"),
            ("\rx", "'\rx"),
            ("x=1", "x=1"),
        ] {
            assert_eq!(neutralized(text), want);
        }
    }

    #[test]
    fn an_empty_table_is_its_header() {
        let text = String::from_utf8(episodes_csv(&[]).unwrap()).unwrap();
        assert_eq!(text, format!("{}\n", EPISODE_COLUMNS.join(",")));
    }
}
