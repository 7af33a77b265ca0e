"""Shared facts and small statistics for the locomotion experiment (paper section 5.2).

Module map: `ENVS` (gymnasium ids, D4RL reference returns for the normalised score),
`normalized_score`, `welch` (Welch's t-test, two-sided, with its own Student-t CDF so that
no SciPy is needed), `paired` (paired-by-seed differences), `episodes` (split a D4RL-style
dict into episodes).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
POLICIES = HERE / "policies"
PLANNERS = HERE / "planners"

# D4RL's reference returns (docs/method.md section 7): score = 100 (R - random) / (expert - random).
ENVS = {
    "hopper": dict(id="Hopper-v5", random=-20.27, expert=3234.3),
    "halfcheetah": dict(id="HalfCheetah-v5", random=-280.18, expert=12135.0),
    "walker2d": dict(id="Walker2d-v5", random=1.63, expert=4592.3),
}


def normalized_score(env: str, ret) -> np.ndarray:
    e = ENVS[env]
    return 100.0 * (np.asarray(ret, dtype=float) - e["random"]) / (e["expert"] - e["random"])


def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta (Numerical Recipes, Lentz)."""
    tiny, qab, qap, qam = 1e-300, a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        m2 = 2 * m
        for aa in (m * (b - m) * x / ((qam + m2) * (a + m2)),
                   -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + aa / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta I_x(a, b)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    lbt = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(lbt) * _betacf(a, b, x) / a
    return 1.0 - math.exp(lbt) * _betacf(b, a, 1.0 - x) / b


def t_two_sided_p(t: float, df: float) -> float:
    """P(|T| >= |t|) for Student's t with df degrees of freedom."""
    if not math.isfinite(t):
        return 0.0
    return betainc(df / 2.0, 0.5, df / (df + t * t))


def welch(a, b) -> dict:
    """Welch's t-test of mean(a) - mean(b), two-sided."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    diff = a.mean() - b.mean()
    if va + vb == 0.0:
        return dict(diff=diff, t=math.inf if diff else 0.0, df=len(a) + len(b) - 2,
                    p=0.0 if diff else 1.0)
    t = diff / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    return dict(diff=diff, t=t, df=df, p=t_two_sided_p(t, df))


def paired(a, b) -> dict:
    """Paired-by-seed differences a - b: mean, standard error, wins, paired t-test p."""
    d = np.asarray(a, float) - np.asarray(b, float)
    se = d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else math.nan
    t = d.mean() / se if se > 0 else (math.inf if d.mean() else 0.0)
    return dict(mean=d.mean(), se=se, wins=int((d > 0).sum()), n=len(d),
                p=t_two_sided_p(t, len(d) - 1) if len(d) > 1 else math.nan)


def episodes(data: dict) -> list[tuple[int, int]]:
    """(start, end) row ranges of the episodes of a D4RL-style dict (terminals/timeouts end one)."""
    ends = np.flatnonzero(np.logical_or(data["terminals"], data["timeouts"]))
    starts = np.concatenate([[0], ends[:-1] + 1])
    return [(int(s), int(e) + 1) for s, e in zip(starts, ends)]
