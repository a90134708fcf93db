"""Entity networks: permutation-invariant actors and values over the entity view.

One set of weights drives a swarm of any size: a rover's view is its own features and a
set of M tokens (the other rovers, POIs and traps), encoded by masked attention, with no
rover ids anywhere. Parameter shapes depend on none of N, P, T, M.

Shape legend
    ...  leading batch axes, typically [B, N] (a batch of swarms, N rovers each) or [N]
    N    rovers (static maximum), P POIs, T traps
    M    tokens per rover = (N - 1) + P + T: the other rovers (index order, skipping the
         rover itself), then the POIs, then the traps
    F    token features: TOKEN_FEATURES = 11, ``[dx, dy, dvx, dvy, is_rover, is_poi,
         is_trap, radius, flag, lead, claim]``: the position relative to the rover, the
         velocity relative to it for rover tokens (0 for POIs and traps)
         (:mod:`roverswarm.env.entities`)
    G    own features: OWN_FEATURES = 4, ``[vx, vy, x, y]``
    A    action size (2)
    D    ``dim``, H ``heads``, d = D / H per head, L ``layers``

Inputs of every network: ``own`` [..., G], ``tokens`` [..., M, F] and ``mask`` [..., M]
bool (True: a real entity; padded tokens may hold anything, NaN included). The networks
act on the last axes only, so a whole swarm [..., N, ...] is one call: a rover's output
depends on its own view alone.

Encoder (:class:`EntityEncoder`), with m_k the mask and LN a LayerNorm if ``layer_norm``
(else the identity)::

    x_k   = m_k ? tokens_k : 0                        padded tokens never reach the network
    u     = relu(W_u own + b_u)                       [..., D]     own embedding
    h_k   = relu(W_e x_k + b_e)                       [..., M, D]  one Dense over all types:
                                                      the one-hot makes it act per type
    L blocks of masked self-attention among the tokens, pre-LN with residuals:
        h_k <- h_k + Attn(LN(h)_k, LN(h), m)
        h_k <- h_k + W_2 relu(W_1 LN(h_k) + b_1) + b_2
    p     = Pool(u, LN(h), m)                         [..., D]     the own embedding asks
    out   = [u, p]                                    [..., 2D]

    Attn(z_j, z, m): per head c = 1..H, with q, k, v the head's slices of d entries,
        q_j = W_q z_j + b_q,  k_k = W_k z_k + b_k,  v_k = W_v z_k + b_v
        s_jk = q_j . k_k / sqrt(d)           if m_k,  else NEG = -1e9
        a_jk = softmax_k(s_jk) * m_k
        Attn = W_o [sum_k a_jk v_k]_{c = 1..H} + b_o  (the heads concatenated)
    Pool(u, z, m): the same attention with the single query u, without W_o (a Dense head
        follows): p = [sum_k a_k v_k]_{c = 1..H}.

The softmax is invariant to the order of the keys, so ``out`` is exactly invariant to any
permutation of the tokens (with their mask), up to float rounding of the sums. A masked
key gets weight exp(NEG - max) = 0 exactly when the row has a real token; with none, the
softmax is uniform and ``* m_k`` zeroes it, so ``p = 0`` (no NaN, and no gradient through
padded tokens).

Heads (MLP: Dense ReLU layers of sizes ``hidden``, LayerNorm before each ReLU if
``layer_norm``, then a linear output)::

    actor   pi(own, tokens)          = MLP_2(enc(own, tokens))       [..., 2] pre-activation:
                                       tanh for a deterministic action, or a Gaussian mean
    value   V(own, tokens)           = MLP_1(enc(own, tokens))       [...]    (MAPPO/IPPO: the
                                       rover's own view, every entity or its K nearest of each type)

Use :func:`make_entity_networks` for a :class:`EntityNetworks` record of pure functions
(init and apply). The off-policy family does not use these networks: its critic over the
nearest view is an MLP on the rover's and its nearest others' views and actions
(:mod:`roverswarm.algos.learner`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from roverswarm.algos.networks import MLP
from roverswarm.env.entities import OWN_FEATURES, TOKEN_FEATURES
from roverswarm.env.mars import ACTION_SIZE

NEG = -1e9
"""Attention logit of a padded token: exp(NEG - any real logit) is exactly 0 in float32."""


# ---------------------------------------------------------------------------------------
# Modules
# ---------------------------------------------------------------------------------------


class MaskedAttention(nn.Module):
    """Multi-head dot-product attention of queries [..., Q, D] over keys [..., M, D] with a
    key mask [..., M]; returns the heads' weighted values concatenated, [..., Q, D]
    (``project``: then a Dense D -> D). Masked keys get weight exactly 0; a query with no
    real key gets a zero vector."""

    dim: int
    heads: int
    project: bool = True

    @nn.compact
    def __call__(self, queries: jax.Array, keys: jax.Array, mask: jax.Array) -> jax.Array:
        per_head = self.dim // self.heads
        split = lambda x: x.reshape(*x.shape[:-1], self.heads, per_head)  # noqa: E731
        q = split(nn.Dense(self.dim, name="query")(queries))  # [..., Q, H, d]
        k = split(nn.Dense(self.dim, name="key")(keys))  # [..., M, H, d]
        v = split(nn.Dense(self.dim, name="value")(keys))  # [..., M, H, d]
        logits = jnp.einsum("...qhd,...khd->...hqk", q, k) * per_head**-0.5
        key_mask = mask[..., None, None, :]  # [..., 1, 1, M]
        weights = jax.nn.softmax(jnp.where(key_mask, logits, NEG), axis=-1) * key_mask
        out = jnp.einsum("...hqk,...khd->...qhd", weights, v)
        out = out.reshape(*out.shape[:-2], self.dim)
        return nn.Dense(self.dim, name="out")(out) if self.project else out


class EntityEncoder(nn.Module):
    """Own features [..., G] and tokens [..., M, F] with mask [..., M] -> [..., 2 * dim]: the
    own embedding and the attention-pooled tokens (see the module docstring)."""

    dim: int = 64
    heads: int = 4
    layers: int = 1
    layer_norm: bool = False

    def _norm(self, x: jax.Array, name: str) -> jax.Array:
        return nn.LayerNorm(name=name)(x) if self.layer_norm else x

    @nn.compact
    def __call__(self, own: jax.Array, tokens: jax.Array, mask: jax.Array) -> jax.Array:
        if self.dim % self.heads:
            raise ValueError(f"dim {self.dim} is not a multiple of heads {self.heads}")
        # zeroed, not only masked: a NaN in a padded slot would survive 0 * NaN
        tokens = jnp.where(mask[..., None], tokens, 0.0)
        u = nn.relu(nn.Dense(self.dim, name="embed_own")(own))
        h = nn.relu(nn.Dense(self.dim, name="embed_token")(tokens))
        for layer in range(self.layers):
            z = self._norm(h, f"norm_attention_{layer}")
            h = h + MaskedAttention(self.dim, self.heads, name=f"attention_{layer}")(z, z, mask)
            z = self._norm(h, f"norm_mlp_{layer}")
            z = nn.relu(nn.Dense(self.dim, name=f"mlp_hidden_{layer}")(z))
            h = h + nn.Dense(self.dim, name=f"mlp_out_{layer}")(z)
        z = self._norm(h, "norm_pool")
        pooled = MaskedAttention(self.dim, self.heads, project=False, name="pool")(u[..., None, :], z, mask)
        return jnp.concatenate([u, pooled[..., 0, :]], axis=-1)


class _EntityHeaded(nn.Module):
    """An :class:`EntityEncoder` under an MLP head: the fields of :class:`EntityConfig`."""

    dim: int = 64
    heads: int = 4
    layers: int = 1
    layer_norm: bool = False
    hidden: tuple[int, ...] = (64, 64)

    def encoder(self) -> EntityEncoder:
        """The encoder submodule (named ``encoder`` in the parameters)."""
        return EntityEncoder(self.dim, self.heads, self.layers, self.layer_norm, name="encoder")


class EntityActor(_EntityHeaded):
    """Own [..., 4], tokens [..., M, F], mask [..., M] -> the pre-activation action [..., 2]."""

    @nn.compact
    def __call__(self, own: jax.Array, tokens: jax.Array, mask: jax.Array) -> jax.Array:
        x = self.encoder()(own, tokens, mask)
        return MLP(self.hidden, ACTION_SIZE, self.layer_norm, name="head")(x)


class EntityValue(_EntityHeaded):
    """Own [..., 4], tokens [..., M, F], mask [..., M] -> the state value [...]."""

    @nn.compact
    def __call__(self, own: jax.Array, tokens: jax.Array, mask: jax.Array) -> jax.Array:
        x = self.encoder()(own, tokens, mask)
        return MLP(self.hidden, 1, self.layer_norm, name="head")(x)[..., 0]


# ---------------------------------------------------------------------------------------
# Configuration and the record of pure functions the learners call
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EntityConfig:
    """Sizes of the entity networks (actor and value alike)."""

    dim: int = 64
    """Width D of the own and token embeddings (the encoder's output is 2 * D)."""
    heads: int = 4
    """Attention heads H; ``dim`` must be a multiple of it."""
    layers: int = 1
    """Self-attention blocks among the tokens before the pooling (0: a deep-sets-like
    encoder, tokens embedded one by one and pooled)."""
    layer_norm: bool = False
    """Pre-LayerNorm in the attention blocks and before the pooling, and LayerNorm after
    every hidden layer of the heads."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths of the MLP heads on the encoding (ReLU)."""


@dataclass(frozen=True)
class EntityNetworks:
    """Entity networks as pure functions (jittable, vmappable; any leading axes)::

        init_actor(key)  / init_value(key)                              -> params
        actor(params, own [..., 4], tokens [..., M, F], mask [..., M])  -> [..., 2]
        value(params, own [..., 4], tokens [..., M, F], mask [..., M])  -> [...]

    With a swarm's view (own [..., N, 4], tokens [..., N, M, F], mask [..., N, M]) each
    call returns every rover's output ([..., N, 2] or [..., N]); M, N, P, T may differ
    from call to call with the same params."""

    config: EntityConfig
    init_actor: Callable[[jax.Array], Any]
    init_value: Callable[[jax.Array], Any]
    actor: Callable[..., jax.Array]
    value: Callable[..., jax.Array]


def make_entity_networks(config: EntityConfig = EntityConfig()) -> EntityNetworks:
    """The :class:`EntityNetworks` of ``config``. Parameters are initialised on one rover's
    view with a single token: their shapes do not depend on M (nor N, P, T)."""
    sizes = (config.dim, config.heads, config.layers, config.layer_norm, config.hidden)
    actor, value = EntityActor(*sizes), EntityValue(*sizes)
    # NumPy, not JAX, arrays: the record is cached (ppo_networks.policy_networks), and arrays
    # made while a caller traces (jax.eval_shape of the networks' sizes) would leak as tracers
    own = np.zeros((OWN_FEATURES,), np.float32)
    tokens = np.zeros((1, TOKEN_FEATURES), np.float32)
    mask = np.ones((1,), bool)
    return EntityNetworks(
        config=config,
        init_actor=lambda key: actor.init(key, own, tokens, mask),
        init_value=lambda key: value.init(key, own, tokens, mask),
        actor=actor.apply,
        value=value.apply,
    )
