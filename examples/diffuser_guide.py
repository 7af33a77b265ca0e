#!/usr/bin/env python3
"""A Diffuser-style guided sampler whose value guide is a relreward reward model.

Diffuser plans with ``n_step_guided_p_sample``: at every denoising step it asks its value guide
for ``y, grad = guide.gradients(x, cond, t)`` on the batch of noisy plans (normalized units),
adds ``scale * grad`` (times the posterior variance with ``scale_grad_by_std``), and takes the
denoising step. ``relreward.guide.RewardGuide`` has that interface and answers over one
GradientStream, so a Diffuser user swaps their trained ValueFunction for a relreward reward by
changing the line that builds the guide::

    # guide = ValueGuide(value_function)                           # Diffuser
    guide = RewardGuide(relreward.Client(endpoint), "maze-reward")  # relreward

The sampler below is Diffuser's loop in numpy: Diffuser's cosine schedule with the reward
model's T, and as the denoiser the exact posterior mean for data N(0, s^2 I) in normalized
units, so the example needs no diffusion network. It runs the loop twice from the same noise,
unguided and guided, and prints one JSON object with the mean rho(x_0) of each: guidance moves
the plans toward what the reward prefers.

    .venv/bin/python examples/diffuser_guide.py --endpoint 127.0.0.1:50051 --model maze-reward
"""

import argparse
import json
import os

import numpy as np

import relreward
from relreward.guide import RewardGuide


def cosine_betas(n: int, s: float = 0.008) -> np.ndarray:
    """Diffuser's cosine_beta_schedule."""
    x = np.linspace(0, n + 1, n + 1) / (n + 1)
    abar = np.cos(((x + s) / (1 + s)) * np.pi * 0.5) ** 2
    abar = abar / abar[0]
    return np.clip(1 - abar[1:] / abar[:-1], 0, 0.999)


def guided_sample(guide, shape, n_timesteps, *, scale, n_guide_steps=2, t_stopgrad=2, scale_grad_by_std=True,
                  data_std=0.5, seed=0):
    """Diffuser's p_sample_loop with n_step_guided_p_sample, over numpy arrays [B, H, D]."""
    betas = cosine_betas(n_timesteps)
    alphas = 1 - betas
    abar = np.cumprod(alphas)
    abar_prev = np.append(1.0, abar[:-1])
    post_var = betas * (1 - abar_prev) / (1 - abar)
    coef1 = betas * np.sqrt(abar_prev) / (1 - abar)
    coef2 = (1 - abar_prev) * np.sqrt(alphas) / (1 - abar)
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(shape).astype(np.float32)
    for i in reversed(range(n_timesteps)):
        t = np.full(shape[0], i, dtype=np.int64)
        if guide is not None:
            for _ in range(n_guide_steps):
                _, grad = guide.gradients(x, None, t)
                grad = np.array(grad)
                if scale_grad_by_std:
                    grad = post_var[i] * grad
                if i < t_stopgrad:
                    grad[:] = 0
                x = (x + scale * grad).astype(np.float32)
        # The denoiser: E[x0 | x_t] for x0 ~ N(0, data_std^2 I), clipped as clip_denoised.
        x0 = np.clip(np.sqrt(abar[i]) * data_std**2 / (abar[i] * data_std**2 + 1 - abar[i]) * x, -1, 1)
        mean = coef1[i] * x0 + coef2[i] * x
        noise = rng.standard_normal(shape).astype(np.float32) if i > 0 else 0.0
        x = (mean + np.sqrt(post_var[i]) * noise).astype(np.float32)
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--endpoint", default=os.environ.get("RELREWARD_ENDPOINT", "127.0.0.1:50051"))
    ap.add_argument("--model", required=True, help="a reward model")
    ap.add_argument("--token", default=os.environ.get("RELREWARD_TOKEN"))
    ap.add_argument("--scale", type=float, default=0.1, help="guidance scale (Diffuser's `scale`)")
    ap.add_argument("--no-scale-grad-by-std", action="store_true")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    client = relreward.Client(args.endpoint, token=args.token)
    model = client.get_model(args.model).reward
    shape = (args.batch, *model.input_shape)
    guide = RewardGuide(client, args.model)  # the one line that replaces Diffuser's ValueGuide
    common = dict(scale=args.scale, scale_grad_by_std=not args.no_scale_grad_by_std, seed=args.seed)
    with guide:
        plain = guided_sample(None, shape, model.n_timesteps, **common)
        guided = guided_sample(guide, shape, model.n_timesteps, **common)
        rho_plain = guide(plain, None, np.zeros(args.batch, np.int64))
        rho_guided = guide(guided, None, np.zeros(args.batch, np.int64))
    client.close()
    print(json.dumps({
        "batch": args.batch,
        "scale": args.scale,
        "rho_unguided": float(np.mean(rho_plain)),
        "rho_guided": float(np.mean(rho_guided)),
        "fraction_improved": float(np.mean(rho_guided > rho_plain)),
    }))


if __name__ == "__main__":
    main()
