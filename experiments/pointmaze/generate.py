"""MuJoCo PointMaze data (gymnasium-robotics) the D4RL way, for validating `relreward extract`.

The simulator is gymnasium-robotics' PointMaze (MuJoCo point mass, one env step = one row);
the controller is D4RL's maze2d waypoint controller (docs/method.md section 5): a shortest path
over free cells, waypoints at cell centres, a = 10 (waypoint - pos) - 1 vel clipped to
[-1, 1], plus N(0, noise^2) action noise (D4RL's --noisy: 0.5), clipped again.

Modes:
- base: a uniformly random goal cell, replaced by another when reached (within 0.5 of its
  centre); episodes run to the cap (umaze 300, medium 600 steps), timeouts at their ends.
- expert --variant d4rl: one fixed goal; episodes run to the cap and the agent keeps holding
  the goal (D4RL's data).
- expert --variant goal-terminated: one fixed goal; each episode ends when the goal is reached
  (terminals = 1 on that row), the next starts from a random free cell: the usual shape of
  demonstration data.

Output (.npz, relreward's maze frame: cell (r, c) has its centre at position (r, c), rows
[row, col, v_row, v_col]; gymnasium-robotics' frame has its origin at the maze centre and y up,
so x = col - x_center + 0.5 and y = y_center - 0.5 - row): observations [N, 4], actions [N, 2]
(in the same frame), terminals, timeouts, goals [N, 2], walls [rows, cols].

    python experiments/pointmaze/generate.py --maze umaze --mode expert --goal 3,1 \
        --variant d4rl --transitions 60000 --seed 1 --out expert.npz
"""

from __future__ import annotations

import argparse
from collections import deque

import gymnasium as gym
import gymnasium_robotics
import numpy as np

gym.register_envs(gymnasium_robotics)

LAYOUTS = {
    "umaze": ["#####", "#OOO#", "###O#", "#OOO#", "#####"],
    "medium": ["########", "#OO##OO#", "#OO#OOO#", "##OOO###", "#OO#OOO#", "#O#OO#O#", "#OOO#OO#", "########"],
}
CAPS = {"umaze": 300, "medium": 600}
GOAL_RADIUS = 0.5
WAYPOINT_RADIUS = 0.1


def distances(walls: np.ndarray, goal: tuple[int, int]) -> np.ndarray:
    """BFS steps from every free cell to `goal` (inf for walls)."""
    d = np.full(walls.shape, np.inf)
    d[goal] = 0
    q = deque([goal])
    while q:
        r, c = q.popleft()
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            n = (r + dr, c + dc)
            if 0 <= n[0] < walls.shape[0] and 0 <= n[1] < walls.shape[1] and not walls[n] and d[n] == np.inf:
                d[n] = d[r, c] + 1
                q.append(n)
    return d


class Controller:
    """D4RL's waypoint controller in relreward's frame (positions in cell units)."""

    def __init__(self, walls: np.ndarray):
        self.walls = walls
        self.tables: dict[tuple[int, int], np.ndarray] = {}
        self.waypoint: np.ndarray | None = None

    def act(self, pos: np.ndarray, vel: np.ndarray, goal: tuple[int, int]) -> np.ndarray:
        d = self.tables.setdefault(goal, distances(self.walls, goal))
        cell = (int(round(pos[0])), int(round(pos[1])))
        if self.waypoint is None or np.linalg.norm(pos - self.waypoint) < WAYPOINT_RADIUS or cell == goal:
            if cell == goal or not np.isfinite(d[cell]):
                self.waypoint = np.array(goal, float)
            else:
                best = min(
                    ((cell[0] + dr, cell[1] + dc) for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1))),
                    key=lambda n: d[n] if 0 <= n[0] < d.shape[0] and 0 <= n[1] < d.shape[1] else np.inf,
                )
                self.waypoint = np.array(best, float)
        return np.clip(10.0 * (self.waypoint - pos) - 1.0 * vel, -1.0, 1.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--maze", choices=sorted(LAYOUTS), required=True)
    ap.add_argument("--mode", choices=("base", "expert"), required=True)
    ap.add_argument("--variant", choices=("d4rl", "goal-terminated"), default="d4rl")
    ap.add_argument("--goal", help="expert goal cell ROW,COL")
    ap.add_argument("--transitions", type=int, required=True)
    ap.add_argument("--noise", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    layout = LAYOUTS[a.maze]
    walls = np.array([[ch == "#" for ch in row] for row in layout])
    free = [tuple(c) for c in np.argwhere(~walls)]
    maze_map = walls.astype(int).tolist()
    cap = CAPS[a.maze]
    env = gym.make("PointMaze_UMaze-v3", maze_map=maze_map, continuing_task=True, reset_target=False,
                   max_episode_steps=10**9)
    u = env.unwrapped
    xc, yc = u.maze.x_map_center, u.maze.y_map_center
    rng = np.random.default_rng(a.seed)
    if a.mode == "expert":
        if not a.goal:
            ap.error("--mode expert needs --goal ROW,COL")
        goal = tuple(int(v) for v in a.goal.split(","))
        if goal not in free:
            ap.error(f"--goal {goal} is not a free cell")
    ctrl = Controller(walls)
    obs_l, act_l, term_l, tout_l, goal_l = [], [], [], [], []

    def to_rc(o: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y, vx, vy = o
        return np.array([yc - 0.5 - y, x + xc - 0.5]), np.array([-vy, vx])

    episode_seed = a.seed * 100_003
    while len(obs_l) < a.transitions:
        start = free[rng.integers(len(free))]
        o, _ = env.reset(seed=episode_seed, options={"reset_cell": np.array(start)})
        episode_seed += 1
        g = goal if a.mode == "expert" else free[rng.integers(len(free))]
        ctrl.waypoint = None
        for step in range(cap):
            pos, vel = to_rc(o["observation"])
            action_rc = ctrl.act(pos, vel, g)
            action_rc = np.clip(action_rc + rng.normal(0, a.noise, 2), -1, 1)
            reached = np.linalg.norm(pos - np.array(g, float)) <= GOAL_RADIUS
            obs_l.append(np.concatenate([pos, vel]))
            act_l.append(action_rc)
            goal_l.append(np.array(g, float))
            done_goal = a.mode == "expert" and a.variant == "goal-terminated" and reached
            last = step == cap - 1 or len(obs_l) >= a.transitions
            term_l.append(done_goal)
            tout_l.append(last and not done_goal)
            if done_goal or len(obs_l) >= a.transitions:
                break
            if a.mode == "base" and reached:
                g = free[rng.integers(len(free))]
                ctrl.waypoint = None
            # relreward frame -> gymnasium's: a_x = a_col, a_y = -a_row.
            o, *_ = env.step(np.array([action_rc[1], -action_rc[0]], np.float32))
    n = len(obs_l)
    np.savez(
        a.out,
        observations=np.array(obs_l, np.float32),
        actions=np.array(act_l, np.float32),
        terminals=np.array(term_l, bool),
        timeouts=np.array(tout_l, bool),
        goals=np.array(goal_l, np.float32),
        walls=walls,
    )
    print(f"{a.out}: {n} rows, {int(np.sum(term_l) + np.sum(tout_l))} episodes")


if __name__ == "__main__":
    main()
