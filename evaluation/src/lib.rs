//! Playing policies on the real simulators, for whoever needs it without the HTTP server: the leaderboard's
//! evaluators (`dsrl-server`), and the data pipeline (`dsrl-admin`) that trains and scores experts.
//!
//! - `simulators`: the pool of `dsrl-sim-worker` processes (local ones supervised, remote ones health-checked);
//! - `evaluator`: episodes from given seeds, played with a policy's deterministic actions, and the checks a policy
//!   passes before it is played;
//! - `inference`: where a submitted policy computes its actions (in a memory-capped child process).

mod config;
mod error;
pub mod evaluator;
pub mod inference;
pub mod simulators;

pub use config::SimulatorsConfig;
pub use error::EvaluationError;

/// Caps the address space of the current process (Linux; a no-op elsewhere). Called first thing in a child process
/// (an upload's converter, a submitted policy's player), so input that makes it allocate without bound fails that
/// child, not the machine.
pub fn limit_memory(bytes: u64) {
    #[cfg(target_os = "linux")]
    {
        let limit = libc::rlimit {
            rlim_cur: bytes as libc::rlim_t,
            rlim_max: bytes as libc::rlim_t,
        };
        // SAFETY: setrlimit with a valid pointer to an initialized struct.
        let rc = unsafe { libc::setrlimit(libc::RLIMIT_AS, &limit) };
        if rc != 0 {
            eprintln!("setrlimit failed: {}", std::io::Error::last_os_error());
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = bytes;
}
