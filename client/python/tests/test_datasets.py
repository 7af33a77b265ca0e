"""Dataset upload (numpy dict, .npz, samples, Minari episodes, HDF5), get, list, delete."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

import relreward
from conftest import tiny_trajectories


def payload_sha(arrays) -> str:
    """sha256 of the concatenated little-endian C-order bytes of the sent arrays, in order."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def test_upload_dict_checks_digest_stats_and_episodes(client):
    data = tiny_trajectories(seed=5)
    data["rewards"] = np.ones(len(data["actions"]), np.float32)  # not part of a dataset: left out
    seen = []
    ds = client.upload_dataset("py-dict", data, chunk_bytes=100, progress=lambda s, t: seen.append((s, t)),
                               description="from a dict")
    sent = [data["observations"], data["actions"], data["terminals"], data["timeouts"]]
    assert ds.sha256 == payload_sha(sent)
    assert ds.num_rows == 112 and ds.kind == "trajectories"
    assert ds.episodes.count == 5 and ds.episodes.min_length == 5 and ds.episodes.max_length == 40
    assert [a.name for a in ds.arrays] == ["observations", "actions", "terminals", "timeouts"]
    # progress: many chunks (100-byte target), monotone, ending at the total
    total = sum(a.nbytes for a in sent)
    assert len(seen) > 10 and seen[-1] == (total, total)
    assert all(a[0] < b[0] for a, b in zip(seen, seen[1:]))
    got = client.get_dataset("py-dict")
    obs = got.arrays[0].stats
    np.testing.assert_allclose(obs.mean, data["observations"].astype(np.float64).mean(0), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(obs.std, data["observations"].astype(np.float64).std(0), rtol=1e-6, atol=1e-7)
    assert got.description == "from a dict"
    assert "py-dict" in [d.name for d in client.list_datasets()]


def test_digest_does_not_depend_on_chunking_and_matches_the_cli(client, server, tmp_path):
    data = tiny_trajectories(seed=6)
    a = client.upload_dataset("py-chunk-a", data, chunk_bytes=17)
    b = client.upload_dataset("py-chunk-b", data, chunk_bytes=1 << 20)
    path = tmp_path / "d.npz"
    np.savez(path, **data)
    cli = server.cli_json("dataset", "upload", str(path), "--name", "py-chunk-cli")
    assert a.sha256 == b.sha256 == cli["sha256"]
    c = client.upload_dataset("py-npz", path)
    assert c.sha256 == a.sha256
    # Column-major arrays (np.save of a transposed array) are the same rows to both readers.
    fortran = tmp_path / "f.npz"
    np.savez(fortran, **{k: np.asfortranarray(v) for k, v in data.items()})
    assert np.load(fortran)["observations"].flags.f_contiguous
    cli = server.cli_json("dataset", "upload", str(fortran), "--name", "py-fortran-cli")
    assert cli["sha256"] == client.upload_dataset("py-fortran", fortran).sha256 == a.sha256


def test_samples_from_array_and_npy(client, tmp_path):
    x = np.random.default_rng(0).standard_normal((50, 3, 4, 4)).astype(np.float64)
    ds = client.upload_dataset("py-latents", x)
    assert ds.kind == "samples" and ds.num_rows == 50
    assert ds.arrays[0].shape == (50, 3, 4, 4) and ds.sha256 == payload_sha([x])
    np.save(tmp_path / "s.npy", x.astype(np.float32))
    ds2 = client.upload_dataset("py-latents-npy", tmp_path / "s.npy")
    assert ds2.sha256 == payload_sha([x.astype(np.float32)])


def test_minari_episodes_drop_the_last_observation_and_mark_starts(client):
    rng = np.random.default_rng(1)
    episodes = []
    for t in (6, 3, 9):
        episodes.append({"observations": rng.standard_normal((t + 1, 3)).astype(np.float32),
                         "actions": rng.standard_normal((t, 2)).astype(np.float32),
                         "terminations": np.eye(1, t, t - 1, dtype=bool)[0] if t == 6 else np.zeros(t, bool),
                         "truncations": np.zeros(t, bool)})
    flat = relreward.from_minari_episodes(episodes)
    assert flat["observations"].shape == (18, 3) and flat["actions"].shape == (18, 2)
    np.testing.assert_array_equal(flat["observations"][6:9], episodes[1]["observations"][:3])
    np.testing.assert_array_equal(np.flatnonzero(flat["episode_starts"]), [0, 6, 9])
    ds = client.upload_dataset("py-minari", flat)
    assert ds.episodes.count == 3 and ds.episodes.min_length == 3 and ds.episodes.max_length == 9


def test_d4rl_keyed_hdf5_file(client, tmp_path):
    h5py = pytest.importorskip("h5py")
    data = tiny_trajectories(seed=7)
    path = tmp_path / "maze2d.hdf5"
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            f.create_dataset(k, data=v)
        f.create_dataset("rewards", data=np.zeros(len(data["actions"]), np.float32))
        f.create_dataset("infos/qpos", data=data["observations"])
    ds = client.upload_dataset("py-hdf5", path, chunk_bytes=256)
    assert ds.sha256 == payload_sha([data["observations"], data["actions"], data["terminals"], data["timeouts"]])
    assert ds.episodes.count == 5


def test_local_validation_and_server_errors(client):
    with pytest.raises(ValueError, match="'actions'"):
        client.upload_dataset("py-bad", {"observations": np.zeros((4, 2), np.float32)})
    with pytest.raises(ValueError, match="'observations' has dtype <U1; expected numbers"):
        client.upload_dataset("py-bad", {"observations": np.full((4, 2), "x"), "actions": np.zeros((4, 1))})
    with pytest.raises(relreward.InvalidArgument) as e:
        client.upload_dataset("Bad Name!", np.zeros((4, 2), np.float32))
    assert e.value.code.name == "INVALID_ARGUMENT" and "name" in e.value.message
    client.upload_dataset("py-dup", np.zeros((4, 2), np.float32))
    with pytest.raises(relreward.AlreadyExists):
        client.upload_dataset("py-dup", np.zeros((4, 2), np.float32))
    client.delete_dataset("py-dup")
    with pytest.raises(relreward.NotFound) as e:
        client.get_dataset("py-dup")
    assert "py-dup" in e.value.message and isinstance(e.value, relreward.RelrewardError)
    with pytest.raises(relreward.NotFound):
        client.delete_dataset("py-dup")


class Flaky:
    """An array-like whose second row chunk cannot be read (a file that goes away mid-upload)."""

    def __init__(self, a: np.ndarray) -> None:
        self.a, self.shape, self.dtype, self.reads = a, a.shape, a.dtype, 0

    def __getitem__(self, index):
        self.reads += 1
        if self.reads == 2:
            raise OSError("disk went away")
        return self.a[index]


def test_a_read_failure_mid_upload_is_reported_and_nothing_is_stored(client):
    data = tiny_trajectories(seed=8)
    data["observations"] = Flaky(data["observations"])
    with pytest.raises(OSError, match="disk went away"):
        client.upload_dataset("py-flaky", data, chunk_bytes=64)
    with pytest.raises(relreward.NotFound):
        client.get_dataset("py-flaky")


def test_cartpole_like_hdf5_with_an_odd_suffix_uploads_as_the_cli_reads_it(client, server, tmp_path):
    """Integer [T] actions, float64 observations, integer 0/1 flags, a '.hdf' suffix: read as
    the Rust reader reads them (values float32 [N, dim], flags bool), so both store the same."""
    h5py = pytest.importorskip("h5py")
    rng = np.random.default_rng(9)
    obs = rng.standard_normal((30, 4))
    act = rng.integers(0, 2, 30)
    terminals = np.zeros(30, np.int64)
    terminals[[11, 29]] = 1
    path = tmp_path / "cartpole.hdf"
    with h5py.File(path, "w") as f:
        f["observations"], f["actions"], f["terminals"] = obs, act, terminals
        f["timeouts"] = np.zeros(30, np.float32)
    ds = client.upload_dataset("py-cartpole", path, chunk_bytes=64)
    assert [(a.name, a.dtype, a.shape) for a in ds.arrays] == [
        ("observations", "float32", (30, 4)),
        ("actions", "float32", (30, 1)),
        ("terminals", "bool", (30,)),
        ("timeouts", "bool", (30,)),
    ]
    assert ds.sha256 == payload_sha([obs.astype(np.float32), act.astype(np.float32).reshape(30, 1),
                                     terminals.astype(bool), np.zeros(30, bool)])
    assert ds.episodes.count == 2
    cli = server.cli_json("dataset", "upload", str(path), "--name", "py-cartpole-cli")
    assert cli["sha256"] == ds.sha256
    # The same arrays from a dict are the same dataset.
    d = client.upload_dataset("py-cartpole-dict", {"observations": obs, "actions": act, "terminals": terminals,
                                                   "timeouts": np.zeros(30, np.float32)})
    assert d.sha256 == ds.sha256


def test_a_non_finite_hdf5_value_stops_the_upload_and_nothing_is_stored(client, tmp_path):
    h5py = pytest.importorskip("h5py")
    obs = np.zeros((40, 2))
    obs[33, 1] = np.nan
    path = tmp_path / "nan.h5"
    with h5py.File(path, "w") as f:
        f["observations"], f["actions"] = obs, np.zeros((40, 1), np.float32)
    with pytest.raises(ValueError, match="'observations': value NaN at row 33, coordinate 1 is not finite"):
        client.upload_dataset("py-nan", path, chunk_bytes=64)
    with pytest.raises(relreward.NotFound):
        client.get_dataset("py-nan")


def test_minari_file_with_an_empty_episode_and_a_nan_last_observation(client, tmp_path):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "main_data.hdf5"
    with h5py.File(path, "w") as f:
        for i, t in ((0, 5), (1, 0), (2, 3)):
            g = f.create_group(f"episode_{i}")
            o = np.arange(2 * (t + 1), dtype=np.float64).reshape(t + 1, 2)
            o[-1] = np.nan  # the state after the last action is dropped
            g["observations"], g["actions"] = o, np.ones(t, np.int64)
            g["terminations"], g["truncations"] = np.zeros(t, bool), np.eye(1, t, t - 1, dtype=np.int8)[0]
    ds = client.upload_dataset("py-minari-gaps", path)
    assert ds.num_rows == 8 and ds.episodes.count == 2
    assert ds.episodes.min_length == 3 and ds.episodes.max_length == 5
