"""Environment throughput: roverswarm's JAX environment against mpe2's ``simple_spread_v3``.

What is measured, in one run on the same machine:

* roverswarm: environment steps per second of ``paper-3`` and ``paper-5`` (N rovers, N POIs,
  N traps) with E = 1, 64 and 1024 environments in parallel. One jitted call runs
  ``jax.lax.scan`` over k episodes; each episode resets the E environments (vmapped) and scans
  25 steps of ``jax.vmap(step_env)``, with random actions uniform in [-1, 1] drawn inside the
  scan. This is the training loop's structure. A second column scans the auto-resetting
  ``step`` instead, which draws a fresh layout at every step. After a compiling warm-up
  call, several calls are timed with ``block_until_ready`` and the median is kept:
  steps/s = E * 25 * k / median seconds.
* mpe2: ``simple_spread_v3.parallel_env(N=N, max_cycles=25, continuous_actions=True)``, a
  single environment, full episodes of random actions from ``action_space(agent).sample()``,
  resetting when the episode ends; steps/s = calls of ``env.step`` / seconds over ~2.5 s.
  mpe2 has no traps, so it does slightly less work per step than ``paper-N``.

The ratio is roverswarm steps/s over mpe2 steps/s. Target: at E = 1024 the ratio is at least
100 for both N = 3 and N = 5.

A second table measures any swarm size at N = 10, 16 and 32 (E = 1024, reset per episode +
``step_env``): the unpadded ``paper-N``; the padded layout of ``paper-2..N`` with every
environment's N drawn per episode (one program, mixed sizes); and the unpadded environment
with the entity view (:func:`~roverswarm.env.entities.observe_entities`) computed at every
step. Target: the padded, mixed environment costs at most 1.5x the unpadded one at its maximum N.

Run ``python benchmarks/env_throughput.py`` (``--quick`` for fewer repetitions). The output is
a Markdown table, then one ``BENCH {json}`` line per row for scripts.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import jax
from mpe2 import simple_spread_v3

from roverswarm.env import ACTION_SIZE, EnvParams, get_scenario, reset, step, step_env
from roverswarm.env.entities import observe_entities
from roverswarm.env.scenarios import draw_sizes, padded_scenario, scenario_sizes, sized
from roverswarm.jaxcache import enable_compilation_cache

ROVER_COUNTS = (3, 5)
ANY_SIZE_COUNTS = (10, 16, 32)
ANY_SIZE_TARGET = 1.5
NUM_ENVS = (1, 64, 1024)
TARGET_RATIO = 100.0
# Episodes per timed call, so that a call of few environments still takes measurable time.
EPISODES_PER_CALL = {1: 64, 64: 4, 1024: 1}


def make_rollout(
    params: EnvParams,
    num_envs: int,
    num_episodes: int,
    auto_reset: bool,
    sizes: tuple[int, ...] | None = None,
    entity_view: bool = False,
):
    """Jitted ``key -> reward_sum`` running ``num_episodes`` random-action episodes of
    ``num_envs`` environments (the reward sum keeps the work from being optimised away).

    ``auto_reset=False`` is the training loop's structure: every environment is reset at the
    start of an episode and ``step_env`` is scanned over its 25 steps (fixed-length episodes
    end together). ``auto_reset=True`` scans ``step``, which draws a fresh layout at every
    step and keeps it only where an episode ended (the generic, gymnax-style API).
    ``sizes``: ``params`` is a padded layout and each environment draws its N from ``sizes``
    at every reset (reset per episode only). ``entity_view``: every step also computes the
    entity view of every environment.
    """
    if sizes is None:
        batch_reset = jax.vmap(reset, in_axes=(0, None))
    else:

        def batch_reset(keys, params):
            counts = draw_sizes(jax.random.fold_in(keys[0], 1), sizes, keys.shape[0])
            return jax.vmap(lambda k, n: reset(k, sized(params, n)))(keys, counts)

    batch_step_env = jax.vmap(step_env, in_axes=(0, 0, None))
    batch_step = jax.vmap(step, in_axes=(0, 0, 0, None))

    def random_actions(key):
        return jax.random.uniform(key, (num_envs, params.num_rovers, ACTION_SIZE), minval=-1.0, maxval=1.0)

    def one_step(state, key):
        k_act, k_step = jax.random.split(key)
        if auto_reset:
            _, state, rewards, *_ = batch_step(jax.random.split(k_step, num_envs), state, random_actions(k_act), params)
        else:  # a padded state carries its sizes: step_env reads no count from params
            _, state, rewards, *_ = batch_step_env(state, random_actions(k_act), params)
        if entity_view:
            view = jax.vmap(observe_entities, in_axes=(0, None))(state, params)
            return state, rewards.sum() + view.tokens.sum()
        return state, rewards.sum()

    def one_episode(state, key):
        k_reset, k_steps = jax.random.split(key)
        if not auto_reset:
            _, state = batch_reset(jax.random.split(k_reset, num_envs), params)
        state, rewards = jax.lax.scan(one_step, state, jax.random.split(k_steps, params.max_steps))
        return state, rewards.sum()

    @jax.jit
    def rollout(key):
        k_reset, k_run = jax.random.split(key)
        _, state = batch_reset(jax.random.split(k_reset, num_envs), params)
        _, rewards = jax.lax.scan(one_episode, state, jax.random.split(k_run, num_episodes))
        return rewards.sum()

    return rollout


def roverswarm_steps_per_second(params: EnvParams, num_envs: int, reps: int, auto_reset: bool, **options) -> float:
    """Median environment steps per second of :func:`make_rollout` over ``reps`` timed calls."""
    episodes = EPISODES_PER_CALL[num_envs]
    rollout = make_rollout(params, num_envs, episodes, auto_reset, **options)
    key = jax.random.key(0)
    jax.block_until_ready(rollout(key))  # compile and warm up
    times = []
    for rep in range(reps):
        start = time.perf_counter()
        jax.block_until_ready(rollout(jax.random.fold_in(key, rep)))
        times.append(time.perf_counter() - start)
    return num_envs * episodes * params.max_steps / statistics.median(times)


def mpe2_steps_per_second(num_agents: int, seconds: float) -> float:
    """Steps per second of one mpe2 ``simple_spread_v3`` environment under random actions."""
    env = simple_spread_v3.parallel_env(N=num_agents, max_cycles=25, continuous_actions=True)
    env.reset(seed=0)
    for i, agent in enumerate(env.agents):
        env.action_space(agent).seed(i)
    steps = 0
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        if not env.agents:
            env.reset()
        env.step({agent: env.action_space(agent).sample() for agent in env.agents})
        steps += 1
    env.close()
    return steps / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions, shorter mpe2 timing")
    args = parser.parse_args()
    reps, mpe2_seconds = (3, 1.0) if args.quick else (10, 2.5)

    enable_compilation_cache()
    device = jax.devices()[0]
    print(f"jax {jax.__version__} | device {device} | {os.cpu_count()} CPUs | median of {reps} timed calls\n")

    rows = []
    for n in ROVER_COUNTS:
        params = get_scenario(f"paper-{n}")
        mpe2_rate = mpe2_steps_per_second(n, mpe2_seconds)
        for num_envs in NUM_ENVS:
            rate = roverswarm_steps_per_second(params, num_envs, reps, auto_reset=False)
            auto = roverswarm_steps_per_second(params, num_envs, reps, auto_reset=True)
            rows.append(
                {
                    "n": n,
                    "envs": num_envs,
                    "roverswarm_steps_per_s": rate,
                    "auto_reset_steps_per_s": auto,
                    "mpe2_steps_per_s": mpe2_rate,
                    "ratio": rate / mpe2_rate,
                }
            )

    print("| N | E | roverswarm steps/s | with per-step auto-reset | mpe2 steps/s (one env) | ratio |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['n']} | {r['envs']} | {r['roverswarm_steps_per_s']:,.0f} "
            f"| {r['auto_reset_steps_per_s']:,.0f} | {r['mpe2_steps_per_s']:,.0f} | {r['ratio']:,.0f}x |"
        )
    print("\nroverswarm runs paper-N (N rovers, N POIs, N traps); mpe2 simple_spread has no traps.")
    for n in ROVER_COUNTS:
        ratio = next(r["ratio"] for r in rows if r["n"] == n and r["envs"] == max(NUM_ENVS))
        verdict = "met" if ratio >= TARGET_RATIO else "NOT met"
        print(f"target N={n}, E={max(NUM_ENVS)}: >= {TARGET_RATIO:.0f}x mpe2: {verdict} ({ratio:,.0f}x)")
    any_size = any_size_rows(reps)
    print()
    for r in rows + any_size:
        print("BENCH " + json.dumps({k: round(v, 1) if isinstance(v, float) else v for k, v in r.items()}))


def any_size_rows(reps: int) -> list[dict]:
    """The any-size table (see the module docstring), printed; returns its rows."""
    rows, envs = [], max(NUM_ENVS)
    for n in ANY_SIZE_COUNTS:
        plain = roverswarm_steps_per_second(get_scenario(f"paper-{n}"), envs, reps, auto_reset=False)
        name = f"paper-2..{n}"
        padded = roverswarm_steps_per_second(
            padded_scenario(name), envs, reps, auto_reset=False, sizes=scenario_sizes(name)
        )
        entities = roverswarm_steps_per_second(get_scenario(f"paper-{n}"), envs, reps, auto_reset=False, entity_view=True)
        rows.append({"n": n, "envs": envs, "unpadded": plain, "padded_mixed": padded, "entity_view": entities})
    print(f"\nAny swarm size, E = {envs}, reset per episode + step_env (steps/s; cost = unpadded / other):\n")
    print("| N | unpadded paper-N | padded paper-2..N, mixed | cost | with the entity view | cost |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['n']} | {r['unpadded']:,.0f} | {r['padded_mixed']:,.0f} | {r['unpadded'] / r['padded_mixed']:.2f}x "
            f"| {r['entity_view']:,.0f} | {r['unpadded'] / r['entity_view']:.2f}x |"
        )
    for r in rows:
        cost = r["unpadded"] / r["padded_mixed"]
        verdict = "met" if cost <= ANY_SIZE_TARGET else "NOT met"
        print(f"target N={r['n']}: padded, mixed at most {ANY_SIZE_TARGET}x the unpadded cost: {verdict} ({cost:.2f}x)")
    return rows


if __name__ == "__main__":
    main()
