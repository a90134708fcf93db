"""Replay partitions of policy ensembles (paper eq. 10-11): D_i^(k), per agent and sub-policy.

Shape legend: C capacity, K sub-policies per agent, N agents, G = N * K sampling groups
(group ``g = i * K + k`` is agent i's sub-policy k), T transitions added at once.

Every stored transition records which sub-policy each agent ran (``Transition.policy``
[N]), so it belongs to exactly one partition per agent: D_i^(k) holds the transitions in
which agent i ran sub-policy k. The replay stays one ring of C transitions; each group keeps
its own ring of slot numbers, in the order the slots were written. The transitions of a
group still in the replay are always the newest ``live`` entries of its ring (the replay
overwrites its oldest transitions first), so drawing uniformly from a partition is drawing
an age ``r`` in ``[0, live)`` and reading the ring, and the partition's newest transitions
(those added since a re-ranking, for the ranked replay) are its smallest ages.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Partitions:
    """Which slots belong to each group (see the module docstring)."""

    ring: jax.Array  # [G, C] int32 slots of the group, at position (entries appended) mod C
    head: jax.Array  # [G] int32 entries ever appended to the group
    live: jax.Array  # [G] int32 of those, still stored in the replay (the newest ones)


def init_partitions(groups: int, capacity: int) -> Partitions:
    zeros = lambda: jnp.zeros((groups,), jnp.int32)  # noqa: E731 (separate arrays: donated state)
    return Partitions(ring=jnp.zeros((groups, capacity), jnp.int32), head=zeros(), live=zeros())


def groups_of(policy: jax.Array, num_policies: int) -> jax.Array:
    """[..., N] sub-policy per agent -> [..., N] group ``i * K + k`` per agent."""
    return policy + num_policies * jnp.arange(policy.shape[-1])


def add_partitions(
    parts: Partitions, slots: jax.Array, policy: jax.Array, replaced: jax.Array, occupied: jax.Array, num_policies: int
) -> Partitions:
    """Record T new transitions written at ``slots`` [T] with sub-policies ``policy`` [T, N];
    ``replaced`` [T, N] are the sub-policies of the transitions they overwrote, where
    ``occupied`` [T] (those leave their groups)."""
    groups, capacity = parts.ring.shape
    group = groups_of(policy, num_policies)  # [T, N]
    member = jax.nn.one_hot(group, groups, dtype=jnp.int32).sum(axis=1)  # [T, G], one group per agent
    order = jnp.cumsum(member, axis=0) - 1  # [T, G] rank of each new transition within its groups
    position = (parts.head[group] + jnp.take_along_axis(order, group, axis=1)) % capacity  # [T, N]
    ring = parts.ring.at[group, position].set(jnp.broadcast_to(slots[:, None], group.shape))
    gone = jax.nn.one_hot(groups_of(replaced, num_policies), groups, dtype=jnp.int32).sum(axis=1)  # [T, G]
    added = member.sum(axis=0)
    dropped = (gone * occupied[:, None].astype(jnp.int32)).sum(axis=0)
    return Partitions(ring=ring, head=parts.head + added, live=parts.live + added - dropped)


def nth_newest(ring: jax.Array, head: jax.Array, age: jax.Array) -> jax.Array:
    """Slot of the entry of age ``age`` (0 = newest) of one group's ``ring`` [C]."""
    return ring[(head - 1 - age) % ring.shape[0]]
