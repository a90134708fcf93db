"""Deterministic evaluation of trained runs beside the random and oracle policies.

Every policy runs the same episodes (same layouts, same key); the normalised score
``(R - R_random) / (R_oracle - R_random)`` puts random at 0 and the oracle at 1.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import jax
import numpy as np
import tyro
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from roverswarm.console import console
from roverswarm.env.mars import EnvParams
from roverswarm.env.scenarios import get_scenario, range_sizes, scenario_sizes
from roverswarm.errors import require
from roverswarm.limits import check_seed
from roverswarm.policies import ORACLE, RANDOM, REFERENCE_POLICIES, shielded
from roverswarm.rollout import normalized_score, rollout
from roverswarm.runs import Partners, Run, SubPolicies, check_fits, check_rollout_memory


@dataclass(frozen=True)
class EvaluateConfig:
    """Deterministic episodes of a trained run beside the random and oracle policies."""

    run: tyro.conf.Positional[Path]
    """Run folder written by `roverswarm train --out`."""
    episodes: int = 1000
    """Evaluation episodes per policy (the same layouts for every policy)."""
    seed: int = 0
    """Seed of the evaluation episodes."""
    sub_policies: Literal["random", "each"] = "random"
    """Runs with --ensemble K: `random` draws every agent's sub-policy per episode, as in
    training; `each` runs sub-policy k of all agents, for every k."""
    scenario: str | None = None
    """Evaluate on this scenario instead of the run's own: a policy of --network entity or
    nearest on any paper-N or range (paper-2..32: every size of it), any other on its own
    numbers of rovers, POIs and traps. Default: the run's scenario (every size of a range)."""
    partners: Literal["own", "other-seeds"] = "own"
    """`own`: each seed's agents together; `other-seeds`: agent i of seed s beside the other
    agents of seeds s + 1, s + 2, ... (mod seeds), partners it never trained with (each rover
    acting as its own seed's policy would in its place: shared networks and normalised
    observations too)."""
    shield: bool = False
    """Drive the trained policies behind the safety layer: each rover's action turned along the
    tangent of any trap or other rover it would reach within a few steps (as the oracle steers),
    the rest unchanged. Random and the oracle, the references, run as they are. A run trained
    with --shield always acts behind the layer."""


def evaluate_run(
    out,
    episodes: int = 1000,
    seed: int = 0,
    sub_policies: SubPolicies = "random",
    partners: Partners = "own",
    scenario: str | None = None,
    shield: bool = False,
    progress: bool = False,
) -> list[dict[str, float | str]]:
    """Deterministic episodes of every seed's trained policy in run folder ``out``, beside the
    random and oracle policies on the same episodes (same layouts), with the normalised score.
    Runs with policy ensembles, and ``partners``, work as :meth:`Run.policies` says; the policy
    names say which. ``scenario`` and ``shield``: see :class:`EvaluateConfig`. ``progress``: a
    bar over the policies and sizes while they run, on a terminal (gone when done).

    Returns one row per policy (and size): ``policy``, the :meth:`EpisodeStats.summary`
    metrics and ``normalized_score``; with several sizes, or a ``scenario``, also ``scenario``.
    """
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    check_seed(seed)
    run = Run(out)
    targets = _targets(run, scenario)
    sets = f"--episodes {episodes}" + (f", --scenario {scenario}" if scenario is not None else "")
    check_rollout_memory(run, [params for _, params in targets], episodes, sets, "this evaluation")  # every size
    key = jax.random.PRNGKey(seed)
    named = scenario is not None or (run.config.mission is None and range_sizes(run.config.scenario) is not None)
    rows = []
    with _progress(progress) as show:
        for name, params in targets:
            policies = run.policies(sub_policies, seed, partners, rovers=params.num_rovers)
            policies = [RANDOM, ORACLE, *(map(shielded, policies) if shield else policies)]
            results = {}
            for policy in policies:  # the same number at every size
                show(f"{name}: {policy.name}, {episodes} episodes", len(targets) * len(policies))
                if policy.name in REFERENCE_POLICIES:
                    results[policy.name] = reference_summary(policy.name, seed, params, episodes)
                else:
                    results[policy.name] = rollout(policy, key, params, episodes).stats.summary()
            low, high = results["random"]["episode_reward"], results["oracle"]["episode_reward"]
            for policy, summary in results.items():
                score = normalized_score(summary["episode_reward"], low, high)
                rows.append(
                    {**({"scenario": name} if named else {}), "policy": policy, **summary, "normalized_score": score}
                )
    return rows


REFERENCES_KEPT = 256
"""Reference summaries :func:`reference_summary` keeps per process (the oldest go first)."""
_references: dict[tuple, dict[str, float]] = {}


def reference_summary(name: str, seed: int, params: EnvParams, episodes: int) -> dict[str, float]:
    """The summary of reference policy ``name`` (random, the oracle) on ``episodes`` episodes
    of ``params`` from key ``seed``, rolled out once per process: every run of a grid or sweep
    at one size is scored against the same references, which depend on nothing of the run's
    (a few seconds each time, most of it preparing the rollout's programs again after a run
    released them). ``params`` is keyed by its values, arrays included (a mission's layout)."""
    leaves, structure = jax.tree.flatten(params)
    values = tuple((a.dtype.str, a.shape, a.tobytes()) for a in map(np.asarray, leaves))
    key = (name, seed, episodes, structure, values)
    if key not in _references:
        if len(_references) >= REFERENCES_KEPT:
            del _references[next(iter(_references))]
        policy = REFERENCE_POLICIES[name]
        _references[key] = rollout(policy, jax.random.PRNGKey(seed), params, episodes).stats.summary()
    return dict(_references[key])


@contextmanager
def _progress(enabled: bool) -> Iterator[Callable[[str, int], None]]:
    """Yields ``show(what, total)``, called before each rollout: on an interactive terminal
    (and ``enabled``) a transient bar of what runs now out of ``total``; elsewhere nothing at
    all, not even an empty line."""
    output = console()
    if not (enabled and output.is_interactive):
        yield lambda what, total: None
        return
    columns = (TextColumn("{task.description}", markup=False), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=output, transient=True) as bar:
        task, done = bar.add_task("evaluating"), itertools.count()
        yield lambda what, total: bar.update(task, description=what, total=total, completed=next(done), refresh=True)


def _targets(run: Run, scenario: str | None) -> list[tuple[str, EnvParams]]:
    """(name, params) of every size to evaluate ``run`` on (see :class:`EvaluateConfig`)."""
    name = run.config.scenario if scenario is None and run.config.mission is None else scenario
    if name is None:
        return [(run.config.env_name(), run.params)]
    sizes = scenario_sizes(name)
    names = [name] if len(sizes) == 1 else [f"paper-{n}" for n in sizes]
    targets = [(n, get_scenario(n).replace(nearest_first=run.params.nearest_first)) for n in names]
    hint = (
        f"Its policies drive those numbers only: omit --scenario (its own {run.config.env_name()}) or give a scenario "
        "of the same numbers; for any size, train with --network nearest (or entity with --algo mappo or ippo)."
    )
    for target, params in targets:  # the run's own check, without loading its networks once per size
        check_fits(run, params, f"scenario '{target}'", hint, "--scenario")
    return targets
