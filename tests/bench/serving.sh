#!/usr/bin/env bash
# Serving benchmark: latency and throughput of RewardService.Gradient / GradientStream over
# loopback, for two reward models created the way a user would:
#
#   maze: windowed MLP (window 4, hidden 128,64,32) on [H, D] = [64, 6] (Maze2D obs 4 + act 2)
#   loco: Diffuser's ValueFunction (widths 64,64,128,128) on [32, 14] (locomotion obs 11 + act 3)
#
# Per model: unary Gradient, 1 client, batch 1, 2000 requests (latency p50 / p99); GradientStream
# with 1, 8 and 64 closed-loop clients for DURATION seconds each (throughput); then the server
# is restarted with RELREWARD__SERVING__MAX_BATCH=1 (one request per forward, the baseline the
# dynamic batcher must beat) and the 64-client run is repeated. Prints one JSON line per run and
# a table at the end; exits 1 if any request failed.
#
# Builds nothing: expects target/release/{relreward-server,relreward,relreward-loadgen}
# (`cargo build --release --workspace --bins`). Starts its own servers on loopback ports with a
# temporary data directory, so it never touches ./data. The load generator runs on the same
# CPUs as the server, which the figures include.
set -euo pipefail
cd "$(dirname "$0")/../.."
DURATION=${DURATION:-10}
REQUESTS=${REQUESTS:-2000}
BIN=target/release
for b in relreward-server relreward relreward-loadgen; do
  [[ -x $BIN/$b ]] || { echo "serving.sh: $BIN/$b is missing: cargo build --release --workspace --bins" >&2; exit 2; }
done
tmp=$(mktemp -d)
server=
stop_server() {
  if [[ -n $server ]]; then
    kill "$server" 2>/dev/null || true
    wait "$server" 2>/dev/null || true
    server=
  fi
}
trap 'stop_server; rm -rf "$tmp"' EXIT

# start_server [ENV=VALUE...]: a server on 127.0.0.1:0 over $tmp/data (metrics port disabled);
# sets $endpoint from the first line it prints.
start_server() {
  : >"$tmp/out"
  env RELREWARD__METRICS__LISTEN= "$@" "$BIN/relreward-server" --listen 127.0.0.1:0 --data-dir "$tmp/data" \
    >"$tmp/out" 2>>"$tmp/log" &
  server=$!
  for _ in $(seq 300); do
    grep -q listening "$tmp/out" && break
    kill -0 "$server" 2>/dev/null || { echo "serving.sh: the server exited:" >&2; tail -20 "$tmp/log" >&2; exit 1; }
    sleep 0.1
  done
  endpoint="http://$(sed -n '1s/^relreward-server listening on //p' "$tmp/out")"
  [[ $endpoint != http:// ]] || { echo "serving.sh: the server did not start" >&2; exit 1; }
  export RELREWARD_ENDPOINT=$endpoint
}
rr() { "$BIN/relreward" "$@"; }
quiet() { "$@" >"$tmp/cmd.log" 2>&1 || { echo "serving.sh: failed: $*" >&2; cat "$tmp/cmd.log" >&2; exit 1; }; }

start_server

# Datasets. Maze-like D = 6 (obs 4 + act 2) from the tests' generator; locomotion-like D = 14
# (obs 11 + act 3, episodes of up to 1000 steps ending in a timeout, a few terminals).
.venv/bin/python tests/python/make_dataset.py --rows 20000 --seed 1 --out "$tmp/maze.npz" --expected "$tmp/e.json"
.venv/bin/python - "$tmp/loco.npz" <<'PY'
import sys
import numpy as np
rng = np.random.default_rng(2)
n = 20000
obs = rng.normal(0.0, 1.0, (n, 11)).astype(np.float32) * np.linspace(0.5, 5.0, 11, dtype=np.float32)
act = np.clip(rng.normal(0.0, 0.5, (n, 3)), -1, 1).astype(np.float32)
timeouts = np.zeros(n, dtype=bool)
timeouts[999::1000] = True
terminals = np.zeros(n, dtype=bool)
terminals[rng.choice(n, size=5, replace=False)] = True
np.savez(sys.argv[1], observations=obs, actions=act, terminals=terminals, timeouts=timeouts)
PY
quiet rr dataset upload "$tmp/maze.npz" --name maze
quiet rr dataset upload "$tmp/loco.npz" --name loco

# Diffusion models: one step each (the weights do not change the reward's serving cost, and
# serving never runs them), small TemporalUnets at the two horizons.
for spec in maze:64 loco:32; do
  ds=${spec%%:*} horizon=${spec#*:}
  cat >"$tmp/$ds-unet.toml" <<TOML
[diffusion]
horizon = $horizon
n_timesteps = 20
architecture = { kind = "temporal_unet", dim = 16, dim_mults = [1, 2] }
TOML
  for m in base expert; do
    quiet rr train diffusion --name "$ds-$m" --dataset "$ds" --config "$tmp/$ds-unet.toml" --steps 1 --batch-size 2 --watch
  done
done
quiet rr train reward --name maze-reward --base maze-base --expert maze-expert --dataset maze \
  --arch windowed_mlp --window 4 --hidden 128,64,32 --steps 1 --batch-size 2 --watch
quiet rr train reward --name loco-reward --base loco-base --expert loco-expert --dataset loco \
  --arch value_function --widths 64,64,128,128 --steps 1 --batch-size 2 --watch

# run LABEL MAX_BATCH LOADGEN-FLAGS...: one load run, printed as one JSON line and kept for the table.
run() {
  local label=$1 max_batch=$2
  shift 2
  "$BIN/relreward-loadgen" --endpoint "$endpoint" --json "$@" >"$tmp/run.json"
  python3 - "$tmp/run.json" "$label" "$max_batch" <<'PY' | tee -a "$tmp/results"
import json, sys
r = json.load(open(sys.argv[1]))
print(json.dumps({"benchmark": "serving", "run": sys.argv[2], "server_max_batch": sys.argv[3], **r}))
PY
}

all_runs() {
  local model=$1
  run "unary c=1" default --model "$model" --mode unary --clients 1 --batch 1 --requests "$REQUESTS"
  for c in 1 8 64; do
    run "stream c=$c" default --model "$model" --mode stream --clients "$c" --batch 1 --duration "$DURATION"
  done
}
all_runs maze-reward
all_runs loco-reward

# The baseline: one request per forward.
stop_server
start_server RELREWARD__SERVING__MAX_BATCH=1
for model in maze-reward loco-reward; do
  run "stream c=64" 1 --model "$model" --mode stream --clients 64 --batch 1 --duration "$DURATION"
done
stop_server

python3 - "$tmp/results" <<'PY'
import json, sys
runs = [json.loads(l) for l in open(sys.argv[1])]
print()
print(f"{'model':<12} {'run':<12} {'max_batch':>9} {'shape':>8} {'requests':>9} {'errors':>6} "
      f"{'items/s':>9} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
for r in runs:
    lat = r.get("latency_ms") or {}
    errors = sum(r["errors"].values())
    shape = "x".join(str(d) for d in r["item_shape"])
    print(f"{r['model']:<12} {r['run']:<12} {r['server_max_batch']:>9} {shape:>8} {r['requests']:>9} {errors:>6} "
          f"{r['items_per_s']:>9.1f} {lat.get('p50', 0):>8.3f} {lat.get('p99', 0):>8.3f} {lat.get('max', 0):>8.3f}")
for model in dict.fromkeys(r["model"] for r in runs):
    batched = [r for r in runs if r["model"] == model and r["run"] == "stream c=64" and r["server_max_batch"] == "default"]
    single = [r for r in runs if r["model"] == model and r["run"] == "stream c=64" and r["server_max_batch"] == "1"]
    if batched and single and single[0]["items_per_s"] > 0:
        print(f"{model}: 64 clients, dynamic batching vs max_batch=1: "
              f"{batched[0]['items_per_s'] / single[0]['items_per_s']:.2f}x items/s")
print(f"note: {runs[0]['note']} ({runs[0]['cpus']} CPUs).")
sys.exit(1 if any(sum(r["errors"].values()) for r in runs) else 0)
PY
