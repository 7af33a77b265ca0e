//! The relreward research toolkit: what the `relreward` CLI and the end-to-end tests (and
//! benchmarks, as they need it) share besides the client itself. It opens no connection, never
//! links libtorch and does not depend on the client library: its readers produce the wire
//! contract's [`relreward_proto::upload::UploadSource`], and its evaluation asks for rewards
//! through [`eval::scorer::Scorer`], which the CLI's operations implement over a connection.
//!
//! Module map:
//! - [`npz`]: reads `.npz`/`.npy` files (D4RL-style trajectories, sample arrays) into an
//!   [`relreward_proto::upload::UploadSource`].
//! - [`episodes`]: the rules every reader applies to episode boundaries (flags, start indices,
//!   lengths) and maze walls (`walls` / `wall_map` / `maze_map`).
//! - [`values`]: the rules every reader applies to values: element types (any integer or
//!   float, either byte order) read as float32 and checked finite, shapes as rows, 0/1 flags.
//! - [`trajectories`]: a trajectory dataset in memory, as converting readers produce it; to an
//!   upload or the canonical `.npz`; absorbing terminal states held at rest, and the rule that
//!   finds the velocity coordinates.
//! - [`hdf5`] (feature `hdf5`): D4RL HDF5 files and Minari datasets (`main_data.hdf5`), dict
//!   observations flattened by gymnasium's rule.
//! - [`profile`]: what `extract` measures in the data (episode lengths, motion per row) and
//!   the rule that turns it into a horizon and a reward window.
//! - [`npz_write`]: writes `.npz` archives (results of `score`, `grad`, `sample`; generated
//!   datasets).
//! - [`maze`]: the built-in Maze2D data generator (D4RL layouts, point mass, waypoint
//!   controller; its own physics or MuJoCo PointMaze's), written with [`npz_write`].
//! - [`eval`]: the paper's evaluation over scores (discriminability, reward heatmaps, goal
//!   recovery) and its PNG pictures.
//! - [`diffuser_import`]: a Diffuser `TemporalUnet` state_dict (exported to `.npz`) checked
//!   against the architecture and written as native safetensors weights (`model import`).
//! - [`diffusers_import`]: a folder written by diffusers' `save_pretrained` (`UNet1DModel` in
//!   Diffuser's TemporalUnet configuration, or `UNet2DModel`, with its `DDPMScheduler`), found
//!   by path or in the local Hugging Face cache, checked and converted into native weights and
//!   a manifest (`model import DIR|ORG/NAME`).

pub mod diffuser_import;
pub mod diffusers_import;
pub mod episodes;
pub mod eval;
#[cfg(feature = "hdf5")]
pub mod hdf5;
pub mod maze;
pub mod npz;
pub mod npz_write;
pub mod profile;
pub mod trajectories;
pub mod values;
