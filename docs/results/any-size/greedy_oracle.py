"""How good a teacher the greedy plan makes: the oracle with its assignment drawn greedily on
device (what ``--teacher`` imitates) against the oracle's Hungarian assignment (every score's 1).

    python docs/results/any-size/greedy_oracle.py   # about a minute

Prints, per swarm size, the greedy oracle's normalised score and its trap contacts and POIs
observed beside the Hungarian oracle's, 500 episodes on the same layouts.
"""

from __future__ import annotations

import jax

from roverswarm.env import get_scenario
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.oracle import greedy_plan
from roverswarm.policies import ORACLE, RANDOM, Policy
from roverswarm.rollout import normalized_score, rollout

GREEDY = Policy(
    "greedy oracle", ORACLE.act, lambda states, params: jax.vmap(greedy_plan, in_axes=(0, None))(states, params)
)


def main(sizes=(2, 3, 5, 8, 10), episodes: int = 500) -> None:
    enable_compilation_cache()
    print("| N | greedy oracle's score | trap contacts: greedy / oracle | POIs observed: greedy / oracle |")
    print("|---|---|---|---|")
    for n in sizes:
        params = get_scenario(f"paper-{n}")
        runs = {
            p.name: rollout(p, jax.random.PRNGKey(0), params, episodes).stats.summary()
            for p in (RANDOM, ORACLE, GREEDY)
        }
        greedy, oracle = runs["greedy oracle"], runs["oracle"]
        score = normalized_score(greedy["episode_reward"], runs["random"]["episode_reward"], oracle["episode_reward"])
        print(
            f"| {n} | {score:.3f} | {greedy['trap_contacts']:.2f} / {oracle['trap_contacts']:.2f} "
            f"| {greedy['pois_observed']:.2f} / {oracle['pois_observed']:.2f} |"
        )


if __name__ == "__main__":
    main()
