"""roverswarm: multi-agent reinforcement learning of rover swarms exploring a planetary surface.

From a notebook::

    import roverswarm
    result = roverswarm.train(roverswarm.TrainConfig(scenario="spread-3", episodes=20_000), out="runs/spread-3")
    rows = roverswarm.evaluate_run("runs/spread-3")          # random, oracle and every seed
    policy = roverswarm.Run("runs/spread-3").policy(seed=0)  # a run folder as a policy

``roverswarm.train`` is a plain function (:func:`roverswarm.trainer.train`); the modules are
named for what they hold (``config``, ``trainer``, ``runs``, ``rollout``, ``evaluate``, ...).
The names below load their modules on first use, so ``import roverswarm.env`` (or the
PettingZoo wrapper) does not load the trainer:

- ``train`` (``roverswarm.trainer``): train the seeds of a config together, into a run folder with ``out``;
- ``Result`` (``roverswarm.trainer``): what ``train`` returns: the config, the metrics rows and the networks;
- ``TrainConfig`` (``roverswarm.config``): a training run's settings, those of ``roverswarm train``;
- ``AlgoConfig`` (``roverswarm.algos.learner``): the learner's hyper-parameters (``TrainConfig.learner``);
- ``ReplayConfig`` (``roverswarm.buffers.base``): the replay's kind, size and batches (``TrainConfig.buffer``);
- ``PRESETS`` (``roverswarm.presets``): the ``TrainConfig`` of each ``train --preset``, by name;
- ``Run`` (``roverswarm.runs``): a run folder: its config, metrics, networks and policies;
- ``evaluate_run`` (``roverswarm.evaluate``): deterministic episodes of every seed of a run folder.
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


def __dir__() -> list[str]:
    """The module's names with the public ones it loads on first use (:data:`__all__`), for
    ``dir(roverswarm)``, ``help(roverswarm)`` and completion."""
    return sorted({*globals(), *__all__})


def __getattr__(name: str):
    """A public name of :data:`__all__`, its module imported on first use."""
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'roverswarm' has no attribute '{name}'")
