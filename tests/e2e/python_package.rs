//! The Python package (`client/python`, maturin + pyo3) against a real server process: the wheel is built here
//! with maturin as `pip install ./client/python` builds it, installed into a scratch folder, and its pytest suite
//! (`client/python/tests`) runs under two interpreters of the repository:
//! - `.venv` (CPython 3.11, NumPy 1.24, gymnasium 0.29, DSRL's pins): the whole suite, including `pre_process_data`
//!   against DSRL's own golden outputs (`filters/tests/it/golden/filters.json`) on the same synthetic datasets;
//! - `.venv-numpy2` (NumPy 2.x, gymnasium 1.x): the loading, caching and error tests.
//!
//! The real simulator behind `gym.make` is checked in `.venv-sim` (the workers' simulators) against the workers'
//! adapter stepped directly. Only CPython 3.11 exists on this machine: the wheel targets the stable ABI from 3.9
//! (`abi3-py39`), but 3.9, 3.10 and 3.12 are not exercised here.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use crate::Env;

/// The golden datasets of the filter fixtures: (name, task, episodes, seed), as `tests/golden/make_golden.py`.
const GOLDEN_DATASETS: [(&str, &str, usize, u64); 5] = [
    ("ball", "OfflineBallRun-v0", 600, 11),
    ("car", "OfflineCarCircle-v0", 400, 12),
    ("ant", "OfflineAntRun-v0", 250, 13),
    ("goal", "OfflinePointGoal1Gymnasium-v0", 40, 14),
    ("drive", "OfflineMetadrive-easydense-v0", 20, 15),
];

/// The wheel, built once per test process and unpacked into a scratch `site` folder the tests put on PYTHONPATH.
pub(crate) fn installed_wheel() -> &'static Path {
    &built_wheel().1
}

/// Runs `script` in `.venv`'s Python with the installed wheel on its path; its standard output, once it has exited
/// successfully (otherwise the test fails showing both outputs).
pub(crate) fn run_script(script: &str) -> String {
    let out = Command::new(dsrl_e2e::python())
        .args(["-c", script])
        .env("PYTHONPATH", installed_wheel())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
    text
}

/// The wheel file and the `site` folder it was unpacked into, built once per test process.
fn built_wheel() -> &'static (PathBuf, PathBuf) {
    static WHEEL: OnceLock<(tempfile::TempDir, (PathBuf, PathBuf))> = OnceLock::new();
    let (_, built) = WHEEL.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let built = install_wheel(dir.path());
        (dir, built)
    });
    built
}

/// The libraries a manylinux wheel's extension may link (the policy's system libraries it needs).
const SYSTEM_LIBRARIES: [&str; 7] = [
    "linux-vdso.so.1",
    "libc.so.6",
    "libm.so.6",
    "libgcc_s.so.1",
    "libpthread.so.0",
    "libdl.so.2",
    "ld-linux-x86-64.so.2",
];

/// Builds the wheel in the test's own profile (sharing the workspace's target folder) and unpacks it into `site`;
/// returns the wheel file and `site`.
fn install_wheel(dir: &Path) -> (PathBuf, PathBuf) {
    let root = dsrl_e2e::repo_root();
    let maturin = root.join(".venv/bin/maturin");
    assert!(
        maturin.exists(),
        "{} missing: run scripts/setup-python.sh",
        maturin.display()
    );
    let wheels = dir.join("wheels");
    let release = std::env::current_exe()
        .unwrap()
        .ancestors()
        .any(|p| p.file_name().is_some_and(|n| n == "release"));
    let mut build = Command::new(&maturin);
    build
        .args(["build", "--quiet", "-m", "client/python/Cargo.toml", "-o"])
        .arg(&wheels)
        .arg("-i")
        .arg(dsrl_e2e::python())
        .current_dir(&root);
    if release {
        build.arg("--release");
    } else {
        build.args(["--profile", "dev"]);
    }
    run(&mut build, "maturin build");
    let wheel = std::fs::read_dir(&wheels)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "whl"))
        .expect("a wheel");
    let name = wheel.file_name().unwrap().to_str().unwrap().to_owned();
    assert!(name.contains("-abi3-"), "the wheel targets the stable ABI: {name}");
    assert!(
        name.contains("-manylinux_2_34_"),
        "maturin checked the symbol versions and tagged the wheel manylinux: {name}"
    );
    let site = dir.join("site");
    let mut install = Command::new(dsrl_e2e::python());
    install
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--no-deps",
            "--target",
        ])
        .arg(&site)
        .arg(&wheel);
    run(&mut install, "pip install");
    // No libhdf5, no libpython, nothing outside the manylinux policy's system libraries.
    let extension = std::fs::read_dir(site.join("dsrl_client"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.to_str().unwrap().ends_with(".abi3.so"))
        .expect("the extension module");
    let linked = run(Command::new("ldd").arg(&extension), "ldd");
    for line in linked.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let library = line.split_whitespace().next().unwrap();
        let library = library.rsplit('/').next().unwrap();
        assert!(
            SYSTEM_LIBRARIES.contains(&library),
            "the extension links {library}, outside the manylinux policy:\n{linked}"
        );
    }
    (wheel, site)
}

/// The `N passed` count of pytest's summary line.
fn passed(out: &str) -> usize {
    let words: Vec<&str> = out.split_whitespace().collect();
    words
        .windows(2)
        .rev()
        .find(|w| w[1].trim_end_matches(',') == "passed")
        .and_then(|w| w[0].parse().ok())
        .unwrap_or_else(|| panic!("no pytest summary in:\n{out}"))
}

fn run(command: &mut Command, what: &str) -> String {
    let out = command.output().unwrap_or_else(|e| panic!("{what}: {e}"));
    let text = format!(
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{what} failed:\n{text}");
    text
}

#[test]
fn the_python_package_loads_filters_and_caches_like_the_cli_and_dsrl() {
    let env = Env::new();
    let site = installed_wheel();
    let mut versions = serde_json::Map::new();
    for (name, task, episodes, seed) in GOLDEN_DATASETS {
        let version = env.ingest_synthetic(task, episodes, seed);
        versions.insert(name.into(), serde_json::json!({"task": task, "version": version}));
    }
    let versions = serde_json::Value::Object(versions).to_string();
    // A file for the upload test, not ingested here: 60 MetaDrive episodes take the server over a second to convert.
    let upload_task = "OfflineMetadrive-hardmean-v0";
    let upload_file = env.path("upload.parquet");
    let made = dsrl_e2e::make_dataset(upload_task, 60, 21, &upload_file);
    let upload =
        serde_json::json!({"task": upload_task, "path": upload_file, "version": made.version.as_str()}).to_string();
    let root = dsrl_e2e::repo_root();
    let golden = root.join("filters/tests/it/golden/filters.json");
    let pytest = |python: &Path, cache: &str, select: Option<&str>| {
        let mut command = Command::new(python);
        command
            .args([
                "-m",
                "pytest",
                "-q",
                "-p",
                "no:cacheprovider",
                "client/python/tests/test_package.py",
            ])
            .args(select.map(|s| vec!["-k", s]).unwrap_or_default())
            .env("PYTHONPATH", site)
            .env("DSRL_SERVER", &env.server.url)
            .env("DSRL_DATASET_DIR", env.path(cache))
            .env("DSRL_TEST_VERSIONS", &versions)
            .env("DSRL_GOLDEN", &golden)
            .env("DSRL_ADMIN_TOKEN", env.server.token())
            .env("DSRL_TEST_UPLOAD", &upload)
            .env("DSRL_TEST_EXPORT", env.path(&format!("export-{cache}")))
            .current_dir(&root);
        run(&mut command, &format!("pytest with {}", python.display()))
    };
    let out = pytest(&dsrl_e2e::python(), "cache-numpy1", None);
    // Every test ran, one per golden case among them: none skipped.
    let golden_cases = serde_json::from_slice::<serde_json::Value>(&std::fs::read(&golden).unwrap()).unwrap()["cases"]
        .as_array()
        .unwrap()
        .len();
    assert_eq!(passed(&out), 9 + golden_cases, "{out}");
    assert!(!out.contains("skipped"), "{out}");
    // The policy the package exported from arrays loads as the evaluator loads a submission, every name and shape
    // checked, and plays the same action for the same episode seed.
    let (config, tensors) = dsrl_policy::checkpoint::read(&env.path("export-cache-numpy1")).unwrap();
    config
        .architecture
        .check_step_cost(config.obs_dim, config.act_dim)
        .unwrap();
    let policy = dsrl_policy::Policy::load(&config, &tensors).unwrap();
    let play = |seed: u64| {
        let mut rollout = policy.rollout(20.0, 1).unwrap();
        rollout.start_episode(0, seed).unwrap();
        rollout.act(&[0], &vec![0.1; config.obs_dim]).unwrap()
    };
    assert_eq!(play(4), play(4));
    assert_ne!(play(4), play(5));

    let numpy2 = root.join(".venv-numpy2/bin/python");
    assert!(
        numpy2.exists(),
        "{} missing: run scripts/setup-python.sh",
        numpy2.display()
    );
    let out = pytest(
        &numpy2,
        "cache-numpy2",
        Some("load_dataset or cached or bad_filter or gym_make or refuses or simulator"),
    );
    assert_eq!(passed(&out), 6, "{out}");

    // The same cache serves the CLI: what Python fetched is a cache hit for `dsrl-client fetch`.
    let ball = serde_json::from_str::<serde_json::Value>(&versions).unwrap()["ball"]["version"]
        .as_str()
        .unwrap()
        .to_owned();
    let cli = env.server.cli(&env.path("cache-numpy1"));
    let fetched = cli
        .run(&["--json", "fetch", "OfflineBallRun-v0", "--version", &ball])
        .ok()
        .json();
    assert_eq!(fetched["cache_hit"], true, "{fetched}");
}

#[test]
fn gym_make_steps_the_same_simulator_the_workers_host() {
    let site = installed_wheel();
    let root = dsrl_e2e::repo_root();
    let python = root.join(".venv-sim/bin/python");
    assert!(python.exists(), "{} missing: run sim/setup.sh", python.display());
    let path = std::env::join_paths([site, &root.join("sim/python")]).unwrap();
    let mut command = Command::new(python);
    command
        .arg("client/python/tests/simulator_check.py")
        .env("PYTHONPATH", path)
        .env("PYTHONWARNINGS", "ignore")
        .current_dir(&root);
    let out = run(&mut command, "simulator_check.py");
    let report: serde_json::Value = serde_json::from_str(out.lines().find(|l| l.starts_with('{')).unwrap()).unwrap();
    assert_eq!(report["steps"], 25, "{report}");
    assert_eq!(report["same_as_worker_adapter"], true, "{report}");
    assert_eq!(report["truncated_at"], report["horizon"], "{report}");
}

/// The wheel installs into a fresh virtual environment where no Rust toolchain is on PATH (pip compiles nothing:
/// the wheel is the package), and the README's drop-in example runs there against a real server. The example's
/// dependencies (NumPy, gymnasium), which pip would fetch from PyPI, come from the repository's `.venv`.
#[test]
fn the_wheel_installs_without_rust_and_runs_the_drop_in_example() {
    let (wheel, _) = built_wheel();
    let env = Env::new();
    let task = "OfflineCarCircle-v0";
    let file = env.path("car.parquet");
    let made = dsrl_e2e::make_dataset(task, 30, 5, &file);
    let version = made.version.to_string();
    env.cli
        .run(&["admin", "ingest", "--task", task, file.to_str().unwrap()])
        .ok();
    let transitions: u64 = made.episode_index.iter().map(|e| u64::from(e.length)).sum();
    let fresh = env.path("fresh");
    run(
        Command::new(dsrl_e2e::python()).args(["-m", "venv"]).arg(&fresh),
        "python -m venv",
    );
    // Only the interpreter's and the system's folders: cargo and rustc live in ~/.cargo/bin.
    let path = format!("{}:/usr/bin:/bin", fresh.join("bin").display());
    let install = run(
        Command::new(fresh.join("bin/pip"))
            .args(["install", "--no-index", "--no-deps", "--disable-pip-version-check"])
            .arg(wheel)
            .env("PATH", &path),
        "pip install the wheel",
    );
    assert!(!install.contains("Building wheel"), "{install}");
    let deps = Command::new(dsrl_e2e::python())
        .args([
            "-c",
            "import numpy, os; print(os.path.dirname(os.path.dirname(numpy.__file__)))",
        ])
        .output()
        .unwrap();
    let deps = String::from_utf8(deps.stdout).unwrap().trim().to_owned();
    let example = format!(
        "import shutil, gymnasium as gym\n\
         assert shutil.which('cargo') is None and shutil.which('rustc') is None\n\
         import dsrl_client as dsrl\n\
         env = gym.make('{task}', version='{version}', progress=False)\n\
         data = env.get_dataset()\n\
         assert sorted(data) == sorted(['observations', 'next_observations', 'actions', 'rewards', 'costs', \
         'terminals', 'timeouts']), sorted(data)\n\
         print(len(data['rewards']))\n"
    );
    let out = run(
        Command::new(fresh.join("bin/python"))
            .args(["-c", &example])
            .env("PATH", &path)
            .env("PYTHONPATH", &deps)
            .env("DSRL_SERVER", &env.server.url)
            .env("DSRL_DATASET_DIR", env.path("cache")),
        "the drop-in example",
    );
    assert_eq!(out.trim().parse::<u64>().unwrap(), transitions, "{out}");
}
