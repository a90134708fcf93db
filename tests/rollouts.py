"""An independent rollout for the replay tests: random actions, views straight from the
environment before and after every step, and the compact records a collector would store."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from roverswarm.buffers import compact
from roverswarm.env.mars import ACTION_SIZE, EnvParams, EnvState, masks_of, step_env


def random_episodes(start: EnvState, params: EnvParams, view: Callable, key: jax.Array, failures: bool = False):
    """E episodes of uniform random actions from the states ``start`` [E]: the episodes as
    :class:`~roverswarm.buffers.compact.Collected` (rewards 0; the masks of padded layouts, and
    the failure steps with ``failures``) and the views (obs, next obs) [T, E, N, O] of ``view``."""
    envs = start.rover_pos.shape[0]

    def body(env, k):
        actions = jax.random.uniform(k, (envs, params.num_rovers, ACTION_SIZE), minval=-1, maxval=1)
        after = jax.vmap(step_env, in_axes=(0, 0, None))(env, actions, params)[1]
        views = [jax.vmap(view, in_axes=(0, None))(s, params) for s in (env, after)]
        stored = (compact.rovers_of(env), actions, jnp.zeros(actions.shape[:2]), jnp.zeros(envs, bool))
        return after, (stored, env.observed, views)

    last, (stored, observed, views) = jax.lax.scan(body, start, jax.random.split(key, params.max_steps))
    episodes = compact.Collected(
        *stored,
        compact.layout_of(start),
        compact.rovers_of(last),
        observed=observed,
        final_observed=last.observed,
        masks=masks_of(start),
        fail_step=start.fail_step if failures else None,
    )
    return episodes, views
