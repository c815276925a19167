//! Records the git commit this crate is built from, for the provenance of every dataset it makes: a recipe and its
//! seed rebuild a dataset exactly only with the same expert code (BallRun rebuilt from its recipe after the expert
//! code had changed gave another build), so the provenance names the code as well as the recipe.

include!("../suite/build-support/commit.rs");

fn main() {
    // What shapes the data this crate makes: its source, the sources of the crates it builds on, the locked
    // dependencies.
    record_build_commit(&[
        "src",
        "../suite/src",
        "../policy/src",
        "../sim/src",
        "../evaluation/src",
        "../proto/src",
        "../Cargo.lock",
    ]);
}
