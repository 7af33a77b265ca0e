//! Dataset ingestion: validates an upload message by message, writes each array to an `.npy`
//! file in a staging directory, hashes the payload and accumulates per-coordinate statistics
//! on the way, so that commit needs no second pass over the data.
//!
//! Every rejection is `Error::InvalidArgument` (or `ResourceExhausted` for the quota) with a
//! message naming the field. Nothing becomes visible here: the caller publishes the staging
//! directory only after [`DatasetIngest::finish`] succeeded, and dropping an unfinished ingest
//! removes its staging directory.

use std::fs::File;
use std::io::{BufWriter, Write};

use relreward_proto::schema::manifest::MAX_ITEM_ELEMENTS;
use relreward_proto::tensor::{self, CodecError};
use relreward_proto::v1::{self as pb, Dtype};
use sha2::{Digest, Sha256};

use super::{ArrayRecord, ArrayStats, DatasetKind, DatasetRecord, EpisodeRecord, Staging, npy};
use crate::error::{Error, Result, brief, quote};

/// Array names of a trajectory dataset; the first two are required.
const TRAJECTORY_ARRAYS: [&str; 5] = ["observations", "actions", "terminals", "timeouts", "episode_starts"];

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    /// Float values; statistics are computed.
    Values,
    /// Episode ends after each flagged row (terminals, timeouts).
    EndsAfter,
    /// Episode starts at each flagged row (episode_starts).
    StartsAt,
    /// Class labels of a sample dataset (`labels`): integers in 0..=MAX_LABEL, whose
    /// statistics (one coordinate: min, max, mean, std) are kept as a float array's are.
    Labels,
}

/// Largest class label a dataset may hold (the manifest's limit on classes, less one).
const MAX_LABEL: i64 = (relreward_proto::schema::manifest::MAX_CONDITION_SIZE - 1) as i64;

/// Running per-coordinate min, max, mean and variance (Welford's algorithm, in f64, so a
/// million rows of float32 lose no precision the way a naive sum of squares would).
struct Moments {
    n: u64,
    min: Vec<f64>,
    max: Vec<f64>,
    mean: Vec<f64>,
    m2: Vec<f64>,
}

impl Moments {
    fn new(coords: usize) -> Self {
        Self {
            n: 0,
            min: vec![f64::INFINITY; coords],
            max: vec![f64::NEG_INFINITY; coords],
            mean: vec![0.0; coords],
            m2: vec![0.0; coords],
        }
    }

    fn push_row(&mut self, row: &[f64]) {
        self.n += 1;
        let n = self.n as f64;
        for (j, &x) in row.iter().enumerate() {
            self.min[j] = self.min[j].min(x);
            self.max[j] = self.max[j].max(x);
            let delta = x - self.mean[j];
            self.mean[j] += delta / n;
            self.m2[j] += delta * (x - self.mean[j]);
        }
    }

    fn finish(self) -> ArrayStats {
        let n = self.n.max(1) as f64;
        ArrayStats {
            std: self.m2.iter().map(|m| (m / n).sqrt()).collect(),
            min: self.min,
            max: self.max,
            mean: self.mean,
        }
    }
}

struct ArrayState {
    name: String,
    dtype: Dtype,
    shape: Vec<u64>,
    row_bytes: u64,
    /// Elements per row (coordinates).
    row_elems: usize,
    rows_done: u64,
    role: Role,
    file_name: String,
    file: BufWriter<File>,
    moments: Option<Moments>,
}

/// Flags per row, one bit each.
struct Bits(Vec<u64>);

impl Bits {
    fn new(n: u64) -> Self {
        Self(vec![0; n.div_ceil(64) as usize])
    }
    fn set(&mut self, i: u64) {
        self.0[(i / 64) as usize] |= 1 << (i % 64);
    }
    fn get(&self, i: u64) -> bool {
        self.0[(i / 64) as usize] & (1 << (i % 64)) != 0
    }
}

pub struct DatasetIngest {
    name: String,
    kind: DatasetKind,
    description: String,
    num_rows: u64,
    arrays: Vec<ArrayState>,
    /// Index of the array currently receiving chunks.
    current: usize,
    chunks: u64,
    hasher: Sha256,
    ends_after: Bits,
    starts_at: Bits,
    staging: Staging,
}

impl DatasetIngest {
    /// Validates the header and opens one file per array in `staging`.
    pub fn begin(header: pb::UploadHeader, max_upload_bytes: u64, staging: Staging) -> Result<Self> {
        let kind = match pb::DatasetKind::try_from(header.kind) {
            Ok(pb::DatasetKind::Trajectories) => DatasetKind::Trajectories,
            Ok(pb::DatasetKind::Samples) => DatasetKind::Samples,
            _ => {
                return Err(Error::invalid(format!(
                    "header.kind: {} is not a dataset kind (expected TRAJECTORIES or SAMPLES)",
                    header.kind
                )));
            }
        };
        if header.arrays.is_empty() {
            return Err(Error::invalid("header.arrays: empty; an upload needs at least one array"));
        }
        let num_rows = header.arrays[0].shape.first().copied().unwrap_or(0);
        let mut total_bytes = 0u64;
        // Every array's header is checked, and the payload against the quota, before anything
        // is allocated or opened: the shapes are the client's, and a row's statistics cost four
        // f64 per coordinate.
        let mut checked = Vec::with_capacity(header.arrays.len());
        for (i, spec) in header.arrays.iter().enumerate() {
            let field = format!("header.arrays[{i}] ({})", quote(&spec.name));
            let role = role_of(kind, &spec.name).ok_or_else(|| {
                let allowed = match kind {
                    DatasetKind::Trajectories => TRAJECTORY_ARRAYS.join(", "),
                    DatasetKind::Samples => "samples, labels".to_owned(),
                };
                Error::invalid(format!("{field}.name: not an array of a {kind:?} dataset (allowed: {allowed})"))
            })?;
            if header.arrays[..i].iter().any(|a| a.name == spec.name) {
                return Err(Error::invalid(format!("{field}.name: array listed twice")));
            }
            let dtype = tensor::known_dtype(spec.dtype).map_err(|e| Error::invalid(format!("{field}.dtype: {e}")))?;
            check_array_shape(kind, role, &field, dtype, &spec.shape)?;
            if spec.shape[0] != num_rows {
                return Err(Error::invalid(format!(
                    "{field}.shape: {} has {} rows but '{}' has {num_rows}; all arrays share the leading dimension",
                    brief(&spec.shape),
                    spec.shape[0],
                    header.arrays[0].name
                )));
            }
            let bytes =
                tensor::byte_len(&spec.shape, dtype).map_err(|e| Error::invalid(format!("{field}.shape: {e}")))?;
            total_bytes = total_bytes.saturating_add(bytes);
            let row_bytes =
                tensor::byte_len(&spec.shape[1..], dtype).map_err(|e| Error::invalid(format!("{field}.shape: {e}")))?;
            let row_elems =
                tensor::numel(&spec.shape[1..]).map_err(|e| Error::invalid(format!("{field}.shape: {e}")))? as usize;
            // A row is one item of a model's space, bounded as those are; its statistics hold
            // eight times its float32 bytes, so the quota alone would not bound them.
            if row_elems as u64 > MAX_ITEM_ELEMENTS {
                return Err(Error::invalid(format!(
                    "{field}.shape: {} has {row_elems} elements per row, more than the {MAX_ITEM_ELEMENTS} an item \
                     may have",
                    brief(&spec.shape)
                )));
            }
            checked.push((spec, dtype, role, row_bytes, row_elems));
        }
        if num_rows == 0 {
            return Err(Error::invalid("header.arrays: N = 0 rows; empty datasets are not stored"));
        }
        let listed = |name: &str| header.arrays.iter().any(|a| a.name == name);
        if kind == DatasetKind::Samples && !listed("samples") {
            return Err(Error::invalid("header.arrays: a samples dataset needs 'samples'"));
        }
        if kind == DatasetKind::Trajectories {
            for required in &TRAJECTORY_ARRAYS[..2] {
                if !listed(required) {
                    return Err(Error::invalid(format!("header.arrays: a trajectory dataset needs '{required}'")));
                }
            }
        }
        if total_bytes > max_upload_bytes {
            return Err(Error::ResourceExhausted(format!(
                "header.arrays: payload of {total_bytes} bytes exceeds the upload quota of {max_upload_bytes} bytes"
            )));
        }
        let mut arrays = Vec::with_capacity(checked.len());
        for (spec, dtype, role, row_bytes, row_elems) in checked {
            let file_name = format!("{}.npy", spec.name);
            let mut file = BufWriter::with_capacity(1 << 20, File::create(staging.path().join(&file_name))?);
            file.write_all(&npy::header(dtype, &spec.shape))?;
            let moments = matches!(role, Role::Values | Role::Labels).then(|| Moments::new(row_elems));
            arrays.push(ArrayState {
                name: spec.name.clone(),
                dtype,
                shape: spec.shape.clone(),
                row_bytes,
                row_elems,
                rows_done: 0,
                role,
                file_name,
                file,
                moments,
            });
        }
        Ok(Self {
            name: header.name,
            kind,
            description: header.description,
            num_rows,
            arrays,
            current: 0,
            chunks: 0,
            hasher: Sha256::new(),
            ends_after: Bits::new(num_rows),
            starts_at: Bits::new(num_rows),
            staging,
        })
    }

    /// Validates and stores one chunk.
    pub fn accept(&mut self, chunk: pb::DatasetChunk) -> Result<()> {
        self.chunks += 1;
        let n = self.chunks;
        // Arrays arrive in header order: move past completed ones.
        while self.current < self.arrays.len() && self.arrays[self.current].rows_done == self.num_rows {
            self.current += 1;
        }
        let Some(a) = self.arrays.get_mut(self.current) else {
            return Err(Error::invalid(format!(
                "chunk {n} (array {}): every array is already complete",
                quote(&chunk.array)
            )));
        };
        if chunk.array != a.name {
            return Err(Error::invalid(format!(
                "chunk {n}.array: {} but '{}' is incomplete ({} of {} rows); arrays are sent whole, in header order",
                quote(&chunk.array),
                a.name,
                a.rows_done,
                self.num_rows
            )));
        }
        let field = format!("chunk {n} (array '{}')", a.name);
        let data = chunk.data.ok_or_else(|| Error::invalid(format!("{field}.data: missing")))?;
        let dtype = tensor::validate(&data).map_err(|e| Error::invalid(format!("{field}.data: {e}")))?;
        if dtype != a.dtype {
            return Err(Error::invalid(format!(
                "{field}.data.dtype: {} but the header declared {}",
                tensor::dtype_name(dtype),
                tensor::dtype_name(a.dtype)
            )));
        }
        if data.shape.len() != a.shape.len() || data.shape[1..] != a.shape[1..] {
            let mut expected: Vec<String> = a.shape.iter().map(u64::to_string).collect();
            expected[0] = "rows".into();
            return Err(Error::invalid(format!(
                "{field}.data.shape: {} is inconsistent with the header's [{}]",
                brief(&data.shape),
                expected.join(", ")
            )));
        }
        let rows = data.shape[0];
        if rows == 0 {
            return Err(Error::invalid(format!("{field}.data: chunk has no rows")));
        }
        if a.rows_done + rows > self.num_rows {
            return Err(Error::invalid(format!(
                "{field}.data.shape: {rows} more rows would make {} but the header declared {}",
                a.rows_done + rows,
                self.num_rows
            )));
        }
        debug_assert_eq!(data.data.len() as u64, rows * a.row_bytes);
        match a.role {
            Role::Values => {
                let first_row = a.rows_done;
                let row_elems = a.row_elems;
                let moments =
                    a.moments.as_mut().ok_or_else(|| Error::internal("ingest", "float array without moments"))?;
                push_rows(&data, row_elems, moments).map_err(|e| match e {
                    CodecError::NotFinite { index, value } => Error::invalid(format!(
                        "{field}.data: value {value} at row {}, coordinate {} is not finite",
                        first_row + index / row_elems as u64,
                        index % row_elems as u64
                    )),
                    CodecError::OutOfF32Range { index, value } => Error::invalid(format!(
                        "{field}.data: value {value:e} at row {}, coordinate {} is {}",
                        first_row + index / row_elems as u64,
                        index % row_elems as u64,
                        tensor::OUTSIDE_F32
                    )),
                    other => Error::invalid(format!("{field}.data: {other}")),
                })?;
            }
            Role::Labels => {
                let first_row = a.rows_done;
                let labels = tensor::decode_i64(&data).map_err(|e| Error::invalid(format!("{field}.data: {e}")))?;
                let moments =
                    a.moments.as_mut().ok_or_else(|| Error::internal("ingest", "label array without moments"))?;
                for (i, &label) in labels.iter().enumerate() {
                    if !(0..=MAX_LABEL).contains(&label) {
                        return Err(Error::invalid(format!(
                            "{field}.data: label {label} at row {} is outside 0..={MAX_LABEL}",
                            first_row + i as u64
                        )));
                    }
                    moments.push_row(&[label as f64]);
                }
            }
            Role::EndsAfter | Role::StartsAt => {
                let bits = if a.role == Role::EndsAfter { &mut self.ends_after } else { &mut self.starts_at };
                for (i, &b) in data.data.iter().enumerate() {
                    if b != 0 {
                        bits.set(a.rows_done + i as u64);
                    }
                }
            }
        }
        a.file.write_all(&data.data)?;
        self.hasher.update(&data.data);
        a.rows_done += rows;
        Ok(())
    }

    /// Checks completeness and the digest, flushes the files and returns the staging directory
    /// with the record to publish.
    pub fn finish(self, sha256: &str) -> Result<(Staging, DatasetRecord)> {
        if let Some(a) = self.arrays.iter().find(|a| a.rows_done < self.num_rows) {
            return Err(Error::invalid(format!(
                "commit: array '{}' is incomplete ({} of {} rows received)",
                a.name, a.rows_done, self.num_rows
            )));
        }
        let claimed = sha256.to_ascii_lowercase();
        if claimed.len() != 64 || !claimed.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(Error::invalid(format!("commit.sha256: {} is not 64 hex digits", quote(sha256))));
        }
        let actual = hex::encode(self.hasher.finalize());
        if claimed != actual {
            return Err(Error::invalid(format!(
                "commit.sha256: digest mismatch: the commit says {claimed} but the received payload hashes to {actual}"
            )));
        }
        let episodes = (self.kind == DatasetKind::Trajectories)
            .then(|| episodes(self.num_rows, &self.ends_after, &self.starts_at));
        let mut records = Vec::with_capacity(self.arrays.len());
        let mut size_bytes = 0;
        for a in self.arrays {
            let file = a.file.into_inner().map_err(|e| Error::internal("flushing array file", e.error()))?;
            file.sync_all()?;
            size_bytes += a.row_bytes * self.num_rows;
            records.push(ArrayRecord {
                name: a.name,
                dtype: tensor::dtype_name(a.dtype).to_owned(),
                shape: a.shape,
                file: a.file_name,
                stats: a.moments.map(Moments::finish),
            });
        }
        let record = DatasetRecord {
            name: self.name,
            kind: self.kind,
            num_rows: self.num_rows,
            arrays: records,
            episodes,
            sha256: actual,
            size_bytes,
            created_at_ms: now_ms(),
            description: self.description,
            blob_key: String::new(),
        };
        Ok((self.staging, record))
    }
}

fn role_of(kind: DatasetKind, name: &str) -> Option<Role> {
    match (kind, name) {
        (DatasetKind::Trajectories, "observations" | "actions") | (DatasetKind::Samples, "samples") => {
            Some(Role::Values)
        }
        (DatasetKind::Trajectories, "terminals" | "timeouts") => Some(Role::EndsAfter),
        (DatasetKind::Trajectories, "episode_starts") => Some(Role::StartsAt),
        (DatasetKind::Samples, "labels") => Some(Role::Labels),
        _ => None,
    }
}

fn check_array_shape(kind: DatasetKind, role: Role, field: &str, dtype: Dtype, shape: &[u64]) -> Result<()> {
    let is_float = matches!(dtype, Dtype::Float32 | Dtype::Float64);
    let is_flag = matches!(dtype, Dtype::Bool | Dtype::Uint8);
    let dims = brief(&shape);
    match role {
        Role::Values if !is_float => Err(Error::invalid(format!(
            "{field}.dtype: {} but values must be float32 or float64",
            tensor::dtype_name(dtype)
        ))),
        Role::Labels if !matches!(dtype, Dtype::Int32 | Dtype::Int64 | Dtype::Uint8) => Err(Error::invalid(format!(
            "{field}.dtype: {} but class labels must be int32, int64 or uint8",
            tensor::dtype_name(dtype)
        ))),
        Role::Labels if shape.len() != 1 => Err(Error::invalid(format!("{field}.shape: {dims} must be [N]"))),
        Role::EndsAfter | Role::StartsAt if !is_flag => Err(Error::invalid(format!(
            "{field}.dtype: {} but episode flags must be bool or uint8",
            tensor::dtype_name(dtype)
        ))),
        Role::Values if kind == DatasetKind::Trajectories && shape.len() != 2 => {
            Err(Error::invalid(format!("{field}.shape: {dims} must be [N, dim]")))
        }
        Role::Values if shape.len() < 2 => {
            Err(Error::invalid(format!("{field}.shape: {dims} must be [N, ...] with at least 2 dimensions")))
        }
        Role::EndsAfter | Role::StartsAt if shape.len() != 1 => {
            Err(Error::invalid(format!("{field}.shape: {dims} must be [N]")))
        }
        _ if shape.iter().skip(1).any(|&d| d == 0) => {
            Err(Error::invalid(format!("{field}.shape: {dims} has an empty dimension")))
        }
        _ => Ok(()),
    }
}

/// Feeds a float chunk row by row into `moments`, refusing non-finite values and float64 values
/// beyond float32's range (models compute in float32, and such values' squares would overflow
/// the statistics to an infinite std, which a stored record cannot hold).
fn push_rows(data: &pb::Tensor, row_elems: usize, moments: &mut Moments) -> std::result::Result<(), CodecError> {
    let mut row = Vec::with_capacity(row_elems);
    let mut index = 0u64;
    let mut bad = None;
    tensor::for_each_float(data, |v| {
        if bad.is_some() {
            return;
        }
        if tensor::beyond_f32(v) {
            bad = Some(CodecError::OutOfF32Range { index, value: v });
            return;
        }
        if !v.is_finite() {
            bad = Some(CodecError::NotFinite { index, value: v });
            return;
        }
        row.push(v);
        if row.len() == row_elems {
            moments.push_row(&row);
            row.clear();
        }
        index += 1;
    })?;
    bad.map_or(Ok(()), Err)
}

/// Episode lengths from boundary flags: an episode ends after a row flagged in `ends_after`
/// and before a row flagged in `starts_at`; a trailing partial episode counts.
fn episodes(n: u64, ends_after: &Bits, starts_at: &Bits) -> EpisodeRecord {
    let (mut count, mut min, mut max, mut len) = (0u64, u64::MAX, 0u64, 0u64);
    let mut close = |len: &mut u64| {
        if *len > 0 {
            count += 1;
            min = min.min(*len);
            max = max.max(*len);
            *len = 0;
        }
    };
    for i in 0..n {
        if i > 0 && starts_at.get(i) {
            close(&mut len);
        }
        len += 1;
        if ends_after.get(i) {
            close(&mut len);
        }
    }
    close(&mut len);
    EpisodeRecord { count, min_length: min, max_length: max, mean_length: n as f64 / count.max(1) as f64 }
}

pub fn now_ms() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis() as i64).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bits(n: u64, set: &[u64]) -> Bits {
        let mut b = Bits::new(n);
        for &i in set {
            b.set(i);
        }
        b
    }

    #[test]
    fn episodes_from_terminals_and_starts() {
        let e = episodes(10, &bits(10, &[2, 6]), &bits(10, &[]));
        assert_eq!((e.count, e.min_length, e.max_length), (3, 3, 4)); // 0..=2, 3..=6, 7..=9
        let e = episodes(10, &bits(10, &[]), &bits(10, &[0, 5]));
        assert_eq!((e.count, e.min_length, e.max_length), (2, 5, 5));
        let e = episodes(4, &bits(4, &[3]), &bits(4, &[]));
        assert_eq!((e.count, e.min_length, e.max_length, e.mean_length), (1, 4, 4, 4.0));
    }

    #[test]
    fn moments_match_two_pass_formulas() {
        let rows = [[1.0, -2.0], [3.0, 5.0], [2.5, 0.5], [1e6 + 1.0, 7.0]];
        let mut m = Moments::new(2);
        for r in &rows {
            m.push_row(r);
        }
        let s = m.finish();
        for j in 0..2 {
            let col: Vec<f64> = rows.iter().map(|r| r[j]).collect();
            let mean = col.iter().sum::<f64>() / 4.0;
            let var = col.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 4.0;
            assert!((s.mean[j] - mean).abs() < 1e-9 * mean.abs().max(1.0));
            assert!((s.std[j] - var.sqrt()).abs() < 1e-9 * var.sqrt().max(1.0));
            assert_eq!(s.min[j], col.iter().copied().fold(f64::INFINITY, f64::min));
            assert_eq!(s.max[j], col.iter().copied().fold(f64::NEG_INFINITY, f64::max));
        }
    }
}
