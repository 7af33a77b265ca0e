#!/usr/bin/env bash
# Fuzzes relreward's parsers (issue 8 part 6) with cargo-fuzz: each target for FUZZ_SECS
# seconds (60 by default), then prints the executions per target. Not part of `make test`;
# the inputs it ever crashed on are replayed there as unit tests next to each parser.
#
#   tests/fuzz.sh                          # every target, 60 s each
#   FUZZ_SECS=300 tests/fuzz.sh npz_file   # chosen targets, longer
#   FUZZ_TARGETS="tensor_decode npy_header npz_file" tests/fuzz.sh   # some, no libtorch
#
# Targets (fuzz/fuzz_targets/): tensor_decode, npy_header, npz_file, manifest_parse, job_spec
# (the proto, client and toolkit crates only) and server_npy_read (links relreward-server, so
# libtorch: found through LIBTORCH, by default the project's .venv/torch-root as in
# .cargo/config.toml).
#
# Stable Rust: RUSTC_BOOTSTRAP=1 lets it accept the -Z flags cargo-fuzz passes. New corpus
# entries go to fuzz/target/corpus/<target> (ignored); the committed seeds in
# fuzz/corpus/<target> and the past crashes in fuzz/regressions/<target> are read, not
# written. A crash leaves its input in fuzz/artifacts/<target>/ and fails the script.
set -euo pipefail
cd "$(dirname "$0")/.."
export RUSTC_BOOTSTRAP=1
FUZZ_SECS="${FUZZ_SECS:-60}"
ALL="tensor_decode npy_header npz_file manifest_parse job_spec server_npy_read"
if [ "$#" -gt 0 ]; then targets="$*"; else targets="${FUZZ_TARGETS:-$ALL}"; fi

if ! cargo fuzz --version >/dev/null 2>&1; then
    cargo install cargo-fuzz --locked
fi

needs_server() { case "$1" in server_npy_read) return 0 ;; *) return 1 ;; esac; }
any_server=""
for t in $targets; do needs_server "$t" && any_server=1; done
if [ -n "$any_server" ] && [ -z "${LIBTORCH:-}" ]; then
    export LIBTORCH="$PWD/.venv/torch-root"
    [ -d "$LIBTORCH" ] || { echo "fuzz: server targets need libtorch; run 'make setup' first" >&2; exit 1; }
fi
# libtorch's libraries are found at run time through the loader path.
if [ -n "${LIBTORCH:-}" ]; then
    export LD_LIBRARY_PATH="$LIBTORCH/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi

summary=()
status=0
for t in $targets; do
    work="fuzz/target/corpus/$t"
    mkdir -p "$work" "fuzz/corpus/$t" "fuzz/regressions/$t"
    log="fuzz/target/$t.log"
    features=()
    # Server targets build without a sanitizer: instrumenting the server's whole dependency tree
    # (tonic, tokio, object_store, tch, ...) for AddressSanitizer is impractically slow on a
    # small machine, and relreward's own crates forbid unsafe code, so what fuzzing finds
    # there is panics and aborts, which libFuzzer reports without one. Client targets keep ASan.
    if needs_server "$t"; then features=(--features server --sanitizer none); fi
    echo "fuzz: $t for ${FUZZ_SECS} s (log: $log)"
    if cargo fuzz run --fuzz-dir fuzz "${features[@]}" "$t" "$work" "fuzz/corpus/$t" "fuzz/regressions/$t" -- \
        -max_total_time="$FUZZ_SECS" -rss_limit_mb=2048 -max_len=65536 -timeout=10 -print_final_stats=1 \
        >"$log" 2>&1; then
        result=ok
    else
        result="FAILED (see $log and fuzz/artifacts/$t/)"
        status=1
    fi
    execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -1)
    rate=$(grep -o 'stat::average_exec_per_sec: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -1)
    summary+=("$(printf '%-16s %12s execs %8s/s  %s' "$t" "${execs:-?}" "${rate:-?}" "$result")")
done
echo
echo "fuzz: ${FUZZ_SECS} s per target"
printf '%s\n' "${summary[@]}"
exit "$status"
