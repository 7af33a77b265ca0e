#!/usr/bin/env bash
# Builds relreward-server for a GPU machine whose PyTorch is older than the 2.13.0 tch 0.26 was
# generated for (the lent machines have 2.11.0+cu130, docs/deployment.md "GPU"), for
# tests/bench/gpu.sh. A binary built against 2.13 starts there but crashes in its first
# libtorch call with a CUDA tensor (ABI drift), and libtorch 2.13 with CUDA is far too large to
# carry. So: that version's wheel from PyPI (its headers and libtorch_cpu/libc10 to link
# against; the machine's own libraries are loaded at run time), a copy of torch-sys whose
# generated glue has the ops missing from that version replaced by a thrown error (relreward
# calls none of them; a call would fail with that message, not crash), and a separate target
# directory, so the project's own build is untouched.
#
#   tests/bench/gpu-build.sh   (TORCH_VERSION=2.11.0 WORK=/tmp/relreward-gpu-build TARGET=$WORK/target)
# writes .gpu/relreward-server, .gpu/relreward-server-tests (the server's unit tests),
# .gpu/relreward, .gpu/relreward-loadgen and .gpu/maze.npz (then tests/bench/gpu.sh there).
set -euo pipefail
cd "$(dirname "$0")/../.."
V=${TORCH_VERSION:-2.11.0}
W=${WORK:-/tmp/relreward-gpu-build}
T=${TARGET:-$W/target}
PY=.venv/bin/python
mkdir -p "$W" .gpu
if [[ ! -d $W/torch/lib ]]; then
  "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --platform manylinux_2_28_x86_64 "torch==$V" -d "$W/wheel"
  (cd "$W" && unzip -q -o wheel/torch-"$V"-*.whl 'torch/include/*' 'torch/lib/*' 'torch/share/*')
fi
# libtorch_cpu names the CUDA runtime and CUPTI; the link resolves them from the project's
# venv (same CUDA major), through the wheel's relative RUNPATH.
ln -sfn "$("$PY" -c 'import nvidia, os; print(os.path.dirname(nvidia.__path__[0]))')/nvidia" "$W/nvidia"
# The patch below rewrites Cargo.lock's torch-sys entry; the project's own is put back.
cp Cargo.lock "$W/Cargo.lock.project"
trap 'cp "$W/Cargo.lock.project" Cargo.lock' EXIT
SRC=$(ls -d ~/.cargo/registry/src/*/torch-sys-0.26.0 | head -1)
if [[ ! -f $W/torch-sys/patched-$V ]]; then
  rm -rf "$W/torch-sys" && cp -r "$SRC" "$W/torch-sys"
fi
# One try of the glue to learn which ops this libtorch lacks, then each of those wrappers'
# bodies replaced by a throw (PROTECT turns it into tch's error).
if ! LIBTORCH=$W/torch LIBTORCH_BYPASS_VERSION_CHECK=1 CARGO_TARGET_DIR=$T \
     cargo build --release -p relreward-server --bin relreward-server \
     --config "patch.crates-io.torch-sys.path=\"$W/torch-sys\"" 2>"$W/first.log"; then
  "$PY" - "$W/first.log" "$W/torch-sys/libtch/torch_api_generated.cpp" "$V" <<'PY'
import re, sys
log, path, version = sys.argv[1], sys.argv[2], sys.argv[3]
bad = sorted({int(m) for m in re.findall(r"torch_api_generated\.cpp:(\d+):\d+: error", open(log).read())})
if not bad:
    sys.exit(f"gpu-build.sh: the build failed for another reason; see {log}")
lines = open(path).read().split("\n")
done = set()
for n in bad:
    i = n - 1
    start = max(k for k in range(i + 1) if lines[k].strip() == "PROTECT(")
    end = next(k for k in range(i, len(lines)) if lines[k] == "  )")
    if start in done:
        continue
    done.add(start)
    lines[start + 1:end] = [f'    throw std::runtime_error("this op is not in libtorch {version}");'] + [""] * (end - start - 2)
open(path, "w").write("\n".join(lines))
open(f"{path.rsplit('/libtch/', 1)[0]}/patched-{version}", "w").write(f"{len(done)} wrappers\n")
print(f"gpu-build.sh: {len(done)} wrappers of ops missing from libtorch {version} now throw", file=sys.stderr)
PY
  LIBTORCH=$W/torch LIBTORCH_BYPASS_VERSION_CHECK=1 CARGO_TARGET_DIR=$T \
    cargo build --release -p relreward-server --bin relreward-server \
    --config "patch.crates-io.torch-sys.path=\"$W/torch-sys\""
fi
strip -o .gpu/relreward-server "$T/release/relreward-server"
# The server's unit tests, for the derivation checks that gpu.sh runs on the device first (the
# reward's gradients without autograd against autograd, on CUDA's operations).
tests=$(LIBTORCH=$W/torch LIBTORCH_BYPASS_VERSION_CHECK=1 CARGO_TARGET_DIR=$T \
  cargo test --release -p relreward-server --lib --no-run --message-format=json \
  --config "patch.crates-io.torch-sys.path=\"$W/torch-sys\"" |
  "$PY" -c 'import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] == "relreward_server":
        print(m["executable"])')
strip -o .gpu/relreward-server-tests "$tests"
cp "$W/Cargo.lock.project" Cargo.lock
# The CLI and the load generator link no libtorch: the project's own build serves.
cargo build --release -p relreward-cli --bin relreward -p relreward-bench --bin relreward-loadgen
strip -o .gpu/relreward target/release/relreward
strip -o .gpu/relreward-loadgen target/release/relreward-loadgen
"$PY" tests/python/make_dataset.py --rows 20000 --seed 1 --out .gpu/maze.npz --expected "$W/expected.json" >/dev/null
ls -la .gpu
