//! [`NpzSource`]: the arrays a reader chose from one `.npz` or `.npy` file, as an
//! [`UploadSource`]. Each array is an [`Entry`]: where its bytes are (an archive member, the
//! `.npy` file itself, or bytes made in memory) and how they are sent (as stored, or converted
//! to float32). Sending reopens the array, checks its header is unchanged, and streams exactly
//! its declared data ([`super::stream`]).

use std::fmt;
use std::fs::File;
use std::io::{self, BufReader, Read};
use std::path::{Path, PathBuf};

use relreward_proto::tensor;
use relreward_proto::upload::UploadSource;
use relreward_proto::v1::{ArraySpec, DatasetKind, Dtype};

use super::archive::Archive;
use super::error::invalid_data;
use super::npy::{Header, read_header};
use super::stream::{ExactReader, F32Reader};

/// Where one array's bytes are, and how they are sent.
#[derive(Debug, Clone)]
pub(super) struct Entry {
    /// Name in the file (differs from the sent name for Minari aliases and samples).
    pub(super) key: String,
    /// Archive entry index; `None` for a plain `.npy` file or an array made in memory.
    pub(super) zip_index: Option<usize>,
    /// The array's header as stored; checked again whenever the array is reopened. `None` for
    /// an array made in memory.
    pub(super) stored: Option<Header>,
    /// The bytes of an array converted while reading (episode flags as bool; episode starts
    /// given as indices or lengths as per-row flags, see [`crate::episodes`]).
    pub(super) memory: Option<Vec<u8>>,
    /// Whether the stored values are converted to float32 as they are read
    /// ([`crate::values`]): observations and actions.
    pub(super) to_f32: bool,
    /// Bytes sent.
    pub(super) sent_len: u64,
}

impl Entry {
    /// An array sent as stored.
    pub(super) fn as_stored(key: String, zip_index: Option<usize>, header: Header) -> Self {
        let sent_len = header.data_len;
        Self { key, zip_index, stored: Some(header), memory: None, to_f32: false, sent_len }
    }

    /// An array made in memory.
    pub(super) fn in_memory(key: String, bytes: Vec<u8>) -> Self {
        let sent_len = bytes.len() as u64;
        Self { key, zip_index: None, stored: None, memory: Some(bytes), to_f32: false, sent_len }
    }
}

/// Arrays of one `.npz` or `.npy` file, ready to upload (see the module docs).
pub struct NpzSource {
    path: PathBuf,
    kind: DatasetKind,
    specs: Vec<ArraySpec>,
    entries: Vec<Entry>,
    ignored: Vec<String>,
    archive: Option<Archive>,
}

impl fmt::Debug for NpzSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("NpzSource")
            .field("path", &self.path)
            .field("kind", &self.kind)
            .field("specs", &self.specs)
            .field("entries", &self.entries)
            .field("ignored", &self.ignored)
            .finish_non_exhaustive()
    }
}

impl NpzSource {
    /// A source of no arrays yet; [`NpzSource::push`] adds them in the order they are sent.
    pub(super) fn new(path: &Path, kind: DatasetKind, ignored: Vec<String>, archive: Option<Archive>) -> Self {
        Self { path: path.to_owned(), kind, specs: Vec::new(), entries: Vec::new(), ignored, archive }
    }

    /// The archive the arrays' members are reopened from when sent.
    pub(super) fn set_archive(&mut self, archive: Archive) {
        self.archive = Some(archive);
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The dataset kind these arrays make.
    pub fn kind(&self) -> DatasetKind {
        self.kind
    }

    /// Arrays in the file that will not be sent, in archive order.
    pub fn ignored_keys(&self) -> &[String] {
        &self.ignored
    }

    /// The name of array `index` in the file (e.g. `terminations` for `terminals`; the only
    /// array of an `.npy` file is named after the file).
    pub fn file_key(&self, index: usize) -> Option<&str> {
        self.entries.get(index).map(|e| e.key.as_str())
    }

    /// Arrays sent under another name than the file's: `(file key, sent name)`.
    pub fn renamed(&self) -> Vec<(String, String)> {
        self.entries
            .iter()
            .zip(&self.specs)
            .filter(|(e, s)| e.key != s.name)
            .map(|(e, s)| (e.key.clone(), s.name.clone()))
            .collect()
    }

    /// Total data bytes of every array that will be sent.
    pub fn total_bytes(&self) -> u64 {
        self.entries.iter().map(|e| e.sent_len).sum()
    }

    /// Reads array `index` whole into memory, as a wire tensor (its full shape and dtype).
    /// For inputs that are sent in pieces of their own making (`score`, `grad`), not uploads.
    pub fn read_tensor(&mut self, index: usize) -> io::Result<relreward_proto::v1::Tensor> {
        let spec = self
            .specs
            .get(index)
            .cloned()
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, format!("no array {index}")))?;
        let len = self.entries[index].sent_len;
        let len =
            usize::try_from(len).map_err(|_| invalid_data(format!("array '{}' does not fit in memory", spec.name)))?;
        let mut data = Vec::new();
        data.try_reserve_exact(len).map_err(|_| {
            io::Error::new(
                io::ErrorKind::OutOfMemory,
                format!("array '{}' ({len} bytes) does not fit in memory", spec.name),
            )
        })?;
        self.open(index)?.read_to_end(&mut data)?;
        let dtype = tensor::known_dtype(spec.dtype).map_err(|e| invalid_data(e.to_string()))?;
        tensor::from_raw(&spec.shape, dtype, data).map_err(|e| invalid_data(format!("array '{}': {e}", spec.name)))
    }

    /// Adds an array sent as `name`.
    pub(super) fn push(&mut self, name: &str, dtype: Dtype, shape: Vec<u64>, entry: Entry) {
        self.specs.push(ArraySpec { name: name.to_owned(), dtype: dtype as i32, shape });
        self.entries.push(entry);
    }
}

impl UploadSource for NpzSource {
    fn arrays(&self) -> &[ArraySpec] {
        &self.specs
    }

    fn open(&mut self, index: usize) -> io::Result<Box<dyn Read + '_>> {
        let entry = self
            .entries
            .get(index)
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, format!("no array {index}")))?;
        let path = self.path.display();
        let key = &entry.key;
        if let Some(bytes) = &entry.memory {
            return Ok(Box::new(bytes.as_slice()));
        }
        let Some(stored) = &entry.stored else { return Err(io::Error::other("npz source is inconsistent")) };
        let changed = |header: Header| {
            if header == *stored {
                Ok(())
            } else {
                Err(invalid_data(format!("{path}: array '{key}' changed since the file was first read")))
            }
        };
        let header_err = |m: String| invalid_data(format!("{path}: array '{key}': {m}"));
        let label = format!("{path}: array '{key}'");
        let data: Box<dyn Read + '_> = match (&mut self.archive, entry.zip_index) {
            (Some(archive), Some(zip_index)) => {
                let mut file = archive.by_index(zip_index).map_err(io::Error::from)?;
                changed(read_header(&mut file).map_err(header_err)?)?;
                Box::new(ExactReader::new(file, stored.data_len, label))
            }
            (None, None) => {
                let mut file = BufReader::new(File::open(&self.path)?);
                changed(read_header(&mut file).map_err(header_err)?)?;
                Box::new(ExactReader::new(file, stored.data_len, label))
            }
            _ => return Err(io::Error::other("npz source is inconsistent")),
        };
        // Arrays stream row by row; one stored column-major is put in row order first, whole.
        let data: Box<dyn Read + '_> = if stored.fortran {
            let mut bytes = Vec::new();
            let mut data = data;
            data.read_to_end(&mut bytes)?;
            Box::new(io::Cursor::new(super::npy::c_order(&bytes, stored.element.size, &stored.shape)))
        } else {
            data
        };
        if entry.to_f32 {
            let label = format!("{path}: '{key}'");
            Ok(Box::new(F32Reader::new(data, stored.element, stored.shape.clone(), label)))
        } else {
            Ok(data)
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::npz::test_files::{UploadSource, d4rl_entries, scratch, write_npz};
    use crate::npz::trajectories_from_npz;
    use relreward_client::client::payload_sha256;
    use relreward_proto::v1::Dtype;

    #[test]
    fn digest_covers_the_arrays_in_header_order() {
        let (_dir, path) = scratch("d.npz");
        let (entries, data) = d4rl_entries();
        write_npz(&path, &entries, true);
        let mut source = trajectories_from_npz(&path).expect("read");
        let mut memory = relreward_proto::upload::MemorySource::new();
        for (s, bytes) in source.arrays().to_vec().iter().zip(data) {
            memory.push_raw(&s.name, Dtype::try_from(s.dtype).expect("dtype"), &s.shape, bytes);
        }
        assert_eq!(payload_sha256(&mut source).expect("digest"), payload_sha256(&mut memory).expect("digest"));
    }
}
