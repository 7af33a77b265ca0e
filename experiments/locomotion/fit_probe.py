"""How Algorithm 1's choice of x_t changes the reward's fit and the closed loop: a PyTorch probe.

Trains a relative reward the way the service's reward job does (the ValueFunction encoder of
relreward_dev.reward_nets, Adam, the alignment loss weighted 10 on the first action and
0 on the first observation, the unclipped target mu_expert - mu_base of the committed planners) on
the union of the medium-replay and expert windows, either on the paper's x_t (the whole window
noised, `--x-t noised`) or with the current state kept clean (`--x-t inpainted`, the service's
`inpaint_condition`), then reports diagnose.py's fit on the base planner's own samples and, with
`--episodes`, closed-loop episodes on the sweep seeds (10000..) guided on the posterior mean and
choosing the plan by rho. A probe, not the experiment: steer.py trains through the service.

    python experiments/locomotion/fit_probe.py --env walker2d --data DIR --x-t inpainted --steps 6000 --episodes 2
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import diagnose
from common import ENVS, PLANNERS, normalized_score
from planner import Planner, act_many, run_episodes
from relreward_dev.reward_nets import build


def train(base: Planner, expert: Planner, win: torch.Tensor, inpainted: bool, steps: int, seed: int, log) -> torch.nn.Module:
    A, s = base.act_dim, base.sched
    H, D = win.shape[1:]
    torch.manual_seed(seed)
    rho = build({"kind": "value_function", "widths": [32, 64, 128]}, [H, D])
    opt = torch.optim.Adam(rho.parameters(), lr=2e-4)
    w = torch.ones(H, D)
    w[0, :A], w[0, A:] = 10.0, 0.0
    sa, s1 = (torch.tensor(v, dtype=torch.float32) for v in (s.sqrt_abar, s.sqrt_1m_abar))
    c1 = torch.tensor(s.coef1, dtype=torch.float32)
    for p in list(base.net.parameters()) + list(expert.net.parameters()):
        p.requires_grad_(False)
    g = torch.Generator().manual_seed(seed)
    for i in range(steps):
        x0 = win[torch.randint(len(win), (128,), generator=g)]
        t = torch.randint(s.T, (128,), generator=g)
        xt = sa[t, None, None] * x0 + s1[t, None, None] * torch.randn(x0.shape, generator=g)
        if inpainted:
            xt[:, 0, A:] = x0[:, 0, A:]
        with torch.no_grad():
            y = c1[t, None, None] * (expert.net(xt, t) - base.net(xt, t))
        xr = xt.clone().requires_grad_(True)
        (gr,) = torch.autograd.grad(rho(xr, t).sum(), xr, create_graph=True)
        loss = ((gr - y) ** 2 * w).flatten(1).sum(1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i % 500 == 0:
            log(f"step {i} loss {loss.item():.4f}")
    rho.eval()
    for p in rho.parameters():
        p.requires_grad_(False)
    return rho


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", required=True, choices=sorted(ENVS))
    p.add_argument("--data", type=Path, required=True, help="directory of data.py's npz files")
    p.add_argument("--planners", type=Path, default=PLANNERS)
    p.add_argument("--x-t", choices=("noised", "inpainted"), required=True)
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=0, help="closed-loop episodes per omega on seeds 10000..")
    p.add_argument("--omegas", default="1.0,0.3")
    p.add_argument("--max-steps", type=int, default=300)
    a = p.parse_args()
    torch.set_num_threads(1)
    base = Planner.load(a.planners / f"{a.env}-medium-replay")
    expert = Planner.load(a.planners / f"{a.env}-expert")
    win = torch.tensor(np.concatenate([base.windows(dict(np.load(a.data / f"{a.env}-{k}.npz")))
                                       for k in ("medium-replay", "expert")]))
    t0 = time.time()
    rho = train(base, expert, win, a.x_t == "inpainted", a.steps, a.seed, lambda m: print(m, file=sys.stderr, flush=True))
    rng = np.random.default_rng(0)
    wb = diagnose.windows(base, a.data / f"{a.env}-medium-replay.npz", 64, rng)
    fit = diagnose.fit(base, expert, rho, wb, 1.0, rng)
    out = dict(env=a.env, x_t=a.x_t, steps=a.steps, train_seconds=round(time.time() - t0, 1),
               fit={r["t"]: dict(rel_err_action=round(r["planner_rel_err_action"], 3),
                                 rel_err_free=round(r["planner_rel_err"], 3),
                                 cos_action=round(r["planner_cos_action"], 3))
                    for r in fit if r["t"] in (0, 2, 5, 10, base.sched.T - 1)})
    seeds = list(range(10_000, 10_000 + a.episodes))
    # Unsteered first (no guidance, the first plan), then each omega.
    for om in [None, *(float(v) for v in a.omegas.split(","))] if a.episodes else ():
        def decide(obs, sd, step, om=om):
            if om is None:
                return act_many(base, obs, 16, [v * 100_003 + step for v in sd])
            return act_many(base, obs, 16, [v * 100_003 + step for v in sd], lambda x, t: diagnose.grad_rho(rho, x, t),
                            om, 0, lambda x: diagnose.rho_value(rho, x, 0), "mean")
        eps = run_episodes(lambda: gym.make(ENVS[a.env]["id"], max_episode_steps=a.max_steps), decide, seeds,
                           a.max_steps)
        out["unsteered" if om is None else f"omega_{om}"] = [round(float(normalized_score(a.env, e["ret"])), 3)
                                                             for e in eps]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
