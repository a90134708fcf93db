"""The Mars exploration environment: pure JAX functions, presets, rendering, PettingZoo wrapper."""

from roverswarm.env.mars import (
    ACTION_SIZE,
    EnvParams,
    EnvState,
    observation_size,
    observe,
    reset,
    step,
    step_env,
)
from roverswarm.env.scenarios import SCENARIOS, get_scenario, scenario_table
from roverswarm.env.validation import validate_params

__all__ = [
    "ACTION_SIZE",
    "EnvParams",
    "EnvState",
    "SCENARIOS",
    "get_scenario",
    "observation_size",
    "observe",
    "reset",
    "scenario_table",
    "step",
    "step_env",
    "validate_params",
]
