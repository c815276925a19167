//! The committed generated code must equal what the `.proto` files generate today.

use std::path::{Path, PathBuf};

const PROTOS: &[&str] = &[
    "dsrl/datasets/v1/datasets.proto",
    "dsrl/leaderboard/v1/leaderboard.proto",
    "dsrl/simulator/v1/simulator.proto",
];

fn generate(out: &Path) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let protoc = protoc_bin_vendored::protoc_bin_path().expect("vendored protoc");
    let mut config = tonic_prost_build::Config::new();
    config.protoc_executable(protoc);
    let protos: Vec<PathBuf> = PROTOS.iter().map(|p| root.join(p)).collect();
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .emit_rerun_if_changed(false)
        .out_dir(out)
        .compile_with_config(config, &protos, &[root.to_path_buf()])
        .expect("protoc failed");
}

#[test]
fn generated_code_is_up_to_date() {
    let committed = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/gen");
    let fresh = tempfile::tempdir().unwrap();
    generate(fresh.path());
    let update = std::env::var_os("DSRL_UPDATE_CODEGEN").is_some();
    let mut stale = Vec::new();
    for entry in std::fs::read_dir(fresh.path()).unwrap() {
        let entry = entry.unwrap();
        let name = entry.file_name();
        let new = std::fs::read_to_string(entry.path()).unwrap();
        let old = std::fs::read_to_string(committed.join(&name)).unwrap_or_default();
        if new != old {
            if update {
                std::fs::write(committed.join(&name), new).unwrap();
            } else {
                stale.push(name.to_string_lossy().into_owned());
            }
        }
    }
    // A committed file that the protos no longer generate (a removed or renamed package) is stale too.
    let fresh_names: Vec<std::ffi::OsString> = std::fs::read_dir(fresh.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    for entry in std::fs::read_dir(&committed).unwrap() {
        let name = entry.unwrap().file_name();
        if !fresh_names.contains(&name) {
            if update {
                std::fs::remove_file(committed.join(&name)).unwrap();
            } else {
                stale.push(format!("{} (no proto generates it)", name.to_string_lossy()));
            }
        }
    }
    assert!(
        stale.is_empty(),
        "generated gRPC code is stale: {stale:?}; run `DSRL_UPDATE_CODEGEN=1 cargo test -p dsrl-proto --test codegen` and commit"
    );
}
