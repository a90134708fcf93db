"""Training throughput: seconds per 1000 episodes, and how much of it is the update itself.

For N = 2..5 (``paper-N``), both algorithms and the off-policy presets of one swarm size
(``default``: one update per 25 environment steps on batches of 256, 2x128 networks;
``reference``: one update per 100 steps on batches of 1024, 2x64 networks; ``swarm``: shared
networks, twin critics; ``anysize-ddpg``, which trains on a range of sizes, has
``anysize_offpolicy.py``), one seed, 20 parallel environments, replay 1e6, in one run:

* ``s/1000 ep``: wall seconds of one jitted training chunk of 1000 episodes (environment,
  replay writes and samples, updates), timed after the warm-up so every chunk has all its
  updates, and with the replay filled to its capacity, as for most of a 60,000-episode run
  (random gathers from 1e6 transitions miss the caches; a nearly empty replay hides that);
  the median of ``--chunks`` chunks (uniform and ranked chunks alternate).
* ``update``: the bare jitted update of all agents on a fixed batch (a chunk's worth of
  them in one ``lax.scan``), i.e. the floor the chunk cannot go below.
* ``overhead``: ``1 - updates * update / chunk``, the share of everything else. Target <= 25%.
* ``ranked``: seconds per 1000 episodes with the experience sample optimizer
  (``--replay ranked``, the preset's alpha, beta and refresh period) and its time relative
  to the uniform replay's: the median over chunks of each back-to-back pair's ratio, with
  the smallest and largest pair in brackets. Target: at most +5% (the paper reports +1.8%
  to +2.7%). Chunks vary by several percent from one to the next, so this ratio is coarse;
* ``ranked replay work``: the same cost from its parts, timed alone on a full replay, as
  the trainer does them: the extra time per update of the ranked replay's draws (all the
  updates of an iteration at once), gathers and loss write-back over the uniform replay's,
  times the updates of a chunk, plus its re-rankings (one per ``--refresh-every`` updates),
  over the uniform chunk's time.
* ``vs reference``: the reference implementations' per-agent Python loop runs at about 90 s
  per 1000 episodes for N = 3 on this machine (one environment, one update per 100 steps,
  the reference preset); the ratio 90 / ours for N = 3 and that preset. Target >= 10x.

A second table gives the cost of the rest of the paper's MADDPG, at the default preset,
with uniform replay, relative to plain MADDPG in the same run (chunks alternate):
``--ensemble 3`` (three sub-policies per agent: three actor steps and a critic step on three
batches per update) and ``--infer-policies`` (each agent fits the others' policies before
each critic step).

A third table gives the on-policy learners (``--preset mappo`` and ``ippo``: 100 parallel
environments, 5 epochs x 4 minibatches per iteration): seconds per 1000 episodes (median of
``--chunks`` chunks), environment steps per second of training (steps of one environment,
all rovers moving at once), and the share of a chunk spent in the rollouts alone (the
chunk's episodes with the stochastic policy, timed alone as one jitted scan); the rest is
GAE and the updates.

Run ``python benchmarks/train_throughput.py`` (``--quick``: N = 3 only; ``--only main``,
``--only extensions`` or ``--only ppo`` for one table; ``--preset default`` or ``--algo maddpg`` for part of the
main table).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from functools import partial

import jax
import jax.numpy as jnp

from roverswarm.algos.learner import init_learner
from roverswarm.algos.maddpg import update
from roverswarm.buffers import compact
from roverswarm.buffers.base import Transition
from roverswarm.config import TrainConfig, validate, with_options
from roverswarm.env.mars import ACTION_SIZE, observation_size
from roverswarm.episodes import sizes_of
from roverswarm.experiments.timing import chunk_seconds, fill, median_seconds, paired_ratio
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.learners import FAMILIES, onpolicy
from roverswarm.learners.offpolicy import run_buffer
from roverswarm.presets import PRESETS

REFERENCE_SECONDS_N3 = 90.0


def update_seconds(config: TrainConfig, count: int) -> float:
    """Seconds of one bare update of all agents (median over repeats of ``count`` scanned updates)."""
    params = validate(config)
    n, o, b = params.num_rovers, observation_size(params), config.buffer.batch_size
    key = jax.random.PRNGKey(0)
    learner = init_learner(key, config.learner, n, o)
    batch = Transition(
        obs=jax.random.normal(key, (n, b, n, o)),
        actions=jax.random.uniform(key, (n, b, n, ACTION_SIZE), minval=-1, maxval=1),
        rewards=jax.random.normal(key, (n, b, n)),
        next_obs=jax.random.normal(key, (n, b, n, o)),
        terminated=jnp.zeros((n, b), bool),
    )

    @jax.jit
    def many(learner):
        return jax.lax.scan(
            lambda s, _: (update(config.learner, s, batch, key=key)[0], None), learner, None, length=count
        )[0]

    return median_seconds(lambda: many(learner), repeats=3) / count


def replay_seconds(config: TrainConfig, iterations: int = 20) -> tuple[float, float]:
    """The replay's own work, timed alone as the trainer does it: seconds per update of
    drawing the batches of an iteration's updates at once, then gathering each and writing
    its losses back (a scan of ``iterations``), and seconds of one re-ranking (zero for
    uniform replay). On a full replay with random losses, 5% of it added since the last
    re-ranking."""
    params = validate(config)
    buffer = run_buffer(config, params)
    updates = config.num_envs * params.max_steps // config.update_every  # per iteration
    state = jax.jit(partial(fill, buffer))(compact.init(buffer, params, config.num_envs))
    if state.extra is not None:
        state = state.replace(
            extra=state.extra.replace(loss=jax.random.uniform(jax.random.PRNGKey(1), state.extra.loss.shape))
        )
        state = jax.jit(buffer.refresh)(state, jnp.bool_(True))
        state = jax.jit(buffer.add)(state, jax.tree.map(lambda x: x[: config.buffer.buffer_size // 20], state.data))

    @partial(jax.jit, donate_argnums=0)  # donated, as in training: the replay is never copied
    def replay_work(state, key):
        def iteration(state, k):
            draws = jax.vmap(buffer.draw, in_axes=(None, 0))(state, jax.random.split(k, updates))

            def one(state, draw):
                batch = compact.expand(state, draw.indices, params, config.num_envs)  # as the trainer reads it
                total = sum(x.sum() for x in jax.tree.leaves(batch))
                return buffer.set_priorities(state, draw.indices, jnp.ones(draw.indices.shape)), total

            return jax.lax.scan(one, state, draws)

        state, totals = jax.lax.scan(iteration, state, jax.random.split(key, iterations))
        return state, totals.sum()

    @jax.jit
    def rerank(state):  # the new rank tables only, so the replay is not copied to an output
        return buffer.refresh(state, jnp.bool_(True)).extra

    def work():
        nonlocal state
        state, total = replay_work(state, jax.random.PRNGKey(0))
        return total

    reranking = 0.0 if state.extra is None else median_seconds(lambda: rerank(state), repeats=7)
    return median_seconds(work, repeats=7) / (iterations * updates), reranking


def main_presets() -> list[str]:
    """The presets of the main table: the off-policy ones of one swarm size (``anysize-ddpg``
    trains on a range of sizes: ``anysize_offpolicy.py``)."""
    return [name for name, p in PRESETS.items() if FAMILIES[p.learner.algo].replay and sizes_of(p) is None]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N = 3 only")
    parser.add_argument("--rovers", type=int, nargs="+", default=[2, 3, 4, 5], help="swarm sizes N to measure")
    parser.add_argument("--chunks", type=int, default=3, help="timed chunks per configuration")
    parser.add_argument("--only", choices=["main", "extensions", "ppo"], help="print one of the three tables")
    replay_presets = main_presets()
    parser.add_argument(
        "--preset", choices=replay_presets, nargs="+", default=replay_presets, help="presets of the main table"
    )
    parser.add_argument(
        "--algo", choices=["maddpg", "ddpg"], nargs="+", default=["maddpg", "ddpg"], help="algorithms of the main table"
    )
    args = parser.parse_args()
    enable_compilation_cache()
    rover_counts = (3,) if args.quick else tuple(args.rovers)
    chunks = args.chunks
    print(f"jax {jax.__version__} | {jax.devices()[0]} | 1 seed, 20 envs, replay 1e6\n")
    if args.only in (None, "main"):
        main_table(rover_counts, chunks, args.preset, args.algo)
    if args.only in (None, "extensions"):
        extensions_table(rover_counts, chunks)
    if args.only in (None, "ppo"):
        ppo_table(rover_counts, chunks)


def main_table(rover_counts: tuple[int, ...], chunks: int, presets: list[str], algos: list[str]) -> None:
    print(
        "| N | algo | preset | s/1000 ep | update (ms) | updates/1000 ep | overhead | ranked s/1000 ep "
        "| ranked vs uniform | ranked replay work per update (ms) | re-ranking (ms) | ranked replay work "
        "| vs reference |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n in rover_counts:
        for algo in algos:
            for preset in presets:
                base = PRESETS[preset]
                config = with_options(base, dict(scenario=f"paper-{n}", algo=algo))
                params = validate(config)
                updates = config.log_every * params.max_steps // config.update_every
                ranked_config = with_options(config, dict(replay="ranked"))
                uniform, ranked = chunk_seconds([config, ranked_config], chunks)
                chunk = statistics.median(uniform)
                ratio, low, high = paired_ratio(uniform, ranked)
                per_update, _ = replay_seconds(config)
                ranked_update, rerank = replay_seconds(ranked_config)
                extra = (ranked_update - per_update) * updates + rerank * updates / config.buffer.refresh_every
                bare = update_seconds(config, updates)
                overhead = 1.0 - updates * bare / chunk
                versus = f"{REFERENCE_SECONDS_N3 / chunk:.0f}x" if n == 3 and preset == "reference" else "-"
                print(
                    f"| {n} | {algo} | {preset} | {chunk:.2f} | {bare * 1e3:.2f} | {updates} | {overhead:.0%} "
                    f"| {statistics.median(ranked):.2f} | {ratio - 1:+.1%} ({low - 1:+.1%} to {high - 1:+.1%}) "
                    f"| {(ranked_update - per_update) * 1e3:.3f} | {rerank * 1e3:.0f} | {extra / chunk:+.1%} "
                    f"| {versus} |",
                    flush=True,
                )


def extensions_table(rover_counts: tuple[int, ...], chunks: int) -> None:
    print("\n| N | plain MADDPG s/1000 ep | --ensemble 3 | vs plain | --infer-policies | vs plain |")
    print("|---|---|---|---|---|---|")
    for n in rover_counts:
        plain = dataclasses.replace(PRESETS["default"], scenario=f"paper-{n}")
        options = [dict(ensemble=3), dict(infer_policies=True)]
        configs = [plain] + [with_options(plain, o) for o in options]
        base, ensemble, infer = chunk_seconds(configs, chunks)
        cells = [f"{statistics.median(times):.2f} | {paired_ratio(base, times)[0]:.2f}x" for times in (ensemble, infer)]
        print(f"| {n} | {statistics.median(base):.2f} | {' | '.join(cells)} |", flush=True)


def ppo_table(rover_counts: tuple[int, ...], chunks: int) -> None:
    print("\n| N | algo | s/1000 ep | env steps/s | rollouts | GAE and updates |")
    print("|---|---|---|---|---|---|")
    for n in rover_counts:
        for algo in [name for name, family in FAMILIES.items() if not family.replay]:
            config = with_options(PRESETS[algo], dict(scenario=f"paper-{n}"))
            params = validate(config)
            program, total = onpolicy.configure(config, params), jnp.int32(config.episodes)
            runner = onpolicy.init(program, params, config.seed)
            runner, metrics = onpolicy.run_chunk(program, params, runner, total)  # compile
            jax.block_until_ready(metrics)
            spent = []
            for _ in range(chunks):
                start = time.perf_counter()
                runner, metrics = onpolicy.run_chunk(program, params, runner, total)
                jax.block_until_ready(metrics)
                spent.append(time.perf_counter() - start)
            chunk = statistics.median(spent)
            actor = jax.tree.map(lambda x: x[0], runner.learner.actor)
            iterations = config.log_every // config.num_envs

            @jax.jit
            def rollouts(key):
                def one(total, k):
                    return total + onpolicy.collect(config, params, actor, k)[1]["episode_reward"].sum(), None

                return jax.lax.scan(one, jnp.zeros(()), jax.random.split(key, iterations))[0]

            share = median_seconds(lambda: rollouts(jax.random.PRNGKey(0)), repeats=chunks) / chunk
            steps = config.log_every * params.max_steps / chunk
            print(f"| {n} | {algo} | {chunk:.2f} | {steps:,.0f} | {share:.0%} | {1 - share:.0%} |", flush=True)


if __name__ == "__main__":
    main()
