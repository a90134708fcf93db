"""The on-policy family's network kinds, each one record: what the networks see, and how.

Shape legend: N rovers, O flat observation size, A action size (2), M entity tokens per rover.

- ``mlp`` (``--network mlp``, the default): the flat view. The shared actor sees the rover's
  observation and its one-hot index [O + N]; MAPPO's value sees every rover's observation
  and the index [N * O + N], IPPO's the actor's input. Tied to the N it was trained on.
- ``entity`` (``--network entity``): the entity view (:mod:`roverswarm.env.entities`) and
  attention over it (:mod:`roverswarm.algos.entity`): no rover index anywhere, so the same
  weights drive any number of rovers. MAPPO's and IPPO's values see the same input, the
  rover's view: every entity relative to it, or with ``--entity-nearest K`` the K nearest of
  each type (then MAPPO's value sees no more than IPPO's; ``--swarm-value`` is refused here).
- ``nearest`` (``--network nearest``): the K nearest other rovers, POIs and traps
  (``--entity-nearest K``), nearest first within each type, as one vector of fixed width
  (empty slots zero, with the mask), read by the flat view's MLPs. Sorting makes it
  permutation-invariant and the width does not depend on N: another encoder for any swarm
  size, a fraction of attention's cost. Its value sees the actor's input, or with
  ``--swarm-value`` (MAPPO) also the swarm's mean of it and the swarm's size (:func:`swarm_tokens`).

Both are Gaussian policies with a learned, state-independent log-std (``log_std`` [A]).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp

from roverswarm.algos.entity import EntityConfig, make_entity_networks
from roverswarm.algos.learner import AlgoConfig
from roverswarm.env.entities import flat_tokens, nearest_width, observe_entities, observe_nearest
from roverswarm.env.mars import ACTION_SIZE, EnvParams, EnvState, observe


@dataclass(frozen=True)
class PolicyNetworks:
    """A network kind of the on-policy family as pure functions (any leading axes)."""

    observe: Callable[[EnvState, EnvParams], Any]
    """One environment's observations in this kind's view: [N, O], or an entity view [N, ...]."""
    actor_inputs: Callable[[Any], Any]
    """Observations [..., N, ...] -> what the actor sees of each rover [..., N, ...]."""
    critic_inputs: Callable[[Any], Any]
    """Observations [..., N, ...] -> what the value network sees for each rover [..., N, ...]."""
    init: Callable[[jax.Array, int, int], tuple[Any, Any]]
    """(key, N, O) -> fresh (actor, value) parameters (an entity network ignores N and O)."""
    policy: Callable[[Any, Any], tuple[jax.Array, jax.Array]]
    """(actor parameters, actor inputs [...]) -> (mean [..., A], log-std [A])."""
    value: Callable[[Any, Any], jax.Array]
    """(value parameters, value inputs [...]) -> value [...]."""
    any_size: bool
    """Whether the same weights serve any number of rovers, POIs and traps."""


# ----------------------------------------------------------------------------- the flat view

_ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu}


def orthogonal(scale: float) -> Callable[..., jax.Array]:
    """flax's orthogonal initialiser (the same numbers), one matrix at a time under ``vmap``.

    Batched by ``vmap`` (over seeds, agents, ensembles), its QR factorisation is one LAPACK
    call on a stack of matrices, which jaxlib (0.10) splits into tasks on XLA's intra-op
    thread pool and waits for *on* a thread of that pool: two such calls running at once on
    a 2-core machine took both threads and waited forever (the initialisation hung in 5 of 8
    runs: docs/performance.md#a-hang-in-the-initialisation). Drawn sequentially, each call
    factorises one matrix in its own thread."""
    init = nn.initializers.orthogonal(scale)

    def draw(key: jax.Array, shape: Sequence[int], dtype: Any = jnp.float32) -> jax.Array:
        return jax.custom_batching.sequential_vmap(lambda k: init(k, shape, dtype))(key)

    return draw


class MLP(nn.Module):
    """Dense layers of sizes ``hidden`` with ``activation``, then a linear output of size
    ``out``; orthogonal initialisation (gain sqrt(2) hidden, ``out_gain`` output), zero biases."""

    hidden: Sequence[int]
    out: int
    activation: str
    out_gain: float

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.Dense(width, kernel_init=orthogonal(math.sqrt(2)))(x)
            x = _ACTIVATIONS[self.activation](x)
        return nn.Dense(self.out, kernel_init=orthogonal(self.out_gain))(x)


class GaussianActor(nn.Module):
    """[..., O + N] -> mean [..., A] (linear, unbounded) and a state-independent log-std [A]."""

    hidden: Sequence[int]
    activation: str
    init_log_std: float

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        mean = MLP(self.hidden, ACTION_SIZE, self.activation, 0.01)(x)
        log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (ACTION_SIZE,))
        return mean, log_std


def networks(learner: AlgoConfig, config: Any) -> tuple[GaussianActor, MLP]:
    """The flat view's (actor, value) modules: hidden widths from the learner, the rest from
    ``config`` (the learner's :class:`~roverswarm.algos.ppo.PPOConfig`)."""
    actor = GaussianActor(learner.hidden, config.activation, config.init_log_std)
    return actor, MLP(learner.hidden, 1, config.activation, 1.0)


def _one_hot_rovers(obs: jax.Array) -> jax.Array:
    """[..., N, X] -> [..., N, X + N]: each rover's row followed by its one-hot index."""
    n = obs.shape[-2]
    return jnp.concatenate([obs, jnp.broadcast_to(jnp.eye(n, dtype=obs.dtype), (*obs.shape[:-1], n))], axis=-1)


def actor_inputs(obs: jax.Array) -> jax.Array:
    """What the shared actor sees: [..., N, O] -> [..., N, O + N] (own observation, one-hot index)."""
    return _one_hot_rovers(obs)


def critic_inputs(algo: str, obs: jax.Array) -> jax.Array:
    """What the shared value network sees for each rover: [..., N, O] -> [..., N, D].

    MAPPO: every rover's observation (flattened, the same for all rovers) and the rover's
    one-hot index; IPPO: the actor's input."""
    if algo == "ippo":
        return _one_hot_rovers(obs)
    *batch, n, o = obs.shape
    return _one_hot_rovers(jnp.broadcast_to(obs.reshape(*batch, 1, n * o), (*batch, n, n * o)))


def _mlp_kind(learner: AlgoConfig, config: Any) -> PolicyNetworks:
    actor_net, critic_net = networks(learner, config)

    def init(key, num_rovers, obs_size):
        k_actor, k_critic = jax.random.split(key)
        obs = jnp.zeros((num_rovers, obs_size))
        return actor_net.init(k_actor, actor_inputs(obs)), critic_net.init(k_critic, critic_inputs(learner.algo, obs))

    return PolicyNetworks(
        observe=observe,
        actor_inputs=actor_inputs,
        critic_inputs=functools.partial(critic_inputs, learner.algo),
        init=init,
        policy=actor_net.apply,
        value=lambda params, inputs: critic_net.apply(params, inputs)[..., 0],
        any_size=False,
    )


# ----------------------------------------------------------------------------- the entity view


def entity_config(learner: AlgoConfig) -> EntityConfig:
    """The entity networks' sizes of the learner's options (heads' hidden widths: ``--hidden``)."""
    return EntityConfig(
        dim=learner.entity_dim, heads=learner.entity_heads, layers=learner.entity_layers, hidden=learner.hidden
    )


def _entity_kind(learner: AlgoConfig, config: Any) -> PolicyNetworks:
    nets = make_entity_networks(entity_config(learner))

    def init(key, num_rovers, obs_size):
        k_actor, k_critic = jax.random.split(key)
        # float32, as the runner a chunk returns holds it (a Python float's weak type made the
        # second chunk compile the whole program again)
        log_std = jnp.full((ACTION_SIZE,), config.init_log_std, jnp.float32)
        return {"net": nets.init_actor(k_actor), "log_std": log_std}, nets.init_value(k_critic)

    def policy(params, view):
        return nets.actor(params["net"], view.own, view.tokens, view.mask), params["log_std"]

    def view(state, params):
        if learner.entity_nearest == 0:
            return observe_entities(state, params)
        return observe_nearest(state, params, learner.entity_nearest, learner.poi_order)

    return PolicyNetworks(
        observe=view,
        actor_inputs=lambda view: view,
        critic_inputs=lambda view: view,
        init=init,
        policy=policy,
        value=lambda params, view: nets.value(params, view.own, view.tokens, view.mask),
        any_size=True,
    )


def swarm_tokens(view) -> jax.Array:
    """``--swarm-value``: each rover's flat view (:func:`flat_tokens`) [..., N, W] followed by the
    swarm's: the mean of its rovers' flat views and its size / 10, [..., N, 2 W + 1]. The same
    under any order of the rovers and for any size; rows of rovers that do not exist (all
    tokens masked) count in neither."""
    own = flat_tokens(view)
    exists = jnp.any(view.mask, axis=-1, keepdims=True).astype(own.dtype)  # [..., N, 1]
    count = jnp.sum(exists, axis=-2, keepdims=True)  # [..., 1, 1]
    mean = jnp.sum(own * exists, axis=-2, keepdims=True) / jnp.maximum(count, 1.0)
    swarm = jnp.concatenate([mean, count / 10.0], axis=-1)
    return jnp.concatenate([own, jnp.broadcast_to(swarm, (*own.shape[:-1], swarm.shape[-1]))], axis=-1)


def _nearest_kind(learner: AlgoConfig, config: Any) -> PolicyNetworks:
    actor_net, critic_net = networks(learner, config)
    k = learner.entity_nearest
    critic_inputs = swarm_tokens if config.swarm_value else flat_tokens

    def view(state, params):
        return observe_nearest(state, params, k, learner.poi_order)

    def init(key, num_rovers, obs_size):
        k_actor, k_critic = jax.random.split(key)
        width = nearest_width(k)
        critic_width = 2 * width + 1 if config.swarm_value else width
        return actor_net.init(k_actor, jnp.zeros((width,))), critic_net.init(k_critic, jnp.zeros((critic_width,)))

    return PolicyNetworks(
        observe=view,
        actor_inputs=flat_tokens,
        critic_inputs=critic_inputs,
        init=init,
        policy=actor_net.apply,
        value=lambda params, inputs: critic_net.apply(params, inputs)[..., 0],
        any_size=True,
    )


KINDS: dict[str, Callable[[AlgoConfig, Any], PolicyNetworks]] = {
    "mlp": _mlp_kind,
    "entity": _entity_kind,
    "nearest": _nearest_kind,
}
"""``--network`` -> its on-policy network kind."""


@functools.lru_cache(maxsize=None)
def policy_networks(learner: AlgoConfig, config: Any) -> PolicyNetworks:
    """The network kind of ``learner.network`` (one record per config: programs that close
    over it are reused)."""
    return KINDS[learner.network](learner, config)
