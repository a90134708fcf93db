"""How a rover steers round what is in its way: the rule the oracle drives by, and the safety
layer (``--shield``) that applies it to any policy's action.

Both work on the known dynamics (:func:`~roverswarm.env.mars.step_env`): the velocity after a
step is ``(1 - damping) * v + gain * action``, and the position moves by the *current*
velocity first, so a rover steers from where it will be after this step. An obstacle (a trap,
or another rover at its predicted position) blocks a rover when its heading passes within the
obstacle's keep-out radius (the two bodies' radii plus :data:`KEEP_OUT_MARGIN`, or the smaller
:data:`FAILED_MARGIN` round a failed rover) before the rover's reach; the rover then heads
along the tangent of the keep-out circle, on the side its heading leans to, at the same speed
(:func:`steer_around`).

The safety layer (:func:`shield_actions`) takes the velocity a policy's action asks for,
looks :data:`SHIELD_STEPS` steps ahead along it, and turns it as the oracle would; an action
whose way is clear passes unchanged. It is a fixed layer, not learned: it reads the rover's
own velocity and where the traps and the other rovers are and go (their velocities predict
their next positions; only what is within its few steps' reach can turn it: what a rover's
hazard cameras would see), never the POIs or a plan.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from roverswarm.env.mars import EnvParams, EnvState, failed_rovers, masks_of, other_rovers, trap_radii

KEEP_OUT_MARGIN = 0.05
"""Clearance kept from a trap's or a working rover's edge (a working rover's velocity predicts
where it will be only roughly)."""
FAILED_MARGIN = 0.03
"""Clearance kept from a failed rover's edge: it stands still, so less than
:data:`KEEP_OUT_MARGIN` keeps the others clear of it, and a POI it stands against stays in
reach (with the full margin the oracle lost missions whose last POI stood 0.25 from a failed
rover's centre; with none it touched failed rovers). Measured in
``docs/results/any-size/README.md``, section "Where the layer lost missions"."""
SHIELD_STEPS = 3.0
"""How many steps ahead, at the velocity its action asks for, the safety layer looks."""


def dynamics(params: EnvParams) -> tuple[float, float]:
    """``(decay, gain)``: the share of its velocity a rover keeps over a step, and the velocity
    change per unit of action."""
    return 1.0 - params.damping, params.sensitivity / params.mass * params.dt


def next_positions(state: EnvState, params: EnvParams) -> jax.Array:
    """[N, 2] where every rover will be after this step, whatever it does: its current velocity
    moves it first, unless it has failed (a failed rover stays where it is)."""
    return jnp.where(failed_rovers(state)[:, None], state.rover_pos, state.rover_pos + state.rover_vel * params.dt)


def obstacles(state: EnvState, params: EnvParams, next_pos: jax.Array) -> tuple[jax.Array, jax.Array]:
    """What every rover keeps clear of: the centres [N, K, 2] (the other rovers at their
    ``next_pos``, then the traps; traps last, as a contact with one is never needed) and their
    keep-out radii [N, K] (0 where a padded layout has no rover or trap): the bodies' radii plus
    :data:`KEEP_OUT_MARGIN`, or :data:`FAILED_MARGIN` round a failed rover."""
    n, t = params.num_rovers, params.num_traps
    centres = jnp.concatenate([next_pos[other_rovers(n)], jnp.broadcast_to(state.trap_pos, (n, t, 2))], axis=1)
    failed = failed_rovers(state)[other_rovers(n)]  # [N, N - 1]
    rovers = 2 * params.rover_radius + jnp.where(failed, FAILED_MARGIN, KEEP_OUT_MARGIN)
    traps = jnp.broadcast_to(trap_radii(params) + params.rover_radius + KEEP_OUT_MARGIN, (n, t))
    keep_out = jnp.concatenate([rovers, traps], axis=1)
    masks = masks_of(state)
    if masks is not None:  # nothing to steer around where a padded layout has no rover or trap
        exists = jnp.concatenate([masks.rovers[other_rovers(n)], jnp.broadcast_to(masks.traps, (n, t))], axis=1)
        keep_out = jnp.where(exists, keep_out, 0.0)
    return centres, keep_out


def steer_around(
    pos: jax.Array, velocity: jax.Array, reach: jax.Array, centres: jax.Array, keep_out: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Re-aim each rover's velocity [N, 2] along the tangent of any obstacle it would cross.

    ``centres`` [N, K, 2] are what each rover at ``pos`` [N, 2] must keep ``keep_out`` [N, K]
    away from. An obstacle blocks a rover when its heading passes within the keep-out radius of
    the obstacle's centre, ahead of it and nearer than ``reach`` [N] plus that radius. The rover
    then heads for the tangent of the keep-out circle on the side its heading already leans to,
    at the same speed, so it travels straight past instead of swerving late (momentum makes
    late swerves fail). Returns the velocity and [N] bool: whether any obstacle turned it.
    """
    speed = jnp.linalg.norm(velocity, axis=-1, keepdims=True)
    heading = velocity / jnp.maximum(speed, 1e-9)
    turned = jnp.zeros(pos.shape[0], bool)
    # two passes, so that a turn taken for a later obstacle is checked against earlier ones
    for k in list(range(centres.shape[1])) * 2:
        to_obstacle = centres[:, k] - pos  # [N, 2]
        dist = jnp.linalg.norm(to_obstacle, axis=-1)
        along = jnp.sum(heading * to_obstacle, axis=-1)
        across = heading[:, 0] * to_obstacle[:, 1] - heading[:, 1] * to_obstacle[:, 0]
        blocked = (along > 0) & (jnp.abs(across) < keep_out[:, k]) & (along < reach + keep_out[:, k])
        # turn away from the obstacle's centre by the tangent angle (90 degrees once inside)
        angle = jnp.arcsin(jnp.clip(keep_out[:, k] / jnp.maximum(dist, 1e-9), 0.0, 1.0))
        angle = jnp.where(across > 0, -angle, angle)
        unit = to_obstacle / jnp.maximum(dist, 1e-9)[:, None]
        cos, sin = jnp.cos(angle)[:, None], jnp.sin(angle)[:, None]
        tangent = jnp.concatenate(
            [cos * unit[:, :1] - sin * unit[:, 1:], sin * unit[:, :1] + cos * unit[:, 1:]], axis=-1
        )
        heading = jnp.where(blocked[:, None], tangent, heading)
        turned = turned | blocked
    return heading * speed, turned


def action_for(velocity: jax.Array, state: EnvState, params: EnvParams) -> jax.Array:
    """[N, 2] the action in [-1, 1] that gives each rover ``velocity`` after this step, scaled
    down as a whole (not clipped per component, so its direction is kept) where out of reach."""
    decay, gain = dynamics(params)
    return clip_norm((velocity - decay * state.rover_vel) / gain, 1.0, ord=jnp.inf)


def shield_actions(state: EnvState, actions: jax.Array, params: EnvParams) -> jax.Array:
    """The safety layer (``--shield``) on one environment's ``actions`` [N, 2]: each rover's
    action clipped to [-1, 1], and where the velocity it asks for would carry the rover, within
    :data:`SHIELD_STEPS` steps, into a trap's or another rover's keep-out circle, the action that
    turns that velocity along the circle's tangent (:func:`steer_around`), scaled down as a
    whole where the turn needs more than a full action (so the turn is then short of the
    tangent). Actions whose way is clear pass unchanged (clipped); failed and absent rovers do
    not move whatever they get, and a failed rover is an obstacle where it stands."""
    decay, gain = dynamics(params)
    clipped = jnp.clip(actions, -1.0, 1.0)
    next_pos = next_positions(state, params)
    velocity = decay * state.rover_vel + gain * clipped
    reach = jnp.linalg.norm(velocity, axis=-1) * params.dt * SHIELD_STEPS
    steered, turned = steer_around(next_pos, velocity, reach, *obstacles(state, params, next_pos))
    return jnp.where(turned[:, None], action_for(steered, state, params), clipped)


def clip_norm(x: jax.Array, max_norm: float, ord: float = 2) -> jax.Array:
    """Scale each row of ``x`` [N, 2] down to norm ``max_norm`` if it is longer."""
    norm = jnp.linalg.norm(x, ord=ord, axis=-1, keepdims=True)
    return x * jnp.minimum(1.0, max_norm / jnp.maximum(norm, 1e-9))
