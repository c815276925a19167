//! What an outside reliability and security probe of the server found, each kept fixed by a test against a real
//! server process: hostile weights refused from their header without stalling other requests, runaway
//! architectures refused by their declared cost, evaluations bounded in time and memory (the policy acts in a
//! child process), authentication before anything else is read, one JSON error shape for every failure, and a
//! refused upload that tells the client its connection is closed. (The filter panic and its metrics are covered in
//! `filters.rs` and the server's own tests; the orphaned converter in `ingest.rs`; worker placement in
//! `simulators.rs`.)

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use crate::leaderboard::{TASK, client, create_user, submit, train_bc, variant};
use crate::{Env, block_on};

/// A safetensors file with the given JSON header and no data.
fn safetensors(header: &str) -> Vec<u8> {
    let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
    bytes.extend_from_slice(header.as_bytes());
    bytes
}

/// POSTs a multipart submission; returns the status and the JSON body.
async fn post_submission(url: &str, token: &str, parts: Vec<(String, Vec<u8>)>) -> (u16, serde_json::Value) {
    let mut form = reqwest::multipart::Form::new()
        .percent_encode_noop()
        .text("task", TASK)
        .text("name", "hostile");
    for (name, bytes) in parts {
        form = form.part(name.clone(), reqwest::multipart::Part::bytes(bytes).file_name(name));
    }
    let response = reqwest::Client::new()
        .post(format!("{url}/v1/submissions"))
        .bearer_auth(token)
        .multipart(form)
        .send()
        .await
        .unwrap();
    let status = response.status().as_u16();
    (status, response.json().await.unwrap_or_default())
}

/// The probe's stall: a 53 MB `policy.safetensors` of 900,000 zero-size tensors took ~4.8 s to refuse (every
/// tensor was built on the async runtime first) and four at once pushed `/healthz` from 3 ms to 15.7 s.
#[test]
fn hostile_weights_are_refused_from_their_header_without_stalling_the_server() {
    let env = Env::new();
    let alice = create_user(&env, "alice");
    let models = env.path("models");
    train_bc(&models, "all", 0);
    let config = std::fs::read(models.join("bc-all/policy.json")).unwrap();
    let entries: Vec<String> = (0..900_000)
        .map(|i| format!(r#""z{i}":{{"dtype":"F32","shape":[0],"data_offsets":[0,0]}}"#))
        .collect();
    let zero_tensors = safetensors(&format!("{{{}}}", entries.join(",")));
    assert!(zero_tensors.len() > 50 << 20);
    let url = env.server.url.clone();
    block_on(async move {
        let started = Instant::now();
        let uploads: Vec<_> = (0..4)
            .map(|_| {
                let parts = vec![
                    ("policy.json".to_owned(), config.clone()),
                    ("policy.safetensors".to_owned(), zero_tensors.clone()),
                ];
                let (url, token) = (url.clone(), alice.clone());
                tokio::spawn(async move { post_submission(&url, &token, parts).await })
            })
            .collect();
        // While the four are being refused, the server answers its health check promptly.
        let mut slowest = Duration::ZERO;
        for _ in 0..10 {
            let t = Instant::now();
            let health = reqwest::get(format!("{url}/healthz")).await.unwrap();
            assert_eq!(health.status(), 200);
            slowest = slowest.max(t.elapsed());
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        for upload in uploads {
            let (status, body) = upload.await.unwrap();
            assert_eq!(status, 400, "{body}");
            let message = body["error"]["message"].as_str().unwrap();
            assert!(message.contains("more than the 262144 allowed"), "{message}");
        }
        assert!(
            slowest < Duration::from_secs(1),
            "/healthz took {slowest:?} during the uploads"
        );
        // The four 53 MB uploads travel over loopback; refusing them is not the slow part.
        assert!(started.elapsed() < Duration::from_secs(30), "{:?}", started.elapsed());
    });
}

/// The probe's memory exhaustion: a 366 KB CDT declaring seq_len = 1000 passed every check and, while scored, grew
/// the server past 500 MB on its way to tens of GB. Its declared cost per step is now over the budget.
#[test]
fn an_architecture_over_the_step_budget_is_refused_with_the_reason() {
    let env = Env::new();
    let bob = create_user(&env, "bob");
    let cdt = crate::make_policy(&env.path("cdt"), TASK, "cdt", 3);
    let long = env.path("cdt-long");
    variant(&cdt, &long, |c| c["architecture"]["seq_len"] = 1000.into());
    let run = submit(&env, &bob, &long, "CDT-long");
    assert_eq!(run.code, 6, "{run:?}");
    assert!(
        run.stdout.contains("multiply-adds") && run.stdout.contains("lower seq_len"),
        "{run:?}"
    );
}

/// A submission that is legal but runs away is ended by the evaluator's budgets, as `failed` with the reason, and
/// the API stays up: the policy acts in a child process under a memory limit, and each evaluation has a deadline
/// (at most `max_evaluation_seconds`).
#[test]
fn evaluations_are_bounded_in_memory_and_time() {
    let binary = dsrl_e2e::bin("dsrl-sim-worker").display().to_string();
    let dir = tempfile::tempdir().unwrap();
    let flags = crate::leaderboard::hosting_the_starter(dir.path());
    let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
    let env = Env::with_kept(
        dir,
        &flags,
        &[
            ("DSRL__SIMULATORS__LOCAL_WORKERS", "1"),
            ("DSRL__SIMULATORS__WORKER_BINARY", &binary),
            // Too little for the policy process to load its weights; the policy acts there, not in the workers
            // (where the checks bound a cheap network's memory, and no address-space limit applies).
            ("DSRL__LEADERBOARD__POLICY_MEMORY_LIMIT_BYTES", "50000000"),
            ("DSRL__LEADERBOARD__ACT_IN_WORKERS_MAX_MULTIPLY_ADDS", "0"),
        ],
    );
    let alice = create_user(&env, "alice");
    let models = env.path("models");
    train_bc(&models, "all", 0);
    let run = submit(&env, &alice, &models.join("bc-all"), "BC-All").ok().json();
    let done = client(&env, &alice, &["--json", "status", &run["id"].to_string(), "--wait"]).json();
    assert_eq!(done["state"], "failed", "{done}");
    let reason = done["reason"].as_str().unwrap();
    assert!(
        reason.contains("the policy process") && reason.contains("47 MB memory limit"),
        "{reason}"
    );
    let health = block_on(async move {
        reqwest::get(format!("{}/healthz", env.server.url))
            .await
            .unwrap()
            .status()
    });
    assert_eq!(health, 200);

    // One second is not enough to play 3 x 20 PointGoal1 episodes of 1000 steps.
    let env = Env::with(
        &[],
        &[
            ("DSRL__SIMULATORS__LOCAL_WORKERS", "1"),
            ("DSRL__SIMULATORS__WORKER_BINARY", &binary),
            ("DSRL__LEADERBOARD__MAX_EVALUATION_SECONDS", "1"),
        ],
    );
    let alice = create_user(&env, "alice");
    let task = "OfflinePointGoal1Gymnasium-v0";
    let policy = crate::make_policy(&env.path("mlp"), task, "target-cost-mlp", 1);
    let submit = || {
        dsrl_e2e::Run::from(
            env.cli
                .command(&["--json", "submit", crate::s(&policy), "--task", task, "--name", "slow"])
                .env("DSRL_TOKEN", &alice)
                .output()
                .unwrap(),
        )
        .ok()
        .json()
    };
    let run = submit();
    let done = client(&env, &alice, &["--json", "status", &run["id"].to_string(), "--wait"]).json();
    assert_eq!(done["state"], "failed", "{done}");
    assert!(
        done["reason"].as_str().unwrap().contains("past its deadline of 1 s"),
        "{done}"
    );
    // A deadline is the machine's time, not the checkpoint's fault: the same checkpoint may be submitted again.
    assert_eq!(done["failure"], "infrastructure", "{done}");
    let again = submit();
    assert_ne!(again["id"], run["id"], "{again}");
}

/// Sends raw HTTP/1.1 and returns what came back until the answer's body ends with `until` (or the connection
/// closes, or 30 s pass).
fn raw(url: &str, request: &str, until: &str) -> String {
    let address = url.trim_start_matches("http://");
    let mut stream = std::net::TcpStream::connect(address).unwrap();
    stream.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    stream.write_all(request.as_bytes()).unwrap();
    let mut response = Vec::new();
    let mut buf = [0u8; 4096];
    while let Ok(n) = stream.read(&mut buf) {
        if n == 0 {
            break;
        }
        response.extend_from_slice(&buf[..n]);
        if String::from_utf8_lossy(&response).trim_end().ends_with(until) {
            break;
        }
    }
    String::from_utf8_lossy(&response).into_owned()
}

/// Authentication comes first and every failure is the JSON error document: the probe got 415/422/400 in plain
/// text from `POST /v1/users` without a token (the body was parsed first) and a plain-text 400 from a bad multipart
/// Content-Type on `/v1/submissions` before the user check.
#[test]
fn authentication_comes_first_and_every_error_is_the_json_document() {
    let env = Env::new();
    let url = env.server.url.clone();
    let admin = env.server.token();
    let alice = create_user(&env, "alice");
    block_on(async move {
        let http = reqwest::Client::new();
        let check = |response: reqwest::Response, status: u16, code: &'static str| async move {
            assert_eq!(response.status().as_u16(), status);
            assert!(
                response.headers()["content-type"]
                    .to_str()
                    .unwrap()
                    .starts_with("application/json"),
                "{:?}",
                response.headers()
            );
            let body: serde_json::Value = response.json().await.unwrap();
            assert_eq!(body["error"]["code"], code, "{body}");
            body["error"]["message"].as_str().unwrap().to_owned()
        };
        // No token: 401, whatever the body.
        for body in ["not json", "{\"nom\": 1}", ""] {
            let r = http.post(format!("{url}/v1/users")).body(body).send().await.unwrap();
            check(r, 401, "unauthenticated").await;
        }
        // With the admin token, a body that is not {"name": ...} is a 400 that says so.
        let r = http
            .post(format!("{url}/v1/users"))
            .bearer_auth(&admin)
            .body("not json")
            .send()
            .await
            .unwrap();
        let message = check(r, 400, "invalid_argument").await;
        assert!(message.contains("{\"name\": NAME}"), "{message}");
        // Submissions: the user first, then the multipart body.
        let r = http
            .post(format!("{url}/v1/submissions"))
            .header("content-type", "text/plain")
            .body("x")
            .send()
            .await
            .unwrap();
        check(r, 401, "unauthenticated").await;
        let r = http
            .post(format!("{url}/v1/submissions"))
            .bearer_auth(&alice)
            .header("content-type", "text/plain")
            .body("x")
            .send()
            .await
            .unwrap();
        let message = check(r, 400, "invalid_argument").await;
        assert!(message.contains("multipart/form-data"), "{message}");
        // Framework answers (a wrong method, a malformed query) are the JSON document too.
        let r = http.delete(format!("{url}/v1/tasks")).send().await.unwrap();
        check(r, 405, "invalid_argument").await;
        let r = http
            .get(format!("{url}/v1/leaderboard?task=a&task=b"))
            .send()
            .await
            .unwrap();
        check(r, 400, "invalid_argument").await;
    });
}

/// A refused upload announces that the server closes the connection: the probe's Python `requests` session failed
/// its next request after a 413 on `/v1/submissions` that closed the socket without `Connection: close`.
#[test]
fn a_refused_submission_says_connection_close() {
    let env = Env::new();
    let alice = create_user(&env, "alice");
    let body_len = 3 * (64u64 << 20);
    // Declares a body larger than the submission limit; sends only the start of it.
    let head = format!(
        "POST /v1/submissions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {alice}\r\n\
         Content-Type: multipart/form-data; boundary=B\r\nContent-Length: {body_len}\r\n\r\n\
         --B\r\nContent-Disposition: form-data; name=\"policy.json\"; filename=\"policy.json\"\r\n\r\n{}",
        " ".repeat(70_000)
    );
    let response = raw(&env.server.url, &head, "}}");
    let status_line = response.lines().next().unwrap_or_default();
    assert!(status_line.contains(" 413 "), "{response}");
    assert!(
        response.to_ascii_lowercase().contains("\r\nconnection: close\r\n"),
        "{response}"
    );
    assert!(response.contains("\"payload_too_large\""), "{response}");
}
