//! The server's one error type and the one table that maps each kind of error to an HTTP status and a gRPC
//! code. Handlers return `ApiError`; REST renders it as JSON `{"error": {"code", "message", ...}}`, gRPC as a
//! `Status` with the same message and the code name in the `dsrl-error-code` metadata.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use dsrl_evaluation::EvaluationError;
use dsrl_suite::UnknownTask;
use serde::Serialize;

/// Kinds of failure a client can act on; each has exactly one HTTP status and one gRPC code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    NotFound,
    InvalidArgument,
    PayloadTooLarge,
    RangeNotSatisfiable,
    Unauthenticated,
    PermissionDenied,
    AlreadyExists,
    ResourceExhausted,
    Unavailable,
    InsufficientStorage,
    Internal,
}

impl ErrorCode {
    pub const ALL: [ErrorCode; 11] = [
        ErrorCode::NotFound,
        ErrorCode::InvalidArgument,
        ErrorCode::PayloadTooLarge,
        ErrorCode::RangeNotSatisfiable,
        ErrorCode::Unauthenticated,
        ErrorCode::PermissionDenied,
        ErrorCode::AlreadyExists,
        ErrorCode::ResourceExhausted,
        ErrorCode::Unavailable,
        ErrorCode::InsufficientStorage,
        ErrorCode::Internal,
    ];

    /// The table.
    pub fn statuses(self) -> (StatusCode, tonic::Code) {
        match self {
            ErrorCode::NotFound => (StatusCode::NOT_FOUND, tonic::Code::NotFound),
            ErrorCode::InvalidArgument => (StatusCode::BAD_REQUEST, tonic::Code::InvalidArgument),
            ErrorCode::PayloadTooLarge => (StatusCode::PAYLOAD_TOO_LARGE, tonic::Code::ResourceExhausted),
            ErrorCode::RangeNotSatisfiable => (StatusCode::RANGE_NOT_SATISFIABLE, tonic::Code::OutOfRange),
            ErrorCode::Unauthenticated => (StatusCode::UNAUTHORIZED, tonic::Code::Unauthenticated),
            ErrorCode::PermissionDenied => (StatusCode::FORBIDDEN, tonic::Code::PermissionDenied),
            ErrorCode::AlreadyExists => (StatusCode::CONFLICT, tonic::Code::AlreadyExists),
            ErrorCode::ResourceExhausted => (StatusCode::TOO_MANY_REQUESTS, tonic::Code::ResourceExhausted),
            ErrorCode::Unavailable => (StatusCode::SERVICE_UNAVAILABLE, tonic::Code::Unavailable),
            // The server's disk (or its database's) is full: nothing the client sent is wrong, and the same request
            // may succeed once space is freed, hence UNAVAILABLE over gRPC.
            ErrorCode::InsufficientStorage => (StatusCode::INSUFFICIENT_STORAGE, tonic::Code::Unavailable),
            ErrorCode::Internal => (StatusCode::INTERNAL_SERVER_ERROR, tonic::Code::Internal),
        }
    }

    /// The code of a status some framework layer answered with (a 405, a 415 from an extractor): the table's
    /// code for that status, else `invalid_argument` for other 4xx and `internal` for 5xx.
    pub fn for_http_status(status: StatusCode) -> ErrorCode {
        ErrorCode::ALL
            .into_iter()
            .find(|c| c.http_status() == status)
            .unwrap_or(if status.is_server_error() {
                ErrorCode::Internal
            } else {
                ErrorCode::InvalidArgument
            })
    }

    pub fn http_status(self) -> StatusCode {
        self.statuses().0
    }

    pub fn grpc_code(self) -> tonic::Code {
        self.statuses().1
    }

    pub fn as_str(self) -> &'static str {
        match self {
            ErrorCode::NotFound => "not_found",
            ErrorCode::InvalidArgument => "invalid_argument",
            ErrorCode::PayloadTooLarge => "payload_too_large",
            ErrorCode::RangeNotSatisfiable => "range_not_satisfiable",
            ErrorCode::Unauthenticated => "unauthenticated",
            ErrorCode::PermissionDenied => "permission_denied",
            ErrorCode::AlreadyExists => "already_exists",
            ErrorCode::ResourceExhausted => "resource_exhausted",
            ErrorCode::Unavailable => "unavailable",
            ErrorCode::InsufficientStorage => "insufficient_storage",
            ErrorCode::Internal => "internal",
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    #[error("{0}")]
    UnknownTask(UnknownTask),
    #[error("{task} has no version {reference:?}; list them with GET /v1/datasets/{task}/versions")]
    VersionNotFound { task: String, reference: String },
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    InvalidArgument(String),
    /// The uploaded file is not a valid dataset for the task; the message names the first problem.
    #[error("rejected upload: {0}")]
    InvalidUpload(String),
    #[error("upload too large: the limit is {limit} bytes")]
    UploadTooLarge { limit: u64 },
    #[error("range not satisfiable: the file has {size} bytes")]
    RangeNotSatisfiable { size: u64 },
    #[error("this operation needs an admin bearer token (Authorization: Bearer <token>)")]
    Unauthenticated,
    #[error("the bearer token is not valid for admin operations")]
    PermissionDenied,
    /// A valid token that may not do this (e.g. cancel another user's submission); the message says why.
    #[error("{0}")]
    Forbidden(String),
    #[error("this operation needs a user bearer token (an admin issues one: dsrl-client admin create-user NAME)")]
    UserUnauthenticated,
    #[error("the bearer token belongs to no user")]
    UnknownUserToken,
    #[error("{0}")]
    AlreadyExists(String),
    #[error("service unavailable: {0}")]
    Unavailable(String),
    /// Too much work waiting: try again after the seconds given (answered with `Retry-After`).
    #[error("busy: {message}; retry after {retry_after} s")]
    Busy { message: String, retry_after: u64 },
    /// A rate limit: try again after the seconds given (answered with `Retry-After`).
    #[error("rate limited: {message}; retry after {retry_after} s")]
    RateLimited { message: String, retry_after: u64 },
    #[error("internal error: {0}")]
    Internal(String),
}

impl ApiError {
    pub fn code(&self) -> ErrorCode {
        match self {
            ApiError::UnknownTask(_) | ApiError::VersionNotFound { .. } | ApiError::NotFound(_) => ErrorCode::NotFound,
            ApiError::InvalidArgument(_) | ApiError::InvalidUpload(_) => ErrorCode::InvalidArgument,
            ApiError::UploadTooLarge { .. } => ErrorCode::PayloadTooLarge,
            ApiError::RangeNotSatisfiable { .. } => ErrorCode::RangeNotSatisfiable,
            ApiError::Unauthenticated | ApiError::UserUnauthenticated | ApiError::UnknownUserToken => {
                ErrorCode::Unauthenticated
            }
            ApiError::AlreadyExists(_) => ErrorCode::AlreadyExists,
            ApiError::RateLimited { .. } => ErrorCode::ResourceExhausted,
            ApiError::Busy { .. } => ErrorCode::Unavailable,
            ApiError::PermissionDenied | ApiError::Forbidden(_) => ErrorCode::PermissionDenied,
            // A failed write whose cause is a full disk, wherever it was raised (a file, the object store, the
            // database, the converter process, which reports in text): the client is told what it is.
            ApiError::Internal(m) | ApiError::Unavailable(m) if storage_full(m) => ErrorCode::InsufficientStorage,
            ApiError::Unavailable(_) => ErrorCode::Unavailable,
            ApiError::Internal(_) => ErrorCode::Internal,
        }
    }

    pub fn internal(e: impl std::fmt::Display) -> Self {
        ApiError::Internal(e.to_string())
    }

    /// The message a client reads: for a full disk, what that means for it first, then the underlying error.
    fn message(&self) -> String {
        match self.code() {
            ErrorCode::InsufficientStorage => format!(
                "insufficient storage: the server's disk is full, so nothing was written; try again after \
                 {STORAGE_RETRY_AFTER_SECONDS} s, or ask its operator to free space ({self})"
            ),
            _ => self.to_string(),
        }
    }

    fn body(&self) -> ErrorBody<'_> {
        ErrorBody {
            error: ErrorDetail {
                code: self.code(),
                message: self.message(),
                suggestions: match self {
                    ApiError::UnknownTask(u) => &u.suggestions,
                    _ => &[],
                },
            },
        }
    }
}

#[derive(Serialize)]
struct ErrorBody<'a> {
    error: ErrorDetail<'a>,
}

#[derive(Serialize)]
struct ErrorDetail<'a> {
    code: ErrorCode,
    message: String,
    #[serde(skip_serializing_if = "<[String]>::is_empty")]
    suggestions: &'a [String],
}

/// How long a client is asked to wait after a full disk (`Retry-After`).
pub const STORAGE_RETRY_AFTER_SECONDS: u64 = 60;

/// Whether an error's text says the disk is full: the OS's ENOSPC and EDQUOT, SQLite's SQLITE_FULL, PostgreSQL's
/// `could not extend file`. Matched on text because the errors reach here as text from several layers (the converter
/// is another process, object_store wraps its I/O errors, sqlx the databases').
pub fn storage_full(message: &str) -> bool {
    const SIGNS: &[&str] = &[
        "No space left on device",
        "os error 28",
        "Disk quota exceeded",
        "os error 122",
        "database or disk is full",
        "could not extend file",
    ];
    SIGNS.iter().any(|sign| message.contains(sign))
}

impl From<UnknownTask> for ApiError {
    fn from(e: UnknownTask) -> Self {
        ApiError::UnknownTask(e)
    }
}

impl From<sqlx::Error> for ApiError {
    fn from(e: sqlx::Error) -> Self {
        crate::db::note_failure(&e);
        match e {
            // Every connection stayed busy for the pool's acquire timeout: the server is overloaded (or its cores
            // are taken by other work), and the same request may succeed in a moment. Clients retry "unavailable".
            sqlx::Error::PoolTimedOut => {
                ApiError::Unavailable(format!("database: {e}: the server is overloaded; try again shortly"))
            }
            e => ApiError::Internal(format!("database: {e}")),
        }
    }
}

impl From<object_store::Error> for ApiError {
    fn from(e: object_store::Error) -> Self {
        ApiError::Unavailable(format!("object store: {e}"))
    }
}

impl From<EvaluationError> for ApiError {
    fn from(e: EvaluationError) -> Self {
        match e {
            EvaluationError::NotFound(m) => ApiError::NotFound(m),
            EvaluationError::InvalidArgument(m) => ApiError::InvalidArgument(m),
            EvaluationError::Unavailable(m) => ApiError::Unavailable(m),
            EvaluationError::Internal(m) => ApiError::Internal(m),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let code = self.code();
        if matches!(
            code,
            ErrorCode::Internal | ErrorCode::Unavailable | ErrorCode::InsufficientStorage
        ) {
            tracing::error!(error = %self, "request failed");
        }
        let mut response = (code.http_status(), axum::Json(self.body())).into_response();
        if let ApiError::RangeNotSatisfiable { size } = self {
            let value = HeaderValue::from_str(&format!("bytes */{size}")).expect("ascii header");
            response.headers_mut().insert(header::CONTENT_RANGE, value);
        }
        if code == ErrorCode::Unauthenticated {
            response
                .headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        if let ApiError::Busy { retry_after, .. } | ApiError::RateLimited { retry_after, .. } = self {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(retry_after));
        } else if code == ErrorCode::InsufficientStorage {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(STORAGE_RETRY_AFTER_SECONDS));
        }
        response
    }
}

impl From<ApiError> for tonic::Status {
    fn from(e: ApiError) -> Self {
        let code = e.code();
        if matches!(
            code,
            ErrorCode::Internal | ErrorCode::Unavailable | ErrorCode::InsufficientStorage
        ) {
            tracing::error!(error = %e, "gRPC request failed");
        }
        let mut status = tonic::Status::new(code.grpc_code(), e.message());
        status
            .metadata_mut()
            .insert("dsrl-error-code", code.as_str().parse().expect("ascii metadata"));
        status
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_code_maps_to_a_distinct_http_status_and_a_matching_grpc_code() {
        let mut seen = std::collections::HashSet::new();
        for code in ErrorCode::ALL {
            assert!(seen.insert(code.http_status()), "{code:?} shares its HTTP status");
            let http = code.http_status().as_u16();
            let grpc = code.grpc_code();
            // Client errors are never reported as server faults, and the reverse.
            assert_eq!(
                http >= 500,
                matches!(grpc, tonic::Code::Internal | tonic::Code::Unavailable),
                "{code:?}"
            );
            assert_eq!(serde_json::to_value(code).unwrap(), code.as_str());
        }
    }

    /// A real pool of one SQLite connection, held while a second request waits past the acquire timeout.
    #[tokio::test]
    async fn a_database_pool_that_times_out_is_unavailable_not_internal() {
        let pool = sqlx::sqlite::SqlitePoolOptions::new()
            .max_connections(1)
            .acquire_timeout(std::time::Duration::from_millis(50))
            .connect("sqlite::memory:")
            .await
            .unwrap();
        let _held = pool.acquire().await.unwrap();
        let err = ApiError::from(pool.acquire().await.unwrap_err());
        assert_eq!(err.code(), ErrorCode::Unavailable, "{err}");
        assert_eq!(tonic::Status::from(err).code(), tonic::Code::Unavailable);
        // Other database errors stay the server's fault.
        assert_eq!(ApiError::from(sqlx::Error::RowNotFound).code(), ErrorCode::Internal);
    }

    #[test]
    fn unknown_task_renders_suggestions_over_both_protocols() {
        let err = ApiError::from(UnknownTask {
            id: "AntRun".into(),
            suggestions: vec!["OfflineAntRun-v0".into()],
        });
        let body = serde_json::to_value(err.body()).unwrap();
        assert_eq!(body["error"]["code"], "not_found");
        assert_eq!(body["error"]["suggestions"][0], "OfflineAntRun-v0");
        let status = tonic::Status::from(err);
        assert_eq!(status.code(), tonic::Code::NotFound);
        assert!(status.message().contains("did you mean OfflineAntRun-v0"));
        assert_eq!(status.metadata().get("dsrl-error-code").unwrap(), "not_found");
    }

    #[test]
    fn a_full_disk_is_insufficient_storage_with_a_retry_whatever_layer_raised_it() {
        for error in [
            ApiError::internal(std::io::Error::from_raw_os_error(28)),
            ApiError::Internal("database: error returned from database: (code: 13) database or disk is full".into()),
            ApiError::Unavailable("object store: Generic LocalFileSystem error: No space left on device".into()),
        ] {
            assert_eq!(error.code(), ErrorCode::InsufficientStorage, "{error}");
            let message = error.message();
            assert!(
                message.starts_with("insufficient storage: the server's disk is full"),
                "{message}"
            );
            let response = error.into_response();
            assert_eq!(response.status(), StatusCode::INSUFFICIENT_STORAGE);
            assert_eq!(response.headers()[header::RETRY_AFTER], "60");
        }
        assert_eq!(ApiError::internal("disk I/O error").code(), ErrorCode::Internal);
    }

    #[test]
    fn range_errors_carry_the_size() {
        let response = ApiError::RangeNotSatisfiable { size: 42 }.into_response();
        assert_eq!(response.status(), StatusCode::RANGE_NOT_SATISFIABLE);
        assert_eq!(response.headers()[header::CONTENT_RANGE], "bytes */42");
    }
}
