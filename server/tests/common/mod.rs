//! Helpers shared by this directory's cross-checks against PyTorch. Each test file is its own
//! crate and takes them with `mod common;`, and not every file uses every helper.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

use relreward_server::engine::rng::Rng;
use tch::nn::VarStore;
use tch::{Device, Tensor};

pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Draws every weight from the test's own seeded generator (libtorch's global one is shared by
/// the tests running in parallel, so its draws would change from run to run): N(0, 0.5^2 /
/// fan_in) for matrices and kernels, 1 + N(0, 0.2^2) for GroupNorm scales, N(0, 0.2^2) for
/// biases, so that every parameter takes part and activations stay of order one.
pub fn randomize(vs: &VarStore, rng: &mut Rng) {
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    tch::no_grad(|| {
        for (name, mut var) in vars {
            let size = var.size();
            let noise = rng.randn(&size, Device::Cpu);
            let value = match size.as_slice() {
                [out, ..] if size.len() > 1 => noise * (0.5 / ((var.numel() as i64 / out).max(1) as f64).sqrt()),
                _ if name.ends_with("weight") => noise * 0.2 + 1.0,
                _ => noise * 0.2,
            };
            var.copy_(&value);
        }
    });
}

/// Writes `cases` to `dir/cases.json` and runs the PyTorch side, `script` (a path from the
/// repository root), on it; prints its output into the test's log.
pub fn run_reference(script: &str, cases: &[serde_json::Value], dir: &Path) {
    let path = dir.join("cases.json");
    std::fs::write(&path, serde_json::to_vec(cases).expect("json")).expect("write cases");
    let script = repo_root().join(script);
    let cwd = script.parent().expect("script dir");
    eprintln!("{}", python(cwd, &[script.to_str().expect("utf-8 path"), path.to_str().expect("utf-8 path")]));
}

/// Runs the project's Python (`.venv`, one OpenMP thread, so that the references compute the
/// same way on every machine) with `args` in `cwd`; asserts that it succeeded and returns its
/// output.
pub fn python(cwd: &Path, args: &[&str]) -> String {
    let python = repo_root().join(".venv/bin/python");
    let out = Command::new(&python)
        .args(args)
        .current_dir(cwd)
        .env("OMP_NUM_THREADS", "1")
        .output()
        .unwrap_or_else(|e| panic!("cannot run {} (run `make setup`): {e}", python.display()));
    let log = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "python {args:?} failed:\n{log}");
    log
}
