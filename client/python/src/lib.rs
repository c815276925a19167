//! `dsrl_client._native`: the Rust half of the Python package. Fetching, verification, the cache and resume are
//! the client crate's own code (the same as `dsrl-client fetch`), so a dataset fetched by either is found by the
//! other. Arrays cross into Python as little-endian bytes that NumPy wraps without another copy (`np.frombuffer`
//! on a `bytearray`), which works the same under NumPy 1.x and 2.x. The gymnasium environments, the DSRL
//! compatibility layer and the PyTorch export are Python (`python/dsrl_client`).

use std::path::{Path, PathBuf};

use dsrl_client::api::{DEFAULT_SERVER, IngestOptions};
use dsrl_client::{Cache, Client, ClientError, FetchOptions};
use dsrl_suite::catalog::Catalog;
use dsrl_suite::parquet_file::ParquetTransitions;
use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::{PyByteArray, PyBytes, PyTuple};

create_exception!(
    _native,
    DsrlError,
    PyException,
    "An error of the dsrl service or client: `code` (the server's error code, e.g. `filter_not_applicable`, or the \
     client's: `unreachable`, `integrity`, `io`, ...), `status` (the HTTP status, or None), `message`, \
     `suggestions` and `exit_code` (what `dsrl-client` would exit with)."
);

/// Maps a client error once to the Python exception, keeping the server's code and message.
fn to_python(py: Python<'_>, error: ClientError) -> PyErr {
    let document = error.to_json();
    let detail = &document["error"];
    let status = match &error {
        ClientError::Server { status, .. } => Some(*status),
        _ => None,
    };
    let err = DsrlError::new_err(error.to_string());
    let value = err.value(py);
    let suggestions: Vec<String> = detail["suggestions"]
        .as_array()
        .map(|a| a.iter().filter_map(|s| s.as_str().map(str::to_owned)).collect())
        .unwrap_or_default();
    let set = || -> PyResult<()> {
        value.setattr("code", detail["code"].as_str().unwrap_or("error"))?;
        value.setattr("status", status)?;
        value.setattr("message", error.to_string())?;
        value.setattr("suggestions", suggestions)?;
        value.setattr("exit_code", error.exit_code())?;
        Ok(())
    };
    match set() {
        Ok(()) => err,
        Err(e) => e,
    }
}

/// Runs one client call on a private runtime with the GIL released (downloads take minutes; other Python
/// threads keep running).
fn block_on<T: Send>(
    py: Python<'_>,
    call: impl std::future::Future<Output = Result<T, ClientError>> + Send,
) -> PyResult<T> {
    let result = py.detach(|| {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(ClientError::io("starting the client's runtime"))?;
        runtime.block_on(call)
    });
    result.map_err(|e| to_python(py, e))
}

fn client(py: Python<'_>, server: Option<&str>, token: Option<String>) -> PyResult<Client> {
    let base = server
        .map(str::to_owned)
        .or_else(|| std::env::var("DSRL_SERVER").ok())
        .unwrap_or_else(|| DEFAULT_SERVER.to_owned());
    Client::new(&base)
        .map(|c| c.with_token(token))
        .map_err(|e| to_python(py, e))
}

fn cache(cache_dir: Option<PathBuf>) -> Cache {
    Cache::new(cache_dir.unwrap_or_else(Cache::default_root))
}

/// The server URL used when none is given: `$DSRL_SERVER`, else the CLI's default.
#[pyfunction]
fn default_server() -> String {
    std::env::var("DSRL_SERVER").unwrap_or_else(|_| DEFAULT_SERVER.to_owned())
}

/// The cache root used when none is given: `$DSRL_DATASET_DIR`, else `~/.dsrl/datasets` (the CLI's).
#[pyfunction]
fn default_cache_dir() -> PathBuf {
    Cache::default_root()
}

/// The 38 tasks of the embedded catalog (`data/tasks.csv`), as JSON.
#[pyfunction]
fn catalog_json() -> PyResult<String> {
    let catalog = Catalog::embedded().map_err(|e| PyException::new_err(e.to_string()))?;
    serde_json::to_string(catalog.tasks()).map_err(|e| PyException::new_err(e.to_string()))
}

/// One task of the embedded catalog, as JSON; an unknown id raises `KeyError` with the catalog's nearest ids.
#[pyfunction]
fn task_json(id: &str) -> PyResult<String> {
    let catalog = Catalog::embedded().map_err(|e| PyException::new_err(e.to_string()))?;
    let task = catalog
        .get(id)
        .map_err(|e| pyo3::exceptions::PyKeyError::new_err(e.to_string()))?;
    serde_json::to_string(task).map_err(|e| PyException::new_err(e.to_string()))
}

/// DSRL's density presets (`DENSITY_CFG`; `data/density_presets.csv`, compiled in) as JSON: one object per task
/// and density with `task`, `density` (as Python writes it), `cbins`, `rbins`, `max_npb` and `min_npb`.
#[pyfunction]
fn density_presets_json() -> PyResult<String> {
    let presets: Vec<serde_json::Value> = dsrl_filters::spec::density_presets()
        .into_iter()
        .map(|((task, density), grid)| {
            serde_json::json!({"task": task, "density": density, "cbins": grid.cbins, "rbins": grid.rbins,
                               "max_npb": grid.max_npb, "min_npb": grid.min_npb})
        })
        .collect();
    serde_json::to_string(&presets).map_err(|e| PyException::new_err(e.to_string()))
}

/// Makes `task`'s version (id or tag; with a DSRL filter, the filtered version the server derives) complete and
/// verified in the cache, downloading or resuming only what is missing. Returns the fetch outcome and the
/// version's manifest as JSON.
#[pyfunction]
#[pyo3(signature = (task, version = "latest", filter = None, server = None, cache_dir = None, progress = true))]
fn fetch(
    py: Python<'_>,
    task: &str,
    version: &str,
    filter: Option<String>,
    server: Option<&str>,
    cache_dir: Option<PathBuf>,
    progress: bool,
) -> PyResult<String> {
    let client = client(py, server, None)?;
    let cache = cache(cache_dir);
    let options = FetchOptions {
        filter,
        progress,
        ..FetchOptions::default()
    };
    let outcome = block_on(py, cache.fetch(&client, task, version, &options))?;
    let manifest = std::fs::read(outcome.path.with_file_name("manifest.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .unwrap_or(serde_json::Value::Null);
    let mut document = serde_json::to_value(&outcome).map_err(|e| PyException::new_err(e.to_string()))?;
    document["manifest"] = manifest;
    Ok(document.to_string())
}

/// Every column of a dataset file as `(key, bytes, shape, dtype)`: float32 matrices and vectors little-endian,
/// flags one byte each (NumPy `bool`). Any file the server would accept is read (canonical, compact, pandas).
#[pyfunction]
fn read_dataset<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Vec<Bound<'py, PyTuple>>> {
    let columns = py.detach(|| read_columns(&path)).map_err(|e| to_python(py, e))?;
    let mut out = Vec::new();
    let rows = columns.rewards.len();
    let floats = [
        ("observations", &columns.observations, Some(columns.obs_dim)),
        ("next_observations", &columns.next_observations, Some(columns.obs_dim)),
        ("actions", &columns.actions, Some(columns.act_dim)),
        ("rewards", &columns.rewards, None),
        ("costs", &columns.costs, None),
    ];
    for (key, values, width) in floats {
        let bytes = PyByteArray::new_with(py, values.len() * 4, |buffer| {
            for (out, v) in buffer.chunks_exact_mut(4).zip(values.iter()) {
                out.copy_from_slice(&v.to_le_bytes());
            }
            Ok(())
        })?;
        let shape: Vec<usize> = match width {
            Some(w) => vec![rows, w],
            None => vec![rows],
        };
        out.push((key, bytes, PyTuple::new(py, shape)?, "<f4").into_pyobject(py)?);
    }
    for (key, flags) in [("terminals", &columns.terminals), ("timeouts", &columns.timeouts)] {
        let bytes = PyByteArray::new_with(py, flags.len(), |buffer| {
            for (out, &f) in buffer.iter_mut().zip(flags.iter()) {
                *out = u8::from(f);
            }
            Ok(())
        })?;
        out.push((key, bytes, PyTuple::new(py, [rows])?, "|b1").into_pyobject(py)?);
    }
    Ok(out)
}

fn read_columns(path: &Path) -> Result<dsrl_suite::transitions::TransitionChunk, ClientError> {
    let file = std::fs::File::open(path).map_err(ClientError::io(format!("opening {}", path.display())))?;
    let invalid = |e: dsrl_suite::parquet_file::ReadError| ClientError::Protocol(format!("{}: {e}", path.display()));
    let mut reader = ParquetTransitions::open(file).map_err(invalid)?;
    let mut all: Option<dsrl_suite::transitions::TransitionChunk> = None;
    for chunk in reader.by_ref() {
        let chunk = chunk.map_err(invalid)?;
        match all.as_mut() {
            Some(all) => all.append(&chunk),
            None => all = Some(chunk),
        }
    }
    Ok(all.unwrap_or_default())
}

/// Uploads a checkpoint folder (one `policy.json` + `policy.safetensors`, or one per `threshold-K/`) as a
/// leaderboard submission with the user's token; returns the queued submission as JSON.
#[pyfunction]
#[pyo3(signature = (folder, task, name, token, server = None))]
fn submit(
    py: Python<'_>,
    folder: PathBuf,
    task: &str,
    name: &str,
    token: String,
    server: Option<&str>,
) -> PyResult<String> {
    let client = client(py, server, Some(token))?;
    block_on(py, async { client.submit(&folder, task, name).await }).map(|v| v.to_string())
}

/// Uploads a dataset file (Parquet, or DSRL's HDF5) for `task` with the admin token; returns the server's answer
/// as JSON (`created`, `version`, `moved_tags`, ...). Waits for as long as the server is converting (a paper-size
/// file takes minutes); an upload of bytes the server already converted, or is converting, is followed, not sent
/// again. `progress` draws the CLI's bar on stderr.
#[pyfunction]
#[pyo3(signature = (task, path, token, server = None, tags = Vec::new(), observation_space = None, license = None,
    keep_latest = false, progress = true))]
#[allow(clippy::too_many_arguments)]
fn ingest(
    py: Python<'_>,
    task: &str,
    path: PathBuf,
    token: String,
    server: Option<&str>,
    tags: Vec<String>,
    observation_space: Option<String>,
    license: Option<String>,
    keep_latest: bool,
    progress: bool,
) -> PyResult<String> {
    let client = client(py, server, Some(token))?;
    let options = IngestOptions {
        tags,
        observation_space,
        license,
        provenance_json: None,
        keep_latest,
    };
    let size = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let bar = Client::upload_bar(size, progress);
    let b = bar.clone();
    let result = block_on(py, async move {
        client.ingest(task, &path, &options, move |n| b.set_position(n)).await
    });
    bar.finish_and_clear();
    serde_json::to_string(&result?).map_err(|e| PyException::new_err(e.to_string()))
}

/// A submission's state and scores, as JSON; with `wait_seconds` (at most 60) the server answers once it has
/// ended or when that time has passed.
#[pyfunction]
#[pyo3(signature = (id, server = None, wait_seconds = 0))]
fn submission(py: Python<'_>, id: i64, server: Option<&str>, wait_seconds: u32) -> PyResult<String> {
    let client = client(py, server, None)?;
    block_on(py, async {
        if wait_seconds == 0 {
            client.submission(id).await
        } else {
            client.submission_when_ended(id, wait_seconds).await
        }
    })
    .map(|v| v.to_string())
}

/// A scored episode's replay as JSON (its seed, returns, length and every step's reward and cost), or `None` while
/// the server is still making it (the request queues it).
#[pyfunction]
#[pyo3(signature = (id, threshold, episode, server = None))]
fn episode_replay(
    py: Python<'_>,
    id: i64,
    threshold: f64,
    episode: u32,
    server: Option<&str>,
) -> PyResult<Option<String>> {
    let client = client(py, server, None)?;
    block_on(py, async { client.episode_replay(id, threshold, episode).await }).map(|r| r.map(|v| v.to_string()))
}

/// The replay's animated GIF (made first through `episode_replay`).
#[pyfunction]
#[pyo3(signature = (id, threshold, episode, server = None))]
fn episode_replay_gif<'py>(
    py: Python<'py>,
    id: i64,
    threshold: f64,
    episode: u32,
    server: Option<&str>,
) -> PyResult<Bound<'py, PyBytes>> {
    let client = client(py, server, None)?;
    let bytes = block_on(py, async { client.episode_replay_gif(id, threshold, episode).await })?;
    Ok(PyBytes::new(py, &bytes))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("DsrlError", m.py().get_type::<DsrlError>())?;
    m.add_function(wrap_pyfunction!(default_server, m)?)?;
    m.add_function(wrap_pyfunction!(default_cache_dir, m)?)?;
    m.add_function(wrap_pyfunction!(catalog_json, m)?)?;
    m.add_function(wrap_pyfunction!(task_json, m)?)?;
    m.add_function(wrap_pyfunction!(density_presets_json, m)?)?;
    m.add_function(wrap_pyfunction!(fetch, m)?)?;
    m.add_function(wrap_pyfunction!(read_dataset, m)?)?;
    m.add_function(wrap_pyfunction!(ingest, m)?)?;
    m.add_function(wrap_pyfunction!(submit, m)?)?;
    m.add_function(wrap_pyfunction!(submission, m)?)?;
    m.add_function(wrap_pyfunction!(episode_replay, m)?)?;
    m.add_function(wrap_pyfunction!(episode_replay_gif, m)?)?;
    Ok(())
}
