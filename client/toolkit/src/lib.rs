//! The relreward research toolkit: what the `relreward` CLI and the end-to-end tests (and
//! benchmarks, as they need it) share besides the client itself. It opens no connection and never links libtorch;
//! it uses the client library only for [`relreward_client::UploadSource`].
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
