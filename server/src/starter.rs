//! Starter datasets committed under `data/starter/<task>/`: ingested at start-up when missing, through the same
//! conversion and validation as uploads. A file `<name>.provenance.json` beside a dataset declares its recipe
//! provenance; without one the file itself is recorded as the source. `latest` is set only where a task has none,
//! so a restart never moves it back from a newer upload.

use std::path::{Path, PathBuf};

use dsrl_suite::{ObservationSpace, Provenance};

use crate::storage::datasets::{Datasets, IngestRequest, LatestPolicy};

/// Ingests every starter dataset under `dir`; returns how many new versions were created.
pub async fn load(datasets: &Datasets, dir: &Path) -> anyhow::Result<usize> {
    let mut created = 0;
    for (task, file) in starter_files(dir)? {
        let provenance_path = PathBuf::from(format!("{}.provenance.json", file.display()));
        let recipe = match std::fs::read(&provenance_path) {
            Ok(bytes) => Some(
                serde_json::from_slice::<Provenance>(&bytes)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", provenance_path.display()))?,
            ),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(e.into()),
        };
        // The upload path is a temporary copy: ingest consumes and deletes it.
        let upload = datasets.temp_file("starter");
        std::fs::copy(&file, upload.path())?;
        let (digest, _) = dsrl_suite::hashing::sha256_reader(std::fs::File::open(&file)?)?;
        let outcome = datasets
            .ingest(IngestRequest {
                task: task.clone(),
                upload,
                upload_sha256: hex::encode(digest),
                file_name: file
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                observation_space: ObservationSpace::Simulator,
                tags: vec![],
                license: None,
                recipe,
                latest: LatestPolicy::IfAbsent,
            })
            .await
            .map_err(|e| anyhow::anyhow!("starter dataset {}: {e}", file.display()))?;
        if outcome.created {
            created += 1;
            tracing::info!(%task, version = %outcome.version.version, file = %file.display(), "loaded starter dataset");
        }
    }
    Ok(created)
}

/// `(task, file)` for every `.parquet`/`.hdf5`/`.h5` file in `dir/<task>/`, sorted for a stable order.
fn starter_files(dir: &Path) -> std::io::Result<Vec<(String, PathBuf)>> {
    let mut files = Vec::new();
    for task_dir in std::fs::read_dir(dir)? {
        let task_dir = task_dir?;
        if !task_dir.file_type()?.is_dir() {
            continue;
        }
        let task = task_dir.file_name().to_string_lossy().into_owned();
        for entry in std::fs::read_dir(task_dir.path())? {
            let path = entry?.path();
            let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
            if matches!(ext, "parquet" | "hdf5" | "h5") {
                files.push((task.clone(), path));
            }
        }
    }
    files.sort();
    Ok(files)
}
