//! Which arrays of an `.npz` make a trajectory dataset, by the rules every reader shares
//! ([`crate::values`], [`crate::episodes`]): `observations` and `actions` sent as float32 rows,
//! episode flags (D4RL or Minari names) sent as bool, explicit episode boundaries sent as
//! per-row `episode_starts`; [`detect_kind`], the rule that tells trajectories from samples; and
//! the maze walls a dataset file may hold ([`walls_from_npz`]).

use std::io;
use std::path::Path;

use relreward_proto::v1::{DatasetKind, Dtype};

use super::archive::{
    Archive, FileFormat, Member, list_keys, member_header, member_values, open_archive, read_numbers, sniff,
};
use super::error::{NpzError, Result, describe_key};
use super::source::{Entry, NpzSource};
use crate::values::Kind;

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
    let mut source = NpzSource::new(path, DatasetKind::Trajectories, ignored, None);
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
    source.set_archive(archive);
    Ok(source)
}

/// The file's explicit episode starts (`episode_starts` as flags or indices, `episode_lengths`)
/// as per-row flags by the rules of [`crate::episodes`], with the key they came from.
fn episode_boundaries(
    path: &Path,
    archive: &mut Archive,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz::test_files::{
        UploadSource, d4rl_entries, encode, f32_bytes, f64_bytes, npy, read_all, scratch, sent_f32, spec,
        trajectories_error, write_npz,
    };

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
    fn minari_names_are_sent_as_d4rl_names() {
        let (dir, path) = scratch("minari.npz");
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
        let err = trajectories_error(&path, &entries);
        assert!(err.contains("'terminals'") && err.contains("'terminations'"), "{err}");
    }

    #[test]
    fn rows_are_one_value_per_row_for_1d_and_flattened_row_major_beyond_2d() {
        let (_dir, path) = scratch("t.npz");
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
        let err = trajectories_error(
            &path,
            &[("observations", npy("<f4", false, &[], &[0; 4])), ("actions", npy("<f4", false, &[1], &[0; 4]))],
        );
        assert!(err.contains("'observations' is a scalar"), "{err}");
    }

    #[test]
    fn flags_of_any_number_type_holding_only_0_and_1_are_sent_as_bool() {
        let (_dir, path) = scratch("t.npz");
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
            let err = trajectories_error(&path, &entries);
            assert!(err.contains(want), "{descr}: {err}");
        }
    }

    #[test]
    fn no_rows_is_refused_by_name() {
        let (_dir, path) = scratch("t.npz");
        let err = trajectories_error(
            &path,
            &[("observations", npy("<f4", false, &[0, 3], &[])), ("actions", npy("<f4", false, &[0, 1], &[]))],
        );
        assert!(err.contains("'observations' has no rows (N = 0)"), "{err}");
    }

    #[test]
    fn missing_and_misshapen_trajectory_arrays() {
        let (dir, path) = scratch("t.npz");
        let err = trajectories_error(&path, &[("actions", npy("<f4", false, &[2, 1], &[0; 8]))]);
        assert!(err.contains("no 'observations' array") && err.contains("'actions'"), "{err}");
        assert_eq!(detect_kind(&path).expect("kind"), DatasetKind::Samples);

        let err = trajectories_error(&path, &[("observations", npy("<f4", false, &[2, 1], &[0; 8]))]);
        assert!(err.contains("no 'actions' array"), "{err}");

        // Mismatched N names both arrays and both shapes.
        let err = trajectories_error(
            &path,
            &[("observations", npy("<f4", false, &[3, 2], &[0; 24])), ("actions", npy("<f4", false, &[2, 1], &[0; 8]))],
        );
        assert!(err.contains("'actions' has shape [2, 1]") && err.contains("'observations' has shape [3, 2]"), "{err}");
        let err = trajectories_error(
            &path,
            &[
                ("observations", npy("<f4", false, &[3, 2], &[0; 24])),
                ("actions", npy("<f4", false, &[3, 1], &[0; 12])),
                ("truncations", npy("|b1", false, &[4], &[0; 4])),
            ],
        );
        assert!(err.contains("'truncations' (sent as 'timeouts') has shape [4]"), "{err}");

        // Flags of shape [N, 1].
        let err = trajectories_error(
            &path,
            &[
                ("observations", npy("<f4", false, &[1, 1], &[0; 4])),
                ("actions", npy("<f4", false, &[1, 1], &[0; 4])),
                ("terminals", npy("|b1", false, &[1, 1], &[0])),
            ],
        );
        assert!(err.contains("'terminals' has shape [1, 1]") && err.contains("1-D [N]"), "{err}");

        // A single .npy cannot be trajectories.
        let npy_path = dir.path().join("obs.npy");
        std::fs::write(&npy_path, npy("<f4", false, &[1, 1], &[0; 4])).expect("write");
        assert!(trajectories_from_npz(&npy_path).is_err());
    }
}
