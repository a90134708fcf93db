"""The entity view: each rover sees itself and a padded set of typed entity tokens.

Shape legend
    N  rovers (the layout's maximum in a padded layout), P  POIs, T  traps,
    M  tokens per rover = (N - 1) + P + T: the other rovers, then the POIs, then the traps,
    F  features per token = :data:`TOKEN_FEATURES`.

Per rover i (pure JAX, jittable, vmappable; leading batch axes come only from vmap):

* ``own`` [N, 4]: its velocity and position (the flat view's first four numbers);
* ``tokens`` [N, M, 11], one per other entity, ``[dx, dy, dvx, dvy, is_rover, is_poi, is_trap,
  radius, flag, lead, claim]``: position and velocity relative to rover i (velocity 0 for POIs
  and traps, which never move), the type as a one-hot, the entity's radius (a rover's body, a
  POI's observation radius, a trap's radius), a flag (a rover: it has failed; a POI: it has
  been observed this episode; a trap: 0) and, for a POI, rover i's lead on it (:func:`poi_leads`:
  how much nearer rover i is than every other working rover, negative if another is nearer)
  and its claim lead (:func:`poi_claims`: the same against only the rovers whose nearest POI
  it is; with ``matched``, instead, 1 on the POI a greedy matching of the rovers to the POIs,
  crossing routes swapped and open POIs handed over, gives rover i, :func:`poi_matches`); both
  0 for rovers and traps. Other rovers in index order skipping i, then POIs, traps;
* ``mask`` [N, M] bool: the token is an entity that exists. In an unpadded layout every token
  exists; in a padded one the slots past the active counts do not (their features are zeros),
  and the rows of rovers that do not exist are all False.

It holds everything the flat view does (the flat view is its positions, relative to the rover,
POIs, then traps, then other rovers; nearest first is a sort of each type by distance) and more: the others'
velocities, who has failed, which POIs are done and which POIs each rover is nearest to (the
lead, which a rover could otherwise work out only from every other rover's position, beyond
what a nearest-K view keeps). Read as a set, it is the same under any permutation of the
layout's POIs, traps and other rovers, and it has no rover index, so a network over it
(:mod:`roverswarm.algos.entity`) serves any swarm size.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from roverswarm.env.mars import (
    EnvParams,
    EnvState,
    failed_rovers,
    masks_of,
    observe_radii,
    other_rovers,
    pairwise_dist,
    trap_radii,
)

OWN_FEATURES = 4
"""Own velocity (2) and position (2)."""
TOKEN_FEATURES = 11
"""Relative position (2), relative velocity (2), type one-hot (3), radius, flag, lead, claim."""
LEAD_CAP = 2.0
"""A POI's lead is clipped to [-LEAD_CAP, LEAD_CAP] (the default map's diagonal is 2.8)."""
ROVER, POI, TRAP = 0, 1, 2
"""Positions of the type one-hot in a token's features (after the first four)."""
FLAG = 8
"""Position of the flag in a token's features: a rover has failed, a POI has been observed."""
LEAD, CLAIM = 9, 10
"""Positions of the lead and the claim lead in a token's features (the last two)."""
POI_ORDERS = ("nearest", "free", "matched")
"""How a view of the K nearest orders its POI slots (``--poi-order``, :func:`observe_nearest`)."""


@struct.dataclass
class EntityView:
    """What every rover sees, as entities (leading batch axes only under vmap)."""

    own: jax.Array  # [N, OWN_FEATURES]
    tokens: jax.Array  # [N, M, TOKEN_FEATURES]
    mask: jax.Array  # [N, M] bool


def token_count(params: EnvParams) -> int:
    """M: tokens per rover, (N - 1) + P + T of the layout's (maximum) counts."""
    return params.num_rovers - 1 + params.num_pois + params.num_traps


def _tokens(
    rel_pos: jax.Array,
    rel_vel: jax.Array,
    kind: int,
    radius: jax.Array,
    flag: jax.Array,
    leads: tuple[jax.Array, jax.Array] | None = None,
) -> jax.Array:
    """[N, K, 2], [N, K, 2], a type, [N, K] radius, flag and (lead, claim lead) (None: 0)
    -> [N, K, TOKEN_FEATURES]."""
    one_hot = jnp.broadcast_to(jax.nn.one_hot(kind, 3, dtype=rel_pos.dtype), (*rel_pos.shape[:2], 3))
    lead, claim = (jnp.zeros_like(flag),) * 2 if leads is None else leads
    features = [rel_pos, rel_vel, one_hot, radius[..., None], flag[..., None], lead[..., None], claim[..., None]]
    return jnp.concatenate(features, axis=-1)


def poi_leads(dist: jax.Array, working: jax.Array) -> jax.Array:
    """[N, P] each rover's lead on each POI from the distances ``dist`` [N, P] (rovers to POIs,
    :func:`~roverswarm.env.mars.pairwise_dist`): the nearest other *working* rover's distance to
    the POI less its own, clipped to +-:data:`LEAD_CAP`. Positive: no other rover that can
    still move is closer (the POI is this rover's to take); negative: another is that much
    closer. ``working`` [N] bool: the rovers that exist and have not failed (the others are
    never nearest: a failed rover beside a POI will not take it; a rover with no working other
    gets +:data:`LEAD_CAP`)."""
    return _lead(dist, jnp.where(working[:, None], dist, jnp.inf))


def _lead(dist: jax.Array, rivals: jax.Array) -> jax.Array:
    """[N, P] the nearest *other* rover's distance to each POI in ``rivals`` [N, P] (inf: that
    rover is no rival for that POI) less each rover's own ``dist`` [N, P], clipped to
    +-:data:`LEAD_CAP`."""
    others = jnp.where(jnp.eye(dist.shape[0], dtype=bool)[:, :, None], jnp.inf, rivals[None])  # [N, N, P]
    return jnp.clip(jnp.min(others, axis=1) - dist, -LEAD_CAP, LEAD_CAP)


def poi_claims(dist: jax.Array, working: jax.Array, pois: jax.Array) -> jax.Array:
    """[N, P] each rover's *claim lead* on each POI: as :func:`poi_leads`, but against only the
    other working rovers whose nearest POI it is (their claim; the lowest index on a tie).
    ``pois`` [P] bool: the POIs that exist (only they are claimed). With the lead it tells a
    rover that a POI another rover is nearer to is still free, because that rover has a
    nearer one of its own: +:data:`LEAD_CAP` where no other rover claims the POI."""
    nearest = jnp.argmin(jnp.where(pois[None], dist, jnp.inf), axis=1)  # [N]
    claims = jax.nn.one_hot(nearest, dist.shape[1], dtype=bool) & working[:, None]
    return _lead(dist, jnp.where(claims, dist, jnp.inf))


def greedy_match(cost: jax.Array) -> jax.Array:
    """[N] the column of ``cost`` [N, P] each row is matched to, greedily: the cheapest finite
    (row, column) pair first, then the cheapest of the rows and columns left, one column per
    row; -1 for a row left without one (all its finite pairs taken, or none finite). Jittable."""
    n, p = cost.shape
    target = jnp.full(n, -1)
    for _ in range(min(n, p)):
        row, column = jnp.divmod(jnp.argmin(cost), p)
        found = jnp.isfinite(cost[row, column])
        target = jnp.where(found & (jnp.arange(n) == row), column, target)
        taken = found & ((jnp.arange(n) == row)[:, None] | (jnp.arange(p) == column)[None, :])
        cost = jnp.where(taken, jnp.inf, cost)
    return target


def hand_over(
    target: jax.Array, dist: jax.Array, working: jax.Array, pois: jax.Array, observed: jax.Array
) -> jax.Array:
    """[N] each rover's POI ``target`` [N] (-1: none) with the *open* POIs handed over, the
    oracle's rule: a POI that exists (``pois`` [P]), is not yet ``observed`` [P] and is the
    target of no ``working`` [N] rover (its rover failed, or there are more POIs than rovers)
    goes to a *free* rover (working, its own POI observed or none), by :func:`greedy_match` on
    their distances ``dist`` [N, P], one rover per POI. Other rovers keep their target. With
    every rover working and every POI someone's target nothing is open: ``target`` unchanged."""
    has = target >= 0
    index = jnp.maximum(target, 0)
    claimed = jnp.zeros(dist.shape[1], bool).at[index].max(has & working & ~observed[index])
    open_poi = pois & ~observed & ~claimed
    free = working & (~has | observed[index])
    handed = greedy_match(jnp.where(free[:, None] & open_poi[None, :], dist, jnp.inf))
    return jnp.where(handed >= 0, handed, target)


def uncross(target: jax.Array, dist: jax.Array) -> jax.Array:
    """[N] each rover's POI ``target`` [N] (-1: none) improved by swaps: while two rovers that
    both have a POI would drive less in sum with their POIs swapped (``dist`` [N, P]), swap the
    pair that saves the most, at most N times (2-opt). Two straight routes that cross always
    save by the swap (the triangle inequality), so the greedy matching's crossing routes, where
    rovers meet on the way, are undone. Jittable."""
    n = target.shape[0]
    rows = jnp.arange(n)
    for _ in range(n):
        has = target >= 0
        index = jnp.maximum(target, 0)
        own = dist[rows, index]
        cross = dist[:, index]  # [a, b]: rover a to rover b's POI
        gain = jnp.where(has[:, None] & has[None, :], own[:, None] + own[None, :] - cross - cross.T, 0.0)
        a, b = jnp.divmod(jnp.argmax(gain), n)
        do = gain[a, b] > 1e-6
        swapped = target.at[a].set(target[b]).at[b].set(target[a])
        target = jnp.where(do, swapped, target)
    return target


def match_pois(cost: jax.Array) -> jax.Array:
    """[N] the POI each rover is matched to (-1: none) by the costs ``cost`` [N, P] (inf: never):
    :func:`greedy_match`, its crossing routes undone (:func:`uncross`). The split of the work
    the matched view shows and the teacher's plan (:func:`~roverswarm.oracle.greedy_plan`)
    follows. Jittable."""
    return uncross(greedy_match(cost), cost)


def poi_matches(dist: jax.Array, working: jax.Array, pois: jax.Array, observed: jax.Array) -> jax.Array:
    """[N, P] 1 on the POI each rover is given, else 0 (a rover left without one, failed or not
    there: 0 everywhere): :func:`match_pois` of the ``working`` [N] rovers to the POIs that
    exist (``pois`` [P]) by their distances ``dist`` [N, P], then the POIs that leaves open
    (not ``observed`` [P], no working rover's) :func:`hand_over` to the rovers whose POI is
    observed. Recomputed at every step, it tells each rover which POI is its own in a
    one-to-one split of the work that still needs doing, and who takes over a failed rover's."""
    target = match_pois(jnp.where(working[:, None] & pois[None, :], dist, jnp.inf))
    target = hand_over(target, dist, working, pois, observed)
    return jax.nn.one_hot(target, dist.shape[1], dtype=dist.dtype)  # a row of -1 is all zeros


def observe_entities(state: EnvState, params: EnvParams, matched: bool = False) -> EntityView:
    """The entity view of every rover in ``state`` (see the module docstring for the features);
    with ``matched``, the POI tokens' claim feature holds :func:`poi_matches` instead of the
    claim lead (``--poi-order matched``)."""
    n, p, t = params.num_rovers, params.num_pois, params.num_traps
    pos, vel = state.rover_pos, state.rover_vel
    others = other_rovers(n)  # [N, N - 1]
    failed = failed_rovers(state)
    rovers = _tokens(
        pos[others] - pos[:, None],
        vel[others] - vel[:, None],
        ROVER,
        jnp.full((n, n - 1), params.rover_radius, pos.dtype),
        failed[others].astype(pos.dtype),
    )
    zero_vel = jnp.zeros((n, 1, 2), pos.dtype)
    masks = masks_of(state)
    working = ~failed if masks is None else masks.rovers & ~failed
    pois_exist = jnp.ones((p,), bool) if masks is None else masks.pois
    dist = pairwise_dist(pos, state.poi_pos)
    pois = _tokens(
        state.poi_pos[None] - pos[:, None],
        jnp.broadcast_to(zero_vel, (n, p, 2)),
        POI,
        jnp.broadcast_to(observe_radii(params), (n, p)),
        jnp.broadcast_to(state.observed.astype(pos.dtype), (n, p)),
        (
            poi_leads(dist, working),
            poi_matches(dist, working, pois_exist, state.observed)
            if matched
            else poi_claims(dist, working, pois_exist),
        ),
    )
    traps = _tokens(
        state.trap_pos[None] - pos[:, None],
        jnp.broadcast_to(zero_vel, (n, t, 2)),
        TRAP,
        jnp.broadcast_to(trap_radii(params), (n, t)),
        jnp.zeros((n, t), pos.dtype),
    )
    tokens = jnp.concatenate([rovers, pois, traps], axis=1)
    own = jnp.concatenate([vel, pos], axis=-1)
    if masks is None:
        return EntityView(own=own, tokens=tokens, mask=jnp.ones(tokens.shape[:2], bool))
    exists = jnp.concatenate(
        [masks.rovers[others], jnp.broadcast_to(masks.pois, (n, p)), jnp.broadcast_to(masks.traps, (n, t))], axis=1
    )
    exists = exists & masks.rovers[:, None]
    return EntityView(
        own=jnp.where(masks.rovers[:, None], own, 0.0),
        tokens=jnp.where(exists[..., None], tokens, 0.0),
        mask=exists,
    )


def nearest_entities(view: EntityView, params: EnvParams, k: int, free_first: bool = False) -> EntityView:
    """The view cut to ``k`` tokens of each type (other rovers, POIs, traps): the nearest ones
    that exist, in that order and nearest first within a type, then empty (masked, zero)
    tokens if a type has fewer: [N, 3k, F] whatever the layout's maxima. A network's cost then
    stops growing with the swarm, and its input has one width for every size; the far
    entities are out of sight. With ``free_first`` the POIs whose claim feature is positive
    come before the others, each part nearest first: with the claim lead (:func:`poi_claims`,
    ``--poi-order free``) the POIs no nearer rover claims, so that a rover whose nearest POIs
    are taken sees the open ones however far; with the matching (:func:`poi_matches`,
    ``--poi-order matched``) the rover's own POI."""
    n, p = params.num_rovers, params.num_pois
    groups = ((0, n - 1), (n - 1, n - 1 + p), (n - 1 + p, token_count(params)))
    tokens, masks = [], []
    for kind, (start, stop) in enumerate(groups):  # ROVER, POI, TRAP
        group, exists = view.tokens[..., start:stop, :], view.mask[..., start:stop]
        missing = max(k - (stop - start), 0)  # a type with fewer than k slots: pad it to k
        group = jnp.concatenate([group, jnp.zeros((*group.shape[:-2], missing, group.shape[-1]), group.dtype)], -2)
        exists = jnp.concatenate([exists, jnp.zeros((*exists.shape[:-1], missing), bool)], -1)
        dist = jnp.sum(jnp.square(group[..., :2]), axis=-1)
        taken = free_first & (kind == POI) & (group[..., CLAIM] <= 0)  # POIs a nearer rover claims, or not matched
        order = jnp.lexsort((dist, jnp.where(exists, taken, 2)), axis=-1)[..., :k]  # empty slots last
        exists = jnp.take_along_axis(exists, order, axis=-1)
        tokens.append(jnp.where(exists[..., None], jnp.take_along_axis(group, order[..., None], axis=-2), 0.0))
        masks.append(exists)
    return EntityView(own=view.own, tokens=jnp.concatenate(tokens, axis=-2), mask=jnp.concatenate(masks, axis=-1))


def flat_tokens(view: EntityView) -> jax.Array:
    """An entity view [..., M, F] as one vector per rover [..., 4 + M * F + M]: own features,
    the tokens (zero where empty) in their order, and the mask."""
    tokens = jnp.where(view.mask[..., None], view.tokens, 0.0)
    flat = tokens.reshape(*tokens.shape[:-2], -1)
    return jnp.concatenate([view.own, flat, view.mask.astype(flat.dtype)], axis=-1)


def nearest_width(k: int) -> int:
    """Width of :func:`flat_tokens` of a view of ``k`` tokens of each type: own features, then
    3k tokens and their mask."""
    return OWN_FEATURES + 3 * k * (TOKEN_FEATURES + 1)


def observe_nearest(state: EnvState, params: EnvParams, k: int, poi_order: str = "nearest") -> EntityView:
    """Every rover's view of its ``k`` nearest other rovers, POIs and traps
    (:func:`nearest_entities` of :func:`observe_entities`): [N, 3k, F] for any swarm size. Its
    POI slots in ``poi_order`` (:data:`POI_ORDERS`): nearest first; the open POIs first
    (``free``); or the rover's POI in the greedy matching, the open POIs handed over, first
    (``matched``, :func:`poi_matches`, which also puts the matching in the claim feature)."""
    view = observe_entities(state, params, matched=poi_order == "matched")
    return nearest_entities(view, params, k, free_first=poi_order != "nearest")
