//! Writes numpy `.npz` archives: an uncompressed zip of `.npy` files (what `np.savez` writes),
//! for the results of `score`, `grad` and `sample`, and for `relabel`, which copies another
//! archive's members unchanged ([`NpzWriter::copy_members`]).
//!
//! Arrays are float32, int64 or bool, little-endian, C order, in npy format 1.0 (headers padded to
//! a multiple of 64 bytes, as numpy does). The archive is written to a temporary file next to
//! the destination and renamed into place only once it is complete, so a failed or interrupted
//! write never leaves a half-written file under the requested name.
//!
//! The zip writer is the one `npyz` re-exports (already used to read archives), so no second
//! zip implementation enters the build; the npy header is written by the reader's own
//! [`crate::npz`] writer, so the two agree on the format by construction.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use npyz::zip::write::FileOptions;
use npyz::zip::{CompressionMethod, ZipWriter};

use crate::npz::write_npy_header;

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
        self.add_le(name, "<f4", shape, values, f32::to_le_bytes)
    }

    /// Adds an int64 array `name` of `shape`.
    pub fn add_i64(&mut self, name: &str, shape: &[u64], values: &[i64]) -> io::Result<()> {
        self.add_le(name, "<i8", shape, values, i64::to_le_bytes)
    }

    /// Adds a bool array `name` of `shape` (episode flags).
    pub fn add_bool(&mut self, name: &str, shape: &[u64], values: &[bool]) -> io::Result<()> {
        self.add(name, "|b1", shape, values.len(), |w| {
            let bytes: Vec<u8> = values.iter().map(|&b| u8::from(b)).collect();
            w.write_all(&bytes)
        })
    }

    /// Adds an array of numbers written little-endian by `to_le`, in blocks so that a large
    /// array is never copied whole.
    fn add_le<T: Copy, const N: usize>(
        &mut self,
        name: &str,
        descr: &str,
        shape: &[u64],
        values: &[T],
        to_le: fn(T) -> [u8; N],
    ) -> io::Result<()> {
        self.add(name, descr, shape, values.len(), |w| {
            for chunk in values.chunks(1 << 14) {
                let bytes: Vec<u8> = chunk.iter().flat_map(|&v| to_le(v)).collect();
                w.write_all(&bytes)?;
            }
            Ok(())
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
        let header = write_npy_header(descr, false, shape);
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

    /// Copies the members of archive `src` byte for byte (compressed ones stay compressed), each
    /// under the name `rename` gives its array name (`rewards` for `rewards.npy`), or skipped
    /// where it gives `None`.
    pub fn copy_members(&mut self, src: &Path, rename: impl Fn(&str) -> Option<String>) -> io::Result<()> {
        let mut archive = npyz::zip::ZipArchive::new(io::BufReader::new(File::open(src)?)).map_err(io::Error::other)?;
        for i in 0..archive.len() {
            let member = archive.by_index_raw(i).map_err(io::Error::other)?;
            let name = member.name().to_owned();
            let array = name.strip_suffix(".npy").unwrap_or(&name);
            let Some(to) = rename(array) else { continue };
            if self.names.contains(&to) {
                return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("array name '{to}' is used twice")));
            }
            let zip = self.zip.as_mut().ok_or_else(|| io::Error::other("the archive is already finished"))?;
            zip.raw_copy_file_rename(member, format!("{to}.npy")).map_err(io::Error::other)?;
            self.names.push(to);
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz::{npz_keys, read_npy_header, samples_from_npz_or_npy};
    use relreward_proto::tensor;
    use relreward_proto::upload::UploadSource;
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
}
