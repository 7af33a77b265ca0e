//! Evaluation of extracted rewards, as the paper reports it, computed on the client from the
//! server's scores (pure Rust, no libtorch):
//!
//! - [`discriminate`]: discriminability (section 5.1, "Discriminability Results"): a logistic
//!   regression ([`logistic`]) on the scalar reward separating held-out base and expert
//!   trajectories;
//! - [`heatmap`]: the Maze2D reward heatmap (Figure 2, section 5.1 "Visualization of Learned
//!   Reward Functions") and goal recovery (appendix "Quantitative Evaluation in Maze2D");
//! - [`plot`]: the pictures: heatmaps, loss curves, reward histograms (PNG);
//! - [`stats`]: percentiles, winsorization, min-max scaling, a seedable random stream;
//! - [`scorer`]: where the rewards come from ([`scorer::Scorer`], implemented by the CLI's
//!   operations over the server's `Score`) and the batched, ordered scoring of every item.
//!
//! Each module's documentation quotes the passages of the paper its protocol follows. The CLI's
//! operations (`relreward_cli::ops::evaluate`) feed these with scores from `Score`.

pub mod discriminate;
pub mod heatmap;
pub mod logistic;
pub mod plot;
pub mod scorer;
pub mod stats;
