"""Writes the tiny HDF5 fixtures the toolkit's reader tests read (committed beside this script).

Run from this directory with h5py installed: python make_fixtures.py. Values are formulas of
the row index, so the Rust tests check them without reading this file.

- d4rl.hdf5: D4RL's layout, gzip-compressed and chunked like D4RL's own files: observations
  [12, 4] float32 = 10 * row + column, actions [12, 2] float64 = -(row + column / 10), terminals
  (bool) at row 4, timeouts (bool) at rows 7 and 11, rewards, infos/goal (ignored), and a
  wall_map [3, 4] int64 (1 = wall).
- minari/data/main_data.hdf5: Minari's layout, episodes 0, 1 and 10 (written out of order so
  id order != name order) of 3, 2 and 4 steps; observations is a dict group
  {observation [T+1, 4], achieved_goal [T+1, 2], desired_goal [T+1, 2]} with value
  100 * episode + 10 * step + column (column counted within each key), actions [T, 2] =
  episode + step / 10; terminations bool at each episode's last step for episode 1 only,
  truncations bool at the last step of the others.
- big_endian.hdf5: D4RL layout with big-endian float32 observations [3, 2] = 0..6, big-endian
  float64 actions [3, 1] = 0..3, and episode_starts int64 [0, 2] (start indices, not flags).
- rules/: the value rules of docs/data-formats.md, each case written twice with the same arrays,
  as NAME.npz and as NAME.hdf5 (D4RL layout), so every reader is checked against the same file:
  - types: observations big-endian int16 [5, 2, 2] = 10 * row + flattened index (read as
    [5, 4]), actions float16 [5] = row / 2 - 1 (read as [5, 1]), terminals int64 0/1 (row 2),
    timeouts float32 0/1 (row 4).
  - f64: observations float64 [3, 2] = 0.1 * (2 * row + column) (rounded to float32), actions
    uint64 [3, 1] = row, terminals bool (row 2).
  - bad_flag: as f64 but terminals int64 [0, 0, 2]: refused naming 'terminals', row 2, value 2.
  - empty: observations float32 [0, 2], actions [0, 1]: refused, N = 0.
  - nan: observations float32 [4, 2] with NaN at row 2, coordinate 1.
  - nan_3d: observations float32 [3, 2, 2] with +inf at [1, 1, 0] (row 1, flattened
    coordinate 2).
  and HDF5 only:
  - minari_edge.hdf5: Minari layout, episode_0 (3 steps), episode_5 (0 steps: observations
    [1, 2], actions [0, 1]) and episode_7 (2 steps, NaN in its last observation, which is
    dropped); observations = 10 * episode + step (both columns), actions = step, terminations
    uint8, truncations float64 0/1.
  - f128.hdf5: observations of 16-byte floats (np.longdouble): refused, named in words.
  - minari_tuple.hdf5: Minari layout, one episode of 2 steps whose observations are a Tuple of
    twelve Box(1) parts stored as `_index_0` .. `_index_11` (written out of order), part i =
    100 * i + step: flattened by number, so a row is [0, 100, ..., 1100] + step.
- minari_jpeg/: a Minari directory whose data/metadata.json says jpeg_encoding = true and whose
  observations are uint8 rows that begin with JPEG's signature: refused, named.
- minari_jpeg_floats/: the same metadata over float32 observations [3, 2] = 0..6: read as they are.
The .npz files are written with fixed zip timestamps, so every file is byte-for-byte the same
at each run.
"""

import json
import os

import h5py
import numpy as np

with h5py.File("d4rl.hdf5", "w") as f:
    n = 12
    rows = np.arange(n)[:, None]
    f.create_dataset("observations", data=(10 * rows + np.arange(4)).astype(np.float32), compression="gzip", chunks=(5, 4))
    f.create_dataset("actions", data=-(rows + np.arange(2) / 10).astype(np.float64), compression="gzip")
    term = np.zeros(n, bool)
    term[4] = True
    tout = np.zeros(n, bool)
    tout[[7, 11]] = True
    f.create_dataset("terminals", data=term, compression="gzip")
    f.create_dataset("timeouts", data=tout)
    f.create_dataset("rewards", data=np.zeros(n, np.float32))
    f.create_dataset("infos/goal", data=np.zeros((n, 2), np.float32))
    f.create_dataset("wall_map", data=np.array([[1, 1, 1, 1], [1, 0, 0, 1], [1, 1, 1, 1]], np.int64))


os.makedirs("minari/data", exist_ok=True)
with h5py.File("minari/data/main_data.hdf5", "w") as f:
    for ep, steps in ((10, 4), (0, 3), (1, 2)):
        g = f.create_group(f"episode_{ep}")
        k = np.arange(steps + 1)[:, None]
        obs = g.create_group("observations")
        for key, width in (("observation", 4), ("desired_goal", 2), ("achieved_goal", 2)):
            obs.create_dataset(key, data=(100 * ep + 10 * k + np.arange(width)).astype(np.float64))
        g.create_dataset("actions", data=(ep + np.arange(steps)[:, None] / 10 + np.zeros(2)).astype(np.float32))
        last = np.zeros(steps, bool)
        last[-1] = True
        g.create_dataset("terminations", data=last if ep == 1 else np.zeros(steps, bool))
        g.create_dataset("truncations", data=np.zeros(steps, bool) if ep == 1 else last)
        g.create_dataset("rewards", data=np.zeros(steps))
        g.create_group("infos")

with h5py.File("big_endian.hdf5", "w") as f:
    f.create_dataset("observations", data=np.arange(6, dtype=">f4").reshape(3, 2))
    f.create_dataset("actions", data=np.arange(3, dtype=">f8").reshape(3, 1))
    f.create_dataset("episode_starts", data=np.array([0, 2], dtype=np.int64))

# ---- end-to-end fixtures (tests/tests/extract.rs): a point mass in a 3x3-cell room (cells 1..3
# of a 5x5 grid bordered by walls; cell (r, c) has its centre at position (r, c)).
# base_d4rl.hdf5: D4RL layout, 20 episodes of 100 steps of a random walk, observations
# [achieved_goal (2), desired_goal (2), observation (4)] (the Minari flattening order), actions
# [2], timeouts at each episode's end, a wall_map. expert_minari/: Minari layout, 10 episodes of
# 100 steps of a PD controller to position (3, 3) with action noise, dict observations.
rng = np.random.default_rng(0)
GOAL = np.array([3.0, 3.0])


def rollout(policy, steps, goal):
    pos = rng.uniform(0.7, 3.3, 2)
    vel = np.zeros(2)
    obs, act = [], []
    for _ in range(steps + 1):
        obs.append(np.concatenate([pos, goal, pos, vel]))
        a = np.clip(policy(pos, vel), -1, 1)
        act.append(a)
        vel = 0.9 * vel + 0.1 * a
        pos = np.clip(pos + vel, 0.55, 3.45)
    return np.array(obs, np.float32), np.array(act[:-1], np.float32)


def random_walk(pos, vel):
    return rng.normal(0, 1, 2)


def expert(pos, vel):
    return 2.0 * (GOAL - pos) - 1.0 * vel + rng.normal(0, 0.3, 2)


walls = np.ones((5, 5), np.uint8)
walls[1:4, 1:4] = 0
obs, act, tout = [], [], []
for ep in range(20):
    o, a = rollout(random_walk, 100, rng.uniform(1, 3, 2))
    obs.append(o[:-1])
    act.append(a)
    t = np.zeros(100, bool)
    t[-1] = True
    tout.append(t)
os.makedirs("e2e", exist_ok=True)
with h5py.File("e2e/base_d4rl.hdf5", "w") as f:
    f.create_dataset("observations", data=np.concatenate(obs), compression="gzip")
    f.create_dataset("actions", data=np.concatenate(act), compression="gzip")
    f.create_dataset("terminals", data=np.zeros(2000, bool))
    f.create_dataset("timeouts", data=np.concatenate(tout))
    f.create_dataset("rewards", data=np.zeros(2000, np.float32))
    f.create_dataset("wall_map", data=walls)

os.makedirs("e2e/expert_minari/data", exist_ok=True)
with h5py.File("e2e/expert_minari/data/main_data.hdf5", "w") as f:
    for ep in range(10):
        o, a = rollout(expert, 100, GOAL)
        g = f.create_group(f"episode_{ep}")
        d = g.create_group("observations")
        d.create_dataset("achieved_goal", data=o[:, 0:2], compression="gzip")
        d.create_dataset("desired_goal", data=o[:, 2:4], compression="gzip")
        d.create_dataset("observation", data=o[:, 4:8], compression="gzip")
        g.create_dataset("actions", data=a, compression="gzip")
        g.create_dataset("terminations", data=np.zeros(100, bool))
        tr = np.zeros(100, bool)
        tr[-1] = True
        g.create_dataset("truncations", data=tr)
        g.create_dataset("rewards", data=np.zeros(100))

# ---- rules/: the value rules (docstring), each case as NAME.npz and NAME.hdf5.
import io
import zipfile


def savez_fixed(path, arrays):
    """np.savez with a fixed timestamp per entry (np.savez stamps the current time)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for key, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            z.writestr(info, buf.getvalue())


def both(name, arrays):
    savez_fixed(f"rules/{name}.npz", arrays)
    with h5py.File(f"rules/{name}.hdf5", "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)


os.makedirs("rules", exist_ok=True)
row = np.arange(5)
both(
    "types",
    {
        "observations": (10 * row[:, None] + np.arange(4)).reshape(5, 2, 2).astype(">i2"),
        "actions": (row / 2 - 1).astype(np.float16),
        "terminals": (row == 2).astype(np.int64),
        "timeouts": (row == 4).astype(np.float32),
    },
)
f64 = {
    "observations": 0.1 * (2 * np.arange(3)[:, None] + np.arange(2)),
    "actions": np.arange(3, dtype=np.uint64)[:, None],
    "terminals": np.array([False, False, True]),
}
both("f64", f64)
both("bad_flag", {**f64, "terminals": np.array([0, 0, 2], np.int64)})
both("empty", {"observations": np.zeros((0, 2), np.float32), "actions": np.zeros((0, 1), np.float32)})
nan = np.arange(8, dtype=np.float32).reshape(4, 2)
nan[2, 1] = np.nan
both("nan", {"observations": nan, "actions": np.zeros((4, 1), np.float32)})
inf = np.arange(12, dtype=np.float32).reshape(3, 2, 2)
inf[1, 1, 0] = np.inf
both("nan_3d", {"observations": inf, "actions": np.zeros((3, 1), np.float32)})

with h5py.File("rules/minari_edge.hdf5", "w", libver="latest") as f:
    for ep, steps in ((0, 3), (5, 0), (7, 2)):
        g = f.create_group(f"episode_{ep}")
        obs = np.repeat((10 * ep + np.arange(steps + 1, dtype=np.float32))[:, None], 2, axis=1)
        if ep == 7:
            obs[-1, 0] = np.nan
        g.create_dataset("observations", data=obs)
        g.create_dataset("actions", data=np.arange(steps, dtype=np.float32)[:, None])
        last = (np.arange(steps) == steps - 1)
        g.create_dataset("terminations", data=last.astype(np.uint8) if ep == 7 else np.zeros(steps, np.uint8))
        g.create_dataset("truncations", data=np.zeros(steps) if ep == 7 else last.astype(np.float64))

with h5py.File("rules/f128.hdf5", "w") as f:
    f.create_dataset("observations", data=np.zeros((2, 2), np.longdouble))
    f.create_dataset("actions", data=np.zeros((2, 1), np.float32))

# Root members a Minari reader must not leave out without a word (docs/data-formats.md, "Minari
# root"): an episode group whose id is not a number, and a second spelling of an id.
for name, groups in (("minari_bad_group", ("episode_1", "episode_abc")), ("minari_dup_id", ("episode_1", "episode_01"))):
    with h5py.File(f"rules/{name}.hdf5", "w", libver="latest") as f:
        for group in groups:
            g = f.create_group(group)
            g.create_dataset("observations", data=np.arange(6, dtype=np.float32).reshape(3, 2))
            g.create_dataset("actions", data=np.zeros((2, 1), np.float32))
            g.create_dataset("terminations", data=np.array([False, True]))
            g.create_dataset("truncations", data=np.zeros(2, bool))

# Minari's Tuple observations (parts `_index_0` .. `_index_11`, which flatten by number, not as
# strings) and JPEG-encoded frames (data/metadata.json: jpeg_encoding = true): the frames are
# refused by name; float observations under the same metadata are read as they are.
def minari_episode(g, observations, steps):
    if isinstance(observations, dict):
        obs = g.create_group("observations")
        for key, value in observations.items():
            obs.create_dataset(key, data=value)
    else:
        g.create_dataset("observations", data=observations)
    g.create_dataset("actions", data=np.arange(steps, dtype=np.float32)[:, None])
    g.create_dataset("terminations", data=np.arange(steps) == steps - 1)
    g.create_dataset("truncations", data=np.zeros(steps, bool))


with h5py.File("rules/minari_tuple.hdf5", "w", libver="latest") as f:
    # Part i at step k holds 100 * i + k: a row reads 0 + k, 100 + k, ..., 1100 + k.
    parts = {f"_index_{i}": (100 * i + np.arange(3, dtype=np.float32))[:, None] for i in (3, 11, 0, 10, 2, 1, 9, 4, 8, 5, 7, 6)}
    minari_episode(f.create_group("episode_0"), parts, 2)
for name, observations in (
    ("minari_jpeg", np.array([[0xFF, 0xD8, 0xFF, 0xE0, 0, 16, 74, 70]] * 3, np.uint8)),
    ("minari_jpeg_floats", np.arange(6, dtype=np.float32).reshape(3, 2)),
):
    os.makedirs(f"{name}/data", exist_ok=True)
    with h5py.File(f"{name}/data/main_data.hdf5", "w", libver="latest") as f:
        minari_episode(f.create_group("episode_0"), observations, 2)
    with open(f"{name}/data/metadata.json", "w") as m:
        json.dump({"dataset_id": f"test/{name}-v0", "jpeg_encoding": True, "total_episodes": 1, "total_steps": 2}, m)
