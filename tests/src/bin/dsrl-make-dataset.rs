//! `dsrl-make-dataset`: writes a deterministic synthetic dataset in a task's shape, as canonical Parquet or DSRL
//! HDF5, for end-to-end tests and benchmarks. Synthetic data is never benchmark data.

use std::path::PathBuf;

use clap::{Parser, ValueEnum};
use dsrl_suite::catalog::{Catalog, ObservationSpace};
use dsrl_suite::convert::write_canonical;
use dsrl_suite::hdf5_file::write_dsrl_hdf5;
use dsrl_suite::parquet_file::ParquetTransitions;
use dsrl_suite::synthetic::{SyntheticSpec, transitions};

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Format {
    Parquet,
    Hdf5,
}

/// Write a synthetic dataset (random observations, spread reward/cost returns, early terminations and time-limit
/// truncations) for TASK with the given number of episodes and seed.
#[derive(Debug, Parser)]
struct Args {
    #[arg(long)]
    task: String,
    #[arg(long)]
    episodes: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long, value_enum, default_value = "parquet")]
    format: Format,
    /// Output file.
    out: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let catalog = Catalog::embedded()?;
    let task = catalog.get(&args.task)?;
    let chunks = transitions(SyntheticSpec::for_task(task, args.episodes, args.seed));
    let parquet = match args.format {
        Format::Parquet => args.out.clone(),
        Format::Hdf5 => args.out.with_extension("tmp.parquet"),
    };
    let converted = write_canonical(task, ObservationSpace::Simulator, chunks.map(Ok), vec![], &parquet)?;
    if let Format::Hdf5 = args.format {
        write_dsrl_hdf5(ParquetTransitions::open(std::fs::File::open(&parquet)?)?, &args.out)?;
        std::fs::remove_file(&parquet)?;
    }
    let transitions: u64 = converted.episode_index.iter().map(|e| e.length as u64).sum();
    println!(
        "{} episodes, {transitions} transitions, {} bytes of Parquet (version {}) -> {}",
        converted.episode_index.len(),
        converted.byte_size,
        converted.version,
        args.out.display()
    );
    Ok(())
}
