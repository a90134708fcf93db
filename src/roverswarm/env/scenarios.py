"""Named scenario presets: data, not code branches.

``paper-2`` .. ``paper-5`` are the paper's four experiments (N rovers, N POIs, N traps);
``paper-N`` grows the same swarm, for any N from 2 to :data:`MAX_ROVERS`;
``spread-3`` is cooperative navigation without traps (comparable to MPE ``simple_spread``).

The map beyond N = 10 (:data:`DENSE_UP_TO`): a fixed map would crowd, so it grows to keep
paper-10's density of entities per area (as PIC grows its arena): half-width
``max(1, sqrt(N / 10))``, 1.0 up to N = 10, 1.26 at N = 16, 1.79 at N = 32.

A *range* of sizes, ``paper-2..10`` (every N from 2 to 10) or a list ``paper-2,4,8``, is one
padded layout (:func:`padded_scenario`: the largest N's slots) in which each environment draws
its own N (:func:`sized`, traced, so one compiled program steps every size).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from roverswarm.env.mars import ACTION_SIZE, EnvParams, observation_size
from roverswarm.env.validation import validate_params
from roverswarm.errors import UserError, require

MAX_ROVERS = 64
"""The largest ``paper-N``."""
DENSE_UP_TO = 10
"""``paper-N`` keeps the map [-1, 1]^2 up to this N, and paper-10's density beyond it."""


def paper_map_size(n):
    """Half-width of ``paper-N``'s map: ``max(1, sqrt(N / DENSE_UP_TO))`` (a float for an int N,
    traced for a traced one)."""
    if isinstance(n, int):
        return max(1.0, math.sqrt(n / DENSE_UP_TO))
    return jnp.maximum(1.0, jnp.sqrt(n / DENSE_UP_TO))


def paper_params(n: int) -> EnvParams:
    """``paper-N``: N rovers, N POIs, N traps on :func:`paper_map_size`'s map."""
    return EnvParams(num_rovers=n, num_pois=n, num_traps=n, map_size=paper_map_size(n))


@dataclass(frozen=True)
class Scenario:
    """A named environment configuration with a one-line description."""

    name: str
    params: EnvParams
    description: str


def _paper(n: int) -> Scenario:
    what = "paper experiment" if n <= 5 else "larger swarm"
    where = "" if n <= DENSE_UP_TO else f", map half-width {paper_map_size(n):.2f}"
    return Scenario(f"paper-{n}", paper_params(n), f"{what}: {n} rovers, {n} POIs, {n} traps{where}")


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


_NAMES = f"one of {', '.join(SCENARIOS)}, paper-N (N in 2..{MAX_ROVERS}), a range paper-A..B or a list paper-A,B,C"
_N = r"(?:0|[1-9][0-9]*)"  # ASCII digits, no leading zero
_RANGE = re.compile(rf"paper-({_N})\.\.({_N})")
_LIST = re.compile(rf"paper-({_N}(?:,{_N})+)")
_SINGLE = re.compile(rf"paper-({_N})")


def scenario_sizes(name: str) -> tuple[int, ...]:
    """The swarm sizes N of scenario ``name``, ascending: one for a single scenario, several
    for a range (``paper-2..10``) or list (``paper-2,4,8``); :class:`UserError` if ``name`` is
    none of these or a size is outside 2..MAX_ROVERS."""
    if name in SCENARIOS:
        return (SCENARIOS[name].params.num_rovers,)
    ranged = _RANGE.fullmatch(name)
    if ranged:
        texts = [ranged[1], ranged[2]]
    elif match := _LIST.fullmatch(name):
        texts = match[1].split(",")
    elif match := _SINGLE.fullmatch(name):
        texts = [match[1]]
    else:
        raise UserError(f"unknown scenario '{name}'; choose {_NAMES}")
    # checked before a range is built (paper-2..10**20 builds nothing), and before int() meets
    # more digits than it converts
    given = [int(t) if len(t) <= 3 else MAX_ROVERS + 1 for t in texts]
    require(
        2 <= min(given) and max(given) <= MAX_ROVERS,
        f"scenario '{name}': every N must be in 2..{MAX_ROVERS}, got {('..' if ranged else ', ').join(texts)}",
    )
    require(not ranged or given[0] < given[1], f"scenario '{name}': a range paper-A..B needs A < B")
    require(len(set(given)) == len(given), f"scenario '{name}': a list paper-A,B,C names each size once")
    low, high = min(given), max(given)
    return tuple(range(low, high + 1)) if ranged else tuple(sorted(given))


def range_sizes(name: str) -> tuple[int, ...] | None:
    """The sizes of a range or list scenario (``paper-2..10``); None for a single size."""
    sizes = scenario_sizes(name)
    return sizes if len(sizes) > 1 else None


def get_scenario(name: str) -> EnvParams:
    """The validated :class:`EnvParams` of one scenario ``name`` (a preset or ``paper-N``);
    :class:`UserError` if unknown, or if it is a range (see :func:`padded_scenario`)."""
    sizes = scenario_sizes(name)
    require(
        len(sizes) == 1,
        f"scenario '{name}' is a range of swarm sizes; this needs one size, such as paper-{sizes[-1]}",
    )
    params = SCENARIOS[name].params if name in SCENARIOS else paper_params(sizes[0])
    return validate_params(params)


def padded_scenario(name: str) -> EnvParams:
    """The padded layout of scenario ``name`` (a ``paper`` size, range or list): the slots of
    its largest N, all of them active; :func:`sized` picks each environment's N within it."""
    sizes = scenario_sizes(name)
    require(
        name not in SCENARIOS or name.startswith("paper-"),
        f"scenario '{name}' has no range of sizes; only the paper-N family has (e.g. paper-2..10)",
    )
    return sized(paper_params(sizes[-1]), sizes[-1])


def sized(params: EnvParams, n) -> EnvParams:
    """``params`` (a padded paper layout) with ``n`` rovers, POIs and traps active on
    paper-N's map (``n`` may be traced: vmap over it to mix sizes in one program)."""
    return params.replace(active_rovers=n, active_pois=n, active_traps=n, map_size=paper_map_size(n))


def draw_sizes(key: jax.Array, sizes: tuple[int, ...], count: int, cap=None, power: float = 0.0) -> jax.Array:
    """[count] swarm sizes drawn from ``sizes`` (ascending): uniformly, or with ``power`` p a
    size N with probability proportional to N^-p; with ``cap`` (traced), from those at most
    ``cap`` (the smallest if none is)."""
    choices = len(sizes) if cap is None else jnp.maximum(jnp.sum(jnp.asarray(sizes) <= cap), 1)
    if power == 0:  # the uniform draw as before the power existed: the same sizes for the same key
        return jnp.asarray(sizes, jnp.int32)[jax.random.randint(key, (count,), 0, choices)]
    logits = jnp.where(jnp.arange(len(sizes)) < choices, -power * jnp.log(jnp.asarray(sizes, jnp.float32)), -jnp.inf)
    return jnp.asarray(sizes, jnp.int32)[jax.random.categorical(key, logits, shape=(count,))]


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


SIZE_RULE = (
    f"paper-N for any N in 2..{MAX_ROVERS}: N rovers, N POIs, N traps; the map is [-1, 1]^2 up to N = "
    f"{DENSE_UP_TO} and grows beyond it to keep paper-{DENSE_UP_TO}'s density (half-width sqrt(N / {DENSE_UP_TO})). "
    "A range paper-A..B or a list paper-A,B,C trains one policy on every size in it."
)
"""What ``roverswarm scenarios`` says of the sizes beyond the listed presets."""
