"""Reference policies that need no training: ``random`` (the floor) and ``oracle`` (the yardstick).

A :class:`Policy` has two parts:

- ``plan(states, params) -> plan``: host-side, once per episode, on a batch of freshly reset
  states ``[E, ...]``; may use NumPy/SciPy. Returns a pytree with leading axis E (or None).
- ``act(key, obs [N, O], state, plan, weights, params) -> actions [N, 2]``: jittable, one
  environment; rollouts vmap it over environments. ``weights`` is the policy's own pytree
  (network parameters of a trained policy; None for the reference policies), passed as data
  so that a new set of weights does not recompile the rollout.

The oracle (:mod:`roverswarm.oracle`) assigns rovers to POIs and drives each to its own,
around traps and other rovers; every score is normalised between random and it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Hashable

import jax
import jax.numpy as jnp
import numpy as np

from roverswarm.algos.normalize import ObsNorm
from roverswarm.env.mars import ACTION_SIZE, EnvParams, EnvState, observe
from roverswarm.jaxcache import stable_name
from roverswarm.learners import learner_family
from roverswarm.oracle import oracle_act, oracle_plan
from roverswarm.steering import shield_actions

if TYPE_CHECKING:
    from roverswarm.config import TrainConfig

Plan = Any
ActFn = Callable[[jax.Array, jax.Array, EnvState, Plan, Any, EnvParams], jax.Array]
PlanFn = Callable[[EnvState, EnvParams], Plan]


def _no_plan(states: EnvState, params: EnvParams) -> None:
    return None


@dataclass(frozen=True)
class Policy:
    """A policy for rollouts: a host-side per-episode ``plan`` and a jittable per-step ``act``."""

    name: str
    act: ActFn
    plan: PlanFn = _no_plan
    weights: Any = None
    shield: bool = False
    """The actions pass the safety layer (:func:`shielded`)."""


# ----------------------------------------------------------------------------- random


def _random_act(
    key: jax.Array, obs: jax.Array, state: EnvState, plan: Plan, weights: Any, params: EnvParams
) -> jax.Array:
    return jax.random.uniform(key, (params.num_rovers, ACTION_SIZE), minval=-1.0, maxval=1.0)


RANDOM = Policy("random", _random_act)

ORACLE = Policy("oracle", oracle_act, oracle_plan)

REFERENCE_POLICIES: dict[str, Policy] = {p.name: p for p in (RANDOM, ORACLE)}


# ----------------------------------------------------------------------------- trained


@functools.lru_cache(maxsize=None)
def _trained_act(algo: str, acting: Hashable, nearest_first: bool) -> ActFn:
    # one function object per learner config, so rollouts of new weights reuse the compiled code
    family = learner_family(algo)
    act, view = family.act, family.view(acting)

    def act_fn(key, obs, state, plan, weights, params):
        if view is not None:  # a view of its own (e.g. entities), for any swarm size
            obs = view(state, params)
        elif params.nearest_first != nearest_first:  # an environment showing another view than training's
            obs = observe(state, params.replace(nearest_first=nearest_first))
        return act(acting, weights, obs, plan)  # plan: with ensembles, every agent's sub-policy [N]

    # named the same in every process, so that its rollouts' programs are kept (roverswarm.jaxcache)
    act_fn.stored_name = f"{__name__}.trained({family.name!r}, {acting!r}, {nearest_first})"
    return act_fn


def _named_after(outer: ActFn, wrapper: str, inner: ActFn) -> ActFn:
    """``outer`` (``wrapper`` around ``inner``) named for the programs kept across processes
    (:func:`~roverswarm.jaxcache.stable_name`), if ``inner`` has such a name."""
    inner_name = stable_name(inner)
    if inner_name is not None:
        outer.stored_name = f"{__name__}.{wrapper}({inner_name})"
    return outer


@functools.lru_cache(maxsize=None)
def _shielded_act(act_fn: ActFn) -> ActFn:
    # one function object per inner act function, so rollouts of new weights reuse the compiled code
    def shielded_act(key, obs, state, plan, weights, params):
        return shield_actions(state, act_fn(key, obs, state, plan, weights, params), params)

    shielded_act.unshielded = act_fn  # for mixed_policy: one layer over the mix, not one per rover
    return _named_after(shielded_act, "shielded", act_fn)


def shielded(policy: Policy) -> Policy:
    """``policy`` behind the safety layer (``--shield``,
    :func:`~roverswarm.steering.shield_actions`): each action turned along the tangent of any
    trap or other rover its velocity would reach within a few steps, the rest unchanged. A
    policy already behind it (trained with ``--shield``) is returned as it is."""
    if policy.shield:
        return policy
    return Policy(f"{policy.name}, shielded", _shielded_act(policy.act), policy.plan, policy.weights, shield=True)


def _sub_policy_plan(num_policies: int, sub_policy: int | None, seed: int) -> PlanFn:
    """Per episode, the sub-policy every agent runs: ``sub_policy``, or a uniform draw per agent
    and episode as in training (the same draws for the same ``seed``)."""

    def plan(states: EnvState, params: EnvParams) -> np.ndarray:
        shape = states.rover_pos.shape[:-1]  # [E, N]
        if sub_policy is not None:
            return np.full(shape, sub_policy, np.int32)
        return np.random.default_rng(seed).integers(0, num_policies, shape).astype(np.int32)

    return plan


@functools.lru_cache(maxsize=None)
def _mixed_act(act_fn: ActFn) -> ActFn:
    # one function object per inner act function, so rollouts of every mix reuse the compiled code
    def mixed(key, obs, state, plan, weights, params):
        every = [act_fn(key, obs, state, plan, w, params)[..., i, :] for i, w in enumerate(weights)]
        return jnp.stack(every, axis=-2)

    return _named_after(mixed, "mixed", act_fn)


def mixed_policy(name: str, policies: list[Policy]) -> Policy:
    """A swarm of rovers taken from different trained policies of one config: rover i acts as
    ``policies[i]`` would in its place, on the same observations (each with its own networks
    and observation normaliser; a shared network with rover i's id). The policies share their
    act function and per-episode plan (the first's plan is used)."""
    if any(p.act is not policies[0].act for p in policies):
        raise ValueError("mixed_policy: the policies must come from one training config")
    first = policies[0]
    act = first.act.unshielded if first.shield else first.act  # each rover's layer reads its own action alone
    mixed = Policy(name, _mixed_act(act), first.plan, weights=tuple(p.weights for p in policies))
    return shielded(mixed) if first.shield else mixed


def trained_policy(
    config: TrainConfig,
    actor_params,
    name: str = "trained",
    sub_policy: int | None = None,
    seed: int = 0,
    obs_norm: ObsNorm | None = None,
) -> Policy:
    """The deterministic policy (no exploration noise) of the actors [N * K, ...] (or [1, ...]
    shared) trained by ``config``, on observations standardised by ``obs_norm`` (runs with
    --normalize-obs) and in the view it was trained on (--nearest-first), whatever view the
    environment shows. With ensembles (K > 1) every agent runs sub-policy ``sub_policy``, or,
    if None, one drawn per episode as in training (by a generator seeded with ``seed``). A run
    trained behind the safety layer (--shield) acts behind it."""
    learner = config.learner
    weights = (actor_params, obs_norm)
    family = learner_family(learner.algo)
    acting = family.acting(config)
    act_fn = _trained_act(learner.algo, acting, config.nearest_first)
    plan = _no_plan if learner.ensemble == 1 else _sub_policy_plan(learner.ensemble, sub_policy, seed)
    policy = Policy(name, act_fn, plan, weights=weights)
    return shielded(policy) if learner.shield else policy
