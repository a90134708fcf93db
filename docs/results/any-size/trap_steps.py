"""When and where the rovers touch traps: the oracle, the trap-blind oracle and a run's policies.

    python docs/results/any-size/trap_steps.py --run runs/anysize --out trap-steps.md

Per swarm size, 1000 deterministic episodes on the same layouts for the oracle, the trap-blind
oracle (:data:`trap_cost.BLIND`: the oracle steering as if there were no traps) and every
seed of the run: trap contacts per episode (each step a rover spends on a trap counts one),
how many times a rover drives onto a trap (a contact the step before did not have), the share
of episodes with any contact, the share of the contacts in the first five of the 25 steps
(while the rovers drive to their POIs) and the median distance of a rover on a trap to the
nearest POI (how far from its goal).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np
from trap_cost import BLIND  # the script beside this one

from roverswarm.env import get_scenario
from roverswarm.env.mars import trap_radii
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.policies import ORACLE
from roverswarm.rollout import Rollout, rollout
from roverswarm.runs import Run
from roverswarm.storage import atomic_write

HEADER = [
    "| N | policy | contacts per episode | drives onto a trap | episodes with a contact | in steps 1-5 "
    "| distance to the nearest POI |",
    "|---|---|---|---|---|---|---|",
]


def trap_contacts(result: Rollout, params) -> np.ndarray:
    """[E, T, N] how many traps each rover touches after each step, from the rollout's paths by
    the environment's contact rule; checked against the environment's own episode totals."""
    pos = result.rover_pos[:, 1:]  # [E, T, N, 2]
    dist = np.linalg.norm(pos[:, :, :, None] - result.trap_pos[:, None, None], axis=-1)  # [E, T, N, traps]
    inside = (dist < params.rover_radius + np.asarray(trap_radii(params))) & result.trap_exists[:, None, None]
    contacts = inside.sum(axis=-1)
    if not np.allclose(contacts.sum(axis=(1, 2)), result.stats.trap_contacts):
        raise AssertionError("the contacts rebuilt from the paths differ from the environment's")
    return contacts


def row(n: int, name: str, result: Rollout, params) -> str:
    """One table row: ``name``'s contacts in ``result`` at N = ``n``."""
    touches = trap_contacts(result, params)
    on = touches > 0  # [E, T, N] rover on a trap
    episodes = len(on)
    before = np.concatenate([np.zeros_like(on[:, :1]), on[:, :-1]], axis=1)
    pos = result.rover_pos[:, 1:]
    to_poi = np.linalg.norm(pos[:, :, :, None] - result.poi_pos[:, None, None], axis=-1).min(axis=-1)
    contacts = touches.sum()
    early = touches[:, :5].sum() / max(contacts, 1)
    where = np.median(to_poi[on]) if contacts else float("nan")
    return (
        f"| {n} | {name} | {contacts / episodes:.2f} | {(on & ~before).sum() / episodes:.2f} "
        f"| {on.any(axis=(1, 2)).mean():.2f} | {early:.2f} | {where:.2f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, required=True, help="a size-agnostic run folder")
    parser.add_argument("--out", type=Path, required=True, help="the markdown table to write")
    parser.add_argument("--sizes", default="2,3,5,8")
    parser.add_argument("--episodes", type=int, default=1000)
    args = parser.parse_args()
    enable_compilation_cache()
    run = Run(args.run)
    lines = list(HEADER)
    for n in (int(s) for s in args.sizes.split(",")):
        params = get_scenario(f"paper-{n}").replace(nearest_first=run.params.nearest_first)
        for policy in (ORACLE, BLIND, *run.policies("random", 0, "own", rovers=n)):
            lines.append(row(n, policy.name, rollout(policy, jax.random.PRNGKey(0), params, args.episodes), params))
            print(lines[-1], flush=True)
    atomic_write(args.out, lambda f: f.write("\n".join(lines) + "\n"))


if __name__ == "__main__":
    main()
