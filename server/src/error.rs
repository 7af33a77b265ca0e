//! The service's one error type and its one mapping to gRPC status codes.
//!
//! Status codes are API: they are decided here, in a single exhaustive match, and nowhere
//! else. Internal errors are logged with their full chain and reach the client as a short
//! message with a correlation id, never as a backtrace or a file path.
//!
//! Messages stay short: a value the client sent is quoted with [`quote`] or [`brief`] (an
//! escaped prefix, never the whole value), and every status message is cut at
//! [`MAX_MESSAGE_BYTES`] as a backstop, because C-core gRPC clients turn an answer whose
//! metadata passes about 8 KiB into RESOURCE_EXHAUSTED. [`wire`] applies the same rules to the
//! statuses that tonic and the other layers make themselves (an oversized message, a status
//! from the security layer).

pub mod wire;

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

/// Most bytes of a status message; longer ones are cut (at a character boundary) and marked.
pub const MAX_MESSAGE_BYTES: usize = 1024;
/// Most characters of a client's value that a message quotes.
pub const QUOTE_CHARS: usize = 48;

/// A client-supplied string for an error message: single-quoted, escaped (control and
/// non-ASCII characters as `\u{..}`), and cut after [`QUOTE_CHARS`] characters with its full
/// length said, so that no input can make a message long or unprintable.
pub fn quote(value: &str) -> String {
    let mut chars = value.chars();
    let head: String = chars.by_ref().take(QUOTE_CHARS).collect();
    let escaped = head.escape_default();
    if chars.next().is_none() { format!("'{escaped}'") } else { format!("'{escaped}...' ({} bytes)", value.len()) }
}

/// A client-supplied value that is not a string (a shape, a list) in its `Debug` form, cut
/// like [`quote`]'s strings.
pub fn brief(value: &impl std::fmt::Debug) -> String {
    let text = format!("{value:?}");
    if text.chars().count() <= QUOTE_CHARS {
        return text;
    }
    let head: String = text.chars().take(QUOTE_CHARS).collect();
    format!("{}... ({} characters)", head.escape_default(), text.len())
}

/// `message` cut to at most [`MAX_MESSAGE_BYTES`] (with the cut marked): the last guard
/// before a message goes on the wire.
pub fn bounded(mut message: String) -> String {
    if message.len() <= MAX_MESSAGE_BYTES {
        return message;
    }
    const MARK: &str = " ... (message cut)";
    let mut end = MAX_MESSAGE_BYTES - MARK.len();
    while !message.is_char_boundary(end) {
        end -= 1;
    }
    message.truncate(end);
    message.push_str(MARK);
    message
}

impl Error {
    pub fn invalid(msg: impl Into<String>) -> Self {
        Self::InvalidArgument(msg.into())
    }

    /// The error a broken inbound stream (client streaming) stands for: a message over the
    /// size limit is RESOURCE_EXHAUSTED naming the setting (as [`wire`] answers for unary
    /// calls), any other failure to read or decode a frame INVALID_ARGUMENT naming `field`.
    pub fn from_inbound(field: &str, status: &tonic::Status) -> Self {
        match wire::message_too_large(status) {
            Some(too_large) => Self::ResourceExhausted(too_large),
            None => Self::InvalidArgument(format!(
                "{field}: a message of the stream could not be read: {}",
                status.message()
            )),
        }
    }

    pub fn internal(context: &str, err: impl std::fmt::Display) -> Self {
        Self::Internal(anyhow::anyhow!("{context}: {err}"))
    }
}

/// A document or message the shared schema (`relreward_proto::schema`) refused: its message
/// names the field.
impl From<relreward_proto::schema::Invalid> for Error {
    fn from(e: relreward_proto::schema::Invalid) -> Self {
        Self::InvalidArgument(e.0)
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

/// An error with its causes (the wire crate's, shared with the client so both ends word them alike).
pub use relreward_proto::error_chain;

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
        Status::new(code, bounded(msg))
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
    fn quoted_values_are_short_and_escaped() {
        assert_eq!(quote("abc"), "'abc'");
        assert_eq!(quote("a\nb\u{7}é"), "'a\\nb\\u{7}\\u{e9}'");
        let long = "x".repeat(10_000);
        let q = quote(&long);
        assert!(q.len() < 80 && q.contains("(10000 bytes)"), "{q}");
        let exact = "y".repeat(QUOTE_CHARS);
        assert_eq!(quote(&exact), format!("'{exact}'"));
        let b = brief(&vec![1u64; 100_000]);
        assert!(b.len() < 100 && b.contains("characters)"), "{b}");
        assert_eq!(brief(&[2, 3]), "[2, 3]");
    }

    #[test]
    fn every_message_is_bounded() {
        let s = Status::from(Error::invalid("é".repeat(1 << 20)));
        assert!(s.message().len() <= MAX_MESSAGE_BYTES, "{}", s.message().len());
        assert!(s.message().ends_with("(message cut)"));
        assert_eq!(bounded("short".into()), "short");
    }

    #[test]
    fn internal_errors_hide_details() {
        let s = Status::from(Error::internal("opening /secret/path", "permission denied"));
        assert_eq!(s.code(), Code::Internal);
        assert!(!s.message().contains("/secret/path"), "{}", s.message());
        assert!(s.message().starts_with("internal error (id "));
    }
}
