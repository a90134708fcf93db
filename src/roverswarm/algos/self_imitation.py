"""Self-imitation (Oh et al., ICML 2018) for the on-policy family: ``--self-imitation W``.

Learning from the reward alone, a policy repeats its own best moves: each seed keeps a
*memory* of C samples (``--self-imitation-memory C``, one per rover and step) whose return
beat the value network's estimate the most, and PPO's loss gains W times an imitation of them.

Shape legend: C memory rows, B samples per iteration, m rows per self-imitation minibatch,
A action size.

After every rollout the memory and the rollout's B samples are ranked together by their
clipped advantage under the current value network and the best C kept:

    A+ = max(R - V(s), 0)        R the discounted return to the episode's end from the
                                 sample's state (GAE with lambda 1: the time limit bootstraps
                                 with the value of the last state), V the value network's
                                 estimate (both standardised with --value-norm)

Every PPO minibatch step also draws m rows from the memory, row j with probability
proportional to A+_j ^ 0.6 (the paper's prioritised replay), m = B / (minibatches x epochs),
so one iteration reads B memory rows, and adds to PPO's loss

    W * ( mean_j[ -log pi(a_j | s_j) * sg(A+_j) ] + 0.01 * 0.5 * mean_j[ (A+_j)^2 ] )

with the sample weights of PPO's loss (--balance-sizes), the advantages recomputed under the
current value network, and the policy's log-std held fixed in it (``sg``: no gradient), so that
imitating its own samples narrows the policy only through the mean, not its exploration.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

PRIORITY_EXPONENT = 0.6
"""Rows are drawn with probability proportional to A+ to this power (the paper's alpha)."""
VALUE_WEIGHT = 0.01
"""Weight of the value part of the self-imitation loss (the paper's beta)."""


@struct.dataclass
class Memory:
    """One seed's remembered samples, leading [C] (or a minibatch's [m])."""

    actor_inputs: Any  # [C, ...] what the actor saw
    critic_inputs: Any  # [C, ...] what the value network saw
    actions: jax.Array  # [C, A] the unclipped actions taken
    returns: jax.Array  # [C] discounted returns to the episode's end (raw units)
    weights: jax.Array  # [C] PPO's sample weights; 0 for an empty row


def empty_memory(capacity: int, actor_row: Any, critic_row: Any, action_size: int) -> Memory:
    """A memory of ``capacity`` empty rows; ``actor_row`` and ``critic_row`` are the shapes
    (``jax.ShapeDtypeStruct`` trees) of one sample's inputs."""
    rows = lambda tree: jax.tree.map(lambda s: jnp.zeros((capacity, *s.shape), s.dtype), tree)  # noqa: E731
    return Memory(
        actor_inputs=rows(actor_row),
        critic_inputs=rows(critic_row),
        actions=jnp.zeros((capacity, action_size)),
        returns=jnp.zeros((capacity,)),
        weights=jnp.zeros((capacity,)),
    )


def clipped_advantages(memory: Memory, values: jax.Array, standardise) -> jax.Array:
    """A+ of every row [C]: max(standardise(R) - V, 0) with ``values`` V [C] in the value
    network's units; 0 for empty rows."""
    return jnp.where(memory.weights > 0, jnp.maximum(standardise(memory.returns) - values, 0.0), 0.0)


def remember(memory: Memory, samples: Memory, advantages_of) -> tuple[Memory, jax.Array]:
    """The best C of the memory's rows followed by ``samples``' rows, ranked by
    ``advantages_of(rows)`` (their A+ [C + B]): the new memory and its rows' A+ [C]."""
    pool = jax.tree.map(lambda old, new: jnp.concatenate([old, new]), memory, samples)
    best, keep = jax.lax.top_k(advantages_of(pool), memory.weights.shape[0])
    return jax.tree.map(lambda x: x[keep], pool), best


def draw(key: jax.Array, memory: Memory, advantages: jax.Array, shape: tuple[int, ...]) -> Memory:
    """Minibatches of rows [*shape, ...], each row drawn with probability proportional to
    ``advantages`` [C] ** 0.6 (uniformly while every row's A+ is 0), by inverting the
    cumulative sum (Gumbel noise for every row and draw would cost C times the draws)."""
    priority = jnp.power(advantages, PRIORITY_EXPONENT)
    priority = jnp.where(jnp.sum(priority) > 0, priority, 1.0)
    cumulative = jnp.cumsum(priority)
    rows = jnp.searchsorted(cumulative, jax.random.uniform(key, shape) * cumulative[-1], side="right")
    return jax.tree.map(lambda x: x[jnp.minimum(rows, advantages.shape[0] - 1)], memory)


def loss(log_probs: jax.Array, values: jax.Array, memory: Memory, standardise) -> tuple[jax.Array, jax.Array]:
    """The self-imitation loss of a minibatch of rows (see the module docstring), before the
    weight W: ``log_probs`` [m] of the rows' actions under the current policy (its log-std held
    fixed), ``values`` [m] under the current value network. Returns (loss, mean A+)."""
    advantages = clipped_advantages(memory, values, standardise)
    weight = jnp.maximum(jnp.sum(memory.weights), 1e-8)
    policy = jnp.sum(-log_probs * jax.lax.stop_gradient(advantages) * memory.weights) / weight
    value = 0.5 * jnp.sum(jnp.square(advantages) * memory.weights) / weight
    return policy + VALUE_WEIGHT * value, jnp.sum(advantages * memory.weights) / weight
