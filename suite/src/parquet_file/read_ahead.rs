//! Reading a canonical file's row groups on several threads, handed out in file order.
//!
//! Decoding (zstd, byte-stream-split, the list columns) and converting to rows is one thread's work in a plain read,
//! and it is what bounds the HDF5 export. Row groups are independent, so thread `k` of `n` reads groups `k`, `k +
//! n`, ... with a reader of its own (its own open file: clones of one descriptor would share its offset), each
//! at most one chunk ahead of the caller, and the caller takes the groups' chunks in turn. The rows are those of a
//! plain read; only the chunk boundaries differ (a chunk never spans two row groups).

use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, sync_channel};

use parquet::arrow::arrow_reader::{ArrowReaderMetadata, ParquetRecordBatchReaderBuilder};
use parquet::errors::ParquetError;

use super::{
    ActiveWriter, EncodingBudget, EncodingHelpers, NEXT_OBSERVATIONS, PROCESS_BUDGET, ParquetTransitions, ReadError,
};
use crate::transitions::TransitionChunk;

/// What a reading thread hands over: its current row group's next chunk, or `None` at the group's end.
type Read = Option<Result<TransitionChunk, ReadError>>;

pub(super) struct ReadAhead {
    /// Thread `k`'s chunks: those of row groups `k`, `k + n`, ...
    threads: Vec<Receiver<Read>>,
    /// This read counts as a write, and its threads beyond one as helpers, in the budget the Parquet writer takes
    /// its helper threads from, while it lives: see [`ParquetTransitions::open_read_ahead`].
    _active: ActiveWriter,
    _helpers: EncodingHelpers,
    groups: usize,
    /// The row group whose chunks come next; `groups` once done (or failed).
    next_group: usize,
}

impl ParquetTransitions {
    /// Like [`ParquetTransitions::open`], decoding the row groups on up to `threads` threads ahead of the caller
    /// (about one chunk of memory each). The threads beyond one are taken, as the Parquet writer takes its helper
    /// threads, only for cores no other write or helper is using: a lone read (the HDF5 export) decodes on the idle
    /// cores, one beside other derivations reads on the calling thread and adds no buffers. Files of one row group,
    /// and those whose next observations may be left out (the compact form: a left-out row takes the following
    /// row's observation), are read on the calling thread too.
    pub fn open_read_ahead(path: &Path, threads: usize) -> Result<Self, ReadError> {
        Self::read_ahead(path, threads, &PROCESS_BUDGET, true)
    }

    /// `open_read_ahead`, counted in `budget`; `budgeted: false` (tests) takes the threads whatever other work runs.
    fn read_ahead(
        path: &Path,
        threads: usize,
        budget: &'static EncodingBudget,
        budgeted: bool,
    ) -> Result<Self, ReadError> {
        let file = std::fs::File::open(path).map_err(ParquetError::from)?;
        let metadata = ArrowReaderMetadata::load(&file, Default::default())?;
        let mut reader = Self::from_builder(
            ParquetRecordBatchReaderBuilder::new_with_metadata(file, metadata.clone()),
            0,
        )?;
        let groups = metadata.metadata().num_row_groups();
        let whole_rows = metadata
            .schema()
            .field_with_name(NEXT_OBSERVATIONS)
            .is_ok_and(|f| !f.is_nullable());
        if groups < 2 || !whole_rows {
            return Ok(reader);
        }
        let active = budget.writer();
        let (helpers, threads) = active.threads(threads.min(groups).saturating_sub(1), budgeted);
        if threads >= 2 {
            reader.ahead = ReadAhead::start(path.to_owned(), metadata, threads, active, helpers);
        }
        Ok(reader)
    }
}

impl ReadAhead {
    /// `None` if a thread could not be started: the caller reads on its own thread instead.
    fn start(
        path: PathBuf,
        metadata: ArrowReaderMetadata,
        threads: usize,
        active: ActiveWriter,
        helpers: EncodingHelpers,
    ) -> Option<ReadAhead> {
        let groups = metadata.metadata().num_row_groups();
        let mut first_rows = Vec::with_capacity(groups);
        let mut row = 0u64;
        for group in metadata.metadata().row_groups() {
            first_rows.push(row);
            row += group.num_rows() as u64;
        }
        let first_rows = std::sync::Arc::new(first_rows);
        let mut receivers = Vec::with_capacity(threads);
        for k in 0..threads {
            let (tx, rx) = sync_channel(1);
            let (path, metadata, first_rows) = (path.clone(), metadata.clone(), first_rows.clone());
            let read = move || {
                for g in (k..groups).step_by(threads) {
                    let opened = std::fs::File::open(&path)
                        .map_err(|e| ReadError::from(ParquetError::from(e)))
                        .and_then(|file| {
                            let builder = ParquetRecordBatchReaderBuilder::new_with_metadata(file, metadata.clone())
                                .with_row_groups(vec![g]);
                            ParquetTransitions::from_builder(builder, first_rows[g])
                        });
                    let rows = match opened {
                        Ok(rows) => rows,
                        Err(e) => {
                            let _ = tx.send(Some(Err(e)));
                            return;
                        }
                    };
                    for chunk in rows {
                        let failed = chunk.is_err();
                        // A closed channel: the caller stopped reading (or dropped the reader).
                        if tx.send(Some(chunk)).is_err() || failed {
                            return;
                        }
                    }
                    if tx.send(None).is_err() {
                        return;
                    }
                }
            };
            std::thread::Builder::new()
                .name(format!("parquet-read-{k}"))
                .spawn(read)
                .ok()?;
            receivers.push(rx);
        }
        Some(ReadAhead {
            threads: receivers,
            _active: active,
            _helpers: helpers,
            groups,
            next_group: 0,
        })
    }

    pub(super) fn next(&mut self) -> Option<Result<TransitionChunk, ReadError>> {
        while self.next_group < self.groups {
            let thread = &self.threads[self.next_group % self.threads.len()];
            match thread.recv() {
                Ok(Some(Ok(chunk))) => return Some(Ok(chunk)),
                Ok(None) => self.next_group += 1,
                Ok(Some(Err(e))) => {
                    self.next_group = self.groups;
                    return Some(Err(e));
                }
                Err(_) => {
                    let group = std::mem::replace(&mut self.next_group, self.groups);
                    return Some(Err(ReadError::Layout(format!(
                        "the thread reading row group {group} stopped"
                    ))));
                }
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::written_as;
    use super::*;

    /// All rows of a reader, in one chunk, and how many chunks they came in.
    fn all_rows(reader: ParquetTransitions) -> (TransitionChunk, usize) {
        let mut rows: Option<TransitionChunk> = None;
        let mut chunks = 0;
        for chunk in reader {
            let chunk = chunk.unwrap();
            chunks += 1;
            match &mut rows {
                Some(rows) => {
                    rows.append(&chunk);
                    let (episode, step) = (rows.episode.as_mut().unwrap(), rows.step.as_mut().unwrap());
                    episode.extend(chunk.episode.unwrap());
                    step.extend(chunk.step.unwrap());
                }
                None => rows = Some(chunk),
            }
        }
        (rows.unwrap(), chunks)
    }

    #[test]
    fn row_groups_read_ahead_on_threads_give_the_rows_of_a_plain_read() {
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(file.path(), written_as("OfflineCarCircle-v0", 30, 1, 700, 8192)).unwrap();
        let (plain, _) = all_rows(ParquetTransitions::open(file.reopen().unwrap()).unwrap());
        for threads in [2, 3, 64] {
            let reader = ParquetTransitions::read_ahead(file.path(), threads, &PROCESS_BUDGET, false).unwrap();
            assert!(reader.ahead.is_some(), "{threads} threads read ahead");
            let (ahead, chunks) = all_rows(reader);
            assert!(chunks > 2, "several row groups: {chunks} chunks");
            assert!(ahead == plain, "{threads} threads: other rows than a plain read");
        }
        // Stopping early ends the threads' work instead of blocking them for good.
        let mut reader = ParquetTransitions::read_ahead(file.path(), 2, &PROCESS_BUDGET, false).unwrap();
        assert!(reader.next().unwrap().is_ok());
        drop(reader);
    }

    #[test]
    fn a_read_beside_other_work_reads_on_its_own_thread() {
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(file.path(), written_as("OfflineCarCircle-v0", 30, 1, 700, 8192)).unwrap();
        let (plain, _) = all_rows(ParquetTransitions::open(file.reopen().unwrap()).unwrap());
        // A budget of its own: the other tests of this process write files at the same time.
        static BUDGET: EncodingBudget = EncodingBudget::new();
        // Every core busy: no threads are taken.
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let busy: Vec<ActiveWriter> = (0..cores).map(|_| BUDGET.writer()).collect();
        let reader = ParquetTransitions::read_ahead(file.path(), 2, &BUDGET, true).unwrap();
        assert!(reader.ahead.is_none(), "no idle core: read on the calling thread");
        assert!(all_rows(reader).0 == plain);
        drop(busy);
        assert_eq!(BUDGET.counts(), (0, 0));
        // An idle core: a helper is taken, counted while the reader lives and given back when it is dropped.
        let reader = ParquetTransitions::read_ahead(file.path(), 2, &BUDGET, true).unwrap();
        if cores >= 2 {
            assert!(reader.ahead.is_some(), "an idle core: read ahead");
            assert_eq!(BUDGET.counts(), (1, 1), "a read ahead counts while it lives");
        }
        assert!(all_rows(reader).0 == plain);
        assert_eq!(BUDGET.counts(), (0, 0));
    }
}
