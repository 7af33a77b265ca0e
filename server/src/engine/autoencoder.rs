//! [`TorchScriptAutoencoder`]: an uploaded TorchScript module with two exported methods,
//! `encode(x) -> z` (images float32 `[B, *image_shape]` to latents `[B, *latent_shape]`) and
//! `decode(z) -> x`, the latent space of issue 37 (the paper's image experiment runs on an
//! autoencoder's latents). The manifest ([`AutoencoderManifest`], the shared schema's) gives
//! both shapes and diffusers' latent scaling: the service's latents are
//! `(encode(x) - shift) * scale` and its images `decode(z / scale + shift)`, applied here so
//! that every caller (Encode, Decode, later a job) sees one convention.
//!
//! Validation at upload ([`TorchScriptAutoencoder::load_and_validate`]) mirrors the other
//! uploads' (`super::torchscript`, whose module loader and message cleaning it shares): each
//! method once under `no_grad` on zeros with batch 2, its output a finite float32 tensor of the
//! other declared shape. Each failure is InvalidArgument naming the method and what was
//! expected and found; a method the module does not have is named as missing.
//!
//! Work is on host values in, host values out ([`TorchScriptAutoencoder::run`]): the caller's
//! thread (an inference slot's blocking task) builds one tensor per call and copies the result
//! back once, so the door never touches libtorch.

use std::path::Path;

use tch::{CModule, Device, IValue, Kind, TchError, Tensor};

use super::torchscript::{LoadedModule, ivalue_kind, module_message};
use crate::error::{Error, Result};

pub use relreward_proto::schema::autoencoder::AutoencoderManifest;

/// Which of the module's two methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Images to (scaled) latents.
    Encode,
    /// (Scaled) latents to images.
    Decode,
}

impl Direction {
    /// The module's method name.
    pub fn method(self) -> &'static str {
        match self {
            Self::Encode => "encode",
            Self::Decode => "decode",
        }
    }

    /// The method's call as messages show it.
    fn call_text(self) -> &'static str {
        match self {
            Self::Encode => "encode(x)",
            Self::Decode => "decode(z)",
        }
    }
}

pub struct TorchScriptAutoencoder {
    module: CModule,
    manifest: AutoencoderManifest,
    image_shape: Vec<i64>,
    latent_shape: Vec<i64>,
    device: Device,
    parameter_count: u64,
    parameter_bytes: u64,
}

impl std::fmt::Debug for TorchScriptAutoencoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TorchScriptAutoencoder")
            .field("manifest", &self.manifest)
            .field("device", &self.device)
            .field("parameter_count", &self.parameter_count)
            .finish_non_exhaustive()
    }
}

impl TorchScriptAutoencoder {
    /// Loads the module onto `device` in eval mode, without running it. A file libtorch cannot
    /// read as TorchScript is InvalidArgument ("module: ..."); a missing file is internal.
    pub fn load(path: &Path, manifest: &AutoencoderManifest, device: Device) -> Result<Self> {
        let LoadedModule { module, parameter_count, parameter_bytes } = LoadedModule::load(path, device)?;
        Ok(Self {
            module,
            image_shape: manifest.image_sizes(),
            latent_shape: manifest.latent_sizes(),
            manifest: manifest.clone(),
            device,
            parameter_count,
            parameter_bytes,
        })
    }

    /// The manifest checked (messages name `header.autoencoder.*`), [`Self::load`], then
    /// `encode` on zeros `[2, *image_shape]` and `decode` on zeros `[2, *latent_shape]`, both
    /// under `no_grad`: each must exist and return finite float32 of the other shape.
    pub fn load_and_validate(path: &Path, manifest: &AutoencoderManifest, device: Device) -> Result<Self> {
        manifest.validate_at("header.autoencoder").map_err(|e| Error::invalid(e.0))?;
        let autoencoder = Self::load(path, manifest, device)?;
        autoencoder.validate(path)?;
        Ok(autoencoder)
    }

    fn validate(&self, path: &Path) -> Result<()> {
        for direction in [Direction::Encode, Direction::Decode] {
            let (input, output, declared) = match direction {
                Direction::Encode => (&self.image_shape, &self.latent_shape, "latent_shape"),
                Direction::Decode => (&self.latent_shape, &self.image_shape, "image_shape"),
            };
            let call = direction.call_text();
            let shape = batched(2, input);
            let x = Tensor::f_zeros(shape.as_slice(), (Kind::Float, self.device))?;
            let out = tch::no_grad(|| self.call(direction, &x)).map_err(|e| {
                let message = module_message(&e, path);
                if is_missing_method(&message) {
                    Error::invalid(format!(
                        "module: has no method `{}` ({message}); an autoencoder module exports encode(x) and \
                         decode(z) (`@torch.jit.export` on both in a scripted nn.Module)",
                        direction.method()
                    ))
                } else {
                    Error::invalid(format!("module: {call} on zeros {shape:?} raised: {message}"))
                }
            })?;
            let want = batched(2, output);
            let (out_shape, out_kind) = (out.size(), out.f_kind()?);
            if out_shape != want {
                return Err(Error::invalid(format!(
                    "module: {call} returned shape {out_shape:?} for input shape {shape:?}; \
                     header.autoencoder.{declared} declares {output:?}, so {want:?} was expected"
                )));
            }
            if out_kind != Kind::Float {
                return Err(Error::invalid(format!(
                    "module: {call} returned dtype {out_kind:?} for float32 input; expected float32"
                )));
            }
            if out.f_isfinite()?.f_all()?.f_int64_value(&[])? != 1 {
                return Err(Error::invalid(format!(
                    "module: {call} on zeros {shape:?} returned NaN or infinite values"
                )));
            }
        }
        Ok(())
    }

    /// The module's method on `x`; no checks.
    fn call(&self, direction: Direction, x: &Tensor) -> std::result::Result<Tensor, TchError> {
        match self.module.method_is(direction.method(), &[IValue::Tensor(x.shallow_clone())])? {
            IValue::Tensor(out) => Ok(out),
            other => {
                Err(TchError::Kind(format!("{} returned {}, not a tensor", direction.call_text(), ivalue_kind(&other))))
            }
        }
    }

    /// Encodes or decodes `batch` items given as row-major float32 host values of the input's
    /// shape (`[batch, *image_shape]` to encode, `[batch, *latent_shape]` to decode; the caller
    /// checked the count), with the manifest's scaling, under `no_grad`; returns the output's
    /// row-major host values. A module failing on this input, or answering another shape or
    /// dtype than at validation, is FailedPrecondition: the model cannot serve the request.
    /// Finiteness of the output is the caller's to judge.
    pub fn run(&self, direction: Direction, values: &[f32], batch: i64) -> Result<Vec<f32>> {
        let _guard = tch::no_grad_guard();
        let (input, output) = match direction {
            Direction::Encode => (&self.image_shape, &self.latent_shape),
            Direction::Decode => (&self.latent_shape, &self.image_shape),
        };
        let x = Tensor::f_from_slice(values)?.f_reshape(batched(batch, input).as_slice())?.f_to_device(self.device)?;
        let (scale, shift) = (self.manifest.scaling_factor, self.manifest.shift_factor);
        // diffusers' order: decode(z / scale + shift); (encode(x) - shift) * scale below.
        let x = match direction {
            Direction::Encode => x,
            Direction::Decode => x.f_div_scalar(scale)?.f_add_scalar(shift)?,
        };
        let out = self.call(direction, &x).map_err(|e| {
            Error::FailedPrecondition(format!(
                "the autoencoder's {} failed on input {:?}: {}",
                direction.call_text(),
                x.size(),
                module_message(&e, Path::new(""))
            ))
        })?;
        let want = batched(batch, output);
        if out.size() != want || out.f_kind()? != Kind::Float {
            return Err(Error::FailedPrecondition(format!(
                "the autoencoder's {} returned {:?} {:?} for a batch of {batch}; expected float32 {want:?}",
                direction.call_text(),
                out.f_kind()?,
                out.size()
            )));
        }
        let out = match direction {
            Direction::Encode => out.f_sub_scalar(shift)?.f_mul_scalar(scale)?,
            Direction::Decode => out,
        };
        let host = out.f_to_device(Device::Cpu)?.f_contiguous()?.f_view([-1])?;
        Ok(Vec::<f32>::try_from(&host)?)
    }

    pub fn manifest(&self) -> &AutoencoderManifest {
        &self.manifest
    }

    pub fn parameter_count(&self) -> u64 {
        self.parameter_count
    }

    /// As `TorchScriptDenoiser::parameter_bytes`.
    pub fn parameter_bytes(&self) -> u64 {
        self.parameter_bytes
    }
}

/// `[batch, *item]`.
fn batched(batch: i64, item: &[i64]) -> Vec<i64> {
    std::iter::once(batch).chain(item.iter().copied()).collect()
}

/// Whether libtorch's message says the module lacks the method called ("Method 'encode' is not
/// defined", or a missing attribute).
fn is_missing_method(message: &str) -> bool {
    message.contains("is not defined") || message.contains("has no attribute") || message.contains("not found")
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;
    use std::process::Command;

    use super::*;

    fn repo() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
    }

    /// Scripts autoencoders with PyTorch: `good` (encode: 2x2 average pooling of [1, 4, 4] into
    /// [1, 2, 2] times 3; decode: nearest upsampling times 0.5), and modules to refuse.
    fn fixtures() -> tempfile::TempDir {
        let dir = tempfile::tempdir().expect("tempdir");
        let script = r#"
import sys
import torch
import torch.nn.functional as F

class Good(torch.nn.Module):
    @torch.jit.export
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x, 2) * 3.0
    @torch.jit.export
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return F.interpolate(z, scale_factor=2.0, mode="nearest") * 0.5

class NoDecode(torch.nn.Module):
    @torch.jit.export
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x, 2)
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x

class NanDecode(Good):
    @torch.jit.export
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return F.interpolate(z, scale_factor=2.0, mode="nearest") * float("nan")

for name, m in (("good", Good()), ("no_decode", NoDecode()), ("nan_decode", NanDecode())):
    torch.jit.script(m).save(f"{sys.argv[1]}/{name}.pt")
"#;
        let path = dir.path().join("make.py");
        std::fs::write(&path, script).expect("write script");
        let out = Command::new(repo().join(".venv/bin/python")).arg(&path).arg(dir.path()).output().expect("python");
        assert!(out.status.success(), "scripting failed: {}", String::from_utf8_lossy(&out.stderr));
        dir
    }

    fn manifest(latent: Vec<usize>, scaling_factor: f64, shift_factor: f64) -> AutoencoderManifest {
        AutoencoderManifest { image_shape: vec![1, 4, 4], latent_shape: latent, scaling_factor, shift_factor }
    }

    fn invalid(result: Result<TorchScriptAutoencoder>) -> String {
        match result {
            Err(Error::InvalidArgument(m)) => m,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn autoencoder_scales_as_diffusers_and_refuses_bad_modules() {
        let dir = fixtures();
        let p = |name: &str| dir.path().join(name);
        let cpu = Device::Cpu;
        let m = manifest(vec![1, 2, 2], 0.5, 0.25);
        let ae = TorchScriptAutoencoder::load_and_validate(&p("good.pt"), &m, cpu).expect("good");
        let x: Vec<f32> = (0..16).map(|i| i as f32).collect();
        // avg of each 2x2 block, times 3, then (z - 0.25) * 0.5.
        let z = ae.run(Direction::Encode, &x, 1).expect("encode");
        let blocks = [2.5f32, 4.5, 10.5, 12.5];
        let want: Vec<f32> = blocks.iter().map(|b| (b * 3.0 - 0.25) * 0.5).collect();
        assert_eq!(z, want);
        // decode(z / 0.5 + 0.25) = upsampled (z / 0.5 + 0.25) * 0.5.
        let back = ae.run(Direction::Decode, &z, 1).expect("decode");
        assert_eq!(back.len(), 16);
        assert!((back[0] - (want[0] / 0.5 + 0.25) * 0.5).abs() < 1e-6, "{back:?}");

        let msg = invalid(TorchScriptAutoencoder::load_and_validate(&p("no_decode.pt"), &m, cpu));
        assert!(msg.contains("has no method `decode`"), "{msg}");
        let msg = invalid(TorchScriptAutoencoder::load_and_validate(&p("nan_decode.pt"), &m, cpu));
        assert!(msg.contains("decode(z)") && msg.contains("NaN"), "{msg}");
        let msg =
            invalid(TorchScriptAutoencoder::load_and_validate(&p("good.pt"), &manifest(vec![4, 2, 2], 1.0, 0.0), cpu));
        assert!(msg.contains("header.autoencoder.latent_shape") && msg.contains("[2, 1, 2, 2]"), "{msg}");
        let msg =
            invalid(TorchScriptAutoencoder::load_and_validate(&p("good.pt"), &manifest(vec![1, 2, 2], 0.0, 0.0), cpu));
        assert!(msg.starts_with("header.autoencoder.scaling_factor"), "{msg}");
    }
}
