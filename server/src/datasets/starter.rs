//! Starter datasets committed under `data/starter/<task>/`: ingested at start-up when missing, through the same
//! conversion and validation as uploads. A file `<name>.provenance.json` beside a dataset declares its recipe
//! provenance; without one the file itself is recorded as the source. A dataset larger than one committed file
//! may be is committed in parts, `<stem>.part-I-of-N.parquet` (see `dsrl_suite::convert::split_compact`), and
//! joined back here into one version; its provenance is `<stem>.parquet.provenance.json`. `latest` is set only
//! where a task has none, so a restart never moves it back from a newer upload (a full build, say); every starter
//! is tagged `starter`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use dsrl_suite::convert::{join_compact_parts, parse_part_file_name};
use dsrl_suite::{ObservationSpace, Provenance};

use crate::datasets::service::{Datasets, IngestRequest, LatestPolicy};

/// One starter dataset: its task, the name it is known by, and its file or its parts in order.
#[derive(Debug, PartialEq)]
struct StarterDataset {
    task: String,
    /// The file's name, or the name its parts share (`<stem>.parquet`).
    name: PathBuf,
    files: Vec<PathBuf>,
}

/// Ingests every starter dataset under `dir`; returns how many new versions were created.
pub async fn load(datasets: &Datasets, dir: &Path) -> anyhow::Result<usize> {
    let mut created = 0;
    for StarterDataset { task, name, files } in starter_datasets(dir)? {
        let provenance_path = PathBuf::from(format!("{}.provenance.json", name.display()));
        let recipe = match std::fs::read(&provenance_path) {
            Ok(bytes) => Some(
                serde_json::from_slice::<Provenance>(&bytes)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", provenance_path.display()))?,
            ),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(e.into()),
        };
        // The upload path is a temporary copy (parts: joined into one file): ingest consumes and deletes it.
        let upload = datasets.temp_file("starter");
        if let [file] = files.as_slice() {
            std::fs::copy(file, upload.path())?;
        } else {
            let (catalog_task, parts, target) =
                (datasets.task(&task)?.clone(), files.clone(), upload.path().to_owned());
            tokio::task::spawn_blocking(move || {
                join_compact_parts(&catalog_task, ObservationSpace::Simulator, &parts, &target)
            })
            .await?
            .map_err(|e| anyhow::anyhow!("starter dataset {}: joining its parts: {e}", name.display()))?;
        }
        let (digest, _) = dsrl_suite::hashing::sha256_reader(std::fs::File::open(upload.path())?)?;
        let outcome = datasets
            .ingest(IngestRequest {
                task: task.clone(),
                upload,
                upload_sha256: hex::encode(digest),
                file_name: name
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                observation_space: ObservationSpace::Simulator,
                // Every starter carries the tag, so it stays reachable (and is shown as a starter) once a full
                // build becomes `latest`.
                tags: vec![dsrl_suite::TagName::starter()],
                license: None,
                recipe,
                latest: LatestPolicy::IfAbsent,
            })
            .await
            .map_err(|e| anyhow::anyhow!("starter dataset {}: {e}", name.display()))?;
        if outcome.created {
            created += 1;
            tracing::info!(%task, version = %outcome.version.version, file = %name.display(), parts = files.len(), "loaded starter dataset");
        }
    }
    Ok(created)
}

/// A part of a starter dataset as found on disk: its index (from 1), the count it names, and its file.
type FoundPart = (usize, usize, PathBuf);

/// Every `.parquet`/`.hdf5`/`.h5` dataset in `dir/<task>/`, sorted for a stable order, with a dataset's parts
/// gathered in order. An incomplete set of parts is an error naming what is missing: joining fewer would host
/// another dataset under the name.
fn starter_datasets(dir: &Path) -> anyhow::Result<Vec<StarterDataset>> {
    // (task, name) → the parts found: (index, count, file).
    let mut found: BTreeMap<(String, PathBuf), Vec<FoundPart>> = BTreeMap::new();
    for task_dir in std::fs::read_dir(dir)? {
        let task_dir = task_dir?;
        // Followed through symbolic links (a starter folder linked in from elsewhere is a starter folder); a link
        // that leads nowhere is an error, not a task silently skipped.
        if task_dir.file_type()?.is_symlink() && std::fs::metadata(task_dir.path()).is_err() {
            anyhow::bail!(
                "starter folder {} is a symbolic link to nothing ({})",
                task_dir.path().display(),
                std::fs::read_link(task_dir.path())
                    .map(|t| t.display().to_string())
                    .unwrap_or_default()
            );
        }
        if !task_dir.path().is_dir() {
            continue;
        }
        let task = task_dir.file_name().to_string_lossy().into_owned();
        for entry in std::fs::read_dir(task_dir.path())? {
            let path = entry?.path();
            let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
            if !matches!(ext, "parquet" | "hdf5" | "h5") {
                continue;
            }
            let file_name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let (name, index, count) = match parse_part_file_name(&file_name) {
                Some((name, index, count)) => (task_dir.path().join(name), index, count),
                None => (path.clone(), 1, 1),
            };
            found
                .entry((task.clone(), name))
                .or_default()
                .push((index, count, path));
        }
    }
    let mut datasets = Vec::with_capacity(found.len());
    for ((task, name), mut parts) in found {
        parts.sort();
        let count = parts[0].1;
        let indices: Vec<usize> = parts.iter().map(|p| p.0).collect();
        anyhow::ensure!(
            parts.iter().all(|p| p.1 == count) && indices == (1..=count).collect::<Vec<_>>(),
            "starter dataset {}: parts {indices:?} of {count} found; a dataset in parts needs each of 1..={count} \
             exactly once, named <stem>.part-I-of-{count}.parquet",
            name.display()
        );
        datasets.push(StarterDataset {
            task,
            name,
            files: parts.into_iter().map(|p| p.2).collect(),
        });
    }
    Ok(datasets)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_are_gathered_in_order_and_an_incomplete_set_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let task = dir.path().join("OfflineCarButton1Gymnasium-v0");
        std::fs::create_dir_all(&task).unwrap();
        for name in [
            "B-250-60.part-2-of-2.parquet",
            "B-250-60.part-1-of-2.parquet",
            "A-250-9.parquet",
            "notes.txt",
        ] {
            std::fs::write(task.join(name), b"").unwrap();
        }
        let found = starter_datasets(dir.path()).unwrap();
        let names: Vec<(PathBuf, Vec<PathBuf>)> = found.into_iter().map(|d| (d.name, d.files)).collect();
        assert_eq!(
            names,
            vec![
                (task.join("A-250-9.parquet"), vec![task.join("A-250-9.parquet")]),
                (
                    task.join("B-250-60.parquet"),
                    vec![
                        task.join("B-250-60.part-1-of-2.parquet"),
                        task.join("B-250-60.part-2-of-2.parquet")
                    ]
                ),
            ]
        );

        std::fs::remove_file(task.join("B-250-60.part-1-of-2.parquet")).unwrap();
        let err = starter_datasets(dir.path()).unwrap_err().to_string();
        assert!(err.contains("B-250-60.parquet: parts [2] of 2 found"), "{err}");
    }

    #[test]
    fn a_task_folder_behind_a_symbolic_link_is_followed_and_a_dangling_one_refused() {
        let real = tempfile::tempdir().unwrap();
        let folder = real.path().join("OfflineBallRun-v0");
        std::fs::create_dir_all(&folder).unwrap();
        std::fs::write(folder.join("A-80-10.parquet"), b"").unwrap();
        let dir = tempfile::tempdir().unwrap();
        std::os::unix::fs::symlink(&folder, dir.path().join("OfflineBallRun-v0")).unwrap();
        let found = starter_datasets(dir.path()).unwrap();
        assert_eq!(found.len(), 1);
        assert_eq!(found[0].task, "OfflineBallRun-v0");
        std::os::unix::fs::symlink(real.path().join("gone"), dir.path().join("OfflineCarRun-v0")).unwrap();
        let err = starter_datasets(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("OfflineCarRun-v0") && err.contains("symbolic link to nothing"),
            "{err}"
        );
    }
}
