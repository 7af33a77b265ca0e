"""The episode, dict-flattening and wall rules shared with the Rust toolkit
(relreward_toolkit::episodes, docs/data-formats.md), on the same HDF5 fixtures the Rust tests
read (client/toolkit/tests/data, made by make_fixtures.py there), and the refusals both readers
must word alike, checked against the CLI's reader where it reads the file before connecting
(:func:`cli_refusal`). Minari's Tuple and JPEG layouts: test_minari_layouts.py."""

import pathlib
import subprocess
import zipfile

import numpy as np
import pytest

from relreward import datasets
from relreward.v1 import tensor_pb2

from conftest import BINARIES

DATA = pathlib.Path(__file__).resolve().parents[2] / "toolkit" / "tests" / "data"


def cli_refusal(path):
    """What the CLI's reader says of ``path`` (its ``error:`` line, without the prefix), or None
    when it reads the file: ``dataset upload`` reads a file before it connects, and nothing
    listens on port 1. Skips when the CLI binary is not built."""
    if not BINARIES.cli.is_file():
        pytest.skip(f"no CLI binary at {BINARIES.cli}")
    p = subprocess.run([str(BINARIES.cli), "dataset", "upload", str(path), "--name", "x", "--endpoint",
                        "http://127.0.0.1:1"], capture_output=True, text=True, timeout=120)
    errors = [line[len("error: "):] for line in p.stderr.splitlines() if line.startswith("error: ")]
    assert errors, p.stderr
    return None if "cannot connect" in errors[0] else errors[0]


def py_refusal(path):
    """What this package says of ``path`` (reading every value, as an upload does), or None."""
    try:
        src, closer = datasets.source_of(path)
        try:
            for _, a in src.arrays:
                for _ in datasets.row_chunks(a, 1 << 20):
                    pass
        finally:
            if closer is not None:
                closer.close()
    except ValueError as e:
        return str(e)
    return None


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
    with pytest.raises(ValueError, match=r"^'observations': value 1e300 at row 3, coordinate 1 is outside float32's "):
        datasets.trajectories({"observations": obs, "actions": np.zeros(5)})
    act = np.zeros((5, 1), np.float32)
    act[4] = np.inf
    with pytest.raises(ValueError, match=r"^'actions': value inf at row 4, coordinate 0 is not finite$"):
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
        with pytest.raises(ValueError) as e:
            next(chunks)
        assert str(e.value) == f"{path}: 'observations': value NaN at row 6, coordinate 0 is not finite"
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
    with pytest.raises(ValueError, match=r"'episode_3/observations': value inf at row 2, coordinate 1 is not finite"):
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


# --- The Rust readers' refusals, word for word (docs/data-formats.md: every reader must refuse
# the same file with the same words): 16-byte floats, values not finite as float32, no rows,
# unreadable archives, object arrays, HDF5 soft links and HDF5 files without observations.


def f128(shape):
    return np.zeros(shape, np.longdouble)


def test_a_16_byte_float_is_refused_as_the_rust_readers_refuse_it(tmp_path):
    h5py = pytest.importorskip("h5py")
    assert np.dtype(np.longdouble).itemsize == 16 and np.dtype(np.longdouble).str == "<f16"  # x86-64 Linux
    words = "is a 16-byte float, which is not supported; expected integers or floats of 1, 2, 4 or 8 bytes"
    np.savez(tmp_path / "obs.npz", observations=f128((4, 2)), actions=np.zeros(4))
    with pytest.raises(ValueError) as e:
        datasets.source_of(tmp_path / "obs.npz")
    assert str(e.value) == f"{tmp_path / 'obs.npz'}: array 'observations': dtype '<f16' {words}"
    assert cli_refusal(tmp_path / "obs.npz") == str(e.value)
    with pytest.raises(ValueError, match=r"^array 'actions': dtype '<f16' is a 16-byte float"):
        datasets.trajectories({"observations": np.zeros((4, 2)), "actions": f128(4)})
    # A flag under its Minari name is named by the file's key, as the .npy reader names it.
    with pytest.raises(ValueError, match=r"^array 'terminations': dtype '<f16' is a 16-byte float"):
        datasets.trajectories({"observations": np.zeros((4, 2)), "actions": np.zeros(4), "terminations": f128(4)})
    # HDF5: the HDF5 reader's words.
    with h5py.File(tmp_path / "obs.hdf5", "w") as f:
        f["observations"], f["actions"] = f128((4, 2)), np.zeros(4)
    with pytest.raises(ValueError) as e:
        datasets.source_of(tmp_path / "obs.hdf5")
    want = "'observations' holds a 16-byte float; expected integers, floats or bool"
    assert str(e.value) == f"{tmp_path / 'obs.hdf5'}: {want}" == cli_refusal(tmp_path / "obs.hdf5")
    minari_file(tmp_path / "main_data.hdf5", h5py, {0: (np.zeros((3, 2)), np.zeros(2), f128(2), np.zeros(2, bool))})
    with pytest.raises(ValueError, match=r"'episode_0/terminations' holds a 16-byte float; expected integers"):
        datasets.source_of(tmp_path / "main_data.hdf5")


def bad_value(shape, index, value, dtype=np.float64):
    a = np.zeros(shape, dtype)
    a[index] = value
    return a


NOT_FINITE = [
    (bad_value((20, 3), (13, 1), np.nan), "value NaN at row 13, coordinate 1 is not finite"),
    (bad_value((20, 3, 2), (13, 1, 1), np.inf), "value inf at row 13, flattened coordinate 3 of [3, 2] is not finite"),
    (bad_value(20, 5, -np.inf), "value -inf at row 5, coordinate 0 is not finite"),
    (bad_value((20, 2), (3, 1), np.inf, np.float16), "value inf at row 3, coordinate 1 is not finite"),
    (bad_value((20, 2), (7, 0), 1e300), "value 1e300 at row 7, coordinate 0 is outside float32's range (about "
                                        "3.4e38), the precision models compute in"),
    (bad_value((20, 2), (7, 1), -3.5e38, ">f8"), "value -3.5e38 at row 7, coordinate 1 is outside float32's range "
                                                 "(about 3.4e38), the precision models compute in"),
    # Just beyond float32's largest value, it rounds to an infinity: refused, as in Rust (`v as f32`).
    (bad_value((20, 2), (7, 1), 3.4028235677973366e38), "value 3.4028235677973366e38 at row 7, coordinate 1 is "
                                                         "outside float32's range (about 3.4e38), the precision "
                                                         "models compute in"),
]


@pytest.mark.parametrize("obs, words", NOT_FINITE)
def test_a_value_not_finite_as_float32_is_refused_naming_value_row_and_coordinate(tmp_path, obs, words):
    h5py = pytest.importorskip("h5py")
    with pytest.raises(ValueError) as e:
        datasets.trajectories({"observations": obs, "actions": np.zeros(20)})
    assert str(e.value) == f"'observations': {words}"
    np.savez(tmp_path / "t.npz", observations=obs, actions=np.zeros(20))
    assert py_refusal(tmp_path / "t.npz") == f"{tmp_path / 't.npz'}: 'observations': {words}"
    with h5py.File(tmp_path / "t.hdf5", "w") as f:
        f["observations"], f["actions"] = obs, np.zeros(20)
    # The HDF5 rows are read by ranges while sending: the same words, naming the file, as the CLI's.
    want = f"{tmp_path / 't.hdf5'}: 'observations': {words}"
    assert py_refusal(tmp_path / "t.hdf5") == want == cli_refusal(tmp_path / "t.hdf5")
    # The same in the actions.
    with pytest.raises(ValueError) as e:
        datasets.trajectories({"observations": np.zeros((20, 1)), "actions": obs})
    assert str(e.value) == f"'actions': {words}"


def test_no_rows_are_refused_locally_naming_the_key(tmp_path):
    h5py = pytest.importorskip("h5py")
    words = "'observations' has no rows (N = 0); a dataset needs at least one"
    with pytest.raises(ValueError) as e:
        datasets.trajectories({"observations": np.zeros((0, 3)), "actions": np.zeros(0), "terminals": np.zeros(0)})
    assert str(e.value) == words
    np.savez(tmp_path / "t.npz", observations=np.zeros((0, 3), np.float32), actions=np.zeros((0, 1), np.float32))
    with h5py.File(tmp_path / "t.hdf5", "w") as f:
        f["observations"], f["actions"] = np.zeros((0, 3), np.float32), np.zeros((0, 1), np.float32)
    for name in ("t.npz", "t.hdf5"):
        assert py_refusal(tmp_path / name) == f"{tmp_path / name}: {words}" == cli_refusal(tmp_path / name)


def test_a_corrupt_npz_is_refused_naming_the_file_and_keeping_the_cause(tmp_path):
    np.savez(tmp_path / "good.npz", observations=np.arange(200, dtype=np.float32).reshape(100, 2),
             actions=np.zeros((100, 1), np.float32))
    data = (tmp_path / "good.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[:len(data) // 2])  # the central directory is gone
    with pytest.raises(ValueError) as e:
        datasets.source_of(tmp_path / "cut.npz")
    assert str(e.value).startswith(f"{tmp_path / 'cut.npz'}: not a readable .npz archive: ")
    assert isinstance(e.value.__cause__, zipfile.BadZipFile)
    assert cli_refusal(tmp_path / "cut.npz").startswith(f"{tmp_path / 'cut.npz'}: not a readable .npz archive: ")
    # A member whose bytes were damaged (its CRC no longer matches): named by its key.
    bad = bytearray(data)
    bad[bad.index(b"NUMPY") + 300] ^= 0xFF  # inside 'observations'' data (np.savez stores uncompressed)
    (tmp_path / "crc.npz").write_bytes(bytes(bad))
    with pytest.raises(ValueError) as e:
        datasets.source_of(tmp_path / "crc.npz")
    assert str(e.value).startswith(f"{tmp_path / 'crc.npz'}: array 'observations': cannot be read: ")
    assert isinstance(e.value.__cause__, zipfile.BadZipFile)


OBJECT_WORDS = "dtype '|O' is an object array (pickled Python objects), which is not supported; expected integers, " \
               "floats or bool"


@pytest.mark.parametrize("arrays, key", [
    ({"observations": np.array([[1, 2], [3, 4]], object), "actions": np.zeros((2, 1))}, "observations"),
    ({"observations": np.zeros((2, 2)), "actions": np.array([[1], [2]], object)}, "actions"),
    ({"observations": np.zeros((2, 2)), "actions": np.zeros(2), "terminals": np.array([0, 1], object)}, "terminals"),
    ({"samples": np.array([[1.0, 2.0]], object)}, "samples"),
])
def test_an_object_array_under_a_taken_key_is_refused_naming_it(tmp_path, arrays, key):
    path = tmp_path / "o.npz"
    np.savez(path, **arrays)
    want = f"{path}: array '{key}': {OBJECT_WORDS}"
    assert py_refusal(path) == want == cli_refusal(path)


def test_an_object_array_left_out_is_never_read_and_an_npy_of_objects_is_refused(tmp_path):
    path = tmp_path / "o.npz"
    np.savez(path, observations=np.zeros((2, 2), np.float32), actions=np.zeros((2, 1), np.float32),
             rewards=np.array([0.5, "x"], object))
    src, closer = datasets.source_of(path)
    closer.close()
    assert src.ignored == ["rewards"] and cli_refusal(path) is None
    np.save(tmp_path / "objs.npy", np.array([[1, 2]], object), allow_pickle=True)
    want = f"{tmp_path / 'objs.npy'}: array 'objs': {OBJECT_WORDS}"
    assert py_refusal(tmp_path / "objs.npy") == want == cli_refusal(tmp_path / "objs.npy")


def test_hdf5_soft_links_are_followed_as_the_cli_follows_them(tmp_path):
    h5py = pytest.importorskip("h5py")
    obs = np.arange(8, dtype=np.float32).reshape(4, 2)
    path = tmp_path / "soft.hdf5"
    with h5py.File(path, "w") as f:
        f["data/obs"], f["data/act"] = obs, np.ones((4, 1), np.float32)
        f["observations"] = h5py.SoftLink("/data/obs")
        f["actions"] = h5py.SoftLink("/data/act")
        f["terminals"] = np.eye(1, 4, 3, dtype=bool)[0]
        f["loop"] = h5py.SoftLink("/")  # a cycle: visited once
        f["gone"] = h5py.SoftLink("/nowhere")  # dangling: no member
    src, closer = datasets.source_of(path)
    try:
        a = arrays_of(src)
        np.testing.assert_array_equal(a["observations"], obs)
        np.testing.assert_array_equal(a["actions"], np.ones((4, 1)))
        assert a["terminals"].tolist() == [False, False, False, True]
        assert "gone" not in src.ignored
    finally:
        closer.close()
    assert cli_refusal(path) is None  # the CLI reads it too


def test_an_hdf5_file_without_observations_is_refused_not_uploaded_as_samples(tmp_path):
    h5py = pytest.importorskip("h5py")
    for key in ("obs", "samples"):
        path = tmp_path / f"{key}.hdf5"
        with h5py.File(path, "w") as f:
            f[key] = np.zeros((4, 2), np.float32)
        want = f"{path}: no 'observations' dataset at the top level (it holds '{key}')"
        assert py_refusal(path) == want == cli_refusal(path)
        # An HDF5 file is trajectories: asking for samples is refused, as the CLI's --kind / --key.
        for ask in ({"kind": "samples"}, {"key": key}):
            with pytest.raises(ValueError, match="an HDF5 file or Minari dataset uploads as trajectories"):
                datasets.source_of(path, **ask)
    with pytest.raises(ValueError, match="an HDF5 file or Minari dataset uploads as trajectories"):
        datasets.source_of(DATA / "minari", kind="samples")
