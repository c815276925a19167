//! Turning a plan into data: the kept episodes are gathered in output order (one sequential read of the parent
//! file), outliers are relabelled, observation noise is added exactly as NumPy would add it, and the result is
//! written as a canonical dataset version.

use std::path::Path;

use crate::plan::Plan;
use dsrl_pynumerics::numpy_math::numpy_std_f32_nd;
use dsrl_suite::catalog::{ObservationSpace, Task};
use dsrl_suite::convert::{Converted, ImportError, write_canonical, write_relabelled};
use dsrl_suite::episode::EpisodeSummary;
use dsrl_suite::parquet_file::ParquetTransitions;
use dsrl_suite::transitions::TransitionChunk;

/// The filtered transitions, in output order, in memory (NumPy's reference holds them in memory too).
pub fn gather(
    parent: &Path,
    episodes: &[EpisodeSummary],
    plan: &Plan,
    obs_dim: usize,
    act_dim: usize,
) -> Result<TransitionChunk, ImportError> {
    // Output row where each kept input episode starts.
    let mut out_start = vec![usize::MAX; episodes.len()];
    let mut total = 0usize;
    for &e in &plan.order {
        out_start[e] = total;
        total += episodes[e].length as usize;
    }
    let mut out = TransitionChunk {
        obs_dim,
        act_dim,
        observations: vec![0.0; total * obs_dim],
        next_observations: vec![0.0; total * obs_dim],
        actions: vec![0.0; total * act_dim],
        rewards: vec![0.0; total],
        costs: vec![0.0; total],
        terminals: vec![false; total],
        timeouts: vec![false; total],
        episode: None,
        step: None,
    };
    for_each_episode_piece(parent, episodes, |chunk, episode, steps, rows| {
        if out_start[episode] != usize::MAX {
            copy_rows(
                chunk,
                rows.start,
                &mut out,
                out_start[episode] + steps.start,
                rows.len(),
            );
        }
        Ok(())
    })?;
    for (&e, steps) in &plan.relabels {
        let start = out_start[e];
        if start == usize::MAX {
            continue; // relabelled, then removed by a later step
        }
        let len = episodes[e].length as usize;
        out.costs[start..start + len].fill(0.0);
        for &s in steps {
            out.costs[start + s] = 1.0;
        }
        for r in &mut out.rewards[start..start + len] {
            *r *= 1.5; // a float32 array times a Python float stays float32
        }
    }
    if let Some(scale) = plan.noise_scale {
        let mut generator = plan.generator.clone();
        for values in [&mut out.observations, &mut out.next_observations] {
            let std = numpy_std_f32_nd(values) as f64;
            for v in values.iter_mut() {
                // obs += noise_scale * rng.normal(0, std): float64 noise, added in float64, stored as float32.
                let noise = scale * generator.normal(0.0, std);
                *v = (*v as f64 + noise) as f32;
            }
        }
    }
    Ok(out)
}

/// Reads the parent once, in order, and calls `visit(chunk, episode, steps, rows)` for each non-empty piece of an
/// episode that a chunk holds: `steps` are the piece's steps within its episode, `rows` the same rows within the chunk.
fn for_each_episode_piece(
    parent: &Path,
    episodes: &[EpisodeSummary],
    mut visit: impl FnMut(
        &TransitionChunk,
        usize,
        std::ops::Range<usize>,
        std::ops::Range<usize>,
    ) -> Result<(), ImportError>,
) -> Result<(), ImportError> {
    let malformed = |e: dsrl_suite::parquet_file::ReadError| ImportError::Malformed {
        format: "Parquet",
        message: e.to_string(),
    };
    let reader = ParquetTransitions::open(std::fs::File::open(parent)?).map_err(malformed)?;
    let mut row = 0u64; // first row of the current chunk
    let mut episode = 0usize; // episode containing `row`
    for chunk in reader {
        let chunk = chunk.map_err(malformed)?;
        let end = row + chunk.len() as u64;
        while episode < episodes.len() && episodes[episode].start < end {
            let e = &episodes[episode];
            let (e_start, e_end) = (e.start, e.start + e.length as u64);
            let (a, b) = (e_start.max(row), e_end.min(end));
            if a < b {
                let steps = (a - e_start) as usize..(b - e_start) as usize;
                visit(&chunk, episode, steps, (a - row) as usize..(b - row) as usize)?;
            }
            if e_end <= end {
                episode += 1;
            } else {
                break;
            }
        }
        row = end;
    }
    Ok(())
}

/// Whether each input episode is in the plan's output.
fn kept_episodes(plan: &Plan, episodes: usize) -> Vec<bool> {
    let mut kept = vec![false; episodes];
    for &e in &plan.order {
        kept[e] = true;
    }
    kept
}

/// Relabels, in place, rows `first_row..` of the parent (whole episodes) as the plan's outliers.
fn relabel_rows(episodes: &[EpisodeSummary], plan: &Plan, first_row: u64, rows: &mut TransitionChunk) {
    let end = first_row + rows.len() as u64;
    let first = episodes.partition_point(|e| e.start + u64::from(e.length) <= first_row);
    for (e, episode) in episodes.iter().enumerate().skip(first) {
        if episode.start >= end {
            break;
        }
        let Some(drawn) = plan.relabels.get(&e) else {
            continue;
        };
        let episode_end = episode.start + u64::from(episode.length);
        for row in episode.start.max(first_row)..episode_end.min(end) {
            let (i, step) = ((row - first_row) as usize, (row - episode.start) as usize);
            (rows.rewards[i], rows.costs[i]) = relabelled(rows.rewards[i], rows.costs[i], Some(drawn), step);
        }
    }
}

/// A step's reward and cost after the plan: an outlier's (`drawn`: its relabelled steps) costs become 1 at its drawn
/// steps and 0 elsewhere, its rewards ×1.5 in float32; other episodes' stay.
fn relabelled(reward: f32, cost: f32, drawn: Option<&Vec<usize>>, step: usize) -> (f32, f32) {
    match drawn {
        Some(steps) => (reward * 1.5, if steps.contains(&step) { 1.0 } else { 0.0 }),
        None => (reward, cost),
    }
}

fn copy_rows(src: &TransitionChunk, from: usize, dst: &mut TransitionChunk, to: usize, n: usize) {
    let (o, a) = (src.obs_dim, src.act_dim);
    dst.observations[to * o..(to + n) * o].copy_from_slice(&src.observations[from * o..(from + n) * o]);
    dst.next_observations[to * o..(to + n) * o].copy_from_slice(&src.next_observations[from * o..(from + n) * o]);
    dst.actions[to * a..(to + n) * a].copy_from_slice(&src.actions[from * a..(from + n) * a]);
    dst.rewards[to..to + n].copy_from_slice(&src.rewards[from..from + n]);
    dst.costs[to..to + n].copy_from_slice(&src.costs[from..from + n]);
    dst.terminals[to..to + n].copy_from_slice(&src.terminals[from..from + n]);
    dst.timeouts[to..to + n].copy_from_slice(&src.timeouts[from..from + n]);
}

/// Writes the gathered transitions as a canonical dataset at `out`.
pub fn write(
    task: &Task,
    space: ObservationSpace,
    data: &TransitionChunk,
    out: &Path,
) -> Result<Converted, ImportError> {
    // Hand the writer moderate chunks so its row groups form as usual.
    const CHUNK_ROWS: usize = 65_536;
    let chunks = (0..data.len())
        .step_by(CHUNK_ROWS)
        .map(|start| Ok(data.rows(start, CHUNK_ROWS.min(data.len() - start))));
    write_canonical(task, space, chunks, vec![], out)
}

/// Row bytes of the spill file: observation, next observation, action, reward, cost, terminal, timeout.
fn spill_row_bytes(obs_dim: usize, act_dim: usize) -> usize {
    4 * (2 * obs_dim + act_dim + 2) + 2
}

/// `np.sum` over a float32 array with more than one dimension, fed in C order piece by piece: 8192-element blocks
/// summed pairwise, accumulated in order (`numpy_math::numpy_sum_f32_nd` without holding the array).
struct StreamingSum {
    block: Vec<f32>,
    total: f32,
    count: usize,
}

impl StreamingSum {
    fn new() -> Self {
        StreamingSum {
            block: Vec::with_capacity(8192),
            total: 0.0,
            count: 0,
        }
    }

    fn push(&mut self, values: impl Iterator<Item = f32>) {
        for v in values {
            self.block.push(v);
            if self.block.len() == 8192 {
                self.total += dsrl_suite::episode::numpy_sum_f32(&self.block);
                self.block.clear();
            }
            self.count += 1;
        }
    }

    fn finish(mut self) -> (f32, usize) {
        if !self.block.is_empty() {
            self.total += dsrl_suite::episode::numpy_sum_f32(&self.block);
            self.block.clear();
        }
        (self.total, self.count)
    }
}

/// The kept episodes of the parent, relabelled, written once in input order to an unindexed scratch file of fixed-size
/// rows, then read back in output order by offset: the filter's whole output is never in memory.
struct Spill {
    file: std::fs::File,
    obs_dim: usize,
    act_dim: usize,
    /// Per input episode kept: its first row in the spill file.
    rows: Vec<u64>,
}

impl Spill {
    fn write(
        parent: &Path,
        episodes: &[EpisodeSummary],
        plan: &Plan,
        obs_dim: usize,
        act_dim: usize,
        scratch: &Path,
    ) -> Result<Spill, ImportError> {
        use std::io::Write;
        let kept = kept_episodes(plan, episodes.len());
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(scratch)?;
        let mut writer = std::io::BufWriter::with_capacity(8 << 20, &file);
        let mut rows = vec![u64::MAX; episodes.len()];
        let mut written = 0u64;
        let mut buf = Vec::with_capacity(spill_row_bytes(obs_dim, act_dim) * 4096);
        for_each_episode_piece(parent, episodes, |chunk, episode, steps, chunk_rows| {
            if !kept[episode] {
                return Ok(());
            }
            if rows[episode] == u64::MAX {
                rows[episode] = written;
            }
            let relabel = plan.relabels.get(&episode);
            for (i, step) in chunk_rows.zip(steps) {
                buf.clear();
                for v in &chunk.observations[i * obs_dim..(i + 1) * obs_dim] {
                    buf.extend_from_slice(&v.to_le_bytes());
                }
                for v in &chunk.next_observations[i * obs_dim..(i + 1) * obs_dim] {
                    buf.extend_from_slice(&v.to_le_bytes());
                }
                for v in &chunk.actions[i * act_dim..(i + 1) * act_dim] {
                    buf.extend_from_slice(&v.to_le_bytes());
                }
                let (reward, cost) = relabelled(chunk.rewards[i], chunk.costs[i], relabel, step);
                buf.extend_from_slice(&reward.to_le_bytes());
                buf.extend_from_slice(&cost.to_le_bytes());
                buf.push(u8::from(chunk.terminals[i]));
                buf.push(u8::from(chunk.timeouts[i]));
                writer.write_all(&buf)?;
                written += 1;
            }
            Ok(())
        })?;
        writer.flush()?;
        drop(writer);
        Ok(Spill {
            file,
            obs_dim,
            act_dim,
            rows,
        })
    }

    /// Input episode `e`'s `len` rows, appended to `out`.
    fn read_episode(&self, e: usize, len: usize, out: &mut TransitionChunk) -> std::io::Result<()> {
        use std::os::unix::fs::FileExt;
        let (o, a) = (self.obs_dim, self.act_dim);
        let row_bytes = spill_row_bytes(o, a);
        let mut bytes = vec![0u8; row_bytes * len];
        self.file.read_exact_at(&mut bytes, self.rows[e] * row_bytes as u64)?;
        let f32_at = |b: &[u8], k: usize| f32::from_le_bytes(b[4 * k..4 * k + 4].try_into().expect("4 bytes"));
        for row in bytes.chunks_exact(row_bytes) {
            out.observations.extend((0..o).map(|k| f32_at(row, k)));
            out.next_observations.extend((o..2 * o).map(|k| f32_at(row, k)));
            out.actions.extend((2 * o..2 * o + a).map(|k| f32_at(row, k)));
            out.rewards.push(f32_at(row, 2 * o + a));
            out.costs.push(f32_at(row, 2 * o + a + 1));
            out.terminals.push(row[row_bytes - 2] != 0);
            out.timeouts.push(row[row_bytes - 1] != 0);
        }
        Ok(())
    }

    /// The output rows in `ROWS`-row chunks, in output order (the chunking `write` hands the writer).
    fn chunks<'a>(
        &'a self,
        episodes: &'a [EpisodeSummary],
        plan: &'a Plan,
    ) -> impl Iterator<Item = Result<TransitionChunk, ImportError>> + 'a {
        const ROWS: usize = PIPELINE_ROWS;
        let (o, a) = (self.obs_dim, self.act_dim);
        let mut pending = TransitionChunk::empty(o, a);
        let mut next = 0usize; // position in plan.order
        let mut offset = 0usize; // rows of plan.order[next] already taken
        std::iter::from_fn(move || {
            while pending.len() < ROWS && next < plan.order.len() {
                let e = plan.order[next];
                let len = episodes[e].length as usize;
                let mut piece = TransitionChunk::empty(o, a);
                if let Err(err) = self.read_episode(e, len, &mut piece) {
                    return Some(Err(err.into()));
                }
                let take = (ROWS - pending.len()).min(len - offset);
                pending.append(&piece.rows(offset, take));
                offset += take;
                if offset == len {
                    next += 1;
                    offset = 0;
                }
            }
            if pending.is_empty() {
                return None;
            }
            Some(Ok(std::mem::replace(&mut pending, TransitionChunk::empty(o, a))))
        })
    }
}

/// `gather` then `write`, in bounded memory: the kept episodes spill to `scratch` (an unindexed file of the filter's
/// output size, removed before returning), the observation-noise statistics are taken in two passes over it in
/// output order (NumPy's summation order: `np.std` of the whole array), and the noise is drawn by two generators,
/// the second advanced past the observations' draws, so the rows stream to the writer one chunk at a time. The
/// output is the same file, byte for byte (a test holds it to `gather` + `write`).
#[allow(clippy::too_many_arguments)]
pub fn filter_to(
    parent: &Path,
    episodes: &[EpisodeSummary],
    plan: &Plan,
    task: &Task,
    space: ObservationSpace,
    obs_dim: usize,
    act_dim: usize,
    out: &Path,
    scratch: &Path,
) -> Result<Converted, ImportError> {
    struct Remove<'a>(&'a Path);
    impl Drop for Remove<'_> {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(self.0);
        }
    }
    let _remove = Remove(scratch);
    let keeps_all_in_order = plan.order.len() == episodes.len() && plan.order.iter().enumerate().all(|(i, &e)| i == e);
    if plan.noise_scale.is_none() && keeps_all_in_order {
        // Only rewards and costs change (outliers): every other column chunk is copied from the parent.
        let relabel = |first_row: u64, rows: &mut TransitionChunk| relabel_rows(episodes, plan, first_row, rows);
        if let Some(written) = write_relabelled(task, space, parent, episodes, relabel, out)? {
            return Ok(written);
        }
    }
    if plan.noise_scale.is_none() && plan.order.windows(2).all(|w| w[0] < w[1]) {
        // Nothing to reorder and no statistics to take first: the kept rows stream from the parent to the writer.
        return write_pipelined(task, space, out, |send| {
            stream_kept(parent, episodes, plan, obs_dim, act_dim, send)
        });
    }
    let spill = Spill::write(parent, episodes, plan, obs_dim, act_dim, scratch)?;
    let Some(scale) = plan.noise_scale else {
        return write_pipelined(task, space, out, |send| {
            for chunk in spill.chunks(episodes, plan) {
                send(chunk)?;
            }
            Ok(())
        });
    };
    // np.std of observations and of next observations, each over the whole output array.
    let (mut obs_sum, mut next_sum) = (StreamingSum::new(), StreamingSum::new());
    for chunk in spill.chunks(episodes, plan) {
        let chunk = chunk?;
        obs_sum.push(chunk.observations.iter().copied());
        next_sum.push(chunk.next_observations.iter().copied());
    }
    let ((obs_total, n), (next_total, _)) = (obs_sum.finish(), next_sum.finish());
    let (obs_mean, next_mean) = (obs_total / n as f32, next_total / n as f32);
    let (mut obs_squares, mut next_squares) = (StreamingSum::new(), StreamingSum::new());
    for chunk in spill.chunks(episodes, plan) {
        let chunk = chunk?;
        obs_squares.push(chunk.observations.iter().map(|&v| (v - obs_mean) * (v - obs_mean)));
        next_squares.push(
            chunk
                .next_observations
                .iter()
                .map(|&v| (v - next_mean) * (v - next_mean)),
        );
    }
    let std = |(sum, count): (f32, usize)| ((sum as f64 / count as f64) as f32).sqrt() as f64;
    let (obs_std, next_std) = (std(obs_squares.finish()), std(next_squares.finish()));
    // DSRL draws every observation's noise, then every next observation's: the second generator starts where the
    // first ends.
    let mut first = plan.generator.clone();
    let mut second = plan.generator.clone();
    for _ in 0..n {
        second.normal(0.0, obs_std);
    }
    write_pipelined(task, space, out, |send| {
        for chunk in spill.chunks(episodes, plan) {
            let mut chunk = match chunk {
                Ok(chunk) => chunk,
                Err(e) => return send(Err(e)),
            };
            for v in chunk.observations.iter_mut() {
                *v = (*v as f64 + scale * first.normal(0.0, obs_std)) as f32;
            }
            for v in chunk.next_observations.iter_mut() {
                *v = (*v as f64 + scale * second.normal(0.0, next_std)) as f32;
            }
            send(Ok(chunk))?;
        }
        Ok(())
    })
}

/// Rows handed from the reading thread to the writing one (~12 MB of CarPush2's rows), and how many chunks may wait
/// between them: small, because every derivation running at once holds its own (four concurrent uncached filters
/// on the paper-size file reached 1.3 GB with 64k-row chunks, two waiting).
const PIPELINE_ROWS: usize = 16_384;
const PIPELINE_DEPTH: usize = 1;

/// The writer stopped (it failed, and says why); the reading side only has to stop too.
struct WriterGone;

/// Writes the canonical file from chunks that `produce` makes on a second thread: reading the parent (and the
/// spill) on one core, validating, encoding and hashing on the other, with at most [`PIPELINE_DEPTH`] chunks
/// between them, so memory stays bounded. The bytes are those of a single-threaded write of the same rows: the
/// writer cuts its row groups from the rows, whatever the chunks.
fn write_pipelined<F>(task: &Task, space: ObservationSpace, out: &Path, produce: F) -> Result<Converted, ImportError>
where
    F: FnOnce(&mut dyn FnMut(Result<TransitionChunk, ImportError>) -> Result<(), WriterGone>) -> Result<(), WriterGone>
        + Send,
{
    std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::sync_channel(PIPELINE_DEPTH);
        let producer = scope.spawn(move || {
            let mut send = |chunk: Result<TransitionChunk, ImportError>| {
                let failed = chunk.is_err();
                tx.send(chunk).map_err(|_| WriterGone)?;
                if failed { Err(WriterGone) } else { Ok(()) }
            };
            let _ = produce(&mut send);
        });
        // The receiver is dropped with the iterator when the writer returns, which stops a producer still sending.
        let written = write_canonical(task, space, rx.into_iter(), vec![], out);
        producer
            .join()
            .map_err(|_| ImportError::Io(std::io::Error::other("the filter's reading thread panicked")))?;
        written
    })
}

/// The kept episodes of the parent in input order (the plan's order when it keeps that order), relabelled, in
/// chunks of about [`PIPELINE_ROWS`] rows: no spill.
fn stream_kept(
    parent: &Path,
    episodes: &[EpisodeSummary],
    plan: &Plan,
    obs_dim: usize,
    act_dim: usize,
    send: &mut dyn FnMut(Result<TransitionChunk, ImportError>) -> Result<(), WriterGone>,
) -> Result<(), WriterGone> {
    let kept = kept_episodes(plan, episodes.len());
    let mut pending = TransitionChunk::empty(obs_dim, act_dim);
    let mut gone = false;
    let read = for_each_episode_piece(parent, episodes, |chunk, episode, steps, rows| {
        if !kept[episode] {
            return Ok(());
        }
        let first = pending.len();
        pending.append(&chunk.rows(rows.start, rows.len()));
        if let Some(drawn) = plan.relabels.get(&episode) {
            for (i, step) in (first..pending.len()).zip(steps) {
                (pending.rewards[i], pending.costs[i]) =
                    relabelled(pending.rewards[i], pending.costs[i], Some(drawn), step);
            }
        }
        if pending.len() >= PIPELINE_ROWS {
            let full = std::mem::replace(&mut pending, TransitionChunk::empty(obs_dim, act_dim));
            if send(Ok(full)).is_err() {
                gone = true;
                return Err(ImportError::Io(std::io::Error::other("the writer stopped")));
            }
        }
        Ok(())
    });
    if gone {
        return Err(WriterGone);
    }
    match read {
        Err(e) => send(Err(e)),
        Ok(()) if pending.is_empty() => Ok(()),
        Ok(()) => send(Ok(pending)),
    }
}
