"""Named scenario presets: data, not code branches.

``paper-2`` .. ``paper-5`` are the paper's four experiments (N rovers, N POIs, N traps);
``paper-6`` .. ``paper-10`` grow the same swarm further;
``spread-3`` is cooperative navigation without traps (comparable to MPE ``simple_spread``).
"""

from __future__ import annotations

from dataclasses import dataclass

from roverswarm.env.mars import ACTION_SIZE, EnvParams, observation_size, validate_params
from roverswarm.errors import UserError


@dataclass(frozen=True)
class Scenario:
    """A named environment configuration with a one-line description."""

    name: str
    params: EnvParams
    description: str


def _paper(n: int) -> Scenario:
    what = "paper experiment" if n <= 5 else "larger swarm"
    return Scenario(
        f"paper-{n}", EnvParams(num_rovers=n, num_pois=n, num_traps=n), f"{what}: {n} rovers, {n} POIs, {n} traps"
    )


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        *(_paper(n) for n in range(2, 11)),
        Scenario(
            "spread-3",
            EnvParams(num_rovers=3, num_pois=3, num_traps=0),
            "3 rovers, 3 POIs, no traps (MPE simple_spread)",
        ),
    )
}


def get_scenario(name: str) -> EnvParams:
    """The validated :class:`EnvParams` of preset ``name``; :class:`UserError` if unknown."""
    if name not in SCENARIOS:
        raise UserError(f"unknown scenario '{name}'; choose one of: {', '.join(SCENARIOS)}")
    return validate_params(SCENARIOS[name].params)


def scenario_table() -> list[dict[str, object]]:
    """One row per preset: name, rovers, POIs, traps, observation and action sizes, description."""
    return [
        {
            "name": s.name,
            "rovers": s.params.num_rovers,
            "pois": s.params.num_pois,
            "traps": s.params.num_traps,
            "obs_size": observation_size(s.params),
            "action_size": ACTION_SIZE,
            "description": s.description,
        }
        for s in SCENARIOS.values()
    ]
