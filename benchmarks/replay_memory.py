"""The compact replay against a replay of full observations: bytes per transition and sampling speed.

For each swarm size N (``paper-N``), both replays are filled with the same stream of episodes
(random actions, 20 environments per add, as the trainer adds them) to ``--capacity``
transitions, then timed in alternation on the trainer's sampling work of ``--updates``
updates (the default preset's batches of 256 per agent, uniform replay): drawing the
batches, reading them (the compact replay rebuilds the observations and next observations
from the rovers' states and the episode table) and summing them, in one jitted scan. Printed:

* bytes per transition: what each replay stores (transitions and, for the compact one, its
  share of the episode table) over its capacity; targets: at most 15% of the full replay's
  at N = 5 and 10% at N = 10;
* sampling: milliseconds per update of each, and compact / full as the median over rounds of
  each back-to-back pair's ratio (min to max in brackets); target: at most 1.

Run ``python benchmarks/replay_memory.py`` (``--rovers 5 10 --capacity 1000000`` by default:
the full replay of N = 10 takes 5 GB).
"""

from __future__ import annotations

import argparse
import statistics
import time
from functools import partial

import jax
import jax.numpy as jnp

from roverswarm.buffers import ReplayConfig, Transition, compact, make_buffer
from roverswarm.buffers.base import gather
from roverswarm.env.mars import ACTION_SIZE, observe, reset, step_env
from roverswarm.env.scenarios import get_scenario
from roverswarm.jaxcache import enable_compilation_cache

ENVS = 20
BATCH = 256


def filled(buffer, params, capacity: int):
    """(full replay, compact replay), both holding the same ``capacity`` transitions."""
    adds = -(-capacity // (ENVS * params.max_steps))

    def episodes(key):
        k_reset, k_act = jax.random.split(key)
        _, start = jax.vmap(reset, in_axes=(0, None))(jax.random.split(k_reset, ENVS), params)

        def body(state, k):
            actions = jax.random.uniform(k, (ENVS, params.num_rovers, ACTION_SIZE), minval=-1, maxval=1)
            _, after, rewards, terminated, _, _ = jax.vmap(step_env, in_axes=(0, 0, None))(state, actions, params)
            see = jax.vmap(observe, in_axes=(0, None))
            full = Transition(see(state, params), actions, rewards, see(after, params), terminated)
            return after, (full, compact.rovers_of(state))

        last, (full, rovers) = jax.lax.scan(body, start, jax.random.split(k_act, params.max_steps))
        collected = compact.Collected(
            rovers, full.actions, full.rewards, full.terminated, compact.layout_of(start), compact.rovers_of(last)
        )
        return jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), full), collected

    @partial(jax.jit, donate_argnums=(0, 1))
    def fill(full_state, compact_state):
        def one(states, key):
            full, collected = episodes(key)
            return (buffer.add(states[0], full), compact.add(buffer, states[1], collected)), None

        return jax.lax.scan(one, (full_state, compact_state), jax.random.split(jax.random.PRNGKey(0), adds))[0]

    example = jax.eval_shape(episodes, jax.random.PRNGKey(0))[0]  # one add's transitions
    full_state = buffer.init(jax.tree.map(lambda s: jnp.zeros(s.shape[1:], s.dtype), example))
    return fill(full_state, compact.init(buffer, params, ENVS))


def sampling(buffer, read, updates: int):
    """A jitted function of (replay, key): ``updates`` draws, each read by ``read`` and summed."""

    @jax.jit
    def run(state, key):
        def one(total, k):
            draw = buffer.draw(state, k)
            return total + sum(x.sum() for x in jax.tree.leaves(read(state, draw.indices))), None

        return jax.lax.scan(one, jnp.zeros(()), jax.random.split(key, updates))[0]

    return run


def seconds(fn, *args) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rovers", type=int, nargs="+", default=[5, 10], help="swarm sizes N (paper-N)")
    parser.add_argument("--capacity", type=int, default=1_000_000, help="transitions in each replay")
    parser.add_argument("--updates", type=int, default=200, help="updates per timed call")
    parser.add_argument("--rounds", type=int, default=7, help="timed pairs of calls")
    args = parser.parse_args()
    enable_compilation_cache()
    print(f"jax {jax.__version__} | {jax.devices()[0]} | capacity {args.capacity:,} | batch {BATCH} per agent\n")
    print("| N | full, bytes/transition | compact | compact / full | full, ms/update | compact | compact / full |")
    print("|---|---|---|---|---|---|---|")
    for n in args.rovers:
        params = get_scenario(f"paper-{n}")
        buffer = make_buffer(ReplayConfig(buffer_size=args.capacity, batch_size=BATCH), n)
        full_state, compact_state = filled(buffer, params, args.capacity)
        full_bytes = compact.nbytes(full_state.data) / buffer.capacity
        compact_bytes = compact.nbytes((compact_state.data, compact_state.episodes)) / buffer.capacity
        read_compact = partial(compact.expand, params=params, num_envs=ENVS)
        runs = [(sampling(buffer, gather, args.updates), full_state)]
        runs.append((sampling(buffer, read_compact, args.updates), compact_state))
        for fn, state in runs:  # compile
            seconds(fn, state, jax.random.PRNGKey(0))
        times = [[], []]
        for r in range(args.rounds):
            for (fn, state), spent in zip(runs, times):
                spent.append(seconds(fn, state, jax.random.PRNGKey(r + 1)) / args.updates)
        ratios = [c / f for f, c in zip(*times)]
        full_ms, compact_ms = (statistics.median(t) * 1e3 for t in times)
        print(
            f"| {n} | {full_bytes:,.0f} | {compact_bytes:,.0f} | {compact_bytes / full_bytes:.1%} "
            f"| {full_ms:.3f} | {compact_ms:.3f} | {statistics.median(ratios):.2f}x "
            f"({min(ratios):.2f} to {max(ratios):.2f}) |",
            flush=True,
        )
        del full_state, compact_state, runs


if __name__ == "__main__":
    main()
