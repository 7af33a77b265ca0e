//! The service's user-written documents, defined once for both ends: the diffusion model
//! manifest ([`manifest`], with the bring-your-own reward's), the training job spec ([`job`]),
//! the sampling recipe ([`recipe`]) both a Sample request and a reward job carry, and the
//! autoencoder manifest ([`autoencoder`]).
//!
//! Each document has one set of Rust types, used three ways: as the file a user writes (TOML or
//! JSON, [`parse_text`]), as what the server stores (serde JSON, every field explicit), and as
//! the proto message on the wire (conversions both ways here). Its defaults are stated once,
//! as constants beside the types (the paper's and Diffuser's settings, with where they come
//! from), and its checks are one `validate` per document whose messages name the field at
//! fault. The server adds only what needs its state (a dataset's kind, a stored model's space)
//! or libtorch (building a schedule); the CLI adds only what needs its flags.
//!
//! Everything here is plain data: no tch, no I/O beyond parsing text.

pub mod autoencoder;
pub mod job;
pub mod manifest;
pub mod recipe;
pub mod summary;

/// A document or wire message refused by a check: the message names the field
/// (`manifest.schedule.betas[2]: 1.5 is not in (0, 1)`). The server answers it as
/// INVALID_ARGUMENT; the CLI prints it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Invalid(pub String);

/// `Err(Invalid(message))`.
pub(crate) fn invalid<T>(message: impl Into<String>) -> Result<T, Invalid> {
    Err(Invalid(message.into()))
}

/// A proto enum field's value as `E`; a number the proto does not define is refused, with the
/// accepted values (`expected`) in the message.
pub fn known<E: TryFrom<i32>>(field: &str, raw: i32, expected: &str) -> Result<E, Invalid> {
    E::try_from(raw).map_err(|_| Invalid(format!("{field}: unknown value {raw}; expected {expected}")))
}

/// Which text form a document is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Toml,
    Json,
}

impl Format {
    /// JSON for a `.json` name, TOML for a `.toml` name, otherwise JSON when the text starts
    /// with `{` (a manifest sent as a string, a file without an extension).
    pub fn guess(name: Option<&str>, text: &str) -> Self {
        let ext = name.and_then(|n| n.rsplit_once('.')).map(|(_, e)| e.to_ascii_lowercase());
        match ext.as_deref() {
            Some("json") => Self::Json,
            Some("toml") => Self::Toml,
            _ if text.trim_start().starts_with('{') => Self::Json,
            _ => Self::Toml,
        }
    }
}

/// Parses a document of type `T` from TOML or JSON; errors carry the parser's line and column
/// and the field (`unknown field `extra``), prefixed with `what` (a file's path, "manifest").
pub fn parse_text<T: serde::de::DeserializeOwned>(text: &str, format: Format, what: &str) -> Result<T, Invalid> {
    match format {
        Format::Json => serde_json::from_str(text).map_err(|e| Invalid(format!("{what} (JSON): {e}"))),
        Format::Toml => {
            toml::from_str(text).map_err(|e| Invalid(format!("{what} (TOML): {}", e.to_string().trim_end())))
        }
    }
}

/// u32 on the wire from a usize held here (values past u32 were refused when they came in).
pub(crate) fn wire_u32(v: usize) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}

pub(crate) fn wire_u32s(v: &[usize]) -> Vec<u32> {
    v.iter().map(|&x| wire_u32(x)).collect()
}

pub(crate) fn usizes(v: &[u32]) -> Vec<usize> {
    v.iter().map(|&x| x as usize).collect()
}

/// A list from the wire, or `default` when the wire left it empty (an unset repeated field).
pub(crate) fn or_default(v: &[u32], default: &[usize]) -> Vec<usize> {
    if v.is_empty() { default.to_vec() } else { usizes(v) }
}
