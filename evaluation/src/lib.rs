//! Playing policies on the real simulators, for whoever needs it without the HTTP server: the leaderboard's
//! evaluators (`dsrl-server`), and the data pipeline (`dsrl-admin`) that trains and scores experts.
//!
//! - the pool of `dsrl-sim-worker` processes it plays through is `dsrl-simulators`'s;
//! - `evaluator`: episodes from given seeds, played with a policy's deterministic actions, and the checks a policy
//!   passes before it is played;
//! - `inference`: where a submitted policy computes its actions (in a memory-capped child process);
//! - `seeds` and `protocol`: the held episode seeds and the protocol version results are scored under.

pub mod evaluator;
mod in_workers;
pub mod inference;
pub mod protocol;
pub mod seeds;

/// What can go wrong while playing a policy: the kinds a simulator session fails with, which the policy's own checks
/// use too (a policy that does not fit its task is `InvalidArgument`, as a malformed request to a worker is).
pub use dsrl_simulators::SimulatorError as EvaluationError;

/// The scorer's revision, part of the protocol version (`dsrl_scoring::protocol`): bump it when a change to the
/// scoring path changes what any episode scores. The scoring path is what `SCORING_PATH` lists; the drift test below
/// holds the digest of every file on it and of the dependencies' versions, so a change to any of them fails until
/// someone decides whether it changes scores (then this is bumped, and the protocol version with it) and records
/// the new digest.
pub const SCORER_REVISION: u32 = 1;

/// Everything between a stored checkpoint and a stored episode's score, relative to the workspace root; a folder
/// stands for every source file under it. The policy runtime (every network a checkpoint can declare, its weights'
/// checks, the fused operations), where a submitted policy runs and how it answers (`inference.rs`), the evaluator
/// and the pool it plays through, the held seeds' derivation, the simulator worker (its sessions, its Python
/// bridge, the simulator package it steps), the leaderboard's runner, and the arithmetic and the normalization
/// constants that turn returns into scores and ranks (with the bootstrap's random numbers).
pub const SCORING_PATH: [&str; 14] = [
    "policy/src",
    "evaluation/src",
    "sim/src",
    "sim/python/dsrl_sim",
    "leaderboard/src/runner.rs",
    "leaderboard/src/checkpoints.rs",
    "suite/src/score.rs",
    "scoring/src/leaderboard.rs",
    "scoring/src/protocol.rs",
    "pynumerics/src/pyrandom.rs",
    "suite/src/catalog.rs",
    "data/tasks.csv",
    "proto/dsrl/simulator/v1/simulator.proto",
    "simulators/src",
];

/// The locked dependencies whose versions the scoring path's results depend on: the tensor library and its matrix
/// kernels, the embedded Python.
pub const SCORING_DEPENDENCIES: [&str; 6] = ["candle-core", "gemm", "gemm-common", "gemm-f32", "half", "pyo3"];

/// The files of the scoring path under `root` (the workspace), sorted: folders expanded to their `.rs` and `.py`
/// files.
pub fn scoring_files(root: &std::path::Path) -> std::io::Result<Vec<String>> {
    fn walk(root: &std::path::Path, relative: &str, out: &mut Vec<String>) -> std::io::Result<()> {
        let path = root.join(relative);
        if path.is_dir() {
            for entry in std::fs::read_dir(&path)? {
                let name = entry?.file_name().to_string_lossy().into_owned();
                if name == "__pycache__" {
                    continue;
                }
                walk(root, &format!("{relative}/{name}"), out)?;
            }
        } else if relative.ends_with(".rs") || relative.ends_with(".py") || !relative.contains("/src") {
            out.push(relative.to_owned());
        }
        Ok(())
    }
    let mut files = Vec::new();
    for entry in SCORING_PATH {
        walk(root, entry, &mut files)?;
    }
    files.sort();
    files.dedup();
    Ok(files)
}

/// A file of the scoring path and a change to its bytes (the coverage test's one-byte edits).
pub type FileChange<'a> = (&'a str, &'a dyn Fn(&mut Vec<u8>));

/// The digest of the scoring path under `root`: each file's name, length and bytes (with `changed` applied to one
/// file's bytes, for the test that shows each file is covered), then `name version` of each scoring dependency as
/// `Cargo.lock` locks it.
pub fn scoring_digest(root: &std::path::Path, changed: Option<FileChange>) -> std::io::Result<String> {
    use sha2::Digest;
    let mut hasher = sha2::Sha256::new();
    for file in scoring_files(root)? {
        let mut bytes = std::fs::read(root.join(&file))?;
        if let Some((name, change)) = changed
            && name == file
        {
            change(&mut bytes);
        }
        hasher.update(file.as_bytes());
        hasher.update((bytes.len() as u64).to_le_bytes());
        hasher.update(&bytes);
    }
    let lock = std::fs::read_to_string(root.join("Cargo.lock"))?;
    let manifest = std::fs::read_to_string(root.join("Cargo.toml"))?;
    hasher.update(scoring_dependencies(&lock, &manifest).as_bytes());
    Ok(hex::encode(hasher.finalize()))
}

/// What the digest takes of the dependencies: per scoring dependency, the versions `Cargo.lock` locks and the line
/// that declares it in the workspace's `Cargo.toml` (its features: gemm's `x86-v4` would pick other kernels on an
/// AVX-512 machine, and so other episodes), or that none does.
pub fn scoring_dependencies(lock: &str, manifest: &str) -> String {
    let mut out = String::new();
    for dependency in SCORING_DEPENDENCIES {
        // `[[package]]` blocks: `name = "x"` followed by `version = "y"`.
        let mut versions: Vec<&str> = lock
            .split("[[package]]")
            .filter(|block| block.contains(&format!("name = \"{dependency}\"\n")))
            .filter_map(|block| block.lines().find_map(|l| l.strip_prefix("version = ")))
            .collect();
        versions.sort_unstable();
        let declared: Vec<&str> = manifest
            .lines()
            .filter(|l| {
                l.strip_prefix(dependency)
                    .is_some_and(|rest| rest.trim_start().starts_with('=') || rest.starts_with('.'))
            })
            .collect();
        out.push_str(&format!(
            "{dependency} {}\n{}\n",
            versions.join(","),
            if declared.is_empty() {
                "undeclared".to_owned()
            } else {
                declared.join("\n")
            }
        ));
    }
    out
}

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

    fn workspace() -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
    }

    /// The digest of the scoring path when `SCORER_REVISION` was last reviewed: kept in a file beside the crate, off
    /// the path it digests (this source file is on it).
    const REVIEWED_SCORING_PATH_SHA256: &str = include_str!("../scoring_path.sha256");

    /// A drift check like the generated gRPC code's: a change to the scoring path fails here until someone decides
    /// whether it changes what an episode scores (then `SCORER_REVISION` is bumped, which changes the protocol
    /// version) and records the new digest.
    #[test]
    fn the_scorer_revision_was_reviewed_against_the_scoring_path() {
        let digest = scoring_digest(&workspace(), None).unwrap();
        assert_eq!(
            digest.as_str(),
            REVIEWED_SCORING_PATH_SHA256.trim(),
            "the scoring path changed: if the change alters what any episode scores, bump SCORER_REVISION (the \
             protocol version changes, and results scored before stop ranking); either way record the new digest in \
             evaluation/scoring_path.sha256"
        );
    }

    /// Every file the scoring path names is in the digest: a one-byte change to any of them changes it, and the
    /// files an audit found outside the older list are on it.
    #[test]
    fn a_one_byte_change_to_any_file_on_the_scoring_path_changes_the_digest() {
        let root = workspace();
        let files = scoring_files(&root).unwrap();
        for expected in [
            "policy/src/fused.rs",
            "policy/src/acting.rs",
            "policy/src/checkpoint.rs",
            "evaluation/src/inference.rs",
            "evaluation/src/seeds.rs",
            "evaluation/src/evaluator.rs",
            "simulators/src/pool.rs",
            "simulators/src/session.rs",
            "sim/src/session.rs",
            "sim/src/python.rs",
            "sim/python/dsrl_sim/tasks.py",
            "leaderboard/src/runner.rs",
            "suite/src/score.rs",
            "data/tasks.csv",
        ] {
            assert!(
                files.iter().any(|f| f == expected),
                "{expected} is not on the scoring path"
            );
        }
        let base = scoring_digest(&root, None).unwrap();
        let flip = |bytes: &mut Vec<u8>| {
            let last = bytes.len() - 1;
            bytes[last] ^= 1;
        };
        for file in &files {
            let changed = scoring_digest(&root, Some((file.as_str(), &flip))).unwrap();
            assert_ne!(changed, base, "a change to {file} went unseen");
        }
        assert!(files.len() > 30, "{files:?}");
    }

    /// A dependency's features are in the digest: turning on gemm's AVX-512 kernels, or changing candle's
    /// declaration, changes what it takes of the dependencies.
    #[test]
    fn a_scoring_dependencys_declared_features_are_in_the_digest() {
        let root = workspace();
        let lock = std::fs::read_to_string(root.join("Cargo.lock")).unwrap();
        let manifest = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
        let base = scoring_dependencies(&lock, &manifest);
        assert!(base.contains("gemm \"0.19.0\"\nundeclared\n"), "{base}");
        assert!(
            base.contains("candle-core \"0.11.1\"\ncandle-core = \"0.11.1\"\n"),
            "{base}"
        );
        let with_avx512 = manifest.replace(
            "candle-core = \"0.11.1\"\n",
            "candle-core = \"0.11.1\"\ngemm = { version = \"0.19\", features = [\"x86-v4\"] }\n",
        );
        assert_ne!(scoring_dependencies(&lock, &with_avx512), base);
        let other_candle = manifest.replace(
            "candle-core = \"0.11.1\"",
            "candle-core = { version = \"0.11.1\", features = [\"mkl\"] }",
        );
        assert_ne!(scoring_dependencies(&lock, &other_candle), base);
        // A dependency whose name begins another's (candle-core-x) is not taken for it.
        let lookalike = format!("{manifest}\ncandle-core-extras = \"1\"\n");
        assert_eq!(scoring_dependencies(&lock, &lookalike), base);
    }
}
