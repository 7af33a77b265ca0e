#!/usr/bin/env python3
"""A planner's sampling loop using relreward's GradientStream, from Python.

One bidirectional stream per planner episode: at every denoising step the planner sends its
current plan x_t with the step's t and gets grad_x rho(x_t, t) back. Here the "planner" is only
the guidance part of Diffuser's guided sampling (x += omega * grad, n_guide_steps times per
step, t from T-1 down to 0), so the example needs nothing but the reward model; a real planner
puts its own denoiser step between two requests (see examples/diffuser_guide.py for a whole
sampler).

It uses the `relreward` package (``pip install ./client/python``; ``make setup`` installs it
into .venv): ``client.gradient_stream(model)`` keeps the stream open and matches answers to
requests.

    .venv/bin/python examples/planner_gradient_stream.py --endpoint 127.0.0.1:50051 --model maze-reward

A server with access control wants a token with scope `read` (--token, or RELREWARD_TOKEN);
one with TLS wants --ca-cert (and --client-cert/--client-key for mutual TLS).

Prints one JSON object: rho at the first and the last step, how much each guide step raised
rho at its own t (positive: the gradient points uphill), and the round-trip latency of the
stream's requests.
"""

import argparse
import json
import os
import sys
import time

import numpy as np

import relreward


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--endpoint", default="127.0.0.1:50051")
    ap.add_argument("--model", required=True, help="a reward model")
    ap.add_argument("--omega", type=float, default=0.1, help="guidance scale")
    ap.add_argument("--n-guide-steps", type=int, default=2)
    ap.add_argument("--batch", type=int, default=4, help="plans per request")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--proto-dir", help=argparse.SUPPRESS)  # accepted for old command lines; unused
    ap.add_argument(
        "--token",
        default=os.environ.get("RELREWARD_TOKEN"),
        help="access token with scope read (default: $RELREWARD_TOKEN)",
    )
    ap.add_argument("--ca-cert", help="PEM CA certificate: connect with TLS, verifying the server against it")
    ap.add_argument("--client-cert", help="PEM client certificate, for servers that require mutual TLS")
    ap.add_argument("--client-key", help="PEM private key of --client-cert")
    args = ap.parse_args()
    if (args.client_cert is None) != (args.client_key is None):
        ap.error("--client-cert and --client-key go together")

    tls = None
    if args.ca_cert is not None or args.client_cert is not None:
        tls = relreward.TLS(ca_cert=args.ca_cert, client_cert=args.client_cert, client_key=args.client_key)
    try:
        with relreward.Client(args.endpoint, token=args.token, tls=tls) as client:
            summary = plan(client, args)
    except relreward.RelrewardError as e:
        sys.exit(f"{args.model}: {e}")
    print(json.dumps(summary))


def plan(client: relreward.Client, args: argparse.Namespace) -> dict:
    model = client.get_model(args.model)
    shape = [args.batch, *model.reward.input_shape]
    big_t = model.reward.n_timesteps
    rng = np.random.default_rng(args.seed)
    x = rng.standard_normal(shape).astype(np.float32)  # a plan in normalized units
    first_rho = last_rho = None
    latencies = []
    gains = []  # rho after minus before one guide step, at the same t
    requests = 0
    # omega is applied by the server; plans and gradients in normalized units, as Diffuser's.
    with client.gradient_stream(args.model, omega=args.omega, units="normalized") as stream:
        for t in range(big_t - 1, -1, -1):
            previous = None
            for _ in range(args.n_guide_steps):
                started = time.perf_counter()
                grad, rho = stream.gradient(x, t)
                latencies.append(time.perf_counter() - started)
                requests += 1
                if previous is not None:
                    gains.append(float(np.mean(rho - previous)))
                previous = rho
                first_rho = rho if first_rho is None else first_rho
                last_rho = rho
                x = x + grad
    lat = np.array(latencies) * 1e3
    return {
        "model": args.model,
        "requests": requests,
        "rho_first_step": float(np.mean(first_rho)),
        "rho_last_step": float(np.mean(last_rho)),
        "mean_gain_per_guide_step": float(np.mean(gains)) if gains else None,
        "latency_ms": {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99))},
    }


if __name__ == "__main__":
    main()
