//! Cross-check of the relative reward networks against an independent PyTorch implementation
//! (`tests/python/reward_nets_reference.py`): the Rust side builds each network, perturbs every
//! weight, saves the weights, inputs and a random gradient target as safetensors; the Python
//! side loads the same file with `load_state_dict(strict = True)` (so parameter names and shapes
//! must agree exactly) and computes rho, the per-window (and per-step) values, grad_x rho, and
//! the parameter gradient of the double-backward loss of Algorithm 1,
//! mean_b || grad_x rho(x_b, t_b) - target_b ||^2 (`torch.autograd.grad(..., create_graph=True)`),
//! which the Rust side computes both through autograd and as training does, without it
//! (`RewardNet::alignment_gradients`). All must agree to 1e-4 in float32, relative to the magnitude of the values when it exceeds 1.
//! The other direction too: a fresh PyTorch state dict loads strictly here and reproduces rho.
//!
//! Needs the project's venv (`make setup`), which the libtorch build needs anyway.

use std::collections::BTreeMap;

use relreward_server::engine::nets::{RewardArchitecture, RewardNet};
use tch::{Device, Kind, Tensor};

mod common;
use common::run_reference;
use relreward_server::engine::rng::Rng;

const TOLERANCE: f64 = 1e-4;

/// Moves every weight off its initial value so that GroupNorm's affine parameters and every
/// bias take part in the comparison, at scales that keep activations of order one (noise of
/// 0.5 / sqrt(fan_in) on weight matrices and kernels, 0.2 on vectors). The weights are visited in
/// name order and the noise comes from the test's own generator, so that every run on every CPU
/// compares the same networks (the var store's map has no fixed order, and libtorch's normal
/// draws depend on the CPU's vector unit).
fn perturb(net: &RewardNet, rng: &mut Rng) {
    let mut vars: Vec<(String, Tensor)> = net.weights().var_store().variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    tch::no_grad(|| {
        for (_, mut var) in vars {
            let size = var.size();
            let scale = match size.as_slice() {
                [out, ..] if size.len() > 1 => 0.5 / ((var.numel() as i64 / out).max(1) as f64).sqrt(),
                _ => 0.2,
            };
            let noise = rng.randn(&size, Device::Cpu) * scale;
            let _ = var.f_add_(&noise).expect("perturb");
        }
    });
}

fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size());
    (a - b).abs().max().double_value(&[])
}

fn max_abs(a: &Tensor) -> f64 {
    a.abs().max().double_value(&[])
}

struct Case {
    architecture: RewardArchitecture,
    item_shape: Vec<i64>,
    t: Vec<i64>,
}

#[test]
fn reward_nets_match_pytorch_including_the_double_backward() {
    let windowed = |window, hidden: &[usize]| RewardArchitecture::WindowedMlp { window, hidden: hidden.to_vec() };
    let value_function = |widths: &[usize]| RewardArchitecture::ValueFunction { widths: widths.to_vec() };
    let conv_encoder = |widths: &[usize]| RewardArchitecture::ConvEncoder { widths: widths.to_vec() };
    let cases = [
        Case { architecture: windowed(4, &[128, 64, 32]), item_shape: vec![16, 6], t: vec![0, 7, 19] },
        Case { architecture: windowed(1, &[32]), item_shape: vec![8, 6], t: vec![3, 50, 99] },
        Case { architecture: windowed(8, &[32, 16]), item_shape: vec![8, 4], t: vec![1, 2] },
        // Walker2d size (horizon 32, 23 = 6 actions + 17 observations) with the paper's widths.
        Case { architecture: value_function(&[64, 64, 128, 128]), item_shape: vec![32, 23], t: vec![0, 19] },
        // HalfCheetah's horizon 4 (lengths stay at 1), and a long horizon (final length 4).
        Case { architecture: value_function(&[16, 64]), item_shape: vec![4, 6], t: vec![5, 9] },
        Case { architecture: value_function(&[16, 32, 64]), item_shape: vec![128, 3], t: vec![2, 17] },
        Case { architecture: conv_encoder(&[16, 32, 64]), item_shape: vec![4, 16, 16], t: vec![0, 25, 49] },
        Case { architecture: conv_encoder(&[16, 32]), item_shape: vec![3, 7, 5], t: vec![1, 8] },
        Case {
            architecture: RewardArchitecture::Mlp { hidden: vec![64, 32] },
            item_shape: vec![4, 3, 2],
            t: vec![1, 10, 999],
        },
    ];

    // Initial weights from libtorch's uniform draws (seeded), the perturbation and the inputs
    // from the test's own generator.
    tch::manual_seed(0);
    let mut rng = Rng::new(0);
    let dir = tempfile::tempdir().expect("tempdir");
    let mut jobs = Vec::new();
    let mut expected = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        let net = RewardNet::new(&case.architecture, &case.item_shape, 0, Device::Cpu).expect("build");
        perturb(&net, &mut rng);
        let weights = dir.path().join(format!("weights-{i}.safetensors"));
        net.save(&weights).expect("save weights");

        let mut shape = vec![case.t.len() as i64];
        shape.extend_from_slice(&case.item_shape);
        let x = rng.randn(&shape, Device::Cpu);
        let t = Tensor::from_slice(&case.t);
        let target = rng.randn(&shape, Device::Cpu);
        let inputs = dir.path().join(format!("inputs-{i}.safetensors"));
        Tensor::write_safetensors(&[("x", &x), ("t", &t), ("target", &target)], &inputs).expect("write inputs");

        let rho = tch::no_grad(|| net.rho(&x, &t)).expect("rho");
        let per_window = tch::no_grad(|| net.per_window(&x, &t)).expect("per window");
        let per_step = net.is_windowed().then(|| tch::no_grad(|| net.per_step(&x, &t)).expect("per step"));
        let (rho_from_grad, grad_x) = tch::no_grad(|| net.grad(&x, &t)).expect("grad");
        assert_eq!(max_diff(&rho, &rho_from_grad), 0.0);

        // The double backward of Algorithm 1.
        let graph_grad = net.grad_create_graph(&x, &t).expect("grad with graph");
        let batch = case.t.len() as f64;
        let loss = (&graph_grad - &target).square().sum(Kind::Float) / batch;
        loss.backward();
        let param_grads: BTreeMap<String, Tensor> = net
            .weights()
            .var_store()
            .variables()
            .into_iter()
            .map(|(name, var)| {
                let g = var.grad();
                (name, if g.defined() { g.detach().copy() } else { var.zeros_like() })
            })
            .collect();
        // The same loss's gradients as training computes them, without autograd (the MLPs'
        // closed form, the convolutional rewards' sweeps).
        let computed = net.alignment_gradients(&x, &t, &target, None, 0.0).expect("alignment gradients");
        let (computed_loss, autograd_loss) = (computed.loss.double_value(&[]), loss.double_value(&[]));
        assert!(
            (computed_loss - autograd_loss).abs() <= 1e-6 * autograd_loss.abs().max(1.0),
            "case {i}: training's loss {computed_loss} against autograd's {autograd_loss}"
        );
        let computed: BTreeMap<String, Tensor> = computed.grads.into_iter().collect();
        assert_eq!(computed.len(), param_grads.len(), "case {i}: one computed gradient per parameter");
        assert!(max_abs(&rho) > 1e-3, "case {i}: rho is trivially zero");
        assert!(max_abs(&grad_x) > 1e-3, "case {i}: grad_x is trivially zero");
        let grads = [("autograd", param_grads), ("training's", computed)];
        expected.push((x, t, rho, per_window, per_step, grad_x, grads, loss.double_value(&[])));
        jobs.push(serde_json::json!({
            "architecture": case.architecture,
            "item_shape": case.item_shape,
            "weights": weights,
            "inputs": inputs,
            "output": dir.path().join(format!("output-{i}.safetensors")),
            "torch_weights": dir.path().join(format!("torch-weights-{i}.safetensors")),
        }));
    }
    run_reference("tests/python/reward_nets_reference.py", &jobs, dir.path());

    for (i, (case, (x, t, rho, per_window, per_step, grad_x, grads, loss))) in cases.iter().zip(&expected).enumerate() {
        let arch = &case.architecture;
        let outputs: BTreeMap<String, Tensor> =
            Tensor::read_safetensors(dir.path().join(format!("output-{i}.safetensors")))
                .expect("read output")
                .into_iter()
                .collect();
        let output = |name: &str| outputs.get(name).unwrap_or_else(|| panic!("case {i}: output {name} missing"));
        // float32 rounding grows with the values (different CPUs pick different kernels: a
        // grad_x of magnitude 3.9 differed by 1.9e-4 on CI), so the tolerance is relative to the
        // largest value once it exceeds 1, as the module comment says.
        let check = |what: &str, ours: &Tensor, theirs: &Tensor, tolerance: f64| {
            let diff = max_diff(ours, theirs);
            let magnitude = max_abs(theirs);
            eprintln!("case {i} {arch}: {what}: max |rust - pytorch| = {diff:.3e} (max |value| {magnitude:.3e})");
            let allowed = tolerance * magnitude.max(1.0);
            assert!(diff < allowed, "case {i} {arch}: {what} differs by {diff} >= {allowed}");
        };

        check("rho", rho, output("rho"), TOLERANCE);
        check("per_window", per_window, output("per_window"), TOLERANCE);
        if let Some(per_step) = per_step {
            check("per_step", per_step, output("per_step"), TOLERANCE);
        }
        check("grad_x", grad_x, output("grad_x"), TOLERANCE);
        let torch_loss = output("loss").double_value(&[0]);
        assert!(
            (loss - torch_loss).abs() <= TOLERANCE * torch_loss.abs().max(1.0),
            "case {i}: loss {loss} vs {torch_loss}"
        );

        // Parameter gradients of the double-backward loss, relative to the largest of them:
        // relreward's autograd and the gradients training takes, each against PyTorch's.
        for (how, param_grads) in grads {
            let scale = param_grads.values().map(max_abs).fold(1.0f64, f64::max);
            let mut worst = 0.0f64;
            let mut nonzero = 0;
            for (name, ours) in param_grads {
                let theirs = output(&format!("grad.{name}"));
                let diff = max_diff(ours, theirs);
                assert!(
                    diff <= TOLERANCE * scale,
                    "case {i} {arch}: {how} d loss / d {name} differs by {diff} (scale {scale})"
                );
                worst = worst.max(diff);
                nonzero += usize::from(max_abs(ours) > 0.0);
            }
            assert!(nonzero + 1 >= param_grads.len(), "case {i}: only {nonzero} parameters receive gradients");
            eprintln!(
                "case {i} {arch}: {how} d loss / d theta: max |rust - pytorch| = {worst:.3e} (scale {scale:.3e})"
            );
        }

        // PyTorch weights, Rust forward.
        let torch_weights = dir.path().join(format!("torch-weights-{i}.safetensors"));
        let net = RewardNet::load(arch, &case.item_shape, &torch_weights, Device::Cpu)
            .expect("PyTorch's state dict loads strictly");
        let rho_rust = tch::no_grad(|| net.rho(x, t)).expect("rho");
        check("rho with PyTorch's weights", &rho_rust, output("rho_torch"), TOLERANCE);
    }
}
