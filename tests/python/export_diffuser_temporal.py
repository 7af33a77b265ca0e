"""A Diffuser-style TemporalUnet checkpoint for `relreward model import`, and its outputs.

    python export_diffuser_temporal.py OUTDIR [--dim 8] [--dim-mults 1,2] [--horizon 8]
                                       [--transition-dim 5] [--seed 0]

Builds Diffuser's `GaussianDiffusion(TemporalUnet(...))` layout in PyTorch (the TemporalUnet of
relreward_dev.nets, the development package's, which follows `diffuser/models/temporal.py`
module by module, wrapped as Diffuser's `GaussianDiffusion` holds it: the network under
`model.`, schedule buffers beside it), draws every parameter at random (GroupNorm affines
included, so that none is at its default), and writes to OUTDIR:

- `state_dict.npz`: the export step of the documented recipe, i.e. what a user runs on a
  Diffuser checkpoint (`torch.load(path)["ema"]` for a trained one):

      np.savez("state_dict.npz", **{k: v.cpu().numpy() for k, v in state_dict.items()})

- `check.safetensors`: inputs `x` [B, H, D] float32, `t` [B] int64 and the network's output
  `y` (PyTorch, eval mode) for the Rust side to compare with.

Needs only torch, numpy and relreward_dev.
"""

import argparse
import os

import numpy as np
import torch
from torch import nn

from relreward_dev.nets import TemporalUnet
from relreward_dev.safetensors import write_safetensors


class GaussianDiffusion(nn.Module):
    """The part of Diffuser's GaussianDiffusion that shapes its state_dict."""

    def __init__(self, model, n_timesteps):
        super().__init__()
        self.model = model
        betas = torch.linspace(1e-4, 2e-2, n_timesteps)
        self.register_buffer("betas", betas)
        self.register_buffer("alphas_cumprod", torch.cumprod(1 - betas, 0))
        self.register_buffer("loss_weights", torch.ones(8, 5))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--dim", type=int, default=8)
    ap.add_argument("--dim-mults", default="1,2")
    ap.add_argument("--horizon", type=int, default=8)
    ap.add_argument("--transition-dim", type=int, default=5)
    ap.add_argument("--n-timesteps", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    dim_mults = tuple(int(m) for m in args.dim_mults.split(","))
    net = TemporalUnet(args.transition_dim, dim=args.dim, dim_mults=dim_mults)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn_like(p) * 0.3)
    diffusion = GaussianDiffusion(net, args.n_timesteps).eval()
    os.makedirs(args.out, exist_ok=True)
    state_dict = diffusion.state_dict()
    np.savez(os.path.join(args.out, "state_dict.npz"), **{k: v.cpu().numpy() for k, v in state_dict.items()})

    x = torch.randn(4, args.horizon, args.transition_dim)
    t = torch.tensor([0, 1, args.n_timesteps // 2, args.n_timesteps - 1], dtype=torch.int64)
    with torch.no_grad():
        y = net(x, t)
    write_safetensors(os.path.join(args.out, "check.safetensors"), {"x": x, "t": t, "y": y.float()})
    print(f"{len(state_dict)} tensors, {sum(p.numel() for p in net.parameters())} parameters, "
          f"max |y| {y.abs().max().item():.3f}")


if __name__ == "__main__":
    main()
