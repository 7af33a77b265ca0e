#!/usr/bin/env python3
"""Exports an exact eps-prediction diffusion model for data N(m, I), as TorchScript plus a
DiffusionManifest JSON, for tests.

Under the VP forward process x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps with x0 ~ N(m, I),
x_t ~ N(sqrt(abar_t) m, I), so the score is -(x_t - sqrt(abar_t) m) and the exact (MMSE) noise
prediction is

    eps(x_t, t) = sqrt(1 - abar_t) (x_t - sqrt(abar_t) m).

The module (relreward_dev.analytic.AnalyticGaussianEps, the development package, dev/python)
computes that in forward(x, t) with the schedule's abar table baked in as a buffer (from
relreward_dev.schedule's float64 tables, cast to float32). t is int64 [B] in 0..T, 0-based as
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
import os

import torch

from relreward_dev.analytic import AnalyticGaussianEps
from relreward_dev.schedule import schedule_tables


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
