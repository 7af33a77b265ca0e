#!/usr/bin/env bash
# Training and sampling benchmark: relreward against the PyTorch references
# (bench/reference/reference.py, cross-checked to compute the same numbers by
# server/tests/training_vs_pytorch.rs), on the paper's maze configuration scaled to a small CPU:
#
#   data: horizon 64, D = 6 (Maze2D observation 4 + action 2), T = 100, Diffuser's cosine
#         schedule, x0 parametrization (relreward's defaults, as Diffuser's maze configs)
#   diffusion models: TemporalUnet dim 32, dim_mults (1, 4, 8)
#   reward: windowed MLP, h = 4, hidden (128, 64, 32)
#
# 1. Algorithm 1 steps/s (batch 64, target mean at x_t, Adam lr 5e-5, EMA): relreward's reward
#    job vs bench.py alg1 on the same base and expert models (weights read from relreward's
#    data directory).
# 2. DDPM training steps/s (batch 64, Adam lr 2e-4, EMA): relreward's diffusion job vs
#    bench.py ddpm.
# 3. Guided sampling time per trajectory (SAMPLE_N trajectories in one batch, n_guide_steps 1,
#    omega 0.1, t_stopgrad 0, start and goal conditioned): `relreward sample` (wall time of the
#    CLI call, so it includes process start and streaming the samples back) vs bench.py sample.
#
# The PyTorch reference also runs under torch.compile (inductor on the CPU; COMPILE=0 skips it)
# in the same rotation (A B C A B C) for Algorithm 1 and DDPM, reporting its compile time.
# Spread: every side's runs are reported as min / median / max, and a ratio whose sides spread
# by more than SPREAD (max / min, default 1.25) is flagged as not meaningful (one descheduled
# run on a shared machine moves a median of 3 that much).
#
# Each benchmark alternates relreward and the reference (A B A B ...) over REPS repetitions and
# reports medians and the speed ratio relreward / reference (> 1: relreward is faster).
# relreward's training rate comes from its job's own progress events, between step WARMUP and
# step WARMUP + STEPS (excluding start-up and the held-out evaluation at the last step); the
# reference times the same steps after WARMUP untimed ones. Peak RSS: relreward's server
# (VmHWM; one server per benchmark, so each figure covers that benchmark only) and each
# reference process (VmHWM). FLOPs per step are counted from the architecture
# (bench/reference/report.py shows the arithmetic), against this CPU's fp32 peak from lscpu.
#
# Settings (environment): REPS (3), WARMUP (10) and ALG1_STEPS (50), DDPM_STEPS (20): multiples
# of relreward's progress interval (10); SAMPLE_N (64); THREADS (libtorch intra-op threads on
# both sides; default: one per core, relreward's default); SPLICE (1: write the `training`
# section of BENCHMARKS.md via tests/bench/splice.py; 0: print only); OUT_DIR (also keep the
# markdown body and the raw results there). About 7 minutes with the defaults on a 2-core
# machine.
#
# Builds nothing: expects target/release/{relreward-server,relreward}
# (`cargo build --release --workspace --bins`). Starts its own servers on loopback ports with a
# temporary data directory, so it never touches ./data.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPS=${REPS:-3}
WARMUP=${WARMUP:-10}
ALG1_STEPS=${ALG1_STEPS:-50}
DDPM_STEPS=${DDPM_STEPS:-20}
SAMPLE_N=${SAMPLE_N:-64}
THREADS=${THREADS:-$(nproc)}
SPLICE=${SPLICE:-1}
OUT_DIR=${OUT_DIR:-}
COMPILE=${COMPILE:-1}
SPREAD=${SPREAD:-1.25}
ONLY=${ONLY:-alg1 ddpm sample}
LOG_EVERY=10
BIN=target/release
PY=.venv/bin/python
for b in relreward-server relreward; do
  [[ -x $BIN/$b ]] || { echo "training.sh: $BIN/$b is missing: cargo build --release --workspace --bins" >&2; exit 2; }
done
[[ -x $PY ]] || { echo "training.sh: $PY is missing: make setup" >&2; exit 2; }
for v in WARMUP ALG1_STEPS DDPM_STEPS; do
  (( ${!v} > 0 && ${!v} % LOG_EVERY == 0 )) || { echo "training.sh: $v must be a positive multiple of $LOG_EVERY" >&2; exit 2; }
done
tmp=$(mktemp -d)
. tests/bench/lib.sh
trap 'stop_server; rm -rf "$tmp"' EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
started=$(date +%s)
results=$tmp/results.jsonl
: >"$results"

server_env=(RELREWARD__ENGINE__INTRA_OP_THREADS="$THREADS")

# server_peak_mib: the running server's peak RSS (VmHWM), MiB.
server_peak_mib() { awk '/^VmHWM:/ { printf "%.1f", $2 / 1024 }' "/proc/$server/status"; }

# record BENCHMARK SIDE REP JSON: one result line, with the 1-minute load average after the run
# (this benchmark's own process counts for about THREADS; more means others shared the CPUs).
record() {
  local load
  load=$(cut -d' ' -f1 /proc/loadavg)
  echo "{\"benchmark\": \"$1\", \"side\": \"$2\", \"rep\": $3, \"load\": $load, \"result\": $4}" | tee -a "$results"
}

# job_rate EVENTS: steps/s of a job between steps WARMUP and WARMUP + STEPS, from its progress
# events (each carries the mean rate since the job started: elapsed(step) = step / rate).
job_rate() {
  "$PY" - "$1" "$WARMUP" "$2" <<'PY'
import json, sys
events = [json.loads(l) for l in open(sys.argv[1]) if l.lstrip().startswith("{")]
rate = {e["step"]: e["steps_per_second"] for e in events if e.get("type") == "progress"}
a, b = int(sys.argv[2]), int(sys.argv[2]) + int(sys.argv[3])
if a not in rate or b not in rate:
    sys.exit(f"training.sh: progress events lack step {a} or {b}: {sorted(rate)}")
seconds = b / rate[b] - a / rate[a]
print(json.dumps({"steps": b - a, "seconds": seconds, "steps_per_second": (b - a) / seconds}))
PY
}

# --- setup: data and the two frozen diffusion models ---------------------------------------------
echo "training.sh: setup (data, base and expert diffusion models)" >&2
"$PY" tests/python/make_dataset.py --rows 20000 --seed 1 --out "$tmp/maze.npz" --expected "$tmp/expected.json"
cat >"$tmp/unet.toml" <<TOML
[diffusion]
horizon = 64
n_timesteps = 100
architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 4, 8] }
TOML
start_server
rr dataset upload "$tmp/maze.npz" --name maze >/dev/null
# The frozen models' weights do not change the cost of a step: one step each suffices.
for m in base expert; do
  rr train diffusion --name "$m" --dataset maze --config "$tmp/unet.toml" --steps 1 --batch-size 2 --watch >/dev/null
  # The reference reads the same weights, fetched through the API.
  rr model download "$m" --out "$tmp/models/$m" >/dev/null
done
stop_server

reference() { "$PY" bench/reference/bench.py "$@" --models-dir "$tmp/models" --threads "$THREADS"; }

# wanted BENCHMARK: whether ONLY names it (ONLY="alg1 ddpm" skips sampling, for quick reruns).
wanted() { [[ " $ONLY " == *" $1 "* ]]; }

# --- 1. Algorithm 1 ------------------------------------------------------------------------------
alg1_total=$((WARMUP + ALG1_STEPS + LOG_EVERY))
if wanted alg1; then
start_server
for rep in $(seq "$REPS"); do
  rr --json train reward --name "reward-$rep" --base base --expert expert --dataset maze --arch windowed_mlp \
    --window 4 --hidden 128,64,32 --steps "$alg1_total" --batch-size 64 --watch >"$tmp/events"
  record alg1 relreward "$rep" "$(job_rate "$tmp/events" "$ALG1_STEPS")"
  record alg1 reference "$rep" "$(reference alg1 --base base --expert expert --dataset "$tmp/maze.npz" \
    --batch 64 --steps "$ALG1_STEPS" --warmup "$WARMUP")"
  if [[ $COMPILE == 1 ]]; then
    record alg1 compiled "$rep" "$(reference alg1 --base base --expert expert --dataset "$tmp/maze.npz" \
      --batch 64 --steps "$ALG1_STEPS" --warmup "$WARMUP" --compile)"
  fi
done
record alg1 relreward-server 0 "{\"peak_rss_mib\": $(server_peak_mib)}"
stop_server
fi

# --- 2. DDPM -------------------------------------------------------------------------------------
ddpm_total=$((WARMUP + DDPM_STEPS + LOG_EVERY))
if wanted ddpm; then
start_server
for rep in $(seq "$REPS"); do
  rr --json train diffusion --name "ddpm-$rep" --dataset maze --config "$tmp/unet.toml" --steps "$ddpm_total" \
    --batch-size 64 --watch >"$tmp/events"
  record ddpm relreward "$rep" "$(job_rate "$tmp/events" "$DDPM_STEPS")"
  record ddpm reference "$rep" "$(reference ddpm --manifest-of base --dataset "$tmp/maze.npz" \
    --batch 64 --steps "$DDPM_STEPS" --warmup "$WARMUP")"
  if [[ $COMPILE == 1 ]]; then
    record ddpm compiled "$rep" "$(reference ddpm --manifest-of base --dataset "$tmp/maze.npz" \
      --batch 64 --steps "$DDPM_STEPS" --warmup "$WARMUP" --compile)"
  fi
done
record ddpm relreward-server 0 "{\"peak_rss_mib\": $(server_peak_mib)}"
stop_server
fi

# --- 3. Guided sampling --------------------------------------------------------------------------
# Maze planning: start and goal observations [x, y, vx, vy] (raw units) at the ends.
conditions=(--condition 0=1.5,1.5,0,10000 --condition 63=6.5,8.5,0,10000)
guide=(--n-guide-steps 1 --t-stopgrad 0)
if wanted sample; then
start_server
# The guiding reward comes from part 1; run alone (ONLY=sample), train one briefly (its weights
# do not change the time of a sampling step).
if ! wanted alg1; then
  rr --json train reward --name reward-1 --base base --expert expert --dataset maze --arch windowed_mlp \
    --window 4 --hidden 128,64,32 --steps "$LOG_EVERY" --batch-size 64 --watch >/dev/null
fi
rr model download reward-1 --out "$tmp/models/reward-1" --force >/dev/null
sample() { rr --json sample --base base --reward reward-1 --scale 0.1 "${guide[@]}" "${conditions[@]}" --n "$SAMPLE_N" --seed "$1" >/dev/null; }
sample 0 # warm-up: loads both models into the server's cache
for rep in $(seq "$REPS"); do
  t0=$(date +%s.%N)
  sample "$rep"
  t1=$(date +%s.%N)
  record sample relreward "$rep" "$("$PY" -c "import json, sys; s = float(sys.argv[2]) - float(sys.argv[1]); \
print(json.dumps({'n': $SAMPLE_N, 'seconds': s, 'seconds_per_trajectory': s / $SAMPLE_N}))" "$t0" "$t1")"
  record sample reference "$rep" "$(reference sample --base base --reward reward-1 --omega 0.1 "${guide[@]}" \
    "${conditions[@]}" --n "$SAMPLE_N" --seed "$rep")"
done
record sample relreward-server 0 "{\"peak_rss_mib\": $(server_peak_mib)}"
stop_server
fi

# --- report --------------------------------------------------------------------------------------
command="REPS=$REPS WARMUP=$WARMUP ALG1_STEPS=$ALG1_STEPS DDPM_STEPS=$DDPM_STEPS SAMPLE_N=$SAMPLE_N"
[[ $THREADS == "$(nproc)" ]] || command+=" THREADS=$THREADS"
[[ $COMPILE == 1 ]] || command+=" COMPILE=$COMPILE"
[[ $ONLY == "alg1 ddpm sample" ]] || command+=" ONLY='$ONLY'"
"$PY" bench/reference/report.py "$results" --threads "$THREADS" --sample-n "$SAMPLE_N" --spread "$SPREAD" \
  --command "cargo build --release --workspace --bins && $command tests/bench/training.sh" \
  --wall-seconds $(($(date +%s) - started)) >"$tmp/training.md"
cat "$tmp/training.md"
if [[ -n $OUT_DIR ]]; then
  mkdir -p "$OUT_DIR"
  cp "$tmp/training.md" "$results" "$OUT_DIR/"
fi
[[ $SPLICE == 1 ]] && "$PY" tests/bench/splice.py training "$tmp/training.md"
echo "training.sh: done in $(($(date +%s) - started)) s" >&2
