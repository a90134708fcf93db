"""Seconds per training chunk measured back to back: the benchmarks' method, used by
``benchmarks/train_throughput.py`` and by ``roverswarm reproduce`` for Table I's time column.

Each configuration is compiled and trained past its warm-up, its replay is filled to capacity
(as for most of a long run: random gathers from a full replay miss the caches, a nearly empty
one hides that), then the configurations' chunks alternate, so a change in the machine's load
hits them alike and chunk j of one pairs with chunk j of another.
"""

from __future__ import annotations

import statistics
import time
from functools import partial

import jax
import jax.numpy as jnp

from roverswarm.config import TrainConfig, validate
from roverswarm.learners.offpolicy import configure, init, run_buffer, run_chunk


def fill(buffer, state):
    """``state`` with copies of its newest transition added until the replay is full."""
    newest = jax.tree.map(lambda x: x[(state.position - 1) % buffer.capacity], state.data)
    copies = jax.tree.map(lambda x: jnp.broadcast_to(x, (buffer.capacity, *x.shape)), newest)
    return buffer.add(state, copies)


def chunk_seconds(configs: list[TrainConfig], chunks: int) -> list[list[float]]:
    """Wall seconds of ``chunks`` chunks (``log_every`` episodes, all seeds) of each off-policy
    config, once updates run in every iteration and the replay is full; the configs' chunks
    alternate (see the module docstring and :func:`paired_ratio`)."""
    runs = []
    for config in configs:
        params = validate(config)
        buffer, program, total = run_buffer(config, params), configure(config, params), jnp.int32(config.episodes)
        runner = init(program, params, config.seed)
        warm_chunks = -(-config.warmup // (config.log_every * params.max_steps)) + 1
        for _ in range(warm_chunks):  # compile, and fill the replay past the warm-up
            runner, metrics = run_chunk(program, params, runner, total)
        runner = runner.replace(buffer=jax.jit(jax.vmap(partial(fill, buffer)), donate_argnums=0)(runner.buffer))
        runner, metrics = run_chunk(program, params, runner, total)  # a re-ranking of the full replay
        jax.block_until_ready(metrics)
        runs.append([program, params, total, runner])
    times: list[list[float]] = [[] for _ in configs]
    for _ in range(chunks):
        for run, spent in zip(runs, times):
            program, params, total, runner = run
            start = time.perf_counter()
            run[3], metrics = run_chunk(program, params, runner, total)
            jax.block_until_ready(metrics)
            spent.append(time.perf_counter() - start)
    return times


def paired_ratio(base: list[float], other: list[float]) -> tuple[float, float, float]:
    """Median, min and max over chunks of ``other[j] / base[j]``: each pair ran back to back,
    so a ratio is robust to load that drifts over the run, and its spread shows the noise."""
    ratios = [o / b for b, o in zip(base, other)]
    return statistics.median(ratios), min(ratios), max(ratios)


def median_seconds(run, repeats: int) -> float:
    """Median wall seconds of ``repeats`` calls of ``run`` (jitted work), after one warm-up call."""
    jax.block_until_ready(run())
    spent = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run())
        spent.append(time.perf_counter() - start)
    return statistics.median(spent)
