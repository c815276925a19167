//! What can go wrong in a simulator session, and so while playing a policy on one (`dsrl-evaluation` uses the same
//! kinds as `EvaluationError`). The service maps each kind to its own `ApiError` (one `From` in
//! `service/src/error.rs`), so the status table stays in one place.

#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum SimulatorError {
    /// Something the caller named does not exist (a worker answered NOT_FOUND).
    #[error("{0}")]
    NotFound(String),
    /// The policy or the request is not valid for the task; the message says what differs.
    #[error("{0}")]
    InvalidArgument(String),
    /// No worker could take the session, or one died or timed out under it: worth retrying elsewhere.
    #[error("{0}")]
    Unavailable(String),
    #[error("{0}")]
    Internal(String),
}
