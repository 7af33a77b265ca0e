//! Rust client for relreward, and the `relreward` command-line tool (feature `cli`).
//!
//! Module map:
//! - [`tensor`]: the wire codec for `relreward.v1.Tensor` (shape + dtype + little-endian bytes).
//!   The server uses the same codec, so both sides agree on what a valid tensor is.
//! - [`client`]: [`Client`], a typed connection to every service, with helpers that hide
//!   streaming details (chunked, digest-checked dataset and model uploads; paging; jobs;
//!   scores, gradients, the gradient stream and guided sampling).
//! - [`watch`]: following a job's events across reconnects (resume bookkeeping, backoff).
//! - [`upload`]: [`UploadSource`], where an upload's array bytes come from, and the chunker.
//! - `eval` (feature `cli`): the paper's evaluation (discriminability, reward heatmaps, goal
//!   recovery) over scores, and its PNG pictures.
//! - `npz` (feature `cli`): reads `.npz`/`.npy` files into an [`UploadSource`].
//! - `npz_write` (feature `cli`): writes `.npz` archives (results of `score`, `grad`, `sample`).
//! - [`maze`]: the built-in Maze2D data generator (D4RL layouts, point mass, waypoint
//!   controller; its `.npz` output needs feature `cli`).
//!
//! The library never links libtorch.

pub mod client;
pub mod maze;
pub mod tensor;
pub mod upload;
pub mod watch;

#[cfg(feature = "cli")]
pub mod eval;
#[cfg(feature = "cli")]
pub mod npz;
#[cfg(feature = "cli")]
pub mod npz_write;

pub use client::{Client, ClientError, error_chain};
pub use relreward_proto::v1 as pb;
pub use upload::{MemorySource, UploadSource};
