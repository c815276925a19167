#!/usr/bin/env bash
# How long CI takes, measured as CI runs it: `.ci/run` on a fresh clone of HEAD with a cold target folder, every
# line of its output stamped with the seconds since start. Writes tests/CI_TIME.md: the total, the phases (system
# packages and Python environments, the test build with clippy's lints, the test binaries (the end-to-end one
# beside the others, scripts/run-tests.py) and the end-to-end binary within them) and the end-to-end tests that finished latest after the one before (with two test threads, an
# approximation of each test's time), with the commit, machine and date. Crates and pip packages already downloaded
# on this machine are not downloaded again, so a new machine takes a few minutes more.
# Usage: scripts/ci-time.sh   (40-50 minutes; run it on a quiet machine)
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d "${TMPDIR:-/tmp}/dsrl-ci-time.XXXXXX")
trap 'rm -rf "$work"' EXIT
git clone -q . "$work/clone"
commit=$(git rev-parse --short=12 HEAD)
# The whole stamped log is kept outside the clone (a failing run is read there).
mkdir -p "$HOME/.dsrl/logs"
log="$HOME/.dsrl/logs/ci-time-$commit.log"
echo "running .ci/run on a fresh clone of $commit (log: $log)" >&2
start=$(date +%s)
status=0
(cd "$work/clone" && CARGO_TARGET_DIR="$work/target" .ci/run) 2>&1 \
  | while IFS= read -r line; do echo "$(( $(date +%s) - start )) $line"; done > "$log" || status=$?
total=$(( $(date +%s) - start ))
python3 - "$log" "$total" "$commit" "$status" > tests/CI_TIME.md <<'PY'
import re, subprocess, sys
log, total, commit, status = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
lines = [l.rstrip("\n").split(" ", 1) for l in open(log)]
lines = [(int(t), rest) for t, *r in lines for rest in (r or [""])]
def first(pattern, after=0):
    return next((t for t, l in lines if t >= after and re.search(pattern, l)), None)
finished = [t for t, l in lines if re.search(r"Finished `\w+` profile", l)]
# One build before the tests: the test build, clippy's lints inside it (scripts/test.sh).
build_start = first(r"Checking|Compiling")
build_end = finished[0] if finished else None
# By line, not by second: the binaries before the end-to-end one report in the same second it starts. The other
# test binaries run beside it (scripts/run-tests.py) and print each of their blocks whole, from its "Running" line
# to its "test result" line: the end-to-end binary's lines are those outside such blocks.
e2e_line = next((i for i, (t, l) in enumerate(lines) if re.search(r"Running e2e/main\.rs", l)), None)
e2e_start = None if e2e_line is None else lines[e2e_line][0]
e2e_lines, e2e_end, inside_other = [], None, False
for t, l in ([] if e2e_line is None else lines[e2e_line + 1:]):
    if re.search(r"^\s*Running ", l):
        inside_other = True
    elif inside_other:
        inside_other = not l.startswith("test result")
    elif l.startswith("test result"):
        e2e_end = t
        break
    else:
        e2e_lines.append((t, l))
cpu = next(l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name"))
nproc = subprocess.run(["nproc"], capture_output=True, text=True).stdout.strip()
date = subprocess.run(["date", "-u", "+%F"], capture_output=True, text=True).stdout.strip()
def m(s):
    return "–" if s is None else f"{s / 60:.1f} min"
print("# CI time\n")
print("A cold `.ci/run` on a fresh clone, measured by `scripts/ci-time.sh` (a generated file; commit it).\n")
failed = sorted({l.split()[1] for t, l in lines if re.match(r"test \S+ \.\.\. FAILED", l)})
print(f"Commit {commit}, {date}, {nproc} cores, {cpu}; exit status {status}. **Total: {total / 60:.1f} min.**\n")
if failed:
    print("Failed: " + ", ".join(failed) + " (every test binary ran: scripts/run-tests.py goes on past a failure).\n")
print("| phase | minutes |\n|---|---|")
print(f"| system packages, fmt, until the first crate compiles | {m(build_start)} |")
print(f"| the test build with clippy's lints (the Python environments install beside it) | {m(None if build_end is None or build_start is None else build_end - build_start)} |")
last_result = max((t for t, l in lines if l.startswith("test result")), default=None)
print(f"| every test binary (the end-to-end one beside the others), then the doc-tests | {m(None if last_result is None or build_end is None else last_result - build_end)} |")
print(f"| of which the end-to-end binary | {m(None if e2e_end is None or e2e_start is None else e2e_end - e2e_start)} |")
tests = [(t, l) for t, l in e2e_lines if re.match(r"test \S+ \.\.\. (ok|FAILED|ignored)", l)]
gaps, last = [], e2e_start
for t, l in tests:
    gaps.append((t - last, l.split()[1], l.split()[-1]))
    last = t
print("\nEnd-to-end tests, by the time from the previous test's end to theirs (two run at once), longest first:\n")
print("| test | outcome | seconds |\n|---|---|---|")
for gap, name, outcome in sorted(gaps, reverse=True)[:15]:
    print(f"| {name} | {outcome} | {gap} |")
PY
echo "recorded in tests/CI_TIME.md (total $(( total / 60 )) min)" >&2
