# Sourced by the bench scripts: the machine line under every table, and writing a table into BENCHMARKS.md.

# The load when this file is sourced (where the script starts measuring): other work slows every column.
bench_load=$(cut -d' ' -f1-3 /proc/loadavg)

cpu_model() { grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'; }
has_avx512() { grep -q avx512f /proc/cpuinfo && echo yes || echo no; }

# One line: cores, CPU model, AVX-512, date, the commit built (marked when code differs from it), the load at start.
machine_line() {
  local commit
  commit=$(git rev-parse --short=12 HEAD)
  # Documents and data (the reference sweep writes its results while it runs) are not code.
  git diff --quiet HEAD -- . ':!*.md' ':!bench/out' ':!data' || commit="$commit (with uncommitted changes)"
  echo "Machine: $(nproc) cores, $(cpu_model), AVX-512: $(has_avx512), $(date -u +%F); release build of $commit;" \
    "load average at the start: $bench_load."
}

# bench_section NAME FILE: FILE goes into BENCHMARKS.md between bench/NAME's markers.
bench_section() {
  python3 bench/into_benchmarks.py "$1" "$2"
  echo "written into BENCHMARKS.md" >&2
}

# start_server OUT_DIR COMMAND...: runs a dsrl-server (or dsrl-sim-worker) command line that listens on port 0 in
# the background, its stdout in OUT_DIR/server.out and its log in OUT_DIR/server.log; waits for its one
# "... listening on URL" line (a minute at most; it stops the script if the process exits first or never says it)
# and sets server_pid and url. The caller's cleanup kills $server_pid.
start_server() {
  local out=$1
  shift
  "$@" > "$out/server.out" 2> "$out/server.log" &
  server_pid=$!
  url=
  for _ in $(seq 600); do
    url=$(sed -n 's/^dsrl-[a-z-]* listening on //p' "$out/server.out" 2>/dev/null)
    [ -n "$url" ] && return 0
    kill -0 "$server_pid" 2>/dev/null || { echo "$1 exited before listening; see $out/server.log" >&2; exit 1; }
    sleep 0.1
  done
  echo "$1 did not say where it listens within a minute; see $out/server.log" >&2
  exit 1
}
