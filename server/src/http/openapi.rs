//! The OpenAPI document served at `/openapi.json`, generated from the handlers' annotations.

use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use super::{datasets, simulators};

#[derive(OpenApi)]
#[openapi(
    info(
        title = "dsrl",
        description = "Offline safe RL datasets (DSRL's 38 tasks): catalog, versioned Parquet datasets, downloads. \
                       gRPC serves the same on the same port (proto/dsrl/datasets/v1/datasets.proto). Errors are \
                       JSON {\"error\": {\"code\", \"message\", \"suggestions\"?}}."
    ),
    paths(
        datasets::server_info,
        datasets::list_tasks,
        datasets::get_task,
        datasets::list_versions,
        datasets::get_manifest,
        datasets::get_plot,
        datasets::ingest,
        datasets::put_tag,
        simulators::list_simulators,
        download_doc,
    ),
    components(schemas(dsrl_suite::EpisodeSummary)),
    modifiers(&AdminToken)
)]
pub struct ApiDoc;

struct AdminToken;

impl Modify for AdminToken {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "admin_token",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// Documentation-only stub for the download route (the handler is in `download.rs`).
#[utoipa::path(get, path = "/v1/datasets/{task}/versions/{version}/download", tag = "datasets",
    params(
        ("task" = String, Path),
        ("version" = String, Path, description = "Version id (sha256) or tag"),
        ("Range" = Option<String>, Header, description = "bytes=A-B, bytes=A- or bytes=-N"),
        ("If-Range" = Option<String>, Header, description = "The ETag the client has part of"),
        ("If-None-Match" = Option<String>, Header),
        ("filter" = Option<String>, Query, description = "A DSRL post-process filter: the download is the filtered version"),
    ),
    responses(
        (status = 200, description = "The Parquet file; ETag is its sha256", content_type = "application/vnd.apache.parquet"),
        (status = 206, description = "The requested byte range"),
        (status = 304, description = "Not modified"),
        (status = 404), (status = 416, description = "Range not satisfiable")))]
#[allow(dead_code)]
fn download_doc() {}

pub fn json() -> String {
    ApiDoc::openapi()
        .to_pretty_json()
        .expect("the OpenAPI document serializes")
}
