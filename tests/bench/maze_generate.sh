#!/usr/bin/env bash
# Speed of the built-in Maze2D generator (`relreward maze generate`): transitions per second for
# every layout in base and expert mode. Builds nothing: expects target/release/relreward
# (`cargo build --release --workspace --bins`). Needs no server; writes to a temporary directory.
#
# Per run: the generator's own rate (simulation + controller, from the command's --json
# summary) and the end-to-end rate (process start, generation and writing the .npz, by the wall
# clock). Prints one JSON line per run, then a table; exits 1 if a run fails or a generation
# rate is below FLOOR (the 100k transitions/s the generator is built for).
#
#   TRANSITIONS=2000000 FLOOR=100000 tests/bench/maze_generate.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
TRANSITIONS=${TRANSITIONS:-2000000}
FLOOR=${FLOOR:-100000}
BIN=target/release/relreward
[[ -x $BIN ]] || { echo "maze_generate.sh: $BIN is missing: cargo build --release --workspace --bins" >&2; exit 2; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

rows=()
slow=0
for layout in open umaze medium large; do
  for mode in base expert; do
    start=$(date +%s.%N)
    "$BIN" --json maze generate --layout "$layout" --mode "$mode" --transitions "$TRANSITIONS" --seed 1 \
      --out "$tmp/$layout-$mode.npz" >"$tmp/summary.json"
    end=$(date +%s.%N)
    line=$(python3 - "$tmp/summary.json" "$start" "$end" "$tmp/$layout-$mode.npz" <<'PY'
import json, os, sys
s = json.load(open(sys.argv[1]))
wall = float(sys.argv[3]) - float(sys.argv[2])
print(json.dumps({
    "layout": s["layout"], "mode": s["mode"], "transitions": s["transitions"], "episodes": s["episodes"],
    "goals_reached": s["goals_reached"], "generate_s": round(s["generate_seconds"], 4),
    "write_s": round(s["write_seconds"], 4), "wall_s": round(wall, 4),
    "generate_per_s": round(s["transitions"] / s["generate_seconds"]),
    "end_to_end_per_s": round(s["transitions"] / wall), "file_bytes": os.path.getsize(sys.argv[4]),
}))
PY
)
    echo "$line"
    rows+=("$line")
    rate=$(python3 -c 'import json,sys; print(json.loads(sys.argv[1])["generate_per_s"])' "$line")
    (( rate >= FLOOR )) || slow=1
    rm -f "$tmp/$layout-$mode.npz"
  done
done

echo
printf '%s\n' "${rows[@]}" >"$tmp/rows.jsonl"
python3 - "$tmp/rows.jsonl" <<'PY'
import json, sys
print("%-8s %-7s %11s %9s %12s %13s" % ("layout", "mode", "transitions", "episodes", "generate/s", "end-to-end/s"))
for line in open(sys.argv[1]):
    r = json.loads(line)
    print("%-8s %-7s %11d %9d %12s %13s" % (r["layout"], r["mode"], r["transitions"], r["episodes"],
          format(r["generate_per_s"], ","), format(r["end_to_end_per_s"], ",")))
PY
if (( slow )); then
  echo "maze_generate.sh: a generation rate is below $FLOOR transitions/s" >&2
  exit 1
fi
