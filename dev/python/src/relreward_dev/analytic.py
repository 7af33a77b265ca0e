"""The exact eps-prediction model of data N(m, I), as a TorchScript-able module.

Under the VP forward process x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps with x0 ~ N(m, I),
x_t ~ N(sqrt(abar_t) m, I), so the score is -(x_t - sqrt(abar_t) m) and the exact (MMSE) noise
prediction is

    eps(x_t, t) = sqrt(1 - abar_t) (x_t - sqrt(abar_t) m).

``AnalyticGaussianEps.forward(x, t)`` computes that with the schedule's abar table (from
``schedule.schedule_tables``, float64 cast to float32) as a buffer; t is int64 [B] in 0..T,
0-based as in Diffuser. With ``nan_beyond`` R the output is NaN at every item with an entry
|x| > R (a model that goes bad only on some inputs). tests/python/analytic_gaussian.py and
export_models.py export it for the sampling, registry and reward-recovery tests.
"""

import math
from typing import List

import torch


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
