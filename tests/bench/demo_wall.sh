#!/usr/bin/env bash
# Wall time and quality of `relreward demo` (LAYOUT, default size, SEED) against a fresh server
# on a temporary data directory: the maze default pipeline's end-to-end figure (issue 38). Prints
# one JSON line: seconds, goals recovered and steered, mean balanced accuracy. Needs `cargo
# build --release --workspace --bins`. About two minutes for umaze.
set -euo pipefail
cd "$(dirname "$0")/../.."
LAYOUT=${LAYOUT:-umaze}; SEED=${SEED:-0}; PORT=${PORT:-50071}
out=$(mktemp -d)
RELREWARD__METRICS__LISTEN= RELREWARD__SERVER__LISTEN=127.0.0.1:$PORT target/release/relreward-server \
  --data-dir "$out/server-data" >"$out/server.out" 2>"$out/server.log" &
server=$!
trap 'kill $server 2>/dev/null || true; wait $server 2>/dev/null || true; rm -rf "$out"' EXIT
rr() { target/release/relreward --endpoint "http://127.0.0.1:$PORT" "$@"; }
for _ in $(seq 300); do rr health >/dev/null 2>&1 && break; sleep 0.1; done
start=$(date +%s.%N)
rr demo --layout "$LAYOUT" --seed "$SEED" --out "$out/demo" --json >"$out/demo.json" 2>"$out/demo.err"
end=$(date +%s.%N)
.venv/bin/python - "$out/demo.json" "$start" "$end" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
keep = ["layout", "seed", "goals_total", "goals_recovered", "goals_steered", "mean_balanced_accuracy"]
print(json.dumps({"seconds": round(float(sys.argv[3]) - float(sys.argv[2]), 1), **{k: d.get(k) for k in keep}}))
PY
