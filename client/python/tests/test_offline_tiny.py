"""The offline-RL harness (experiments/locomotion/offline.py) end to end at a tiny size: a dataset
rolled out in a small gymnasium environment whose rows have the `tiny` reward's layout (2 action
+ 2 observation values), relabelled by the tiny reward `rw` and a discriminator trained for a
few steps on the server, d3rlpy's IQL trained 60 steps per agent (two seeds on each of the four
arms, a few hundred steps in all) and evaluated. Nothing is expected to learn; the test checks
the plumbing: the relabelled rewards are the Score of the windows docs/relabel.md defines, every
arm trains and evaluates on the same seeds, a seed reruns to the same returns, and the summary
and table carry every arm. Skipped when d3rlpy is not installed (tests/python/requirements.txt
pins it; `make setup` installs it); the normalisation test needs no d3rlpy."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import relreward


class Drift(gym.Env):
    """A point in the plane moved by the action (velocity in [-1, 1]^2), rewarded for closeness
    to the origin; 20 steps an episode, no termination (as HalfCheetah)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        return self.x.copy(), {}

    def step(self, action):
        self.x = (self.x + 0.1 * np.clip(action, -1, 1)).astype(np.float32)
        return self.x.copy(), -float(np.linalg.norm(self.x)), False, False, {}


def make_env():
    return gym.wrappers.TimeLimit(Drift(), max_episode_steps=20)


def rollouts(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    env = make_env()
    cols = {k: [] for k in ("observations", "actions", "rewards", "terminals", "timeouts")}
    for _ in range(n):
        obs, _ = env.reset(seed=int(rng.integers(1 << 20)))
        done = False
        while not done:
            act = rng.uniform(-1, 1, 2).astype(np.float32)
            nxt, r, term, trunc, _ = env.step(act)
            for k, v in zip(cols, (obs, act, r, term, trunc and not term)):
                cols[k].append(v)
            obs, done = nxt, term or trunc
    out = {k: np.asarray(v) for k, v in cols.items()}
    for k in ("observations", "actions", "rewards"):
        out[k] = out[k].astype(np.float32)
    return out


def test_offline_harness_runs_every_arm_on_relabelled_data(client, tiny, tmp_path):
    pytest.importorskip("d3rlpy")
    import offline

    data = rollouts(6, seed=0)
    src = tmp_path / "drift-medium-replay.npz"
    np.savez(src, **data)
    client.upload_dataset("offline-expert", rollouts(3, seed=1))
    job = client.submit_job(relreward.DiscriminatorJob(
        output_model="offline-disc", base_dataset=tiny.dataset, expert_dataset="offline-expert",
        diffusion_model=tiny.base, architecture=("windowed_mlp", {"window": 4, "hidden": [8]}), seed=1,
        optimization=relreward.Optimization(steps=4, batch_size=8)))
    assert client.wait_job(job.id).state == "succeeded"

    rewards = offline.arm_rewards(client, src, {"rho": tiny.reward, "discriminator": "offline-disc"}, tmp_path)
    assert list(rewards) == list(offline.ARMS)
    n = len(data["actions"])
    np.testing.assert_array_equal(rewards["true"], data["rewards"])
    np.testing.assert_array_equal(rewards["constant"], np.zeros(n, np.float32))
    # Row 30 (episode 2 spans rows 20-39): the item of the reward's horizon ending there, scored directly.
    i = 30
    assert i - tiny.horizon + 1 >= 20
    rows = np.concatenate([data["actions"], data["observations"]], 1)
    direct = client.score(tiny.reward, rows[i - tiny.horizon + 1:i + 1][None], per_window=True).per_window[0, -1]
    assert rewards["rho"][i] == pytest.approx(direct, rel=1e-5, abs=1e-6)
    with np.load(tmp_path / "drift-medium-replay-rho.npz") as z:
        np.testing.assert_array_equal(z["rewards"], rewards["rho"])
        np.testing.assert_array_equal(z["rewards_original"], data["rewards"])
    assert rewards["discriminator"].std() > 0 and not np.allclose(rewards["discriminator"], rewards["rho"])

    log = []
    rows = offline.run_arms(data, rewards, make_env, seeds=2, steps=60, eval_episodes=3, batch_size=16,
                            hidden=(16, 16), log=log.append)
    assert [(r["arm"], r["seed"]) for r in rows] == [(a, s) for a in offline.ARMS for s in (0, 1)]
    assert all(len(r["returns"]) == 3 and all(math.isfinite(x) and x < 0 for x in r["returns"]) for r in rows)
    assert len(log) == 8 and rows[2]["returns"] != rows[3]["returns"]
    # Same evaluation seeds for every agent: episode k starts at the same state, so two agents
    # that happened to act alike would score alike; and a seed reruns to the same returns.
    again = offline.run_arms(data, {"rho": rewards["rho"]}, make_env, seeds=1, steps=60, eval_episodes=3,
                             batch_size=16, hidden=(16, 16), log=log.append)
    assert again[0]["returns"] == rows[2]["returns"]

    summary = offline.summarize(rows, None)
    assert not summary["normalized"] and list(summary["arms"]) == list(offline.ARMS)
    for a in ("true", "rho", "discriminator"):
        w = summary["arms"][a]["vs_constant"]
        assert 0.0 <= w["p"] <= 1.0 and w["diff"] == pytest.approx(
            summary["arms"][a]["mean"] - summary["arms"]["constant"]["mean"])
    assert "vs_constant" not in summary["arms"]["constant"]
    text = offline.table("drift", summary)
    assert all(f"| {a} | 6 |" in text for a in offline.ARMS)


def test_offline_normalises_with_d4rl_reference_scores():
    import offline

    # D4RL's random and expert returns score 0 and 100; their midpoint 50.
    rows = [dict(arm="rho", seed=0, returns=[-280.18, 12135.0]),
            dict(arm="constant", seed=0, returns=[5927.41, 5927.41])]
    s = offline.summarize(rows, "halfcheetah")
    assert s["normalized"]
    assert s["arms"]["rho"]["mean"] == pytest.approx(50.0, abs=1e-3)
    assert s["arms"]["constant"]["mean"] == pytest.approx(50.0, abs=1e-3)
