//! The OpenAPI document served at `/openapi.json`, generated from the handlers' annotations.

use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use super::metrics;
use crate::datasets::{dsrl_download, pages, rest as datasets};
use crate::leaderboard::rest as leaderboard;
use crate::simulators;

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
        datasets::get_croissant,
        datasets::ingest,
        datasets::get_upload,
        datasets::find_uploads,
        datasets::put_tag,
        simulators::list_simulators,
        download_doc,
        dsrl_download::dsrl_download,
        pages::index,
        pages::card,
        leaderboard::create_user,
        leaderboard::submit,
        leaderboard::get_submission,
        leaderboard::cancel_submission,
        leaderboard::get_leaderboard,
        leaderboard::leaderboard_page,
        leaderboard::agreement_page,
        leaderboard::plot,
        leaderboard::leaderboard_csv,
        leaderboard::leaderboard_parquet,
        leaderboard::submission_episodes_csv,
        leaderboard::episode_replay,
        leaderboard::episode_replay_gif,
        leaderboard::user_submissions,
        leaderboard::user_page,
        leaderboard::submission_page,
        super::healthz,
        super::openapi_json,
        metrics::metrics,
    ),
    components(schemas(dsrl_suite::EpisodeSummary, ErrorDocument)),
    modifiers(&AdminToken, &Conventions)
)]
pub struct ApiDoc;

/// The one error shape of every REST failure (documentation type; `error.rs` renders it).
#[derive(utoipa::ToSchema)]
#[allow(dead_code)]
pub struct ErrorDocument {
    error: ErrorDetail,
}

#[derive(utoipa::ToSchema)]
#[allow(dead_code)]
struct ErrorDetail {
    /// not_found, invalid_argument, payload_too_large, range_not_satisfiable, unauthenticated, permission_denied,
    /// already_exists, resource_exhausted, unavailable or internal.
    code: String,
    message: String,
    /// Nearest task ids, for an unknown task.
    suggestions: Option<Vec<String>>,
}

struct AdminToken;

impl Modify for AdminToken {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        for name in ["admin_token", "user_token"] {
            components.add_security_scheme(
                name,
                SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
            );
        }
    }
}

/// What holds for every route, written once: each error response is the JSON error document, and the path
/// parameters have the patterns the server accepts (anything else is a 404 for a task, a 400 otherwise).
struct Conventions;

/// Path parameter name → the pattern of a value the server may accept, and an example.
const PATH_PATTERNS: [(&str, &str, &str); 5] = [
    ("task", "^[A-Za-z0-9._-]{1,128}$", "OfflineBallRun-v0"),
    // A version id (sha256) or a tag.
    ("version", "^([0-9a-f]{64}|[a-z][a-z0-9._-]{0,63})$", "latest"),
    ("tag", "^[a-z][a-z0-9._-]{0,63}$", "stable"),
    ("id", "^[0-9]{1,18}$", "1"),
    ("upload", "^[0-9a-f]{24}$", "0123456789abcdef01234567"),
];

impl Modify for Conventions {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::schema::{ObjectBuilder, Type};
        use utoipa::openapi::{Content, Ref, RefOr};
        for item in openapi.paths.paths.values_mut() {
            let operations = [
                &mut item.get,
                &mut item.put,
                &mut item.post,
                &mut item.delete,
                &mut item.patch,
                &mut item.head,
            ];
            for operation in operations.into_iter().flatten() {
                for parameter in operation.parameters.iter_mut().flatten() {
                    if parameter.parameter_in != utoipa::openapi::path::ParameterIn::Path {
                        continue;
                    }
                    if let Some((_, pattern, example)) = PATH_PATTERNS.iter().find(|(name, ..)| *name == parameter.name)
                    {
                        parameter.schema = Some(RefOr::T(
                            ObjectBuilder::new()
                                .schema_type(Type::String)
                                .pattern(Some(*pattern))
                                .examples([*example])
                                .into(),
                        ));
                    }
                }
                // Any route may find the server's disk full (a write, a derivation, the health probe).
                operation.responses.responses.entry("507".into()).or_insert_with(|| {
                    RefOr::T(utoipa::openapi::Response::new(
                        "The server's disk is full: nothing was written; retry after Retry-After",
                    ))
                });
                for (status, response) in operation.responses.responses.iter_mut() {
                    let RefOr::T(response) = response else { continue };
                    if status.as_str() >= "400" && response.content.is_empty() {
                        response.content.insert(
                            "application/json".into(),
                            Content::new(Some(Ref::from_schema_name("ErrorDocument"))),
                        );
                    }
                    if response.description.is_empty() {
                        response.description = "See the error message".into();
                    }
                }
            }
        }
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
        ("format" = Option<String>, Query, description = "parquet (default) or hdf5: DSRL's HDF5 layout, converted once per version on the server and stored; its ETag is its sha256"),
    ),
    responses(
        (status = 200, description = "The Parquet file; ETag is its sha256", content_type = "application/vnd.apache.parquet"),
        (status = 206, description = "The requested byte range"),
        (status = 304, description = "Not modified"),
        (status = 400, description = "An invalid version reference or filter"),
        (status = 404, description = "Unknown task or version"), (status = 416, description = "Range not satisfiable"),
        (status = 429, description = "The anonymous derivation budget of the hour is spent: send a token, or retry after Retry-After"),
        (status = 503, description = "Too much derivation work waiting: retry after Retry-After")))]
#[allow(dead_code)]
fn download_doc() {}

pub fn json() -> String {
    ApiDoc::openapi()
        .to_pretty_json()
        .expect("the OpenAPI document serializes")
}
