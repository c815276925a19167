//! The REST and gRPC surfaces as other tools see them: HTTP caching and range semantics, health, metrics,
//! OpenAPI, and the Arrow stream.

use std::io::Cursor;

use arrow_array::cast::AsArray;
use arrow_array::types::Float32Type;
use dsrl_proto::datasets::v1::StreamTransitionsRequest;
use dsrl_proto::datasets::v1::dataset_service_client::DatasetServiceClient;
use dsrl_suite::parquet_file::ParquetTransitions;
use futures::StreamExt;

use crate::Env;

#[tokio::test]
async fn downloads_follow_http_range_and_cache_semantics() {
    let env = Env::new();
    let task = "OfflineCarRun-v0";
    let file = env.path("car.parquet");
    let made = dsrl_e2e::make_dataset(task, 8, 30, &file);
    let bytes = std::fs::read(&file).unwrap();
    let size = bytes.len() as u64;
    env.cli.run(&["admin", "ingest", "--task", task, crate::s(&file)]).ok();
    let http = env.http();
    let by_tag = format!("{}/v1/datasets/{task}/versions/latest/download", env.server.url);
    let by_id = format!(
        "{}/v1/datasets/{task}/versions/{}/download",
        env.server.url, made.version
    );
    let etag = format!("\"{}\"", made.version);

    let full = http.get(&by_tag).send().await.unwrap();
    assert_eq!(full.status(), 200);
    assert_eq!(full.headers()["etag"], etag.as_str());
    assert_eq!(full.headers()["content-length"], size.to_string().as_str());
    assert_eq!(full.headers()["accept-ranges"], "bytes");
    assert_eq!(full.headers()["cache-control"], "no-cache", "a tag can move");
    assert_eq!(
        full.headers()["content-disposition"],
        "attachment; filename=\"SafetyCarRun-v0-40-8.parquet\""
    );
    assert_eq!(full.bytes().await.unwrap().as_ref(), &bytes[..]);
    let pinned = http.get(&by_id).send().await.unwrap();
    assert!(
        pinned.headers()["cache-control"]
            .to_str()
            .unwrap()
            .contains("immutable")
    );

    let part = http.get(&by_id).header("range", "bytes=100-199").send().await.unwrap();
    assert_eq!(part.status(), 206);
    assert_eq!(
        part.headers()["content-range"],
        format!("bytes 100-199/{size}").as_str()
    );
    assert_eq!(part.bytes().await.unwrap().as_ref(), &bytes[100..200]);
    let suffix = http.get(&by_id).header("range", "bytes=-16").send().await.unwrap();
    assert_eq!(suffix.status(), 206);
    assert_eq!(suffix.bytes().await.unwrap().as_ref(), &bytes[bytes.len() - 16..]);
    let resumed = http
        .get(&by_id)
        .header("range", "bytes=1000-")
        .header("if-range", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(resumed.status(), 206);
    assert_eq!(resumed.bytes().await.unwrap().as_ref(), &bytes[1000..]);
    // If-Range names other bytes: the whole file, not a range of the wrong one.
    let changed = http
        .get(&by_id)
        .header("range", "bytes=1000-")
        .header("if-range", "\"0000\"")
        .send()
        .await
        .unwrap();
    assert_eq!(changed.status(), 200);
    assert_eq!(changed.bytes().await.unwrap().len() as u64, size);
    let multi = http.get(&by_id).header("range", "bytes=0-1,5-6").send().await.unwrap();
    assert_eq!(multi.status(), 200);
    let bad = http
        .get(&by_id)
        .header("range", format!("bytes={size}-"))
        .send()
        .await
        .unwrap();
    assert_eq!(bad.status(), 416);
    assert_eq!(bad.headers()["content-range"], format!("bytes */{size}").as_str());
    let body: serde_json::Value = bad.json().await.unwrap();
    assert_eq!(body["error"]["code"], "range_not_satisfiable");
    let cached = http.get(&by_tag).header("if-none-match", &etag).send().await.unwrap();
    assert_eq!(cached.status(), 304);
    let head = http.head(&by_id).send().await.unwrap();
    assert_eq!(head.headers()["content-length"], size.to_string().as_str());
}

#[tokio::test]
async fn health_metrics_and_openapi() {
    let env = Env::new();
    env.ingest_synthetic("OfflineBallRun-v0", 2, 31);
    let http = env.http();
    let url = &env.server.url;
    let health: serde_json::Value = http
        .get(format!("{url}/healthz"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        (&health["status"], &health["database"]),
        (&"ok".into(), &"ok".into()),
        "{health}"
    );
    http.get(format!("{url}/v1/datasets/OfflineBallRun-v0/versions/latest/download"))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let metrics = http
        .get(format!("{url}/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(metrics.contains("dsrl_dataset_versions 1"), "{metrics}");
    assert!(
        metrics.contains(r#"dsrl_ingests_total{outcome="created"} 1"#),
        "{metrics}"
    );
    assert!(
        metrics.contains(r#"route="/v1/datasets/{task}/versions/{version}/download""#),
        "{metrics}"
    );
    let served = metrics
        .lines()
        .find(|l| l.starts_with("dsrl_download_bytes_total"))
        .unwrap();
    assert!(
        served.split(' ').nth(1).unwrap().parse::<u64>().unwrap() > 0,
        "{served}"
    );
    let doc: serde_json::Value = http
        .get(format!("{url}/openapi.json"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert!(doc["openapi"].as_str().unwrap().starts_with("3."));
    for path in [
        "/v1/server",
        "/v1/tasks",
        "/v1/tasks/{task}",
        "/v1/datasets/{task}/versions",
        "/v1/datasets/{task}/versions/{version}",
        "/v1/datasets/{task}/versions/{version}/download",
        "/v1/datasets/{task}/versions/{version}/plot.svg",
        "/v1/datasets/{task}/tags/{tag}",
    ] {
        assert!(doc["paths"][path].is_object(), "{path} missing from /openapi.json");
    }
    assert!(doc["components"]["schemas"]["Manifest"].is_object());
}

#[tokio::test]
async fn grpc_streams_the_same_transitions_as_arrow_ipc() {
    let env = Env::new();
    let task = "OfflineMetadrive-mediummean-v0";
    let file = env.path("md.parquet");
    let made = dsrl_e2e::make_dataset(task, 3, 32, &file);
    env.cli.run(&["admin", "ingest", "--task", task, crate::s(&file)]).ok();
    let mut grpc = DatasetServiceClient::connect(env.server.url.clone()).await.unwrap();
    let mut stream = grpc
        .stream_transitions(StreamTransitionsRequest {
            task: task.into(),
            version: made.version.to_string(),
            filter: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    let mut ipc = Vec::new();
    let mut messages = 0;
    while let Some(chunk) = stream.next().await {
        ipc.extend(chunk.unwrap().arrow_ipc);
        messages += 1;
    }
    assert!(messages > 3, "batches stream as separate messages ({messages})");
    let reader = arrow_ipc::reader::StreamReader::try_new(Cursor::new(ipc), None).unwrap();
    let mut rewards = Vec::new();
    let mut observations = Vec::new();
    for batch in reader {
        let batch = batch.unwrap();
        rewards.extend(
            batch
                .column_by_name("rewards")
                .unwrap()
                .as_primitive::<Float32Type>()
                .values()
                .iter()
                .copied(),
        );
        let obs = batch.column_by_name("observations").unwrap().as_fixed_size_list();
        observations.extend(obs.values().as_primitive::<Float32Type>().values().iter().copied());
    }
    let mut expected_rewards = Vec::new();
    let mut expected_obs = Vec::new();
    for chunk in ParquetTransitions::open(std::fs::File::open(&file).unwrap()).unwrap() {
        let chunk = chunk.unwrap();
        expected_rewards.extend(chunk.rewards);
        expected_obs.extend(chunk.observations);
    }
    assert_eq!(rewards, expected_rewards);
    assert_eq!(observations, expected_obs);
    assert_eq!(
        rewards.len() as u64,
        made.episode_index.iter().map(|e| e.length as u64).sum::<u64>()
    );
}

/// Each hosted version is described in Croissant: MLCommons' `mlcroissant` finds no error in the document and reads
/// its records from the Parquet file it names (over HTTP, checking the sha256), equal to the version's rows.
#[test]
fn a_version_is_described_in_croissant_that_mlcroissant_validates_and_reads() {
    let env = Env::new();
    let task = "OfflineCarRun-v0";
    let version = env.ingest_synthetic(task, 3, 5);
    let url = format!(
        "{}/v1/datasets/{task}/versions/{version}/croissant.json",
        env.server.url
    );
    let document = crate::get_json(&url);
    assert_eq!(document["@type"], "sc:Dataset");
    assert_eq!(document["distribution"][0]["sha256"], version.as_str());
    let path = env.path("croissant.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&document).unwrap()).unwrap();
    let out = dsrl_e2e::run_python("croissant_check.py", &[crate::s(&path), "3"]);
    let report: serde_json::Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
    assert_eq!(report["errors"], serde_json::json!([]), "{report:#}");
    let records = report["records"].as_array().unwrap();
    assert_eq!(records.len(), 3, "{report:#}");
    // The first rows of the file, as pyarrow reads them: mlcroissant's records are the same.
    let rows = dsrl_e2e::run_python(
        "parquet_rows.py",
        &[
            crate::s(
                &env.server
                    .data_dir
                    .join("objects/datasets")
                    .join(task)
                    .join(format!("{version}.parquet")),
            ),
            "3",
        ],
    );
    let rows: serde_json::Value = serde_json::from_str(rows.lines().last().unwrap()).unwrap();
    for (record, row) in records.iter().zip(rows.as_array().unwrap()) {
        for key in [
            "episode",
            "step",
            "rewards",
            "costs",
            "terminals",
            "timeouts",
            "actions",
        ] {
            assert_eq!(record[key], row[key], "{key}: {record} vs {row}");
        }
    }
}
