"""relreward.relabel against the real server and the tiny windowed reward `rw` (horizon 8,
window 4, rows [action (2) | observation (2)], T = 10): every file form relabelled, the values
compared with a direct Score of windows built here by the rule written out plainly
(docs/relabel.md), the originals kept, everything else unchanged, and every refusal leaving no
file behind."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

import relreward
from relreward.relabel import ORIGINAL, transition_rewards

from conftest import tiny_trajectories

h5py = pytest.importorskip("h5py")

LENGTHS = [30, 5, 40, 12, 25]  # tiny_trajectories' episodes


def close(a: np.ndarray, b: np.ndarray) -> None:
    """Equal up to the last bits that a different batch composition changes on the server
    (docs/python.md: 1-2 float32 ulps; 1e-6 relative to the largest value is ample)."""
    assert a.shape == b.shape and a.dtype == np.float32
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * float(np.abs(b).max()))


def reference_items(obs: np.ndarray, act: np.ndarray, starts: np.ndarray, horizon: int) -> np.ndarray:
    """The item of every row i: rows i-H+1 .. i, a row before the episode's first row e being
    [0 | obs[e]]; written with loops, independently of the module's vectorised gather."""
    items, first = [], 0
    for i in range(len(obs)):
        if starts[i]:
            first = i
        item = []
        for j in range(i - horizon + 1, i + 1):
            if j < first:
                item.append(np.concatenate([np.zeros(act.shape[1]), obs[first]]))
            else:
                item.append(np.concatenate([act[j], obs[j]]))
        items.append(item)
    return np.asarray(items, np.float32)


def starts_of(data: dict) -> np.ndarray:
    ends = data["terminals"] | data["timeouts"]
    return np.concatenate([[True], ends[:-1]])


def direct(client, tiny, obs, act, starts):
    """(per_window[:, -1], per_step[:, H - h]) of one Score of the reference items."""
    h = client.get_model(tiny.reward).reward.window
    r = client.score(tiny.reward, reference_items(obs, act, starts, tiny.horizon), 0, per_window=True,
                     per_step=True)
    return r.per_window[:, -1].copy(), r.per_step[:, tiny.horizon - h].copy()


def npz_data(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    d = tiny_trajectories(seed)
    n = len(d["observations"])
    return {**d, "rewards": rng.normal(size=n), "next_observations": rng.normal(size=(n, 2)).astype(np.float32),
            "infos/goal": np.tile([1.5, -2.0], (n, 1))}


def test_npz_is_relabelled_with_scores_of_the_windows_ending_at_each_row(client, tiny, tmp_path):
    data = npz_data()
    src, dst = tmp_path / "src.npz", tmp_path / "dst.npz"
    np.savez_compressed(src, **data)
    done = relreward.relabel(client, tiny.reward, src, dst)
    assert (done.form, done.episodes, done.original, done.dst) == ("npz", 5, ORIGINAL, dst)
    out = np.load(dst)
    assert sorted(out.files) == sorted([*data, ORIGINAL])
    window, step = direct(client, tiny, data["observations"], data["actions"], starts_of(data))
    # One request of the same items in the same order (the default batch holds all 112): bit
    # for bit; per_step[:, H - h] is the same window's value, computed in another layout.
    np.testing.assert_array_equal(out["rewards"], window)
    close(out["rewards"], step)
    np.testing.assert_array_equal(out["rewards"], done.rewards)
    np.testing.assert_array_equal(out[ORIGINAL], data["rewards"])
    assert out[ORIGINAL].dtype == np.float64
    for key in data:
        if key != "rewards":
            np.testing.assert_array_equal(out[key], data[key])
            assert out[key].dtype == data[key].dtype
    with zipfile.ZipFile(dst) as z:  # compressed as the input was
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_DEFLATED}


def test_a_rows_reward_uses_no_later_row_and_batches_do_not_change_it(client, tiny, tmp_path):
    data = npz_data()
    full = transition_rewards(client, tiny.reward, data)
    # Cut inside the third episode (rows 35.. belong to it): the rewards of the kept rows stay,
    # so an online agent at step i could compute the same value.
    cut = {k: v[:50] for k, v in data.items()}
    close(transition_rewards(client, tiny.reward, cut, batch=7), full[:50])
    seen = []
    close(transition_rewards(client, tiny.reward, data, batch=3, progress=lambda d, n: seen.append((d, n))), full)
    assert seen[-1] == (112, 112) and len(seen) == 38


def test_d4rl_hdf5_keeps_everything_but_rewards(client, tiny, tmp_path):
    data = tiny_trajectories()
    n = len(data["observations"])
    src, dst = tmp_path / "d4rl.hdf5", tmp_path / "out.hdf5"
    with h5py.File(src, "w") as f:
        f.attrs["env"] = "tiny-v0"
        f.attrs["seed"] = np.int32(7)
        f.create_dataset("observations", data=data["observations"].astype(np.float64), compression="gzip",
                         chunks=(16, 2))
        f["actions"] = data["actions"]
        f["terminals"], f["timeouts"] = data["terminals"], data["timeouts"].astype(np.float32)
        f["rewards"] = np.arange(n, dtype=np.float32)
        f["rewards"].attrs["source"] = "environment"
        f["infos/goal"] = np.ones((n, 2))
        f["infos"].attrs["note"] = "kept"
    done = relreward.relabel(client, tiny.reward, src, dst, batch=5)
    assert (done.form, done.episodes, done.original) == ("hdf5", 5, ORIGINAL)
    window, _ = direct(client, tiny, data["observations"], data["actions"], starts_of(data))
    with h5py.File(src, "r") as a, h5py.File(dst, "r") as b:
        assert sorted(b.keys()) == sorted([*a.keys(), ORIGINAL])
        assert dict(b.attrs) == dict(a.attrs) and b.attrs["seed"].dtype == np.int32
        close(b["rewards"][()], window)  # 23 requests of 5: other batches, the same windows
        np.testing.assert_array_equal(b["rewards"][()], done.rewards)
        assert b["rewards"].dtype == np.float32
        assert (b["rewards"].attrs["relreward_model"], b["rewards"].attrs["relreward_t"]) == (tiny.reward, 0)
        np.testing.assert_array_equal(b[ORIGINAL][()], a["rewards"][()])
        assert dict(b[ORIGINAL].attrs) == {"source": "environment"}
        for key in ("observations", "actions", "terminals", "timeouts", "infos/goal"):
            np.testing.assert_array_equal(b[key][()], a[key][()])
            assert b[key].dtype == a[key].dtype
        assert b["observations"].compression == "gzip" and b["observations"].chunks == (16, 2)
        assert dict(b["infos"].attrs) == {"note": "kept"}


def minari_dir(tmp_path, data, root=None, metadata=None):
    """A Minari dataset directory (``root``, default ``tmp_path/minari-tiny``) of
    tiny_trajectories' episodes (ids 0, 1, 2, 5, 10 and an empty 3, so id order is not name
    order), dict observations {'a', 'b'} that flatten to the rows' 2 columns, episode
    attributes, rewards, infos and, where Minari keeps it, data/metadata.json (``metadata``,
    default an id and the step count)."""
    root = root or tmp_path / "minari-tiny"
    (root / "data").mkdir(parents=True)
    metadata = metadata or {"dataset_id": "tiny/test-v0", "total_steps": 112}
    (root / "data" / "metadata.json").write_text(json.dumps(metadata))
    ids = [0, 1, 2, 5, 10]
    bounds = np.concatenate([[0], np.cumsum(LENGTHS)])
    with h5py.File(root / "data" / "main_data.hdf5", "w") as f:
        f.attrs["total_episodes"] = 6
        for eid, lo, hi in zip(ids, bounds[:-1], bounds[1:]):
            g = f.create_group(f"episode_{eid}")
            g.attrs["id"], g.attrs["total_steps"] = eid, hi - lo
            obs = np.concatenate([data["observations"][lo:hi], [[9.0, 9.0]]])  # + the state after the last action
            g["observations/b"], g["observations/a"] = obs[:, 1:], obs[:, :1]
            g["actions"] = data["actions"][lo:hi]
            g["terminations"], g["truncations"] = data["terminals"][lo:hi], data["timeouts"][lo:hi]
            g["rewards"] = np.full(hi - lo, float(eid))
            g["infos/success"] = np.zeros(hi - lo, bool)
        e = f.create_group("episode_3")
        e["observations/a"], e["observations/b"] = np.zeros((1, 1)), np.zeros((1, 1))
        e["actions"], e["rewards"] = np.zeros((0, 2), np.float32), np.zeros(0)
        e["terminations"], e["truncations"] = np.zeros(0, bool), np.zeros(0, bool)
    return root, ids


def test_minari_directory_and_file_have_each_episodes_rewards_replaced(client, tiny, tmp_path):
    data = tiny_trajectories()
    # The rows' columns are the sorted keys: a then b.
    src, ids = minari_dir(tmp_path, data)
    window, _ = direct(client, tiny, data["observations"], data["actions"], starts_of(data))
    dst = tmp_path / "relabelled"
    done = relreward.relabel(client, tiny.reward, src, dst)
    assert (done.form, done.episodes, done.original) == ("minari-dir", 5, ORIGINAL)
    # Under no Minari root: the id is the folder's name (test_minari_metadata_names_the_copy).
    assert json.loads((dst / "data" / "metadata.json").read_text()) == {"dataset_id": "relabelled",
                                                                          "total_steps": 112}
    np.testing.assert_array_equal(done.rewards, window)
    bounds = np.concatenate([[0], np.cumsum(LENGTHS)])
    with h5py.File(src / "data" / "main_data.hdf5", "r") as a, h5py.File(dst / "data" / "main_data.hdf5", "r") as b:
        assert sorted(b.keys()) == sorted(a.keys()) and b.attrs["total_episodes"] == 6
        for eid, lo, hi in zip(ids, bounds[:-1], bounds[1:]):
            ga, gb = a[f"episode_{eid}"], b[f"episode_{eid}"]
            np.testing.assert_array_equal(gb["rewards"][()], window[lo:hi])
            np.testing.assert_array_equal(gb[ORIGINAL][()], np.full(hi - lo, float(eid)))
            assert dict(gb.attrs) == dict(ga.attrs)
            for key in ("observations/a", "observations/b", "actions", "terminations", "truncations",
                        "infos/success"):
                np.testing.assert_array_equal(gb[key][()], ga[key][()])
        assert b["episode_3/rewards"].shape == (0,) and b[f"episode_3/{ORIGINAL}"].shape == (0,)
    # The main_data.hdf5 file alone is the Minari form too.
    out = tmp_path / "main.hdf5"
    one = relreward.relabel(client, tiny.reward, src / "data" / "main_data.hdf5", out)
    assert one.form == "minari-hdf5"
    with h5py.File(out, "r") as b:
        np.testing.assert_array_equal(b["episode_10/rewards"][()], window[bounds[4]:])


def minari_ids(root) -> dict[str, str]:
    """{id: metadata's dataset_id} of every dataset under a Minari root, found as
    minari.list_local_datasets finds them (a folder holding ``data`` is a dataset named by its
    path from the root; hidden folders are skipped; others are namespaces) and which it lists
    only where the two agree (else it warns "Misconfigured dataset" and skips it)."""
    found = {}

    def walk(folder, prefix):
        for d in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
            name = f"{prefix}{d.name}"
            if (d / "data").exists():
                found[name] = json.loads((d / "data" / "metadata.json").read_text())["dataset_id"]
            else:
                walk(d, name + "/")

    walk(root, "")
    return found


def test_minari_metadata_names_the_copy_as_minari_derives_ids(client, tiny, tmp_path, monkeypatch):
    root, other = tmp_path / "datasets", tmp_path / "elsewhere"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    metadata = {"dataset_id": "tiny/test-v0", "total_episodes": 6, "total_steps": 112, "dataset_size": 0.0,
                "author": ["A"], "minari_version": "0.5.1", "ref_min_score": -1.5, "env_spec": "{}",
                "description": "kept"}
    src, _ = minari_dir(tmp_path, tiny_trajectories(), root / "tiny" / "test-v0", metadata)
    wants = {root / "tiny" / "test-rho-v0": "tiny/test-rho-v0",  # a namespace of Minari's root
             root / "plain-v0": "plain-v0",                       # no namespace
             root / "a" / "b" / "deep-v1": "a/b/deep-v1"}         # nested namespaces
    for dst, want in wants.items():
        dst.parent.mkdir(parents=True, exist_ok=True)
        relreward.relabel(client, tiny.reward, src, dst)
        got = json.loads((dst / "data" / "metadata.json").read_text())
        assert got["dataset_id"] == want
        size = sum(p.stat().st_size for p in (dst / "data").glob("**/*"))
        assert got["dataset_size"] == round(size / 1e6, 1) and size > 0
        assert list(got) == list(metadata)  # the keys' order too
        assert {k: v for k, v in got.items() if k not in ("dataset_id", "dataset_size")} == \
            {k: v for k, v in metadata.items() if k not in ("dataset_id", "dataset_size")}
    # The data folder alone relabelled into another dataset's place: named by the folder above it.
    (root / "tiny" / "flat-v0").mkdir()
    relreward.relabel(client, tiny.reward, src / "data", root / "tiny" / "flat-v0" / "data")
    # Every dataset under the root, the source included, is listed: none is misconfigured.
    assert minari_ids(root) == {i: i for i in ["a/b/deep-v1", "plain-v0", "tiny/flat-v0", "tiny/test-rho-v0",
                                               "tiny/test-v0"]}
    assert json.loads((src / "data" / "metadata.json").read_text()) == metadata  # the source is untouched
    # Minari's root moved elsewhere: the source's own root (its path ends with its id) still names it.
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(other))
    relreward.relabel(client, tiny.reward, src, root / "tiny" / "again-v0")
    assert minari_ids(root)["tiny/again-v0"] == "tiny/again-v0"
    # Under no root: the folder's name, what Minari reads once the folder is moved into one.
    loose = tmp_path / "loose" / "ns"
    loose.mkdir(parents=True)
    relreward.relabel(client, tiny.reward, src, loose / "x-v2")
    assert json.loads((loose / "x-v2" / "data" / "metadata.json").read_text())["dataset_id"] == "x-v2"
    # Under the root Minari is told now, wherever the source is.
    (other / "ns").mkdir(parents=True)
    relreward.relabel(client, tiny.reward, src, other / "ns" / "x-v2")
    assert minari_ids(other) == {"ns/x-v2": "ns/x-v2"}
    # Relabelled again (with overwrite), the copy of a copy is named by its own place.
    relreward.relabel(client, tiny.reward, root / "plain-v0", root / "tiny" / "test-rho-v0", overwrite=True)
    assert minari_ids(root)["tiny/test-rho-v0"] == "tiny/test-rho-v0"


def test_minari_metadata_that_is_not_an_object_is_refused(client, tiny, tmp_path):
    src, _ = minari_dir(tmp_path, tiny_trajectories())
    for text in ("[1, 2]", "{not json"):
        (src / "data" / "metadata.json").write_text(text)
        refused(lambda: relreward.relabel(client, tiny.reward, src, tmp_path / "out"),
                r"src: .*metadata.json: .*Minari's metadata is a JSON object", tmp_path)


def test_relabelling_again_keeps_the_first_original_and_overwrite_replaces(client, tiny, tmp_path):
    data = npz_data()
    src, once, twice = tmp_path / "a.npz", tmp_path / "b.npz", tmp_path / "c.npz"
    np.savez(src, **data)
    relreward.relabel(client, tiny.reward, src, once, t=3)
    relreward.relabel(client, tiny.reward, once, twice)
    first, second = np.load(once), np.load(twice)
    np.testing.assert_array_equal(second[ORIGINAL], data["rewards"])
    assert not np.array_equal(second["rewards"], first["rewards"])  # t = 0 against t = 3
    np.testing.assert_array_equal(second["rewards"], transition_rewards(client, tiny.reward, data))
    done = relreward.relabel(client, tiny.reward, src, once, overwrite=True)
    np.testing.assert_array_equal(np.load(once)["rewards"], done.rewards)
    # A Minari directory over an existing one.
    mdir, _ = minari_dir(tmp_path, tiny_trajectories())
    out = tmp_path / "m-out"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    relreward.relabel(client, tiny.reward, mdir, out, overwrite=True)
    assert not (out / "stale.txt").exists() and (out / "data" / "main_data.hdf5").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz", "c.npz", "m-out", "minari-tiny"]


def test_without_an_original_only_rewards_is_written(client, tiny, tmp_path):
    data = tiny_trajectories()
    src, dst = tmp_path / "plain.npz", tmp_path / "out.npz"
    np.savez(src, **data)
    done = relreward.relabel(client, tiny.reward, src, dst)
    assert done.original is None and sorted(np.load(dst).files) == sorted([*data, "rewards"])


def refused(call, match: str, folder) -> None:
    before = sorted(p.name for p in folder.iterdir())
    with pytest.raises(relreward.InvalidInput, match=match):
        call()
    assert sorted(p.name for p in folder.iterdir()) == before  # no dst, no temporary left


def test_refusals_name_the_reason_and_write_nothing(client, tiny, tmp_path):
    data = npz_data()
    src, dst = tmp_path / "src.npz", tmp_path / "dst.npz"
    np.savez(src, **data)
    rw = tiny.reward

    def npz(name, **arrays):
        p = tmp_path / name
        np.savez(p, **arrays)
        return p

    no_actions = npz("no-actions.npz", observations=data["observations"], rewards=data["rewards"])
    refused(lambda: relreward.relabel(client, rw, no_actions, dst), r"src: .*no 'actions' array", tmp_path)
    wide = npz("wide.npz", observations=np.zeros((20, 3)), actions=np.zeros((20, 2)))
    refused(lambda: relreward.relabel(client, rw, wide, dst), r"2 action \+ 3 observation values = 5, but model "
            r"'rw' takes rows of 4", tmp_path)
    split = npz("split.npz", observations=np.zeros((20, 3)), actions=np.zeros((20, 1)))
    refused(lambda: relreward.relabel(client, rw, split, dst), r"1 action \+ 3 observation values, but model 'rw' "
            r"was extracted from 'base', whose rows are 2 action \+ 2 observation", tmp_path)
    text = tmp_path / "notes.txt"
    text.write_text("not data")
    refused(lambda: relreward.relabel(client, rw, text, dst), "src: .*not a form relreward reads", tmp_path)
    npy = tmp_path / "x.npy"
    np.save(npy, np.zeros((4, 4), np.float32))
    refused(lambda: relreward.relabel(client, rw, npy, dst), r"src: .*\.npy file holds one array", tmp_path)
    refused(lambda: relreward.relabel(client, rw, tmp_path / "missing.npz", dst), "src: .* does not exist", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, src), "dst: .* is src", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, tmp_path / "." / "src.npz"), "dst: .* is src", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, no_actions), "dst: .* exists; pass overwrite=True", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, tmp_path, overwrite=True), "dst: .* holds src", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, tmp_path / "nope" / "x.npz"), "dst: the folder", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, dst, t=tiny.n_timesteps), r"t: 10 is outside \[0, 10\)",
            tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, dst, t=-1), r"t: -1 is outside", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, dst, t=1.5), "t: 1.5 is not an integer", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, dst, batch=0), "batch: 0", tmp_path)
    refused(lambda: relreward.relabel(client, rw, src, dst, progress="yes"), "progress: 'yes'", tmp_path)
    refused(lambda: relreward.relabel(client, tiny.base, src, dst), "model: 'base' is a diffusion model", tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(relreward.NotFound):
        relreward.relabel(client, "no-such-reward", src, dst)
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert np.load(no_actions).files == ["observations", "rewards"]  # the existing dst is untouched


def test_a_bad_value_found_while_scoring_leaves_no_file(client, tiny, tmp_path):
    # HDF5 rows are read by ranges while scoring, so this NaN is met after 10 requests of 5.
    data = tiny_trajectories()
    data["observations"][57, 1] = np.nan
    src, dst = tmp_path / "nan.hdf5", tmp_path / "out.hdf5"
    with h5py.File(src, "w") as f:
        for k, v in data.items():
            f[k] = v
    refused(lambda: relreward.relabel(client, tiny.reward, src, dst, batch=5),
            "'observations': value NaN at row 57, coordinate 1 is not finite", tmp_path)


def test_progress_true_without_tqdm_warns(client, tiny, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "tqdm.auto", None)  # an absent tqdm: its import fails
    with pytest.warns(RuntimeWarning, match="tqdm is not installed") as caught:
        transition_rewards(client, tiny.reward, tiny_trajectories(), progress=True)
    assert caught[0].filename == __file__


@pytest.fixture(scope="module")
def value_reward(server, tiny) -> str:
    """A value_function reward (one window per item, no per-step values) from the tiny pair."""
    server.cli("train", "reward", "--name", "rw-vf", "--base", tiny.base, "--expert", tiny.expert, "--dataset",
               tiny.dataset, "--arch", "value_function", "--widths", "8,32", "--seed", "3", "--watch", "--steps", "4",
               "--batch-size", "8")
    return "rw-vf"


def test_a_reward_without_windows_gives_rho_of_the_item_ending_at_each_row(client, tiny, value_reward):
    data = npz_data()
    items = reference_items(data["observations"], data["actions"], starts_of(data), tiny.horizon)
    rho = client.score(value_reward, items, 0).rewards
    close(transition_rewards(client, value_reward, data, batch=16), rho)
    with pytest.raises(relreward.InvalidArgument, match="per-step values need a windowed_mlp reward"):
        client.score(value_reward, items[:2], 0, per_step=True)  # why the rule does not read per_step


def test_the_cli_relabels_an_npz_as_the_package_does(server, client, tiny, tmp_path):
    """`relreward relabel` (Rust) follows the same rule: the same rewards, bit for bit, for the
    same requests; the same original kept; every other member byte for byte; refusals first."""
    data = npz_data()
    src = tmp_path / "src.npz"
    np.savez_compressed(src, **data)
    want = relreward.relabel(client, tiny.reward, src, tmp_path / "py.npz").rewards
    report = server.cli_json("relabel", "--model", tiny.reward, "--input", str(src), "--output",
                             str(tmp_path / "cli.npz"))
    assert (report["rows"], report["episodes"], report["original"]) == (112, 5, ORIGINAL)
    out = np.load(tmp_path / "cli.npz")
    np.testing.assert_array_equal(out["rewards"], want)
    assert sorted(out.files) == sorted([*data, ORIGINAL])
    for key in data:
        expected = data["rewards"] if key == "rewards" else data[key]
        got = out[ORIGINAL] if key == "rewards" else out[key]
        np.testing.assert_array_equal(got, expected)
        assert got.dtype == expected.dtype
    # Smaller batches, the same values up to the documented batching tolerance.
    server.cli("relabel", "--model", tiny.reward, "--input", str(src), "--output", str(tmp_path / "b3.npz"),
               "--batch", "3")
    close(np.load(tmp_path / "b3.npz")["rewards"], want)
    # Relabelling the relabelled file keeps the first original.
    server.cli("relabel", "--model", tiny.reward, "--input", str(tmp_path / "cli.npz"), "--output",
               str(tmp_path / "again.npz"))
    np.testing.assert_array_equal(np.load(tmp_path / "again.npz")[ORIGINAL], data["rewards"])

    bad_width = tmp_path / "wide.npz"
    np.savez(bad_width, **{**data, "observations": np.zeros((112, 3), np.float32)})
    cases = [
        (["--input", str(src), "--output", str(tmp_path / "cli.npz")], "exists; pass --overwrite"),
        (["--input", str(src), "--output", str(src)], "is --input"),
        (["--input", str(tmp_path / "x.hdf5"), "--output", str(tmp_path / "o.npz")], "no such file"),
        (["--input", str(bad_width), "--output", str(tmp_path / "o.npz")], "D = action_dim + obs_dim"),
        (["--input", str(src), "--output", str(tmp_path / "o.npz"), "--t", "10"], "--t 10: outside 0..10"),
        (["--input", str(src), "--output", str(tmp_path / "o.npz"), "--batch", "0"], "--batch"),
        (["--input", str(src), "--output", str(tmp_path / "o.h5")], "must end in .npz"),
    ]
    (tmp_path / "d.hdf5").write_bytes(b"")
    cases.append((["--input", str(tmp_path / "d.hdf5"), "--output", str(tmp_path / "o.npz")], "relreward.relabel"))
    before = sorted(p.name for p in tmp_path.iterdir())
    for args, needle in cases:
        p = server.cli("relabel", "--model", tiny.reward, *args, check=False)
        assert p.returncode != 0 and needle in p.stderr, (args, p.stderr)
    p = server.cli("relabel", "--model", tiny.base, "--input", str(src), "--output", str(tmp_path / "o.npz"),
                   check=False)
    assert p.returncode != 0 and "is a diffusion model" in p.stderr, p.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == before, "a refusal wrote nothing"
