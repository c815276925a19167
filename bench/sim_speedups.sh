#!/usr/bin/env bash
# Benchmark: CPU microseconds per env step of the Safety-Gymnasium tasks without a full build (the level-2 and Button
# tasks, which the speed-ups touch most), one they do not touch (HopperVelocity, a control for the measurement's
# noise) and the eight Bullet-Safety-Gym tasks, with the library's own functions and with dsrl_sim's speed-ups,
# side by side in one process (bench/sim_speedups.py). Prints a Markdown table (bench/out/sim_speedups.md, and into
# BENCHMARKS.md at the default size).
# Usage: bench/sim_speedups.sh [STEPS=2000] [ROUNDS=3]
set -euo pipefail
cd "$(dirname "$0")/.."
source bench/lib.sh
steps=${1:-2000}
rounds=${2:-3}
sim/setup.sh >&2
mkdir -p bench/out
out=bench/out/sim_speedups.md
{
  echo "$(machine_line)"
  echo
  echo "| task | env steps (per block x blocks) | library's functions, CPU µs/step (median) | dsrl_sim's speed-ups, CPU µs/step (median) | speed-up | same episodes |"
  echo "|---|---|---|---|---|---|"
  PYTHONWARNINGS=ignore .venv-sim/bin/python bench/sim_speedups.py --steps "$steps" --rounds "$rounds" \
    SafetyPointButton1-v0 SafetyPointButton2-v0 SafetyCarButton1-v0 SafetyCarButton2-v0 SafetyPointGoal2-v0 \
    SafetyCarGoal2-v0 SafetyPointPush2-v0 SafetyCarPush1-v0 SafetyCarPush2-v0 SafetyHopperVelocity-v1 \
    SafetyBallRun-v0 SafetyBallCircle-v0 SafetyCarRun-v0 SafetyCarCircle-v0 SafetyDroneRun-v0 SafetyDroneCircle-v0 \
    SafetyAntRun-v0 SafetyAntCircle-v0
} > "$out"
cat "$out"
if [ "$steps" = 2000 ] && [ "$rounds" = 3 ]; then bench_section sim_speedups.sh "$out"; fi
