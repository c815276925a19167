//! Ingest: formats, idempotence, validation errors, limits, auth, observation spaces, tags, and crashes.

use std::time::Duration;

use dsrl_e2e::{run_python, wait_for};
use dsrl_suite::catalog::{Catalog, ObservationSpace};
use dsrl_suite::convert::write_canonical;
use dsrl_suite::synthetic::{SyntheticSpec, transitions};

use crate::{Env, get_json, s};

fn versions(env: &Env, task: &str) -> Vec<serde_json::Value> {
    let body = get_json(&format!("{}/v1/datasets/{task}/versions", env.server.url));
    body["versions"].as_array().unwrap().clone()
}

#[test]
fn parquet_and_dsrl_hdf5_of_the_same_data_are_one_version() {
    let env = Env::new();
    let task = "OfflineDroneCircle-v0";
    let parquet = env.path("drone.parquet");
    let made = dsrl_e2e::make_dataset(task, 6, 3, &parquet);
    let first = env
        .cli
        .run(&["--json", "admin", "ingest", "--task", task, s(&parquet)])
        .ok()
        .json();
    assert_eq!(first["created"], true);
    assert_eq!(first["version"]["version"], made.version.as_str());
    assert_eq!(first["moved_tags"], serde_json::json!(["latest"]));

    let again = env
        .cli
        .run(&["--json", "admin", "ingest", "--task", task, s(&parquet)])
        .ok()
        .json();
    assert_eq!(again["created"], false, "identical bytes are a no-op");

    // HDF5 written by h5py the way DSRL wrote its files, in three flag/shape conventions: all the same data.
    for extra in [
        &[][..],
        &["--flags", "int8", "--column-vectors"][..],
        &["--flags", "float64", "--extra-key", "crash_costs"][..],
    ] {
        let h5 = env.path("drone.hdf5");
        let mut args = vec![s(&parquet), s(&h5)];
        args.extend_from_slice(extra);
        run_python("make_dsrl_hdf5.py", &args);
        let out = env
            .cli
            .run(&["--json", "admin", "ingest", "--task", task, s(&h5)])
            .ok()
            .json();
        assert_eq!(
            out["version"]["version"],
            made.version.as_str(),
            "HDF5 {extra:?} converts to the same bytes"
        );
        assert_eq!(out["created"], false);
    }
    assert_eq!(versions(&env, task).len(), 1);
    let manifest = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(manifest["provenance"]["kind"], "import");
    assert_eq!(manifest["provenance"]["file_name"], "drone.parquet");
    assert_eq!(manifest["provenance"]["source_format"], "parquet");
    assert_eq!(manifest["provenance"]["sha256"], made.version.as_str());
    assert_eq!(manifest["episodes"], 6);
    assert_eq!(manifest["file_name"], "SafetyDroneCircle-v0-100-6.parquet");

    // An HDF5 upload of new data records the HDF5 file as its source.
    let other = env.path("other.parquet");
    dsrl_e2e::make_dataset(task, 2, 4, &other);
    let h5 = env.path("other.hdf5");
    run_python(
        "make_dsrl_hdf5.py",
        &[s(&other), s(&h5), "--extra-key", "proximity_costs"],
    );
    let out = env
        .cli
        .run(&["--json", "admin", "ingest", "--task", task, s(&h5)])
        .ok()
        .json();
    assert_eq!(out["created"], true);
    let manifest = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(manifest["provenance"]["source_format"], "hdf5");
    assert_eq!(
        manifest["provenance"]["dropped_columns"],
        serde_json::json!(["proximity_costs"])
    );
}

#[test]
fn bad_uploads_are_rejected_with_the_first_problem_named() {
    let env = Env::new();
    let task = "OfflineCarRun-v0";
    let good = env.path("car.parquet");
    dsrl_e2e::make_dataset(task, 3, 5, &good);
    let h5 = env.path("bad.hdf5");
    let reject = |file: &std::path::Path| {
        let out = env.cli.run(&["--json", "admin", "ingest", "--task", task, s(file)]);
        assert_eq!(out.code, 6, "{out:?}");
        assert_eq!(out.json()["error"]["code"], "invalid_argument");
        out.json()["error"]["message"].as_str().unwrap().to_owned()
    };
    let cases: &[(&[&str], &str)] = &[
        (
            &["--nan-at", "17"],
            "row 17, column observations[0]: value NaN is not finite",
        ),
        (&["--unclosed"], "are not closed by a terminal or timeout flag"),
        (&["--drop-key", "costs"], "missing key(s) costs"),
        (&["--short-key", "rewards"], "key rewards has"),
    ];
    for (variant, expected) in cases {
        let mut args = vec![s(&good), s(&h5)];
        args.extend_from_slice(variant);
        run_python("make_dsrl_hdf5.py", &args);
        let message = reject(&h5);
        assert!(message.contains(expected), "{variant:?}: {message}");
    }
    // Another task's shape.
    let ant = env.path("ant.parquet");
    dsrl_e2e::make_dataset("OfflineAntRun-v0", 1, 5, &ant);
    assert!(reject(&ant).contains("33 features per observation, but OfflineCarRun-v0 expects 7"));
    // Not a dataset at all, and a truncated Parquet file.
    let garbage = env.path("garbage.bin");
    std::fs::write(&garbage, b"GIF89a definitely not a dataset").unwrap();
    assert!(reject(&garbage).contains("unrecognized file format"));
    let truncated = env.path("truncated.parquet");
    let bytes = std::fs::read(&good).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    assert!(reject(&truncated).contains("not a usable Parquet dataset"));
    let empty = env.path("empty.parquet");
    std::fs::write(&empty, b"").unwrap();
    assert!(reject(&empty).contains("empty"));

    // Bad parameters.
    let out = env
        .cli
        .run(&["admin", "ingest", "--task", task, "--tag", "Not A Tag", s(&good)]);
    assert_eq!(out.code, 6, "{out:?}");
    assert!(out.stderr.contains("invalid tag"), "{}", out.stderr);
    let out = env.cli.run(&[
        "admin",
        "ingest",
        "--task",
        task,
        "--observation-space",
        "latent",
        s(&good),
    ]);
    assert_eq!(out.code, 6, "{out:?}");

    // Nothing of the above is visible, and nothing is left in the temporary folder.
    assert!(versions(&env, task).is_empty());
    assert!(versions(&env, "OfflineAntRun-v0").is_empty());
    let tmp = env.server.data_dir.join("tmp");
    assert_eq!(
        std::fs::read_dir(&tmp).unwrap().count(),
        0,
        "leftovers in {}",
        tmp.display()
    );
}

#[tokio::test]
async fn admin_operations_need_the_token() {
    let env = Env::new();
    let file = env.path("ball.parquet");
    dsrl_e2e::make_dataset("OfflineBallCircle-v0", 2, 6, &file);
    let url = format!("{}/v1/datasets/OfflineBallCircle-v0/versions", env.server.url);
    let body = std::fs::read(&file).unwrap();
    let response = env.http().post(&url).body(body.clone()).send().await.unwrap();
    assert_eq!(response.status(), 401);
    assert_eq!(response.headers()["www-authenticate"], "Bearer");
    let response = env
        .http()
        .post(&url)
        .bearer_auth("not-the-token")
        .body(body)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 403);
    let mut cli = env.cli.clone();
    cli.token = Some("wrong-token-0123456789".into());
    let out = cli.run(&["admin", "ingest", "--task", "OfflineBallCircle-v0", crate::s(&file)]);
    assert_eq!(out.code, 7, "{out:?}");
    cli.token = None;
    let out = cli.run(&["admin", "ingest", "--task", "OfflineBallCircle-v0", crate::s(&file)]);
    assert_eq!(out.code, 2, "no token at all is a usage error: {out:?}");
    assert!(out.stderr.contains("need a token"), "{}", out.stderr);
    let response = env
        .http()
        .put(format!("{}/v1/datasets/OfflineBallCircle-v0/tags/x", env.server.url))
        .json(&serde_json::json!({"version": "0".repeat(64)}))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 401);
}

#[tokio::test]
async fn oversized_uploads_get_413_whether_declared_or_streamed() {
    let env = Env::with(&[], &[("DSRL__DATASETS__MAX_UPLOAD_BYTES", "100000")]);
    let file = env.path("big.parquet");
    dsrl_e2e::make_dataset("OfflineAntCircle-v0", 3, 7, &file);
    let size = std::fs::metadata(&file).unwrap().len();
    assert!(size > 100_000);
    // The CLI asks for the limit first and sends nothing.
    let out = env
        .cli
        .run(&["--json", "admin", "ingest", "--task", "OfflineAntCircle-v0", s(&file)]);
    assert_eq!(out.code, 6, "{out:?}");
    assert_eq!(out.json()["error"]["code"], "payload_too_large");
    assert!(out.stderr.contains("upload limit of 100000 bytes"), "{}", out.stderr);

    // A declared Content-Length over the limit: refused without reading the body.
    let url = env.server.url.trim_start_matches("http://").to_owned();
    let request = format!(
        "POST /v1/datasets/OfflineAntCircle-v0/versions HTTP/1.1\r\nHost: {url}\r\n\
         Authorization: Bearer {}\r\nContent-Length: 1000000000000\r\n\r\nPAR1",
        env.server.token()
    );
    let mut conn = tokio::net::TcpStream::connect(&url).await.unwrap();
    tokio::io::AsyncWriteExt::write_all(&mut conn, request.as_bytes())
        .await
        .unwrap();
    let mut answer = String::new();
    tokio::io::AsyncReadExt::read_to_string(&mut conn, &mut answer)
        .await
        .unwrap();
    assert!(answer.starts_with("HTTP/1.1 413"), "{answer}");
    assert!(answer.contains("payload_too_large"), "{answer}");

    // Chunked, without Content-Length: cut off once the limit is passed, and the client still gets the answer
    // because the server reads out the rest (within bounds) before replying.
    let bytes = std::fs::read(&file).unwrap();
    let chunks: Vec<Result<Vec<u8>, std::io::Error>> = bytes.chunks(16 << 10).map(|c| Ok(c.to_vec())).collect();
    let response = env
        .http()
        .post(format!("{}/v1/datasets/OfflineAntCircle-v0/versions", env.server.url))
        .bearer_auth(env.server.token())
        .body(reqwest::Body::wrap_stream(futures::stream::iter(chunks)))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 413);
    assert!(
        get_json(&format!("{}/v1/tasks/OfflineAntCircle-v0", env.server.url))["versions"]
            .as_array()
            .unwrap()
            .is_empty()
    );
}

#[test]
fn paper_space_metadrive_data_is_labelled_never_silently_accepted() {
    let env = Env::new();
    let task_id = "OfflineMetadrive-easydense-v0";
    let catalog = Catalog::embedded().unwrap();
    let task = catalog.get(task_id).unwrap();
    let mut spec = SyntheticSpec::for_task(task, 2, 8);
    spec.obs_dim = 261;
    let file = env.path("paper.parquet");
    write_canonical(task, ObservationSpace::Paper, transitions(spec).map(Ok), vec![], &file).unwrap();
    let out = env.cli.run(&["admin", "ingest", "--task", task_id, s(&file)]);
    assert_eq!(out.code, 6, "{out:?}");
    assert!(
        out.stderr
            .contains("261 features per observation, but OfflineMetadrive-easydense-v0 expects 259")
    );
    assert!(out.stderr.contains("observation_space=paper"), "{}", out.stderr);
    let out = env
        .cli
        .run(&[
            "--json",
            "admin",
            "ingest",
            "--task",
            task_id,
            "--observation-space",
            "paper",
            "--tag",
            "paper-era",
            s(&file),
        ])
        .ok()
        .json();
    assert_eq!(out["created"], true);
    assert_eq!(out["version"]["observation_space"], "paper");
    assert_eq!(
        out["version"]["tags"],
        serde_json::json!(["paper-era"]),
        "paper data never becomes latest"
    );
    let version = out["version"]["version"].as_str().unwrap().to_owned();
    let out = env
        .cli
        .run(&["admin", "tag", "--task", task_id, "--version", &version, "latest"]);
    assert_eq!(out.code, 6, "{out:?}");
    let manifest = env
        .cli
        .run(&["--json", "show", task_id, "--version", "paper-era"])
        .ok()
        .json();
    assert_eq!(
        manifest["observation_space"],
        serde_json::json!({"kind": "paper", "dim": 261})
    );
    // `fetch` of latest finds nothing: the hosted simulator-space data does not exist yet.
    assert_eq!(env.cli.run(&["fetch", task_id]).code, 4);
}

#[test]
fn tags_move_and_latest_follows_new_versions() {
    let env = Env::new();
    let task = "OfflineCarCircle-v0";
    let v1_file = env.path("v1.parquet");
    let v1 = dsrl_e2e::make_dataset(task, 2, 10, &v1_file).version.to_string();
    env.cli
        .run(&["admin", "ingest", "--task", task, "--tag", "release-1", s(&v1_file)])
        .ok();
    let v2 = env.ingest_synthetic(task, 3, 11);
    let list = versions(&env, task);
    assert_eq!(list[0]["version"], v2.as_str(), "newest first");
    assert_eq!(list[0]["tags"], serde_json::json!(["latest"]));
    assert_eq!(list[1]["tags"], serde_json::json!(["release-1"]));
    env.cli
        .run(&["admin", "tag", "--task", task, "--version", &v1, "latest"])
        .ok();
    let shown = env.cli.run(&["--json", "show", task]).ok().json();
    assert_eq!(shown["version"], v1.as_str());
    let fetched = env
        .cli
        .run(&["--json", "fetch", task, "--version", "release-1"])
        .ok()
        .json();
    assert_eq!(fetched["version"], v1.as_str());
    let out = env
        .cli
        .run(&["admin", "tag", "--task", task, "--version", &"f".repeat(64), "latest"]);
    assert_eq!(out.code, 4, "tagging a version that does not exist: {out:?}");
}

/// Kills the server at two moments of an ingest (mid-upload, mid-conversion): after a restart no version is
/// visible, the temporary files are gone, and the same upload then succeeds.
#[test]
fn a_killed_ingest_leaves_no_visible_version() {
    let mut env = Env::new();
    let task = "OfflineMetadrive-hardmean-v0";
    let file = env.path("md.parquet");
    let made = dsrl_e2e::make_dataset(task, 12, 12, &file);
    let tmp = env.server.data_dir.join("tmp");
    for stage in ["upload-", "canonical-"] {
        let mut child = env
            .cli
            .command(&["admin", "ingest", "--task", task, s(&file)])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let reached = wait_for(Duration::from_secs(60), || {
            std::fs::read_dir(&tmp)
                .map(|d| {
                    d.flatten().any(|e| {
                        e.file_name().to_string_lossy().starts_with(stage)
                            && e.metadata().map(|m| m.len() > 0).unwrap_or(false)
                    })
                })
                .unwrap_or(false)
        });
        assert!(reached, "the ingest never reached the {stage} stage");
        env.restart();
        let _ = child.wait();
        assert!(
            versions(&env, task).is_empty(),
            "a version became visible after a kill at {stage}"
        );
        assert_eq!(std::fs::read_dir(&tmp).unwrap().count(), 0, "start-up clears leftovers");
    }
    let out = env
        .cli
        .run(&["--json", "admin", "ingest", "--task", task, s(&file)])
        .ok()
        .json();
    assert_eq!(out["version"]["version"], made.version.as_str());
    assert_eq!(versions(&env, task).len(), 1);
}

/// Uploads are parsed in a child process: when it dies (here SIGKILL, in real life a crash in libhdf5 or the
/// memory limit), that one request fails with a clear 400 and the server carries on.
#[test]
fn a_dying_converter_fails_only_its_own_request() {
    let env = Env::new();
    let task = "OfflineMetadrive-hardmean-v0";
    let file = env.path("md.parquet");
    dsrl_e2e::make_dataset(task, 12, 13, &file);
    let child = env
        .cli
        .command(&["admin", "ingest", "--task", task, s(&file)])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut pid = None;
    assert!(
        wait_for(Duration::from_secs(60), || {
            pid = crate::process_running("convert", &env.server.data_dir);
            pid.is_some()
        }),
        "no converter process appeared"
    );
    crate::kill_hard(pid.unwrap());
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(6), "{out:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("the converter process died"), "{stderr}");
    assert_eq!(
        get_json(&format!("{}/v1/tasks/{task}", env.server.url))["versions"],
        serde_json::json!([])
    );
    let tmp = env.server.data_dir.join("tmp");
    assert_eq!(std::fs::read_dir(&tmp).unwrap().count(), 0);
    env.cli.run(&["admin", "ingest", "--task", task, s(&file)]).ok();
}

/// A converter child dies with its parent. An outside probe killed the server with SIGKILL mid-ingest and its
/// `dsrl-server convert` child kept running, holding the deleted upload, even across a restart. Here the child
/// reads from a FIFO that nobody writes, so it blocks for ever on its own; closing its standard input (what the
/// kernel does when the server dies) must end it.
#[test]
fn a_converter_exits_when_its_parent_goes_away() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("upload.fifo");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status().unwrap();
    assert!(made.success());
    let mut child = std::process::Command::new(dsrl_e2e::bin("dsrl-server"))
        .args([
            "convert",
            "--task",
            "OfflineBallRun-v0",
            "--observation-space",
            "simulator",
        ])
        .args(["--memory-limit", "4000000000"])
        .arg(&fifo)
        .arg(dir.path().join("out.parquet"))
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    assert!(child.try_wait().unwrap().is_none(), "the converter blocks on the FIFO");
    drop(child.stdin.take());
    assert!(
        wait_for(Duration::from_secs(10), || child.try_wait().unwrap().is_some()),
        "the converter outlived its parent's end of the pipe"
    );

    // And the probe's scenario: the server is SIGKILLed while a converter works for it.
    let mut env = Env::new();
    let task = "OfflineMetadrive-hardmean-v0";
    let file = env.path("md.parquet");
    dsrl_e2e::make_dataset(task, 12, 14, &file);
    let mut ingest = env
        .cli
        .command(&["admin", "ingest", "--task", task, s(&file)])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut pid = None;
    assert!(
        wait_for(Duration::from_secs(60), || {
            pid = crate::process_running("convert", &env.server.data_dir);
            pid.is_some()
        }),
        "no converter process appeared"
    );
    env.server.kill();
    assert!(
        wait_for(Duration::from_secs(10), || !std::path::Path::new(&format!(
            "/proc/{}/cmdline",
            pid.unwrap()
        ))
        .exists()
            || crate::process_running("convert", &env.server.data_dir).is_none()),
        "the converter outlived the server"
    );
    let _ = ingest.wait();
    env.restart();
}

/// A file whose conversion outlasts the client's timeout: the server answers once the bytes are received and
/// converts in the background, the CLI follows the conversion and succeeds where a request waiting for the answer
/// times out; uploading the same file again follows the finished upload instead of converting it again.
#[test]
fn an_upload_whose_conversion_outlasts_the_client_timeout_finishes_and_a_retry_converts_nothing() {
    let env = Env::new();
    let task = "OfflineMetadrive-hardmean-v0";
    let file = env.path("big.parquet");
    // 150 MetaDrive episodes: their conversion takes a few seconds on any machine here; 60 had taken
    // just under the 1 s timeout on an idle AVX-512 machine, and the test below needs the timeout to pass first.
    let made = dsrl_e2e::make_dataset(task, 150, 21, &file);
    let bytes = std::fs::read(&file).unwrap();
    let token = env.server.token();
    // The same file sent by a request that waits for the answer, with a 1 s timeout: the conversion takes longer.
    let started = std::time::Instant::now();
    let (url, waited_token, body) = (env.server.url.clone(), token.clone(), bytes.clone());
    let waited = crate::block_on(async move {
        reqwest::Client::builder()
            .timeout(Duration::from_secs(1))
            .build()
            .unwrap()
            .post(format!("{url}/v1/datasets/{task}/versions?latest=false"))
            .bearer_auth(waited_token)
            .body(body)
            .send()
            .await
    });
    assert!(
        waited.as_ref().is_err_and(|e| e.is_timeout()),
        "the conversion answered within 1 s ({:?} after {:?}): the test needs a slower one",
        waited.map(|r| r.status()),
        started.elapsed()
    );
    let version = |v: &serde_json::Value| v["version"]["version"].as_str().unwrap_or_default().to_owned();
    let mut cli = env
        .cli
        .command(&["--json", "admin", "ingest", "--task", task, s(&file)]);
    cli.env("DSRL_CLIENT_TIMEOUT", "1");
    let out = cli.output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let done: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(version(&done), made.version.as_str());

    // The server's record of the upload (or uploads, the timed-out one's conversion having finished too): all
    // done, each once; a second ingest of the same file follows one of them and sends nothing.
    let sha = crate::sha256_file(&file);
    let list = || {
        crate::get_json_with_token(
            &format!("{}/v1/uploads?task={task}&sha256={sha}", env.server.url),
            &token,
        )["uploads"]
            .as_array()
            .unwrap()
            .clone()
    };
    let before = list();
    assert!(!before.is_empty() && before.len() <= 2, "{before:?}");
    let mut again = env
        .cli
        .command(&["--json", "admin", "ingest", "--task", task, s(&file)]);
    again.env("DSRL_CLIENT_TIMEOUT", "1");
    let out = again.output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(
        version(&serde_json::from_slice(&out.stdout).unwrap()),
        made.version.as_str()
    );
    assert_eq!(list().len(), before.len(), "the retry started another conversion");
    assert!(list().iter().all(|u| u["state"] == "done"), "{:?}", list());
}

/// A server that accepts the connection but never answers: the client says it timed out, not that it cannot
/// reach the server (exit code 5 either way).
#[test]
fn a_silent_server_is_a_timeout_not_unreachable() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let held = std::thread::spawn(move || {
        let (stream, _) = listener.accept().unwrap();
        std::thread::sleep(Duration::from_secs(5));
        drop(stream);
    });
    let out = std::process::Command::new(dsrl_e2e::bin("dsrl-client"))
        .args(["--server", &url, "list"])
        .env("DSRL_CLIENT_TIMEOUT", "1")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(5), "{out:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("did not answer within 1 s"), "{stderr}");
    assert!(!stderr.contains("cannot reach"), "{stderr}");
    held.join().unwrap();
}
