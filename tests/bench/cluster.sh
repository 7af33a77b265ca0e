#!/usr/bin/env bash
# Scale-out benchmark (issue 9), on loopback against a real PostgreSQL and S3-protocol server
# (tests/cluster/infra.sh):
#
# 1. Gradient throughput, GradientStream with CLIENTS closed-loop clients for DURATION seconds
#    on a maze-sized reward (windowed MLP h = 4, hidden 128,64,32, [64, 6]): one serving
#    replica, then two behind a client-side round-robin (relreward-loadgen --endpoint twice:
#    client i on replica i mod 2), A B A B over REPS repetitions, medians. On a 2-core machine
#    two replicas cannot add compute, which the table says.
# 2. Queue overhead per job: submit-to-start latency (the RUNNING event's time minus the
#    PENDING event's) of JOBS one-step diffusion jobs, submitted one at a time: the shared
#    backend (submitted to a serving replica, claimed by a separate worker polling PostgreSQL
#    every jobs.poll_ms) against the embedded one (one process, woken by the submission).
#
# Writes the `cluster` section of BENCHMARKS.md (tests/bench/splice.py) unless SPLICE=0.
# Builds nothing: expects target/release/{relreward-server,relreward,relreward-loadgen}.
# About 3 minutes on a 2-core machine after the first run of infra.sh.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPS=${REPS:-3}
DURATION=${DURATION:-10}
CLIENTS=${CLIENTS:-64}
JOBS=${JOBS:-10}
POLLS=${POLLS:-1000 100}
SPLICE=${SPLICE:-1}
BIN=target/release
PY=.venv/bin/python
for b in relreward-server relreward relreward-loadgen; do
  [[ -x $BIN/$b ]] || { echo "cluster.sh: $BIN/$b is missing: cargo build --release --workspace --bins" >&2; exit 2; }
done
tmp=$(mktemp -d /tmp/relreward-bench-cluster.XXXXXX)
# wait_line, rr and quiet (its servers are several, started by `start` below).
. tests/bench/lib.sh
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  tests/cluster/infra.sh stop "$tmp/infra" >/dev/null 2>&1 || true
  rm -rf "$tmp"
}
trap cleanup EXIT
started=$(date +%s)

# The PostgreSQL server runs as the postgres user (initdb refuses root): it must reach infra/.
chmod o+x "$tmp"
mkdir -p "$tmp/infra"
tests/cluster/infra.sh start "$tmp/infra" >"$tmp/infra.log" 2>&1 || { cat "$tmp/infra.log" >&2; exit 1; }
# shellcheck disable=SC1091
source "$tmp/infra/env"

# start NAME ROLE|embedded [POLL_MS]: a server on 127.0.0.1:0; sets ${NAME}_endpoint and
# ${NAME}_pid.
start() {
  local name=$1 role=$2 env=(RELREWARD__METRICS__LISTEN= RELREWARD__ENGINE__INTRA_OP_THREADS=1)
  if [[ $role != embedded ]]; then
    env+=(RELREWARD__SERVER__ROLE="$role" RELREWARD__STORAGE__BACKEND=shared
      RELREWARD__STORAGE__POSTGRES__URL="$RELREWARD_TEST_PG_URL"
      RELREWARD__STORAGE__POSTGRES__CA_FILE="$RELREWARD_TEST_PG_CA"
      RELREWARD__STORAGE__S3__ENDPOINT="$RELREWARD_TEST_S3_ENDPOINT"
      RELREWARD__STORAGE__S3__BUCKET="$RELREWARD_TEST_S3_BUCKET"
      RELREWARD__STORAGE__S3__REGION="$RELREWARD_TEST_S3_REGION"
      RELREWARD__STORAGE__S3__ACCESS_KEY_ID="$RELREWARD_TEST_S3_ACCESS_KEY_ID"
      RELREWARD__STORAGE__S3__SECRET_ACCESS_KEY="$RELREWARD_TEST_S3_SECRET_ACCESS_KEY"
      RELREWARD__STORAGE__S3__ALLOW_HTTP=true RELREWARD__JOBS__POLL_MS="${3:-1000}")
  fi
  env "${env[@]}" "$BIN/relreward-server" --listen 127.0.0.1:0 --data-dir "$tmp/$name" \
    >"$tmp/$name.out" 2>"$tmp/$name.log" &
  local pid=$! address
  pids+=("$pid")
  printf -v "${name}_pid" '%s' "$pid"
  address=$(wait_line "$tmp/$name.out" 'relreward-server listening on ' "$pid" "$name" "$tmp/$name.log")
  printf -v "${name}_endpoint" 'http://%s' "$address"
}

# --- Models: through replica 1, trained by the worker --------------------------------------
start serve1 serve
start work1 work
export RELREWARD_ENDPOINT=$serve1_endpoint
"$PY" tests/python/make_dataset.py --rows 20000 --seed 1 --out "$tmp/maze.npz" --expected "$tmp/e.json" >/dev/null
quiet rr dataset upload "$tmp/maze.npz" --name maze
cat >"$tmp/unet.toml" <<'TOML'
[diffusion]
horizon = 64
n_timesteps = 20
architecture = { kind = "temporal_unet", dim = 16, dim_mults = [1, 2] }
TOML
for m in base expert; do
  quiet rr train diffusion --name "$m" --dataset maze --config "$tmp/unet.toml" --steps 1 --batch-size 2 --watch
done
quiet rr train reward --name maze-reward --base base --expert expert --dataset maze --arch windowed_mlp \
  --window 4 --hidden 128,64,32 --steps 1 --batch-size 2 --watch

# --- 1. Throughput: one replica vs two --------------------------------------------------------
start serve2 serve
load() { # ENDPOINT...: one loadgen run, its JSON report
  local args=()
  for e in "$@"; do args+=(--endpoint "$e"); done
  "$BIN/relreward-loadgen" "${args[@]}" --model maze-reward --mode stream --clients "$CLIENTS" \
    --duration "$DURATION" --json
}
: >"$tmp/load.jsonl"
for rep in $(seq "$REPS"); do
  echo "{\"replicas\": 1, \"rep\": $rep, \"report\": $(load "$serve1_endpoint")}" >>"$tmp/load.jsonl"
  echo "{\"replicas\": 2, \"rep\": $rep, \"report\": $(load "$serve1_endpoint" "$serve2_endpoint")}" >>"$tmp/load.jsonl"
done

# --- 2. Queue overhead: submit-to-start, shared vs embedded --------------------------------
latencies() { # LABEL: JOBS one-step jobs, one at a time, against $RELREWARD_ENDPOINT
  for i in $(seq "$JOBS"); do
    rr --json train diffusion --name "q-${1//[^a-z0-9]/-}-$i" --dataset maze --config "$tmp/unet.toml" --steps 1 \
      --batch-size 2 --watch >"$tmp/events" 2>>"$tmp/cmd.log"
    "$PY" - "$1" "$tmp/events" <<'PY' >>"$tmp/queue.jsonl"
import json, sys
from datetime import datetime
def at(e):
    return datetime.fromisoformat(e["time"].replace("Z", "+00:00")).timestamp()
states = {}
for line in open(sys.argv[2]):
    line = line.strip()
    if line.startswith("{"):
        e = json.loads(line)
        if e.get("type") == "state":
            states.setdefault(e["state"], at(e))
print(json.dumps({"backend": sys.argv[1], "ms": 1000 * (states["running"] - states["pending"])}))
PY
  done
}
: >"$tmp/queue.jsonl"
# The worker that trained the models, then one per poll interval.
kill "$work1_pid"; wait "$work1_pid" 2>/dev/null || true
for poll in $POLLS; do
  start "work_$poll" work "$poll"
  latencies "shared:$poll"
  pid_var="work_${poll}_pid"
  kill "${!pid_var}"; wait "${!pid_var}" 2>/dev/null || true
done
start solo embedded
export RELREWARD_ENDPOINT=$solo_endpoint
quiet rr dataset upload "$tmp/maze.npz" --name maze
latencies embedded

# --- Report -------------------------------------------------------------------------------------
cpu=$(sed -n 's/^model name[[:space:]]*: //p' /proc/cpuinfo | head -1)
"$PY" - "$tmp/load.jsonl" "$tmp/queue.jsonl" "$cpu" "$(nproc)" "$(( $(date +%s) - started ))" \
  "$REPS" "$DURATION" "$CLIENTS" "$JOBS" "$POLLS" >"$tmp/cluster.md" <<'PY'
import json, statistics, sys, datetime
load_file, queue_file, cpu, cores, secs, reps, duration, clients, jobs, polls = sys.argv[1:]
runs = [json.loads(l) for l in open(load_file)]
queue = [json.loads(l) for l in open(queue_file)]
def med(xs): return statistics.median(xs)
print("Scale-out on one machine (`tests/bench/cluster.sh`): PostgreSQL and s3s-fs on loopback "
      "(tests/cluster/infra.sh), serving replicas with `--role serve`, one worker with `--role work`, "
      "the shared backend. The load generator, both replicas, the worker, PostgreSQL and the S3 "
      "server share the same CPUs.")
print()
print(f"Machine: {cpu}, {cores} cores; libtorch intra-op threads 1 per process; "
      f"{datetime.date.today()}. Command: `cargo build --release --workspace --bins && REPS={reps} "
      f"DURATION={duration} CLIENTS={clients} JOBS={jobs} POLLS='{polls}' tests/bench/cluster.sh` ({secs} s).")
print()
print(f"Gradient throughput, GradientStream, {clients} closed-loop clients, {duration} s, maze-sized "
      "windowed MLP reward [64, 6], B = 1; two replicas: client i connects to replica i mod 2 "
      f"(client-side round-robin). A B A B over {reps} repetitions, medians, every repetition in brackets.")
print()
print("| replicas | items/s | p50 ms | p99 ms |")
print("|---|---|---|---|")
base = None
for n in (1, 2):
    rs = [r["report"] for r in runs if r["replicas"] == n]
    ips = [r["items_per_s"] for r in rs]
    p50 = [r["latency_ms"]["p50"] for r in rs]
    p99 = [r["latency_ms"]["p99"] for r in rs]
    base = base or med(ips)
    br = lambda xs, f: ", ".join(f.format(x) for x in xs)
    print(f"| {n} | {med(ips):.0f} [{br(ips, '{:.0f}')}] ({med(ips) / base:.2f}x) | "
          f"{med(p50):.2f} [{br(p50, '{:.2f}')}] | {med(p99):.1f} [{br(p99, '{:.1f}')}] |")
print()
print(f"On {cores} cores a second replica adds no compute: both replicas, the load generator and "
      "the other processes compete for the same cores, so the figure shows the cost of the split "
      "(two batchers forming smaller batches), not the gain a second machine would bring.")
print()
print(f"Queue overhead per job: submit-to-start latency of {jobs} one-step diffusion jobs submitted one "
      "at a time (time of the job's RUNNING event minus its PENDING event, both recorded in the job's "
      "events).")
print()
print("| backend | how the job reaches a worker | median ms | max ms |")
print("|---|---|---|---|")
for b in [f"shared:{p}" for p in polls.split()] + ["embedded"]:
    ms = [q["ms"] for q in queue if q["backend"] == b]
    if b == "embedded":
        how = "one process: the submission wakes its dispatcher, which claims from SQLite"
    else:
        how = (f"submitted to a serving replica; a separate worker claims it from PostgreSQL "
               f"(`FOR UPDATE SKIP LOCKED`), polling every jobs.poll_ms = {b.split(':')[1]}")
    print(f"| {b.split(':')[0]} | {how} | {med(ms):.0f} | {max(ms):.0f} |")
print()
print("With the shared backend the latency is the wait for the worker's next poll, up to "
      "jobs.poll_ms (here close to it: each job is submitted right after the previous one ended, "
      "when the idle worker has just gone back to sleep); the claim itself is one short "
      "transaction. Lower `jobs.poll_ms` where submissions are interactive; a submission to a "
      "process that also works (role all) wakes its dispatcher at once.")
PY
cat "$tmp/cluster.md"
[[ $SPLICE == 1 ]] && "$PY" tests/bench/splice.py cluster "$tmp/cluster.md"
exit 0
