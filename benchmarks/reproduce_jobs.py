"""`reproduce --jobs`: wall time of the same grid trained one run at a time in one process
(``--jobs 1``) and side by side, each run in its own process on its share of the CPUs
(``--jobs J``, default: every CPU), measured back to back in one invocation, with the ratio.

The grid is ``reproduce --quick`` cut to ``--scenarios`` (default paper-2 paper-3: 6 runs
of 2 seeds at the reference preset) with ``--episodes`` per seed (default 2000, the quick
grid's), each timing in a fresh folder and a fresh compilation cache so neither side gets
the other's compiled programs. Run ``python benchmarks/reproduce_jobs.py`` on an otherwise
idle machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from roverswarm.experiments.arms import usable_cpus


def timed(jobs: int, scenarios: list[str], episodes: int) -> float:
    """Wall seconds of ``roverswarm reproduce --quick --jobs jobs`` in fresh folders."""
    with tempfile.TemporaryDirectory() as scratch:
        env = {**os.environ, "ROVERSWARM_JAX_CACHE": os.path.join(scratch, "cache")}
        command = [sys.executable, "-m", "roverswarm.cli", "reproduce", "--quick", "--jobs", str(jobs)]
        command += ["--out", os.path.join(scratch, "grid"), "--episodes", str(episodes), "--scenarios", *scenarios]
        start = time.perf_counter()
        subprocess.run(command, env=env, check=True, stdout=subprocess.DEVNULL)
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=len(usable_cpus()))
    parser.add_argument("--scenarios", nargs="+", default=["paper-2", "paper-3"])
    parser.add_argument("--episodes", type=int, default=2000)
    args = parser.parse_args()
    one = timed(1, args.scenarios, args.episodes)
    many = timed(args.jobs, args.scenarios, args.episodes)
    print(f"| grid | --jobs 1 | --jobs {args.jobs} | speed-up |")
    print("|---|---|---|---|")
    grid = f"quick, {' '.join(args.scenarios)}, {args.episodes} episodes"
    print(f"| {grid} | {one:.0f} s | {many:.0f} s | {one / many:.2f}x |")


if __name__ == "__main__":
    main()
