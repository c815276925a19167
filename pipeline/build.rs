//! Records the git commit this crate is built from, for the provenance of every dataset it makes: a recipe and its
//! seed rebuild a dataset exactly only with the same expert code (BallRun rebuilt from its recipe after the expert
//! code had changed gave another build), so the provenance names the code as well as the recipe.

include!("../suite/build-support/commit.rs");
include!("../suite/build-support/python_digest.rs");

fn main() {
    // The simulator adapter the workers run and its pins, file by file: the folder itself also holds the
    // `__pycache__` that every run of the workers rewrites.
    let mut simulator: Vec<String> = ["requirements.txt", "constraints.txt", "apply_fixes.py"]
        .iter()
        .map(|f| format!("../sim/python/{f}"))
        .collect();
    if let Ok(entries) = std::fs::read_dir("../sim/python/dsrl_sim") {
        let mut modules: Vec<String> = entries
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|x| x == "py"))
            .map(|p| p.display().to_string())
            .collect();
        modules.sort();
        simulator.extend(modules);
    }
    // What shapes the data this crate makes: its source, the sources of the crates it builds on, the simulator
    // adapter and its pins, the locked dependencies.
    let mut sources: Vec<&str> = vec![
        "src",
        "../suite/src",
        "../pynumerics/src",
        "../policy/src",
        "../sim/src",
        "../evaluation/src",
        "../proto/src",
        "../simulators/src",
        "../Cargo.lock",
    ];
    sources.extend(simulator.iter().map(String::as_str));
    record_build_commit(&sources);
    // The workers import this package at run time; a build played on workers that report another one is not this
    // commit's (`Run::code_version`).
    let digest =
        python_package_digest(std::path::Path::new("../sim/python/dsrl_sim")).expect("read sim/python/dsrl_sim");
    println!("cargo:rustc-env=DSRL_SIM_PYTHON_DIGEST={digest}");
}
