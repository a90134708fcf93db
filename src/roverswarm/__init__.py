"""roverswarm: multi-agent reinforcement learning of rover swarms exploring a planetary surface.

From a notebook::

    import roverswarm
    result = roverswarm.train(roverswarm.TrainConfig(scenario="spread-3", episodes=20_000))

``roverswarm.train`` is the training module, and calling it calls
:func:`roverswarm.train.train`, so ``import roverswarm.train`` and
``from roverswarm.train import REFERENCE`` keep working.
"""

import roverswarm.train  # noqa: F401 (makes the module callable; see train.py's last lines)
from roverswarm.algos.maddpg import AlgoConfig
from roverswarm.train import Result, TrainConfig

__version__ = "0.1.0"
__all__ = ["AlgoConfig", "Result", "TrainConfig", "train"]
