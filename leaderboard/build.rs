//! Records the git commit this crate (the scorer) is built from, so every result names the build that scored it
//! (`SCORER_BUILD`), with `-modified` where the scoring path's sources differ from that commit.

include!("../suite/build-support/commit.rs");

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
}
