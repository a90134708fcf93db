"""What episodes training draws, for every learner family: the swarm size of each episode of a
range scenario (``--scenario paper-2..10``, with ``--size-curriculum`` and
``--size-draw-power``), rover failures (``--fail-rate``, ``--fail-count``,
``--fail-max-rovers``), episodes that end once every POI is observed
(``--stop-when-complete``), the actions the environment gets (``--shield``) and the reward
the learner trains on.

``config`` below is a family's own config (an :class:`EpisodeOptions`) or a
:class:`~roverswarm.config.TrainConfig`: any record with the fields of :class:`EpisodeOptions`
besides ``num_envs`` and ``learner``.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from roverswarm.env.mars import EnvParams, EnvState, reset
from roverswarm.env.scenarios import draw_sizes, range_sizes, sized
from roverswarm.metrics import shaped_rewards
from roverswarm.steering import shield_actions


@dataclass(frozen=True, kw_only=True)
class EpisodeOptions:
    """What a family's config reads of the episodes it trains on: the fields of the run's
    :class:`~roverswarm.config.TrainConfig` of the same names (documented there)."""

    scenario: str = "paper-3"
    mission: str | None = None
    size_curriculum: int = 0
    size_draw_power: float = 0.0
    fail_rate: float = 0.0
    fail_count: int = 1
    fail_max_rovers: int = 0
    stop_when_complete: bool = False


def sizes_of(config) -> tuple[int, ...] | None:
    """The swarm sizes each environment draws from per episode (a range scenario); None: one size."""
    return None if config.mission is not None else range_sizes(config.scenario)


def size_cap(config, episodes: jax.Array) -> jax.Array:
    """The largest swarm size drawn after ``episodes`` episodes: with --size-curriculum E, it
    grows linearly from the range's smallest to its largest over the first E episodes."""
    sizes = sizes_of(config)
    low, high = sizes[0], sizes[-1]
    if config.size_curriculum == 0:
        return jnp.asarray(high)
    return low + jnp.minimum(episodes / config.size_curriculum, 1.0) * (high - low)


def training_params(config, params: EnvParams) -> EnvParams:
    """The environment training steps: ``params`` with --fail-rate (one rover, or up to
    --fail-count, may fail in each episode; with --fail-max-rovers only in small swarms, per
    episode at reset) and --stop-when-complete (an episode ends once every POI is observed)."""
    if config.fail_rate > 0:
        params = params.replace(fail_rate=config.fail_rate, fail_count=config.fail_count)
    return params.replace(terminate_on_complete=params.terminate_on_complete or config.stop_when_complete)


def reset_all(config, params: EnvParams, key: jax.Array, episodes: jax.Array) -> EnvState:
    """E fresh episodes of :func:`training_params` ``params``: of one size, or each of a size
    drawn from :func:`sizes_of` (up to :func:`size_cap` after ``episodes`` episodes)."""
    keys = jax.random.split(key, config.num_envs)  # the layouts of one size as before sizes could mix
    sizes = sizes_of(config)
    if sizes is None:
        return jax.vmap(reset, in_axes=(0, None))(keys, params)[1]
    # the sizes' key is the layouts' next sibling: fold_in(key, i) is split(key, E)[i], so
    # fold_in(key, 1) drew environment 1's layout from the sizes' bits
    counts = draw_sizes(
        jax.random.fold_in(key, config.num_envs),
        sizes,
        config.num_envs,
        size_cap(config, episodes),
        config.size_draw_power,
    )
    return jax.vmap(lambda k, n: reset(k, _failures_up_to(config, sized(params, n), n)))(keys, counts)[1]


def _failures_up_to(config, params: EnvParams, rovers) -> EnvParams:
    """One episode's ``params`` of ``rovers`` rovers: with --fail-max-rovers K, no failures
    in a swarm of more than K."""
    if config.fail_max_rovers == 0 or params.fail_rate is None:
        return params
    return params.replace(fail_rate=jnp.where(rovers <= config.fail_max_rovers, params.fail_rate, 0.0))


def exists(state: EnvState) -> jax.Array:
    """[..., N] bool: the rovers that exist in ``state`` (all of them unless sizes are mixed)."""
    return jnp.ones(state.fail_step.shape, bool) if state.rover_mask is None else state.rover_mask


def executed(learner, states: EnvState, actions: jax.Array, params: EnvParams) -> jax.Array:
    """[E, N, 2] what the environments ``states`` [E] get of the policy's ``actions``: clipped to
    [-1, 1], and with ``learner.shield`` (an ``AlgoConfig``) behind the safety layer
    (:func:`~roverswarm.steering.shield_actions`). The learner keeps its own actions."""
    if learner.shield:
        return jax.vmap(shield_actions, in_axes=(0, 0, None))(states, actions, params)
    return jnp.clip(actions, -1.0, 1.0)


def training_rewards(config, rewards: jax.Array, info, rovers: jax.Array) -> jax.Array:
    """[E, N] the rewards learned from (:func:`~roverswarm.metrics.shaped_rewards`); with
    --fail-max-rovers K the unobserved shaping only in swarms of at most K rovers (``rovers``
    [E, N], from :func:`exists`, counts them)."""
    if config.fail_max_rovers:
        small = jnp.sum(rovers, axis=-1) <= config.fail_max_rovers
        info = {**info, "unobserved_distance": jnp.where(small, info["unobserved_distance"], 0.0)}
    return shaped_rewards(rewards, info, config.learner)
