//! Test fixtures of the reader's unit tests: npy and npz files written as numpy writes them,
//! the bytes a source sends read back, and the error the trajectory reader gives for a file.

use std::fs::File;
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

use npyz::zip::{CompressionMethod, ZipWriter, write::FileOptions};
use relreward_proto::v1::{ArraySpec, Dtype};

pub(super) use relreward_proto::upload::UploadSource;

use super::npy::write_npy_header;
use super::source::NpzSource;
use super::trajectories::trajectories_from_npz;

/// A fresh directory for a test's files (removed when dropped) and the path `name` in it.
pub(super) fn scratch(name: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join(name);
    (dir, path)
}

/// An npy file as numpy writes it (format 1.0, header padded to 64 bytes).
pub(super) fn npy(descr: &str, fortran: bool, shape: &[u64], data: &[u8]) -> Vec<u8> {
    let mut out = write_npy_header(descr, fortran, shape);
    out.extend_from_slice(data);
    out
}

pub(super) fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

pub(super) fn f64_bytes(values: &[f64]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

pub(super) fn write_npz(path: &Path, entries: &[(&str, Vec<u8>)], compressed: bool) {
    let file = File::create(path).expect("create npz");
    let mut zip = ZipWriter::new(file);
    let method = if compressed { CompressionMethod::Deflated } else { CompressionMethod::Stored };
    let options = FileOptions::default().compression_method(method);
    for (name, bytes) in entries {
        zip.start_file(format!("{name}.npy"), options).expect("start entry");
        zip.write_all(bytes).expect("write entry");
    }
    zip.finish().expect("finish npz");
}

pub(super) fn read_all(source: &mut NpzSource, index: usize) -> io::Result<Vec<u8>> {
    let mut out = Vec::new();
    source.open(index)?.read_to_end(&mut out)?;
    Ok(out)
}

pub(super) fn spec(name: &str, dtype: Dtype, shape: &[u64]) -> ArraySpec {
    ArraySpec { name: name.to_owned(), dtype: dtype as i32, shape: shape.to_vec() }
}

/// Archive entries: (array name, npy file bytes).
pub(super) type Entries = Vec<(&'static str, Vec<u8>)>;

/// A small D4RL-like file: 4 rows, obs_dim 3, act_dim 2 (float64), bool flags, plus extras;
/// and the data bytes of the arrays that are sent, in order.
pub(super) fn d4rl_entries() -> (Entries, Vec<Vec<u8>>) {
    let obs = f32_bytes(&(0..12).map(|i| i as f32 * 0.5).collect::<Vec<_>>());
    let act = f64_bytes(&[1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0]);
    let terminals = vec![0u8, 0, 0, 1];
    let timeouts = vec![0u8, 1, 0, 0];
    let rewards = f32_bytes(&[0.0, 1.0, 2.0, 3.0]);
    let entries = vec![
        ("rewards", npy("<f4", false, &[4], &rewards)),
        ("observations", npy("<f4", false, &[4, 3], &obs)),
        ("actions", npy("<f8", false, &[4, 2], &act)),
        ("terminals", npy("|b1", false, &[4], &terminals)),
        ("timeouts", npy("|b1", false, &[4], &timeouts)),
        ("infos/qpos", npy("<f8", false, &[4, 1], &f64_bytes(&[0.0; 4]))),
    ];
    // Actions are sent as float32 whatever their stored type.
    let act_sent = f32_bytes(&[1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0]);
    (entries, vec![obs, act_sent, terminals, timeouts])
}

/// The float32 values a trajectories archive sends for array `index`.
pub(super) fn sent_f32(source: &mut NpzSource, index: usize) -> io::Result<Vec<f32>> {
    let bytes = read_all(source, index)?;
    Ok(bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

/// `values` stored as `descr` (`'<i2'`, `'>f8'`, ...).
pub(super) fn encode(descr: &str, values: &[f64]) -> Vec<u8> {
    let big = descr.starts_with('>');
    let mut out = Vec::new();
    for &v in values {
        let mut b: Vec<u8> = match &descr[1..] {
            "i1" => (v as i8).to_le_bytes().to_vec(),
            "i2" => (v as i16).to_le_bytes().to_vec(),
            "i4" => (v as i32).to_le_bytes().to_vec(),
            "i8" => (v as i64).to_le_bytes().to_vec(),
            "u1" => (v as u8).to_le_bytes().to_vec(),
            "u2" => (v as u16).to_le_bytes().to_vec(),
            "u4" => (v as u32).to_le_bytes().to_vec(),
            "u8" => (v as u64).to_le_bytes().to_vec(),
            // Small integers and halves only: exact in binary16.
            "f2" => {
                let bits: u16 = (0..=u16::MAX).find(|&h| f64::from(crate::values::f16_to_f32(h)) == v).expect("a half");
                bits.to_le_bytes().to_vec()
            }
            "f4" => (v as f32).to_le_bytes().to_vec(),
            "f8" => v.to_le_bytes().to_vec(),
            other => panic!("{other}"),
        };
        if big {
            b.reverse();
        }
        out.extend(b);
    }
    out
}

/// Writes `entries` at `path` as an uncompressed archive and returns the error the trajectory
/// reader gives for it.
pub(super) fn trajectories_error(path: &Path, entries: &[(&str, Vec<u8>)]) -> String {
    write_npz(path, entries, false);
    trajectories_from_npz(path).expect_err("must fail").to_string()
}
