#!/usr/bin/env bash
# The long load and soak test (issue 8): tests/tests/soak.rs for SOAK_SECS seconds (600 by
# default; `make test` runs it for 60). Loopback only: it starts its own server on port 0 with
# a temporary data directory and stops it afterwards. Prints the requests sent and their
# answers by status code, the server's memory (first and last quarter, peak) and the job runs.
#
#   tests/soak.sh                 # 10 minutes
#   SOAK_SECS=1800 tests/soak.sh  # longer
set -euo pipefail
cd "$(dirname "$0")/.."
export SOAK_SECS="${SOAK_SECS:-600}"
cargo build --release --workspace --bins
echo "soak: running for ${SOAK_SECS} s"
exec cargo test --release -p relreward-tests --test soak -- --nocapture --test-threads 1
