//! `relreward score`, `relreward grad` and `relreward sample`: the RewardService from the
//! command line, one module per command ([`score`], [`grad`], [`sample`]) over what they share:
//! reading inputs ([`input`]) and handling answers ([`results`]).
//!
//! Inputs of `score` and `grad` (`--input`) are read whole into memory:
//! - an array of items `[B, *item_shape]` (`x` by default, another with `--key`; float32 or
//!   float64), whose item shape must be the reward model's `input_shape`;
//! - or a D4RL-style trajectories archive (`observations`, `actions`, optional `terminals`,
//!   `timeouts`, `episode_starts`), cut into the model's `[H, D]` windows ([`Windows`]): rows
//!   are `[action | observation]` as in Diffuser, a window is H consecutive rows of one episode,
//!   and windows start every `--stride` rows.
//!
//! Items go to the server in requests of `--batch` (two in flight), lowered when needed so that
//! one request stays under [`input::MAX_REQUEST_BYTES`]. Results are written with `--out` as an `.npz`
//! ([`relreward_toolkit::npz_write`]) and summarised as text or, with `--json`, one document.

pub mod grad;
pub mod input;
pub mod results;
pub mod sample;
pub mod score;

pub use grad::{GradArgs, grad};
pub use input::{InputArgs, UnitsArg};
pub(crate) use input::{Items, batches, read_items, request_batch};
pub(crate) use results::{IN_FLIGHT, floats, item_bar, request_error, summarize};
pub use sample::{SampleArgs, sample};
pub use score::{ScoreArgs, score};
