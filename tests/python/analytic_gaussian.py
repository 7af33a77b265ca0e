#!/usr/bin/env python3
"""Exports an exact eps-prediction diffusion model for data N(m, I), as TorchScript plus a
DiffusionManifest JSON, for tests.

Under the VP forward process x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps with x0 ~ N(m, I),
x_t ~ N(sqrt(abar_t) m, I), so the score is -(x_t - sqrt(abar_t) m) and the exact (MMSE) noise
prediction is

    eps(x_t, t) = sqrt(1 - abar_t) (x_t - sqrt(abar_t) m).

The module's forward(x, t) computes that with the schedule's abar table baked in as a buffer
(from check_schedule.py's float64 tables, cast to float32). t is int64 [B] in 0..T, 0-based as
in Diffuser.

With --nan-beyond R the output is NaN at every item with an entry |x| > R: a model that goes
bad only on some inputs (finite at the upload's probe, x = 0), for tests of training jobs
whose targets are not always finite.

Writes OUT/model.pt and OUT/manifest.json.

    .venv/bin/python tests/python/analytic_gaussian.py --out DIR --mean 1,-2,0.5 \
        --schedule cosine --T 100
    # trajectories [H, action_dim + obs_dim]; --mean gives one transition, repeated over H:
    .venv/bin/python tests/python/analytic_gaussian.py --out DIR --mean 0,0,1 \
        --space trajectory --horizon 8 --action-dim 1 --schedule diffuser_cosine --T 20
"""

import argparse
import json
import math
import os
import sys
from typing import List

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from check_schedule import schedule_tables  # noqa: E402


class AnalyticGaussianEps(torch.nn.Module):
    def __init__(self, alphas_cumprod: torch.Tensor, mean: torch.Tensor, nan_beyond: float = float("inf")):
        super().__init__()
        self.nan_beyond = nan_beyond
        self.register_buffer("sqrt_abar", alphas_cumprod.sqrt().to(torch.float32))
        self.register_buffer("sqrt_one_minus_abar", (1.0 - alphas_cumprod).sqrt().to(torch.float32))
        self.register_buffer("mean", mean.to(torch.float32))

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        shape: List[int] = [t.shape[0]] + [1] * (x.dim() - 1)
        sa = self.sqrt_abar.index_select(0, t).reshape(shape)
        s1m = self.sqrt_one_minus_abar.index_select(0, t).reshape(shape)
        eps = s1m * (x - sa * self.mean)
        if math.isinf(self.nan_beyond):
            # The exact model, without the test-only mask's ops (benchmarks time these models).
            return eps
        bad = (x.abs() > self.nan_beyond).flatten(1).any(1).reshape(shape)
        return torch.where(bad, torch.full_like(eps, float("nan")), eps)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--mean", required=True, help="comma-separated mean: one item, or one transition")
    p.add_argument("--schedule", default="cosine", choices=["cosine", "diffuser_cosine", "linear"])
    p.add_argument("--s", type=float, default=0.008, help="cosine offset s")
    p.add_argument("--T", type=int, default=100, help="number of diffusion steps")
    p.add_argument("--space", default="sample", choices=["sample", "trajectory"])
    p.add_argument("--horizon", type=int, default=0, help="trajectory horizon H")
    p.add_argument("--action-dim", type=int, default=0, help="trajectory action_dim")
    p.add_argument("--nan-beyond", type=float, default=float("inf"),
                   help="output NaN for items with an entry |x| above this (default: never)")
    args = p.parse_args()

    mean = [float(v) for v in args.mean.split(",")]
    spec = {"kind": args.schedule} if args.schedule == "linear" else {"kind": args.schedule, "s": args.s}
    tables = schedule_tables(spec, args.T)

    if args.space == "sample":
        space = {"kind": "sample", "shape": [len(mean)]}
        mean_t = torch.tensor(mean, dtype=torch.float64)
    else:
        obs_dim = len(mean) - args.action_dim
        if args.horizon <= 0 or obs_dim < 0:
            p.error("trajectory: need --horizon > 0 and --action-dim <= len(mean)")
        space = {"kind": "trajectory", "horizon": args.horizon, "action_dim": args.action_dim, "obs_dim": obs_dim}
        mean_t = torch.tensor(mean, dtype=torch.float64).repeat(args.horizon, 1)

    module = torch.jit.script(AnalyticGaussianEps(tables["alphas_cumprod"], mean_t, args.nan_beyond))
    os.makedirs(args.out, exist_ok=True)
    module.save(os.path.join(args.out, "model.pt"))
    manifest = {
        "parametrization": "epsilon",
        "schedule": spec,
        "n_timesteps": args.T,
        "clip_denoised": False,
        "space": space,
        "normalizer": {"kind": "identity"},
    }
    with open(os.path.join(args.out, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=2)


if __name__ == "__main__":
    main()
