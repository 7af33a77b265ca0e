"""Every DDPM schedule table, computed in float64 with PyTorch from the formulas (Ho et al. 2020;
Nichol & Dhariwal 2021; Diffuser's `cosine_beta_schedule` and `GaussianDiffusion` buffers),
independently of the Rust code.

Module map: ``TABLES`` (the tables' names), the beta schedules (``linear_betas``,
``nichol_cosine_betas``, ``diffuser_cosine_betas``), ``tables_from_betas`` and
``schedule_tables`` (a ScheduleSpec as JSON and T to the tables, or ValueError).
tests/python/check_schedule.py drives it for server/tests/schedule_vs_pytorch.rs.
"""

import math

import numpy as np
import torch

F64 = torch.float64

TABLES = [
    "betas",
    "alphas",
    "alphas_cumprod",
    "alphas_cumprod_prev",
    "sqrt_alphas_cumprod",
    "sqrt_one_minus_alphas_cumprod",
    "sqrt_recip_alphas_cumprod",
    "sqrt_recipm1_alphas_cumprod",
    "posterior_variance",
    "posterior_log_variance_clipped",
    "posterior_mean_coef1",
    "posterior_mean_coef2",
]


def linear_betas(T):
    """DDPM's linear schedule, endpoints scaled by 1000 / T (improved-diffusion's form)."""
    scale = 1000.0 / T
    return torch.linspace(scale * 1e-4, scale * 0.02, T, dtype=F64)


def nichol_cosine_betas(T, s=0.008, max_beta=0.999):
    """improved-diffusion's betas_for_alpha_bar: beta_i = min(1 - f((i+1)/T) / f(i/T), max_beta)."""

    def f(u):
        return math.cos((u + s) / (1 + s) * math.pi / 2) ** 2

    return torch.tensor([min(1 - f((i + 1) / T) / f(i / T), max_beta) for i in range(T)], dtype=F64)


def diffuser_cosine_betas(T, s=0.008):
    """Diffuser's cosine_beta_schedule, in numpy float64 exactly as it is written there."""
    steps = T + 1
    x = np.linspace(0, steps, steps)
    alphas_cumprod = np.cos(((x / steps) + s) / (1 + s) * np.pi * 0.5) ** 2
    alphas_cumprod = alphas_cumprod / alphas_cumprod[0]
    betas = 1 - (alphas_cumprod[1:] / alphas_cumprod[:-1])
    return torch.tensor(np.clip(betas, a_min=0, a_max=0.999), dtype=F64)


def tables_from_betas(betas):
    """Every derived buffer, as Diffuser's GaussianDiffusion registers them, in float64."""
    betas = betas.to(F64)
    alphas = 1.0 - betas
    abar = torch.cumprod(alphas, dim=0)
    abar_prev = torch.cat([torch.ones(1, dtype=F64), abar[:-1]])
    posterior_variance = betas * (1.0 - abar_prev) / (1.0 - abar)
    return {
        "betas": betas,
        "alphas": alphas,
        "alphas_cumprod": abar,
        "alphas_cumprod_prev": abar_prev,
        "sqrt_alphas_cumprod": torch.sqrt(abar),
        "sqrt_one_minus_alphas_cumprod": torch.sqrt(1.0 - abar),
        "sqrt_recip_alphas_cumprod": torch.sqrt(1.0 / abar),
        "sqrt_recipm1_alphas_cumprod": torch.sqrt(1.0 / abar - 1),
        "posterior_variance": posterior_variance,
        "posterior_log_variance_clipped": torch.log(torch.clamp(posterior_variance, min=1e-20)),
        "posterior_mean_coef1": betas * torch.sqrt(abar_prev) / (1.0 - abar),
        "posterior_mean_coef2": (1.0 - abar_prev) * torch.sqrt(alphas) / (1.0 - abar),
    }


def betas_for(spec, T):
    kind = spec["kind"]
    if kind == "linear":
        return linear_betas(T)
    if kind == "cosine":
        return nichol_cosine_betas(T, spec.get("s", 0.008))
    if kind == "diffuser_cosine":
        return diffuser_cosine_betas(T, spec.get("s", 0.008))
    if kind == "betas":
        return torch.tensor(spec["betas"], dtype=F64)
    raise ValueError(f"unknown schedule kind {kind}")


def schedule_tables(spec, T):
    """The tables, or raises ValueError for a schedule with a beta outside (0, 1)."""
    betas = betas_for(spec, T)
    bad = ((betas <= 0) | (betas >= 1) | ~torch.isfinite(betas)).nonzero()
    if len(bad):
        i = int(bad[0])
        raise ValueError(f"beta[{i}] = {float(betas[i])} is not in (0, 1)")
    return tables_from_betas(betas)
