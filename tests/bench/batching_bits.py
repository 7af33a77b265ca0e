#!/usr/bin/env python3
"""How much merging into a batch changes an answer: for every reward model on a server, rho
and grad_x rho of 64 items sent as one 64-item Gradient request (the path merged requests
take) against the same items sent one per request, in normalized units, x standard normal,
t uniform over [0, T) (seed 0). Prints, per model, the largest absolute difference, the same
relative to the largest value, and how many of the 64 rho values are bitwise equal.

The figures in README.md and docs/python.md ("Merging changes the last bits") came from the
four umaze rewards of `relreward demo` (default size) on the 2-core CPU machine:

    target/release/relreward-server --listen 127.0.0.1:50612 --data-dir /tmp/bits &
    target/release/relreward --endpoint http://127.0.0.1:50612 demo --out /tmp/bits-demo
    .venv/bin/python tests/bench/batching_bits.py --endpoint 127.0.0.1:50612
"""

import argparse

import numpy as np

import relreward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--endpoint", default="127.0.0.1:50051", help="HOST:PORT of a relreward server")
    parser.add_argument("--items", type=int, default=64, help="items in the batched request")
    args = parser.parse_args()
    client = relreward.Client(args.endpoint)
    for model in client.list_models(kind="reward"):
        shape, T = tuple(model.reward.input_shape), model.reward.n_timesteps
        rng = np.random.default_rng(0)
        x = rng.standard_normal((args.items,) + shape).astype(np.float32)
        t = rng.integers(0, T, args.items)
        batched = client.gradient(model.name, x, t=t, units="normalized")
        alone = [client.gradient(model.name, x[i:i + 1], t=t[i:i + 1], units="normalized") for i in range(args.items)]
        rho_b, grad_b = np.asarray(batched.rewards).reshape(-1), np.asarray(batched.gradient)
        rho_1 = np.concatenate([np.asarray(a.rewards).reshape(-1) for a in alone])
        grad_1 = np.concatenate([np.asarray(a.gradient) for a in alone])

        def relative(a: np.ndarray, b: np.ndarray) -> float:
            return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-30))

        print(f"{model.name}: rho max abs {np.max(np.abs(rho_b - rho_1)):.3g} relative {relative(rho_b, rho_1):.3g} "
              f"bitwise equal {int(np.sum(rho_b == rho_1))}/{args.items}; gradient max abs "
              f"{np.max(np.abs(grad_b - grad_1)):.3g} relative {relative(grad_b, grad_1):.3g}")


if __name__ == "__main__":
    main()
