//! Writes `.npy` files (format 1.0), the on-disk form of stored arrays: researchers can
//! `np.load` a dataset's files directly, and the bytes after the header are exactly the
//! uploaded (and digested) bytes.

use relreward_proto::v1::Dtype;

/// numpy's type string for a dtype.
pub fn descr(dtype: Dtype) -> &'static str {
    match dtype {
        Dtype::Float32 => "<f4",
        Dtype::Float64 => "<f8",
        Dtype::Int32 => "<i4",
        Dtype::Int64 => "<i8",
        Dtype::Uint8 => "|u1",
        Dtype::Bool => "|b1",
        Dtype::Unspecified => "|V0",
    }
}

/// The complete header (magic, version, length, dict, padding) for a C-order array.
pub fn header(dtype: Dtype, shape: &[u64]) -> Vec<u8> {
    let dims = match shape {
        [one] => format!("({one},)"),
        _ => format!("({})", shape.iter().map(u64::to_string).collect::<Vec<_>>().join(", ")),
    };
    let mut dict = format!("{{'descr': '{}', 'fortran_order': False, 'shape': {dims}, }}", descr(dtype));
    // magic(6) + version(2) + len(2) + dict + '\n' must be a multiple of 64.
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

/// An array read back from a stored `.npy` file.
pub struct Array {
    pub shape: Vec<u64>,
    pub dtype: Dtype,
    /// Raw little-endian bytes after the header.
    pub data: Vec<u8>,
}

impl Array {
    /// The values as float32 (float64 narrowed); `None` for non-float arrays.
    pub fn to_f32(&self) -> Option<Vec<f32>> {
        match self.dtype {
            Dtype::Float32 => {
                Some(self.data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
            }
            Dtype::Float64 => Some(
                self.data
                    .chunks_exact(8)
                    .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32)
                    .collect(),
            ),
            _ => None,
        }
    }

    /// The values as int64 (integer arrays: int32, int64, uint8); `None` for the others.
    pub fn to_i64(&self) -> Option<Vec<i64>> {
        match self.dtype {
            Dtype::Int64 => Some(
                self.data
                    .chunks_exact(8)
                    .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
                    .collect(),
            ),
            Dtype::Int32 => Some(
                self.data.chunks_exact(4).map(|c| i64::from(i32::from_le_bytes([c[0], c[1], c[2], c[3]]))).collect(),
            ),
            Dtype::Uint8 => Some(self.data.iter().map(|&b| i64::from(b)).collect()),
            _ => None,
        }
    }

    /// The values as flags (non-zero is true); `None` for non-flag arrays.
    pub fn to_flags(&self) -> Option<Vec<bool>> {
        matches!(self.dtype, Dtype::Bool | Dtype::Uint8).then(|| self.data.iter().map(|&b| b != 0).collect())
    }
}

/// Reads a file this module wrote, given the dtype and shape its record declares: the header
/// is skipped by its stored length and the payload length is checked, so a truncated or
/// altered file is reported rather than misread.
pub fn read(path: &std::path::Path, dtype: Dtype, shape: &[u64]) -> crate::error::Result<Array> {
    use crate::error::Error;
    let bytes = std::fs::read(path).map_err(|e| Error::internal(&format!("reading {}", path.display()), e))?;
    let expected_header = header(dtype, shape);
    let payload = relreward_proto::tensor::byte_len(shape, dtype)
        .map_err(|e| Error::DataLoss(format!("{}: {e}", path.display())))? as usize;
    if bytes.len() != expected_header.len() + payload || bytes[..expected_header.len()] != expected_header[..] {
        return Err(Error::DataLoss(format!(
            "{} does not match its record (expected {} bytes of {:?} {}); the stored dataset is damaged",
            path.display(),
            expected_header.len() + payload,
            shape,
            descr(dtype)
        )));
    }
    Ok(Array { shape: shape.to_vec(), dtype, data: bytes[expected_header.len()..].to_vec() })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn read_returns_what_was_written_and_detects_truncation() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("a.npy");
        let values = [1.5f32, -2.0, 3.25, 0.0];
        let mut bytes = header(Dtype::Float32, &[2, 2]);
        for v in values {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        std::fs::write(&path, &bytes).expect("write");
        let a = read(&path, Dtype::Float32, &[2, 2]).expect("read");
        assert_eq!(a.to_f32().expect("float"), values);
        std::fs::write(&path, &bytes[..bytes.len() - 1]).expect("truncate");
        assert!(read(&path, Dtype::Float32, &[2, 2]).is_err());
    }

    #[test]
    fn header_is_aligned_and_well_formed() {
        for shape in [vec![7u64], vec![1_000_000, 4], vec![3, 4, 8, 8]] {
            let h = header(Dtype::Float32, &shape);
            assert_eq!(h.len() % 64, 0);
            assert_eq!(&h[..8], b"\x93NUMPY\x01\x00");
            let len = u16::from_le_bytes([h[8], h[9]]) as usize;
            assert_eq!(len + 10, h.len());
            let text = std::str::from_utf8(&h[10..]).expect("ascii");
            assert!(text.ends_with('\n'));
            assert!(text.contains("'descr': '<f4'"));
        }
        let h = header(Dtype::Bool, &[5]);
        assert!(std::str::from_utf8(&h[10..]).expect("ascii").contains("'shape': (5,)"));
    }
}
