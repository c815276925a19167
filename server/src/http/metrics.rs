//! Prometheus metrics in the text exposition format at `/metrics`: requests by route and status (REST) or method
//! and code (gRPC), request latency, bytes served, ingests by outcome, hosted versions.

use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

use crate::AppState;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RequestLabels {
    pub method: String,
    pub route: String,
    /// HTTP status for REST; the `grpc-status` code for gRPC (0 when it only arrives in trailers, i.e. OK).
    pub status: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RouteLabels {
    pub route: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct OutcomeLabels {
    pub outcome: &'static str,
}

pub struct Metrics {
    registry: Registry,
    pub requests: Family<RequestLabels, Counter>,
    pub latency: Family<RouteLabels, Histogram>,
    pub download_bytes: Counter,
    pub ingests: Family<OutcomeLabels, Counter>,
    pub dataset_versions: Gauge,
}

impl Metrics {
    pub fn new() -> Metrics {
        let mut registry = Registry::with_prefix("dsrl");
        let requests = Family::<RequestLabels, Counter>::default();
        registry.register(
            "requests",
            "Requests by method (HTTP verb or gRPC method), route and status",
            requests.clone(),
        );
        let latency = Family::<RouteLabels, Histogram>::new_with_constructor(|| {
            Histogram::new(exponential_buckets(0.0005, 4.0, 10))
        });
        registry.register(
            "request_duration_seconds",
            "Time to the response head, by route",
            latency.clone(),
        );
        let download_bytes = Counter::default();
        registry.register(
            "download_bytes",
            "Dataset bytes sent to clients",
            download_bytes.clone(),
        );
        let ingests = Family::<OutcomeLabels, Counter>::default();
        registry.register(
            "ingests",
            "Ingest requests by outcome (created, unchanged, rejected)",
            ingests.clone(),
        );
        let dataset_versions = Gauge::default();
        registry.register(
            "dataset_versions",
            "Hosted dataset versions",
            dataset_versions.clone(),
        );
        Metrics {
            registry,
            requests,
            latency,
            download_bytes,
            ingests,
            dataset_versions,
        }
    }

    pub fn render(&self) -> String {
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &self.registry)
            .expect("writing to a String");
        out
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}

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

fn is_grpc(request: &Request) -> bool {
    request
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"))
}

pub async fn metrics(State(state): State<AppState>) -> impl IntoResponse {
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        state.metrics.render(),
    )
}
