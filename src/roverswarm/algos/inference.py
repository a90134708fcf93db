"""Inferred policies (paper eq. 7-8): agent i's Gaussian approximations of the other agents' policies.

Agent i keeps an approximation mu_hat_i^j of every other agent j's policy: a Gaussian with
mean ``tanh(MLP(o_j))`` and a learned, state-independent log-std, fitted to j's actions in a
batch of recent transitions by minimising the negative log-likelihood minus lambda times the
entropy. :mod:`roverswarm.algos.maddpg` uses the means of the approximations' soft-updated
targets in agent i's target (eq. 8).
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import optax

from roverswarm.algos.networks import MLP, GaussianPolicy, actor_forward
from roverswarm.buffers.base import Transition
from roverswarm.env.mars import ACTION_SIZE


def gaussian_policies(hidden: Sequence[int]) -> GaussianPolicy:
    """The module of an inferred policy (a Gaussian over the action, hidden widths ``hidden``)."""
    return GaussianPolicy(tuple(hidden), ACTION_SIZE)


def approx_actions(hidden: Sequence[int], approx, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One agent's approximations [N] of every agent's policy on [..., N, O]: mean and log-std [..., N, A]."""
    return jax.vmap(gaussian_policies(hidden).apply, in_axes=(0, -2), out_axes=-2)(approx, obs)


def fit_approximations(
    hidden: Sequence[int],
    optimizer: optax.GradientTransformation,
    entropy_weight: float,
    approx,
    approx_opt,
    agent: jax.Array,
    batch: Transition,
):
    """Agent ``agent``'s step on its approximations of the other agents' policies (eq. 7):
    minimise -log N(a_j | mean_j(o_j), std_j) - lambda * entropy_j, for every j != agent.

    Returns the new approximations, their optimiser state and the mean loss over the others."""
    others = (jnp.arange(batch.actions.shape[-2]) != agent).astype(jnp.float32)

    def loss(params, obs, actions):  # one other agent's approximation: [B, O], [B, A]
        mean, log_std = gaussian_policies(hidden).apply(params, obs)
        nll = 0.5 * jnp.square((actions - mean) * jnp.exp(-log_std)) + log_std + 0.5 * jnp.log(2 * jnp.pi)
        entropy = log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e)
        return jnp.mean(nll.sum(-1)) - entropy_weight * jnp.mean(entropy.sum(-1))

    losses, grads = jax.vmap(jax.value_and_grad(loss), in_axes=(0, -2, -2))(approx, batch.obs, batch.actions)
    grads = jax.tree.map(lambda g: g * others.reshape(-1, *([1] * (g.ndim - 1))), grads)  # its own: unused, left alone
    updates, approx_opt = jax.vmap(optimizer.update)(grads, approx_opt, approx)
    approx = optax.apply_updates(approx, updates)
    return approx, approx_opt, (losses * others).sum() / jnp.maximum(others.sum(), 1.0)


def own_target_action(
    actor_net: MLP, ensemble: int, target_actors, agent: jax.Array, obs: jax.Array, policy: jax.Array | None
) -> jax.Array:
    """Agent ``agent``'s target action [B, A] (of the sub-policy it ran) on observations
    [B, N, O], reading no other agent's target actor."""
    own = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, agent * ensemble, ensemble), target_actors)
    every = jax.vmap(lambda p: actor_forward(actor_net, p, obs[:, agent])[0])(own)  # [K, B, A]
    chosen = jnp.zeros(obs.shape[0], jnp.int32) if policy is None else policy[:, agent]
    return jnp.take_along_axis(every, chosen[None, :, None], axis=0)[0]
