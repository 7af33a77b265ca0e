//! One `.npy` array: its header checked and parsed, its dtype judged, its data decoded; and the
//! header written (the same layout numpy writes, shared with [`crate::npz_write`]).
//!
//! Two judges of a dtype: [`read_npy_header`] takes only what the wire carries as stored
//! ([`map_dtype`]: samples, model inputs), the crate's [`Header`] reader takes any integer,
//! float or bool in either byte order ([`element_of`], decoded by [`crate::values`]). The first
//! refuses Fortran order where it changes the layout (its bytes are sent as they are); the
//! second reads it, marking the header ([`Header::fortran`]) so that the data is put in C order
//! ([`c_order`]) before it is decoded or sent. Both check the header text
//! ([`precheck_header_text`]) before `npyz` parses it, so hostile headers are errors, not panics.

use std::io::{self, Read};

use npyz::{DType, Endianness, Order, TypeChar};

use crate::values::{Element, Kind};
use relreward_proto::tensor;
use relreward_proto::v1::Dtype;

/// Largest npy header text accepted. numpy itself refuses headers over 10,000 bytes by
/// default; the dtypes accepted here need well under 200.
pub const MAX_HEADER_TEXT_BYTES: usize = 64 * 1024;

/// Deepest bracket nesting accepted in a header (numpy writes depth 2).
const MAX_HEADER_NESTING: usize = 16;

pub(super) const NPY_MAGIC: &[u8; 6] = b"\x93NUMPY";

/// What an accepted npy header declares.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyInfo {
    pub dtype: Dtype,
    pub shape: Vec<u64>,
    /// Bytes before the data: magic string, version, header length and header text.
    pub header_len: u64,
    /// Bytes of data: `numel(shape) * itemsize`.
    pub data_len: u64,
}

/// Reads and checks an npy header, leaving `reader` at the first data byte. Only dtypes the wire
/// format carries as they are (little-endian or byte-order-free `float32`, `float64`, `int32`,
/// `int64`, `uint8`, `bool`) are accepted: this is the reader of arrays sent unconverted
/// (samples, model inputs). The trajectory reader takes any integer or float type
/// ([`crate::values`]).
///
/// Errors are plain messages that do not name the array; callers add that.
pub fn read_npy_header(reader: &mut dyn Read) -> Result<NpyInfo, String> {
    let parsed = parse_header(reader)?;
    let dtype = map_dtype(&parsed.dtype)?;
    check_order(&parsed)?;
    let data_len = tensor::byte_len(&parsed.shape, dtype).map_err(|e| e.to_string())?;
    Ok(NpyInfo { dtype, shape: parsed.shape, header_len: parsed.header_len, data_len })
}

/// What an npy header declares, as stored: the element type (any integer, float or bool the
/// readers decode), shape and sizes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Header {
    pub(super) element: Element,
    pub(super) shape: Vec<u64>,
    /// The dtype as the file writes it (`'<i8'`), for messages.
    pub(super) descr: String,
    pub(super) header_len: u64,
    pub(super) data_len: u64,
    /// Stored in Fortran (column-major) order where that changes the layout (two or more
    /// dimensions above 1): the data is reordered in memory ([`c_order`]) before use.
    pub(super) fortran: bool,
}

impl Header {
    /// The wire dtype the data already is, if any (little-endian or one-byte `float32`,
    /// `float64`, `int32`, `int64`, `uint8`, `bool`).
    pub(super) fn wire_dtype(&self) -> Option<Dtype> {
        let e = self.element;
        if e.big_endian { None } else { wire_dtype(e.kind, e.size) }
    }
}

/// The wire dtype of elements of `kind` and `size` bytes, byte order aside: the types the wire
/// carries as stored (`float32`, `float64`, `int32`, `int64`, `uint8`, `bool`).
fn wire_dtype(kind: Kind, size: usize) -> Option<Dtype> {
    Some(match (kind, size) {
        (Kind::Float, 4) => Dtype::Float32,
        (Kind::Float, 8) => Dtype::Float64,
        (Kind::Int, 4) => Dtype::Int32,
        (Kind::Int, 8) => Dtype::Int64,
        (Kind::Uint, 1) => Dtype::Uint8,
        (Kind::Bool, 1) => Dtype::Bool,
        _ => return None,
    })
}

/// The kind of number an npy type character stands for; `None` for what no reader decodes.
fn kind_of(type_char: TypeChar) -> Option<Kind> {
    match type_char {
        TypeChar::Bool => Some(Kind::Bool),
        TypeChar::Int => Some(Kind::Int),
        TypeChar::Uint => Some(Kind::Uint),
        TypeChar::Float => Some(Kind::Float),
        _ => None,
    }
}

/// Reads and checks an npy header of any integer, float or bool dtype in either byte order.
pub(super) fn read_header(reader: &mut dyn Read) -> Result<Header, String> {
    let parsed = parse_header(reader)?;
    let element = element_of(&parsed.dtype)?;
    let fortran = check_order(&parsed).is_err();
    let descr = parsed.dtype.descr();
    let data_len = parsed
        .shape
        .iter()
        .try_fold(element.size as u64, |a, &d| a.checked_mul(d))
        .ok_or("npy header declares a shape with more bytes than fit in 64 bits")?;
    Ok(Header { element, shape: parsed.shape, descr, header_len: parsed.header_len, data_len, fortran })
}

/// `data`, the elements of an array of `shape` stored in Fortran (column-major) order, `size`
/// bytes each, in C (row-major) order: what numpy's `np.ascontiguousarray` gives. Arrays are
/// read row by row everywhere else, so a Fortran-order array is reordered whole, in memory.
pub(super) fn c_order(data: &[u8], size: usize, shape: &[u64]) -> Vec<u8> {
    let dims: Vec<usize> = shape.iter().map(|&d| d as usize).collect();
    // Fortran strides, in elements: the first index varies fastest.
    let mut strides = vec![1usize; dims.len()];
    for k in 1..dims.len() {
        strides[k] = strides[k - 1] * dims[k - 1];
    }
    let n: usize = dims.iter().product();
    let mut out = Vec::with_capacity(n * size);
    let mut index = vec![0usize; dims.len()];
    for _ in 0..n {
        let at = index.iter().zip(&strides).map(|(i, s)| i * s).sum::<usize>() * size;
        out.extend_from_slice(&data[at..at + size]);
        // The next C-order index: the last dimension varies fastest.
        for k in (0..dims.len()).rev() {
            index[k] += 1;
            if index[k] < dims[k] {
                break;
            }
            index[k] = 0;
        }
    }
    out
}

/// A header's fields before its dtype is judged.
struct Parsed {
    dtype: DType,
    shape: Vec<u64>,
    order: Order,
    header_len: u64,
}

fn parse_header(reader: &mut dyn Read) -> Result<Parsed, String> {
    const TRUNCATED: &str = "file ends inside the npy header";
    let mut pre = [0u8; 8];
    read_exact_or(reader, &mut pre, TRUNCATED)?;
    if &pre[..6] != NPY_MAGIC {
        return Err("not an npy array (no \\x93NUMPY magic string)".into());
    }
    let len_bytes = match pre[6] {
        1 => 2,
        2 | 3 => 4,
        major => return Err(format!("unsupported npy format version {major}.{}", pre[7])),
    };
    let mut len = [0u8; 4];
    read_exact_or(reader, &mut len[..len_bytes], TRUNCATED)?;
    let text_len = u32::from_le_bytes(len) as usize;
    if text_len > MAX_HEADER_TEXT_BYTES {
        return Err(format!("npy header of {text_len} bytes exceeds the {MAX_HEADER_TEXT_BYTES} allowed"));
    }
    let mut buf = Vec::with_capacity(pre.len() + len_bytes + text_len);
    buf.extend_from_slice(&pre);
    buf.extend_from_slice(&len[..len_bytes]);
    let text_start = buf.len();
    buf.resize(text_start + text_len, 0);
    read_exact_or(reader, &mut buf[text_start..], TRUNCATED)?;
    precheck_header_text(&buf[text_start..])?;

    let header = npyz::NpyHeader::from_reader(buf.as_slice()).map_err(|e| format!("invalid npy header: {e}"))?;
    Ok(Parsed {
        dtype: header.dtype(),
        shape: header.shape().to_vec(),
        order: header.order(),
        header_len: buf.len() as u64,
    })
}

/// Fortran order only changes the layout when two or more dimensions exceed 1.
fn check_order(parsed: &Parsed) -> Result<(), String> {
    let shape = &parsed.shape;
    if parsed.order == Order::Fortran && shape.iter().filter(|&&d| d > 1).count() > 1 {
        return Err(format!(
            "Fortran-order (column-major) array of shape {shape:?} is not supported; \
             save np.ascontiguousarray(arr) instead"
        ));
    }
    Ok(())
}

/// The element type of an npy dtype, or what it is, in words, when the readers cannot decode it.
fn element_of(dtype: &DType) -> Result<Element, String> {
    let DType::Plain(ts) = dtype else {
        return Err(format!("structured dtype {} is not supported; expected integers, floats or bool", dtype.descr()));
    };
    let name = ts.to_string();
    let size = usize::try_from(ts.size_field()).unwrap_or(usize::MAX);
    let Some(kind) = kind_of(ts.type_char()) else {
        let what = match ts.type_char() {
            TypeChar::Complex => "complex numbers",
            TypeChar::TimeDelta => "time deltas",
            TypeChar::DateTime => "dates",
            TypeChar::ByteStr | TypeChar::UnicodeStr => "strings",
            TypeChar::Object => "an object array (pickled Python objects)",
            _ => "raw bytes",
        };
        return Err(format!("dtype '{name}' is {what}, which is not supported; expected integers, floats or bool"));
    };
    Element::new(kind, size, ts.endianness() == Endianness::Big).ok_or_else(|| {
        let what = match kind {
            Kind::Float => "float",
            Kind::Bool => "bool",
            _ => "integer",
        };
        format!("dtype '{name}' is a {size}-byte {what}, which is not supported; expected integers or floats of 1, 2, 4 or 8 bytes")
    })
}

fn read_exact_or(reader: &mut dyn Read, buf: &mut [u8], eof_message: &str) -> Result<(), String> {
    reader.read_exact(buf).map_err(|e| match e.kind() {
        io::ErrorKind::UnexpectedEof => eof_message.to_owned(),
        _ => format!("reading the npy header: {e}"),
    })
}

/// Refuses header text that could make the Python-literal parser misbehave: non-ASCII text,
/// deep nesting, anything but strings, `True`/`False`, punctuation and decimal integers, and
/// integers whose product (zeros counted as one) overflows 64 bits.
fn precheck_header_text(text: &[u8]) -> Result<(), String> {
    if !text.is_ascii() {
        return Err("npy header is not ASCII (structured dtypes are not supported)".into());
    }
    let mut depth = 0usize;
    let mut product = 1u64;
    let mut i = 0;
    while let Some(&c) = text.get(i) {
        match c {
            b' ' | b'\t' | b'\n' | b'\r' | b':' | b',' => i += 1,
            b'{' | b'(' | b'[' => {
                depth += 1;
                if depth > MAX_HEADER_NESTING {
                    return Err("npy header nests too deeply".into());
                }
                i += 1;
            }
            b'}' | b')' | b']' => {
                depth = depth.checked_sub(1).ok_or("npy header has unbalanced brackets")?;
                i += 1;
            }
            b'\'' | b'"' => {
                i += 1;
                loop {
                    match text.get(i) {
                        None => return Err("npy header has an unterminated string".into()),
                        Some(b'\\') => i += 2,
                        Some(&q) if q == c => {
                            i += 1;
                            break;
                        }
                        Some(_) => i += 1,
                    }
                }
            }
            b'0'..=b'9' => {
                let start = i;
                while text.get(i).is_some_and(u8::is_ascii_digit) {
                    i += 1;
                }
                if text.get(i).is_some_and(|&b| b.is_ascii_alphanumeric() || b == b'_' || b == b'.') {
                    return Err("npy header has a number that is not a plain decimal integer".into());
                }
                let n = std::str::from_utf8(&text[start..i])
                    .ok()
                    .and_then(|s| s.parse::<u64>().ok())
                    .ok_or("npy header declares a dimension that does not fit in 64 bits")?;
                product = product
                    .checked_mul(n.max(1))
                    .ok_or("npy header declares a shape with more elements than fit in 64 bits")?;
            }
            b'A'..=b'Z' | b'a'..=b'z' | b'_' => {
                let start = i;
                while text.get(i).is_some_and(|&b| b.is_ascii_alphanumeric() || b == b'_') {
                    i += 1;
                }
                let word = String::from_utf8_lossy(&text[start..i]);
                if word != "True" && word != "False" {
                    return Err(format!("unexpected '{word}' in npy header"));
                }
            }
            other => {
                return Err(format!("unexpected character {:?} in npy header", char::from(other)));
            }
        }
    }
    if depth != 0 {
        return Err("npy header has unbalanced brackets".into());
    }
    Ok(())
}

/// The wire dtype for an npy dtype, or why it cannot be sent as is.
fn map_dtype(dtype: &DType) -> Result<Dtype, String> {
    let DType::Plain(ts) = dtype else {
        return Err(format!("structured dtype {} is not supported", dtype.descr()));
    };
    let name = ts.to_string();
    if ts.type_char() == TypeChar::Object {
        return Err(format!("dtype '{name}' is an object array (pickled Python objects), which is not supported"));
    }
    let size = usize::try_from(ts.size_field()).ok();
    let Some(mapped) = kind_of(ts.type_char()).zip(size).and_then(|(kind, size)| wire_dtype(kind, size)) else {
        return Err(format!(
            "unsupported dtype '{name}' (supported: '<f4' float32, '<f8' float64, '<i4' int32, \
             '<i8' int64, '|u1' uint8, '|b1' bool)"
        ));
    };
    // A one-byte type has no byte order whatever the file says.
    if ts.endianness() == Endianness::Big && ts.size_field() > 1 {
        return Err(format!(
            "dtype '{name}' is big-endian; convert it with arr.astype('{}')",
            name.replacen('>', "<", 1)
        ));
    }
    Ok(mapped)
}

/// The data of an array whose header was just read from `reader`, decoded as f64.
pub(super) fn read_values(reader: &mut dyn Read, header: &Header) -> Result<Vec<f64>, String> {
    let len = usize::try_from(header.data_len).map_err(|_| "too large for this machine".to_owned())?;
    let mut data = Vec::new();
    data.try_reserve_exact(len).map_err(|_| format!("{len} bytes do not fit in memory"))?;
    reader.take(header.data_len).read_to_end(&mut data).map_err(|e| e.to_string())?;
    if data.len() != len {
        return Err(format!("ends after {} of its {len} data bytes (truncated file?)", data.len()));
    }
    if header.fortran {
        data = c_order(&data, header.element.size, &header.shape);
    }
    Ok(header.element.decode_all(&data))
}

/// The npy 1.0 header of an array as numpy writes it: magic string, version, length and the
/// dictionary, space-padded so that the data starts at a multiple of 64 bytes. `descr` is a dtype
/// string (`<f4`); a structured dtype's field list (`[('a', '<f4')]`) is written unquoted, as
/// numpy does. The one header writer: [`crate::npz_write`] and this reader's tests use it.
pub(crate) fn write_npy_header(descr: &str, fortran_order: bool, shape: &[u64]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
    let shape_text = match dims.as_slice() {
        [one] => format!("({one},)"),
        _ => format!("({})", dims.join(", ")),
    };
    let descr = if descr.starts_with('[') { descr.to_owned() } else { format!("'{descr}'") };
    let fortran_order = if fortran_order { "True" } else { "False" };
    let mut text = format!("{{'descr': {descr}, 'fortran_order': {fortran_order}, 'shape': {shape_text}, }}");
    // magic (6) + version (2) + length (2) + text + '\n'
    let unpadded = 10 + text.len() + 1;
    text.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    text.push('\n');
    let mut out = NPY_MAGIC.to_vec();
    out.extend_from_slice(&[1, 0]);
    // Shapes of any realistic rank keep the text far below u16::MAX.
    out.extend_from_slice(&(text.len().min(usize::from(u16::MAX)) as u16).to_le_bytes());
    out.extend_from_slice(text.as_bytes());
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz::samples_from_npz_or_npy;
    use crate::npz::test_files::{f32_bytes, f64_bytes, npy, read_all, scratch, trajectories_error, write_npz};
    use crate::npz::trajectories_from_npz;

    fn npy_error(descr: &str, fortran: bool, shape: &[u64], data: &[u8]) -> String {
        let (_dir, path) = scratch("x.npz");
        let obs = npy(descr, fortran, shape, data);
        let act = npy("<f4", false, &[shape[0], 1], &vec![0u8; 4 * shape[0] as usize]);
        trajectories_error(&path, &[("observations", obs), ("actions", act)])
    }

    #[test]
    fn unsupported_layouts_and_dtypes_are_refused_naming_array_and_dtype() {
        let err = npy_error("<c8", false, &[2, 2], &[0; 32]);
        assert!(err.contains("'observations'") && err.contains("'<c8'") && err.contains("complex"), "{err}");
        let err = npy_error("<f16", false, &[2, 2], &[0; 64]);
        assert!(err.contains("'<f16'") && err.contains("16-byte float"), "{err}");
        let err = npy_error("<U3", false, &[2, 2], &[0; 48]);
        assert!(err.contains("'<U3'") && err.contains("strings"), "{err}");
        let err = npy_error("|O", false, &[2, 2], &[0x80, 0x02]);
        assert!(err.contains("'observations'") && err.contains("object"), "{err}");
        let err = npy_error("|b1", false, &[2, 2], &[0; 4]);
        assert!(err.contains("'observations' has dtype bool"), "{err}");
        // A structured dtype.
        let err = npy_error("[('a', '<f4')]", false, &[2, 2], &[0; 16]);
        assert!(err.contains("'observations'") && err.contains("structured"), "{err}");

        // Fortran order is read as numpy reads it: the trajectories' rows, and samples sent as
        // stored, are the C-order array's (np.ascontiguousarray), for any number of dimensions.
        let (dir, path) = scratch("fortran.npz");
        let column_major: Vec<f32> = vec![0.0, 10.0, 20.0, 1.0, 11.0, 21.0]; // [[0, 1], [10, 11], [20, 21]]
        let act = npy("<f8", true, &[3, 2], &f64_bytes(&[0.5, 1.5, 2.5, -0.5, -1.5, -2.5]));
        write_npz(
            &path,
            &[("observations", npy("<f4", true, &[3, 2], &f32_bytes(&column_major))), ("actions", act)],
            true,
        );
        let mut source = trajectories_from_npz(&path).expect("fortran trajectories");
        assert_eq!(read_all(&mut source, 0).expect("obs"), f32_bytes(&[0.0, 1.0, 10.0, 11.0, 20.0, 21.0]));
        assert_eq!(read_all(&mut source, 1).expect("act"), f32_bytes(&[0.5, -0.5, 1.5, -1.5, 2.5, -2.5]));
        // [2, 3, 2] column-major: element (i, j, k) at i + 2 j + 6 k.
        let cube: Vec<f32> = (0..12).map(|f| f as f32).collect();
        let c: Vec<f32> = (0..12).map(|c| ((c / 6) + 2 * ((c / 2) % 3) + 6 * (c % 2)) as f32).collect();
        let path = dir.path().join("cube.npy");
        std::fs::write(&path, npy("<f4", true, &[2, 3, 2], &f32_bytes(&cube))).expect("write");
        let mut source = samples_from_npz_or_npy(&path, None).expect("fortran samples");
        assert_eq!(read_all(&mut source, 0).expect("samples"), f32_bytes(&c));
        // Fortran order with one non-trivial dimension is the same layout: accepted.
        let path = dir.path().join("f.npy");
        std::fs::write(&path, npy("<f8", true, &[3, 1], &f64_bytes(&[1.0, 2.0, 3.0]))).expect("write");
        samples_from_npz_or_npy(&path, None).expect("trivial fortran order");
        // '>u1' has no byte order to swap.
        let path = dir.path().join("u.npz");
        write_npz(
            &path,
            &[
                ("observations", npy("<f4", false, &[1, 1], &[0; 4])),
                ("actions", npy("<f4", false, &[1, 1], &[0; 4])),
                ("terminals", npy(">u1", false, &[1], &[1])),
            ],
            false,
        );
        trajectories_from_npz(&path).expect("one-byte big-endian");
    }

    #[test]
    fn hostile_headers_are_refused() {
        let header = |text: &str| {
            let mut out = b"\x93NUMPY\x01\x00".to_vec();
            out.extend_from_slice(&(text.len() as u16).to_le_bytes());
            out.extend_from_slice(text.as_bytes());
            read_npy_header(&mut out.as_slice())
        };
        let ok = header("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }\n").expect("valid");
        assert_eq!(ok, NpyInfo { dtype: Dtype::Float32, shape: vec![2, 3], header_len: 70, data_len: 24 });
        for bad in [
            "{'descr': '<f4', 'fortran_order': False, 'shape': (4294967296, 4294967296), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (0, 4294967296, 4294967296), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (99999999999999999999999,), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (0x10,), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (-1,), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (1.5,), }",
            "{'descr': '\u{e9}', 'fortran_order': False, 'shape': (1,), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': ((((((((((((((((((1,)))))))))))))))))), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (1,), ",
            "{'descr': '<f4, 'fortran_order': False, 'shape': (1,), }",
            "{'descr': '<f4', 'fortran_order': Nope, 'shape': (1,), }",
            "{'descr': '<f4', 'fortran_order': False}",
            "{'descr': '<f99999999999999999999999', 'fortran_order': False, 'shape': (1,), }",
            "[1, 2]",
            "",
        ] {
            assert!(header(bad).is_err(), "accepted {bad:?}");
        }
        // Oversized header length.
        let mut big = b"\x93NUMPY\x02\x00".to_vec();
        big.extend_from_slice(&u32::MAX.to_le_bytes());
        let err = read_npy_header(&mut big.as_slice()).expect_err("must fail");
        assert!(err.contains("exceeds"), "{err}");
        // Unknown version.
        assert!(read_npy_header(&mut &b"\x93NUMPY\x09\x00\x00\x00"[..]).is_err());
    }

    #[test]
    fn headers_are_padded_like_numpy() {
        for shape in [vec![], vec![7], vec![3, 4, 2], vec![1 << 40, 1]] {
            let h = write_npy_header("<f4", false, &shape);
            assert_eq!(h.len() % 64, 0, "{shape:?}");
            assert_eq!(*h.last().expect("newline"), b'\n');
            let info = read_npy_header(&mut h.as_slice()).expect("parses");
            assert_eq!(info.shape, shape);
        }
    }
}
