#!/usr/bin/env bash
# Real backing services for the multi-process cluster test (`make test-cluster`).
#
# Why: the PostgreSQL metadata/job-queue backend and the S3 blob backend must be tested against
# real servers speaking the real protocols (SQL over the wire with password auth, SigV4-signed
# S3 requests), not in-process mocks, or the test would prove nothing about production. This
# script starts a throwaway PostgreSQL cluster and an S3-compatible server (s3s-fs, from the s3s
# project on crates.io) bound to 127.0.0.1 only, on free ports, with all state under one
# caller-owned temp directory, and writes the connection settings as an env file.
#
#   tests/cluster/infra.sh start DIR   start both in the fresh directory DIR, write DIR/env
#   tests/cluster/infra.sh stop  DIR   stop both; never fails, even if already stopped
#   tests/cluster/infra.sh check DIR   smoke test through DIR/env (psql + signed curl requests)
#
# DIR layout: env (export lines), pids, postgres.log, s3.log, pg/data, pg/sock, pg/tls (CA and
# server certificate: PostgreSQL takes TCP connections over TLS only), s3/<bucket>.
#
# Requirements: PostgreSQL server binaries (installed with apt-get when missing and running as
# root), cargo (only for the first run: s3s-fs is built into <repo>/.tools), curl >= 7.75
# (--aws-sigv4). PostgreSQL refuses to run as root, so as root it runs as the `postgres` user.
#
# -E: the ERR trap set by `start` also fires inside functions, so any failed command stops what
# was started (the steps run as plain commands, never under `||`, which would disable -e).
set -Eeuo pipefail

SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO_ROOT="$(cd "$SCRIPT_DIR/../.." && pwd)"
readonly SCRIPT_DIR REPO_ROOT
readonly TOOLS="$REPO_ROOT/.tools"
readonly S3S_FS_VERSION="0.14.1" # newest s3s-fs whose rust-version (1.92) fits our toolchain
readonly S3S_FS="$TOOLS/bin/s3s-fs"
readonly DB_NAME="relreward"
readonly DB_USER="relreward"
readonly BUCKET="relreward"
readonly REGION="us-east-1"
readonly READY_TIMEOUT_S=60

# ---------------------------------------------------------------------------------------------
# Helpers

log() { printf '[infra] %s\n' "$*" >&2; }
warn() { printf '[infra] WARNING: %s\n' "$*" >&2; }

now() { date +%s.%N; }
# elapsed START: seconds since START (from `now`), two decimals.
elapsed() { awk -v s="$1" -v e="$(now)" 'BEGIN { printf "%.2f", e - s }'; }

# phase NAME CMD...: run one step of the setup and print how long it took.
phase() {
    local name=$1 t0
    shift
    t0=$(now)
    log "$name ..."
    "$@"
    log "$name: done in $(elapsed "$t0")s"
}

# tail_log FILE: the end of a log, indented, for failure messages.
tail_log() {
    if [[ -s $1 ]]; then
        printf '[infra] ---- last lines of %s ----\n' "$1" >&2
        tail -n 30 "$1" | sed 's/^/    /' >&2
        printf '[infra] ----\n' >&2
    fi
}

# random_hex BYTES: a random hex string (URL- and shell-safe: used for keys and passwords).
random_hex() { od -An -N"$1" -tx1 /dev/urandom | tr -d ' \n'; }

# port_in_use PORT: true when something listens on 127.0.0.1:PORT.
port_in_use() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }

# free_port: a TCP port that nothing listens on. The kernel picks it (bind to port 0) when
# python3 is available; otherwise a random port in the ephemeral range that refuses a connect.
free_port() {
    local p
    if command -v python3 >/dev/null 2>&1 &&
        p=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])' 2>/dev/null) &&
        [[ $p =~ ^[0-9]+$ ]]; then
        echo "$p"
        return
    fi
    for _ in $(seq 1 100); do
        p=$((20000 + RANDOM % 40000))
        if ! port_in_use "$p"; then
            echo "$p"
            return
        fi
    done
    return 1
}

is_root() { [[ $(id -u) -eq 0 ]]; }

# as_pg CMD...: run a PostgreSQL server program; as the `postgres` user when we are root,
# because initdb and postgres refuse to run as root.
as_pg() {
    if is_root; then
        runuser -u postgres -- "$@"
    else
        "$@"
    fi
}

# ---------------------------------------------------------------------------------------------
# State kept in DIR

DIR=""
PG_DATA="" PG_SOCK="" PG_LOG="" S3_ROOT="" S3_LOG="" ENV_FILE="" PIDS_FILE=""

set_dir() {
    [[ -n ${1:-} ]] || usage
    DIR=$1
    if [[ ! -d $DIR ]]; then
        echo "infra.sh: $DIR is not a directory (create it first, e.g. with mktemp -d)" >&2
        exit 2
    fi
    DIR=$(cd "$DIR" && pwd)
    PG_DATA="$DIR/pg/data"
    PG_SOCK="$DIR/pg/sock"
    PG_LOG="$DIR/postgres.log"
    S3_ROOT="$DIR/s3"
    S3_LOG="$DIR/s3.log"
    ENV_FILE="$DIR/env"
    PIDS_FILE="$DIR/pids"
}

# pid_of NAME: the pid recorded in DIR/pids for NAME (postgres or s3s-fs), or nothing.
pid_of() {
    [[ -f $PIDS_FILE ]] || return 0
    awk -v n="$1" '$1 == n { print $2 }' "$PIDS_FILE" | tail -n 1
}

# is_s3s_fs_pid PID: true when PID is alive and is an s3s-fs (guards against pid reuse).
is_s3s_fs_pid() {
    [[ -n $1 && -r /proc/$1/cmdline ]] && tr '\0' ' ' <"/proc/$1/cmdline" | grep -q 's3s-fs'
}

# ---------------------------------------------------------------------------------------------
# PostgreSQL

PG_BIN=""

# find_pg_bin: the directory holding initdb, pg_ctl, postgres, pg_isready and psql. Debian keeps
# them in /usr/lib/postgresql/<major>/bin (not on PATH); a symlink on PATH is followed.
find_pg_bin() {
    local cand
    if cand=$(command -v initdb 2>/dev/null); then
        cand=$(dirname "$(readlink -f "$cand")")
        if [[ -x $cand/pg_ctl && -x $cand/postgres ]]; then
            PG_BIN=$cand
            return 0
        fi
    fi
    # The newest major version (an unmatched glob stays literal and fails the -x tests).
    cand=$(printf '%s\n' /usr/lib/postgresql/*/bin | sort -V | tail -n 1)
    if [[ -n $cand && -x $cand/initdb && -x $cand/pg_ctl && -x $cand/postgres ]]; then
        PG_BIN=$cand
        return 0
    fi
    return 1
}

ensure_postgres() {
    find_pg_bin && return 0
    if ! is_root; then
        cat >&2 <<'EOF'
[infra] PostgreSQL server binaries (initdb, pg_ctl, postgres) were not found on PATH nor in
[infra] /usr/lib/postgresql/*/bin, and installing them needs root. Install PostgreSQL, e.g.:
[infra]     sudo apt-get update && sudo apt-get install -y --no-install-recommends postgresql
[infra] (or put a PostgreSQL >= 13 bin directory on PATH), then run this again.
EOF
        return 1
    fi
    command -v apt-get >/dev/null 2>&1 || {
        log "PostgreSQL is not installed and apt-get is unavailable: install PostgreSQL (initdb, pg_ctl, postgres, psql) by hand"
        return 1
    }
    log "PostgreSQL not found: installing it with apt-get (Debian package 'postgresql')"
    # The package's post-install may create and start a default cluster on 5432; we do not use it.
    DEBIAN_FRONTEND=noninteractive apt-get update -q >&2
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends postgresql >&2
    find_pg_bin || {
        log "apt-get installed postgresql but no initdb was found in /usr/lib/postgresql/*/bin"
        return 1
    }
}

# prepare_pg_dirs: data and socket directories owned by the user the server runs as.
prepare_pg_dirs() {
    mkdir -p "$PG_DATA" "$PG_SOCK"
    chmod 700 "$PG_DATA"
    : >"$PG_LOG"
    if is_root; then
        id postgres >/dev/null 2>&1 || {
            log "running as root, but there is no 'postgres' user to run PostgreSQL as (the Debian package creates it)"
            return 1
        }
        # The postgres user must be able to reach DIR/pg: let it traverse (not list) DIR.
        chmod o+x "$DIR"
        chown -R postgres: "$DIR/pg" "$PG_LOG"
        if ! runuser -u postgres -- test -w "$PG_DATA"; then
            log "the postgres user cannot reach $PG_DATA (a parent directory is not traversable): use a DIR under /tmp, e.g. mktemp -d"
            return 1
        fi
    fi
    # A unix socket path is limited to 107 bytes.
    if ((${#PG_SOCK} + 20 > 107)); then
        log "DIR path is too long for a unix socket ($PG_SOCK): use a shorter DIR, e.g. mktemp -d"
        return 1
    fi
}

pg_initdb() {
    # The bootstrap superuser `postgres` authenticates by trust, and only over the unix socket
    # in DIR/pg/sock (mode 0700 via unix_socket_permissions); TCP connections need a password
    # (SCRAM), like production.
    # (`if`, not a bare redirected command: the ERR trap would run with stderr still in the log.)
    if ! as_pg "$PG_BIN/initdb" -D "$PG_DATA" -U postgres --encoding=UTF8 --locale=C \
        --auth-local=trust --auth-host=scram-sha-256 >>"$PG_LOG" 2>&1; then
        log "initdb failed (its output is in $PG_LOG)"
        return 1
    fi
    # Settings go into postgresql.conf (not the pg_ctl command line), so a restart keeps them.
    # Everything else, fsync included, keeps its default.
    as_pg tee -a "$PG_DATA/postgresql.conf" >/dev/null <<EOF

# tests/cluster/infra.sh
listen_addresses = '127.0.0.1'
port = $PG_PORT
unix_socket_directories = '$PG_SOCK'
unix_socket_permissions = 0700
EOF
}

# pg_tls: a throwaway CA and a server certificate for 127.0.0.1, TLS on, and pg_hba.conf's TCP
# lines turned into hostssl: every TCP connection must use TLS, so the tests prove that
# relreward's connections do, verifying the server against the CA (RELREWARD_TEST_PG_CA).
pg_tls() {
    local tls="$DIR/pg/tls" ec=(-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes)
    mkdir -p "$tls"
    openssl req -x509 "${ec[@]}" -days 2 -subj "/CN=relreward test CA" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -keyout "$tls/ca.key" -out "$tls/ca.pem" 2>>"$PG_LOG"
    openssl req -new "${ec[@]}" -subj "/CN=127.0.0.1" -keyout "$tls/server.key" -out "$tls/server.csr" 2>>"$PG_LOG"
    printf '%s\n' "subjectAltName=IP:127.0.0.1,DNS:localhost" "basicConstraints=critical,CA:FALSE" \
        "keyUsage=critical,digitalSignature" "extendedKeyUsage=serverAuth" >"$tls/server.ext"
    openssl x509 -req -in "$tls/server.csr" -CA "$tls/ca.pem" -CAkey "$tls/ca.key" -CAcreateserial -days 2 \
        -extfile "$tls/server.ext" -out "$tls/server.pem" 2>>"$PG_LOG"
    rm -f "$tls/ca.key" "$tls/ca.srl" "$tls/server.csr" "$tls/server.ext"
    # PostgreSQL insists on a private key only its own user can read.
    chmod 600 "$tls/server.key"
    if is_root; then
        chown postgres "$tls/server.key" "$tls/server.pem"
    fi
    as_pg tee -a "$PG_DATA/postgresql.conf" >/dev/null <<EOF
ssl = on
ssl_cert_file = '$tls/server.pem'
ssl_key_file = '$tls/server.key'
EOF
    as_pg sed -i 's/^host\([[:space:]]\)/hostssl\1/' "$PG_DATA/pg_hba.conf"
}

pg_start() {
    local attempt
    for attempt in 1 2 3; do
        if as_pg "$PG_BIN/pg_ctl" -D "$PG_DATA" -l "$PG_LOG" -w -t "$READY_TIMEOUT_S" start >/dev/null; then
            record_pid postgres "$(head -n 1 "$PG_DATA/postmaster.pid")"
            return 0
        fi
        # Lost a race for the port between free_port and the bind: pick another one.
        if grep -q 'could not bind\|Address already in use' "$PG_LOG" && ((attempt < 3)); then
            PG_PORT=$(free_port)
            warn "port taken, retrying PostgreSQL on port $PG_PORT"
            as_pg sed -i "s/^port = .*/port = $PG_PORT/" "$PG_DATA/postgresql.conf"
            continue
        fi
        return 1
    done
}

pg_wait_ready() {
    local deadline=$((SECONDS + READY_TIMEOUT_S))
    until "$PG_BIN/pg_isready" -q -h 127.0.0.1 -p "$PG_PORT" -d postgres; do
        ((SECONDS < deadline)) || {
            log "pg_isready did not succeed within ${READY_TIMEOUT_S}s"
            return 1
        }
        sleep 0.2
    done
}

# pg_admin SQL: run SQL as the superuser over the unix socket.
pg_admin() {
    as_pg "$PG_BIN/psql" -X -q -v ON_ERROR_STOP=1 -h "$PG_SOCK" -p "$PG_PORT" -U postgres -d postgres -c "$1" >/dev/null
}

pg_create_db() {
    pg_admin "CREATE ROLE $DB_USER LOGIN PASSWORD '$PG_PASSWORD'"
    pg_admin "CREATE DATABASE $DB_NAME OWNER $DB_USER"
    # Prove the URL the tests get works: TCP, password auth, the right database.
    local got
    got=$("$PG_BIN/psql" -X -qAt -v ON_ERROR_STOP=1 "$PG_URL" -c 'select current_user || current_database()')
    [[ $got == "$DB_USER$DB_NAME" ]] || {
        log "connecting with $PG_URL returned '$got'"
        return 1
    }
}

pg_stop() {
    [[ -f $PG_DATA/postmaster.pid ]] || return 0
    find_pg_bin || return 0
    as_pg "$PG_BIN/pg_ctl" -D "$PG_DATA" -m fast -w -t 60 stop >/dev/null 2>&1 || true
}

# ---------------------------------------------------------------------------------------------
# s3s-fs

s3s_fs_version_ok() {
    [[ -x $S3S_FS ]] || return 1
    # `s3s-fs --version` when the binary supports it, else cargo's install record.
    "$S3S_FS" --version 2>/dev/null | grep -qw "$S3S_FS_VERSION" && return 0
    [[ -f $TOOLS/.crates.toml ]] && grep -q "^\"s3s-fs $S3S_FS_VERSION " "$TOOLS/.crates.toml"
}

ensure_s3s_fs() {
    if s3s_fs_version_ok; then
        log "s3s-fs $S3S_FS_VERSION already installed in $TOOLS/bin"
        return 0
    fi
    command -v cargo >/dev/null 2>&1 || {
        log "cargo not found: it is needed once to build s3s-fs $S3S_FS_VERSION into $TOOLS (install the Rust toolchain)"
        return 1
    }
    log "building s3s-fs $S3S_FS_VERSION into $TOOLS (once; takes a few minutes)"
    local t0
    t0=$(now)
    cargo install --locked --root "$TOOLS" s3s-fs --version "$S3S_FS_VERSION" --features binary >&2
    log "cargo install s3s-fs took $(elapsed "$t0")s"
    s3s_fs_version_ok || {
        log "cargo install finished but $S3S_FS is missing or not version $S3S_FS_VERSION"
        return 1
    }
}

s3_start() {
    local attempt pid
    mkdir -p "$S3_ROOT"
    : >"$S3_LOG"
    for attempt in 1 2 3; do
        # In its own session (setsid), so it outlives this script and a Ctrl-C in the caller's
        # terminal, like the postmaster. setsid forks when run as a process group leader (a
        # caller with job control), making $! useless: the pid comes from the process that execs
        # s3s-fs instead.
        rm -f "$DIR/.s3s-fs.pid"
        # shellcheck disable=SC2016 # $$ and $@ are for the inner bash
        RUST_LOG="${RELREWARD_TEST_S3_LOG:-info}" setsid bash -c 'echo $$ >"$0" && exec "$@"' \
            "$DIR/.s3s-fs.pid" "$S3S_FS" \
            --host 127.0.0.1 --port "$S3_PORT" \
            --access-key "$S3_ACCESS_KEY" --secret-key "$S3_SECRET_KEY" \
            "$S3_ROOT" </dev/null >>"$S3_LOG" 2>&1 &
        for _ in $(seq 1 100); do
            [[ -s $DIR/.s3s-fs.pid ]] && break
            sleep 0.05
        done
        pid=$(cat "$DIR/.s3s-fs.pid" 2>/dev/null || true)
        [[ -n $pid ]] || {
            log "s3s-fs did not start (no pid after 5s)"
            return 1
        }
        record_pid s3s-fs "$pid"
        if s3_wait_ready "$pid"; then
            return 0
        fi
        if ! kill -0 "$pid" 2>/dev/null && grep -qi 'address already in use\|AddrInUse' "$S3_LOG" && ((attempt < 3)); then
            S3_PORT=$(free_port)
            warn "port taken, retrying s3s-fs on port $S3_PORT"
            continue
        fi
        return 1
    done
}

# s3_curl ARGS...: curl with SigV4 signing for the S3 server in the current env.
s3_curl() {
    curl -sS --max-time 60 --aws-sigv4 "aws:amz:${S3_REGION:-$REGION}:s3" --user "$S3_ACCESS_KEY:$S3_SECRET_KEY" \
        -H "x-amz-content-sha256: ${S3_PAYLOAD_SHA256:-e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855}" \
        "$@"
}

# s3_wait_ready PID: until a signed ListBuckets answers 200 (or the server exits).
s3_wait_ready() {
    local deadline=$((SECONDS + READY_TIMEOUT_S)) code
    while :; do
        kill -0 "$1" 2>/dev/null || {
            log "s3s-fs exited during startup"
            return 1
        }
        # A short timeout: if another process took the port, it may accept and never answer.
        code=$(s3_curl --max-time 2 -o /dev/null -w '%{http_code}' "http://127.0.0.1:$S3_PORT/" 2>/dev/null || true)
        [[ $code == 200 ]] && return 0
        ((SECONDS < deadline)) || {
            log "s3s-fs did not answer a signed ListBuckets with 200 within ${READY_TIMEOUT_S}s (last status: ${code:-none})"
            return 1
        }
        sleep 0.1
    done
}

s3_create_bucket() {
    local code
    code=$(s3_curl -o "$DIR/.s3-resp" -w '%{http_code}' -X PUT "http://127.0.0.1:$S3_PORT/$BUCKET")
    [[ $code == 200 ]] || {
        log "CreateBucket $BUCKET returned HTTP $code: $(cat "$DIR/.s3-resp" 2>/dev/null)"
        return 1
    }
    code=$(s3_curl -o /dev/null -w '%{http_code}' -I "http://127.0.0.1:$S3_PORT/$BUCKET")
    rm -f "$DIR/.s3-resp"
    [[ $code == 200 ]] || {
        log "HeadBucket $BUCKET returned HTTP $code"
        return 1
    }
}

s3_stop() {
    local pid
    pid=$(pid_of s3s-fs)
    is_s3s_fs_pid "$pid" || return 0
    # SIGINT is s3s-fs's graceful shutdown (it stops accepting and drains connections); SIGKILL
    # after 5 s.
    kill -INT "$pid" 2>/dev/null || return 0
    for _ in $(seq 1 50); do
        is_s3s_fs_pid "$pid" || return 0
        sleep 0.1
    done
    warn "s3s-fs (pid $pid) did not exit within 5s of SIGINT: killing it"
    kill -KILL "$pid" 2>/dev/null || true
}

# ---------------------------------------------------------------------------------------------
# Commands

record_pid() {
    # One line per service: "NAME PID"; a later line for the same name wins.
    printf '%s %s\n' "$1" "$2" >>"$PIDS_FILE"
}

write_env() {
    umask 077
    cat >"$ENV_FILE.tmp" <<EOF
export RELREWARD_TEST_PG_URL=$PG_URL
# The CA of the server's certificate: PostgreSQL accepts TCP connections over TLS only.
export RELREWARD_TEST_PG_CA=$DIR/pg/tls/ca.pem
export RELREWARD_TEST_S3_ENDPOINT=http://127.0.0.1:$S3_PORT
export RELREWARD_TEST_S3_BUCKET=$BUCKET
export RELREWARD_TEST_S3_REGION=$REGION
export RELREWARD_TEST_S3_ACCESS_KEY_ID=$S3_ACCESS_KEY
export RELREWARD_TEST_S3_SECRET_ACCESS_KEY=$S3_SECRET_KEY
# s3s-fs keeps each bucket as a directory of plain files here (tests inspect stored objects).
export RELREWARD_TEST_S3_ROOT=$S3_ROOT
EOF
    mv "$ENV_FILE.tmp" "$ENV_FILE"
}

# fail_start: report the failed start step with the tail of its log, stop what was started, and
# exit non-zero. Runs from the ERR trap set by cmd_start.
CURRENT_STEP="" CURRENT_LOG=""
fail_start() {
    local status=$?
    # In a command substitution or subshell: let the parent shell's trap do the reporting.
    ((BASH_SUBSHELL == 0)) || exit "$status"
    trap - ERR
    log "FAILED: ${CURRENT_STEP:-setup} (exit status $status)"
    [[ -n $CURRENT_LOG ]] && tail_log "$CURRENT_LOG"
    log "stopping what was started"
    s3_stop || true
    pg_stop || true
    rm -f "$ENV_FILE"
    exit 1
}

# step NAME LOG CMD...: a timed start phase; on failure the ERR trap reports NAME and LOG's tail.
step() {
    CURRENT_STEP=$1 CURRENT_LOG=$2
    shift 2
    phase "$CURRENT_STEP" "$@"
}

already_running() {
    [[ -f $ENV_FILE && -f $PIDS_FILE ]] || return 1
    local pg_pid s3_pid
    pg_pid=$(pid_of postgres)
    s3_pid=$(pid_of s3s-fs)
    [[ -n $pg_pid ]] && kill -0 "$pg_pid" 2>/dev/null && is_s3s_fs_pid "$s3_pid"
}

cmd_start() {
    local t0
    t0=$(now)
    if already_running; then
        log "already running in $DIR (see $ENV_FILE); nothing to do"
        return 0
    fi
    if [[ -e $PIDS_FILE || -e $DIR/pg || -e $DIR/s3 ]]; then
        log "leftovers of an earlier start in $DIR: stopping and removing them"
        cmd_stop
        rm -rf "$DIR/pg" "$DIR/s3" "$PIDS_FILE" "$ENV_FILE"
    fi
    : >"$PIDS_FILE"
    # From here on, any failure stops what was started (see fail_start).
    trap fail_start ERR

    PG_PORT=$(free_port)
    PG_PASSWORD=$(random_hex 16)
    S3_ACCESS_KEY="rr$(random_hex 8)"
    S3_SECRET_KEY=$(random_hex 20)

    step "PostgreSQL: find or install" "" ensure_postgres
    log "PostgreSQL binaries: $PG_BIN ($("$PG_BIN/postgres" --version))"
    step "s3s-fs: find or install" "" ensure_s3s_fs

    step "PostgreSQL: prepare directories" "" prepare_pg_dirs
    step "PostgreSQL: initdb" "$PG_LOG" pg_initdb
    step "PostgreSQL: TLS certificates (hostssl only)" "$PG_LOG" pg_tls
    step "PostgreSQL: start" "$PG_LOG" pg_start
    log "PostgreSQL listening on 127.0.0.1:$PG_PORT"
    step "PostgreSQL: wait for pg_isready" "$PG_LOG" pg_wait_ready
    PG_URL="postgres://$DB_USER:$PG_PASSWORD@127.0.0.1:$PG_PORT/$DB_NAME"
    step "PostgreSQL: create role and database $DB_NAME" "$PG_LOG" pg_create_db

    S3_PORT=$(free_port)
    step "s3s-fs: start" "$S3_LOG" s3_start
    log "s3s-fs listening on 127.0.0.1:$S3_PORT"
    step "s3s-fs: create bucket $BUCKET" "$S3_LOG" s3_create_bucket

    write_env
    trap - ERR
    log "pids: $(tr '\n' ' ' <"$PIDS_FILE")"
    log "env:  $ENV_FILE (source it)"
    log "start: ready in $(elapsed "$t0")s"
}

cmd_stop() {
    local t0
    t0=$(now)
    phase "s3s-fs: stop" s3_stop || true
    phase "PostgreSQL: stop (fast)" pg_stop || true
    log "stop: done in $(elapsed "$t0")s"
    return 0
}

# ---- check ----

CHECK_PASSED=()
pass() {
    CHECK_PASSED+=("$1")
    log "ok: $1"
}
check_fail() {
    log "CHECK FAILED: $*"
    [[ -n ${CHECK_LOG:-} ]] && tail_log "$CHECK_LOG"
    exit 1
}

# s3_req OUT METHOD PATH_AND_QUERY [curl args...]: a signed request; prints the HTTP status.
# The query must already be in canonical form (keys sorted, values URI-encoded, `key=` for
# valueless keys): curl before 8.1 signs the query string exactly as written.
s3_req() {
    local out=$1 method=$2 path=$3
    shift 3
    s3_curl -o "$out" -w '%{http_code}' -X "$method" "$@" "$RELREWARD_TEST_S3_ENDPOINT$path"
}

# s3_put_file PATH_AND_QUERY FILE [HEADERS_OUT]: signed PUT of FILE's bytes; prints the status.
s3_put_file() {
    local path=$1 file=$2 headers=${3:-/dev/null}
    S3_PAYLOAD_SHA256=$(sha256sum "$file" | cut -d' ' -f1) \
        s3_req "$WORK/resp" PUT "$path" -D "$headers" --data-binary "@$file" -H 'Content-Type: application/octet-stream'
}

cmd_check() {
    local t0 code
    t0=$(now)
    [[ -f $ENV_FILE ]] || check_fail "$ENV_FILE not found: run '$0 start $DIR' first"
    # shellcheck disable=SC1090
    source "$ENV_FILE"
    find_pg_bin || check_fail "no PostgreSQL client found (psql)"
    WORK=$(mktemp -d)
    trap 'rm -rf "$WORK"' EXIT

    # ---- PostgreSQL
    CHECK_LOG=$PG_LOG
    local got
    got=$("$PG_BIN/psql" -X -qAt -v ON_ERROR_STOP=1 "$RELREWARD_TEST_PG_URL" -c 'select 1' 2>&1) ||
        check_fail "psql select 1: $got"
    [[ $got == 1 ]] || check_fail "psql select 1 returned '$got'"
    pass "PostgreSQL: select 1 through RELREWARD_TEST_PG_URL (TCP, password auth)"
    local sep='?'
    [[ $RELREWARD_TEST_PG_URL == *'?'* ]] && sep='&'
    got=$("$PG_BIN/psql" -X -qAt -v ON_ERROR_STOP=1 \
        "$RELREWARD_TEST_PG_URL${sep}sslmode=verify-full&sslrootcert=$RELREWARD_TEST_PG_CA" \
        -c 'select ssl from pg_stat_ssl where pid = pg_backend_pid()' 2>&1) ||
        check_fail "psql with sslmode=verify-full against RELREWARD_TEST_PG_CA: $got"
    [[ $got == t ]] || check_fail "pg_stat_ssl says ssl = '$got' for a verify-full connection"
    if got=$("$PG_BIN/psql" -X -qAt "$RELREWARD_TEST_PG_URL${sep}sslmode=disable" -c 'select 1' 2>&1); then
        check_fail "a plaintext TCP connection was accepted: $got"
    fi
    pass "PostgreSQL: TLS verified against RELREWARD_TEST_PG_CA (verify-full); plaintext TCP refused"

    # ---- S3, through the same credentials the server under test gets
    CHECK_LOG=$S3_LOG
    S3_ACCESS_KEY=$RELREWARD_TEST_S3_ACCESS_KEY_ID
    S3_SECRET_KEY=$RELREWARD_TEST_S3_SECRET_ACCESS_KEY
    S3_REGION=$RELREWARD_TEST_S3_REGION
    local b="/$RELREWARD_TEST_S3_BUCKET" key="check/dir/object.bin"

    head -c 100000 /dev/urandom >"$WORK/obj"
    code=$(s3_put_file "$b/$key" "$WORK/obj")
    [[ $code == 200 ]] || check_fail "PutObject $key: HTTP $code $(cat "$WORK/resp")"
    echo top >"$WORK/top"
    code=$(s3_put_file "$b/check/top.txt" "$WORK/top")
    [[ $code == 200 ]] || check_fail "PutObject check/top.txt: HTTP $code $(cat "$WORK/resp")"
    pass "S3: PutObject (100000 random bytes)"

    code=$(s3_req "$WORK/list" GET "$b?delimiter=%2F&list-type=2&prefix=check%2F")
    [[ $code == 200 ]] || check_fail "ListObjectsV2: HTTP $code $(cat "$WORK/list")"
    grep -q '<Prefix>check/dir/</Prefix>' "$WORK/list" ||
        check_fail "ListObjectsV2 prefix=check/ delimiter=/: no CommonPrefix check/dir/ in: $(cat "$WORK/list")"
    grep -q '<Key>check/top.txt</Key>' "$WORK/list" ||
        check_fail "ListObjectsV2 prefix=check/ delimiter=/: no Key check/top.txt in: $(cat "$WORK/list")"
    if grep -q "<Key>$key</Key>" "$WORK/list"; then
        check_fail "ListObjectsV2 with delimiter listed $key, which is below a common prefix: $(cat "$WORK/list")"
    fi
    pass "S3: ListObjectsV2 with prefix and delimiter (CommonPrefixes + Contents)"

    code=$(s3_req "$WORK/got" GET "$b/$key")
    [[ $code == 200 ]] || check_fail "GetObject $key: HTTP $code"
    cmp -s "$WORK/obj" "$WORK/got" || check_fail "GetObject $key: bytes differ from what was put"
    pass "S3: GetObject returns the bytes put, identical"

    code=$(s3_req "$WORK/resp" HEAD "$b/$key" -I)
    [[ $code == 200 ]] || check_fail "HeadObject $key: HTTP $code"
    pass "S3: HeadObject"

    for k in "$key" check/top.txt; do
        code=$(s3_req "$WORK/resp" DELETE "$b/$k")
        [[ $code == 204 || $code == 200 ]] || check_fail "DeleteObject $k: HTTP $code $(cat "$WORK/resp")"
    done
    code=$(s3_req "$WORK/resp" GET "$b/$key")
    [[ $code == 404 ]] || check_fail "GetObject after DeleteObject: HTTP $code, expected 404"
    grep -q 'NoSuchKey' "$WORK/resp" || check_fail "GetObject after DeleteObject: no NoSuchKey error in: $(cat "$WORK/resp")"
    pass "S3: DeleteObject (then GetObject is 404 NoSuchKey)"

    # ---- Multipart upload: 5 MiB + 1 byte (the minimum non-final part size is 5 MiB)
    local mkey="check/multipart.bin" upload_id etag1 etag2
    head -c $((5 * 1024 * 1024)) /dev/urandom >"$WORK/part1"
    head -c 1 /dev/urandom >"$WORK/part2"
    cat "$WORK/part1" "$WORK/part2" >"$WORK/whole"
    code=$(s3_req "$WORK/init" POST "$b/$mkey?uploads=")
    [[ $code == 200 ]] || check_fail "CreateMultipartUpload: HTTP $code $(cat "$WORK/init")"
    upload_id=$(sed -n 's:.*<UploadId>\([^<]*\)</UploadId>.*:\1:p' "$WORK/init")
    [[ $upload_id =~ ^[A-Za-z0-9._~-]+$ ]] ||
        check_fail "CreateMultipartUpload: unexpected UploadId '$upload_id' in: $(cat "$WORK/init")"
    code=$(s3_put_file "$b/$mkey?partNumber=1&uploadId=$upload_id" "$WORK/part1" "$WORK/h1")
    [[ $code == 200 ]] || check_fail "UploadPart 1: HTTP $code $(cat "$WORK/resp")"
    code=$(s3_put_file "$b/$mkey?partNumber=2&uploadId=$upload_id" "$WORK/part2" "$WORK/h2")
    [[ $code == 200 ]] || check_fail "UploadPart 2: HTTP $code $(cat "$WORK/resp")"
    etag1=$(tr -d '\r' <"$WORK/h1" | sed -n 's/^[Ee][Tt][Aa][Gg]: *//p')
    etag2=$(tr -d '\r' <"$WORK/h2" | sed -n 's/^[Ee][Tt][Aa][Gg]: *//p')
    [[ -n $etag1 && -n $etag2 ]] || check_fail "UploadPart: no ETag header in the responses"
    cat >"$WORK/complete" <<EOF
<CompleteMultipartUpload><Part><PartNumber>1</PartNumber><ETag>$etag1</ETag></Part><Part><PartNumber>2</PartNumber><ETag>$etag2</ETag></Part></CompleteMultipartUpload>
EOF
    code=$(S3_PAYLOAD_SHA256=$(sha256sum "$WORK/complete" | cut -d' ' -f1) \
        s3_req "$WORK/resp" POST "$b/$mkey?uploadId=$upload_id" --data-binary "@$WORK/complete" -H 'Content-Type: application/xml')
    [[ $code == 200 ]] || check_fail "CompleteMultipartUpload: HTTP $code $(cat "$WORK/resp")"
    grep -q '<Error>' "$WORK/resp" && check_fail "CompleteMultipartUpload: error in a 200 response: $(cat "$WORK/resp")"
    code=$(s3_req "$WORK/got" GET "$b/$mkey")
    [[ $code == 200 ]] || check_fail "GetObject $mkey: HTTP $code"
    cmp -s "$WORK/whole" "$WORK/got" || check_fail "multipart object: bytes differ from the two parts concatenated"
    code=$(s3_req "$WORK/resp" DELETE "$b/$mkey")
    [[ $code == 204 || $code == 200 ]] || check_fail "DeleteObject $mkey: HTTP $code"
    pass "S3: multipart upload of 2 parts (5 MiB + 1 byte), read back identical, deleted"

    code=$(s3_req "$WORK/list" GET "$b?list-type=2&prefix=check%2F")
    [[ $code == 200 ]] || check_fail "ListObjectsV2: HTTP $code"
    if grep -q '<Key>' "$WORK/list"; then
        check_fail "objects left under check/ after the deletes: $(cat "$WORK/list")"
    fi
    pass "S3: bucket empty under check/ afterwards"

    log "check: ${#CHECK_PASSED[@]} checks passed in $(elapsed "$t0")s"
}

usage() {
    echo "usage: $0 {start|stop|check} DIR" >&2
    exit 2
}

main() {
    [[ $# -eq 2 ]] || usage
    local cmd=$1
    set_dir "$2"
    case $cmd in
    start) cmd_start ;;
    stop) cmd_stop ;;
    check) cmd_check ;;
    *) usage ;;
    esac
}

main "$@"
