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
"""

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

import os

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
