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


def update_obs_norm(norm: ObsNorm, obs: jax.Array) -> ObsNorm:
    """``norm`` with observations [..., O] folded in (Chan et al.'s parallel update of mean and variance)."""
    flat = obs.reshape(-1, obs.shape[-1])
    n = jnp.asarray(flat.shape[0], jnp.float32)
    mean, var = flat.mean(axis=0), flat.var(axis=0)
    total = norm.count + n
    delta = mean - norm.mean
    new_mean = norm.mean + delta * n / total
    m2 = norm.var * norm.count + var * n + jnp.square(delta) * norm.count * n / total
    return ObsNorm(mean=new_mean, var=m2 / total, count=total)


def normalize(norm: ObsNorm | None, obs: jax.Array) -> jax.Array:
    """Observations [..., O] standardised by ``norm`` and clipped to +-OBS_CLIP (unchanged if None)."""
    if norm is None:
        return obs
    return jnp.clip((obs - norm.mean) / jnp.sqrt(norm.var + 1e-8), -OBS_CLIP, OBS_CLIP)
