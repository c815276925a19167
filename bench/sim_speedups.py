"""Benchmark: CPU time per env step of Safety-Gymnasium and Bullet-Safety-Gym tasks with the library's own functions
and with dsrl_sim's speed-ups (sim/python/dsrl_sim/speedups.py), side by side in one process: the same seeds and uniform random
actions, the two envs stepped in alternating blocks (each side first in every other round) so that both see the same
machine. Each block is checked as it
is timed: the two envs' outputs must agree bit for bit (`speedups.verify` is the full check, with the physics
state). Prints Markdown rows (bench/sim_speedups.sh makes the table); run with the simulators' Python:

    .venv-sim/bin/python bench/sim_speedups.py --steps 2000 --rounds 3 SafetyPointButton1-v0 ...
"""
import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "sim" / "python"))
from dsrl_sim import speedups, tasks  # noqa: E402

tasks.quiet()


class Player:
    """One env playing episodes from seeds 0, 1, ... with actions from a generator seeded 0."""

    def __init__(self, env):
        self.env, self.episode, self.actions, self.done = env, 0, np.random.default_rng(0), True

    def play(self, steps):
        """-> CPU seconds for `steps` steps (resets included) and what they returned, as bytes."""
        out = []
        start = time.process_time()
        for _ in range(steps):
            if self.done:
                out.append(self.env.reset(self.episode).tobytes())
                self.episode += 1
            result = self.env.step(self.actions.uniform(-1.0, 1.0, self.env.act_dim))
            out.append(np.concatenate([result[0], result[1:5]]).tobytes())
            self.done = result[3] or result[4]
        return time.process_time() - start, b"".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("tasks", nargs="+", help="Safety-Gymnasium or Bullet-Safety-Gym simulator ids (SafetyPointButton1-v0, ...)")
    parser.add_argument("--steps", type=int, default=2000, help="env steps per block (default 2000)")
    parser.add_argument("--rounds", type=int, default=3, help="blocks per side (default 3); the median is shown")
    args = parser.parse_args()
    if args.steps < 1 or args.rounds < 1:
        parser.error("--steps and --rounds must be at least 1")
    for task in args.tasks:
        if tasks.family(task) not in (tasks.SAFETY_GYMNASIUM, tasks.BULLET):
            parser.error(f"{task}: the speed-ups are Safety-Gymnasium's and Bullet-Safety-Gym's")
        fast = Player(tasks.make_env(task))
        with speedups.LibraryFunctions():
            library = Player(tasks.make_env(task))
        library_s, fast_s = [], []
        for round in range(args.rounds):
            # Each side goes first in every other round, so neither always finds the caches the other left.
            for side in ((0, 1) if round % 2 == 0 else (1, 0)):
                if side == 0:
                    with speedups.LibraryFunctions():
                        seconds, expected = library.play(args.steps)
                    library_s.append(seconds)
                else:
                    seconds, got = fast.play(args.steps)
                    fast_s.append(seconds)
            if got != expected:
                sys.exit(f"{task}: the speed-ups changed an episode")
        lib, spd = statistics.median(library_s), statistics.median(fast_s)
        print(f"| {task} | {args.steps} x {args.rounds} | {lib / args.steps * 1e6:.0f} | {spd / args.steps * 1e6:.0f} "
              f"| {lib / spd:.2f}x | yes |", flush=True)


if __name__ == "__main__":
    main()
