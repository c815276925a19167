//! DSRL's own download URLs: an unmodified `dsrl` 0.1.0 from PyPI (`tests/python/dsrl_download.py`) downloads and
//! loads datasets from `/download/{file}` with its own `get_dataset`, only the host of its URLs pointed at a real
//! server. Every name of DSRL's `DATASET_URLS` maps to its task: hosted ones answer, others 404 with the JSON error
//! (never an empty file, which DSRL would keep as the dataset); MetaDrive names answer only when the operator opts
//! in; the arrays DSRL loads equal the served version's Parquet; and a connection cut mid-file is shown for what DSRL
//! does with it.

use crate::{Env, block_on, s};

/// A starter folder holding only the named tasks' committed starters (the server ingests it at start).
pub(crate) fn starters(dir: &std::path::Path, tasks: &[&str]) -> std::path::PathBuf {
    let root = dir.join("starters");
    for task in tasks {
        let from = dsrl_e2e::repo_root().join("data/starter").join(task);
        std::fs::create_dir_all(root.join(task)).unwrap();
        for entry in std::fs::read_dir(&from).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), root.join(task).join(entry.file_name())).unwrap();
        }
    }
    root
}

/// DSRL's `DATASET_URLS` keys of the nine MetaDrive tasks.
const METADRIVE: [&str; 9] = [
    "easysparse",
    "easymean",
    "easydense",
    "mediumsparse",
    "mediummean",
    "mediumdense",
    "hardsparse",
    "hardmean",
    "harddense",
];

#[test]
fn dsrls_own_get_dataset_downloads_from_download_file_names() {
    let dir = tempfile::tempdir().unwrap();
    let root = starters(dir.path(), &["OfflineBallRun-v0", "OfflineMetadrive-easysparse-v0"]);
    let env = Env::with(&["--starter-datasets", s(&root)], &[]);
    let cache = dir.path().join("dsrl-cache");
    std::fs::create_dir_all(&cache).unwrap();
    let out = dsrl_e2e::run_python("dsrl_download.py", &[&env.server.url, s(&cache), "BallRun", "BallRun"]);
    let report: serde_json::Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
    let heads = report["heads"].as_object().unwrap();
    assert_eq!(heads.len(), 38, "{report}");
    for (name, head) in heads {
        match name.as_str() {
            "BallRun" => {
                assert_eq!(head["status"], 200, "{head}");
                assert_eq!(head["task"], "OfflineBallRun-v0");
            }
            // Every MetaDrive name, hosted or not, is refused before its version is looked up.
            n if METADRIVE.contains(&n) => {
                assert_eq!(head["status"], 404, "{head}");
                assert!(head["message"].as_str().unwrap().contains("261"), "{head}");
            }
            _ => {
                assert_eq!(head["status"], 404, "{name}: {head}");
                assert!(
                    head["message"].as_str().unwrap().contains("no version"),
                    "{name}: {head}"
                );
            }
        }
    }
    // DSRL's get_dataset loaded exactly the served version's transitions.
    let loaded = &report["loaded"];
    assert_eq!(loaded["task"], "OfflineBallRun-v0");
    assert!(loaded["rows"].as_u64().unwrap() > 0);
    for (key, equal) in loaded["equal"].as_object().unwrap() {
        assert_eq!(equal, true, "{key} differs: {loaded}");
    }
    assert_eq!(loaded["cached_bytes"], heads["BallRun"]["length"]);
    // A cut connection: urlretrieve raises, but keeps the partial file, and DSRL reuses any file it finds; its
    // loader then fails on it (h5py cannot open a truncated file), so it is never taken for a dataset. The user
    // must delete it (README: "DSRL's own download URLs").
    let truncated = &report["truncated"];
    assert_eq!(truncated["error"], "ContentTooShortError", "{truncated}");
    assert_eq!(truncated["file_left"], true, "{truncated}");
    let left = truncated["bytes_left"].as_u64().unwrap();
    assert!(left > 0 && left < 4096, "{truncated}");
    assert_ne!(truncated["load_after"], "loaded", "{truncated}");

    // The same server answers Range requests and conditional requests on the HDF5.
    let url = format!("{}/download/SafetyBallRun-v0-80-940.hdf5", env.server.url);
    let base = env.server.url.clone();
    block_on(async move {
        let http = reqwest::Client::new();
        let part = http.get(&url).header("Range", "bytes=0-7").send().await.unwrap();
        assert_eq!(part.status(), 206);
        let etag = part.headers()["etag"].to_str().unwrap().to_owned();
        assert_eq!(
            part.bytes().await.unwrap().as_ref(),
            b"\x89HDF\r\n\x1a\n",
            "the HDF5 signature"
        );
        let again = http.get(&url).header("If-None-Match", &etag).send().await.unwrap();
        assert_eq!(again.status(), 304);
        let unknown = http
            .get(format!("{base}/download/NotADsrlFile.hdf5"))
            .send()
            .await
            .unwrap();
        assert_eq!(unknown.status(), 404);
        assert!(unknown.text().await.unwrap().contains("DATASET_URLS"));
    });

    // With the operator's opt-in, the MetaDrive names serve the 259-feature data.
    let opted = Env::with(
        &["--starter-datasets", s(&root)],
        &[("DSRL__DATASETS__DSRL_DOWNLOAD_METADRIVE", "true")],
    );
    let url = format!("{}/download/SafeMetaDrive-easysparse-v0-85-1000.hdf5", opted.server.url);
    block_on(async move {
        let head = reqwest::Client::new().head(&url).send().await.unwrap();
        assert_eq!(head.status(), 200);
        assert_eq!(head.headers()["x-dsrl-task"], "OfflineMetadrive-easysparse-v0");
    });
}
