//! Uploaded TorchScript modules: [`TorchScriptDenoiser`], a diffusion model's network called
//! as `forward(x, t)` with `x` float32 `[B, *item_shape]` and `t` int64 `[B]` (a conditional
//! one as `forward(x, t, cond)`, cond per the manifest's `conditioning`), implementing
//! [`Denoiser`]; and [`TorchScriptReward`], a bring-your-own reward called as `forward(x, t)
//! -> [B]` or as Diffuser's value function `forward(x, cond, t) -> [B, 1]` (the manifest's
//! [`RewardSignature`]), served through [`super::reward_model::RewardModel`].
//!
//! A TorchScript file is a program (PyTorch's SECURITY.md): loading and calling it runs its
//! author's code inside the server, which is why uploads are off unless
//! `models.allow_torchscript_upload` is set. What this module can do is refuse files that do not
//! honour their manifest before they are registered: `load_and_validate` loads the module
//! ([`LoadedModule`], shared by both kinds) and runs one forward pass on zeros of the declared
//! shape; a reward also one backward to `x`, since its gradient is served.
//!
//! Error messages never contain the file's path (a server-side location) and keep only the
//! part of libtorch's message that concerns the module, not the C++ backtrace behind it.

use std::path::Path;
use std::sync::Arc;

use tch::{CModule, Device, IValue, Kind, TchError, Tensor};

use super::denoiser::{Denoiser, ValidationProbe};
use super::manifest::{Conditioning, DiffusionManifest, RewardSignature, RewardUploadManifest};
use super::nets::inputs::{check_condition, check_inputs};
use crate::error::{Error, Result};

/// Longest module message passed on to the client.
const MAX_MESSAGE_CHARS: usize = 600;

pub struct TorchScriptDenoiser {
    module: CModule,
    item_shape: Vec<i64>,
    /// A conditional module is called as forward(x, t, cond).
    conditioning: Option<Conditioning>,
    device: Device,
    parameter_count: u64,
    parameter_bytes: u64,
}

impl std::fmt::Debug for TorchScriptDenoiser {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TorchScriptDenoiser")
            .field("item_shape", &self.item_shape)
            .field("device", &self.device)
            .field("parameter_count", &self.parameter_count)
            .finish_non_exhaustive()
    }
}

impl TorchScriptDenoiser {
    /// Loads the module onto `device` in eval mode, without running it. A file libtorch cannot
    /// read as TorchScript is InvalidArgument ("module: ..."); a missing file is internal.
    pub fn load(path: &Path, manifest: &DiffusionManifest, device: Device) -> Result<Self> {
        let LoadedModule { module, parameter_count, parameter_bytes } = LoadedModule::load(path, device)?;
        Ok(Self {
            module,
            item_shape: manifest.space.item_shape(),
            conditioning: manifest.conditioning,
            device,
            parameter_count,
            parameter_bytes,
        })
    }

    /// [`Self::load`], then one forward pass under `no_grad` on zeros `[2, *item_shape]` with
    /// `t = [0, T - 1]`: the output must be a float32 tensor of the input's shape with finite
    /// values. Every failure is InvalidArgument naming what was expected and what was found;
    /// an exception raised by the module is reported with the module's own message.
    pub fn load_and_validate(path: &Path, manifest: &DiffusionManifest, device: Device) -> Result<Self> {
        manifest.validate()?;
        let denoiser = Self::load(path, manifest, device)?;
        denoiser.validate(manifest.n_timesteps, path)?;
        Ok(denoiser)
    }

    fn validate(&self, n_timesteps: usize, path: &Path) -> Result<()> {
        let probe = ValidationProbe::new(&self.item_shape, n_timesteps, self.conditioning.as_ref(), self.device)?;
        let (shape, last) = (&probe.shape, probe.last);
        let call = if self.conditioning.is_some() { "forward(x, t, cond)" } else { "forward(x, t)" };
        let out = tch::no_grad(|| self.call(&probe.x, &probe.t, probe.cond.as_ref())).map_err(|e| {
            Error::invalid(format!(
                "module: {call} on zeros {shape:?} with t = [0, {last}]{} raised: {}",
                if probe.cond.is_some() { " and the null condition" } else { "" },
                module_message(&e, path)
            ))
        })?;
        let (out_shape, out_kind) = (out.size(), out.f_kind()?);
        if out_shape != *shape {
            return Err(Error::invalid(format!(
                "module: {call} returned shape {out_shape:?} for input shape {shape:?}; the manifest's space \
                 declares items of shape {:?}, and a denoiser's output must have its input's shape",
                self.item_shape
            )));
        }
        if out_kind != Kind::Float {
            return Err(Error::invalid(format!(
                "module: {call} returned dtype {out_kind:?} for float32 input; expected float32"
            )));
        }
        probe.check_finite(&out, &format!("module: {call}"))
    }

    fn call(&self, x: &Tensor, t: &Tensor, cond: Option<&Tensor>) -> std::result::Result<Tensor, TchError> {
        match cond {
            Some(c) => self.module.forward_ts(&[x, t, c]),
            None => self.module.forward_ts(&[x, t]),
        }
    }

    /// Bytes of the module's parameters (buffers are not visible through libtorch's C API; the
    /// registry bounds those by the file's size).
    pub fn parameter_bytes(&self) -> u64 {
        self.parameter_bytes
    }

    pub fn device(&self) -> Device {
        self.device
    }
}

impl Denoiser for TorchScriptDenoiser {
    fn forward(&self, x: &Tensor, t: &Tensor, cond: Option<&Tensor>) -> Result<Tensor> {
        let batch = check_inputs("denoiser", x, t, &self.item_shape, Kind::Float)?;
        check_condition("denoiser", cond, self.conditioning.as_ref(), batch)?;
        let size = x.size();
        // The module passed validation at registration, so a failure now depends on the input
        // (or the module's own code): the model cannot serve this request.
        self.call(x, t, cond).map_err(|e| {
            Error::FailedPrecondition(format!(
                "the TorchScript module failed on input {size:?}: {}",
                module_message(&e, Path::new(""))
            ))
        })
    }

    fn parameter_count(&self) -> u64 {
        self.parameter_count
    }
}

/// A TorchScript file loaded onto a device in eval mode, with its parameter count and bytes:
/// what every kind of upload starts from (denoisers, rewards, and `super::autoencoder`'s).
pub(super) struct LoadedModule {
    pub(super) module: CModule,
    pub(super) parameter_count: u64,
    pub(super) parameter_bytes: u64,
}

impl LoadedModule {
    pub(super) fn load(path: &Path, device: Device) -> Result<Self> {
        // A missing or unreadable file is the server's problem, not the module's.
        std::fs::metadata(path)?;
        let mut module = CModule::load_on_device(path, device).map_err(|e| {
            Error::invalid(format!("module: not a loadable TorchScript file: {}", module_message(&e, path)))
        })?;
        module
            .f_set_eval()
            .map_err(|e| Error::invalid(format!("module: cannot switch to eval mode: {}", module_message(&e, path))))?;
        let parameters = module
            .named_parameters()
            .map_err(|e| Error::invalid(format!("module: cannot list its parameters: {}", module_message(&e, path))))?;
        let mut parameter_count = 0u64;
        let mut parameter_bytes = 0u64;
        for (_, p) in &parameters {
            let numel = u64::try_from(p.numel()).unwrap_or(u64::MAX);
            let width = p.f_kind().map(|k| k.elt_size_in_bytes()).unwrap_or(4) as u64;
            parameter_count = parameter_count.saturating_add(numel);
            parameter_bytes = parameter_bytes.saturating_add(numel.saturating_mul(width));
        }
        Ok(Self { module, parameter_count, parameter_bytes })
    }
}

/// A bring-your-own reward: an uploaded TorchScript module computing a scalar per item, over
/// `x` in normalized units. Behind [`super::reward_model::RewardModel`], so Score, Gradient,
/// guidance and OIP serve it as they serve a trained [`super::nets::RewardNet`].
pub struct TorchScriptReward {
    /// Shared with its replicas (serving's helper threads): libtorch runs one module's methods
    /// from several threads at once (its graph executor locks what it compiles per input
    /// shape), and tch marks `CModule` `Sync`. A module that changes its own attributes in
    /// `forward` would race: the README's contract for uploads rules that out.
    module: Arc<CModule>,
    signature: RewardSignature,
    item_shape: Vec<i64>,
    device: Device,
    parameter_count: u64,
    parameter_bytes: u64,
}

impl std::fmt::Debug for TorchScriptReward {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TorchScriptReward")
            .field("signature", &self.signature)
            .field("item_shape", &self.item_shape)
            .field("device", &self.device)
            .field("parameter_count", &self.parameter_count)
            .finish_non_exhaustive()
    }
}

impl TorchScriptReward {
    /// Loads the module onto `device` in eval mode, without running it (as
    /// [`TorchScriptDenoiser::load`]).
    pub fn load(path: &Path, signature: RewardSignature, item_shape: &[i64], device: Device) -> Result<Self> {
        let LoadedModule { module, parameter_count, parameter_bytes } = LoadedModule::load(path, device)?;
        let module = Arc::new(module);
        Ok(Self { module, signature, item_shape: item_shape.to_vec(), device, parameter_count, parameter_bytes })
    }

    /// Another handle on the same module, for another thread (no copy, nothing reloaded).
    pub fn replica(&self) -> Self {
        Self {
            module: Arc::clone(&self.module),
            signature: self.signature,
            item_shape: self.item_shape.clone(),
            device: self.device,
            parameter_count: self.parameter_count,
            parameter_bytes: self.parameter_bytes,
        }
    }

    /// [`Self::load`], then on zeros `[2, *item_shape]` with `t = [0, T - 1]`: one forward
    /// under `no_grad`, whose output must be float32 of the signature's shape (`[2]`, or
    /// `[2, 1]` for a value function) and finite; then one forward and backward with `x`
    /// requiring grad, whose gradient must exist (the output depends on `x` differentiably)
    /// and be finite. Every failure is InvalidArgument naming what was expected and found.
    pub fn load_and_validate(path: &Path, manifest: &RewardUploadManifest, device: Device) -> Result<Self> {
        manifest.validate_at("header.reward").map_err(|e| Error::invalid(e.0))?;
        let reward = Self::load(path, manifest.signature, &manifest.space.item_shape(), device)?;
        reward.validate(manifest.n_timesteps, path)?;
        Ok(reward)
    }

    fn validate(&self, n_timesteps: usize, path: &Path) -> Result<()> {
        let probe = ValidationProbe::new(&self.item_shape, n_timesteps, None, self.device)?;
        let (shape, last) = (&probe.shape, probe.last);
        let call = self.call_text();
        let raised = |e: TchError| {
            Error::invalid(format!(
                "module: {call} on zeros {shape:?} with t = [0, {last}] raised: {}",
                module_message(&e, path)
            ))
        };
        let out = tch::no_grad(|| self.call(&probe.x, &probe.t)).map_err(raised)?;
        let want = self.output_shape(2);
        let (out_shape, out_kind) = (out.size(), out.f_kind()?);
        if out_shape != want {
            return Err(Error::invalid(format!(
                "module: {call} returned shape {out_shape:?} for input shape {shape:?}; a reward of signature {} \
                 must return {want:?} (one value per item)",
                self.signature
            )));
        }
        if out_kind != Kind::Float {
            return Err(Error::invalid(format!(
                "module: {call} returned dtype {out_kind:?} for float32 input; expected float32"
            )));
        }
        probe.check_finite(&out, &format!("module: {call}"))?;
        let grad = tch::with_grad(|| -> Result<Option<Tensor>> {
            let x = probe.x.f_detach_copy()?.f_set_requires_grad(true)?;
            let y = self.call(&x, &probe.t).map_err(raised)?;
            if !y.requires_grad() {
                return Ok(None);
            }
            let sum = y.f_sum(None::<Kind>)?;
            let grads = Tensor::f_run_backward(&[&sum], &[&x], false, true).map_err(|e| {
                Error::invalid(format!(
                    "module: the backward of {call} to x failed (gradients are served): {}",
                    module_message(&e, path)
                ))
            })?;
            Ok(grads.into_iter().next().filter(Tensor::defined))
        })?;
        let Some(grad) = grad else {
            return Err(Error::invalid(format!(
                "module: {call}'s output does not depend differentiably on x (computed without grad, detached, or \
                 not from x); Gradient and guidance need grad_x of the reward"
            )));
        };
        probe.check_finite(&grad, &format!("module: the gradient of {call} with respect to x"))
    }

    /// The module's call for the manifest's signature (see [`RewardSignature`]); no checks.
    fn call(&self, x: &Tensor, t: &Tensor) -> std::result::Result<Tensor, TchError> {
        match self.signature {
            RewardSignature::Rho => self.module.forward_ts(&[x, t]),
            RewardSignature::ValueFunction => {
                // cond: always an empty Dict[str, Tensor] (the only dict type libtorch's C API
                // builds; Diffuser's ValueFunction never reads it: the proto's RewardSignature).
                let inputs = [
                    IValue::Tensor(x.shallow_clone()),
                    IValue::GenericDict(Vec::new()),
                    IValue::Tensor(t.shallow_clone()),
                ];
                match self.module.forward_is(&inputs)? {
                    IValue::Tensor(out) => Ok(out),
                    other => Err(TchError::Kind(format!("forward returned {}, not a tensor", ivalue_kind(&other)))),
                }
            }
        }
    }

    fn call_text(&self) -> &'static str {
        match self.signature {
            RewardSignature::Rho => "forward(x, t)",
            RewardSignature::ValueFunction => "forward(x, cond, t)",
        }
    }

    fn output_shape(&self, batch: i64) -> Vec<i64> {
        match self.signature {
            RewardSignature::Rho => vec![batch],
            RewardSignature::ValueFunction => vec![batch, 1],
        }
    }

    /// The reward `[B]` of `x` float32 `[B, *item_shape]` (normalized units) at `t` int64 `[B]`;
    /// differentiable with respect to `x` when grad mode is on. A value function's `[B, 1]` is
    /// squeezed (Diffuser's ValueGuide). A module failing, or answering another shape than it
    /// did at validation, is FailedPrecondition: the model cannot serve this request.
    pub fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        let batch = check_inputs("reward", x, t, &self.item_shape, Kind::Float)?;
        let out = self.call(x, t).map_err(|e| {
            Error::FailedPrecondition(format!(
                "the TorchScript reward failed on input {:?}: {}",
                x.size(),
                module_message(&e, Path::new(""))
            ))
        })?;
        let want = self.output_shape(batch);
        if out.size() != want || out.f_kind()? != Kind::Float {
            return Err(Error::FailedPrecondition(format!(
                "the TorchScript reward returned {:?} {:?} for a batch of {batch}; expected float32 {want:?}",
                out.f_kind()?,
                out.size()
            )));
        }
        Ok(out.f_reshape([batch])?)
    }

    pub fn signature(&self) -> RewardSignature {
        self.signature
    }

    pub fn item_shape(&self) -> &[i64] {
        &self.item_shape
    }

    pub fn parameter_count(&self) -> u64 {
        self.parameter_count
    }

    /// As [`TorchScriptDenoiser::parameter_bytes`].
    pub fn parameter_bytes(&self) -> u64 {
        self.parameter_bytes
    }
}

/// What a non-tensor output was, for messages.
pub(super) fn ivalue_kind(v: &IValue) -> &'static str {
    match v {
        IValue::None => "None",
        IValue::Tuple(_) => "a tuple",
        IValue::GenericList(_)
        | IValue::TensorList(_)
        | IValue::DoubleList(_)
        | IValue::IntList(_)
        | IValue::BoolList(_) => "a list",
        IValue::GenericDict(_) => "a dict",
        IValue::Double(_) | IValue::Int(_) | IValue::Bool(_) => "a number",
        IValue::String(_) => "a string",
        _ => "a non-tensor value",
    }
}

/// The part of a libtorch error worth showing: for an exception raised by TorchScript code,
/// its final "SomeError: message" line; otherwise the first line. Never the C++ backtrace
/// ("Exception raised from ...") nor the file's path; at most [`MAX_MESSAGE_CHARS`].
pub(super) fn module_message(err: &TchError, path: &Path) -> String {
    let text = match err {
        TchError::Torch(msg) => msg.clone(),
        other => other.to_string(),
    };
    // libtorch appends the C++ frames after this marker.
    let text = text.split("\nException raised from").next().unwrap_or_default();
    let lines: Vec<&str> = text.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    let is_exception_line = |l: &&&str| {
        l.split_once(": ").is_some_and(|(kind, _)| {
            let kind = kind.rsplit('.').next().unwrap_or(kind);
            (kind.ends_with("Error") || kind.ends_with("Exception")) && !kind.contains(' ')
        })
    };
    let chosen = if text.contains("Traceback of TorchScript") {
        lines.iter().rev().find(is_exception_line).or(lines.last())
    } else {
        lines.first()
    };
    let mut message = chosen.map(|l| (*l).to_owned()).unwrap_or_else(|| "unknown libtorch error".to_owned());
    let path = path.to_string_lossy();
    if !path.is_empty() {
        message = message.replace(path.as_ref(), "<module file>");
    }
    if message.chars().count() > MAX_MESSAGE_CHARS {
        message = message.chars().take(MAX_MESSAGE_CHARS).collect::<String>() + "...";
    }
    message
}

#[cfg(test)]
pub(crate) mod tests {
    use std::path::PathBuf;
    use std::process::Command;

    use super::*;
    use crate::engine::manifest::{Parametrization, ScheduleSpec, Space};
    use crate::engine::normalizer::Normalizer;

    fn repo() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
    }

    /// Runs tests/python/export_models.py into a fresh directory.
    pub(crate) fn export_fixtures() -> tempfile::TempDir {
        let dir = tempfile::tempdir().expect("tempdir");
        let python = repo().join(".venv/bin/python");
        assert!(python.exists(), "{} is missing: run `make setup` first", python.display());
        let out = Command::new(&python)
            .arg(repo().join("tests/python/export_models.py"))
            .args(["--out", dir.path().to_str().expect("utf-8 path"), "--mean", "1,-2,0.5", "--T", "50"])
            .output()
            .expect("run python");
        assert!(out.status.success(), "export_models.py failed: {}", String::from_utf8_lossy(&out.stderr));
        dir
    }

    fn manifest(shape: Vec<usize>) -> DiffusionManifest {
        DiffusionManifest {
            parametrization: Parametrization::Epsilon,
            schedule: ScheduleSpec::Cosine { s: 0.008 },
            n_timesteps: 50,
            clip_denoised: false,
            space: Space::Sample { shape },
            normalizer: Normalizer::Identity,
            architecture: None,
            conditioning: None,
        }
    }

    fn invalid(result: Result<TorchScriptDenoiser>) -> String {
        match result {
            Err(Error::InvalidArgument(m)) => m,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn torchscript_validation_accepts_good_modules_and_names_each_failure() {
        let dir = export_fixtures();
        let p = |name: &str| dir.path().join(name);
        let cpu = Device::Cpu;

        let good = TorchScriptDenoiser::load_and_validate(&p("gaussian.pt"), &manifest(vec![3]), cpu).expect("good");
        assert_eq!(good.parameter_count(), 0, "buffers are not parameters");
        let linear =
            TorchScriptDenoiser::load_and_validate(&p("linear.pt"), &manifest(vec![4, 3]), cpu).expect("linear");
        assert_eq!((linear.parameter_count(), linear.parameter_bytes()), (12, 48));

        let msg = invalid(TorchScriptDenoiser::load_and_validate(&p("gaussian.pt"), &manifest(vec![4]), cpu));
        assert!(msg.contains("raised"), "{msg}");
        let msg = invalid(TorchScriptDenoiser::load_and_validate(&p("wrong_shape.pt"), &manifest(vec![3]), cpu));
        assert!(msg.contains("[2, 2]") && msg.contains("[2, 3]"), "{msg}");
        let msg = invalid(TorchScriptDenoiser::load_and_validate(&p("nan.pt"), &manifest(vec![3]), cpu));
        assert!(msg.contains("NaN"), "{msg}");
        let msg = invalid(TorchScriptDenoiser::load_and_validate(&p("raises.pt"), &manifest(vec![3]), cpu));
        assert!(msg.contains("deliberate failure: this module always raises"), "{msg}");
        assert!(!msg.contains("Exception raised from") && msg.len() < 800, "{msg}");

        let bytes = std::fs::read(p("gaussian.pt")).expect("read");
        std::fs::write(p("truncated.pt"), &bytes[..bytes.len() / 2]).expect("write");
        std::fs::write(p("garbage.pt"), b"definitely not a zip archive").expect("write");
        for name in ["truncated.pt", "garbage.pt"] {
            let msg = invalid(TorchScriptDenoiser::load_and_validate(&p(name), &manifest(vec![3]), cpu));
            assert!(msg.starts_with("module: not a loadable TorchScript file"), "{msg}");
            assert!(!msg.contains(&dir.path().display().to_string()), "{msg} leaks the path");
        }
        assert!(matches!(
            TorchScriptDenoiser::load_and_validate(&p("absent.pt"), &manifest(vec![3]), cpu),
            Err(Error::Internal(_))
        ));
    }

    /// Scripts bring-your-own reward modules with PyTorch into a fresh directory: rho(x, t) =
    /// (t + 1) sum x^2, the same times a parameter w = 1.5 (`scaled`), and the value function
    /// (t + 1) sum x as [B, 1] (analytic gradients 2 (t + 1) x, 2 w (t + 1) x and t + 1), and
    /// two that must be refused (`detached`, `column`).
    pub(crate) fn byo_fixtures() -> tempfile::TempDir {
        let dir = tempfile::tempdir().expect("tempdir");
        let script = r#"
import sys
from typing import Dict
import torch

class Rho(torch.nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return (t.float() + 1) * (x * x).flatten(1).sum(1)

class Value(torch.nn.Module):
    def forward(self, x: torch.Tensor, cond: Dict[str, torch.Tensor], t: torch.Tensor) -> torch.Tensor:
        return ((t.float() + 1) * x.flatten(1).sum(1)).unsqueeze(1)

class Scaled(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(1.5))

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return self.w * (t.float() + 1) * (x * x).flatten(1).sum(1)

class Detached(torch.nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x.detach().flatten(1).sum(1)

class Column(torch.nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x.flatten(1).sum(1, keepdim=True)

for name, m in (("rho", Rho()), ("value", Value()), ("scaled", Scaled()), ("detached", Detached()),
                ("column", Column())):
    torch.jit.script(m).save(f"{sys.argv[1]}/{name}.pt")
"#;
        let path = dir.path().join("make.py");
        std::fs::write(&path, script).expect("write script");
        let out = Command::new(repo().join(".venv/bin/python")).arg(&path).arg(dir.path()).output().expect("python");
        assert!(out.status.success(), "scripting failed: {}", String::from_utf8_lossy(&out.stderr));
        dir
    }

    fn upload(signature: RewardSignature) -> RewardUploadManifest {
        RewardUploadManifest {
            signature,
            n_timesteps: 5,
            space: Space::Sample { shape: vec![2, 3] },
            normalizer: Normalizer::Identity,
            base_model: String::new(),
        }
    }

    /// Both signatures served through `RewardModel` (rho, gradient, windows), and refusals
    /// naming the problem.
    #[test]
    fn byo_rewards_are_served_through_reward_model_and_bad_ones_refused() {
        use crate::engine::relative_reward::RewardManifest;
        use crate::engine::reward_model::RewardModel;
        let dir = byo_fixtures();
        let p = |name: &str| dir.path().join(name);
        let x =
            Tensor::from_slice(&[0.5f32, -1.0, 2.0, 0.0, 1.5, -0.25, 1.0, 1.0, -2.0, 0.3, 0.7, 0.1]).reshape([2, 2, 3]);
        let t = Tensor::from_slice(&[0i64, 4]);
        let t1 = (t.to_kind(Kind::Float) + 1.0).reshape([2, 1, 1]);
        for (file, signature) in [("rho.pt", RewardSignature::Rho), ("value.pt", RewardSignature::ValueFunction)] {
            let m = upload(signature);
            let model =
                RewardModel::load(RewardManifest::uploaded(&m), &p(file), dir.path(), Device::Cpu).expect("load");
            assert_eq!((model.item_shape(), model.window()), (&[2i64, 3][..], None));
            let (want, want_grad) = match signature {
                RewardSignature::Rho => {
                    ((&x * &x * &t1).sum_dim_intlist([1i64, 2].as_slice(), false, Kind::Float), &x * &t1 * 2.0)
                }
                RewardSignature::ValueFunction => {
                    ((&x * &t1).sum_dim_intlist([1i64, 2].as_slice(), false, Kind::Float), x.ones_like() * &t1)
                }
            };
            let rho = tch::no_grad(|| model.rho(&x, &t)).expect("rho");
            assert!(rho.allclose(&want, 1e-6, 1e-6, false), "{signature}: {rho} vs {want}");
            let (rho, grad) = tch::no_grad(|| model.grad(&x, &t)).expect("grad");
            assert!(
                rho.allclose(&want, 1e-6, 1e-6, false) && grad.allclose(&want_grad, 1e-6, 1e-6, false),
                "{signature}"
            );
            assert_eq!(model.per_window(&x, &t).expect("windows").size(), [2, 1]);
            assert!(matches!(model.per_step(&x, &t), Err(Error::InvalidArgument(_))));
        }
        let refused = |file: &str, signature| match TorchScriptReward::load_and_validate(
            &p(file),
            &upload(signature),
            Device::Cpu,
        ) {
            Err(Error::InvalidArgument(m)) => m,
            other => panic!("{file}: expected InvalidArgument, got {other:?}"),
        };
        assert!(refused("detached.pt", RewardSignature::Rho).contains("does not depend differentiably on x"));
        let m = refused("column.pt", RewardSignature::Rho);
        assert!(m.contains("returned shape [2, 1]") && m.contains("must return [2]"), "{m}");
        let m = refused("rho.pt", RewardSignature::ValueFunction);
        assert!(m.contains("forward(x, cond, t)") && m.contains("raised"), "{m}");
        let m = refused("value.pt", RewardSignature::Rho);
        assert!(m.contains("forward(x, t)") && m.contains("raised"), "{m}");
    }

    /// A replica shares the module (nothing reloaded), and two threads evaluate the same
    /// module, parameters and all, at once, each getting the analytic answer for its own rows
    /// (serving's split passes, `serving/split.rs`).
    #[test]
    fn byo_reward_replicas_evaluate_the_shared_module_on_two_threads_at_once() {
        use crate::engine::relative_reward::RewardManifest;
        use crate::engine::reward_model::RewardModel;
        let dir = byo_fixtures();
        let path = dir.path().join("scaled.pt");
        let reward = TorchScriptReward::load(&path, RewardSignature::Rho, &[2, 3], Device::Cpu).expect("load");
        assert!(Arc::ptr_eq(&reward.module, &reward.replica().module), "a replica shares the loaded module");
        let manifest = RewardManifest::uploaded(&upload(RewardSignature::Rho));
        let model = RewardModel::load(manifest, &path, dir.path(), Device::Cpu).expect("load");
        let replica = model.replica().expect("replica");
        // 1.5 (t + 1) sum x^2 (1.5 the module's parameter) and its gradient 3 (t + 1) x, on rows
        // that differ per thread and pass.
        let passes = |model: RewardModel, offset: f64| {
            move || {
                for k in 0..200i64 {
                    let x = (Tensor::arange(18, (Kind::Float, Device::Cpu)) * 0.1 + offset + k as f64 * 0.01)
                        .reshape([3, 2, 3]);
                    let t = Tensor::from_slice(&[k % 5, (k + 2) % 5, (k + 4) % 5]);
                    let t1 = (t.to_kind(Kind::Float) + 1.0).reshape([3, 1, 1]);
                    let (rho, grad) = tch::no_grad(|| model.grad(&x, &t)).expect("grad");
                    let want = (&x * &x * &t1).sum_dim_intlist([1i64, 2].as_slice(), false, Kind::Float) * 1.5;
                    assert!(rho.allclose(&want, 1e-5, 1e-5, false), "pass {k} (offset {offset}): rho");
                    assert!(grad.allclose(&(&x * &t1 * 3.0), 1e-5, 1e-5, false), "pass {k} (offset {offset}): grad");
                }
            }
        };
        let helper = std::thread::spawn(passes(replica, -1.0));
        passes(model, 1.0)();
        helper.join().expect("the helper thread's passes");
    }

    #[test]
    fn torchscript_forward_checks_inputs_and_reports_module_failures() {
        let dir = export_fixtures();
        let cpu = Device::Cpu;
        let good = TorchScriptDenoiser::load(&dir.path().join("gaussian.pt"), &manifest(vec![3]), cpu).expect("load");
        let x = Tensor::zeros([5, 3], (Kind::Float, cpu));
        let t = Tensor::from_slice(&[0i64, 1, 2, 3, 4]);
        assert_eq!(good.forward(&x, &t, None).expect("forward").size(), vec![5, 3]);
        assert!(matches!(good.forward(&x.narrow(1, 0, 2), &t, None), Err(Error::InvalidArgument(_))));
        assert!(matches!(good.forward(&x, &t.to_kind(Kind::Float), None), Err(Error::InvalidArgument(_))));
        let raises = TorchScriptDenoiser::load(&dir.path().join("raises.pt"), &manifest(vec![3]), cpu).expect("load");
        match raises.forward(&x, &t, None) {
            Err(Error::FailedPrecondition(m)) => assert!(m.contains("deliberate failure"), "{m}"),
            other => panic!("expected FailedPrecondition, got {other:?}"),
        }
    }
}
