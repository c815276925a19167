//! The catalog over REST, gRPC and the CLI, and unknown ids.

use dsrl_proto::datasets::v1::dataset_service_client::DatasetServiceClient;
use dsrl_proto::datasets::v1::{GetManifestRequest, ListTasksRequest};

use crate::Env;

#[test]
fn list_shows_all_38_tasks_with_constants_and_hosted_versions() {
    let env = Env::new();
    let tasks = env.cli.run(&["--json", "list"]).ok().json();
    let tasks = tasks.as_array().unwrap();
    assert_eq!(tasks.len(), 38);
    let ant = tasks.iter().find(|t| t["id"] == "OfflineAntRun-v0").unwrap();
    assert_eq!(ant["family"], "bullet");
    assert_eq!(ant["simulator_env_id"], "SafetyAntRun-v0");
    assert_eq!(ant["max_episode_steps"], 200);
    assert_eq!(ant["obs_dim"], 33);
    assert_eq!(ant["act_dim"], 8);
    assert_eq!(ant["max_episode_reward"], 955.4818725585938);
    assert_eq!(ant["cost_thresholds"], serde_json::json!([10.0, 20.0, 40.0]));
    assert_eq!(ant["paper_trajectories"], 1816);
    assert_eq!(ant["versions"], serde_json::json!([]));
    let md = tasks
        .iter()
        .find(|t| t["id"] == "OfflineMetadrive-hardsparse-v0")
        .unwrap();
    assert_eq!(
        (md["obs_dim"].as_u64(), md["obs_dim_paper"].as_u64()),
        (Some(259), Some(261))
    );

    let version = env.ingest_synthetic("OfflineCarCircle-v0", 4, 1);
    let tasks = env.cli.run(&["--json", "list"]).ok().json();
    let car = tasks
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["id"] == "OfflineCarCircle-v0")
        .unwrap()
        .clone();
    assert_eq!(car["versions"][0]["version"], version.as_str());
    assert_eq!(car["versions"][0]["tags"], serde_json::json!(["latest"]));
    let human = env.cli.run(&["list"]).ok();
    assert!(
        human.stdout.contains("38 tasks, 1 with hosted versions"),
        "{}",
        human.stdout
    );
    assert!(human.stdout.contains(&version[..12]));
}

#[tokio::test]
async fn unknown_ids_are_not_found_with_suggestions_over_cli_rest_and_grpc() {
    let env = Env::new();
    let out = env.cli.run(&["fetch", "AntRun"]);
    assert_eq!(out.code, 4, "{out:?}");
    assert!(out.stderr.contains("did you mean OfflineAntRun-v0"), "{}", out.stderr);
    let file = env.path("ant.parquet");
    dsrl_e2e::make_dataset("OfflineAntRun-v0", 1, 1, &file);
    let out = env
        .cli
        .run(&["admin", "ingest", "--task", "AntRun", file.to_str().unwrap()]);
    assert_eq!(out.code, 4, "{out:?}");
    assert!(out.stderr.contains("did you mean OfflineAntRun-v0"), "{}", out.stderr);
    let out = env.cli.run(&["--json", "show", "OfflineAntRun-v1"]);
    assert_eq!(out.code, 4);
    assert_eq!(out.json()["error"]["suggestions"][0], "OfflineAntRun-v0");

    let response = env
        .http()
        .get(format!("{}/v1/tasks/OfflineCarCirlce-v0", env.server.url))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 404);
    let body: serde_json::Value = response.json().await.unwrap();
    assert_eq!(body["error"]["code"], "not_found");
    assert_eq!(body["error"]["suggestions"][0], "OfflineCarCircle-v0");

    // A known task without that version or tag.
    let response = env
        .http()
        .get(format!(
            "{}/v1/datasets/OfflineCarCircle-v0/versions/latest/download",
            env.server.url
        ))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 404);
    let out = env.cli.run(&["fetch", "OfflineCarCircle-v0", "--version", "nightly"]);
    assert_eq!(out.code, 4, "{out:?}");
    let response = env
        .http()
        .get(format!("{}/v1/nothing-here", env.server.url))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 404);

    let mut grpc = DatasetServiceClient::connect(env.server.url.clone()).await.unwrap();
    let status = grpc
        .get_manifest(GetManifestRequest {
            task: "AntRun".into(),
            version: String::new(),
            filter: String::new(),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::NotFound);
    assert!(status.message().contains("did you mean OfflineAntRun-v0"), "{status:?}");
    assert_eq!(status.metadata().get("dsrl-error-code").unwrap(), "not_found");
    let status = grpc
        .get_manifest(GetManifestRequest {
            task: "OfflineAntRun-v0".into(),
            version: "Not A Tag".into(),
            filter: String::new(),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
}

#[tokio::test]
async fn grpc_lists_the_catalog_in_one_response() {
    let env = Env::new();
    let version = env.ingest_synthetic("OfflineBallRun-v0", 3, 2);
    let mut grpc = DatasetServiceClient::connect(env.server.url.clone()).await.unwrap();
    let tasks = grpc.list_tasks(ListTasksRequest {}).await.unwrap().into_inner().tasks;
    assert_eq!(tasks.len(), 38);
    let ball = tasks.iter().find(|t| t.id == "OfflineBallRun-v0").unwrap();
    assert_eq!((ball.obs_dim, ball.act_dim, ball.max_episode_steps), (7, 2, 100));
    assert_eq!(ball.versions.len(), 1);
    assert_eq!(ball.versions[0].version, version);
    assert_eq!(ball.versions[0].tags, vec!["latest".to_owned()]);
    let manifest = grpc
        .get_manifest(GetManifestRequest {
            task: "OfflineBallRun-v0".into(),
            version: String::new(),
            filter: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    let json: serde_json::Value = serde_json::from_str(&manifest.manifest_json).unwrap();
    assert_eq!(json["version"], version.as_str());
    assert_eq!(json["episode_index"].as_array().unwrap().len(), 3);
}
