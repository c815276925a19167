//! Prometheus metrics: requests by route and status (REST) or method and code (gRPC), request latency, bytes
//! served, ingests by outcome, filter requests by outcome and computation time, hosted versions.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

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
    /// Filter requests: `computed` (a filtered version was made), `cached` (it existed), `rejected`.
    pub filters: Family<OutcomeLabels, Counter>,
    pub filter_seconds: Histogram,
    pub dataset_versions: Gauge,
    /// Leaderboard jobs waiting for an evaluator (shared database: every replica reports the same number).
    pub queue_depth: Gauge,
    /// Request handlers that panicked, by route (each also counts as a 500 / INTERNAL in `requests`).
    pub panics: Family<RouteLabels, Counter>,
    /// Evaluators of this process started again after a panic (the leaderboard's supervisor counts into it).
    pub evaluator_restarts: Counter,
    pub replays_rendered: Counter,
    pub replay_failures: Counter,
    pub renderer_restarts: Counter,
    /// HDF5 export requests: `computed` (converted now) or `cached`.
    pub hdf5_exports: Family<OutcomeLabels, Counter>,
    /// Bytes of all filtered versions stored, read at scrape time.
    pub derived_bytes: Gauge,
    /// Runs of the derived-data policy while the server runs, by outcome (ok, failed).
    pub gc_runs: Family<OutcomeLabels, Counter>,
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
        let filters = Family::<OutcomeLabels, Counter>::default();
        registry.register(
            "filters",
            "Filter requests by outcome (computed, cached, rejected)",
            filters.clone(),
        );
        let filter_seconds = Histogram::new(exponential_buckets(0.01, 2.0, 12));
        registry.register(
            "filter_seconds",
            "Time to compute a filtered version",
            filter_seconds.clone(),
        );
        let dataset_versions = Gauge::default();
        registry.register("dataset_versions", "Hosted dataset versions", dataset_versions.clone());
        let queue_depth = dsrl_leaderboard::queue::register_depth_gauge(&mut registry);
        let panics = Family::<RouteLabels, Counter>::default();
        registry.register(
            "panics",
            "Request handlers that panicked, by route (answered 500 / INTERNAL)",
            panics.clone(),
        );
        let evaluator_restarts = Counter::default();
        registry.register(
            "evaluator_restarts",
            "Evaluator tasks of this process started again after a panic",
            evaluator_restarts.clone(),
        );
        let replays_rendered = Counter::default();
        registry.register(
            "replays_rendered",
            "Scored episodes replayed, drawn and stored to watch",
            replays_rendered.clone(),
        );
        let replay_failures = Counter::default();
        registry.register(
            "replay_failures",
            "Replays of scored episodes that failed (the reason is served with the replay)",
            replay_failures.clone(),
        );
        let renderer_restarts = Counter::default();
        registry.register(
            "renderer_restarts",
            "The replay renderer started again after a panic",
            renderer_restarts.clone(),
        );
        let hdf5_exports = Family::<OutcomeLabels, Counter>::default();
        registry.register(
            "hdf5_exports",
            "HDF5 export requests by outcome (computed, cached)",
            hdf5_exports.clone(),
        );
        let derived_bytes = Gauge::default();
        registry.register(
            "derived_bytes",
            "Bytes of the filtered versions stored (the run-time budget is gc.derived_max_bytes)",
            derived_bytes.clone(),
        );
        let gc_runs = Family::<OutcomeLabels, Counter>::default();
        registry.register(
            "gc_runs",
            "Runs of the derived-data policy while the server runs, by outcome",
            gc_runs.clone(),
        );
        Metrics {
            gc_runs,
            hdf5_exports,
            derived_bytes,
            evaluator_restarts,
            replays_rendered,
            replay_failures,
            renderer_restarts,
            panics,
            registry,
            requests,
            latency,
            download_bytes,
            ingests,
            filters,
            filter_seconds,
            dataset_versions,
            queue_depth,
        }
    }

    pub fn render(&self) -> String {
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &self.registry).expect("writing to a String");
        out
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}
