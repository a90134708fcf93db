"""Episodes of a policy and their statistics, for evaluation and missions (deterministic
episodes); the totals are :mod:`roverswarm.metrics`'s, the ones the learner families log.

Shape legend: E episodes (parallel environments), T steps per episode, N rovers, P POIs.

Per-episode metrics (:class:`EpisodeStats`): the totals of :func:`~roverswarm.metrics.episode_totals`
(``reward`` is ``episode_reward``; ``coverage_distance`` from the final positions) and
``pois_observed``: POIs observed (a rover within ``observe_radius``) at some step.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from roverswarm.env.mars import EnvParams, EnvState, coverage_distance, masks_of, reset, step_env
from roverswarm.jaxcache import stored_jit
from roverswarm.metrics import EPISODE_METRICS, episode_totals, settled_coverage, step_stats
from roverswarm.policies import ActFn, Plan, Policy


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
        """Mean over episodes of every scalar metric: :data:`~roverswarm.metrics.EPISODE_METRICS`
        and ``pois_observed``."""
        means = {name: float(getattr(self, name).mean()) for name in (*EPISODE_METRICS[1:], "pois_observed")}
        return {"episode_reward": float(self.reward.mean()), **means}


@dataclass(frozen=True)
class Rollout:
    """What a rollout saw: the metrics, the fixed layout and the rovers' paths."""

    stats: EpisodeStats
    rover_pos: np.ndarray  # [E, T + 1, N, 2], including the start
    poi_pos: np.ndarray  # [E, P, 2]
    trap_pos: np.ndarray  # [E, T_traps, 2]
    observed: np.ndarray  # [E, T + 1, P] bool
    rewards: np.ndarray  # [E, T, N], zero after a termination
    rover_exists: np.ndarray  # [E, N] bool: False for the empty slots of a padded layout
    poi_exists: np.ndarray  # [E, P] bool
    trap_exists: np.ndarray  # [E, T_traps] bool


def _run_episode(act: ActFn, key: jax.Array, obs: jax.Array, state: EnvState, plan: Plan, weights, params: EnvParams):
    """One episode of at most ``max_steps``; after a termination the state stands still and
    the steps contribute nothing."""

    def body(carry, step_key):
        obs, state, done = carry
        actions = act(step_key, obs, state, plan, weights, params)
        next_obs, next_state, rewards, terminated, _, info = step_env(state, actions, params)
        settled = settled_coverage(state, params)  # the state a finished episode stands in
        obs, state = jax.tree.map(lambda old, new: jnp.where(done, old, new), (obs, state), (next_obs, next_state))
        live = 1.0 - done.astype(jnp.float32)
        stats = step_stats(rewards, info, live, settled)
        out = {**stats, "rover_pos": state.rover_pos, "observed": state.observed}
        return (obs, state, done | terminated), out

    carry = (obs, state, jnp.zeros((), bool))
    _, out = jax.lax.scan(body, carry, jax.random.split(key, params.max_steps))
    return out


@stored_jit(static_argnums=(0,))
def _rollout_batch(
    act: ActFn, keys: jax.Array, obs: jax.Array, states: EnvState, plan: Plan, weights, params: EnvParams
):
    return jax.vmap(partial(_run_episode, act, weights=weights, params=params))(keys, obs, states, plan)


@stored_jit
def _reset_batch(keys: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
    return jax.vmap(reset, in_axes=(0, None))(keys, params)


_coverage_batch = jax.jit(jax.vmap(coverage_distance))


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
    totals = episode_totals(out, axis=1)
    stats = EpisodeStats(
        reward=totals["episode_reward"],
        agent_rewards=totals["agent_rewards"],
        collisions=totals["collisions"],
        trap_contacts=totals["trap_contacts"],
        # from the final positions: after a termination the last step's info is of a discarded step
        coverage_distance=np.asarray(_coverage_batch(out["rover_pos"][:, -1], states.poi_pos, masks_of(states))),
        pois_observed=observed[:, -1].sum(axis=-1),
    )
    return Rollout(
        stats=stats,
        rover_pos=np.concatenate([start_pos, out["rover_pos"]], axis=1),
        poi_pos=np.asarray(states.poi_pos),
        trap_pos=np.asarray(states.trap_pos),
        observed=observed,
        rewards=rewards,
        **_exists(states),
    )


def _exists(states: EnvState) -> dict[str, np.ndarray]:
    """Which slots of a batch of layouts [E, ...] hold an entity (all of them unless padded)."""
    masks = masks_of(states)
    if masks is None:
        shapes = (states.fail_step.shape, states.poi_pos.shape[:-1], states.trap_pos.shape[:-1])
        return dict(zip(("rover_exists", "poi_exists", "trap_exists"), (np.ones(s, bool) for s in shapes)))
    return {
        "rover_exists": np.asarray(masks.rovers),
        "poi_exists": np.asarray(masks.pois),
        "trap_exists": np.asarray(masks.traps),
    }


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
        success = (observed[:, -1] | ~data.poi_exists).all(axis=-1)
        latest = np.where(data.poi_exists, first, -np.inf).max(axis=1)
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
    """``(R - R_random) / (R_oracle - R_random)``: 0 is random, 1 is the oracle; NaN where the
    oracle earns no more than random does not tell them apart (the same reward on every layout)."""
    span = oracle_reward - random_reward
    return (reward - random_reward) / span if span != 0 else float("nan")
