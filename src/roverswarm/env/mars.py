"""The Mars exploration environment (paper sections II.A and IV.A) as pure JAX functions.

Shape legend
    N  rovers (the agents), P  points of interest (POIs), T  traps (craters),
    O  observation size of one rover = 4 + 2P + 2T + 2(N - 1),
    A  action size of one rover = 2 (a force in [-1, 1]^2, scaled by ``sensitivity``).

Physics is the Multi-Particle Environment model, integrated in the order of mpe2's
``World.step`` (position from the old velocity first, then damping and force), so one step
can be checked against mpe2's ``simple_spread`` to float precision.

Reward of rover i (paper eq. 16)::

    r_i = - sum_j min_m ||p_m - poi_j||  -  C_rr(i)  -  C_rt(i)

the swarm's coverage distance (shared by all rovers), the number of other rovers that rover i
touches and the number of traps it touches. An *episode reward* in roverswarm is the sum of
``r_i`` over all rovers and all steps (as the reference MADDPG code reports it); per-rover
episode rewards are reported too. Published MPE numbers that average over agents differ by
exactly a factor N.

Episodes last ``max_steps`` (25) steps. The time limit is a *truncation*: learners bootstrap
through it. ``terminated`` is only ever true in mission mode (``terminate_on_complete``), when
every POI has been observed.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from roverswarm.env.autoreset import where_done
from roverswarm.env.layouts import NEVER, Masks, draw_failures, draw_layout
from roverswarm.errors import UserError

ACTION_SIZE = 2


@struct.dataclass
class EnvParams:
    """Static sizes (not traced) and physical/reward constants (traced: can be vmapped)."""

    num_rovers: int = struct.field(pytree_node=False, default=3)
    num_pois: int = struct.field(pytree_node=False, default=3)
    num_traps: int = struct.field(pytree_node=False, default=3)
    max_steps: int = struct.field(pytree_node=False, default=25)
    terminate_on_complete: bool = struct.field(pytree_node=False, default=False)
    # observations list each rover's POIs, traps and other rovers nearest first (not in index order)
    nearest_first: bool = struct.field(pytree_node=False, default=False)
    map_size: float = 1.0  # half-width of the square map [-map_size, map_size]^2
    rover_radius: float = 0.15
    poi_radius: float = 0.05  # drawn size only: POIs never collide
    trap_radius: float = 0.1  # scalar, or [T] per trap
    observe_radius: float = 0.1  # a POI is observed when a rover's centre is this close; scalar or [P]
    dt: float = 0.1
    damping: float = 0.25
    mass: float = 1.0
    sensitivity: float = 5.0  # force = sensitivity * action
    contact_force: float = 1e2
    contact_margin: float = 1e-3
    collision_penalty: float = 1.0  # reward per rover touched per step
    trap_penalty: float = 1.0  # reward per trap touched per step
    # A fixed layout (mission files): each None is drawn at reset instead.
    fixed_pois: jax.Array | None = None  # [P, 2]
    fixed_traps: jax.Array | None = None  # [T, 2]
    fixed_starts: jax.Array | None = None  # [N, 2]
    start_zone: jax.Array | None = None  # [2, 2] low and high corner of the rovers' release zone (default: the map)
    # Any swarm size in one program: the static counts above are then maxima, and only the first
    # ``active_*`` rovers, POIs and traps exist (traced, so a vmapped batch may mix sizes; see
    # :func:`is_padded`). None: every slot exists (an unpadded layout, masks never built).
    active_rovers: jax.Array | int | None = None  # [] int
    active_pois: jax.Array | int | None = None  # [] int
    active_traps: jax.Array | int | None = None  # [] int
    # Rover failures while training: with this probability per episode one active rover, drawn
    # uniformly, fails at a step drawn uniformly in [0, max_steps) (None or 0: none fails);
    # with ``fail_count`` K > 1, k rovers, k drawn uniformly in [1, min(K, active rovers - 1)].
    fail_rate: jax.Array | float | None = None  # [] float in [0, 1]
    fail_count: int = struct.field(pytree_node=False, default=1)


@struct.dataclass
class EnvState:
    """One episode's state. Leading batch axes appear only under vmap."""

    rover_pos: jax.Array  # [N, 2]
    rover_vel: jax.Array  # [N, 2]
    poi_pos: jax.Array  # [P, 2]
    trap_pos: jax.Array  # [T, 2]
    observed: jax.Array  # [P] bool, POI observed at some step of this episode
    time: jax.Array  # [] int32, steps taken in this episode
    fail_step: jax.Array  # [N] int32, rover i is frozen from step fail_step[i] on (NEVER: it never fails)
    # padded layouts (params with ``active_*``) only; None: every slot exists
    rover_mask: jax.Array | None = None  # [N] bool, the rover exists
    poi_mask: jax.Array | None = None  # [P] bool
    trap_mask: jax.Array | None = None  # [T] bool


def count_text(params: EnvParams) -> str:
    """'3 rovers, 3 POIs, 3 traps': the numbers a trained policy is tied to."""
    return f"{params.num_rovers} rovers, {params.num_pois} POIs, {params.num_traps} traps"


OWN_POSITION = slice(2, 4)
"""Where a rover's own position sits in its observation (after its velocity)."""


def observation_size(params: EnvParams) -> int:
    """Length O of one rover's observation vector."""
    return 4 + 2 * params.num_pois + 2 * params.num_traps + 2 * (params.num_rovers - 1)


def is_padded(params: EnvParams) -> bool:
    """Whether ``params`` give active counts, so that states carry masks (static: decided at trace time)."""
    return any(c is not None for c in (params.active_rovers, params.active_pois, params.active_traps))


def _active(count, size: int) -> jax.Array:
    """[size] bool: the first ``count`` slots (all if None)."""
    return jnp.arange(size) < (size if count is None else count)


def masks_of(state: EnvState) -> Masks | None:
    """The state's masks, or None for an unpadded layout (every slot exists)."""
    if state.rover_mask is None:
        return None
    return Masks(state.rover_mask, state.poi_mask, state.trap_mask)


def failed_rovers(state: EnvState) -> jax.Array:
    """[N] bool: the rovers that have failed (``time >= fail_step``) and stand still for good."""
    return state.time >= state.fail_step


def trap_radii(params: EnvParams) -> jax.Array:
    """[T] radius of each trap (``trap_radius`` broadcast)."""
    return jnp.broadcast_to(jnp.asarray(params.trap_radius, jnp.float32), (params.num_traps,))


def observe_radii(params: EnvParams) -> jax.Array:
    """[P] observation radius of each POI (``observe_radius`` broadcast)."""
    return jnp.broadcast_to(jnp.asarray(params.observe_radius, jnp.float32), (params.num_pois,))


def pairwise_dist(a: jax.Array, b: jax.Array) -> jax.Array:
    """[A, 2], [B, 2] -> [A, B] Euclidean distances; where two points coincide (a rover on a
    POI) the distance is 0 with a gradient of 0, not the square root's NaN."""
    squared = jnp.sum(jnp.square(a[:, None, :] - b[None, :, :]), axis=-1)
    apart = squared > 0
    return jnp.where(apart, jnp.sqrt(jnp.where(apart, squared, 1.0)), 0.0)


def coverage_distance(rover_pos: jax.Array, poi_pos: jax.Array, masks: Masks | None = None) -> jax.Array:
    """The swarm's coverage distance: sum over POIs [P, 2] of the nearest rover's [N, 2] distance
    (with ``masks``, over the POIs that exist, of the nearest rover that exists)."""
    dist = pairwise_dist(rover_pos, poi_pos)
    if masks is None:
        return jnp.sum(jnp.min(dist, axis=0))
    nearest = jnp.min(jnp.where(masks.rovers[:, None], dist, jnp.inf), axis=0)
    return jnp.sum(jnp.where(masks.pois, nearest, 0.0))


def unobserved_distance(state: EnvState, masks: Masks | None = None) -> jax.Array:
    """[] Sum over the POIs not yet observed (that exist) of the nearest *working* rover's
    distance (a rover that exists and has not failed; 0 for a POI when none works): how far
    the swarm still is from finishing its survey."""
    working = ~failed_rovers(state)
    pois = ~state.observed
    if masks is not None:
        working, pois = working & masks.rovers, pois & masks.pois
    nearest = jnp.min(jnp.where(working[:, None], pairwise_dist(state.rover_pos, state.poi_pos), jnp.inf), axis=0)
    return jnp.sum(jnp.where(pois & jnp.isfinite(nearest), nearest, 0.0))


def reset(key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
    """Start an episode: POIs, then traps clear of POIs, then rovers clear of traps, drawn
    with ``key`` by :func:`~roverswarm.env.layouts.draw_layout` (uniform positions, 16
    candidates per trap and rover, unless the params fix them). No rover has failed
    (``fail_step`` is NEVER) unless ``fail_rate`` draws a failure, from a key of its own (the
    layout is the same whatever the rate).

    Padded params (``active_*``): every slot is drawn, the state carries masks, and only the
    entities that exist keep each other clear.

    Returns ``(obs [N, O], state)``.
    """
    n, p, t = params.num_rovers, params.num_pois, params.num_traps
    masks = None
    if is_padded(params):
        masks = Masks(_active(params.active_rovers, n), _active(params.active_pois, p), _active(params.active_traps, t))
    poi_pos, trap_pos, rover_pos = draw_layout(key, params, trap_radii(params), masks)
    fail_step = jnp.full((n,), NEVER, jnp.int32)
    if params.fail_rate is not None:
        active = n if params.active_rovers is None else params.active_rovers
        fail_step = draw_failures(jax.random.fold_in(key, 3), params, active)
    state = EnvState(
        rover_pos=jnp.asarray(rover_pos, jnp.float32),
        rover_vel=jnp.zeros((n, 2)),
        poi_pos=jnp.asarray(poi_pos, jnp.float32),
        trap_pos=jnp.asarray(trap_pos, jnp.float32),
        observed=jnp.zeros((p,), bool),
        time=jnp.zeros((), jnp.int32),
        fail_step=fail_step,
        rover_mask=None if masks is None else masks.rovers,
        poi_mask=None if masks is None else masks.pois,
        trap_mask=None if masks is None else masks.traps,
    )
    state = state.replace(observed=_observed_now(state, params))
    return observe(state, params), state


def other_rovers(num_rovers: int) -> np.ndarray:
    """[N, N - 1] int: row i lists every rover but i, in index order."""
    return np.array([[j for j in range(num_rovers) if j != i] for i in range(num_rovers)], dtype=np.int32).reshape(
        num_rovers, num_rovers - 1
    )


def observe(state: EnvState, params: EnvParams) -> jax.Array:
    """Observations ``[N, O]``: own velocity, own position, then positions relative to the
    rover of all POIs, all traps and all other rovers: in index order (skipping itself), or
    with ``params.nearest_first`` each of the three groups ordered nearest first.

    The nearest-first view is the same for every permutation of the layout's POIs, traps and
    rovers, so a network need not learn each assignment of indices to places. In a padded
    layout the slots of entities that do not exist (and the rows of rovers that do not) hold
    zeros, after the real ones in each group."""
    return observe_positions(state.rover_pos, state.rover_vel, state.poi_pos, state.trap_pos, params, masks_of(state))


def observe_positions(
    rover_pos: jax.Array,
    rover_vel: jax.Array,
    poi_pos: jax.Array,
    trap_pos: jax.Array,
    params: EnvParams,
    masks: Masks | None = None,
) -> jax.Array:
    """:func:`observe` from the only parts of the state it reads (rovers [N, 2], POIs [P, 2],
    traps [T, 2], and a padded layout's masks): what the compact replay keeps to rebuild observations."""
    others = other_rovers(params.num_rovers)
    groups = [poi_pos[None] - rover_pos[:, None], trap_pos[None] - rover_pos[:, None]]
    groups.append(rover_pos[others] - rover_pos[:, None])  # [N, N - 1, 2]
    if masks is None:
        if params.nearest_first:
            groups = [_nearest_first(g) for g in groups]
        flat = [g.reshape(params.num_rovers, -1) for g in groups]
        return jnp.concatenate([rover_vel, rover_pos, *flat], axis=-1)
    exists = [
        jnp.broadcast_to(masks.pois, groups[0].shape[:2]),
        jnp.broadcast_to(masks.traps, groups[1].shape[:2]),
        masks.rovers[others],
    ]
    if params.nearest_first:
        groups, exists = zip(*(_nearest_first(g, e) for g, e in zip(groups, exists)))
    else:  # index order keeps the real entities first: they are the first slots
        groups = [jnp.where(e[..., None], g, 0.0) for g, e in zip(groups, exists)]
    flat = [g.reshape(params.num_rovers, -1) for g in groups]
    obs = jnp.concatenate([rover_vel, rover_pos, *flat], axis=-1)
    return jnp.where(masks.rovers[:, None], obs, 0.0)


def _nearest_first(rel: jax.Array, exists: jax.Array | None = None):
    """[N, K, 2] relative positions -> the same, each row's K points ordered by distance.
    With ``exists`` [N, K]: the real points first, zeros after them; returns (points, exists) reordered."""
    dist = jnp.sum(jnp.square(rel), axis=-1)
    if exists is None:
        order = jnp.argsort(dist, axis=-1, stable=True)
        return jnp.take_along_axis(rel, order[..., None], axis=1)
    order = jnp.argsort(jnp.where(exists, dist, jnp.inf), axis=-1, stable=True)
    exists = jnp.take_along_axis(exists, order, axis=1)
    return jnp.where(exists[..., None], jnp.take_along_axis(rel, order[..., None], axis=1), 0.0), exists


def _observed_now(state: EnvState, params: EnvParams) -> jax.Array:
    near = pairwise_dist(state.rover_pos, state.poi_pos) < observe_radii(params)
    masks = masks_of(state)
    if masks is None:
        return state.observed | jnp.any(near, axis=0)
    return (state.observed | jnp.any(near & masks.rovers[:, None], axis=0)) & masks.pois


def contact_forces(pos: jax.Array, params: EnvParams, exists: jax.Array | None = None) -> jax.Array:
    """[N, 2] positions -> [N, 2] total soft contact force on each rover from the others (only
    between rovers that ``exists`` [N] says exist, if given)."""
    n = params.num_rovers
    delta = pos[:, None, :] - pos[None, :, :]  # [N, N, 2], rover a minus rover b
    eye = jnp.eye(n, dtype=bool)
    squared = jnp.sum(jnp.square(delta), axis=-1)
    # a rover and itself, or two at one spot (no direction to push; delta is 0 there): a distance
    # of 1 instead of 0 inside the root, whose gradient at 0 is infinite and made every
    # gradient through a later step NaN
    dist = jnp.sqrt(jnp.where(eye | (squared == 0), 1.0, squared))
    k = params.contact_margin
    penetration = jnp.logaddexp(0.0, -(dist - 2 * params.rover_radius) / k) * k
    force = params.contact_force * delta / dist[..., None] * penetration[..., None]
    apart = eye if exists is None else eye | ~(exists[:, None] & exists[None, :])
    return jnp.sum(jnp.where(apart[..., None], 0.0, force), axis=1)


def check_actions(actions: jax.Array, params: EnvParams) -> None:
    """Raise :class:`UserError` unless ``actions`` has shape ``[N, 2]`` (checked at trace time)."""
    expected = (params.num_rovers, ACTION_SIZE)
    if tuple(actions.shape) != expected:
        raise UserError(f"actions must have shape {expected} (one 2-D force per rover), got {tuple(actions.shape)}")


def step_env(
    state: EnvState, actions: jax.Array, params: EnvParams
) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, jax.Array]]:
    """Advance one step without auto-reset. ``actions`` is ``[N, 2]``, clipped to [-1, 1].

    A failed rover (``state.time >= state.fail_step``) stays where it is, whatever its action
    and whatever pushes it; it still counts in contacts and coverage: the others can touch it,
    and it covers the POIs near it (the same rule in training, evaluation and ``mission stress``).
    In a padded layout a rover that does not exist never moves, touches nothing, covers nothing
    and earns 0; POIs and traps that do not exist are not there for anyone.

    Returns ``(obs [N, O], state, rewards [N], terminated [], truncated [], info)`` where info
    holds ``collisions`` [N] (other rovers touched), ``trap_contacts`` [N] (traps touched),
    ``trap_gaps`` [N, T] (each rover's distance to each trap less both radii; below 0 is a
    contact; infinite for a rover or trap that does not exist),
    ``coverage_distance`` [] (sum over POIs of the nearest rover's distance),
    ``pois_observed`` [] (POIs observed so far this episode), ``pois_first_observed`` []
    (POIs observed for the first time at this step) and ``unobserved_distance`` [] (sum over
    the POIs not yet observed of the nearest working rover's distance, :func:`unobserved_distance`).
    """
    check_actions(actions, params)
    masks = masks_of(state)
    exists = None if masks is None else masks.rovers
    force = params.sensitivity * jnp.clip(actions, -1.0, 1.0)
    force = force + contact_forces(state.rover_pos, params, exists)
    pos = state.rover_pos + state.rover_vel * params.dt
    vel = state.rover_vel * (1.0 - params.damping) + force / params.mass * params.dt
    frozen = failed_rovers(state)
    if masks is not None:  # a rover that does not exist stands still
        frozen = frozen | ~masks.rovers
    pos = jnp.where(frozen[:, None], state.rover_pos, pos)
    vel = jnp.where(frozen[:, None], 0.0, vel)
    state = state.replace(rover_pos=pos, rover_vel=vel, time=state.time + 1)
    seen_before = jnp.sum(state.observed)
    state = state.replace(observed=_observed_now(state, params))
    seen = jnp.sum(state.observed)

    rover_dist = pairwise_dist(pos, pos)
    touching = (rover_dist < 2 * params.rover_radius) & ~jnp.eye(params.num_rovers, dtype=bool)
    trap_dist = pairwise_dist(pos, state.trap_pos)
    reach = params.rover_radius + trap_radii(params)  # centre distance at which a rover touches each trap
    in_trap = trap_dist < reach
    trap_gaps = trap_dist - reach
    if masks is not None:
        touching = touching & masks.rovers[:, None] & masks.rovers[None, :]
        in_trap = in_trap & masks.rovers[:, None] & masks.traps[None, :]
        trap_gaps = jnp.where(masks.rovers[:, None] & masks.traps[None, :], trap_gaps, jnp.inf)
    collisions = jnp.sum(touching, axis=1)
    trap_contacts = jnp.sum(in_trap, axis=1)
    coverage = coverage_distance(pos, state.poi_pos, masks)
    rewards = -coverage - params.collision_penalty * collisions - params.trap_penalty * trap_contacts
    all_observed = jnp.all(state.observed)
    if masks is not None:  # a rover that does not exist earns nothing; a POI that does not exist needs no visit
        rewards = jnp.where(masks.rovers, rewards, 0.0)
        all_observed = jnp.all(state.observed | ~masks.pois)

    truncated = state.time >= params.max_steps
    terminated = jnp.asarray(params.terminate_on_complete) & all_observed
    info = {
        "collisions": collisions,
        "trap_contacts": trap_contacts,
        "trap_gaps": trap_gaps,
        "coverage_distance": coverage,
        "pois_observed": seen,
        "pois_first_observed": seen - seen_before,
        "unobserved_distance": unobserved_distance(state, masks),
    }
    return observe(state, params), state, rewards, terminated, truncated, info


def step(
    key: jax.Array, state: EnvState, actions: jax.Array, params: EnvParams
) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
    """:func:`step_env` with auto-reset: when the episode ends (terminated or truncated) the
    returned observation and state are those of ``reset(key, params)``, a fresh episode, and
    the last observation of the finished episode is kept in ``info["final_obs"]`` [N, O].

    The reset is drawn only where an episode ended, also under ``jax.vmap``
    (:func:`~roverswarm.env.autoreset.where_done`), so a vmapped ``step`` costs little more
    than :func:`step_env` (see ``benchmarks/env_throughput.py``)."""
    obs, next_state, rewards, terminated, truncated, info = step_env(state, actions, params)
    done = terminated | truncated
    reset_obs, reset_state = where_done(done, reset, params.max_steps, key, params)
    next_state = jax.tree.map(lambda r, s: jnp.where(done, r, s), reset_state, next_state)
    info = {**info, "final_obs": obs}
    return jnp.where(done, reset_obs, obs), next_state, rewards, terminated, truncated, info
