//! The HTTP side of metrics: a middleware that counts every request, and `/metrics` in the Prometheus text format.

use std::time::Instant;

use crate::AppState;
use crate::metrics::{RequestLabels, RouteLabels};
use axum::extract::{MatchedPath, Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// Counts every request by its route template (not the raw path, which would explode label cardinality).
pub async fn track(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let started = Instant::now();
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_owned())
        .unwrap_or_else(|| {
            if is_grpc(&request) {
                request.uri().path().to_owned()
            } else {
                "unmatched".into()
            }
        });
    let method = request.method().to_string();
    let grpc = is_grpc(&request);
    let response = next.run(request).await;
    // gRPC answers HTTP 200 and carries its status in `grpc-status`: in the head for an immediate error, in
    // the trailers otherwise.
    let status = match response.headers().get("grpc-status") {
        Some(v) => v.to_str().unwrap_or("2").to_owned(),
        None if grpc => "0".to_owned(),
        None => response.status().as_u16().to_string(),
    };
    state
        .metrics
        .requests
        .get_or_create(&RequestLabels {
            method,
            route: route.clone(),
            status,
        })
        .inc();
    state
        .metrics
        .latency
        .get_or_create(&RouteLabels { route })
        .observe(started.elapsed().as_secs_f64());
    response
}

pub(crate) fn is_grpc(request: &Request) -> bool {
    request
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"))
}

#[utoipa::path(get, path = "/metrics", tag = "operations",
    responses((status = 200, content_type = "application/openmetrics-text", body = String,
        description = "Prometheus metrics: requests by route and status, latency, panics, downloads, ingests, filters")))]
pub async fn metrics(State(state): State<AppState>) -> impl IntoResponse {
    dsrl_leaderboard::queue::refresh_depth_gauge(&state.metrics.queue_depth, &state.leaderboard.db).await;
    match state.datasets.db().derived_bytes().await {
        Ok(bytes) => {
            state.metrics.derived_bytes.set(bytes as i64);
        }
        Err(e) => tracing::warn!(error = %e, "reading the derived bytes"),
    }
    (
        [(header::CONTENT_TYPE, dsrl_service::OPENMETRICS_CONTENT_TYPE)],
        state.metrics.render(),
    )
}
