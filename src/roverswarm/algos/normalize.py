"""Running observation normalisation (``--normalize-obs``): a mean and variance per observation
entry, pooled over rovers, updated from every collected observation and kept in the learner
state (so in checkpoints and trained policies)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

OBS_CLIP = 10.0
"""Standardised observations are clipped to [-OBS_CLIP, OBS_CLIP]."""


@struct.dataclass
class ObsNorm:
    """Running mean and variance of the observation entries (all rovers pooled)."""

    mean: jax.Array  # [O]
    var: jax.Array  # [O]
    count: jax.Array  # [] float32, observations seen


def init_obs_norm(obs_size: int) -> ObsNorm:
    """A normaliser that has seen nothing (mean 0, variance 1)."""
    return ObsNorm(mean=jnp.zeros(obs_size), var=jnp.ones(obs_size), count=jnp.zeros(()))


def update_obs_norm(norm: ObsNorm, obs: jax.Array, mask: jax.Array | None = None) -> ObsNorm:
    """``norm`` with the rows of ``obs`` [..., O] folded in, only those where ``mask`` [...]
    is 1 if given (Chan et al.'s parallel update of mean and variance)."""
    flat = obs.reshape(-1, obs.shape[-1])
    if mask is None:
        n = jnp.asarray(flat.shape[0], jnp.float32)
        mean, var = flat.mean(axis=0), flat.var(axis=0)
    else:
        weight = mask.reshape(-1, 1).astype(flat.dtype)
        n = jnp.sum(weight)
        mean = jnp.sum(flat * weight, axis=0) / jnp.maximum(n, 1.0)
        var = jnp.sum(jnp.square(flat - mean) * weight, axis=0) / jnp.maximum(n, 1.0)
    total = norm.count + n
    safe_total = jnp.maximum(total, 1.0)  # nothing seen yet and nothing new: keep the statistics
    delta = mean - norm.mean
    new_mean = norm.mean + delta * n / safe_total
    m2 = norm.var * norm.count + var * n + jnp.square(delta) * norm.count * n / safe_total
    return ObsNorm(mean=new_mean, var=jnp.where(total > 0, m2 / safe_total, norm.var), count=total)


def std(norm: ObsNorm) -> jax.Array:
    """The standard deviation [O] that standardises (variance plus 1e-8)."""
    return jnp.sqrt(norm.var + 1e-8)


def normalize(norm: ObsNorm | None, obs: jax.Array) -> jax.Array:
    """Observations [..., O] standardised by ``norm`` and clipped to +-OBS_CLIP (unchanged if None)."""
    if norm is None:
        return obs
    return jnp.clip((obs - norm.mean) / std(norm), -OBS_CLIP, OBS_CLIP)
