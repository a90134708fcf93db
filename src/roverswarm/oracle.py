"""The oracle: the yardstick every score is normalised by, and the teacher ``--teacher`` imitates.

It assigns rovers to POIs by the Hungarian method (minimum total distance, SciPy's
``linear_sum_assignment``, host-side once per episode: :func:`oracle_plan`) and then drives
each rover to its POI with a go-to-goal controller on the known dynamics that heads along the
tangent of any trap or other rover in its way (:func:`oracle_act`, jittable; the steering is
:mod:`roverswarm.steering`'s, which the safety layer ``--shield`` shares). Rovers whose POI
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

from roverswarm.env.entities import hand_over, match_pois
from roverswarm.env.mars import EnvParams, EnvState, failed_rovers, masks_of, pairwise_dist
from roverswarm.steering import action_for, clip_norm, dynamics, next_positions, obstacles, steer_around

# How many steps the controller takes to close the remaining distance to its goal (1 = deadbeat, larger = gentler).
_APPROACH_STEPS = 2.0


def assign_pois(rover_pos: np.ndarray, poi_pos: np.ndarray) -> np.ndarray:
    """Optimal assignment (Hungarian method) of rovers ``[N, 2]`` to POIs ``[P, 2]``.

    Minimises the total rover-to-POI distance. Returns the POI index of each rover ``[N]``,
    -1 for a rover left without one (N > P).
    """
    from scipy.optimize import linear_sum_assignment  # here: half a second that processes without the oracle skip

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
    working = ~failed_rovers(state)  # [N]
    pois = jnp.ones(params.num_pois, bool)
    masks = masks_of(state)
    if masks is not None:  # the empty slots of a padded layout neither work nor need a visit
        working, pois = working & masks.rovers, masks.pois
    dist = pairwise_dist(state.rover_pos, state.poi_pos)  # [N, P]
    target = hand_over(plan.poi, dist, working, pois, state.observed)  # the plan's POI unless handed another
    return jnp.where((target >= 0)[:, None], state.poi_pos[jnp.maximum(target, 0)], plan.home)


def oracle_act(
    key: jax.Array, obs: jax.Array, state: EnvState, plan: OraclePlan, weights: Any, params: EnvParams
) -> jax.Array:
    """The oracle as a :class:`~roverswarm.policies.Policy`'s act: :func:`oracle_actions`."""
    return oracle_actions(state, plan, params)


def oracle_actions(state: EnvState, plan: OraclePlan, params: EnvParams) -> jax.Array:
    """[N, 2] the oracle's actions in one environment: each rover's velocity towards its goal
    (:func:`oracle_goals`), steered around traps and the other rovers
    (:func:`~roverswarm.steering.steer_around`), as an action in [-1, 1]."""
    goal = oracle_goals(state, plan, params)
    decay, gain = dynamics(params)
    # the current velocity moves the rover this step whatever we do; steer from there
    next_pos = next_positions(state, params)
    velocity = clip_norm((goal - next_pos) / (params.dt * _APPROACH_STEPS), gain / (1.0 - decay))
    reach = jnp.linalg.norm(goal - next_pos, axis=-1)
    steered, _ = steer_around(next_pos, velocity, reach, *obstacles(state, params, next_pos))
    return action_for(steered, state, params)
