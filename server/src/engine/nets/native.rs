//! [`NativeDenoiser`]: a built-in architecture ([`Architecture`]) with its weights in a tch
//! `VarStore`, implementing [`Denoiser`]. Weights travel as safetensors only (data, never code),
//! under the PyTorch module names of the same architecture, so one file loads both here and in
//! `relreward_dev.nets` (`dev/python`; `load_state_dict(strict=True)`).
//!
//! Loading is strict and checked before anything is copied: the file must hold exactly the
//! network's tensor names, each float32 with the variable's shape. tch's `VarStore::load` is not
//! used because it ignores extra tensors, broadcasts mis-shaped ones through `copy_` and converts
//! the variables to the file's dtype.

use std::path::Path;

use tch::{Device, Kind, Tensor};

use super::inputs::check_condition;
use super::inputs::check_inputs;
use super::mlp::MlpDenoiser;
use super::temporal_unet::TemporalUnet;
use super::unet2d::ClassEmbedding;
use super::unet2d::{Unet2d, Unet2dConfig};
use super::weights::{Start, Weights};
use crate::engine::denoiser::Denoiser;
use crate::engine::manifest::{Architecture, Conditioning, Space};
use crate::error::{Error, Result};

/// Largest network this service builds: 2^28 parameters are 1 GiB of float32 weights (and
/// three times that again while training with Adam), far above the paper's networks (a few
/// million) while a request cannot make the server allocate without bound.
pub const MAX_PARAMETERS: u64 = 1 << 28;

#[derive(Debug)]
enum Network {
    // Boxed: the U-Net's level vectors and blocks make it far larger than the MLP.
    TemporalUnet(Box<TemporalUnet>),
    Mlp(MlpDenoiser),
    Unet2d(Box<Unet2d>),
}

/// A native denoiser: the network, its variables, and the space it was built for.
#[derive(Debug)]
pub struct NativeDenoiser {
    weights: Weights,
    network: Network,
    architecture: Architecture,
    space: Space,
    conditioning: Option<Conditioning>,
    item_shape: Vec<i64>,
}

fn to_i64(value: usize, field: &str) -> Result<i64> {
    i64::try_from(value).map_err(|_| Error::invalid(format!("{field}: {value} is too large")))
}

/// The architecture's hyperparameters in i64, checked against the space.
enum Plan {
    TemporalUnet { horizon: i64, transition_dim: i64, dim: i64, dim_mults: Vec<i64> },
    Mlp { features: i64, hidden: Vec<i64> },
    Unet2d(Unet2dConfig),
}

impl Plan {
    fn new(
        architecture: &Architecture,
        space: &Space,
        conditioning: Option<&Conditioning>,
    ) -> Result<(Self, Vec<i64>)> {
        if conditioning.is_some() && !matches!(architecture, Architecture::Unet2d { .. }) {
            return Err(Error::invalid(format!(
                "conditioning: the native {} takes no condition; only unet2d is conditional",
                architecture.kind_name()
            )));
        }
        let item_shape = match space {
            Space::Trajectory { horizon, action_dim, obs_dim } => {
                let transition = action_dim
                    .checked_add(*obs_dim)
                    .ok_or_else(|| Error::invalid("space: action_dim + obs_dim is too large"))?;
                vec![to_i64(*horizon, "space.horizon")?, to_i64(transition, "space: action_dim + obs_dim")?]
            }
            Space::Sample { shape } => {
                if shape.is_empty() || shape.contains(&0) {
                    return Err(Error::invalid(format!(
                        "space.shape: {shape:?} must be non-empty with positive dimensions"
                    )));
                }
                shape.iter().map(|&d| to_i64(d, "space.shape")).collect::<Result<Vec<_>>>()?
            }
        };
        let plan = match architecture {
            Architecture::TemporalUnet { dim, dim_mults } => {
                let Space::Trajectory { .. } = space else {
                    return Err(Error::invalid(
                        "architecture: temporal_unet needs a trajectory space [horizon, action_dim + obs_dim]",
                    ));
                };
                let (horizon, transition_dim) = (item_shape[0], item_shape[1]);
                let dim = to_i64(*dim, "architecture.dim")?;
                let dim_mults =
                    dim_mults.iter().map(|&m| to_i64(m, "architecture.dim_mults")).collect::<Result<Vec<_>>>()?;
                TemporalUnet::validate(horizon, transition_dim, dim, &dim_mults)?;
                Self::TemporalUnet { horizon, transition_dim, dim, dim_mults }
            }
            Architecture::Mlp { hidden } => {
                let features = item_shape
                    .iter()
                    .try_fold(1i64, |acc, &d| acc.checked_mul(d))
                    .ok_or_else(|| Error::invalid(format!("space: item shape {item_shape:?} is too large")))?;
                let hidden = hidden.iter().map(|&h| to_i64(h, "architecture.hidden")).collect::<Result<Vec<_>>>()?;
                MlpDenoiser::validate(features, &hidden)?;
                Self::Mlp { features, hidden }
            }
            Architecture::Unet2d {
                block_out_channels,
                layers_per_block,
                attention,
                norm_num_groups,
                attention_head_dim,
            } => {
                let (Space::Sample { .. }, &[channels, height, width]) = (space, item_shape.as_slice()) else {
                    return Err(Error::invalid(format!(
                        "architecture: unet2d needs a sample space of shape [C, H, W], not {item_shape:?}"
                    )));
                };
                let config = Unet2dConfig {
                    channels,
                    height,
                    width,
                    block_out_channels: block_out_channels
                        .iter()
                        .map(|&c| to_i64(c, "architecture.block_out_channels"))
                        .collect::<Result<Vec<_>>>()?,
                    layers_per_block: to_i64(*layers_per_block, "architecture.layers_per_block")?,
                    attention: *attention,
                    norm_num_groups: to_i64(*norm_num_groups, "architecture.norm_num_groups")?,
                    attention_head_dim: to_i64(*attention_head_dim, "architecture.attention_head_dim")?,
                    class_embedding: match conditioning {
                        None => None,
                        Some(Conditioning::Labels { num_classes, .. }) => Some(ClassEmbedding::Table {
                            rows: to_i64(*num_classes, "conditioning.labels.num_classes")?,
                        }),
                        Some(Conditioning::Embedding { dim }) => {
                            Some(ClassEmbedding::Identity { dim: to_i64(*dim, "conditioning.embedding.dim")? })
                        }
                    },
                };
                config.validate()?;
                Self::Unet2d(config)
            }
        };
        Ok((plan, item_shape))
    }

    /// Number of parameters, within [`MAX_PARAMETERS`].
    fn params(&self) -> Result<u64> {
        let count = match self {
            Self::TemporalUnet { transition_dim, dim, dim_mults, .. } => {
                TemporalUnet::params(*transition_dim, *dim, dim_mults)
            }
            Self::Mlp { features, hidden } => MlpDenoiser::params(*features, hidden),
            Self::Unet2d(config) => config.params(),
        };
        if count > u128::from(MAX_PARAMETERS) {
            return Err(Error::invalid(format!(
                "architecture: {count} parameters exceed the limit of {MAX_PARAMETERS}"
            )));
        }
        u64::try_from(count).map_err(|_| Error::invalid("architecture: too many parameters"))
    }
}

impl NativeDenoiser {
    /// Validates the architecture against the space and returns the number of parameters the
    /// network would have, without allocating it. Errors name the manifest field at fault.
    pub fn planned_parameter_count(
        architecture: &Architecture,
        space: &Space,
        conditioning: Option<&Conditioning>,
    ) -> Result<u64> {
        Plan::new(architecture, space, conditioning)?.0.params()
    }

    /// A freshly initialised network (PyTorch's default initialisation, drawn from `seed`) on
    /// `device`, taking `conditioning`'s input when given (unet2d only).
    pub fn new(
        architecture: &Architecture,
        space: &Space,
        conditioning: Option<&Conditioning>,
        seed: u64,
        device: Device,
    ) -> Result<Self> {
        Self::build(architecture, space, conditioning, Start::Seeded(seed), device)
    }

    fn build(
        architecture: &Architecture,
        space: &Space,
        conditioning: Option<&Conditioning>,
        start: Start,
        device: Device,
    ) -> Result<Self> {
        let (plan, item_shape) = Plan::new(architecture, space, conditioning)?;
        let (weights, network) = Weights::build(device, plan.params()?, "NativeDenoiser", start, |root| {
            Ok(match &plan {
                Plan::TemporalUnet { horizon, transition_dim, dim, dim_mults } => Network::TemporalUnet(Box::new(
                    TemporalUnet::new(root, *horizon, *transition_dim, *dim, dim_mults)?,
                )),
                Plan::Mlp { features, hidden } => Network::Mlp(MlpDenoiser::new(root, *features, hidden)?),
                Plan::Unet2d(config) => Network::Unet2d(Box::new(Unet2d::new(root, config)?)),
            })
        })?;
        Ok(Self {
            weights,
            network,
            architecture: architecture.clone(),
            space: space.clone(),
            conditioning: conditioning.copied(),
            item_shape,
        })
    }

    /// Builds the network and loads its weights from a safetensors file (strictly, see
    /// [`Weights::load_strict`]).
    pub fn load(
        architecture: &Architecture,
        space: &Space,
        path: &Path,
        conditioning: Option<&Conditioning>,
        device: Device,
    ) -> Result<Self> {
        let denoiser = Self::build(architecture, space, conditioning, Start::Replaced, device)?;
        denoiser.weights.load_strict(path)?;
        Ok(denoiser)
    }

    /// Writes every weight to `path` atomically (see [`Weights::save_atomic`]).
    pub fn save(&self, path: &Path) -> Result<()> {
        self.weights.save_atomic(path)
    }

    /// The variables: names, loading, the `VarStore` a trainer optimises.
    pub fn weights(&self) -> &Weights {
        &self.weights
    }

    /// The weights stop requiring gradients (a copy that is only evaluated and traced).
    pub fn freeze(&mut self) {
        self.weights.var_store_mut().freeze();
    }

    pub fn architecture(&self) -> &Architecture {
        &self.architecture
    }

    pub fn space(&self) -> &Space {
        &self.space
    }

    /// Shape of one item, without the batch dimension.
    pub fn item_shape(&self) -> &[i64] {
        &self.item_shape
    }
}

impl Denoiser for NativeDenoiser {
    fn forward(&self, x: &Tensor, t: &Tensor, cond: Option<&Tensor>) -> Result<Tensor> {
        let batch = check_inputs("denoiser", x, t, &self.item_shape, Kind::Float)?;
        check_condition("denoiser", cond, self.conditioning.as_ref(), batch)?;
        let t = t.f_to_kind(Kind::Float)?;
        match &self.network {
            Network::TemporalUnet(net) => net.forward(x, &t),
            Network::Mlp(net) => net.forward(x, &t),
            Network::Unet2d(net) => net.forward(x, &t, cond),
        }
    }

    fn parameter_count(&self) -> u64 {
        self.weights.parameter_count()
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;

    fn trajectory(horizon: usize) -> Space {
        Space::Trajectory { horizon, action_dim: 2, obs_dim: 4 }
    }

    fn unet(dim: usize, dim_mults: &[usize]) -> Architecture {
        Architecture::TemporalUnet { dim, dim_mults: dim_mults.to_vec() }
    }

    fn mlp(hidden: &[usize]) -> Architecture {
        Architecture::Mlp { hidden: hidden.to_vec() }
    }

    fn build(arch: &Architecture, space: &Space) -> NativeDenoiser {
        NativeDenoiser::new(arch, space, None, 0, Device::Cpu).expect("network builds")
    }

    /// Moves every weight off its initial value (GroupNorm's ones and zeros included) so that
    /// a weight that fails to load or save would show.
    fn perturb(d: &NativeDenoiser) {
        tch::no_grad(|| {
            for (_, var) in d.weights().var_store().variables() {
                let mut var = var;
                let noise = var.randn_like() * 0.1;
                let _ = var.f_add_(&noise).expect("perturb");
            }
        });
    }

    fn inputs(d: &NativeDenoiser, batch: i64) -> (Tensor, Tensor) {
        let mut shape = vec![batch];
        shape.extend_from_slice(d.item_shape());
        let x = Tensor::randn(shape.as_slice(), (Kind::Float, Device::Cpu));
        let t = Tensor::arange(batch, (Kind::Int64, Device::Cpu)) * 7 + 1;
        (x, t)
    }

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b).abs().max().double_value(&[])
    }

    fn invalid_message(result: Result<impl std::fmt::Debug>) -> String {
        match result {
            Err(Error::InvalidArgument(msg)) => msg,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn nets_parameter_names_mirror_the_pytorch_modules() {
        let d = build(&unet(32, &[1, 2, 4, 8]), &trajectory(32));
        let names = d.weights().parameter_names();
        for expected in [
            "time_mlp.1.weight",
            "time_mlp.3.bias",
            "downs.0.0.blocks.0.block.0.weight",
            "downs.0.0.blocks.0.block.2.weight",
            "downs.0.0.blocks.1.block.2.bias",
            "downs.0.0.time_mlp.1.weight",
            "downs.0.0.residual_conv.weight",
            "downs.0.3.conv.weight",
            "downs.2.3.conv.bias",
            "mid_block1.blocks.1.block.0.weight",
            "mid_block2.time_mlp.1.bias",
            "ups.0.0.residual_conv.weight",
            "ups.2.3.conv.weight",
            "final_conv.0.block.0.weight",
            "final_conv.0.block.2.bias",
            "final_conv.1.weight",
        ] {
            assert!(names.iter().any(|n| n == expected), "{expected} missing from {names:?}");
        }
        // No downsampling on the last level, no residual conv where widths agree, and exactly
        // levels - 1 up levels.
        for absent in ["downs.3.3.conv.weight", "downs.0.1.residual_conv.weight", "ups.3.0.time_mlp.1.weight"] {
            assert!(!names.iter().any(|n| n == absent), "{absent} should not exist");
        }
        let d = build(&mlp(&[64, 32]), &Space::Sample { shape: vec![4, 3] });
        assert_eq!(
            d.weights().parameter_names(),
            [
                "net.0.bias",
                "net.0.weight",
                "net.2.bias",
                "net.2.weight",
                "net.4.bias",
                "net.4.weight",
                "time_mlp.1.bias",
                "time_mlp.1.weight",
                "time_mlp.3.bias",
                "time_mlp.3.weight"
            ]
        );
        // (12 + 32) * 64 + 64, 64 * 32 + 32, 32 * 12 + 12, time MLP 32 * 128 + 128 + 128 * 32 + 32.
        assert_eq!(d.parameter_count(), 2880 + 2080 + 396 + 8352);
    }

    #[test]
    fn nets_forward_keeps_the_shape_and_checks_its_inputs() {
        for (arch, space) in [
            (unet(32, &[1, 2, 4, 8]), trajectory(32)),
            (unet(32, &[1, 4, 8]), trajectory(16)),
            (unet(16, &[2]), trajectory(5)),
            (mlp(&[32]), Space::Sample { shape: vec![2, 3, 4] }),
        ] {
            let d = build(&arch, &space);
            assert_eq!(
                u128::from(d.parameter_count()),
                u128::from(NativeDenoiser::planned_parameter_count(&arch, &space, None).expect("plan"))
            );
            let (x, t) = inputs(&d, 3);
            let y = tch::no_grad(|| d.forward(&x, &t, None)).expect("forward");
            assert_eq!(y.size(), x.size(), "{arch:?}");
            assert!(y.isfinite().all().int64_value(&[]) == 1);

            let wrong_shape = Tensor::zeros([3, 7], (Kind::Float, Device::Cpu));
            assert!(invalid_message(d.forward(&wrong_shape, &t, None)).contains("denoiser input x"));
            assert!(invalid_message(d.forward(&x.to_kind(Kind::Double), &t, None)).contains("float32"));
            assert!(invalid_message(d.forward(&x, &t.to_kind(Kind::Float), None)).contains("denoiser input t"));
            assert!(invalid_message(d.forward(&x, &t.narrow(0, 0, 2), None)).contains("denoiser input t"));
        }
    }

    #[test]
    fn nets_invalid_architectures_name_the_field() {
        let cases = [
            (unet(30, &[1, 2]), trajectory(32), "architecture.dim"),
            (unet(0, &[1, 2]), trajectory(32), "architecture.dim"),
            (unet(32, &[]), trajectory(32), "architecture.dim_mults"),
            (unet(32, &[1, 0]), trajectory(32), "architecture.dim_mults"),
            (unet(32, &[1, 2, 4, 8]), trajectory(20), "space.horizon"),
            (unet(32, &[1, 2]), Space::Sample { shape: vec![4, 4] }, "trajectory space"),
            (unet(8, &[1 << 20]), trajectory(32), "architecture.dim_mults"),
            (unet(4096, &[1, 2, 4, 8]), trajectory(32), "exceed the limit"),
            (mlp(&[]), Space::Sample { shape: vec![4] }, "architecture.hidden"),
            (mlp(&[16, 0]), Space::Sample { shape: vec![4] }, "architecture.hidden"),
            (mlp(&[16]), Space::Sample { shape: vec![] }, "space.shape"),
            (mlp(&[16]), Space::Sample { shape: vec![4, 0] }, "space.shape"),
            (mlp(&[1 << 20, 1 << 20]), Space::Sample { shape: vec![4] }, "exceed the limit"),
            (mlp(&[16]), Space::Sample { shape: vec![usize::MAX, 4] }, "space"),
        ];
        for (arch, space, needle) in cases {
            let msg = invalid_message(NativeDenoiser::new(&arch, &space, None, 0, Device::Cpu));
            assert!(msg.contains(needle), "{arch:?} {space:?}: {msg} should contain {needle}");
        }
    }

    #[test]
    fn nets_save_then_load_reproduces_outputs_exactly() {
        let dir = tempfile::tempdir().expect("tempdir");
        for (i, (arch, space)) in
            [(unet(32, &[1, 4, 8]), trajectory(16)), (mlp(&[64, 32]), Space::Sample { shape: vec![4, 3] })]
                .into_iter()
                .enumerate()
        {
            let original = build(&arch, &space);
            perturb(&original);
            // Any extension: the format is always safetensors.
            let path = dir.path().join(format!("weights-{i}.bin"));
            original.save(&path).expect("save");
            let leftovers = std::fs::read_dir(dir.path()).expect("list").count();
            assert_eq!(leftovers, i + 1, "no temporary file may remain");

            let loaded = NativeDenoiser::load(&arch, &space, &path, None, Device::Cpu).expect("load");
            let (x, t) = inputs(&original, 3);
            let run = |d: &NativeDenoiser| tch::no_grad(|| d.forward(&x, &t, None)).expect("forward");
            let (a, b) = (run(&original), run(&loaded));
            assert_eq!(max_abs_diff(&a, &b), 0.0);
            // ...and the comparison is not vacuous: another initialisation differs.
            assert!(max_abs_diff(&a, &run(&build(&arch, &space))) > 0.0);
        }
    }

    #[test]
    fn nets_strict_loading_rejects_mismatched_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        let arch = unet(16, &[1, 2]);
        let space = trajectory(8);
        let d = build(&arch, &space);
        let named: Vec<(String, Tensor)> =
            d.weights().var_store().variables().into_iter().collect::<BTreeMap<_, _>>().into_iter().collect();
        let write = |name: &str, tensors: &[(String, Tensor)]| {
            let path = dir.path().join(name);
            Tensor::write_safetensors(tensors, &path).expect("write");
            path
        };
        let detached = |t: &Tensor| t.detach().contiguous();

        let victim = "downs.0.0.blocks.0.block.2.weight";
        let missing: Vec<_> =
            named.iter().filter(|(n, _)| n != victim).map(|(n, t)| (n.clone(), detached(t))).collect();
        let wrong_shape: Vec<_> = named
            .iter()
            .map(|(n, t)| {
                (n.clone(), if n == victim { Tensor::ones([3], (Kind::Float, Device::Cpu)) } else { detached(t) })
            })
            .collect();
        let wrong_dtype: Vec<_> = named
            .iter()
            .map(|(n, t)| (n.clone(), if n == victim { detached(t).to_kind(Kind::Double) } else { detached(t) }))
            .collect();
        let mut extra: Vec<_> = named.iter().map(|(n, t)| (n.clone(), detached(t))).collect();
        extra.push(("downs.0.2.fn.weight".to_string(), Tensor::ones([2], (Kind::Float, Device::Cpu))));

        let cases = [
            (write("missing.safetensors", &missing), format!("missing tensor(s) '{victim}'")),
            (write("shape.safetensors", &wrong_shape), format!("tensor '{victim}' has shape [3], expected [16]")),
            (write("dtype.safetensors", &wrong_dtype), format!("tensor '{victim}' has dtype Double")),
            (write("extra.safetensors", &extra), "unexpected tensor(s) 'downs.0.2.fn.weight'".to_string()),
        ];
        let garbage = dir.path().join("garbage.safetensors");
        std::fs::write(&garbage, b"\xff\xff\xff\xff\xff\xff\xff\x7fnot a header").expect("write");
        let truncated = dir.path().join("truncated.safetensors");
        let full = write("full.safetensors", &extra);
        let bytes = std::fs::read(&full).expect("read");
        std::fs::write(&truncated, &bytes[..bytes.len() / 2]).expect("write");
        let cases = cases.into_iter().chain([
            (garbage, "not a valid safetensors file".to_string()),
            (truncated, "not a valid safetensors file".to_string()),
        ]);

        let target = build(&arch, &space);
        let before: BTreeMap<String, Tensor> =
            target.weights().var_store().variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
        for (path, needle) in cases {
            let msg = invalid_message(target.weights().load_strict(&path));
            assert!(msg.contains(&needle), "{msg} should contain {needle}");
            assert!(!msg.contains(&dir.path().display().to_string()), "{msg} leaks the path");
        }
        // Nothing was copied by the failed loads.
        let after: BTreeMap<String, Tensor> =
            target.weights().var_store().variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
        assert!(before.iter().zip(&after).all(|((na, a), (nb, b))| na == nb && a.equal(b)));
        // A missing file is the server's problem, not the caller's.
        assert!(matches!(
            target.weights().load_strict(&dir.path().join("absent.safetensors")),
            Err(Error::Internal(_))
        ));
    }

    #[test]
    fn a_non_finite_weight_is_named_with_its_index() {
        let d = build(&mlp(&[16]), &Space::Sample { shape: vec![4, 3] });
        d.weights().check_finite().expect("fresh weights are finite");
        let names = d.weights().parameter_names();
        let victim = names.iter().find(|n| d.weights().var_store().variables()[*n].dim() == 2).expect("a matrix");
        let var = d.weights().var_store().variables()[victim].shallow_clone();
        let cols = var.size()[1];
        tch::no_grad(|| {
            let _ = var.shallow_clone().view(-1).get(cols + 2).fill_(f64::NAN);
        });
        let msg = invalid_message(d.weights().check_finite());
        assert!(msg.contains(&format!("tensor '{victim}' holds a non-finite value (NaN) at index [1, 2]")), "{msg}");
    }

    #[test]
    fn nets_every_parameter_and_the_input_receive_gradients() {
        for (arch, space) in
            [(unet(32, &[1, 2, 4, 8]), trajectory(32)), (mlp(&[64, 32]), Space::Sample { shape: vec![4, 3] })]
        {
            let d = build(&arch, &space);
            let (x, t) = inputs(&d, 3);
            let x = x.set_requires_grad(true);
            let loss = d.forward(&x, &t, None).expect("forward").square().mean(Kind::Float);
            loss.backward();
            for (name, var) in d.weights().var_store().variables() {
                let grad = var.grad();
                assert!(grad.defined(), "{name}: no gradient");
                assert!(grad.abs().sum(Kind::Float).double_value(&[]) > 0.0, "{name}: zero gradient");
            }
            assert!(x.grad().abs().sum(Kind::Float).double_value(&[]) > 0.0, "input gradient (guidance)");
        }
    }
}
