//! Sampling with an exact denoiser exported from PyTorch (`tests/python/analytic_gaussian.py`):
//! data N(m, I) has eps(x_t, t) = sqrt(1 - abar_t) (x_t - sqrt(abar_t) m), so the sampler's
//! output must have mean m and (for DDPM's posterior variances) a slightly-below-one variance
//! that the schedule predicts exactly.
//!
//! The TorchScript adapter here is private to the test (the production loader lives in
//! `engine/torchscript.rs`).

use std::path::{Path, PathBuf};
use std::process::Command;

use relreward_server::engine::denoiser::Denoiser;
use relreward_server::engine::diffusion::DiffusionModel;
use relreward_server::engine::manifest::DiffusionManifest;
use relreward_server::engine::rng::Rng;
use relreward_server::engine::sampling::GuidedSampler;
use relreward_server::engine::schedule::Table;
use relreward_server::error::Result;
use tch::{Kind, Tensor};

struct TorchScriptDenoiser(tch::CModule);

impl Denoiser for TorchScriptDenoiser {
    fn forward(&self, x: &Tensor, t: &Tensor, _cond: Option<&Tensor>) -> Result<Tensor> {
        Ok(self.0.forward_ts(&[x, t])?)
    }

    fn parameter_count(&self) -> u64 {
        0
    }
}

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn export(dir: &Path, mean: &[f64], schedule: &str, t: usize) -> DiffusionModel {
    let python = repo().join(".venv/bin/python");
    assert!(python.exists(), "{} is missing: run `make setup` first", python.display());
    let mean_arg = mean.iter().map(f64::to_string).collect::<Vec<_>>().join(",");
    let out = Command::new(&python)
        .arg(repo().join("tests/python/analytic_gaussian.py"))
        .args([
            "--out",
            dir.to_str().expect("utf-8 path"),
            "--mean",
            &mean_arg,
            "--schedule",
            schedule,
            "--T",
            &t.to_string(),
        ])
        .output()
        .expect("run python");
    assert!(out.status.success(), "analytic_gaussian.py failed: {}", String::from_utf8_lossy(&out.stderr));
    let manifest = DiffusionManifest::parse(
        &std::fs::read_to_string(dir.join("manifest.json")).expect("manifest"),
        Some("manifest.json"),
    )
    .expect("manifest parses");
    let module = tch::CModule::load(dir.join("model.pt")).expect("load TorchScript");
    DiffusionModel::new(manifest, Box::new(TorchScriptDenoiser(module))).expect("model")
}

#[test]
fn exact_gaussian_model_samples_have_the_data_moments() {
    // Small tensors: one intra-op thread avoids OpenMP spinning on a busy 2-core machine.
    tch::set_num_threads(1);
    let dir = tempfile::tempdir().expect("tempdir");
    let mean = [1.0, -2.0, 0.5];
    let big_t = 1000;
    let model = export(dir.path(), &mean, "cosine", big_t);
    let s = &model.schedule;

    // The exported module agrees with the formula evaluated on Rust's own schedule.
    let x = Rng::new(1).randn(&[5, 3], tch::Device::Cpu);
    let t = Tensor::from_slice(&[0i64, 1, 500, 998, 999]);
    let got = model.predict(&x, &t).expect("predict");
    let m = Tensor::from_slice(&mean).to_kind(Kind::Float).unsqueeze(0);
    let sa = s.extract(Table::SqrtAlphasCumprod, &t, 2).expect("extract");
    let s1m = s.extract(Table::SqrtOneMinusAlphasCumprod, &t, 2).expect("extract");
    let want = s1m * (&x - sa * m);
    let err = (&got - &want).abs().max().double_value(&[]);
    assert!(err < 1e-5, "TorchScript eps differs from the formula by {err}");

    // Sample. The reverse process with posterior variances loses a little variance:
    // V_{t-1} = alpha_t V_t + posterior_variance_t from V = 1 (see the sampling module); the
    // mean is exact up to abar_{T-1} (~1e-9).
    let n = 16_384usize;
    let samples = GuidedSampler::new(&model).sample(n, &mut Rng::new(2024)).expect("sample").x.to_kind(Kind::Double);
    assert_eq!(samples.size(), vec![n as i64, 3]);
    let mut predicted_var = 1.0;
    for t in (0..big_t).rev() {
        predicted_var = s.values(Table::Alphas)[t] * predicted_var + s.values(Table::PosteriorVariance)[t];
    }
    let se_mean = (predicted_var / n as f64).sqrt();
    let se_var = (2.0 / n as f64).sqrt() * predicted_var;
    for (d, &m) in mean.iter().enumerate() {
        let col = samples.select(1, d as i64);
        let mu = col.mean(Kind::Double).double_value(&[]);
        let var = col.var(true).double_value(&[]);
        eprintln!("coordinate {d}: mean {mu:.4} (m = {m}), variance {var:.4} (predicted {predicted_var:.4})");
        assert!((mu - m).abs() < 3.0 * se_mean, "coordinate {d}: mean {mu} vs {m} (3 SE = {})", 3.0 * se_mean);
        assert!((var - 1.0).abs() < 0.05, "coordinate {d}: variance {var} not within 5% of 1");
        assert!(
            (var - predicted_var).abs() < 4.0 * se_var,
            "coordinate {d}: variance {var} vs predicted {predicted_var}"
        );
    }
}
