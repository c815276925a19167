//! What a build costs: its wall time and the CPU time of its whole process tree (this process, its simulator
//! workers and their own children, MetaDrive's environment processes), summed over every run that worked on it, a
//! killed and resumed build included. Kept in `<state>/compute.json`, rewritten every few seconds, so a kill loses
//! at most that much of the count.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Compute {
    /// Wall seconds of the runs that worked on the build.
    pub wall_seconds: f64,
    /// CPU seconds (user + system) of those runs' process trees.
    pub cpu_seconds: f64,
    /// Runs that worked on it (more than one after a kill and a resume).
    pub runs: u32,
    /// Simulator workers of the last run.
    pub workers: u32,
    /// The CPU (`/proc/cpuinfo`'s model name) and the cores the machine had.
    pub cpu: String,
    /// Anything the counts do not cover (work done before measuring began), said in words.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
}

/// The machine's CPU, as records name it: `AMD EPYC 9B14 (2 cores, AVX2 kernels)`.
pub fn cpu_name() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_owned())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_owned());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    format!("{model} ({cores} cores, {} kernels)", dsrl_policy::matrix_kernels())
}

/// CPU seconds of the process `root` and all its descendants, read from `/proc`: each process's own user and
/// system time and that of its children it has reaped (children still running are counted as processes of the
/// tree, so nothing is counted twice).
pub fn tree_cpu_seconds(root: u32) -> f64 {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return 0.0;
    };
    // pid → (parent pid, CPU ticks).
    let mut processes: HashMap<u32, (u32, u64)> = HashMap::new();
    for entry in entries.flatten() {
        let Some(pid) = entry.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        // The command name (field 2) is in parentheses and may hold spaces: the fields after its last ')'.
        let Some((_, rest)) = stat.rsplit_once(')') else {
            continue;
        };
        let fields: Vec<&str> = rest.split_whitespace().collect();
        // rest[0] is field 3 (state): ppid is field 4, utime..cstime fields 14..17.
        let number = |i: usize| fields.get(i - 3).and_then(|f| f.parse::<u64>().ok()).unwrap_or(0);
        processes.insert(
            pid,
            (number(4) as u32, number(14) + number(15) + number(16) + number(17)),
        );
    }
    let mut total = 0u64;
    let mut frontier = vec![root];
    while let Some(pid) = frontier.pop() {
        if let Some((_, ticks)) = processes.get(&pid) {
            total += ticks;
        }
        frontier.extend(
            processes
                .iter()
                .filter(|(_, (parent, _))| *parent == pid)
                .map(|(child, _)| *child),
        );
    }
    // SAFETY: sysconf has no preconditions.
    let ticks_per_second = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
    total as f64 / ticks_per_second
}

/// Counts one run's compute into `<state>/compute.json` while the run goes on.
pub struct Meter {
    path: PathBuf,
    before: Compute,
    started: Instant,
    workers: u32,
}

impl Meter {
    /// Starts counting a run of `workers` simulator workers on the build in `state`.
    pub fn start(state: &Path, workers: u32) -> anyhow::Result<Meter> {
        let path = state.join("compute.json");
        let before = match std::fs::read(&path) {
            Ok(bytes) => serde_json::from_slice(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Compute::default(),
            Err(e) => anyhow::bail!("reading {}: {e}", path.display()),
        };
        let meter = Meter {
            path,
            before,
            started: Instant::now(),
            workers,
        };
        meter.save()?;
        Ok(meter)
    }

    /// The build's compute so far: earlier runs and this one.
    pub fn now(&self) -> Compute {
        let mut compute = self.before.clone();
        compute.wall_seconds = (compute.wall_seconds + self.started.elapsed().as_secs_f64()).round();
        compute.cpu_seconds = (compute.cpu_seconds + tree_cpu_seconds(std::process::id())).round();
        compute.runs += 1;
        compute.workers = self.workers;
        compute.cpu = cpu_name();
        compute
    }

    pub fn save(&self) -> anyhow::Result<Compute> {
        let compute = self.now();
        crate::write_atomically(&self.path, &serde_json::to_vec_pretty(&compute)?)?;
        Ok(compute)
    }

    /// Saves every `every` until the returned task is aborted.
    pub fn keep_saving(self: std::sync::Arc<Self>, every: Duration) -> tokio::task::JoinHandle<()> {
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(every).await;
                if let Err(e) = self.save() {
                    tracing::warn!(error = %e, "saving the build's compute");
                }
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tree_counts_a_busy_child_and_the_meter_adds_runs_up() {
        // A child that spins for a while: its CPU time shows in the tree of this process.
        let mut child = std::process::Command::new("sh")
            .args(["-c", "i=0; while [ $i -lt 300000 ]; do i=$((i+1)); done; sleep 5"])
            .spawn()
            .unwrap();
        let before = tree_cpu_seconds(std::process::id());
        let mut spun = 0.0;
        for _ in 0..100 {
            std::thread::sleep(Duration::from_millis(100));
            spun = tree_cpu_seconds(std::process::id()) - before;
            if spun >= 0.2 {
                break;
            }
        }
        child.kill().unwrap();
        child.wait().unwrap();
        assert!(spun >= 0.2, "the child's CPU time was not counted ({spun} s)");

        let dir = tempfile::tempdir().unwrap();
        let first = Meter::start(dir.path(), 2).unwrap().save().unwrap();
        assert_eq!(first.runs, 1);
        assert!(first.cpu.contains("cores"), "{}", first.cpu);
        let second = Meter::start(dir.path(), 1).unwrap().save().unwrap();
        assert_eq!((second.runs, second.workers), (2, 1));
        assert!(second.cpu_seconds >= first.cpu_seconds);
    }
}
