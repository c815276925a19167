#!/usr/bin/env bash
# Benchmark (issue "beyond one machine"): requests per second and p99 latency of the catalog (/v1/tasks), a manifest
# and a ~200 MB download, side by side in one run, for
#   1. one dsrl-server on SQLite (the embedded default);
#   2. one dsrl-server on PostgreSQL;
#   3. two dsrl-server replicas on the same PostgreSQL, the load split between them;
# and the leaderboard queue's throughput (jobs claimed and finished per second, 60 episodes stored per job) with 1
# and 4 evaluators on 1000 queued jobs, and 1 on 4000 (the claim's cost must not grow with the queue), on SQLite and
# PostgreSQL (leaderboard/examples/queue_claims.rs), with the disk's sync latency beside them.
#
# Load comes from wrk (Debian's package, installed if missing), 16 connections in all (8 per replica with two),
# 10 s per figure (20 s for downloads, 4 connections). PostgreSQL is Debian's, started here in a temporary folder.
# The object store is local; the second replica sees the first's objects through a symlinked folder (a stand-in
# for a shared filesystem: S3 through moto would measure moto). Everything, wrk included, shares this machine's
# cores. Prints a Markdown table (also bench/out/replicas.md, and into BENCHMARKS.md). Usage: bench/replicas.sh
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
if ! command -v wrk > /dev/null; then
  echo "installing wrk (Debian package)" >&2
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo=sudo
  $sudo apt-get install -y -qq wrk > /dev/null
fi
export PYO3_PYTHON="${PYO3_PYTHON:-$(command -v "${PYTHON:-python3}")}"
echo "building (release): dsrl-server, dsrl-client, dsrl-make-dataset, the queue benchmark" >&2
cargo build --release --locked -p dsrl-server -p dsrl-client -p dsrl-e2e --bins >&2
cargo build --release --locked -p dsrl-leaderboard --example queue_claims >&2
bin=${CARGO_TARGET_DIR:-target}/release
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-replicas-bench.XXXXXX")
pids=()
cleanup() {
  for f in "$work"/*.pid; do [ -f "$f" ] && kill "$(cat "$f")" 2> /dev/null || true; done
  for p in "${pids[@]}"; do kill "$p" 2> /dev/null || true; done
  wait 2> /dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT
token=bench-admin-token-0123456789

# PostgreSQL in a temporary folder (as the postgres user when run as root: PostgreSQL refuses root).
pgbin=$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -1)
as_pg=()
if [ "$(id -u)" -eq 0 ]; then
  chown postgres:postgres "$work"
  as_pg=(setpriv --reuid=postgres --regid=postgres --init-groups)
fi
echo "starting PostgreSQL ($pgbin)" >&2
"${as_pg[@]}" "$pgbin/initdb" -U dsrl -A trust -E UTF8 --no-sync -D "$work/pg" > /dev/null
pgport=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
"${as_pg[@]}" "$pgbin/postgres" -D "$work/pg" -p "$pgport" -k "$work/pg" -c listen_addresses=127.0.0.1 \
  -c max_connections=200 > "$work/pg.log" 2>&1 &
pids+=($!)
until "$pgbin/pg_isready" -q -h 127.0.0.1 -p "$pgport"; do sleep 0.2; done
pgurl="postgres://dsrl@127.0.0.1:$pgport/postgres"

# A server on a free port; prints its URL.
serve() { # data_dir [env...]
  local dir=$1; shift
  mkdir -p "$dir"
  env DSRL__AUTH__ADMIN_TOKEN=$token DSRL__LEADERBOARD__SEED_SECRET=bench DSRL__SIMULATORS__LOCAL_WORKERS=0 \
    DSRL__LEADERBOARD__EVALUATORS=0 DSRL_LOG=warn "$@" \
    "$bin/dsrl-server" --listen 127.0.0.1:0 --data-dir "$dir" --starter-datasets "$dir/none" \
    > "$dir.out" 2> "$dir.log" &
  echo $! > "$dir.pid"
  for _ in $(seq 600); do grep -q "listening on" "$dir.out" 2> /dev/null && break; sleep 0.1; done
  grep -q "listening on" "$dir.out" || { echo "dsrl-server did not start:" >&2; cat "$dir.log" >&2; exit 1; }
  sed -n 's/^dsrl-server listening on //p' "$dir.out"
}

task=OfflineMetadrive-easysparse-v0
echo "writing a ~200 MB synthetic $task dataset" >&2
"$bin/dsrl-make-dataset" --task $task --episodes 140 --seed 7 "$work/big.parquet" > /dev/null
ingest() { # url
  DSRL_SERVER=$1 DSRL_ADMIN_TOKEN=$token DSRL_DATASET_DIR="$work/cache" HOME="$work" \
    "$bin/dsrl-client" --json admin ingest --task $task "$work/big.parquet" \
    | python3 -c 'import json,sys; print(json.load(sys.stdin)["version"]["version"])'
}

# wrk against one or more base URLs at once (connections split); prints "rps p99_ms MB/s".
load() { # path connections seconds url...
  local path=$1 conns=$2 secs=$3; shift 3
  local per=$((conns / $#)) i=0 outs=() wrks=()
  for url in "$@"; do
    wrk -t1 -c"$per" -d"${secs}s" --latency "$url$path" > "$work/wrk.$i" &
    wrks+=($!); outs+=("$work/wrk.$i"); i=$((i + 1))
  done
  wait "${wrks[@]}"
  python3 - "${outs[@]}" << 'EOF'
import re, sys
rps = mb = 0.0
p99 = 0.0
unit = {"us": 1e-3, "ms": 1.0, "s": 1e3}
size = {"B": 1e-6, "KB": 1e-3, "MB": 1.0, "GB": 1e3}
for f in sys.argv[1:]:
    text = open(f).read()
    rps += float(re.search(r"Requests/sec:\s+([\d.]+)", text).group(1))
    v, u = re.search(r"99%\s+([\d.]+)(us|ms|s)", text).groups()
    p99 = max(p99, float(v) * unit[u])
    v, u = re.search(r"Transfer/sec:\s+([\d.]+)(B|KB|MB|GB)", text).groups()
    mb += float(v) * size[u]
print(f"{rps:.1f} {p99:.1f} {mb:.0f}")
EOF
}

row() { # label urls...
  local label=$1; shift
  local catalog manifest download
  catalog=$(load /v1/tasks 16 10 "$@")
  manifest=$(load "/v1/datasets/$task/versions/$version" 16 10 "$@")
  download=$(load "/v1/datasets/$task/versions/$version/download" 4 20 "$@")
  read -r c_rps c_p99 _ <<< "$catalog"
  read -r m_rps m_p99 _ <<< "$manifest"
  read -r d_rps d_p99 d_mb <<< "$download"
  printf "| %s | %s | %s | %s | %s | %s | %s | %s |\n" "$label" "$c_rps" "$c_p99" "$m_rps" "$m_p99" "$d_rps" "$d_p99" "$d_mb"
}

echo "1 replica on SQLite" >&2
sqlite_url=$(serve "$work/sqlite")
version=$(ingest "$sqlite_url")
size=$(stat -c %s "$work/sqlite/objects/datasets/$task/$version.parquet")
rows=()
rows+=("$(row "1 replica, SQLite" "$sqlite_url")")

echo "1 replica on PostgreSQL" >&2
a_url=$(serve "$work/pg-a" DSRL__DATABASE__URL="$pgurl")
[ "$(ingest "$a_url")" = "$version" ]
rows+=("$(row "1 replica, PostgreSQL" "$a_url")")

echo "2 replicas on PostgreSQL" >&2
mkdir -p "$work/pg-b"
ln -s "$work/pg-a/objects" "$work/pg-b/objects"
b_url=$(serve "$work/pg-b" DSRL__DATABASE__URL="$pgurl")
rows+=("$(row "2 replicas, PostgreSQL" "$a_url" "$b_url")")

echo "queue throughput" >&2
# Claims per second, or the error that stopped the run (the table keeps the other figures; the error is shown, not
# dropped).
queue() {
  local out
  if out=$(RUST_BACKTRACE=0 "$bin/examples/queue_claims" --database "$1" --evaluators "$2" --jobs "$3" 2>&1); then
    echo "$out" | tail -1 | python3 -c 'import json,sys; print(round(json.load(sys.stdin)["claims_per_second"]))'
  else
    echo "failed: $(echo "$out" | grep -m1 -i error | tr "|" "/" | cut -c1-120)"
  fi
}
# Every claim and finish commits with a sync to disk, so the queue's per-job cost follows this disk's sync latency,
# which varies with what else writes to it: measured just before and just after the queue runs, in the folder the
# SQLite files are in (50 appends of 4 KiB, each followed by fsync, as SQLite syncs its write-ahead log).
sync_latency() {
  python3 - "${TMPDIR:-/tmp}" <<'PY'
import os, statistics, sys, tempfile, time
with tempfile.NamedTemporaryFile(dir=sys.argv[1]) as f:
    times = []
    for _ in range(50):
        os.write(f.fileno(), b"x" * 4096)
        t = time.perf_counter()
        os.fsync(f.fileno())
        times.append(time.perf_counter() - t)
times.sort()
print(f"median {1000 * statistics.median(times):.2f} ms, slowest {1000 * times[-1]:.2f} ms")
PY
}
sync_before=$(sync_latency)
q_sqlite_1=$(queue sqlite 1 1000)
q_sqlite_4=$(queue sqlite 4 1000)
q_sqlite_long=$(queue sqlite 1 4000)
q_pg_1=$(queue "$pgurl" 1 1000)
q_pg_4=$(queue "$pgurl" 4 1000)
q_pg_long=$(queue "$pgurl" 1 4000)
sync_after=$(sync_latency)

mkdir -p bench/out
{
  machine_line
  echo "Download: $((size / 1000000)) MB; wrk $(wrk -v 2>&1 | head -1 | cut -d' ' -f2)."
  echo
  echo "| deployment | catalog req/s | catalog p99 ms | manifest req/s | manifest p99 ms | download req/s | download p99 ms | download MB/s |"
  echo "|---|---|---|---|---|---|---|---|"
  printf "%s\n" "${rows[@]}"
  echo
  echo "| queue (jobs claimed + finished with 60 episodes, per second) | 1 evaluator, 1000 jobs | 4 evaluators, 1000 jobs | 1 evaluator, 4000 jobs |"
  echo "|---|---|---|---|"
  echo "| SQLite | $q_sqlite_1 | $q_sqlite_4 | $q_sqlite_long |"
  echo "| PostgreSQL | $q_pg_1 | $q_pg_4 | $q_pg_long |"
  echo
  echo "Disk sync (fsync after a 4 KiB append, 50 times, in ${TMPDIR:-/tmp}): before the queue runs $sync_before; after them $sync_after."
} > bench/out/replicas.md
cat bench/out/replicas.md
bench_section replicas.sh bench/out/replicas.md
