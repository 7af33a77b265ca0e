#!/usr/bin/env bash
# Wall time and quality of `relreward demo` (LAYOUT, default size, SEED) against a fresh server
# on a temporary data directory: the maze default pipeline's end-to-end figure (issue 38). Prints
# one JSON line: seconds, goals recovered and steered, mean balanced accuracy. Needs `cargo
# build --release --workspace --bins`, or BIN (default target/release) naming another build's
# binaries (an older commit's, for a before-and-after). About two minutes for umaze.
set -euo pipefail
cd "$(dirname "$0")/../.."
LAYOUT=${LAYOUT:-umaze}; SEED=${SEED:-0}
BIN=${BIN:-target/release}
tmp=$(mktemp -d)
. tests/bench/lib.sh
trap 'stop_server; rm -rf "$tmp"' EXIT
start_server
start=$(date +%s.%N)
rr demo --layout "$LAYOUT" --seed "$SEED" --out "$tmp/demo" --json >"$tmp/demo.json" 2>"$tmp/demo.err"
end=$(date +%s.%N)
.venv/bin/python - "$tmp/demo.json" "$start" "$end" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
keep = ["layout", "seed", "goals_total", "goals_recovered", "goals_steered", "mean_balanced_accuracy"]
print(json.dumps({"seconds": round(float(sys.argv[3]) - float(sys.argv[2]), 1), **{k: d.get(k) for k in keep}}))
PY
