"""Deterministic evaluation of trained runs beside the random and oracle policies.

Every policy runs the same episodes (same layouts, same key); the normalised score
``(R - R_random) / (R_oracle - R_random)`` puts random at 0 and the oracle at 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import jax
import tyro

from roverswarm.errors import require
from roverswarm.limits import check_memory, check_seed, evaluation_parts
from roverswarm.policies import ORACLE, RANDOM
from roverswarm.rollout import normalized_score, rollout
from roverswarm.runs import Partners, Run, SubPolicies


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
    partners: Literal["own", "other-seeds"] = "own"
    """`own`: each seed's agents together; `other-seeds`: agent i of seed s beside the other
    agents of seeds s + 1, s + 2, ... (mod seeds), partners it never trained with (each rover
    acting as its own seed's policy would in its place: shared networks and normalised
    observations too)."""


def evaluate_run(
    out, episodes: int = 1000, seed: int = 0, sub_policies: SubPolicies = "random", partners: Partners = "own"
) -> list[dict[str, float | str]]:
    """Deterministic episodes of every seed's trained policy in run folder ``out``, beside the
    random and oracle policies on the same episodes (same layouts), with the normalised score.
    Runs with policy ensembles, and ``partners``, work as :meth:`Run.policies` says; the policy
    names say which.

    Returns one row per policy: ``policy``, the :meth:`EpisodeStats.summary` metrics and
    ``normalized_score``.
    """
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    check_seed(seed)
    run = Run(out)
    check_memory(evaluation_parts(run.config, run.params, episodes), "this evaluation")
    key = jax.random.PRNGKey(seed)
    policies = run.policies(sub_policies, seed, partners)
    results = {p.name: rollout(p, key, run.params, episodes).stats.summary() for p in (RANDOM, ORACLE, *policies)}
    low, high = results["random"]["episode_reward"], results["oracle"]["episode_reward"]
    return [
        {"policy": name, **summary, "normalized_score": normalized_score(summary["episode_reward"], low, high)}
        for name, summary in results.items()
    ]
