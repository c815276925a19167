//! Where a submitted policy computes its actions while it is scored. A submission is weights plus a declared
//! architecture, checked before it is queued; still, a network that is legal but expensive (a CDT with a long
//! context) could take the CPU or the memory of the API process. So the leaderboard plays such submissions in a
//! child process (`dsrl-server play-policy`, hidden) under an address-space limit and at a lower scheduling
//! priority: the worst a policy can do is fail its own evaluation. A cheap network (its declared cost per action at
//! most `leaderboard.act_in_workers_max_multiply_adds`) is scored acting inside the simulator workers instead
//! (`crate::in_workers`: the same episodes without a round trip per step); replays always play here, in a child.
//! `dsrl-admin evaluate` and tests that embed the server act in process.
//!
//! The child speaks a small binary protocol on its standard input and output. Each request is
//! `[op: u8][length: u32 LE][payload]`, each answer `[status: u8][length: u32 LE][payload]` (status 0: the
//! payload is the result, 1: a UTF-8 error message). Numbers are little-endian.
//! - `LOAD` = config length (u32), `policy.json`, `policy.safetensors`, cost threshold (f64), slots (u32);
//! - `START` = slot (u32), episode seed (u64);
//! - `ACT` = n (u32), n slots (u32), observations (f32, row-major) → actions (f32, row-major);
//! - `OBSERVE` = n (u32), n slots (u32), n rewards (f64), n costs (f64).
//!
//! Requests may be pipelined, and answers come in the order of the requests. The parent holds back the requests
//! whose answers carry nothing (`START`, `OBSERVE`) and writes them with the next `ACT`, in one write; the child
//! flushes its answers only when it has no further request already read. So a step costs one exchange with the
//! child, not two: each exchange wakes both processes, and on a machine whose cores the simulator workers share
//! with the server and its policy processes, every wake-up takes time from the simulators (BENCHMARKS.md,
//! scoring).

use std::io::{Read, Write};
use std::path::PathBuf;
use std::process::Stdio;

use bytes::{Buf, BufMut, Bytes, BytesMut};
use dsrl_policy::{Policy, Rollout, checkpoint};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::EvaluationError;

const LOAD: u8 = 1;
const START: u8 = 2;
const ACT: u8 = 3;
const OBSERVE: u8 = 4;
/// Largest frame either side accepts: a load carries at most the weights limit plus the config limit.
const MAX_FRAME: u32 = (checkpoint::MAX_WEIGHTS_BYTES + checkpoint::MAX_CONFIG_BYTES + 64) as u32;

/// A submitted checkpoint to be played in a child process.
#[derive(Debug, Clone)]
pub struct IsolatedPolicy {
    /// The `dsrl-server` binary.
    pub program: PathBuf,
    pub memory_limit_bytes: u64,
    /// Every request must be answered within this; a process that does not is stopped and the evaluation fails.
    pub request_timeout: std::time::Duration,
    /// Score it acting inside the simulator workers (`crate::in_workers`) rather than in a child process; replays
    /// always play it in a child process.
    pub act_in_workers: bool,
    pub config: Bytes,
    pub weights: Bytes,
}

/// The policy an evaluation plays: built in this process, or a checkpoint played in a child process.
#[derive(Clone, Copy)]
pub enum PolicySource<'a> {
    Local(&'a Policy),
    Isolated(&'a IsolatedPolicy),
}

/// A policy playing episodes in a fixed number of environment slots at one cost threshold, wherever it runs.
pub enum Player<'a> {
    Local(Rollout<'a>),
    Child(Box<ChildPlayer>),
}

fn policy_error(e: impl std::fmt::Display) -> EvaluationError {
    EvaluationError::Internal(format!("evaluating the policy: {e}"))
}

impl<'a> Player<'a> {
    pub async fn new(
        source: PolicySource<'a>,
        cost_threshold: f64,
        slots: usize,
    ) -> Result<Player<'a>, EvaluationError> {
        match source {
            PolicySource::Local(policy) => Ok(Player::Local(
                policy.rollout(cost_threshold, slots).map_err(policy_error)?,
            )),
            PolicySource::Isolated(isolated) => Ok(Player::Child(Box::new(
                ChildPlayer::spawn(isolated, cost_threshold, slots).await?,
            ))),
        }
    }

    pub async fn start_episode(&mut self, slot: usize, seed: u64) -> Result<(), EvaluationError> {
        match self {
            Player::Local(rollout) => rollout.start_episode(slot, seed).map_err(policy_error),
            Player::Child(child) => {
                let mut payload = BytesMut::with_capacity(12);
                payload.put_u32_le(slot as u32);
                payload.put_u64_le(seed);
                child.hold(START, &payload);
                Ok(())
            }
        }
    }

    pub async fn act(&mut self, slots: &[u32], observations: &[f32]) -> Result<Vec<f32>, EvaluationError> {
        match self {
            Player::Local(rollout) => rollout.act(slots, observations).map_err(policy_error),
            Player::Child(child) => {
                let mut payload = BytesMut::with_capacity(4 + 4 * slots.len() + 4 * observations.len());
                put_slots(&mut payload, slots);
                observations.iter().for_each(|&x| payload.put_f32_le(x));
                let answer = child.call(ACT, &payload).await?;
                Ok(answer
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
                    .collect())
            }
        }
    }

    pub async fn observe(&mut self, slots: &[u32], rewards: &[f64], costs: &[f64]) -> Result<(), EvaluationError> {
        match self {
            Player::Local(rollout) => rollout.observe(slots, rewards, costs).map_err(policy_error),
            Player::Child(child) => {
                let mut payload = BytesMut::with_capacity(4 + 20 * slots.len());
                put_slots(&mut payload, slots);
                rewards.iter().for_each(|&x| payload.put_f64_le(x));
                costs.iter().for_each(|&x| payload.put_f64_le(x));
                child.hold(OBSERVE, &payload);
                Ok(())
            }
        }
    }

    /// Sends the requests held back for the next `ACT` and waits for their answers: call it when a rollout ends,
    /// so that none of them is left unsent (and a failure of one is not lost).
    pub async fn finish(&mut self) -> Result<(), EvaluationError> {
        match self {
            Player::Local(_) => Ok(()),
            Player::Child(child) => child.send_held().await.map(drop),
        }
    }
}

fn put_slots(payload: &mut BytesMut, slots: &[u32]) {
    payload.put_u32_le(slots.len() as u32);
    slots.iter().for_each(|&s| payload.put_u32_le(s));
}

/// How often [`within_budget`] looks at the clock, and how late a look may come before the time since the last one
/// counts as time this process did not run: when the evaluator itself was not running (its process group stopped,
/// the machine suspended or starved for seconds), the policy's process was not either, and a look that comes far
/// later than asked adds one tick, not the gap.
const AWAKE_TICK: std::time::Duration = std::time::Duration::from_millis(250);
const SUSPENDED_AFTER: std::time::Duration = std::time::Duration::from_millis(1250);

/// How long a request may take on the clock, in multiples of its CPU budget, before the policy process is taken for
/// one that makes no progress.
const CLOCK_FACTOR: u32 = 4;

/// How a policy request ran out of time.
#[derive(Debug, PartialEq)]
enum Overdue {
    /// The policy process used more CPU seconds on the request than it may (the checkpoint's doing).
    Cpu(f64),
    /// The request outlasted `CLOCK_FACTOR` times the budget on the evaluator's running clock while the policy
    /// process used less than its budget of CPU: it was starved or stopped, which is the machine's doing.
    Clock,
}

/// The CPU seconds (user and system) process `pid` has used; `None` where that cannot be read (the process gone).
/// It is read twice per policy request, so it asks the kernel for the process's CPU-time clock (one system call,
/// nanoseconds) and falls back to `/proc/<pid>/stat` (a file to open and parse, in clock ticks) where that clock
/// cannot be had.
fn cpu_seconds(pid: u32) -> Option<f64> {
    cpu_clock_seconds(pid).or_else(|| proc_stat_seconds(pid))
}

fn cpu_clock_seconds(pid: u32) -> Option<f64> {
    let mut clock: libc::clockid_t = 0;
    let mut now = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: both calls only write the values they are given pointers to, which live on this stack.
    let read = unsafe {
        libc::clock_getcpuclockid(pid as libc::pid_t, &mut clock) == 0 && libc::clock_gettime(clock, &mut now) == 0
    };
    read.then_some(now.tv_sec as f64 + now.tv_nsec as f64 * 1e-9)
}

fn proc_stat_seconds(pid: u32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces: count the fields after its ')'. The first
    // of them is field 3, so utime and stime (fields 14 and 15) are the 12th and 13th.
    let fields: Vec<&str> = stat.get(stat.rfind(')')? + 1..)?.split_whitespace().collect();
    let ticks = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    // SAFETY: sysconf reads a constant of the system.
    let per_second = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    (per_second > 0).then(|| ticks as f64 / per_second as f64)
}

/// A policy request held to its budget: `limit` of the policy process's CPU time, which is what a checkpoint
/// decides (a network too expensive to act in time), and not the clock, which a busy machine decides (a policy
/// process starved of CPU by other work answers late through no fault of the checkpoint). A process that makes no
/// progress at all is not waited on forever: after `CLOCK_FACTOR` times the budget of the evaluator's running time
/// (`AWAKE_TICK`), the request ends as `Overdue::Clock`. Where the process's CPU time cannot be read, the clock
/// alone is the budget, as the checkpoint's.
///
/// The process's CPU time is read when the request is sent and at each clock look: the request is charged what the
/// process used in between, never the evaluator's own waiting (a starved evaluator may look tens of seconds late,
/// and charging that wait as CPU once failed a checkpoint for the machine's sake).
async fn within_budget<F: std::future::Future>(
    pid: Option<u32>,
    limit: std::time::Duration,
    call: F,
) -> Result<F::Output, Overdue> {
    tokio::pin!(call);
    let started = tokio::time::Instant::now();
    let limit_seconds = limit.as_secs_f64();
    // The process's CPU seconds when the request is sent: what it uses from here on is the request's.
    let cpu_at_start = pid.and_then(cpu_seconds);
    let mut readable = cpu_at_start.is_some();
    let cpu_used = || -> Option<f64> { Some(cpu_seconds(pid?)? - cpu_at_start?) };
    let mut looked = false;
    let mut awake = std::time::Duration::ZERO;
    let mut last = started;
    loop {
        let clock_limit = if readable { limit * CLOCK_FACTOR } else { limit };
        let left = clock_limit.saturating_sub(awake);
        match tokio::time::timeout(left.min(AWAKE_TICK), &mut call).await {
            Ok(output) => {
                // A request that ended between two looks is held to the budget too (one shorter than a look
                // costs no second read).
                if let Some(used) = looked.then(cpu_used).flatten().filter(|&used| used > limit_seconds) {
                    return Err(Overdue::Cpu(used));
                }
                return Ok(output);
            }
            Err(_) => {
                let now = tokio::time::Instant::now();
                let gap = now - last;
                last = now;
                awake += if gap > SUSPENDED_AFTER { AWAKE_TICK } else { gap };
                looked = true;
                let used = if readable { cpu_used() } else { None };
                readable = used.is_some();
                if let Some(used) = used.filter(|&used| used > limit_seconds) {
                    return Err(Overdue::Cpu(used));
                }
                let clock_limit = if readable { limit * CLOCK_FACTOR } else { limit };
                if awake >= clock_limit {
                    return Err(if readable {
                        Overdue::Clock
                    } else {
                        Overdue::Cpu(awake.as_secs_f64())
                    });
                }
            }
        }
    }
}

/// The parent's side of one child process.
pub struct ChildPlayer {
    child: tokio::process::Child,
    stdin: tokio::process::ChildStdin,
    stdout: tokio::io::BufReader<tokio::process::ChildStdout>,
    memory_limit_bytes: u64,
    request_timeout: std::time::Duration,
    /// Requests written to no pipe yet (whole frames), sent before the next request that waits for its answer.
    held: BytesMut,
    /// The ops of the frames in `held`, in order.
    held_ops: Vec<u8>,
}

impl ChildPlayer {
    async fn spawn(policy: &IsolatedPolicy, cost_threshold: f64, slots: usize) -> Result<ChildPlayer, EvaluationError> {
        let mut child = tokio::process::Command::new(&policy.program)
            .arg(CHILD_COMMAND)
            .args(["--memory-limit", &policy.memory_limit_bytes.to_string()])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .map_err(|e| {
                EvaluationError::Internal(format!("starting {} play-policy: {e}", policy.program.display()))
            })?;
        let stdin = child.stdin.take().expect("piped");
        let stdout = child.stdout.take().expect("piped");
        let mut player = ChildPlayer::new(child, stdin, stdout, policy.memory_limit_bytes, policy.request_timeout);
        let mut payload = BytesMut::with_capacity(policy.config.len() + policy.weights.len() + 16);
        payload.put_u32_le(policy.config.len() as u32);
        payload.put_slice(&policy.config);
        payload.put_slice(&policy.weights);
        payload.put_f64_le(cost_threshold);
        payload.put_u32_le(slots as u32);
        player.call(LOAD, &payload).await?;
        Ok(player)
    }

    fn new(
        child: tokio::process::Child,
        stdin: tokio::process::ChildStdin,
        stdout: tokio::process::ChildStdout,
        memory_limit_bytes: u64,
        request_timeout: std::time::Duration,
    ) -> ChildPlayer {
        ChildPlayer {
            child,
            stdin,
            stdout: tokio::io::BufReader::new(stdout),
            memory_limit_bytes,
            request_timeout,
            held: BytesMut::new(),
            held_ops: Vec::new(),
        }
    }

    /// Keeps a request whose answer carries nothing for the next exchange.
    fn hold(&mut self, op: u8, payload: &[u8]) {
        self.held.put_u8(op);
        self.held.put_u32_le(payload.len() as u32);
        self.held.put_slice(payload);
        self.held_ops.push(op);
    }

    /// Sends the held requests and `op` with `payload`, and returns the answer to `op`.
    async fn call(&mut self, op: u8, payload: &[u8]) -> Result<Bytes, EvaluationError> {
        self.hold(op, payload);
        self.send_held().await
    }

    /// Sends the held requests in one write and returns the last one's answer (nothing when none was held). The
    /// exchange is held to the budget of one request: what a request needs of it is the `ACT` (`START` and
    /// `OBSERVE` only write down a number or two).
    async fn send_held(&mut self) -> Result<Bytes, EvaluationError> {
        let Some(&last) = self.held_ops.last() else {
            return Ok(Bytes::new());
        };
        let what = match last {
            LOAD => "load",
            START => "start",
            ACT => "act",
            _ => "observe",
        };
        let frames = std::mem::take(&mut self.held).freeze();
        let ops = std::mem::take(&mut self.held_ops);
        let pid = self.child.id();
        match within_budget(pid, self.request_timeout, self.exchange(&frames, ops.len())).await {
            Ok(Ok(Ok(answer))) => Ok(answer),
            // The policy itself failed (a shape it cannot handle, a non-finite action): not worth a retry.
            Ok(Ok(Err(message))) => Err(policy_error(message)),
            Err(Overdue::Cpu(used)) => {
                let _ = self.child.start_kill();
                Err(EvaluationError::InvalidArgument(format!(
                    "the policy process did not answer a {what} request within {} s of CPU time (it used {used:.1} \
                     s; leaderboard.policy_request_seconds); it was stopped",
                    self.request_timeout.as_secs_f64()
                )))
            }
            Err(Overdue::Clock) => {
                let _ = self.child.start_kill();
                Err(EvaluationError::Unavailable(format!(
                    "the policy process did not answer a {what} request within {} s while using less than its {} s \
                     of CPU time: it was starved or stopped, not too slow; the job goes back to the queue",
                    (self.request_timeout * CLOCK_FACTOR).as_secs_f64(),
                    self.request_timeout.as_secs_f64()
                )))
            }
            Ok(Err(_)) => Err(self.died(what).await),
        }
    }

    /// Why the pipe broke, from the child's exit status, as observed. A crash signal is the process's own doing
    /// and would come again with the same checkpoint: an abort is what an allocation past its memory limit ends in,
    /// the others (SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGXCPU, SIGSYS, SIGTRAP) a fault while playing it. Any other
    /// signal came from outside (no participant code runs in the child): an operator's or a service manager's
    /// SIGTERM or SIGINT to the server's process group, a SIGHUP, the kernel's OOM killer's SIGKILL. That is not
    /// the checkpoint's fault, and the job goes back to the queue instead of failing it for good.
    async fn died(&mut self, what: &str) -> EvaluationError {
        let status = match tokio::time::timeout(std::time::Duration::from_secs(5), self.child.wait()).await {
            Ok(Ok(status)) => status,
            _ => {
                return EvaluationError::Unavailable(format!(
                    "the policy process stopped answering during a {what} request and gave no exit status"
                ));
            }
        };
        #[cfg(unix)]
        {
            use std::os::unix::process::ExitStatusExt;
            match status.signal() {
                Some(libc::SIGABRT) => {
                    return EvaluationError::InvalidArgument(format!(
                        "the policy process aborted during a {what} request, as it does when an allocation fails \
                         under its {} MB memory limit",
                        self.memory_limit_bytes >> 20
                    ));
                }
                Some(
                    signal @ (libc::SIGSEGV
                    | libc::SIGBUS
                    | libc::SIGILL
                    | libc::SIGFPE
                    | libc::SIGXCPU
                    | libc::SIGSYS
                    | libc::SIGTRAP),
                ) => {
                    return EvaluationError::InvalidArgument(format!(
                        "the policy process crashed on signal {signal} during a {what} request"
                    ));
                }
                Some(signal) => {
                    return EvaluationError::Unavailable(format!(
                        "the policy process was stopped by signal {signal} from outside the evaluator during a \
                         {what} request (not by its own limits); the job goes back to the queue"
                    ));
                }
                None => {}
            }
        }
        EvaluationError::InvalidArgument(format!("the policy process exited ({status}) during a {what} request"))
    }

    /// Writes `frames` (`requests` whole requests) and reads as many answers: the last one's, or the first error.
    async fn exchange(&mut self, frames: &[u8], requests: usize) -> std::io::Result<Result<Bytes, String>> {
        self.stdin.write_all(frames).await?;
        self.stdin.flush().await?;
        let mut answer = Ok(Bytes::new());
        for _ in 0..requests {
            let mut head = [0u8; 5];
            self.stdout.read_exact(&mut head).await?;
            let len = u32::from_le_bytes(head[1..].try_into().expect("4 bytes"));
            if len > MAX_FRAME {
                return Err(std::io::Error::other("oversized answer"));
            }
            let mut body = vec![0u8; len as usize];
            self.stdout.read_exact(&mut body).await?;
            if head[0] != 0 {
                // The child goes on answering after an error; the evaluation ends with this one.
                return Ok(Err(String::from_utf8_lossy(&body).into_owned()));
            }
            answer = Ok(Bytes::from(body));
        }
        Ok(answer)
    }
}

/// The hidden command a policy child is started with: `<program> play-policy --memory-limit BYTES`.
const CHILD_COMMAND: &str = "play-policy";

/// Serves as a policy child when this process was started as one (the command line `ChildPlayer::spawn` writes);
/// otherwise returns `None` and the binary goes on with its own command line. Every binary that scores submissions
/// (`dsrl-server`, `dsrl-evaluator`) calls it first thing in `main`, so the parent's and the child's sides of the
/// command line are written here only.
///
/// # Safety
/// As [`serve_child`]: first thing in `main`, before any other thread exists.
pub unsafe fn serve_child_if_started_as_one() -> Option<std::process::ExitCode> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) != Some(CHILD_COMMAND) {
        return None;
    }
    let memory_limit = match args.as_slice() {
        [_, flag, bytes] if flag == "--memory-limit" => bytes.parse::<u64>().ok(),
        _ => None,
    };
    Some(match memory_limit {
        // SAFETY: the caller's contract.
        Some(bytes) => unsafe { serve_child(bytes) },
        None => {
            eprintln!(
                "usage: {CHILD_COMMAND} --memory-limit BYTES (an evaluator starts it; it is not for use by hand)"
            );
            std::process::ExitCode::from(2)
        }
    })
}

/// The child's side (`play-policy`): pins candle to one thread, lowers its priority, caps its memory, dies with
/// its parent, then answers requests on stdin/stdout until stdin closes. Returns the process exit code.
///
/// # Safety
/// Sets an environment variable (see `dsrl_policy::pin_candle_threads`): call it first thing in `main`, before
/// any other thread exists.
pub unsafe fn serve_child(memory_limit_bytes: u64) -> std::process::ExitCode {
    // SAFETY: the caller's contract, the same as this one's.
    unsafe { dsrl_policy::pin_candle_threads() };
    #[cfg(target_os = "linux")]
    // SAFETY: plain system calls with constant arguments. PR_SET_PDEATHSIG kills this process when the thread
    // that spawned it (an async worker thread of the server, alive as long as the server) goes away; the
    // getppid check covers a parent that died before the prctl.
    unsafe {
        libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
        if libc::getppid() == 1 {
            return std::process::ExitCode::FAILURE;
        }
        libc::setpriority(libc::PRIO_PROCESS, 0, 10);
    }
    crate::limit_memory(memory_limit_bytes);
    // The pipes themselves, buffered here: the parent pipelines requests (see the module's comment), and an answer
    // is flushed only once no request already read waits behind it. (Rust's own stdout flushes at every newline
    // byte, which binary answers hold at random.)
    use std::os::fd::FromRawFd;
    // SAFETY: descriptors 0 and 1 are this process's standard input and output, open for its whole life;
    // ManuallyDrop leaves them open when these handles go.
    let (stdin, stdout) = unsafe {
        (
            std::mem::ManuallyDrop::new(std::fs::File::from_raw_fd(0)),
            std::mem::ManuallyDrop::new(std::fs::File::from_raw_fd(1)),
        )
    };
    let mut input = std::io::BufReader::with_capacity(1 << 16, &*stdin);
    let mut output = std::io::BufWriter::with_capacity(1 << 16, &*stdout);
    // The first request loads the policy; every later one plays it.
    let Some((op, payload)) = read_frame(&mut input) else {
        return std::process::ExitCode::FAILURE;
    };
    let loaded = match op {
        LOAD => decode_load(&payload),
        op => Err(format!("request {op} before the policy was loaded")),
    };
    let (policy, threshold, slots) = match loaded {
        Ok(loaded) => loaded,
        Err(message) => {
            let _ = reply(&mut output, Err(message)).and_then(|()| output.flush());
            return std::process::ExitCode::FAILURE;
        }
    };
    let mut rollout = match policy.rollout(threshold, slots) {
        Ok(rollout) => rollout,
        Err(e) => {
            let _ = reply(&mut output, Err(e.to_string())).and_then(|()| output.flush());
            return std::process::ExitCode::FAILURE;
        }
    };
    let loaded = reply(&mut output, Ok(Vec::new()));
    if loaded.and_then(|()| output.flush()).is_err() {
        return std::process::ExitCode::FAILURE;
    }
    // Until the parent closes the pipe. An answer waits in the buffer while a request already read follows it.
    while let Some((op, payload)) = read_frame(&mut input) {
        let mut answered = reply(&mut output, handle(&mut rollout, op, &payload));
        if answered.is_ok() && input.buffer().is_empty() {
            answered = output.flush();
        }
        if answered.is_err() {
            return std::process::ExitCode::FAILURE;
        }
    }
    std::process::ExitCode::SUCCESS
}

fn read_frame(input: &mut impl Read) -> Option<(u8, Vec<u8>)> {
    let mut head = [0u8; 5];
    input.read_exact(&mut head).ok()?;
    let len = u32::from_le_bytes(head[1..].try_into().expect("4 bytes"));
    if len > MAX_FRAME {
        return None;
    }
    let mut payload = vec![0u8; len as usize];
    input.read_exact(&mut payload).ok()?;
    Some((head[0], payload))
}

/// Writes one answer into `output`'s buffer (the caller flushes).
fn reply(output: &mut impl Write, answer: Result<Vec<u8>, String>) -> std::io::Result<()> {
    let (status, body) = match answer {
        Ok(body) => (0u8, body),
        Err(message) => (1u8, message.into_bytes()),
    };
    output.write_all(&[status])?;
    output.write_all(&(body.len() as u32).to_le_bytes())?;
    output.write_all(&body)
}

fn decode_load(payload: &[u8]) -> Result<(Policy, f64, usize), String> {
    let mut buf = payload;
    let short = || "a truncated LOAD request".to_owned();
    if buf.remaining() < 4 {
        return Err(short());
    }
    let config_len = buf.get_u32_le() as usize;
    if buf.remaining() < config_len + 12 {
        return Err(short());
    }
    let config = checkpoint::parse_config(&buf[..config_len]).map_err(|e| e.to_string())?;
    let weights = &buf[config_len..buf.len() - 12];
    let tensors = checkpoint::parse_weights(weights).map_err(|e| e.to_string())?;
    let policy = Policy::load(&config, &tensors).map_err(|e| e.to_string())?;
    let mut tail = &buf[buf.len() - 12..];
    let threshold = tail.get_f64_le();
    let slots = tail.get_u32_le() as usize;
    Ok((policy, threshold, slots))
}

fn slots_of(buf: &mut &[u8]) -> Result<Vec<u32>, String> {
    if buf.remaining() < 4 {
        return Err("a truncated request".into());
    }
    let n = buf.get_u32_le() as usize;
    if buf.remaining() < 4 * n {
        return Err("a truncated request".into());
    }
    Ok((0..n).map(|_| buf.get_u32_le()).collect())
}

fn handle(rollout: &mut Rollout<'_>, op: u8, payload: &[u8]) -> Result<Vec<u8>, String> {
    let mut buf = payload;
    match op {
        START => {
            if buf.remaining() != 12 {
                return Err("a malformed START request".into());
            }
            let slot = buf.get_u32_le() as usize;
            let seed = buf.get_u64_le();
            rollout.start_episode(slot, seed).map_err(|e| e.to_string())?;
            Ok(Vec::new())
        }
        ACT => {
            let slots = slots_of(&mut buf)?;
            if !buf.remaining().is_multiple_of(4) {
                return Err("a malformed ACT request".into());
            }
            let observations: Vec<f32> = buf
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().expect("4")))
                .collect();
            let actions = rollout.act(&slots, &observations).map_err(|e| e.to_string())?;
            Ok(actions.iter().flat_map(|a| a.to_le_bytes()).collect())
        }
        OBSERVE => {
            let slots = slots_of(&mut buf)?;
            let n = slots.len();
            if buf.remaining() != 16 * n {
                return Err("a malformed OBSERVE request".into());
            }
            let rewards: Vec<f64> = (0..n).map(|_| buf.get_f64_le()).collect();
            let costs: Vec<f64> = (0..n).map(|_| buf.get_f64_le()).collect();
            rollout.observe(&slots, &rewards, &costs).map_err(|e| e.to_string())?;
            Ok(Vec::new())
        }
        other => Err(format!("unknown request {other}")),
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    /// An answer 2.6 s after the call, 2 s of which the runtime was blocked (as in a stopped process group), comes
    /// within a 1 s limit; a call that never answers still ends at its limit.
    #[tokio::test(flavor = "current_thread")]
    async fn time_the_evaluator_did_not_run_is_not_held_against_the_policy() {
        let answer = tokio::time::sleep(std::time::Duration::from_millis(2600));
        let stall = async {
            tokio::task::yield_now().await;
            std::thread::sleep(std::time::Duration::from_secs(2));
        };
        let started = std::time::Instant::now();
        let (result, ()) = tokio::join!(within_budget(None, std::time::Duration::from_secs(1), answer), stall);
        assert!(result.is_ok(), "timed out after {:?}", started.elapsed());
        let started = std::time::Instant::now();
        let never = within_budget(
            None,
            std::time::Duration::from_millis(500),
            std::future::pending::<()>(),
        )
        .await;
        assert!(never.is_err());
        assert!(
            started.elapsed() < std::time::Duration::from_secs(2),
            "{:?}",
            started.elapsed()
        );
    }

    /// A process that computes past its CPU budget is the checkpoint's doing; one that sleeps (as a starved or
    /// stopped process does) ends on the clock, at `CLOCK_FACTOR` times the budget, as the machine's. Real processes:
    /// a shell's busy loop and `sleep`.
    #[tokio::test(flavor = "current_thread")]
    async fn a_request_is_held_to_the_policy_processes_cpu_time_not_the_clock() {
        let spawn = |script: &str| {
            tokio::process::Command::new("sh")
                .args(["-c", script])
                .kill_on_drop(true)
                .spawn()
                .unwrap()
        };
        let busy = spawn("while :; do :; done");
        let limit = std::time::Duration::from_millis(600);
        let started = std::time::Instant::now();
        let overdue = within_budget(busy.id(), limit, std::future::pending::<()>()).await;
        assert!(matches!(overdue, Err(Overdue::Cpu(used)) if used > 0.6), "{overdue:?}");
        assert!(started.elapsed() < limit * CLOCK_FACTOR, "{:?}", started.elapsed());

        let idle = spawn("sleep 30");
        let started = std::time::Instant::now();
        let overdue = within_budget(idle.id(), limit, std::future::pending::<()>()).await;
        assert_eq!(overdue, Err(Overdue::Clock));
        assert!(started.elapsed() >= limit * CLOCK_FACTOR, "{:?}", started.elapsed());

        // An evaluator blocked past the budget (the thread that polls the request does not run) while the policy
        // process sleeps: the wait is the machine's, not the policy's CPU, so the request is answered.
        let blocked = within_budget(idle.id(), limit, async {
            std::thread::sleep(limit * 2);
            tokio::task::yield_now().await;
            8
        })
        .await;
        assert_eq!(blocked, Ok(8));

        // An answer within the budget is an answer; without a process to read, the clock is the budget.
        let answer = within_budget(idle.id(), limit, async { 7 }).await;
        assert_eq!(answer, Ok(7));
        let unreadable = within_budget(None, limit, std::future::pending::<()>()).await;
        assert!(matches!(unreadable, Err(Overdue::Cpu(_))), "{unreadable:?}");
        assert!(cpu_seconds(std::process::id()).is_some_and(|s| s > 0.0));
    }

    /// The kernel's CPU-time clock of another process and its `/proc` ticks count the same seconds.
    #[test]
    fn a_processs_cpu_clock_agrees_with_its_proc_ticks() {
        let mut busy = std::process::Command::new("sh")
            .args(["-c", "while :; do :; done"])
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(400));
        let (clock, ticks) = (cpu_clock_seconds(busy.id()), proc_stat_seconds(busy.id()));
        busy.kill().unwrap();
        busy.wait().unwrap();
        let (clock, ticks) = (clock.unwrap(), ticks.unwrap());
        assert!(clock > 0.05, "the busy process used {clock} s");
        assert!((clock - ticks).abs() < 0.05, "clock {clock} s, /proc {ticks} s");
        assert_eq!(cpu_clock_seconds(busy.id()), None, "a reaped process has no clock");
    }

    /// A child that answers nothing, stopped by `signal` before it is asked to act: `sleep` stands in for the
    /// policy process, since what is tested is how its exit status is read, not how it plays (no core file).
    async fn stopped_by(signal: i32) -> EvaluationError {
        let mut command = tokio::process::Command::new("sh");
        command
            .args(["-c", "ulimit -c 0; exec sleep 600"])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .kill_on_drop(true);
        // A test run started in the background (`nohup … &`) hands its children SIGINT and SIGHUP ignored, and an
        // ignored signal survives exec (a shell cannot even trap it again): restore the defaults the test sends.
        // SAFETY: `signal` is async-signal-safe, as a pre_exec closure must be.
        unsafe {
            command.pre_exec(|| {
                for signal in [libc::SIGINT, libc::SIGHUP, libc::SIGQUIT] {
                    libc::signal(signal, libc::SIG_DFL);
                }
                Ok(())
            });
        }
        let mut child = command.spawn().unwrap();
        let (stdin, stdout) = (child.stdin.take().unwrap(), child.stdout.take().unwrap());
        // Let the shell exec sleep, so the signal reaches the process that stands in for the policy.
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
        // SAFETY: a plain system call on the pid of a child this test owns and has not reaped.
        assert_eq!(unsafe { libc::kill(child.id().unwrap() as i32, signal) }, 0);
        let mut player = ChildPlayer::new(child, stdin, stdout, 64 << 20, std::time::Duration::from_secs(30));
        player.call(ACT, b"observations").await.unwrap_err()
    }

    /// A stand-in child that writes `answers` (the bytes of whole answers) at once, then reads its input to the end.
    fn answering(answers: &str) -> ChildPlayer {
        let mut child = tokio::process::Command::new("sh")
            .args(["-c", &format!("printf '{answers}'; exec cat > /dev/null")])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let (stdin, stdout) = (child.stdin.take().unwrap(), child.stdout.take().unwrap());
        ChildPlayer::new(child, stdin, stdout, 64 << 20, std::time::Duration::from_secs(30))
    }

    /// Held requests go with the next call, and their answers are read before its own: the call returns its own
    /// answer, and an error answered to a held request is the call's error (not lost, not taken for the action).
    #[tokio::test]
    async fn held_requests_are_answered_before_the_call_that_sends_them() {
        // Two answers: an empty one (the held OBSERVE's), then 4 bytes (the ACT's).
        let mut player = answering(r"\000\000\000\000\000\000\004\000\000\000abcd");
        player.hold(OBSERVE, &[0; 4]);
        assert_eq!(&player.call(ACT, &[0; 4]).await.unwrap()[..], b"abcd");
        assert!(player.held.is_empty() && player.held_ops.is_empty());
        // The held OBSERVE failed: its message is what the ACT's call returns.
        let mut player = answering(r"\001\005\000\000\000oops!\000\004\000\000\000abcd");
        player.hold(OBSERVE, &[0; 4]);
        let e = player.call(ACT, &[0; 4]).await.unwrap_err();
        assert!(
            matches!(&e, EvaluationError::Internal(m) if m.contains("oops!")),
            "{e:?}"
        );
        // Nothing held: finishing sends nothing and waits for nothing.
        let mut player = answering("");
        assert!(player.send_held().await.unwrap().is_empty());
    }

    #[tokio::test]
    async fn a_policy_process_stopped_from_outside_gives_its_job_back_and_a_crash_fails_it() {
        for signal in [libc::SIGTERM, libc::SIGINT, libc::SIGHUP, libc::SIGKILL] {
            let e = stopped_by(signal).await;
            assert!(
                matches!(&e, EvaluationError::Unavailable(m) if m.contains(&format!("signal {signal} from outside"))),
                "signal {signal}: {e:?}"
            );
        }
        let e = stopped_by(libc::SIGSEGV).await;
        assert!(
            matches!(&e, EvaluationError::InvalidArgument(m) if m.contains("crashed on signal")),
            "{e:?}"
        );
        let e = stopped_by(libc::SIGABRT).await;
        assert!(
            matches!(&e, EvaluationError::InvalidArgument(m) if m.contains("64 MB memory limit")),
            "{e:?}"
        );
    }
}
