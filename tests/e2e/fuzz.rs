//! A bounded property-based fuzz run of the whole REST API from its own OpenAPI document (schemathesis, from the
//! pinned test environment) against a real server hosting a dataset, once with the admin token and once with a
//! user token. Any 5xx, an undocumented status, a wrong content type or a body that breaks the documented schema
//! fails the test. The seed is fixed so a failure reproduces; the time budget keeps it to a couple of minutes.

use crate::Env;

/// Seconds of fuzzing per token.
const BUDGET_SECONDS: &str = "45";
const SEED: &str = "20261123";

fn schemathesis(url: &str, token: &str) -> std::process::Output {
    let program = dsrl_e2e::python()
        .parent()
        .expect("the venv's bin folder")
        .join("schemathesis");
    std::process::Command::new(program)
        .args(["run", &format!("{url}/openapi.json")])
        .args(["-H", &format!("Authorization: Bearer {token}")])
        .args([
            "--checks",
            "not_a_server_error,status_code_conformance,content_type_conformance,response_schema_conformance",
        ])
        .args(["--phases", "examples,coverage,fuzzing"])
        .args(["--max-time", BUDGET_SECONDS, "--seed", SEED, "--workers", "1"])
        .args(["--request-timeout", "30"])
        .env("SCHEMATHESIS_TELEMETRY", "false")
        .env("NO_COLOR", "1")
        .output()
        .expect("running schemathesis from the test environment (scripts/setup-python.sh installs it)")
}

#[test]
fn the_openapi_document_holds_under_fuzzing_with_admin_and_user_tokens() {
    let env = Env::new();
    env.ingest_synthetic("OfflineBallRun-v0", 30, 7);
    let admin = env.server.token();
    let user = crate::leaderboard::create_user(&env, "fuzzer");
    for (who, token) in [("admin", admin.as_str()), ("user", user.as_str())] {
        let out = schemathesis(&env.server.url, token);
        let text = format!(
            "{}\n{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(
            out.status.success(),
            "schemathesis with the {who} token failed:\n{text}"
        );
        assert!(text.contains("passed"), "{text}");
    }
}
