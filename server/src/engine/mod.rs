//! Tensor computation on libtorch (through tch). Knows tch, never tonic.
//!
//! Module map:
//! - [`data`]: training batches (sub-trajectories within episodes) from a dataset.
//! - [`rng`]: the engine's own seedable, checkpointable random stream.
//! - [`normalizer`]: raw units <-> normalized units, with the Jacobian for gradients.
//! - [`manifest`]: what a diffusion model is (parametrization, schedule, layout, normalizer).
//! - [`schedule`]: DDPM beta schedules and every derived quantity, in float64.
//! - [`denoiser`]: the [`denoiser::Denoiser`] trait: (x_t, t) -> eps or x0 prediction.
//! - [`diffusion`]: [`diffusion::DiffusionModel`]: x0_hat, eps_hat, posterior mean and variance,
//!   score, forward process.
//! - [`sampling`]: ancestral sampling with inpainting conditions and classifier guidance.
//! - [`optim`]: Adam and EMA whose state checkpoints can hold.
//! - [`relative_reward`]: the gradient-alignment objective of Algorithm 1.
//! - [`nets`]: native architectures (TemporalUnet, MLP denoiser) with safetensors weights.
//! - [`torchscript`]: [`torchscript::TorchScriptDenoiser`], an uploaded TorchScript module as a
//!   denoiser, validated against its manifest by one forward pass.
//! - [`reward_model`]: [`reward_model::RewardModel`], a stored reward as served: rho over
//!   normalized inputs (with Algorithm 2's per-step standardisation), its gradient.
//! - [`registry`]: [`registry::ModelRegistry`], stored diffusion and reward models loaded on
//!   demand, integrity-checked (sha256) and cached in memory up to `models.cache_bytes` (LRU).

pub mod data;
pub mod denoiser;
pub mod diffusion;
pub mod manifest;
pub mod nets;
pub mod normalizer;
pub mod optim;
pub mod registry;
pub mod relative_reward;
pub mod reward_model;
pub mod rng;
pub mod sampling;
pub mod schedule;
pub mod torchscript;

use crate::config::EngineConfig;

/// Configures libtorch's thread pool once at start, before any tensor work, and reports what
/// the process runs on.
pub fn init(config: &EngineConfig) {
    let threads = match config.intra_op_threads {
        0 => std::thread::available_parallelism().map_or(1, usize::from),
        n => n,
    };
    tch::set_num_threads(i32::try_from(threads).unwrap_or(1));
    tracing::info!(intra_op_threads = tch::get_num_threads(), cuda = tch::Cuda::is_available(), "libtorch initialised");
}
