//! `relreward model import`, end to end: a Diffuser-layout `GaussianDiffusion(TemporalUnet)`
//! with random weights built in PyTorch (`tests/python/export_diffuser_temporal.py`), its
//! state_dict exported to `.npz` by the documented one-liner, converted by the real `relreward`
//! CLI binary into native weights, loaded the way the model registry loads a native model
//! ([`NativeDenoiser::load`], strict) must give the PyTorch module's output to 1e-5. Then the
//! CLI's refusals: a missing, a mis-shaped and an unexpected tensor, all named in one message.
//!
//! The CLI binary is the one `make build` (`cargo build --release --workspace --bins`) leaves
//! beside this test's directory, as the end-to-end crate finds its binaries.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use relreward_server::engine::denoiser::Denoiser;
use relreward_server::engine::manifest::{Architecture, Space};
use relreward_server::engine::nets::native::NativeDenoiser;
use tch::{Device, Tensor};

use common::repo_root;

const TOLERANCE: f64 = 1e-5;

/// target/<profile>/deps/<test> -> target/<profile>/relreward
fn cli_binary() -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    let path = exe.parent().and_then(Path::parent).expect("target dir").join("relreward");
    assert!(path.exists(), "{} not found: build the binaries first (make build)", path.display());
    path
}

fn python(args: &[&str]) {
    common::python(&repo_root().join("tests/python"), args);
}

fn log(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

fn import(dir: &Path, npz: &Path, prefix: &str) -> Output {
    Command::new(cli_binary())
        .args(["model", "import"])
        .arg(npz)
        .arg("--manifest")
        .arg(dir.join("manifest.toml"))
        .args(["--dim", "8", "--dim-mults", "1,2", "--prefix", prefix, "--out"])
        .arg(dir.join("weights.safetensors"))
        .output()
        .expect("run relreward")
}

#[test]
fn an_imported_diffuser_temporal_unet_matches_pytorch() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    python(&["export_diffuser_temporal.py", d.to_str().expect("utf-8 path")]);
    // horizon 8, transition dim 2 + 3 = 5, as the export script's defaults.
    std::fs::write(
        d.join("manifest.toml"),
        "parametrization = \"epsilon\"\nn_timesteps = 20\nschedule = { kind = \"linear\" }\n\
         space = { kind = \"trajectory\", horizon = 8, action_dim = 2, obs_dim = 3 }\n",
    )
    .expect("manifest");

    let out = import(d, &d.join("state_dict.npz"), "model.");
    assert!(out.status.success(), "model import failed:\n{}", log(&out));

    let architecture = Architecture::TemporalUnet { dim: 8, dim_mults: vec![1, 2] };
    let space = Space::Trajectory { horizon: 8, action_dim: 2, obs_dim: 3 };
    let net = NativeDenoiser::load(&architecture, &space, &d.join("weights.safetensors"), None, Device::Cpu)
        .expect("the imported weights load strictly");
    let check: BTreeMap<String, Tensor> =
        Tensor::read_safetensors(d.join("check.safetensors")).expect("check file").into_iter().collect();
    let y = tch::no_grad(|| net.forward(&check["x"], &check["t"], None).expect("forward"));
    let diff = (&y - &check["y"]).abs().max().double_value(&[]);
    eprintln!("max |relreward - PyTorch| = {diff:e}");
    assert!(check["y"].abs().max().double_value(&[]) > 0.1, "the reference output is trivially small");
    assert!(diff < TOLERANCE, "imported TemporalUnet differs from PyTorch by {diff}");

    // Without the prefix, the GaussianDiffusion's buffers are unexpected and every network
    // tensor is missing under its bare name: the message says so.
    let out = import(d, &d.join("state_dict.npz"), "");
    assert!(!out.status.success());
    let text = log(&out);
    assert!(text.contains("unexpected tensor 'betas'"), "{text}");
    assert!(text.contains("missing tensor 'time_mlp.1.weight' (expected shape [32, 8])"), "{text}");
}

#[test]
fn import_names_every_missing_misshaped_and_unexpected_tensor() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    python(&["export_diffuser_temporal.py", d.to_str().expect("utf-8 path")]);
    std::fs::write(
        d.join("manifest.toml"),
        "parametrization = \"x0\"\nn_timesteps = 20\nschedule = { kind = \"linear\" }\n\
         space = { kind = \"trajectory\", horizon = 8, action_dim = 2, obs_dim = 3 }\n",
    )
    .expect("manifest");
    // Drop one tensor, reshape one, add one, through numpy (as a user's broken export would).
    let bad = d.join("bad.npz");
    let script = format!(
        "import numpy as np\n\
         d = dict(np.load({src:?}))\n\
         del d['model.mid_block2.blocks.1.block.2.weight']\n\
         d['model.final_conv.1.weight'] = np.zeros((5, 16, 1), np.float32)\n\
         d['model.downs.0.2.fn.fn.to_qkv.weight'] = np.zeros((24, 8, 1), np.float32)\n\
         np.savez({dst:?}, **d)\n",
        src = d.join("state_dict.npz").to_str().expect("utf-8 path"),
        dst = bad.to_str().expect("utf-8 path"),
    );
    python(&["-c", &script]);
    let out = import(d, &bad, "model.");
    assert!(!out.status.success(), "a broken state_dict was accepted");
    let text = log(&out);
    for needle in [
        "missing tensor 'mid_block2.blocks.1.block.2.weight' (expected shape [16])",
        "tensor 'final_conv.1.weight' has shape [5, 16, 1], expected [5, 8, 1]",
        "unexpected tensor 'downs.0.2.fn.fn.to_qkv.weight' (shape [24, 8, 1])",
        "1 missing, 1 unexpected, 1 mis-shaped",
    ] {
        assert!(text.contains(needle), "{needle:?} not in:\n{text}");
    }
    assert!(!d.join("weights.safetensors").exists(), "nothing is written on error");
}
