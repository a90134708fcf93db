"""What the paper's reward asks of the traps: the oracle against the same oracle blind to traps.

    python docs/results/any-size/trap_cost.py   # about 4 minutes; writes trap-cost.md

The trap-blind oracle is the oracle (its Hungarian plan, its steering around the other rovers)
driving as if there were no traps: it steers on a copy of the state with the traps moved far
off the map, while the environment keeps them (every contact is charged). Per swarm size,
1000 episodes on the same layouts for random, the oracle and the trap-blind oracle: the blind
one's normalised score (1 is the oracle), its trap contacts beside the oracle's and the
`anysize` preset's run ([any-size.csv](any-size.csv), the seeds' mean), and the trap penalty at
which steering around traps starts to pay: the episode reward is linear in the penalty (each
contact costs it once), so the two oracles' rewards meet at
``1 + (R_blind - R_oracle) / (T_blind - T_oracle)`` (the environment's penalty is 1).

A second table does the same for the example mission (``examples/mission.yaml``) under
``mission stress`` (500 episodes, seed 0, one random rover failing in each): what steering
round the craters costs a swarm that has lost a rover, in finished missions.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
from any_size import MISSION  # the script beside this one

from roverswarm.env import get_scenario
from roverswarm.env.missions import load_mission
from roverswarm.experiments.sweep import read_table
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.oracle import oracle_actions
from roverswarm.policies import ORACLE, RANDOM, Policy
from roverswarm.rollout import normalized_score, rollout
from roverswarm.storage import atomic_write
from roverswarm.stress import stress_rows

HERE = Path(__file__).resolve().parent

SIZES = (2, 3, 4, 5, 6, 8, 10)


def _blind_act(key, obs, state, plan, weights, params):
    far = jnp.full_like(state.trap_pos, 1e3)  # the traps, as far as the steering knows
    return oracle_actions(state.replace(trap_pos=far), plan, params)


BLIND = Policy("trap-blind oracle", _blind_act, ORACLE.plan)


def _trained_traps() -> dict[int, float]:
    """The anysize run's mean trap contacts per size (any-size.csv)."""
    return {int(r["scenario"].split("-")[1]): r["trap_contacts"] for r in read_table(HERE / "any-size.csv")}


def main(episodes: int = 1000) -> None:
    enable_compilation_cache()
    trained = _trained_traps()
    lines = [
        "| N | trap-blind oracle's score | trap contacts: blind / oracle / the anysize run "
        "| collisions: blind / oracle | trap penalty at which steering pays |",
        "|---|---|---|---|---|",
    ]
    for n in SIZES:
        params = get_scenario(f"paper-{n}")
        runs = {
            p.name: rollout(p, jax.random.PRNGKey(0), params, episodes).stats.summary() for p in (RANDOM, ORACLE, BLIND)
        }
        blind, oracle = runs[BLIND.name], runs[ORACLE.name]
        score = normalized_score(blind["episode_reward"], runs[RANDOM.name]["episode_reward"], oracle["episode_reward"])
        pays = 1.0 + (blind["episode_reward"] - oracle["episode_reward"]) / (
            blind["trap_contacts"] - oracle["trap_contacts"]
        )
        lines.append(
            f"| {n} | {score:.3f} | {blind['trap_contacts']:.2f} / {oracle['trap_contacts']:.2f} / {trained[n]:.2f} "
            f"| {blind['collisions']:.2f} / {oracle['collisions']:.2f} | {pays:.2f} |"
        )
        print(lines[-1], flush=True)
    lines += ["", *mission_lines()]
    atomic_write(HERE / "trap-cost.md", lambda f: f.write("\n".join(lines) + "\n"))


def mission_lines(episodes: int = 500) -> list[str]:
    """The example mission's stress rows for the oracle and the trap-blind oracle."""
    rows, _ = stress_rows([ORACLE, BLIND], load_mission(MISSION), episodes, seed=0)
    lines = [
        f"The example mission ({MISSION.name}), `mission stress`, {episodes} episodes, seed 0:",
        "",
        "| policy | condition | success | time to observe all (steps) | trap contacts | collisions |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['policy']} | {r['condition']} | {r['success']:.0%} | {r['time_to_all']:.1f} "
            f"| {r['trap_contacts']:.2f} | {r['collisions']:.2f} |"
        )
        print(lines[-1], flush=True)
    return lines


if __name__ == "__main__":
    main()
