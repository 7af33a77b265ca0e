"""Quality of a reward extracted from the analytic Gaussian pair (tests/bench/amortised.sh): the
cosine between grad_x rho (the server's Gradient RPC, normalized units; the models' normalizer
is the identity) and the exact target, which for base N(0, I) and expert N(m, I) is c_t m for a
positive c_t, so its direction is m at every t. Points are drawn from the union of the two
marginals at t, x_t ~ N(sqrt(abar_t) {0 or m}, I), as server/tests/reward_recovery.rs does; the
t kept are those whose exact target norm (mean target, beta_t / sqrt(alpha_t) sqrt(abar_t) |m|)
is at least 10% of the largest, the test's criterion. Prints one JSON object: min and mean over
those t of the mean cosine.

    amortised_quality.py --endpoint http://127.0.0.1:PORT --model NAME --mean 1,-0.5,0.75,-1.25 --T 20
"""

import argparse
import json
import math

import numpy as np
from relreward import Client


def cosine_schedule(big_t, s=0.008):
    """(betas, alphas, alphas_cumprod) of the cosine schedule (Nichol and Dhariwal)."""
    f = [math.cos(((x / big_t) + s) / (1 + s) * math.pi / 2) ** 2 for x in range(big_t + 1)]
    abar = np.array([v / f[0] for v in f])
    betas = np.clip(1 - abar[1:] / abar[:-1], 0, 0.999)
    alphas = 1 - betas
    return betas, alphas, np.cumprod(alphas)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--endpoint", required=True)
    ap.add_argument("--model", required=True)
    ap.add_argument("--mean", required=True)
    ap.add_argument("--T", type=int, required=True)
    ap.add_argument("--n", type=int, default=512)
    args = ap.parse_args()
    m = np.array([float(v) for v in args.mean.split(",")])
    betas, alphas, abar = cosine_schedule(args.T)
    norms = betas / np.sqrt(alphas) * np.sqrt(abar) * np.linalg.norm(m)
    keep = [t for t in range(args.T) if norms[t] >= 0.1 * norms.max()]
    rng = np.random.default_rng(100)
    cosines = []
    with Client(args.endpoint.removeprefix("http://")) as client:
        for t in keep:
            z = rng.standard_normal((args.n, m.size))
            z[args.n // 2:] += np.sqrt(abar[t]) * m
            g = np.asarray(client.gradient(args.model, z.astype(np.float32), t, units="normalized").gradient, np.float64)
            cos = (g @ m) / (np.linalg.norm(g, axis=1) * np.linalg.norm(m) + 1e-12)
            cosines.append(float(cos.mean()))
    print(json.dumps({"min_cosine": min(cosines), "mean_cosine": float(np.mean(cosines)), "t_kept": len(keep)}))


if __name__ == "__main__":
    main()
