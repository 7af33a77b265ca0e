//! Cross-check of the native [`Unet2d`](relreward_server::engine::nets::unet2d) against diffusers'
//! own `UNet2DModel` (`tests/python/unet2d_reference.py`), an implementation written without
//! reference to ours: the Rust side builds each network, randomises every weight (so GroupNorm's
//! affine parameters and every bias take part), saves it as safetensors and runs
//!
//! - the forward pass at several diffusion steps;
//! - one DDPM training step: [`DiffusionModel::loss`] (x_t from relreward's linear schedule) and
//!   the gradient of every parameter,
//!
//! and diffusers loads the same file with `load_state_dict(strict=True)` (so every name and
//! shape is diffusers'), computes both with its `DDPMScheduler.add_noise`, and also writes the
//! state dict of a fresh `UNet2DModel`, which must load strictly here and give its outputs.
//!
//! Tolerance 1e-4, relative to a value's magnitude where that exceeds 1 (gradients of the
//! output convolution are sums over the whole batch and image).

use std::collections::BTreeMap;

use relreward_server::engine::diffusion::DiffusionModel;
use relreward_server::engine::manifest::{
    Architecture, Conditioning, DiffusionManifest, Parametrization, ScheduleSpec, Space,
};
use relreward_server::engine::nets::NativeDenoiser;
use relreward_server::engine::normalizer::Normalizer;
use relreward_server::engine::optim::named_parameters;
use relreward_server::engine::rng::Rng;
use serde_json::json;
use tch::{Device, Kind, Tensor};

mod common;
use common::{randomize, run_reference};

const TOLERANCE: f64 = 1e-4;
const T: usize = 50;

fn relative_diff(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size());
    let scale = a.abs().max().double_value(&[]).max(1.0);
    (a - b).abs().max().double_value(&[]) / scale
}

struct Case {
    architecture: Architecture,
    shape: Vec<usize>,
    parametrization: Parametrization,
    conditioning: Option<Conditioning>,
}

fn unet2d(block_out_channels: &[usize], layers_per_block: usize, attention: bool, groups: usize) -> Architecture {
    Architecture::Unet2d {
        block_out_channels: block_out_channels.to_vec(),
        layers_per_block,
        attention,
        norm_num_groups: groups,
        attention_head_dim: 8,
    }
}

#[test]
fn unet2d_matches_diffusers_forward_and_training_step() {
    let cases = [
        Case {
            architecture: unet2d(&[16, 32], 1, true, 8),
            shape: vec![1, 8, 8],
            parametrization: Parametrization::Epsilon,
            conditioning: None,
        },
        Case {
            architecture: unet2d(&[16, 16, 32], 2, false, 4),
            shape: vec![3, 8, 12],
            parametrization: Parametrization::X0,
            conditioning: None,
        },
        Case {
            architecture: unet2d(&[8], 1, true, 2),
            shape: vec![2, 5, 3],
            parametrization: Parametrization::Epsilon,
            conditioning: None,
        },
        // Class-conditional (diffusers' num_class_embeds) and embedding-conditional
        // (class_embed_type "identity": width 4 * 16).
        Case {
            architecture: unet2d(&[16, 32], 1, true, 8),
            shape: vec![1, 8, 8],
            parametrization: Parametrization::Epsilon,
            conditioning: Some(Conditioning::Labels { num_classes: 11, null_class: Some(10) }),
        },
        Case {
            architecture: unet2d(&[16, 32], 1, false, 4),
            shape: vec![2, 4, 8],
            parametrization: Parametrization::V,
            conditioning: Some(Conditioning::Embedding { dim: 64 }),
        },
    ];
    let dir = tempfile::tempdir().expect("tempdir");
    let mut rng = Rng::new(7);
    let mut jobs = Vec::new();
    let mut rust = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        let space = Space::Sample { shape: case.shape.clone() };
        let conditioning = case.conditioning.as_ref();
        let d = NativeDenoiser::new(&case.architecture, &space, conditioning, 0, Device::Cpu).expect("build");
        randomize(d.weights().var_store(), &mut rng);
        let weights = dir.path().join(format!("weights-{i}.safetensors"));
        d.save(&weights).expect("save weights");
        let params = named_parameters(d.weights().var_store());

        let mut shape = vec![3i64];
        shape.extend(case.shape.iter().map(|&s| s as i64));
        let x = rng.randn(&shape, Device::Cpu);
        let t = Tensor::from_slice(&[0i64, 17, (T - 1) as i64]);
        let x0 = rng.randn(&shape, Device::Cpu).tanh();
        let noise = rng.randn(&shape, Device::Cpu);
        let t_train = rng.randint(T as u64, 3, Device::Cpu);
        // Two distinct conditions per pass, so the embedding's rows differ within a batch.
        let (cond, cond_train) = match case.conditioning {
            None => (None, None),
            Some(Conditioning::Labels { .. }) => {
                (Some(Tensor::from_slice(&[3i64, 10, 0])), Some(Tensor::from_slice(&[7i64, 7, 2])))
            }
            Some(Conditioning::Embedding { dim }) => {
                (Some(rng.randn(&[3, dim as i64], Device::Cpu)), Some(rng.randn(&[3, dim as i64], Device::Cpu)))
            }
        };
        let inputs = dir.path().join(format!("inputs-{i}.safetensors"));
        let mut named = vec![("x", &x), ("t", &t), ("x0", &x0), ("noise", &noise), ("t_train", &t_train)];
        if let (Some(c), Some(ct)) = (&cond, &cond_train) {
            named.extend([("cond", c), ("cond_train", ct)]);
        }
        Tensor::write_safetensors(&named, &inputs).expect("write inputs");

        let y = tch::no_grad(|| {
            use relreward_server::engine::denoiser::Denoiser;
            d.forward(&x, &t, cond.as_ref())
        })
        .expect("rust forward");
        assert!(y.abs().max().double_value(&[]) > 1e-3, "case {i}: output is trivially zero");

        let manifest = DiffusionManifest {
            parametrization: case.parametrization,
            schedule: ScheduleSpec::Linear,
            n_timesteps: T,
            clip_denoised: false,
            space: space.clone(),
            normalizer: Normalizer::Identity,
            architecture: Some(case.architecture.clone()),
            conditioning: case.conditioning,
        };
        let model = DiffusionModel::new(manifest, Box::new(d)).expect("model");
        let loss = model.loss(&x0, &t_train, &noise, None, cond_train.as_ref()).expect("loss");
        loss.backward();
        let grads: BTreeMap<String, Tensor> = params.iter().map(|(n, p)| (n.clone(), p.grad().copy())).collect();
        rust.push((x, t, cond, y, loss.double_value(&[]), grads, space));

        // The architecture's own fields (diffusers' names) with the image's shape.
        let mut config = serde_json::to_value(&case.architecture).expect("architecture json");
        config["conditioning"] = serde_json::to_value(case.conditioning).expect("conditioning json");
        config["channels"] = json!(case.shape[0]);
        config["height"] = json!(case.shape[1]);
        config["width"] = json!(case.shape[2]);
        jobs.push(json!({
            "config": config,
            "parametrization": case.parametrization,
            "n_timesteps": T,
            "weights": weights,
            "inputs": inputs,
            "output": dir.path().join(format!("output-{i}.safetensors")),
            "torch_weights": dir.path().join(format!("torch-weights-{i}.safetensors")),
        }));
    }
    run_reference("tests/python/unet2d_reference.py", &jobs, dir.path());

    for (i, (case, (x, t, cond, y, loss, grads, space))) in cases.iter().zip(&rust).enumerate() {
        let outputs: BTreeMap<String, Tensor> =
            Tensor::read_safetensors(dir.path().join(format!("output-{i}.safetensors")))
                .expect("read output")
                .into_iter()
                .collect();
        let arch = &case.architecture;

        let diff = relative_diff(y, &outputs["y"]);
        eprintln!("case {i} {arch:?}: forward, max |rust - diffusers| = {diff:e}");
        assert!(diff < TOLERANCE, "case {i}: forward differs by {diff}");

        let torch_loss = outputs["loss"].double_value(&[0]);
        let diff = (loss - torch_loss).abs() / loss.abs().max(1.0);
        eprintln!("case {i}: loss rust {loss:.6} diffusers {torch_loss:.6}");
        assert!(diff < TOLERANCE, "case {i}: loss {loss} vs {torch_loss}");
        let mut worst = (0.0f64, String::new());
        for (name, grad) in grads {
            let theirs = outputs.get(&format!("grad.{name}")).unwrap_or_else(|| panic!("case {i}: no gradient {name}"));
            assert!(grad.abs().sum(Kind::Float).double_value(&[]) > 0.0, "case {i}: {name} has a zero gradient");
            let diff = relative_diff(grad, theirs);
            if diff > worst.0 {
                worst = (diff, name.clone());
            }
        }
        eprintln!("case {i}: {} parameter gradients, worst {:e} ({})", grads.len(), worst.0, worst.1);
        assert!(worst.0 < TOLERANCE, "case {i}: gradient of {} differs by {}", worst.1, worst.0);
        assert_eq!(grads.len(), outputs.keys().filter(|k| k.starts_with("grad.")).count(), "case {i}: parameter sets");

        // diffusers' weights, relreward's forward.
        let torch_weights = dir.path().join(format!("torch-weights-{i}.safetensors"));
        let d = NativeDenoiser::load(arch, space, &torch_weights, case.conditioning.as_ref(), Device::Cpu)
            .expect("diffusers' state dict loads");
        let y_rust = tch::no_grad(|| {
            use relreward_server::engine::denoiser::Denoiser;
            d.forward(x, t, cond.as_ref())
        })
        .expect("rust forward");
        let diff = relative_diff(&y_rust, &outputs["y_torch"]);
        eprintln!("case {i}: diffusers' weights, max |rust - diffusers| = {diff:e}");
        assert!(diff < TOLERANCE, "case {i}: forward on diffusers' weights differs by {diff}");
    }
}
