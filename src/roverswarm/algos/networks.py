"""Actor and critic networks (hidden ReLU layers, Flax linen) and the Gaussian policy of inferred policies.

Parameters of all agents are stacked along a leading agent axis and applied with
``jax.vmap``; every rover has the same observation and action sizes.
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


class MLP(nn.Module):
    """Dense ReLU layers of sizes ``hidden``, then a linear output of size ``out``; with
    ``layer_norm``, each hidden layer is normalised (LayerNorm) before its ReLU."""

    hidden: Sequence[int]
    out: int
    layer_norm: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.Dense(width)(x)
            if self.layer_norm:
                x = nn.LayerNorm()(x)
            x = nn.relu(x)
        return nn.Dense(self.out)(x)


def actor_forward(net: MLP, params, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Deterministic action ``tanh(pre)`` in [-1, 1] and the pre-activation ``pre``."""
    pre = net.apply(params, obs)
    return jnp.tanh(pre), pre


def critic_forward(net: MLP, params, inputs: jax.Array) -> jax.Array:
    """Q-value [...] of the concatenated critic inputs [..., D]."""
    return net.apply(params, inputs)[..., 0]


class GaussianPolicy(nn.Module):
    """A Gaussian over actions in [-1, 1]: mean ``tanh(MLP(obs))`` and a learned log-std per
    action dimension (state-independent, clipped to [-5, 1]). Returns (mean, log_std)."""

    hidden: Sequence[int]
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        mean = jnp.tanh(MLP(self.hidden, self.out)(x))
        log_std = jnp.clip(self.param("log_std", nn.initializers.zeros, (self.out,)), -5.0, 1.0)
        return mean, jnp.broadcast_to(log_std, mean.shape)
