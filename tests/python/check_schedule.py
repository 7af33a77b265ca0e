#!/usr/bin/env python3
"""Reference values for every DDPM schedule table, computed in float64 with PyTorch.

The tables come from relreward_dev.schedule (the development package, dev/python), written
from the formulas (docs/method.md section 2; Nichol & Dhariwal 2021; Diffuser's
`cosine_beta_schedule`; Diffuser's `GaussianDiffusion` buffers), independently of the Rust
code, so that `server/tests/schedule_vs_pytorch.rs` can compare the two.

Prints one JSON object to stdout:
    {"cases": [{"spec": {...ScheduleSpec JSON...}, "n_timesteps": T,
                "tables": {"betas": [...], ...}}            # a valid schedule
               or {"spec": ..., "n_timesteps": T, "error": "..."}]}   # one that must be refused

Run with the project's venv: .venv/bin/python tests/python/check_schedule.py
"""

import json
import sys

import numpy as np

from relreward_dev.schedule import TABLES, schedule_tables


def cases():
    rng = np.random.default_rng(1234)
    specs = []
    for T in (1, 20, 100, 1000):
        specs.append(({"kind": "cosine", "s": 0.008}, T))
        specs.append(({"kind": "diffuser_cosine", "s": 0.008}, T))
        specs.append(({"kind": "linear"}, T))
        betas = rng.uniform(1e-4, 0.05, size=T)
        specs.append(({"kind": "betas", "betas": [float(b) for b in betas]}, T))
    specs.append(({"kind": "cosine", "s": 0.0}, 50))
    specs.append(({"kind": "diffuser_cosine", "s": 0.1}, 50))
    specs.append(({"kind": "linear"}, 21))
    specs.append(({"kind": "linear"}, 2))
    return specs


def main():
    out = []
    for spec, T in cases():
        case = {"spec": spec, "n_timesteps": T}
        try:
            tables = schedule_tables(spec, T)
            case["tables"] = {name: [float(v) for v in tables[name]] for name in TABLES}
        except ValueError as e:
            case["error"] = str(e)
        out.append(case)
    json.dump({"cases": out}, sys.stdout)


if __name__ == "__main__":
    main()
