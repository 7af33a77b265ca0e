"""Records `pointmaze_mujoco.npz`: MuJoCo PointMaze (gymnasium-robotics) driven by fixed action
sequences, for `tests/maze_vs_mujoco.rs`, which drives relreward's maze generator
(`Physics::MUJOCO` and the default) with the same actions and compares positions per row.

Layout: D4RL's `open` (5 x 7, relreward's built-in `open`). Positions and actions are in
relreward's maze frame (cell (r, c) centred at (r, c); experiments/pointmaze/generate.py has the
conversion). Each sequence starts at rest at the exact position given (the env's reset noise is
overwritten with `set_state`).

Arrays (K = sequence index): `start_K` [2], `actions_K` [T, 2], `positions_K` [T + 1, 2]
(before the first action, then after each), `velocities_K` [T + 1, 2].
- 0, free space: 100 steps of actions uniform in [-1, 1]^2 (seed 7); checked here never to come
  within 0.2 of a wall face (so no contact);
- 1, wall contact: 70 steps of (1, 0.3) from (2, 3): the point speeds up toward the wall at
  row 3.5 past the velocity clip (5), hits it and slides along it.

    python client/toolkit/tests/data/make_pointmaze_fixture.py   # needs gymnasium-robotics 1.4.2
"""

from pathlib import Path

import gymnasium as gym
import gymnasium_robotics
import numpy as np

gym.register_envs(gymnasium_robotics)

OPEN = ["#######", "#OOOOO#", "#OOOOO#", "#OOOOO#", "#######"]


def record(env, start, actions):
    u = env.unwrapped
    xc, yc = u.maze.x_map_center, u.maze.y_map_center
    env.reset(seed=0)
    # relreward (row, col) -> gymnasium (x, y): x = col - xc + 0.5, y = yc - 0.5 - row.
    qpos = np.array([start[1] - xc + 0.5, yc - 0.5 - start[0]])
    u.point_env.set_state(qpos, np.zeros(2))
    pos, vel = [], []

    def log():
        x, y, vx, vy = u.point_env.data.qpos[0], u.point_env.data.qpos[1], *u.point_env.data.qvel[:2]
        pos.append([yc - 0.5 - y, x + xc - 0.5])
        vel.append([-vy, vx])

    log()
    for a in actions:
        env.step(np.array([a[1], -a[0]], np.float32))
        log()
    return np.array(pos), np.array(vel)


def main():
    walls = [[int(ch == "#") for ch in row] for row in OPEN]
    env = gym.make("PointMaze_UMaze-v3", maze_map=walls, continuing_task=True, reset_target=False,
                   max_episode_steps=10**9)
    rng = np.random.default_rng(7)
    sequences = [
        (np.array([2.0, 3.0]), rng.uniform(-1, 1, (100, 2))),
        (np.array([2.0, 3.0]), np.tile([1.0, 0.3], (70, 1))),
    ]
    out = {}
    for k, (start, actions) in enumerate(sequences):
        pos, vel = record(env, start, actions.astype(np.float32).astype(np.float64))
        if k == 0:
            # Free space: the disc (radius 0.1) stays 0.2 from every wall face.
            assert (pos[:, 0] > 0.5 + 0.3).all() and (pos[:, 0] < 3.5 - 0.3).all(), pos[:, 0].min()
            assert (pos[:, 1] > 0.5 + 0.3).all() and (pos[:, 1] < 5.5 - 0.3).all()
        out[f"start_{k}"] = start
        out[f"actions_{k}"] = actions.astype(np.float32).astype(np.float64)
        out[f"positions_{k}"] = pos
        out[f"velocities_{k}"] = vel
    dest = Path(__file__).with_name("pointmaze_mujoco.npz")
    np.savez(dest, **out)
    print(dest, {k: v.shape for k, v in out.items()})
    print("wall sequence rows 30..45:", out["positions_1"][30:45].round(4).tolist())


if __name__ == "__main__":
    main()
