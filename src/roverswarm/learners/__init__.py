"""The learner families behind one record (:class:`~roverswarm.learners.base.Family`) and the
registry that maps ``--algo`` to its family: the one place that knows which learner is which.

A new family is one module building a :class:`~roverswarm.learners.base.Family` record, plus
its algorithms' lines in :data:`FAMILIES`; a new network kind is an option of the families
that use it.
"""

from __future__ import annotations

from roverswarm.learners import offpolicy, onpolicy
from roverswarm.learners.base import Family, Runner

FAMILIES: dict[str, Family] = {
    "maddpg": offpolicy.FAMILY,
    "ddpg": offpolicy.FAMILY,
    "mappo": onpolicy.FAMILY,
    "ippo": onpolicy.FAMILY,
}
"""``--algo`` -> its learner family."""

ALGOS: tuple[str, ...] = tuple(FAMILIES)

FAMILY_OPTIONS: frozenset[str] = frozenset().union(*(f.options for f in FAMILIES.values()))
"""Every option some family reads and another does not (with the options every family reads)."""


def learner_family(algo: str) -> Family:
    """The family of ``--algo`` ``algo`` (validated: see :func:`roverswarm.config.validate`)."""
    return FAMILIES[algo]


__all__ = ["ALGOS", "FAMILIES", "FAMILY_OPTIONS", "Family", "Runner", "learner_family"]
