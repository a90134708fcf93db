"""The uniform replay of the reference MADDPG code (see :mod:`roverswarm.buffers.base` for the interface)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from roverswarm.buffers.base import Buffer, BufferState, Draw, Transition, empty_state, population, write
from roverswarm.buffers.partitions import nth_newest


@functools.lru_cache(maxsize=None)
def uniform_buffer(capacity: int, batch_size: int, num_agents: int, num_policies: int = 1) -> Buffer:
    """The reference MADDPG replay: every stored transition of a group's partition equally likely.

    Cached, so equal arguments give the same (hashable) record and jitted code that takes
    it as a static argument compiles once."""

    def init(example: Transition) -> BufferState:
        return empty_state(capacity, example, num_policies)

    def add(state: BufferState, transitions: Transition) -> BufferState:
        return write(state, transitions)[0]

    def draw(state: BufferState, key: jax.Array) -> Draw:
        counts = population(state, num_agents * num_policies)
        if state.partitions is None:
            indices = jax.random.randint(key, (num_agents, batch_size), 0, jnp.maximum(state.size, 1))
        else:
            ages = jax.random.randint(key, (len(counts), batch_size), 0, jnp.maximum(counts, 1)[:, None])
            indices = jax.vmap(nth_newest)(state.partitions.ring, state.partitions.head, ages)
        probabilities = jnp.ones(indices.shape) / jnp.maximum(counts, 1)[:, None]
        return Draw(indices, probabilities, counts)

    def unchanged(state: BufferState, *_) -> BufferState:
        return state

    return Buffer(capacity, batch_size, num_agents, num_policies, init, add, draw, unchanged, unchanged)
