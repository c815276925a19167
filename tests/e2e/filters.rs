//! Filters as a service: the paper's names, canonical forms, derived versions computed once and cached, errors,
//! plots, and the same over gRPC.

use std::io::Cursor;

use dsrl_filters::{apply, plan::plan, spec::FilterSpec};
use dsrl_proto::datasets::v1::dataset_service_client::DatasetServiceClient;
use dsrl_proto::datasets::v1::{GetManifestRequest, StreamTransitionsRequest};
use dsrl_suite::catalog::{Catalog, ObservationSpace};
use futures::StreamExt;

use crate::{Env, get_json, s, sha256_file};

/// `dsrl_filters_total{outcome=...}` from a server's /metrics.
pub(crate) async fn filter_count(server_url: &str, outcome: &str) -> u64 {
    let text = reqwest::get(format!("{server_url}/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let prefix = format!("dsrl_filters_total{{outcome=\"{outcome}\"}} ");
    text.lines()
        .find_map(|l| l.strip_prefix(&prefix))
        .map_or(0, |v| v.parse().unwrap())
}

/// The filtered version the library makes from the same file, for comparison with what the service serves.
fn expected_version(file: &std::path::Path, task_id: &str, filter: &str) -> String {
    let catalog = Catalog::embedded().unwrap();
    let task = catalog.get(task_id).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (_, parent) =
        dsrl_suite::convert::import_file(file, task, ObservationSpace::Simulator, &dir.path().join("p")).unwrap();
    let spec = FilterSpec::parse(filter, task).unwrap().unwrap();
    let planned = plan(&spec, task, &parent.episode_index).unwrap();
    let data = apply::gather(
        file,
        &parent.episode_index,
        &planned,
        task.obs_dim as usize,
        task.act_dim as usize,
    )
    .unwrap();
    let out = apply::write(task, ObservationSpace::Simulator, &data, &dir.path().join("out")).unwrap();
    out.version.to_string()
}

#[tokio::test]
async fn the_papers_noise_filter_is_a_derived_version_computed_once() {
    let env = Env::new();
    let task = "OfflineCarCircle-v0";
    let file = env.path("car.parquet");
    let parent = dsrl_e2e::make_dataset(task, 120, 60, &file).version.to_string();
    env.cli.run(&["admin", "ingest", "--task", task, s(&file)]).ok();

    let fetched = env
        .cli
        .run(&["--json", "fetch", task, "--filter", "noise=0.05"])
        .ok()
        .json();
    let version = fetched["version"].as_str().unwrap().to_owned();
    assert_ne!(version, parent);
    assert_eq!(
        version,
        expected_version(&file, task, "noise=0.05"),
        "the service serves the library's result"
    );
    assert_eq!(
        sha256_file(std::path::Path::new(fetched["path"].as_str().unwrap())),
        version
    );
    let manifest = env
        .cli
        .run(&["--json", "show", task, "--filter", "outliers_percent=0.05"])
        .ok()
        .json();
    assert_eq!(
        manifest["version"],
        version.as_str(),
        "DSRL's own name is the same filter"
    );
    let p = &manifest["provenance"];
    assert_eq!(p["kind"], "filter");
    assert_eq!(p["parent"], parent.as_str());
    assert_eq!(p["filter"], "outliers_percent=0.05,target_cost=10");
    assert_eq!(p["counts"]["relabelled_outliers"], 6); // int(120 * 0.05)
    assert_eq!(p["counts"]["output_episodes"], 120);
    assert!(p["reference"].as_str().unwrap().contains("pre_process_data"));
    assert_eq!(filter_count(&env.server.url, "computed").await, 1);
    assert_eq!(filter_count(&env.server.url, "cached").await, 1);

    // Fetching again from an empty cache downloads the stored result: no filter work.
    let mut other = env.cli.clone();
    other.cache = env.path("cache2");
    let again = other
        .run(&["--json", "fetch", task, "--filter", "noise=0.05"])
        .ok()
        .json();
    assert_eq!(again["version"], version.as_str());
    assert_eq!(filter_count(&env.server.url, "computed").await, 1);
    assert_eq!(filter_count(&env.server.url, "cached").await, 2);

    // Filtered versions are addressable by id but not listed among the task's versions.
    let listed = get_json(&format!("{}/v1/datasets/{task}/versions", env.server.url));
    assert_eq!(listed["versions"].as_array().unwrap().len(), 1);
    let by_id = env
        .cli
        .run(&["--json", "show", task, "--version", &version])
        .ok()
        .json();
    assert_eq!(by_id["provenance"]["kind"], "filter");
    // And a filter of a density preset downloads as DSRL HDF5 too.
    let h5 = env.cli.run(&[
        "--json",
        "fetch",
        task,
        "--filter",
        "density=0.5",
        "--filter",
        "seed=4",
        "--format",
        "hdf5",
    ]);
    assert!(h5.ok().json()["path"].as_str().unwrap().ends_with(".hdf5"));
}

#[tokio::test]
async fn concurrent_identical_filter_requests_compute_once() {
    let env = Env::new();
    let task = "OfflineAntRun-v0";
    env.ingest_synthetic(task, 80, 61);
    let url = format!(
        "{}/v1/datasets/{task}/versions/latest?filter=obs_noise%3D0.1",
        env.server.url
    );
    let requests = (0..6).map(|_| {
        let url = url.clone();
        tokio::spawn(async move {
            let response = reqwest::get(&url).await.unwrap();
            assert_eq!(response.status(), 200);
            response.json::<serde_json::Value>().await.unwrap()["version"]
                .as_str()
                .unwrap()
                .to_owned()
        })
    });
    let versions: Vec<String> = futures::future::join_all(requests)
        .await
        .into_iter()
        .map(|r| r.unwrap())
        .collect();
    assert!(versions.windows(2).all(|w| w[0] == w[1]), "{versions:?}");
    assert_eq!(
        filter_count(&env.server.url, "computed").await,
        1,
        "one computation for six identical requests"
    );
    assert_eq!(filter_count(&env.server.url, "cached").await, 5);
}

#[tokio::test]
async fn bad_filters_get_400_over_rest_cli_and_grpc() {
    let env = Env::new();
    let task = "OfflineBallRun-v0";
    env.ingest_synthetic(task, 40, 62);
    let base = format!("{}/v1/datasets/{task}/versions/latest", env.server.url);
    for (filter, expected) in [
        ("colour%3Dred", "unknown key"),
        ("epsilon%3D0", "epsilon=0"),
        ("inpaint%3D0:0.5:0:1;0.5:1:0:1", "several inpaint ranges"),
        ("noise%3D0.1,target_cost%3D0.5", "target_cost >= 1"),
        // An outside probe's unauthenticated panic: 1e19 saturated `target_cost as usize` (9.2e18 was a 400,
        // 9.3e18 and above a 500 from a panic in the NumPy generator emulation).
        ("noise%3D0.05,target_cost%3D1e19", "outside [0, 100000]"),
        ("noise%3D0.05,target_cost%3D9.3e18", "outside [0, 100000]"),
    ] {
        for suffix in ["", "/download", "/plot.svg"] {
            let response = reqwest::get(format!("{base}{suffix}?filter={filter}")).await.unwrap();
            assert_eq!(response.status(), 400, "{filter} {suffix}");
            let body: serde_json::Value = response.json().await.unwrap();
            let message = body["error"]["message"].as_str().unwrap();
            assert!(
                message.contains(expected) && message.contains("valid keys"),
                "{message}"
            );
        }
    }
    // Valid, but this dataset cannot satisfy it (too few high-cost, high-reward trajectories).
    let out = env.cli.run(&["--json", "fetch", task, "--filter", "noise=0.95"]);
    assert_eq!(out.code, 6, "{out:?}");
    assert!(
        out.json()["error"]["message"]
            .as_str()
            .unwrap()
            .contains("not applicable to this dataset")
    );
    let response = reqwest::get(format!("{base}?filters=noise%3D0.1")).await.unwrap();
    assert_eq!(response.status(), 400, "a misspelled query parameter is not ignored");
    let mut grpc = DatasetServiceClient::connect(env.server.url.clone()).await.unwrap();
    let status = grpc
        .get_manifest(GetManifestRequest {
            task: task.into(),
            version: String::new(),
            filter: "seed=x,density=0.5".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    // The probe's panic over gRPC answered UNKNOWN on both calls.
    let status = grpc
        .get_manifest(GetManifestRequest {
            task: task.into(),
            version: String::new(),
            filter: "noise=0.05,target_cost=1e19".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    let status = match grpc
        .stream_transitions(StreamTransitionsRequest {
            task: task.into(),
            version: String::new(),
            filter: "noise=0.05,target_cost=1e19".into(),
        })
        .await
    {
        Err(status) => status,
        Ok(stream) => stream.into_inner().next().await.unwrap().unwrap_err(),
    };
    assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    assert!(filter_count(&env.server.url, "rejected").await >= 20);
    assert_eq!(filter_count(&env.server.url, "computed").await, 0);
}

#[tokio::test]
async fn plots_show_the_scatter_and_what_a_filter_removes() {
    let env = Env::new();
    let task = "OfflineCarCircle-v0";
    env.ingest_synthetic(task, 100, 63);
    let base = format!("{}/v1/datasets/{task}/versions/latest/plot.svg", env.server.url);
    let response = reqwest::get(&base).await.unwrap();
    assert_eq!(response.headers()["content-type"], "image/svg+xml");
    let svg = response.text().await.unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("100 trajectories"));
    assert_eq!(
        svg.matches("<circle").count(),
        100 + 1,
        "one point per trajectory, one legend marker"
    );
    let filtered = reqwest::get(format!("{base}?filter=density%3D0.5,seed%3D1,noise%3D0.05"))
        .await
        .unwrap();
    let svg = filtered.text().await.unwrap();
    assert!(
        svg.contains("removed by density") && svg.contains("relabelled outliers"),
        "{}",
        &svg[..300]
    );
    assert!(svg.contains("filter: cbins=10,rbins=50,max_npb=5,min_npb=2,seed=1,outliers_percent=0.05"));
    // The plot needs no filtered data: nothing was computed.
    assert_eq!(filter_count(&env.server.url, "computed").await, 0);
    let file = env.path("plot.svg");
    env.cli
        .run(&["show", task, "--filter", "discard=tempting", "--plot", s(&file)])
        .ok();
    let saved = std::fs::read_to_string(&file).unwrap();
    assert!(saved.contains("removed by inpainting"));
}

#[tokio::test]
async fn grpc_streams_the_filtered_transitions() {
    let env = Env::new();
    let task = "OfflineDroneRun-v0";
    env.ingest_synthetic(task, 60, 64);
    let mut grpc = DatasetServiceClient::connect(env.server.url.clone()).await.unwrap();
    let filter = "discard=low-reward".to_owned();
    let manifest = grpc
        .get_manifest(GetManifestRequest {
            task: task.into(),
            version: "latest".into(),
            filter: filter.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    let json: serde_json::Value = serde_json::from_str(&manifest.manifest_json).unwrap();
    assert_eq!(json["provenance"]["filter"], "inpaint=0:0.5:0:0.5");
    let mut stream = grpc
        .stream_transitions(StreamTransitionsRequest {
            task: task.into(),
            version: "latest".into(),
            filter,
        })
        .await
        .unwrap()
        .into_inner();
    let mut ipc = Vec::new();
    while let Some(chunk) = stream.next().await {
        ipc.extend(chunk.unwrap().arrow_ipc);
    }
    let rows: usize = arrow_ipc::reader::StreamReader::try_new(Cursor::new(ipc), None)
        .unwrap()
        .map(|b| b.unwrap().num_rows())
        .sum();
    assert_eq!(rows as u64, json["transitions"].as_u64().unwrap());
    assert!(json["counts"].is_null() && json["provenance"]["counts"]["removed_by_inpaint"].as_u64().unwrap() > 0);
}
