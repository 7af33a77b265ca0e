# What the benchmark scripts that start one relreward server share (sourced, not run). Source it
# from the repository root after setting BIN (the binaries' directory) and tmp (the script's
# scratch directory); the script's EXIT trap calls stop_server. Messages name the script.
#
#   wait_line FILE PREFIX PID WHAT [LOG]
#                                    waits up to 60 s for a line of FILE starting with PREFIX,
#                                    prints the rest of it; exits with LOG's tail ($tmp/log by
#                                    default) if PID dies or the time runs out (WHAT names it)
#   start_server [ENV=VALUE...]      relreward-server on 127.0.0.1:0 over $tmp/data, the metrics
#                                    port off, with the settings (RELREWARD__...) of the array
#                                    server_env (the script's, set after sourcing) and then these;
#                                    sets $server (its pid) and $endpoint, exports
#                                    RELREWARD_ENDPOINT; its stdout goes to $tmp/out, its log is
#                                    appended to $tmp/log
#   stop_server                      stops it (nothing when none runs)
#   rr ARGS...                       the CLI
#   quiet CMD...                     runs CMD, showing its output only if it fails (then exits)

bench=${0##*/}
server=
server_env=()

wait_line() {
  for _ in $(seq 600); do
    if grep -qs "^$2" "$1"; then
      sed -n "s/^$2//p" "$1" | head -1
      return
    fi
    kill -0 "$3" 2>/dev/null || break
    sleep 0.1
  done
  echo "$bench: $4 did not start:" >&2
  tail -20 "${5:-$tmp/log}" >&2
  exit 1
}

start_server() {
  # Emptied first: a restart must not read the previous server's address.
  : >"$tmp/out"
  env RELREWARD__METRICS__LISTEN= "${server_env[@]}" "$@" "$BIN/relreward-server" --listen 127.0.0.1:0 --data-dir "$tmp/data" \
    >"$tmp/out" 2>>"$tmp/log" &
  server=$!
  endpoint="http://$(wait_line "$tmp/out" 'relreward-server listening on ' "$server" relreward-server)"
  export RELREWARD_ENDPOINT=$endpoint
}

stop_server() {
  if [[ -n $server ]]; then
    kill "$server" 2>/dev/null || true
    wait "$server" 2>/dev/null || true
    server=
  fi
}

rr() { "$BIN/relreward" "$@"; }

quiet() { "$@" >"$tmp/cmd.log" 2>&1 || { echo "$bench: failed: $*" >&2; cat "$tmp/cmd.log" >&2; exit 1; }; }
