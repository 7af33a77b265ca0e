//! [`UsageError`]: a request that parses but cannot be run as given. Both the operations and
//! the commands raise it; `main` turns it into exit status 2, like clap's own usage errors.

use std::fmt;

/// A command line (or an operation's input) that parses but cannot be run as given (exit
/// status 2, like clap's errors).
#[derive(Debug)]
pub struct UsageError(pub String);

impl fmt::Display for UsageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}
