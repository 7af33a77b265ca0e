#!/usr/bin/env bash
# Bring-your-own reward serving benchmark (issue 36 item 3's bar): a TorchScript value function
# of Diffuser's signature, forward(x, cond, t) -> [B, 1], against a native reward of the same
# network, both served by GradientStream to 64 closed-loop clients. Bar: the BYO's throughput
# and p99 within 20% of the native's.
#
# The two are the same network, so that only the serving path differs: the native reward is
# Diffuser's ValueFunction (widths 64,64,128,128) on [32, 14] (serving.sh's `loco` model,
# trained one step); the BYO module is its export (`relreward model export`, traced, raw units
# with the normalizer inside) wrapped by a scripted module of the value function's signature,
# and uploaded with `model upload --reward` (identity normalizer, since the export takes raw
# units). Both answer the same numbers (checked once here before the runs).
#
# Runs A B A B ... over REPS rotations of DURATION seconds each (native first in odd rotations,
# BYO first in even ones, so drift on a shared machine falls on both), and prints one JSON line
# per run, then medians and ratios as markdown rows for BENCHMARKS.md. THREADS libtorch intra-op
# threads (default 1: the load generator shares the cores; see serving.sh). Builds nothing:
# expects target/release/{relreward-server,relreward,relreward-loadgen}. About 3 minutes with
# the defaults on a 2-core machine.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPS=${REPS:-4}
DURATION=${DURATION:-10}
CLIENTS=${CLIENTS:-64}
THREADS=${THREADS:-1}
BIN=target/release
PY=.venv/bin/python
for b in relreward-server relreward relreward-loadgen; do
  [[ -x $BIN/$b ]] || { echo "byo.sh: $BIN/$b is missing: cargo build --release --workspace --bins" >&2; exit 2; }
done
tmp=$(mktemp -d)
. tests/bench/lib.sh
trap 'stop_server; rm -rf "$tmp"' EXIT
server_env=(RELREWARD__ENGINE__INTRA_OP_THREADS="$THREADS" RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD=true)

start_server
"$PY" - "$tmp/loco.npz" <<'PY'
import sys
import numpy as np
rng = np.random.default_rng(2)
n = 20000
obs = rng.normal(0.0, 1.0, (n, 11)).astype(np.float32) * np.linspace(0.5, 5.0, 11, dtype=np.float32)
act = np.clip(rng.normal(0.0, 0.5, (n, 3)), -1, 1).astype(np.float32)
timeouts = np.zeros(n, dtype=bool)
timeouts[999::1000] = True
np.savez(sys.argv[1], observations=obs, actions=act, terminals=np.zeros(n, dtype=bool), timeouts=timeouts)
PY
quiet rr dataset upload "$tmp/loco.npz" --name loco
cat >"$tmp/unet.toml" <<TOML
[diffusion]
horizon = 32
n_timesteps = 20
architecture = { kind = "temporal_unet", dim = 16, dim_mults = [1, 2] }
TOML
for m in base expert; do
  quiet rr train diffusion --name "loco-$m" --dataset loco --config "$tmp/unet.toml" --steps 1 --batch-size 2 --watch
done
quiet rr train reward --name native --base loco-base --expert loco-expert --dataset loco \
  --arch value_function --widths 64,64,128,128 --steps 1 --batch-size 2 --watch
quiet rr model export native --out "$tmp/export"
# The export in Diffuser's value-function signature: forward(x, cond, t) -> [B, 1] (from a
# file: torch.jit.script reads the class's source).
cat >"$tmp/wrap.py" <<'PY'
import sys
from typing import Dict
import torch

class ValueFunction(torch.nn.Module):
    def __init__(self, rho):
        super().__init__()
        self.rho = rho

    def forward(self, x: torch.Tensor, cond: Dict[str, torch.Tensor], time: torch.Tensor) -> torch.Tensor:
        return self.rho(x, time).unsqueeze(-1)

torch.jit.script(ValueFunction(torch.jit.load(sys.argv[1]))).save(sys.argv[2])
PY
"$PY" "$tmp/wrap.py" "$tmp/export/module.pt" "$tmp/byo.pt"
cat >"$tmp/byo.toml" <<TOML
signature = "value_function"
n_timesteps = 20
space = { kind = "trajectory", horizon = 32, action_dim = 3, obs_dim = 11 }
normalizer = { kind = "identity" }
TOML
quiet rr model upload "$tmp/byo.pt" --name byo --manifest "$tmp/byo.toml" --reward
# Same numbers: Gradient of both on one batch (raw units).
"$PY" - "$endpoint" <<'PY'
import sys
import numpy as np
import relreward
x = np.random.default_rng(0).normal(0, 1, (5, 32, 14)).astype(np.float32)
with relreward.Client(sys.argv[1].removeprefix("http://")) as c:
    a, b = c.gradient("native", x, t=3), c.gradient("byo", x, t=3)
np.testing.assert_allclose(a.rewards, b.rewards, rtol=1e-5, atol=1e-5)
np.testing.assert_allclose(a.gradient, b.gradient, rtol=1e-5, atol=1e-5)
PY
stop_server
start_server  # fresh: the training jobs loaded diffusion models

for rep in $(seq "$REPS"); do
  order="native byo"
  (( rep % 2 == 0 )) && order="byo native"
  for model in $order; do
    "$BIN/relreward-loadgen" --endpoint "$endpoint" --model "$model" --shape 32,14 --mode stream \
      --clients "$CLIENTS" --duration "$DURATION" --json >"$tmp/run.json"
    python3 - "$tmp/run.json" "$model" "$rep" <<'PY' | tee -a "$tmp/results"
import json, sys
r = json.load(open(sys.argv[1]))
print(json.dumps({"benchmark": "byo", "model": sys.argv[2], "rep": int(sys.argv[3]), **r}))
PY
  done
done

python3 - "$tmp/results" "$CLIENTS" "$DURATION" "$REPS" "$THREADS" <<'PY'
import json, statistics, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
clients, duration, reps, threads = sys.argv[2:]
failed = sum(sum(r["errors"].values()) for r in rows)
med = {}
for m in ("native", "byo"):
    rs = [r for r in rows if r["model"] == m]
    med[m] = (statistics.median(r["items_per_s"] for r in rs), statistics.median(r["latency_ms"]["p99"] for r in rs),
              [round(r["items_per_s"]) for r in rs], [round(r["latency_ms"]["p99"], 2) for r in rs])
cpus = rows[0]["cpus"]
print()
print(f"| reward ({clients} GradientStream clients, [32, 14], B = 1) | items/s (median of {reps}) | p99 ms (median) | per run items/s | per run p99 ms |")
print("|---|---|---|---|---|")
for m, label in (("native", "native ValueFunction (64, 64, 128, 128)"), ("byo", "BYO TorchScript value function, same net")):
    ips, p99, all_ips, all_p99 = med[m]
    print(f"| {label} | {ips:.0f} | {p99:.2f} | {all_ips} | {all_p99} |")
ratio_ips = med["byo"][0] / med["native"][0]
ratio_p99 = med["byo"][1] / med["native"][1]
ok = ratio_ips >= 0.8 and ratio_p99 <= 1.2
print(f"| BYO / native | {ratio_ips:.2f} | {ratio_p99:.2f} | | |")
print()
print(f"Bar (throughput >= 0.8x, p99 <= 1.2x native): {'met' if ok else 'NOT met'}; {cpus} CPUs shared with the "
      f"load generator, {threads} intra-op thread(s), {duration} s per run, failed requests: {failed}.")
sys.exit(1 if failed else 0)
PY
