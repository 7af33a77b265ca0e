//! Unit tests of the reward networks: every architecture at a small size (rho, windows and
//! steps, gradients against finite differences, the double backward, names, counts, strict
//! files).

use std::collections::BTreeMap;

use super::*;
use crate::engine::nets::kernels;

const CPU: Device = Device::Cpu;

fn windowed(window: usize, hidden: &[usize]) -> RewardArchitecture {
    RewardArchitecture::WindowedMlp { window, hidden: hidden.to_vec() }
}

fn value_function(widths: &[usize]) -> RewardArchitecture {
    RewardArchitecture::ValueFunction { widths: widths.to_vec() }
}

fn conv_encoder(widths: &[usize]) -> RewardArchitecture {
    RewardArchitecture::ConvEncoder { widths: widths.to_vec() }
}

fn mlp(hidden: &[usize]) -> RewardArchitecture {
    RewardArchitecture::Mlp { hidden: hidden.to_vec() }
}

fn build(arch: &RewardArchitecture, item_shape: &[i64]) -> RewardNet {
    build_on(arch, item_shape, CPU)
}

fn build_on(arch: &RewardArchitecture, item_shape: &[i64], device: Device) -> RewardNet {
    RewardNet::new(arch, item_shape, 0, device).expect("reward network builds")
}

/// Where the derivation checks (`reward_closed_form_*`) run: the CPU, or the first CUDA device
/// with RELREWARD_TEST_DEVICE=cuda (`tests/bench/gpu.sh` runs them there first: on a GPU the
/// CPU kernels decline and the sweeps take libtorch's operations, the path its jobs use).
fn check_device() -> Device {
    match std::env::var("RELREWARD_TEST_DEVICE").as_deref() {
        Err(_) | Ok("" | "cpu") => CPU,
        Ok("cuda") => Device::Cuda(0),
        Ok(other) => panic!("RELREWARD_TEST_DEVICE: expected cpu or cuda, got {other:?}"),
    }
}

/// float32's tolerance in the derivation checks for `arch`: `cpu` on the CPU, and on a GPU for
/// the MLPs (cuBLAS's TF32 is off by default); 1e-2 for the convolutional rewards on a GPU,
/// whose float32 convolutions libtorch runs in TF32 there by default (cuDNN's allow_tf32, a
/// 10-bit mantissa). float64 keeps 1e-10 everywhere.
fn float32_tolerance(device: Device, arch: &RewardArchitecture, cpu: f64) -> f64 {
    let convolutional =
        matches!(arch, RewardArchitecture::ValueFunction { .. } | RewardArchitecture::ConvEncoder { .. });
    if device != CPU && convolutional { 1e-2 } else { cpu }
}

/// Deterministic pseudo-random values in [-1, 1) (a sine hash): the tests do not draw from
/// libtorch's global generator, which tests running in parallel threads share.
fn pseudo_random(shape: &[i64], seed: f64, kind: Kind) -> Tensor {
    let n: i64 = shape.iter().product();
    let hashed = ((Tensor::arange(n, (Kind::Double, CPU)) * 12.9898 + seed * 78.233).sin() * 43758.5453).frac();
    let unit = &hashed - hashed.floor();
    (unit * 2.0 - 1.0).reshape(shape).to_kind(kind)
}

/// Replaces every weight with deterministic values at PyTorch-like scales (GroupNorm
/// weights around 1, biases around 0): moves every weight off its initial value.
fn perturb(net: &RewardNet) {
    let variables: BTreeMap<String, Tensor> = net.weights().var_store().variables().into_iter().collect();
    tch::no_grad(|| {
        for (i, (name, mut var)) in variables.into_iter().enumerate() {
            let size = var.size();
            let noise = pseudo_random(&size, i as f64 + 0.5, var.kind());
            let value = match size.as_slice() {
                [out, ..] if size.len() > 1 => {
                    let fan_in = (var.numel() as i64 / out).max(1) as f64;
                    noise * (1.5 / fan_in.sqrt())
                }
                _ if name.ends_with(".weight") => noise * 0.3 + 1.0,
                _ => noise * 0.3,
            };
            var.copy_(&value);
        }
    });
}

/// A batch of inputs on the net's device.
fn inputs(net: &RewardNet, batch: i64, kind: Kind) -> (Tensor, Tensor) {
    let mut shape = vec![batch];
    shape.extend_from_slice(net.item_shape());
    let device = net.weights().var_store().device();
    let x = (pseudo_random(&shape, 0.25, kind) * 1.5).to_device(device);
    let t = (Tensor::arange(batch, (Kind::Int64, CPU)) * 7 + 1).to_device(device);
    (x, t)
}

fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size());
    (a - b).abs().max().double_value(&[])
}

/// Asserts max |a - b| <= tolerance * max(1, max |b|) (float32 rounding scales with the
/// values).
#[track_caller]
fn assert_close(a: &Tensor, b: &Tensor, tolerance: f64, what: &str) {
    let diff = max_abs_diff(a, b);
    let scale = b.abs().max().double_value(&[]).max(1.0);
    assert!(diff <= tolerance * scale, "{what}: max |difference| {diff:e} exceeds {tolerance:e} * {scale}");
}

fn invalid_message<T: std::fmt::Debug>(result: Result<T>) -> String {
    match result {
        Err(Error::InvalidArgument(msg)) => msg,
        other => panic!("expected InvalidArgument, got {other:?}"),
    }
}

/// Every architecture at a small size, with its item shape. Widths keep at least two
/// channels per GroupNorm group (w / 4 = 16 in the value function's mid blocks): with one
/// channel per group a convolution's bias is normalized away and cannot receive gradients.
fn small_cases() -> Vec<(RewardArchitecture, Vec<i64>)> {
    vec![
        (windowed(4, &[32, 16]), vec![16, 3]),
        (windowed(1, &[16]), vec![8, 3]),
        (value_function(&[16, 64]), vec![16, 3]),
        (value_function(&[16, 64]), vec![64, 3]),
        (conv_encoder(&[16, 32]), vec![3, 7, 5]),
        (mlp(&[16, 8]), vec![2, 3, 2]),
    ]
}

#[test]
fn reward_windowed_rho_is_the_mean_of_its_windows() {
    let net = build(&windowed(4, &[32, 16]), &[16, 3]);
    perturb(&net);
    let (x, t) = inputs(&net, 3, Kind::Float);
    let rho = tch::no_grad(|| net.rho(&x, &t)).expect("rho");
    let windows = tch::no_grad(|| net.per_window(&x, &t)).expect("per window");
    assert_eq!(rho.size(), [3]);
    assert_eq!(windows.size(), [3, 4]);
    assert_close(&rho, &windows.mean_dim(1, false, Kind::Float), 1e-6, "rho vs mean of windows");
    // One pass for both (what Score with per_window runs) gives the same numbers, bit for bit,
    // for every architecture.
    let (rho1, windows1) = tch::no_grad(|| net.rho_and_windows(&x, &t)).expect("one pass");
    assert_eq!((max_abs_diff(&rho1, &rho), max_abs_diff(&windows1, &windows)), (0.0, 0.0));
    for (arch, shape) in small_cases().into_iter().skip(2) {
        let other = build(&arch, &shape);
        let (x, t) = inputs(&other, 3, Kind::Float);
        let (r, w) = tch::no_grad(|| other.rho_and_windows(&x, &t)).expect("one pass");
        let apart = tch::no_grad(|| other.rho(&x, &t)).expect("rho");
        assert_eq!((max_abs_diff(&r, &apart), w.size()), (0.0, vec![3, 1]), "{arch}");
    }
    // Not the sum, and not trivially constant.
    assert!(max_abs_diff(&rho, &windows.sum_dim_intlist(1, false, Kind::Float)) > 1e-3);
    assert!(windows.std(true).double_value(&[]) > 1e-3);

    // Every 4th per-step value is a per-window value.
    let steps = tch::no_grad(|| net.per_step(&x, &t)).expect("per step");
    assert_eq!(steps.size(), [3, 16]);
    let aligned = steps.slice(1, 0, 16, 4);
    assert_close(&aligned, &windows, 1e-6, "every h-th step vs windows");
}

#[test]
fn reward_windowed_per_step_values_line_up_with_states() {
    let (h, horizon) = (4i64, 16i64);
    let net = build(&windowed(4, &[32, 16]), &[horizon, 3]);
    perturb(&net);
    let (x, t) = inputs(&net, 2, Kind::Float);
    let run = |x: &Tensor| {
        tch::no_grad(|| (net.per_step(x, &t).expect("per step"), net.per_window(x, &t).expect("per window")))
    };
    let (steps, windows) = run(&x);
    for k in [0i64, 6, 9, 15] {
        let changed = x.copy();
        let _ = changed.narrow(1, k, 1).f_add_scalar_(0.5).expect("edit");
        let (steps2, windows2) = run(&changed);
        let step_moved = (&steps2 - &steps).abs().amax(0, false);
        let window_moved = (&windows2 - &windows).abs().amax(0, false);
        for j in 0..horizon {
            let moved = step_moved.double_value(&[j]) > 1e-6;
            assert_eq!(moved, (k - h + 1..=k).contains(&j), "state {k}: per_step[{j}] moved = {moved}");
        }
        for w in 0..horizon / h {
            let moved = window_moved.double_value(&[w]) > 1e-6;
            assert_eq!(moved, w == k / h, "state {k}: per_window[{w}] moved = {moved}");
        }
    }
}

#[test]
fn reward_windowed_per_step_pads_by_repeating_the_last_row() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (h, horizon, d) = (4i64, 12i64, 3i64);
    let arch = windowed(4, &[32, 16]);
    let net = build(&arch, &[horizon, d]);
    perturb(&net);
    let path = dir.path().join("windowed.safetensors");
    net.save(&path).expect("save");
    // The same weights score single windows: they depend on h and D only.
    let single = RewardNet::load(&arch, &[h, d], &path, CPU).expect("loads for another horizon");

    let (x, t) = inputs(&net, 2, Kind::Float);
    let steps = tch::no_grad(|| net.per_step(&x, &t)).expect("per step");
    let last = x.narrow(1, horizon - 1, 1);
    let padded = Tensor::cat(&[x.shallow_clone(), last.repeat([1, h - 1, 1])], 1);
    for k in 0..horizon {
        let window = padded.narrow(1, k, h).contiguous();
        let value = tch::no_grad(|| single.rho(&window, &t)).expect("window rho");
        assert_close(&value, &steps.select(1, k), 1e-6, &format!("step {k} vs its padded window"));
    }

    // h = 1: per-step and per-window values coincide.
    let net1 = build(&windowed(1, &[16]), &[8, 3]);
    perturb(&net1);
    let (x, t) = inputs(&net1, 2, Kind::Float);
    let steps = tch::no_grad(|| net1.per_step(&x, &t)).expect("per step");
    let windows = tch::no_grad(|| net1.per_window(&x, &t)).expect("per window");
    assert_eq!(steps.size(), [2, 8]);
    assert_close(&steps, &windows, 1e-6, "h = 1: steps vs windows");
}

#[test]
fn reward_window_must_divide_the_horizon() {
    let msg = invalid_message(RewardNet::new(&windowed(4, &[32]), &[30, 6], 0, CPU));
    assert!(msg.contains("horizon 30 is not divisible by window 4"), "{msg}");
    assert!(msg.contains("architecture.window"), "{msg}");
}

#[test]
fn reward_non_windowed_nets_have_one_window_and_no_steps() {
    for (arch, shape) in small_cases().into_iter().skip(2) {
        let net = build(&arch, &shape);
        let (x, t) = inputs(&net, 2, Kind::Float);
        let rho = tch::no_grad(|| net.rho(&x, &t)).expect("rho");
        let windows = tch::no_grad(|| net.per_window(&x, &t)).expect("per window");
        assert_eq!(windows.size(), [2, 1]);
        assert_close(&windows.squeeze_dim(1), &rho, 1e-6, "one window vs rho");
        assert!(!net.is_windowed());
        let msg = invalid_message(net.per_step(&x, &t));
        assert!(msg.contains("per-step values need a windowed reward"), "{msg}");
    }
}

/// Central finite differences of rho in float64 against `grad`, for every architecture,
/// also from inside a no-grad region.
/// A replica (another thread's handle, `RewardNet::replica`) shares the weights' storage, so it
/// costs no copy and sees what the original holds, and evaluates to the same values bit for
/// bit, on another thread too.
#[test]
fn a_replica_shares_the_weights_and_evaluates_alike_on_another_thread() {
    for (arch, shape) in small_cases() {
        let net = build(&arch, &shape);
        perturb(&net);
        let replica = net.replica().expect("replica");
        let originals = net.weights().var_store().variables();
        let shared = replica.weights().var_store().variables();
        assert_eq!(originals.len(), shared.len(), "{arch:?}");
        for (name, var) in &originals {
            assert_eq!(var.data_ptr(), shared[name].data_ptr(), "{arch:?}: '{name}' was copied");
        }
        let (x, t) = inputs(&net, 5, Kind::Float);
        let (rho, grad) = net.grad(&x, &t).expect("grad");
        let (x2, t2) = (x.shallow_clone(), t.shallow_clone());
        let (rho2, grad2) = std::thread::spawn(move || replica.grad(&x2, &t2).expect("replica grad"))
            .join()
            .expect("the replica's thread");
        assert!(rho.equal(&rho2) && grad.equal(&grad2), "{arch:?}: the replica's values differ");
    }
}

#[test]
fn reward_grad_matches_finite_differences() {
    for (arch, shape) in small_cases() {
        let mut net = build(&arch, &shape);
        perturb(&net);
        net.weights_mut().var_store_mut().double();
        assert_eq!(net.kind(), Kind::Double);
        let (x, t) = inputs(&net, 2, Kind::Double);
        let (rho, grad) = tch::no_grad(|| net.grad(&x, &t)).expect("grad inside no_grad");
        assert_eq!(grad.size(), x.size());
        assert!(!rho.requires_grad() && !grad.requires_grad());
        let (rho_outside, grad_outside) = net.grad(&x, &t).expect("grad");
        assert_eq!(max_abs_diff(&rho, &rho_outside), 0.0);
        assert_eq!(max_abs_diff(&grad, &grad_outside), 0.0);
        // Parameter gradients are not accumulated by `grad`.
        assert!(net.weights().var_store().variables().values().all(|v| !v.grad().defined()));

        let flat_x = x.reshape([-1]);
        let flat_grad = grad.reshape([-1]);
        let eps = 1e-5;
        let n = flat_x.size()[0];
        let scale = flat_grad.abs().max().double_value(&[]);
        let mut worst = 0.0f64;
        for index in (0..n).step_by(usize::try_from((n / 24).max(1)).expect("step")) {
            // d sum(rho) / dx: the sum also catches any coupling between batch items.
            let bump = |delta: f64| {
                let y = flat_x.copy();
                let _ = y.narrow(0, index, 1).f_add_scalar_(delta).expect("bump");
                tch::no_grad(|| net.rho(&y.reshape(x.size()), &t)).expect("rho").sum(Kind::Double).double_value(&[])
            };
            let numeric = (bump(eps) - bump(-eps)) / (2.0 * eps);
            let analytic = flat_grad.double_value(&[index]);
            worst = worst.max((numeric - analytic).abs());
            assert!(
                (numeric - analytic).abs() <= 1e-6 * scale + 1e-9,
                "{arch}: coordinate {index}: finite difference {numeric} vs grad {analytic}"
            );
        }
        eprintln!("{arch}: worst |finite difference - grad| = {worst:.2e} (max |grad| {scale:.2e})");
        assert!(scale > 1e-3, "{arch}: gradient trivially zero");
    }
}

/// The double backward reaches every parameter that grad_x depends on (all but the output
/// bias), and grad_create_graph equals grad.
#[test]
fn reward_double_backward_reaches_the_parameters() {
    for (arch, shape) in small_cases() {
        let net = build(&arch, &shape);
        perturb(&net);
        let (x, t) = inputs(&net, 3, Kind::Float);
        let graph_grad = tch::no_grad(|| net.grad_create_graph(&x, &t)).expect("grad_create_graph");
        assert!(graph_grad.requires_grad());
        let (_, grad) = net.grad(&x, &t).expect("grad");
        assert_close(&graph_grad, &grad, 1e-5, &format!("{arch}: grad_create_graph vs grad"));

        let target = pseudo_random(&x.size(), 0.75, Kind::Float);
        let loss = (&graph_grad - &target).square().sum(Kind::Float) / 3.0;
        loss.backward();
        let output_bias = match &arch {
            RewardArchitecture::WindowedMlp { hidden, .. } | RewardArchitecture::Mlp { hidden } => {
                format!("net.{}.bias", 2 * hidden.len())
            }
            _ => "final_block.2.bias".to_string(),
        };
        for (name, var) in net.weights().var_store().variables() {
            let g = var.grad();
            let size = if g.defined() { g.abs().sum(Kind::Float).double_value(&[]) } else { 0.0 };
            if name == output_bias {
                assert!(size == 0.0, "{arch}: {name} cannot affect grad_x, got {size}");
            } else {
                assert!(size > 0.0, "{arch}: {name} received no gradient through the double backward");
            }
        }
        // No gradient leaks into the caller's x.
        assert!(!x.grad().defined());
    }
}

/// Mish inputs past exp's overflow (every bias raised by 100) leave the double backward
/// finite: libtorch's fused Mish would make every parameter gradient NaN here.
#[test]
fn reward_double_backward_stays_finite_for_large_activations() {
    for (arch, shape) in small_cases() {
        let net = build(&arch, &shape);
        perturb(&net);
        tch::no_grad(|| {
            for (name, var) in net.weights().var_store().variables() {
                if name.ends_with("bias") {
                    let _ = var.shallow_clone().f_add_scalar_(100.0).expect("raise bias");
                }
            }
        });
        let (x, t) = inputs(&net, 3, Kind::Float);
        let graph_grad = tch::no_grad(|| net.grad_create_graph(&x, &t)).expect("grad_create_graph");
        let target = pseudo_random(&x.size(), 0.75, Kind::Float);
        (&graph_grad - &target).square().sum(Kind::Float).backward();
        for (name, var) in net.weights().var_store().variables() {
            let g = var.grad();
            if g.defined() {
                let finite = bool::try_from(g.isfinite().all()).expect("bool");
                assert!(finite, "{arch}: {name}'s gradient is not finite");
            }
        }
    }
}

#[test]
fn reward_parameter_names_and_counts() {
    let net = build(&value_function(&[64, 64, 128, 128]), &[32, 23]);
    let names = net.weights().parameter_names();
    for expected in [
        "time_mlp.1.weight",
        "time_mlp.3.bias",
        "blocks.0.0.blocks.0.block.0.weight",
        "blocks.0.0.residual_conv.weight",
        "blocks.0.0.time_mlp.1.weight",
        "blocks.3.1.blocks.1.block.2.bias",
        "blocks.3.2.conv.weight",
        "mid_block1.residual_conv.weight",
        "mid_down1.conv.weight",
        "mid_block2.blocks.1.block.2.weight",
        "mid_down2.conv.bias",
        "final_block.0.weight",
        "final_block.2.bias",
    ] {
        assert!(names.iter().any(|n| n == expected), "{expected} missing from {names:?}");
    }
    assert!(!names.iter().any(|n| n == "blocks.1.0.residual_conv.weight"), "same widths: identity residual");
    // Horizon 32 through 6 downsamplings: length 1, fc = 128 / 4 = 32.
    let vars = net.weights().var_store().variables();
    assert_eq!(vars["final_block.0.weight"].size(), [16, 32 + 64]);
    assert_eq!(vars["mid_down2.conv.weight"].size(), [32, 32, 3]);
    assert_eq!(
        u128::from(net.parameter_count()),
        RewardNet::planned_parameter_count(&net.architecture, &[32, 23]).expect("plan").into()
    );
    // HalfCheetah's horizon 4: still length 1.
    let cheetah = build(&value_function(&[64, 64, 128, 128]), &[4, 23]);
    assert_eq!(cheetah.weights().var_store().variables()["final_block.0.weight"].size(), [16, 32 + 64]);
    // Horizon 256 with two levels: 256 / 2^4 = 16, fc = 8 * 16.
    let long = build(&value_function(&[16, 32]), &[256, 6]);
    assert_eq!(long.weights().var_store().variables()["final_block.0.weight"].size(), [64, 128 + 16]);

    let net = build(&windowed(4, &[128, 64, 32]), &[256, 6]);
    assert_eq!(
        net.weights().parameter_names(),
        [
            "net.0.bias",
            "net.0.weight",
            "net.2.bias",
            "net.2.weight",
            "net.4.bias",
            "net.4.weight",
            "net.6.bias",
            "net.6.weight",
            "time_mlp.1.bias",
            "time_mlp.1.weight",
            "time_mlp.3.bias",
            "time_mlp.3.weight"
        ]
    );
    // (24 + 32) * 128 + 128, 128 * 64 + 64, 64 * 32 + 32, 32 + 1, time MLP 8352.
    assert_eq!(net.parameter_count(), 7296 + 8256 + 2080 + 33 + 8352);
    assert_eq!(net.describe(), "windowed_mlp(h=4, hidden=[128, 64, 32])");

    let net = build(&conv_encoder(&[32, 64, 128, 256]), &[4, 64, 64]);
    let vars = net.weights().var_store().variables();
    assert_eq!(vars["blocks.0.conv.weight"].size(), [32, 4, 3, 3]);
    assert_eq!(vars["blocks.3.norm.weight"].size(), [256]);
    assert_eq!(vars["blocks.2.time_mlp.1.weight"].size(), [128, 32]);
    assert_eq!(vars["final_block.0.weight"].size(), [128, 256 + 32]);
    assert_eq!(net.describe(), "conv_encoder(widths=[32, 64, 128, 256])");
    for (arch, shape) in small_cases() {
        let net = build(&arch, &shape);
        let planned = RewardNet::planned_parameter_count(&arch, &shape).expect("plan");
        assert_eq!(net.parameter_count(), planned, "{arch}");
    }
}

#[test]
fn reward_inputs_are_checked() {
    let net = build(&value_function(&[8, 32]), &[16, 3]);
    let (x, t) = inputs(&net, 2, Kind::Float);
    let wrong = Tensor::zeros([2, 15, 3], (Kind::Float, CPU));
    let msg = invalid_message(net.rho(&wrong, &t));
    assert!(msg.contains("[2, 15, 3]") && msg.contains("[B >= 1, 16, 3]"), "{msg}");
    assert!(invalid_message(net.grad(&wrong, &t)).contains("reward input x"));
    assert!(invalid_message(net.rho(&x.to_kind(Kind::Double), &t)).contains("Float"));
    assert!(invalid_message(net.rho(&x, &t.to_kind(Kind::Float))).contains("reward input t"));
    assert!(invalid_message(net.grad_create_graph(&x, &t.narrow(0, 0, 1))).contains("reward input t"));
    let empty = Tensor::zeros([0, 16, 3], (Kind::Float, CPU));
    assert!(invalid_message(net.rho(&empty, &t.narrow(0, 0, 0))).contains("reward input x"));
}

#[test]
fn reward_invalid_architectures_name_the_field() {
    let cases = [
        (windowed(0, &[32]), vec![16, 6], "architecture.window"),
        (windowed(4, &[]), vec![16, 6], "architecture.hidden"),
        (windowed(4, &[32, 0]), vec![16, 6], "architecture.hidden"),
        (windowed(4, &[32]), vec![4, 4, 4], "trajectory item shape"),
        (windowed(4, &[32]), vec![16, 0], "item shape"),
        (windowed(usize::MAX, &[32]), vec![16, 6], "architecture.window"),
        (value_function(&[]), vec![32, 6], "architecture.widths"),
        (value_function(&[12, 32]), vec![32, 6], "architecture.widths: 12"),
        (value_function(&[8, 16]), vec![32, 6], "last width 16"),
        (value_function(&[64, 64, 128, 128]), vec![48, 6], "horizon 48"),
        (value_function(&[64, 64, 128, 128]), vec![12, 6], "horizon 12"),
        (value_function(&[32]), vec![6], "trajectory item shape"),
        (conv_encoder(&[32, 20]), vec![4, 8, 8], "architecture.widths: 20"),
        (conv_encoder(&[32]), vec![4, 8], "image-like item shape"),
        (conv_encoder(&[1 << 21]), vec![4, 8, 8], "architecture.widths"),
        (mlp(&[]), vec![4], "architecture.hidden"),
        (mlp(&[1 << 20, 1 << 20]), vec![4], "exceed the limit"),
        (mlp(&[16]), vec![], "item shape"),
        (mlp(&[16]), vec![i64::MAX, 4], "item shape"),
    ];
    for (arch, shape, needle) in cases {
        let msg = invalid_message(RewardNet::new(&arch, &shape, 0, CPU));
        assert!(msg.contains(needle), "{arch} {shape:?}: {msg} should contain {needle}");
    }
    // Powers of two below 2^(levels + 2) are fine (HalfCheetah's horizon 4), as are multiples.
    for horizon in [1, 2, 4, 8, 64, 128, 192] {
        assert!(RewardNet::planned_parameter_count(&value_function(&[64, 64, 128, 128]), &[horizon, 6]).is_ok());
    }
}

#[test]
fn reward_architecture_serde() {
    let arch: RewardArchitecture =
        serde_json::from_str(r#"{"kind": "windowed_mlp", "window": 4, "hidden": [128, 64, 32]}"#).expect("json");
    assert_eq!(arch, windowed(4, &[128, 64, 32]));
    let arch: RewardArchitecture =
        toml::from_str("kind = \"value_function\"\nwidths = [64, 64, 128, 128]").expect("toml");
    assert_eq!(arch, value_function(&[64, 64, 128, 128]));
    let json = serde_json::to_string(&conv_encoder(&[32, 64])).expect("serialize");
    assert_eq!(json, r#"{"kind":"conv_encoder","widths":[32,64]}"#);
    for (text, needle) in [
        (r#"{"kind": "mlp", "hidden": [8], "extra": 1}"#, "unknown field `extra`"),
        (r#"{"kind": "transformer"}"#, "unknown variant `transformer`"),
    ] {
        let err = serde_json::from_str::<RewardArchitecture>(text).expect_err(needle).to_string();
        assert!(err.contains(needle), "{err} should contain {needle}");
    }
    // A field left out takes the schema's default for the kind (the wire's default too).
    let arch: RewardArchitecture = serde_json::from_str(r#"{"kind": "windowed_mlp", "hidden": [8]}"#).expect("default");
    assert_eq!(arch, windowed(relreward_proto::schema::job::DEFAULT_WINDOW, &[8]));
    assert_eq!(mlp(&[8]).to_string(), "mlp(hidden=[8])");
    assert_eq!(value_function(&[8, 32]).to_string(), "value_function(widths=[8, 32])");
}

#[test]
fn reward_save_then_load_reproduces_rho_exactly() {
    let dir = tempfile::tempdir().expect("tempdir");
    for (i, (arch, shape)) in small_cases().into_iter().enumerate() {
        let original = build(&arch, &shape);
        perturb(&original);
        let path = dir.path().join(format!("reward-{i}.bin"));
        original.save(&path).expect("save");
        let loaded = RewardNet::load(&arch, &shape, &path, CPU).expect("load");
        let (x, t) = inputs(&original, 3, Kind::Float);
        let run = |net: &RewardNet| tch::no_grad(|| net.rho(&x, &t)).expect("rho");
        assert_eq!(max_abs_diff(&run(&original), &run(&loaded)), 0.0, "{arch}");
        assert!(max_abs_diff(&run(&original), &run(&build(&arch, &shape))) > 0.0, "{arch}");
    }
    assert_eq!(std::fs::read_dir(dir.path()).expect("list").count(), small_cases().len(), "no temporary files");
}

#[test]
fn reward_strict_loading_rejects_mismatched_files() {
    let dir = tempfile::tempdir().expect("tempdir");
    let arch = value_function(&[8, 32]);
    let shape = [16i64, 3];
    let net = build(&arch, &shape);
    let named: Vec<(String, Tensor)> = net
        .weights()
        .var_store()
        .variables()
        .into_iter()
        .collect::<BTreeMap<_, _>>()
        .into_iter()
        .map(|(n, t)| (n, t.detach().contiguous()))
        .collect();
    let write = |name: &str, tensors: &[(String, Tensor)]| {
        let path = dir.path().join(name);
        Tensor::write_safetensors(tensors, &path).expect("write");
        path
    };
    let victim = "mid_block2.blocks.0.block.2.weight";
    let replace = |with: &dyn Fn(&Tensor) -> Tensor| -> Vec<(String, Tensor)> {
        named.iter().map(|(n, t)| (n.clone(), if n == victim { with(t) } else { t.shallow_clone() })).collect()
    };
    let missing: Vec<_> =
        named.iter().filter(|(n, _)| n != victim).map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
    let wrong_shape = replace(&|_| Tensor::ones([3], (Kind::Float, CPU)));
    let wrong_dtype = replace(&|t| t.to_kind(Kind::Double));
    let mut extra: Vec<_> = named.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
    extra.push(("mid_attn.weight".to_string(), Tensor::ones([2], (Kind::Float, CPU))));
    let mut oversized: Vec<_> = named.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
    oversized.push(("padding".to_string(), Tensor::zeros([1 << 19], (Kind::Float, CPU))));
    let garbage = dir.path().join("garbage.safetensors");
    std::fs::write(&garbage, b"\xff\xff\xff\xff\xff\xff\xff\x7fnot a header").expect("write");
    let cases = [
        (write("missing.safetensors", &missing), format!("missing tensor(s) '{victim}'")),
        (write("shape.safetensors", &wrong_shape), format!("tensor '{victim}' has shape [3], expected [8]")),
        (write("dtype.safetensors", &wrong_dtype), format!("tensor '{victim}' has dtype Double")),
        (write("extra.safetensors", &extra), "unexpected tensor(s) 'mid_attn.weight'".to_string()),
        (garbage, "not a valid safetensors file".to_string()),
        (write("oversized.safetensors", &oversized), "more than the".to_string()),
    ];
    let target = build(&arch, &shape);
    let before: BTreeMap<String, Tensor> =
        target.weights().var_store().variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
    for (path, needle) in cases {
        let msg = invalid_message(target.weights().load_strict(&path));
        assert!(msg.contains(&needle), "{msg} should contain {needle}");
        assert!(!msg.contains(&dir.path().display().to_string()), "{msg} leaks the path");
    }
    let after: BTreeMap<String, Tensor> =
        target.weights().var_store().variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
    assert!(before.iter().zip(&after).all(|((na, a), (nb, b))| na == nb && a.equal(b)), "nothing copied");
    // Another architecture's file is refused by name.
    let other = build(&windowed(4, &[16]), &[16, 3]);
    let other_path = dir.path().join("other.safetensors");
    other.save(&other_path).expect("save");
    assert!(invalid_message(target.weights().load_strict(&other_path)).contains("missing tensor(s)"));
    assert!(matches!(target.weights().load_strict(&dir.path().join("absent")), Err(Error::Internal(_))));
}

#[test]
fn reward_net_is_send() {
    fn send<T: Send>() {}
    send::<RewardNet>();
}

#[test]
fn reward_paper_sizes_run() {
    // Walker2d-sized value function and an SD-latent-sized encoder: forward and grad run.
    for (arch, shape) in
        [(value_function(&[64, 64, 128, 128]), vec![32i64, 23]), (conv_encoder(&[32, 64, 128, 256]), vec![4, 32, 32])]
    {
        let net = build(&arch, &shape);
        let (x, t) = inputs(&net, 2, Kind::Float);
        let (rho, grad) = net.grad(&x, &t).expect("grad");
        assert_eq!(rho.size(), [2]);
        assert_eq!(grad.size(), x.size());
        assert!(grad.isfinite().all().int64_value(&[]) == 1);
    }
}

/// The architectures with a closed form (the MLP heads), at small sizes with their item shapes.
fn closed_form_cases() -> Vec<(RewardArchitecture, Vec<i64>)> {
    vec![
        (windowed(4, &[32, 16]), vec![16, 3]),
        (windowed(1, &[16]), vec![8, 3]),
        (windowed(2, &[24, 16, 8]), vec![8, 5]),
        (mlp(&[16, 8]), vec![2, 3, 2]),
        (mlp(&[12]), vec![5]),
    ]
}

/// The convolutional rewards at small sizes: horizons down to one step (every downsampling
/// then keeps length 1), odd and even image sides (the transposed convolutions' output
/// padding), residual blocks with and without their 1x1 convolution.
fn convolutional_cases() -> Vec<(RewardArchitecture, Vec<i64>)> {
    vec![
        (value_function(&[8, 32]), vec![8, 3]),
        (value_function(&[16, 16, 32]), vec![16, 5]),
        (value_function(&[32]), vec![4, 2]),
        (value_function(&[8, 32]), vec![1, 4]),
        (value_function(&[16, 32]), vec![64, 3]),
        (conv_encoder(&[8, 16]), vec![3, 7, 5]),
        (conv_encoder(&[16]), vec![4, 8, 8]),
        (conv_encoder(&[16, 16]), vec![1, 1, 3]),
    ]
}

/// The alignment gradients without autograd (`closed_form.rs` for the MLP heads, the sweeps
/// of `blocks/second_order.rs` for the convolutional rewards) against autograd's double
/// backward of the same loss (`relative_reward::alignment_loss`) in float64: the loss and every
/// parameter's gradient, for every architecture at several sizes, with and without entry
/// weights and rho's L2 penalty, at several seeds; in float64 to 1e-10 (the derivation), in
/// float32 to 1e-5 (the bar), except where group norms see two values a group (below). Also
/// with the biases of the first linear layers raised by 30, past Mish's pass-through (where the
/// second derivative is 0).
///
/// float32 is compared with the float64 reference rather than with autograd's own float32
/// result, which is no closer to it: on the convolutional cases the two are off the reference
/// by similar amounts. Two cases are ill-conditioned in float32 by design, a horizon of one
/// step (the value function's mid blocks normalize groups of 2 values and 1) and a 1 x 3 image
/// (the encoder's last block, groups of 2 pixels): their variances come near the norm's eps,
/// rstd near 1 / sqrt(eps), and rounding grows with rstd squared; autograd's float32 double
/// backward is up to 8.6e-5 off there, these sweeps up to 3.2e-5, hence 1e-4 for them.
#[test]
fn reward_closed_form_alignment_gradients_equal_autograd() {
    let device = check_device();
    let ill_conditioned = |shape: &[i64]| shape == [1, 4] || shape == [1, 1, 3];
    for (arch, shape) in closed_form_cases().into_iter().chain(convolutional_cases()) {
        let float_tolerance = float32_tolerance(device, &arch, if ill_conditioned(&shape) { 1e-4 } else { 1e-5 });
        for seed in [0.5, 1.5, 2.5] {
            for (weighted, rho_l2, raised) in [(false, 0.0, false), (true, 0.3, false), (false, 0.1, true)] {
                let mut net = build_on(&arch, &shape, device);
                perturb(&net);
                if raised {
                    tch::no_grad(|| {
                        for (name, var) in net.weights().var_store().variables() {
                            // Not a convolution's before a group norm: the norm removes the
                            // shift, leaving only float32's cancellation.
                            if name.ends_with("0.bias") && !name.ends_with(".block.0.bias") {
                                let _ = var.shallow_clone().f_add_scalar_(30.0).expect("raise bias");
                            }
                        }
                    });
                }
                let mut single = build_on(&arch, &shape, device);
                single.weights_mut().var_store_mut().copy(net.weights().var_store()).expect("float32 copy");
                net.weights_mut().var_store_mut().double();
                let (x, t) = inputs(&net, 3, Kind::Double);
                let x = x * (1.0 + seed);
                let target = pseudo_random(&x.size(), seed, Kind::Double).to_device(device);
                let weights =
                    weighted.then(|| (pseudo_random(&shape, seed + 0.1, Kind::Double).abs() + 0.5).to_device(device));
                let what =
                    format!("{arch} {shape:?} {device:?} seed {seed} weights {weighted} l2 {rho_l2} raised {raised}");
                let loss =
                    crate::engine::relative_reward::alignment_loss(&net, &x, &t, &target, weights.as_ref(), rho_l2)
                        .expect("autograd loss");
                loss.backward();
                let variables: BTreeMap<String, Tensor> = net.weights().var_store().variables().into_iter().collect();
                let float = |t: &Tensor| t.to_kind(Kind::Float);
                let float_weights = weights.as_ref().map(float);
                for (net, kind, tolerance) in [(&net, Kind::Double, 1e-10), (&single, Kind::Float, float_tolerance)] {
                    let (x, target) = (x.to_kind(kind), target.to_kind(kind));
                    let weights = if kind == Kind::Double { weights.as_ref() } else { float_weights.as_ref() };
                    let ours = net
                        .alignment_gradients(&x, &t, &target, weights, rho_l2)
                        .expect("alignment gradients without autograd");
                    let what = format!("{what} {kind:?}");
                    let to_double = |t: &Tensor| t.to_kind(Kind::Double);
                    assert_close(&to_double(&ours.loss), &loss.detach(), tolerance, &format!("{what}: loss"));
                    assert_eq!(ours.grads.len(), variables.len(), "{what}: one gradient per parameter");
                    for (name, grad) in &ours.grads {
                        let want = variables[name].grad();
                        let want = if want.defined() { want } else { variables[name].zeros_like() };
                        assert_close(&to_double(grad), &want, tolerance, &format!("{what}: {name}"));
                    }
                }
            }
        }
    }
}

/// `grad` by the closed form (the MLP heads) and by the hand-written backward (the
/// convolutional rewards) against autograd's input gradient of the same network, and its rho
/// against `rho` (scored alone) bit for bit: OIP serves rho with its gradient and must answer
/// what Score answers.
#[test]
fn reward_closed_form_grad_equals_autograd() {
    let device = check_device();
    for (arch, shape) in closed_form_cases().into_iter().chain(convolutional_cases()) {
        for seed in [0.5, 1.5, 2.5] {
            for (kind, tolerance) in [(Kind::Double, 1e-10), (Kind::Float, float32_tolerance(device, &arch, 1e-5))] {
                let mut net = build_on(&arch, &shape, device);
                perturb(&net);
                if kind == Kind::Double {
                    net.weights_mut().var_store_mut().double();
                }
                let (x, t) = inputs(&net, 5, kind);
                let x = x * (1.0 + seed);
                let what = format!("{arch} {shape:?} {device:?} seed {seed} {kind:?}");
                let (rho, grad) = net.grad(&x, &t).expect("closed form");
                assert!(!grad.requires_grad() && !rho.requires_grad(), "{what}: no graph");
                let want = net.rho(&x, &t).expect("rho");
                assert!(tch::no_grad(|| rho.equal(&want)), "{what}: rho equals rho() bit for bit");
                // Autograd's d sum(rho) / dx through libtorch's Mish (the pass Algorithm 1
                // differentiates twice), independent of the kernels.
                let auto = net.grad_create_graph(&x, &t).expect("autograd").detach();
                assert_close(&grad, &auto, tolerance, &format!("{what}: grad_x"));
                // Where the kernels decline (many threads, tracing), libtorch's operations:
                // Mish's input on the tape and group norm's backward in closed form.
                let (rho, grad) = kernels::with_libtorch_ops(|| net.grad(&x, &t)).expect("libtorch ops");
                let want = kernels::with_libtorch_ops(|| net.rho(&x, &t)).expect("rho");
                assert!(tch::no_grad(|| rho.equal(&want)), "{what}: rho equals rho() with libtorch's ops");
                assert_close(&grad, &auto, tolerance, &format!("{what}: grad_x with libtorch's ops"));
            }
        }
    }
}

/// Convolutional rewards on the CPU run merged batches at a few sizes (oneDNN compiles a
/// kernel per shape); the others at any.
#[test]
fn padded_batches_take_a_few_sizes_with_at_most_a_third_padding() {
    let conv = build(&value_function(&[32]), &[8, 3]);
    let sizes: Vec<i64> = (1..=256).map(|n| conv.padded_batch(n)).collect();
    for (n, &rows) in (1..=256).zip(&sizes) {
        assert!(rows >= n && (rows - n) * 3 <= rows, "{n} items ran as {rows}");
    }
    let mut distinct = sizes.clone();
    distinct.dedup();
    assert_eq!(distinct, [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256]);
    let encoder = build(&conv_encoder(&[8]), &[1, 4, 4]);
    assert_eq!(encoder.padded_batch(5), 6);
    let windowed = build(&windowed(4, &[8]), &[8, 3]);
    assert!((1..=256).all(|n| windowed.padded_batch(n) == n));
}

/// Not a test: times the closed form against autograd at the maze default size
/// (`cargo test --release -p relreward-server --lib time_closed_form -- --ignored --nocapture`).
#[test]
#[ignore]
fn time_closed_form_against_autograd() {
    tch::set_num_threads(1);
    let net = build(&windowed(4, &[128, 64, 32]), &[16, 6]);
    let (x, t) = inputs(&net, 64, Kind::Float);
    let target = pseudo_random(&x.size(), 0.3, Kind::Float);
    let time = crate::engine::nets::kernels::timing::best_of;
    time("closed form", &mut || {
        let g = net.alignment_gradients(&x, &t, &target, None, 0.0).expect("closed");
        let _ = g.loss.double_value(&[]);
    });
    time("autograd", &mut || {
        let loss = crate::engine::relative_reward::alignment_loss(&net, &x, &t, &target, None, 0.0).expect("loss");
        loss.backward();
        let _ = loss.double_value(&[]);
    });
    let Network::WindowedMlp(w) = &net.network else { panic!("windowed") };
    let rows = w.rows(&x).expect("rows");
    let tf = t.to_kind(Kind::Float);
    time("pass only", &mut || {
        let _p = tch::no_grad(|| w.head.pass(&rows, &tf, true)).expect("pass");
    });
    let r = pseudo_random(&[256, 24], 0.1, Kind::Float);
    time("pass + grads", &mut || {
        let p = tch::no_grad(|| w.head.pass(&rows, &tf, true)).expect("pass");
        let _g = tch::no_grad(|| w.head.alignment_grads(&p, &r, None)).expect("grads");
    });
    let params = crate::engine::optim::named_parameters(net.weights().var_store());
    let mut adam = crate::engine::optim::Adam::new(&params, 1e-3);
    let grads: Vec<(String, Tensor)> = params.iter().map(|(n, p)| (n.clone(), p.ones_like() * 1e-3)).collect();
    time("adam", &mut || {
        let g = grads.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
        let _ = adam.step_with(&params, g, None);
    });
    time("grad (serving, closed form)", &mut || {
        let _ = net.grad(&x, &t).expect("grad");
    });
    time("closed form, again", &mut || {
        let g = net.alignment_gradients(&x, &t, &target, None, 0.0).expect("closed");
        let _ = g.loss.double_value(&[]);
    });
}

/// Not a test: times the ValueFunction's hand-written gradient against autograd's at the
/// serving benchmark's size, [B, 32, 14] with widths (64, 64, 128, 128), B = 64 (a merged pass)
/// and B = 1 (a lone unary call), one thread, rounds interleaved so that the machine's drift
/// touches both alike
/// (`cargo test --release -p relreward-server --lib time_value_function -- --ignored --nocapture`).
#[test]
#[ignore]
fn time_value_function_grad_against_autograd() {
    tch::set_num_threads(1);
    let net = build(&value_function(&[64, 64, 128, 128]), &[32, 14]);
    for batch in [64, 1] {
        let (x, t) = inputs(&net, batch, Kind::Float);
        let tf = t.to_kind(Kind::Float);
        let mut hand = || drop(net.grad(&x, &t).expect("grad"));
        let mut autograd = || {
            let grad = tch::with_grad(|| {
                let x_req = x.detach_copy().set_requires_grad(true);
                let rho = net.rho_unchecked(&x_req, &tf, Mish::Fused).expect("rho");
                Tensor::run_backward(&[rho.sum(Kind::Float)], &[&x_req], false, false)
            });
            drop(grad);
        };
        let mut rho = || drop(tch::no_grad(|| net.rho(&x, &t)).expect("rho"));
        let mut best = [f64::INFINITY; 3];
        let mut runs: [&mut dyn FnMut(); 3] = [&mut hand, &mut autograd, &mut rho];
        for _ in 0..10 {
            for (best, f) in best.iter_mut().zip(runs.iter_mut()) {
                let start = std::time::Instant::now();
                for _ in 0..5 {
                    f();
                }
                *best = best.min(start.elapsed().as_secs_f64() * 1e6 / 5.0);
            }
        }
        eprintln!(
            "batch {batch}: grad (hand-written): {:.0} us, autograd: {:.0} us, rho alone: {:.0} us",
            best[0], best[1], best[2]
        );
    }
}

/// Timing harness (run by hand, `--ignored`): the ValueFunction's `grad` per item at several
/// batch sizes on one thread, then on two threads at once (each its own network): whether a
/// pass split by rows across two cores (`serving.pass_threads`) costs what its half does.
#[test]
#[ignore]
fn time_value_function_grad_on_two_threads() {
    tch::set_num_threads(1);
    let per_item_us = |batch: i64| {
        let net = build(&value_function(&[64, 64, 128, 128]), &[32, 14]);
        let (x, t) = inputs(&net, batch, Kind::Float);
        for _ in 0..3 {
            drop(net.grad(&x, &t).expect("grad"));
        }
        let start = std::time::Instant::now();
        for _ in 0..20 {
            drop(net.grad(&x, &t).expect("grad"));
        }
        start.elapsed().as_secs_f64() * 1e6 / 20.0 / batch as f64
    };
    for batch in [16i64, 32, 48, 64] {
        let one = per_item_us(batch);
        let two: Vec<f64> = std::thread::scope(|s| {
            let threads: Vec<_> = (0..2).map(|_| s.spawn(|| per_item_us(batch))).collect();
            threads.into_iter().map(|h| h.join().expect("timing thread")).collect()
        });
        eprintln!("batch {batch}: one thread {one:.0} us/item; two at once {:.0} / {:.0} us/item", two[0], two[1]);
    }
}

/// Not a test: times a training step's alignment loss and gradients for the convolutional
/// rewards, the sweeps without autograd (`RewardNet::alignment_gradients`) against autograd's
/// double backward of the same loss (`relative_reward::alignment_loss`, what training ran
/// before), one thread, best of 5 rounds of 3 steps each, interleaved: the ValueFunction at the
/// locomotion size ([64, 32, 14], widths (64, 64, 128, 128)) and the encoder at the digits
/// experiment's ([128, 1, 8, 8], widths (16, 32, 64))
/// (`cargo test --release -p relreward-server --lib time_convolutional_alignment -- --ignored --nocapture`).
#[test]
#[ignore]
fn time_convolutional_alignment_against_autograd() {
    tch::set_num_threads(1);
    let cases =
        [(value_function(&[64, 64, 128, 128]), vec![32i64, 14], 64), (conv_encoder(&[16, 32, 64]), vec![1, 8, 8], 128)];
    for (arch, shape, batch) in cases {
        let net = build(&arch, &shape);
        let (x, t) = inputs(&net, batch, Kind::Float);
        let target = pseudo_random(&x.size(), 0.3, Kind::Float);
        let mut sweeps = || {
            let g = net.alignment_gradients(&x, &t, &target, None, 0.0).expect("sweeps");
            let _ = g.loss.double_value(&[]);
        };
        let mut autograd = || {
            let loss = crate::engine::relative_reward::alignment_loss(&net, &x, &t, &target, None, 0.0).expect("loss");
            loss.backward();
            let _ = loss.double_value(&[]);
        };
        let mut best = [f64::INFINITY; 2];
        let mut runs: [&mut dyn FnMut(); 2] = [&mut sweeps, &mut autograd];
        for _ in 0..5 {
            for (best, f) in best.iter_mut().zip(runs.iter_mut()) {
                let start = std::time::Instant::now();
                for _ in 0..3 {
                    f();
                }
                *best = best.min(start.elapsed().as_secs_f64() * 1e3 / 3.0);
            }
        }
        eprintln!(
            "{arch} batch {batch}: sweeps {:.1} ms, autograd's double backward {:.1} ms ({:.2}x)",
            best[0],
            best[1],
            best[1] / best[0]
        );
    }
}
