use std::net::SocketAddr;
use std::process::Stdio;
use std::time::{Duration, Instant};

use dsrl_proto::simulator::v1::simulator_client::SimulatorClient;
use dsrl_proto::simulator::v1::{AutoReset, HealthRequest, HealthResponse, Open};
use dsrl_simulators::session::SimulatorSession;
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tonic::transport::Channel;

/// A worker process on a free loopback port, killed when dropped (and exiting on its own if the test binary dies,
/// through `--exit-with-stdin`).
pub struct Worker {
    _child: Child,
    pub pid: u32,
    pub addr: SocketAddr,
}

impl Worker {
    pub async fn start(extra: &[&str]) -> Worker {
        let log = std::env::temp_dir().join(format!("dsrl-sim-worker-test-{}.log", std::process::id()));
        let stderr = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log)
            .expect("worker log");
        let mut child = Command::new(env!("CARGO_BIN_EXE_dsrl-sim-worker"))
            .args(["--listen", "127.0.0.1:0", "--exit-with-stdin"])
            .args(extra)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(stderr)
            .kill_on_drop(true)
            .spawn()
            .expect("spawn dsrl-sim-worker");
        let mut lines = BufReader::new(child.stdout.take().expect("stdout")).lines();
        let addr = tokio::time::timeout(Duration::from_secs(120), async {
            while let Some(line) = lines.next_line().await.expect("worker stdout") {
                if let Some(addr) = line.strip_prefix("dsrl-sim-worker listening on ") {
                    return addr.parse().expect("address");
                }
            }
            panic!(
                "dsrl-sim-worker exited before listening; see {} (is .venv-sim set up? run sim/setup.sh)",
                log.display()
            )
        })
        .await
        .expect("worker start-up timed out");
        // Keep draining stdout: the simulators print to it, and a full pipe would block the worker.
        tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
        let pid = child.id().expect("worker pid");
        Worker {
            _child: child,
            pid,
            addr,
        }
    }

    /// The worker's live child processes (MetaDrive hosts one environment per process).
    pub fn child_processes(&self) -> usize {
        let tasks = std::fs::read_dir(format!("/proc/{}/task", self.pid)).expect("/proc");
        tasks
            .filter_map(|t| std::fs::read_to_string(t.ok()?.path().join("children")).ok())
            .map(|c| c.split_whitespace().count())
            .sum()
    }

    pub async fn channel(&self) -> Channel {
        tonic::transport::Endpoint::from_shared(format!("http://{}", self.addr))
            .unwrap()
            .connect()
            .await
            .unwrap()
    }

    pub async fn client(&self) -> SimulatorClient<Channel> {
        SimulatorClient::new(self.channel().await)
    }

    pub async fn health(&self) -> HealthResponse {
        self.client().await.health(HealthRequest {}).await.unwrap().into_inner()
    }

    pub async fn open(&self, task: &str, seeds: &[u64], auto_reset: AutoReset) -> (SimulatorSession, Vec<f32>) {
        let open = Open {
            task: task.into(),
            num_envs: seeds.len() as u32,
            seeds: seeds.to_vec(),
            auto_reset: auto_reset as i32,
            controller: None,
        };
        SimulatorSession::open(self.channel().await, open)
            .await
            .unwrap_or_else(|e| panic!("open {task}: {e}"))
    }

    /// Waits until the worker reports no sessions and no environments.
    pub async fn wait_idle(&self, within: Duration) -> HealthResponse {
        let deadline = Instant::now() + within;
        loop {
            let health = self.health().await;
            if health.sessions == 0 && health.envs == 0 {
                return health;
            }
            assert!(
                Instant::now() < deadline,
                "worker still busy after {within:?}: {health:?}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

pub use dsrl_sim::random_actions::UniformActions as Actions;
