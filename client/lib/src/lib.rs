//! Typed Rust client library for relreward (tonic only: no file formats, no command line).
//!
//! Module map (imports point down this list, never up):
//! - [`client`]: [`Client`], one connection to every service (endpoint, TLS, token), with
//!   helpers that hide streaming details (chunked, digest-checked dataset and model uploads;
//!   paging; jobs; scores, gradients, the gradient stream and guided sampling; Encode and
//!   Decode through an autoencoder); reads are
//!   retried over a broken connection.
//! - [`download`]: writing a `DownloadModel` stream into a directory, every file checked
//!   against its size and sha256 before any is put in place.
//! - [`watch`]: following a job's events across reconnects (resume bookkeeping, the loop).
//! - [`retry`]: the retry policy, backoff and which failures are worth a retry; used by both
//!   of the above.
//! - [`upload`]: the chunker that cuts an upload into messages; [`UploadSource`] (where an
//!   upload's array bytes come from) and [`MemorySource`] are `relreward-proto`'s, re-exported.
//! - [`tensor`]: the `relreward.v1.Tensor` codec, re-exported from `relreward-proto` (the
//!   wire contract lives there, shared with the server).
//!
//! File formats, the Maze2D generator and evaluation are in `relreward-toolkit`; the
//! `relreward` command line is `relreward-cli`. The library never links libtorch.

pub mod client;
pub mod download;
pub mod retry;
pub mod upload;
pub mod watch;

pub use client::{Client, ClientError};
pub use download::DownloadedModel;
pub use relreward_proto::v1 as pb;
pub use relreward_proto::{error_chain, given_number, tensor};
pub use upload::{MemorySource, UploadSource};
