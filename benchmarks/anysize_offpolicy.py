"""Training across sizes: seconds per 1000 episodes of one seed on ``paper-2..10``, the
off-policy family against MAPPO, and what ``--one-batch`` saves.

Rows, in one run: the ``swarm`` preset's DDPG and MATD3 (``--critic-neighbors 2``) over the
nearest view (4 of each type, shared networks) with one draw of transitions for every rover
(``--one-batch``) and with one draw per rover slot (10 at ``paper-2..10``: 10 times the views
rebuilt from the compact replay per update), and the ``anysize`` preset (MAPPO). Each time is
the median of ``--chunks`` jitted chunks of 200 episodes (times 5), timed after a first chunk
that compiles and fills the warm-up (set to 500 transitions, so that every timed chunk has all
its updates). ``vs one batch``: the row's time over the same learner's with ``--one-batch``;
``vs MAPPO``: over MAPPO's.

Run ``python benchmarks/anysize_offpolicy.py`` (``--chunks 3`` by default).
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

from roverswarm.config import PRESETS, TrainConfig, validate, with_options
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.learners import learner_family

NEAREST = {"scenario": "paper-2..10", "network": "nearest", "entity_nearest": 4, "size_curriculum": 5000}


def chunk_seconds(config: TrainConfig, chunks: int) -> float:
    """Median wall seconds per 1000 episodes of ``chunks`` chunks of ``config.log_every``
    episodes, after one more."""
    params = validate(config)
    family = learner_family(config.learner.algo)
    program = family.configure(config, params)
    runner = family.init(program, params, 0)
    total = jnp.asarray(config.episodes)
    runner, metrics = family.run_chunk(program, params, runner, total)
    jax.block_until_ready(metrics)
    times = []
    for _ in range(chunks):
        start = time.perf_counter()
        runner, metrics = family.run_chunk(program, params, runner, total)
        jax.block_until_ready(metrics)
        times.append((time.perf_counter() - start) * 1000 / config.log_every)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chunks", type=int, default=3, help="timed chunks per row")
    args = parser.parse_args()
    enable_compilation_cache()
    short = {"seeds": 1, "episodes": 100_000, "log_every": 200}
    offpolicy = {**NEAREST, **short, "warmup": 500}
    rows = {}
    for name, options in (("DDPG", {"algo": "ddpg"}), ("MATD3", {"critic_neighbors": 2})):
        for one_batch in (True, False):
            config = with_options(PRESETS["swarm"], {**offpolicy, **options, "one_batch": one_batch})
            rows[name, one_batch] = chunk_seconds(config, args.chunks)
    mappo = chunk_seconds(with_options(PRESETS["anysize"], short), args.chunks)
    print(f"{'learner':<8} {'draws':<14} {'s/1000 ep':>10} {'vs one batch':>13} {'vs MAPPO':>9}")
    for (name, one_batch), seconds in rows.items():
        draws = "one batch" if one_batch else "one per rover"
        ratio = seconds / rows[name, True]
        print(f"{name:<8} {draws:<14} {seconds:>10.1f} {ratio:>12.2f}x {seconds / mappo:>8.1f}x")
    print(f"{'MAPPO':<8} {'(anysize)':<14} {mappo:>10.1f} {'':>13} {1.0:>8.1f}x")


if __name__ == "__main__":
    main()
