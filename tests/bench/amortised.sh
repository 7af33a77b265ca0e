#!/usr/bin/env bash
# Amortised diffusion targets (issue 21) against the per-step recipe of Algorithm 1: what the
# pool saves in time and what it costs in quality.
#
# 1. Gaussian pair (quality vs time): base N(0, I) and expert N(m, I) in 4 dimensions as exact
#    (analytic) TorchScript eps-models, cosine schedule, T = 20 (tests/python/analytic_gaussian.py,
#    as server/tests/reward_recovery.rs); rho an MLP (64, 64) trained on the union of 4096
#    samples of each, batch 256, lr 3e-3, mean target at x_t. For each recipe and each step count
#    in GAUSS_STEPS, one job; its training time (from its progress events: steps / rate at the
#    last step, so without start-up) and its quality: the cosine of grad rho with the exact
#    target m at x_t drawn from the marginals, at every t whose target norm is at least 10% of
#    the largest (the test's criterion), min over those t (bench/amortised_quality.py). Time to
#    quality: the training time of the first step count whose min cosine reaches 0.98.
# 2. The benchmark's maze size (tests/bench/training.sh: horizon 64, D = 6, T = 100, two
#    TemporalUnets dim 32 (1, 4, 8), windowed MLP reward, batch 64): Algorithm 1 steps/s per-step
#    vs amortised (MAZE_POOL), STEPS steps each: the whole job's training time (the pool's first
#    fill and every refresh included), and the steady rate after step 10.
#    The models are trained one step (their weights do not change the cost), so this part
#    measures speed only; quality on the maze pipeline comes from part 3 (at the demo's size).
# 3. The maze default pipeline (quality and time to a reward): `relreward demo` (default size,
#    LAYOUT, seed MAZE_SEED) with per-step targets, then the same command with DEMO_POOL's
#    amortised flags against the same server, so the second run reuses the first's diffusion
#    models (the same names and weights) and only the rewards (named apart), their evaluation
#    and steering are redone. Reported per goal: goal recovery and balanced accuracy of each
#    recipe (summary.json); time to a reward: each reward job's training time from its events
#    (steps / rate at the last step), summed over the goals. About 20 minutes on a loaded
#    2-core machine (the per-step demo trains five diffusion models first).
# 4. maze-unet: quality where the frozen models dominate the step. `relreward extract` over umaze
#    data from `relreward maze generate` (base 200k rows seed MAZE_SEED, experts 60k rows at
#    UNET_GOALS, seeds MAZE_SEED+1.., action noise 0.5 as the demo's) with --config's [extract]
#    table UNET_CONFIG (TemporalUnet denoisers instead of the default MLPs), per-step and then
#    with DEMO_POOL's amortised flags against the same server and --name, so the second run
#    reuses the first's diffusion models and only the rewards and their evaluation are redone.
#    Reported per goal as part 3 (report.json), with each reward job's training time and rate.
#    Then (UNET_STEPS) time to a reward of equal quality: both recipes again at shorter runs,
#    each amortised run's pool sized to it (UNET_STEPS x the reward batch / (reuse / refresh)
#    items, so each target is still used about reuse / refresh times; the default pool, 16384,
#    would be filled once and barely refreshed by a short run). The reference quality is the
#    per-step recipe at the full length (the [extract] reward_steps); a run has "equal quality"
#    when it recovers the same goals and its mean balanced accuracy is at most 1 point below.
#    Each recipe's time to that quality is the reward training time of its shortest run that
#    has it (steps from the grid only: the true time may be shorter than the grid shows).
# 5. ceiling: the largest speed-up any pool settings can give, per pipeline (the Gaussian pair,
#    the maze default size): the per-step recipe's steps/s against the amortised recipe's when
#    its models never run after the first fill (details at the part).
#
# Settings (environment): GAUSS_STEPS ("100 200 400 800 1600"), POOL ("4096 4 0.25": pool size,
# reuse, refresh fraction for the Gaussian pair; MAZE_POOL ("4096 4 0.25", an epoch of 256
# steps at batch 64, so refreshes fall inside the run) for the maze part), STEPS (600), THREADS (1), OUT (a directory to keep results.jsonl).
# PARTS ("gaussian maze-speed maze-quality ceiling"; maze-unet only when named: which parts run), LAYOUT (umaze), MAZE_SEED (0),
# DEMO_POOL ("16384 4 0.25", the server's defaults), BIN (target/release); part 4: UNET_GOALS
# ("1,1 3,3"), UNET_CONFIG (the [extract] table's body, "; " between keys: 'diffusion_architecture =
# { kind = "temporal_unet", dim = 48, dim_mults = [1, 2] }; diffusion_steps = 2000'), UNET_STEPS
# ("250 500 1000": the shorter runs of both recipes; "" for none); part 5 (ceiling):
# CEIL_POOL (4096), CEIL_STEPS (1000, under the pool's epoch at either batch), CEIL_LOG_EVERY (10,
# the server's default: the jobs' progress interval; a divisor of 100).
# Prints one JSON line per job and a markdown summary.
#
# Builds nothing: expects target/release/{relreward-server,relreward}. Starts its own server on
# a loopback port with a temporary data directory.
set -euo pipefail
cd "$(dirname "$0")/../.."
GAUSS_STEPS=${GAUSS_STEPS:-100 200 400 800 1600}
POOL=${POOL:-4096 4 0.25}
MAZE_POOL=${MAZE_POOL:-4096 4 0.25}
STEPS=${STEPS:-600}
THREADS=${THREADS:-1}
OUT=${OUT:-}
PARTS=${PARTS:-gaussian maze-speed maze-quality ceiling}
LAYOUT=${LAYOUT:-umaze}
MAZE_SEED=${MAZE_SEED:-0}
DEMO_POOL=${DEMO_POOL:-16384 4 0.25}
UNET_GOALS=${UNET_GOALS:-1,1 3,3}
UNET_ARCH='{ kind = "temporal_unet", dim = 48, dim_mults = [1, 2] }'
UNET_CONFIG=${UNET_CONFIG:-diffusion_architecture = $UNET_ARCH; diffusion_steps = 2000}
UNET_STEPS=${UNET_STEPS-250 500 1000}
CEIL_POOL=${CEIL_POOL:-4096}
CEIL_STEPS=${CEIL_STEPS:-1000}
CEIL_LOG_EVERY=${CEIL_LOG_EVERY:-10}
BIN=${BIN:-target/release}
PY=.venv/bin/python
for b in relreward-server relreward; do
  [[ -x $BIN/$b ]] || { echo "amortised.sh: $BIN/$b is missing: cargo build --release --workspace --bins" >&2; exit 2; }
done
tmp=$(mktemp -d)
. tests/bench/lib.sh
trap 'stop_server; rm -rf "$tmp"' EXIT
started=$(date +%s)
results=$tmp/results.jsonl
: >"$results"

server_env=(RELREWARD__ENGINE__INTRA_OP_THREADS="$THREADS" RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD=true)

# train_seconds EVENTS: {"steps", "seconds"} of a job from its last progress event.
train_seconds() {
  "$PY" - "$1" <<'PY'
import json, sys
events = [json.loads(l) for l in open(sys.argv[1]) if l.lstrip().startswith("{")]
last = [e for e in events if e.get("type") == "progress"][-1]
print(json.dumps({"steps": last["step"], "seconds": last["step"] / last["steps_per_second"]}))
PY
}

# steady_rate EVENTS FROM: a job's steps/s between step FROM and its last progress event, with
# its first FROM steps' seconds and the whole run's.
steady_rate() {
  "$PY" - "$1" "$2" <<'PY'
import json, sys
events = [json.loads(l) for l in open(sys.argv[1]) if l.lstrip().startswith("{")]
rate = {e["step"]: e["steps_per_second"] for e in events if e.get("type") == "progress"}
a, b = int(sys.argv[2]), max(rate)
seconds = b / rate[b] - a / rate[a]
print(json.dumps({"from": a, "to": b, "seconds": seconds, "steps_per_second": (b - a) / seconds,
                  "first_steps_seconds": a / rate[a], "total_steps": b, "total_seconds": b / rate[b]}))
PY
}

pool_flags() { # "P R F" -> flags
  read -r p r f <<<"$1"
  echo "--amortised-pool $p --amortised-reuse $r --amortised-refresh $f"
}

want() { [[ " $PARTS " == *" $1 "* ]]; }

# --- 1. Gaussian pair ----------------------------------------------------------------------------
# The Gaussian pair's exact models (base, expert) and samples of each (base-samples,
# expert-samples), uploaded to the running server.
M=1.0,-0.5,0.75,-1.25
T=20
gaussian_pair() {
for who in base expert; do
  mean=0,0,0,0
  [[ $who == expert ]] && mean=$M
  "$PY" tests/python/analytic_gaussian.py --out "$tmp/$who" --mean "$mean" --schedule cosine --T "$T" >/dev/null
  quiet rr model upload "$tmp/$who/model.pt" --name "$who" --manifest "$tmp/$who/manifest.json"
done
"$PY" - "$tmp" "$M" <<'PY'
import sys
import numpy as np
tmp, m = sys.argv[1], np.array([float(v) for v in sys.argv[2].split(",")], np.float32)
rng = np.random.default_rng(0)
np.savez(f"{tmp}/base.npz", samples=rng.standard_normal((4096, 4)).astype(np.float32))
np.savez(f"{tmp}/expert.npz", samples=(rng.standard_normal((4096, 4)) + m).astype(np.float32))
PY
quiet rr dataset upload "$tmp/base.npz" --name base-samples --kind samples
quiet rr dataset upload "$tmp/expert.npz" --name expert-samples --kind samples
}

if want gaussian; then
start_server
gaussian_pair
for steps in $GAUSS_STEPS; do
  for recipe in per-step amortised; do
    extra=()
    [[ $recipe == amortised ]] && read -ra extra <<<"$(pool_flags "$POOL")"
    name="g-$recipe-$steps"
    # The test's optimisation (server/tests/reward_recovery.rs): EMA 0.9 over the second half.
    printf '[optimization]\nema_decay = 0.9\nema_start = %d\neval_every = 100000\ncheckpoint_every = 100000\n' \
      $((steps / 2)) >"$tmp/opt.toml"
    rr --json train reward --name "$name" --base base --expert expert --dataset base-samples --dataset expert-samples \
      --arch mlp --hidden 64,64 --steps "$steps" --batch-size 256 --lr 3e-3 --seed 11 --config "$tmp/opt.toml" \
      "${extra[@]}" --watch >"$tmp/events"
    quality=$("$PY" bench/amortised_quality.py --endpoint "$RELREWARD_ENDPOINT" --model "$name" --mean "$M" --T "$T")
    echo "{\"part\": \"gaussian\", \"recipe\": \"$recipe\", \"pool\": \"$POOL\", \"time\": $(train_seconds "$tmp/events"), \"quality\": $quality}" | tee -a "$results"
  done
done
stop_server
fi

# --- 2. the benchmark's maze size: steps/s -------------------------------------------------------
if want maze-speed; then
start_server
"$PY" tests/python/make_dataset.py --rows 20000 --seed 1 --out "$tmp/maze.npz" --expected "$tmp/expected.json" >/dev/null
cat >"$tmp/unet.toml" <<TOML
[diffusion]
horizon = 64
n_timesteps = 100
architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 4, 8] }
TOML
quiet rr dataset upload "$tmp/maze.npz" --name maze
for m in mbase mexpert; do
  quiet rr train diffusion --name "$m" --dataset maze --config "$tmp/unet.toml" --steps 1 --batch-size 2 --watch
done
read -r mp mr mf <<<"$MAZE_POOL"
epoch=$(( (mp * mr + 63) / 64 ))
for recipe in per-step amortised; do
  extra=()
  [[ $recipe == amortised ]] && read -ra extra <<<"$(pool_flags "$MAZE_POOL")"
  printf '[optimization]\neval_every = 100000\ncheckpoint_every = 100000\n' >"$tmp/opt.toml"
  rr --json train reward --name "m-$recipe" --base mbase --expert mexpert --dataset maze --arch windowed_mlp \
    --window 4 --hidden 128,64,32 --steps "$STEPS" --batch-size 64 --config "$tmp/opt.toml" \
    "${extra[@]}" --watch >"$tmp/events"
  # Steps/s between step 10 (after the pool's first fill) and the end; the per-step recipe the
  # same way. Refreshes every `epoch` steps are inside the window when STEPS > epoch.
  rate=$(steady_rate "$tmp/events" 10)
  echo "{\"part\": \"maze-speed\", \"recipe\": \"$recipe\", \"pool\": \"$MAZE_POOL\", \"epoch_steps\": $epoch, \"rate\": $rate}" | tee -a "$results"
done
stop_server
fi

# --- 3. the maze default pipeline: quality and time to a reward ------------------------------------
# The training seconds of every reward job a demo summary or extract report names, as a JSON list.
reward_seconds() {
  local list="[" reward
  for reward in $("$PY" -c 'import json,sys; print(" ".join(json.load(open(sys.argv[1]))["models"]["rewards"]))' "$1"); do
    rr --json job watch "$reward" >"$tmp/events"
    list+="$(train_seconds "$tmp/events"),"
  done
  echo "${list%,}]"
}

if want maze-quality; then
start_server
for recipe in per-step amortised; do
  extra=()
  [[ $recipe == amortised ]] && read -ra extra <<<"$(pool_flags "$DEMO_POOL")"
  t0=$(date +%s.%N)
  quiet rr demo --layout "$LAYOUT" --seed "$MAZE_SEED" --out "$tmp/demo-$recipe" "${extra[@]}"
  wall=$(echo "$(date +%s.%N) - $t0" | bc)
  jobs_json=$(reward_seconds "$tmp/demo-$recipe/summary.json")
  echo "{\"part\": \"maze-quality\", \"recipe\": \"$recipe\", \"pool\": \"$DEMO_POOL\", \"pool_flags\": \"$*\", \"layout\": \"$LAYOUT\", \"seed\": $MAZE_SEED, \"demo_seconds\": $wall, \"reward_jobs\": $jobs_json, \"summary\": $("$PY" -c 'import json,sys; print(json.dumps(json.load(open(sys.argv[1]))))' "$tmp/demo-$recipe/summary.json")}" | tee -a "$results"
done
stop_server
fi

# --- 4. maze-unet: quality with TemporalUnet denoisers --------------------------------------------
if want maze-unet; then
start_server
gen() { quiet rr maze generate --layout "$LAYOUT" --action-noise 0.5 "$@"; }
gen --mode base --transitions 200000 --seed "$MAZE_SEED" --out "$tmp/unet-base.npz"
experts=()
k=1
for g in $UNET_GOALS; do
  gen --mode expert --goal "$g" --transitions 60000 --seed $((MAZE_SEED + k)) --out "$tmp/unet-expert-${g/,/-}.npz"
  experts+=(--expert "$tmp/unet-expert-${g/,/-}.npz" --goal "$g")
  k=$((k + 1))
done
printf '[extract]\n%s\n' "${UNET_CONFIG//; /$'\n'}" >"$tmp/unet.toml"
unet_extract() { # RECIPE CONFIG [FLAGS...]: one extract, its record appended to the results
  local recipe=$1 config=$2
  shift 2
  local t0 wall jobs_json
  t0=$(date +%s.%N)
  quiet rr extract --base "$tmp/unet-base.npz" "${experts[@]}" --config "$config" --name unet \
    --seed "$MAZE_SEED" --out "$tmp/unet-$recipe" "$@"
  wall=$(echo "$(date +%s.%N) - $t0" | bc)
  jobs_json=$(reward_seconds "$tmp/unet-$recipe/report.json")
  echo "{\"part\": \"maze-unet\", \"recipe\": \"$recipe\", \"pool\": \"$DEMO_POOL\", \"pool_flags\": \"$*\", \"layout\": \"$LAYOUT\", \"seed\": $MAZE_SEED, \"extract_seconds\": $wall, \"reward_jobs\": $jobs_json, \"report\": $("$PY" -c 'import json,sys; print(json.dumps(json.load(open(sys.argv[1]))))' "$tmp/unet-$recipe/report.json")}" | tee -a "$results"
  if [[ -n $OUT ]]; then mkdir -p "$OUT" && cp -r "$tmp/unet-$recipe" "$OUT/"; fi
}
unet_extract per-step "$tmp/unet.toml"
read -ra extra <<<"$(pool_flags "$DEMO_POOL")"
unet_extract amortised "$tmp/unet.toml" "${extra[@]}"
read -r _ reuse refresh <<<"$DEMO_POOL"
for n in $UNET_STEPS; do
  # Only the rewards' sizes change, so the same diffusion models are reused.
  { grep -v '^reward_steps' "$tmp/unet.toml"; echo "reward_steps = $n"; } >"$tmp/unet-$n.toml"
  unet_extract "per-step-$n" "$tmp/unet-$n.toml"
  batch=$("$PY" -c 'import json,sys; print(json.load(open(sys.argv[1]))["sizes"]["reward_batch"])' "$tmp/unet-per-step-$n/report.json")
  pool=$("$PY" -c "import math; print(max($batch, math.ceil($n * $batch * $refresh / $reuse)))")
  unet_extract "amortised-$n" "$tmp/unet-$n.toml" $(pool_flags "$pool $reuse $refresh")
done
stop_server
fi

# --- 5. ceiling: the most any pool settings can save ----------------------------------------------
# Amortising saves the frozen models' passes and nothing else, so its speed-up is bounded by
# (models + reward step) / reward step. Measured directly: the per-step recipe against the
# amortised recipe with models-free steps (pool CEIL_POOL, reuse 1024, refresh 0.001: the epoch
# is longer than the run, so after the first fill the models never run again), CEIL_STEPS steps
# each, steps/s from step 100 to the end (the fill excluded). The ratio is the ceiling of
# per-step / amortised training time at equal steps for every pool size, reuse and refresh; time
# to a reward of equal quality cannot beat it either, unless a pool made a reward learn in fewer
# steps than fresh targets, which parts 1, 3 and 4 do not show. Two pipelines: the Gaussian pair
# (part 1's job) and the maze default size (`relreward demo`'s reward job: two MLP (256, 256,
# 256) denoisers over horizon-16 windows, T = 20, trained a few steps since weights do not change
# the cost; windowed MLP reward h = 4, (128, 64, 32), batch 64, lr 1e-3).
if want ceiling; then
# Models-free only while no refresh falls inside the run: an epoch is CEIL_POOL x 1024 / batch
# steps, shortest at the Gaussian pair's batch of 256.
(( CEIL_LOG_EVERY > 0 && 100 % CEIL_LOG_EVERY == 0 )) ||
  { echo "amortised.sh: CEIL_LOG_EVERY=$CEIL_LOG_EVERY must divide 100 (the rate is read from step 100; the last step is always reported)" >&2; exit 2; }
(( CEIL_STEPS < CEIL_POOL * 1024 / 256 )) ||
  { echo "amortised.sh: CEIL_STEPS=$CEIL_STEPS must stay under CEIL_POOL x 4 = $((CEIL_POOL * 4)) (an epoch)" >&2; exit 2; }
start_server
gaussian_pair
quiet rr maze generate --layout "$LAYOUT" --action-noise 0.5 --mode base --transitions 100000 --seed "$MAZE_SEED" \
  --out "$tmp/ceil-base.npz"
quiet rr maze generate --layout "$LAYOUT" --action-noise 0.5 --mode expert --goal 1,1 --transitions 50000 \
  --seed $((MAZE_SEED + 1)) --out "$tmp/ceil-expert.npz"
for who in base expert; do quiet rr dataset upload "$tmp/ceil-$who.npz" --name "ceil-$who"; done
printf '[diffusion]\narchitecture = { kind = "mlp", hidden = [256, 256, 256] }\nnormalizer_datasets = ["ceil-base", "ceil-expert"]\n' \
  >"$tmp/ceil-diffusion.toml"
for who in base expert; do
  quiet rr train diffusion --name "ceil-m$who" --dataset "ceil-$who" --horizon 16 --n-timesteps 20 --steps 20 \
    --batch-size 64 --config "$tmp/ceil-diffusion.toml" --watch
done
printf '[optimization]\neval_every = 100000\ncheckpoint_every = 100000\nlog_every = %s\n' "$CEIL_LOG_EVERY" >"$tmp/opt.toml"
for pair in gaussian maze-default; do
  for recipe in per-step models-free; do
    extra=()
    [[ $recipe == models-free ]] && extra=(--amortised-pool "$CEIL_POOL" --amortised-reuse 1024 --amortised-refresh 0.001)
    if [[ $pair == gaussian ]]; then
      job=(--base base --expert expert --dataset base-samples --dataset expert-samples --arch mlp --hidden 64,64
        --batch-size 256 --lr 3e-3)
    else
      job=(--base ceil-mbase --expert ceil-mexpert --dataset ceil-base --dataset ceil-expert --arch windowed_mlp
        --window 4 --hidden 128,64,32 --batch-size 64 --lr 1e-3)
    fi
    rr --json train reward --name "ceil-$pair-$recipe" "${job[@]}" --steps "$CEIL_STEPS" --seed 11 \
      --config "$tmp/opt.toml" "${extra[@]}" --watch >"$tmp/events"
    echo "{\"part\": \"ceiling\", \"pair\": \"$pair\", \"recipe\": \"$recipe\", \"rate\": $(steady_rate "$tmp/events" 100)}" |
      tee -a "$results"
  done
done
stop_server
fi

# --- report --------------------------------------------------------------------------------------
"$PY" - "$results" "$(($(date +%s) - started))" "GAUSS_STEPS='$GAUSS_STEPS' POOL='$POOL' MAZE_POOL='$MAZE_POOL' STEPS=$STEPS THREADS=$THREADS PARTS='$PARTS' LAYOUT=$LAYOUT MAZE_SEED=$MAZE_SEED DEMO_POOL='$DEMO_POOL' UNET_GOALS='$UNET_GOALS' UNET_CONFIG='$UNET_CONFIG' UNET_STEPS='$UNET_STEPS' CEIL_POOL=$CEIL_POOL CEIL_STEPS=$CEIL_STEPS CEIL_LOG_EVERY=$CEIL_LOG_EVERY" <<'PY'
import json, sys, subprocess, time
runs = [json.loads(l) for l in open(sys.argv[1])]
cpu = [l.split(":", 1)[1].strip() for l in subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines()
       if l.startswith("Model name")][0]
print(f"Machine: {cpu}, {subprocess.run(['nproc'], capture_output=True, text=True).stdout.strip()} CPUs; "
      f"{time.strftime('%Y-%m-%d', time.gmtime())}; {sys.argv[2]} s in all. Command: "
      f"`cargo build --release --workspace --bins && {sys.argv[3]} tests/bench/amortised.sh`.")
print()
first = {}
if any(r["part"] == "gaussian" for r in runs):
    print("| recipe | steps | training s | min cosine (t with target norm >= 10% of max) | mean cosine |")
    print("|---|---|---|---|---|")
for r in runs:
    if r["part"] != "gaussian":
        continue
    q, t = r["quality"], r["time"]
    print(f"| {r['recipe']} | {t['steps']} | {t['seconds']:.2f} | {q['min_cosine']:.4f} | {q['mean_cosine']:.4f} |")
    if q["min_cosine"] >= 0.98 and r["recipe"] not in first:
        first[r["recipe"]] = (t["steps"], t["seconds"])
print()
for recipe in ("per-step", "amortised") if any(r["part"] == "gaussian" for r in runs) else ():
    f = first.get(recipe)
    print(f"- {recipe}: min cosine >= 0.98 first at " + (f"{f[0]} steps, {f[1]:.2f} s" if f else "no step count tried"))
if len(first) == 2:
    print(f"- time to cosine >= 0.98, per-step / amortised: **{first['per-step'][1] / first['amortised'][1]:.2f}x**")
maze = {r["recipe"]: r for r in runs if r["part"] == "maze-speed"}
if len(maze) == 2:
    a, b = maze["per-step"]["rate"], maze["amortised"]["rate"]
    print()
    print("| recipe (maze benchmark size) | steps | whole job s (fill and refreshes included) | steps/s, steps 10 to end | first 10 steps s |")
    print("|---|---|---|---|---|")
    for k in ("per-step", "amortised"):
        rr = maze[k]["rate"]
        print(f"| {k} | {rr['total_steps']} | {rr['total_seconds']:.1f} | {rr['steps_per_second']:.2f} | {rr['first_steps_seconds']:.1f} |")
    print()
    print(f"- per-step / amortised training time for the same steps: **{a['total_seconds'] / b['total_seconds']:.2f}x** "
          f"(pool {maze['amortised']['pool']}, an epoch is {maze['amortised']['epoch_steps']} steps)")


def quality_table(intro, first_column, pairs, summaries, counts, wall, rates):
    """The maze parts' per-goal table (per-step / amortised) and its summary lines. pairs:
    (first cell, per-step goal, amortised goal, per-step job, amortised job); summaries: the
    two runs' summaries; counts: (recovered key, total key); wall: (label, per-step s,
    amortised s); rates: add the steps/s column."""
    print()
    print(intro)
    print()
    cols = ["recovered", "balanced accuracy", "reward training s"] + (["steps/s"] if rates else [])
    print(f"| {first_column} | " + " | ".join(f"{c} per-step / amortised" for c in cols) + " |")
    print("|---|" + "---|" * len(cols))
    yn = lambda g: "yes" if g["goal_recovered"] else "no"  # noqa: E731
    for cell, gp, ga, jp, ja in pairs:
        row = [f"{yn(gp)} / {yn(ga)}", f"{gp['balanced_accuracy']:.3f} / {ga['balanced_accuracy']:.3f}",
               f"{jp['seconds']:.1f} / {ja['seconds']:.1f}"]
        if rates:
            row.append(f"{jp['steps'] / jp['seconds']:.1f} / {ja['steps'] / ja['seconds']:.1f}")
        print(f"| {cell} | " + " | ".join(row) + " |")
    sp, sa = (sum(pair[k]["seconds"] for pair in pairs) for k in (3, 4))
    (ps, as_), (recovered, total) = summaries, counts
    print()
    print(f"- goals recovered: per-step {ps[recovered]}, amortised {as_[recovered]} of {ps[total]}; mean balanced "
          f"accuracy: per-step {100 * ps['mean_balanced_accuracy']:.1f}%, amortised {100 * as_['mean_balanced_accuracy']:.1f}%")
    print(f"- reward training time, all goals: per-step {sp:.1f} s, amortised {sa:.1f} s: **{sp / sa:.2f}x**")
    print(f"- whole {wall[0]} wall time: per-step {wall[1]:.0f} s (diffusion models trained), "
          f"amortised {wall[2]:.0f} s (diffusion models reused)")


demo = {r["recipe"]: r for r in runs if r["part"] == "maze-quality"}
if len(demo) == 2:
    p, a = demo["per-step"], demo["amortised"]
    quality_table(
        f"Maze default pipeline: `relreward demo --layout {p['layout']} --seed {p['seed']}`, per-step vs "
        f"amortised (pool, reuse, refresh {a['pool']}; the same diffusion models)",
        "goal cell",
        [(",".join(str(c) for c in gp["goal_cell"]), gp, ga, jp, ja)
         for gp, ga, jp, ja in zip(p["summary"]["goals"], a["summary"]["goals"], p["reward_jobs"], a["reward_jobs"])],
        (p["summary"], a["summary"]), ("goals_recovered", "goals_total"),
        ("demo", p["demo_seconds"], a["demo_seconds"]), rates=False)
unet = {r["recipe"]: r for r in runs if r["part"] == "maze-unet"}
if "per-step" in unet and "amortised" in unet:
    p, a = unet["per-step"], unet["amortised"]
    quality_table(
        f"Maze, TemporalUnet denoisers: `relreward extract` ({p['layout']}, seed {p['seed']}, sizes "
        f"{json.dumps(p['report']['sizes'])}), per-step vs amortised (pool, reuse, refresh {a['pool']}; the same diffusion models)",
        "expert",
        [(gp["label"], gp, ga, jp, ja)
         for gp, ga, jp, ja in zip(p["report"]["rewards"], a["report"]["rewards"], p["reward_jobs"], a["reward_jobs"])],
        (p["report"], a["report"]), ("goals_recovered", "goals_evaluated"),
        ("extract", p["extract_seconds"], a["extract_seconds"]), rates=True)
    # Time to a reward of equal quality: the shortest run of each recipe that recovers the same
    # goals as the full-length per-step reward, with a mean balanced accuracy at most 1 point below.
    ref = p["report"]
    recovered = lambda r: {g["label"] for g in r["rewards"] if g["goal_recovered"]}  # noqa: E731
    seconds = lambda r: sum(j["seconds"] for j in r["reward_jobs"])  # noqa: E731
    grid = sorted({int(k.rsplit("-", 1)[1]) for k in unet if k.rsplit("-", 1)[-1].isdigit()})
    if grid:
        full = ref["sizes"]["reward_steps"]
        print()
        print(f"Time to a reward of equal quality (reference: per-step at {full} steps, {len(recovered(ref))} of "
              f"{ref['goals_evaluated']} goals, mean balanced accuracy {100 * ref['mean_balanced_accuracy']:.1f}%; "
              "equal: the same goals recovered, at most 1 point below)")
        print()
        print("| reward steps | per-step: goals, balanced accuracy, s | amortised (pool): goals, balanced accuracy, s |")
        print("|---|---|---|")
        first = {}
        for n in grid + [full]:
            cells = []
            for recipe in ("per-step", "amortised"):
                r = unet.get(f"{recipe}-{n}") or (unet[recipe] if n == full else None)
                if r is None:
                    cells.append("not run")
                    continue
                rep_ = r["report"]
                equal = recovered(rep_) == recovered(ref) and rep_["mean_balanced_accuracy"] >= ref["mean_balanced_accuracy"] - 0.01
                if equal and recipe not in first:
                    first[recipe] = (n, seconds(r))
                flags = r.get("pool_flags", "").split()
                pool = f" (pool {flags[1]})" if recipe == "amortised" and len(flags) > 1 else ""
                cells.append(f"{rep_['goals_recovered']}, {100 * rep_['mean_balanced_accuracy']:.1f}%, "
                             f"{seconds(r):.1f}{pool}{' (equal)' if equal else ''}")
            print(f"| {n} | " + " | ".join(cells) + " |")
        print()
        for recipe in ("per-step", "amortised"):
            f = first.get(recipe)
            print(f"- {recipe}: equal quality first at " + (f"{f[0]} steps, {f[1]:.1f} s" if f else "no run"))
        if len(first) == 2:
            print(f"- time to a reward of equal quality, per-step / amortised: **{first['per-step'][1] / first['amortised'][1]:.2f}x**")

ceil = {(r["pair"], r["recipe"]): r["rate"] for r in runs if r["part"] == "ceiling"}
if ceil:
    print()
    print("| pipeline | per-step steps/s | models-free amortised steps/s | ceiling of per-step / amortised time |")
    print("|---|---|---|---|")
    for pair in ("gaussian", "maze-default"):
        p, f = ceil.get((pair, "per-step")), ceil.get((pair, "models-free"))
        if p and f:
            print(f"| {pair} | {p['steps_per_second']:.1f} | {f['steps_per_second']:.1f} | "
                  f"**{f['steps_per_second'] / p['steps_per_second']:.2f}x** |")
PY
if [[ -n $OUT ]]; then mkdir -p "$OUT" && cp "$results" "$OUT/"; fi
