"""The compact replay record: what a transition's observations are made of, not the observations.

Shape legend: N rovers, P POIs, T traps, O observation size, A action size.

A rover's observation (:func:`~roverswarm.env.mars.observe`) lists every POI, trap and other
rover relative to it, so the N observations of a step hold O = 4 + 2P + 2T + 2(N - 1) numbers
each, N * O in all, where the environment itself has only every rover's velocity and position
(4N numbers) and the episode's layout (2P + 2T). The trainer's replay stores a
:class:`CompactTransition` (the rovers before and after the step, the layout, actions,
rewards), and :func:`expand` rebuilds the :class:`~roverswarm.buffers.base.Transition` a learner
reads with the environment's own observation function, inside the jitted update, for the
sampled transitions only. Observations depend on nothing else (not on time, failures or
what was observed), so the rebuilt batch is the stored one, bit for bit
(``tests/test_compact_replay.py`` checks this against a replay of full observations, for every
replay kind). At N = 5 a transition takes 301 bytes instead of 1,341; at N = 10, 601 instead
of 5,081.

The buffers store any record with a ``policy`` field, so every replay kind (uniform, ranked,
partitioned for policy ensembles) keeps this one unchanged.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from roverswarm.buffers.base import Transition
from roverswarm.env.mars import ACTION_SIZE, EnvParams, EnvState, observe_positions


@struct.dataclass
class CompactTransition:
    """One step of the swarm, compact (leading axes as the context says)."""

    rovers: jax.Array  # [..., N, 4] every rover's velocity and position before the step
    next_rovers: jax.Array  # [..., N, 4] the same after the step (before any reset)
    layout: jax.Array  # [..., P + T, 2] the episode's POIs, then its traps
    actions: jax.Array  # [..., N, A]
    rewards: jax.Array  # [..., N]
    terminated: jax.Array  # [...] bool; a truncation is not a termination
    policy: Any = None  # [..., N] int32 sub-policy each agent ran (policy ensembles only)


def _rovers(state: EnvState) -> jax.Array:
    return jnp.concatenate([state.rover_vel, state.rover_pos], axis=-1)


def compact(
    state: EnvState,
    next_state: EnvState,
    actions: jax.Array,
    rewards: jax.Array,
    terminated: jax.Array,
    policy: jax.Array | None = None,
) -> CompactTransition:
    """The record of the step from ``state`` to ``next_state`` (any leading axes, the same on all)."""
    return CompactTransition(
        rovers=_rovers(state),
        next_rovers=_rovers(next_state),
        layout=jnp.concatenate([state.poi_pos, state.trap_pos], axis=-2),
        actions=actions,
        rewards=rewards,
        terminated=terminated,
        policy=policy,
    )


def expand(record: CompactTransition, params: EnvParams) -> Transition:
    """The :class:`Transition` of ``record`` (any leading axes): observations rebuilt by the
    environment's observation function from the rovers and the layout."""
    lead = record.rewards.shape[:-1]

    def observations(rovers: jax.Array, layout: jax.Array) -> jax.Array:
        rovers = rovers.reshape(-1, *rovers.shape[-2:])
        layout = layout.reshape(-1, *layout.shape[-2:])
        poi, trap = layout[:, : params.num_pois], layout[:, params.num_pois :]
        obs = jax.vmap(observe_positions, in_axes=(0, 0, 0, 0, None))(
            rovers[..., 2:], rovers[..., :2], poi, trap, params
        )
        return obs.reshape(*lead, *obs.shape[-2:])

    return Transition(
        obs=observations(record.rovers, record.layout),
        actions=record.actions,
        rewards=record.rewards,
        next_obs=observations(record.next_rovers, record.layout),
        terminated=record.terminated,
        policy=record.policy,
    )


def example_record(params: EnvParams, ensemble: int = 1) -> CompactTransition:
    """A zero record of one step of ``params``'s swarm (no batch axes): the replay's template;
    ``policy`` is kept with policy ensembles (``ensemble`` > 1)."""
    n, items = params.num_rovers, params.num_pois + params.num_traps
    return CompactTransition(
        rovers=jnp.zeros((n, 4)),
        next_rovers=jnp.zeros((n, 4)),
        layout=jnp.zeros((items, 2)),
        actions=jnp.zeros((n, ACTION_SIZE)),
        rewards=jnp.zeros((n,)),
        terminated=jnp.zeros((), bool),
        policy=jnp.zeros((n,), jnp.int32) if ensemble > 1 else None,
    )
