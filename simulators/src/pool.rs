use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::Stdio;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::future::BoxFuture;

use crate::session::SimulatorSession;
use dsrl_proto::simulator::v1::simulator_client::SimulatorClient;
use dsrl_proto::simulator::v1::{HealthRequest, Open};
use serde::Serialize;
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tokio::sync::watch;
use tonic::transport::{Channel, Endpoint};

use crate::config::SimulatorsConfig;
use crate::error::SimulatorError;
use crate::pooled::PooledSession;

/// A worker as `GET /v1/simulators` shows it.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct WorkerStatus {
    pub name: String,
    /// "local" (started and supervised by this server), "remote" (configured by address) or "discovered" (behind
    /// one of `worker_services`).
    pub kind: String,
    pub address: Option<String>,
    pub pid: Option<u32>,
    pub healthy: bool,
    pub sessions: u32,
    pub envs: u32,
    pub max_envs: u32,
    pub version: Option<String>,
    /// Times a local worker was replaced after dying or failing its health checks.
    pub restarts: u32,
    pub last_error: Option<String>,
}

enum Source {
    Local { binary: PathBuf, args: Vec<String> },
    Remote { address: String },
}

struct Slot {
    source: Source,
    state: Mutex<SlotState>,
    /// The service name a discovered worker was resolved from (`None`: configured or local).
    service: Option<String>,
    /// Set when discovery no longer lists the worker: its supervision ends, and no new session goes there (sessions
    /// already open keep their own channel and finish).
    retired: AtomicBool,
    /// Sessions of this pool open on the worker now: a call's deadline grows with them (`session::WorkerLoad`).
    open_sessions: Arc<std::sync::atomic::AtomicUsize>,
}

/// Resolves a `host:port` service name to the addresses behind it (the default is the system resolver, which
/// answers a Kubernetes headless Service with one address per ready pod). Tests substitute their own.
pub type Resolver = Arc<dyn Fn(String) -> BoxFuture<'static, std::io::Result<Vec<SocketAddr>>> + Send + Sync>;

/// The system resolver.
pub fn system_resolver() -> Resolver {
    Arc::new(|service: String| Box::pin(async move { Ok(tokio::net::lookup_host(service).await?.collect()) }))
}

#[derive(Default)]
struct SlotState {
    status: Option<WorkerStatus>,
    channel: Option<Channel>,
    child: Option<Child>,
    failed_checks: u32,
    /// Environments of sessions being opened here: counted from placement on, so that concurrent opens (an
    /// evaluation's three threshold sessions) spread over the workers instead of all seeing equal load.
    reserved: u32,
}

pub struct SimulatorPool {
    /// Local and configured workers first, then discovered ones as discovery finds them.
    slots: Arc<Mutex<Vec<Arc<Slot>>>>,
    /// Held while a session is placed (see `place`).
    placing: Mutex<()>,
    request_timeout: Duration,
    stop: watch::Sender<bool>,
}

impl Slot {
    fn new(name: String, address: Option<String>, source: Source) -> Arc<Slot> {
        Slot::with_service(name, address, source, None)
    }

    fn with_service(name: String, address: Option<String>, source: Source, service: Option<String>) -> Arc<Slot> {
        let kind = match source {
            Source::Local { .. } => "local",
            Source::Remote { .. } => "remote",
        };
        let kind = if service.is_some() { "discovered" } else { kind };
        let status = WorkerStatus {
            name,
            kind: kind.into(),
            address,
            pid: None,
            healthy: false,
            sessions: 0,
            envs: 0,
            max_envs: 0,
            version: None,
            restarts: 0,
            last_error: None,
        };
        Arc::new(Slot {
            source,
            state: Mutex::new(SlotState {
                status: Some(status),
                ..Default::default()
            }),
            service,
            retired: AtomicBool::new(false),
            open_sessions: Arc::new(std::sync::atomic::AtomicUsize::new(0)),
        })
    }

    fn status(&self) -> WorkerStatus {
        self.state
            .lock()
            .expect("slot state")
            .status
            .clone()
            .expect("status set at creation")
    }

    fn update(&self, f: impl FnOnce(&mut SlotState)) {
        f(&mut self.state.lock().expect("slot state"))
    }
}

/// Starts a local worker and waits for its "listening on" line.
async fn spawn_worker(binary: &PathBuf, args: &[String], name: &str) -> Result<(Child, String), String> {
    let mut child = Command::new(binary)
        .args(["--listen", "127.0.0.1:0", "--exit-with-stdin"])
        .args(args)
        // The worker exits when this pipe closes, so even a SIGKILLed server leaves no workers behind.
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| format!("starting {}: {e}", binary.display()))?;
    let mut lines = BufReader::new(child.stdout.take().expect("piped stdout")).lines();
    let address = tokio::time::timeout(Duration::from_secs(120), async {
        while let Ok(Some(line)) = lines.next_line().await {
            if let Some(address) = line.strip_prefix("dsrl-sim-worker listening on ") {
                return Ok(address.to_owned());
            }
        }
        Err(format!(
            "{} exited before listening (is the simulator environment set up? run sim/setup.sh)",
            binary.display()
        ))
    })
    .await
    .map_err(|_| "the worker did not start listening within 120 s".to_owned())??;
    // The simulators print to stdout; drain it into the log so a full pipe never blocks the worker.
    let worker = name.to_owned();
    tokio::spawn(async move {
        while let Ok(Some(line)) = lines.next_line().await {
            tracing::debug!(%worker, "{line}");
        }
    });
    Ok((child, address))
}

fn channel_to(address: &str) -> Result<Channel, String> {
    let endpoint =
        Endpoint::from_shared(format!("http://{address}")).map_err(|e| format!("bad address {address}: {e}"))?;
    Ok(endpoint
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true)
        .connect_lazy())
}

impl SimulatorPool {
    /// Creates the pool and starts supervising its workers (local ones are spawned in the background) and
    /// discovering the workers behind `worker_services`.
    pub fn start(config: &SimulatorsConfig) -> SimulatorPool {
        SimulatorPool::start_with_resolver(config, system_resolver())
    }

    /// `start` with another resolver for `worker_services`.
    pub fn start_with_resolver(config: &SimulatorsConfig, resolver: Resolver) -> SimulatorPool {
        let binary = config.worker_binary.clone().unwrap_or_else(default_worker_binary);
        let mut slots = Vec::new();
        for i in 0..config.local_workers {
            let source = Source::Local {
                binary: binary.clone(),
                args: config.worker_args.clone(),
            };
            slots.push(Slot::new(format!("local-{i}"), None, source));
        }
        for (i, address) in config.remote_workers.iter().enumerate() {
            let source = Source::Remote {
                address: address.clone(),
            };
            slots.push(Slot::new(format!("remote-{i}"), Some(address.clone()), source));
        }
        let (stop, stopped) = watch::channel(false);
        let interval = Duration::from_millis(config.health_interval_ms.max(50));
        for slot in &slots {
            tokio::spawn(supervise(slot.clone(), interval, stopped.clone()));
        }
        let slots = Arc::new(Mutex::new(slots));
        let every = Duration::from_millis(config.discovery_interval_ms.max(50));
        for service in &config.worker_services {
            tokio::spawn(discover(
                service.clone(),
                resolver.clone(),
                slots.clone(),
                every,
                interval,
                stopped.clone(),
            ));
        }
        SimulatorPool {
            slots,
            placing: Mutex::new(()),
            request_timeout: Duration::from_secs(config.request_timeout_s.max(1)),
            stop,
        }
    }

    pub fn workers(&self) -> Vec<WorkerStatus> {
        self.current().iter().map(|s| s.status()).collect()
    }

    fn current(&self) -> Vec<Arc<Slot>> {
        self.slots.lock().expect("slots").clone()
    }

    /// Waits until at least `n` workers are healthy, or `timeout` passes.
    pub async fn wait_healthy(&self, n: usize, timeout: Duration) -> bool {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            if self.workers().iter().filter(|w| w.healthy).count() >= n {
                return true;
            }
            if tokio::time::Instant::now() >= deadline {
                return false;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Opens a session on the healthy worker with the most free capacity.
    pub async fn open(&self, open: Open) -> Result<PooledSession, SimulatorError> {
        let num_envs = open.num_envs;
        let (slot, channel, name) = self.place(num_envs)?;
        let opened = tokio::time::timeout(self.request_timeout, SimulatorSession::open(channel, open)).await;
        let result = match opened {
            Ok(result) => result.map_err(|status| PooledSession::error(&name, status)),
            Err(_) => Err(SimulatorError::Unavailable(format!(
                "simulator worker {name} did not open a session within {:?}",
                self.request_timeout
            ))),
        };
        // The reservation becomes the session's count (or is released when the open failed); counted at once
        // so the next placement sees it before the next health check does.
        slot.update(|s| {
            s.reserved = s.reserved.saturating_sub(num_envs);
            if result.is_ok()
                && let Some(status) = &mut s.status
            {
                status.envs += num_envs;
                status.sessions += 1;
            }
        });
        let (session, observations) = result?;
        let load = crate::pooled::WorkerLoad::join(&slot.open_sessions);
        Ok(PooledSession::new(
            session,
            observations,
            name,
            self.request_timeout,
            load,
        ))
    }

    /// Chooses the healthy worker with the most free capacity and reserves `num_envs` there; one placement at a
    /// time, so two concurrent opens never both see the same free capacity.
    fn place(&self, num_envs: u32) -> Result<(Arc<Slot>, Channel, String), SimulatorError> {
        let _one_at_a_time = self.placing.lock().expect("placement lock");
        let mut best: Option<(f64, Arc<Slot>, Channel, String)> = None;
        for slot in &self.current() {
            let state = slot.state.lock().expect("slot state");
            let (Some(status), Some(channel)) = (&state.status, &state.channel) else {
                continue;
            };
            let used = status.envs + state.reserved;
            if !status.healthy || used + num_envs > status.max_envs {
                continue;
            }
            let load = f64::from(used) / f64::from(status.max_envs.max(1));
            if best.as_ref().is_none_or(|(b, ..)| load < *b) {
                best = Some((load, slot.clone(), channel.clone(), status.name.clone()));
            }
        }
        match best {
            Some((_, slot, channel, name)) => {
                slot.update(|s| s.reserved += num_envs);
                Ok((slot, channel, name))
            }
            None => {
                let workers = self.workers();
                let detail: Vec<String> = workers
                    .iter()
                    .map(|w| match (&w.last_error, w.healthy) {
                        (_, true) => format!("{} full ({}/{} envs)", w.name, w.envs, w.max_envs),
                        (Some(e), false) => format!("{} down: {e}", w.name),
                        (None, false) => format!("{} starting", w.name),
                    })
                    .collect();
                Err(SimulatorError::Unavailable(if workers.is_empty() {
                    "no simulator workers are configured or discovered (simulators.local_workers / remote_workers / \
                     worker_services)"
                        .to_owned()
                } else {
                    format!(
                        "no simulator worker can take {num_envs} more environments: {}",
                        detail.join("; ")
                    )
                }))
            }
        }
    }
}

impl Drop for SimulatorPool {
    fn drop(&mut self) {
        let _ = self.stop.send(true);
        for slot in self.current() {
            if let Some(child) = &mut slot.state.lock().expect("slot state").child {
                let _ = child.start_kill();
            }
        }
    }
}

fn default_worker_binary() -> PathBuf {
    std::env::current_exe()
        .ok()
        .map(|exe| exe.with_file_name("dsrl-sim-worker"))
        .filter(|p| p.exists())
        .unwrap_or_else(|| PathBuf::from("dsrl-sim-worker"))
}

/// One worker's life: start (local), health-check every `interval`, replace a local worker that exits or fails
/// three checks in a row.
async fn supervise(slot: Arc<Slot>, interval: Duration, mut stopped: watch::Receiver<bool>) {
    let mut backoff = interval;
    loop {
        if *stopped.borrow() || slot.retired.load(Ordering::Relaxed) {
            return;
        }
        let needs_start = match &slot.source {
            Source::Local { .. } => {
                let mut state = slot.state.lock().expect("slot state");
                let exited = match state.child.as_mut().map(|c| c.try_wait()) {
                    None => true,
                    Some(Ok(Some(code))) => {
                        let status = state.status.as_mut().expect("status");
                        tracing::warn!(worker = %status.name, %code, "simulator worker exited; replacing it");
                        status.last_error = Some(format!("exited with {code}"));
                        true
                    }
                    Some(_) => false,
                };
                if exited {
                    state.child = None;
                    state.channel = None;
                    let status = state.status.as_mut().expect("status");
                    status.healthy = false;
                    status.pid = None;
                }
                exited
            }
            Source::Remote { address } => {
                let mut state = slot.state.lock().expect("slot state");
                if state.channel.is_none() {
                    match channel_to(address) {
                        Ok(channel) => state.channel = Some(channel),
                        Err(e) => state.status.as_mut().expect("status").last_error = Some(e),
                    }
                }
                false
            }
        };
        if let (true, Source::Local { binary, args }) = (needs_start, &slot.source) {
            let name = slot.status().name;
            match spawn_worker(binary, args, &name).await {
                Ok((child, address)) => {
                    let pid = child.id();
                    let channel = channel_to(&address).ok();
                    tracing::info!(worker = %name, %address, ?pid, "simulator worker started");
                    slot.update(|s| {
                        let status = s.status.as_mut().expect("status");
                        if status.address.is_some() {
                            status.restarts += 1;
                        }
                        status.address = Some(address);
                        status.pid = pid;
                        s.child = Some(child);
                        s.channel = channel;
                        s.failed_checks = 0;
                    });
                    backoff = interval;
                }
                Err(e) => {
                    tracing::error!(worker = %name, error = %e, "simulator worker failed to start");
                    slot.update(|s| s.status.as_mut().expect("status").last_error = Some(e));
                    backoff = (backoff * 2).min(Duration::from_secs(30));
                    tokio::select! {
                        _ = tokio::time::sleep(backoff) => {}
                        _ = stopped.changed() => return,
                    }
                    continue;
                }
            }
        }
        check_health(&slot).await;
        tokio::select! {
            _ = tokio::time::sleep(interval) => {}
            _ = stopped.changed() => return,
        }
    }
}

/// Keeps the pool's discovered workers equal to what `service` resolves to: every `every`, a new address becomes a
/// worker (supervised like a configured remote one) and a vanished one is retired. A failed lookup changes
/// nothing (a DNS hiccup must not drop every worker); workers that really went away fail their health checks.
async fn discover(
    service: String,
    resolve: Resolver,
    slots: Arc<Mutex<Vec<Arc<Slot>>>>,
    every: Duration,
    health_interval: Duration,
    mut stopped: watch::Receiver<bool>,
) {
    loop {
        match resolve(service.clone()).await {
            Ok(found) => {
                let found: BTreeSet<String> = found.iter().map(SocketAddr::to_string).collect();
                let mut slots = slots.lock().expect("slots");
                slots.retain(|slot| {
                    let Source::Remote { address } = &slot.source else {
                        return true;
                    };
                    if slot.service.as_deref() != Some(service.as_str()) || found.contains(address) {
                        return true;
                    }
                    tracing::info!(%service, %address, "simulator worker no longer discovered; retiring it");
                    slot.retired.store(true, Ordering::Relaxed);
                    false
                });
                for address in found {
                    let known = slots.iter().any(|slot| {
                        slot.service.as_deref() == Some(service.as_str())
                            && matches!(&slot.source, Source::Remote { address: a } if *a == address)
                    });
                    if !known {
                        tracing::info!(%service, %address, "simulator worker discovered");
                        let slot = Slot::with_service(
                            format!("{service}@{address}"),
                            Some(address.clone()),
                            Source::Remote { address },
                            Some(service.clone()),
                        );
                        tokio::spawn(supervise(slot.clone(), health_interval, stopped.clone()));
                        slots.push(slot);
                    }
                }
            }
            Err(e) => tracing::warn!(%service, error = %e, "resolving simulator workers; keeping the last answer"),
        }
        tokio::select! {
            _ = tokio::time::sleep(every) => {}
            _ = stopped.changed() => return,
        }
    }
}

async fn check_health(slot: &Slot) {
    let Some(channel) = slot.state.lock().expect("slot state").channel.clone() else {
        return;
    };
    let answer = tokio::time::timeout(
        Duration::from_secs(5),
        SimulatorClient::new(channel).health(HealthRequest {}),
    )
    .await;
    let mut state = slot.state.lock().expect("slot state");
    match answer {
        Ok(Ok(health)) => {
            let health = health.into_inner();
            state.failed_checks = 0;
            let status = state.status.as_mut().expect("status");
            status.healthy = true;
            status.sessions = health.sessions;
            status.envs = health.envs;
            status.max_envs = health.max_envs;
            status.version = Some(health.version);
            status.last_error = None;
        }
        failure => {
            let error = match failure {
                Ok(Err(status)) => status.message().to_owned(),
                _ => "health check timed out".to_owned(),
            };
            state.failed_checks += 1;
            let failed = state.failed_checks;
            let status = state.status.as_mut().expect("status");
            status.healthy = false;
            status.last_error = Some(error);
            if failed >= 3
                && let Some(child) = &mut state.child
            {
                tracing::warn!("simulator worker failed {failed} health checks; replacing it");
                let _ = child.start_kill();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Discovery follows the resolver's answers as pods come and go. The resolver is a stand-in (a real DNS server
    /// whose records change cannot run here); the system resolver is exercised by the e2e test that discovers a
    /// real worker behind `localhost:PORT`. Nothing listens on these addresses, so the workers stay unhealthy.
    #[tokio::test]
    async fn discovered_workers_follow_the_service_records() {
        let records: Arc<Mutex<std::io::Result<Vec<SocketAddr>>>> = Arc::new(Mutex::new(Ok(vec![
            "127.0.0.1:9".parse().unwrap(),
            "127.0.0.2:9".parse().unwrap(),
        ])));
        let answers = records.clone();
        let resolver: Resolver = Arc::new(move |service: String| {
            assert_eq!(service, "workers.dsrl.svc:50051");
            let answer = match &*answers.lock().unwrap() {
                Ok(found) => Ok(found.clone()),
                Err(e) => Err(std::io::Error::new(e.kind(), e.to_string())),
            };
            Box::pin(async move { answer })
        });
        let config = SimulatorsConfig {
            local_workers: 0,
            worker_services: vec!["workers.dsrl.svc:50051".into()],
            discovery_interval_ms: 50,
            ..SimulatorsConfig::default()
        };
        let pool = SimulatorPool::start_with_resolver(&config, resolver);
        let addresses = |pool: &SimulatorPool| {
            let mut found: Vec<(String, String)> = pool
                .workers()
                .into_iter()
                .map(|w| (w.kind, w.address.unwrap_or_default()))
                .collect();
            found.sort();
            found
        };
        let settle = || tokio::time::sleep(Duration::from_millis(300));
        settle().await;
        assert_eq!(
            addresses(&pool),
            [
                ("discovered".into(), "127.0.0.1:9".into()),
                ("discovered".into(), "127.0.0.2:9".into())
            ]
        );
        // A pod goes, another comes.
        *records.lock().unwrap() = Ok(vec!["127.0.0.2:9".parse().unwrap(), "127.0.0.3:9".parse().unwrap()]);
        settle().await;
        assert_eq!(
            addresses(&pool),
            [
                ("discovered".into(), "127.0.0.2:9".into()),
                ("discovered".into(), "127.0.0.3:9".into())
            ]
        );
        // A failed lookup keeps the last answer.
        *records.lock().unwrap() = Err(std::io::Error::other("SERVFAIL"));
        settle().await;
        assert_eq!(addresses(&pool).len(), 2);
        // Nothing healthy to place on: the error says what the pool holds.
        let err = pool.place(1).err().expect("placed on a worker nobody runs");
        assert!(err.to_string().contains("workers.dsrl.svc:50051@127.0.0.2:9"), "{err}");
    }
}
