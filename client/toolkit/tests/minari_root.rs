//! Issue 34, items 1 and 6: what the Minari reader does with a root member it does not take and
//! with a directory that is not a Minari dataset. Every such member is refused, named, rather
//! than left out of the upload without a word; a file without `rewards` or `infos` does not
//! claim to leave them out; a directory names what is wrong with it (docs/data-formats.md,
//! "Minari root"). Fixtures: `tests/data/rules/minari_*.hdf5`, made by `make_fixtures.py`.
#![cfg(feature = "hdf5")]

use std::path::{Path, PathBuf};

use relreward_toolkit::hdf5::{is_hdf5, read_hdf5};

fn rules(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/rules").join(name)
}

#[test]
fn an_episode_group_without_a_numeric_id_is_refused_by_name() {
    let err = read_hdf5(&rules("minari_bad_group.hdf5")).expect_err("episode_abc refused").to_string();
    assert!(err.contains("group 'episode_abc'") && err.contains("not an episode group 'episode_<id>'"), "{err}");
    assert!(!err.contains("episode_1'"), "only the group not taken is named: {err}");
}

#[test]
fn two_spellings_of_one_episode_id_are_refused() {
    let err = read_hdf5(&rules("minari_dup_id.hdf5")).expect_err("episode_01 beside episode_1").to_string();
    assert!(err.contains("'episode_01' and 'episode_1' are both episode 1"), "{err}");
}

#[test]
fn only_members_the_file_holds_are_listed_as_left_out() {
    // minari_edge.hdf5 holds no `rewards` and no `infos`: nothing is left out.
    let t = read_hdf5(&rules("minari_edge.hdf5")).expect("minari");
    assert!(t.ignored.is_empty(), "{:?}", t.ignored);
    // The layout fixture holds both, in every episode: each named once.
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/minari");
    let t = read_hdf5(&dir).expect("minari");
    assert_eq!(t.ignored, ["infos/", "rewards"]);
}

#[test]
fn a_directory_that_is_not_a_minari_dataset_says_what_it_holds() {
    let tmp = tempfile::tempdir().expect("tmp");
    // Any directory goes to this reader, so its message (not the OS's "Is a directory") shows.
    assert!(is_hdf5(tmp.path()));
    let err = read_hdf5(tmp.path()).expect_err("empty dir").to_string();
    assert!(err.contains("a directory without data/main_data.hdf5 (not a Minari dataset)"), "{err}");

    let data = tmp.path().join("data");
    std::fs::create_dir_all(data.join("main_data.hdf5")).expect("mkdir");
    let err = read_hdf5(tmp.path()).expect_err("main_data.hdf5 a directory").to_string();
    assert!(err.contains("main_data.hdf5: is a directory, not Minari's main_data.hdf5 file"), "{err}");

    let looped = tempfile::tempdir().expect("tmp");
    let link = looped.path().join("main_data.hdf5");
    std::os::unix::fs::symlink(&link, &link).expect("symlink loop");
    let err = read_hdf5(looped.path()).expect_err("symlink loop").to_string();
    assert!(err.contains("main_data.hdf5: cannot be opened") && err.contains("symlink loop"), "{err}");

    let err = read_hdf5(&link).expect_err("the loop itself").to_string();
    assert!(is_hdf5(&link) && err.contains("symlink loop"), "{err}");
}
