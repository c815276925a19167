use dsrl_server::datasets::converter::Converter;
use dsrl_server::datasets::service::{IngestRequest, LatestPolicy};
use dsrl_suite::ObservationSpace;

use crate::{config, dataset};

fn request(state: &dsrl_server::AppState, file: &std::path::Path) -> IngestRequest {
    let upload = state.datasets.temp_file("upload");
    std::fs::copy(file, upload.path()).unwrap();
    IngestRequest {
        task: "OfflineCarCircle-v0".into(),
        upload,
        upload_sha256: "test".into(),
        file_name: "car.parquet".into(),
        observation_space: ObservationSpace::Simulator,
        tags: vec![],
        license: None,
        recipe: None,
        latest: LatestPolicy::Move,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_identical_ingests_store_one_version() {
    let dir = tempfile::tempdir().unwrap();
    let state = dsrl_server::build_state(&config(&dir.path().join("server")), Converter::InProcess)
        .await
        .unwrap();
    let file = dataset(dir.path(), "OfflineCarCircle-v0", 20, 1);
    let ingests: Vec<_> = (0..4)
        .map(|_| {
            let state = state.clone();
            let req = request(&state, &file);
            tokio::spawn(async move { state.datasets.ingest(req).await.unwrap() })
        })
        .collect();
    let mut created = 0;
    let mut versions = std::collections::HashSet::new();
    for ingest in ingests {
        let outcome = ingest.await.unwrap();
        created += outcome.created as usize;
        versions.insert(outcome.version.version.clone());
    }
    assert_eq!(created, 1, "exactly one ingest creates the version");
    assert_eq!(versions.len(), 1);
    let (_, listed) = state.datasets.versions("OfflineCarCircle-v0").await.unwrap();
    assert_eq!(listed.len(), 1);
    assert_eq!(listed[0].tags, vec!["latest".to_owned()]);
}

#[tokio::test]
async fn an_orphaned_object_from_a_crash_does_not_block_a_later_ingest() {
    // A crash between storing the file and committing the row leaves an object no row names. It is invisible,
    // and the next ingest of the same data overwrites it and commits.
    let dir = tempfile::tempdir().unwrap();
    let server_dir = dir.path().join("server");
    let file = dataset(dir.path(), "OfflineCarCircle-v0", 3, 2);
    let (version, _) = dsrl_suite::hashing::file_version_id(&file).unwrap();
    let objects = server_dir.join("objects/datasets/OfflineCarCircle-v0");
    std::fs::create_dir_all(&objects).unwrap();
    std::fs::write(objects.join(format!("{version}.parquet")), b"half a file").unwrap();
    let state = dsrl_server::build_state(&config(&server_dir), Converter::InProcess)
        .await
        .unwrap();
    assert!(
        state
            .datasets
            .versions("OfflineCarCircle-v0")
            .await
            .unwrap()
            .1
            .is_empty()
    );
    let outcome = state.datasets.ingest(request(&state, &file)).await.unwrap();
    assert!(outcome.created);
    let stored = std::fs::read(objects.join(format!("{version}.parquet"))).unwrap();
    assert_eq!(stored, std::fs::read(&file).unwrap());
}
