//! The relreward research toolkit: what the `relreward` CLI, the end-to-end tests and the
//! benchmarks share besides the client itself. No network, no libtorch.
//!
//! Module map:
//! - [`npz`]: reads `.npz`/`.npy` files (D4RL-style trajectories, sample arrays) into an
//!   [`relreward_client::UploadSource`].
//! - [`npz_write`]: writes `.npz` archives (results of `score`, `grad`, `sample`; generated
//!   datasets).
//! - [`maze`]: the built-in Maze2D data generator (D4RL layouts, point mass, waypoint
//!   controller), written with [`npz_write`].
//! - [`eval`]: the paper's evaluation over scores (discriminability, reward heatmaps, goal
//!   recovery) and its PNG pictures.
//!
//! Data readers for further formats (HDF5, Minari, D4RL) belong beside [`npz`], producing the
//! same [`relreward_client::UploadSource`].

pub mod eval;
pub mod maze;
pub mod npz;
pub mod npz_write;
