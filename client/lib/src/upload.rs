//! How an upload is cut into messages. Where its bytes come from, [`UploadSource`] and
//! [`MemorySource`], is part of the wire contract and lives in `relreward-proto` (shared with
//! the toolkit's file readers); it is re-exported here and at the crate root.
//!
//! An upload sends every array in header order, each as row chunks; the sha256 sent at commit
//! covers the concatenation of all arrays' raw bytes in that order, so it does not depend on
//! the chunk size (see `UploadDataset` in datasets.proto).

use relreward_proto::tensor;
pub use relreward_proto::upload::{MemorySource, UploadSource};
use relreward_proto::v1::ArraySpec;

/// Bytes of one row (the product of the trailing dimensions times the item size).
pub fn row_bytes(spec: &ArraySpec) -> Result<u64, tensor::CodecError> {
    let dtype = tensor::known_dtype(spec.dtype)?;
    tensor::byte_len(spec.shape.get(1..).unwrap_or(&[]), dtype)
}

/// Total payload bytes of all arrays.
pub fn total_bytes(specs: &[ArraySpec]) -> Result<u64, tensor::CodecError> {
    specs.iter().try_fold(0u64, |acc, s| {
        let dtype = tensor::known_dtype(s.dtype)?;
        let n = tensor::byte_len(&s.shape, dtype)?;
        acc.checked_add(n).ok_or_else(|| tensor::CodecError::ShapeOverflow { shape: s.shape.clone() })
    })
}

/// Rows per chunk so that one chunk carries about `target_bytes` (at least one row).
pub fn rows_per_chunk(row_bytes: u64, target_bytes: u64) -> u64 {
    (target_bytes / row_bytes.max(1)).max(1)
}
