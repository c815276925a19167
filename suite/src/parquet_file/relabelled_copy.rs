//! A canonical dataset file rewritten with new rewards and costs, every other column chunk copied byte for byte.
//!
//! DSRL's outlier filter (the `noise` filter) keeps every trajectory in order and changes only the rewards and costs
//! of the ones it relabels. Its output has the parent's rows and episodes, so the writer would cut the same row
//! groups and encode the same pages for the observation, action, counter and flag columns: those are copied from
//! the parent as they are (the two observation columns are nearly all of a file's bytes), and only the two relabelled
//! float columns are encoded. The file is the one a full decode and re-encode writes, byte for byte, when the parent
//! is the writer's own canonical layout; [`RelabelSource::open`] declines any other parent, and the caller
//! re-encodes.

use std::io::Write;
use std::sync::Arc;

use arrow_array::{ArrayRef, Float32Array, RecordBatch};
use parquet::arrow::ProjectionMask;
use parquet::arrow::arrow_reader::{ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder};
use parquet::basic::Compression;
use parquet::column::writer::ColumnCloseResult;
use parquet::errors::ParquetError;
use parquet::file::metadata::PageIndexPolicy;

use super::{
    COSTS, REWARDS, ReadError, TERMINALS, TIMEOUTS, dataset_schema, file_writer, flag_vector, float_vector,
    write_leaves,
};
use crate::convert::{ImportError, parquet_io};
use crate::transitions::TransitionChunk;

/// A parent file in the canonical layout whose row groups are the ones its episodes give.
pub struct RelabelSource {
    file: std::fs::File,
    metadata: ArrowReaderMetadata,
    groups: Vec<usize>,
    obs_dim: usize,
    act_dim: usize,
}

impl RelabelSource {
    /// `file` as a source of copied column chunks, if it holds the canonical layout for these widths (the format key
    /// of this writer, its schema, zstd pages with page indexes) in exactly the row groups `groups` (by their rows:
    /// what [`super::row_group_rows`] cuts from its episodes); `None` if not.
    pub fn open(
        file: std::fs::File,
        obs_dim: usize,
        act_dim: usize,
        groups: &[usize],
    ) -> Result<Option<RelabelSource>, ReadError> {
        // The page indexes and the pages' encoding statistics as written (not as a mask): the copied chunks'
        // metadata goes into the new footer as it is.
        let options = ArrowReaderOptions::new()
            .with_page_index_policy(PageIndexPolicy::Optional)
            .with_encoding_stats_as_mask(false);
        let metadata = ArrowReaderMetadata::load(&file, options)?;
        let parquet = metadata.metadata();
        let format = parquet
            .file_metadata()
            .key_value_metadata()
            .and_then(|kv| kv.iter().find(|k| k.key == "dsrl.format"))
            .and_then(|k| k.value.as_deref());
        let canonical = format == Some(crate::manifest::FORMAT)
            && metadata.schema().fields() == dataset_schema(obs_dim, act_dim).fields()
            && parquet.num_row_groups() == groups.len()
            && parquet.row_groups().iter().enumerate().all(|(g, group)| {
                let pages = parquet.page_index_for_row_group(g);
                group.num_rows() as usize == groups[g]
                    && group.columns().iter().enumerate().all(|(c, column)| {
                        matches!(column.compression(), Compression::ZSTD(_))
                            && pages.column_index(c).is_some()
                            && pages.offset_index(c).is_some()
                    })
            });
        Ok(canonical.then(|| RelabelSource {
            file,
            metadata,
            groups: groups.to_vec(),
            obs_dim,
            act_dim,
        }))
    }

    /// Writes the file to `out` with the footer's key-value `metadata`: for each row group, `relabel(first_row,
    /// rows)` may change the rows' rewards and costs (`rows` holds only the scalar columns: no observations or
    /// actions, widths 0), which are then encoded; every other column chunk is the parent's. Returns `out`.
    pub fn write<W: Write + Send>(
        &self,
        out: W,
        metadata: Vec<(String, String)>,
        mut relabel: impl FnMut(u64, &mut TransitionChunk) -> Result<(), ImportError>,
    ) -> Result<W, ImportError> {
        let (mut writer, factory, schema) =
            file_writer(out, self.obs_dim, self.act_dim, metadata, false).map_err(parquet_io)?;
        let parquet = self.metadata.metadata().clone();
        let descriptor = parquet.file_metadata().schema_descr_ptr();
        // The leaf column of each relabelled field (flat columns: one leaf each, named by the field).
        let leaf_of = |name: &str| {
            descriptor
                .columns()
                .iter()
                .position(|c| c.path().parts() == [name])
                .ok_or_else(|| ImportError::from_parquet(ReadError::Layout(format!("no {name} column"))))
        };
        let (rewards_leaf, costs_leaf) = (leaf_of(REWARDS)?, leaf_of(COSTS)?);
        let roots = [REWARDS, COSTS, TERMINALS, TIMEOUTS]
            .iter()
            .map(|k| schema.index_of(k))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| ImportError::from_parquet(e.into()))?;
        let mut first_row = 0u64;
        for (g, &rows) in self.groups.iter().enumerate() {
            let mut chunk = self
                .scalars(g, rows, first_row, &roots)
                .map_err(ImportError::from_parquet)?;
            relabel(first_row, &mut chunk)?;
            let mut encoded = Vec::with_capacity(2);
            for (leaf, mut column_writer) in factory
                .create_column_writers(g)
                .map_err(parquet_io)?
                .into_iter()
                .enumerate()
            {
                let (name, values) = match leaf {
                    l if l == rewards_leaf => (REWARDS, std::mem::take(&mut chunk.rewards)),
                    l if l == costs_leaf => (COSTS, std::mem::take(&mut chunk.costs)),
                    _ => continue,
                };
                let array: ArrayRef = Arc::new(Float32Array::from(values));
                let field = schema
                    .field_with_name(name)
                    .map_err(|e| ImportError::from_parquet(e.into()))?;
                write_leaves(&mut column_writer, field, &array).map_err(parquet_io)?;
                encoded.push((leaf, column_writer.close().map_err(parquet_io)?));
            }
            let mut row_group = writer.next_row_group().map_err(parquet_io)?;
            let pages = parquet.page_index_for_row_group(g);
            for (c, column) in parquet.row_group(g).columns().iter().enumerate() {
                let appended = match encoded.iter().position(|(leaf, _)| *leaf == c) {
                    Some(i) => encoded.swap_remove(i).1.append_to_row_group(&mut row_group),
                    None => row_group.append_column(
                        &self.file,
                        ColumnCloseResult {
                            bytes_written: column.compressed_size() as u64,
                            rows_written: rows as u64,
                            metadata: column.clone(),
                            bloom_filter: None,
                            column_index: pages.column_index(c).cloned(),
                            offset_index: pages.offset_index(c).cloned(),
                        },
                    ),
                };
                appended.map_err(parquet_io)?;
            }
            row_group.close().map_err(parquet_io)?;
            first_row += rows as u64;
        }
        writer.into_inner().map_err(parquet_io)
    }

    /// Row group `g`'s rewards, costs and done flags.
    fn scalars(&self, g: usize, rows: usize, first_row: u64, roots: &[usize]) -> Result<TransitionChunk, ReadError> {
        let builder = ParquetRecordBatchReaderBuilder::new_with_metadata(
            self.file.try_clone().map_err(ParquetError::from)?,
            self.metadata.clone(),
        );
        let mask = ProjectionMask::roots(builder.parquet_schema(), roots.iter().copied());
        let reader = builder
            .with_row_groups(vec![g])
            .with_projection(mask)
            .with_batch_size(rows.max(1))
            .build()?;
        let mut chunk = TransitionChunk::empty(0, 0);
        for batch in reader {
            let batch: RecordBatch = batch?;
            let base = first_row + chunk.len() as u64;
            let col = |name: &str| batch.column_by_name(name).expect("projected column").clone();
            chunk.rewards.extend(float_vector(base, REWARDS, &col(REWARDS))?);
            chunk.costs.extend(float_vector(base, COSTS, &col(COSTS))?);
            chunk.terminals.extend(flag_vector(base, TERMINALS, &col(TERMINALS))?);
            chunk.timeouts.extend(flag_vector(base, TIMEOUTS, &col(TIMEOUTS))?);
        }
        if chunk.len() != rows {
            return Err(ReadError::Layout(format!(
                "row group {g} gave {} rows, its footer says {rows}",
                chunk.len()
            )));
        }
        Ok(chunk)
    }
}

#[cfg(test)]
mod tests {
    use super::super::{DatasetWriter, row_group_rows};
    use super::*;
    use crate::synthetic::{SyntheticSpec, transitions};
    use crate::validate::{EpisodeTracker, Expectation};

    fn metadata() -> Vec<(String, String)> {
        vec![("dsrl.format".into(), crate::manifest::FORMAT.into())]
    }

    /// Some rows' rewards and costs changed, by their row in the file.
    fn relabel(first_row: u64, rows: &mut TransitionChunk) {
        for i in 0..rows.len() {
            let row = first_row + i as u64;
            if row % 7 == 3 || (row / 500) % 3 == 1 {
                rows.rewards[i] *= 1.5;
                rows.costs[i] = (row % 2) as f32;
            }
        }
    }

    /// The canonical bytes of these rows in row groups of at most `target_rows` rows (the full encode), and their
    /// episodes' lengths.
    fn written(chunks: &[TransitionChunk], max_episode_steps: u32, target_rows: usize) -> (Vec<u8>, Vec<usize>) {
        let (o, a) = (chunks[0].obs_dim, chunks[0].act_dim);
        let mut writer = DatasetWriter::new(Vec::new(), o, a, metadata()).unwrap();
        writer.set_target_rows(target_rows);
        let mut tracker = EpisodeTracker::new(Expectation {
            obs_dim: o,
            act_dim: a,
            max_episode_steps,
        });
        for chunk in chunks {
            writer.push(chunk, tracker.check(chunk).unwrap()).unwrap();
        }
        let lengths = tracker.finish().unwrap().iter().map(|e| e.length as usize).collect();
        (writer.finish().unwrap(), lengths)
    }

    #[test]
    fn copying_all_but_the_relabelled_columns_writes_the_file_a_full_encode_writes() {
        let catalog = crate::catalog::Catalog::embedded().unwrap();
        // Row groups of several episodes, and CarPush2's observation columns of several pages each.
        for (task, episodes, target_rows) in [
            ("OfflineCarCircle-v0", 30, 2500),
            ("OfflineCarPush2Gymnasium-v0", 9, 3000),
        ] {
            let task = catalog.get(task).unwrap();
            let mut spec = SyntheticSpec::for_task(task, episodes, 5);
            spec.chunk_rows = 777;
            let (o, a) = (spec.obs_dim, spec.act_dim);
            let chunks: Vec<TransitionChunk> = transitions(spec).collect();
            let (parent, lengths) = written(&chunks, task.max_episode_steps, target_rows);
            let mut first_row = 0;
            let relabelled: Vec<TransitionChunk> = chunks
                .into_iter()
                .map(|mut chunk| {
                    relabel(first_row, &mut chunk);
                    first_row += chunk.len() as u64;
                    chunk
                })
                .collect();
            let (expected, _) = written(&relabelled, task.max_episode_steps, target_rows);

            let file = tempfile::tempfile().unwrap();
            (&file).write_all(&parent).unwrap();
            let groups = row_group_rows(lengths.iter().copied(), target_rows);
            assert!(groups.len() > 2, "{}: several row groups: {groups:?}", task.id);
            let other_groups = row_group_rows(lengths.iter().copied(), target_rows * 2);
            assert_ne!(groups, other_groups);
            assert!(
                RelabelSource::open(file.try_clone().unwrap(), o, a, &other_groups)
                    .unwrap()
                    .is_none(),
                "other row groups than the parent's are declined"
            );
            let source = RelabelSource::open(file, o, a, &groups)
                .unwrap()
                .expect("the writer's own layout");
            let copied = source
                .write(Vec::new(), metadata(), |first_row, rows| {
                    relabel(first_row, rows);
                    Ok(())
                })
                .unwrap();
            assert!(copied == expected, "{}: the copy differs from a full encode", task.id);
            assert!(copied != parent, "{}: relabelled", task.id);
        }
    }
}
