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

Then where the time of DDPG's iteration goes (``--one-batch``, the replay full): the median of
``--repeats`` calls of each part alone, jitted: collecting the iteration's episodes (20
environments of 25 steps), rebuilding the views of one draw of 256 transitions from the
compact replay, and one update of the shared networks on them (every rover of every
transition a sample: 2560 at 10 slots); an iteration runs one collection and 20 of the other two.

Run ``python benchmarks/anysize_offpolicy.py`` (``--chunks 3`` by default; ``--only chunks`` or
``--only parts`` for one table).
"""

from __future__ import annotations

import argparse
import statistics
from functools import partial

import jax
import jax.numpy as jnp

from roverswarm.algos.maddpg import update
from roverswarm.buffers import compact
from roverswarm.config import validate, with_options
from roverswarm.experiments.timing import chunk_seconds, fill, median_seconds, paired_ratio
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.learners import offpolicy
from roverswarm.presets import PRESETS

TIMED = {"seeds": 1, "episodes": 40_000, "log_every": 200, "warmup": 500}
"""The ``anysize-ddpg`` preset timed: one seed, chunks of 200 episodes, a short warm-up."""


def iteration_parts(repeats: int) -> tuple[dict[str, float], int]:
    """Milliseconds of one collection, one view rebuild of a draw and one update of the
    preset's DDPG (one seed; its replay trained past the warm-up, then filled), and the
    updates per iteration."""
    config = with_options(PRESETS["anysize-ddpg"], TIMED)
    params = validate(config)
    program, total = offpolicy.configure(config, params), jnp.int32(config.episodes)
    runner = offpolicy.init(program, params, config.seed)
    for _ in range(2):
        runner, _metrics = offpolicy.run_chunk(program, params, runner, total)
    buffer = offpolicy.run_buffer(config, params)
    learner, replay = jax.tree.map(lambda x: x[0], (runner.learner, runner.buffer))
    replay = jax.jit(partial(fill, buffer))(replay)
    key = jax.random.PRNGKey(0)
    view = offpolicy.vector_view(program.learner)
    rebuild = jax.jit(lambda r, i: compact.expand(r, i, params=params, num_envs=program.num_envs, view=view))
    indices = jax.jit(buffer.draw)(replay, key).indices[:1]
    batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (params.num_rovers, *x.shape[1:])), rebuild(replay, indices))
    collect = jax.jit(lambda ln, k: offpolicy.collect(program, params, ln, k, config.noise_std, total // 2))
    learn = jax.jit(lambda ln, b, k: update(program.learner, ln, b, jnp.ones(b.rewards.shape[:2]), key=k))
    parts = {
        "collect": lambda: collect(learner, key),
        "rebuild": lambda: rebuild(replay, indices),
        "update": lambda: learn(learner, batch, key),
    }
    milliseconds = {name: 1000 * median_seconds(run, repeats) for name, run in parts.items()}
    return milliseconds, program.num_envs * params.max_steps // program.update_every


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chunks", type=int, default=3, help="timed chunks per row")
    parser.add_argument("--repeats", type=int, default=21, help="timed calls of each part of an iteration")
    parser.add_argument("--only", choices=["chunks", "parts"], help="print one of the tables")
    args = parser.parse_args()
    enable_compilation_cache()
    if args.only in (None, "chunks"):
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
    if args.only in (None, "parts"):
        parts, updates = iteration_parts(args.repeats)
        spent = {
            "collect": parts["collect"],
            "rebuild": updates * parts["rebuild"],
            "update": updates * parts["update"],
        }
        print(f"\nDDPG, one iteration ({updates} updates), ms: " + ", ".join(f"{k} {v:.1f}" for k, v in parts.items()))
        print("shares of an iteration: " + ", ".join(f"{k} {v / sum(spent.values()):.0%}" for k, v in spent.items()))


if __name__ == "__main__":
    main()
