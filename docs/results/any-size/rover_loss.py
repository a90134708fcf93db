"""Why a trained swarm that lost a rover does not finish its mission: two measurements.

    python docs/results/any-size/rover_loss.py runs/anysize                     # seed 0
    python docs/results/any-size/rover_loss.py runs/anysize runs/p3-specialist --seed 1
    python docs/results/any-size/rover_loss.py runs/anysize --shield   # each run also behind the safety layer
    python docs/results/any-size/rover_loss.py runs/anysize --mission examples/survey.yaml --failures 2
    python docs/results/any-size/rover_loss.py runs/anysize-stop-fail --seed 2 --failures 2 --standstill

1. ``examples/mission.yaml`` (or ``--mission``) with one rover (or ``--failures``) failing at a
   random step before the mission would be complete (the failures of ``roverswarm mission
   stress``, same key): of the episodes that fail, how many POIs stay unobserved, how far the
   working rovers end from the first of them (median) and from the nearest open POI, how far
   they moved in the last 5 steps (median of the farther), how many leave a POI that a failed
   rover stands on (its centre within the rover radius of the POI) or
   against (within the keep-out radius round a failed rover less the POI's observation radius:
   no working rover observes it without entering the keep-out circle, which the oracle's
   steering and the safety layer hold them out of), and success by when the failure came (as a
   share of the time the episode took without it), per fifth; and over every episode, how many
   rover-steps a working rover touched a failed one.
   With ``--standstill`` (a trained run): the working rovers of those episodes that stood
   still at the end (moved under 0.01 in the last 5 steps), and at each one's last state the
   policy's action as it is and with every failed rover's token but the nearest hidden from
   its view (a view with one failed rover, as training with one failure per episode shows):
   the median action length and how many then head for an open POI.
2. ``paper-3``, one rover failing at a uniform step in every episode: the episode reward, the
   distance of the working rovers to the POIs not yet observed summed over the steps (what
   ``--unobserved-shaping`` charges, per rover) and the share of episodes that observe every
   POI, for the oracle and each run.

Each run's seed ``--seed`` drives the rovers; deterministic (no exploration noise).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np
from any_size import MISSION  # the script beside this one

from roverswarm.env import get_scenario
from roverswarm.env.entities import FLAG, ROVER
from roverswarm.env.mars import NEVER, EnvState, observe_radii
from roverswarm.env.missions import load_mission
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.learners import learner_family
from roverswarm.rollout import MissionStats, Rollout, rollout
from roverswarm.runs import Run, load_policy
from roverswarm.steering import FAILED_MARGIN
from roverswarm.stress import random_failures


def one_failed_in_view(view, group: int) -> tuple[object, np.ndarray]:
    """``view`` with every failed rover's token but the nearest hidden (masked and moved behind
    the rover tokens kept, within the first ``group`` tokens, the rovers'), and [N] which
    rovers saw more than one failed rover."""
    tokens, mask = np.asarray(view.tokens), np.asarray(view.mask)
    failed = (tokens[..., 4 + ROVER] > 0) & (tokens[..., FLAG] > 0) & mask  # [N, M]
    failed[:, group:] = False
    dist = np.where(failed, np.sum(np.square(tokens[..., :2]), axis=-1), np.inf)
    hidden = failed & (np.arange(failed.shape[1]) != np.argmin(dist, axis=1)[:, None])
    order = np.argsort(hidden[:, :group], axis=1, kind="stable")  # the kept rover tokens first, in their order
    mask = mask & ~hidden
    tokens = np.where(mask[..., None], tokens, 0.0)
    tokens[:, :group] = np.take_along_axis(tokens[:, :group], order[..., None], axis=1)
    mask[:, :group] = np.take_along_axis(mask[:, :group], order, axis=1)
    return view.replace(tokens=tokens, mask=mask), hidden.any(axis=1)


def standstill(spec: str, seed: int, data: Rollout, fail_step: np.ndarray, lost: np.ndarray, params) -> None:
    """``--standstill``: the working rovers of the ``lost`` episodes that stood still at the end
    with more than one failed rover in view, and the actor's action (before any safety layer)
    in the last state it acted in, as it is and with one failed rover in view."""
    run = Run(spec)
    family = learner_family(run.config.learner.algo)
    acting = family.acting(run.config)
    observe = family.view(acting)
    if observe is None or run.config.learner.ensemble > 1:
        print("  standstill: needs a run of one policy per seed over the entity or nearest view")
        return
    weights = run.policy(seed).weights
    k = run.config.learner.entity_nearest
    group = k if k else params.num_rovers - 1  # the rover tokens, first in the view
    steps = data.rover_pos.shape[1] - 1
    found = []  # (action length, action length with one failed rover seen, heads for an open POI then)
    for e in lost:
        last, end = data.rover_pos[e, -2], data.rover_pos[e, -1]
        state = EnvState(  # the state of the last step: its velocity is what moved the rovers from it
            rover_pos=last,
            rover_vel=(end - last) / params.dt,
            poi_pos=data.poi_pos[e],
            trap_pos=data.trap_pos[e],
            observed=data.observed[e, -2],
            time=np.int32(steps - 1),
            fail_step=fail_step[e],
        )
        view = observe(state, params)
        fewer, seen = one_failed_in_view(view, group)
        as_is = np.asarray(family.act(acting, weights, view, None))
        one = np.asarray(family.act(acting, weights, fewer, None))
        open_pois = data.poi_pos[e, ~data.observed[e, -2]]
        for i in np.flatnonzero((fail_step[e] == NEVER) & seen):
            if np.linalg.norm(end[i] - data.rover_pos[e, -6, i]) >= 0.01:
                continue
            to_poi = open_pois - last[i]
            cosine = to_poi @ one[i] / (np.linalg.norm(to_poi, axis=1) * np.linalg.norm(one[i]) + 1e-9)
            found.append((np.linalg.norm(as_is[i]), np.linalg.norm(one[i]), cosine.max() > 0.7))
    if not found:
        print("  standstill: no working rover stood still with more than one failed rover in view")
        return
    length, with_one, heads = np.asarray(found).T
    print(
        f"  standstill: {len(found)} working rovers stood still with more than one failed rover in view; their"
        f" action {np.median(length):.3f} long (median), with one failed rover in view {np.median(with_one):.3f},"
        f" then {heads.mean():.0%} head for an open POI (cosine > 0.7)"
    )


def mission_failures(
    spec: str,
    seed: int,
    episodes: int,
    shield: bool = False,
    path: Path = MISSION,
    failures: int = 1,
    still: bool = False,
) -> None:
    """Measurement 1 for the run (or ``oracle``) ``spec`` on the mission file ``path`` with
    ``failures`` rovers failing, with ``shield`` behind the safety layer."""
    mission = load_mission(path)
    params = mission.params
    policy = load_policy(spec, params, f"mission '{mission.name}'", seed, shield=shield)
    keep_out, radii = 2 * params.rover_radius + FAILED_MARGIN, np.asarray(observe_radii(params))
    key = jax.random.PRNGKey(0)
    clean = MissionStats.of(rollout(policy, key, params, episodes))
    finish = np.where(clean.success, clean.time_to_all, params.max_steps)
    fail_step = random_failures(jax.random.fold_in(key, 1), finish, params.num_rovers, failures)
    data = rollout(policy, key, params, episodes, fail_step=fail_step)
    stats = MissionStats.of(data)
    failed = fail_step != NEVER  # [E, N]
    gaps = np.linalg.norm(data.rover_pos[:, :, :, None] - data.rover_pos[:, :, None], axis=-1)  # [E, T + 1, N, N]
    contact = (gaps < 2 * params.rover_radius) & failed[:, None, None, :] & ~np.eye(params.num_rovers, dtype=bool)
    touching = contact.any(axis=-1) & ~failed[:, None, :]  # [E, T + 1, N]: a working rover touching a failed one
    ending, nearest, moving, missing, under, against = [], [], [], [], [], []
    for e in np.flatnonzero(~stats.success):
        unobserved = np.flatnonzero(~data.observed[e, -1])
        working = ~failed[e]
        end = data.rover_pos[e, -1, working]
        to_open = np.linalg.norm(end[:, None] - data.poi_pos[e, unobserved][None], axis=-1)  # [working, open]
        ending.append(to_open[:, 0].min())
        nearest.append(to_open.min())
        moving.append(np.linalg.norm(end - data.rover_pos[e, -6, working], axis=-1).max())
        missing.append(len(unobserved))
        gap = np.linalg.norm(
            data.poi_pos[e, unobserved][:, None] - data.rover_pos[e, -1, failed[e]][None], axis=-1
        ).min(axis=1)
        under.append(np.any(gap < params.rover_radius))
        against.append(np.any(gap < keep_out - radii[unobserved]))
    name = f"{spec} behind the safety layer" if shield else spec
    lost = "one failure" if failures == 1 else f"{failures} failures"
    print(
        f"{name} (seed {seed}), mission '{mission.name}' with {lost}: {stats.success.mean():.0%} of {episodes},"
        f" {touching.sum(axis=(1, 2)).mean():.2f} rover-steps touching a failed rover per episode"
    )
    if missing:
        counts = np.bincount(missing)
        print(
            f"  {len(missing)} fail; POIs unobserved: "
            + ", ".join(f"{k}: {c}" for k, c in enumerate(counts) if c)
            + f"; working rovers end {np.median(ending):.2f} from the first (median; from the nearest open POI"
            f" {np.median(nearest):.3f}, its observation radius {np.median(radii):.2f}) and moved"
            f" {np.median(moving):.3f} in the last 5 steps (median); {sum(against)} leave a POI a failed rover"
            f" stands against ({sum(under)} of them on it)"
        )
    share = fail_step.min(axis=1) / np.maximum(finish, 1)
    fifths = [
        f"{stats.success[(share >= b / 5) & (share < (b + 1) / 5)].mean():.0%}"
        for b in range(5)
        if np.any((share >= b / 5) & (share < (b + 1) / 5))
    ]
    print("  success by when the (first) failure came, per fifth of the clean episode: " + " / ".join(fifths))
    if still and spec != "oracle":
        standstill(spec, seed, data, fail_step, np.flatnonzero(~stats.success), params)


def unobserved_distance(data: Rollout, fail_step: np.ndarray) -> np.ndarray:
    """[E] the working rovers' distance to the POIs not yet observed, summed over the steps."""
    pos = data.rover_pos[:, 1:]  # [E, T, N, 2]
    steps = pos.shape[1]
    dist = np.linalg.norm(pos[:, :, :, None] - data.poi_pos[:, None, None], axis=-1)  # [E, T, N, P]
    working = np.arange(1, steps + 1)[None, :, None] < fail_step[:, None, :]
    nearest = np.where(working[..., None], dist, np.inf).min(axis=2)  # [E, T, P]
    return np.where(~data.observed[:, 1:] & np.isfinite(nearest), nearest, 0.0).sum(axis=(1, 2))


def failure_returns(spec: str, seed: int, episodes: int) -> None:
    """Measurement 2 for the run (or ``oracle``) ``spec``."""
    params = get_scenario("paper-3")
    if spec != "oracle":
        params = params.replace(nearest_first=Run(spec).params.nearest_first)
    rng = np.random.default_rng(0)
    fail_step = np.full((episodes, params.num_rovers), NEVER, np.int32)
    fail_step[np.arange(episodes), rng.integers(0, params.num_rovers, episodes)] = rng.integers(
        0, params.max_steps, episodes
    )
    policy = load_policy(spec, params, "paper-3", seed)
    data = rollout(policy, jax.random.PRNGKey(0), params, episodes, fail_step=fail_step)
    print(
        f"| {spec} (seed {seed}) | {data.stats.reward.mean():.1f} | {unobserved_distance(data, fail_step).mean():.1f} "
        f"| {MissionStats.of(data).success.mean():.0%} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run folders of `roverswarm train` (and/or `oracle`)")
    parser.add_argument("--seed", type=int, default=0, help="which seed of each run drives the rovers")
    parser.add_argument("--episodes", type=int, default=500, help="mission episodes (paper-3: twice as many)")
    parser.add_argument("--shield", action="store_true", help="measurement 1 also behind the safety layer")
    parser.add_argument("--mission", type=Path, default=MISSION, help="measurement 1's mission file")
    parser.add_argument("--failures", type=int, default=1, help="measurement 1's rovers failing per episode")
    parser.add_argument("--standstill", action="store_true", help="measurement 1: why working rovers stand still")
    args = parser.parse_args()
    enable_compilation_cache()
    specs = ["oracle", *(r for r in args.runs if r != "oracle")]
    for spec in specs:
        seed = args.seed if spec != "oracle" else 0
        mission_failures(spec, seed, args.episodes, path=args.mission, failures=args.failures, still=args.standstill)
        if args.shield and spec != "oracle":
            mission_failures(spec, seed, args.episodes, True, args.mission, args.failures)
    print("\npaper-3, one rover failing at a uniform step in every episode:\n")
    print("| policy | episode reward | distance to unobserved POIs, summed | all POIs observed |\n|---|---|---|---|")
    for spec in specs:
        failure_returns(spec, args.seed if spec != "oracle" else 0, 2 * args.episodes)


if __name__ == "__main__":
    main()
