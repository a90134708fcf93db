"""Programs kept across processes (``roverswarm.jaxcache.stored_jit``): how long a new process
takes to train its first chunk and evaluate, with every program already compiled in the
compilation cache, when the training chunk and the rollouts are jitted as they are (traced
and lowered again in every process) and when they are read from the store, measured in one
invocation, with the ratio.

Each preset runs ``train`` for one chunk (2 seeds) and ``evaluate`` (50 episodes: the
policy, random and the oracle) in a fresh process, in a fresh compilation cache of its own:
a first process fills the cache and the store, then each side is timed ``--reps`` times in
turn. Run ``python benchmarks/stored_programs.py`` on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

PRESETS = {"default": "paper-3", "swarm": "paper-3", "mappo": "paper-3", "anysize": "paper-2..10"}
"""The presets timed (each at a scenario of its own) unless ``--presets`` names others."""

CHILD = """
import json, sys, time
start = time.perf_counter()
import dataclasses, tempfile
import jax
from roverswarm.jaxcache import enable_compilation_cache
enable_compilation_cache()
from roverswarm import train
from roverswarm.config import with_options
from roverswarm.evaluate import evaluate_run
from roverswarm.presets import PRESETS
preset, scenario, stored = sys.argv[1], sys.argv[2], sys.argv[3] == "stored"
if not stored:  # each stored function jitted as it is: traced and lowered in this process
    import roverswarm.learners.base as base, roverswarm.rollout as rollout
    from roverswarm.learners import FAMILIES
    def plain(f):
        return jax.jit(f.__wrapped__, static_argnums=f.static_argnums, donate_argnums=f.donate_argnums)
    for algo, family in list(FAMILIES.items()):
        FAMILIES[algo] = dataclasses.replace(family, run_chunk=plain(family.run_chunk))
    base._build = plain(base._build)
    rollout._rollout_batch, rollout._reset_batch = plain(rollout._rollout_batch), plain(rollout._reset_batch)
config = PRESETS[preset]
config = with_options(config, {"scenario": scenario, "seeds": 2, "episodes": config.log_every, "checkpoint_every": 1})
with tempfile.TemporaryDirectory() as out:
    train(config, out=out, progress=False)
    evaluate_run(out, episodes=50, scenario=scenario.split("..")[0])
print(json.dumps(time.perf_counter() - start))
"""


def timed(preset: str, scenario: str, side: str, cache: str) -> float:
    """Seconds of one fresh process training ``preset``'s first chunk and evaluating it."""
    env = {**os.environ, "ROVERSWARM_JAX_CACHE": cache}
    done = subprocess.run(
        [sys.executable, "-c", CHILD, preset, scenario, side], env=env, check=True, capture_output=True, text=True
    )
    return float(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS))
    parser.add_argument("--reps", type=int, default=3)
    args = parser.parse_args()
    print("| preset (scenario) | jitted as it is | read from the store | ratio |")
    print("|---|---|---|---|")
    for preset in args.presets:
        scenario = PRESETS[preset]
        with tempfile.TemporaryDirectory() as cache:
            for side in ("plain", "stored"):  # fill the compilation cache and the store
                timed(preset, scenario, side, cache)
            seconds = {"plain": [], "stored": []}
            for _ in range(args.reps):
                for side in seconds:
                    seconds[side].append(timed(preset, scenario, side, cache))
        plain, stored = (statistics.median(seconds[side]) for side in ("plain", "stored"))
        print(f"| {preset} ({scenario}) | {plain:.1f} s | {stored:.1f} s | {plain / stored:.2f}x |")


if __name__ == "__main__":
    main()
