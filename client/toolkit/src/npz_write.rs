//! Writes numpy `.npz` archives: an uncompressed zip of `.npy` files (what `np.savez` writes),
//! for the results of `score`, `grad` and `sample`.
//!
//! Arrays are float32, int64 or bool, little-endian, C order, in npy format 1.0 (headers padded to
//! a multiple of 64 bytes, as numpy does). The archive is written to a temporary file next to
//! the destination and renamed into place only once it is complete, so a failed or interrupted
//! write never leaves a half-written file under the requested name.
//!
//! The zip writer is the one `npyz` re-exports (already used to read archives), so no second
//! zip implementation enters the build.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use npyz::zip::write::FileOptions;
use npyz::zip::{CompressionMethod, ZipWriter};

/// Entries larger than this need zip64 records.
const ZIP32_LIMIT: u64 = u32::MAX as u64;

/// An `.npz` archive being written; nothing appears at the destination until [`finish`].
///
/// [`finish`]: NpzWriter::finish
pub struct NpzWriter {
    dest: PathBuf,
    tmp: PathBuf,
    zip: Option<ZipWriter<BufWriter<File>>>,
    names: Vec<String>,
    /// Set once the archive is renamed into place; until then dropping removes `tmp`.
    published: bool,
}

impl NpzWriter {
    /// Starts an archive that [`NpzWriter::finish`] moves to `dest`.
    pub fn create(dest: impl AsRef<Path>) -> io::Result<Self> {
        let dest = dest.as_ref().to_owned();
        let file_name = dest
            .file_name()
            .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "the output path names no file"))?;
        let mut tmp_name = std::ffi::OsString::from(".");
        tmp_name.push(file_name);
        tmp_name.push(format!(".{}.tmp", std::process::id()));
        let tmp = dest.with_file_name(tmp_name);
        let file = File::create(&tmp)?;
        Ok(Self { dest, tmp, zip: Some(ZipWriter::new(BufWriter::new(file))), names: Vec::new(), published: false })
    }

    /// Adds a float32 array `name` of `shape` (`values` in row-major order).
    pub fn add_f32(&mut self, name: &str, shape: &[u64], values: &[f32]) -> io::Result<()> {
        self.add(name, "<f4", shape, values.len(), |w| {
            for chunk in values.chunks(1 << 14) {
                let bytes: Vec<u8> = chunk.iter().flat_map(|v| v.to_le_bytes()).collect();
                w.write_all(&bytes)?;
            }
            Ok(())
        })
    }

    /// Adds an int64 array `name` of `shape`.
    pub fn add_i64(&mut self, name: &str, shape: &[u64], values: &[i64]) -> io::Result<()> {
        self.add(name, "<i8", shape, values.len(), |w| {
            for chunk in values.chunks(1 << 14) {
                let bytes: Vec<u8> = chunk.iter().flat_map(|v| v.to_le_bytes()).collect();
                w.write_all(&bytes)?;
            }
            Ok(())
        })
    }

    /// Adds a bool array `name` of `shape` (episode flags).
    pub fn add_bool(&mut self, name: &str, shape: &[u64], values: &[bool]) -> io::Result<()> {
        self.add(name, "|b1", shape, values.len(), |w| {
            let bytes: Vec<u8> = values.iter().map(|&b| u8::from(b)).collect();
            w.write_all(&bytes)
        })
    }

    fn add(
        &mut self,
        name: &str,
        descr: &str,
        shape: &[u64],
        len: usize,
        write: impl FnOnce(&mut ZipWriter<BufWriter<File>>) -> io::Result<()>,
    ) -> io::Result<()> {
        let invalid = |m: String| io::Error::new(io::ErrorKind::InvalidInput, m);
        if name.is_empty() || name.contains(['/', '\\']) || self.names.iter().any(|n| n == name) {
            return Err(invalid(format!("array name '{name}' is empty, has a path separator or is used twice")));
        }
        let numel = shape.iter().try_fold(1u64, |acc, &d| acc.checked_mul(d));
        if numel != Some(len as u64) {
            return Err(invalid(format!("array '{name}': {len} values do not fill shape {shape:?}")));
        }
        let header = npy_header(descr, shape);
        let size = header.len() as u64 + (len as u64) * 8;
        let options = FileOptions::default()
            .compression_method(CompressionMethod::Stored)
            .large_file(size > ZIP32_LIMIT)
            // A fixed timestamp: the same arrays give the same file bytes.
            .last_modified_time(npyz::zip::DateTime::default());
        let zip = self.zip.as_mut().ok_or_else(|| io::Error::other("the archive is already finished"))?;
        zip.start_file(format!("{name}.npy"), options).map_err(io::Error::other)?;
        zip.write_all(&header)?;
        write(zip)?;
        self.names.push(name.to_owned());
        Ok(())
    }

    /// Writes the zip directory, flushes to disk and renames the archive into place.
    pub fn finish(mut self) -> io::Result<PathBuf> {
        let mut zip = self.zip.take().ok_or_else(|| io::Error::other("the archive is already finished"))?;
        let buffered = zip.finish().map_err(io::Error::other)?;
        let file = buffered.into_inner().map_err(io::IntoInnerError::into_error)?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(&self.tmp, &self.dest)?;
        self.published = true;
        Ok(self.dest.clone())
    }
}

impl Drop for NpzWriter {
    /// An archive that was not finished is removed.
    fn drop(&mut self) {
        if !self.published {
            drop(self.zip.take());
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// The npy 1.0 header for a little-endian C-order array: magic, version, length and the
/// dictionary, space-padded so that the data starts at a multiple of 64 bytes.
fn npy_header(descr: &str, shape: &[u64]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
    let shape_text = match dims.as_slice() {
        [one] => format!("({one},)"),
        _ => format!("({})", dims.join(", ")),
    };
    let mut text = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_text}, }}");
    // magic (6) + version (2) + length (2) + text + '\n'
    let unpadded = 10 + text.len() + 1;
    text.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    text.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    // Shapes of any realistic rank keep the text far below u16::MAX.
    out.extend_from_slice(&(text.len().min(usize::from(u16::MAX)) as u16).to_le_bytes());
    out.extend_from_slice(text.as_bytes());
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz::{npz_keys, read_npy_header, samples_from_npz_or_npy};
    use relreward_client::UploadSource;
    use relreward_proto::tensor;
    use relreward_proto::v1::Dtype;

    #[test]
    fn round_trip_through_the_npz_reader() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("out.npz");
        let x: Vec<f32> = (0..24).map(|i| i as f32 * 0.25 - 3.0).collect();
        let reward = [1.5f32, -2.0, f32::MIN_POSITIVE];
        let starts = [0i64, 7, 1 << 40];
        let mut w = NpzWriter::create(&path).expect("create");
        w.add_f32("x", &[3, 4, 2], &x).expect("x");
        w.add_f32("reward", &[3], &reward).expect("reward");
        w.add_i64("window_start", &[3], &starts).expect("starts");
        w.add_f32("empty", &[0, 5], &[]).expect("empty");
        // Nothing under the destination name before finish.
        assert!(!path.exists());
        assert_eq!(w.finish().expect("finish"), path);
        assert_eq!(npz_keys(&path).expect("keys"), ["x", "reward", "window_start", "empty"]);
        // Only the destination is left in the directory.
        assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 1);

        let mut source = samples_from_npz_or_npy(&path, Some("x")).expect("read x");
        assert_eq!(source.arrays()[0].shape, [3, 4, 2]);
        let t = source.read_tensor(0).expect("x tensor");
        assert_eq!(tensor::decode_finite_f32(&t).expect("finite"), x);

        // 1-D arrays are refused as samples; read them through the header parser instead.
        let file = File::open(&path).expect("open");
        let mut archive = npyz::zip::ZipArchive::new(file).expect("zip");
        for (name, dtype, shape) in
            [("reward.npy", Dtype::Float32, vec![3]), ("window_start.npy", Dtype::Int64, vec![3])]
        {
            let mut entry = archive.by_name(name).expect("entry");
            assert_eq!(entry.compression(), CompressionMethod::Stored);
            let info = read_npy_header(&mut entry).expect("header");
            assert_eq!((info.dtype, info.shape.clone()), (dtype, shape));
            assert_eq!(info.header_len % 64, 0, "data aligned to 64 bytes");
            let mut data = Vec::new();
            io::Read::read_to_end(&mut entry, &mut data).expect("data");
            let t = tensor::from_raw(&info.shape, info.dtype, data).expect("tensor");
            if dtype == Dtype::Float32 {
                let got = tensor::decode_finite_f32(&t).expect("finite");
                assert_eq!(got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), reward.map(f32::to_bits));
            } else {
                let got: Vec<i64> =
                    t.data.chunks_exact(8).map(|c| i64::from_le_bytes(c.try_into().expect("8 bytes"))).collect();
                assert_eq!(got, starts);
            }
        }
    }

    #[test]
    fn bad_arrays_are_refused_and_unfinished_archives_removed() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("bad.npz");
        let mut w = NpzWriter::create(&path).expect("create");
        assert!(w.add_f32("x", &[2, 2], &[1.0; 3]).is_err(), "wrong count");
        w.add_f32("x", &[1], &[1.0]).expect("x");
        assert!(w.add_f32("x", &[1], &[1.0]).is_err(), "duplicate");
        assert!(w.add_f32("a/b", &[1], &[1.0]).is_err(), "path separator");
        assert!(w.add_f32("", &[1], &[1.0]).is_err(), "empty name");
        drop(w);
        assert!(!path.exists());
        assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 0, "temporary file removed");
        // A directory that does not exist is an error at create.
        assert!(NpzWriter::create(dir.path().join("missing/out.npz")).is_err());
    }

    #[test]
    fn headers_are_padded_like_numpy() {
        for shape in [vec![], vec![7], vec![3, 4, 2], vec![1 << 40, 1]] {
            let h = npy_header("<f4", &shape);
            assert_eq!(h.len() % 64, 0, "{shape:?}");
            assert_eq!(*h.last().expect("newline"), b'\n');
            let info = read_npy_header(&mut h.as_slice()).expect("parses");
            assert_eq!(info.shape, shape);
        }
    }
}
