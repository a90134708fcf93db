"""roverswarm: multi-agent reinforcement learning of rover swarms exploring a planetary surface.

From a notebook::

    import roverswarm
    result = roverswarm.train(roverswarm.TrainConfig(scenario="spread-3", episodes=20_000), out="runs/spread-3")
    rows = roverswarm.evaluate_run("runs/spread-3")          # random, oracle and every seed
    policy = roverswarm.Run("runs/spread-3").policy(seed=0)  # a run folder as a policy

``roverswarm.train`` is a plain function (:func:`roverswarm.trainer.train`); the modules are
named for what they hold (``config``, ``trainer``, ``runs``, ``rollout``, ``evaluate``, ...).
The names below load their modules on first use, so ``import roverswarm.env`` (or the
PettingZoo wrapper) does not load the trainer.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from roverswarm.algos.learner import AlgoConfig
    from roverswarm.buffers.base import ReplayConfig
    from roverswarm.config import TrainConfig
    from roverswarm.evaluate import evaluate_run
    from roverswarm.presets import PRESETS
    from roverswarm.runs import Run
    from roverswarm.trainer import Result, train

_EXPORTS = {
    "AlgoConfig": "roverswarm.algos.learner",
    "ReplayConfig": "roverswarm.buffers.base",
    "PRESETS": "roverswarm.presets",
    "TrainConfig": "roverswarm.config",
    "evaluate_run": "roverswarm.evaluate",
    "Run": "roverswarm.runs",
    "Result": "roverswarm.trainer",
    "train": "roverswarm.trainer",
}

__version__ = "0.1.0"
__all__ = ["PRESETS", "AlgoConfig", "ReplayConfig", "Result", "Run", "TrainConfig", "evaluate_run", "train"]


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'roverswarm' has no attribute '{name}'")
