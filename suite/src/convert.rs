//! Turning a source file (DSRL HDF5, or Parquet from any writer) into the canonical Parquet layout: read in
//! chunks, validate against the task, number episodes and steps, write, hash. The same path serves uploads,
//! the starter datasets and the data pipeline, so every hosted version went through the same checks.

use std::fs::File;
use std::io::{self, BufWriter, Read};
use std::path::Path;

use crate::catalog::{ObservationSpace, Task};
use crate::episode::EpisodeSummary;
use crate::hashing::HashingWriter;
#[cfg(feature = "hdf5")]
use crate::hdf5_file::{Hdf5Error, Hdf5Transitions};
use crate::ids::VersionId;
use crate::parquet_file::{DatasetWriter, ParquetTransitions, ReadError, RelabelSource, row_group_rows, target_rows};
use crate::transitions::TransitionChunk;
use crate::validate::{EpisodeTracker, Expectation, ValidationError};
use crate::writeback::WritebackFile;

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SourceFormat {
    Parquet,
    Hdf5,
}

impl SourceFormat {
    pub fn as_str(self) -> &'static str {
        match self {
            SourceFormat::Parquet => "parquet",
            SourceFormat::Hdf5 => "hdf5",
        }
    }

    /// Recognizes a file by its magic bytes (Parquet `PAR1`, HDF5's 8-byte signature at offset 0).
    pub fn sniff(path: &Path) -> io::Result<Option<SourceFormat>> {
        let mut head = [0u8; 8];
        let mut file = File::open(path)?;
        let mut filled = 0;
        while filled < head.len() {
            match file.read(&mut head[filled..])? {
                0 => break,
                n => filled += n,
            }
        }
        Ok(if filled >= 4 && &head[..4] == b"PAR1" {
            Some(SourceFormat::Parquet)
        } else if filled == 8 && head == *b"\x89HDF\r\n\x1a\n" {
            Some(SourceFormat::Hdf5)
        } else {
            None
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The data breaks a rule of the format or the task (names the row and column).
    #[error("{0}")]
    Invalid(#[from] ValidationError),
    /// The file cannot be read as the format it claims to be, or lacks the dataset's keys.
    #[error("not a usable {format} dataset: {message}")]
    Malformed { format: &'static str, message: String },
    /// Neither Parquet nor HDF5.
    #[error("unrecognized file format: expected Parquet (starts with PAR1) or HDF5 (DSRL's layout)")]
    UnknownFormat,
    #[error("I/O error: {0}")]
    Io(#[from] io::Error),
}

impl ImportError {
    pub(crate) fn from_parquet(e: ReadError) -> Self {
        match e {
            ReadError::Value(v) => ImportError::Invalid(v),
            other => ImportError::Malformed {
                format: "Parquet",
                message: other.to_string(),
            },
        }
    }
    #[cfg(feature = "hdf5")]
    fn from_hdf5(e: Hdf5Error) -> Self {
        match e {
            Hdf5Error::Value(v) => ImportError::Invalid(v),
            other => ImportError::Malformed {
                format: "HDF5",
                message: other.to_string(),
            },
        }
    }
}

/// What a canonical file holds, as measured while writing it.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Converted {
    pub version: VersionId,
    pub byte_size: u64,
    pub episode_index: Vec<EpisodeSummary>,
    /// Source columns or keys that are not part of the format and were not kept.
    pub dropped_columns: Vec<String>,
}

/// Converts an uploaded file (Parquet or DSRL HDF5) to the canonical layout at `out`, validating it against
/// `task` in the given observation space.
pub fn import_file(
    source: &Path,
    task: &Task,
    space: ObservationSpace,
    out: &Path,
) -> Result<(SourceFormat, Converted), ImportError> {
    let format = SourceFormat::sniff(source)?.ok_or(ImportError::UnknownFormat)?;
    let converted = match format {
        SourceFormat::Parquet => {
            let reader = ParquetTransitions::open(File::open(source)?).map_err(ImportError::from_parquet)?;
            let dropped = reader.ignored_columns().to_vec();
            write_canonical(
                task,
                space,
                reader.map(|c| c.map_err(ImportError::from_parquet)),
                dropped,
                out,
            )?
        }
        #[cfg(not(feature = "hdf5"))]
        SourceFormat::Hdf5 => {
            return Err(ImportError::Malformed {
                format: "HDF5",
                message: "this build reads no HDF5 (dsrl-suite without its `hdf5` feature)".into(),
            });
        }
        #[cfg(feature = "hdf5")]
        SourceFormat::Hdf5 => {
            let reader = Hdf5Transitions::open(source).map_err(ImportError::from_hdf5)?;
            let dropped = reader.ignored_keys().to_vec();
            write_canonical(
                task,
                space,
                reader.map(|c| c.map_err(ImportError::from_hdf5)),
                dropped,
                out,
            )?
        }
    };
    Ok((format, converted))
}

/// Validates `chunks` against `task` and writes them in the canonical layout to `out` (flushed and synced).
/// Deterministic: the same rows give the same bytes and version id.
pub fn write_canonical(
    task: &Task,
    space: ObservationSpace,
    chunks: impl Iterator<Item = Result<TransitionChunk, ImportError>>,
    dropped_columns: Vec<String>,
    out: &Path,
) -> Result<Converted, ImportError> {
    write_form(task, space, chunks, dropped_columns, out, false)
}

/// Writes the compact form of a dataset (see `parquet_file`): what a committed starter file holds. Ingesting it
/// gives the canonical file of the same rows, so the version id is the canonical one; returns the compact file's
/// size in bytes.
pub fn write_compact(
    task: &Task,
    space: ObservationSpace,
    chunks: impl Iterator<Item = Result<TransitionChunk, ImportError>>,
    out: &Path,
) -> Result<u64, ImportError> {
    Ok(write_form(task, space, chunks, Vec::new(), out, true)?.byte_size)
}

fn write_form(
    task: &Task,
    space: ObservationSpace,
    chunks: impl Iterator<Item = Result<TransitionChunk, ImportError>>,
    dropped_columns: Vec<String>,
    out: &Path,
    compact: bool,
) -> Result<Converted, ImportError> {
    let expect = Expectation {
        obs_dim: task.observation_dim(space) as usize,
        act_dim: task.act_dim as usize,
        max_episode_steps: task.max_episode_steps,
    };
    if space == ObservationSpace::Paper && task.obs_dim_paper == task.obs_dim {
        return Err(ValidationError::column(
            "observations",
            format!(
                "{}'s paper and simulator observation spaces are the same ({} features); the paper label is only \
                 for tasks where they differ (MetaDrive)",
                task.id, task.obs_dim
            ),
        )
        .into());
    }
    let sink = file_sink(out)?;
    let mut writer = DatasetWriter::with_form(
        sink,
        expect.obs_dim,
        expect.act_dim,
        file_metadata(task, space),
        compact,
    )
    .map_err(parquet_io)?;
    let mut tracker = EpisodeTracker::new(expect);
    for chunk in chunks {
        let chunk = chunk?;
        if tracker.rows_seen() == 0 {
            check_space(task, space, &chunk)?;
        }
        let numbering = tracker.check(&chunk)?;
        writer.push(&chunk, numbering).map_err(parquet_io)?;
    }
    let episode_index = tracker.finish()?;
    let sink = writer.finish().map_err(parquet_io)?;
    finish_file(sink, episode_index, dropped_columns)
}

/// The footer's key-value metadata of a dataset of `task`.
fn file_metadata(task: &Task, space: ObservationSpace) -> Vec<(String, String)> {
    vec![
        ("dsrl.format".to_owned(), crate::manifest::FORMAT.to_owned()),
        ("dsrl.task".to_owned(), task.id.to_string()),
        ("dsrl.observation_space".to_owned(), space.as_str().to_owned()),
    ]
}

type FileSink = HashingWriter<BufWriter<WritebackFile>>;

/// A new dataset file at `out`, hashed as it is written, its write-back to disk started as it grows.
fn file_sink(out: &Path) -> io::Result<FileSink> {
    Ok(HashingWriter::new(BufWriter::with_capacity(
        8 << 20,
        WritebackFile::new(File::create(out)?),
    )))
}

/// Flushes and syncs a written dataset file; its version id is the digest of its bytes.
fn finish_file(
    sink: FileSink,
    episode_index: Vec<EpisodeSummary>,
    dropped_columns: Vec<String>,
) -> Result<Converted, ImportError> {
    let (buffered, digest, byte_size) = sink.finish();
    let file = buffered.into_inner().map_err(|e| e.into_error())?.into_inner();
    file.sync_all()?;
    Ok(Converted {
        version: VersionId::from_digest(&digest),
        byte_size,
        episode_index,
        dropped_columns,
    })
}

/// Writes to `out` the canonical dataset of `parent`'s rows with only their rewards and costs changed by `relabel`
/// (called per row group with its first row and its scalar columns, see [`RelabelSource::write`]), copying every
/// other column chunk of `parent` instead of encoding it again: the same file as decoding the parent, relabelling
/// and writing with [`write_canonical`]. `episodes` is the parent's episode index. `None` (and nothing written)
/// when `parent` is not this writer's canonical layout of those episodes: the caller writes it the long way.
pub fn write_relabelled(
    task: &Task,
    space: ObservationSpace,
    parent: &Path,
    episodes: &[EpisodeSummary],
    mut relabel: impl FnMut(u64, &mut TransitionChunk),
    out: &Path,
) -> Result<Option<Converted>, ImportError> {
    let (obs_dim, act_dim) = (task.observation_dim(space) as usize, task.act_dim as usize);
    let groups = row_group_rows(
        episodes.iter().map(|e| e.length as usize),
        target_rows(obs_dim, act_dim),
    );
    let Some(source) =
        RelabelSource::open(File::open(parent)?, obs_dim, act_dim, &groups).map_err(ImportError::from_parquet)?
    else {
        return Ok(None);
    };
    let sink = file_sink(out)?;
    // The rows' other columns are the parent's, checked when it was written; the tracker checks the new values and
    // the episodes, and makes the output's episode index.
    let mut tracker = EpisodeTracker::new(Expectation {
        obs_dim: 0,
        act_dim: 0,
        max_episode_steps: task.max_episode_steps,
    });
    let sink = source.write(sink, file_metadata(task, space), |first_row, chunk| {
        relabel(first_row, chunk);
        tracker.check(chunk)?;
        Ok(())
    })?;
    let episode_index = tracker.finish()?;
    finish_file(sink, episode_index, Vec::new()).map(Some)
}

/// A clear message for the common mismatch: MetaDrive data in the paper's 261-feature space.
fn check_space(task: &Task, space: ObservationSpace, chunk: &TransitionChunk) -> Result<(), ValidationError> {
    let expected = task.observation_dim(space) as usize;
    if chunk.obs_dim == expected {
        return Ok(());
    }
    let hint = if space == ObservationSpace::Simulator && chunk.obs_dim == task.obs_dim_paper as usize {
        format!(
            "; that is the paper's observation space, not the {expected} features the simulator pinned here \
             produces, so policies trained on it cannot be scored here. To host it anyway, ingest with \
             observation_space=paper: it is then labelled as such and not tagged latest"
        )
    } else {
        String::new()
    };
    Err(ValidationError::column(
        "observations",
        format!(
            "{} features per observation, but {} expects {expected}{hint}",
            chunk.obs_dim, task.id
        ),
    ))
}

/// The canonical writer writes to a local file: its errors are I/O errors, not problems with the upload.
pub(crate) fn parquet_io(e: parquet::errors::ParquetError) -> ImportError {
    ImportError::Io(io::Error::other(e))
}

/// The name of part `index` (from 1) of `count` of a starter dataset named `name` (`<stem>.parquet`):
/// `<stem>.part-<index>-of-<count>.parquet`. A dataset too large for one committed file is committed in parts of
/// whole episodes, each a valid compact dataset on its own; ingest joins them back (see `join_compact_parts`).
pub fn part_file_name(name: &str, index: usize, count: usize) -> String {
    let stem = name.strip_suffix(".parquet").unwrap_or(name);
    format!("{stem}.part-{index}-of-{count}.parquet")
}

/// The inverse of `part_file_name`: `(dataset name, index, count)` for a part's file name, `None` for any other.
pub fn parse_part_file_name(file_name: &str) -> Option<(String, usize, usize)> {
    let stem = file_name.strip_suffix(".parquet")?;
    let (stem, part) = stem.rsplit_once(".part-")?;
    let (index, count) = part.split_once("-of-")?;
    let (index, count): (usize, usize) = (index.parse().ok()?, count.parse().ok()?);
    (index >= 1 && index <= count).then(|| (format!("{stem}.parquet"), index, count))
}

/// Splits the canonical file `canonical`, whose episodes are `episodes` (its `Converted::episode_index`), into
/// `outs.len()` compact files of consecutive whole episodes, about the same number of rows each, numbered from
/// episode 0 on their own; returns each file's size in bytes. Joined in order (`join_compact_parts`), they give the
/// canonical file back, hence its version id. With one output it is the compact form of the whole file: the
/// committed single-file starters are byte-identical to it (checked on them when this replaced a separate copy).
pub fn split_compact(
    task: &Task,
    space: ObservationSpace,
    canonical: &Path,
    episodes: &[EpisodeSummary],
    outs: &[std::path::PathBuf],
) -> Result<Vec<u64>, ImportError> {
    let malformed = |e: ReadError| ImportError::Io(io::Error::other(e));
    // Each part ends at the first episode end past its share of the rows.
    let ends: Vec<u64> = episodes.iter().map(|e| e.start + u64::from(e.length)).collect();
    let rows = ends.last().copied().unwrap_or(0);
    if outs.is_empty() || ends.len() < outs.len() {
        return Err(ValidationError::column(
            "terminals",
            format!("{} episodes cannot be split into {} parts", ends.len(), outs.len()),
        )
        .into());
    }
    let mut bounds = Vec::with_capacity(outs.len());
    let mut used = 0; // episodes already given to a part
    for k in 1..=outs.len() {
        let share = rows * k as u64 / outs.len() as u64;
        // Leave at least one episode for each later part.
        let last_allowed = ends.len() - (outs.len() - k) - 1;
        let end = ends[used..=last_allowed]
            .iter()
            .position(|&e| e >= share)
            .map_or(last_allowed, |p| used + p);
        bounds.push(ends[end]);
        used = end + 1;
    }

    let mut reader = ParquetTransitions::open(File::open(canonical)?).map_err(malformed)?;
    let mut pending: Option<TransitionChunk> = None;
    let mut sizes = Vec::with_capacity(outs.len());
    let mut start = 0u64;
    for (out, end) in outs.iter().zip(bounds) {
        let mut remaining = (end - start) as usize;
        start = end;
        let rows_of_part = std::iter::from_fn(|| {
            if remaining == 0 {
                return None;
            }
            let mut chunk = match pending.take() {
                Some(chunk) => chunk,
                None => match reader.next()? {
                    Ok(chunk) => chunk,
                    Err(e) => return Some(Err(malformed(e))),
                },
            };
            if chunk.len() > remaining {
                // `take_front` leaves the rest in `chunk`: it waits for the next part.
                let front = chunk.take_front(remaining);
                pending = Some(std::mem::replace(&mut chunk, front));
            }
            remaining -= chunk.len();
            // Each part numbers its episodes from 0: it is a dataset on its own.
            chunk.episode = None;
            chunk.step = None;
            Some(Ok(chunk))
        });
        sizes.push(write_compact(task, space, rows_of_part, out)?);
    }
    Ok(sizes)
}

/// Joins the parts of a dataset (`split_compact`'s files, in order) into one compact file at `out`, validating
/// every part's rows as any upload's; returns its size in bytes. Each part's episode numbers are checked against
/// its own done flags, then continue the previous part's.
pub fn join_compact_parts(
    task: &Task,
    space: ObservationSpace,
    parts: &[std::path::PathBuf],
    out: &Path,
) -> Result<u64, ImportError> {
    let mut readers = Vec::with_capacity(parts.len());
    for part in parts {
        readers.push(ParquetTransitions::open(File::open(part)?).map_err(ImportError::from_parquet)?);
    }
    let mut readers = readers.into_iter();
    let mut current = readers.next();
    // Episodes in the parts before the current one, and ended so far in the current one.
    let (mut offset, mut ended) = (0u32, 0u32);
    let chunks = std::iter::from_fn(move || {
        loop {
            match current.as_mut()?.next() {
                Some(Ok(mut chunk)) => {
                    if let Some(episodes) = &mut chunk.episode {
                        episodes.iter_mut().for_each(|e| *e = e.saturating_add(offset));
                    }
                    ended += (0..chunk.len()).filter(|&i| chunk.is_done(i)).count() as u32;
                    return Some(Ok(chunk));
                }
                Some(Err(e)) => return Some(Err(ImportError::from_parquet(e))),
                None => {
                    offset += std::mem::take(&mut ended);
                    current = readers.next();
                }
            }
        }
    });
    write_compact(task, space, chunks, out)
}
