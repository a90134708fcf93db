"""The layout sampler: where an episode's POIs, traps and rovers start (paper section IV.A),
and which rovers fail when (training's ``fail_rate``, :func:`draw_failures`).

Shape legend: N rovers, P POIs, T traps, C candidate positions per trap or rover
(:data:`LAYOUT_CANDIDATES`).

Positions are uniform in the map (rovers: in ``start_zone`` if set) unless the params fix them
(``fixed_pois``, ``fixed_traps``, ``fixed_starts``: a mission's layout). A drawn trap keeps
``trap_radius + rover_radius`` away from every POI (so a rover sitting on a POI touches no
trap) and a drawn rover starts outside every trap (in a ``start_zone``, also clear of the rovers
placed before it); each uses the first of its C uniform candidates that satisfies this, the
first candidate if none does: a fixed-size, jittable rejection sampler.

Cost: one distance per candidate and obstacle, C (P T + N T) in all, computed as separate x and
y differences and reduced to the first clear candidate without a gather (XLA's CPU code for a
size-2 last axis and for ``take_along_axis`` under ``vmap`` cost ten times more at N = 32). A
start zone places its rovers in turn, in a loop of N steps (a rover's choice depends on those
before it).

This module imports nothing of the environment (:mod:`roverswarm.env.mars` imports it):
``params`` below is an :class:`~roverswarm.env.mars.EnvParams`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

LAYOUT_CANDIDATES = 16
"""Candidate positions drawn per trap and per rover."""


@struct.dataclass
class Masks:
    """Which slots of a padded layout exist."""

    rovers: jax.Array  # [N] bool
    pois: jax.Array  # [P] bool
    traps: jax.Array  # [T] bool


def clear_of(
    candidates: jax.Array, obstacles: jax.Array, clearance: jax.Array, exists: jax.Array | None = None
) -> jax.Array:
    """[K, C, 2] candidates, [B, 2] obstacles, [B] or broadcastable clearance -> [K, C] bool:
    the candidate is at least ``clearance`` from every obstacle that ``exists`` ([B] bool; all if None)."""
    dx = candidates[..., 0, None] - obstacles[:, 0]  # [K, C, B]
    dy = candidates[..., 1, None] - obstacles[:, 1]
    far = jnp.sqrt(dx * dx + dy * dy) >= clearance
    if exists is not None:
        far = far | ~exists
    return jnp.all(far, axis=-1)


def first_of(candidates: jax.Array, ok: jax.Array) -> jax.Array:
    """[K, C, 2] candidates, [K, C] bool -> [K, 2]: each item's first ``ok`` candidate, its first
    candidate if none is."""
    count = candidates.shape[1]
    index = jnp.min(jnp.where(ok, jnp.arange(count), count), axis=-1)
    pick = jnp.arange(count) == jnp.where(index == count, 0, index)[:, None]  # [K, C], one True per row
    return jnp.sum(jnp.where(pick[..., None], candidates, 0.0), axis=1)


def place_in_turn(candidates: jax.Array, ok: jax.Array, spacing, exists: jax.Array | None = None) -> jax.Array:
    """[N, C, 2] candidates, [N, C] bool -> [N, 2]: rover i takes its first ``ok`` candidate
    at least ``spacing`` from rovers 0 .. i-1 (those that ``exists`` [N] says exist), its first
    candidate if none is.

    N turns of one rover each. (Rounds of every rover at once until no choice changes give the
    same layouts, but a crowded zone needs many rounds: 1.8x slower at N = 32.)"""
    n = candidates.shape[0]
    earlier_exists = jnp.ones((n,), bool) if exists is None else exists

    def place(i, placed):
        clear = clear_of(candidates[i, None], placed, spacing, earlier_exists & (jnp.arange(n) < i))
        return placed.at[i].set(first_of(candidates[i, None], ok[i, None] & clear)[0])

    return jax.lax.fori_loop(0, n, place, jnp.zeros((n, 2), candidates.dtype))


def draw_layout(
    key: jax.Array, params, trap_radius: jax.Array, masks: Masks | None = None
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """POIs, then traps clear of POIs, then rovers clear of traps (see the module docstring).

    ``trap_radius`` is [T]; with ``masks`` only the entities that exist keep each other clear
    (every slot is drawn). Returns ``(poi_pos [P, 2], trap_pos [T, 2], rover_pos [N, 2])``.
    """
    n, p, t = params.num_rovers, params.num_pois, params.num_traps
    k_poi, k_trap, k_rover = jax.random.split(key, 3)
    size, keep = params.map_size, trap_radius + params.rover_radius
    poi_pos = params.fixed_pois
    if poi_pos is None:
        poi_pos = jax.random.uniform(k_poi, (p, 2), minval=-size, maxval=size)
    trap_pos = params.fixed_traps
    if trap_pos is None:
        trap_cand = jax.random.uniform(k_trap, (t, LAYOUT_CANDIDATES, 2), minval=-size, maxval=size)
        ok = clear_of(trap_cand, poi_pos, keep[:, None, None], None if masks is None else masks.pois)
        trap_pos = first_of(trap_cand, ok)
    rover_pos = params.fixed_starts
    if rover_pos is None:
        low, high = (-size, size) if params.start_zone is None else (params.start_zone[0], params.start_zone[1])
        rover_cand = jax.random.uniform(k_rover, (n, LAYOUT_CANDIDATES, 2), minval=low, maxval=high)
        ok = clear_of(rover_cand, trap_pos, keep, None if masks is None else masks.traps)
        if params.start_zone is None:
            rover_pos = first_of(rover_cand, ok)
        else:  # a release zone is crowded: each rover also keeps clear of those placed before it
            rover_pos = place_in_turn(rover_cand, ok, 2 * params.rover_radius, None if masks is None else masks.rovers)
    return poi_pos, trap_pos, rover_pos


NEVER = np.iinfo(np.int32).max
"""``fail_step`` of a rover that does not fail."""


def draw_failures(key: jax.Array, params, active_rovers) -> jax.Array:
    """[N] fail steps: with probability ``fail_rate`` one of the ``active_rovers`` first rovers,
    uniform, fails at a uniform step in [0, max_steps); NEVER elsewhere. With ``fail_count`` K >
    1, k - 1 more of them, distinct and uniform, each at its own uniform step, k drawn uniformly
    in [1, min(K, active_rovers - 1)] (one keeps working), from keys of their own: the first
    failure is drawn as with K = 1. A lone rover would fail too: training refuses --fail-rate
    for one rover (:func:`roverswarm.config.validate`), as ``mission stress`` does."""
    k_fails, k_rover, k_step = jax.random.split(key, 3)
    fails = jax.random.uniform(k_fails) < params.fail_rate
    index = jnp.arange(params.num_rovers)
    rover = jax.random.randint(k_rover, (), 0, active_rovers)
    when = jax.random.randint(k_step, (), 0, params.max_steps)
    fail_step = jnp.where(index == rover, when, NEVER)
    if params.fail_count > 1:
        # fold_in(key, 1) and (key, 2) are split(key, 3)'s second and third keys: 3 on
        k_count, k_order, k_steps = (jax.random.fold_in(key, j) for j in (3, 4, 5))
        most = jnp.maximum(jnp.minimum(params.fail_count, active_rovers - 1), 1)
        count = jax.random.randint(k_count, (), 1, most + 1)
        # the other active rovers in a random order; the first count - 1 of them fail too
        draw = jnp.where((index < active_rovers) & (index != rover), jax.random.uniform(k_order, index.shape), 2.0)
        more = jnp.argsort(jnp.argsort(draw)) < count - 1
        fail_step = jnp.where(more, jax.random.randint(k_steps, index.shape, 0, params.max_steps), fail_step)
    return jnp.where(fails, fail_step, NEVER).astype(jnp.int32)
