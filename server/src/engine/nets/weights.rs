//! Weights files of the native networks: strict safetensors loading (exactly the network's
//! tensor names, shapes and dtype, or an error naming the tensor, with nothing changed) and
//! atomic saving (a synced temporary sibling renamed over the target). Shared by the
//! denoisers and the reward networks, so both refuse the same bad files the same way.
//! Loading a safetensors file never executes code.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use tch::nn::VarStore;
use tch::{TchError, Tensor};

use crate::error::{Error, Result};

/// Room for the safetensors header on top of the weights themselves.
const HEADER_ALLOWANCE: u64 = 1 << 20;
/// At most this many names are listed in an error message.
const NAMES_SHOWN: usize = 5;

/// Replaces every variable of `vs` with the tensor of the same name in a safetensors file. The
/// file must hold exactly these names, each with the variable's shape and dtype; on any
/// mismatch the error (InvalidArgument) names the tensor and nothing is changed. The file may
/// be at most the size `parameter_count` weights need plus a header allowance. Messages never
/// include the file's path (it may be a server-side location).
pub fn load_strict(vs: &VarStore, parameter_count: u64, path: &Path) -> Result<()> {
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

/// Writes every variable of `vs` to `path` in safetensors format, sorted by name, through a
/// synced temporary sibling renamed over `path` (never a truncated file under the final name).
pub fn save_atomic(vs: &VarStore, path: &Path) -> Result<()> {
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
