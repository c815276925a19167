//! Records the git commit this crate is built from in every model's training record (`code_commit`): the same
//! dataset, budget and seed give the same weights only with the same learner code.

include!("../suite/build-support/commit.rs");

fn main() {
    // What shapes the weights: the learners, the networks and the data reader they build on, the locked
    // dependencies.
    record_build_commit(&[
        "src",
        "../policy/src",
        "../suite/src",
        "../filters/src",
        "../pynumerics/src",
        "../Cargo.lock",
    ]);
}
