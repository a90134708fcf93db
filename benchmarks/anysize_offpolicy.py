"""Training across sizes: seconds per 1000 episodes of the off-policy family on ``paper-2..10``,
and what ``--one-batch`` saves.

Rows, in one run: the ``anysize-ddpg`` preset's DDPG and its MATD3 (``--algo maddpg
--critic-neighbors 2``) over the nearest view (4 of each type, shared networks, one seed, 20
environments) with one draw of transitions for every rover (``--one-batch``, the preset's)
and with one draw per rover slot (10 at
``paper-2..10``: 10 times the views rebuilt from the compact replay per update). Chunks of 200
episodes, timed as ``benchmarks/train_throughput.py`` times them
(:mod:`roverswarm.experiments.timing`: past the warm-up, the replay full, a learner's two rows'
chunks back to back); ``s/1000 ep`` is the median chunk's time times 5, ``per rover / one
batch`` the median over chunk pairs of the ratio of the two rows' times, the smallest and
largest pair in brackets. For scale: the ``anysize`` preset (MAPPO) trains 5 seeds at about 17
to 18 s per 1000 episodes on the idle machine (docs/results/any-size/README.md).

Run ``python benchmarks/anysize_offpolicy.py`` (``--chunks 3`` by default).
"""

from __future__ import annotations

import argparse
import statistics

from roverswarm.config import PRESETS, with_options
from roverswarm.experiments.timing import chunk_seconds, paired_ratio
from roverswarm.jaxcache import enable_compilation_cache

TIMED = {"seeds": 1, "episodes": 40_000, "log_every": 200, "warmup": 500}
"""The ``anysize-ddpg`` preset timed: one seed, chunks of 200 episodes, a short warm-up."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chunks", type=int, default=3, help="timed chunks per row")
    args = parser.parse_args()
    enable_compilation_cache()
    print(f"{'learner':<8} {'s/1000 ep, one batch':>21} {'one per rover':>14} {'per rover / one batch':>28}")
    for name, options in (("DDPG", {}), ("MATD3", {"algo": "maddpg", "critic_neighbors": 2})):
        configs = [
            with_options(PRESETS["anysize-ddpg"], {**TIMED, **options, "one_batch": one_batch})
            for one_batch in (True, False)
        ]
        one, each = chunk_seconds(configs, args.chunks)
        ratio, low, high = paired_ratio(one, each)
        scale = 1000 / TIMED["log_every"]
        per_1000 = [statistics.median(times) * scale for times in (one, each)]
        print(f"{name:<8} {per_1000[0]:>21.1f} {per_1000[1]:>14.1f} {ratio:>14.2f}x [{low:.2f}, {high:.2f}]")


if __name__ == "__main__":
    main()
