#!/usr/bin/env python3
"""Exports the TorchScript fixtures of the model-registry tests (tests/tests/models.rs).

Writes into OUT:

- ``gaussian.pt`` + ``gaussian.json``: the exact eps-model for data N(m, I) from
  ``relreward_dev.analytic``, as ``analytic_gaussian.py`` exports it (eps = sqrt(1 - abar_t) (x_t - sqrt(abar_t) m), the schedule's abar
  table baked in as a buffer) over samples of shape [len(m)]. No parameters, three buffers.
- ``linear.pt``: eps = W x + b with one ``nn.Linear(D, D)`` over the last dimension (D
  parameters squared plus D), for checking the parameter count; any item shape ending in D.
- ``wrong_shape.pt``: returns x without its last coordinate (output shape != input shape).
- ``nan.pt``: returns NaN everywhere.
- ``raises.pt``: raises ``RuntimeError("deliberate failure: this module always raises")``.

The schedule and T of the Gaussian model are arguments; the tests build the matching
DiffusionManifest on their side and compare against ``gaussian.json``.

    .venv/bin/python tests/python/export_models.py --out DIR --mean 1,-2,0.5 \
        --schedule cosine --T 50
"""

import argparse
import json
import os

import torch

from relreward_dev.analytic import AnalyticGaussianEps
from relreward_dev.schedule import schedule_tables

RAISE_MESSAGE = "deliberate failure: this module always raises"


class LinearEps(torch.nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.proj = torch.nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return self.proj(x)


class WrongShape(torch.nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x[..., :-1]


class NaNOutput(torch.nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return torch.full_like(x, float("nan"))


class Raises(torch.nn.Module):
    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        if t.numel() >= 0:
            raise RuntimeError("deliberate failure: this module always raises")
        return x


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--mean", default="1,-2,0.5", help="comma-separated mean of the Gaussian data")
    p.add_argument("--schedule", default="cosine", choices=["cosine", "diffuser_cosine", "linear"])
    p.add_argument("--s", type=float, default=0.008, help="cosine offset s")
    p.add_argument("--T", type=int, default=50, help="number of diffusion steps")
    p.add_argument("--linear-dim", type=int, default=3, help="D of linear.pt")
    args = p.parse_args()

    torch.manual_seed(0)
    os.makedirs(args.out, exist_ok=True)
    mean = [float(v) for v in args.mean.split(",")]
    spec = {"kind": args.schedule} if args.schedule == "linear" else {"kind": args.schedule, "s": args.s}
    tables = schedule_tables(spec, args.T)

    gaussian = AnalyticGaussianEps(tables["alphas_cumprod"], torch.tensor(mean, dtype=torch.float64))
    torch.jit.script(gaussian).save(os.path.join(args.out, "gaussian.pt"))
    manifest = {
        "parametrization": "epsilon",
        "schedule": spec,
        "n_timesteps": args.T,
        "clip_denoised": False,
        "space": {"kind": "sample", "shape": [len(mean)]},
        "normalizer": {"kind": "identity"},
    }
    with open(os.path.join(args.out, "gaussian.json"), "w") as f:
        json.dump(manifest, f, indent=2)

    torch.jit.script(LinearEps(args.linear_dim)).save(os.path.join(args.out, "linear.pt"))
    torch.jit.script(WrongShape()).save(os.path.join(args.out, "wrong_shape.pt"))
    torch.jit.script(NaNOutput()).save(os.path.join(args.out, "nan.pt"))
    torch.jit.script(Raises()).save(os.path.join(args.out, "raises.pt"))


if __name__ == "__main__":
    main()
