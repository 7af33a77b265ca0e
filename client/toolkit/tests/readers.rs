//! The HDF5 readers on the fixtures of `tests/data` (made by `tests/data/make_fixtures.py`
//! with h5py; values are formulas of the row index, checked here), the `.npz` reader's
//! index-style episode boundaries and wall keys, and the value rules of `docs/data-formats.md`
//! on the pairs of `tests/data/rules` (the same arrays as `.npz` and as HDF5: both readers must
//! send the same dataset, or refuse with the same words). The HDF5 tests need the `hdf5`
//! feature (`cargo test -p relreward-toolkit --features hdf5`).

use std::path::Path;
#[cfg(feature = "hdf5")]
use std::path::PathBuf;

use relreward_client::UploadSource;
#[cfg(feature = "hdf5")]
use relreward_client::client::payload_sha256;
#[cfg(feature = "hdf5")]
use relreward_toolkit::hdf5::{is_hdf5, read_hdf5};
use relreward_toolkit::npz::{trajectories_from_npz, walls_from_npz};
use relreward_toolkit::npz_write::NpzWriter;
#[cfg(feature = "hdf5")]
use relreward_toolkit::trajectories::Trajectories;

#[cfg(feature = "hdf5")]
fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data").join(name)
}

#[cfg(feature = "hdf5")]
#[test]
fn d4rl_layout_with_gzip_chunks_flags_and_wall_map() {
    let path = data("d4rl.hdf5");
    assert!(is_hdf5(&path));
    let t = read_hdf5(&path).expect("d4rl");
    assert_eq!((t.len(), t.obs_dim, t.act_dim), (12, 4, 2));
    for r in 0..12 {
        for c in 0..4 {
            assert_eq!(t.observations[r * 4 + c], (10 * r + c) as f32);
        }
        for c in 0..2 {
            assert!((t.actions[r * 2 + c] - -(r as f32 + c as f32 / 10.0)).abs() < 1e-6);
        }
    }
    assert_eq!(t.terminals.iter().positions(), vec![4]);
    assert_eq!(t.timeouts.iter().positions(), vec![7, 11]);
    assert!(t.episode_starts.is_empty());
    assert_eq!(t.episodes(), vec![0..5, 5..8, 8..12]);
    let (rows, cols, walls) = t.walls.clone().expect("wall_map");
    assert_eq!((rows, cols), (3, 4));
    assert_eq!(walls.iter().filter(|w| !**w).count(), 2);
    assert!(t.ignored.contains(&"rewards".to_owned()) && t.ignored.contains(&"infos/".to_owned()), "{:?}", t.ignored);
}

#[cfg(feature = "hdf5")]
#[test]
fn minari_layout_orders_episodes_by_id_and_flattens_dict_observations() {
    for path in [data("minari"), data("minari/data/main_data.hdf5")] {
        let t = read_hdf5(&path).expect("minari");
        // Episodes 0, 1, 10 (not 0, 10, 1) of 3, 2 and 4 steps; the last observation dropped.
        assert_eq!((t.len(), t.obs_dim, t.act_dim), (9, 8, 2));
        assert_eq!(t.episode_starts.iter().positions(), vec![0, 3, 5]);
        let episode_of_row = [0, 0, 0, 1, 1, 10, 10, 10, 10];
        let step_of_row = [0, 1, 2, 0, 1, 0, 1, 2, 3];
        for r in 0..9 {
            let (ep, k) = (episode_of_row[r] as f32, step_of_row[r] as f32);
            let row = &t.observations[r * 8..r * 8 + 8];
            let base = 100.0 * ep + 10.0 * k;
            // Sorted keys: achieved_goal (2), desired_goal (2), observation (4).
            assert_eq!(row, [base, base + 1.0, base, base + 1.0, base, base + 1.0, base + 2.0, base + 3.0], "row {r}");
            assert!((t.actions[r * 2] - (ep + k / 10.0)).abs() < 1e-6);
        }
        assert_eq!(t.terminals.iter().positions(), vec![4]);
        assert_eq!(t.timeouts.iter().positions(), vec![2, 8]);
        assert_eq!(t.episodes(), vec![0..3, 3..5, 5..9]);
    }
}

#[cfg(feature = "hdf5")]
#[test]
fn big_endian_values_and_index_style_starts() {
    let t = read_hdf5(&data("big_endian.hdf5")).expect("big endian");
    assert_eq!(t.observations, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    assert_eq!(t.actions, [0.0, 1.0, 2.0]);
    assert_eq!(t.episode_starts, [true, false, true]);
}

#[cfg(feature = "hdf5")]
#[test]
fn not_hdf5_and_missing_keys_are_named() {
    let dir = tempfile::tempdir().expect("tmp");
    let junk = dir.path().join("junk.hdf5");
    std::fs::write(&junk, b"not hdf5 at all").expect("write");
    assert!(!is_hdf5(&junk));
    assert!(read_hdf5(&junk).is_err());
    let err = read_hdf5(dir.path()).expect_err("no main_data").to_string();
    assert!(err.contains("main_data.hdf5"), "{err}");
}

#[cfg(feature = "hdf5")]
trait Positions {
    fn positions(self) -> Vec<usize>;
}

#[cfg(feature = "hdf5")]
impl<'a, I: Iterator<Item = &'a bool>> Positions for I {
    fn positions(self) -> Vec<usize> {
        self.enumerate().filter(|(_, b)| **b).map(|(i, _)| i).collect()
    }
}

fn npz_with(path: &Path, extra: impl FnOnce(&mut NpzWriter)) {
    let mut w = NpzWriter::create(path).expect("create");
    w.add_f32("observations", &[6, 1], &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]).expect("obs");
    w.add_f32("actions", &[6, 1], &[0.0; 6]).expect("act");
    w.add_bool("terminals", &[6], &[false; 6]).expect("terminals");
    w.add_bool("timeouts", &[6], &[false, false, false, false, false, true]).expect("timeouts");
    extra(&mut w);
    w.finish().expect("finish");
}

/// Reads the `episode_starts` the npz reader would send.
fn sent_starts(path: &Path) -> Vec<bool> {
    let mut source = trajectories_from_npz(path).expect("read");
    let index = source.arrays().iter().position(|s| s.name == "episode_starts").expect("episode_starts sent");
    let mut bytes = Vec::new();
    std::io::Read::read_to_end(&mut source.open(index).expect("open"), &mut bytes).expect("bytes");
    bytes.iter().map(|&b| b != 0).collect()
}

#[test]
fn npz_integer_episode_starts_beside_flags_are_indices() {
    // The file: integer start indices beside terminals and timeouts.
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("idx.npz");
    npz_with(&path, |w| w.add_i64("episode_starts", &[2], &[0, 4]).expect("starts"));
    assert_eq!(sent_starts(&path), [true, false, false, false, true, false]);
    let lengths = dir.path().join("len.npz");
    npz_with(&lengths, |w| w.add_i64("episode_lengths", &[3], &[1, 2, 3]).expect("lengths"));
    assert_eq!(sent_starts(&lengths), [true, true, false, true, false, false]);
    let bad = dir.path().join("bad.npz");
    npz_with(&bad, |w| w.add_i64("episode_lengths", &[2], &[1, 2]).expect("lengths"));
    let err = trajectories_from_npz(&bad).expect_err("short").to_string();
    assert!(err.contains("'episode_lengths'"), "{err}");
}

#[test]
fn npz_walls_from_any_known_key() {
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("walls.npz");
    npz_with(&path, |w| w.add_i64("maze_map", &[2, 2], &[1, 0, 0, 1]).expect("maze_map"));
    assert_eq!(walls_from_npz(&path).expect("read"), Some((2, 2, vec![true, false, false, true])));
    let source = trajectories_from_npz(&path).expect("read");
    assert!(source.ignored_keys().contains(&"maze_map".to_owned()));
}

#[cfg(feature = "hdf5")]
fn rules(name: &str) -> PathBuf {
    data("rules").join(name)
}

/// The error both readers give for `rules/NAME.{npz,hdf5}`: (npz, hdf5). An `.npz` is read
/// lazily, so its values are checked when they are read for sending (the digest reads them).
#[cfg(feature = "hdf5")]
fn both_errors(name: &str) -> (String, String) {
    let npz = match trajectories_from_npz(rules(&format!("{name}.npz"))) {
        Err(e) => e.to_string(),
        Ok(mut source) => payload_sha256(&mut source).expect_err("npz values refused").to_string(),
    };
    let hdf5 = read_hdf5(&rules(&format!("{name}.hdf5"))).expect_err("hdf5 refused").to_string();
    (npz, hdf5)
}

/// Items 1, 2, 4 and 10 of the reader probe: integer, big-endian, float16 and float64 values,
/// 1-D and 3-D arrays, integer and float 0/1 flags: both readers send the same bytes.
#[cfg(feature = "hdf5")]
#[test]
fn same_arrays_send_the_same_dataset_from_npz_and_hdf5() {
    for name in ["types", "f64"] {
        let h = read_hdf5(&rules(&format!("{name}.hdf5"))).expect("hdf5");
        let mut npz = trajectories_from_npz(rules(&format!("{name}.npz"))).expect("npz");
        let n = Trajectories::from_npz(&rules(&format!("{name}.npz"))).expect("npz whole");
        assert_eq!(
            (&n.observations, n.obs_dim, &n.actions, n.act_dim, &n.terminals, &n.timeouts),
            (&h.observations, h.obs_dim, &h.actions, h.act_dim, &h.terminals, &h.timeouts),
            "{name}"
        );
        assert_eq!(npz.arrays(), h.upload_source().arrays(), "{name}");
        assert_eq!(
            payload_sha256(&mut npz).expect("npz digest"),
            payload_sha256(&mut h.upload_source()).expect("hdf5 digest"),
            "{name}: the stored dataset must not depend on the file format"
        );
    }
    // types: big-endian int16 [5, 2, 2] flattened row-major, float16 [5] as [5, 1], int64 and
    // float32 flags.
    let t = read_hdf5(&rules("types.hdf5")).expect("types");
    assert_eq!((t.len(), t.obs_dim, t.act_dim), (5, 4, 1));
    for r in 0..5 {
        assert_eq!(&t.observations[r * 4..r * 4 + 4], [0, 1, 2, 3].map(|c| (10 * r + c) as f32), "row {r}");
        assert_eq!(t.actions[r], r as f32 / 2.0 - 1.0);
    }
    assert_eq!(t.terminals.iter().positions(), vec![2]);
    assert_eq!(t.timeouts.iter().positions(), vec![4]);
    // f64: rounded to float32 (not kept as float64 by either reader), uint64 actions.
    let t = read_hdf5(&rules("f64.hdf5")).expect("f64");
    let want: Vec<f32> = (0..6).map(|i| (0.1 * f64::from(i)) as f32).collect();
    assert_eq!(t.observations, want);
    assert_eq!(t.actions, [0.0, 1.0, 2.0]);
    let mut source = trajectories_from_npz(rules("f64.npz")).expect("npz");
    assert!(source.arrays()[..2].iter().all(|s| s.dtype == relreward_client::pb::Dtype::Float32 as i32));
    let mut bytes = Vec::new();
    std::io::Read::read_to_end(&mut source.open(0).expect("open"), &mut bytes).expect("read");
    assert_eq!(bytes, want.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>());
}

/// Item 3: flags other than 0/1 are refused by both, naming the key, the row and the value.
#[cfg(feature = "hdf5")]
#[test]
fn flags_other_than_0_and_1_are_refused_alike() {
    let (npz, hdf5) = both_errors("bad_flag");
    for err in [npz, hdf5] {
        assert!(err.contains("'terminals' holds 2 at row 2"), "{err}");
    }
}

/// Item 8: no rows is refused by both, naming 'observations' and N = 0.
#[cfg(feature = "hdf5")]
#[test]
fn no_rows_is_refused_alike() {
    let (npz, hdf5) = both_errors("empty");
    for err in [npz, hdf5] {
        assert!(err.contains("'observations' has no rows (N = 0)"), "{err}");
    }
}

/// Item 7: a non-finite value is placed by row and coordinate (flattened beyond 2-D).
#[cfg(feature = "hdf5")]
#[test]
fn non_finite_values_are_placed_by_row_and_coordinate_alike() {
    for (name, want) in [
        ("nan", "'observations': value NaN at row 2, coordinate 1 is not finite"),
        ("nan_3d", "'observations': value inf at row 1, flattened coordinate 2 of [2, 2] is not finite"),
    ] {
        let (npz, hdf5) = both_errors(name);
        for err in [npz, hdf5] {
            assert!(err.contains(want), "{name}: {err}");
            assert!(!err.contains("element"), "{name}: {err}");
        }
    }
}

/// Items 5 and 6: an episode of zero steps is skipped (and said so), and a NaN in the last
/// observation of an episode, which is dropped, is not refused; uint8 and float64 0/1 flags.
#[cfg(feature = "hdf5")]
#[test]
fn minari_skips_empty_episodes_and_checks_only_the_rows_kept() {
    let t = read_hdf5(&rules("minari_edge.hdf5")).expect("minari");
    assert_eq!((t.len(), t.obs_dim, t.act_dim), (5, 2, 1));
    let firsts: Vec<f32> = t.observations.iter().step_by(2).copied().collect();
    assert_eq!(firsts, [0.0, 1.0, 2.0, 70.0, 71.0]);
    assert!(t.observations.iter().all(|v| v.is_finite()));
    assert_eq!(t.actions, [0.0, 1.0, 2.0, 0.0, 1.0]);
    assert_eq!(t.episode_starts.iter().positions(), vec![0, 3]);
    assert_eq!(t.terminals.iter().positions(), vec![4]);
    assert_eq!(t.timeouts.iter().positions(), vec![2]);
    assert_eq!(t.episodes(), vec![0..3, 3..5]);
    assert!(t.notes.iter().any(|n| n.contains("'episode_5'") && n.contains("empty")), "{:?}", t.notes);
}

/// Item 4: a type no reader decodes is described in words, naming the key.
#[cfg(feature = "hdf5")]
#[test]
fn unsupported_hdf5_types_are_named_in_words() {
    let err = read_hdf5(&rules("f128.hdf5")).expect_err("16-byte float").to_string();
    assert!(err.contains("'observations' holds a 16-byte float; expected integers, floats or bool"), "{err}");
    assert!(!err.contains("FloatingPoint"), "{err}");
}

/// A Tuple observation space, stored by Minari as parts `_index_0` .. `_index_11`, flattens by
/// the parts' numbers (gymnasium's `spaces.flatten` order), not as strings (`_index_10` before
/// `_index_2`).
#[cfg(feature = "hdf5")]
#[test]
fn minari_tuple_parts_flatten_by_their_number() {
    let t = read_hdf5(&rules("minari_tuple.hdf5")).expect("tuple");
    assert_eq!((t.len(), t.obs_dim, t.act_dim), (2, 12, 1));
    for k in 0..2 {
        let want: Vec<f32> = (0..12).map(|i| (100 * i + k) as f32).collect();
        assert_eq!(&t.observations[k * 12..(k + 1) * 12], want.as_slice(), "step {k}");
    }
}

/// Frames Minari stored JPEG-encoded are refused naming the place and the setting that made
/// them, not read as bytes; float observations under the same metadata are read as they are.
#[cfg(feature = "hdf5")]
#[test]
fn minari_jpeg_frames_are_refused_by_name() {
    let err = read_hdf5(&data("minari_jpeg")).expect_err("jpeg").to_string();
    assert!(err.contains("'episode_0/observations' is JPEG-encoded by Minari's DataCollector"), "{err}");
    assert!(err.contains("jpeg_encoding=False"), "{err}");
    let t = read_hdf5(&data("minari_jpeg_floats")).expect("floats");
    assert_eq!(t.observations, [0.0, 1.0, 2.0, 3.0]);
}
