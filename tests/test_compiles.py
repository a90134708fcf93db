"""The compiled chunk is keyed on what shapes the program: a run compiles it once, and a second
run in the same process with another seed and episode count compiles nothing new, for every
learner family."""

from __future__ import annotations

import dataclasses

import jax
import pytest

from roverswarm.config import validate
from roverswarm.learners import learner_family, offpolicy, onpolicy
from roverswarm.trainer import train

COMPILE_EVENTS = ("/jax/core/compile/jaxpr_to_mlir_module_duration", "/jax/core/compile/backend_compile_duration")
"""Lowering a program and compiling it (a program found in the persistent cache is lowered, not compiled)."""


class Compilations:
    """Counts the programs JAX lowers or compiles while the context is open."""

    def __enter__(self):
        self.events: list[str] = []
        jax.monitoring.register_event_duration_secs_listener(self._record)
        return self

    def _record(self, event: str, duration: float, **kwargs) -> None:
        if event in COMPILE_EVENTS:
            self.events.append(event)

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._record)


@pytest.mark.parametrize("family", ["off-policy", "on-policy"])
def test_another_seed_and_episode_count_compile_no_new_program(family, tiny_config, tiny_ppo_config):
    off = family == "off-policy"
    config, chunk = (tiny_config, offpolicy.run_chunk) if off else (tiny_ppo_config, onpolicy.run_chunk)
    # a replay shorter than the run (4000 transitions): its length changes no shape
    config = dataclasses.replace(config, episodes=200, seeds=1)
    before = chunk._cache_size()
    with Compilations() as first:
        train(config, progress=False)
    programs = chunk._cache_size()
    assert programs == before + 1  # its two chunks: one program
    assert first.events  # the listener sees compilations (this program is new to the process)
    with Compilations() as second:
        train(dataclasses.replace(config, seed=7, episodes=300), progress=False)
    assert chunk._cache_size() == programs
    assert second.events == []
    # what does shape the program still compiles one: a seed count no other test trains (a module
    # run before in this worker may have compiled the tiny configuration's 2 seeds)
    with Compilations() as third:
        train(dataclasses.replace(config, seeds=5), progress=False)
    assert chunk._cache_size() == programs + 1 and third.events


def test_a_run_of_the_entity_network_compiles_its_chunk_once(tiny_anysize):
    """The runner a chunk returns has the types of the one it was given: a weakly typed initial
    log-std (a Python float's) once made the second chunk compile the whole program again."""
    before = onpolicy.run_chunk._cache_size()
    train(tiny_anysize, progress=False)  # two chunks
    assert onpolicy.run_chunk._cache_size() == before + 1


@pytest.mark.parametrize("family", ["off-policy", "on-policy"])
def test_a_fresh_runs_networks_and_replays_are_one_program(family, tiny_config, tiny_ppo_config):
    # built operation by operation, the networks' initialisers and the empty replays compiled a
    # program per operation and shape: dozens for a new shape (here 3 seeds)
    off = family == "off-policy"
    config = tiny_config if off else tiny_ppo_config
    config = dataclasses.replace(config, seeds=3)
    params = validate(config)
    learners = learner_family(config.learner.algo)
    program = learners.configure(config, params)
    with Compilations() as built:
        runner = learners.init(program, params, 5)
    # the one program, and the seeds' keys (a split and a fold-in vmapped over the 3 seeds)
    assert 1 <= len(built.events) // 2 <= 4, len(built.events)
    assert all(leaf.shape[0] == 3 for leaf in jax.tree.leaves(runner.learner))
    assert (runner.buffer is not None) == off
