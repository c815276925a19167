//! `dsrl-sim-bench`: env-steps per second through the simulator protocol, stepping random actions (uniform in the
//! action box, from a seeded generator) in K environments with auto-reset. `bench/sim.sh` runs it next to the same
//! loop in-process in Python and writes the comparison into BENCHMARKS.md.

use std::time::Instant;

use clap::Parser;
use dsrl_proto::simulator::v1::{AutoReset, Open};
use dsrl_sim::random_actions::UniformActions;
use dsrl_simulators::session::{Reply, SimulatorSession};

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
    /// Split the K environments into this many groups and keep every group's next step in flight while the
    /// others are answered (EnvPool-style asynchronous stepping through the protocol's pipelining); 1: lockstep.
    #[arg(long, default_value_t = 1)]
    groups: u32,
    /// Seed of the environments (env i gets seed + i) and of the random actions.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

// One thread: the client's own task handoffs would otherwise add to the protocol cost being measured.
#[tokio::main(flavor = "current_thread")]
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
        controller: None,
    };
    let (mut session, _) = SimulatorSession::open(channel, open).await?;
    let spec = session.spec().clone();
    let mut actions = UniformActions::new(args.seed);
    let mut random_actions = |n: usize| actions.batch(&spec.action_low, &spec.action_high, n);
    // Group g holds envs g, g + G, g + 2G, ...; each group steps `warmup + steps` times.
    let groups = args.groups.clamp(1, args.envs) as usize;
    let members: Vec<Vec<u32>> = (0..groups)
        .map(|g| (g as u32..args.envs).step_by(groups).collect())
        .collect();
    let envs_of = |g: usize| if groups == 1 { Vec::new() } else { members[g].clone() };
    let mut episodes = 0u64;
    let mut started = Instant::now();
    for (g, group) in members.iter().enumerate() {
        session.send_step(&envs_of(g), &random_actions(group.len())).await?;
    }
    let total = (args.warmup + args.steps) * groups as u64;
    for i in 0..total {
        if i == args.warmup * groups as u64 {
            started = Instant::now();
        }
        let Reply::Step(result) = session.receive().await? else {
            anyhow::bail!("unexpected reply to a step")
        };
        episodes += result
            .terminated
            .iter()
            .zip(&result.truncated)
            .filter(|(a, b)| **a || **b)
            .count() as u64;
        // Answers come in request order, so this was group i mod G; queue its next step.
        let g = (i % groups as u64) as usize;
        if i + (groups as u64) < total {
            session
                .send_step(&envs_of(g), &random_actions(members[g].len()))
                .await?;
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    session.close().await?;
    let env_steps = args.steps * u64::from(args.envs);
    println!(
        "{{\"task\": \"{}\", \"envs\": {}, \"groups\": {groups}, \"env_steps\": {env_steps}, \"seconds\": {seconds:.3}, \"env_steps_per_s\": \
         {:.1}, \"episodes_ended\": {episodes}, \"simulator\": \"{}\"}}",
        spec.task,
        args.envs,
        env_steps as f64 / seconds,
        spec.simulator
    );
    Ok(())
}
