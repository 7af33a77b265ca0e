#!/usr/bin/env bash
# The reward's training step at the maze default size, relreward against PyTorch eager (issue 38's
# first CPU bar), RUNS rotations (default 3), each one run of each, back to back:
#
# - relreward: `PARTS=ceiling tests/bench/amortised.sh`'s models-free job at the maze default
#   size (windowed MLP h = 4, (128, 64, 32), batch 64, lr 1e-3, horizon 16, D = 6, T = 20, a pool
#   of 4096 targets that the frozen models never refill during the run; steps/s from step 100 to
#   1000), one intra-op thread (the server's default);
# - PyTorch eager: `bench/reference/bench.py reward-step` with the same sizes, pool, batch, lr,
#   Adam and EMA, one thread: per step a gather from the pool, the alignment loss through
#   autograd's double backward, backward, Adam, the EMA and the loss read back.
#
# Prints one JSON line per run and a table of the ratios. Needs `cargo build --release
# --workspace --bins` and the project's .venv (make). About 30 s per rotation.
set -euo pipefail
cd "$(dirname "$0")/../.."
RUNS=${RUNS:-3}
PY=.venv/bin/python
results=$(mktemp)
trap 'rm -f "$results"' EXIT
for run in $(seq "$RUNS"); do
  rate=$(PARTS=ceiling tests/bench/amortised.sh 2>/dev/null |
    "$PY" -c 'import json, sys
for line in sys.stdin:
    if line.startswith("{"):
        r = json.loads(line)
        if r.get("pair") == "maze-default" and r.get("recipe") == "models-free":
            print(r["rate"]["steps_per_second"])')
  echo "{\"run\": $run, \"who\": \"relreward\", \"steps_per_second\": $rate}" | tee -a "$results"
  eager=$("$PY" bench/reference/bench.py reward-step --threads 1 --horizon 16 --transition-dim 6 --n-timesteps 20 \
    --window 4 --hidden 128,64,32 --batch 64 --pool 4096 --lr 1e-3 --steps 900 --warmup 100 |
    "$PY" -c 'import json, sys; print(json.load(sys.stdin)["steps_per_second"])')
  echo "{\"run\": $run, \"who\": \"eager\", \"steps_per_second\": $eager}" | tee -a "$results"
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
