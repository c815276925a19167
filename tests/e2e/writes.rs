//! What an outside reliability probe found about writes, each held by a test on a real server: a database that
//! cannot be written for a moment (its SQLite files made immutable, `chattr +i`, which even root's writes obey)
//! answers errors and never a token for a user it did not keep, `/healthz` says the writes fail, and once the files
//! are writable again every write succeeds without a restart (no pooled connection is left inside a failed
//! transaction); a full disk (a small tmpfs) is 507 with `Retry-After` on uploads, filters and submissions; quotas
//! answer with `Retry-After`; the admin cancels any submission; `/v1/server` answers any token.

use std::path::Path;
use std::process::Command;

use crate::{Env, block_on, get_json, s};

/// `chattr` on the files of the server's SQLite database: the file and its WAL. (Not the shared-memory index: the
/// server maps it, and a write to a mapped page of an immutable file is a SIGBUS, which no full disk gives.)
fn chattr(data_dir: &Path, flag: &str) {
    for suffix in ["", "-wal"] {
        let file = data_dir.join(format!("dsrl.sqlite3{suffix}"));
        if !file.exists() {
            continue;
        }
        let status = Command::new("chattr").arg(flag).arg(&file).status().unwrap();
        assert!(
            status.success(),
            "chattr {flag} {}: this test needs root on a filesystem with the immutable flag (ext4, as CI's)",
            file.display()
        );
    }
}

/// POST /v1/users as the admin: the status and the body.
fn create_user(url: &str, admin: &str, name: &str) -> (u16, serde_json::Value) {
    let (url, admin, name) = (url.to_owned(), admin.to_owned(), name.to_owned());
    block_on(async move {
        let response = reqwest::Client::new()
            .post(format!("{url}/v1/users"))
            .bearer_auth(admin)
            .json(&serde_json::json!({ "name": name }))
            .send()
            .await
            .unwrap();
        let status = response.status().as_u16();
        (status, response.json().await.unwrap_or(serde_json::Value::Null))
    })
}

fn status_of(url: &str) -> u16 {
    let url = url.to_owned();
    block_on(async move { reqwest::get(url).await.unwrap().status().as_u16() })
}

#[test]
fn an_unwritable_database_loses_no_acknowledged_write_and_every_write_after_it_succeeds() {
    let env = Env::new();
    let (url, admin) = (env.server.url.clone(), env.server.token());
    assert_eq!(create_user(&url, &admin, "before").0, 201);
    let data_dir = env.server.data_dir.clone();

    chattr(&data_dir, "+i");
    let during: Vec<(u16, serde_json::Value)> = (0..6)
        .map(|i| create_user(&url, &admin, &format!("during{i}")))
        .collect();
    let health = status_of(&format!("{url}/healthz"));
    chattr(&data_dir, "-i");

    // No write that was not kept was acknowledged: no 2xx, no token.
    for (status, body) in &during {
        assert!(
            *status >= 500,
            "a write to an unwritable database answered {status}: {body}"
        );
        assert!(body["token"].is_null(), "a token for a user that was not kept: {body}");
    }
    assert_eq!(health, 503, "/healthz said the database was fine while writes failed");
    // Every write afterwards succeeds (a poisoned pooled connection failed about one in eight), and the users the
    // failed writes named do not exist.
    for i in 0..24 {
        let (status, body) = create_user(&url, &admin, &format!("after{i}"));
        assert_eq!(status, 201, "write {i} after recovery: {body}");
    }
    assert_eq!(status_of(&format!("{url}/healthz")), 200);
    for i in 0..6 {
        assert_eq!(status_of(&format!("{url}/v1/users/during{i}/submissions")), 404);
        assert_eq!(
            create_user(&url, &admin, &format!("during{i}")).0,
            201,
            "during{i} exists after all"
        );
    }
}

/// A data folder on a small tmpfs that a file then fills: every write path answers 507 with `Retry-After` and a
/// message that says the disk is full.
#[test]
fn a_full_disk_is_insufficient_storage_on_uploads_filters_and_submissions() {
    let dir = tempfile::tempdir().unwrap();
    let mount = dir.path().join("small");
    std::fs::create_dir_all(&mount).unwrap();
    let mounted = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=48m", "tmpfs"])
        .arg(&mount)
        .status()
        .unwrap();
    assert!(mounted.success(), "mounting a tmpfs needs root, as CI has");
    struct Unmount(std::path::PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = Command::new("umount").arg("-l").arg(&self.0).status();
        }
    }
    let _unmount = Unmount(mount.clone());
    let server = dsrl_e2e::Server::start(&mount.join("server"), &[], &[]);
    let cli = server.cli(&dir.path().join("cache"));
    let task = "OfflineCarRun-v0";
    // A dataset hosted before the disk fills, to filter afterwards.
    let small = dir.path().join("small.parquet");
    dsrl_e2e::make_dataset(task, 40, 1, &small);
    let version = cli
        .run(&["--json", "admin", "ingest", "--task", task, s(&small)])
        .ok()
        .json()["version"]["version"]
        .as_str()
        .unwrap()
        .to_owned();
    // A user and a checkpoint ready to submit once the disk is full.
    let (status, user) = create_user(&server.url, &server.token(), "alice");
    assert_eq!(status, 201, "{user}");
    let alice = user["token"].as_str().unwrap().to_owned();
    let policy = crate::make_policy(&dir.path().join("p"), crate::leaderboard::TASK, "target-cost-mlp", 5);
    // Fill the disk, leaving a few kilobytes.
    let filler = mount.join("filler");
    let _ = Command::new("dd")
        .args(["if=/dev/zero", "bs=1M", "count=64"])
        .arg(format!("of={}", filler.display()))
        .output();

    let expect_507 = |status: u16, headers: &reqwest::header::HeaderMap, body: &str, what: &str| {
        assert_eq!(status, 507, "{what}: {body}");
        assert!(headers.get("retry-after").is_some(), "{what}: no Retry-After");
        assert!(
            body.contains("insufficient_storage") && body.contains("disk is full"),
            "{what}: {body}"
        );
    };
    let upload = std::fs::read(&small).unwrap();
    let (url, token) = (server.url.clone(), server.token());
    let (status, headers, body) = block_on({
        let (url, token) = (url.clone(), token.clone());
        async move {
            let r = reqwest::Client::new()
                .post(format!("{url}/v1/datasets/OfflineBallRun-v0/versions"))
                .bearer_auth(token)
                .body(upload)
                .send()
                .await
                .unwrap();
            (r.status().as_u16(), r.headers().clone(), r.text().await.unwrap())
        }
    });
    expect_507(status, &headers, &body, "an upload");
    let (status, headers, body) = block_on({
        let url = format!("{url}/v1/datasets/{task}/versions/{version}?filter=noise%3D0.05");
        let token = token.clone();
        async move {
            let r = reqwest::Client::new().get(url).bearer_auth(token).send().await.unwrap();
            (r.status().as_u16(), r.headers().clone(), r.text().await.unwrap())
        }
    });
    expect_507(status, &headers, &body, "a filter");
    let out = cli
        .command(&[
            "--json",
            "submit",
            s(&policy),
            "--task",
            crate::leaderboard::TASK,
            "--name",
            "full-disk",
        ])
        .env("DSRL_TOKEN", &alice)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("insufficient_storage") && text.contains("disk is full"),
        "a submission: {text}"
    );
    drop(server);
}

#[test]
fn quotas_answer_retry_after_the_admin_cancels_any_submission_and_the_server_view_takes_any_token() {
    let env = Env::with(&[], &[("DSRL__LEADERBOARD__SUBMISSIONS_PER_DAY", "1")]);
    let alice = crate::leaderboard::create_user(&env, "alice");
    let policies = env.path("policies");
    let first = crate::make_policy(&policies.join("a"), crate::leaderboard::TASK, "target-cost-mlp", 1);
    let second = crate::make_policy(&policies.join("b"), crate::leaderboard::TASK, "target-cost-mlp", 2);
    let queued = crate::leaderboard::submit(&env, &alice, &first, "first").ok().json();
    // The day's quota: 429 with the seconds until the day's first submission leaves the window.
    let files = |dir: &Path| -> Vec<(String, Vec<u8>)> {
        ["policy.json", "policy.safetensors"]
            .iter()
            .map(|f| (f.to_string(), std::fs::read(dir.join(f)).unwrap()))
            .collect()
    };
    let (url, token, parts) = (env.server.url.clone(), alice.clone(), files(&second));
    let (status, retry_after) = block_on(async move {
        let mut form = reqwest::multipart::Form::new()
            .text("task", crate::leaderboard::TASK)
            .text("name", "second");
        for (name, bytes) in parts {
            form = form.part(name.clone(), reqwest::multipart::Part::bytes(bytes).file_name(name));
        }
        let r = reqwest::Client::new()
            .post(format!("{url}/v1/submissions"))
            .bearer_auth(token)
            .multipart(form)
            .send()
            .await
            .unwrap();
        let retry = r
            .headers()
            .get("retry-after")
            .map(|v| v.to_str().unwrap().parse::<u64>().unwrap());
        (r.status().as_u16(), retry)
    });
    assert_eq!(status, 429);
    let retry_after = retry_after.expect("a quota refusal without Retry-After");
    assert!((86_000..=86_400).contains(&retry_after), "{retry_after}");

    // The admin cancels a user's submission (the user's own token is not needed).
    let mut admin = env.cli.clone();
    admin.token = Some(env.server.token());
    let id = queued["id"].to_string();
    let (url, admin_token) = (env.server.url.clone(), env.server.token());
    let cancelled: serde_json::Value = block_on(async move {
        reqwest::Client::new()
            .post(format!("{url}/v1/submissions/{id}/cancel"))
            .bearer_auth(admin_token)
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap()
    });
    assert_eq!(cancelled["state"], "cancelled", "{cancelled}");
    assert_eq!(cancelled["reason"], "cancelled by the admin");
    // Its episodes.csv is the header alone.
    let csv = crate::leaderboard::reqwest_text(&format!(
        "{}/v1/submissions/{}/episodes.csv",
        env.server.url, queued["id"]
    ));
    assert_eq!(csv, "cost_threshold,episode,reward_return,cost_return,length\n");
    // Cancelled, it no longer counts toward the day: the second is accepted.
    let accepted = crate::leaderboard::submit(&env, &alice, &second, "second").ok().json();
    assert_eq!(accepted["state"], "queued");

    // /v1/server: the public view for a user's token (it answered 403), `admin` only for the admin's.
    let view = |token: &str| crate::get_json_with_token(&format!("{}/v1/server", env.server.url), token);
    assert_eq!(view(&alice)["admin"], false);
    assert_eq!(view("not-a-token")["admin"], false);
    assert_eq!(view(&env.server.token())["admin"], true);
    assert_eq!(get_json(&format!("{}/v1/server", env.server.url))["admin"], false);
}

/// Names a spreadsheet or a browser would misread, and a dataset version that is not a hosted version, are refused
/// before anything is stored.
#[test]
fn names_and_dataset_versions_that_would_reach_the_exports_unchecked_are_refused() {
    let env = Env::new();
    let admin = env.server.token();
    for name in ["..", ".", "-A1-B1", "Paper", "dsrl_reference"] {
        let (status, body) = create_user(&env.server.url, &admin, name);
        assert_eq!(status, 400, "user name {name:?}: {body}");
    }
    let alice = crate::leaderboard::create_user(&env, "alice");
    let policy = crate::make_policy(&env.path("p"), crate::leaderboard::TASK, "target-cost-mlp", 4);
    let run = crate::leaderboard::client(
        &env,
        &alice,
        &[
            "--json",
            "submit",
            s(&policy),
            "--task",
            crate::leaderboard::TASK,
            "--name=-A1-B1",
        ],
    );
    assert_eq!(run.code, 6, "{run:?}");
    for said in ["=HYPERLINK(\"http://evil.example/\")", &"a".repeat(64)] {
        let dir = env.path("with-version");
        crate::leaderboard::variant(&policy, &dir, |c| {
            c["training"] = serde_json::json!({ "dataset_version": said })
        });
        let run = crate::leaderboard::submit(&env, &alice, &dir, "claims-a-version");
        assert_eq!(run.code, 6, "{run:?}");
        assert!(
            run.stdout
                .contains("is not a version of OfflineBallRun-v0 on this server"),
            "{run:?}"
        );
    }
    // Nothing was queued.
    let listed = get_json(&format!("{}/v1/users/alice/submissions", env.server.url));
    assert_eq!(listed, serde_json::json!([]), "{listed}");
}

/// `dsrl-train --submit` checks the entry's name (the server's rule) before it trains: a name the server would
/// refuse fails at once, with nothing trained.
#[test]
fn dsrl_train_refuses_a_bad_entry_name_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let started = std::time::Instant::now();
    let run = Command::new(dsrl_e2e::bin("dsrl-train"))
        .args([
            "bc",
            "--mode",
            "all",
            "--task",
            crate::leaderboard::TASK,
            "--steps",
            "100000",
            "--submit",
            "my entry",
        ])
        .arg("--dataset")
        .arg(crate::leaderboard::starter())
        .arg("--out")
        .arg(&out)
        .args(["--server", "http://127.0.0.1:9"])
        .env("DSRL_TOKEN", "dsrl_unused")
        .output()
        .unwrap();
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains("\"my entry\": use 1 to 64 letters"), "{stderr}");
    assert!(
        started.elapsed() < std::time::Duration::from_secs(10),
        "it trained first"
    );
    assert!(!out.join("bc-all").exists(), "a model was written");
}
