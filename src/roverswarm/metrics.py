"""What an episode adds up to and what a run logs: one definition of every episode metric,
read by the learner families (training episodes), rollouts (evaluation) and the run folder.

Shape legend: T steps, E episodes (parallel environments), N rovers; ``...`` any leading axes.

Per-episode totals (:func:`episode_totals`):

- ``episode_reward``: sum of every rover's reward over every step (the paper's "episode reward");
- ``agent_rewards`` [N]: the same per rover (``agent_i_reward`` in ``metrics.csv``, a mean
  over the episodes in which rover i exists: :func:`chunk_means`);
- ``collisions``: rover-rover contacts, one per touching pair per step;
- ``trap_contacts``: rover-trap contacts, one per (rover, trap) pair per step;
- ``coverage_distance``: sum over POIs of the nearest rover's distance at the last step.

Rollouts add ``pois_observed`` (POIs a rover came within ``observe_radius`` of at some step).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from roverswarm.env.mars import EnvParams, EnvState, coverage_distance, masks_of

if TYPE_CHECKING:
    from roverswarm.algos.learner import AlgoConfig

EPISODE_METRICS = ("episode_reward", "collisions", "trap_contacts", "coverage_distance")
"""The scalar per-episode totals a training run logs, in ``metrics.csv``'s order (after the
per-rover ``agent_i_reward`` columns, which follow ``episode_reward``)."""


def contact_counts(info: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """One step's contacts from :func:`~roverswarm.env.mars.step_env`'s info (any leading axes):
    ``collisions`` (touching pairs, each counted once) and ``trap_contacts`` ((rover, trap) pairs)."""
    return {"collisions": jnp.sum(info["collisions"], -1) / 2, "trap_contacts": jnp.sum(info["trap_contacts"], -1)}


def shaped_rewards(rewards: jax.Array, info: dict[str, jax.Array], learner: AlgoConfig) -> jax.Array:
    """The rewards a learner trains on: the environment's ``rewards`` [..., N] less
    ``learner.trap_shaping`` more per trap each rover touches (``--trap-shaping``; with
    ``--trap-margin M`` from M off the trap, a ramp to the full amount on contact) and
    ``learner.collision_shaping`` more per other rover it touches (``--collision-shaping``), plus
    ``learner.observe_bonus`` for every rover per POI first observed at the step
    (``--observe-bonus``), less ``learner.unobserved_shaping`` times the distance the swarm's
    working rovers still have to the POIs not yet observed, for every rover
    (``--unobserved-shaping``). Episode rewards, metrics and evaluations stay the environment's."""
    swarm = (
        learner.observe_bonus * info["pois_first_observed"] - learner.unobserved_shaping * info["unobserved_distance"]
    )
    traps = info["trap_contacts"]
    if learner.trap_margin:  # each trap charged from trap_margin off, in full on contact
        traps = jnp.sum(jnp.clip(1.0 - info["trap_gaps"] / learner.trap_margin, 0.0, 1.0), axis=-1)
    contacts = learner.trap_shaping * traps + learner.collision_shaping * info["collisions"]
    return rewards - contacts + swarm[..., None]


def step_stats(
    rewards: jax.Array, info: dict[str, jax.Array], live: jax.Array | None = None, settled: jax.Array | None = None
) -> dict[str, jax.Array]:
    """What one step [...] adds to its episode's totals: ``rewards`` [..., N], ``collisions``,
    ``trap_contacts`` and ``coverage_distance``; with ``live`` [...] (0 or False after a
    termination) the rewards and contacts of dead steps count nothing, and their coverage
    distance is ``settled`` [...] (:func:`settled_coverage`: that of the state the episode
    ended in, not of the state stepped on from it)."""
    stats = {"rewards": rewards, **contact_counts(info)}
    if live is not None:
        stats = {k: v * (live[..., None] if k == "rewards" else live) for k, v in stats.items()}
    coverage = info["coverage_distance"]
    stats["coverage_distance"] = coverage if settled is None else jnp.where(live > 0, coverage, settled)
    return stats


def settled_coverage(state: EnvState, params: EnvParams) -> jax.Array | None:
    """[] The coverage distance of ``state``, the state a step starts from, where episodes end
    when complete (``params.terminate_on_complete``: after the end the state stands still);
    None where they never end early."""
    if not params.terminate_on_complete:
        return None
    return coverage_distance(state.rover_pos, state.poi_pos, masks_of(state))


def episode_totals(steps: dict, axis: int = 0) -> dict:
    """Per-episode totals of :func:`step_stats` stacked along the time axis ``axis`` (JAX or
    NumPy arrays): ``episode_reward``, ``agent_rewards`` [..., N], ``collisions``,
    ``trap_contacts`` and ``coverage_distance`` (at the last step)."""
    rewards = steps["rewards"]
    return {
        "episode_reward": rewards.sum(axis=(axis, rewards.ndim - 1)),
        "agent_rewards": rewards.sum(axis=axis),
        "collisions": steps["collisions"].sum(axis=axis),
        "trap_contacts": steps["trap_contacts"].sum(axis=axis),
        "coverage_distance": steps["coverage_distance"][(slice(None),) * axis + (-1,)],
    }


def chunk_means(episode: dict, axis: tuple[int, ...]) -> dict:
    """A chunk's per-episode totals (:func:`episode_totals` with ``rovers`` [..., N], the
    rovers that exist) as means over ``axis``: ``agent_rewards`` over the episodes in which
    each rover exists (where swarm sizes mix, the last slots exist in only some; 0 for a slot
    that never did), the rest over every episode."""
    means = {k: v.mean(axis=axis) for k, v in episode.items() if k != "rovers"}
    means["agent_rewards"] = masked_mean(episode["agent_rewards"], episode["rovers"], axis)
    return means


def masked_mean(x: jax.Array, mask: jax.Array, axis: int | tuple[int, ...] | None = None) -> jax.Array:
    """The mean of ``x`` over the entries where ``mask`` (0/1 or bool) is set, along ``axis``
    (all axes by default); 0 where none is."""
    return jnp.sum(x * mask, axis) / jnp.maximum(jnp.sum(mask, axis), 1.0)


def reduce_metric(name: str, x, axis):
    """Aggregate a metric: ``*_max`` metrics by their maximum, the others by their mean."""
    return x.max(axis=axis) if name.endswith("_max") else x.mean(axis=axis)
