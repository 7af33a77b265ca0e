"""A stored reward model as relreward serves it, in PyTorch: the network on the downloaded
weights, the manifest's normalizer as (offset, scale) and, for an Algorithm 2 reward, the
per-step input standardisation. The reference server (bench/reference/grpc_server.py) and the
benchmarks that compare relreward with in-process PyTorch (tests/bench/rl_wrapper.py) share it.
"""

from __future__ import annotations

import pathlib

import numpy as np
import torch

from relreward_dev.nets import item_shape
from relreward_dev.reward_nets import build
from relreward_dev.safetensors import read_safetensors

#: The step tables' file, beside the weights, as relreward's download writes it.
STEP_NORM_FILE = "step_norm.safetensors"
#: Ranges narrower than this normalize to 0 (relreward's engine/normalizer.rs MIN_RANGE).
MIN_RANGE = 1e-12


class RewardModel:
    """rho_theta with its manifest: normalizer, T, item shape, optional step tables."""

    def __init__(self, name: str, manifest: dict, weights: pathlib.Path):
        self.name = name
        self.item_shape = item_shape(manifest["space"])
        self.n_timesteps = int(manifest["n_timesteps"])
        self.net = build(manifest["architecture"], self.item_shape)
        self.net.load_state_dict(read_safetensors(weights), strict=True)
        self.net.eval()
        for p in self.net.parameters():
            p.requires_grad_(False)  # only grad_x is wanted
        self.offset, self.scale = affine(manifest.get("normalizer", {"kind": "identity"}), manifest["space"])
        self.step_norm = None
        if manifest.get("step_normalization"):
            tables = read_safetensors(weights.parent / STEP_NORM_FILE)
            self.step_norm = (tables["input_mean"].float(), tables["input_std"].float())

    def rho(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        if self.step_norm is not None:
            mean, std = self.step_norm
            x = (x - mean[t]) / std[t]
        return self.net(x, t)


def affine(normalizer: dict, space: dict):
    """(offset, scale) float32 tensors broadcasting over an item, x_norm = (x - offset) * scale;
    (None, None) for the identity. Computed in float64 and rounded once, as relreward does."""
    kind = normalizer["kind"]
    if kind == "identity":
        return None, None
    if kind == "limits":
        lo, hi = np.asarray(normalizer["min"], np.float64), np.asarray(normalizer["max"], np.float64)
        offset = (lo + hi) / 2.0
        scale = np.where(hi - lo > MIN_RANGE, 2.0 / np.maximum(hi - lo, MIN_RANGE), 0.0)
    elif kind == "gaussian":
        offset = np.asarray(normalizer["mean"], np.float64)
        std = np.asarray(normalizer["std"], np.float64)
        scale = np.where(std > MIN_RANGE, 1.0 / np.maximum(std, MIN_RANGE), 0.0)
    else:
        raise ValueError(f"unknown normalizer kind {kind}")
    # Trajectories: per coordinate along the last axis; samples: over all item elements.
    shape = [-1] if space["kind"] == "trajectory" else list(space["shape"])
    return (
        torch.from_numpy(offset.astype(np.float32)).reshape(shape),
        torch.from_numpy(scale.astype(np.float32)).reshape(shape),
    )
