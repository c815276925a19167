#!/usr/bin/env bash
# Follows the full builds with their reference entries: for each named task in turn, waits until its full build is
# finished under the builds' root (${DSRL_FULL_ROOT:-~/.dsrl/full}, as `dsrl-admin build --status` says), then runs
# `dsrl-admin reference <phases> --task <task>` (by default the phases `full` and `full-seeds` of
# data/reference/plan.toml: BC-All and BC-Safe, training seeds 0-2), which writes each scored entry into
# data/reference/full_builds.jsonl. A task whose build is committed but whose data is not on this machine is skipped,
# with the rebuild that would bring it here. At the end it regenerates the documents (`dsrl-admin docs`). Like
# scripts/full-builds.sh it runs in the background, in a session of its own at the lowest priority (its autogroup
# gets nice 19), so builds, trainings and the rest of the machine's work share the cores in that order of need.
# Resumable: run it again after a kill and each task's reference continues from its state folder
# (~/.dsrl/reference-full); entries the results file holds are not trained again.
#
#   scripts/full-builds.sh --record A B          # the builds, one after the other
#   scripts/full-references.sh A B               # the entries on each, as soon as its build is finished
#   PHASES="full-six" scripts/full-references.sh OfflineBallRun-v0
#   tail -f ~/.dsrl/reference-full/follow.log
#
# It trains with the release binaries beside dsrl-admin (DSRL_TRAIN, DSRL_SERVER_BIN to choose others), copied
# when it starts (below), so a release build made while it runs does not reach it. Commit the
# results file and the regenerated documents with explicit paths when it is done (CONTRIBUTING.md).
set -euo pipefail
self=$(realpath "$0")
cd "$(dirname "$self")/.."
root=${DSRL_FULL_ROOT:-$HOME/.dsrl/full}
admin=${DSRL_ADMIN:-$(command -v dsrl-admin || echo "${CARGO_TARGET_DIR:-target}/release/dsrl-admin")}
log_dir=$HOME/.dsrl/reference-full
read -r -a phases <<< "${PHASES:-full full-seeds}"

# The loop itself, run by the copy of this script started in the background below.
if [ "${1:-}" = "--follow" ]; then
  shift
  for task in "$@"; do
    echo "$(date -u +%FT%TZ) $task: waiting for its full build under $root"
    # The build's state: finished (go on), committed (its record is in git but its data is not on this machine:
    # nothing here will finish it, so the task is skipped with what to do), or anything else (wait).
    state=""
    until [ "$state" = finished ] || [ "$state" = committed ]; do
      [ -z "$state" ] || sleep 60
      state=$("$admin" build --root "$root" --status --json "$task" | python3 -c '
import json, sys
print(next((p["state"] for p in json.load(sys.stdin) if p["task"] == sys.argv[1]), "unknown"))' "$task") ||
        state=unknown
    done
    if [ "$state" = committed ]; then
      echo "$(date -u +%FT%TZ) $task: skipped: its full build is committed but not under $root; rebuild it" \
        "(scripts/full-builds.sh $task: the same version while the code that shapes the data is unchanged)" \
        "and run this script again once the rebuild has started"
      continue
    fi
    echo "$(date -u +%FT%TZ) $task: reference phases ${phases[*]}"
    # One reference run at a time (flock): the phases share a private server in one state folder.
    if ! flock "$log_dir/reference.lock" "$admin" reference "${phases[@]}" --full-builds "$root" --task "$task"; then
      echo "$(date -u +%FT%TZ) $task: the reference phases stopped with an error (above); run the script again to resume"
    fi
  done
  "$admin" docs
  echo "$(date -u +%FT%TZ) done: commit data/reference/full_builds.jsonl and the regenerated documents"
  exit 0
fi

[ $# -gt 0 ] || { echo "usage: scripts/full-references.sh TASK... (see the header of this script)" >&2; exit 2; }
[ -x "$admin" ] || { echo "no dsrl-admin at $admin: run scripts/serve.sh (or cargo build --release) first" >&2; exit 1; }
bin_dir=$(dirname "$(realpath "$admin")")
export DSRL_TRAIN=${DSRL_TRAIN:-$bin_dir/dsrl-train} DSRL_SERVER_BIN=${DSRL_SERVER_BIN:-$bin_dir/dsrl-server}
for b in "$DSRL_TRAIN" "$DSRL_SERVER_BIN"; do
  [ -x "$b" ] || { echo "no $b: build the release binaries (scripts/serve.sh) or set DSRL_TRAIN/DSRL_SERVER_BIN" >&2; exit 1; }
done
# The loop runs copies of the binaries, pinned in a folder named by their digest: it goes on for hours, and a release
# build made meanwhile would otherwise train one task's models with two builds, which `dsrl-admin reference` refuses
# to record as one entry. The server starts its simulator workers and policy processes from beside itself, so its
# dsrl-sim-worker is pinned with it. (Old pins: rm -rf ~/.dsrl/reference-full/bin while nothing runs.)
worker=$(dirname "$DSRL_SERVER_BIN")/dsrl-sim-worker
[ -x "$worker" ] || { echo "no $worker beside $DSRL_SERVER_BIN" >&2; exit 1; }
pin=$log_dir/bin/$(cat "$admin" "$DSRL_TRAIN" "$DSRL_SERVER_BIN" "$worker" | sha256sum | cut -c1-16)
if [ ! -d "$pin" ]; then
  mkdir -p "$log_dir/bin" && rm -rf "$pin.partial" && mkdir "$pin.partial"
  cp "$admin" "$pin.partial/dsrl-admin" && cp "$DSRL_TRAIN" "$pin.partial/dsrl-train"
  cp "$DSRL_SERVER_BIN" "$pin.partial/dsrl-server" && cp "$worker" "$pin.partial/dsrl-sim-worker"
  mv "$pin.partial" "$pin"
fi
admin=$pin/dsrl-admin DSRL_TRAIN=$pin/dsrl-train DSRL_SERVER_BIN=$pin/dsrl-server
echo "running the binaries pinned in $pin" >&2
# Every task and phase is checked before anything waits: an unknown name fails now, not hours later.
"$admin" build --root "$root" --status "$@" > /dev/null
# The list is read whole first: `grep -q` in the pipe would stop reading at its match, and under pipefail the
# writer's broken pipe would fail the check now and then.
known=$("$admin" reference --list)
for phase in "${phases[@]}"; do
  grep -q "^$phase " <<< "$known" || { echo "no phase $phase in data/reference/plan.toml" >&2; exit 2; }
done
mkdir -p "$log_dir"
export DSRL_ADMIN=$admin DSRL_FULL_ROOT=$root
# setsid: a new session, so a new autogroup; the child sets that autogroup's nice before it execs the loop.
setsid bash -c 'echo 19 > /proc/self/autogroup 2>/dev/null || true; exec nice -n 19 "$0" --follow "$@"' \
  "$self" "$@" >> "$log_dir/follow.log" 2>&1 < /dev/null &
echo "following the builds in the background (pid $!); log: $log_dir/follow.log" >&2
