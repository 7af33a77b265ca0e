"""ARS V2-t (Mania, Guy & Recht 2018): linear policies on running-normalised states.

Module map: `Policy` (linear map on normalised states, the thing committed as npz),
`rollout` (one episode, optionally updating the running state statistics), `train` (the
ARS loop; every `snapshot_every` iterations a copy of the policy is kept, so the
`medium-replay`-like data can later be regenerated deterministically from the snapshots of
training up to a medium policy, see data.py), `main` (CLI).

Why ARS: it trains a Hopper expert on one core in ~15 minutes (docs/method.md section 10),
which no gradient-based RL method does on this machine.

    python experiments/locomotion/ars.py --env Hopper-v5 --seed 0 --out experiments/locomotion/policies
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

# Per-environment ARS hyper-parameters (step size, exploration noise, directions, top-b),
# from docs/method.md section 10 / the ARS paper; `survival` is the per-step healthy reward
# removed while training (ARS's trick against standing still), 0 where none.
HYPER = {
    "Hopper-v5": dict(step=0.01, noise=0.025, dirs=8, top=4, survival=1.0),
    # Walker2d uses Hopper's settings: 16 rollouts an iteration fit the 2-core machine, where
    # the ARS paper's 40 directions (80 rollouts) cost ~20 s an iteration.
    "Walker2d-v5": dict(step=0.01, noise=0.025, dirs=8, top=4, survival=1.0),
    "HalfCheetah-v5": dict(step=0.02, noise=0.03, dirs=32, top=4, survival=0.0),
}


class RunningStat:
    """Welford running mean/variance of observed states (ARS V2's state normaliser)."""

    def __init__(self, dim: int):
        self.n = 0
        self.mean = np.zeros(dim)
        self.m2 = np.zeros(dim)

    def push_many(self, xs: np.ndarray) -> None:
        for x in xs:
            self.n += 1
            d = x - self.mean
            self.mean += d / self.n
            self.m2 += d * (x - self.mean)

    @property
    def std(self) -> np.ndarray:
        if self.n < 2:
            return np.ones_like(self.mean)
        s = np.sqrt(self.m2 / (self.n - 1))
        return np.where(s < 1e-8, 1.0, s)


class Policy:
    """a = clip(M (s - mean) / std, -1, 1)."""

    def __init__(self, m: np.ndarray, mean: np.ndarray, std: np.ndarray):
        self.m, self.mean, self.std = m, mean, std

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.clip(self.m @ ((obs - self.mean) / self.std), -1.0, 1.0)

    @staticmethod
    def load(path: Path, index: int | None = None) -> "Policy":
        """The expert policy of an npz written by `train`, or snapshot `index`."""
        z = np.load(path)
        if index is None:
            return Policy(z["m"], z["mean"], z["std"])
        return Policy(z["snap_m"][index], z["snap_mean"][index], z["snap_std"][index])


def rollout(env, policy: Policy, seed: int, horizon: int = 1000, survival: float = 0.0,
            stat: RunningStat | None = None) -> tuple[float, int]:
    obs, _ = env.reset(seed=seed)
    total, states = 0.0, [obs]
    for t in range(horizon):
        obs, r, term, trunc, _ = env.step(policy.act(obs))
        total += r - survival
        states.append(obs)
        if term or trunc:
            break
    if stat is not None:
        stat.push_many(np.asarray(states))
    return total, t + 1


def evaluate(env, policy: Policy, seeds) -> float:
    return float(np.mean([rollout(env, policy, int(s))[0] for s in seeds]))


def train(env_id: str, seed: int, iters: int, snapshot_every: int, budget_s: float, log, save=None) -> dict:
    h = HYPER[env_id]
    env = gym.make(env_id)
    rng = np.random.default_rng(seed)
    obs_dim = env.observation_space.shape[0]
    act_dim = env.action_space.shape[0]
    m = np.zeros((act_dim, obs_dim))
    stat = RunningStat(obs_dim)
    stat.push_many(np.zeros((1, obs_dim)))
    snaps, snap_iters, snap_evals = [], [], []
    best = (-np.inf, None, -1)
    steps, t0 = 0, time.time()
    episode_seed = int(rng.integers(1 << 30))
    for it in range(iters + 1):
        mean, std = stat.mean.copy(), stat.std.copy()
        if it % snapshot_every == 0:
            pol = Policy(m.copy(), mean, std)
            ev = evaluate(env, pol, range(10_000 + it, 10_003 + it))
            snaps.append((m.copy(), mean, std))
            snap_iters.append(it)
            snap_evals.append(ev)
            if ev > best[0]:
                best = (ev, (m.copy(), mean, std), it)
            log(f"{env_id} it {it} steps {steps} eval {ev:.1f} best {best[0]:.1f} "
                f"{time.time() - t0:.0f}s")
            if save is not None:
                # Written at every snapshot, so a run stopped early still leaves its policies.
                save(_result(best, snaps, snap_iters, snap_evals, steps, time.time() - t0, it))
            if time.time() - t0 > budget_s:
                break
        if it == iters:
            break
        deltas = rng.standard_normal((h["dirs"], act_dim, obs_dim))
        r_pos, r_neg = np.zeros(h["dirs"]), np.zeros(h["dirs"])
        for k in range(h["dirs"]):
            for sign, store in ((1.0, r_pos), (-1.0, r_neg)):
                episode_seed += 1
                ret, n = rollout(env, Policy(m + sign * h["noise"] * deltas[k], mean, std),
                                 episode_seed, survival=h["survival"], stat=stat)
                store[k] = ret
                steps += n
        order = np.argsort(-np.maximum(r_pos, r_neg))[: h["top"]]
        sigma = np.concatenate([r_pos[order], r_neg[order]]).std() + 1e-8
        m = m + h["step"] / (h["top"] * sigma) * np.einsum(
            "k,kij->ij", r_pos[order] - r_neg[order], deltas[order])
    return _result(best, snaps, snap_iters, snap_evals, steps, time.time() - t0, it)


def _result(best, snaps, snap_iters, snap_evals, steps, seconds, it) -> dict:
    ev, (bm, bmean, bstd), bit = best
    return dict(m=bm, mean=bmean, std=bstd, best_iter=bit, best_eval=ev, last_iter=it,
                snap_m=np.stack([s[0] for s in snaps]), snap_mean=np.stack([s[1] for s in snaps]),
                snap_std=np.stack([s[2] for s in snaps]), snap_iter=np.array(snap_iters),
                snap_eval=np.array(snap_evals), steps=steps, seconds=seconds)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", required=True, choices=sorted(HYPER))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--iters", type=int, default=1000)
    p.add_argument("--snapshot-every", type=int, default=10)
    p.add_argument("--budget-s", type=float, default=1e9, help="stop at a snapshot after this")
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    name = a.env.split("-")[0].lower()

    def save(res: dict) -> None:
        tmp = a.out / f".{name}.tmp.npz"
        np.savez_compressed(tmp, **res)
        tmp.replace(a.out / f"{name}.npz")
        meta = {k: float(v) for k, v in res.items() if np.ndim(v) == 0}
        # The command that reproduces exactly this file (training is deterministic per seed).
        meta.update(env=a.env, seed=a.seed, hyper=HYPER[a.env], command=" ".join(
            ["python experiments/locomotion/ars.py", f"--env {a.env} --seed {a.seed}",
             f"--iters {int(res['last_iter'])} --snapshot-every {a.snapshot_every}", f"--out {a.out}"]))
        (a.out / f"{name}.json").write_text(json.dumps(meta, indent=1) + "\n")

    res = train(a.env, a.seed, a.iters, a.snapshot_every, a.budget_s, lambda s: print(s, flush=True), save)
    save(res)
    print(json.dumps({k: float(v) for k, v in res.items() if np.ndim(v) == 0}), flush=True)


if __name__ == "__main__":
    main()
