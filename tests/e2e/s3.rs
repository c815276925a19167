//! The S3 backend against a real S3-protocol server (moto, from the pinned Python environment) on loopback.

use crate::services::Moto;
use crate::{Env, sha256_file};

#[tokio::test]
async fn datasets_live_in_s3_when_configured() {
    let moto = Moto::start("dsrl-datasets");
    let endpoint = moto.endpoint.clone();
    let http = reqwest::Client::new();

    let envs = [
        ("DSRL__STORAGE__BACKEND", "s3"),
        ("DSRL__STORAGE__S3__BUCKET", "dsrl-datasets"),
        ("DSRL__STORAGE__S3__PREFIX", "prod"),
        ("DSRL__STORAGE__S3__ENDPOINT", endpoint.as_str()),
        ("DSRL__STORAGE__S3__ALLOW_HTTP", "true"),
        ("DSRL__STORAGE__S3__REGION", "us-east-1"),
        ("AWS_ACCESS_KEY_ID", "test"),
        ("AWS_SECRET_ACCESS_KEY", "test"),
    ];
    let env = Env::with(&[], &envs);
    let version = env.ingest_synthetic("OfflineAntCircle-v0", 4, 40);
    let listing = http
        .get(format!("{endpoint}/dsrl-datasets?list-type=2"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(
        listing.contains(&format!("prod/datasets/OfflineAntCircle-v0/{version}.parquet")),
        "{listing}"
    );
    assert!(listing.contains(&format!("prod/datasets/OfflineAntCircle-v0/{version}.manifest.json")));
    assert!(
        !env.server.data_dir.join("objects").exists(),
        "nothing goes to the local object folder"
    );
    let out = env.cli.run(&["--json", "fetch", "OfflineAntCircle-v0"]).ok().json();
    assert_eq!(
        sha256_file(std::path::Path::new(out["path"].as_str().unwrap())),
        version
    );
    let part = reqwest::Client::new()
        .get(format!(
            "{}/v1/datasets/OfflineAntCircle-v0/versions/{version}/download",
            env.server.url
        ))
        .header("range", "bytes=4-9")
        .send()
        .await
        .unwrap();
    assert_eq!(part.status(), 206);
    assert_eq!(part.bytes().await.unwrap().len(), 6);
}
