use axum::body::Body;
use axum::http::{Request, StatusCode};
use dsrl_server::datasets::converter::Converter;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tower::ServiceExt;

use crate::config;

#[tokio::test]
async fn run_serves_on_port_zero_and_stops_on_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(dsrl_server::run(listener, config(dir.path()), async {
        let _ = stopped.await;
    }));
    let mut body = String::new();
    for _ in 0..100 {
        if let Ok(mut conn) = tokio::net::TcpStream::connect(addr).await {
            conn.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
                .await
                .unwrap();
            conn.read_to_string(&mut body).await.unwrap();
            if !body.is_empty() {
                break;
            }
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    assert!(body.starts_with("HTTP/1.1 200 OK"), "{body}");
    assert!(body.contains(r#""status":"ok""#), "{body}");
    stop.send(()).unwrap();
    tokio::time::timeout(std::time::Duration::from_secs(10), server)
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(dir.path().join("dsrl.sqlite3").exists());
}

async fn app(dir: &std::path::Path) -> axum::Router {
    dsrl_server::app(
        dsrl_server::build_state(&config(dir), Converter::InProcess)
            .await
            .unwrap(),
    )
}

async fn json(response: axum::response::Response) -> serde_json::Value {
    let bytes = axum::body::to_bytes(response.into_body(), 1 << 20).await.unwrap();
    serde_json::from_slice(&bytes).unwrap()
}

#[tokio::test]
async fn malformed_requests_get_the_json_error_document() {
    let dir = tempfile::tempdir().unwrap();
    let app = app(dir.path()).await;
    let auth = "Bearer integration-test-token";
    let cases = [
        // Unknown query parameter on ingest (a typo must not be ignored).
        Request::post("/v1/datasets/OfflineAntRun-v0/versions?tag=x")
            .header("authorization", auth)
            .body(Body::from("x")),
        // Malformed JSON for a tag.
        Request::put("/v1/datasets/OfflineAntRun-v0/tags/stable")
            .header("authorization", auth)
            .header("content-type", "application/json")
            .body(Body::from("{not json")),
        // A version reference that is neither an id nor a tag.
        Request::get("/v1/datasets/OfflineAntRun-v0/versions/UPPER%20CASE").body(Body::empty()),
        // A recipe provenance header that is not JSON.
        Request::post("/v1/datasets/OfflineAntRun-v0/versions")
            .header("authorization", auth)
            .header("dsrl-provenance", "{")
            .body(Body::from("x")),
    ];
    for request in cases {
        let request = request.unwrap();
        let what = format!("{} {}", request.method(), request.uri());
        let response = app.clone().oneshot(request).await.unwrap();
        assert_eq!(response.status(), StatusCode::BAD_REQUEST, "{what}");
        let body = json(response).await;
        assert_eq!(body["error"]["code"], "invalid_argument", "{what}: {body}");
        assert!(!body["error"]["message"].as_str().unwrap().is_empty());
    }
    // Import provenance cannot be declared by the uploader: the server records it.
    let request = Request::post("/v1/datasets/OfflineAntRun-v0/versions")
        .header("authorization", auth)
        .header(
            "dsrl-provenance",
            r#"{"kind":"import","file_name":"x","sha256":"y","source_format":"hdf5"}"#,
        )
        .body(Body::from("x"))
        .unwrap();
    let body = json(app.clone().oneshot(request).await.unwrap()).await;
    assert!(
        body["error"]["message"]
            .as_str()
            .unwrap()
            .contains("only recipe provenance"),
        "{body}"
    );
}

#[tokio::test]
async fn grpc_and_rest_share_the_port_and_unknown_routes_are_json_404s() {
    let dir = tempfile::tempdir().unwrap();
    let app = app(dir.path()).await;
    let response = app
        .clone()
        .oneshot(Request::get("/v2/anything").body(Body::empty()).unwrap())
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::NOT_FOUND);
    assert_eq!(json(response).await["error"]["code"], "not_found");
    // A gRPC call routed by path to the tonic service: an empty ListTasks frame answers with grpc-status 0.
    let frame = Body::from(vec![0u8, 0, 0, 0, 0]);
    let request = Request::post("/dsrl.datasets.v1.DatasetService/ListTasks")
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(frame)
        .unwrap();
    let response = app.clone().oneshot(request).await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(response.headers()["content-type"], "application/grpc");
}

/// A panicking handler answers the JSON error shape (REST) or INTERNAL (gRPC), and `/metrics` counts it both as a
/// 500 by route and in `dsrl_panics_total` (before, the catch-panic layer sat outside the metrics middleware and a
/// panic's 500 was never counted).
#[tokio::test]
async fn a_panicking_handler_is_a_counted_json_500_and_a_grpc_internal() {
    let dir = tempfile::tempdir().unwrap();
    let state = dsrl_server::build_state(&config(dir.path()), Converter::InProcess)
        .await
        .unwrap();
    async fn boom() -> &'static str {
        panic!("deliberate test panic")
    }
    let routes = axum::Router::new()
        .route("/test/panic", axum::routing::get(boom))
        .route("/test.Grpc/Panic", axum::routing::post(boom))
        .route("/metrics", axum::routing::get(dsrl_server::http::metrics::metrics))
        .with_state(state.clone());
    let app = dsrl_server::with_layers(routes, state);
    let response = app
        .clone()
        .oneshot(Request::get("/test/panic").body(Body::empty()).unwrap())
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::INTERNAL_SERVER_ERROR);
    let body = json(response).await;
    assert_eq!(body["error"]["code"], "internal", "{body}");
    let response = app
        .clone()
        .oneshot(
            Request::post("/test.Grpc/Panic")
                .header("content-type", "application/grpc")
                .body(Body::empty())
                .unwrap(),
        )
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(response.headers()["grpc-status"], "13", "INTERNAL");
    let metrics = app
        .oneshot(Request::get("/metrics").body(Body::empty()).unwrap())
        .await
        .unwrap();
    let text = String::from_utf8(
        axum::body::to_bytes(metrics.into_body(), 1 << 20)
            .await
            .unwrap()
            .to_vec(),
    )
    .unwrap();
    assert!(
        text.contains(r#"dsrl_requests_total{method="GET",route="/test/panic",status="500"} 1"#),
        "{text}"
    );
    assert!(
        text.contains(r#"dsrl_requests_total{method="POST",route="/test.Grpc/Panic",status="13"} 1"#),
        "{text}"
    );
    assert!(text.contains(r#"dsrl_panics_total{route="/test/panic"} 1"#), "{text}");
}
