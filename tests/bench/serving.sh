#!/usr/bin/env bash
# Serving and memory benchmark: relreward against the Python reference server
# (bench/reference/grpc_server.py: grpcio + the PyTorch reference nets, one forward/backward per
# request, cross-checked by tests/tests/reference_server.rs), over loopback, for two reward
# models created the way a user would:
#
#   maze: windowed MLP (window 4, hidden 128,64,32) on [H, D] = [64, 6] (Maze2D obs 4 + act 2)
#   loco: Diffuser's ValueFunction (widths 64,64,128,128) on [32, 14] (locomotion obs 11 + act 3)
#
# The strongest Python peer runs beside both in the same rotation (A B C A B C): a dynamic-
# batching server (bench/reference/grpc_batching_server.py: grpc.aio, one batching queue per
# model, one pass per batch on a compute thread, the same nets and checks); its table follows
# the main one (issue 21's bar: 64 streaming clients, at least 3x its throughput, lower p99).
#
# Serving, A B A B over REPS repetitions (medians and ratios), per model: unary Gradient with 1
# client for UNARY_SECS (latency p50 / p99), and GradientStream with 64 closed-loop clients for
# DURATION seconds (throughput, p99). Then relreward alone: GradientStream with 1 and 8 clients,
# and 64 clients again after a restart with RELREWARD__SERVING__MAX_BATCH=1 (one request per
# forward, the baseline its dynamic batcher must beat).
#
# Memory (relreward's VmRSS from /proc): a fresh server on the same data directory, idle, then
# with 10 reward models loaded (each queried once), then under SOAK_CLIENTS GradientStream
# clients for SOAK_SECS seconds, sampled every few seconds (growth and least-squares slope);
# SOAK_SECS=600 gives the issue's 10-minute figure. The reference server is measured beside it
# (started with the same 10 models, which it loads at start).
#
# Both servers run with THREADS libtorch intra-op threads (default 1; relreward's
# engine.intra_op_threads, the reference's torch.set_num_threads; THREADS=0 leaves both at their
# default, one per core). One, because the load generator shares the cores: a second OpenMP
# thread then waits at every parallel region's barrier for a core the clients hold, and both
# servers lose throughput several times over (with 2 threads on 2 shared cores, 64 streaming
# clients: relreward 5.7k -> 0.1-1.1k items/s, the reference 0.9k -> 0.3-0.5k).
#
# Prints one JSON line per load run and the tables at the end, and splices the markdown into
# BENCHMARKS.md (sections `serving` and `memory`, tests/bench/splice.py) unless SPLICE=0; with
# OUT_DIR=DIR the bodies are also kept as DIR/serving.md and DIR/memory.md. Exits 1 if any
# request failed. Missed bars are reported in the tables, not as a failure.
#
# Builds nothing: expects target/release/{relreward-server,relreward,relreward-loadgen}
# (`cargo build --release --workspace --bins`). Starts its own servers on loopback ports with a
# temporary data directory, so it never touches ./data. The load generator runs on the same
# CPUs as the servers, which every figure includes. About 7 minutes with the defaults on a
# 2-core machine.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPS=${REPS:-3}
DURATION=${DURATION:-10}
UNARY_SECS=${UNARY_SECS:-4}
SOAK_SECS=${SOAK_SECS:-60}
SOAK_CLIENTS=${SOAK_CLIENTS:-16}
THREADS=${THREADS:-1}
SPLICE=${SPLICE:-1}
OUT_DIR=${OUT_DIR:-}
BIN=target/release
PY=.venv/bin/python
for b in relreward-server relreward relreward-loadgen; do
  [[ -x $BIN/$b ]] || { echo "serving.sh: $BIN/$b is missing: cargo build --release --workspace --bins" >&2; exit 2; }
done
[[ -x $PY ]] || { echo "serving.sh: $PY is missing: make setup" >&2; exit 2; }
tmp=$(mktemp -d)
reference= batching=
stop() { # stop PID-VARIABLE
  local pid=${!1}
  if [[ -n $pid ]]; then
    kill "$pid" 2>/dev/null || true
    wait "$pid" 2>/dev/null || true
    printf -v "$1" ''
  fi
}
. tests/bench/lib.sh
trap 'stop_server; stop reference; stop batching; rm -rf "$tmp"' EXIT
started=$(date +%s)

# relreward (start_server, tests/bench/lib.sh) with THREADS intra-op threads (0: its default).
[[ $THREADS == 0 ]] || server_env=(RELREWARD__ENGINE__INTRA_OP_THREADS="$THREADS")

# start_reference MODEL...: the Python server over the same models, as downloaded through the
# API into $tmp/models (see the download after training).
start_reference() {
  local models=()
  for m in "$@"; do models+=(--model "$m"); done
  "$PY" bench/reference/grpc_server.py --listen 127.0.0.1:0 --models-dir "$tmp/models" --threads "$THREADS" \
    "${models[@]}" >"$tmp/reference.out" 2>>"$tmp/reference.log" &
  reference=$!
  ref_endpoint="http://$(wait_line "$tmp/reference.out" 'reference grpc_server listening on ' "$reference" grpc_server.py \
    "$tmp/reference.log")"
}

# start_batching MODEL...: the dynamic-batching Python server over the same downloaded models.
start_batching() {
  local models=()
  for m in "$@"; do models+=(--model "$m"); done
  "$PY" bench/reference/grpc_batching_server.py --listen 127.0.0.1:0 --models-dir "$tmp/models" --threads "$THREADS" \
    "${models[@]}" >"$tmp/batching.out" 2>>"$tmp/batching.log" &
  batching=$!
  batch_endpoint="http://$(wait_line "$tmp/batching.out" 'reference grpc_batching_server listening on ' "$batching" \
    grpc_batching_server.py "$tmp/batching.log")"
}

rss_kib() { sed -n 's/^VmRSS:[[:space:]]*\([0-9]*\) kB/\1/p' "/proc/$1/status"; }
hwm_kib() { sed -n 's/^VmHWM:[[:space:]]*\([0-9]*\) kB/\1/p' "/proc/$1/status"; }

# ---------------------------------------------------------------------------------------------
# Models

start_server
# Maze-like D = 6 (obs 4 + act 2) from the tests' generator; locomotion-like D = 14 (obs 11 +
# act 3, episodes of up to 1000 steps ending in a timeout, a few terminals).
"$PY" tests/python/make_dataset.py --rows 20000 --seed 1 --out "$tmp/maze.npz" --expected "$tmp/e.json" >/dev/null
"$PY" - "$tmp/loco.npz" <<'PY'
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
# Eight more (other seeds, and widths for the windowed MLPs) for the 10-models memory figure.
ten=(maze-reward loco-reward)
for i in 2 3 4 5; do
  quiet rr train reward --name "maze-reward-$i" --base maze-base --expert maze-expert --dataset maze \
    --arch windowed_mlp --window 4 --hidden "$((64 * i)),64,32" --seed "$i" --steps 1 --batch-size 2 --watch
  quiet rr train reward --name "loco-reward-$i" --base loco-base --expert loco-expert --dataset loco \
    --arch value_function --widths 64,64,128,128 --seed "$i" --steps 1 --batch-size 2 --watch
  ten+=("maze-reward-$i" "loco-reward-$i")
done
declare -A shape=([maze-reward]=64,6 [loco-reward]=32,14)
# The Python references read the same weights, fetched through the API (DownloadModel).
for m in "${ten[@]}"; do quiet rr model download "$m" --out "$tmp/models/$m"; done
for i in 2 3 4 5; do shape[maze-reward-$i]=64,6; shape[loco-reward-$i]=32,14; done

# ---------------------------------------------------------------------------------------------
# Serving, A B A B

# load SERVER LABEL MODEL ENDPOINT EXTRA-JSON LOADGEN-FLAGS...: one load run, one JSON line.
load() {
  local who=$1 label=$2 model=$3 ep=$4 extra=$5
  shift 5
  "$BIN/relreward-loadgen" --endpoint "$ep" --model "$model" --shape "${shape[$model]}" --json "$@" >"$tmp/run.json"
  python3 - "$tmp/run.json" "$who" "$label" "$extra" <<'PY' | tee -a "$tmp/results"
import json, sys
r = json.load(open(sys.argv[1]))
if r.get("rss"):
    r["rss"].pop("samples")  # one line per run stays short; the soak's samples stay in run.json
print(json.dumps({"benchmark": "serving", "server": sys.argv[2], "run": sys.argv[3], **json.loads(sys.argv[4]), **r}))
PY
}

# Both servers fresh: relreward restarted after the training jobs (which loaded diffusion models).
start_reference maze-reward loco-reward
start_batching maze-reward loco-reward
stop_server
start_server
threads_rr=$(sed -n 's/.*intra_op_threads[=: ]*\([0-9]*\).*/\1/p' "$tmp/log" | tail -1)
threads_ref=$(sed -n 's/.*torch intra-op threads \([0-9]*\).*/\1/p' "$tmp/reference.log" | tail -1)
for rep in $(seq "$REPS"); do
  for model in maze-reward loco-reward; do
    for who in relreward reference batching; do
      case $who in
        relreward) ep=$endpoint pid=$server ;;
        reference) ep=$ref_endpoint pid=$reference ;;
        batching) ep=$batch_endpoint pid=$batching ;;
      esac
      load "$who" "unary c=1" "$model" "$ep" "{\"rep\": $rep}" --mode unary --clients 1 --duration "$UNARY_SECS"
      load "$who" "stream c=64" "$model" "$ep" "{\"rep\": $rep}" --mode stream --clients 64 --duration "$DURATION" \
        --rss-pid "$pid"
    done
  done
done
peak_rr=$(hwm_kib "$server") peak_ref=$(hwm_kib "$reference")
stop reference
stop batching

# relreward alone: fewer streaming clients, and one request per forward.
for model in maze-reward loco-reward; do
  for c in 1 8; do
    load relreward "stream c=$c" "$model" "$endpoint" '{}' --mode stream --clients "$c" --duration "$DURATION"
  done
done
stop_server
start_server RELREWARD__SERVING__MAX_BATCH=1
for model in maze-reward loco-reward; do
  load relreward "stream c=64, max_batch=1" "$model" "$endpoint" '{}' --mode stream --clients 64 --duration "$DURATION"
done
stop_server

# ---------------------------------------------------------------------------------------------
# Memory

# query_each ENDPOINT MODEL...: one Gradient per model (loads it).
query_each() {
  local ep=$1
  shift
  for m in "$@"; do
    quiet "$BIN/relreward-loadgen" --endpoint "$ep" --model "$m" --shape "${shape[$m]}" --requests 1 --warmup 0
  done
}
start_server
sleep 2
mem_idle=$(rss_kib "$server")
query_each "$endpoint" "${ten[@]}"
sleep 1
mem_ten=$(rss_kib "$server")
soak_every=$(python3 -c "print(max(1.0, $SOAK_SECS / 120))")
load relreward "soak c=$SOAK_CLIENTS" maze-reward "$endpoint" '{}' --mode stream --clients "$SOAK_CLIENTS" \
  --duration "$SOAK_SECS" --warmup 5 --rss-pid "$server" --rss-every "$soak_every"
cp "$tmp/run.json" "$tmp/soak.json"

stop_server
start_reference "${ten[@]}"
sleep 2
ref_idle=$(rss_kib "$reference")
query_each "$ref_endpoint" "${ten[@]}"
sleep 1
ref_ten=$(rss_kib "$reference")
stop reference

# ---------------------------------------------------------------------------------------------
# Report

cpu=$(lscpu | sed -n 's/^Model name:[[:space:]]*//p' | head -1)
cores=$(lscpu -p=socket,core | grep -v '^#' | sort -u | wc -l)
threads=$(nproc)
elapsed=$(($(date +%s) - started))
status=0
export REPS DURATION UNARY_SECS SOAK_SECS SOAK_CLIENTS THREADS cpu cores threads elapsed threads_rr threads_ref \
  mem_idle mem_ten ref_idle ref_ten peak_rr peak_ref
python3 - "$tmp" <<'PY' || status=$?
import json, os, statistics, sys, time
tmp = sys.argv[1]
E = os.environ
REPS, SOAK_SECS, SOAK_CLIENTS = int(E["REPS"]), int(E["SOAK_SECS"]), int(E["SOAK_CLIENTS"])
runs = [json.loads(l) for l in open(f"{tmp}/results")]
errors = sum(sum(r["errors"].values()) for r in runs)
machine = (f"{E['cpu']}, {E['cores']} cores ({E['threads']} hardware threads), libtorch intra-op threads: relreward "
           f"{E['threads_rr'] or '?'}, reference {E['threads_ref'] or '?'}"
           f"{' (THREADS=0: both defaults, one per core)' if E['THREADS'] == '0' else ' (THREADS; the default 1 leaves the other core to the load generator)'}; "
           f"{runs[0]['note']}")
env = " ".join(f"{k}={v}" for k, v in [("REPS", E["REPS"]), ("DURATION", E["DURATION"]), ("UNARY_SECS", E["UNARY_SECS"]),
                                        ("SOAK_SECS", E["SOAK_SECS"]), ("SOAK_CLIENTS", E["SOAK_CLIENTS"]), ("THREADS", E["THREADS"])])
command = f"cargo build --release --workspace --bins && {env} tests/bench/serving.sh"
date = time.strftime("%Y-%m-%d", time.gmtime())
models = {"maze-reward": "maze: windowed MLP h = 4, hidden (128, 64, 32), [64, 6]",
          "loco-reward": "loco: ValueFunction widths (64, 64, 128, 128), [32, 14]"}

def pick(who, label, model):
    return [r for r in runs if r["server"] == who and r["run"] == label and r["model"] == model]

def median(values):
    return statistics.median(values) if values else float("nan")

def fmt(v, digits=None):
    """Three significant-ish digits: 0.783, 28.5, 3942; `digits` fixes the decimals."""
    if v != v:
        return "n/a"
    if digits is not None:
        return f"{v:.{digits}f}"
    return f"{v:.3f}" if abs(v) < 10 else f"{v:.1f}" if abs(v) < 100 else f"{v:.0f}"

lines = [f"relreward against the Python reference server (`bench/reference/grpc_server.py`: grpcio thread pool, "
         f"the PyTorch reference nets on relreward's weights, one forward/backward per request; it computes the same "
         f"gradients and rho to 1e-5, `tests/tests/reference_server.rs`). Loopback, closed-loop clients of "
         f"`relreward-loadgen` (one connection and one request in flight each, B = 1, normalized units, t = 0), "
         f"A B A B over {REPS} repetition{'s' if REPS > 1 else ''}: medians, with every repetition in brackets. Ratio: > 1 means relreward "
         f"is better (throughput relreward / reference; latency reference / relreward).",
         "",
         f"Machine: {machine}. {date}. Command: `{command}` ({E['elapsed']} s in all).",
         "",
         "| model | configuration | metric | relreward | reference | ratio |",
         "|---|---|---|---|---|---|"]
summary = {}
for model in ("maze-reward", "loco-reward"):
    for label, metrics in (("unary c=1", (("p50 ms", "p50"), ("p99 ms", "p99"))),
                           ("stream c=64", (("items/s", "items_per_s"), ("p99 ms", "p99")))):
        config = ("unary Gradient, 1 client, " + E["UNARY_SECS"] + " s" if label == "unary c=1"
                  else "GradientStream, 64 clients, " + E["DURATION"] + " s")
        for name, key in metrics:
            got = {}
            for who in ("relreward", "reference"):
                vals = [r["items_per_s"] if key == "items_per_s" else (r.get("latency_ms") or {}).get(key, float("nan"))
                        for r in pick(who, label, model)]
                got[who] = (median(vals), vals)
            a, b = got["relreward"][0], got["reference"][0]
            ratio = a / b if key == "items_per_s" else b / a
            summary[(model, label, key)] = (a, b, ratio)
            cell = lambda m, vals: f"{fmt(m)} [{', '.join(fmt(v) for v in vals)}]"
            bold = "**" if model == "maze-reward" and (label, key) in (("unary c=1", "p50"), ("stream c=64", "items_per_s"), ("stream c=64", "p99")) else ""
            lines.append(f"| {models[model].split(':')[0]} | {config} | {name} | {bold}{cell(*got['relreward'])}{bold} | "
                         f"{cell(*got['reference'])} | {bold}{fmt(ratio, 2)}x{bold} |")
lines += ["", "Models: " + "; ".join(models.values()) + ". Each trained one step (weights do not change the cost)."]
tp = summary[("maze-reward", "stream c=64", "items_per_s")]
p99 = summary[("maze-reward", "stream c=64", "p99")]
p50 = summary[("maze-reward", "unary c=1", "p50")]
ok = lambda c: "met" if c else "**missed**"
lines += ["", "Bars (issue 7, maze model):", "",
          f"- 64 streaming clients, at least 5x the reference's throughput: {fmt(tp[2], 2)}x, {ok(tp[2] >= 5)}; "
          f"with lower p99 ({fmt(p99[0])} vs {fmt(p99[1])} ms): {ok(p99[0] < p99[1])}.",
          f"- single-client p50 under 1 ms: {fmt(p50[0])} ms (unary Gradient), {ok(p50[0] < 1.0)}."]
lines += ["", "relreward alone, one run each: fewer streaming clients, and 64 clients after a restart with "
          "`RELREWARD__SERVING__MAX_BATCH=1` (one request per forward: what the dynamic batcher is measured against).", "",
          "| model | configuration | items/s | p50 ms | p99 ms | max ms |", "|---|---|---|---|---|---|"]
alone = {"stream c=1": "GradientStream, 1 client", "stream c=8": "GradientStream, 8 clients",
         "stream c=64, max_batch=1": "GradientStream, 64 clients, `max_batch = 1`"}
for model in ("maze-reward", "loco-reward"):
    for label in alone:
        for r in pick("relreward", label, model):
            l = r.get("latency_ms") or {}
            lines.append(f"| {models[model].split(':')[0]} | {alone[label]} | "
                         f"{fmt(r['items_per_s'])} | {fmt(l.get('p50', float('nan')))} | {fmt(l.get('p99', float('nan')))} | {fmt(l.get('max', float('nan')))} |")
    batched = summary[(model, "stream c=64", "items_per_s")][0]
    single = [r["items_per_s"] for r in pick("relreward", "stream c=64, max_batch=1", model)]
    if single and single[0] > 0:
        lines.append(f"| {models[model].split(':')[0]} | dynamic batching vs max_batch = 1, 64 clients | "
                     f"{fmt(batched / single[0], 2)}x | | | |")
lines += ["", "relreward against the dynamic-batching Python server (`bench/reference/grpc_batching_server.py`: grpc.aio, "
          "one batching queue per model taking whatever is queued up to 256 items (relreward's `max_batch`, "
          "`max_delay_us = 0`), one forward/backward per batch on a compute thread, the same nets, weights and checks "
          "as the reference), measured in the same rotation. relreward runs its `[serving]` defaults unless the "
          "environment overrides them: a batch waits for the last pass's callers (`refill_fraction`), and a long pass "
          "(the ValueFunction's) is split by rows across up to `pass_threads` = 2 threads, so it may use both cores "
          "where the Python server computes on one thread. Ratio as above.", "",
          "| model | configuration | metric | relreward | batching Python | ratio |", "|---|---|---|---|---|---|"]
for model in ("maze-reward", "loco-reward"):
    for label, key, name in (("unary c=1", "p50", "p50 ms"), ("stream c=64", "items_per_s", "items/s"),
                             ("stream c=64", "p99", "p99 ms")):
        got = {}
        for who in ("relreward", "batching"):
            vals = [r["items_per_s"] if key == "items_per_s" else (r.get("latency_ms") or {}).get(key, float("nan"))
                    for r in pick(who, label, model)]
            got[who] = (median(vals), vals)
        a, b = got["relreward"][0], got["batching"][0]
        ratio = a / b if key == "items_per_s" else b / a
        summary[(model, label, key, "batching")] = (a, b, ratio)
        config = "unary Gradient, 1 client" if label == "unary c=1" else "GradientStream, 64 clients"
        cell = lambda m, vals: f"{fmt(m)} [{', '.join(fmt(v) for v in vals)}]"
        lines.append(f"| {models[model].split(':')[0]} | {config} | {name} | {cell(*got['relreward'])} | "
                     f"{cell(*got['batching'])} | {fmt(ratio, 2)}x |")
btp = summary[("maze-reward", "stream c=64", "items_per_s", "batching")]
bp99 = summary[("maze-reward", "stream c=64", "p99", "batching")]
lines += ["", f"Bar (issue 21, maze model): 64 streaming clients, at least 3x the batching Python server's throughput: "
          f"{fmt(btp[2], 2)}x, {ok(btp[2] >= 3)}; with lower p99 ({fmt(bp99[0])} vs {fmt(bp99[1])} ms): {ok(bp99[0] < bp99[1])}."]
serving_md = "\n".join(lines) + "\n"

soak = json.load(open(f"{tmp}/soak.json"))
rss = soak["rss"]
mib = lambda kib: f"{int(kib) / 1024:.1f} MiB"
growth_pct = 100.0 * rss["growth_kib"] / rss["start_kib"]
slope = lambda s: "n/a" if s is None else f"{s / 1024:+.2f} MiB/min"
mem = [f"Resident set size (VmRSS from /proc/PID/status) of relreward-server and of the Python reference server, "
       f"same machine and date as the serving section. Command: `{command}`.",
       "",
       "| state | relreward | reference |",
       "|---|---|---|",
       f"| idle: fresh start (the reference loads its 10 models at start) | {mib(E['mem_idle'])} | {mib(E['ref_idle'])} |",
       f"| 10 reward models loaded (5 maze windowed MLPs, 5 ValueFunctions), each queried once | {mib(E['mem_ten'])} | {mib(E['ref_ten'])} |",
       f"| peak (VmHWM) over the serving runs above (64 streaming clients) | {mib(E['peak_rr'])} | {mib(E['peak_ref'])} |",
       "",
       f"Sustained load: relreward with the 10 models loaded, GradientStream on the maze model with {SOAK_CLIENTS} "
       f"clients for {SOAK_SECS} s after a 5 s warm-up, {soak['items']} requests ({fmt(soak['items_per_s'])} items/s, "
       f"p99 {fmt((soak.get('latency_ms') or {}).get('p99', float('nan')))} ms), VmRSS sampled every {rss['every_s']:g} s "
       f"({len(soak['rss']['samples'])} samples).",
       "",
       "| RSS at the window's start | at its end | growth | least-squares slope | slope over the second half | max | peak (VmHWM) |",
       "|---|---|---|---|---|---|---|",
       f"| {mib(rss['start_kib'])} | {mib(rss['end_kib'])} | {rss['growth_kib'] / 1024:+.1f} MiB ({growth_pct:+.2f} %) | "
       f"{slope(rss['slope_kib_per_min'])} | {slope(rss['slope_second_half_kib_per_min'])} | {mib(rss['max_kib'])} | {mib(rss['peak_kib'])} |",
       "",
       f"No-growth bar (a 10-minute run: SOAK_SECS=600): growth under 1 % of the starting RSS over the window: "
       f"{ok(abs(growth_pct) < 1.0)}" + ("" if SOAK_SECS >= 600 else f" (this run: {SOAK_SECS} s)") + "."]
memory_md = "\n".join(mem) + "\n"
open(f"{tmp}/serving.md", "w").write(serving_md)
open(f"{tmp}/memory.md", "w").write(memory_md)
print()
print(serving_md)
print(memory_md)
sys.exit(1 if errors else 0)
PY
if [[ -n $OUT_DIR ]]; then mkdir -p "$OUT_DIR" && cp "$tmp/serving.md" "$tmp/memory.md" "$OUT_DIR/"; fi
if [[ $SPLICE != 0 ]]; then
  "$PY" tests/bench/splice.py serving "$tmp/serving.md"
  "$PY" tests/bench/splice.py memory "$tmp/memory.md"
fi
exit $status
