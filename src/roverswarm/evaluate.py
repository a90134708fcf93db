"""Rollouts of a policy over many episodes and the metrics the paper and missions report.

Shape legend: E episodes (parallel environments), T steps per episode, N rovers, P POIs.

Per-episode metrics (:class:`EpisodeStats`):

- ``reward``: sum of every rover's reward over every step (the paper's "episode reward");
- ``agent_rewards`` [N]: the same per rover;
- ``collisions``: rover-rover contacts, one per touching pair per step;
- ``trap_contacts``: rover-trap contacts, one per (rover, trap) pair per step;
- ``coverage_distance``: sum over POIs of the nearest rover's distance at the last step;
- ``pois_observed``: POIs observed (a rover within ``observe_radius``) at some step.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from roverswarm.env.mars import EnvParams, EnvState, coverage_distance, reset, step_env
from roverswarm.errors import require
from roverswarm.algos.maddpg import LearnerState
from roverswarm.policies import ORACLE, RANDOM, ActFn, Plan, Policy, trained_policy
from roverswarm.train import TrainConfig, load_run, validate


@dataclass(frozen=True)
class EpisodeStats:
    """Per-episode metrics, each an array with leading axis E."""

    reward: np.ndarray  # [E]
    agent_rewards: np.ndarray  # [E, N]
    collisions: np.ndarray  # [E]
    trap_contacts: np.ndarray  # [E]
    coverage_distance: np.ndarray  # [E]
    pois_observed: np.ndarray  # [E]

    def summary(self) -> dict[str, float]:
        """Mean over episodes of every scalar metric."""
        return {
            "episode_reward": float(self.reward.mean()),
            "collisions": float(self.collisions.mean()),
            "trap_contacts": float(self.trap_contacts.mean()),
            "coverage_distance": float(self.coverage_distance.mean()),
            "pois_observed": float(self.pois_observed.mean()),
        }


@dataclass(frozen=True)
class Rollout:
    """What a rollout saw: the metrics, the fixed layout and the rovers' paths."""

    stats: EpisodeStats
    rover_pos: np.ndarray  # [E, T + 1, N, 2], including the start
    poi_pos: np.ndarray  # [E, P, 2]
    trap_pos: np.ndarray  # [E, T_traps, 2]
    observed: np.ndarray  # [E, T + 1, P] bool
    rewards: np.ndarray  # [E, T, N], zero after a termination


def _run_episode(act: ActFn, key: jax.Array, obs: jax.Array, state: EnvState, plan: Plan, weights, params: EnvParams):
    """One episode of at most ``max_steps``; after a termination the state stands still and
    the steps contribute nothing."""

    def body(carry, step_key):
        obs, state, done = carry
        actions = act(step_key, obs, state, plan, weights, params)
        next_obs, next_state, rewards, terminated, _, info = step_env(state, actions, params)
        obs, state = jax.tree.map(lambda old, new: jnp.where(done, old, new), (obs, state), (next_obs, next_state))
        live = 1.0 - done.astype(jnp.float32)
        out = {
            "rewards": rewards * live,
            "collisions": jnp.sum(info["collisions"]) * live / 2,
            "trap_contacts": jnp.sum(info["trap_contacts"]) * live,
            "rover_pos": state.rover_pos,
            "observed": state.observed,
        }
        return (obs, state, done | terminated), out

    carry = (obs, state, jnp.zeros((), bool))
    _, out = jax.lax.scan(body, carry, jax.random.split(key, params.max_steps))
    return out


@partial(jax.jit, static_argnames=("act",))
def _rollout_batch(act: ActFn, keys: jax.Array, obs: jax.Array, states: EnvState, plan: Plan, weights, params: EnvParams):
    return jax.vmap(partial(_run_episode, act, weights=weights, params=params))(keys, obs, states, plan)


_reset_batch = jax.jit(jax.vmap(reset, in_axes=(0, None)))


def rollout(policy: Policy, key: jax.Array, params: EnvParams, num_episodes: int, fail_step=None) -> Rollout:
    """Run ``policy`` for ``num_episodes`` independent episodes (vmapped) and collect metrics.

    ``fail_step`` ([N] or [E, N] int, :data:`~roverswarm.env.mars.NEVER` for a working rover)
    freezes rover i from step ``fail_step[i]`` on. Same key, policy, params and failures =>
    identical results.
    """
    reset_key, run_key = jax.random.split(key)
    obs, states = _reset_batch(jax.random.split(reset_key, num_episodes), params)
    if fail_step is not None:
        fail = jnp.broadcast_to(jnp.asarray(fail_step, jnp.int32), states.fail_step.shape)
        states = states.replace(fail_step=fail)
    plan = policy.plan(states, params)
    out = jax.device_get(
        _rollout_batch(policy.act, jax.random.split(run_key, num_episodes), obs, states, plan, policy.weights, params)
    )
    rewards = out["rewards"]
    start_pos = np.asarray(states.rover_pos)[:, None]
    start_observed = np.asarray(states.observed)[:, None]
    observed = np.concatenate([start_observed, out["observed"]], axis=1)
    stats = EpisodeStats(
        reward=rewards.sum(axis=(1, 2)),
        agent_rewards=rewards.sum(axis=1),
        collisions=out["collisions"].sum(axis=1),
        trap_contacts=out["trap_contacts"].sum(axis=1),
        # from the final positions: after a termination the last step's info is of a discarded step
        coverage_distance=np.asarray(jax.vmap(coverage_distance)(out["rover_pos"][:, -1], states.poi_pos)),
        pois_observed=observed[:, -1].sum(axis=-1),
    )
    return Rollout(
        stats=stats,
        rover_pos=np.concatenate([start_pos, out["rover_pos"]], axis=1),
        poi_pos=np.asarray(states.poi_pos),
        trap_pos=np.asarray(states.trap_pos),
        observed=observed,
        rewards=rewards,
    )


@dataclass(frozen=True)
class MissionStats:
    """What a mission planner asks of each episode of a rollout (times in steps, NaN: never).

    A mission *succeeds* when every POI was observed (a rover's centre within the POI's
    observation radius) before the episode ended; collisions and trap contacts are counted
    beside it, not folded into it."""

    first_observed: np.ndarray  # [E, P] step of each POI's first observation (0: at the start)
    pois_observed: np.ndarray  # [E]
    time_to_all: np.ndarray  # [E] step at which the last POI was first observed
    path_length: np.ndarray  # [E, N] distance each rover drove
    collisions: np.ndarray  # [E]
    trap_contacts: np.ndarray  # [E]
    success: np.ndarray  # [E] bool

    @classmethod
    def of(cls, data: Rollout) -> MissionStats:
        observed = data.observed  # [E, T + 1, P]
        first = np.where(observed.any(axis=1), observed.argmax(axis=1), np.nan)
        success = observed[:, -1].all(axis=-1)
        latest = first.max(axis=1)
        return cls(
            first_observed=first,
            pois_observed=data.stats.pois_observed,
            time_to_all=np.where(success, latest, np.nan),
            path_length=np.linalg.norm(np.diff(data.rover_pos, axis=1), axis=-1).sum(axis=1),
            collisions=data.stats.collisions,
            trap_contacts=data.stats.trap_contacts,
            success=success,
        )

    def summary(self) -> dict[str, float]:
        """Means over episodes; ``time_to_all`` over the successful ones (NaN if none)."""
        return {
            "success": float(self.success.mean()),
            "time_to_all": float(np.nanmean(self.time_to_all)) if self.success.any() else float("nan"),
            "pois_observed": float(self.pois_observed.mean()),
            "collisions": float(self.collisions.mean()),
            "trap_contacts": float(self.trap_contacts.mean()),
        }


def normalized_score(reward: float, random_reward: float, oracle_reward: float) -> float:
    """``(R - R_random) / (R_oracle - R_random)``: 0 is random, 1 is the oracle."""
    return (reward - random_reward) / (oracle_reward - random_reward)


SubPolicies = Literal["random", "each"]
Partners = Literal["own", "other-seeds"]


def partner_seeds(seed: int, num_agents: int, seeds: int) -> np.ndarray:
    """[N] the seed each agent's actor comes from under ``other-seeds``: ``(seed + i) mod S``."""
    return (seed + np.arange(num_agents)) % seeds


def seed_actor(actor, seed: int, num_agents: int, partners: Partners = "own"):
    """The actors [N * K, ...] that seed ``seed`` of a run's actors [S, N * K, ...] plays with:
    its own (``own``), or agent i's from seed ``(seed + i) mod S`` (``other-seeds``: partners
    trained apart, which never saw each other during training; :func:`partner_seeds`)."""
    if partners == "own":
        return jax.tree.map(lambda x: x[seed], actor)
    seeds, rows = jax.tree.leaves(actor)[0].shape[:2]  # S, N * K
    source = partner_seeds(seed, num_agents, seeds)[np.arange(rows) // (rows // num_agents)]
    return jax.tree.map(lambda x: x[source, np.arange(rows)], actor)


def run_policies(config: TrainConfig, learner: LearnerState, sub_policies: SubPolicies = "random", seed: int = 0, partners: Partners = "own") -> list[Policy]:
    """Every seed's trained policy; with ensembles, a random sub-policy per agent and episode
    as in training (``random``), or every sub-policy k of all agents in turn (``each``).
    With ``partners="other-seeds"`` every agent plays beside the other agents of other seeds
    (:func:`seed_actor`), a test of how well a policy copes with partners it was not trained with."""
    require(partners in ("own", "other-seeds"), f"--partners must be 'own' or 'other-seeds', got '{partners}'")
    require(partners == "own" or config.seeds >= 2, f"--partners other-seeds needs a run trained with --seeds >= 2, this one has {config.seeds}")
    require(
        partners == "own" or not (config.learner.share_parameters or config.learner.normalize_obs),
        "--partners other-seeds needs one network and no observation normaliser per agent: this run has --share-parameters or --normalize-obs",
    )
    num_agents = validate(config).num_rovers
    policies = []
    for s in range(config.seeds):
        actor = seed_actor(learner.actor, s, num_agents, partners)
        norm = None if learner.obs_norm is None else jax.tree.map(lambda x: x[s], learner.obs_norm)
        if partners == "own":
            name = f"{config.learner.algo} seed {s}"
        else:
            name = f"{config.learner.algo} agents of seeds {'/'.join(map(str, partner_seeds(s, num_agents, config.seeds)))}"
        if config.learner.ensemble == 1:
            policies.append(trained_policy(config.learner, actor, name, obs_norm=norm))
        elif sub_policies == "random":
            policies.append(trained_policy(config.learner, actor, f"{name}, random sub-policies", seed=seed, obs_norm=norm))
        else:
            policies += [trained_policy(config.learner, actor, f"{name}, sub-policy {k}", k, obs_norm=norm) for k in range(config.learner.ensemble)]
    return policies


def evaluate_run(out, episodes: int = 1000, seed: int = 0, sub_policies: SubPolicies = "random", partners: Partners = "own") -> list[dict[str, float | str]]:
    """Deterministic episodes of every seed's trained policy in run folder ``out``, beside the
    random and oracle policies on the same episodes (same layouts), with the normalised score.
    Runs with policy ensembles, and ``partners``, work as :func:`run_policies` says; the policy
    names say which.

    Returns one row per policy: ``policy``, the :meth:`EpisodeStats.summary` metrics and
    ``normalized_score``.
    """
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    require(sub_policies in ("random", "each"), f"--sub-policies must be 'random' or 'each', got '{sub_policies}'")
    config, learner = load_run(out)
    params = validate(config)
    key = jax.random.PRNGKey(seed)
    policies = run_policies(config, learner, sub_policies, seed, partners)
    results = {p.name: rollout(p, key, params, episodes).stats.summary() for p in (RANDOM, ORACLE, *policies)}
    low, high = results["random"]["episode_reward"], results["oracle"]["episode_reward"]
    return [
        {"policy": name, **summary, "normalized_score": normalized_score(summary["episode_reward"], low, high)}
        for name, summary in results.items()
    ]
