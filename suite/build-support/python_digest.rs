// Shared by the scorer's and the data pipeline's build scripts and the simulator worker (`include!`d; see commit.rs
// for why a build script cannot call a workspace crate): the identity of the `dsrl_sim` Python package, which the
// workers import from a folder at run time rather than compiling in. The scorer and the pipeline bake the digest of
// the tree's package at build time, the worker reports the digest of the package it imported, and a result scored
// or data made on a worker whose package differs is labelled `-modified` (dsrl_simulators::label_with_workers_python).

/// sha256 (lower-case hex) over the package's Python files, `*.py` directly in `folder` in byte order of their
/// names: each file's name, a NUL byte, its length as 8 little-endian bytes, then its bytes.
fn python_package_digest(folder: &std::path::Path) -> std::io::Result<String> {
    use sha2::Digest as _;
    let mut names: Vec<String> = std::fs::read_dir(folder)?
        .map(|entry| entry.map(|e| e.file_name().to_string_lossy().into_owned()))
        .collect::<std::io::Result<_>>()?;
    names.retain(|name| name.ends_with(".py"));
    names.sort();
    let mut digest = sha2::Sha256::new();
    for name in names {
        let bytes = std::fs::read(folder.join(&name))?;
        digest.update(name.as_bytes());
        digest.update([0]);
        digest.update((bytes.len() as u64).to_le_bytes());
        digest.update(&bytes);
    }
    Ok(digest.finalize().iter().map(|b| format!("{b:02x}")).collect())
}
