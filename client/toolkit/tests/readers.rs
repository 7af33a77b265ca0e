//! The HDF5 readers on the fixtures of `tests/data` (made by `tests/data/make_fixtures.py`
//! with h5py; values are formulas of the row index, checked here), and the `.npz` reader's
//! index-style episode boundaries and wall keys.
#![cfg(feature = "hdf5")]

use std::path::{Path, PathBuf};

use relreward_client::UploadSource;
use relreward_toolkit::hdf5::{is_hdf5, read_hdf5};
use relreward_toolkit::npz::{trajectories_from_npz, walls_from_npz};
use relreward_toolkit::npz_write::NpzWriter;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data").join(name)
}

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

#[test]
fn big_endian_values_and_index_style_starts() {
    let t = read_hdf5(&data("big_endian.hdf5")).expect("big endian");
    assert_eq!(t.observations, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    assert_eq!(t.actions, [0.0, 1.0, 2.0]);
    assert_eq!(t.episode_starts, [true, false, true]);
}

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

trait Positions {
    fn positions(self) -> Vec<usize>;
}

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
