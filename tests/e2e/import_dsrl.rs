//! `dsrl-admin import-dsrl`: DSRL-shaped files written by h5py under DSRL's names (stand-ins for the released files,
//! small) hosted in one step, each checked against the catalog before upload: a BallRun file is hosted and tagged
//! `dsrl-0.1.0` without moving `latest`, a MetaDrive file with the paper's 261 features as the paper's observation
//! space, a file whose trajectory count differs from its name and one with a wrong observation width are refused
//! with the reason; a second run finds the first's work done.

use dsrl_suite::Catalog;

use crate::{Env, get_json};

#[test]
fn dsrl_files_are_checked_hosted_tagged_and_a_second_run_resumes() {
    let env = Env::new();
    let dir = tempfile::tempdir().unwrap();
    let catalog = Catalog::embedded().unwrap();
    let name = |task: &str| {
        let t = catalog.get(task).unwrap();
        format!("{}.hdf5", t.dataset_file_stem(u64::from(t.paper_trajectories)))
    };
    let write = |file: &str, obs: u32, act: u32, episodes: u32| {
        let path = dir.path().join(file);
        dsrl_e2e::run_python(
            "make_dsrl_file.py",
            &[
                path.to_str().unwrap(),
                &obs.to_string(),
                &act.to_string(),
                &episodes.to_string(),
                "2",
            ],
        );
    };
    let task = |id: &str| catalog.get(id).unwrap();
    let ball = task("OfflineBallRun-v0");
    write(
        &name("OfflineBallRun-v0"),
        ball.obs_dim,
        ball.act_dim,
        ball.paper_trajectories,
    );
    let md = task("OfflineMetadrive-easysparse-v0");
    write(
        &name("OfflineMetadrive-easysparse-v0"),
        md.obs_dim_paper,
        md.act_dim,
        md.paper_trajectories,
    );
    let car = task("OfflineCarRun-v0");
    write(
        &name("OfflineCarRun-v0"),
        car.obs_dim,
        car.act_dim,
        car.paper_trajectories - 1,
    );
    let circle = task("OfflineBallCircle-v0");
    write(
        &name("OfflineBallCircle-v0"),
        circle.obs_dim + 1,
        circle.act_dim,
        circle.paper_trajectories,
    );

    let import = || {
        std::process::Command::new(dsrl_e2e::bin("dsrl-admin"))
            .args([
                "import-dsrl",
                dir.path().to_str().unwrap(),
                "--json",
                "--server",
                &env.server.url,
            ])
            .args(["--token", &env.server.token()])
            .output()
            .unwrap()
    };
    let out = import();
    assert!(!out.status.success(), "refusals make it exit 1");
    let report: serde_json::Value =
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    let of = |task: &str| {
        report
            .as_array()
            .unwrap()
            .iter()
            .find(|r| r["task"] == task)
            .unwrap_or_else(|| panic!("{task} not in {report}"))
            .clone()
    };
    let ballrun = of("OfflineBallRun-v0");
    assert_eq!(ballrun["outcome"], "imported", "{report}");
    assert_eq!(ballrun["observation_space"], "simulator");
    let metadrive = of("OfflineMetadrive-easysparse-v0");
    assert_eq!(metadrive["outcome"], "imported", "{report}");
    assert_eq!(metadrive["observation_space"], "paper");
    let carrun = of("OfflineCarRun-v0");
    assert_eq!(carrun["outcome"], "refused");
    assert!(carrun["reason"].as_str().unwrap().contains("trajectories"), "{carrun}");
    let ballcircle = of("OfflineBallCircle-v0");
    assert_eq!(ballcircle["outcome"], "refused");
    assert!(
        ballcircle["reason"].as_str().unwrap().contains("features"),
        "{ballcircle}"
    );

    // Tagged with the release's tag; latest not moved (none was set).
    let url = &env.server.url;
    let tagged = get_json(&format!("{url}/v1/datasets/OfflineBallRun-v0/versions/dsrl-0.1.0"));
    assert_eq!(tagged["version"], ballrun["version"], "{tagged}");
    assert_eq!(tagged["episodes"], ball.paper_trajectories);
    let latest = get_json(&format!("{url}/v1/datasets/OfflineBallRun-v0/versions/latest"));
    assert_eq!(latest["error"]["code"], "not_found", "{latest}");
    let paper = get_json(&format!(
        "{url}/v1/datasets/OfflineMetadrive-easysparse-v0/versions/dsrl-0.1.0"
    ));
    assert_eq!(paper["observation_space"]["kind"], "paper", "{paper}");
    for refused in ["OfflineCarRun-v0", "OfflineBallCircle-v0"] {
        let versions = get_json(&format!("{url}/v1/datasets/{refused}/versions"));
        assert!(
            versions["versions"].as_array().unwrap().is_empty(),
            "{refused} uploaded: {versions}"
        );
    }

    // A second run: the imported files are found done, the refused ones refused again.
    let again: serde_json::Value = serde_json::from_slice(&import().stdout).unwrap();
    let outcomes: Vec<(&str, &str)> = again
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["task"].as_str().unwrap(), r["outcome"].as_str().unwrap()))
        .collect();
    assert!(outcomes.contains(&("OfflineBallRun-v0", "present")), "{outcomes:?}");
    assert!(
        outcomes.contains(&("OfflineMetadrive-easysparse-v0", "present")),
        "{outcomes:?}"
    );
}
