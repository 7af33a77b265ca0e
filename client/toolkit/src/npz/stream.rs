//! Readers over one array's stored data bytes, as an upload sends them: [`ExactReader`] yields
//! exactly the bytes the header declares (and says so when the file ends early);
//! [`F32Reader`] converts any stored integer or float to float32 as it reads, refusing a value
//! that is not finite as float32 by array, row and coordinate ([`crate::values::to_f32`]).
//! Both stream, so an array larger than memory uploads fine.

use std::io::{self, Read};

use super::error::invalid_data;
use crate::values::Element;

/// Yields exactly `len` bytes of `inner`, and a clear error if it ends before that.
pub(super) struct ExactReader<R> {
    inner: R,
    remaining: u64,
    len: u64,
    label: String,
}

impl<R: Read> ExactReader<R> {
    pub(super) fn new(inner: R, len: u64, label: String) -> Self {
        Self { inner, remaining: len, len, label }
    }
}

impl<R: Read> Read for ExactReader<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.remaining == 0 || buf.is_empty() {
            return Ok(0);
        }
        let want = usize::try_from(self.remaining).map_or(buf.len(), |r| r.min(buf.len()));
        let n = self.inner.read(&mut buf[..want])?;
        if n == 0 {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                format!(
                    "{} ends after {} of its {} data bytes (truncated file?)",
                    self.label,
                    self.len - self.remaining,
                    self.len
                ),
            ));
        }
        self.remaining -= n as u64;
        Ok(n)
    }
}

/// Converts a stream of stored elements to float32 (little-endian bytes), refusing a value that
/// is not finite as float32 ([`crate::values::to_f32`]) with an `InvalidData` error that names
/// the array, the row and the coordinate.
pub(super) struct F32Reader<R> {
    inner: R,
    element: Element,
    /// The stored shape, to place a bad value.
    shape: Vec<u64>,
    label: String,
    /// Elements converted so far.
    index: usize,
    /// Bytes of a partly read element.
    carry: Vec<u8>,
    out: Vec<u8>,
    at: usize,
}

impl<R: Read> F32Reader<R> {
    const BLOCK: usize = 64 * 1024;

    pub(super) fn new(inner: R, element: Element, shape: Vec<u64>, label: String) -> Self {
        Self { inner, element, shape, label, index: 0, carry: Vec::new(), out: Vec::new(), at: 0 }
    }

    /// Converts the next block; `false` at the end of the data.
    fn fill(&mut self) -> io::Result<bool> {
        let size = self.element.size;
        let mut raw = std::mem::take(&mut self.carry);
        let start = raw.len();
        raw.resize(start + Self::BLOCK, 0);
        let n = loop {
            match self.inner.read(&mut raw[start..]) {
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                other => break other?,
            }
        };
        raw.truncate(start + n);
        if n == 0 {
            if raw.is_empty() {
                return Ok(false);
            }
            return Err(invalid_data(format!("{} ends inside an element", self.label)));
        }
        let whole = raw.len() / size * size;
        self.carry = raw[whole..].to_vec();
        self.out.clear();
        self.at = 0;
        for chunk in raw[..whole].chunks_exact(size) {
            let value = crate::values::to_f32(&self.label, self.element.decode(chunk), self.index, &self.shape)
                .map_err(invalid_data)?;
            self.out.extend_from_slice(&value.to_le_bytes());
            self.index += 1;
        }
        Ok(true)
    }
}

impl<R: Read> Read for F32Reader<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if buf.is_empty() {
            return Ok(0);
        }
        while self.at == self.out.len() {
            if !self.fill()? {
                return Ok(0);
            }
        }
        let n = buf.len().min(self.out.len() - self.at);
        buf[..n].copy_from_slice(&self.out[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use std::io;

    use crate::npz::test_files::{UploadSource, encode, f64_bytes, npy, read_all, scratch, sent_f32, spec, write_npz};
    use crate::npz::trajectories_from_npz;
    use relreward_client::client::payload_sha256;
    use relreward_proto::tensor;
    use relreward_proto::v1::Dtype;

    #[test]
    fn every_integer_and_float_dtype_in_either_byte_order_is_sent_as_float32() {
        let (_dir, path) = scratch("t.npz");
        // Values every type holds exactly (unsigned: no negatives).
        let signed = [0.0, -1.0, 2.0, -3.0, 4.0, 5.5, -6.5, 7.0];
        let unsigned = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0];
        for order in ['<', '>'] {
            for ty in ["i1", "i2", "i4", "i8", "u1", "u2", "u4", "u8", "f2", "f4", "f8"] {
                let descr = if ty.ends_with('1') { format!("|{ty}") } else { format!("{order}{ty}") };
                let values: Vec<f64> = if ty.starts_with('f') {
                    signed.to_vec()
                } else if ty.starts_with('u') {
                    unsigned.to_vec()
                } else {
                    signed.iter().map(|v| v.trunc()).collect()
                };
                let data = encode(&format!("{order}{ty}"), &values);
                write_npz(
                    &path,
                    &[
                        ("observations", npy(&descr, false, &[4, 2], &data)),
                        ("actions", npy(&descr, false, &[4], &data[..data.len() / 2])),
                    ],
                    false,
                );
                let mut source = trajectories_from_npz(&path).unwrap_or_else(|e| panic!("{descr}: {e}"));
                assert_eq!(
                    source.arrays(),
                    &[spec("observations", Dtype::Float32, &[4, 2]), spec("actions", Dtype::Float32, &[4, 1])],
                    "{descr}"
                );
                let want: Vec<f32> = values.iter().map(|&v| v as f32).collect();
                assert_eq!(sent_f32(&mut source, 0).expect("obs"), want, "{descr}");
                assert_eq!(sent_f32(&mut source, 1).expect("act"), &want[..4], "{descr}");
                assert_eq!(source.total_bytes(), 32 + 16);
                // Whole-array reads (score, extract) convert too.
                let t = source.read_tensor(0).expect("tensor");
                assert_eq!(tensor::decode_finite_f32(&t).expect("finite"), want, "{descr}");
            }
        }
        // float64 is rounded to float32, as the HDF5 reader does.
        write_npz(
            &path,
            &[
                ("observations", npy("<f8", false, &[1, 1], &f64_bytes(&[0.1]))),
                ("actions", npy(">f8", false, &[1, 1], &0.1f64.to_be_bytes())),
            ],
            false,
        );
        let mut source = trajectories_from_npz(&path).expect("f64");
        assert_eq!(sent_f32(&mut source, 0).expect("obs"), [0.1f32]);
        assert_eq!(sent_f32(&mut source, 1).expect("act"), [0.1f32]);
    }

    #[test]
    fn values_not_finite_as_float32_are_refused_naming_row_and_coordinate() {
        let (_dir, path) = scratch("t.npz");
        let act = npy("<f4", false, &[2, 1], &[0; 8]);
        for (values, shape, want) in [
            (vec![0.0, 1.0, 2.0, f64::NAN], vec![2, 2], "value NaN at row 1, coordinate 1 is not finite"),
            (vec![0.0, 1e300, 2.0, 3.0], vec![2, 2], "value 1e300 at row 0, coordinate 1 is outside float32's range"),
            (vec![0.0, 1.0, f64::INFINITY, 3.0], vec![2, 1, 2], "row 1, flattened coordinate 0 of [1, 2]"),
        ] {
            write_npz(
                &path,
                &[("observations", npy("<f8", false, &shape, &f64_bytes(&values))), ("actions", act.clone())],
                false,
            );
            let mut source = trajectories_from_npz(&path).expect("opens: values are read when sent");
            let err = read_all(&mut source, 0).expect_err("not finite");
            assert_eq!(err.kind(), io::ErrorKind::InvalidData);
            let err = err.to_string();
            assert!(err.contains("'observations'") && err.contains(want), "{err}");
            assert!(payload_sha256(&mut source).is_err());
        }
    }
}
