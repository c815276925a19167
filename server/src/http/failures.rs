//! Every failure answers in the one error shape, whoever produced it:
//! - a handler that panics answers 500 with the JSON error document over REST, `INTERNAL` over gRPC; this layer
//!   sits inside the metrics middleware, so the 500 is counted by route and status (a 5xx alert fires), and
//!   `dsrl_panics_total` counts it once more by route;
//! - an error that a framework layer answered in plain text (axum's extractor rejections, a 405, a body limit)
//!   is rewritten into the JSON document with the same status, its text as the message.

use std::panic::AssertUnwindSafe;

use axum::extract::{MatchedPath, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use futures::FutureExt;

use crate::AppState;
use crate::error::{ApiError, ErrorCode};
use crate::metrics::RouteLabels;

pub async fn catch(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let grpc = super::metrics::is_grpc(&request);
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_owned())
        .unwrap_or_else(|| request.uri().path().to_owned());
    match AssertUnwindSafe(next.run(request)).catch_unwind().await {
        Ok(response) if grpc => response,
        Ok(response) => as_error_document(response).await,
        Err(payload) => {
            let what = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic without a message".to_owned());
            tracing::error!(%route, panic = %what, "a request handler panicked");
            state.metrics.panics.get_or_create(&RouteLabels { route }).inc();
            let error = ApiError::Internal("the request handler failed; this is a server bug and was logged".into());
            if grpc {
                grpc_internal(&error)
            } else {
                error.into_response()
            }
        }
    }
}

/// A 4xx or 5xx whose body is not JSON becomes the JSON error document with the same status and headers.
async fn as_error_document(response: Response) -> Response {
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = match axum::body::to_bytes(body, 64 << 10).await {
        Ok(bytes) => String::from_utf8_lossy(&bytes).trim().to_owned(),
        Err(_) => String::new(),
    };
    let message = if text.is_empty() {
        status.canonical_reason().unwrap_or("error").to_lowercase()
    } else {
        text
    };
    let code = ErrorCode::for_http_status(status);
    let body = serde_json::json!({ "error": { "code": code, "message": message } });
    parts.headers.remove(header::CONTENT_LENGTH);
    parts
        .headers
        .insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
    Response::from_parts(parts, axum::body::Body::from(body.to_string()))
}

/// A trailers-only gRPC answer: HTTP 200 with `grpc-status` in the head, as tonic answers an immediate error.
fn grpc_internal(error: &ApiError) -> Response {
    let mut response = StatusCode::OK.into_response();
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/grpc"));
    let code = ErrorCode::Internal;
    headers.insert("grpc-status", HeaderValue::from(code.grpc_code() as i32));
    // grpc-message is percent-encoded; this message is plain ASCII without '%'.
    let message = error.to_string().replace(' ', "%20");
    if let Ok(v) = HeaderValue::from_str(&message) {
        headers.insert("grpc-message", v);
    }
    headers.insert("dsrl-error-code", HeaderValue::from_static(code.as_str()));
    response
}
