"""The episode, dict-flattening and wall rules shared with the Rust toolkit
(relreward_toolkit::episodes, docs/data-formats.md), on the same HDF5 fixtures the Rust tests
read (client/toolkit/tests/data, made by make_fixtures.py there)."""

import pathlib

import numpy as np
import pytest

from relreward import datasets

DATA = pathlib.Path(__file__).resolve().parents[2] / "toolkit" / "tests" / "data"


def starts(src):
    return dict(src.arrays).get("episode_starts")


def test_integer_starts_beside_flags_are_indices():
    obs = np.zeros((6, 1), np.float32)
    data = {
        "observations": obs,
        "actions": obs,
        "terminals": np.zeros(6, bool),
        "timeouts": np.zeros(6, bool),
        "episode_starts": np.array([0, 4]),
    }
    np.testing.assert_array_equal(starts(datasets.trajectories(data)), [1, 0, 0, 0, 1, 0])
    data["episode_starts"] = np.array([1, 0, 0, 1, 0, 0], np.int64)  # per-row 0/1: flags
    np.testing.assert_array_equal(starts(datasets.trajectories(data)), [1, 0, 0, 1, 0, 0])
    del data["episode_starts"]
    data["episode_lengths"] = np.array([1, 2, 3])
    src = datasets.trajectories(data)
    np.testing.assert_array_equal(starts(src), [1, 1, 0, 1, 0, 0])
    assert "episode_lengths" not in src.ignored


@pytest.mark.parametrize(
    "extra, message",
    [
        ({"episode_starts": np.array([0, 7])}, "'episode_starts'"),
        ({"episode_starts": np.array([0, 3, 3])}, "does not increase"),
        ({"episode_starts": np.array([0.0, 3.0])}, "float"),
        ({"episode_lengths": np.array([1, 2])}, "'episode_lengths' sum to 3"),
        ({"episode_starts": np.array([0, 2]), "episode_lengths": np.array([3, 3])}, "disagree"),
    ],
)
def test_bad_boundaries_are_refused_naming_the_key(extra, message):
    obs = np.zeros((6, 1), np.float32)
    with pytest.raises(ValueError, match=message):
        datasets.trajectories({"observations": obs, "actions": obs, **extra})


def test_walls_from_any_known_key():
    assert datasets.walls_of({"x": 1}) is None
    np.testing.assert_array_equal(datasets.walls_of({"maze_map": np.array([[1, 0]])}), [[True, False]])
    with pytest.raises(ValueError, match="'walls' and 'wall_map'"):
        datasets.walls_of({"walls": np.array([[1, 0]]), "wall_map": np.array([[0, 1]])})


def test_minari_layout_matches_the_rust_reader():
    pytest.importorskip("h5py")
    for path in (DATA / "minari", DATA / "minari" / "data" / "main_data.hdf5"):
        src, closer = datasets.source_of(path)
        assert closer is None
        a = dict(src.arrays)
        assert a["observations"].shape == (9, 8)
        np.testing.assert_array_equal(np.flatnonzero(a["episode_starts"]), [0, 3, 5])
        # Row 5 is episode 10, step 0: [achieved_goal, desired_goal, observation] sorted.
        np.testing.assert_array_equal(a["observations"][5], [1000, 1001, 1000, 1001, 1000, 1001, 1002, 1003])
        np.testing.assert_array_equal(np.flatnonzero(a["terminals"]), [4])
        np.testing.assert_array_equal(np.flatnonzero(a["timeouts"]), [2, 8])


def test_d4rl_layout_and_index_starts_in_hdf5():
    pytest.importorskip("h5py")
    src, closer = datasets.source_of(DATA / "d4rl.hdf5")
    try:
        a = dict(src.arrays)
        assert a["observations"].shape == (12, 4)
        assert "wall_map" in src.ignored and "rewards" in src.ignored
    finally:
        closer.close()
    src, closer = datasets.source_of(DATA / "big_endian.hdf5")
    try:
        np.testing.assert_array_equal(dict(src.arrays)["episode_starts"], [1, 0, 1])
    finally:
        closer.close()
