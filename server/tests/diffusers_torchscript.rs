//! Bring your own image model: a diffusers `UNet2DModel` with its `DDPMScheduler` (cosine
//! betas, clip_sample), exported by the documented recipe `tests/python/export_diffusers.py`
//! (TorchScript module + manifest from the scheduler's config), loaded the way the model
//! registry loads an uploaded module ([`TorchScriptDenoiser::load_and_validate`]), must give
//! diffusers' own eps (`unet(x, t).sample`) and posterior mean (`DDPMScheduler.step` without its
//! noise) to 1e-5 (relative where the values exceed 1), at t = 0 (no previous step), 1, inside the schedule and at T - 1.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Command;

use relreward_server::engine::diffusion::DiffusionModel;
use relreward_server::engine::manifest::DiffusionManifest;
use relreward_server::engine::torchscript::TorchScriptDenoiser;
use tch::{Device, Tensor};

const TOLERANCE: f64 = 1e-5;

fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

#[test]
fn diffusers_unet2d_eps_and_posterior_mean_match_diffusers() {
    let dir = tempfile::tempdir().expect("tempdir");
    let python = repo_root().join(".venv/bin/python");
    let out = Command::new(&python)
        .arg("export_diffusers.py")
        .arg(dir.path())
        .arg("--check")
        .current_dir(repo_root().join("tests/python"))
        .output()
        .unwrap_or_else(|e| panic!("cannot run {} (run `make setup`): {e}", python.display()));
    let log = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "export_diffusers.py failed:\n{log}");

    let text = std::fs::read_to_string(dir.path().join("manifest.json")).expect("manifest");
    let manifest = DiffusionManifest::parse(&text, Some("manifest.json")).expect("the exported manifest is valid");
    assert!(manifest.clip_denoised, "clip_sample carried over");
    let denoiser = TorchScriptDenoiser::load_and_validate(&dir.path().join("module.pt"), &manifest, Device::Cpu)
        .expect("the traced module passes the upload checks");
    let model = DiffusionModel::new(manifest, Box::new(denoiser)).expect("model");

    let check: BTreeMap<String, Tensor> =
        Tensor::read_safetensors(dir.path().join("check.safetensors")).expect("check file").into_iter().collect();
    let (x, t) = (&check["x"], &check["t"]);
    let (eps, mean) = tch::no_grad(|| (model.eps_hat(x, t).expect("eps"), model.model_mean(x, t).expect("mean")));
    let diff = |a: &Tensor, b: &Tensor| (a - b).abs().max().double_value(&[]);
    let (d_eps, d_mean) = (diff(&eps, &check["eps"]), diff(&mean, &check["mean"]));
    let magnitude = |a: &Tensor| a.abs().max().double_value(&[]);
    let (m_eps, m_mean) = (magnitude(&check["eps"]), magnitude(&check["mean"]));
    eprintln!(
        "max |relreward - diffusers|: eps {d_eps:e} (max |eps| {m_eps:.3}), posterior mean {d_mean:e} (max |mean| {m_mean:.3})"
    );
    assert!(m_eps > 1e-2, "eps is trivially small");
    // 1e-5, relative to the values where they exceed 1: float32 rounding grows with them, and
    // the inputs (torch.randn in the export script) differ between CPUs' vector units.
    assert!(d_eps < TOLERANCE * m_eps.max(1.0), "eps differs from diffusers' by {d_eps}");
    assert!(d_mean < TOLERANCE * m_mean.max(1.0), "posterior mean differs from diffusers' by {d_mean}");
    // Clipping mattered somewhere (|x0_hat| > 1), so the comparison covers it.
    let unclipped = tch::no_grad(|| model.posterior_mean(x, t, false).expect("unclipped mean"));
    assert!(diff(&unclipped, &mean) > 1e-4, "no x0_hat was clipped: the test would not see a clipping mismatch");
}
