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
