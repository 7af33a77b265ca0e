#!/usr/bin/env bash
# Algorithm 1 at the paper's maze size on a GPU: relreward's reward job against the PyTorch
# reference (bench/reference/gpu_alg1.py) on the same device. For a GPU machine that has
# PyTorch (and so libtorch with CUDA) but no Rust toolchain: build here, carry the binaries.
#
#   here:  mkdir -p .gpu && strip -o .gpu/relreward-server target/release/relreward-server \
#            && strip -o .gpu/relreward target/release/relreward \
#            && .venv/bin/python tests/python/make_dataset.py --rows 20000 --seed 1 --out .gpu/maze.npz --expected /tmp/e.json
#          (or tests/bench/gpu-build.sh, which builds against that machine's older libtorch,
#          and also carries relreward-loadgen for the serving figure below)
#   there: tests/bench/gpu.sh            (BIN=.gpu, STEPS, WARMUP, PORT, KEEP overridable;
#                                         KEEP=DIR keeps the servers' logs there; HOST_CHECKS=0
#                                         skips the per-step job's second run)
#
# First, when .gpu/relreward-server-tests was carried (gpu-build.sh), the reward's derivation
# checks on CUDA (one JSON line, "cuda-derivation-checks": passed or failed; KEEP keeps the log).
#
# Sizes: TemporalUnet(dim 32, dim_mults (1, 4, 8)) base and expert over [256, 6] windows,
# T = 256, Diffuser's cosine schedule, x0 (relreward's defaults); reward ValueFunction widths
# (32, 128, 256); batch 256. relreward's rate comes from its job's progress events between
# steps WARMUP and WARMUP + STEPS (as tests/bench/training.sh). The per-step job runs twice:
# with the server's default step checks (on CUDA: decided on the device, the losses read where
# progress is reported) and with engine.step_checks = host (the gradient norm and loss read
# inside each step), on a second server. The server loads that
# machine's libtorch: the binary links libtorch_cpu and libc10 only, so libtorch_cuda is
# preloaded to make CUDA visible (docs/deployment.md, "GPU").
set -euo pipefail
BIN=${BIN:-.gpu}
STEPS=${STEPS:-40}
WARMUP=${WARMUP:-20}
PORT=${PORT:-50077}
PY=${PY:-python3}
TL=$("$PY" -c 'import os, torch; print(os.path.dirname(torch.__file__))')/lib
tmp=$(mktemp -d)
export RELREWARD_ENDPOINT=http://127.0.0.1:$PORT

# start_server CHECKS: a server with engine.step_checks = CHECKS, the base and expert models
# trained (one step each: only their sizes matter) on the maze dataset.
start_server() {
  LD_LIBRARY_PATH=$TL LD_PRELOAD=$TL/libtorch_cuda.so RELREWARD__ENGINE__DEVICE=cuda RELREWARD__METRICS__LISTEN= \
    RELREWARD__ENGINE__STEP_CHECKS=$1 \
    "$BIN/relreward-server" --listen 127.0.0.1:$PORT --data-dir "$tmp/data-$1" >"$tmp/out" 2>"$tmp/log-$1" &
  server=$!
  for _ in $(seq 100); do grep -q "listening on" "$tmp/out" 2>/dev/null && break; sleep 0.2; done
  grep -m1 "libtorch initialised" "$tmp/log-$1" >&2 || { tail -20 "$tmp/log-$1" >&2; exit 1; }
  rr dataset upload "$BIN/maze.npz" --name maze >/dev/null
  for m in base expert; do
    rr train diffusion --name "$m" --dataset maze --config "$tmp/unet.toml" --steps 1 --batch-size 2 --watch >/dev/null
  done
}
server=
trap 'kill $server 2>/dev/null || true; wait $server 2>/dev/null || true; if [[ -n ${KEEP:-} ]]; then for l in "$tmp"/log-*; do cp "$l" "$KEEP/server-${l##*/log-}.log"; done; fi; rm -rf "$tmp"' EXIT
rr() { "$BIN/relreward" "$@"; }
cat >"$tmp/unet.toml" <<TOML
[diffusion]
horizon = 256
n_timesteps = 256
architecture = { kind = "temporal_unet", dim = 32, dim_mults = [1, 4, 8] }
TOML
# First the derivation checks on CUDA's operations (when gpu-build.sh carried the unit tests):
# the reward's input and training gradients without autograd against autograd, every
# architecture, float64 to 1e-10 (float32 to 1e-2: TF32 convolutions). A failure is reported
# and the timings still run.
if [[ -x $BIN/relreward-server-tests ]]; then
  checks=passed
  LD_LIBRARY_PATH=$TL LD_PRELOAD=$TL/libtorch_cuda.so RELREWARD_TEST_DEVICE=cuda \
    "$BIN/relreward-server-tests" --exact --test-threads 1 \
    engine::nets::reward::tests::reward_closed_form_alignment_gradients_equal_autograd \
    engine::nets::reward::tests::reward_closed_form_grad_equals_autograd >"$tmp/checks" 2>&1 || checks=failed
  # Passed only if both ran (libtest exits 0 when no name matches).
  grep -q "test result: ok. 2 passed" "$tmp/checks" || checks=failed
  tail -5 "$tmp/checks" >&2
  echo "{\"side\": \"relreward\", \"variant\": \"cuda-derivation-checks\", \"result\": \"$checks\"}"
  if [[ -n ${KEEP:-} ]]; then mkdir -p "$KEEP" && cp "$tmp/checks" "$KEEP/derivation-checks.log"; fi
fi
start_server auto

rate() {
  "$PY" - "$1" "$WARMUP" "$STEPS" <<'PY'
import json, sys
events = [json.loads(l) for l in open(sys.argv[1]) if l.lstrip().startswith("{")]
rate = {e["step"]: e["steps_per_second"] for e in events if e.get("type") == "progress"}
a, b = int(sys.argv[2]), int(sys.argv[2]) + int(sys.argv[3])
if a not in rate or b not in rate:
    sys.exit(f"gpu.sh: progress events lack step {a} or {b}: {sorted(rate)}")
seconds = b / rate[b] - a / rate[a]
print(json.dumps({"steps": b - a, "steps_per_s": (b - a) / seconds, "ms_per_step": 1000 * seconds / (b - a)}))
PY
}
total=$((WARMUP + STEPS + 10))
for variant in per-step amortised; do
  extra=()
  [[ $variant == amortised ]] && extra=(--amortised-pool 16384)
  rr --json train reward --name "r-$variant" --base base --expert expert --dataset maze --arch value_function \
    --widths 32,128,256 --steps "$total" --batch-size 256 "${extra[@]}" --watch >"$tmp/events-$variant"
  echo "{\"side\": \"relreward\", \"variant\": \"$variant\", \"result\": $(rate "$tmp/events-$variant")}"
done
# Serving on the device: 64 streaming planners, one [256, 6] window per request at t = 10, on
# the per-step reward (when the load generator was carried).
if [[ -x $BIN/relreward-loadgen ]]; then
  "$BIN/relreward-loadgen" --endpoint "$RELREWARD_ENDPOINT" --model r-per-step --mode stream --clients 64 \
    --t 10 --warmup 3 --duration 10 --json | "$PY" -c 'import json, sys; print(json.dumps({"side": "relreward", "variant": "serving-64-stream", "result": json.load(sys.stdin)}))'
fi
kill $server; wait $server 2>/dev/null || true
if [[ ${HOST_CHECKS:-1} == 1 ]]; then
  start_server host
  rr --json train reward --name r-host --base base --expert expert --dataset maze --arch value_function \
    --widths 32,128,256 --steps "$total" --batch-size 256 --watch >"$tmp/events-host"
  echo "{\"side\": \"relreward\", \"variant\": \"per-step-host-checks\", \"result\": $(rate "$tmp/events-host")}"
  kill $server; wait $server 2>/dev/null || true
fi

# The reference nets come from the development package (dev/python); that machine has no
# `make setup`, so it is read from the checkout.
export PYTHONPATH="$PWD/dev/python/src${PYTHONPATH:+:$PYTHONPATH}"
(cd bench/reference && "$PY" gpu_alg1.py --device cuda --steps "$STEPS" --warmup 5) | sed 's/^/{"side": "pytorch-eager", "result": /; s/$/}/'
(cd bench/reference && "$PY" gpu_alg1.py --device cuda --steps "$STEPS" --warmup 5 --compile) | sed 's/^/{"side": "pytorch-compile", "result": /; s/$/}/'
