//! Every way a simulator request can fail, and the one place each maps to a gRPC code.

use tonic::{Code, Status};

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("unknown task {id:?}{}", suggest(.suggestions))]
    UnknownTask { id: String, suggestions: Vec<String> },
    #[error("{0}")]
    InvalidArgument(String),
    #[error("{0}")]
    FailedPrecondition(String),
    #[error("{0}")]
    ResourceExhausted(String),
    /// The simulator raised; the message carries its exception.
    #[error("simulator error: {0}")]
    Simulator(String),
    /// The worker cannot host simulators at all (missing environment, broken install).
    #[error("{0}")]
    Setup(String),
}

fn suggest(suggestions: &[String]) -> String {
    if suggestions.is_empty() {
        String::new()
    } else {
        format!("; did you mean {}?", suggestions.join(", "))
    }
}

impl SimError {
    pub fn code(&self) -> Code {
        match self {
            SimError::UnknownTask { .. } => Code::NotFound,
            SimError::InvalidArgument(_) => Code::InvalidArgument,
            SimError::FailedPrecondition(_) => Code::FailedPrecondition,
            SimError::ResourceExhausted(_) => Code::ResourceExhausted,
            SimError::Simulator(_) => Code::Internal,
            SimError::Setup(_) => Code::Unavailable,
        }
    }
}

impl From<SimError> for Status {
    fn from(err: SimError) -> Status {
        Status::new(err.code(), err.to_string())
    }
}
