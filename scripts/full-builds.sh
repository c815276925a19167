#!/usr/bin/env bash
# Runs `dsrl-admin build` (the full builds, data/full_builds.toml) in the background, in a session of its own at
# the lowest priority: its processes run on what the machine leaves idle (the session's autogroup gets nice 19,
# which is what orders CPU between sessions; a plain `nice` only orders processes within one). Resumable: run it
# again after a kill or a reboot and every task continues from its state folder under ${DSRL_FULL_ROOT:-~/.dsrl/full}.
# Arguments go to `dsrl-admin build` (tasks, --jobs, --server, --record...). Its log: <root>/build.log.
#
#   scripts/full-builds.sh                         # every task, in the plan's order
#   scripts/full-builds.sh --jobs 2 OfflineBallRun-v0 OfflineCarRun-v0
#   tail -f ~/.dsrl/full/build.log                 # progress every 5 minutes, a line per finished task;
#                                                  # per-task logs in <root>/logs/
set -euo pipefail
cd "$(dirname "$0")/.."
root=${DSRL_FULL_ROOT:-$HOME/.dsrl/full}
admin=${DSRL_ADMIN:-$(command -v dsrl-admin || echo "${CARGO_TARGET_DIR:-target}/release/dsrl-admin")}
[ -x "$admin" ] || { echo "no dsrl-admin at $admin: run scripts/serve.sh (or cargo build --release) first" >&2; exit 1; }
mkdir -p "$root"
# setsid: a new session, so a new autogroup; the child sets that autogroup's nice before it execs the build.
setsid bash -c 'echo 19 > /proc/self/autogroup 2>/dev/null || true; exec nice -n 19 "$0" build --root "$1" --json "${@:2}"' \
  "$admin" "$root" "$@" >> "$root/build.log" 2>&1 < /dev/null &
echo "building in the background (pid $!); log: $root/build.log, per task: $root/logs/<task>.log" >&2
