//! `dsrl-sim-bench`: env-steps per second through the simulator protocol, stepping random actions (uniform in the
//! action box, from a seeded generator) in K environments with auto-reset. `bench/sim.sh` runs it next to the same
//! loop in-process in Python and writes the comparison into BENCHMARKS.md.

use std::time::Instant;

use clap::Parser;
use dsrl_proto::simulator::v1::{AutoReset, Open};
use dsrl_proto::simulator_session::SimulatorSession;

/// Measures env-steps/s of one task through a running dsrl-sim-worker; prints one JSON line.
#[derive(Parser, Debug)]
struct Args {
    /// The worker's address, e.g. 127.0.0.1:50051.
    #[arg(long)]
    worker: String,
    /// Simulator or offline task id.
    #[arg(long)]
    task: String,
    /// K, environments stepped together.
    #[arg(long, default_value_t = 1)]
    envs: u32,
    /// Batched steps to time (each steps all K environments).
    #[arg(long, default_value_t = 1000)]
    steps: u64,
    /// Untimed batched steps first.
    #[arg(long, default_value_t = 20)]
    warmup: u64,
    /// Seed of the environments (env i gets seed + i) and of the random actions.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// SplitMix64: a seeded, dependency-free source of uniform actions.
struct SplitMix(u64);

impl SplitMix {
    fn next_unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", args.worker))?
        .connect()
        .await?;
    let open = Open {
        task: args.task.clone(),
        num_envs: args.envs,
        seeds: (0..u64::from(args.envs)).map(|i| args.seed + i).collect(),
        auto_reset: AutoReset::SameStep as i32,
    };
    let (mut session, _) = SimulatorSession::open(channel, open).await?;
    let spec = session.spec().clone();
    let mut rng = SplitMix(args.seed);
    let mut actions = vec![0f32; args.envs as usize * spec.act_dim as usize];
    let mut episodes = 0u64;
    let mut started = Instant::now();
    for i in 0..args.warmup + args.steps {
        if i == args.warmup {
            started = Instant::now();
        }
        for (j, a) in actions.iter_mut().enumerate() {
            let d = j % spec.act_dim as usize;
            let (low, high) = (spec.action_low[d], spec.action_high[d]);
            *a = (low + (high - low) * rng.next_unit()) as f32;
        }
        let result = session.step(&[], &actions).await?;
        episodes += result
            .terminated
            .iter()
            .zip(&result.truncated)
            .filter(|(a, b)| **a || **b)
            .count() as u64;
    }
    let seconds = started.elapsed().as_secs_f64();
    session.close().await?;
    let env_steps = args.steps * u64::from(args.envs);
    println!(
        "{{\"task\": \"{}\", \"envs\": {}, \"env_steps\": {env_steps}, \"seconds\": {seconds:.3}, \"env_steps_per_s\": \
         {:.1}, \"episodes_ended\": {episodes}, \"simulator\": \"{}\"}}",
        spec.task,
        args.envs,
        env_steps as f64 / seconds,
        spec.simulator
    );
    Ok(())
}
