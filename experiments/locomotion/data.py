"""Locomotion data sets made the D4RL way from committed ARS policies (deterministic rollouts).

Module map: `rollouts` (episodes of one policy with Gaussian action noise, as D4RL-style arrays
with rewards/terminals/timeouts), `make_expert` (rollouts of the trained policy), `make_medium_replay`
(rollouts of the training snapshots up to the first one that reaches a medium return, about a
third of the expert's: the replay buffer of training up to a medium policy), `main` (CLI, writes
`<out>/<env>-{expert,medium-replay}.npz` and prints returns and normalised scores as JSON).

Every episode's seed is derived from (--seed, set, episode), so the same command writes the same
arrays.

    python experiments/locomotion/data.py --env hopper --out /tmp/loco-data
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym
import numpy as np

from ars import Policy
from common import ENVS, POLICIES, episodes, normalized_score


# (expert, medium-replay) episodes per environment: the sets the committed planners were
# trained on. HalfCheetah never terminates, so its episodes are all 1000 steps long.
EPISODES = {"hopper": (50, 400), "halfcheetah": (20, 100), "walker2d": (50, 400)}


def rollouts(env_id: str, policies: list[Policy], n_episodes: int, noise: float, seed: int,
             max_steps: int = 1000) -> dict:
    """n_episodes episodes, policy k % len(policies) for episode k, actions + N(0, noise^2)."""
    env = gym.make(env_id, max_episode_steps=max_steps)
    rng = np.random.default_rng(seed)
    cols = {k: [] for k in ("observations", "actions", "rewards", "terminals", "timeouts")}
    for k in range(n_episodes):
        pol = policies[k % len(policies)]
        obs, _ = env.reset(seed=int(rng.integers(1 << 31)))
        while True:
            act = np.clip(pol.act(obs) + noise * rng.standard_normal(env.action_space.shape), -1, 1)
            nxt, r, term, trunc, _ = env.step(act)
            cols["observations"].append(obs)
            cols["actions"].append(act)
            cols["rewards"].append(r)
            cols["terminals"].append(term)
            cols["timeouts"].append(trunc and not term)
            obs = nxt
            if term or trunc:
                break
    out = {k: np.asarray(v) for k, v in cols.items()}
    out["observations"] = out["observations"].astype(np.float32)
    out["actions"] = out["actions"].astype(np.float32)
    out["rewards"] = out["rewards"].astype(np.float32)
    return out


def episode_returns(data: dict) -> np.ndarray:
    return np.array([data["rewards"][s:e].sum() for s, e in episodes(data)])


def make_expert(env: str, n_episodes: int, noise: float, seed: int, max_steps: int = 1000) -> dict:
    return rollouts(ENVS[env]["id"], [Policy.load(POLICIES / f"{env}.npz")], n_episodes, noise, seed, max_steps)


def medium_snapshots(env: str, medium_frac: float) -> list[int]:
    """Snapshots from the start of training up to the first whose evaluation reaches
    `medium_frac` of the best evaluation (ARS's training history up to a medium policy)."""
    z = np.load(POLICIES / f"{env}.npz")
    ev = z["snap_eval"]
    hit = np.flatnonzero(ev >= medium_frac * ev.max())
    last = int(hit[0]) if len(hit) else len(ev) - 1
    return list(range(last + 1))


def make_medium_replay(env: str, n_episodes: int, noise: float, seed: int, medium_frac: float,
                       max_steps: int = 1000) -> dict:
    path = POLICIES / f"{env}.npz"
    pols = [Policy.load(path, i) for i in medium_snapshots(env, medium_frac)]
    return rollouts(ENVS[env]["id"], pols, n_episodes, noise, seed, max_steps)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", required=True, choices=sorted(ENVS))
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--expert-episodes", type=int, default=None, help="default: EPISODES[env][0]")
    p.add_argument("--replay-episodes", type=int, default=None, help="default: EPISODES[env][1]")
    p.add_argument("--expert-noise", type=float, default=0.02,
                   help="action noise std of the expert set (Hopper's expert falls at 0.1)")
    p.add_argument("--replay-noise", type=float, default=0.05)
    p.add_argument("--medium-frac", type=float, default=1 / 3)
    a = p.parse_args()
    a.expert_episodes = a.expert_episodes or EPISODES[a.env][0]
    a.replay_episodes = a.replay_episodes or EPISODES[a.env][1]
    a.out.mkdir(parents=True, exist_ok=True)
    report = {}
    for name, data in (
        ("expert", make_expert(a.env, a.expert_episodes, a.expert_noise, a.seed)),
        ("medium-replay", make_medium_replay(a.env, a.replay_episodes, a.replay_noise, a.seed + 1,
                                             a.medium_frac)),
    ):
        np.savez(a.out / f"{a.env}-{name}.npz", **data)
        r = episode_returns(data)
        report[name] = dict(transitions=len(data["rewards"]), episodes=len(r), mean_return=float(r.mean()),
                            mean_normalized=float(normalized_score(a.env, r).mean()),
                            mean_length=float(len(data["rewards"]) / len(r)))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
