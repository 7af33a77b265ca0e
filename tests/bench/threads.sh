#!/usr/bin/env bash
# Diffusion-training steps per second under three libtorch threading setups, to choose
# engine.intra_op_threads: one OpenMP thread per core (intra_op_threads = 0), the same with
# OMP_WAIT_POLICY=PASSIVE (idle OpenMP threads sleep instead of spinning), and one thread
# (the default). Run it on a quiet machine and again while something else loads the cores
# (e.g. `make bench` in another terminal): the difference is in the second run.
# Each setup starts its own loopback server on a temporary data dir. Prints one line each.
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=target/release
STEPS=${STEPS:-1500}
tmp=$(mktemp -d)
. tests/bench/lib.sh
trap 'stop_server; rm -rf "$tmp"' EXIT
"$BIN/relreward" maze generate --layout medium --mode base --transitions 400000 --seed 0 \
  --action-noise 0.5 --out "$tmp/base.npz" >/dev/null
cat >"$tmp/diffusion.toml" <<'TOML'
[diffusion]
horizon = 16
n_timesteps = 20
architecture = { kind = "mlp", hidden = [256, 256, 256] }
TOML
# run LABEL [ENV=VALUE...]: a fresh server (an empty data directory) with those settings.
run() {
  local label=$1; shift
  rm -rf "$tmp/data"
  start_server "$@"
  quiet rr dataset upload "$tmp/base.npz" --name base
  rr --json train diffusion --name m --dataset base --config "$tmp/diffusion.toml" \
    --steps "$STEPS" --batch-size 64 --watch >"$tmp/events" 2>/dev/null
  python3 - "$label" "$tmp/events" <<'PY'
import json, sys
events = [json.loads(l) for l in open(sys.argv[2]) if l.startswith("{")]
last = [e for e in events if e.get("type") == "progress"][-1]
print(f"{sys.argv[1]:<28} {last['steps_per_second']:8.1f} steps/s")
PY
  stop_server
}
run "per-core" RELREWARD__ENGINE__INTRA_OP_THREADS=0
run "per-core, OMP passive" RELREWARD__ENGINE__INTRA_OP_THREADS=0 OMP_WAIT_POLICY=PASSIVE
run "one (default)" RELREWARD__ENGINE__INTRA_OP_THREADS=1
