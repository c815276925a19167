//! Playing policies on the real simulators, for whoever needs it without the HTTP server: the leaderboard's
//! evaluators (`dsrl-server`), and the data pipeline (`dsrl-admin`) that trains and scores experts.
//!
//! - `simulators`: the pool of `dsrl-sim-worker` processes (local ones supervised, remote ones health-checked);
//! - `evaluator`: episodes from given seeds, played with a policy's deterministic actions, and the checks a policy
//!   passes before it is played;
//! - `inference`: where a submitted policy computes its actions (in a memory-capped child process);
//! - `seeds` and `protocol`: the held episode seeds and the protocol version results are scored under.

mod config;
mod error;
pub mod evaluator;
pub mod inference;
pub mod protocol;
pub mod seeds;
pub mod simulators;

pub use config::SimulatorsConfig;
pub use error::EvaluationError;

/// The scorer's revision, part of the protocol version (`dsrl_suite::protocol`): bump it when a change to the
/// scoring code changes what any episode scores. The scoring code is what `SCORER_SOURCES` lists; the drift test
/// `tests/it/scorer.rs` holds their digest, so a change to any of them must be looked at (and the digest updated,
/// with this revision bumped where scores change).
pub const SCORER_REVISION: u32 = 1;

/// The files the scorer's revision covers, relative to the workspace root: how episodes are played and seeded
/// (the evaluator, the rollout, the simulator package), and how their returns become scores.
pub const SCORER_SOURCES: [&str; 7] = [
    "evaluation/src/evaluator.rs",
    "policy/src/acting.rs",
    "suite/src/score.rs",
    "suite/src/leaderboard.rs",
    "sim/python/dsrl_sim/tasks.py",
    "sim/python/dsrl_sim/metadrive_tasks.py",
    "sim/python/dsrl_sim/batch.py",
];

/// The simulator pins as the protocol version covers them: the pinned requirements and constraints of the worker's
/// Python environment and the fixes `sim/setup.sh` applies to it.
pub const SIMULATOR_PINS: &str = concat!(
    include_str!("../../sim/python/requirements.txt"),
    include_str!("../../sim/python/constraints.txt"),
    include_str!("../../sim/python/apply_fixes.py"),
);

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

#[cfg(test)]
mod tests {
    use super::*;

    /// The digest of `SCORER_SOURCES` when `SCORER_REVISION` was last reviewed.
    const REVIEWED_SCORER_SOURCES_SHA256: &str = "c5a51d82c65a041f7027053365f4cf5f5417dedb8bfa837ece8ebbd3432e735b";

    /// A drift check like the generated gRPC code's: a change to the scoring code fails here until someone decides
    /// whether it changes what an episode scores (then `SCORER_REVISION` is bumped, which changes the protocol
    /// version) and records the new digest.
    #[test]
    fn the_scorer_revision_was_reviewed_against_the_scoring_code() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut all = Vec::new();
        for source in SCORER_SOURCES {
            let bytes = std::fs::read(root.join(source)).unwrap_or_else(|e| panic!("{source}: {e}"));
            all.extend_from_slice(source.as_bytes());
            all.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
            all.extend_from_slice(&bytes);
        }
        let (digest, _) = dsrl_suite::hashing::sha256_reader(&all[..]).unwrap();
        let digest = dsrl_suite::VersionId::from_digest(&digest);
        assert_eq!(
            digest.as_str(),
            REVIEWED_SCORER_SOURCES_SHA256,
            "the scoring code changed ({}): if the change alters what any episode scores, bump SCORER_REVISION \
             (the protocol version changes, and results scored before stop ranking); either way record the new \
             digest in REVIEWED_SCORER_SOURCES_SHA256",
            SCORER_SOURCES.join(", ")
        );
    }
}
