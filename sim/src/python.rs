//! The embedded CPython: start-up (the simulator venv's site-packages and `sim/python` on `sys.path`), the one
//! thread that runs all Python, and the calls into `dsrl_sim.batch.Batch`, with raw little-endian bytes crossing
//! the boundary both ways.
//!
//! All Python runs on a single dedicated thread holding one thread state for the life of the worker. Python calls
//! are serialized by the GIL anyway, and this keeps the simulators' C extensions away from thread-state juggling:
//! with calls spread over a thread pool, MuJoCo's pybind11 layer once re-acquired the GIL through a stale thread
//! state of a reused pool thread and deadlocked the worker.

use std::path::{Path, PathBuf};

use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyTuple};

use crate::error::SimError;

/// Where the worker finds its Python code and packages.
#[derive(Debug, Clone)]
pub struct PythonPaths {
    /// The folder holding the `dsrl_sim` package (`sim/python` in the repository).
    pub source: PathBuf,
    /// The simulator virtual environment made by `sim/setup.sh` (`.venv-sim`).
    pub venv: PathBuf,
}

/// The shape of a task as the simulator reports it.
#[derive(Debug, Clone)]
pub struct BatchShape {
    pub obs_dim: u32,
    pub act_dim: u32,
    pub action_low: Vec<f64>,
    pub action_high: Vec<f64>,
    pub max_episode_steps: u32,
    pub family: String,
    pub simulator: String,
}

/// Raw outputs of one batched step; see `dsrl_sim/batch.py`.
pub struct StepBytes {
    pub observations: Vec<u8>,
    pub rewards: Vec<u8>,
    pub costs: Vec<u8>,
    pub terminated: Vec<u8>,
    pub truncated: Vec<u8>,
    pub final_observations: Vec<u8>,
    pub applied_actions: Vec<u8>,
}

/// The rest of one episode its controller drove; see `dsrl_sim/tasks.py` `drive`.
pub struct DrivenBytes {
    pub observations: Vec<u8>,
    pub applied_actions: Vec<u8>,
    pub rewards: Vec<u8>,
    pub costs: Vec<u8>,
    pub terminated: bool,
    pub truncated: bool,
}

/// A built-in driver instead of the client's actions (see `Controller` in the proto).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Controller {
    /// `maps`: how many of the task's maps, from its own on, the episodes are drawn from (at least 1).
    Idm {
        target_speed: f64,
        acc_factor: f64,
        maps: u32,
    },
}

type Job = Box<dyn FnOnce() + Send>;

/// The worker's Python thread: every Python call is a job run there, in order.
#[derive(Clone)]
pub struct PythonThread {
    jobs: std::sync::mpsc::Sender<Job>,
}

impl PythonThread {
    /// Starts the interpreter on a new thread and imports `dsrl_sim` there (blocks until it is ready).
    pub fn start(paths: &PythonPaths) -> Result<(PythonThread, PythonHost), SimError> {
        let (jobs, queue) = std::sync::mpsc::channel::<Job>();
        let (ready, started) = std::sync::mpsc::channel();
        let paths = paths.clone();
        std::thread::Builder::new()
            .name("python".into())
            .spawn(move || {
                let host = PythonHost::start(&paths);
                let failed = host.is_err();
                let _ = ready.send(host);
                if failed {
                    return;
                }
                Python::attach(|py| {
                    // Wait for work with the GIL released; run each job with it held.
                    let queue = std::sync::Mutex::new(queue);
                    while let Ok(job) = py.detach(|| queue.lock().expect("job queue").recv()) {
                        if std::panic::catch_unwind(std::panic::AssertUnwindSafe(job)).is_err() {
                            tracing::error!("a Python job panicked");
                        }
                    }
                });
            })
            .map_err(|e| SimError::Setup(format!("starting the Python thread: {e}")))?;
        let host = started
            .recv()
            .map_err(|_| SimError::Setup("the Python thread died while starting".into()))??;
        Ok((PythonThread { jobs }, host))
    }

    /// Runs `f` on the Python thread and waits for its result.
    pub async fn run<T: Send + 'static>(&self, f: impl FnOnce() -> T + Send + 'static) -> Result<T, SimError> {
        let (reply, answer) = tokio::sync::oneshot::channel();
        self.jobs
            .send(Box::new(move || {
                let _ = reply.send(f());
            }))
            .map_err(|_| SimError::Setup("the Python thread has stopped".into()))?;
        answer
            .await
            .map_err(|_| SimError::Simulator("a simulator call panicked".into()))
    }

    /// Queues `f` on the Python thread without waiting (closing batches).
    pub fn spawn(&self, f: impl FnOnce() + Send + 'static) {
        let _ = self.jobs.send(Box::new(f));
    }
}

pub struct PythonHost {
    batch_class: Py<PyAny>,
    tasks: Py<PyModule>,
    /// The digest of the `dsrl_sim` package imported (`python_package_digest`), reported by Health.
    package_digest: String,
}

include!("../../suite/build-support/python_digest.rs");

/// K environments of one task living in the embedded interpreter (or, for MetaDrive, in its child processes).
pub struct PyBatch {
    batch: Py<PyAny>,
}

fn simulator_error(py: Python<'_>, context: &str, err: PyErr) -> SimError {
    let traceback = err.traceback(py).and_then(|t| t.format().ok()).unwrap_or_default();
    tracing::warn!(%context, error = %err, %traceback, "simulator raised");
    SimError::Simulator(format!("{context}: {err}"))
}

impl PythonHost {
    /// Starts the interpreter and imports `dsrl_sim`. Fails with a message naming the missing piece (usually: run
    /// `sim/setup.sh`). Runs on the Python thread.
    fn start(paths: &PythonPaths) -> Result<PythonHost, SimError> {
        let python = paths.venv.join("bin").join("python");
        if !python.exists() {
            return Err(SimError::Setup(format!(
                "no simulator environment at {} (run sim/setup.sh)",
                paths.venv.display()
            )));
        }
        if !paths.source.join("dsrl_sim").is_dir() {
            return Err(SimError::Setup(format!(
                "no dsrl_sim package under {}",
                paths.source.display()
            )));
        }
        Python::initialize();
        Python::attach(|py| {
            Self::bootstrap(py, paths, &python).map_err(|err| {
                let message = err.to_string();
                SimError::Setup(format!("starting the embedded Python failed: {message}"))
            })
        })
    }

    fn bootstrap(py: Python<'_>, paths: &PythonPaths, python: &Path) -> PyResult<PythonHost> {
        let sys = py.import("sys")?;
        let version = sys.getattr("version_info")?;
        let (major, minor): (u32, u32) = (version.get_item(0)?.extract()?, version.get_item(1)?.extract()?);
        let site_packages = paths
            .venv
            .join("lib")
            .join(format!("python{major}.{minor}"))
            .join("site-packages");
        if !site_packages.is_dir() {
            return Err(pyo3::exceptions::PyRuntimeError::new_err(format!(
                "{} is missing: the simulator environment was made with another Python than {major}.{minor}",
                site_packages.display()
            )));
        }
        py.import("site")?
            .call_method1("addsitedir", (site_packages.to_string_lossy(),))?;
        sys.getattr("path")?
            .call_method1("insert", (0, paths.source.to_string_lossy()))?;
        // multiprocessing (MetaDrive's one-process-per-env) reads argv and must start children with a real Python.
        sys.setattr("argv", vec!["dsrl-sim-worker"])?;
        let environ = py.import("os")?.getattr("environ")?;
        environ.set_item("DSRL_SIM_PYTHON", python.to_string_lossy())?;
        environ.set_item("PYTHONWARNINGS", "ignore")?;
        let tasks = py.import("dsrl_sim.tasks")?;
        tasks.call_method0("quiet")?;
        let batch_class = py.import("dsrl_sim.batch")?.getattr("Batch")?.unbind();
        // The package as imported (the folder Python found it in), which is what plays every episode.
        let folder: String = py.import("dsrl_sim")?.getattr("__path__")?.get_item(0)?.extract()?;
        let package_digest = python_package_digest(Path::new(&folder)).map_err(|e| {
            pyo3::exceptions::PyRuntimeError::new_err(format!("reading the dsrl_sim package in {folder}: {e}"))
        })?;
        Ok(PythonHost {
            batch_class,
            tasks: tasks.unbind(),
            package_digest,
        })
    }

    /// The digest of the `dsrl_sim` package this worker imported.
    pub fn package_digest(&self) -> &str {
        &self.package_digest
    }

    /// Builds K environments of `sim_id` (a simulator id) without resetting them.
    pub fn open(
        &self,
        sim_id: &str,
        seeds: &[u64],
        auto_reset: bool,
        controller: Option<Controller>,
    ) -> Result<(PyBatch, BatchShape), SimError> {
        Python::attach(|py| {
            let controller = controller_dict(py, controller)?;
            let built = self
                .batch_class
                .bind(py)
                .call1((sim_id, seeds.to_vec(), auto_reset, controller));
            let batch = built.map_err(|e| simulator_error(py, &format!("building {sim_id}"), e))?;
            let shape = self
                .shape(py, sim_id, &batch)
                .map_err(|e| simulator_error(py, "reading the task's spaces", e))?;
            Ok((PyBatch { batch: batch.unbind() }, shape))
        })
    }

    fn shape(&self, py: Python<'_>, sim_id: &str, batch: &Bound<'_, PyAny>) -> PyResult<BatchShape> {
        let tasks = self.tasks.bind(py);
        let family: String = tasks.call_method1("family", (sim_id,))?.extract()?;
        let simulator: String = tasks.call_method1("simulator_version", (&family,))?.extract()?;
        let bounds = |name: &str| -> PyResult<Vec<f64>> { batch.getattr(name)?.call_method0("tolist")?.extract() };
        Ok(BatchShape {
            obs_dim: batch.getattr("obs_dim")?.extract()?,
            act_dim: batch.getattr("act_dim")?.extract()?,
            action_low: bounds("low")?,
            action_high: bounds("high")?,
            max_episode_steps: batch.getattr("max_episode_steps")?.extract()?,
            family,
            simulator,
        })
    }
}

fn bytes_of(item: Bound<'_, PyAny>) -> PyResult<Vec<u8>> {
    Ok(item.cast_into::<PyBytes>()?.as_bytes().to_vec())
}

/// The Python form of a controller (`{"idm": {"target_speed": v, "acc_factor": a, "maps": n}}`), or None.
fn controller_dict(py: Python<'_>, controller: Option<Controller>) -> Result<Bound<'_, PyAny>, SimError> {
    let Some(Controller::Idm {
        target_speed,
        acc_factor,
        maps,
    }) = controller
    else {
        return Ok(py.None().into_bound(py));
    };
    let idm = PyDict::new(py);
    let inner = PyDict::new(py);
    let set = inner
        .set_item("target_speed", target_speed)
        .and(inner.set_item("acc_factor", acc_factor))
        .and(inner.set_item("maps", maps));
    set.and(idm.set_item("idm", inner))
        .map_err(|e| simulator_error(py, "controller", e))?;
    Ok(idm.into_any())
}

impl PyBatch {
    /// CPU seconds the Python thread spent building the environments (`Batch.build_cpu_seconds`; a MetaDrive
    /// env's own process is not counted).
    pub fn build_cpu_seconds(&self) -> Result<f64, SimError> {
        Python::attach(|py| {
            let seconds = self
                .batch
                .bind(py)
                .getattr("build_cpu_seconds")
                .and_then(|s| s.extract());
            seconds.map_err(|e| simulator_error(py, "reading the build's CPU time", e))
        })
    }

    /// Resets `envs` with one seed each; `switch` changes their driver first (a controlled batch only).
    pub fn reset(&self, envs: &[u32], seeds: &[u64], switch: Option<Controller>) -> Result<Vec<u8>, SimError> {
        Python::attach(|py| {
            let switch = controller_dict(py, switch)?;
            let result = self
                .batch
                .bind(py)
                .call_method1("reset", (envs.to_vec(), seeds.to_vec(), switch));
            result.and_then(bytes_of).map_err(|e| simulator_error(py, "reset", e))
        })
    }

    pub fn step(&self, envs: &[u32], actions: &[u8]) -> Result<StepBytes, SimError> {
        Python::attach(|py| {
            let call = || -> PyResult<StepBytes> {
                let actions = PyBytes::new(py, actions);
                let result = self.batch.bind(py).call_method1("step", (envs.to_vec(), actions))?;
                let parts = result.cast_into::<PyTuple>()?;
                Ok(StepBytes {
                    observations: bytes_of(parts.get_item(0)?)?,
                    rewards: bytes_of(parts.get_item(1)?)?,
                    costs: bytes_of(parts.get_item(2)?)?,
                    terminated: bytes_of(parts.get_item(3)?)?,
                    truncated: bytes_of(parts.get_item(4)?)?,
                    final_observations: bytes_of(parts.get_item(5)?)?,
                    applied_actions: bytes_of(parts.get_item(6)?)?,
                })
            };
            call().map_err(|e| simulator_error(py, "step", e))
        })
    }

    /// Plays the rest of each named environment's episode, its controller driving (a controlled batch only).
    pub fn drive(&self, envs: &[u32]) -> Result<Vec<DrivenBytes>, SimError> {
        Python::attach(|py| {
            let call = || -> PyResult<Vec<DrivenBytes>> {
                let result = self.batch.bind(py).call_method1("drive", (envs.to_vec(),))?;
                let mut episodes = Vec::with_capacity(envs.len());
                for item in result.try_iter()? {
                    let parts = item?.cast_into::<PyTuple>()?;
                    episodes.push(DrivenBytes {
                        observations: bytes_of(parts.get_item(0)?)?,
                        applied_actions: bytes_of(parts.get_item(1)?)?,
                        rewards: bytes_of(parts.get_item(2)?)?,
                        costs: bytes_of(parts.get_item(3)?)?,
                        terminated: parts.get_item(4)?.extract()?,
                        truncated: parts.get_item(5)?.extract()?,
                    });
                }
                Ok(episodes)
            };
            call().map_err(|e| simulator_error(py, "drive", e))
        })
    }

    /// RGB images of `envs` as they are now: uint8 `[n, height, width, 3]` (see `tasks.Env.frame`).
    pub fn frames(&self, envs: &[u32], width: u32, height: u32) -> Result<Vec<u8>, SimError> {
        Python::attach(|py| {
            let result = self
                .batch
                .bind(py)
                .call_method1("frames", (envs.to_vec(), width, height));
            result.and_then(bytes_of).map_err(|e| simulator_error(py, "render", e))
        })
    }

    pub fn close(&self) {
        Python::attach(|py| {
            if let Err(err) = self.batch.bind(py).call_method0("close") {
                tracing::warn!(error = %err, "closing a batch failed");
            }
        })
    }
}
