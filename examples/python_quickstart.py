#!/usr/bin/env python3
"""The relreward Python package in a few lines: connect, look up a reward model, score a batch
of plans and ask for grad_x rho at a diffusion step, then the same over one GradientStream.

    pip install ./client/python          # once, from a clone (make setup does it for .venv)
    .venv/bin/python examples/python_quickstart.py --endpoint 127.0.0.1:50051 --model maze-reward

Prints one JSON object: the model's input shape, rho of the batch, the gradient's norm and the
round-trip time of each call in milliseconds.
"""

import argparse
import json
import os
import time

import numpy as np

import relreward


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--endpoint", default=os.environ.get("RELREWARD_ENDPOINT", "127.0.0.1:50051"))
    ap.add_argument("--model", required=True, help="a reward model")
    ap.add_argument("--token", default=os.environ.get("RELREWARD_TOKEN"), help="access token (scope read)")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--t", type=int, default=1, help="diffusion step of the gradient")
    args = ap.parse_args()

    with relreward.Client(args.endpoint, token=args.token) as client:
        model = client.get_model(args.model)
        shape = [args.batch, *model.reward.input_shape]  # [B, H, D]
        x = np.random.default_rng(0).uniform(-1, 1, shape).astype(np.float32)  # raw units

        started = time.perf_counter()
        rho = client.score(args.model, x).rewards  # [B] float32
        score_ms = 1e3 * (time.perf_counter() - started)

        started = time.perf_counter()
        grad, rho_t = client.gradient(args.model, x, t=args.t)  # grad: [B, H, D]
        gradient_ms = 1e3 * (time.perf_counter() - started)

        with client.gradient_stream(args.model) as stream:
            streamed = [stream.gradient(x, t) for t in range(model.reward.n_timesteps)]

    print(json.dumps({
        "input_shape": shape,
        "rho": rho.tolist(),
        "rho_at_t": rho_t.tolist(),
        "gradient_norm": float(np.linalg.norm(grad)),
        "stream_steps": len(streamed),
        "stream_matches_unary": bool(np.allclose(streamed[args.t].gradient, grad, rtol=1e-4, atol=1e-7)),
        "latency_ms": {"score": score_ms, "gradient": gradient_ms},
    }))


if __name__ == "__main__":
    main()
