//! Cross-check of the native denoisers against an independent PyTorch implementation
//! (`tests/python/nets_reference.py`): the Rust side builds each network, draws every weight,
//! saves the weights and some inputs as safetensors, and the Python side loads the same file
//! with `load_state_dict(strict = True)` (so the parameter names and shapes must agree exactly)
//! and runs its own forward pass. Outputs must agree to 1e-4 in float32. The other direction
//! too: weights written by PyTorch (a fresh `state_dict()`) load strictly here and reproduce
//! PyTorch's outputs.
//!
//! Needs the project's venv (`make setup`), which the libtorch build needs anyway.

use relreward_server::engine::denoiser::Denoiser;
use relreward_server::engine::manifest::{Architecture, Space};
use relreward_server::engine::nets::NativeDenoiser;
use tch::{Device, Tensor};

mod common;
use common::{randomize, run_reference};
use relreward_server::engine::rng::Rng;

const TOLERANCE: f64 = 1e-4;

struct Case {
    architecture: Architecture,
    space: Space,
    t: Vec<i64>,
}

#[test]
fn nets_match_pytorch_in_both_directions() {
    let trajectory = |horizon| Space::Trajectory { horizon, action_dim: 2, obs_dim: 4 };
    let cases = [
        Case {
            architecture: Architecture::TemporalUnet { dim: 32, dim_mults: vec![1, 2, 4, 8] },
            space: trajectory(32),
            t: vec![0, 7, 19],
        },
        Case {
            architecture: Architecture::TemporalUnet { dim: 32, dim_mults: vec![1, 4, 8] },
            space: trajectory(16),
            t: vec![3, 50, 99],
        },
        Case {
            architecture: Architecture::Mlp { hidden: vec![64, 32] },
            space: Space::Sample { shape: vec![4, 3, 2] },
            t: vec![1, 10, 999],
        },
        Case { architecture: Architecture::Mlp { hidden: vec![128, 64, 32] }, space: trajectory(8), t: vec![0, 2, 4] },
    ];

    // The test's own generator: the weights are visited in name order and drawn from it, so
    // every run (and every CPU) compares the same networks on the same inputs.
    let mut rng = Rng::new(0);
    let dir = tempfile::tempdir().expect("tempdir");
    let mut jobs = Vec::new();
    let mut expected = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        let d = NativeDenoiser::new(&case.architecture, &case.space, None, 0, Device::Cpu).expect("build");
        randomize(d.weights().var_store(), &mut rng);
        let weights = dir.path().join(format!("weights-{i}.safetensors"));
        d.save(&weights).expect("save weights");

        let mut shape = vec![case.t.len() as i64];
        shape.extend_from_slice(d.item_shape());
        let x = rng.randn(&shape, Device::Cpu);
        let t = Tensor::from_slice(&case.t);
        let inputs = dir.path().join(format!("inputs-{i}.safetensors"));
        Tensor::write_safetensors(&[("x", &x), ("t", &t)], &inputs).expect("write inputs");

        let y = tch::no_grad(|| d.forward(&x, &t, None)).expect("rust forward");
        assert!(y.abs().max().double_value(&[]) > 1e-3, "case {i}: output is trivially zero");
        expected.push((x, t, y));
        jobs.push(serde_json::json!({
            "architecture": case.architecture,
            "space": case.space,
            "weights": weights,
            "inputs": inputs,
            "output": dir.path().join(format!("output-{i}.safetensors")),
            "torch_weights": dir.path().join(format!("torch-weights-{i}.safetensors")),
        }));
    }
    run_reference("tests/python/nets_reference.py", &jobs, dir.path());

    let max_diff = |a: &Tensor, b: &Tensor| {
        assert_eq!(a.size(), b.size());
        (a - b).abs().max().double_value(&[])
    };
    for (i, (case, (x, t, y))) in cases.iter().zip(&expected).enumerate() {
        let outputs =
            Tensor::read_safetensors(dir.path().join(format!("output-{i}.safetensors"))).expect("read output");
        let output = |name: &str| outputs.iter().find(|(n, _)| n == name).map(|(_, t)| t).expect(name);

        // Rust weights, PyTorch forward.
        let diff = max_diff(y, output("y"));
        eprintln!("case {i} {:?}: rust weights, max |rust - pytorch| = {diff:e}", case.architecture);
        assert!(diff < TOLERANCE, "case {i} {:?}: max abs difference {diff} >= {TOLERANCE}", case.architecture);

        // PyTorch weights, Rust forward.
        let torch_weights = dir.path().join(format!("torch-weights-{i}.safetensors"));
        let d = NativeDenoiser::load(&case.architecture, &case.space, &torch_weights, None, Device::Cpu)
            .expect("PyTorch's state dict loads strictly");
        let y_rust = tch::no_grad(|| d.forward(x, t, None)).expect("rust forward");
        let diff = max_diff(&y_rust, output("y_torch"));
        eprintln!("case {i} {:?}: pytorch weights, max |rust - pytorch| = {diff:e}", case.architecture);
        assert!(diff < TOLERANCE, "case {i} {:?}: max abs difference {diff} >= {TOLERANCE}", case.architecture);
    }
}
