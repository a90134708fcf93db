"""The benchmarks' independent references, checked in the suite (their timings are not: they
print ratios measured in one run, benchmarks/)."""

from __future__ import annotations

import importlib.util
from functools import partial
from pathlib import Path

import jax

from roverswarm.algos.ppo import init_ppo, update_minibatch
from roverswarm.config import validate, with_options
from roverswarm.env.mars import observation_size
from roverswarm.presets import PRESETS


def benchmark(name: str):
    """The module ``benchmarks/<name>.py``."""
    path = Path(__file__).parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"benchmark_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def nets(state):
    """A PPO state's networks (actor, value)."""
    return state.actor, state.critic


def test_the_anysize_update_equals_its_plain_jax_numpy_reference():
    """The anysize preset's PPO update (Flax, optax) and the benchmark's hand-written one give
    the same parameters after an update, from a state whose Adam moments are not zero."""
    bench = benchmark("anysize_update")
    config, params = bench.anysize_config(5)
    batch = bench.make_batch(jax.random.PRNGKey(5), config, params, steps=2)
    state = init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, observation_size(params))
    ours = jax.jit(partial(update_minibatch, config))
    state, _ = ours(state, batch)
    reference = jax.jit(partial(bench.ref_update, config))
    (after, parts), (after_ref, parts_ref) = ours(state, batch), reference(state, batch)
    assert bench.largest_diff(nets(after), nets(state)) > 1e-4  # the update moves the networks
    assert bench.largest_diff(nets(after), nets(after_ref)) < 1e-6
    assert bench.largest_diff(parts, parts_ref) < 1e-5


def test_the_throughput_tables_defaults_are_presets_of_one_swarm_size():
    """train_throughput.py's main table sets ``paper-N`` on each default preset and algorithm:
    every one must take it (a preset trained on a range of sizes crashed the table)."""
    presets = benchmark("train_throughput").main_presets()
    assert {"default", "reference"} <= set(presets)
    for name in presets:
        for algo in ("maddpg", "ddpg"):
            validate(with_options(PRESETS[name], dict(scenario="paper-5", algo=algo)))
