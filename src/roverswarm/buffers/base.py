"""The replay buffer interface: transitions, buffer state, draws, the :class:`Buffer` record
of pure functions, ring helpers, and the replay's settings (:class:`ReplayConfig`).

Shape legend: C capacity (transitions), T transitions added at once, N agents, K sub-policies
per agent (policy ensembles; 1 without), G = N * K sampling groups, B batch size per group,
O observation size, A action size.

A :class:`Buffer` is a frozen record of pure functions (Flashbax style)::

    init(example)                      -> BufferState   (example: one record, no batch axis)
    add(state, transitions [T, ...])   -> BufferState   (a ring: the oldest are overwritten)
    draw(state, key)                   -> Draw          (G independent batches of B indices, one per group)
    set_priorities(state, idx, losses) -> BufferState   (idx, losses [G, B]; no-op if uniform)
    refresh(state, due)                -> BufferState   (re-rank if ``due``; no-op if uniform)
    resized(state)                     -> BufferState   (a replay of another capacity, :func:`placed`
                                                         into this one, made whole; no-op if uniform)

and ``sample(state, key)`` -> :class:`Sample`, a draw with its transitions gathered, so the
learner never knows which kind it has. A record is any pytree of arrays with a ``policy``
field: a :class:`Transition`, or the trainer's compact :class:`~roverswarm.buffers.compact.Step`,
from which (with the episode table in :attr:`BufferState.episodes`) the observations are
rebuilt after the gather. A draw reads nothing that ``set_priorities`` writes
(written-back losses count from the next ``refresh``), so the trainer draws the batches of
all the updates between two calls of ``add`` at once, in one vectorised call; the index arithmetic
is then done once per update, not again inside the gather of every field (XLA on CPU fuses
cheap index arithmetic into each gather that reads it). Every agent draws its own batch, as in the
reference MADDPG code; a batch holds all agents' data of the sampled transitions. With
policy ensembles (``num_policies`` K > 1) every agent draws one batch per sub-policy, from
that sub-policy's partition of the replay (:mod:`roverswarm.buffers.partitions`): group
``g = i * K + k`` is agent i's sub-policy k. With K = 1 the groups are the agents.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Literal

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from roverswarm.buffers.partitions import add_partitions, init_partitions, nth_newest


@struct.dataclass
class Transition:
    """One step of the swarm (leading axes as the context says)."""

    obs: jax.Array  # [..., N, O]
    actions: jax.Array  # [..., N, A]
    rewards: jax.Array  # [..., N]
    next_obs: jax.Array  # [..., N, O], the true next observation (before any reset)
    terminated: jax.Array  # [...] bool; a truncation is not a termination
    policy: Any = None  # [..., N] int32 sub-policy each agent ran (policy ensembles only)
    rovers: Any = None  # [..., N] bool the rovers that exist (swarm sizes mixed in training only)


@struct.dataclass
class BufferState:
    data: Transition  # [C, ...]
    position: jax.Array  # [] int32, where the next transition goes
    size: jax.Array  # [] int32, transitions stored (<= C)
    extra: Any = None  # implementation state (priorities of the ranked buffer)
    partitions: Any = None  # Partitions of the policy ensembles' groups (K > 1 only)
    episodes: Any = None  # the compact replay's episode table (:mod:`roverswarm.buffers.compact`)


@struct.dataclass
class Draw:
    indices: jax.Array  # [G, B] int32
    probabilities: jax.Array  # [G, B], probability of drawing each index
    population: jax.Array  # [G] int32, transitions each group draws from (M)


@struct.dataclass
class Sample(Draw):
    batch: Transition  # [G, B, ...]: group g's batch at [g], the transitions at ``indices``


@dataclass(frozen=True)
class Buffer:
    """Replay buffer as pure functions; see the module docstring."""

    capacity: int
    batch_size: int
    num_agents: int
    num_policies: int
    init: Callable[[Transition], BufferState]
    add: Callable[[BufferState, Transition], BufferState]
    draw: Callable[[BufferState, jax.Array], Draw]
    set_priorities: Callable[[BufferState, jax.Array, jax.Array], BufferState]
    refresh: Callable[[BufferState, jax.Array], BufferState]
    resized: Callable[[BufferState], BufferState] = lambda state: state
    """One seed's replay of another capacity whose arrays were :func:`placed` into this one's,
    made whole (the ranked replay recomputes the running totals of its sampling table)."""

    def sample(self, state: BufferState, key: jax.Array) -> Sample:
        """A draw and its transitions."""
        draw = self.draw(state, key)
        return Sample(draw.indices, draw.probabilities, draw.population, gather(state, draw.indices))


def empty_state(capacity: int, example: Transition, num_policies: int, extra: Any = None) -> BufferState:
    """A buffer of ``capacity`` zeroed transitions shaped like ``example``, with partitions
    for ``num_policies`` > 1 sub-policies per agent (``example.policy`` then required)."""
    data = jax.tree.map(lambda x: jnp.zeros((capacity, *jnp.shape(x)), jnp.asarray(x).dtype), example)
    parts = None
    if num_policies > 1:
        parts = init_partitions(jnp.shape(example.policy)[-1] * num_policies, capacity)
    counter = lambda: jnp.zeros((), jnp.int32)  # noqa: E731 (separate arrays: donated state)
    return BufferState(data=data, position=counter(), size=counter(), extra=extra, partitions=parts)


def placed(saved: np.ndarray, empty: jax.Array) -> jax.Array:
    """An array of a replay of another capacity in the shape of the same array of an empty
    replay (``empty``, on the device): the part of ``saved`` that fits, at the start of every
    axis, and ``empty``'s values beyond it, made on the device (no host copy of the whole).

    Exact for a replay whose ring has not wrapped (its transitions in slots 0 .. size - 1,
    every array beyond them as an empty replay holds it) and that fits: the state a replay
    of the new capacity would hold after the same transitions, but for running totals that
    :attr:`Buffer.resized` recomputes. (A replay of ``C`` transitions capped at a run's own,
    whose run is extended, has never wrapped: see ``docs/training.md``.)"""
    if saved.shape == empty.shape:
        return jnp.asarray(saved)
    common = tuple(slice(0, min(a, b)) for a, b in zip(saved.shape, empty.shape))
    return jax.lax.dynamic_update_slice(empty, jnp.asarray(saved[common], empty.dtype), (0,) * empty.ndim)


def write(state: BufferState, transitions: Transition) -> tuple[BufferState, jax.Array]:
    """Store ``transitions`` [T, ...] at the ring position; returns the state and the T indices."""
    capacity = jax.tree.leaves(state.data)[0].shape[0]
    count = jax.tree.leaves(transitions)[0].shape[0]
    indices = (state.position + jnp.arange(count)) % capacity
    parts = state.partitions
    if parts is not None:
        num_policies = parts.ring.shape[0] // transitions.policy.shape[-1]
        parts = add_partitions(
            parts, indices, transitions.policy, state.data.policy[indices], indices < state.size, num_policies
        )
    data = jax.tree.map(lambda d, x: d.at[indices].set(x), state.data, transitions)
    return (
        state.replace(
            data=data,
            position=(state.position + count) % capacity,
            size=jnp.minimum(state.size + count, capacity),
            partitions=parts,
        ),
        indices,
    )


def population(state: BufferState, groups: int) -> jax.Array:
    """[G] transitions each of the ``groups`` draws from: its partition, or the whole replay (K = 1)."""
    if state.partitions is None:
        return jnp.broadcast_to(state.size, (groups,))
    return state.partitions.live


def nth_stored(
    state: BufferState, age: jax.Array, ring: jax.Array | None = None, head: jax.Array | None = None
) -> jax.Array:
    """Slot of the stored transition of age ``age`` (0 = newest): of one group (its ``ring``
    and ``head``, K > 1), or of the whole replay."""
    if ring is None:
        return (state.position - 1 - age) % jax.tree.leaves(state.data)[0].shape[0]
    return nth_newest(ring, head, age)


def gather(state: BufferState, indices: jax.Array) -> Transition:
    """The transitions at ``indices`` (any shape), e.g. [N, B] -> Transition [N, B, ...]."""
    return jax.tree.map(lambda d: d[indices], state.data)


def recent_indices(state: BufferState, key: jax.Array, window: int, batch_size: int) -> jax.Array:
    """[B] slots drawn uniformly from the newest ``window`` stored transitions."""
    ages = jax.random.randint(key, (batch_size,), 0, jnp.clip(state.size, 1, window))
    return nth_stored(state, ages)


def importance_weights(draw: Draw, exponent: float | jax.Array = 1.0) -> jax.Array:
    """[G, B] importance-sampling weights ``(M * P(i))^-exponent``, divided by each batch's
    maximum (Schaul et al.'s w_i; ``exponent`` 1 corrects the draw's bias fully)."""
    weights = (jnp.maximum(draw.population, 1)[:, None] * draw.probabilities) ** -exponent
    return weights / weights.max(axis=-1, keepdims=True)


def update_weights(draw: Draw, exponent: float | jax.Array | None) -> jax.Array:
    """[G, B] the weights of each group's draw in the update: importance weights (``exponent``;
    None: 1 each), and 0 for a group with no transitions, whose draw is a placeholder (its
    probabilities may be 0, which would make an importance weight inf and the update NaN)."""
    weights = jnp.ones(draw.probabilities.shape) if exponent is None else importance_weights(draw, exponent)
    return jnp.where((draw.population > 0)[:, None], weights, 0.0)


def newest_fraction(state: BufferState, indices: jax.Array, share: float) -> jax.Array:
    """[G] fraction of each group's sampled ``indices`` among the newest ``share`` of the replay."""
    capacity = jax.tree.leaves(state.data)[0].shape[0]
    age = (state.position - 1 - indices) % capacity  # 0 = the newest transition
    return (age < jnp.ceil(share * state.size)).mean(axis=-1)


@dataclass(frozen=True)
class ReplayConfig:
    """The replay of a training run: its kind, size, batches and the ranked replay's settings."""

    replay: Literal["uniform", "ranked"] = "uniform"
    """`uniform`: the reference replay; `ranked`: the paper's experience sample optimizer
    (eq. 12-15), sampling by the rank of each transition's latest TD loss."""
    batch_size: int = 256
    """Transitions per update, per agent."""
    buffer_size: int = 1_000_000
    """Replay capacity in transitions."""
    reading: Literal["paper", "schaul"] = "paper"
    """Ranked replay: how a loss rank becomes a weight. `paper`: eq. 12-13 normalised,
    (rank / M)^alpha with rank 1 the smallest loss; `schaul`: Schaul et al.'s rank-based
    prioritised replay, rank^-alpha with rank 1 the largest loss (docs/replay.md#readings)."""
    alpha: float = 1.0
    """Ranked replay: how sharply the weights follow the rank (0 = uniform; Schaul used 0.7)."""
    beta: float = 0.1
    """Ranked replay: share of samples drawn uniformly, in [0, 1] (1 = uniform)."""
    importance_weights: bool = False
    """Weight each sample's critic loss by (M * P(i))^-e, normalised to a batch maximum of 1."""
    importance_exponent: float = 1.0
    """The importance weights' exponent e at the first episode, in [0, 1]; it rises linearly
    to 1 at the run's last episode (Schaul et al. start at 0.5)."""
    refresh_every: int = 1000
    """Ranked replay: updates between re-rankings of the whole buffer (checked once per iteration)."""

    def refresh_due(self, updates_before: jax.Array, updates_after: jax.Array) -> jax.Array:
        """Whether a re-ranking falls due between two update counts (every ``refresh_every``)."""
        return updates_after // self.refresh_every > updates_before // self.refresh_every
