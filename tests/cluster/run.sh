#!/usr/bin/env bash
# `make test-cluster`: starts a real PostgreSQL and a real S3-protocol server on loopback
# (tests/cluster/infra.sh), runs the store tests (server/tests/shared_store.rs) and the
# multi-process test (tests/tests/cluster.rs: two serving replicas and two workers) against
# them, and stops everything, pass or fail.
set -euo pipefail
cd "$(dirname "$0")/../.."

dir=$(mktemp -d /tmp/relreward-cluster.XXXXXX)
cleanup() {
    tests/cluster/infra.sh stop "$dir" || true
    rm -rf "$dir"
}
trap cleanup EXIT

tests/cluster/infra.sh start "$dir"
# shellcheck disable=SC1091
source "$dir/env"
# The two stores on their own (leases, fencing, downloads, corruption), then the processes.
cargo test --release -p relreward-server --test shared_store -- --ignored
cargo test --release -p relreward-tests --test cluster -- --ignored --nocapture
