"""The episode, dict-flattening and wall rules shared with the Rust toolkit
(relreward_toolkit::episodes, docs/data-formats.md), on the same HDF5 fixtures the Rust tests
read (client/toolkit/tests/data, made by make_fixtures.py there)."""

import pathlib

import numpy as np
import pytest

from relreward import datasets
from relreward.v1 import tensor_pb2

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


# --- Values, flags, forms and Minari episodes by docs/data-formats.md (the probe of real
# gymnasium/Minari recordings: CartPole's int64 actions, 1-D and [N, a, b] arrays, float64,
# 0/1 flags, dict observations in a D4RL file, odd suffixes, empty and NaN-ended episodes).


def arrays_of(src):
    return {name: np.asarray(a) for name, a in src.arrays}


@pytest.mark.parametrize("dtype", ["<i8", ">i8", "<i4", "u1", "<f2", ">f2", "<f8", ">f8", ">f4", "<u2"])
def test_any_integer_or_float_dtype_is_read_as_float32(dtype):
    obs = np.arange(12).reshape(6, 2).astype(dtype)
    act = np.array([0, 1, 1, 0, 1, 0]).astype(dtype)  # CartPole's Discrete actions: [T] integers
    src = datasets.trajectories({"observations": obs, "actions": act})
    a = dict(src.arrays)
    assert a["observations"].dtype == np.float32 and a["actions"].dtype == np.float32
    assert a["observations"].dtype.byteorder in ("<", "=") and a["actions"].shape == (6, 1)
    np.testing.assert_array_equal(a["observations"], np.arange(12).reshape(6, 2))
    np.testing.assert_array_equal(a["actions"][:, 0], [0, 1, 1, 0, 1, 0])
    assert [s.dtype for s in src.specs()][:2] == [tensor_pb2.DTYPE_FLOAT32] * 2


def test_float64_values_are_sent_as_float32_but_samples_keep_their_dtype():
    x = np.random.default_rng(0).standard_normal((5, 3))
    a = dict(datasets.trajectories({"observations": x, "actions": x[:, :1]}).arrays)
    assert a["observations"].dtype == np.float32
    np.testing.assert_array_equal(a["observations"], x.astype(np.float32))
    # A samples dataset keeps its precision (diffusion latents are stored as given).
    assert dict(datasets.samples(x).arrays)["samples"].dtype == np.float64


def test_values_beyond_float32_or_not_finite_are_refused_naming_the_key_and_row():
    obs = np.zeros((5, 2))
    obs[3, 1] = 1e300
    with pytest.raises(ValueError, match=r"'observations' holds a value beyond float32's range at row 3"):
        datasets.trajectories({"observations": obs, "actions": np.zeros(5)})
    act = np.zeros((5, 1), np.float32)
    act[4] = np.inf
    with pytest.raises(ValueError, match=r"'actions' holds a value that is not finite at row 4"):
        datasets.trajectories({"observations": np.zeros((5, 2)), "actions": act})


@pytest.mark.parametrize("bad, message", [(np.zeros((4, 2), bool), "'observations' is bool"),
                                          (np.array(["a", "b", "c", "d"]), "'observations' has dtype <U1"),
                                          (np.float32(3), "'observations' is a scalar")])
def test_values_that_are_not_numbers_are_refused_naming_the_key(bad, message):
    with pytest.raises(ValueError, match=message):
        datasets.trajectories({"observations": bad, "actions": np.zeros(4)})


def test_1d_values_are_one_column_and_more_dimensions_are_flattened_row_major():
    obs = np.arange(24, dtype=np.float32).reshape(4, 3, 2)
    a = dict(datasets.trajectories({"observations": obs, "actions": np.arange(4)}).arrays)
    assert a["observations"].shape == (4, 6) and a["actions"].shape == (4, 1)
    np.testing.assert_array_equal(a["observations"], obs.reshape(4, 6))


def test_hdf5_values_are_converted_lazily_by_row_ranges(tmp_path):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "d.hdf5"
    obs = np.arange(60, dtype=">f8").reshape(10, 3, 2)
    with h5py.File(path, "w") as f:
        f["observations"] = obs
        f["actions"] = np.arange(10, dtype=np.int64)  # [N] integers
        f["terminals"] = np.eye(1, 10, 9, dtype=np.int64)[0]
    src, closer = datasets.source_of(path)
    try:
        o = dict(src.arrays)["observations"]
        assert not isinstance(o, np.ndarray) and o.shape == (10, 6) and o.dtype == np.float32
        chunks = list(datasets.row_chunks(o, 3 * 6 * 4))
        assert [c.shape for c in chunks] == [(3, 6), (3, 6), (3, 6), (1, 6)]
        assert all(c.dtype == np.dtype("<f4") and c.flags.c_contiguous for c in chunks)
        np.testing.assert_array_equal(np.concatenate(chunks), obs.reshape(10, 6))
        np.testing.assert_array_equal(o[-1], obs[-1].reshape(6))
        a = arrays_of(src)
        assert a["actions"].shape == (10, 1) and a["terminals"].dtype == bool
        assert src.total_bytes() == 10 * 6 * 4 + 10 * 4 + 10
    finally:
        closer.close()


def test_a_non_finite_hdf5_value_is_refused_when_read_naming_the_key_and_row(tmp_path):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "d.h5"
    obs = np.zeros((8, 2))
    obs[6, 0] = np.nan
    with h5py.File(path, "w") as f:
        f["observations"] = obs
        f["actions"] = np.zeros((8, 1), np.float32)
    src, closer = datasets.source_of(path)
    try:
        o = dict(src.arrays)["observations"]
        chunks = datasets.row_chunks(o, 2 * 2 * 4)
        assert [next(chunks).shape for _ in range(3)] == [(2, 2)] * 3  # rows 0..5 read fine
        with pytest.raises(ValueError, match=r"'observations' holds a value that is not finite at row 6"):
            next(chunks)
    finally:
        closer.close()


@pytest.mark.parametrize("flags", [np.array([0, 0, 1, 0]), np.array([0, 0, 1, 0], np.uint8),
                                   np.array([0.0, 0.0, 1.0, 0.0], np.float32), np.array([0, 0, 1, 0], ">i2"),
                                   np.array([False, False, True, False])])
def test_flags_are_bool_or_numbers_that_are_all_0_or_1(flags):
    obs = np.zeros((4, 1), np.float32)
    a = dict(datasets.trajectories({"observations": obs, "actions": obs, "terminals": flags,
                                    "truncations": flags}).arrays)
    for name in ("terminals", "timeouts"):
        assert a[name].dtype == bool
        np.testing.assert_array_equal(a[name], [False, False, True, False])


@pytest.mark.parametrize("key, flags, message", [
    ("terminals", np.array([0, 1, 0, 2, 1]), r"'terminals' holds 2 at row 3"),
    ("timeouts", np.array([0, 0, 0.5, 1, 0], np.float32), r"'timeouts' holds 0.5 at row 2"),
    ("terminations", np.array([0, 0, 0, 0, np.nan]), r"'terminations' \(sent as 'terminals'\) holds nan at row 4"),
    ("truncations", np.array([0, -1, 0, 0, 0], np.int8), r"'truncations' \(sent as 'timeouts'\) holds -1 at row 1"),
    ("terminals", np.array(["0", "1", "0", "0", "0"]), r"'terminals' has dtype <U1"),
])
def test_flags_with_other_values_are_refused_naming_the_key_and_first_row(key, flags, message):
    obs = np.zeros((5, 1), np.float32)
    with pytest.raises(ValueError, match=message):
        datasets.trajectories({"observations": obs, "actions": obs, key: flags})


def test_a_d4rl_hdf5_with_dict_observations_is_refused_as_the_rust_reader_does(tmp_path):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "maze.hdf5"
    with h5py.File(path, "w") as f:
        for k in ("achieved_goal", "desired_goal", "observation"):
            f[f"observations/{k}"] = np.zeros((6, 2), np.float32)
        f["actions"] = np.zeros((6, 2), np.float32)
        f["rewards"] = np.zeros(6, np.float32)
        f["terminals"] = np.zeros(6, bool)
        f["timeouts"] = np.zeros(6, bool)
    expected = (f"{path}: no 'observations' dataset at the top level (it holds 'actions', 'rewards', 'terminals', "
                "'timeouts', group 'observations')")
    with pytest.raises(ValueError) as e:
        datasets.source_of(path)
    assert str(e.value) == expected
    with pytest.raises(ValueError, match="'observations' is a dict"):  # the same in a Python dict
        datasets.trajectories({"observations": {"a": np.zeros((6, 2))}, "actions": np.zeros((6, 2))})


def write_d4rl(path, h5py):
    with h5py.File(path, "w") as f:
        f["observations"] = np.arange(8, dtype=np.float32).reshape(4, 2)
        f["actions"] = np.zeros((4, 1), np.float32)


def test_a_file_is_read_by_its_signature_not_its_suffix(tmp_path):
    h5py = pytest.importorskip("h5py")
    write_d4rl(tmp_path / "data.hdf", h5py)
    np.savez(tmp_path / "traj.bin", observations=np.zeros((3, 2), np.float32), actions=np.zeros((3, 1), np.float32))
    (tmp_path / "traj.bin.npz").rename(tmp_path / "traj.dat")  # np.savez appends .npz
    np.save(tmp_path / "lat.npy", np.zeros((5, 2, 2), np.float32))
    (tmp_path / "lat.npy").rename(tmp_path / "lat.hdf5")
    src, closer = datasets.source_of(tmp_path / "data.hdf")
    closer.close()
    assert src.kind == datasets.TRAJECTORIES and src.arrays[0][1].shape == (4, 2)
    src, closer = datasets.source_of(tmp_path / "traj.dat")
    closer.close()
    assert src.kind == datasets.TRAJECTORIES and src.arrays[0][1].shape == (3, 2)
    src, closer = datasets.source_of(tmp_path / "lat.hdf5")
    assert closer is None and src.kind == datasets.SAMPLES and src.arrays[0][1].shape == (5, 2, 2)
    (tmp_path / "notes.npz").write_text("observations,actions\n1,2\n")
    with pytest.raises(ValueError) as e:
        datasets.source_of(tmp_path / "notes.npz")
    message = str(e.value)
    assert message.startswith(f"{tmp_path / 'notes.npz'}: ")
    assert all(form in message for form in ("HDF5", ".npz", ".npy", "Minari"))
    (tmp_path / "empty").write_bytes(b"")
    with pytest.raises(ValueError, match="not HDF5, .npz or .npy"):
        datasets.source_of(tmp_path / "empty")


def minari_file(path, h5py, episodes):
    """episodes: {id: (observations, actions, terminations, truncations)}."""
    with h5py.File(path, "w") as f:
        for i, (o, a, te, tr) in episodes.items():
            g = f.create_group(f"episode_{i}")
            g["observations"], g["actions"], g["terminations"], g["truncations"] = o, a, te, tr


def test_minari_empty_episodes_are_skipped(tmp_path):
    h5py = pytest.importorskip("h5py")

    def ep(t, base):
        o = base + np.arange(2 * (t + 1), dtype=np.float32).reshape(t + 1, 2)
        return o, np.arange(t, dtype=np.int64), np.zeros(t, bool), np.eye(1, t, t - 1, dtype=np.uint8)[0]

    empty = (np.full((1, 2), 7, np.float32), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, bool))
    minari_file(tmp_path / "main_data.hdf5", h5py, {0: ep(3, 0), 2: ep(5, 100), 5: empty, 10: ep(7, 200)})
    a = arrays_of(datasets.source_of(tmp_path / "main_data.hdf5")[0])
    assert a["observations"].shape == (15, 2) and a["actions"].shape == (15, 1)
    np.testing.assert_array_equal(np.flatnonzero(a["episode_starts"]), [0, 3, 8])
    np.testing.assert_array_equal(np.flatnonzero(a["timeouts"]), [2, 7, 14])
    np.testing.assert_array_equal(a["observations"][8], [200, 201])
    flat = datasets.from_minari_episodes([dict(zip(("observations", "actions", "terminations", "truncations"), e))
                                          for e in (empty, ep(2, 0), empty)])
    assert flat["observations"].shape == (2, 2) and flat["episode_starts"].tolist() == [True, False]
    with pytest.raises(ValueError, match="every episode is empty"):
        datasets.from_minari_episodes([dict(zip(("observations", "actions", "terminations", "truncations"), empty))])


def test_minari_last_observation_is_dropped_before_the_finite_check(tmp_path):
    h5py = pytest.importorskip("h5py")
    o = np.arange(10, dtype=np.float64).reshape(5, 2)
    o[4] = np.nan  # the state after the last action: dropped, so it does not matter
    flags = np.zeros(4, bool)
    minari_file(tmp_path / "ok.hdf5", h5py, {0: (o, np.zeros((4, 1)), flags, flags)})
    a = arrays_of(datasets.source_of(tmp_path / "ok.hdf5")[0])
    np.testing.assert_array_equal(a["observations"], np.arange(8).reshape(4, 2))
    assert a["observations"].dtype == np.float32
    flat = datasets.from_minari_episodes([{"observations": o, "actions": np.zeros(4), "terminations": flags,
                                           "truncations": flags}])
    assert np.isfinite(flat["observations"]).all() and flat["observations"].shape == (4, 2)
    bad = o.copy()
    bad[2, 1] = np.inf  # a kept row
    minari_file(tmp_path / "bad.hdf5", h5py, {0: (o, np.zeros(4), flags, flags), 3: (bad, np.zeros(4), flags, flags)})
    with pytest.raises(ValueError, match=r"'episode_3/observations' holds a value that is not finite at row 2"):
        datasets.source_of(tmp_path / "bad.hdf5")


def test_minari_integer_and_float16_values_and_flag_values(tmp_path):
    h5py = pytest.importorskip("h5py")
    t = 4
    o = np.arange(2 * (t + 1) * 3, dtype=np.uint8).reshape(t + 1, 2, 3)  # [T+1, 2, 3]: flattened to 6
    ep = {"observations": o, "actions": np.array([1, 0, 1, 1], np.int64),
          "terminations": np.array([0, 0, 0, 1], np.int64), "truncations": np.zeros(t, np.float16)}
    flat = datasets.from_minari_episodes([ep])
    assert flat["observations"].dtype == np.float32 and flat["observations"].shape == (t, 6)
    np.testing.assert_array_equal(flat["observations"], o[:t].reshape(t, 6))
    assert flat["actions"].shape == (t, 1) and flat["terminals"].tolist() == [False, False, False, True]
    minari_file(tmp_path / "f16.hdf5", h5py, {0: (o.astype(np.float16), ep["actions"], ep["terminations"],
                                                  ep["truncations"])})
    a = arrays_of(datasets.source_of(tmp_path / "f16.hdf5")[0])
    np.testing.assert_array_equal(a["observations"], o[:t].reshape(t, 6))
    ep["terminations"] = np.array([0, 3, 0, 1])
    with pytest.raises(ValueError, match=r"'episode\[0\]/terminations' holds 3 at row 1"):
        datasets.from_minari_episodes([ep])
    minari_file(tmp_path / "bad_flags.hdf5", h5py, {0: (o, ep["actions"], np.zeros(t, bool), np.array([0, 0, 2, 0]))})
    with pytest.raises(ValueError, match=r"'episode_0/truncations' holds 2 at row 2"):
        datasets.source_of(tmp_path / "bad_flags.hdf5")


# Issue 34, items 1 and 6: a root member the Minari reader does not take is refused by name (the
# Rust reader's rule, tests/minari_root.rs there), never left out of the upload without a word.
@pytest.mark.parametrize(
    "fixture, message",
    [
        ("minari_bad_group.hdf5", r"group 'episode_abc' that is not an episode group 'episode_<id>'"),
        ("minari_dup_id.hdf5", r"'episode_01' and 'episode_1' are both episode 1"),
    ],
)
def test_minari_root_members_not_taken_are_refused(fixture, message):
    pytest.importorskip("h5py")
    with pytest.raises(ValueError, match=message):
        datasets.source_of(DATA / "rules" / fixture)


def test_a_directory_that_is_not_a_minari_dataset_says_what_it_holds(tmp_path):
    (tmp_path / "data" / "main_data.hdf5").mkdir(parents=True)
    with pytest.raises(ValueError, match="main_data.hdf5: is a directory, not Minari's main_data.hdf5 file"):
        datasets.source_of(tmp_path)
    looped = tmp_path / "looped"
    looped.mkdir()
    (looped / "main_data.hdf5").symlink_to(looped / "main_data.hdf5")
    with pytest.raises(ValueError, match="symlink loop"):
        datasets.source_of(looped)
