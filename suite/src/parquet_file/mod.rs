//! The dataset's Parquet layout and its reader and writer.
//!
//! One row per transition with DSRL's key names, so pyarrow/pandas users need no custom code:
//! `episode` (u32), `step` (u32), `observations`, `next_observations`, `actions` (FixedSizeList<f32, dim>),
//! `rewards`, `costs` (f32), `terminals`, `timeouts` (bool). Float columns use BYTE_STREAM_SPLIT + zstd, the
//! counters delta encoding; every row group holds whole episodes, so one episode is one row-group read.
//! The writer is deterministic: the same rows always give the same bytes, hence the same version id.
//!
//! **Compact form** (committed starter files): the same rows, stored smaller in two ways. `next_observations` is
//! null wherever it equals the next row's `observations` in the same episode, which is every step but an episode's
//! last in collected data; Parquet stores nothing for a null list, which halves the file. And `observations` is a
//! struct of one float32 field per feature (`"0"`, `"1"`, ...), so Parquet keeps each feature in its own column:
//! a feature's values over time compress far better than the row-major mix of all features (13-18% less on
//! Safety-Gymnasium and MetaDrive starters, measured on the committed files). The reader takes either form of
//! `observations` and fills the nulls back in, so ingesting a compact file gives exactly the canonical rows, hence
//! the same version id. Starters committed before the struct form keep the list form and read as before.

use std::io::Write;
use std::sync::Arc;

use arrow_array::cast::AsArray;
use arrow_array::types::{Float32Type, Float64Type, Int8Type, Int16Type, Int32Type, Int64Type};
use arrow_array::types::{UInt8Type, UInt16Type, UInt32Type, UInt64Type};
use arrow_array::{
    Array, ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, RecordBatch, StructArray, UInt32Array,
};
use arrow_schema::{DataType, Field, FieldRef, Schema, SchemaRef};
use parquet::arrow::arrow_reader::{ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder};
use parquet::arrow::arrow_writer::{ArrowColumnChunk, ArrowColumnWriter, ArrowRowGroupWriterFactory, compute_leaves};
use parquet::arrow::{ArrowSchemaConverter, ArrowWriter, ProjectionMask};
use parquet::basic::{Compression, Encoding, Type as PhysicalType, ZstdLevel};
use parquet::errors::ParquetError;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::file::writer::SerializedFileWriter;

use crate::transitions::TransitionChunk;
use crate::validate::{Numbering, ValidationError, flags_from_numbers};

mod read_ahead;
mod relabelled_copy;
pub use relabelled_copy::RelabelSource;

pub const EPISODE: &str = "episode";
pub const STEP: &str = "step";
pub const OBSERVATIONS: &str = "observations";
pub const NEXT_OBSERVATIONS: &str = "next_observations";
pub const ACTIONS: &str = "actions";
pub const REWARDS: &str = "rewards";
pub const COSTS: &str = "costs";
pub const TERMINALS: &str = "terminals";
pub const TIMEOUTS: &str = "timeouts";

/// The seven keys of a DSRL dataset, in DSRL's order.
pub const DSRL_KEYS: [&str; 7] = [
    OBSERVATIONS,
    NEXT_OBSERVATIONS,
    ACTIONS,
    REWARDS,
    COSTS,
    TERMINALS,
    TIMEOUTS,
];

/// Target uncompressed size of one row group; episodes are never split, so groups can be larger.
const ROW_GROUP_TARGET_BYTES: usize = 64 << 20;
/// Target uncompressed size of one batch when reading.
const READ_BATCH_TARGET_BYTES: usize = 16 << 20;

/// The Arrow schema of a dataset with these widths.
pub fn dataset_schema(obs_dim: usize, act_dim: usize) -> SchemaRef {
    schema_of(obs_dim, act_dim, false)
}

/// The schema; in the compact form `next_observations` is nullable and `observations` a struct of features.
fn schema_of(obs_dim: usize, act_dim: usize, compact: bool) -> SchemaRef {
    let list =
        |dim: usize| DataType::FixedSizeList(Arc::new(Field::new_list_field(DataType::Float32, false)), dim as i32);
    let observations = if compact {
        DataType::Struct(feature_fields(obs_dim))
    } else {
        list(obs_dim)
    };
    Arc::new(Schema::new(vec![
        Field::new(EPISODE, DataType::UInt32, false),
        Field::new(STEP, DataType::UInt32, false),
        Field::new(OBSERVATIONS, observations, false),
        Field::new(NEXT_OBSERVATIONS, list(obs_dim), compact),
        Field::new(ACTIONS, list(act_dim), false),
        Field::new(REWARDS, DataType::Float32, false),
        Field::new(COSTS, DataType::Float32, false),
        Field::new(TERMINALS, DataType::Boolean, false),
        Field::new(TIMEOUTS, DataType::Boolean, false),
    ]))
}

/// The compact form's observation fields: one float32 per feature, named by its index.
fn feature_fields(dim: usize) -> arrow_schema::Fields {
    (0..dim)
        .map(|j| Field::new(j.to_string(), DataType::Float32, false))
        .collect()
}

fn row_bytes(obs_dim: usize, act_dim: usize) -> usize {
    4 * (2 * obs_dim + act_dim) + 4 * 4 + 2
}

/// Rows a row group aims for: [`ROW_GROUP_TARGET_BYTES`] of rows (never fewer than one episode, see
/// [`row_group_rows`]).
pub(crate) fn target_rows(obs_dim: usize, act_dim: usize) -> usize {
    (ROW_GROUP_TARGET_BYTES / row_bytes(obs_dim, act_dim)).max(1)
}

/// The row groups, by their rows, that the writer cuts from episodes of these lengths: a group ends at the last
/// episode end within `target_rows`, or after its first episode when that alone is longer.
pub fn row_group_rows(lengths: impl IntoIterator<Item = usize>, target_rows: usize) -> Vec<usize> {
    let mut groups = Vec::new();
    let mut open = 0;
    for length in lengths {
        if open > 0 && open + length > target_rows {
            groups.push(open);
            open = 0;
        }
        open += length;
        if open >= target_rows {
            groups.push(open);
            open = 0;
        }
    }
    if open > 0 {
        groups.push(open);
    }
    groups
}

/// The Parquet file writer of the layout (its properties fix every page's bytes), the factory of a row group's
/// column writers, and the Arrow schema.
fn file_writer<W: Write + Send>(
    out: W,
    obs_dim: usize,
    act_dim: usize,
    metadata: Vec<(String, String)>,
    compact: bool,
) -> Result<(SerializedFileWriter<W>, ArrowRowGroupWriterFactory, SchemaRef), ParquetError> {
    let schema = schema_of(obs_dim, act_dim, compact);
    let parquet_schema = ArrowSchemaConverter::new().convert(&schema)?;
    let mut props = WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::try_new(3)?))
        // Row groups are cut by us at episode boundaries, never by the writer.
        .set_max_row_group_row_count(None)
        .set_max_row_group_bytes(None)
        .set_key_value_metadata(Some(metadata.into_iter().map(|(k, v)| KeyValue::new(k, v)).collect()));
    for column in parquet_schema.columns() {
        let encoding = match column.physical_type() {
            PhysicalType::FLOAT | PhysicalType::DOUBLE => Encoding::BYTE_STREAM_SPLIT,
            PhysicalType::INT32 | PhysicalType::INT64 => Encoding::DELTA_BINARY_PACKED,
            _ => continue,
        };
        props = props
            .set_column_dictionary_enabled(column.path().clone(), false)
            .set_column_encoding(column.path().clone(), encoding);
    }
    let (writer, columns) = ArrowWriter::try_new(out, schema.clone(), Some(props.build()))?.into_serialized_writer()?;
    Ok((writer, columns, schema))
}

/// Writes validated transitions as the canonical Parquet layout.
pub struct DatasetWriter<W: Write + Send> {
    writer: SerializedFileWriter<W>,
    /// Makes each row group's column writers (the ones `ArrowWriter` would use, with the same properties).
    columns: ArrowRowGroupWriterFactory,
    /// Threads a row group's columns are encoded on, at most.
    threads: usize,
    /// Whether the threads beyond the writing one come from the process's budget (tests may ask for more).
    budgeted: bool,
    /// This writer, counted in the budget its helper threads come from.
    active: ActiveWriter,
    schema: SchemaRef,
    /// The row group being written, once it has rows.
    group: Option<OpenRowGroup>,
    /// Validated rows not yet encoded: those after the last episode end handed to a row group.
    pending: TransitionChunk,
    pending_numbering: Numbering,
    target_rows: usize,
    /// [`SLICE_TARGET_ROWS`]; tests make it small.
    slice_target_rows: usize,
    compact: bool,
}

impl<W: Write + Send> DatasetWriter<W> {
    /// `metadata` is stored in the Parquet footer's key-value metadata (e.g. the task id).
    pub fn new(out: W, obs_dim: usize, act_dim: usize, metadata: Vec<(String, String)>) -> Result<Self, ParquetError> {
        Self::with_form(out, obs_dim, act_dim, metadata, false)
    }

    /// A writer of the compact form (see the module's documentation) when `compact`, else the canonical one.
    pub fn with_form(
        out: W,
        obs_dim: usize,
        act_dim: usize,
        metadata: Vec<(String, String)>,
        compact: bool,
    ) -> Result<Self, ParquetError> {
        let (writer, columns, schema) = file_writer(out, obs_dim, act_dim, metadata, compact)?;
        let target_rows = target_rows(obs_dim, act_dim);
        Ok(DatasetWriter {
            writer,
            columns,
            threads: encoding_threads(),
            budgeted: true,
            active: PROCESS_BUDGET.writer(),
            group: None,
            schema,
            pending: TransitionChunk::empty(obs_dim, act_dim),
            pending_numbering: Numbering::default(),
            target_rows,
            slice_target_rows: SLICE_TARGET_ROWS,
            compact,
        })
    }

    /// Appends rows that the episode tracker has checked and numbered. The rows of the row group being written are
    /// encoded as soon as they are known to belong to it (they end an episode within the group's target), so only
    /// the group's encoded bytes and an unfinished episode wait in memory, never the group's rows.
    pub fn push(&mut self, chunk: &TransitionChunk, numbering: Numbering) -> Result<(), ParquetError> {
        self.pending.append(chunk);
        self.pending_numbering.episode.extend(numbering.episode);
        self.pending_numbering.step.extend(numbering.step);
        self.advance(false)
    }

    /// Hands the pending rows to row groups as far as the cut rule allows: a row group ends at the last episode end
    /// within the target rows, or at the first episode end when a single episode is longer than the target; when
    /// `finishing`, also at the last episode end so far.
    fn advance(&mut self, finishing: bool) -> Result<(), ParquetError> {
        loop {
            let in_group = self.group.as_ref().map_or(0, |g| g.rows);
            let (mut take, mut close) = (0, false);
            for i in 0..self.pending.len() {
                if !self.pending.is_done(i) {
                    continue;
                }
                let end = in_group + i + 1;
                if end <= self.target_rows {
                    take = i + 1;
                    if end == self.target_rows {
                        close = true;
                        break;
                    }
                } else {
                    if in_group == 0 && take == 0 {
                        take = i + 1;
                    }
                    close = true;
                    break;
                }
            }
            if take > 0 {
                self.feed(take)?;
            }
            if close || (finishing && self.group.is_some()) {
                self.close_group()?;
            } else {
                return Ok(());
            }
        }
    }

    /// Encodes the first `rows` pending rows into the open row group (opening one if none is).
    fn feed(&mut self, rows: usize) -> Result<(), ParquetError> {
        let chunk = self.pending.take_front(rows);
        let rest_episode = self.pending_numbering.episode.split_off(rows);
        let rest_step = self.pending_numbering.step.split_off(rows);
        let episode = std::mem::replace(&mut self.pending_numbering.episode, rest_episode);
        let step = std::mem::replace(&mut self.pending_numbering.step, rest_step);
        let batch = record_batch(&self.schema, chunk, episode, step, self.compact)?;
        let mut group = match self.group.take() {
            Some(group) => group,
            None => self.open_group()?,
        };
        let jobs = std::mem::take(&mut group.columns)
            .into_iter()
            .zip(batch.columns().iter().cloned())
            .map(|(feed, column)| {
                let size = column.get_array_memory_size();
                ((feed, column), size)
            })
            .collect();
        let (helpers, threads) = self.take_threads();
        group.columns = on_threads(jobs, threads, |(mut feed, column)| {
            feed.feed(column)?;
            Ok(feed)
        })?;
        drop(helpers);
        group.rows += rows;
        self.group = Some(group);
        Ok(())
    }

    fn open_group(&mut self) -> Result<OpenRowGroup, ParquetError> {
        let mut writers = self
            .columns
            .create_column_writers(self.writer.flushed_row_groups().len())?
            .into_iter();
        let mut columns = Vec::new();
        for field in self.schema.fields() {
            let mut take = |n: usize| -> Result<Vec<ArrowColumnWriter>, ParquetError> {
                let taken: Vec<_> = writers.by_ref().take(n).collect();
                if taken.len() < n {
                    return Err(ParquetError::General("fewer column writers than leaves".into()));
                }
                Ok(taken)
            };
            columns.push(match slice_rows(field, self.slice_target_rows) {
                Some((per_run, rows)) => ColumnFeed::Sliced {
                    writer: Box::new(take(1)?.pop().expect("one writer")),
                    field: field.clone(),
                    per_run,
                    rows,
                    leftover: None,
                },
                None => ColumnFeed::Whole {
                    writers: take(leaf_count(field.data_type()))?,
                    field: field.clone(),
                    held: Vec::new(),
                },
            });
        }
        Ok(OpenRowGroup { columns, rows: 0 })
    }

    /// Finishes the open row group's columns and appends them to the file, in the schema's order.
    fn close_group(&mut self) -> Result<(), ParquetError> {
        let Some(group) = self.group.take() else {
            return Ok(());
        };
        let jobs = group
            .columns
            .into_iter()
            .map(|feed| {
                let size = feed.waiting_bytes();
                (feed, size)
            })
            .collect();
        let (helpers, threads) = self.take_threads();
        let chunks = on_threads(jobs, threads, ColumnFeed::close)?;
        drop(helpers);
        let mut row_group = self.writer.next_row_group()?;
        for chunk in chunks.into_iter().flatten() {
            chunk.append_to_row_group(&mut row_group)?;
        }
        row_group.close()?;
        Ok(())
    }

    /// The threads to encode on now (the helpers are given back when the first is dropped). Helpers beyond the
    /// writing thread only for idle cores: where other writes already keep the cores busy (concurrent derivations),
    /// a write encodes alone instead of adding threads, each of which would hold its own column's buffers at the
    /// same time.
    fn take_threads(&self) -> (EncodingHelpers, usize) {
        self.active.threads(self.threads.saturating_sub(1), self.budgeted)
    }

    /// Row groups of at most `rows` rows (beyond one episode), for tests that need several groups of few rows.
    #[cfg(test)]
    pub(crate) fn set_target_rows(&mut self, rows: usize) {
        self.target_rows = rows;
    }

    /// Writes the remaining closed episodes and the footer; returns the output.
    pub fn finish(mut self) -> Result<W, ParquetError> {
        self.advance(true)?;
        if !self.pending.is_empty() {
            return Err(ParquetError::General(
                "unclosed episode at the end of the dataset".into(),
            ));
        }
        self.writer.into_inner()
    }
}

/// At most this many threads encode one row group's columns: the two observation columns are most of its bytes.
const ENCODING_THREADS: usize = 4;

/// Threads that encode a row group's columns: the cores, at most [`ENCODING_THREADS`], or `DSRL_ENCODING_THREADS`
/// (1 encodes every column on the writing thread, as `ArrowWriter` does; the file is the same either way); the
/// threads beyond the writing one are taken only for cores no other writer or helper is using, so fewer may run.
fn encoding_threads() -> usize {
    std::env::var("DSRL_ENCODING_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| n >= 1)
        .unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map_or(1, |n| n.get())
                .min(ENCODING_THREADS)
        })
}

/// The writers and helper threads counted in one budget: a helper is taken only for a core no writer or helper in
/// the budget is using, so a lone write spreads its columns over the idle cores while concurrent writes
/// (derivations running at once) encode alone, each holding only its own buffers. The process has one
/// ([`PROCESS_BUDGET`]); a test that checks the counting keeps its own, so the other tests of its process, writing
/// at the same time, do not move its counts.
pub(super) struct EncodingBudget {
    /// (writers, helpers) now.
    state: std::sync::Mutex<(usize, usize)>,
}

static PROCESS_BUDGET: EncodingBudget = EncodingBudget::new();

impl EncodingBudget {
    pub(super) const fn new() -> EncodingBudget {
        EncodingBudget {
            state: std::sync::Mutex::new((0, 0)),
        }
    }

    fn state(&self) -> std::sync::MutexGuard<'_, (usize, usize)> {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The writers and helpers counted now.
    #[cfg(test)]
    pub(super) fn counts(&self) -> (usize, usize) {
        *self.state()
    }

    /// A writer counted in this budget while it lives.
    pub(super) fn writer(&'static self) -> ActiveWriter {
        self.state().0 += 1;
        ActiveWriter { budget: self }
    }
}

/// A writer counted among its budget's active writers while it lives.
pub(super) struct ActiveWriter {
    budget: &'static EncodingBudget,
}

impl ActiveWriter {
    /// The threads to work on now, this one and up to `wanted` helpers: those taken from the writer's budget, as
    /// many cores as no writer or helper is using (never waits), or, unless `budgeted` (tests), all `wanted`
    /// without taking any. The helpers are given back when the first is dropped.
    fn threads(&self, wanted: usize, budgeted: bool) -> (EncodingHelpers, usize) {
        if !budgeted {
            let none = EncodingHelpers {
                budget: self.budget,
                count: 0,
            };
            return (none, 1 + wanted);
        }
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let mut state = self.budget.state();
        let count = wanted.min(cores.saturating_sub(state.0 + state.1));
        state.1 += count;
        let helpers = EncodingHelpers {
            budget: self.budget,
            count,
        };
        (helpers, 1 + count)
    }
}

impl Drop for ActiveWriter {
    fn drop(&mut self) {
        let mut state = self.budget.state();
        state.0 = state.0.saturating_sub(1);
    }
}

/// Helper threads taken for one row group, given back when dropped.
struct EncodingHelpers {
    budget: &'static EncodingBudget,
    count: usize,
}

impl Drop for EncodingHelpers {
    fn drop(&mut self) {
        let mut state = self.budget.state();
        state.1 = state.1.saturating_sub(self.count);
    }
}

/// Parquet's mini-batch of levels (`WriterProperties::write_batch_size`, left at its default): a column writer takes
/// its values in runs of this many levels, a repeated column's run extended to the next row's start, and decides
/// after each run whether to cut a page.
const PARQUET_WRITE_BATCH_LEVELS: usize = 1024;

/// About this many rows of a column are turned into levels and written at a time ([`slice_rows`]).
const SLICE_TARGET_ROWS: usize = 8192;

/// The rows in each of parquet's runs of `field` and the rows per slice (a multiple of them), when the column can be
/// written slice by slice, as its rows arrive, with the bytes of one write of the whole column: every write but a
/// row group's last a whole number of runs, so the runs, and with them the pages, are the same. `None` for columns
/// whose runs do not fall on fixed rows (nullable lists, structs: the compact form), which are written whole. Why: a
/// list column's levels take two 16-bit numbers per value, as much memory again as its floats, for the whole row
/// group at once (measured: most of a filter's peak heap); a slice's levels are small.
fn slice_rows(field: &Field, target_rows: usize) -> Option<(usize, usize)> {
    if target_rows == 0 {
        return None; // tests: every column whole, as `ArrowWriter` writes it
    }
    let per_run = match field.data_type() {
        _ if field.is_nullable() => return None,
        DataType::FixedSizeList(item, width) if !item.is_nullable() && *width > 0 => {
            PARQUET_WRITE_BATCH_LEVELS.div_ceil(*width as usize)
        }
        DataType::Float32 | DataType::UInt32 | DataType::Boolean => PARQUET_WRITE_BATCH_LEVELS,
        _ => return None,
    };
    Some((per_run, per_run * (target_rows / per_run).max(1)))
}

/// Parquet leaf columns of a field of the layout.
fn leaf_count(data_type: &DataType) -> usize {
    match data_type {
        DataType::Struct(fields) => fields.iter().map(|f| leaf_count(f.data_type())).sum(),
        _ => 1,
    }
}

/// The row group being written.
struct OpenRowGroup {
    /// Per field of the schema, in order.
    columns: Vec<ColumnFeed>,
    rows: usize,
}

/// One field's column writers and what they have not been given yet.
enum ColumnFeed {
    /// Written as rows arrive, in slices of `rows` rows, each a multiple of `per_run` ([`slice_rows`]); rows short of
    /// a whole run wait in `leftover` for the next rows or the group's end.
    Sliced {
        writer: Box<ArrowColumnWriter>,
        field: FieldRef,
        per_run: usize,
        rows: usize,
        leftover: Option<ArrayRef>,
    },
    /// Written whole when the group closes (the compact form's structs and nullable lists): its arrays wait here.
    Whole {
        writers: Vec<ArrowColumnWriter>,
        field: FieldRef,
        held: Vec<ArrayRef>,
    },
}

impl ColumnFeed {
    /// Gives the field's writer `column`, the field's next rows.
    fn feed(&mut self, mut column: ArrayRef) -> Result<(), ParquetError> {
        let (writer, field, per_run, rows, leftover) = match self {
            ColumnFeed::Whole { held, .. } => {
                held.push(column);
                return Ok(());
            }
            ColumnFeed::Sliced {
                writer,
                field,
                per_run,
                rows,
                leftover,
            } => (writer, field, *per_run, *rows, leftover),
        };
        if let Some(left) = leftover.take() {
            let need = (per_run - left.len()).min(column.len());
            let head = arrow_select::concat::concat(&[left.as_ref(), column.slice(0, need).as_ref()])?;
            column = column.slice(need, column.len() - need);
            if head.len() < per_run {
                *leftover = Some(head);
                return Ok(());
            }
            write_leaves(writer, field, &head)?;
        }
        let whole_runs = column.len() / per_run * per_run;
        for start in (0..whole_runs).step_by(rows) {
            write_leaves(writer, field, &column.slice(start, rows.min(whole_runs - start)))?;
        }
        if whole_runs < column.len() {
            *leftover = Some(column.slice(whole_runs, column.len() - whole_runs));
        }
        Ok(())
    }

    /// Bytes still to encode at the group's end (to share that work out evenly).
    fn waiting_bytes(&self) -> usize {
        match self {
            ColumnFeed::Sliced { leftover, .. } => leftover.as_ref().map_or(0, |a| a.get_array_memory_size()),
            ColumnFeed::Whole { held, .. } => held.iter().map(|a| a.get_array_memory_size()).sum(),
        }
    }

    /// The field's encoded column chunks (one per leaf).
    fn close(self) -> Result<Vec<ArrowColumnChunk>, ParquetError> {
        match self {
            ColumnFeed::Sliced {
                mut writer,
                field,
                leftover,
                ..
            } => {
                if let Some(left) = leftover {
                    write_leaves(&mut writer, &field, &left)?;
                }
                Ok(vec![writer.close()?])
            }
            ColumnFeed::Whole { writers, field, held } => {
                let arrays: Vec<&dyn Array> = held.iter().map(|a| a.as_ref()).collect();
                let column = arrow_select::concat::concat(&arrays)?;
                let leaves = compute_leaves(field.as_ref(), &column)?;
                if leaves.len() != writers.len() {
                    return Err(ParquetError::General(
                        "column writers and leaves differ in number".into(),
                    ));
                }
                writers
                    .into_iter()
                    .zip(leaves)
                    .map(|(mut writer, leaf)| {
                        writer.write(&leaf)?;
                        writer.close()
                    })
                    .collect()
            }
        }
    }
}

fn write_leaves(writer: &mut ArrowColumnWriter, field: &Field, column: &ArrayRef) -> Result<(), ParquetError> {
    for leaf in compute_leaves(field, column)? {
        writer.write(&leaf)?;
    }
    Ok(())
}

/// Runs `work` on each item on up to `threads` threads, the largest items (by the given size) dealt first to the
/// least loaded thread; returns the results in the items' order. Each column's bytes are those one thread writes
/// for it, so the file is the same whatever the threads.
fn on_threads<T: Send, R: Send>(
    items: Vec<(T, usize)>,
    threads: usize,
    work: impl Fn(T) -> Result<R, ParquetError> + Sync,
) -> Result<Vec<R>, ParquetError> {
    if threads <= 1 || items.len() <= 1 {
        return items.into_iter().map(|(item, _)| work(item)).collect();
    }
    let count = items.len();
    let mut largest_first: Vec<(usize, (T, usize))> = items.into_iter().enumerate().collect();
    largest_first.sort_by_key(|(_, (_, size))| std::cmp::Reverse(*size));
    let mut bins: Vec<(usize, Vec<(usize, T)>)> = (0..threads).map(|_| (0, Vec::new())).collect();
    for (i, (item, size)) in largest_first {
        let bin = bins.iter_mut().min_by_key(|b| b.0).expect("threads > 1");
        bin.0 += size;
        bin.1.push((i, item));
    }
    let mut results: Vec<Option<R>> = (0..count).map(|_| None).collect();
    let work = &work;
    std::thread::scope(|scope| -> Result<(), ParquetError> {
        let handles: Vec<_> = bins
            .into_iter()
            .map(|(_, items)| items)
            .filter(|items| !items.is_empty())
            .map(|items| {
                scope.spawn(move || {
                    items
                        .into_iter()
                        .map(|(i, item)| Ok((i, work(item)?)))
                        .collect::<Result<Vec<_>, ParquetError>>()
                })
            })
            .collect();
        for handle in handles {
            let done = handle
                .join()
                .map_err(|_| ParquetError::General("a column encoding thread panicked".into()))??;
            for (i, result) in done {
                results[i] = Some(result);
            }
        }
        Ok(())
    })?;
    results
        .into_iter()
        .map(|r| r.ok_or_else(|| ParquetError::General("a column was not encoded".into())))
        .collect()
}

fn record_batch(
    schema: &SchemaRef,
    chunk: TransitionChunk,
    episode: Vec<u32>,
    step: Vec<u32>,
    compact: bool,
) -> Result<RecordBatch, ParquetError> {
    let list = |values: Vec<f32>, dim: usize, valid: Option<Vec<bool>>| -> Result<ArrayRef, ParquetError> {
        let field = Arc::new(Field::new_list_field(DataType::Float32, false));
        let nulls = valid.map(arrow_buffer::NullBuffer::from);
        let array = FixedSizeListArray::try_new(field, dim as i32, Arc::new(Float32Array::from(values)), nulls)?;
        Ok(Arc::new(array))
    };
    // Compact: a row's next observation is left out (null) where the next row of its episode starts from it.
    let derivable = compact.then(|| {
        let d = chunk.obs_dim;
        (0..chunk.len())
            .map(|i| {
                let derivable = i + 1 < chunk.len()
                    && !chunk.is_done(i)
                    && episode[i] == episode[i + 1]
                    && chunk.next_observations[i * d..(i + 1) * d]
                        .iter()
                        .zip(&chunk.observations[(i + 1) * d..(i + 2) * d])
                        .all(|(a, b)| a.to_bits() == b.to_bits());
                !derivable
            })
            .collect::<Vec<bool>>()
    });
    let observations = if compact {
        // One column per feature: the row-major matrix transposed.
        let (d, n) = (chunk.obs_dim, chunk.len());
        let features: Vec<ArrayRef> = (0..d)
            .map(|j| {
                Arc::new(Float32Array::from_iter_values(
                    (0..n).map(|i| chunk.observations[i * d + j]),
                )) as ArrayRef
            })
            .collect();
        Arc::new(StructArray::try_new(feature_fields(d), features, None)?) as ArrayRef
    } else {
        list(chunk.observations, chunk.obs_dim, None)?
    };
    let columns: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(episode)),
        Arc::new(UInt32Array::from(step)),
        observations,
        list(chunk.next_observations, chunk.obs_dim, derivable)?,
        list(chunk.actions, chunk.act_dim, None)?,
        Arc::new(Float32Array::from(chunk.rewards)),
        Arc::new(Float32Array::from(chunk.costs)),
        Arc::new(BooleanArray::from(chunk.terminals)),
        Arc::new(BooleanArray::from(chunk.timeouts)),
    ];
    Ok(RecordBatch::try_new(schema.clone(), columns)?)
}

/// Problems reading a Parquet file as a dataset.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The bytes are not a readable Parquet file.
    #[error("{0}")]
    Parquet(#[from] ParquetError),
    /// The file is Parquet but not in a dataset layout.
    #[error("{0}")]
    Layout(String),
    /// A value is of the right type but not acceptable.
    #[error("{0}")]
    Value(#[from] ValidationError),
}

impl From<arrow_schema::ArrowError> for ReadError {
    fn from(e: arrow_schema::ArrowError) -> Self {
        ReadError::Parquet(ParquetError::from(e))
    }
}

/// The episode index of dataset files read in order (a whole file, or the parts of one), from their reward, cost
/// and done columns only: observations and actions are never decoded. The returns are summed as the manifest's
/// index sums them (float32, `np.sum`'s order), episode by episode; an episode left open at a file's end is an
/// error. For tools that need a dataset's returns without ingesting it (`dsrl-admin docs`).
pub fn read_episode_index(files: &[std::path::PathBuf]) -> Result<Vec<crate::episode::EpisodeSummary>, ReadError> {
    use crate::episode::{EpisodeSummary, numpy_sum_f32};
    let mut episodes = Vec::new();
    let (mut rewards, mut costs) = (Vec::<f32>::new(), Vec::<f32>::new());
    let mut row = 0u64;
    for path in files {
        let builder = ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(path).map_err(ParquetError::from)?)?;
        let schema = builder.schema().clone();
        let roots = [REWARDS, COSTS, TERMINALS, TIMEOUTS]
            .iter()
            .map(|k| schema.index_of(k))
            .collect::<Result<Vec<_>, _>>()?;
        let mask = ProjectionMask::roots(builder.parquet_schema(), roots);
        for batch in builder.with_projection(mask).with_batch_size(1 << 16).build()? {
            let batch = batch?;
            let col = |name: &str| batch.column_by_name(name).expect("projected column").clone();
            let r = float_vector(row, REWARDS, &col(REWARDS))?;
            let c = float_vector(row, COSTS, &col(COSTS))?;
            let t = flag_vector(row, TERMINALS, &col(TERMINALS))?;
            let o = flag_vector(row, TIMEOUTS, &col(TIMEOUTS))?;
            for i in 0..r.len() {
                rewards.push(r[i]);
                costs.push(c[i]);
                if t[i] || o[i] {
                    let length = rewards.len() as u32;
                    episodes.push(EpisodeSummary {
                        start: row + i as u64 + 1 - u64::from(length),
                        length,
                        reward_return: numpy_sum_f32(&rewards),
                        cost_return: numpy_sum_f32(&costs),
                    });
                    rewards.clear();
                    costs.clear();
                }
            }
            row += r.len() as u64;
        }
        if !rewards.is_empty() {
            return Err(ReadError::Layout(format!(
                "{} ends inside an episode (no terminal or timeout flag on its last row)",
                path.display()
            )));
        }
    }
    Ok(episodes)
}

/// Reads any Parquet file with DSRL's columns as transition chunks: the canonical layout, the compact form, or a
/// file written by pandas/pyarrow with float64 values, variable-length lists, structs of one float per feature, or
/// integer flags. Columns outside the format are reported, not read.
pub struct ParquetTransitions {
    reader: ParquetRecordBatchReader,
    obs_dim: usize,
    act_dim: usize,
    has_episode: bool,
    has_step: bool,
    ignored_columns: Vec<String>,
    rows: u64,
    next_row: u64,
    /// Compact form: the last row read, whose next observation is the following batch's first observation.
    held: Option<(u64, TransitionChunk)>,
    /// Row groups read on other threads ([`ParquetTransitions::open_read_ahead`]), in place of `reader`.
    ahead: Option<read_ahead::ReadAhead>,
}

impl ParquetTransitions {
    pub fn open(file: std::fs::File) -> Result<Self, ReadError> {
        Self::from_builder(ParquetRecordBatchReaderBuilder::try_new(file)?, 0)
    }

    /// The reader of `builder`'s rows (all or some row groups), the first of which is row `first_row` of the file.
    fn from_builder(
        builder: ParquetRecordBatchReaderBuilder<std::fs::File>,
        first_row: u64,
    ) -> Result<Self, ReadError> {
        let schema = builder.schema().clone();
        let rows = builder.metadata().file_metadata().num_rows() as u64;
        let mut missing = Vec::new();
        let mut roots = Vec::new();
        for key in DSRL_KEYS {
            match schema.index_of(key) {
                Ok(i) => roots.push(i),
                Err(_) => missing.push(key),
            }
        }
        if !missing.is_empty() {
            return Err(ReadError::Layout(format!(
                "missing column(s) {}; a dataset needs {}",
                missing.join(", "),
                DSRL_KEYS.join(", ")
            )));
        }
        let has_episode = schema.index_of(EPISODE).is_ok();
        let has_step = schema.index_of(STEP).is_ok();
        for (name, present) in [(EPISODE, has_episode), (STEP, has_step)] {
            if present {
                roots.push(schema.index_of(name)?);
            }
        }
        let known: Vec<&str> = DSRL_KEYS.iter().copied().chain([EPISODE, STEP]).collect();
        let ignored_columns = schema
            .fields()
            .iter()
            .map(|f| f.name().clone())
            .filter(|n| !known.contains(&n.as_str()))
            .collect();
        let obs_dim = list_width(&schema, OBSERVATIONS)?;
        let act_dim = list_width(&schema, ACTIONS)?;
        let next_dim = list_width(&schema, NEXT_OBSERVATIONS)?;
        if let (Some(o), Some(n)) = (obs_dim, next_dim)
            && o != n
        {
            return Err(ReadError::Value(ValidationError::column(
                NEXT_OBSERVATIONS,
                format!("{n} features per observation but observations has {o}"),
            )));
        }
        let batch_rows = match (obs_dim, act_dim) {
            (Some(o), Some(a)) => (READ_BATCH_TARGET_BYTES / row_bytes(o, a)).clamp(1024, 1 << 20),
            _ => 8192,
        };
        let mask = ProjectionMask::roots(builder.parquet_schema(), roots);
        let reader = builder.with_projection(mask).with_batch_size(batch_rows).build()?;
        // Variable-length lists get their width from the first row; every later row is checked against it.
        Ok(ParquetTransitions {
            reader,
            obs_dim: obs_dim.unwrap_or(0),
            act_dim: act_dim.unwrap_or(0),
            has_episode,
            has_step,
            ignored_columns,
            rows,
            next_row: first_row,
            held: None,
            ahead: None,
        })
    }

    /// Rows in the file, from its footer.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Columns of the file that are not part of the dataset format.
    pub fn ignored_columns(&self) -> &[String] {
        &self.ignored_columns
    }

    fn convert(&mut self, batch: RecordBatch) -> Result<(TransitionChunk, bool), ReadError> {
        let base = self.next_row;
        let col = |name: &str| batch.column_by_name(name).expect("projected column").clone();
        let (observations, obs_dim) = float_matrix(base, OBSERVATIONS, &col(OBSERVATIONS), self.obs_dim)?;
        let (next_observations, left_out) = next_observation_matrix(base, &col(NEXT_OBSERVATIONS), obs_dim)?;
        let (actions, act_dim) = float_matrix(base, ACTIONS, &col(ACTIONS), self.act_dim)?;
        self.obs_dim = obs_dim;
        self.act_dim = act_dim;
        let chunk = TransitionChunk {
            obs_dim,
            act_dim,
            observations,
            next_observations,
            actions,
            rewards: float_vector(base, REWARDS, &col(REWARDS))?,
            costs: float_vector(base, COSTS, &col(COSTS))?,
            terminals: flag_vector(base, TERMINALS, &col(TERMINALS))?,
            timeouts: flag_vector(base, TIMEOUTS, &col(TIMEOUTS))?,
            episode: if self.has_episode {
                Some(counter_vector(base, EPISODE, &col(EPISODE))?)
            } else {
                None
            },
            step: if self.has_step {
                Some(counter_vector(base, STEP, &col(STEP))?)
            } else {
                None
            },
        };
        self.next_row += batch.num_rows() as u64;
        fill_left_out(base, chunk, &left_out)
    }

    /// The next rows with every next observation in place: a compact file's last row of a batch waits for the
    /// next batch's first observation.
    fn next_filled(&mut self) -> Option<Result<TransitionChunk, ReadError>> {
        loop {
            let batch = match self.reader.next() {
                Some(Ok(batch)) => batch,
                Some(Err(e)) => return Some(Err(e.into())),
                None => {
                    return self.held.take().map(|(row, _)| {
                        Err(ReadError::Value(ValidationError::at(
                            row,
                            NEXT_OBSERVATIONS,
                            "null at the last row: a next observation can be left out only where the next row \
                             of the same episode starts from it",
                        )))
                    });
                }
            };
            let (mut chunk, last_left_out) = match self.convert(batch) {
                Ok(converted) => converted,
                Err(e) => return Some(Err(e)),
            };
            if let Some((row, mut held)) = self.held.take() {
                if let Err(e) = complete_from(row, &mut held, &chunk, 0) {
                    return Some(Err(e));
                }
                // `append` drops the source's numbering; carry it over by hand.
                let numbering = |a: Option<Vec<u32>>, b: Option<Vec<u32>>| {
                    a.zip(b).map(|(mut a, b)| {
                        a.extend(b);
                        a
                    })
                };
                let (episode, step) = (held.episode.take(), held.step.take());
                held.append(&chunk);
                held.episode = numbering(episode, chunk.episode.take());
                held.step = numbering(step, chunk.step.take());
                chunk = held;
            }
            if last_left_out {
                let n = chunk.len();
                let last = chunk.rows(n - 1, 1);
                chunk = chunk.rows(0, n - 1);
                self.held = Some((self.next_row - 1, last));
            }
            if !chunk.is_empty() {
                return Some(Ok(chunk));
            }
        }
    }
}

/// Fills `rows`' left-out next observation (its only row) from row `at` of `from`, which must continue its
/// episode.
fn complete_from(row: u64, rows: &mut TransitionChunk, from: &TransitionChunk, at: usize) -> Result<(), ReadError> {
    let d = rows.obs_dim;
    let same_episode = match (&rows.episode, &from.episode) {
        (Some(a), Some(b)) => a[0] == b[at],
        _ => true,
    };
    if rows.is_done(0) || !same_episode {
        return Err(ReadError::Value(ValidationError::at(
            row,
            NEXT_OBSERVATIONS,
            "null at an episode's last step: its next observation cannot come from the next row",
        )));
    }
    rows.next_observations[..d].copy_from_slice(&from.observations[at * d..(at + 1) * d]);
    Ok(())
}

/// Fills the left-out next observations of `chunk` from the following rows; returns the chunk and whether its
/// last row is still left out (to be filled from the next batch).
fn fill_left_out(
    base: u64,
    mut chunk: TransitionChunk,
    left_out: &[bool],
) -> Result<(TransitionChunk, bool), ReadError> {
    let d = chunk.obs_dim;
    let n = chunk.len();
    for i in (0..n.saturating_sub(1)).filter(|&i| left_out[i]) {
        let same_episode = chunk.episode.as_ref().is_none_or(|e| e[i] == e[i + 1]);
        if chunk.is_done(i) || !same_episode {
            return Err(ReadError::Value(ValidationError::at(
                base + i as u64,
                NEXT_OBSERVATIONS,
                "null at an episode's last step: its next observation cannot come from the next row",
            )));
        }
        chunk.next_observations[i * d..(i + 1) * d].copy_from_slice(&chunk.observations[(i + 1) * d..(i + 2) * d]);
    }
    Ok((chunk, n > 0 && left_out[n - 1]))
}

/// The `next_observations` column: values and which rows are null (left out in the compact form). Only the
/// fixed-size list form may hold nulls; other forms are read as any float matrix.
fn next_observation_matrix(base: u64, array: &ArrayRef, width: usize) -> Result<(Vec<f32>, Vec<bool>), ReadError> {
    if let DataType::FixedSizeList(_, _) = array.data_type()
        && array.null_count() > 0
    {
        let list = array.as_fixed_size_list();
        let w = list.value_length() as usize;
        let values = list.values();
        let floats = match values.data_type() {
            DataType::Float32 => values.as_primitive::<Float32Type>().values().to_vec(),
            DataType::Float64 => values
                .as_primitive::<Float64Type>()
                .values()
                .iter()
                .map(|&v| v as f32)
                .collect(),
            other => {
                return Err(ReadError::Layout(format!(
                    "column {NEXT_OBSERVATIONS} holds {other}; expected float32 or float64"
                )));
            }
        };
        let left_out: Vec<bool> = (0..list.len()).map(|i| list.is_null(i)).collect();
        // Values of present rows must themselves be present.
        if let Some(nulls) = values.logical_nulls()
            && let Some(i) = (0..list.len()).find(|&i| !left_out[i] && (i * w..(i + 1) * w).any(|j| nulls.is_null(j)))
        {
            return Err(ReadError::Value(ValidationError::at(
                base + i as u64,
                NEXT_OBSERVATIONS,
                "null value",
            )));
        }
        if width != 0 && w != width {
            return Err(ReadError::Value(ValidationError::column(
                NEXT_OBSERVATIONS,
                format!("{w} features per observation but observations has {width}"),
            )));
        }
        return Ok((floats, left_out));
    }
    let (values, _) = float_matrix(base, NEXT_OBSERVATIONS, array, width)?;
    let rows = values.len().checked_div(width).unwrap_or(0);
    Ok((values, vec![false; rows]))
}

impl Iterator for ParquetTransitions {
    type Item = Result<TransitionChunk, ReadError>;
    fn next(&mut self) -> Option<Self::Item> {
        match &mut self.ahead {
            Some(ahead) => ahead.next(),
            None => self.next_filled(),
        }
    }
}

/// Width of a fixed-size list column, `None` for variable-length lists; an error for other types.
fn list_width(schema: &Schema, name: &str) -> Result<Option<usize>, ReadError> {
    let field = schema.field_with_name(name)?;
    let item = match field.data_type() {
        DataType::FixedSizeList(item, n) => {
            check_float(name, item.data_type())?;
            return Ok(Some(*n as usize));
        }
        // The compact form's observations: one float field per feature.
        DataType::Struct(fields) if !fields.is_empty() => {
            for field in fields {
                check_float(name, field.data_type())?;
            }
            return Ok(Some(fields.len()));
        }
        DataType::List(item) | DataType::LargeList(item) => item,
        other => {
            return Err(ReadError::Layout(format!(
                "column {name} has type {other}; expected a list of float32 (one vector per transition)"
            )));
        }
    };
    check_float(name, item.data_type())?;
    Ok(None)
}

fn check_float(name: &str, t: &DataType) -> Result<(), ReadError> {
    match t {
        DataType::Float32 | DataType::Float64 => Ok(()),
        other => Err(ReadError::Layout(format!(
            "column {name} holds {other}; expected float32 or float64"
        ))),
    }
}

fn no_nulls(base: u64, name: &str, array: &dyn Array) -> Result<(), ValidationError> {
    match array
        .logical_nulls()
        .and_then(|n| (0..array.len()).find(|&i| n.is_null(i)))
    {
        Some(i) => Err(ValidationError::at(base + i as u64, name, "null value")),
        None => Ok(()),
    }
}

fn floats_of(name: &str, values: &ArrayRef) -> Result<Vec<f32>, ReadError> {
    match values.data_type() {
        DataType::Float32 => Ok(values.as_primitive::<Float32Type>().values().to_vec()),
        // DSRL's `get_dataset` casts float64 to float32 the same way.
        DataType::Float64 => Ok(values
            .as_primitive::<Float64Type>()
            .values()
            .iter()
            .map(|&v| v as f32)
            .collect()),
        other => Err(ReadError::Layout(format!(
            "column {name} holds {other}; expected float32 or float64"
        ))),
    }
}

/// Row-major values of a list column, or of a struct of one float field per feature, and its width
/// (`width == 0`: take it from the first row).
fn float_matrix(base: u64, name: &str, array: &ArrayRef, width: usize) -> Result<(Vec<f32>, usize), ReadError> {
    no_nulls(base, name, array.as_ref())?;
    match array.data_type() {
        DataType::Struct(_) => {
            let features = array.as_struct().columns();
            let (d, n) = (features.len(), array.len());
            let mut values = vec![0f32; n * d];
            for (j, feature) in features.iter().enumerate() {
                no_nulls(base, name, feature.as_ref())?;
                for (i, v) in floats_of(name, feature)?.into_iter().enumerate() {
                    values[i * d + j] = v;
                }
            }
            Ok((values, d))
        }
        DataType::FixedSizeList(_, _) => {
            let list = array.as_fixed_size_list();
            no_nulls(base, name, list.values().as_ref())?;
            Ok((floats_of(name, list.values())?, list.value_length() as usize))
        }
        DataType::List(_) | DataType::LargeList(_) => {
            let (offsets, values): (Vec<usize>, &ArrayRef) = match array.data_type() {
                DataType::List(_) => {
                    let l = array.as_list::<i32>();
                    (l.value_offsets().iter().map(|&o| o as usize).collect(), l.values())
                }
                _ => {
                    let l = array.as_list::<i64>();
                    (l.value_offsets().iter().map(|&o| o as usize).collect(), l.values())
                }
            };
            let mut width = width;
            for (i, w) in offsets.windows(2).enumerate() {
                let len = w[1] - w[0];
                if width == 0 {
                    width = len;
                }
                if len != width || len == 0 {
                    return Err(ReadError::Value(ValidationError::at(
                        base + i as u64,
                        name,
                        format!("{len} features, but earlier rows have {width}"),
                    )));
                }
            }
            let (start, end) = (offsets[0], offsets[offsets.len() - 1]);
            let values = values.slice(start, end - start);
            no_nulls(base, name, values.as_ref())?;
            Ok((floats_of(name, &values)?, width))
        }
        other => Err(ReadError::Layout(format!(
            "column {name} has type {other}; expected a list of floats"
        ))),
    }
}

fn float_vector(base: u64, name: &str, array: &ArrayRef) -> Result<Vec<f32>, ReadError> {
    no_nulls(base, name, array.as_ref())?;
    floats_of(name, array)
}

/// Done flags stored as bool, integers or floats; anything but 0 or 1 is an error (DSRL tests `== 1`).
fn flag_vector(base: u64, name: &str, array: &ArrayRef) -> Result<Vec<bool>, ReadError> {
    no_nulls(base, name, array.as_ref())?;
    if let DataType::Boolean = array.data_type() {
        return Ok(array.as_boolean().values().iter().collect());
    }
    let as_f64: Vec<f64> = numbers(array).ok_or_else(|| {
        ReadError::Layout(format!(
            "column {name} has type {}; expected bool or 0/1 numbers",
            array.data_type()
        ))
    })?;
    Ok(flags_from_numbers(base, name, as_f64)?)
}

fn counter_vector(base: u64, name: &str, array: &ArrayRef) -> Result<Vec<u32>, ReadError> {
    no_nulls(base, name, array.as_ref())?;
    let values = match array.data_type() {
        DataType::Float32 | DataType::Float64 => None,
        _ => numbers(array),
    }
    .ok_or_else(|| {
        ReadError::Layout(format!(
            "column {name} has type {}; expected integers",
            array.data_type()
        ))
    })?;
    values
        .into_iter()
        .enumerate()
        .map(|(i, v)| {
            if (0.0..=u32::MAX as f64).contains(&v) {
                Ok(v as u32)
            } else {
                Err(ReadError::Value(ValidationError::at(
                    base + i as u64,
                    name,
                    format!("{v} is out of range"),
                )))
            }
        })
        .collect()
}

/// Any integer or float column as f64 (exact for every integer a u32 counter or flag can hold).
fn numbers(array: &ArrayRef) -> Option<Vec<f64>> {
    macro_rules! conv {
        ($t:ty) => {
            array
                .as_primitive::<$t>()
                .values()
                .iter()
                .map(|&v| v as f64)
                .collect()
        };
    }
    Some(match array.data_type() {
        DataType::Int8 => conv!(Int8Type),
        DataType::Int16 => conv!(Int16Type),
        DataType::Int32 => conv!(Int32Type),
        DataType::Int64 => conv!(Int64Type),
        DataType::UInt8 => conv!(UInt8Type),
        DataType::UInt16 => conv!(UInt16Type),
        DataType::UInt32 => conv!(UInt32Type),
        DataType::UInt64 => conv!(UInt64Type),
        DataType::Float32 => conv!(Float32Type),
        DataType::Float64 => conv!(Float64Type),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::{SyntheticSpec, transitions};
    use crate::validate::{EpisodeTracker, Expectation};

    /// The bytes of a dataset written with `threads` encoding threads, in row groups of at most 700 rows.
    fn written(threads: usize) -> Vec<u8> {
        written_as("OfflineCarCircle-v0", 12, threads, 700, SLICE_TARGET_ROWS)
    }

    /// The bytes of `episodes` synthetic episodes of `task`, in row groups of at most `target_rows` rows, the columns
    /// written in slices of about `slice_target_rows` rows (0: whole).
    pub(super) fn written_as(
        task: &str,
        episodes: usize,
        threads: usize,
        target_rows: usize,
        slice_target_rows: usize,
    ) -> Vec<u8> {
        let catalog = crate::catalog::Catalog::embedded().unwrap();
        let task = catalog.get(task).unwrap();
        let mut spec = SyntheticSpec::for_task(task, episodes, 5);
        // Pushed in chunks that end anywhere in an episode and in a run.
        spec.chunk_rows = 777;
        let (o, a) = (spec.obs_dim, spec.act_dim);
        let mut writer = DatasetWriter::new(Vec::new(), o, a, vec![("k".into(), "v".into())]).unwrap();
        writer.threads = threads;
        writer.budgeted = false;
        writer.target_rows = target_rows;
        writer.slice_target_rows = slice_target_rows;
        let mut tracker = EpisodeTracker::new(Expectation {
            obs_dim: o,
            act_dim: a,
            max_episode_steps: task.max_episode_steps,
        });
        for chunk in transitions(spec) {
            let numbering = tracker.check(&chunk).unwrap();
            writer.push(&chunk, numbering).unwrap();
        }
        writer.finish().unwrap()
    }

    #[test]
    fn columns_encoded_on_several_threads_write_the_same_file() {
        let one = written(1);
        for threads in [2, 3, 8] {
            assert_eq!(written(threads), one, "{threads} threads");
        }
        let file = tempfile::tempfile().unwrap();
        (&file).write_all(&one).unwrap();
        let metadata = ParquetRecordBatchReaderBuilder::try_new(file)
            .unwrap()
            .metadata()
            .clone();
        assert!(
            metadata.num_row_groups() > 2,
            "several row groups: {}",
            metadata.num_row_groups()
        );
    }

    #[test]
    fn row_group_rows_are_the_groups_the_writer_cuts() {
        for (task, episodes, target_rows) in [
            ("OfflineCarCircle-v0", 30, 700),
            ("OfflineCarCircle-v0", 30, 2500),
            ("OfflineCarCircle-v0", 12, 300),
            ("OfflineCarPush2Gymnasium-v0", 12, 6000),
        ] {
            let file = tempfile::NamedTempFile::new().unwrap();
            std::fs::write(
                file.path(),
                written_as(task, episodes, 1, target_rows, SLICE_TARGET_ROWS),
            )
            .unwrap();
            let groups: Vec<usize> = ParquetRecordBatchReaderBuilder::try_new(file.reopen().unwrap())
                .unwrap()
                .metadata()
                .row_groups()
                .iter()
                .map(|g| g.num_rows() as usize)
                .collect();
            let lengths = read_episode_index(&[file.path().to_path_buf()])
                .unwrap()
                .iter()
                .map(|e| e.length as usize)
                .collect::<Vec<_>>();
            assert_eq!(
                row_group_rows(lengths, target_rows),
                groups,
                "{task}, {target_rows} rows"
            );
        }
    }

    #[test]
    fn columns_written_in_slices_write_the_same_file_as_whole_columns() {
        // CarCircle: 8 features (a run of parquet's is 128 rows), 300-step episodes; CarPush2: 88 features (12 rows
        // and 32 levels more than 1024), 1000-step episodes. Row groups of several thousand rows, so the scalar
        // columns (runs of 1024 rows) are sliced too, and CarPush2's observation columns several 1 MiB pages each
        // (a page is cut after a run: misplaced runs move the cuts).
        for (task, episodes, target_rows) in [
            ("OfflineCarCircle-v0", 30, 2500),
            ("OfflineCarPush2Gymnasium-v0", 12, 6000),
        ] {
            let whole = written_as(task, episodes, 1, target_rows, 0);
            for slice_target_rows in [1, 100, 1024, 1500, SLICE_TARGET_ROWS] {
                for threads in [1, 3] {
                    assert!(
                        written_as(task, episodes, threads, target_rows, slice_target_rows) == whole,
                        "{task}: slices of about {slice_target_rows} rows on {threads} threads"
                    );
                }
            }
        }
    }
}
