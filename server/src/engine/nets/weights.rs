//! The variables of a native network and their files, shared by the denoisers and the reward
//! networks so that both are built, checked, loaded and saved the same way:
//!
//! - [`Weights`]: a network's `VarStore` with its parameter count, built once and checked
//!   against the count its plan computed without allocating, its first values drawn from a seed
//!   of its own, or none drawn where they are replaced at once ([`Start`], [`first_values`]).
//! - strict safetensors loading ([`Weights::load_strict`]: exactly the network's tensor names,
//!   shapes and dtype, or an error naming the tensor, with nothing changed) and atomic saving
//!   ([`Weights::save_atomic`]: a synced temporary sibling renamed over the target). Loading a
//!   safetensors file never executes code.

use std::cell::Cell;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

use tch::nn::{self, Init, VarStore};
use tch::{Device, TchError, Tensor};

use crate::error::{Error, Result};

/// Room for the safetensors header on top of the weights themselves.
const HEADER_ALLOWANCE: u64 = 1 << 20;
/// At most this many names are listed in an error message.
const NAMES_SHOWN: usize = 5;

/// How a network's variables start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Start {
    /// PyTorch's default initialisation, drawn from libtorch's generator seeded with this value:
    /// the same seed, the same first weights (a training job's `seed`).
    Seeded(u64),
    /// Values that are replaced at once (a load, a replica sharing another network's storage):
    /// zeros, nothing drawn ([`first_values`]).
    Replaced,
}

/// Held by every seeded build, from its seeding to its last draw. Layers draw their first
/// values from libtorch's generator, which is process-wide: two seeded builds at once (two jobs
/// starting) would interleave their draws, and the same seed would no longer give the same
/// first weights.
static SEEDED_BUILDS: Mutex<()> = Mutex::new(());

thread_local! {
    /// Set while this thread builds a network whose values are replaced at once
    /// ([`Start::Replaced`]): its layers start at zero and draw nothing, so a load or a serving
    /// replica never takes draws from a job's stream and never waits for a job's build.
    static REPLACED: Cell<bool> = const { Cell::new(false) };
}

/// A layer's first values: `init` as the layer asks, or zeros, with no draw from libtorch's
/// generator, while this thread builds a network whose values are replaced at once. Every
/// layer's random initialisation goes through here (`blocks::torch_default_init` and the
/// UNet2D's class table).
pub fn first_values(init: Init) -> Init {
    if REPLACED.with(Cell::get) { Init::Const(0.0) } else { init }
}

/// A network's variables (parameters and buffers, under PyTorch's state-dict names) and their
/// number.
#[derive(Debug)]
pub struct Weights {
    vs: VarStore,
    parameter_count: u64,
}

impl Weights {
    /// Creates the variables of a network on `device`: `build` makes its layers under the root
    /// path, from `start`'s seed or for values replaced next. The number of values built must
    /// equal `planned`, the count the network's plan computed without allocating (which the
    /// parameter limits were checked against); a mismatch is an internal error of `network`'s
    /// bookkeeping.
    pub fn build<N>(
        device: Device,
        planned: u64,
        network: &str,
        start: Start,
        build: impl FnOnce(&nn::Path) -> Result<N>,
    ) -> Result<(Self, N)> {
        let vs = VarStore::new(device);
        let layers = match start {
            Start::Seeded(seed) => {
                // A build that failed half way leaves nothing to protect: a poisoned lock is taken.
                let _seeded = SEEDED_BUILDS.lock().unwrap_or_else(PoisonError::into_inner);
                // libtorch takes the seed's bits as a u64; tch's signature is i64.
                tch::manual_seed(seed as i64);
                build(&vs.root())?
            }
            Start::Replaced => super::with_flag_set(&REPLACED, || build(&vs.root()))?,
        };
        let parameter_count = vs
            .variables()
            .values()
            .map(|t| u64::try_from(t.numel()).unwrap_or(u64::MAX))
            .fold(0u64, u64::saturating_add);
        if parameter_count != planned {
            return Err(Error::internal(network, format!("built {parameter_count} parameters, planned {planned}")));
        }
        Ok((Self { vs, parameter_count }, layers))
    }

    pub fn var_store(&self) -> &VarStore {
        &self.vs
    }

    /// Mutable access for a trainer (optimizer, freezing, `double()` for precise checks).
    /// Changing the set of variables breaks the network.
    pub fn var_store_mut(&mut self) -> &mut VarStore {
        &mut self.vs
    }

    pub fn parameter_count(&self) -> u64 {
        self.parameter_count
    }

    /// The parameter names (the PyTorch state-dict keys), sorted.
    pub fn parameter_names(&self) -> Vec<String> {
        let mut names: Vec<String> = self.vs.variables().into_keys().collect();
        names.sort();
        names
    }

    /// Replaces every variable with the tensor of the same name in a safetensors file. The
    /// file must hold exactly these names, each with the variable's shape and dtype; on any
    /// mismatch the error (InvalidArgument) names the tensor and nothing is changed. The file
    /// may be at most the size the parameters need plus a header allowance. Messages never
    /// include the file's path (it may be a server-side location).
    pub fn load_strict(&self, path: &Path) -> Result<()> {
        load_strict(&self.vs, self.parameter_count, path)
    }

    /// Every variable finite, or InvalidArgument naming the first tensor (in name order) that
    /// holds a NaN or an infinity, with the index and value of its first such element. Uploads
    /// are checked with it, so a bad weight is named rather than found by a forward's NaN.
    pub fn check_finite(&self) -> Result<()> {
        let variables: BTreeMap<String, Tensor> = self.vs.variables().into_iter().collect();
        for (name, var) in &variables {
            let flat = var.f_detach()?.f_to_device(Device::Cpu)?.f_reshape([-1])?;
            let bad = flat.f_isfinite()?.f_logical_not()?.f_nonzero()?;
            if bad.size().first().copied().unwrap_or(0) == 0 {
                continue;
            }
            let first = bad.f_int64_value(&[0, 0])?;
            let value = flat.f_double_value(&[first])?;
            // The flat position as an index into the tensor's shape, last dimension fastest.
            let mut index = Vec::new();
            let mut rest = first;
            for &d in var.size().iter().rev() {
                index.push(rest % d.max(1));
                rest /= d.max(1);
            }
            index.reverse();
            return Err(Error::invalid(format!(
                "weights: tensor '{name}' holds a non-finite value ({value}) at index {index:?}, shape {:?}",
                var.size()
            )));
        }
        Ok(())
    }

    /// Makes every variable share the storage of the variable of the same name in `source`
    /// (libtorch's `set_data`: the fresh values are freed, nothing is copied), so that another
    /// thread can evaluate the same network through its own handles. Both must be the same
    /// network: a name missing from `source` or a shape that differs is an internal error, with
    /// nothing shared.
    pub fn share_storage_of(&mut self, source: &Weights) -> Result<()> {
        let sources = source.vs.variables();
        let mut targets = self.vs.variables();
        for (name, target) in &targets {
            match sources.get(name) {
                Some(s) if s.size() == target.size() && s.kind() == target.kind() => {}
                _ => return Err(Error::internal("sharing weights", format!("'{name}' differs between the networks"))),
            }
        }
        tch::no_grad(|| {
            for (name, target) in &mut targets {
                if let Some(s) = sources.get(name) {
                    target.f_set_data(s)?;
                }
            }
            Ok(())
        })
    }

    /// Writes every variable to `path` in safetensors format, sorted by name, through a synced
    /// temporary sibling renamed over `path` (never a truncated file under the final name).
    pub fn save_atomic(&self, path: &Path) -> Result<()> {
        save_atomic(&self.vs, path)
    }
}

fn load_strict(vs: &VarStore, parameter_count: u64, path: &Path) -> Result<()> {
    let variables: BTreeMap<String, Tensor> = vs.variables().into_iter().collect();
    let kind = variables.values().next().map_or(tch::Kind::Float, Tensor::kind);
    let size = std::fs::metadata(path)?.len();
    let bytes_per_weight = u64::try_from(kind.elt_size_in_bytes()).unwrap_or(u64::MAX);
    let limit = parameter_count.saturating_mul(bytes_per_weight).saturating_add(HEADER_ALLOWANCE);
    if size > limit {
        return Err(Error::invalid(format!(
            "weights: the file has {size} bytes, more than the {limit} that {parameter_count} {kind:?} parameters need"
        )));
    }
    let file: BTreeMap<String, Tensor> =
        Tensor::read_safetensors(path).map_err(unreadable_weights)?.into_iter().collect();
    let missing: Vec<&String> = variables.keys().filter(|name| !file.contains_key(*name)).collect();
    if !missing.is_empty() {
        return Err(Error::invalid(format!(
            "weights: missing tensor(s) {} (the file does not match this architecture)",
            name_list(&missing)
        )));
    }
    let extra: Vec<&String> = file.keys().filter(|name| !variables.contains_key(*name)).collect();
    if !extra.is_empty() {
        return Err(Error::invalid(format!(
            "weights: unexpected tensor(s) {} (the file does not match this architecture)",
            name_list(&extra)
        )));
    }
    for (name, var) in &variables {
        let src = &file[name];
        if src.kind() != var.kind() {
            return Err(Error::invalid(format!(
                "weights: tensor '{name}' has dtype {:?}, expected {:?}",
                src.kind(),
                var.kind()
            )));
        }
        if src.size() != var.size() {
            return Err(Error::invalid(format!(
                "weights: tensor '{name}' has shape {:?}, expected {:?}",
                src.size(),
                var.size()
            )));
        }
    }
    // Shallow clones share storage with the VarStore's tensors: copying into them updates
    // the network in place (and any optimizer over the store keeps pointing at them).
    tch::no_grad(|| -> Result<()> {
        for (name, var) in &variables {
            let mut dst = var.shallow_clone();
            dst.f_copy_(&file[name])?;
        }
        Ok(())
    })
}

fn save_atomic(vs: &VarStore, path: &Path) -> Result<()> {
    let named = vs
        .variables()
        .into_iter()
        .collect::<BTreeMap<_, _>>()
        .into_iter()
        .map(|(name, t)| Ok((name, t.f_detach()?.f_to_device(tch::Device::Cpu)?.f_contiguous()?)))
        .collect::<Result<Vec<(String, Tensor)>>>()?;
    let tmp = temporary_sibling(path);
    let written = Tensor::write_safetensors(&named, &tmp)
        .map_err(Error::from)
        .and_then(|()| Ok(std::fs::File::open(&tmp)?.sync_all()?))
        .and_then(|()| Ok(std::fs::rename(&tmp, path)?));
    if written.is_err() {
        // Best effort: the original error is the one worth reporting.
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// Maps a failure to parse a weights file to InvalidArgument, without the path that tch puts in
/// its message; anything else (I/O, libtorch) stays internal.
fn unreadable_weights(err: TchError) -> Error {
    match err {
        TchError::SafeTensorError { err, .. } => {
            Error::invalid(format!("weights: not a valid safetensors file: {err}"))
        }
        TchError::Convert(msg) => Error::invalid(format!("weights: {msg}")),
        other => Error::from(other),
    }
}

fn name_list(names: &[&String]) -> String {
    let shown: Vec<String> = names.iter().take(NAMES_SHOWN).map(|n| format!("'{n}'")).collect();
    match names.len().saturating_sub(NAMES_SHOWN) {
        0 => shown.join(", "),
        more => format!("{} and {more} more", shown.join(", ")),
    }
}

fn temporary_sibling(path: &Path) -> PathBuf {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(format!(".tmp-{}", std::process::id()));
    path.with_file_name(name)
}
