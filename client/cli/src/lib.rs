//! The library of the `relreward` command line: the operations its commands run, as functions
//! with typed inputs and results, so that tests and other programs (and the commands that
//! compose others, `extract` and `demo`) call them instead of command lines. The binary
//! (`main.rs`, with one thin module per command family in `commands/`) parses flags into these
//! inputs and prints the results as text or JSON.
//!
//! Module map (imports point down this list, never up):
//! - [`ops`]: the operations: upload or reuse a dataset, submit a job and wait for it on the
//!   client's watch, the paper's evaluation (discriminability, heatmap with goal recovery, a
//!   job's loss plot), `extract`'s pipeline and report, the demo's steering. Progress goes to
//!   an [`ops::Progress`] the caller provides.
//! - [`train`]: the job spec files and the `train` flags, and the rules that turn them into a
//!   `JobSpec` (what `extract` builds its jobs with, too).
//! - [`manifest`]: the diffusion model manifest file (TOML or JSON), to and from the proto.
//! - [`output`]: formatting shared by the commands and the operations: JSON and text, number
//!   and time formats, progress bars, terminal writes that never panic.
//! - [`error`]: [`UsageError`], a request that parses but cannot run (exit status 2).
//!
//! The connection is `relreward-client`; file formats, the maze generator and the evaluation's
//! math and pictures are `relreward-toolkit` (which asks for rewards through its
//! `eval::scorer::Scorer`, implemented here by [`ops::scoring::ServerScorer`]).

pub mod error;
pub mod manifest;
pub mod ops;
pub mod output;
pub mod train;

pub use error::UsageError;
