"""Environment throughput: roverswarm's JAX environment against mpe2 and JaxMARL, and its layout sampler.

Every number is environment steps per second of a jitted ``jax.lax.scan``: random actions drawn
inside the scan, E environments vmapped. After a compiling warm-up call, several calls are timed
with ``block_until_ready`` and the median is kept (steps/s = E * 25 * episodes per call / median
seconds); the columns of one row are timed in turn, rep by rep, so that a busy machine slows
them alike and their ratios hold. Four tables (``--only`` prints one):

* ``mpe2``: ``paper-3`` and ``paper-5`` (N rovers, N POIs, N traps) with E = 1, 64 and 1024
  against mpe2's ``simple_spread_v3.parallel_env(N=N, max_cycles=25, continuous_actions=True)``,
  a single environment stepped for ~2.5 s with actions from ``action_space(agent).sample()``,
  once per N before roverswarm's columns (not rep by rep: a plain Python loop, far from the
  ratio's target either way), its rate reused for every E.
  roverswarm's main column resets every environment at the start of an episode and scans 25
  steps of ``step_env`` (the training loop's structure); the second scans the auto-resetting
  ``step``. Ratio: roverswarm over mpe2, target at least 100 at E = 1024. mpe2 has no traps.
* ``peers``: E = 1024, N = 2, 3, 5, 8, 10, 16, 32, four columns: reset per episode + ``step_env``;
  ``step`` (auto-reset) with every episode ending at the same step; ``step`` with staggered
  episodes (each environment starts at a random time in [0, 25), so about E / 25 episodes end at
  every step); and JaxMARL 0.2.0's ``MPE_simple_spread_v3`` (N agents, N landmarks, continuous
  actions in [0, 1]^5) through its ``step``, which auto-resets by drawing a reset at every step
  and selecting it where the episode ended. Targets: ``step`` costs at most 1.5x reset per
  episode + ``step_env`` (both ``step`` columns), and is at least as fast as JaxMARL's ``step``.
  The JaxMARL column needs ``jaxmarl`` importable (``pip install 'roverswarm[jaxmarl]'``, or
  into a directory of its own on ``PYTHONPATH``: see docs/performance.md); without it the
  column is left out.
* ``sampler``: the layout sampler alone: ``reset`` of E = 1024 environments, for N = 2 .. 32,
  in microseconds per layout and per entity (3N entities), for ``paper-N`` and for ``paper-N``
  with rovers released in a start zone (the map's lower-left quarter: rovers placed in turn).
* ``anysize``: N = 10, 16 and 32 (E = 1024, reset per episode + ``step_env``): the unpadded
  ``paper-N``; the padded layout of ``paper-2..N`` with every environment's N drawn per episode
  (one program, mixed sizes); and the unpadded environment with the entity view
  (:func:`~roverswarm.env.entities.observe_entities`) computed at every step. Target: the padded,
  mixed environment costs at most 1.5x the unpadded one at its maximum N.

Run ``python benchmarks/env_throughput.py`` (``--quick`` for fewer repetitions). The output is
Markdown tables, then one ``BENCH {json}`` line per row for scripts.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import jax
import jax.numpy as jnp
from mpe2 import simple_spread_v3

from roverswarm.env import ACTION_SIZE, EnvParams, get_scenario, reset, step, step_env
from roverswarm.env.entities import observe_entities
from roverswarm.env.scenarios import draw_sizes, padded_scenario, paper_params, scenario_sizes, sized
from roverswarm.jaxcache import enable_compilation_cache

try:
    import jaxmarl
except ImportError:  # an optional peer: its column is left out
    jaxmarl = None

ROVER_COUNTS = (3, 5)
PEER_COUNTS = (2, 3, 5, 8, 10, 16, 32)
SAMPLER_COUNTS = (2, 3, 4, 5, 8, 10, 16, 24, 32)
ANY_SIZE_COUNTS = (10, 16, 32)
ANY_SIZE_TARGET = 1.5
STEP_COST_TARGET = 1.5
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
    staggered: bool = False,
):
    """Jitted ``key -> reward_sum`` running ``num_episodes`` random-action episodes of
    ``num_envs`` environments (the reward sum keeps the work from being optimised away).

    ``auto_reset=False`` is the training loop's structure: every environment is reset at the
    start of an episode and ``step_env`` is scanned over its 25 steps (fixed-length episodes
    end together). ``auto_reset=True`` scans ``step`` (the generic, gymnax-style API), which
    resets each environment whose episode ended; ``staggered`` starts each environment at a
    random time in [0, max_steps), so that episodes end at different steps.
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
        k_reset, k_run, k_time = jax.random.split(key, 3)
        _, state = batch_reset(jax.random.split(k_reset, num_envs), params)
        if staggered:
            state = state.replace(time=jax.random.randint(k_time, (num_envs,), 0, params.max_steps))
        _, rewards = jax.lax.scan(one_episode, state, jax.random.split(k_run, num_episodes))
        return rewards.sum()

    return rollout


def make_jaxmarl_rollout(num_agents: int, num_envs: int, num_episodes: int):
    """:func:`make_rollout`'s auto-reset structure for JaxMARL's ``MPE_simple_spread_v3``
    (``num_agents`` agents and landmarks, continuous actions uniform in [0, 1]^5): its vmapped
    ``step`` scanned over ``num_episodes`` x 25 steps."""
    env = jaxmarl.make(
        "MPE_simple_spread_v3", num_agents=num_agents, num_landmarks=num_agents, action_type="Continuous"
    )
    action_size = env.action_space(env.agents[0]).shape[0]
    batch_step = jax.vmap(env.step)

    def one_step(state, key):
        k_act, k_step = jax.random.split(key)
        actions = jax.random.uniform(k_act, (num_agents, num_envs, action_size))
        _, state, rewards, _, _ = batch_step(jax.random.split(k_step, num_envs), state, dict(zip(env.agents, actions)))
        return state, sum(rewards.values()).sum()

    @jax.jit
    def rollout(key):
        k_reset, k_run = jax.random.split(key)
        _, state = jax.vmap(env.reset)(jax.random.split(k_reset, num_envs))
        _, rewards = jax.lax.scan(one_step, state, jax.random.split(k_run, num_episodes * 25))
        return rewards.sum()

    return rollout


def steps_per_second(rollouts: dict[str, tuple], reps: int) -> dict[str, float]:
    """``{name: (rollout, steps per call)}`` -> ``{name: steps per second}``: each rollout is
    compiled and warmed up, then timed ``reps`` times, the rollouts in turn; the median call."""
    key = jax.random.key(0)
    for rollout, _ in rollouts.values():
        jax.block_until_ready(rollout(key))
    times = {name: [] for name in rollouts}
    for rep in range(reps):
        for name, (rollout, _) in rollouts.items():
            start = time.perf_counter()
            jax.block_until_ready(rollout(jax.random.fold_in(key, rep)))
            times[name].append(time.perf_counter() - start)
    return {name: steps / statistics.median(times[name]) for name, (_, steps) in rollouts.items()}


def roverswarm_rollout(params: EnvParams, num_envs: int, auto_reset: bool, **options) -> tuple:
    """(rollout, steps per call) for :func:`steps_per_second`."""
    episodes = EPISODES_PER_CALL[num_envs]
    rollout = make_rollout(params, num_envs, episodes, auto_reset, **options)
    return rollout, num_envs * episodes * params.max_steps


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
    parser.add_argument("--only", choices=["mpe2", "peers", "sampler", "anysize"], help="print one of the tables")
    args = parser.parse_args()
    reps, mpe2_seconds = (3, 1.0) if args.quick else (10, 2.5)

    enable_compilation_cache()
    device = jax.devices()[0]
    peer = f"jaxmarl {jaxmarl.__version__}" if jaxmarl is not None else "jaxmarl not installed"
    print(f"jax {jax.__version__} | {peer} | device {device} | {os.cpu_count()} CPUs | median of {reps} timed calls\n")
    tables = {
        "mpe2": lambda: mpe2_rows(reps, mpe2_seconds),
        "peers": lambda: peer_rows(reps),
        "sampler": lambda: sampler_rows(reps),
        "anysize": lambda: any_size_rows(reps),
    }
    rows = []
    for name, table in tables.items():
        if args.only in (None, name):
            rows += [{"table": name, **row} for row in table()]
            print()
    for r in rows:
        print("BENCH " + json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in r.items()}))


def mpe2_rows(reps: int, mpe2_seconds: float) -> list[dict]:
    """The mpe2 table (see the module docstring), printed; returns its rows."""
    rows = []
    for n in ROVER_COUNTS:
        params = get_scenario(f"paper-{n}")
        mpe2_rate = mpe2_steps_per_second(n, mpe2_seconds)
        for num_envs in NUM_ENVS:
            rates = steps_per_second(
                {
                    "reset_step_env": roverswarm_rollout(params, num_envs, auto_reset=False),
                    "step": roverswarm_rollout(params, num_envs, auto_reset=True),
                },
                reps,
            )
            rows.append(
                {"n": n, "envs": num_envs, **rates, "mpe2": mpe2_rate, "ratio": rates["reset_step_env"] / mpe2_rate}
            )

    print("| N | E | reset per episode + step_env, steps/s | step (auto-reset) | mpe2 steps/s (one env) | ratio |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['n']} | {r['envs']} | {r['reset_step_env']:,.0f} | {r['step']:,.0f} | {r['mpe2']:,.0f} "
            f"| {r['ratio']:,.0f}x |"
        )
    print("\nroverswarm runs paper-N (N rovers, N POIs, N traps); mpe2 simple_spread has no traps.")
    for n in ROVER_COUNTS:
        ratio = next(r["ratio"] for r in rows if r["n"] == n and r["envs"] == max(NUM_ENVS))
        verdict = "met" if ratio >= TARGET_RATIO else "NOT met"
        print(f"target N={n}, E={max(NUM_ENVS)}: >= {TARGET_RATIO:.0f}x mpe2: {verdict} ({ratio:,.0f}x)")
    return rows


def peer_rows(reps: int) -> list[dict]:
    """The peers table (see the module docstring), printed; returns its rows."""
    rows, envs = [], max(NUM_ENVS)
    for n in PEER_COUNTS:
        params = get_scenario(f"paper-{n}")
        rollouts = {
            "reset_step_env": roverswarm_rollout(params, envs, auto_reset=False),
            "step": roverswarm_rollout(params, envs, auto_reset=True),
            "step_staggered": roverswarm_rollout(params, envs, auto_reset=True, staggered=True),
        }
        if jaxmarl is not None:
            rollouts["jaxmarl_step"] = (make_jaxmarl_rollout(n, envs, 1), envs * params.max_steps)
        rows.append({"n": n, "envs": envs, **steps_per_second(rollouts, reps)})

    print(f"roverswarm paper-N and JaxMARL MPE_simple_spread_v3, E = {envs}, steps/s (cost: reset per episode")
    print("+ step_env over step; vs JaxMARL: step over JaxMARL's step):\n")
    print(
        "| N | reset per episode + step_env | step | cost | step, staggered | cost | JaxMARL step | step vs JaxMARL |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        jm = r.get("jaxmarl_step")
        peer = f"{jm:,.0f} | {r['step'] / jm:.2f}x" if jm else "- | -"
        print(
            f"| {r['n']} | {r['reset_step_env']:,.0f} | {r['step']:,.0f} | {r['reset_step_env'] / r['step']:.2f}x "
            f"| {r['step_staggered']:,.0f} | {r['reset_step_env'] / r['step_staggered']:.2f}x | {peer} |"
        )
    for r in rows:
        cost = max(r["reset_step_env"] / r["step"], r["reset_step_env"] / r["step_staggered"])
        verdict = "met" if cost <= STEP_COST_TARGET else "NOT met"
        line = f"target N={r['n']}: step at most {STEP_COST_TARGET}x reset + step_env: {verdict} ({cost:.2f}x)"
        if "jaxmarl_step" in r:
            ratio = r["step"] / r["jaxmarl_step"]
            line += f"; at least JaxMARL's step: {'met' if ratio >= 1 else 'NOT met'} ({ratio:.2f}x)"
        print(line)
    if jaxmarl is None:
        print("JaxMARL is not installed: its column is left out (see the module docstring).")
    return rows


def sampler_rows(reps: int) -> list[dict]:
    """The sampler table (see the module docstring), printed; returns its rows."""
    rows, envs = [], max(NUM_ENVS)

    def resets(params):
        return jax.jit(
            lambda k: jax.vmap(reset, in_axes=(0, None))(jax.random.split(k, envs), params)[1].rover_pos.sum()
        )

    for n in SAMPLER_COUNTS:
        params = paper_params(n)
        size = params.map_size
        zone = params.replace(start_zone=jnp.array([[-size, -size], [0.0, 0.0]]))
        rates = steps_per_second({"paper": (resets(params), envs), "start_zone": (resets(zone), envs)}, reps)
        rows.append({"n": n, "envs": envs, **{f"{k}_us": 1e6 / v for k, v in rates.items()}})
    print(f"The layout sampler: reset of E = {envs} environments, microseconds per layout (per entity: 3N):\n")
    print("| N | paper-N | per entity | paper-N, start zone | per entity |")
    print("|---|---|---|---|---|")
    for r in rows:
        per = 3 * r["n"]
        print(
            f"| {r['n']} | {r['paper_us']:.2f} | {r['paper_us'] / per:.3f} "
            f"| {r['start_zone_us']:.2f} | {r['start_zone_us'] / per:.3f} |"
        )
    return rows


def any_size_rows(reps: int) -> list[dict]:
    """The any-size table (see the module docstring), printed; returns its rows."""
    rows, envs = [], max(NUM_ENVS)
    for n in ANY_SIZE_COUNTS:
        name = f"paper-{n}"
        rates = steps_per_second(
            {
                "unpadded": roverswarm_rollout(get_scenario(name), envs, auto_reset=False),
                "padded_mixed": roverswarm_rollout(
                    padded_scenario(f"paper-2..{n}"), envs, auto_reset=False, sizes=scenario_sizes(f"paper-2..{n}")
                ),
                "entity_view": roverswarm_rollout(get_scenario(name), envs, auto_reset=False, entity_view=True),
            },
            reps,
        )
        rows.append({"n": n, "envs": envs, **rates})
    print(f"Any swarm size, E = {envs}, reset per episode + step_env (steps/s; cost = unpadded / other):\n")
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
