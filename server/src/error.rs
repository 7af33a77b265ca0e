//! The service's one error type and its one mapping to gRPC status codes.
//!
//! Status codes are API: they are decided here, in a single exhaustive match, and nowhere
//! else. Internal errors are logged with their full chain and reach the client as a short
//! message with a correlation id, never as a backtrace or a file path.

use tonic::{Code, Status};

pub type Result<T, E = Error> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The request is malformed; the message names the field and the problem.
    #[error("{0}")]
    InvalidArgument(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    AlreadyExists(String),
    /// A quota, a size limit or a full queue.
    #[error("{0}")]
    ResourceExhausted(String),
    /// The request is valid but the system is not in a state to run it.
    #[error("{0}")]
    FailedPrecondition(String),
    /// Part of the v1 contract that this server does not implement yet.
    #[error("{0}")]
    Unimplemented(String),
    /// The server is shutting down.
    #[error("{0}")]
    Unavailable(String),
    /// The caller's deadline passed before the work was done (it was then not started).
    #[error("{0}")]
    DeadlineExceeded(String),
    /// Stored data failed an integrity check.
    #[error("{0}")]
    DataLoss(String),
    /// Anything else: a bug or an environment failure (disk, database).
    #[error(transparent)]
    Internal(#[from] anyhow::Error),
}

impl Error {
    pub fn invalid(msg: impl Into<String>) -> Self {
        Self::InvalidArgument(msg.into())
    }

    pub fn internal(context: &str, err: impl std::fmt::Display) -> Self {
        Self::Internal(anyhow::anyhow!("{context}: {err}"))
    }
}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        Self::Internal(anyhow::Error::new(e))
    }
}

impl From<tch::TchError> for Error {
    fn from(e: tch::TchError) -> Self {
        Self::Internal(anyhow::Error::new(e).context("libtorch"))
    }
}

impl From<rusqlite::Error> for Error {
    fn from(e: rusqlite::Error) -> Self {
        Self::Internal(anyhow::Error::new(e).context("metadata database"))
    }
}

/// An error with its causes (the client library's, so both ends word them alike).
pub use relreward_client::error_chain;

impl From<tokio_postgres::Error> for Error {
    fn from(e: tokio_postgres::Error) -> Self {
        // No SQLSTATE: the connection failed or closed (the database is down or unreachable),
        // which a client may retry; a statement the database refused is a bug.
        if e.code().is_none() {
            Self::Unavailable(format!("metadata database unreachable: {e}"))
        } else {
            Self::Internal(anyhow::Error::new(e).context("metadata database"))
        }
    }
}

impl From<Error> for Status {
    fn from(e: Error) -> Self {
        let (code, msg) = match e {
            Error::InvalidArgument(m) => (Code::InvalidArgument, m),
            Error::NotFound(m) => (Code::NotFound, m),
            Error::AlreadyExists(m) => (Code::AlreadyExists, m),
            Error::ResourceExhausted(m) => (Code::ResourceExhausted, m),
            Error::FailedPrecondition(m) => (Code::FailedPrecondition, m),
            Error::Unimplemented(m) => (Code::Unimplemented, m),
            Error::Unavailable(m) => (Code::Unavailable, m),
            Error::DeadlineExceeded(m) => (Code::DeadlineExceeded, m),
            Error::DataLoss(m) => (Code::DataLoss, m),
            Error::Internal(err) => {
                let id = uuid::Uuid::new_v4().simple().to_string();
                let id = &id[..12];
                tracing::error!(error_id = id, error = ?err, "internal error");
                (Code::Internal, format!("internal error (id {id}; details in the server log)"))
            }
        };
        Status::new(code, msg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_and_messages_pass_through() {
        let s = Status::from(Error::invalid("header.name: bad"));
        assert_eq!((s.code(), s.message()), (Code::InvalidArgument, "header.name: bad"));
        assert_eq!(Status::from(Error::NotFound("x".into())).code(), Code::NotFound);
        assert_eq!(Status::from(Error::AlreadyExists("x".into())).code(), Code::AlreadyExists);
        assert_eq!(Status::from(Error::ResourceExhausted("x".into())).code(), Code::ResourceExhausted);
        assert_eq!(Status::from(Error::Unimplemented("x".into())).code(), Code::Unimplemented);
    }

    #[test]
    fn internal_errors_hide_details() {
        let s = Status::from(Error::internal("opening /secret/path", "permission denied"));
        assert_eq!(s.code(), Code::Internal);
        assert!(!s.message().contains("/secret/path"), "{}", s.message());
        assert!(s.message().starts_with("internal error (id "));
    }
}
