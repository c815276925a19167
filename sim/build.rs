// The worker embeds CPython through libpython3.x.so. pyo3 links against it; the rpath set here lets the binary
// find it at run time without LD_LIBRARY_PATH (pyenv and other non-system Pythons keep it outside the loader path).
fn main() {
    let config = pyo3_build_config::get();
    if let Some(dir) = &config.lib_dir {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
    println!("cargo:rerun-if-env-changed=PYO3_PYTHON");
}
