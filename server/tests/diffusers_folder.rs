//! `relreward model import DIR|ORG/NAME`, end to end: folders written by diffusers' own
//! `save_pretrained` (`tests/python/diffusers_folder.py`: small, seeded, random weights) are
//! converted by the real `relreward` CLI binary into native weights and a manifest, and the
//! model the registry would build from them ([`NativeDenoiser::load`], strict, with the written
//! manifest) must give diffusers' raw output (`model(x, t).sample`: eps, or x0 for
//! prediction_type "sample") and its posterior mean (`DDPMScheduler.step` without its noise) to
//! 1e-5, relative where the values exceed 1, at t = 0, 1, inside and T - 1. The posterior mean is
//! diffusers' step evaluated in float64 (`mean64`): diffusers' float32 step cancels digits in
//! 1 - alphas_cumprod for small betas (4e-5 at t = 1 of `planner`'s linear schedule), while
//! relreward derives its tables in float64; against the float32 step the bound is 1e-5 plus that
//! float32 error, which the test prints.
//!
//! - `unet1d`: the UNet1DModel of Diffuser's TemporalUnet as diffusers' converter writes it
//!   (flip_sin_to_cos false, freq_shift 1), saved on its own, squaredcos_cap_v2, epsilon, clipped;
//! - `planner`: a pipeline folder (unet/, scheduler/) found by repository id in a local Hugging
//!   Face cache (HF_HOME), flip_sin_to_cos true, linear, x0 ("sample"), clipped;
//! - `unet2d`: a UNet2DModel with attention, saved on its own, squaredcos_cap_v2, clipped;
//! - `pipeline2d`: a DDPMPipeline folder, UNet2DModel without attention, flip_sin_to_cos false,
//!   three levels of two layers, an 8 x 12 sample_size, scaled_linear, unclipped.
//!
//! Then a folder missing a tensor is refused naming it, with nothing written; and the round trip
//! on a live server: `model import --name` registers the folder as a native model and `sample`
//! draws from it.
//!
//! The binaries are the ones `make build` leaves beside this test's directory.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};

use relreward_server::engine::diffusion::DiffusionModel;
use relreward_server::engine::manifest::{DiffusionManifest, Parametrization};
use relreward_server::engine::nets::native::NativeDenoiser;
use relreward_tests::{TestServer, bin, np_load, npz_shape, npz_values, ok};
use tch::{Device, Tensor};

mod common;

const TOLERANCE: f64 = 1e-5;

fn log(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

/// `relreward model import SOURCE --out DIR/NAME.safetensors ARGS`, the hub cache at `hf_home`.
fn import(dir: &Path, source: &str, name: &str, args: &[&str]) -> Output {
    Command::new(bin("relreward"))
        .args(["model", "import", source, "--out"])
        .arg(dir.join(format!("{name}.safetensors")))
        .args(args)
        .env("HF_HOME", dir)
        .env_remove("HF_HUB_CACHE")
        .current_dir(dir)
        .output()
        .expect("run relreward")
}

fn max_abs(a: &Tensor) -> f64 {
    a.abs().max().double_value(&[])
}

/// Imports one case and compares relreward's output and posterior mean with diffusers'.
fn check_case(dir: &Path, source: &str, name: &str, args: &[&str], clipped: bool) {
    let out = import(dir, source, name, args);
    assert!(out.status.success(), "{name}: model import failed:\n{}", log(&out));
    eprintln!("{}", log(&out));
    let manifest_path = dir.join(format!("{name}.manifest.toml"));
    let text = std::fs::read_to_string(&manifest_path).expect("the manifest is written beside the weights");
    let manifest = DiffusionManifest::parse(&text, Some("manifest.toml")).expect("the written manifest is valid");
    assert_eq!(manifest.clip_denoised, clipped, "{name}: clip_sample carried over");
    let architecture = manifest.architecture.clone().expect("a native manifest");
    let net = NativeDenoiser::load(
        &architecture,
        &manifest.space,
        &dir.join(format!("{name}.safetensors")),
        None,
        Device::Cpu,
    )
    .expect("the imported weights load strictly");
    let epsilon = manifest.parametrization == Parametrization::Epsilon;
    let model = DiffusionModel::new(manifest, Box::new(net)).expect("model");

    let check: BTreeMap<String, Tensor> = Tensor::read_safetensors(dir.join(format!("check-{name}.safetensors")))
        .expect("check file")
        .into_iter()
        .collect();
    let (x, t) = (&check["x"], &check["t"]);
    let (pred, mean) = tch::no_grad(|| (model.predict(x, t).expect("predict"), model.model_mean(x, t).expect("mean")));
    let mean64 = check["mean64"].to_kind(tch::Kind::Float);
    let d_pred = max_abs(&(&pred - &check["pred"]));
    let (d_mean, d_mean32) = (max_abs(&(&mean - &mean64)), max_abs(&(&mean - &check["mean"])));
    let float32_error = max_abs(&(&check["mean"] - &mean64));
    let (m_pred, m_mean) = (max_abs(&check["pred"]), max_abs(&mean64));
    let what = if epsilon { "eps" } else { "x0" };
    eprintln!(
        "{name}: max |relreward - diffusers|: {what} {d_pred:e} (max |{what}| {m_pred:.3}), posterior mean {d_mean:e} \
         (max |mean| {m_mean:.3}); against diffusers' float32 step {d_mean32:e}, whose own float32 error is {float32_error:e}"
    );
    assert!(m_pred > 1e-2, "{name}: the output is trivially small");
    assert!(d_pred < TOLERANCE * m_pred.max(1.0), "{name}: {what} differs from diffusers' by {d_pred}");
    assert!(d_mean < TOLERANCE * m_mean.max(1.0), "{name}: posterior mean differs from diffusers' by {d_mean}");
    assert!(
        d_mean32 < TOLERANCE * m_mean.max(1.0) + float32_error,
        "{name}: posterior mean differs from diffusers' float32 step by {d_mean32}"
    );
    if epsilon {
        let eps = tch::no_grad(|| model.eps_hat(x, t).expect("eps"));
        assert!(max_abs(&(&eps - &check["pred"])) < TOLERANCE * m_pred.max(1.0), "{name}: eps_hat");
    }
    if clipped {
        // Clipping mattered somewhere (|x0_hat| > 1), so the comparison covers it.
        let unclipped = tch::no_grad(|| model.posterior_mean(x, t, false).expect("unclipped mean"));
        assert!(max_abs(&(&unclipped - &mean)) > 1e-4, "{name}: no x0_hat was clipped");
    }
}

#[test]
fn imported_diffusers_folders_match_diffusers() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    common::python(&common::repo_root().join("tests/python"), &["diffusers_folder.py", d.to_str().expect("utf-8")]);
    let trajectory = ["--horizon", "8", "--action-dim", "2"];
    check_case(d, "unet1d", "unet1d", &trajectory, true);
    check_case(d, "relreward-test/planner", "planner", &trajectory, true);
    check_case(d, "unet2d", "unet2d", &[], true);
    check_case(d, "pipeline2d", "pipeline2d", &[], false);

    // A folder whose weights lack a tensor: named, nothing written.
    let out = import(d, "missing_tensor", "missing", &trajectory);
    assert!(!out.status.success(), "a folder missing a tensor was imported");
    let text = log(&out);
    assert!(text.contains("missing tensor 'mid_block.resnets.1.time_emb.weight' (expected shape [32, 8])"), "{text}");
    assert!(!d.join("missing.safetensors").exists() && !d.join("missing.manifest.toml").exists(), "nothing is written");
}

#[test]
fn an_imported_folder_registers_and_samples() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    common::python(&common::repo_root().join("tests/python"), &["diffusers_folder.py", d.to_str().expect("utf-8")]);
    let server = TestServer::start();
    let path = |p: &str| d.join(p).to_str().expect("utf-8").to_owned();
    for (folder, name, extra, shape) in [
        ("unet1d", "planner-1d", vec!["--horizon", "8", "--action-dim", "2"], vec![3u64, 8, 5]),
        ("pipeline2d", "ddpm-2d", vec![], vec![3, 3, 8, 12]),
    ] {
        let (source, weights) = (path(folder), path(&format!("{name}.safetensors")));
        let mut args = vec!["model", "import", source.as_str(), "--out", weights.as_str(), "--name", name];
        args.extend(extra);
        let text = ok(&server, &args);
        assert!(text.contains(&format!("registered as model '{name}' (native)")), "{text}");
        let samples = path(&format!("{name}-samples.npz"));
        ok(&server, &["sample", "--base", name, "--n", "3", "--seed", "1", "--out", samples.as_str()]);
        let npz = np_load(Path::new(&samples));
        assert_eq!(npz_shape(&npz, "x"), shape, "{name}");
        assert!(npz_values(&npz, "x").iter().all(|v| v.is_finite()), "{name}: samples are finite");
    }
}
