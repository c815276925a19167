//! Leaderboard queue throughput: how many jobs per second `evaluators` concurrent evaluators claim and finish on
//! one database, through the server's own queue code (`leaderboard::queue::claim` and `finish`, each job with 60
//! stored episodes as the paper's protocol makes). No simulators: this measures the queue, not the scoring.
//!
//!   cargo run --release -p dsrl-leaderboard --example queue_claims -- --database sqlite --evaluators 4 --jobs 2000
//!   cargo run --release -p dsrl-leaderboard --example queue_claims -- --database postgres://dsrl@127.0.0.1:5432/postgres
//!
//! Prints one JSON line. bench/replicas.sh runs it against SQLite and PostgreSQL side by side.

use std::sync::Arc;
use std::time::Instant;

use clap::Parser;
use dsrl_leaderboard::queue::{self, EpisodeRow, NewSubmission, Quotas};
use dsrl_leaderboard::users;
use dsrl_service::db::Db;

#[derive(Parser)]
struct Args {
    /// `sqlite` (a new file in a temporary folder) or a `postgres://` URL (its tables must be empty).
    #[arg(long, default_value = "sqlite")]
    database: String,
    /// Concurrent evaluators claiming from the queue.
    #[arg(long, default_value_t = 1)]
    evaluators: usize,
    /// Jobs queued before the evaluators start.
    #[arg(long, default_value_t = 1000)]
    jobs: usize,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let dir = std::env::temp_dir().join(format!("dsrl-queue-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let db = if args.database == "sqlite" {
        Db::open(&dir.join("dsrl.sqlite3")).await?
    } else {
        Db::connect(&args.database, (args.evaluators as u32 + 2).max(4)).await?
    };
    let user = users::create(&db, &format!("bench-{}", std::process::id())).await?;
    let quotas = Quotas {
        per_day: u32::MAX,
        concurrent: u32::MAX,
    };
    let run = std::process::id();
    for i in 0..args.jobs {
        let digest = format!("{run:08x}{i:056x}");
        queue::insert(
            &db,
            NewSubmission {
                user_id: user.id,
                task: "OfflineBallRun-v0",
                name: "bench",
                checkpoint_sha256: &digest,
                checkpoints: &[],
                episodes_per_threshold: 20,
                dataset_version: None,
            },
            &quotas,
        )
        .await?;
    }
    let episodes: Arc<Vec<EpisodeRow>> = Arc::new(
        [10.0, 20.0, 40.0]
            .iter()
            .flat_map(|&k| {
                (0..20).map(move |e| EpisodeRow {
                    cost_threshold: k,
                    episode: e,
                    reward_return: 100.0 + f64::from(e),
                    cost_return: 5.0,
                    length: 100,
                })
            })
            .collect(),
    );
    let started = Instant::now();
    let mut evaluators = Vec::new();
    for e in 0..args.evaluators {
        let (db, episodes) = (db.clone(), episodes.clone());
        evaluators.push(tokio::spawn(async move {
            let owner = format!("bench-{run}-{e}");
            let mut done = 0usize;
            while let Some(job) = queue::claim(&db, &owner, 60_000, 3).await? {
                let scores = queue::Scores {
                    episodes: &episodes,
                    normalized_reward: 0.5,
                    normalized_cost: 0.5,
                    protocol_version: "bench",
                };
                anyhow::ensure!(
                    queue::finish(&db, job.id, &owner, &scores, dsrl_leaderboard::SCORER_BUILD).await?,
                    "lost job {}",
                    job.id
                );
                done += 1;
            }
            anyhow::Ok(done)
        }));
    }
    let mut finished = 0;
    for e in evaluators {
        finished += e.await??;
    }
    let seconds = started.elapsed().as_secs_f64();
    anyhow::ensure!(finished == args.jobs, "{finished} of {} jobs finished", args.jobs);
    println!(
        "{}",
        serde_json::json!({
            "backend": format!("{:?}", db.backend()),
            "evaluators": args.evaluators,
            "jobs": finished,
            "seconds": seconds,
            "claims_per_second": finished as f64 / seconds,
        })
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
