//! The rules every trajectory reader (`.npz`, D4RL HDF5, Minari) applies to the values it
//! reads, so that the same data gives the same dataset whatever file it came in
//! (`docs/data-formats.md`). The Python package (`relreward.datasets`) applies the same rules.
//!
//! - **Element types.** Any integer (int8..int64, uint8..uint64) or float (float16, float32,
//!   float64) in either byte order; bool only for flags. [`Element`] decodes one stored value.
//! - **Observations and actions are float32**: every value is converted to float32 (float16
//!   exactly; float64 and large integers rounded to nearest) and must be finite as float32
//!   ([`to_f32`]): NaN and infinities are refused, and so is a finite value beyond float32's
//!   range, naming the key, the row and the coordinate.
//! - **Shapes as rows** ([`row_shape`]): an array `[N]` is `N` rows of one value, `[N, d]` is
//!   `N` rows of `d`, and `[N, a, b, ...]` is `N` rows of `a * b * ...` values (the trailing
//!   dimensions flattened row-major, as numpy's `reshape(N, -1)`). A scalar is refused.
//! - **Episode flags** (`terminals`, `timeouts` and their Minari names) are `[N]` arrays of
//!   bool, or of any integer or float type whose values are all 0 or 1 ([`flags`]); any other
//!   value is refused naming the key, the first bad row and its value.

use std::fmt;

use relreward_proto::tensor;

/// What kind of number a stored element is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Bool,
    Int,
    Uint,
    Float,
}

/// One stored element: its kind, size in bytes (1, 2, 4 or 8; floats 2, 4 or 8) and byte order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Element {
    pub kind: Kind,
    pub size: usize,
    pub big_endian: bool,
}

impl Element {
    /// An element of `kind` and `size` bytes, or `None` when the pair is not one the readers
    /// decode (e.g. a 16-byte float, a 3-byte integer).
    pub fn new(kind: Kind, size: usize, big_endian: bool) -> Option<Self> {
        let ok = match kind {
            Kind::Bool => size == 1,
            Kind::Int | Kind::Uint => matches!(size, 1 | 2 | 4 | 8),
            Kind::Float => matches!(size, 2 | 4 | 8),
        };
        // One byte has no byte order.
        ok.then_some(Self { kind, size, big_endian: big_endian && size > 1 })
    }

    /// Whether the values are integers (not floats, not bool).
    pub fn is_integer(&self) -> bool {
        matches!(self.kind, Kind::Int | Kind::Uint)
    }

    /// Decodes one element from exactly [`Element::size`] bytes. Integers of 64 bits beyond
    /// 2^53 are rounded to the nearest f64; a bool byte is its value (0 or 1 when well formed).
    pub fn decode(&self, bytes: &[u8]) -> f64 {
        let mut b = [0u8; 8];
        let n = self.size.min(8).min(bytes.len());
        b[..n].copy_from_slice(&bytes[..n]);
        if self.big_endian {
            b[..n].reverse();
        }
        match (self.kind, self.size) {
            (Kind::Bool | Kind::Uint, 1) => f64::from(b[0]),
            (Kind::Uint, 2) => f64::from(u16::from_le_bytes([b[0], b[1]])),
            (Kind::Uint, 4) => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (Kind::Uint, _) => u64::from_le_bytes(b) as f64,
            (Kind::Int, 1) => f64::from(b[0] as i8),
            (Kind::Int, 2) => f64::from(i16::from_le_bytes([b[0], b[1]])),
            (Kind::Int, 4) => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (Kind::Int, _) => i64::from_le_bytes(b) as f64,
            (Kind::Float, 2) => f64::from(f16_to_f32(u16::from_le_bytes([b[0], b[1]]))),
            (Kind::Float, 4) => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (_, _) => f64::from_le_bytes(b),
        }
    }

    /// Decodes every element of `bytes` (a whole number of elements).
    pub fn decode_all(&self, bytes: &[u8]) -> Vec<f64> {
        bytes.chunks_exact(self.size).map(|c| self.decode(c)).collect()
    }
}

/// numpy's name for the type, with `big-endian` when it is (`int64`, `big-endian float32`).
impl fmt::Display for Element {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.big_endian {
            f.write_str("big-endian ")?;
        }
        match self.kind {
            Kind::Bool => f.write_str("bool"),
            Kind::Int => write!(f, "int{}", self.size * 8),
            Kind::Uint => write!(f, "uint{}", self.size * 8),
            Kind::Float => write!(f, "float{}", self.size * 8),
        }
    }
}

/// IEEE 754 half precision (binary16) to single precision. Exact: every half value (normal,
/// subnormal, zero, infinity) is a single-precision value; NaN stays NaN (payload kept).
pub fn f16_to_f32(bits: u16) -> f32 {
    let sign = if bits & 0x8000 != 0 { -1.0f32 } else { 1.0 };
    let exponent = u32::from((bits >> 10) & 0x1f);
    let mantissa = u32::from(bits & 0x3ff);
    match exponent {
        // Zero and subnormals: mantissa * 2^-24, exact in f32 (a power-of-two scaling of an
        // integer below 2^10, far above f32's smallest normal).
        0 => sign * (mantissa as f32) * f32::from_bits(0x3380_0000),
        0x1f => f32::from_bits((u32::from(bits & 0x8000) << 16) | 0x7f80_0000 | (mantissa << 13)),
        _ => f32::from_bits((u32::from(bits & 0x8000) << 16) | ((exponent + 127 - 15) << 23) | (mantissa << 13)),
    }
}

/// `(N, width)` of an array of `shape` read as rows: `[N]` is `(N, 1)`, `[N, d]` is `(N, d)`,
/// `[N, a, b, ...]` is `(N, a * b * ...)`. A scalar, and rows of no values (`[N, 0]`), are
/// refused naming `key` (quoted by the caller's convention: pass `'observations'`).
pub fn row_shape(key: &str, shape: &[u64]) -> Result<(usize, usize), String> {
    let Some((&n, trailing)) = shape.split_first() else {
        return Err(format!("{key} is a scalar (shape []); expected rows [N, ...]"));
    };
    if trailing.contains(&0) {
        return Err(format!("{key} has shape {shape:?}: its rows hold no values"));
    }
    let width = trailing.iter().try_fold(1u64, |a, &d| a.checked_mul(d));
    match (usize::try_from(n), width.and_then(|w| usize::try_from(w).ok())) {
        (Ok(n), Some(width)) => Ok((n, width)),
        _ => Err(format!("{key} has shape {shape:?}, too large for this machine")),
    }
}

/// Where flat element `index` of an array of `shape` (read by [`row_shape`]) is, in words:
/// `row R, coordinate C` for `[N]` and `[N, d]`; for more dimensions the coordinate is the
/// flattened (row-major) index within the row: `row R, flattened coordinate C of [a, b]`.
pub fn position(index: usize, shape: &[u64]) -> String {
    let trailing = shape.get(1..).unwrap_or(&[]);
    let width = trailing.iter().product::<u64>().max(1) as usize;
    let (row, col) = (index / width, index % width);
    if trailing.len() <= 1 {
        format!("row {row}, coordinate {col}")
    } else {
        format!("row {row}, flattened coordinate {col} of {trailing:?}")
    }
}

/// A value as float32, or why it cannot be one: not finite (NaN, infinite), or finite but
/// beyond float32's range. `index` and `shape` place it in the message ([`position`]).
pub fn to_f32(key: &str, value: f64, index: usize, shape: &[u64]) -> Result<f32, String> {
    if value.is_finite() && !tensor::beyond_f32(value) {
        return Ok(value as f32);
    }
    let at = position(index, shape);
    if value.is_finite() {
        Err(format!("{key}: value {value:e} at {at} is {}", tensor::OUTSIDE_F32))
    } else {
        Err(format!("{key}: value {value} at {at} is not finite"))
    }
}

/// Values as float32 by [`to_f32`], checking only the first `keep` rows (all of them when
/// `None`); rows after those are converted without a check (readers that drop them, as
/// Minari's last observation, must not refuse them).
pub fn rows_to_f32(key: &str, values: &[f64], shape: &[u64], keep: Option<usize>) -> Result<Vec<f32>, String> {
    let width = shape.get(1..).unwrap_or(&[]).iter().product::<u64>() as usize;
    let checked = keep.map_or(values.len(), |rows| rows.saturating_mul(width).min(values.len()));
    let mut out = Vec::with_capacity(values.len());
    for (i, &v) in values.iter().enumerate() {
        out.push(if i < checked { to_f32(key, v, i, shape)? } else { v as f32 });
    }
    Ok(out)
}

/// Episode flags from the values of a 1-D array (`key` as the caller shows it): every value must
/// be 0 or 1; the first other one (NaN included) is refused with its row and value.
pub fn flags(key: &str, values: &[f64]) -> Result<Vec<bool>, String> {
    if let Some((row, v)) = values.iter().enumerate().find(|(_, v)| **v != 0.0 && **v != 1.0) {
        return Err(format!(
            "{key} holds {v} at row {row}; episode flags must be bool, or numbers that are all 0 or 1"
        ));
    }
    Ok(values.iter().map(|&v| v == 1.0).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The value of a binary16 by its definition, in f64.
    fn half_value(bits: u16) -> f64 {
        let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
        let e = i32::from((bits >> 10) & 0x1f);
        let m = f64::from(bits & 0x3ff);
        match e {
            0 => sign * m * 2f64.powi(-24),
            0x1f if m == 0.0 => sign * f64::INFINITY,
            0x1f => f64::NAN,
            _ => sign * (1.0 + m / 1024.0) * 2f64.powi(e - 15),
        }
    }

    #[test]
    fn every_half_converts_exactly() {
        for bits in 0..=u16::MAX {
            let got = f16_to_f32(bits);
            let want = half_value(bits);
            if want.is_nan() {
                assert!(got.is_nan(), "{bits:#06x}");
            } else {
                assert_eq!(f64::from(got), want, "{bits:#06x}");
                assert_eq!(got.is_sign_negative(), bits & 0x8000 != 0, "{bits:#06x} sign");
            }
        }
        assert_eq!(f16_to_f32(0x3c00), 1.0);
        assert_eq!(f16_to_f32(0xc000), -2.0);
        assert_eq!(f16_to_f32(0x7bff), 65504.0);
        assert_eq!(f16_to_f32(0x0001), 2f32.powi(-24));
    }

    #[test]
    fn elements_decode_in_either_byte_order() {
        let e = |kind, size, be| Element::new(kind, size, be).expect("supported");
        assert_eq!(e(Kind::Int, 2, true).decode(&[0xff, 0xfe]), -2.0);
        assert_eq!(e(Kind::Int, 2, false).decode(&[0xfe, 0xff]), -2.0);
        assert_eq!(e(Kind::Uint, 8, true).decode(&[0, 0, 0, 0, 0, 0, 1, 0]), 256.0);
        assert_eq!(e(Kind::Int, 1, false).decode(&[0x80]), -128.0);
        assert_eq!(e(Kind::Float, 4, true).decode(&1.5f32.to_be_bytes()), 1.5);
        assert_eq!(e(Kind::Float, 8, false).decode(&(-0.25f64).to_le_bytes()), -0.25);
        assert_eq!(e(Kind::Float, 2, true).decode(&[0x3c, 0x00]), 1.0);
        assert_eq!(e(Kind::Uint, 4, false).decode_all(&[1, 0, 0, 0, 2, 0, 0, 0]), [1.0, 2.0]);
        // A one-byte type has no byte order.
        assert!(!e(Kind::Uint, 1, true).big_endian);
        assert!(Element::new(Kind::Float, 16, false).is_none());
        assert!(Element::new(Kind::Int, 3, false).is_none());
        assert_eq!(e(Kind::Float, 4, true).to_string(), "big-endian float32");
        assert_eq!(e(Kind::Uint, 2, false).to_string(), "uint16");
    }

    #[test]
    fn shapes_are_rows_and_positions_name_row_and_coordinate() {
        assert_eq!(row_shape("'x'", &[5]), Ok((5, 1)));
        assert_eq!(row_shape("'x'", &[5, 3]), Ok((5, 3)));
        assert_eq!(row_shape("'x'", &[5, 3, 2]), Ok((5, 6)));
        assert_eq!(row_shape("'x'", &[0, 3]), Ok((0, 3)));
        assert!(row_shape("'x'", &[]).expect_err("scalar").contains("'x' is a scalar"));
        assert_eq!(row_shape("'x'", &[60, 0]), Err("'x' has shape [60, 0]: its rows hold no values".to_owned()));
        assert!(row_shape("'x'", &[6, 2, 0]).is_err());
        assert_eq!(position(7, &[5, 3]), "row 2, coordinate 1");
        assert_eq!(position(3, &[5]), "row 3, coordinate 0");
        assert_eq!(position(8, &[5, 3, 2]), "row 1, flattened coordinate 2 of [3, 2]");
    }

    #[test]
    fn values_must_be_finite_float32_in_the_rows_kept() {
        let err = to_f32("'o'", f64::NAN, 7, &[5, 3]).expect_err("nan");
        assert_eq!(err, "'o': value NaN at row 2, coordinate 1 is not finite");
        let err = to_f32("'o'", 1e300, 0, &[5, 3]).expect_err("too big");
        assert!(err.contains("1e300") && err.contains("float32's range"), "{err}");
        assert_eq!(to_f32("'o'", 1e-50, 0, &[1]), Ok(0.0));
        // Only the rows kept are checked.
        let v = [1.0, 2.0, f64::NAN, f64::NAN];
        assert!(rows_to_f32("'o'", &v, &[2, 2], None).is_err());
        let got = rows_to_f32("'o'", &v, &[2, 2], Some(1)).expect("first row only");
        assert_eq!(&got[..2], [1.0, 2.0]);
    }

    #[test]
    fn flags_are_zeros_and_ones() {
        assert_eq!(flags("'t'", &[0.0, 1.0, 1.0]), Ok(vec![false, true, true]));
        let err = flags("'t'", &[0.0, 1.0, 2.0, 3.0]).expect_err("2");
        assert!(err.contains("'t' holds 2 at row 2"), "{err}");
        let err = flags("'t'", &[f64::NAN]).expect_err("nan");
        assert!(err.contains("NaN at row 0"), "{err}");
    }
}
