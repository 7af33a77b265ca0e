//! Tensor computation on libtorch (through tch). Knows tch, never tonic.
//!
//! Module map:
//! - [`data`]: training batches (sub-trajectories within episodes) from a dataset.
//! - [`rng`]: the engine's own seedable, checkpointable random stream.
//! - [`normalizer`]: raw units <-> normalized units, with the Jacobian for gradients.
//! - [`manifest`]: what a diffusion model is (parametrization, schedule, layout, normalizer).
//! - [`schedule`]: DDPM beta schedules and every derived quantity, in float64.
//! - [`denoiser`]: the [`denoiser::Denoiser`] trait: (x_t, t[, condition]) -> eps, x0 or v
//!   prediction.
//! - [`diffusion`]: [`diffusion::DiffusionModel`]: x0_hat, eps_hat, posterior mean and variance,
//!   score, forward process.
//! - [`sampling`]: DDPM ancestral and DDIM sampling with inpainting conditions and classifier
//!   guidance.
//! - [`recipe`]: how a conditional model's prediction is formed per step: classifier-free
//!   guidance and Safe Latent Diffusion's guidance away from a concept ([`recipe::Recipe`]),
//!   applied to a batch of chains by a [`recipe::RecipeRun`].
//! - [`ddim`]: DDIM's step subset and coefficients, as diffusers' DDIMScheduler forms them.
//! - [`optim`]: Adam and EMA whose state checkpoints can hold.
//! - [`relative_reward`]: the gradient-alignment objective of Algorithm 1.
//! - [`reward_trainer`]: [`reward_trainer::RelativeRewardTrainer`], Algorithms 1 and 2 as one
//!   type a job drives: rho, the frozen models, the training pairs, a step's loss and the
//!   held-out error.
//! - [`target_pool`]: Algorithm 1's amortised targets: a pool of (t, target, point) computed
//!   in big passes, each reused several times, refreshed a fraction per epoch.
//! - [`threads`]: two independent computations (Algorithm 1's base and expert passes) side
//!   by side, one intra-op thread each.
//! - [`nets`]: native architectures (TemporalUnet, MLP denoiser) with safetensors weights.
//! - [`torchscript`]: [`torchscript::TorchScriptDenoiser`], an uploaded TorchScript module as a
//!   denoiser, validated against its manifest by one forward pass.
//! - [`autoencoder`]: [`autoencoder::TorchScriptAutoencoder`], an uploaded encoder/decoder
//!   between images and (scaled) latents, validated by one call of each method.
//! - [`reward_model`]: [`reward_model::RewardModel`], a stored reward as served: rho over
//!   normalized inputs (with Algorithm 2's per-step standardisation), its gradient.
//! - [`export`]: a stored native network traced into a TorchScript module for PyTorch users.

pub mod autoencoder;
pub mod data;
pub mod ddim;
pub mod denoiser;
pub mod diffusion;
pub mod export;
pub mod manifest;
pub mod nets;
pub mod normalizer;
pub mod optim;
pub mod recipe;
pub mod relative_reward;
pub mod reward_model;
pub mod reward_trainer;
pub mod rng;
pub mod sampling;
pub mod schedule;
pub mod target_pool;
pub mod threads;
pub mod torchscript;

use std::sync::OnceLock;

use tch::Device;

use crate::config::{ConfigError, EngineConfig};

/// The device resolved from `engine.device` at start. Process-wide on purpose, like
/// libtorch's thread pool that `init` also sets: one server process computes on one device,
/// and jobs, sampling, serving and registry loads all read it here (unset, as in unit tests
/// that never call `init`: the CPU).
static DEVICE: OnceLock<Device> = OnceLock::new();

/// `engine.step_checks` as set at start (unset: `auto`).
static STEP_CHECKS: OnceLock<String> = OnceLock::new();

/// Whether training on `device` decides each step's skip and clip on the device and reads the
/// steps' figures together where they are looked at (`engine.step_checks`: `device`, or `auto`
/// on CUDA), rather than on the host as each step runs (see
/// [`optim::Adam::deciding_on_device`], `jobs::training::TrainLoop::run`).
pub fn step_checks_on_device(device: Device) -> bool {
    match STEP_CHECKS.get().map_or("auto", String::as_str) {
        "device" => true,
        "host" => false,
        // `auto`, the only other value the configuration accepts.
        _ => device.is_cuda(),
    }
}

/// The device every computation of this process runs on (see [`init`]).
pub fn device() -> Device {
    DEVICE.get().copied().unwrap_or(Device::Cpu)
}

/// `t` (a host tensor) on `device`, without making the host wait for the device's queue.
///
/// Why not `to_device`: a plain copy from pageable host memory to a CUDA device synchronises
/// the stream first, so each of a training step's small uploads (noise, timesteps, batch
/// indices, schedule coefficients) would drain the GPU's queue and leave it idle while the
/// next kernels are launched. The copy is staged in pinned memory and made asynchronously;
/// libtorch's host allocator keeps the staging block until the copy has run. Where pinning is
/// refused (pinned memory exhausted), a plain copy does. On the CPU, and for a tensor already
/// there, nothing is copied.
pub fn upload(t: &tch::Tensor, device: Device) -> tch::Result<tch::Tensor> {
    if t.device() == device {
        return Ok(t.shallow_clone());
    }
    match device {
        Device::Cuda(_) if t.device() == Device::Cpu => {
            // `_pin_memory`, not `pin_memory`: tch passes `pin_memory` a device, which
            // libtorch deprecates with a warning at every call; `_pin_memory` is the same
            // copy into the pinned allocator without that warning (the tensor is a fresh host
            // tensor, never already pinned).
            match t.f_internal_pin_memory(device) {
                Ok(pinned) => pinned.f_to_device_(device, t.f_kind()?, true, false),
                Err(_) => t.f_to_device(device),
            }
        }
        _ => t.f_to_device(device),
    }
}

/// `engine.device` against the CUDA devices libtorch sees: `cpu`, `cuda` (= `cuda:0`),
/// `cuda:N`, or `auto` (the first CUDA device if there is one, else the CPU). A CUDA device
/// that is not there is an error naming the key, never a silent fall back to the CPU.
pub fn resolve_device(setting: &str, cuda_devices: usize) -> Result<Device, ConfigError> {
    let invalid = |message: String| ConfigError::Invalid { key: "engine.device", message };
    let absent = || {
        invalid(format!(
            "'{setting}' is not available: libtorch sees {cuda_devices} CUDA device(s){} (use cpu or auto, or run on a machine with the GPU and a CUDA build of libtorch)",
            if cuda_devices > 0 { format!(", numbered 0 to {}", cuda_devices - 1) } else { String::new() }
        ))
    };
    match setting.trim() {
        "cpu" => Ok(Device::Cpu),
        "auto" => Ok(if cuda_devices > 0 { Device::Cuda(0) } else { Device::Cpu }),
        "cuda" if cuda_devices > 0 => Ok(Device::Cuda(0)),
        "cuda" => Err(absent()),
        s => match s.strip_prefix("cuda:").map(str::parse::<usize>) {
            Some(Ok(n)) if n < cuda_devices => Ok(Device::Cuda(n)),
            Some(Ok(_)) => Err(absent()),
            _ => Err(invalid(format!("'{setting}' is not one of cpu, cuda, cuda:N (N a device number) or auto"))),
        },
    }
}

/// `engine.device` resolved against the CUDA devices libtorch sees on this machine.
pub fn check_device(config: &EngineConfig) -> Result<Device, ConfigError> {
    resolve_device(&config.device, usize::try_from(tch::Cuda::device_count()).unwrap_or(0))
}

/// Configures libtorch once at start, before any tensor work: its thread pool, and the device
/// (`engine.device`, resolved by [`resolve_device`]; a device that is absent stops the start).
/// Returns the device and reports what the process runs on.
pub fn init(config: &EngineConfig) -> Result<Device, ConfigError> {
    let cuda_devices = usize::try_from(tch::Cuda::device_count()).unwrap_or(0);
    let device = resolve_device(&config.device, cuda_devices)?;
    let threads = match config.intra_op_threads {
        0 => std::thread::available_parallelism().map_or(1, usize::from),
        n => n,
    };
    tch::set_num_threads(i32::try_from(threads).unwrap_or(1));
    // A second `init` in one process (tests start several servers) keeps the first device.
    let device = *DEVICE.get_or_init(|| device);
    let _ = STEP_CHECKS.set(config.step_checks.clone());
    tracing::info!(
        intra_op_threads = tch::get_num_threads(),
        cuda_devices,
        device = ?device,
        setting = config.device,
        step_checks_on_device = step_checks_on_device(device),
        "libtorch initialised"
    );
    Ok(device)
}

#[cfg(test)]
mod device_tests {
    use super::*;

    #[test]
    fn engine_device_resolves_or_names_the_key() {
        assert_eq!(resolve_device("cpu", 0).expect("cpu"), Device::Cpu);
        assert_eq!(resolve_device("auto", 0).expect("auto"), Device::Cpu);
        assert_eq!(resolve_device("auto", 2).expect("auto"), Device::Cuda(0));
        assert_eq!(resolve_device("cuda", 1).expect("cuda"), Device::Cuda(0));
        assert_eq!(resolve_device("cuda:1", 2).expect("cuda:1"), Device::Cuda(1));
        for (setting, n, needle) in [
            ("cuda", 0, "'cuda' is not available: libtorch sees 0 CUDA device(s)"),
            ("cuda:0", 0, "'cuda:0' is not available"),
            ("cuda:2", 2, "numbered 0 to 1"),
            ("gpu", 1, "'gpu' is not one of cpu, cuda, cuda:N"),
            ("cuda:x", 1, "is not one of"),
            ("", 0, "is not one of"),
        ] {
            let e = resolve_device(setting, n).expect_err(setting).to_string();
            assert!(e.contains("engine.device") && e.contains(needle), "{setting}: {e}");
        }
        // This machine's answer for `auto` is whatever libtorch sees; `cpu` never needs CUDA.
        let here = usize::try_from(tch::Cuda::device_count()).unwrap_or(0);
        assert_eq!(resolve_device("auto", here).expect("auto").is_cuda(), here > 0);
    }
}
