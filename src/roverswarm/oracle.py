"""The oracle: the yardstick every score is normalised by, and the teacher ``--teacher`` imitates.

It assigns rovers to POIs by the Hungarian method (minimum total distance, SciPy's
``linear_sum_assignment``, host-side once per episode: :func:`oracle_plan`) and then drives
each rover to its POI with a go-to-goal controller on the known dynamics that heads along the
tangent of any trap or other rover in its way (:func:`oracle_act`, jittable). Rovers whose POI
is observed take over the POIs left open, by a failed rover or because there are more POIs
than rovers, one rover per POI (:func:`oracle_goals`). It is a strong yardstick, not a perfect
one: in crowded layouts rovers still brush each other or a crater now and then (about 0.3
trap contacts per episode on ``paper-3`` and 1.7 on ``paper-5``, against 5 and 13 for the
random policy).

Inside a jitted training loop the Hungarian method is out of reach; :func:`greedy_plan`
assigns greedily instead (the closest remaining rover and POI first, then crossing routes
swapped apart), on device.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy.optimize import linear_sum_assignment

from roverswarm.env.entities import hand_over, match_pois
from roverswarm.env.mars import EnvParams, EnvState, masks_of, other_rovers, pairwise_dist, trap_radii

# Clearance kept from a trap's or another rover's edge, and how many steps the controller takes to close the
# remaining distance to its goal (1 = deadbeat, larger = gentler).
_KEEP_OUT_MARGIN = 0.05
_APPROACH_STEPS = 2.0


def assign_pois(rover_pos: np.ndarray, poi_pos: np.ndarray) -> np.ndarray:
    """Optimal assignment (Hungarian method) of rovers ``[N, 2]`` to POIs ``[P, 2]``.

    Minimises the total rover-to-POI distance. Returns the POI index of each rover ``[N]``,
    -1 for a rover left without one (N > P).
    """
    assigned = np.full(len(rover_pos), -1, dtype=np.int32)
    if len(poi_pos):
        cost = np.linalg.norm(rover_pos[:, None, :] - poi_pos[None, :, :], axis=-1)
        rows, cols = linear_sum_assignment(cost)
        assigned[rows] = cols
    return assigned


@struct.dataclass
class OraclePlan:
    """Per episode: each rover's assigned POI (-1: none) and its start (where a rover with
    nothing to do waits)."""

    poi: jax.Array  # [N] int32
    home: jax.Array  # [N, 2]


def oracle_plan(states: EnvState, params: EnvParams) -> OraclePlan:
    """The oracle's plan of a batch of freshly reset states [E, ...], on the host: each rover's
    POI by :func:`assign_pois` (a padded layout's real rovers and POIs only), its start as home."""
    rover = np.asarray(states.rover_pos)
    poi = np.asarray(states.poi_pos)
    masks = masks_of(states)
    if masks is None:
        assigned = [assign_pois(r, p) for r, p in zip(rover, poi)]
    else:  # a padded layout's entities are its first slots: assign those, the empty rover slots get none
        assigned = []
        for r, p, n, m in zip(rover, poi, np.asarray(masks.rovers).sum(-1), np.asarray(masks.pois).sum(-1)):
            assigned.append(np.concatenate([assign_pois(r[:n], p[:m]), np.full(len(r) - n, -1, np.int32)]))
    return OraclePlan(poi=jnp.asarray(np.stack(assigned)), home=jnp.asarray(rover))


def greedy_plan(state: EnvState, params: EnvParams) -> OraclePlan:
    """The oracle's plan of one freshly reset environment, on device: rovers matched to POIs by
    :func:`~roverswarm.env.entities.match_pois` on their distances (greedy, crossing routes
    swapped apart; the Hungarian method of :func:`oracle_plan` is host-side), as the matched
    view splits the work. A padded layout's empty slots take no part."""
    cost = pairwise_dist(state.rover_pos, state.poi_pos)
    masks = masks_of(state)
    if masks is not None:
        cost = jnp.where(masks.rovers[:, None] & masks.pois[None, :], cost, jnp.inf)
    return OraclePlan(poi=match_pois(cost), home=state.rover_pos)


def oracle_goals(state: EnvState, plan: OraclePlan, params: EnvParams) -> jax.Array:
    """[N, 2] where each rover heads now.

    A rover heads for its assigned POI. Once that POI is observed (or if it has none) it is
    free. Free rovers take the *open* POIs: not yet observed, and assigned to no working rover
    (because that rover failed, or because there are more POIs than rovers). They are matched
    greedily, the closest free rover and open POI first, one rover per POI
    (:func:`~roverswarm.env.entities.hand_over`). A free rover left
    without one stays at its assigned POI (or its start). With every rover working and at
    least as many rovers as POIs nothing is ever open, so this is the plain assignment. The
    empty rover slots of a padded layout neither work nor claim a POI.
    """
    working = state.time < state.fail_step  # [N]
    pois = jnp.ones(params.num_pois, bool)
    masks = masks_of(state)
    if masks is not None:  # the empty slots of a padded layout neither work nor need a visit
        working, pois = working & masks.rovers, masks.pois
    dist = pairwise_dist(state.rover_pos, state.poi_pos)  # [N, P]
    target = hand_over(plan.poi, dist, working, pois, state.observed)  # the plan's POI unless handed another
    return jnp.where((target >= 0)[:, None], state.poi_pos[jnp.maximum(target, 0)], plan.home)


def _steer_around(
    pos: jax.Array, vel_des: jax.Array, goal: jax.Array, obstacles: jax.Array, keep_out: jax.Array
) -> jax.Array:
    """Re-aim each rover's desired velocity [N, 2] along the tangent of any obstacle it would cross.

    ``obstacles`` [N, K, 2] are the centres each rover must keep ``keep_out`` [N, K] away from.
    An obstacle blocks a rover when the straight line to its goal passes within the keep-out
    radius of the obstacle's centre before the goal. The rover then heads for the tangent of
    the keep-out circle on the side its heading already leans to, at the same speed, so it
    travels straight past instead of swerving late (momentum makes late swerves fail).
    """
    speed = jnp.linalg.norm(vel_des, axis=-1, keepdims=True)
    heading = vel_des / jnp.maximum(speed, 1e-9)
    to_goal = jnp.linalg.norm(goal - pos, axis=-1)
    # two passes, so that a turn taken for a later obstacle is checked against earlier ones
    for k in list(range(obstacles.shape[1])) * 2:
        to_obstacle = obstacles[:, k] - pos  # [N, 2]
        dist = jnp.linalg.norm(to_obstacle, axis=-1)
        along = jnp.sum(heading * to_obstacle, axis=-1)
        across = heading[:, 0] * to_obstacle[:, 1] - heading[:, 1] * to_obstacle[:, 0]
        blocked = (along > 0) & (jnp.abs(across) < keep_out[:, k]) & (along < to_goal + keep_out[:, k])
        # turn away from the obstacle's centre by the tangent angle (90 degrees once inside)
        angle = jnp.arcsin(jnp.clip(keep_out[:, k] / jnp.maximum(dist, 1e-9), 0.0, 1.0))
        angle = jnp.where(across > 0, -angle, angle)
        unit = to_obstacle / jnp.maximum(dist, 1e-9)[:, None]
        cos, sin = jnp.cos(angle)[:, None], jnp.sin(angle)[:, None]
        tangent = jnp.concatenate(
            [cos * unit[:, :1] - sin * unit[:, 1:], sin * unit[:, :1] + cos * unit[:, 1:]], axis=-1
        )
        heading = jnp.where(blocked[:, None], tangent, heading)
    return heading * speed


def oracle_act(
    key: jax.Array, obs: jax.Array, state: EnvState, plan: OraclePlan, weights: Any, params: EnvParams
) -> jax.Array:
    """The oracle as a :class:`~roverswarm.policies.Policy`'s act: :func:`oracle_actions`."""
    return oracle_actions(state, plan, params)


def oracle_actions(state: EnvState, plan: OraclePlan, params: EnvParams) -> jax.Array:
    """[N, 2] the oracle's actions in one environment: each rover's velocity towards its goal
    (:func:`oracle_goals`), steered around traps and the other rovers, as an action in [-1, 1]."""
    goal = oracle_goals(state, plan, params)
    decay = 1.0 - params.damping
    gain = params.sensitivity / params.mass * params.dt  # velocity change per unit action
    # the current velocity moves the rover this step whatever we do; steer from there
    next_pos = state.rover_pos + state.rover_vel * params.dt
    vel_des = _clip_norm((goal - next_pos) / (params.dt * _APPROACH_STEPS), gain / (1.0 - decay))
    # keep clear of traps and of the other rovers (at their predicted positions)
    n, t = params.num_rovers, params.num_traps
    # traps last: a trap contact costs as much as a collision and is never needed
    obstacles = jnp.concatenate([next_pos[other_rovers(n)], jnp.broadcast_to(state.trap_pos, (n, t, 2))], axis=1)
    keep_out = (
        jnp.concatenate([jnp.full((n - 1,), 2 * params.rover_radius), trap_radii(params) + params.rover_radius])
        + _KEEP_OUT_MARGIN
    )
    keep_out = jnp.broadcast_to(keep_out, (n, keep_out.shape[0]))
    masks = masks_of(state)
    if masks is not None:  # nothing to steer around where a padded layout has no rover or trap
        exists = jnp.concatenate([masks.rovers[other_rovers(n)], jnp.broadcast_to(masks.traps, (n, t))], axis=1)
        keep_out = jnp.where(exists, keep_out, 0.0)
    vel_des = _steer_around(next_pos, vel_des, goal, obstacles, keep_out)
    # scale rather than clip per component, so the steered direction is kept
    return _clip_norm((vel_des - decay * state.rover_vel) / gain, 1.0, ord=jnp.inf)


def _clip_norm(x: jax.Array, max_norm: float, ord: float = 2) -> jax.Array:
    """Scale each row of ``x`` [N, 2] down to norm ``max_norm`` if it is longer."""
    norm = jnp.linalg.norm(x, ord=ord, axis=-1, keepdims=True)
    return x * jnp.minimum(1.0, max_norm / jnp.maximum(norm, 1e-9))
