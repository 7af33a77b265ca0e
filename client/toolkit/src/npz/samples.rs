//! A samples dataset: one float array `[N, ...]` of an `.npy` file or an `.npz` archive (chosen
//! by key, by the name `samples`, or as the only array), sent as stored under the name
//! `samples`, so only little-endian (or byte-order-free) float32 and float64 are taken; an
//! archive's `labels` `[N]` beside them (class labels, integers) travel with them.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use relreward_proto::v1::{DatasetKind, Dtype};

use super::archive::{
    Archive, FileFormat, Member, check_complete, list_keys, member_header, member_values, open_archive, sniff,
};
use super::error::{NpzError, Result, describe_key};
use super::npy::{Header, read_header};
use super::source::{Entry, NpzSource};
use crate::values::Kind;

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
/// named `samples`, else the only array besides `labels`. An array `labels` is sent beside the
/// samples as their class labels ([`labels_entry`]); other arrays of the archive are left out
/// and listed by [`NpzSource::ignored_keys`].
pub fn samples_from_npz_or_npy(path: impl AsRef<Path>, key: Option<&str>) -> Result<NpzSource> {
    let path = path.as_ref();
    let (entry, ignored, archive, labels) = match sniff(path)? {
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
            (Entry::as_stored(stem, None, header), Vec::new(), None, None)
        }
        FileFormat::Npz => {
            let (mut archive, members) = open_archive(path)?;
            let member = match key {
                Some(key) => members.iter().find(|m| m.key == key).ok_or_else(|| {
                    NpzError::new(path, format!("no array '{key}' (the archive holds {})", list_keys(&members)))
                })?,
                // Labels travel beside the samples, so they do not count as a second candidate.
                None => match members.iter().find(|m| m.key == "samples") {
                    Some(m) => m,
                    None => match members.iter().filter(|m| m.key != "labels").collect::<Vec<_>>().as_slice() {
                        [only] => only,
                        [] if members.is_empty() => return Err(NpzError::new(path, "the archive holds no arrays")),
                        [] => {
                            return Err(NpzError::new(path, "the archive holds only 'labels'; no samples beside them"));
                        }
                        _ => {
                            return Err(NpzError::new(
                                path,
                                format!(
                                    "the archive holds {} and none is named 'samples'; choose one by key (CLI: \
                                     --key), or, for trajectories, name the arrays 'observations' and 'actions' \
                                     (D4RL's keys)",
                                    list_keys(&members)
                                ),
                            ));
                        }
                    },
                },
            };
            let header = member_header(path, &mut archive, member)?;
            // A `labels` array beside the samples travels with them (class-conditional training).
            let labels = match members.iter().find(|m| m.key == "labels" && m.index != member.index) {
                Some(m) => Some(labels_entry(path, &mut archive, m)?),
                None => None,
            };
            let sent = |m: &&Member| m.index != member.index && (labels.is_none() || m.key != "labels");
            let ignored = members.iter().filter(sent).map(|m| m.key.clone()).collect();
            (Entry::as_stored(member.key.clone(), Some(member.index), header), ignored, Some(archive), labels)
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
    let rows = stored.shape[0];
    let mut source = NpzSource::new(path, DatasetKind::Samples, ignored, archive);
    source.push("samples", dtype, stored.shape, entry);
    if let Some((dtype, shape, labels)) = labels {
        if shape != [rows] {
            return Err(NpzError::new(
                path,
                format!("'labels' has shape {shape:?}; expected [{rows}] (one per sample)"),
            ));
        }
        source.push("labels", dtype, shape, labels);
    }
    Ok(source)
}

/// Class labels `[N]` beside the samples: integers >= 0, sent as stored when int32, int64 or
/// uint8 (little-endian), else as int64 (the Python package's rule); the server checks their
/// range and row count.
fn labels_entry(path: &Path, archive: &mut Archive, member: &Member) -> Result<(Dtype, Vec<u64>, Entry)> {
    let (header, values) = member_values(path, archive, member)?;
    if !matches!(header.element.kind, Kind::Int | Kind::Uint | Kind::Bool) {
        return Err(NpzError::new(
            path,
            format!("'labels' has dtype {}; class labels must be integers", header.element),
        ));
    }
    if let Some(min) = values.iter().copied().reduce(f64::min).filter(|&m| m < 0.0) {
        return Err(NpzError::new(path, format!("'labels' hold {min}; class labels must be >= 0")));
    }
    let shape = header.shape.clone();
    Ok(match header.wire_dtype() {
        Some(dtype @ (Dtype::Int32 | Dtype::Int64 | Dtype::Uint8)) => {
            (dtype, shape, Entry::as_stored("labels".into(), Some(member.index), header))
        }
        _ => {
            let bytes = values.iter().flat_map(|&v| (v as i64).to_le_bytes()).collect();
            (Dtype::Int64, shape, Entry::in_memory("labels".into(), bytes))
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz::test_files::{UploadSource, f32_bytes, f64_bytes, npy, read_all, scratch, spec, write_npz};
    use crate::npz::{detect_kind, npz_keys};

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

        // 'samples' by default, another by key; 'labels' travel with them, the rest are ignored.
        let path = dir.path().join("many.npz");
        let other = f64_bytes(&[1.0, 2.0]);
        let labels: Vec<u8> = (0..12i64).flat_map(|l| (l % 3).to_le_bytes()).collect();
        write_npz(
            &path,
            &[
                ("labels", npy("<i8", false, &[12], &labels)),
                ("samples", npy("<f4", false, &[12, 2], &bytes)),
                ("other", npy("<f8", false, &[1, 2], &other)),
            ],
            false,
        );
        assert_eq!(detect_kind(&path).expect("kind"), DatasetKind::Samples);
        assert_eq!(npz_keys(&path).expect("keys"), ["labels", "samples", "other"]);
        let mut source = samples_from_npz_or_npy(&path, None).expect("default key");
        assert_eq!(source.arrays(), &[spec("samples", Dtype::Float32, &[12, 2]), spec("labels", Dtype::Int64, &[12])]);
        assert_eq!(source.ignored_keys(), &["other".to_owned()]);
        assert_eq!(read_all(&mut source, 1).expect("read"), labels);
        // Labels belong to every sample: a choice of another array of another row count is refused.
        let err = samples_from_npz_or_npy(&path, Some("other")).expect_err("labels of 12 for 1 sample").to_string();
        assert!(err.contains("'labels' has shape [12]; expected [1]"), "{err}");
        let err = samples_from_npz_or_npy(&path, Some("missing")).expect_err("must fail").to_string();
        assert!(err.contains("'missing'") && err.contains("'labels'"), "{err}");
        let err = samples_from_npz_or_npy(&path, Some("labels")).expect_err("must fail").to_string();
        assert!(err.contains("'labels'") && err.contains("int64"), "{err}");

        // Labels of another integer type are sent as int64 (the Python package's rule); the only
        // array besides them is the samples, whatever its name; floats or negatives are refused.
        let path = dir.path().join("latents.npz");
        let x = npy("<f4", false, &[3, 2], &bytes[..24]);
        write_npz(&path, &[("x", x.clone()), ("labels", npy(">i2", false, &[3], &[0, 1, 0, 0, 0, 2]))], false);
        let mut source = samples_from_npz_or_npy(&path, None).expect("x with labels");
        assert_eq!(source.arrays(), &[spec("samples", Dtype::Float32, &[3, 2]), spec("labels", Dtype::Int64, &[3])]);
        let want: Vec<u8> = [1i64, 0, 2].iter().flat_map(|l| l.to_le_bytes()).collect();
        assert_eq!(read_all(&mut source, 1).expect("read"), want);
        for (labels, needle) in [
            (npy("<f4", false, &[3], &f32_bytes(&[0.0, 1.0, 2.0])), "class labels must be integers"),
            (npy("<i4", false, &[3], &[0, 0, 0, 0, 255, 255, 255, 255, 1, 0, 0, 0]), "'labels' hold -1"),
        ] {
            write_npz(&path, &[("x", x.clone()), ("labels", labels)], false);
            let err = samples_from_npz_or_npy(&path, None).expect_err(needle).to_string();
            assert!(err.contains(needle), "{err}");
        }

        // Several arrays, none named samples: ambiguous.
        let path = dir.path().join("ambiguous.npz");
        write_npz(
            &path,
            &[("a", npy("<f4", false, &[2, 1], &bytes[..8])), ("b", npy("<f4", false, &[2, 1], &bytes[..8]))],
            false,
        );
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("'a', 'b'") && err.contains("key") && err.contains("'observations'"), "{err}");

        // 1-D samples are refused.
        let path = dir.path().join("flat.npy");
        std::fs::write(&path, npy("<f4", false, &[24], &bytes)).expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("[24]") && err.contains("at least 2 dimensions"), "{err}");
    }

    #[test]
    fn samples_keep_their_stored_float_type() {
        let (_dir, path) = scratch("s.npy");
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
}
