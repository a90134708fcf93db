"""Where a trained swarm loses to the oracle at one size: the coverage over the episode, the
POIs left open at its end and the rovers that share their nearest POI or leave the map.

    python docs/results/any-size/open_pois.py runs/anysize --size 5
    python docs/results/any-size/open_pois.py runs/anysize runs/anysize-free --size 5 --seeds 0 1

Each policy (the oracle first, then every seed of every run) drives the same ``--episodes``
layouts of ``paper-N`` deterministically. Per policy, one table row: the episode reward; the
coverage distance (each POI's distance to its nearest rover, summed over the POIs) at steps 1,
5, 10, 15, 20 and 25; at the last step, the POIs with no rover within 0.2, the rovers whose
nearest POI is also another rover's nearest (one per POI in excess), the rovers outside the
map; the share of episodes with a POI open at the end; and, of the POIs left open, how many
were the farthest from every rover's start.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from roverswarm.env import get_scenario
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.rollout import rollout
from roverswarm.runs import Run, load_policy

STEPS = (1, 5, 10, 15, 20, 25)
OPEN = 0.2
"""A POI with no rover nearer than this at the end is open (twice its observation radius)."""


def row(name: str, data, map_size: float) -> str:
    """One table row of the rollout ``data`` (see the module docstring)."""
    dist = np.linalg.norm(data.rover_pos[:, :, :, None] - data.poi_pos[:, None, None], axis=-1)  # [E, T+1, N, P]
    coverage = dist.min(axis=2).sum(axis=-1).mean(axis=0)  # [T + 1]
    end = dist[:, -1]  # [E, N, P]
    open_pois = end.min(axis=1) > OPEN  # [E, P]
    shared = np.mean([len(o) - len(set(o)) for o in end.argmin(axis=2)])
    outside = (np.abs(data.rover_pos[:, -1]) > map_size).any(axis=-1).sum(axis=-1).mean()
    farthest = dist[:, 0].min(axis=1).argmax(axis=-1)  # [E] the POI farthest from every start
    episodes, pois = np.nonzero(open_pois)
    far = np.mean(pois == farthest[episodes]) if len(pois) else float("nan")
    cells = [f"{data.stats.reward.mean():.1f}", " / ".join(f"{coverage[t]:.2f}" for t in STEPS)]
    cells += [f"{open_pois.sum(axis=1).mean():.2f}", f"{shared:.2f}", f"{outside:.2f}"]
    cells += [f"{open_pois.any(axis=1).mean():.0%}", f"{far:.0%}"]
    return f"| {name} | " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run folders of `roverswarm train` of any size")
    parser.add_argument("--size", type=int, default=5, help="N of paper-N")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="which seeds of each run")
    parser.add_argument("--episodes", type=int, default=300)
    args = parser.parse_args()
    enable_compilation_cache()
    params = get_scenario(f"paper-{args.size}")
    key = jax.random.PRNGKey(7)
    print(
        f"paper-{args.size}, {args.episodes} episodes\n\n| policy | episode reward | coverage at steps "
        + ", ".join(map(str, STEPS))
        + " | POIs open at the end | rovers sharing a nearest POI | rovers off the map "
        "| episodes with a POI open | open POIs that were the farthest |\n|---|---|---|---|---|---|---|---|"
    )
    print(row("oracle", rollout(load_policy("oracle", params, "paper-N"), key, params, args.episodes), params.map_size))
    for run in args.runs:
        view = params.replace(nearest_first=Run(run).params.nearest_first)
        for seed in args.seeds:
            data = rollout(load_policy(run, view, f"paper-{args.size}", seed), key, view, args.episodes)
            print(row(f"{run} (seed {seed})", data, params.map_size))


if __name__ == "__main__":
    main()
