//! The workspace's build as a whole: a dev-dependency must not change the features of a crate the binaries use.
//!
//! Why it matters: the end-to-end tests run `cargo build --workspace --bins` after `cargo test --workspace` built
//! everything. Cargo resolves features per build, and a dev-dependency is part of the test build only; if it turns
//! on a feature of a normal dependency (candle-nn asking for candle-core's default features, png for flate2's), that
//! dependency and every crate above it — the whole workspace — compile a second time for the binaries. A cold CI run
//! paid minutes for it. `cargo tree` shows both resolutions; this test compares them. The same holds for the Python
//! package's wheel, which maturin builds alone (client/python/Cargo.toml, "build sharing").

use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;

use dsrl_e2e::repo_root;

/// Every package of a dependency graph with the feature sets it is built with, as `cargo tree` resolves them for
/// the packages selected by `selection` and the given edge kinds (`normal,build`: a build of binaries or of the
/// wheel; `normal,build,dev`: the tests').
fn resolved_features(selection: &[&str], edges: &str) -> BTreeMap<String, BTreeSet<String>> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["tree", "--locked", "--offline", "--prefix", "none"])
        .args(selection)
        .args(["-e", edges, "-f", "{p}|{f}"])
        .current_dir(repo_root())
        .output()
        .expect("running cargo tree");
    assert!(
        out.status.success(),
        "cargo tree {selection:?} -e {edges}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut packages: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for line in String::from_utf8(out.stdout).unwrap().lines() {
        // "name vX.Y.Z (path)|feat,feat (*)": the package's name and version, then its features.
        let Some((package, features)) = line.split_once('|') else {
            continue;
        };
        let mut words = package.split_whitespace();
        let (Some(name), Some(version)) = (words.next(), words.next()) else {
            continue;
        };
        let features = features.split_whitespace().next().unwrap_or("");
        let features = if features.starts_with('(') { "" } else { features };
        packages
            .entry(format!("{name} {version}"))
            .or_default()
            .insert(features.to_owned());
    }
    packages
}

/// The packages of `build` whose features differ from every feature set the tests' build has for them.
fn differing(build: &BTreeMap<String, BTreeSet<String>>, tests: &BTreeMap<String, BTreeSet<String>>) -> Vec<String> {
    build
        .iter()
        .filter_map(|(package, features)| {
            let in_tests = tests.get(package)?;
            (!features.is_subset(in_tests)).then(|| format!("{package}: {features:?}, tests {in_tests:?}"))
        })
        .collect()
}

#[test]
fn dev_dependencies_change_no_feature_of_a_crate_the_binaries_build() {
    let binaries = resolved_features(&["--workspace"], "normal,build");
    let tests = resolved_features(&["--workspace"], "normal,build,dev");
    assert!(
        binaries.contains_key("dsrl-server v0.1.0") && binaries.len() > 100,
        "cargo tree listed the workspace: {} packages",
        binaries.len()
    );
    let differing = differing(&binaries, &tests);
    assert!(
        differing.is_empty(),
        "these crates are built with other features for the binaries than for the tests, so `cargo build \
         --workspace --bins` compiles them and the crates above them again; give the normal dependency the \
         features the dev-dependency asks for (see Cargo.toml's candle-core):\n{}",
        differing.join("\n")
    );
}

#[test]
fn the_wheel_builds_its_dependencies_as_the_tests_do() {
    let wheel = resolved_features(
        &["-p", "dsrl-python", "--features", "dsrl-python/extension-module"],
        "normal,build",
    );
    let tests = resolved_features(&["--workspace"], "normal,build,dev");
    assert!(wheel.contains_key("pyo3 v0.27.2"), "{:?}", wheel.keys());
    // What must differ: the crates built without HDF5 (and so without the server's OpenAPI schemas), and pyo3 as
    // an extension module for the stable ABI.
    let must_differ = ["dsrl-", "pyo3"];
    let differing: Vec<String> = differing(&wheel, &tests)
        .into_iter()
        .filter(|line| !must_differ.iter().any(|prefix| line.starts_with(prefix)))
        .collect();
    assert!(
        differing.is_empty(),
        "the wheel's build (maturin builds dsrl-python alone) resolves other features than the tests' build for \
         these crates, so it compiles them and the crates above them again; list them with the tests' features \
         under \"build sharing\" in client/python/Cargo.toml:\n{}",
        differing.join("\n")
    );
}
