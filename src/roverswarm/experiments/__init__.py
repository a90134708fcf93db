"""The paper's experiments: the grid of runs (local or Ray) and its Table I, Figures 8-9 and report."""

from roverswarm.experiments.arms import ALGORITHMS, ReproduceConfig
from roverswarm.experiments.grid import run_grid
from roverswarm.experiments.paper import reproduce

__all__ = ["ALGORITHMS", "ReproduceConfig", "reproduce", "run_grid"]
