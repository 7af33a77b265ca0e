//! Where the bytes of a dataset upload come from: [`UploadSource`] and the in-memory
//! [`MemorySource`].
//!
//! It is part of the wire contract the way [`crate::tensor`] is: an upload sends every array in
//! header order, each as row chunks, and the sha256 sent at commit covers the concatenation of
//! all arrays' raw bytes in that order (see `UploadDataset` in datasets.proto). It lives here,
//! the crate every side depends on, so that the toolkit's file readers can produce a source
//! without depending on the client, and the client can send one without depending on the
//! toolkit. The chunker that cuts a source into messages is the client's (`relreward_client::upload`).

use std::io::{self, Read};

use crate::tensor;
use crate::v1::{ArraySpec, Dtype};

/// A set of arrays to upload, read one after the other.
pub trait UploadSource: Send + 'static {
    /// The arrays in the order they will be sent, with full shapes.
    fn arrays(&self) -> &[ArraySpec];
    /// A reader of array `index`'s raw little-endian, row-major bytes: exactly
    /// `numel(shape) * itemsize` of them.
    fn open(&mut self, index: usize) -> io::Result<Box<dyn Read + '_>>;
}

/// Arrays already in memory (tests, small uploads, programmatic use).
#[derive(Debug, Clone, Default)]
pub struct MemorySource {
    specs: Vec<ArraySpec>,
    bytes: Vec<Vec<u8>>,
}

impl MemorySource {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds an array of raw little-endian bytes.
    pub fn push_raw(&mut self, name: &str, dtype: Dtype, shape: &[u64], bytes: Vec<u8>) -> &mut Self {
        self.specs.push(ArraySpec { name: name.to_owned(), dtype: dtype as i32, shape: shape.to_vec() });
        self.bytes.push(bytes);
        self
    }

    /// Adds a float32 array.
    pub fn push_f32(&mut self, name: &str, shape: &[u64], values: &[f32]) -> &mut Self {
        let t = tensor::encode_f32(shape, values);
        self.push_raw(name, Dtype::Float32, shape, t.data)
    }

    /// Adds a bool array.
    pub fn push_bool(&mut self, name: &str, values: &[bool]) -> &mut Self {
        let bytes = values.iter().map(|&b| u8::from(b)).collect();
        self.push_raw(name, Dtype::Bool, &[values.len() as u64], bytes)
    }
}

impl UploadSource for MemorySource {
    fn arrays(&self) -> &[ArraySpec] {
        &self.specs
    }

    fn open(&mut self, index: usize) -> io::Result<Box<dyn Read + '_>> {
        let bytes = self
            .bytes
            .get(index)
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, format!("no array {index}")))?;
        Ok(Box::new(bytes.as_slice()))
    }
}
