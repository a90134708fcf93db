"""The replay buffer interface and its uniform implementation.

Shape legend: C capacity (transitions), K transitions added at once, N agents, B batch size
per agent, O observation size, A action size.

A :class:`Buffer` is a frozen record of pure functions (Flashbax style)::

    init(example)                      -> BufferState   (example: one Transition, no batch axis)
    add(state, transitions [K, ...])   -> BufferState   (a ring: the oldest are overwritten)
    sample(state, key)                 -> Sample        (N independent batches of B, one per agent)
    set_priorities(state, idx, losses) -> BufferState   (idx, losses [N, B]; no-op if uniform)
    refresh(state, due)                -> BufferState   (re-rank if ``due``; no-op if uniform)

so the learner never knows which kind it has. Every agent draws its own batch, as in the
reference MADDPG code; a batch holds all agents' data of the sampled transitions.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Transition:
    """One step of the swarm (leading axes as the context says)."""

    obs: jax.Array  # [..., N, O]
    actions: jax.Array  # [..., N, A]
    rewards: jax.Array  # [..., N]
    next_obs: jax.Array  # [..., N, O], the true next observation (before any reset)
    terminated: jax.Array  # [...] bool; a truncation is not a termination


@struct.dataclass
class BufferState:
    data: Transition  # [C, ...]
    position: jax.Array  # [] int32, where the next transition goes
    size: jax.Array  # [] int32, transitions stored (<= C)
    extra: Any = None  # implementation state (priorities of the ranked buffer)


@struct.dataclass
class Sample:
    batch: Transition  # [N, B, ...]: agent i's batch at [i]
    indices: jax.Array  # [N, B] int32
    probabilities: jax.Array  # [N, B], probability of drawing each index


@dataclass(frozen=True)
class Buffer:
    """Replay buffer as pure functions; see the module docstring."""

    capacity: int
    batch_size: int
    num_agents: int
    init: Callable[[Transition], BufferState]
    add: Callable[[BufferState, Transition], BufferState]
    sample: Callable[[BufferState, jax.Array], Sample]
    set_priorities: Callable[[BufferState, jax.Array, jax.Array], BufferState]
    refresh: Callable[[BufferState, jax.Array], BufferState]


def empty_state(capacity: int, example: Transition, extra: Any = None) -> BufferState:
    """A buffer of ``capacity`` zeroed transitions shaped like ``example``."""
    data = jax.tree.map(lambda x: jnp.zeros((capacity, *jnp.shape(x)), jnp.asarray(x).dtype), example)
    return BufferState(data=data, position=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32), extra=extra)


def write(state: BufferState, transitions: Transition) -> tuple[BufferState, jax.Array]:
    """Store ``transitions`` [K, ...] at the ring position; returns the state and the K indices."""
    capacity = jax.tree.leaves(state.data)[0].shape[0]
    count = jax.tree.leaves(transitions)[0].shape[0]
    indices = (state.position + jnp.arange(count)) % capacity
    data = jax.tree.map(lambda d, x: d.at[indices].set(x), state.data, transitions)
    return (
        state.replace(
            data=data,
            position=(state.position + count) % capacity,
            size=jnp.minimum(state.size + count, capacity),
        ),
        indices,
    )


def gather(state: BufferState, indices: jax.Array) -> Transition:
    """The transitions at ``indices`` (any shape), e.g. [N, B] -> Transition [N, B, ...]."""
    return jax.tree.map(lambda d: d[indices], state.data)


def importance_weights(sample: Sample, size: jax.Array) -> jax.Array:
    """[N, B] importance-sampling weights ``1 / (M * P(i))``, divided by each batch's maximum."""
    weights = 1.0 / (jnp.maximum(size, 1) * sample.probabilities)
    return weights / weights.max(axis=-1, keepdims=True)


def newest_fraction(state: BufferState, indices: jax.Array, share: float) -> jax.Array:
    """[N] fraction of each agent's sampled ``indices`` among the newest ``share`` of the replay."""
    capacity = jax.tree.leaves(state.data)[0].shape[0]
    age = (state.position - 1 - indices) % capacity  # 0 = the newest transition
    return (age < jnp.ceil(share * state.size)).mean(axis=-1)


@functools.lru_cache(maxsize=None)
def uniform_buffer(capacity: int, batch_size: int, num_agents: int) -> Buffer:
    """The reference MADDPG replay: every stored transition equally likely.

    Cached, so equal arguments give the same (hashable) record and jitted code that takes
    it as a static argument compiles once."""

    def init(example: Transition) -> BufferState:
        return empty_state(capacity, example)

    def add(state: BufferState, transitions: Transition) -> BufferState:
        return write(state, transitions)[0]

    def sample(state: BufferState, key: jax.Array) -> Sample:
        indices = jax.random.randint(key, (num_agents, batch_size), 0, jnp.maximum(state.size, 1))
        probabilities = jnp.full(indices.shape, 1.0) / jnp.maximum(state.size, 1)
        return Sample(batch=gather(state, indices), indices=indices, probabilities=probabilities)

    def unchanged(state: BufferState, *_) -> BufferState:
        return state

    return Buffer(capacity, batch_size, num_agents, init, add, sample, unchanged, unchanged)
