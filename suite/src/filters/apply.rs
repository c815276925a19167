//! Turning a plan into data: the kept episodes are gathered in output order (one sequential read of the parent
//! file), outliers are relabelled, observation noise is added exactly as NumPy would add it, and the result is
//! written as a canonical dataset version.

use std::path::Path;

use super::numpy_math::numpy_std_f32_nd;
use super::plan::Plan;
use crate::catalog::{ObservationSpace, Task};
use crate::convert::{Converted, ImportError, write_canonical};
use crate::episode::EpisodeSummary;
use crate::parquet_file::ParquetTransitions;
use crate::transitions::TransitionChunk;

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
    let malformed = |e: crate::parquet_file::ReadError| ImportError::Malformed {
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
            if out_start[episode] != usize::MAX && a < b {
                let dst = out_start[episode] + (a - e_start) as usize;
                let (src, n) = ((a - row) as usize, (b - a) as usize);
                copy_rows(&chunk, src, &mut out, dst, n);
            }
            if e_end <= end {
                episode += 1;
            } else {
                break;
            }
        }
        row = end;
    }
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
