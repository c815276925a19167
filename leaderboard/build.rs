//! Records the git commit this crate (the scorer) is built from, so every result names the build that scored it
//! (`SCORER_BUILD`), with `-modified` where the scoring path's sources differ from that commit, and the digest of the
//! simulator workers' Python package (`SIMULATOR_PYTHON`), which they load at run time.

include!("../suite/build-support/commit.rs");
include!("../suite/build-support/python_digest.rs");

/// `dsrl_evaluation::SCORING_PATH` and `SCORING_DEPENDENCIES` (their versions in Cargo.lock, their declarations in
/// the workspace's Cargo.toml), relative to this crate; the test `the_scorer_build_watches_the_scoring_path` holds
/// the two lists together.
const SCORING_SOURCES: [&str; 16] = [
    "src",
    "../policy/src",
    "../evaluation/src",
    "../sim/src",
    "../sim/python/dsrl_sim",
    "../suite/src/score.rs",
    "../scoring/src/leaderboard.rs",
    "../scoring/src/protocol.rs",
    "../pynumerics/src/pyrandom.rs",
    "../suite/src/catalog.rs",
    "../data/tasks.csv",
    "../proto/dsrl/simulator/v1/simulator.proto",
    "../simulators/src",
    "../sim/python/requirements.txt",
    "../Cargo.lock",
    "../Cargo.toml",
];

fn main() {
    record_build_commit(&SCORING_SOURCES);
    // The workers import this package at run time: its digest here is what a worker must report for a result to
    // carry this build's commit unmarked (`scorer_build`). The folder is watched above, so an edit re-runs this.
    let package = std::path::Path::new("../sim/python/dsrl_sim");
    let digest = python_package_digest(package).expect("read sim/python/dsrl_sim");
    println!("cargo:rustc-env=DSRL_SIM_PYTHON_DIGEST={digest}");
}
