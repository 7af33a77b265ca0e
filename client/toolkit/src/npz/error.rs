//! The reader's errors and the pieces of its messages: [`NpzError`] (the file and what is wrong
//! with it, for opening), `InvalidData` I/O errors (for bytes found wrong while sending), and how
//! an array is named when the file's key differs from the name it is sent under.

use std::io;
use std::path::{Path, PathBuf};

/// Why a file cannot be uploaded: the file and what is wrong with it.
#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct NpzError {
    pub path: PathBuf,
    pub message: String,
}

impl NpzError {
    pub(super) fn new(path: &Path, message: impl Into<String>) -> Self {
        Self { path: path.to_owned(), message: message.into() }
    }
}

pub type Result<T, E = NpzError> = std::result::Result<T, E>;

/// An `InvalidData` I/O error: what a reader returns for bytes that break the format.
pub(super) fn invalid_data(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, message)
}

/// `'terminations' (sent as 'terminals')` or just `'observations'`.
pub(super) fn describe_key(key: &str, name: &str) -> String {
    if key == name { format!("'{key}'") } else { format!("'{key}' (sent as '{name}')") }
}
