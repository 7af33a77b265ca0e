#!/usr/bin/env bash
# The Open Inference Protocol over HTTP/JSON against the same protocol over gRPC (issue 36's
# bar: REST p50 for one item within 2x of gRPC's), with the stock Triton clients
# (tests/bench/oip_http.py: tritonclient.grpc, tritonclient.http with binary tensors, and with
# JSON tensors), one closed-loop client, one item per call, a gradient query (reward and
# grad_x), rotated A B C over REPS repetitions of SECONDS each.
#
# Model: serving.sh's maze reward (windowed MLP, window 4, hidden 128,64,32, on [64, 6]) on a
# fresh server with oip_http.listen on; one libtorch intra-op thread (the client shares the
# cores). Splices the table into BENCHMARKS.md (section `oip-http`) unless SPLICE=0. Builds
# nothing: expects target/release/{relreward-server,relreward}. About 1 minute.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPS=${REPS:-3}
SECONDS_PER_RUN=${SECONDS_PER_RUN:-4}
SPLICE=${SPLICE:-1}
BIN=target/release
PY=.venv/bin/python
for b in relreward-server relreward; do
  [[ -x $BIN/$b ]] || { echo "oip_http.sh: $BIN/$b is missing: cargo build --release --workspace --bins" >&2; exit 2; }
done
tmp=$(mktemp -d)
. tests/bench/lib.sh
trap 'stop_server; rm -rf "$tmp"' EXIT

start_server RELREWARD__OIP_HTTP__LISTEN=127.0.0.1:0 RELREWARD__ENGINE__INTRA_OP_THREADS=1
http=$(wait_line "$tmp/out" 'relreward-server oip_http on ' "$server" "the OIP HTTP listener")

"$PY" tests/python/make_dataset.py --rows 20000 --seed 1 --out "$tmp/maze.npz" --expected "$tmp/e.json" >/dev/null
quiet rr dataset upload "$tmp/maze.npz" --name maze
cat >"$tmp/unet.toml" <<TOML
[diffusion]
horizon = 64
n_timesteps = 20
architecture = { kind = "temporal_unet", dim = 16, dim_mults = [1, 2] }
TOML
for m in base expert; do
  quiet rr train diffusion --name "maze-$m" --dataset maze --config "$tmp/unet.toml" --steps 1 --batch-size 2 --watch
done
quiet rr train reward --name maze-reward --base maze-base --expert maze-expert --dataset maze \
  --arch windowed_mlp --window 4 --hidden 128,64,32 --steps 1 --batch-size 2 --watch

"$PY" tests/bench/oip_http.py --grpc "${endpoint#http://}" --http "$http" --model maze-reward --data "$tmp/maze.npz" \
  --seconds "$SECONDS_PER_RUN" --reps "$REPS" >"$tmp/result.json"
cat "$tmp/result.json"; echo

"$PY" - "$tmp/result.json" "$REPS" "$SECONDS_PER_RUN" "$(cut -d' ' -f1-3 /proc/loadavg)" >"$tmp/section.md" <<'PY'
import json, os, statistics, sys
r = json.load(open(sys.argv[1]))
reps, secs, load = sys.argv[2], sys.argv[3], sys.argv[4]
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "unknown CPU")
res = r["results"]
med = lambda side, k: statistics.median(x[k] for x in res[side])
every = lambda side, k: ", ".join(f"{x[k]:.2f}" for x in res[side])
grpc50 = med("grpc", "p50_ms")
print(f"One item ([1, {', '.join(map(str, r['item_shape']))}], t = {r['t']}, reward and grad_x) per call, one "
      f"closed-loop client, through the stock Triton clients: `tritonclient.grpc` against `tritonclient.http` "
      f"(binary tensors, its default, and JSON tensors) on the same server. A B C over {reps} repetitions of "
      f"{secs} s: medians, every repetition in brackets; every answer checked bit for bit against gRPC's. "
      f"Command: `tests/bench/oip_http.sh`; machine: {cpu}, {os.cpu_count()} cores, client and server on it "
      f"together, engine.intra_op_threads = 1, load average {load} when it ended. Bar (issue 36): REST p50 "
      f"within 2x gRPC's.")
print()
print("| side | p50 ms | p99 ms | calls per run | p50 / gRPC p50 |")
print("|---|---|---|---|---|")
for side in ("grpc", "http-binary", "http-json"):
    ratio = med(side, "p50_ms") / grpc50
    bar = "" if side == "grpc" else (" (bar met)" if ratio <= 2 else " (**bar missed**)")
    print(f"| {side} | {med(side, 'p50_ms'):.2f} [{every(side, 'p50_ms')}] | {med(side, 'p99_ms'):.2f} "
          f"[{every(side, 'p99_ms')}] | {statistics.median(x['calls'] for x in res[side]):.0f} | {ratio:.2f}{bar} |")
PY
cat "$tmp/section.md"
if [[ $SPLICE == 1 ]]; then
  "$PY" tests/bench/splice.py oip-http "$tmp/section.md"
fi
