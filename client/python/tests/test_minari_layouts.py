"""Minari's on-disk layouts the Python reader must read as the Rust reader does
(client/toolkit/src/hdf5.rs, docs/data-formats.md): Tuple observation spaces (parts
``_index_0`` .. ``_index_<n>``, flattened by their number), JPEG-encoded frames (refused when
``data/metadata.json`` says ``jpeg_encoding``), and values that are not finite in a part of a
dict observation (named by the part). The files are written with h5py in Minari's layout
(minari itself is not needed): root groups ``episode_<id>`` holding ``observations`` (a dataset,
or a group for Dict/Tuple spaces; one more row than actions), ``actions``, ``terminations``,
``truncations``, and ``metadata.json`` beside ``main_data.hdf5``."""

import json
import pathlib

import numpy as np
import pytest

from relreward import datasets

from test_data_rules import DATA, cli_refusal

h5py = pytest.importorskip("h5py")

JPEG_WORDS = ("JPEG-encoded by Minari's DataCollector (data/metadata.json: jpeg_encoding = true); relreward reads "
              "raw arrays: record with DataCollector(..., jpeg_encoding=False), or decode the frames into an .npz")
JPEG_HEADER = [0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10, 0x4A, 0x46]  # SOI, then an APP0 (JFIF) marker


def put(group, name, value):
    """A dataset, or (for a dict) a group of them, recursively."""
    if isinstance(value, dict):
        sub = group.create_group(name)
        for k, v in value.items():
            put(sub, k, v)
    else:
        group.create_dataset(name, data=value)


def minari_dir(root: pathlib.Path, episodes, metadata=None) -> pathlib.Path:
    """A Minari dataset directory: ``data/main_data.hdf5`` with ``episodes`` ({id: (observations,
    steps)}) and, when given, ``data/metadata.json``."""
    (root / "data").mkdir(parents=True)
    with h5py.File(root / "data" / "main_data.hdf5", "w") as f:
        for i, (observations, steps) in episodes.items():
            g = f.create_group(f"episode_{i}")
            put(g, "observations", observations)
            g["actions"] = np.arange(steps, dtype=np.float32)[:, None]
            g["terminations"] = np.arange(steps) == steps - 1
            g["truncations"] = np.zeros(steps, bool)
    if metadata is not None:
        (root / "data" / "metadata.json").write_text(json.dumps(metadata))
    return root


def observations(path):
    src, closer = datasets.source_of(path)
    assert closer is None
    return np.asarray(dict(src.arrays)["observations"])


# --- Tuple spaces: parts by number, before any other key, recursively.


def test_tuple_parts_flatten_by_their_number_not_as_strings(tmp_path):
    # Part i at step k holds 100 * i + k; written out of order.
    parts = {f"_index_{i}": (100 * i + np.arange(3, dtype=np.float32))[:, None] for i in (3, 11, 0, 10, 2, 1, 9, 4,
                                                                                         8, 5, 7, 6)}
    root = minari_dir(tmp_path / "tuple", {0: (parts, 2)})
    want = np.array([[100 * i + k for i in range(12)] for k in range(2)], np.float32)
    np.testing.assert_array_equal(observations(root), want)
    # The Rust tests' fixture (client/toolkit/tests/data/make_fixtures.py) reads the same.
    fixture = DATA / "rules" / "minari_tuple.hdf5"
    if fixture.is_file():
        np.testing.assert_array_equal(observations(fixture), want)


def test_tuple_parts_come_before_other_keys_and_nested_groups_follow_the_same_rule(tmp_path):
    rows = np.arange(3, dtype=np.float32)[:, None]
    obs = {
        "a": 1 + rows,  # not a part: after every part, in string order
        "_index_x": 2 + rows,  # not a number: a plain key ("_index_x" < "a")
        "_index_10": {"z": 3 + rows, "_index_2": 4 + rows, "_index_10": 5 + rows, "b": 6 + rows},
        "_index_9": 7 + rows,
    }
    root = minari_dir(tmp_path / "nested", {0: (obs, 2)})
    # _index_9, _index_10 (its own parts by number: _index_2, _index_10, then b, z), then _index_x, a.
    want = np.concatenate([7 + rows, 4 + rows, 5 + rows, 6 + rows, 3 + rows, 2 + rows, 1 + rows], axis=1)[:2]
    np.testing.assert_array_equal(observations(root), want)
    assert datasets._space_order(["b", "_index_1", "_index_01x", "_index_", "_index_2", "_index_10"]) == [
        "_index_1", "_index_2", "_index_10", "_index_", "_index_01x", "b"]


# --- Values that are not finite in a dict part are named by the part, as the Rust reader names them.


def test_a_value_not_finite_in_a_dict_part_names_the_part(tmp_path):
    bad = np.zeros((4, 3, 2))
    bad[2, 1, 0] = -np.inf
    dropped = np.zeros((4, 2))
    dropped[3] = np.nan  # the last observation: dropped, never checked
    root = minari_dir(tmp_path / "dict", {0: ({"a": dropped, "b": bad}, 3)})
    path = root / "data" / "main_data.hdf5"
    want = (f"{path}: 'episode_0/observations/b': value -inf at row 2, flattened coordinate 2 of [3, 2] is not "
            "finite")
    with pytest.raises(ValueError) as e:
        datasets.source_of(root)
    assert str(e.value) == want == cli_refusal(root)


# --- JPEG frames (minari 0.5's DataCollector default for uint8 images): refused by name when the
# metadata says jpeg_encoding, as the Rust reader refuses them.

JPEG_ON = {"dataset_id": "test/jpeg-v0", "jpeg_encoding": True, "total_episodes": 1, "total_steps": 2}


def jpeg_rows(n, size=8):
    return np.array([JPEG_HEADER + [k] * (size - len(JPEG_HEADER)) for k in range(n)], np.uint8)


def test_constant_size_jpeg_frames_are_refused_naming_the_place_and_the_setting(tmp_path):
    root = minari_dir(tmp_path / "jpeg", {0: (jpeg_rows(3), 2)}, JPEG_ON)
    path = root / "data" / "main_data.hdf5"
    want = f"{path}: 'episode_0/observations' is {JPEG_WORDS}"
    for given in (root, path):
        with pytest.raises(ValueError) as e:
            datasets.source_of(given)
        assert str(e.value) == want
    assert cli_refusal(root) == want
    # Without the metadata's word the same bytes are read as they are (numbers).
    (root / "data" / "metadata.json").write_text(json.dumps({**JPEG_ON, "jpeg_encoding": False}))
    np.testing.assert_array_equal(observations(root), jpeg_rows(2))
    (root / "data" / "metadata.json").unlink()
    np.testing.assert_array_equal(observations(root), jpeg_rows(2))
    # The Rust tests' fixture is refused the same way.
    if (DATA / "minari_jpeg" / "data" / "metadata.json").is_file():
        with pytest.raises(ValueError, match="'episode_0/observations' is JPEG-encoded by Minari's DataCollector"):
            datasets.source_of(DATA / "minari_jpeg")


def test_variable_length_jpeg_frames_are_refused_not_called_a_sequence(tmp_path):
    root = tmp_path / "vlen"
    (root / "data").mkdir(parents=True)
    path = root / "data" / "main_data.hdf5"
    with h5py.File(path, "w") as f:
        g = f.create_group("episode_0")
        frames = g.create_dataset("observations", (3,), dtype=h5py.vlen_dtype(np.uint8))
        for k in range(3):
            frames[k] = np.array(JPEG_HEADER + [k] * (5 + k), np.uint8)  # JPEG sizes vary
        g["actions"] = np.zeros((2, 1), np.float32)
        g["terminations"] = g["truncations"] = np.zeros(2, bool)
    (root / "data" / "metadata.json").write_text(json.dumps(JPEG_ON))
    want = f"{path}: 'episode_0/observations' is {JPEG_WORDS}"
    with pytest.raises(ValueError) as e:
        datasets.source_of(root)
    assert str(e.value) == want == cli_refusal(root)


def test_a_jpeg_part_of_a_dict_observation_is_named_and_other_observations_are_read(tmp_path):
    obs = {"state": np.zeros((3, 2), np.float32), "pixels": jpeg_rows(3)}
    root = minari_dir(tmp_path / "dict", {0: (obs, 2)}, JPEG_ON)
    with pytest.raises(ValueError, match=r"'episode_0/observations/pixels' is JPEG-encoded by Minari's"):
        datasets.source_of(root)
    # Floats, and raw uint8 images that do not begin with JPEG's signature, are read as today.
    raw = np.arange(3 * 36, dtype=np.uint8).reshape(3, 6, 6)
    root = minari_dir(tmp_path / "raw", {0: ({"state": np.ones((3, 2), np.float32), "pixels": raw}, 2)}, JPEG_ON)
    np.testing.assert_array_equal(observations(root), np.concatenate([raw.reshape(3, 36), np.ones((3, 2))], 1)[:2])
    root = minari_dir(tmp_path / "floats", {0: (np.arange(6, dtype=np.float32).reshape(3, 2), 2)}, JPEG_ON)
    np.testing.assert_array_equal(observations(root), [[0, 1], [2, 3]])
    if (DATA / "minari_jpeg_floats" / "data" / "metadata.json").is_file():
        np.testing.assert_array_equal(observations(DATA / "minari_jpeg_floats"), [[0, 1], [2, 3]])


def test_an_empty_episode_is_skipped_without_reading_its_observations(tmp_path):
    # As the Rust reader: an episode of no steps has no row, so its (JPEG) first state is not read.
    root = minari_dir(tmp_path / "gap", {0: (np.arange(6, dtype=np.float32).reshape(3, 2), 2),
                                         1: (jpeg_rows(1), 0)}, JPEG_ON)
    np.testing.assert_array_equal(observations(root), [[0, 1], [2, 3]])
    assert cli_refusal(root) is None
