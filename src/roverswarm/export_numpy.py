"""roverswarm's observation functions in NumPy alone: what an exported policy
(``roverswarm export``) reads, built from a swarm's state as a user's own estimates give it;
and the safety layer (:func:`shield_actions`), for a policy exported with it.

This file imports nothing but NumPy, so it runs where JAX is not installed: ``roverswarm
export`` copies it beside the model as ``observation.py``. A test holds every function here
to the package's JAX functions (``roverswarm.env.mars.observe``,
``roverswarm.env.entities.observe_entities`` and ``nearest_entities``,
``roverswarm.steering.shield_actions``) on random states.

Shape legend: N rovers, P points of interest (POIs), T traps; every position and velocity is
in the map's frame (x, y), as the environment's.

* Flat view (:func:`observe_flat`), [N, O] with O = 4 + 2P + 2T + 2(N - 1): own velocity, own
  position, then the positions relative to the rover of every POI, every trap and every other
  rover (index order, skipping itself), or, with ``nearest_first``, each of those three
  groups ordered nearest first.
* Entity view (:func:`observe_entities`): ``own`` [N, 4] (velocity, position), ``tokens``
  [N, M, 11] with M = (N - 1) + P + T, one per other rover, POI and trap in that order, each
  ``[dx, dy, dvx, dvy, is_rover, is_poi, is_trap, radius, flag, lead, claim]`` relative to the
  rover (flag: a rover has failed, a POI has been observed this episode; lead, of a POI: the
  nearest other working rover's distance to it less this rover's, clipped to +-2; claim: the
  same against only the other working rovers whose nearest POI it is), and ``mask`` [N, M] bool
  (every token here is a real entity). :func:`nearest_entities` cuts it to the K nearest of each type.

Only swarms whose every rover, POI and trap exists are described here (no padded slots):
give the arrays of what is there.
"""

from __future__ import annotations

import numpy as np

OWN_FEATURES = ("vx", "vy", "x", "y")
"""The own features of the entity view, in order."""
TOKEN_FEATURES = ("dx", "dy", "dvx", "dvy", "is_rover", "is_poi", "is_trap", "radius", "flag", "lead", "claim")
"""The features of one entity token, in order."""
ROVER, POI, TRAP = 0, 1, 2
"""The token types, in the order of the view and of their one-hot features."""
CLAIM = TOKEN_FEATURES.index("claim")
"""Position of the claim feature (the claim lead, or the matching) in a token's features."""


def _f32(x) -> np.ndarray:
    return np.asarray(x, np.float32)


def other_rovers(n: int) -> np.ndarray:
    """[N, N - 1] int: row i lists every rover but i, in index order."""
    return np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int64).reshape(n, n - 1)


def _by_distance(rel: np.ndarray) -> np.ndarray:
    """[N, K] the order of each row's K relative positions [N, K, 2], nearest first (stable)."""
    return np.argsort(np.sum(np.square(rel), axis=-1), axis=-1, kind="stable")


def observe_flat(rover_pos, rover_vel, poi_pos, trap_pos, nearest_first: bool = False) -> np.ndarray:
    """The flat view [N, O] (float32) of rovers at ``rover_pos`` [N, 2] moving at ``rover_vel``
    [N, 2], POIs at ``poi_pos`` [P, 2] and traps at ``trap_pos`` [T, 2]."""
    pos, vel, pois, traps = _f32(rover_pos), _f32(rover_vel), _f32(poi_pos), _f32(trap_pos)
    n = len(pos)
    groups = [pois[None] - pos[:, None], traps[None] - pos[:, None], pos[other_rovers(n)] - pos[:, None]]
    if nearest_first:
        groups = [np.take_along_axis(g, _by_distance(g)[..., None], axis=1) for g in groups]
    return np.concatenate([vel, pos, *(g.reshape(n, 2 * g.shape[1]) for g in groups)], axis=-1)


LEAD_CAP = 2.0
"""A POI's lead is clipped to [-LEAD_CAP, LEAD_CAP]."""


def poi_leads(dist: np.ndarray, working: np.ndarray) -> np.ndarray:
    """[N, P] from each rover's distance to each POI ``dist`` [N, P]: the nearest other working
    rover's distance to each POI less the rover's own, clipped to +-:data:`LEAD_CAP` (+LEAD_CAP
    for a rover with no working other). ``working`` [N] bool: the rovers that have not failed."""
    return _lead(dist, np.where(working[:, None], dist, np.inf))


def _lead(dist: np.ndarray, rivals: np.ndarray) -> np.ndarray:
    """[N, P] the nearest other rover's distance to each POI in ``rivals`` (inf: no rival)
    less each rover's own ``dist``, clipped to +-:data:`LEAD_CAP`."""
    others = np.where(np.eye(len(dist), dtype=bool)[:, :, None], np.inf, rivals[None])
    return np.clip(np.min(others, axis=1, initial=np.inf) - dist, -LEAD_CAP, LEAD_CAP).astype(np.float32)


def poi_claims(dist: np.ndarray, working: np.ndarray) -> np.ndarray:
    """[N, P] the claim lead: as :func:`poi_leads`, against only the other working rovers whose
    nearest POI it is (the first on a tie); +LEAD_CAP where no other rover claims it."""
    claims = (np.arange(dist.shape[1])[None] == np.argmin(dist, axis=1)[:, None]) & working[:, None]
    return _lead(dist, np.where(claims, dist, np.inf))


def _greedy(dist: np.ndarray, rovers: np.ndarray, pois: np.ndarray) -> dict[int, int]:
    """{rover: POI} matching the ``rovers`` [N] bool to the ``pois`` [P] bool greedily: the
    nearest pair first, then the nearest of the rovers and POIs left (the first in row-major
    order on a tie)."""
    matched: dict[int, int] = {}
    rovers, pois = rovers.copy(), pois.copy()
    for flat in np.argsort(dist, axis=None, kind="stable"):
        rover, poi = divmod(int(flat), dist.shape[1])
        if rovers[rover] and pois[poi]:
            matched[rover], rovers[rover], pois[poi] = poi, False, False
    return matched


def _uncross(own: dict[int, int], dist: np.ndarray) -> None:
    """Swap two rovers' POIs in ``own`` {rover: POI} while that shortens their summed distance,
    the pair that saves the most first (the first in row-major order on a tie), at most N
    times."""
    for _ in range(len(dist)):
        best, pair = 1e-6, None
        for a in range(len(dist)):
            for b in range(len(dist)):
                if a in own and b in own:
                    saving = dist[a, own[a]] + dist[b, own[b]] - dist[a, own[b]] - dist[b, own[a]]
                    if saving > best:
                        best, pair = saving, (a, b)
        if pair is None:
            return
        a, b = pair
        own[a], own[b] = own[b], own[a]


def poi_matches(dist: np.ndarray, working: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """[N, P] 1 on the POI each working rover is given, else 0: the claim feature of
    ``poi_order`` "matched". A greedy matching of the working rovers to the POIs, its crossing
    routes swapped apart; then the POIs it leaves open (not ``observed``, given to no rover) go,
    by a greedy matching again, to the rovers whose POI is observed or who have none."""
    own = _greedy(dist, working, np.ones(dist.shape[1], bool))
    _uncross(own, dist)
    pending = {poi for poi in own.values() if not observed[poi]}
    open_pois = np.array([not observed[poi] and poi not in pending for poi in range(dist.shape[1])])
    free = np.array([working[r] and (r not in own or observed[own[r]]) for r in range(len(dist))])
    own.update(_greedy(dist, free, open_pois))
    matched = np.zeros(dist.shape, np.float32)
    for rover, poi in own.items():
        matched[rover, poi] = 1.0
    return matched


def _tokens(rel_pos: np.ndarray, rel_vel, kind: int, radius, flag, lead=0.0, claim=0.0) -> np.ndarray:
    """[N, K, 11] tokens of one type from positions [N, K, 2] and velocities (None: they never
    move) relative to the rover, the type (:data:`ROVER`, :data:`POI`, :data:`TRAP`), radius,
    flag, lead and claim lead."""
    tokens = np.zeros((*rel_pos.shape[:2], len(TOKEN_FEATURES)), np.float32)
    tokens[..., 0:2] = rel_pos
    if rel_vel is not None:
        tokens[..., 2:4] = rel_vel
    tokens[..., 4 + kind] = 1.0
    tokens[..., 7] = radius
    tokens[..., 8] = flag
    tokens[..., 9] = lead
    tokens[..., 10] = claim
    return tokens


def observe_entities(
    rover_pos,
    rover_vel,
    poi_pos,
    trap_pos,
    observed=None,
    failed=None,
    rover_radius: float = 0.15,
    observe_radius=0.1,
    trap_radius=0.1,
    matched: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The entity view (own [N, 4], tokens [N, M, 11], mask [N, M] bool). ``observed`` [P]
    bool: POIs observed so far this episode; ``failed`` [N] bool: rovers that have failed
    (default: none of either). ``observe_radius`` is a scalar or one per POI [P],
    ``trap_radius`` a scalar or one per trap [T]: the environment's, see ``policy.json``.
    With ``matched`` the POI tokens' claim feature is :func:`poi_matches`."""
    pos, vel, pois, traps = _f32(rover_pos), _f32(rover_vel), _f32(poi_pos), _f32(trap_pos)
    n, p = len(pos), len(pois)
    observed = np.zeros(p, bool) if observed is None else np.asarray(observed, bool)
    failed = np.zeros(n, bool) if failed is None else np.asarray(failed, bool)
    others = other_rovers(n)
    dist = np.sqrt(np.sum(np.square(pos[:, None] - pois[None]), axis=-1))  # [N, P]
    tokens = np.concatenate(
        [
            _tokens(pos[others] - pos[:, None], vel[others] - vel[:, None], ROVER, rover_radius, failed[others]),
            _tokens(
                pois[None] - pos[:, None],
                None,
                POI,
                _f32(observe_radius),
                observed,
                poi_leads(dist, ~failed),
                poi_matches(dist, ~failed, observed) if matched else poi_claims(dist, ~failed),
            ),
            _tokens(traps[None] - pos[:, None], None, TRAP, _f32(trap_radius), 0.0),
        ],
        axis=1,
    )
    return np.concatenate([vel, pos], axis=-1), tokens, np.ones(tokens.shape[:2], bool)


def nearest_entities(own, tokens, mask, k: int, counts: tuple[int, int, int], free_first: bool = False):
    """An entity view cut to the ``k`` nearest real tokens of each type (other rovers, POIs,
    traps, whose numbers in ``tokens`` are ``counts``), nearest first within a type (with
    ``free_first``, the POIs whose claim feature is positive before the others), then empty
    tokens (zeros, masked out) where a type has fewer than ``k``: tokens [N, 3k, 11]."""
    cut_tokens, cut_mask, start = [], [], 0
    for kind, count in enumerate(counts):
        group, exists = tokens[:, start : start + count], mask[:, start : start + count]
        start += count
        missing = max(k - count, 0)
        group = np.concatenate([group, np.zeros((len(group), missing, group.shape[-1]), np.float32)], axis=1)
        exists = np.concatenate([exists, np.zeros((len(exists), missing), bool)], axis=1)
        dist = np.sum(np.square(group[..., :2]), axis=-1)
        taken = free_first and kind == POI and group[..., CLAIM] <= 0  # POIs a nearer rover claims, or not matched
        order = np.lexsort((dist, np.where(exists, taken, 2)), axis=-1)[:, :k]  # empty slots last
        exists = np.take_along_axis(exists, order, axis=1)
        cut_tokens.append(np.where(exists[..., None], np.take_along_axis(group, order[..., None], axis=1), 0.0))
        cut_mask.append(exists)
    return own, _f32(np.concatenate(cut_tokens, axis=1)), np.concatenate(cut_mask, axis=1)


def model_inputs(meta: dict, rover_pos, rover_vel, poi_pos, trap_pos, observed=None, failed=None) -> dict:
    """The exported model's inputs for one swarm (a batch of one), in the view it was trained
    on: ``meta`` is the export's ``policy.json``; the state as in :func:`observe_entities`
    (a flat-view policy reads neither ``observed`` nor ``failed``)."""
    view, env = meta["view"], meta["env"]
    if view["kind"] == "flat":
        return {"obs": observe_flat(rover_pos, rover_vel, poi_pos, trap_pos, view["nearest_first"])[None]}
    # exports from before --poi-order hold free_pois_first, or (older still) neither
    poi_order = view.get("poi_order", "free" if view.get("free_pois_first") else "nearest")
    own, tokens, mask = observe_entities(
        rover_pos,
        rover_vel,
        poi_pos,
        trap_pos,
        observed,
        failed,
        env["rover_radius"],
        env["observe_radius"],
        env["trap_radius"],
        matched=poi_order == "matched",
    )
    if view["nearest"]:
        counts = (len(own) - 1, len(np.asarray(poi_pos)), len(np.asarray(trap_pos)))
        own, tokens, mask = nearest_entities(own, tokens, mask, view["nearest"], counts, poi_order != "nearest")
    return {"own": own[None], "tokens": tokens[None], "mask": mask[None]}


def shield_actions(meta: dict, actions, rover_pos, rover_vel, trap_pos, failed=None) -> np.ndarray:
    """The safety layer (``--shield``) on one swarm's ``actions`` [N, 2], for an export that
    holds it (``meta["shield"]``: its margins and look-ahead; ``meta["env"]``: the dynamics).

    Each action is clipped to [-1, 1]; where the velocity it asks for would carry the rover,
    within ``meta["shield"]["steps"]`` steps, into the keep-out circle of a trap or another
    rover (their radii plus ``keep_out_margin``, or ``failed_margin`` round a failed rover),
    the rover heads along that circle's tangent on the side its heading leans to, at the same
    speed, and the action that gives that velocity (scaled down as a whole where it needs more
    than a full action) replaces it. The rule is ``roverswarm.steering.shield_actions``'s,
    obstacle by obstacle (the other rovers where they will be after this step, then the traps,
    twice over), in float32 as there. ``failed`` [N] bool: a failed rover stands still.
    ``actions`` [N, 2] or the model's [1, N, 2]. Returns [N, 2] float32."""
    if not meta.get("shield"):
        raise ValueError("this export holds no safety layer (policy.json: shield); export it with --shield")
    env, rule = meta["env"], meta["shield"]
    pos, vel, traps = _f32(rover_pos), _f32(rover_vel), _f32(trap_pos).reshape(-1, 2)
    n, t = len(pos), len(traps)
    if np.shape(actions) not in ((n, 2), (1, n, 2)):
        raise ValueError(f"actions must be [N, 2] or [1, N, 2] for {n} rovers, got shape {np.shape(actions)}")
    failed = np.zeros(n, bool) if failed is None else np.asarray(failed, bool)
    dt, decay = np.float32(env["dt"]), np.float32(1.0 - env["damping"])
    gain = np.float32(env["sensitivity"] / env["mass"] * env["dt"])
    clipped = np.clip(_f32(actions).reshape(n, 2), -1.0, 1.0)
    next_pos = np.where(failed[:, None], pos, pos + vel * dt)
    velocity = decay * vel + gain * clipped
    speed = np.linalg.norm(velocity, axis=-1, keepdims=True)
    reach = speed[:, 0] * dt * np.float32(rule["steps"])
    others = other_rovers(n)
    centres = np.concatenate([next_pos[others], np.broadcast_to(traps, (n, t, 2))], axis=1)
    rovers = 2 * env["rover_radius"] + np.where(failed[others], rule["failed_margin"], rule["keep_out_margin"])
    trap_keep_out = np.broadcast_to(_f32(env["trap_radius"]) + env["rover_radius"] + rule["keep_out_margin"], (t,))
    keep_out = _f32(np.concatenate([rovers, np.broadcast_to(trap_keep_out, (n, t))], axis=1))
    heading = velocity / np.maximum(speed, 1e-9)
    turned = np.zeros(n, bool)
    for k in list(range(centres.shape[1])) * 2:  # twice, so a later turn is checked against earlier obstacles
        gap = centres[:, k] - next_pos
        dist = np.linalg.norm(gap, axis=-1)
        along = np.sum(heading * gap, axis=-1)
        across = heading[:, 0] * gap[:, 1] - heading[:, 1] * gap[:, 0]
        blocked = (along > 0) & (np.abs(across) < keep_out[:, k]) & (along < reach + keep_out[:, k])
        angle = np.arcsin(np.clip(keep_out[:, k] / np.maximum(dist, 1e-9), 0.0, 1.0))
        angle = np.where(across > 0, -angle, angle)
        unit = gap / np.maximum(dist, 1e-9)[:, None]
        cos, sin = np.cos(angle), np.sin(angle)
        tangent = np.stack([cos * unit[:, 0] - sin * unit[:, 1], sin * unit[:, 0] + cos * unit[:, 1]], axis=-1)
        heading = np.where(blocked[:, None], tangent, heading)
        turned |= blocked
    steered = (heading * speed - decay * vel) / gain
    steered = steered * np.minimum(1.0, 1.0 / np.maximum(np.max(np.abs(steered), axis=-1, keepdims=True), 1e-9))
    return _f32(np.where(turned[:, None], steered, clipped))
