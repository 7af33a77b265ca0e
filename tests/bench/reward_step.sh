#!/usr/bin/env bash
# The reward's training step, relreward against PyTorch eager, RUNS rotations (default 3), each
# one run of each, back to back, one intra-op thread on both sides (the server's default).
#
# ARCH=windowed_mlp (default; issue 38's first CPU bar), the maze default size:
# - relreward: `PARTS=ceiling tests/bench/amortised.sh`'s models-free job at the maze default
#   size (windowed MLP h = 4, (128, 64, 32), batch 64, lr 1e-3, horizon 16, D = 6, T = 20, a pool
#   of 4096 targets that the frozen models never refill during the run; steps/s from step 100 to
#   1000; its progress written every CEIL_LOG_EVERY steps, default 10, the server's default);
# - PyTorch eager: `bench/reference/bench.py reward-step` with the same sizes, pool, batch, lr,
#   Adam and EMA: per step a gather from the pool, the alignment loss through autograd's double
#   backward, backward, Adam, the EMA and the loss read back.
#
# ARCH=value_function, the locomotion size: Diffuser's ValueFunction with the paper's widths
# (64, 64, 128, 128) over Hopper-shaped trajectories (horizon 32, D = 14: 3 actions, 11
# observations), batch 64, lr 2e-4, T = 20, the same models-free recipe (pool 4096, reuse 1024,
# refresh 0.001), VF_STEPS steps (default 300, steps/s from step 50); the two diffusion models
# are MLPs trained 20 steps on a smooth random walk of that shape (their weights do not change
# the reward step's cost). PyTorch eager: the same `reward-step` with `--widths`.
#
# Prints one JSON line per run and a table of the ratios. Needs `cargo build --release
# --workspace --bins` and the project's .venv (make). About 30 s (windowed) or 90 s (value
# function) per rotation.
set -euo pipefail
cd "$(dirname "$0")/../.."
RUNS=${RUNS:-3}
ARCH=${ARCH:-windowed_mlp}
VF_STEPS=${VF_STEPS:-300}
BIN=${BIN:-target/release}
PY=.venv/bin/python
tmp=$(mktemp -d)
. tests/bench/lib.sh
trap 'stop_server; rm -rf "$tmp"' EXIT
results=$tmp/results.jsonl

# A server with the two frozen models and the dataset of the value function's rotation.
value_function_setup() {
  start_server RELREWARD__ENGINE__INTRA_OP_THREADS=1
  "$PY" - "$tmp" <<'PY'
import sys
import numpy as np
rng = np.random.default_rng(0)
for who in ("base", "expert"):
    n = 20000
    obs = np.cumsum(rng.normal(0, 0.1, (n, 11)), axis=0).astype(np.float32)
    act = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    timeouts = np.zeros(n, bool)
    timeouts[999::1000] = True
    np.savez(f"{sys.argv[1]}/vf-{who}.npz", observations=obs, actions=act, rewards=np.zeros(n, np.float32),
             terminals=np.zeros(n, bool), timeouts=timeouts)
PY
  printf '[diffusion]\narchitecture = { kind = "mlp", hidden = [256, 256] }\nnormalizer_datasets = ["vf-base", "vf-expert"]\n' \
    >"$tmp/diffusion.toml"
  for who in base expert; do quiet rr dataset upload "$tmp/vf-$who.npz" --name "vf-$who"; done
  for who in base expert; do
    quiet rr train diffusion --name "vf-m$who" --dataset "vf-$who" --horizon 32 --n-timesteps 20 --steps 20 \
      --batch-size 64 --config "$tmp/diffusion.toml" --watch
  done
  printf '[optimization]\neval_every = 100000\ncheckpoint_every = 100000\n' >"$tmp/opt.toml"
}

# steps/s of the value function's models-free job between step 50 and its end.
value_function_rate() {
  local run=$1
  rr --json train reward --name "vf-$run" --base vf-mbase --expert vf-mexpert --dataset vf-base --dataset vf-expert \
    --arch value_function --widths 64,64,128,128 --batch-size 64 --lr 2e-4 --steps "$VF_STEPS" --seed 11 \
    --config "$tmp/opt.toml" --amortised-pool 4096 --amortised-reuse 1024 --amortised-refresh 0.001 --watch \
    >"$tmp/events" 2>>"$tmp/log"
  "$PY" - "$tmp/events" <<'PY'
import json, sys
events = [json.loads(l) for l in open(sys.argv[1]) if l.lstrip().startswith("{")]
rate = {e["step"]: e["steps_per_second"] for e in events if e.get("type") == "progress"}
a, b = 50, max(rate)
print((b - a) / (b / rate[b] - a / rate[a]))
PY
}

if [[ $ARCH == value_function ]]; then
  value_function_setup
elif [[ $ARCH != windowed_mlp ]]; then
  echo "reward_step.sh: ARCH must be windowed_mlp or value_function, not $ARCH" >&2
  exit 2
fi
for run in $(seq "$RUNS"); do
  if [[ $ARCH == value_function ]]; then
    rate=$(value_function_rate "$run")
    eager_args=(--horizon 32 --transition-dim 14 --widths 64,64,128,128 --lr 2e-4 --steps 100 --warmup 10)
  else
    rate=$(PARTS=ceiling tests/bench/amortised.sh 2>/dev/null |
      "$PY" -c 'import json, sys
for line in sys.stdin:
    if line.startswith("{"):
        r = json.loads(line)
        if r.get("pair") == "maze-default" and r.get("recipe") == "models-free":
            print(r["rate"]["steps_per_second"])')
    eager_args=(--horizon 16 --transition-dim 6 --window 4 --hidden 128,64,32 --lr 1e-3 --steps 900 --warmup 100)
  fi
  echo "{\"run\": $run, \"arch\": \"$ARCH\", \"who\": \"relreward\", \"steps_per_second\": $rate}" | tee -a "$results"
  eager=$("$PY" bench/reference/bench.py reward-step --threads 1 --n-timesteps 20 --batch 64 --pool 4096 \
    "${eager_args[@]}" | "$PY" -c 'import json, sys; print(json.load(sys.stdin)["steps_per_second"])')
  echo "{\"run\": $run, \"arch\": \"$ARCH\", \"who\": \"eager\", \"steps_per_second\": $eager}" | tee -a "$results"
done
"$PY" - "$results" <<'PY'
import json, statistics, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
ours = [r["steps_per_second"] for r in rows if r["who"] == "relreward"]
eager = [r["steps_per_second"] for r in rows if r["who"] == "eager"]
print("\n| run | relreward steps/s | PyTorch eager steps/s | ratio |\n|---|---|---|---|")
for i, (a, b) in enumerate(zip(ours, eager), 1):
    print(f"| {i} | {a:.1f} | {b:.1f} | {a / b:.2f}x |")
print(f"| median | {statistics.median(ours):.1f} | {statistics.median(eager):.1f} | "
      f"**{statistics.median(ours) / statistics.median(eager):.2f}x** |")
PY
