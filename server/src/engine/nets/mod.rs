//! Native network architectures, built on tch's `nn` variables with PyTorch-compatible
//! parameter names so that weights move between this service and PyTorch as safetensors.
//!
//! - [`blocks`]: Diffuser's building blocks (sinusoidal embedding, Mish, Conv1dBlock,
//!   ResidualTemporalBlock, Down/Upsample1d, time MLP), shared with the reward networks;
//!   `blocks::second_order`, their tangents and second-order reverses, by which the
//!   convolutional rewards train without autograd.
//! - [`temporal_unet`]: Diffuser's TemporalUnet over trajectories [B, H, D].
//! - [`mlp`]: an MLP denoiser over samples of any shape.
//! - [`unet2d`]: diffusers' `UNet2DModel` over images [B, C, H, W], with diffusers' parameter
//!   names (checked against diffusers itself by `server/tests/unet2d_vs_diffusers.rs`).
//! - [`reward`]: [`RewardNet`], the relative reward network rho(x, t) with its input gradient
//!   and training's parameter gradients of the alignment loss; one file per
//!   architecture (windowed MLP, Diffuser's ValueFunction, a strided 2D conv encoder, a flat
//!   MLP) under `reward/`.
//! - [`native`]: [`NativeDenoiser`], the [`super::denoiser::Denoiser`] over either network.
//! - [`weights`]: [`weights::Weights`], a network's variables built against its planned
//!   parameter count, strict safetensors loading and atomic saving, shared by every network.
//! - [`inputs`]: the (x, t) shape and dtype check of every network's forward pass.
//! - [`kernels`]: Mish and its derivatives fused by hand into one loop over float32 CPU
//!   memory, for the passes nobody differentiates and the reward's closed form.
//!
//! `relreward_dev.nets` (`dev/python`) is an independent PyTorch implementation of the same
//! networks; `server/tests/nets_vs_pytorch.rs` checks that both agree on the same weights,
//! through the driver `tests/python/nets_reference.py` (`relreward_dev.reward_nets` and
//! `reward_nets_vs_pytorch.rs` for the reward networks).

pub mod blocks;
pub mod inputs;
pub mod kernels;
pub mod mlp;
pub mod native;
pub mod reward;
pub mod temporal_unet;
pub mod unet2d;
pub mod weights;

pub use native::NativeDenoiser;
pub use reward::{RewardArchitecture, RewardNet};

use std::cell::Cell;
use std::thread::LocalKey;

/// Runs `f` with this thread's `flag` set, restoring its previous value however `f` ends (a
/// return, an error, a panic): the scope of a building or tracing mode that layers and kernels
/// read without it being passed through every call (`weights::first_values`,
/// `kernels::with_libtorch_ops`).
fn with_flag_set<R>(flag: &'static LocalKey<Cell<bool>>, f: impl FnOnce() -> R) -> R {
    struct Restore(&'static LocalKey<Cell<bool>>, bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            self.0.with(|cell| cell.set(self.1));
        }
    }
    let _restore = Restore(flag, flag.with(|cell| cell.replace(true)));
    f()
}
