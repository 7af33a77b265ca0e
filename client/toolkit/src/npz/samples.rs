//! A samples dataset: one float array `[N, ...]` of an `.npy` file or an `.npz` archive (chosen
//! by key, by the name `samples`, or as the only array), sent as stored under the name
//! `samples`, so only little-endian (or byte-order-free) float32 and float64 are taken.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use relreward_proto::v1::{DatasetKind, Dtype};

use super::archive::{FileFormat, check_complete, list_keys, member_header, open_archive, sniff};
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
    let mut source = NpzSource::new(path, DatasetKind::Samples, ignored, archive);
    source.push("samples", dtype, stored.shape, entry);
    Ok(source)
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
