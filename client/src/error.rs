//! Client errors and the CLI's documented exit codes.

use serde::Deserialize;

/// Exit codes of `dsrl-client`, documented in `--help`.
pub mod exit {
    pub const OK: u8 = 0;
    pub const FAILURE: u8 = 1;
    pub const USAGE: u8 = 2;
    /// A download did not match its sha256, or `verify` found (and removed) corrupt files.
    pub const INTEGRITY: u8 = 3;
    pub const NOT_FOUND: u8 = 4;
    /// The server could not be reached or failed (5xx).
    pub const UNAVAILABLE: u8 = 5;
    /// The server rejected the request as invalid (400, 413, 416).
    pub const REJECTED: u8 = 6;
    /// Missing or wrong admin token (401, 403).
    pub const UNAUTHORIZED: u8 = 7;
    /// The server queued the work and has not done it yet (`watch` without `--wait`): run the command again.
    pub const PENDING: u8 = 8;
}

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server answered with an error document.
    #[error("{message}")]
    Server {
        status: u16,
        code: String,
        message: String,
        suggestions: Vec<String>,
    },
    #[error("cannot reach the dsrl server at {url}: {source}")]
    Unreachable { url: String, source: reqwest::Error },
    /// The server was reached but did not answer in time (it may still be working).
    #[error("the dsrl server at {url} did not answer within {seconds} s: {what}")]
    Timeout { url: String, seconds: u64, what: String },
    #[error("integrity check failed: {0}")]
    Integrity(String),
    #[error("{context}: {source}")]
    Io { context: String, source: std::io::Error },
    /// The server's answer is not what the protocol says.
    #[error("unexpected answer from the server: {0}")]
    Protocol(String),
    #[error("{0}")]
    Usage(String),
    #[error("the file has {size} bytes, more than the server's upload limit of {limit} bytes")]
    TooLarge { size: u64, limit: u64 },
    #[error("converting to HDF5: {0}")]
    Conversion(String),
}

impl ClientError {
    pub fn io(context: impl Into<String>) -> impl FnOnce(std::io::Error) -> ClientError {
        let context = context.into();
        move |source| ClientError::Io { context, source }
    }

    pub fn exit_code(&self) -> u8 {
        match self {
            ClientError::Server { status, .. } => match status {
                404 => exit::NOT_FOUND,
                401 | 403 => exit::UNAUTHORIZED,
                400..=499 => exit::REJECTED,
                _ => exit::UNAVAILABLE,
            },
            ClientError::Unreachable { .. } | ClientError::Timeout { .. } => exit::UNAVAILABLE,
            ClientError::Integrity(_) => exit::INTEGRITY,
            ClientError::Usage(_) => exit::USAGE,
            ClientError::TooLarge { .. } => exit::REJECTED,
            ClientError::Io { .. } | ClientError::Protocol(_) | ClientError::Conversion(_) => exit::FAILURE,
        }
    }

    /// Machine-readable form for `--json`.
    pub fn to_json(&self) -> serde_json::Value {
        let (code, suggestions) = match self {
            ClientError::Server { code, suggestions, .. } => (code.as_str(), suggestions.clone()),
            ClientError::Unreachable { .. } => ("unreachable", vec![]),
            ClientError::Timeout { .. } => ("timeout", vec![]),
            ClientError::Integrity(_) => ("integrity", vec![]),
            ClientError::Io { .. } => ("io", vec![]),
            ClientError::Protocol(_) => ("protocol", vec![]),
            ClientError::Usage(_) => ("usage", vec![]),
            ClientError::TooLarge { .. } => ("payload_too_large", vec![]),
            ClientError::Conversion(_) => ("conversion", vec![]),
        };
        serde_json::json!({"error": {"code": code, "message": self.to_string(), "suggestions": suggestions,
                                     "exit_code": self.exit_code()}})
    }
}

/// The server's error document: `{"error": {"code", "message", "suggestions"?}}`.
#[derive(Debug, Deserialize)]
pub(crate) struct ErrorDocument {
    pub error: ErrorDetail,
}

#[derive(Debug, Deserialize)]
pub(crate) struct ErrorDetail {
    pub code: String,
    pub message: String,
    #[serde(default)]
    pub suggestions: Vec<String>,
}
