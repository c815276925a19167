//! DSRL's HDF5 layout: a flat file with the seven keys `observations, next_observations, actions, rewards, costs,
//! terminals, timeouts` as N-row arrays, gzip-compressed (spec §1.3). Import reads it in row chunks (a MetaDrive
//! file is gigabytes); export writes the same layout so DSRL/OSRL code loads it with `get_dataset(h5path=...)`.

use std::path::Path;

use hdf5::types::TypeDescriptor;
use hdf5::{Dataset, File, Group};
use ndarray::s;

use crate::parquet_file::{
    ACTIONS, COSTS, DSRL_KEYS, NEXT_OBSERVATIONS, OBSERVATIONS, ParquetTransitions, REWARDS, ReadError, TERMINALS,
    TIMEOUTS,
};
use crate::transitions::TransitionChunk;
use crate::validate::{ValidationError, flags_from_numbers};

/// Target uncompressed size of one chunk read from HDF5.
const READ_CHUNK_BYTES: usize = 16 << 20;
/// Target uncompressed size of one HDF5 storage chunk when writing (h5py's auto-chunking aims near this).
const WRITE_CHUNK_BYTES: usize = 256 << 10;
/// gzip level h5py uses for `compression='gzip'`.
const GZIP_LEVEL: u8 = 4;
/// A key whose first chunk deflate shrinks by less than this share is written in deflate's stored blocks (level 0):
/// still the gzip filter every reader expects, without the cost of compressing what does not compress (float
/// observations shrink by ~6% at level 4, which took the export to ~30 MB/s on 2 cores).
const WORTH_COMPRESSING: f64 = 0.10;

#[derive(Debug, thiserror::Error)]
pub enum Hdf5Error {
    #[error("{0}")]
    Library(#[from] hdf5::Error),
    #[error("{0}")]
    Layout(String),
    #[error("{0}")]
    Value(#[from] ValidationError),
    #[error("{0}")]
    Parquet(#[from] ReadError),
}

/// Reads a DSRL HDF5 file chunk by chunk.
pub struct Hdf5Transitions {
    datasets: [Dataset; 7],
    rows: usize,
    obs_dim: usize,
    act_dim: usize,
    chunk_rows: usize,
    next_row: usize,
    ignored_keys: Vec<String>,
    // Keeps the file open while the datasets are read.
    _file: File,
}

impl Hdf5Transitions {
    pub fn open(path: &Path) -> Result<Self, Hdf5Error> {
        let file = File::open(path)?;
        // Like DSRL's `visititems`, every dataset anywhere in the file is a key; nested ones are "group/name".
        let mut all_keys = Vec::new();
        collect_dataset_keys(&file, "", &mut all_keys)?;
        let missing: Vec<&str> = DSRL_KEYS
            .iter()
            .copied()
            .filter(|k| !all_keys.iter().any(|a| a == k))
            .collect();
        if !missing.is_empty() {
            return Err(Hdf5Error::Layout(format!(
                "missing key(s) {}; a DSRL dataset has the top-level keys {} (found: {})",
                missing.join(", "),
                DSRL_KEYS.join(", "),
                if all_keys.is_empty() {
                    "none".to_owned()
                } else {
                    all_keys.join(", ")
                }
            )));
        }
        let ignored_keys = all_keys
            .into_iter()
            .filter(|k| !DSRL_KEYS.contains(&k.as_str()))
            .collect();
        let open = |k: &str| file.dataset(k);
        let datasets = [
            open(OBSERVATIONS)?,
            open(NEXT_OBSERVATIONS)?,
            open(ACTIONS)?,
            open(REWARDS)?,
            open(COSTS)?,
            open(TERMINALS)?,
            open(TIMEOUTS)?,
        ];
        let (rows, obs_dim) = matrix_shape(OBSERVATIONS, &datasets[0])?;
        let (next_rows, next_dim) = matrix_shape(NEXT_OBSERVATIONS, &datasets[1])?;
        let (act_rows, act_dim) = matrix_shape(ACTIONS, &datasets[2])?;
        if next_dim != obs_dim {
            return Err(Hdf5Error::Value(ValidationError::column(
                NEXT_OBSERVATIONS,
                format!("{next_dim} features per observation but observations has {obs_dim}"),
            )));
        }
        let mut lengths = vec![(NEXT_OBSERVATIONS, next_rows), (ACTIONS, act_rows)];
        for (i, key) in [REWARDS, COSTS, TERMINALS, TIMEOUTS].into_iter().enumerate() {
            lengths.push((key, vector_len(key, &datasets[3 + i])?));
        }
        if let Some((key, n)) = lengths.iter().find(|(_, n)| *n != rows) {
            return Err(Hdf5Error::Layout(format!(
                "key {key} has {n} rows but observations has {rows}"
            )));
        }
        for (i, key) in [OBSERVATIONS, NEXT_OBSERVATIONS, ACTIONS, REWARDS, COSTS]
            .into_iter()
            .enumerate()
        {
            if !matches!(datasets[i].dtype()?.to_descriptor()?, TypeDescriptor::Float(_)) {
                return Err(Hdf5Error::Layout(format!("key {key} must hold floats")));
            }
        }
        let row_bytes = 4 * (2 * obs_dim + act_dim + 4);
        let chunk_rows = (READ_CHUNK_BYTES / row_bytes).max(1);
        Ok(Hdf5Transitions {
            datasets,
            rows,
            obs_dim,
            act_dim,
            chunk_rows,
            next_row: 0,
            ignored_keys,
            _file: file,
        })
    }

    pub fn rows(&self) -> u64 {
        self.rows as u64
    }

    /// Keys of the file that are not part of the dataset format (e.g. MetaDrive's cost breakdown).
    pub fn ignored_keys(&self) -> &[String] {
        &self.ignored_keys
    }

    fn read_chunk(&self, a: usize, b: usize) -> Result<TransitionChunk, Hdf5Error> {
        let [obs, next, act, rew, cost, term, timeout] = &self.datasets;
        Ok(TransitionChunk {
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            observations: read_matrix(obs, a, b)?,
            next_observations: read_matrix(next, a, b)?,
            actions: read_matrix(act, a, b)?,
            rewards: read_vector_f32(rew, a, b)?,
            costs: read_vector_f32(cost, a, b)?,
            terminals: read_flags(TERMINALS, term, a, b)?,
            timeouts: read_flags(TIMEOUTS, timeout, a, b)?,
            episode: None,
            step: None,
        })
    }
}

impl Iterator for Hdf5Transitions {
    type Item = Result<TransitionChunk, Hdf5Error>;
    fn next(&mut self) -> Option<Self::Item> {
        if self.next_row >= self.rows {
            return None;
        }
        let a = self.next_row;
        let b = (a + self.chunk_rows).min(self.rows);
        self.next_row = b;
        Some(self.read_chunk(a, b))
    }
}

fn collect_dataset_keys(group: &Group, prefix: &str, out: &mut Vec<String>) -> Result<(), hdf5::Error> {
    for name in group.member_names()? {
        let key = if prefix.is_empty() {
            name.clone()
        } else {
            format!("{prefix}/{name}")
        };
        if let Ok(ds) = group.dataset(&name) {
            drop(ds);
            out.push(key);
        } else if let Ok(sub) = group.group(&name) {
            collect_dataset_keys(&sub, &key, out)?;
        }
    }
    Ok(())
}

fn matrix_shape(key: &str, ds: &Dataset) -> Result<(usize, usize), Hdf5Error> {
    match ds.shape()[..] {
        [n, d] if d > 0 => Ok((n, d)),
        ref other => Err(Hdf5Error::Layout(format!(
            "key {key} has shape {other:?}; expected (N, dim)"
        ))),
    }
}

fn vector_len(key: &str, ds: &Dataset) -> Result<usize, Hdf5Error> {
    match ds.shape()[..] {
        [n] | [n, 1] => Ok(n),
        ref other => Err(Hdf5Error::Layout(format!(
            "key {key} has shape {other:?}; expected (N,) or (N, 1)"
        ))),
    }
}

fn read_matrix(ds: &Dataset, a: usize, b: usize) -> Result<Vec<f32>, Hdf5Error> {
    // HDF5 converts float64 to float32 on read, as DSRL's `astype(np.float32)` does.
    let array = ds.read_slice_2d::<f32, _>(s![a..b, ..])?;
    Ok(array.into_iter().collect())
}

fn read_vector<T: hdf5::H5Type + Copy>(ds: &Dataset, a: usize, b: usize) -> Result<Vec<T>, Hdf5Error> {
    Ok(if ds.ndim() == 2 {
        ds.read_slice_2d::<T, _>(s![a..b, ..])?.into_iter().collect()
    } else {
        ds.read_slice_1d::<T, _>(s![a..b])?.to_vec()
    })
}

fn read_vector_f32(ds: &Dataset, a: usize, b: usize) -> Result<Vec<f32>, Hdf5Error> {
    read_vector::<f32>(ds, a, b)
}

/// What a DSRL HDF5 file holds, from its shapes and done flags alone (no observation is read): its rows, the width
/// of its observations, and its episodes (rows whose terminal or timeout flag is set), for checking a file against
/// the name it came under before uploading it.
pub fn summarize(path: &std::path::Path) -> Result<(u64, u64, u64), Hdf5Error> {
    let file = hdf5::File::open(path)?;
    let observations = file.dataset(OBSERVATIONS)?;
    let shape = observations.shape();
    let (rows, width) = (shape.first().copied().unwrap_or(0), shape.get(1).copied().unwrap_or(0));
    let (term, timeout) = (file.dataset(TERMINALS)?, file.dataset(TIMEOUTS)?);
    let mut episodes = 0u64;
    let chunk = 1 << 20;
    for a in (0..rows).step_by(chunk) {
        let b = (a + chunk).min(rows);
        let t = read_flags(TERMINALS, &term, a, b)?;
        let o = read_flags(TIMEOUTS, &timeout, a, b)?;
        episodes += t.iter().zip(&o).filter(|(t, o)| **t || **o).count() as u64;
    }
    Ok((rows as u64, width as u64, episodes))
}

/// Flags stored as HDF5 bool (h5py's enum), integers or floats; anything but 0/1 is an error.
fn read_flags(key: &str, ds: &Dataset, a: usize, b: usize) -> Result<Vec<bool>, Hdf5Error> {
    let numbers: Vec<f64> = match ds.dtype()?.to_descriptor()? {
        TypeDescriptor::Boolean => return read_vector::<bool>(ds, a, b),
        TypeDescriptor::Integer(_) => read_vector::<i64>(ds, a, b)?.into_iter().map(|v| v as f64).collect(),
        TypeDescriptor::Unsigned(_) => read_vector::<u64>(ds, a, b)?.into_iter().map(|v| v as f64).collect(),
        TypeDescriptor::Float(_) => read_vector::<f64>(ds, a, b)?,
        other => {
            return Err(Hdf5Error::Layout(format!(
                "key {key} holds {other}; expected bool or 0/1 numbers"
            )));
        }
    };
    Ok(flags_from_numbers(a as u64, key, numbers)?)
}

/// `raw` as a zlib stream (what HDF5's deflate filter stores) at `level` (0: stored blocks).
fn deflate(raw: &[u8], level: u32) -> std::io::Result<Vec<u8>> {
    let mut encoder =
        flate2::write::ZlibEncoder::new(Vec::with_capacity(raw.len() / 2), flate2::Compression::new(level));
    std::io::Write::write_all(&mut encoder, raw)?;
    encoder.finish()
}

/// The deflate level of a key from its first chunk: h5py's 4 where that shrinks it by at least
/// [`WORTH_COMPRESSING`], else 0.
fn deflate_level(first_chunk: &[u8]) -> std::io::Result<u32> {
    let shrunk = deflate(first_chunk, u32::from(GZIP_LEVEL))?.len();
    Ok(
        if (shrunk as f64) < (1.0 - WORTH_COMPRESSING) * first_chunk.len() as f64 {
            u32::from(GZIP_LEVEL)
        } else {
            0
        },
    )
}

/// One chunk's bytes of a key on its way to compression: its key index, its first row, its deflate level, its raw
/// (full-size, zero-padded) bytes.
type Raw = (usize, usize, u32, Vec<u8>);

/// A compressed chunk on its way to the writer: its key index (in `DSRL_KEYS`), its first row, its bytes.
type Compressed = (usize, usize, Vec<u8>);

/// A compression thread: deflates raw chunks `(key, first row, level, bytes)` until the reader stops sending or
/// the writer stops taking.
fn compress_chunks(
    raw: &std::sync::Mutex<std::sync::mpsc::Receiver<Raw>>,
    compressed: &std::sync::mpsc::SyncSender<Compressed>,
) {
    loop {
        let next = raw.lock().map(|rx| rx.recv());
        let Ok(Ok((key, row, level, bytes))) = next else { break };
        let Ok(bytes) = deflate(&bytes, level) else { break };
        if compressed.send((key, row, bytes)).is_err() {
            break;
        }
    }
}

/// The writer: the one thread that calls into libhdf5 once the datasets exist, writing each compressed chunk
/// directly at its row (`ids`: each key's dataset id).
fn write_chunks(
    ids: &[(hdf5_sys::h5i::hid_t, usize)],
    chunks: std::sync::mpsc::Receiver<Compressed>,
) -> Result<(), Hdf5Error> {
    for (key, row, bytes) in chunks {
        let offset: [u64; 2] = [row as u64, 0];
        let id = ids[key].0;
        // SAFETY: a live dataset id of this file, an offset of the dataset's rank (1 or 2; the second entry is read
        // only for matrices), and a buffer of `bytes.len()` bytes; under the library's lock.
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5d::H5Dwrite_chunk(
                id,
                hdf5_sys::h5p::H5P_DEFAULT,
                0,
                offset.as_ptr(),
                bytes.len(),
                bytes.as_ptr().cast(),
            )
        });
        if status < 0 {
            return Err(Hdf5Error::Layout(format!(
                "writing a chunk of {} at row {row}",
                DSRL_KEYS[key]
            )));
        }
    }
    Ok(())
}

/// Appends rows `rows` of the transitions `c` to key `key`'s chunk buffer, as HDF5 stores them (little-endian
/// float32, or one byte per bool); `dim` is the key's width.
fn append_rows(buf: &mut Vec<u8>, key: usize, c: &TransitionChunk, rows: std::ops::Range<usize>, dim: usize) {
    // HDF5's little-endian float32 is the machine's own layout here: one copy of the bytes.
    let floats = |values: &[f32], buf: &mut Vec<u8>| {
        if cfg!(target_endian = "little") {
            buf.extend_from_slice(arrow_buffer::ToByteSlice::to_byte_slice(values));
        } else {
            for v in values {
                buf.extend_from_slice(&v.to_le_bytes());
            }
        }
    };
    let (r, end) = (rows.start, rows.end);
    match key {
        0 => floats(&c.observations[r * dim..end * dim], buf),
        1 => floats(&c.next_observations[r * dim..end * dim], buf),
        2 => floats(&c.actions[r * dim..end * dim], buf),
        3 => floats(&c.rewards[r..end], buf),
        4 => floats(&c.costs[r..end], buf),
        5 => buf.extend(c.terminals[r..end].iter().map(|&b| u8::from(b))),
        _ => buf.extend(c.timeouts[r..end].iter().map(|&b| u8::from(b))),
    }
}

/// Writes a dataset in DSRL's HDF5 layout: float32 arrays, bool flags, the gzip filter, keys in DSRL's order, chunks
/// of about 256 kB as h5py makes them. The chunks are compressed on every core and written straight into the file
/// (`H5Dwrite_chunk`), so libhdf5's one-thread deflate is not the bound: the source is read, the chunks compressed
/// and written at once, in bounded memory. Each key is deflated at level 4 (h5py's), or stored in deflate's
/// uncompressed blocks when its first chunk shrinks by less than [`WORTH_COMPRESSING`] (decided before any chunk is
/// written, so the file is the same on every run). h5py and DSRL read the result like any gzip-filtered file.
pub fn write_dsrl_hdf5(mut source: ParquetTransitions, out: &Path) -> Result<(), Hdf5Error> {
    let rows = source.rows() as usize;
    let first = match source.next() {
        Some(chunk) => chunk?,
        None => return Err(Hdf5Error::Layout("the dataset has no transitions".into())),
    };
    let (obs_dim, act_dim) = (first.obs_dim, first.act_dim);
    let file = File::create(out)?;
    // Each key: its dataset, its width (1 for a vector) and bytes per value, and rows per chunk.
    let matrix = |name: &str, dim: usize| -> Result<(Dataset, usize), hdf5::Error> {
        let chunk = (WRITE_CHUNK_BYTES / (4 * dim)).clamp(1, rows);
        let ds = file
            .new_dataset::<f32>()
            .chunk((chunk, dim))
            .deflate(GZIP_LEVEL)
            .shape((rows, dim))
            .create(name)?;
        Ok((ds, chunk))
    };
    let vector = |name: &str, float: bool| -> Result<(Dataset, usize), hdf5::Error> {
        let chunk = (WRITE_CHUNK_BYTES / 4).clamp(1, rows);
        let builder = if float {
            file.new_dataset::<f32>()
        } else {
            file.new_dataset::<bool>()
        };
        Ok((
            builder.chunk(chunk).deflate(GZIP_LEVEL).shape(rows).create(name)?,
            chunk,
        ))
    };
    // In the order of `DSRL_KEYS`, which names them by index in errors.
    let keys = [
        (matrix(OBSERVATIONS, obs_dim)?, obs_dim, 4),
        (matrix(NEXT_OBSERVATIONS, obs_dim)?, obs_dim, 4),
        (matrix(ACTIONS, act_dim)?, act_dim, 4),
        (vector(REWARDS, true)?, 1, 4),
        (vector(COSTS, true)?, 1, 4),
        (vector(TERMINALS, false)?, 1, 1),
        (vector(TIMEOUTS, false)?, 1, 1),
    ];

    let workers = std::thread::available_parallelism().map_or(1, |n| n.get()).max(1);
    let (to_compress, compress_rx) = std::sync::mpsc::sync_channel::<Raw>(2 * workers);
    let compress_rx = std::sync::Arc::new(std::sync::Mutex::new(compress_rx));
    let (to_write, write_rx) = std::sync::mpsc::sync_channel::<Compressed>(2 * workers);
    let ids: Vec<(hdf5_sys::h5i::hid_t, usize)> = keys
        .iter()
        .map(|((ds, chunk), dim, _)| (ds.id(), chunk * dim))
        .collect();
    let result = std::thread::scope(|scope| -> Result<usize, Hdf5Error> {
        for _ in 0..workers {
            let (rx, tx) = (compress_rx.clone(), to_write.clone());
            scope.spawn(move || compress_chunks(&rx, &tx));
        }
        drop(to_write);
        let writer = scope.spawn(move || write_chunks(&ids, write_rx));
        // The reader: fills each key's current chunk and hands it over when full.
        let mut pending: Vec<Vec<u8>> = keys
            .iter()
            .map(|((_, chunk), dim, width)| Vec::with_capacity(chunk * dim * width))
            .collect();
        let mut chunk_start = [0usize; 7];
        let mut at = 0usize;
        // Each key's level, fixed by its first chunk.
        let mut levels: [Option<u32>; 7] = [None; 7];
        // Owns the sender: dropping it tells the compression threads that no chunk follows.
        let mut hand_over = move |key: usize, row: usize, raw: Vec<u8>| -> Result<(), Hdf5Error> {
            let level = match levels[key] {
                Some(level) => level,
                None => {
                    let level =
                        deflate_level(&raw).map_err(|e| Hdf5Error::Layout(format!("compressing a chunk: {e}")))?;
                    *levels.get_mut(key).expect("seven keys") = Some(level);
                    level
                }
            };
            to_compress
                .send((key, row, level, raw))
                .map_err(|_| Hdf5Error::Layout("a compression thread stopped".into()))
        };
        for chunk in std::iter::once(Ok(first)).chain(source) {
            let c = chunk?;
            if at + c.len() > rows {
                return Err(Hdf5Error::Layout(
                    "the Parquet file has more rows than its footer says".into(),
                ));
            }
            for (key, ((_, chunk_rows), dim, _)) in keys.iter().enumerate() {
                // Rows of `c` in segments that end where this key's chunks end.
                let mut r = 0usize;
                while r < c.len() {
                    let room = chunk_start[key] + chunk_rows - (at + r);
                    let end = (r + room).min(c.len());
                    let buf = &mut pending[key];
                    append_rows(buf, key, &c, r..end, *dim);
                    if at + end - chunk_start[key] == *chunk_rows {
                        let full = std::mem::replace(buf, Vec::with_capacity(buf.capacity()));
                        hand_over(key, chunk_start[key], full)?;
                        chunk_start[key] = at + end;
                    }
                    r = end;
                }
            }
            at += c.len();
        }
        // The last, partial chunks: stored at full size, padded with zeros (HDF5's fill value).
        for (key, ((_, chunk_rows), dim, width)) in keys.iter().enumerate() {
            let mut buf = std::mem::take(&mut pending[key]);
            if !buf.is_empty() {
                buf.resize(chunk_rows * dim * width, 0);
                hand_over(key, chunk_start[key], buf)?;
            }
        }
        drop(hand_over);
        writer
            .join()
            .map_err(|_| Hdf5Error::Layout("the HDF5 writer thread panicked".into()))??;
        Ok(at)
    });
    let at = result?;
    if at != rows {
        return Err(Hdf5Error::Layout(format!(
            "the Parquet file has {at} rows but its footer says {rows}"
        )));
    }
    drop(keys);
    file.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn what_deflate_cannot_shrink_is_stored_and_the_rest_deflated() {
        // Bytes from a linear congruential generator: deflate saves nothing on them.
        let mut x = 1u64;
        let noise: Vec<u8> = (0..262_144)
            .map(|_| {
                x = x
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                (x >> 56) as u8
            })
            .collect();
        assert_eq!(deflate_level(&noise).unwrap(), 0);
        assert_eq!(deflate_level(&[0u8; 262_144]).unwrap(), u32::from(GZIP_LEVEL));
        // Stored blocks are still a zlib stream, which inflates to the input.
        let stored = deflate(&noise, 0).unwrap();
        let mut back = Vec::new();
        std::io::Read::read_to_end(&mut flate2::read::ZlibDecoder::new(&stored[..]), &mut back).unwrap();
        assert_eq!(back, noise);
    }
}
