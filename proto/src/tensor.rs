//! Codec for `relreward.v1.Tensor`: `shape` + `dtype` + raw little-endian, row-major bytes.
//!
//! Decoding validates before it trusts anything a peer sent: the dtype must be known, the
//! element count must not overflow, and the byte count must equal `numel * itemsize`. Errors
//! say which of these failed so that a server can answer INVALID_ARGUMENT with a useful
//! message (prefixed by the field name).

use crate::v1::{Dtype, Tensor};

/// Why a `Tensor` message is not a valid tensor.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CodecError {
    #[error("unknown dtype {0} (expected float32, float64, int32, int64, uint8 or bool)")]
    UnknownDType(i32),
    #[error("dtype is unset (DTYPE_UNSPECIFIED; expected float32, float64, int32, int64, uint8 or bool)")]
    UnsetDType,
    #[error("shape {shape:?} has more elements than fit in memory")]
    ShapeOverflow { shape: Vec<u64> },
    #[error("data has {actual} bytes but shape {shape:?} of {dtype} needs {expected}")]
    ByteCount { shape: Vec<u64>, dtype: &'static str, expected: u64, actual: u64 },
    #[error("dtype is {actual} where {expected} was expected")]
    WrongDType { expected: &'static str, actual: String },
    #[error("value at flat index {index} is not finite ({value})")]
    NotFinite { index: u64, value: f64 },
    #[error("value at flat index {index} ({value:e}) is {OUTSIDE_F32}")]
    OutOfF32Range { index: u64, value: f64 },
    #[error("bool byte at flat index {index} is {value}; a bool is one byte, 0 or 1")]
    NotBool { index: u64, value: u8 },
}

/// Size in bytes of one element, or `None` for `DTYPE_UNSPECIFIED`.
pub fn item_size(dtype: Dtype) -> Option<usize> {
    match dtype {
        Dtype::Unspecified => None,
        Dtype::Float32 | Dtype::Int32 => Some(4),
        Dtype::Float64 | Dtype::Int64 => Some(8),
        Dtype::Uint8 | Dtype::Bool => Some(1),
    }
}

/// Short lowercase name, as numpy spells it.
pub fn dtype_name(dtype: Dtype) -> &'static str {
    match dtype {
        Dtype::Unspecified => "unspecified",
        Dtype::Float32 => "float32",
        Dtype::Float64 => "float64",
        Dtype::Int32 => "int32",
        Dtype::Int64 => "int64",
        Dtype::Uint8 => "uint8",
        Dtype::Bool => "bool",
    }
}

/// Parses a numpy-style dtype name (`float32`, `f4`, `bool`, ...).
pub fn parse_dtype(name: &str) -> Option<Dtype> {
    Some(match name {
        "float32" | "f4" => Dtype::Float32,
        "float64" | "f8" => Dtype::Float64,
        "int32" | "i4" => Dtype::Int32,
        "int64" | "i8" => Dtype::Int64,
        "uint8" | "u1" => Dtype::Uint8,
        "bool" | "b1" => Dtype::Bool,
        _ => return None,
    })
}

/// The element type as a known `Dtype`, refusing `UNSPECIFIED` and out-of-range values.
pub fn known_dtype(raw: i32) -> Result<Dtype, CodecError> {
    match Dtype::try_from(raw) {
        Ok(Dtype::Unspecified) => Err(CodecError::UnsetDType),
        Err(_) => Err(CodecError::UnknownDType(raw)),
        Ok(d) => Ok(d),
    }
}

/// Number of elements of `shape`, checked for overflow (an empty shape is a scalar: 1).
pub fn numel(shape: &[u64]) -> Result<u64, CodecError> {
    shape
        .iter()
        .try_fold(1u64, |acc, &d| acc.checked_mul(d))
        .filter(|&n| n <= (isize::MAX as u64))
        .ok_or_else(|| CodecError::ShapeOverflow { shape: shape.to_vec() })
}

/// Byte length of `numel(shape)` elements of `dtype`, checked for overflow.
pub fn byte_len(shape: &[u64], dtype: Dtype) -> Result<u64, CodecError> {
    let size = item_size(dtype).ok_or(CodecError::UnsetDType)? as u64;
    numel(shape)?
        .checked_mul(size)
        .filter(|&n| n <= (isize::MAX as u64))
        .ok_or_else(|| CodecError::ShapeOverflow { shape: shape.to_vec() })
}

/// Checks that `t` is self-consistent and returns its dtype.
pub fn validate(t: &Tensor) -> Result<Dtype, CodecError> {
    let dtype = known_dtype(t.dtype)?;
    let expected = byte_len(&t.shape, dtype)?;
    let actual = t.data.len() as u64;
    if expected != actual {
        return Err(CodecError::ByteCount { shape: t.shape.clone(), dtype: dtype_name(dtype), expected, actual });
    }
    if dtype == Dtype::Bool
        && let Some(index) = t.data.iter().position(|&b| b > 1)
    {
        return Err(CodecError::NotBool { index: index as u64, value: t.data[index] });
    }
    Ok(dtype)
}

/// Encodes float32 values (row major) with the given shape. The caller guarantees
/// `data.len() == numel(shape)`; a mismatch is a programming error and is caught by `validate`
/// on the receiving side.
pub fn encode_f32(shape: &[u64], data: &[f32]) -> Tensor {
    let mut bytes = Vec::with_capacity(data.len() * 4);
    for v in data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    Tensor { shape: shape.to_vec(), dtype: Dtype::Float32 as i32, data: bytes }
}

/// Encodes float64 values (row major) with the given shape.
pub fn encode_f64(shape: &[u64], data: &[f64]) -> Tensor {
    let mut bytes = Vec::with_capacity(data.len() * 8);
    for v in data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    Tensor { shape: shape.to_vec(), dtype: Dtype::Float64 as i32, data: bytes }
}

/// Wraps raw little-endian bytes that the caller already holds (no conversion).
pub fn from_raw(shape: &[u64], dtype: Dtype, data: Vec<u8>) -> Result<Tensor, CodecError> {
    let t = Tensor { shape: shape.to_vec(), dtype: dtype as i32, data };
    validate(&t)?;
    Ok(t)
}

/// `t`'s dtype when it is one of `allowed` (`expected` names them in the error), then the
/// tensor's consistency. The dtype comes first: a tensor of another type is refused as that,
/// not for a byte count that only its type makes wrong.
fn validate_among(t: &Tensor, allowed: &[Dtype], expected: &'static str) -> Result<Dtype, CodecError> {
    let actual = match Dtype::try_from(t.dtype) {
        Ok(d) if allowed.contains(&d) => return validate(t),
        Ok(Dtype::Unspecified) => "unset (DTYPE_UNSPECIFIED)".to_owned(),
        Ok(d) => dtype_name(d).to_owned(),
        Err(_) => format!("an unknown value ({})", t.dtype),
    };
    Err(CodecError::WrongDType { expected, actual })
}

/// Visits every element of a float32 or float64 tensor as f64, in row-major order.
/// Integer and bool tensors are refused: they are not values to compute statistics on.
pub fn for_each_float(t: &Tensor, mut f: impl FnMut(f64)) -> Result<(), CodecError> {
    // validate_among lets only the two float types through: anything but float32 is float64.
    if validate_among(t, &[Dtype::Float32, Dtype::Float64], "float32 or float64")? == Dtype::Float32 {
        for c in t.data.chunks_exact(4) {
            f(f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])));
        }
    } else {
        for c in t.data.chunks_exact(8) {
            f(f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]));
        }
    }
    Ok(())
}

/// How every reader of values words [`beyond_f32`]'s case (the server's decoders, the client's
/// file readers), so a user meets one message for one rule.
pub const OUTSIDE_F32: &str = "outside float32's range (about 3.4e38), the precision models compute in";

/// Whether `v` is finite but beyond float32's range: narrowed, it would become an infinity.
/// The one place of this rule: NaN and infinities are not this case (callers refuse them as
/// "not finite", each with its own placing of the element).
pub fn beyond_f32(v: f64) -> bool {
    v.is_finite() && !(v as f32).is_finite()
}

/// Decodes a float32 or float64 tensor to float32 values (float64 is narrowed), refusing
/// NaN and infinities.
pub fn decode_finite_f32(t: &Tensor) -> Result<Vec<f32>, CodecError> {
    let mut out = Vec::with_capacity(t.data.len() / 4);
    let mut bad = None;
    for_each_float(t, |v| {
        if bad.is_none() && (beyond_f32(v) || !v.is_finite()) {
            bad = Some((out.len() as u64, v));
        }
        out.push(v as f32);
    })?;
    match bad {
        Some((index, value)) if value.is_finite() => Err(CodecError::OutOfF32Range { index, value }),
        Some((index, value)) => Err(CodecError::NotFinite { index, value }),
        None => Ok(out),
    }
}

/// Decodes an integer tensor (int32, int64 or uint8) to int64 values (class labels).
pub fn decode_i64(t: &Tensor) -> Result<Vec<i64>, CodecError> {
    let dtype = validate_among(t, &[Dtype::Int32, Dtype::Int64, Dtype::Uint8], "int32, int64 or uint8")?;
    Ok(match dtype {
        Dtype::Int64 => t.data.chunks_exact(8).map(|c| i64::from_le_bytes(c.try_into().unwrap_or([0; 8]))).collect(),
        Dtype::Int32 => {
            t.data.chunks_exact(4).map(|c| i64::from(i32::from_le_bytes(c.try_into().unwrap_or([0; 4])))).collect()
        }
        _ => t.data.iter().map(|&b| i64::from(b)).collect(),
    })
}

/// Decodes a bool or uint8 tensor as flags (non-zero is true).
pub fn decode_flags(t: &Tensor) -> Result<Vec<bool>, CodecError> {
    validate_among(t, &[Dtype::Bool, Dtype::Uint8], "bool or uint8")?;
    Ok(t.data.iter().map(|&b| b != 0).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_float64_beyond_float32_is_named_as_such() {
        let e = decode_finite_f32(&encode_f64(&[2], &[1.0, 1e300])).expect_err("1e300");
        assert!(e.to_string().contains("index 1 (1e300) is outside float32's range"), "{e}");
        let e = decode_finite_f32(&encode_f64(&[1], &[f64::NAN])).expect_err("nan");
        assert!(e.to_string().contains("not finite"), "{e}");
    }

    #[test]
    fn a_bool_byte_other_than_0_or_1_is_refused() {
        let t = Tensor { shape: vec![3], dtype: Dtype::Bool as i32, data: vec![0, 1, 7] };
        let e = validate(&t).expect_err("byte 7");
        assert!(e.to_string().contains("index 2 is 7"), "{e}");
        let ok = Tensor { shape: vec![3], dtype: Dtype::Uint8 as i32, data: vec![0, 1, 7] };
        assert_eq!(validate(&ok).expect("uint8 takes any byte"), Dtype::Uint8);
    }

    #[test]
    fn f32_round_trip_preserves_bits() {
        let values = [0.0f32, -1.5, f32::MIN_POSITIVE, 3.25e7, -0.0];
        let t = encode_f32(&[5], &values);
        assert_eq!(validate(&t), Ok(Dtype::Float32));
        let back = decode_finite_f32(&t).expect("finite");
        assert_eq!(
            back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            values.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
    }

    #[test]
    fn bytes_are_little_endian_row_major() {
        let t = encode_f32(&[2, 2], &[1.0, 2.0, 3.0, 4.0]);
        // 2.0f32 = 0x40000000, stored little-endian as the second element.
        assert_eq!(&t.data[4..8], &[0x00, 0x00, 0x00, 0x40]);
        let t64 = encode_f64(&[1], &[1.0]);
        assert_eq!(t64.data, 1.0f64.to_le_bytes().to_vec());
    }

    #[test]
    fn float64_is_narrowed() {
        let t = encode_f64(&[3], &[0.1, 2.0, -7.0]);
        assert_eq!(decode_finite_f32(&t).expect("finite"), vec![0.1f32, 2.0, -7.0]);
    }

    #[test]
    fn wrong_byte_count_is_reported_with_both_sizes() {
        let mut t = encode_f32(&[3], &[1.0, 2.0, 3.0]);
        t.data.pop();
        let err = validate(&t).expect_err("wrong byte count");
        assert_eq!(err, CodecError::ByteCount { shape: vec![3], dtype: "float32", expected: 12, actual: 11 });
        assert!(err.to_string().contains("11 bytes") && err.to_string().contains("needs 12"));
    }

    #[test]
    fn unknown_and_unspecified_dtypes_are_refused() {
        let t = Tensor { shape: vec![1], dtype: 99, data: vec![0; 4] };
        assert_eq!(validate(&t), Err(CodecError::UnknownDType(99)));
        let t = Tensor { shape: vec![1], dtype: 0, data: vec![0; 4] };
        assert_eq!(validate(&t), Err(CodecError::UnsetDType));
    }

    #[test]
    fn overflowing_shapes_are_refused_not_panicking() {
        let t = Tensor { shape: vec![u64::MAX, 2], dtype: Dtype::Float32 as i32, data: vec![] };
        assert!(matches!(validate(&t), Err(CodecError::ShapeOverflow { .. })));
        let t = Tensor { shape: vec![1 << 62], dtype: Dtype::Float64 as i32, data: vec![] };
        assert!(matches!(validate(&t), Err(CodecError::ShapeOverflow { .. })));
    }

    #[test]
    fn scalar_and_empty_shapes() {
        let t = encode_f32(&[], &[4.0]);
        assert_eq!(decode_finite_f32(&t).expect("scalar"), vec![4.0]);
        let t = encode_f32(&[0, 3], &[]);
        assert_eq!(decode_finite_f32(&t).expect("empty"), Vec::<f32>::new());
    }

    #[test]
    fn non_finite_values_are_located() {
        let t = encode_f32(&[4], &[1.0, 2.0, f32::NAN, f32::INFINITY]);
        assert!(matches!(decode_finite_f32(&t), Err(CodecError::NotFinite { index: 2, .. })));
        let t = encode_f64(&[2], &[f64::NEG_INFINITY, 0.0]);
        assert!(matches!(decode_finite_f32(&t), Err(CodecError::NotFinite { index: 0, .. })));
    }

    #[test]
    fn flags_accept_bool_and_uint8_only() {
        let t = Tensor { shape: vec![3], dtype: Dtype::Bool as i32, data: vec![0, 1, 0] };
        assert_eq!(decode_flags(&t).expect("bool"), vec![false, true, false]);
        let t = encode_f32(&[1], &[1.0]);
        assert!(matches!(decode_flags(&t), Err(CodecError::WrongDType { .. })));
    }

    #[test]
    fn a_decoder_names_a_wrong_dtype_before_any_byte_count() {
        // float32 bytes labelled as another type: the type is what is wrong.
        let floats = encode_f32(&[2, 3], &[0.5; 6]);
        for (dtype, named) in [
            (Dtype::Bool as i32, "dtype is bool where float32 or float64"),
            (Dtype::Int64 as i32, "dtype is int64 where float32 or float64"),
            (0, "dtype is unset (DTYPE_UNSPECIFIED) where float32 or float64"),
            (99, "dtype is an unknown value (99) where float32 or float64"),
        ] {
            let t = Tensor { dtype, ..floats.clone() };
            let err = decode_finite_f32(&t).expect_err("wrong dtype").to_string();
            assert!(err.starts_with(named), "{err}");
        }
        let err = decode_flags(&Tensor { dtype: Dtype::Int32 as i32, ..floats.clone() }).expect_err("int32");
        assert!(err.to_string().starts_with("dtype is int32 where bool or uint8"), "{err}");
        // float64 is one of the types allowed: its byte count is then what is wrong.
        let t = Tensor { dtype: Dtype::Float64 as i32, ..floats };
        assert!(matches!(decode_finite_f32(&t), Err(CodecError::ByteCount { .. })));
    }

    #[test]
    fn dtype_names_round_trip() {
        for d in [Dtype::Float32, Dtype::Float64, Dtype::Int32, Dtype::Int64, Dtype::Uint8, Dtype::Bool] {
            assert_eq!(parse_dtype(dtype_name(d)), Some(d));
        }
        assert_eq!(parse_dtype("complex64"), None);
    }
}
