"""External-planner cost: time per environment step and the share spent waiting for the service,
against the same loop with the reward computed in this process by PyTorch.

Module map: `torch_reward` (the stored reward rebuilt in PyTorch from what the service's
DownloadModel hands out: its safetensors weights and manifest, the architecture of
relreward_dev.reward_nets), `main` (checks that both gradient sources agree on
random plans, then runs the reward-steered arm with each on the same seeds, one episode at a
time and all in lockstep (`--batch-episodes`), and prints JSON).

Run after steer.py, on its work directory (a server is started on the same data directory):

    python experiments/locomotion/bench.py --env hopper --work steer-out/hopper --episodes 3
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import torch

import relreward
from planner import Planner
from relreward_dev.reward_nets import build
from relreward_dev.safetensors import read_safetensors
from steer import Config, run_arm, start_server


def torch_reward(client: relreward.Client, name: str) -> torch.nn.Module:
    with tempfile.TemporaryDirectory(prefix="relreward-bench-") as tmp:
        got = client.download_model(name, tmp)
        man = got.manifest
        sp = man["space"]
        net = build(man["architecture"], [sp["horizon"], sp["action_dim"] + sp["obs_dim"]])
        net.load_state_dict(read_safetensors(got.path), strict=True)
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", required=True)
    p.add_argument("--work", type=Path, required=True, help="steer.py's --work directory")
    p.add_argument("--planners", type=Path, default=Path(__file__).resolve().parent / "planners")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--seed-base", type=int, default=30_000)
    p.add_argument("--batch-episodes", default="1,0",
                   help="lockstep settings to time (steer.py's --batch-episodes; 0: all episodes at once)")
    a = p.parse_args()
    torch.set_num_threads(1)
    res = json.loads((a.work / f"{a.env}-results.json").read_text())
    # The reward arm's rule as steer.py chose or was told it ("mean" in results from before it
    # was recorded).
    names, omega, ts, rule = res["names"], res["omega"], res["t_stopgrad"], res.get("guide_at", "mean")

    def torch_source(model):
        def grad_fn(x, t):
            xt = torch.tensor(x, dtype=torch.float32, requires_grad=True)
            rho = net(xt, torch.full((x.shape[0],), int(t), dtype=torch.int64))
            (g,) = torch.autograd.grad(rho.sum(), xt)
            return g.numpy().astype(np.float64)

        def score_fn(x):
            with torch.no_grad():
                return net(torch.tensor(x, dtype=torch.float32), torch.zeros(x.shape[0], dtype=torch.int64)).numpy()
        return grad_fn, score_fn

    server = start_server(a.work / "server-data")
    try:
        client = relreward.Client(server.addr)
        net = torch_reward(client, names["reward"])
        planner = Planner.load(a.planners / f"{a.env}-medium-replay")
        # Both sources compute the same gradient (float32 on both sides).
        x = np.random.default_rng(0).uniform(-1, 1, (16, planner.horizon, planner.act_dim + planner.obs_dim))
        g_srv = client.gradient(names["reward"], x.astype(np.float32), 5, units="normalized").gradient
        g_pt = torch_source(None)[0](x, 5)
        agree = float(np.abs(g_srv - g_pt).max() / (np.abs(g_pt).max() + 1e-12))
        seeds = range(a.seed_base, a.seed_base + a.episodes)
        out = dict(env=a.env, guide_at=rule, omega=omega, t_stopgrad=ts, gradient_max_rel_diff=agree)
        for k in (int(v) for v in a.batch_episodes.split(",")):
            cfg = Config(env=a.env, data=Path("."), planners=a.planners, work=a.work, max_steps=a.max_steps,
                         batch_episodes=k, guide_at=rule, log=lambda s: print(s, flush=True))
            for label, src in (("service", None), ("pytorch", torch_source)):
                eps = run_arm("reward", "external", seeds, planner, client, names, cfg, omega, ts, grad_source=src)
                steps = sum(e["length"] for e in eps)
                out[f"{label} batch_episodes={k}"] = dict(
                    ms_per_step=1e3 * sum(e["seconds"] for e in eps) / steps,
                    wait_ms_per_step=1e3 * sum(e["wait_seconds"] for e in eps) / steps,
                    wait_share=sum(e["wait_seconds"] for e in eps) / sum(e["seconds"] for e in eps),
                    steps=steps, returns=[round(e["ret"], 3) for e in eps])
        print(json.dumps(out, indent=1))
    finally:
        server.stop(grace=30)


if __name__ == "__main__":
    main()
