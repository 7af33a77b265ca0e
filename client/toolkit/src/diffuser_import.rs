//! Importing a Diffuser `TemporalUnet` state_dict (`diffuser/models/temporal.py`, without
//! attention) into relreward's native weights format, without Python or libtorch.
//!
//! Module map:
//! - [`temporal_unet_shapes`]: every tensor name and shape of the TemporalUnet that the
//!   manifest's architecture (dim, dim_mults) and space (horizon, transition dim) imply; the
//!   same table `server/src/engine/nets/temporal_unet.rs` registers.
//! - [`import_npz`]: reads a state_dict exported to `.npz` (see below), strips an optional
//!   prefix (`model.` for a `GaussianDiffusion` state_dict), checks presence and shape of every
//!   tensor and reports ALL missing, unexpected and mis-shaped tensors in one error.
//! - [`write_safetensors`]: writes the float32 tensors as safetensors (the native format).
//!
//! Why `.npz` and not the `.pt` itself: `torch.save` writes pickles, which only Python can read
//! safely; the CLI links no libtorch. The export is one documented line of Python:
//! `np.savez(path, **{k: v.cpu().numpy() for k, v in state_dict.items()})`.
//! relreward's native TemporalUnet uses Diffuser's own parameter names (nn.Sequential indices
//! included), so the mapping is the identity after the prefix; what this module adds is the
//! shape contract and one complete error message.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

/// Kernel of the residual blocks' convolutions (Diffuser's `kernel_size=5`).
const KERNEL: u64 = 5;

/// Tensor name -> shape of a TemporalUnet, for `dims = [transition_dim, dim * m...]`.
/// Diffuser's layout: `time_mlp.{1,3}` Linear; `downs.i.{0,1}` ResidualTemporalBlock,
/// `downs.i.3.conv` Downsample1d except on the last level; `mid_block{1,2}`; `ups.i.{0,1}`,
/// `ups.i.3.conv` ConvTranspose1d on every up level; `final_conv.0` Conv1dBlock,
/// `final_conv.1` Conv1d(dim, transition_dim, 1).
pub fn temporal_unet_shapes(transition_dim: u64, dim: u64, dim_mults: &[u64]) -> BTreeMap<String, Vec<u64>> {
    let mut out = BTreeMap::new();
    let mut put = |name: String, shape: Vec<u64>| {
        out.insert(name, shape);
    };
    let linear = |put: &mut dyn FnMut(String, Vec<u64>), p: &str, i: u64, o: u64| {
        put(format!("{p}.weight"), vec![o, i]);
        put(format!("{p}.bias"), vec![o]);
    };
    let conv_block = |put: &mut dyn FnMut(String, Vec<u64>), p: &str, i: u64, o: u64, k: u64| {
        put(format!("{p}.block.0.weight"), vec![o, i, k]);
        put(format!("{p}.block.0.bias"), vec![o]);
        put(format!("{p}.block.2.weight"), vec![o]);
        put(format!("{p}.block.2.bias"), vec![o]);
    };
    let res_block = |put: &mut dyn FnMut(String, Vec<u64>), p: &str, i: u64, o: u64| {
        conv_block(put, &format!("{p}.blocks.0"), i, o, KERNEL);
        conv_block(put, &format!("{p}.blocks.1"), o, o, KERNEL);
        linear(put, &format!("{p}.time_mlp.1"), dim, o);
        if i != o {
            put(format!("{p}.residual_conv.weight"), vec![o, i, 1]);
            put(format!("{p}.residual_conv.bias"), vec![o]);
        }
    };
    let dims: Vec<u64> = std::iter::once(transition_dim).chain(dim_mults.iter().map(|m| dim * m)).collect();
    let levels = dims.len() - 1;
    linear(&mut put, "time_mlp.1", dim, 4 * dim);
    linear(&mut put, "time_mlp.3", 4 * dim, dim);
    for (i, pair) in dims.windows(2).enumerate() {
        let (w_in, w_out) = (pair[0], pair[1]);
        res_block(&mut put, &format!("downs.{i}.0"), w_in, w_out);
        res_block(&mut put, &format!("downs.{i}.1"), w_out, w_out);
        if i + 1 < levels {
            put(format!("downs.{i}.3.conv.weight"), vec![w_out, w_out, 3]);
            put(format!("downs.{i}.3.conv.bias"), vec![w_out]);
        }
    }
    let mid = dims[levels];
    res_block(&mut put, "mid_block1", mid, mid);
    res_block(&mut put, "mid_block2", mid, mid);
    for (i, pair) in dims[1..].windows(2).rev().enumerate() {
        let (w_in, w_out) = (pair[0], pair[1]);
        res_block(&mut put, &format!("ups.{i}.0"), 2 * w_out, w_in);
        res_block(&mut put, &format!("ups.{i}.1"), w_in, w_in);
        // ConvTranspose1d weights are [in, out, k].
        put(format!("ups.{i}.3.conv.weight"), vec![w_in, w_in, 4]);
        put(format!("ups.{i}.3.conv.bias"), vec![w_in]);
    }
    conv_block(&mut put, "final_conv.0", dims[1], dim, KERNEL);
    put("final_conv.1.weight".to_owned(), vec![transition_dim, dim, 1]);
    put("final_conv.1.bias".to_owned(), vec![transition_dim]);
    out
}

/// What [`import_npz`] found wrong; every list is complete (sorted by name).
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Mismatch {
    pub missing: Vec<(String, Vec<u64>)>,
    pub unexpected: Vec<(String, Vec<u64>)>,
    /// (name, found, expected)
    pub misshaped: Vec<(String, Vec<u64>, Vec<u64>)>,
}

impl Mismatch {
    pub fn is_empty(&self) -> bool {
        self.missing.is_empty() && self.unexpected.is_empty() && self.misshaped.is_empty()
    }
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "the state_dict does not match the TemporalUnet that the manifest and flags describe:")?;
        for (name, shape) in &self.missing {
            writeln!(f, "  missing tensor '{name}' (expected shape {shape:?})")?;
        }
        for (name, shape) in &self.unexpected {
            writeln!(f, "  unexpected tensor '{name}' (shape {shape:?})")?;
        }
        for (name, found, expected) in &self.misshaped {
            writeln!(f, "  tensor '{name}' has shape {found:?}, expected {expected:?}")?;
        }
        write!(
            f,
            "({} missing, {} unexpected, {} mis-shaped; check --dim, --dim-mults, --prefix and the manifest's space)",
            self.missing.len(),
            self.unexpected.len(),
            self.misshaped.len()
        )
    }
}

/// Compares the shapes found (names already stripped of any prefix) with the expected table.
pub fn check_shapes(found: &BTreeMap<String, Vec<u64>>, expected: &BTreeMap<String, Vec<u64>>) -> Mismatch {
    let mut m = Mismatch::default();
    for (name, shape) in expected {
        match found.get(name) {
            None => m.missing.push((name.clone(), shape.clone())),
            Some(s) if s != shape => m.misshaped.push((name.clone(), s.clone(), shape.clone())),
            Some(_) => {}
        }
    }
    for (name, shape) in found {
        if !expected.contains_key(name) {
            m.unexpected.push((name.clone(), shape.clone()));
        }
    }
    m
}

/// One imported tensor: relreward's name, its shape and its values (float32, C order).
pub type NamedTensor = (String, Vec<u64>, Vec<f32>);

/// Errors of an import: the file could not be read, or its tensors do not match.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{0}")]
    Read(String),
    #[error("{0}")]
    Mismatch(Mismatch),
}

/// Reads a state_dict `.npz` (one array per tensor name), keeps the arrays whose name starts
/// with `prefix` (an empty prefix keeps all; with a prefix, other arrays, e.g. a
/// `GaussianDiffusion`'s schedule buffers, are ignored), strips it and checks them against
/// `expected`. Returns the tensors as float32 in `expected`'s order.
pub fn import_npz(
    path: &Path,
    prefix: &str,
    expected: &BTreeMap<String, Vec<u64>>,
) -> Result<Vec<NamedTensor>, ImportError> {
    let read = |e: &dyn std::fmt::Display| ImportError::Read(format!("{}: {e}", path.display()));
    let keys = crate::npz::npz_keys(path).map_err(|e| read(&e))?;
    if keys.is_empty() {
        return Err(ImportError::Read(format!(
            "{}: not an .npz archive of named tensors (export with np.savez(path, **state_dict))",
            path.display()
        )));
    }
    let mut found = BTreeMap::new();
    let mut file_key = BTreeMap::new();
    for key in keys {
        let Some(name) = key.strip_prefix(prefix) else { continue };
        let shape = crate::npz::npz_array_shape(path, &key).map_err(|e| read(&e))?.unwrap_or_default();
        found.insert(name.to_owned(), shape);
        file_key.insert(name.to_owned(), key);
    }
    let mismatch = check_shapes(&found, expected);
    if !mismatch.is_empty() {
        return Err(ImportError::Mismatch(mismatch));
    }
    let mut out = Vec::with_capacity(expected.len());
    for (name, shape) in expected {
        let key = &file_key[name];
        let (_, values) = crate::npz::read_numbers(path, key)
            .map_err(|e| read(&format!("tensor '{key}': {e}")))?
            .ok_or_else(|| read(&format!("tensor '{key}' vanished")))?;
        if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
            return Err(read(&format!("tensor '{key}' holds a non-finite value at flat index {bad}")));
        }
        out.push((name.clone(), shape.clone(), values.into_iter().map(|v| v as f32).collect()));
    }
    Ok(out)
}

/// Writes float32 tensors as a safetensors file (8-byte little-endian header length, JSON
/// header, raw little-endian data), the format of native weights (`weights.safetensors`).
pub fn write_safetensors(path: &Path, tensors: &[NamedTensor]) -> std::io::Result<()> {
    let mut header = String::from("{");
    let mut offset = 0usize;
    for (i, (name, shape, values)) in tensors.iter().enumerate() {
        let end = offset + values.len() * 4;
        let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
        if i > 0 {
            header.push(',');
        }
        // Names come from `temporal_unet_shapes` (ASCII letters, digits, dots, underscores):
        // nothing to escape.
        header.push_str(&format!(
            "\"{name}\":{{\"dtype\":\"F32\",\"shape\":[{}],\"data_offsets\":[{offset},{end}]}}",
            dims.join(",")
        ));
        offset = end;
    }
    header.push('}');
    // Pad the header with spaces to a multiple of 8, as the reference writer does.
    while !header.len().is_multiple_of(8) {
        header.push(' ');
    }
    let mut file = std::io::BufWriter::new(std::fs::File::create(path)?);
    file.write_all(&(header.len() as u64).to_le_bytes())?;
    file.write_all(header.as_bytes())?;
    for (_, _, values) in tensors {
        for v in values {
            file.write_all(&v.to_le_bytes())?;
        }
    }
    file.into_inner().map_err(|e| e.into_error())?.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz_write::NpzWriter;

    fn write_npz(path: &Path, tensors: &BTreeMap<String, Vec<u64>>) {
        let mut w = NpzWriter::create(path).unwrap();
        for (name, shape) in tensors {
            let n: u64 = shape.iter().product();
            w.add_f32(name, shape, &vec![0.5; n as usize]).unwrap();
        }
        w.finish().unwrap();
    }

    #[test]
    fn shapes_cover_the_documented_layout() {
        // dims [3, 8, 16]: two levels, one downsampling, one up level.
        let s = temporal_unet_shapes(3, 8, &[1, 2]);
        assert_eq!(s["time_mlp.1.weight"], vec![32, 8]);
        assert_eq!(s["downs.0.0.residual_conv.weight"], vec![8, 3, 1]);
        assert!(!s.contains_key("downs.0.1.residual_conv.weight"));
        assert_eq!(s["downs.0.3.conv.weight"], vec![8, 8, 3]);
        assert!(!s.contains_key("downs.1.3.conv.weight"));
        assert_eq!(s["ups.0.0.blocks.0.block.0.weight"], vec![8, 32, 5]);
        assert_eq!(s["ups.0.3.conv.weight"], vec![8, 8, 4]);
        assert!(!s.contains_key("ups.1.0.blocks.0.block.0.weight"));
        assert_eq!(s["final_conv.1.weight"], vec![3, 8, 1]);
    }

    #[test]
    fn every_missing_unexpected_and_misshaped_tensor_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let expected = temporal_unet_shapes(3, 8, &[1, 2]);
        let mut bad = expected.clone();
        bad.remove("mid_block1.blocks.0.block.0.bias");
        bad.remove("final_conv.1.weight");
        bad.insert("downs.0.2.fn.to_qkv.weight".into(), vec![8, 8]);
        bad.insert("time_mlp.3.weight".into(), vec![8, 16]);
        let path = dir.path().join("sd.npz");
        write_npz(&path, &bad);
        let err = import_npz(&path, "", &expected).unwrap_err();
        let ImportError::Mismatch(m) = &err else { panic!("{err}") };
        assert_eq!(m.missing.len(), 2);
        assert_eq!(m.unexpected.len(), 1);
        assert_eq!(m.misshaped.len(), 1);
        let text = err.to_string();
        for needle in [
            "missing tensor 'final_conv.1.weight' (expected shape [3, 8, 1])",
            "missing tensor 'mid_block1.blocks.0.block.0.bias'",
            "unexpected tensor 'downs.0.2.fn.to_qkv.weight' (shape [8, 8])",
            "tensor 'time_mlp.3.weight' has shape [8, 16], expected [8, 32]",
        ] {
            assert!(text.contains(needle), "{needle} not in:\n{text}");
        }
    }

    #[test]
    fn a_prefix_selects_the_network_and_the_rest_is_ignored() {
        let dir = tempfile::tempdir().unwrap();
        let expected = temporal_unet_shapes(2, 8, &[1]);
        let mut prefixed: BTreeMap<String, Vec<u64>> =
            expected.iter().map(|(k, v)| (format!("model.{k}"), v.clone())).collect();
        prefixed.insert("betas".into(), vec![10]);
        let path = dir.path().join("sd.npz");
        write_npz(&path, &prefixed);
        let tensors = import_npz(&path, "model.", &expected).unwrap();
        assert_eq!(tensors.len(), expected.len());
        let err = import_npz(&path, "", &expected).unwrap_err().to_string();
        assert!(err.contains("unexpected tensor 'betas'"), "{err}");
        assert!(err.contains("missing tensor 'time_mlp.1.weight'"), "{err}");
    }

    #[test]
    fn safetensors_layout() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.safetensors");
        write_safetensors(&path, &[("a".into(), vec![2], vec![1.0, -2.0]), ("b".into(), vec![], vec![3.0])]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        assert_eq!(n % 8, 0);
        let header = std::str::from_utf8(&bytes[8..8 + n]).unwrap().trim_end();
        assert_eq!(
            header,
            r#"{"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"F32","shape":[],"data_offsets":[8,12]}}"#
        );
        let data = &bytes[8 + n..];
        assert_eq!(data.len(), 12);
        assert_eq!(f32::from_le_bytes(data[4..8].try_into().unwrap()), -2.0);
    }
}
