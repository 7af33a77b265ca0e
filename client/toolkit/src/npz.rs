//! Reads numpy `.npz` archives and `.npy` files into an [`UploadSource`], streaming the data.
//!
//! Trajectories ([`trajectories_from_npz`]) follow the rules every reader shares
//! ([`crate::values`], [`crate::episodes`], `docs/data-formats.md`): observations and actions of
//! any integer or float dtype in either byte order are sent as float32 rows, converted as they
//! are read; episode flags of bool or of numbers that are all 0 or 1 are sent as bool.
//! Samples ([`samples_from_npz_or_npy`]) are sent as stored, so only little-endian (or
//! byte-order-free) `float32` and `float64` are taken there. Everything else (Fortran order,
//! object/pickled arrays, strings, complex numbers) is refused with an error that names the
//! array and its dtype string, so the fix (`astype`, `np.ascontiguousarray`) is obvious.
//!
//! Opening a file reads only the npy headers of the arrays that will be sent; [`NpzSource::open`]
//! reopens an array and returns a reader of exactly its declared data bytes, so files larger
//! than memory upload fine.
//!
//! Malformed input is an error, never a panic: the header text is checked (ASCII, bounded
//! size and nesting, plain decimal dimensions whose product fits in 64 bits) before `npyz`
//! parses it, and declared sizes are checked against the file before any data is read.
//!
//! Entry points:
//! - [`trajectories_from_npz`]: D4RL / Minari style `observations`, `actions` and episode
//!   boundaries (flags, start indices or lengths: [`crate::episodes`]).
//! - [`walls_from_npz`]: maze walls from `walls` / `wall_map` / `maze_map` in the file.
//! - [`samples_from_npz_or_npy`]: one `[N, ...]` float array, sent as `samples`.
//! - [`detect_kind`]: which of the two a file looks like.
//! - [`read_npy_header`]: the checked header parser on its own (useful for fuzzing).
//! - [`NpzSource::read_tensor`]: one array whole in memory (inputs of `score` and `grad`).

use std::fmt;
use std::fs::File;
use std::io::{self, BufReader, Read};
use std::path::{Path, PathBuf};

use npyz::zip::ZipArchive;
use npyz::{DType, Endianness, Order, TypeChar};

use crate::values::{Element, Kind};
use relreward_proto::v1::{ArraySpec, DatasetKind, Dtype};

use relreward_client::UploadSource;
use relreward_proto::tensor;

/// Largest npy header text accepted. numpy itself refuses headers over 10,000 bytes by
/// default; the dtypes accepted here need well under 200.
pub const MAX_HEADER_TEXT_BYTES: usize = 64 * 1024;

/// Deepest bracket nesting accepted in a header (numpy writes depth 2).
const MAX_HEADER_NESTING: usize = 16;

const NPY_MAGIC: &[u8; 6] = b"\x93NUMPY";

/// Why a file cannot be uploaded: the file and what is wrong with it.
#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct NpzError {
    pub path: PathBuf,
    pub message: String,
}

impl NpzError {
    fn new(path: &Path, message: impl Into<String>) -> Self {
        Self { path: path.to_owned(), message: message.into() }
    }
}

pub type Result<T, E = NpzError> = std::result::Result<T, E>;

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
struct Header {
    element: Element,
    shape: Vec<u64>,
    /// The dtype as the file writes it (`'<i8'`), for messages.
    descr: String,
    header_len: u64,
    data_len: u64,
}

impl Header {
    /// The wire dtype the data already is, if any (little-endian or one-byte `float32`,
    /// `float64`, `int32`, `int64`, `uint8`, `bool`).
    fn wire_dtype(&self) -> Option<Dtype> {
        let e = self.element;
        if e.big_endian {
            return None;
        }
        Some(match (e.kind, e.size) {
            (Kind::Float, 4) => Dtype::Float32,
            (Kind::Float, 8) => Dtype::Float64,
            (Kind::Int, 4) => Dtype::Int32,
            (Kind::Int, 8) => Dtype::Int64,
            (Kind::Uint, 1) => Dtype::Uint8,
            (Kind::Bool, 1) => Dtype::Bool,
            _ => return None,
        })
    }
}

/// Reads and checks an npy header of any integer, float or bool dtype in either byte order.
fn read_header(reader: &mut dyn Read) -> Result<Header, String> {
    let parsed = parse_header(reader)?;
    let element = element_of(&parsed.dtype)?;
    check_order(&parsed)?;
    let descr = parsed.dtype.descr();
    let data_len = parsed
        .shape
        .iter()
        .try_fold(element.size as u64, |a, &d| a.checked_mul(d))
        .ok_or("npy header declares a shape with more bytes than fit in 64 bits")?;
    Ok(Header { element, shape: parsed.shape, descr, header_len: parsed.header_len, data_len })
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
    let kind = match ts.type_char() {
        TypeChar::Bool => Kind::Bool,
        TypeChar::Int => Kind::Int,
        TypeChar::Uint => Kind::Uint,
        TypeChar::Float => Kind::Float,
        other => {
            let what = match other {
                TypeChar::Complex => "complex numbers",
                TypeChar::TimeDelta => "time deltas",
                TypeChar::DateTime => "dates",
                TypeChar::ByteStr | TypeChar::UnicodeStr => "strings",
                TypeChar::Object => "an object array (pickled Python objects)",
                _ => "raw bytes",
            };
            return Err(format!("dtype '{name}' is {what}, which is not supported; expected integers, floats or bool"));
        }
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
    let mapped = match (ts.type_char(), ts.size_field()) {
        (TypeChar::Float, 4) => Dtype::Float32,
        (TypeChar::Float, 8) => Dtype::Float64,
        (TypeChar::Int, 4) => Dtype::Int32,
        (TypeChar::Int, 8) => Dtype::Int64,
        (TypeChar::Uint, 1) => Dtype::Uint8,
        (TypeChar::Bool, 1) => Dtype::Bool,
        (TypeChar::Object, _) => {
            return Err(format!("dtype '{name}' is an object array (pickled Python objects), which is not supported"));
        }
        _ => {
            return Err(format!(
                "unsupported dtype '{name}' (supported: '<f4' float32, '<f8' float64, '<i4' int32, \
                 '<i8' int64, '|u1' uint8, '|b1' bool)"
            ));
        }
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

/// What a file starts with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FileFormat {
    Npy,
    Npz,
}

fn sniff(path: &Path) -> Result<FileFormat> {
    let mut file = File::open(path).map_err(|e| NpzError::new(path, e.to_string()))?;
    let mut magic = [0u8; 6];
    let mut got = 0;
    while got < magic.len() {
        match file.read(&mut magic[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(NpzError::new(path, e.to_string())),
        }
    }
    if got == magic.len() && &magic == NPY_MAGIC {
        Ok(FileFormat::Npy)
    } else if got >= 4 && (magic[..4] == *b"PK\x03\x04" || magic[..4] == *b"PK\x05\x06") {
        Ok(FileFormat::Npz)
    } else {
        Err(NpzError::new(path, "not an .npy or .npz file"))
    }
}

/// One array of an archive: its name (the entry's file name without `.npy`) and entry index.
#[derive(Debug, Clone)]
struct Member {
    key: String,
    index: usize,
}

fn open_archive(path: &Path) -> Result<(ZipArchive<BufReader<File>>, Vec<Member>)> {
    let file = File::open(path).map_err(|e| NpzError::new(path, e.to_string()))?;
    let mut archive = ZipArchive::new(BufReader::new(file))
        .map_err(|e| NpzError::new(path, format!("not a readable .npz archive: {e}")))?;
    let mut members: Vec<Member> = Vec::new();
    for index in 0..archive.len() {
        let entry = archive
            .by_index_raw(index)
            .map_err(|e| NpzError::new(path, format!("reading archive entry {index}: {e}")))?;
        if entry.is_dir() {
            continue;
        }
        let Some(key) = npyz::npz::array_name_from_file_name(entry.name()) else {
            continue;
        };
        if members.iter().any(|m| m.key == key) {
            return Err(NpzError::new(path, format!("the archive holds array '{key}' twice")));
        }
        members.push(Member { key: key.to_owned(), index });
    }
    Ok((archive, members))
}

/// Reads the header of archive member `member`, checking that the entry holds all the data it
/// declares.
fn member_header(path: &Path, archive: &mut ZipArchive<BufReader<File>>, member: &Member) -> Result<Header> {
    let key = &member.key;
    let mut entry = archive.by_index(member.index).map_err(|e| NpzError::new(path, format!("array '{key}': {e}")))?;
    let size = entry.size();
    let header = read_header(&mut entry).map_err(|m| NpzError::new(path, format!("array '{key}': {m}")))?;
    check_complete(path, key, &header, size)?;
    Ok(header)
}

/// The header and every value (as f64) of archive member `member`.
fn member_values(
    path: &Path,
    archive: &mut ZipArchive<BufReader<File>>,
    member: &Member,
) -> Result<(Header, Vec<f64>)> {
    let key = &member.key;
    let header = member_header(path, archive, member)?;
    let mut entry = archive.by_index(member.index).map_err(|e| NpzError::new(path, format!("array '{key}': {e}")))?;
    read_header(&mut entry).map_err(|m| NpzError::new(path, format!("array '{key}': {m}")))?;
    let values = read_values(&mut entry, &header).map_err(|m| NpzError::new(path, format!("array '{key}': {m}")))?;
    Ok((header, values))
}

/// The data of an array whose header was just read from `reader`, decoded as f64.
fn read_values(reader: &mut dyn Read, header: &Header) -> Result<Vec<f64>, String> {
    let len = usize::try_from(header.data_len).map_err(|_| "too large for this machine".to_owned())?;
    let mut data = Vec::new();
    data.try_reserve_exact(len).map_err(|_| format!("{len} bytes do not fit in memory"))?;
    reader.take(header.data_len).read_to_end(&mut data).map_err(|e| e.to_string())?;
    if data.len() != len {
        return Err(format!("ends after {} of its {len} data bytes (truncated file?)", data.len()));
    }
    Ok(header.element.decode_all(&data))
}

fn check_complete(path: &Path, key: &str, header: &Header, stored: u64) -> Result<()> {
    let available = stored.saturating_sub(header.header_len);
    if available < header.data_len {
        return Err(NpzError::new(
            path,
            format!(
                "array '{key}' is truncated: shape {:?} of {} needs {} data bytes but only {available} are stored",
                header.shape, header.element, header.data_len
            ),
        ));
    }
    Ok(())
}

/// Where one array's bytes are, and how they are sent.
#[derive(Debug, Clone)]
struct Entry {
    /// Name in the file (differs from the sent name for Minari aliases and samples).
    key: String,
    /// Archive entry index; `None` for a plain `.npy` file or an array made in memory.
    zip_index: Option<usize>,
    /// The array's header as stored; checked again whenever the array is reopened. `None` for
    /// an array made in memory.
    stored: Option<Header>,
    /// The bytes of an array converted while reading (episode flags as bool; episode starts
    /// given as indices or lengths as per-row flags, see [`crate::episodes`]).
    memory: Option<Vec<u8>>,
    /// Whether the stored values are converted to float32 as they are read
    /// ([`crate::values`]): observations and actions.
    to_f32: bool,
    /// Bytes sent.
    sent_len: u64,
}

impl Entry {
    /// An array sent as stored.
    fn as_stored(key: String, zip_index: Option<usize>, header: Header) -> Self {
        let sent_len = header.data_len;
        Self { key, zip_index, stored: Some(header), memory: None, to_f32: false, sent_len }
    }

    /// An array made in memory.
    fn in_memory(key: String, bytes: Vec<u8>) -> Self {
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
    archive: Option<ZipArchive<BufReader<File>>>,
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

    fn push(&mut self, name: &str, dtype: Dtype, shape: Vec<u64>, entry: Entry) {
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
        if entry.to_f32 {
            let label = format!("{path}: '{key}'");
            Ok(Box::new(F32Reader::new(data, stored.element, stored.shape.clone(), label)))
        } else {
            Ok(data)
        }
    }
}

fn invalid_data(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, message)
}

/// Yields exactly `len` bytes of `inner`, and a clear error if it ends before that.
struct ExactReader<R> {
    inner: R,
    remaining: u64,
    len: u64,
    label: String,
}

impl<R: Read> ExactReader<R> {
    fn new(inner: R, len: u64, label: String) -> Self {
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
struct F32Reader<R> {
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

    fn new(inner: R, element: Element, shape: Vec<u64>, label: String) -> Self {
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

/// Which kind a file looks like: trajectories for an `.npz` holding `observations`, else
/// samples.
pub fn detect_kind(path: impl AsRef<Path>) -> Result<DatasetKind> {
    let path = path.as_ref();
    match sniff(path)? {
        FileFormat::Npy => Ok(DatasetKind::Samples),
        FileFormat::Npz => {
            let (_, members) = open_archive(path)?;
            Ok(if members.iter().any(|m| m.key == "observations") {
                DatasetKind::Trajectories
            } else {
                DatasetKind::Samples
            })
        }
    }
}

/// Names of the arrays an `.npz` archive holds, in archive order (for an `.npy` file: none).
pub fn npz_keys(path: impl AsRef<Path>) -> Result<Vec<String>> {
    let path = path.as_ref();
    match sniff(path)? {
        FileFormat::Npy => Ok(Vec::new()),
        FileFormat::Npz => Ok(open_archive(path)?.1.into_iter().map(|m| m.key).collect()),
    }
}

/// One numeric array of an `.npz` (or of a plain `.npy`, whatever `key`) as f64 with its
/// shape; `None` when an archive has no such array. Any integer, bool or float dtype in either
/// byte order ([`crate::values::Element`]); C order only. Errors do not name the file; callers
/// add it.
pub fn read_numbers(path: &Path, key: &str) -> io::Result<Option<(Vec<u64>, Vec<f64>)>> {
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy")) {
        let mut reader = BufReader::new(File::open(path)?);
        let header = read_header(&mut reader).map_err(|m| invalid_data(format!("'{key}': {m}")))?;
        let values = read_values(&mut reader, &header).map_err(|m| invalid_data(format!("'{key}': {m}")))?;
        return Ok(Some((header.shape, values)));
    }
    let (mut archive, members) = open_archive(path).map_err(|e| invalid_data(e.message))?;
    let Some(member) = members.iter().find(|m| m.key == key) else { return Ok(None) };
    let (header, values) = member_values(path, &mut archive, member).map_err(|e| invalid_data(e.message))?;
    Ok(Some((header.shape, values)))
}

/// The shape of array `key` of an `.npz` archive, from its header; `None` when the archive has
/// no such array.
pub fn npz_array_shape(path: &Path, key: &str) -> io::Result<Option<Vec<u64>>> {
    let mut archive = npyz::npz::NpzArchive::open(path)?;
    Ok(archive.by_name(key)?.map(|npy| npy.shape().to_vec()))
}

fn list_keys(members: &[Member]) -> String {
    if members.is_empty() {
        "none".to_owned()
    } else {
        members.iter().map(|m| format!("'{}'", m.key)).collect::<Vec<_>>().join(", ")
    }
}

/// A D4RL / Minari style trajectory dataset from an `.npz` archive, by the rules of
/// [`crate::values`] and [`crate::episodes`] (the HDF5 reader's too).
///
/// Required: `observations` and `actions`, `N` rows each (`[N]`, `[N, d]` or `[N, a, b, ...]`,
/// the trailing dimensions flattened row-major), of any integer or float dtype in either byte
/// order; they are sent as float32 `[N, width]`, converted as they are read, and a value that is
/// not finite as float32 fails the read naming the array, row and coordinate. `N = 0` is
/// refused. Optional, `[N]` bool or any integer or float type holding only 0 and 1, sent as
/// bool: `terminals` (Minari: `terminations`) and `timeouts` (Minari: `truncations`); Minari
/// names are sent under the D4RL names. Optional episode boundaries: `episode_starts` (per-row
/// flags or start indices) and/or `episode_lengths`, sent as per-row `episode_starts` flags.
/// Other arrays are left out and listed by [`NpzSource::ignored_keys`].
pub fn trajectories_from_npz(path: impl AsRef<Path>) -> Result<NpzSource> {
    let path = path.as_ref();
    if sniff(path)? == FileFormat::Npy {
        return Err(NpzError::new(
            path,
            "is a single .npy array; trajectories need an .npz archive with 'observations' and 'actions'",
        ));
    }
    let (mut archive, members) = open_archive(path)?;
    let find = |key: &str| members.iter().find(|m| m.key == key);
    let required = |key: &str| {
        find(key)
            .ok_or_else(|| NpzError::new(path, format!("no '{key}' array (the archive holds {})", list_keys(&members))))
    };
    let aliased = |name: &'static str, alias: &'static str| match (find(name), find(alias)) {
        (Some(_), Some(_)) => {
            Err(NpzError::new(path, format!("holds both '{name}' and its Minari alias '{alias}'; keep only one")))
        }
        (Some(m), None) | (None, Some(m)) => Ok(Some(m)),
        (None, None) => Ok(None),
    };
    // (sent name, member), in the order they are sent.
    let mut chosen: Vec<(&'static str, &Member)> =
        vec![("observations", required("observations")?), ("actions", required("actions")?)];
    for (name, alias) in [("terminals", "terminations"), ("timeouts", "truncations")] {
        if let Some(m) = aliased(name, alias)? {
            chosen.push((name, m));
        }
    }
    let starts_member = find("episode_starts");
    let lengths_member = find("episode_lengths");

    // (header, width of a row) of each chosen array.
    let mut headers = Vec::with_capacity(chosen.len());
    for &(name, member) in &chosen {
        let header = member_header(path, &mut archive, member)?;
        let shown = describe_key(&member.key, name);
        let width = if matches!(name, "observations" | "actions") {
            if header.element.kind == Kind::Bool {
                return Err(NpzError::new(
                    path,
                    format!("{shown} has dtype bool; expected integers or floats (read as float32)"),
                ));
            }
            crate::values::row_shape(&shown, &header.shape).map_err(|m| NpzError::new(path, m))?.1
        } else {
            if header.shape.len() != 1 {
                return Err(NpzError::new(
                    path,
                    format!("{shown} has shape {:?}; episode flags must be 1-D [N]", header.shape),
                ));
            }
            1
        };
        headers.push((header, width));
    }
    // Every array must have N = len(observations) rows.
    let rows = headers.first().and_then(|(h, _)| h.shape.first().copied()).unwrap_or(0);
    if let (Some((first, _)), Some(&(first_name, first_member))) = (headers.first(), chosen.first()) {
        for ((header, _), &(name, member)) in headers.iter().zip(&chosen).skip(1) {
            if header.shape.first().copied().unwrap_or(0) != rows {
                return Err(NpzError::new(
                    path,
                    format!(
                        "{} has shape {:?} but {} has shape {:?}: the leading dimensions (rows) differ",
                        describe_key(&member.key, name),
                        header.shape,
                        describe_key(&first_member.key, first_name),
                        first.shape
                    ),
                ));
            }
        }
    }
    if rows == 0 {
        return Err(NpzError::new(path, "'observations' has no rows (N = 0); a dataset needs at least one"));
    }

    let starts = episode_boundaries(path, &mut archive, rows, starts_member, lengths_member)?;
    let used = |m: &Member| {
        chosen.iter().any(|(_, c)| c.index == m.index)
            || (starts.is_some() && [starts_member, lengths_member].iter().flatten().any(|s| s.index == m.index))
    };
    let ignored = members.iter().filter(|m| !used(m)).map(|m| m.key.clone()).collect();
    let mut source = NpzSource {
        path: path.to_owned(),
        kind: DatasetKind::Trajectories,
        specs: Vec::new(),
        entries: Vec::new(),
        ignored,
        archive: None,
    };
    for (&(name, member), (header, width)) in chosen.iter().zip(headers) {
        if matches!(name, "observations" | "actions") {
            let mut entry = Entry::as_stored(member.key.clone(), Some(member.index), header);
            entry.to_f32 = true;
            entry.sent_len = rows * width as u64 * 4;
            source.push(name, Dtype::Float32, vec![rows, width as u64], entry);
        } else {
            // Flags are small ([N] bytes): read whole, checked and sent as bool.
            let (_, values) = member_values(path, &mut archive, member)?;
            let flags =
                crate::values::flags(&describe_key(&member.key, name), &values).map_err(|m| NpzError::new(path, m))?;
            let bytes = flags.iter().map(|&f| u8::from(f)).collect();
            let mut entry = Entry::in_memory(member.key.clone(), bytes);
            entry.zip_index = Some(member.index);
            source.push(name, Dtype::Bool, vec![rows], entry);
        }
    }
    if let Some((key, flags)) = starts {
        let bytes = flags.iter().map(|&f| u8::from(f)).collect();
        source.push("episode_starts", Dtype::Bool, vec![rows], Entry::in_memory(key, bytes));
    }
    source.archive = Some(archive);
    Ok(source)
}

/// The file's explicit episode starts (`episode_starts` as flags or indices, `episode_lengths`)
/// as per-row flags by the rules of [`crate::episodes`], with the key they came from.
fn episode_boundaries(
    path: &Path,
    archive: &mut ZipArchive<BufReader<File>>,
    rows: u64,
    starts: Option<&Member>,
    lengths: Option<&Member>,
) -> Result<Option<(String, Vec<bool>)>> {
    if starts.is_none() && lengths.is_none() {
        return Ok(None);
    }
    let rows_usize = usize::try_from(rows).map_err(|_| NpzError::new(path, "too many rows for this machine"))?;
    // (shape, values, is_bool, is_integer) of one member.
    let mut load = |member: &Member| -> Result<(Vec<u64>, Vec<f64>, bool, bool)> {
        let (header, values) = member_values(path, archive, member)?;
        let is_bool = header.element.kind == Kind::Bool;
        let is_integer = header.element.is_integer();
        Ok((header.shape, values, is_bool, is_integer))
    };
    let s = starts.map(&mut load).transpose()?;
    let l = lengths.map(&mut load).transpose()?;
    let flags = crate::episodes::explicit_starts(
        rows_usize,
        s.as_ref().map(|(shape, v, b, i)| (shape.as_slice(), v.as_slice(), *b, *i)),
        l.as_ref().map(|(shape, v, _, i)| (shape.as_slice(), v.as_slice(), *i)),
    )
    .map_err(|m| NpzError::new(path, m))?;
    let key = starts.or(lengths).map(|m| m.key.clone()).unwrap_or_default();
    Ok(flags.map(|(f, _)| (key, f)))
}

/// The maze walls a file holds under any of [`crate::episodes::WALL_KEYS`] (rule in
/// [`crate::episodes`]); `None` when it holds none. A plain `.npy` file is read as the walls.
pub fn walls_from_npz(path: &Path) -> io::Result<Option<crate::episodes::Walls>> {
    let invalid = |m: String| io::Error::new(io::ErrorKind::InvalidData, m);
    let mut found = Vec::new();
    for key in crate::episodes::WALL_KEYS {
        if let Some((shape, values)) = read_numbers(path, key)? {
            found.push((key, shape, values));
        }
        if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy")) {
            break;
        }
    }
    crate::episodes::pick_walls(&found).map_err(invalid)
}

/// `'terminations' (sent as 'terminals')` or just `'observations'`.
fn describe_key(key: &str, name: &str) -> String {
    if key == name { format!("'{key}'") } else { format!("'{key}' (sent as '{name}')") }
}

/// Samples are sent as stored: little-endian float32 or float64 only.
fn require_float(path: &Path, shown: &str, header: &Header) -> Result<Dtype> {
    match header.wire_dtype() {
        Some(dtype @ (Dtype::Float32 | Dtype::Float64)) => Ok(dtype),
        _ if header.element.kind == Kind::Float && header.element.big_endian => Err(NpzError::new(
            path,
            format!(
                "{shown} has dtype {} ({}); samples are sent as stored: convert with arr.astype('<f{}')",
                header.descr,
                header.element,
                header.element.size.max(4)
            ),
        )),
        _ => Err(NpzError::new(
            path,
            format!(
                "{shown} has dtype {}; it must be float32 or float64 (convert with arr.astype('float32'))",
                header.element
            ),
        )),
    }
}

/// A samples dataset: one float32 or float64 array `[N, ...]` (at least 2-D), sent as
/// `samples`.
///
/// From a plain `.npy` file, or from an `.npz` archive: the array named `key`, else the one
/// named `samples`, else the only array. Other arrays of the archive are left out and listed by
/// [`NpzSource::ignored_keys`].
pub fn samples_from_npz_or_npy(path: impl AsRef<Path>, key: Option<&str>) -> Result<NpzSource> {
    let path = path.as_ref();
    let (entry, ignored, archive) = match sniff(path)? {
        FileFormat::Npy => {
            if let Some(key) = key {
                return Err(NpzError::new(
                    path,
                    format!("is a single .npy array; a key ('{key}') only selects an array of an .npz archive"),
                ));
            }
            let file = File::open(path).map_err(|e| NpzError::new(path, e.to_string()))?;
            let stored = file.metadata().map_err(|e| NpzError::new(path, e.to_string()))?.len();
            let mut reader = BufReader::new(file);
            let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            let header = read_header(&mut reader).map_err(|m| NpzError::new(path, format!("array '{stem}': {m}")))?;
            check_complete(path, &stem, &header, stored)?;
            (Entry::as_stored(stem, None, header), Vec::new(), None)
        }
        FileFormat::Npz => {
            let (mut archive, members) = open_archive(path)?;
            let member = match key {
                Some(key) => members.iter().find(|m| m.key == key).ok_or_else(|| {
                    NpzError::new(path, format!("no array '{key}' (the archive holds {})", list_keys(&members)))
                })?,
                None => match members.iter().find(|m| m.key == "samples") {
                    Some(m) => m,
                    None => match members.as_slice() {
                        [only] => only,
                        [] => return Err(NpzError::new(path, "the archive holds no arrays")),
                        _ => {
                            return Err(NpzError::new(
                                path,
                                format!(
                                    "the archive holds {} and none is named 'samples'; choose one by key (CLI: --key)",
                                    list_keys(&members)
                                ),
                            ));
                        }
                    },
                },
            };
            let header = member_header(path, &mut archive, member)?;
            let ignored = members.iter().filter(|m| m.index != member.index).map(|m| m.key.clone()).collect();
            (Entry::as_stored(member.key.clone(), Some(member.index), header), ignored, Some(archive))
        }
    };
    let shown = describe_key(&entry.key, "samples");
    let Some(stored) = entry.stored.clone() else { return Err(NpzError::new(path, "npz source is inconsistent")) };
    let dtype = require_float(path, &shown, &stored)?;
    if stored.shape.len() < 2 {
        return Err(NpzError::new(
            path,
            format!(
                "{shown} has shape {:?}; samples must be [N, ...] with at least 2 dimensions \
                 (reshape 1-D data to [N, 1])",
                stored.shape
            ),
        ));
    }
    let mut source = NpzSource {
        path: path.to_owned(),
        kind: DatasetKind::Samples,
        specs: Vec::new(),
        entries: Vec::new(),
        ignored,
        archive,
    };
    source.push("samples", dtype, stored.shape, entry);
    Ok(source)
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use npyz::zip::{CompressionMethod, ZipWriter, write::FileOptions};

    use super::*;
    use relreward_client::client::payload_sha256;

    /// An npy file as numpy writes it (format 1.0, header padded to 64 bytes).
    fn npy(descr: &str, fortran: bool, shape: &[u64], data: &[u8]) -> Vec<u8> {
        let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
        let shape_text = match dims.as_slice() {
            [one] => format!("({one},)"),
            _ => format!("({})", dims.join(", ")),
        };
        let fortran = if fortran { "True" } else { "False" };
        // Structured dtypes are lists, written unquoted.
        let descr = if descr.starts_with('[') { descr.to_owned() } else { format!("'{descr}'") };
        let mut text = format!("{{'descr': {descr}, 'fortran_order': {fortran}, 'shape': {shape_text}, }}");
        let unpadded = 10 + text.len() + 1;
        text.push_str(&" ".repeat((64 - unpadded % 64) % 64));
        text.push('\n');
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&u16::try_from(text.len()).expect("short header").to_le_bytes());
        out.extend_from_slice(text.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn f32_bytes(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn f64_bytes(values: &[f64]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn write_npz(path: &Path, entries: &[(&str, Vec<u8>)], compressed: bool) {
        let file = File::create(path).expect("create npz");
        let mut zip = ZipWriter::new(file);
        let method = if compressed { CompressionMethod::Deflated } else { CompressionMethod::Stored };
        let options = FileOptions::default().compression_method(method);
        for (name, bytes) in entries {
            zip.start_file(format!("{name}.npy"), options).expect("start entry");
            zip.write_all(bytes).expect("write entry");
        }
        zip.finish().expect("finish npz");
    }

    fn read_all(source: &mut NpzSource, index: usize) -> io::Result<Vec<u8>> {
        let mut out = Vec::new();
        source.open(index)?.read_to_end(&mut out)?;
        Ok(out)
    }

    fn spec(name: &str, dtype: Dtype, shape: &[u64]) -> ArraySpec {
        ArraySpec { name: name.to_owned(), dtype: dtype as i32, shape: shape.to_vec() }
    }

    /// Archive entries: (array name, npy file bytes).
    type Entries = Vec<(&'static str, Vec<u8>)>;

    /// A small D4RL-like file: 4 rows, obs_dim 3, act_dim 2 (float64), bool flags, plus extras;
    /// and the data bytes of the arrays that are sent, in order.
    fn d4rl_entries() -> (Entries, Vec<Vec<u8>>) {
        let obs = f32_bytes(&(0..12).map(|i| i as f32 * 0.5).collect::<Vec<_>>());
        let act = f64_bytes(&[1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0]);
        let terminals = vec![0u8, 0, 0, 1];
        let timeouts = vec![0u8, 1, 0, 0];
        let rewards = f32_bytes(&[0.0, 1.0, 2.0, 3.0]);
        let entries = vec![
            ("rewards", npy("<f4", false, &[4], &rewards)),
            ("observations", npy("<f4", false, &[4, 3], &obs)),
            ("actions", npy("<f8", false, &[4, 2], &act)),
            ("terminals", npy("|b1", false, &[4], &terminals)),
            ("timeouts", npy("|b1", false, &[4], &timeouts)),
            ("infos/qpos", npy("<f8", false, &[4, 1], &f64_bytes(&[0.0; 4]))),
        ];
        // Actions are sent as float32 whatever their stored type.
        let act_sent = f32_bytes(&[1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0]);
        (entries, vec![obs, act_sent, terminals, timeouts])
    }

    #[test]
    fn d4rl_trajectories_read_shapes_dtypes_and_bytes() {
        let dir = tempfile::tempdir().expect("tempdir");
        for compressed in [false, true] {
            let path = dir.path().join(format!("d4rl-{compressed}.npz"));
            let (entries, data) = d4rl_entries();
            write_npz(&path, &entries, compressed);
            assert_eq!(detect_kind(&path).expect("kind"), DatasetKind::Trajectories);
            let mut source = trajectories_from_npz(&path).expect("read trajectories");
            assert_eq!(source.kind(), DatasetKind::Trajectories);
            assert_eq!(
                source.arrays(),
                &[
                    spec("observations", Dtype::Float32, &[4, 3]),
                    spec("actions", Dtype::Float32, &[4, 2]),
                    spec("terminals", Dtype::Bool, &[4]),
                    spec("timeouts", Dtype::Bool, &[4]),
                ]
            );
            assert_eq!(source.ignored_keys(), &["rewards".to_owned(), "infos/qpos".to_owned()]);
            assert!(source.renamed().is_empty());
            assert_eq!(source.total_bytes(), 48 + 32 + 4 + 4);
            for (i, expected) in data.iter().enumerate() {
                assert_eq!(&read_all(&mut source, i).expect("read array"), expected, "array {i}");
                // Reopening gives the same bytes again.
                assert_eq!(&read_all(&mut source, i).expect("reread array"), expected, "array {i}");
            }
            assert!(source.open(9).is_err());
        }
    }

    #[test]
    fn digest_covers_the_arrays_in_header_order() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("d.npz");
        let (entries, data) = d4rl_entries();
        write_npz(&path, &entries, true);
        let mut source = trajectories_from_npz(&path).expect("read");
        let mut memory = relreward_client::MemorySource::new();
        for (s, bytes) in source.arrays().to_vec().iter().zip(data) {
            memory.push_raw(&s.name, Dtype::try_from(s.dtype).expect("dtype"), &s.shape, bytes);
        }
        assert_eq!(payload_sha256(&mut source).expect("digest"), payload_sha256(&mut memory).expect("digest"));
    }

    #[test]
    fn minari_names_are_sent_as_d4rl_names() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("minari.npz");
        let obs = f64_bytes(&[0.0, 1.0, 2.0]);
        let entries = vec![
            ("observations", npy("<f8", false, &[3, 1], &obs)),
            ("actions", npy("<f4", false, &[3, 1], &f32_bytes(&[0.0, 0.1, 0.2]))),
            ("terminations", npy("|u1", false, &[3], &[0, 0, 1])),
            ("truncations", npy("|b1", false, &[3], &[0, 1, 0])),
            ("episode_starts", npy("|b1", false, &[3], &[1, 0, 0])),
        ];
        write_npz(&path, &entries, false);
        let mut source = trajectories_from_npz(&path).expect("read");
        let names: Vec<&str> = source.arrays().iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["observations", "actions", "terminals", "timeouts", "episode_starts"]);
        // uint8 flags (0/1) are sent as bool.
        assert_eq!(source.arrays()[2].dtype, Dtype::Bool as i32);
        assert_eq!(source.file_key(2), Some("terminations"));
        assert_eq!(
            source.renamed(),
            vec![
                ("terminations".to_owned(), "terminals".to_owned()),
                ("truncations".to_owned(), "timeouts".to_owned())
            ]
        );
        assert!(source.ignored_keys().is_empty());
        assert_eq!(read_all(&mut source, 2).expect("read"), vec![0, 0, 1]);
        assert_eq!(read_all(&mut source, 3).expect("read"), vec![0, 1, 0]);

        // Both spellings at once is ambiguous.
        let path = dir.path().join("both.npz");
        let mut entries = entries;
        entries.push(("terminals", npy("|b1", false, &[3], &[0, 0, 1])));
        write_npz(&path, &entries, false);
        let err = trajectories_from_npz(&path).expect_err("must fail").to_string();
        assert!(err.contains("'terminals'") && err.contains("'terminations'"), "{err}");
    }

    #[test]
    fn samples_from_npy_and_npz() {
        let dir = tempfile::tempdir().expect("tempdir");
        let values: Vec<f32> = (0..24).map(|i| i as f32).collect();
        let bytes = f32_bytes(&values);

        let path = dir.path().join("latents.npy");
        std::fs::write(&path, npy("<f4", false, &[2, 3, 2, 2], &bytes)).expect("write");
        assert_eq!(detect_kind(&path).expect("kind"), DatasetKind::Samples);
        let mut source = samples_from_npz_or_npy(&path, None).expect("npy");
        assert_eq!(source.arrays(), &[spec("samples", Dtype::Float32, &[2, 3, 2, 2])]);
        assert_eq!(source.file_key(0), Some("latents"));
        assert_eq!(read_all(&mut source, 0).expect("read"), bytes);
        assert!(samples_from_npz_or_npy(&path, Some("x")).is_err());

        // The only array of an archive, whatever its name.
        let path = dir.path().join("one.npz");
        write_npz(&path, &[("arr_0", npy("<f4", false, &[6, 4], &bytes))], true);
        let mut source = samples_from_npz_or_npy(&path, None).expect("single");
        assert_eq!(source.arrays(), &[spec("samples", Dtype::Float32, &[6, 4])]);
        assert_eq!(read_all(&mut source, 0).expect("read"), bytes);

        // 'samples' by default, another by key; the rest are ignored.
        let path = dir.path().join("many.npz");
        let other = f64_bytes(&[1.0, 2.0]);
        write_npz(
            &path,
            &[
                ("labels", npy("<i8", false, &[2], &[0; 16])),
                ("samples", npy("<f4", false, &[12, 2], &bytes)),
                ("other", npy("<f8", false, &[1, 2], &other)),
            ],
            false,
        );
        assert_eq!(detect_kind(&path).expect("kind"), DatasetKind::Samples);
        assert_eq!(npz_keys(&path).expect("keys"), ["labels", "samples", "other"]);
        let source = samples_from_npz_or_npy(&path, None).expect("default key");
        assert_eq!(source.arrays(), &[spec("samples", Dtype::Float32, &[12, 2])]);
        assert_eq!(source.ignored_keys(), &["labels".to_owned(), "other".to_owned()]);
        let mut source = samples_from_npz_or_npy(&path, Some("other")).expect("by key");
        assert_eq!(source.arrays(), &[spec("samples", Dtype::Float64, &[1, 2])]);
        assert_eq!(read_all(&mut source, 0).expect("read"), other);
        let err = samples_from_npz_or_npy(&path, Some("missing")).expect_err("must fail").to_string();
        assert!(err.contains("'missing'") && err.contains("'labels'"), "{err}");
        let err = samples_from_npz_or_npy(&path, Some("labels")).expect_err("must fail").to_string();
        assert!(err.contains("'labels'") && err.contains("int64"), "{err}");

        // Several arrays, none named samples: ambiguous.
        let path = dir.path().join("ambiguous.npz");
        write_npz(
            &path,
            &[("a", npy("<f4", false, &[2, 1], &bytes[..8])), ("b", npy("<f4", false, &[2, 1], &bytes[..8]))],
            false,
        );
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("'a', 'b'") && err.contains("key"), "{err}");

        // 1-D samples are refused.
        let path = dir.path().join("flat.npy");
        std::fs::write(&path, npy("<f4", false, &[24], &bytes)).expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("[24]") && err.contains("at least 2 dimensions"), "{err}");
    }

    fn npy_error(descr: &str, fortran: bool, shape: &[u64], data: &[u8]) -> String {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("x.npz");
        let obs = npy(descr, fortran, shape, data);
        let act = npy("<f4", false, &[shape[0], 1], &vec![0u8; 4 * shape[0] as usize]);
        write_npz(&path, &[("observations", obs), ("actions", act)], false);
        trajectories_from_npz(&path).expect_err("must fail").to_string()
    }

    #[test]
    fn unsupported_layouts_and_dtypes_are_refused_naming_array_and_dtype() {
        let err = npy_error("<f4", true, &[2, 2], &[0; 16]);
        assert!(err.contains("'observations'") && err.contains("Fortran"), "{err}");
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

        // Fortran order with one non-trivial dimension is the same layout: accepted.
        let dir = tempfile::tempdir().expect("tempdir");
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

    /// The float32 values a trajectories archive sends for array `index`.
    fn sent_f32(source: &mut NpzSource, index: usize) -> io::Result<Vec<f32>> {
        let bytes = read_all(source, index)?;
        Ok(bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }

    /// `values` stored as `descr` (`'<i2'`, `'>f8'`, ...).
    fn encode(descr: &str, values: &[f64]) -> Vec<u8> {
        let big = descr.starts_with('>');
        let mut out = Vec::new();
        for &v in values {
            let mut b: Vec<u8> = match &descr[1..] {
                "i1" => (v as i8).to_le_bytes().to_vec(),
                "i2" => (v as i16).to_le_bytes().to_vec(),
                "i4" => (v as i32).to_le_bytes().to_vec(),
                "i8" => (v as i64).to_le_bytes().to_vec(),
                "u1" => (v as u8).to_le_bytes().to_vec(),
                "u2" => (v as u16).to_le_bytes().to_vec(),
                "u4" => (v as u32).to_le_bytes().to_vec(),
                "u8" => (v as u64).to_le_bytes().to_vec(),
                // Small integers and halves only: exact in binary16.
                "f2" => {
                    let bits: u16 =
                        (0..=u16::MAX).find(|&h| f64::from(crate::values::f16_to_f32(h)) == v).expect("a half");
                    bits.to_le_bytes().to_vec()
                }
                "f4" => (v as f32).to_le_bytes().to_vec(),
                "f8" => v.to_le_bytes().to_vec(),
                other => panic!("{other}"),
            };
            if big {
                b.reverse();
            }
            out.extend(b);
        }
        out
    }

    #[test]
    fn every_integer_and_float_dtype_in_either_byte_order_is_sent_as_float32() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.npz");
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
    fn rows_are_one_value_per_row_for_1d_and_flattened_row_major_beyond_2d() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.npz");
        let obs: Vec<f32> = (0..12).map(|i| i as f32).collect();
        write_npz(
            &path,
            &[
                ("observations", npy("<f4", false, &[2, 3, 2], &f32_bytes(&obs))),
                ("actions", npy("<i8", false, &[2], &encode("<i8", &[3.0, -4.0]))),
            ],
            false,
        );
        let mut source = trajectories_from_npz(&path).expect("read");
        assert_eq!(
            source.arrays(),
            &[spec("observations", Dtype::Float32, &[2, 6]), spec("actions", Dtype::Float32, &[2, 1])]
        );
        assert_eq!(sent_f32(&mut source, 0).expect("obs"), obs);
        assert_eq!(sent_f32(&mut source, 1).expect("act"), [3.0, -4.0]);
        // A scalar is not rows.
        write_npz(
            &path,
            &[("observations", npy("<f4", false, &[], &[0; 4])), ("actions", npy("<f4", false, &[1], &[0; 4]))],
            false,
        );
        let err = trajectories_from_npz(&path).expect_err("scalar").to_string();
        assert!(err.contains("'observations' is a scalar"), "{err}");
    }

    #[test]
    fn values_not_finite_as_float32_are_refused_naming_row_and_coordinate() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.npz");
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

    #[test]
    fn flags_of_any_number_type_holding_only_0_and_1_are_sent_as_bool() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.npz");
        let base = || {
            vec![
                ("observations", npy("<f4", false, &[4, 1], &[0; 16])),
                ("actions", npy("<f4", false, &[4, 1], &[0; 16])),
            ]
        };
        for (descr, key) in [
            ("<i8", "terminals"),
            ("<f4", "timeouts"),
            (">f8", "terminations"),
            ("|i1", "truncations"),
            ("<f2", "terminals"),
        ] {
            let mut entries = base();
            entries.push((key, npy(descr, false, &[4], &encode(&descr.replace('|', "<"), &[0.0, 1.0, 0.0, 1.0]))));
            write_npz(&path, &entries, false);
            let mut source = trajectories_from_npz(&path).unwrap_or_else(|e| panic!("{descr}: {e}"));
            assert_eq!(source.arrays()[2].dtype, Dtype::Bool as i32, "{descr}");
            assert_eq!(read_all(&mut source, 2).expect("flags"), [0, 1, 0, 1], "{descr}");
        }
        for (descr, values, want) in [
            ("<i8", [0.0, 1.0, 2.0, 1.0], "'terminals' holds 2 at row 2"),
            ("<f4", [0.0, 0.5, 0.0, 1.0], "'terminals' holds 0.5 at row 1"),
            ("<i4", [-1.0, 0.0, 0.0, 0.0], "'terminals' holds -1 at row 0"),
            ("|u1", [0.0, 0.0, 0.0, 7.0], "'terminals' holds 7 at row 3"),
        ] {
            let mut entries = base();
            entries.push(("terminals", npy(descr, false, &[4], &encode(&descr.replace('|', "<"), &values))));
            write_npz(&path, &entries, false);
            let err = trajectories_from_npz(&path).expect_err("not 0/1").to_string();
            assert!(err.contains(want), "{descr}: {err}");
        }
    }

    #[test]
    fn no_rows_is_refused_by_name() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.npz");
        write_npz(
            &path,
            &[("observations", npy("<f4", false, &[0, 3], &[])), ("actions", npy("<f4", false, &[0, 1], &[]))],
            false,
        );
        let err = trajectories_from_npz(&path).expect_err("empty").to_string();
        assert!(err.contains("'observations' has no rows (N = 0)"), "{err}");
    }

    #[test]
    fn samples_keep_their_stored_float_type() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("s.npy");
        std::fs::write(&path, npy("<f8", false, &[2, 1], &f64_bytes(&[0.1, 0.2]))).expect("write");
        let source = samples_from_npz_or_npy(&path, None).expect("f64 samples");
        assert_eq!(source.arrays(), &[spec("samples", Dtype::Float64, &[2, 1])]);
        std::fs::write(&path, npy(">f4", false, &[2, 1], &[0; 8])).expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("big-endian").to_string();
        assert!(err.contains("'>f4'") && err.contains("astype('<f4')"), "{err}");
        std::fs::write(&path, npy("<i8", false, &[2, 1], &[0; 16])).expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("int").to_string();
        assert!(err.contains("int64") && err.contains("float32 or float64"), "{err}");
    }

    #[test]
    fn missing_and_misshapen_trajectory_arrays() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.npz");
        write_npz(&path, &[("actions", npy("<f4", false, &[2, 1], &[0; 8]))], false);
        let err = trajectories_from_npz(&path).expect_err("must fail").to_string();
        assert!(err.contains("no 'observations' array") && err.contains("'actions'"), "{err}");
        assert_eq!(detect_kind(&path).expect("kind"), DatasetKind::Samples);

        write_npz(&path, &[("observations", npy("<f4", false, &[2, 1], &[0; 8]))], false);
        let err = trajectories_from_npz(&path).expect_err("must fail").to_string();
        assert!(err.contains("no 'actions' array"), "{err}");

        // Mismatched N names both arrays and both shapes.
        write_npz(
            &path,
            &[("observations", npy("<f4", false, &[3, 2], &[0; 24])), ("actions", npy("<f4", false, &[2, 1], &[0; 8]))],
            false,
        );
        let err = trajectories_from_npz(&path).expect_err("must fail").to_string();
        assert!(err.contains("'actions' has shape [2, 1]") && err.contains("'observations' has shape [3, 2]"), "{err}");
        write_npz(
            &path,
            &[
                ("observations", npy("<f4", false, &[3, 2], &[0; 24])),
                ("actions", npy("<f4", false, &[3, 1], &[0; 12])),
                ("truncations", npy("|b1", false, &[4], &[0; 4])),
            ],
            false,
        );
        let err = trajectories_from_npz(&path).expect_err("must fail").to_string();
        assert!(err.contains("'truncations' (sent as 'timeouts') has shape [4]"), "{err}");

        // Flags of shape [N, 1].
        write_npz(
            &path,
            &[
                ("observations", npy("<f4", false, &[1, 1], &[0; 4])),
                ("actions", npy("<f4", false, &[1, 1], &[0; 4])),
                ("terminals", npy("|b1", false, &[1, 1], &[0])),
            ],
            false,
        );
        let err = trajectories_from_npz(&path).expect_err("must fail").to_string();
        assert!(err.contains("'terminals' has shape [1, 1]") && err.contains("1-D [N]"), "{err}");

        // A single .npy cannot be trajectories.
        let npy_path = dir.path().join("obs.npy");
        std::fs::write(&npy_path, npy("<f4", false, &[1, 1], &[0; 4])).expect("write");
        assert!(trajectories_from_npz(&npy_path).is_err());
    }

    #[test]
    fn truncated_files_are_errors_not_panics() {
        let dir = tempfile::tempdir().expect("tempdir");
        let full = npy("<f4", false, &[4, 2], &[7; 32]);

        // Cut inside the data: refused when the file is opened.
        let path = dir.path().join("short.npy");
        std::fs::write(&path, &full[..full.len() - 5]).expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("truncated") && err.contains("32 data bytes"), "{err}");
        // Cut inside the header.
        for cut in [0, 3, 9, 20, 127] {
            std::fs::write(&path, &full[..cut]).expect("write");
            assert!(samples_from_npz_or_npy(&path, None).is_err(), "cut at {cut}");
        }

        // Truncated after it was opened: reading fails.
        std::fs::write(&path, &full).expect("write");
        let mut source = samples_from_npz_or_npy(&path, None).expect("open");
        std::fs::write(&path, &full[..full.len() - 5]).expect("truncate");
        let err = read_all(&mut source, 0).expect_err("must fail");
        assert_eq!(err.kind(), io::ErrorKind::UnexpectedEof);
        assert!(err.to_string().contains("27 of its 32 data bytes"), "{err}");
        assert!(payload_sha256(&mut source).is_err());

        // A truncated archive.
        let path = dir.path().join("short.npz");
        let (entries, _) = d4rl_entries();
        write_npz(&path, &entries, true);
        let bytes = std::fs::read(&path).expect("read");
        for cut in [0, 10, bytes.len() / 2, bytes.len() - 1] {
            std::fs::write(&path, &bytes[..cut]).expect("write");
            assert!(trajectories_from_npz(&path).is_err(), "cut at {cut}");
            assert!(detect_kind(&path).is_err(), "cut at {cut}");
        }

        // An archive entry whose data is shorter than its header declares.
        let path = dir.path().join("lying.npz");
        write_npz(
            &path,
            &[
                ("observations", npy("<f4", false, &[4, 2], &[0; 31])),
                ("actions", npy("<f4", false, &[4, 1], &[0; 16])),
            ],
            false,
        );
        let err = trajectories_from_npz(&path).expect_err("must fail").to_string();
        assert!(err.contains("'observations' is truncated"), "{err}");
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
    fn not_npy_or_npz() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("x.csv");
        std::fs::write(&path, "a,b\n1,2\n").expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("not an .npy or .npz file") && err.contains("x.csv"), "{err}");
        assert!(trajectories_from_npz(dir.path().join("missing.npz")).is_err());
    }

    /// A cheap stand-in for fuzzing: flip, cut and splice bytes of valid files and check that
    /// every reader returns (Ok or Err) without panicking.
    #[test]
    fn mutated_files_never_panic() {
        let dir = tempfile::tempdir().expect("tempdir");
        let clean_npz = dir.path().join("clean.npz");
        let (entries, _) = d4rl_entries();
        write_npz(&clean_npz, &entries, false);
        let npz_bytes = std::fs::read(&clean_npz).expect("read");
        let npy_bytes = npy("<f8", false, &[3, 2], &f64_bytes(&[1.0; 6]));
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let path = dir.path().join("mutant");
        for round in 0..600 {
            let base = if round % 2 == 0 { &npz_bytes } else { &npy_bytes };
            let mut bytes = base.clone();
            for _ in 0..1 + next() % 4 {
                let at = (next() % bytes.len() as u64) as usize;
                match next() % 4 {
                    0 => bytes[at] ^= 1 << (next() % 8),
                    1 => bytes[at] = b"0123456789(),'<>|fFTx\x00\xff"[(next() % 22) as usize],
                    2 => bytes.truncate(at.max(1)),
                    _ => bytes.insert(at, (next() % 256) as u8),
                }
            }
            std::fs::write(&path, &bytes).expect("write");
            let _ = detect_kind(&path);
            let _ = npz_keys(&path);
            if let Ok(mut s) = trajectories_from_npz(&path) {
                let _ = payload_sha256(&mut s);
            }
            if let Ok(mut s) = samples_from_npz_or_npy(&path, None) {
                let _ = payload_sha256(&mut s);
            }
            let _ = read_npy_header(&mut bytes.as_slice());
        }
    }
}
