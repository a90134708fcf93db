"""A PettingZoo ``ParallelEnv`` over the JAX environment, so any MARL library can use it.

NumPy in and out, agents named ``rover_0`` .. ``rover_{N-1}``, Box spaces, and
``render_mode="rgb_array"``. This is the only place with a dict-of-agents view; the two
converters :func:`stack_agents` and :func:`split_agents` are the whole bridge.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from roverswarm.env.mars import ACTION_SIZE, EnvParams, is_padded, observation_size, observe, reset, step_env
from roverswarm.env.render import FrameRenderer
from roverswarm.env.scenarios import get_scenario
from roverswarm.env.validation import validate_params
from roverswarm.errors import UserError
from roverswarm.limits import check_seed


def agent_names(num_rovers: int) -> list[str]:
    """``["rover_0", ..., "rover_{N-1}"]``."""
    return [f"rover_{i}" for i in range(num_rovers)]


def stack_agents(values: dict[str, Any], agents: list[str]) -> np.ndarray:
    """Dict of per-agent arrays -> array with agents as the leading axis, in ``agents`` order."""
    missing = [a for a in agents if a not in values]
    if missing:
        raise UserError(f"no action given for {', '.join(missing)}; every live rover needs one")
    return np.stack([np.asarray(values[a], dtype=np.float32) for a in agents])


def split_agents(array: np.ndarray, agents: list[str]) -> dict[str, Any]:
    """Array with agents as the leading axis -> dict keyed by agent name."""
    return {a: array[i] for i, a in enumerate(agents)}


_reset = jax.jit(reset)
_step = jax.jit(step_env)


class RoverSwarmEnv(ParallelEnv):
    """PettingZoo parallel environment of a roverswarm scenario.

    ``RoverSwarmEnv("paper-3")`` or ``RoverSwarmEnv(params=EnvParams(...))``. Rewards are the
    per-rover rewards of eq. 16; ``info`` per rover holds its collisions and trap contacts
    this step, the swarm's coverage distance and the number of POIs observed so far.
    """

    metadata = {"name": "roverswarm_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(self, scenario: str = "paper-3", params: EnvParams | None = None, render_mode: str | None = None):
        if render_mode not in (None, "rgb_array"):
            raise UserError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.params = validate_params(params) if params is not None else get_scenario(scenario)
        if is_padded(self.params):  # its empty slots would be agents, drawn and observed as zeros
            raise UserError(
                "RoverSwarmEnv serves one swarm size: give params without active_rovers, active_pois or "
                "active_traps (e.g. get_scenario('paper-4')), not a padded layout"
            )
        self.render_mode = render_mode
        self.possible_agents = agent_names(self.params.num_rovers)
        self.agents: list[str] = []
        self._key = jax.random.PRNGKey(int(np.random.SeedSequence().generate_state(1)[0]))
        self._state = None
        self._trail: list[np.ndarray] = []
        self._renderer = None

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-np.inf, np.inf, (observation_size(self.params),), np.float32)

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32)

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._key = jax.random.PRNGKey(check_seed(seed, "reset(seed=...)"))
        self._key, key = jax.random.split(self._key)
        obs, self._state = _reset(key, self.params)
        self.agents = list(self.possible_agents)
        self._trail = [np.asarray(self._state.rover_pos)]
        return split_agents(np.asarray(obs), self.agents), {a: {} for a in self.agents}

    def step(self, actions: dict[str, np.ndarray]):
        if not self.agents:
            raise UserError("step() called on a finished episode; call reset() first")
        stacked = self._action_array(actions)
        obs, self._state, rewards, terminated, truncated, info = _step(self._state, jnp.asarray(stacked), self.params)
        self._trail.append(np.asarray(self._state.rover_pos))
        agents = self.agents
        info = jax.device_get(info)
        infos = {
            a: {
                "collisions": int(info["collisions"][i]),
                "trap_contacts": int(info["trap_contacts"][i]),
                "coverage_distance": float(info["coverage_distance"]),
                "pois_observed": int(info["pois_observed"]),
            }
            for i, a in enumerate(agents)
        }
        rewards = {a: float(r) for a, r in zip(agents, np.asarray(rewards))}
        terms = dict.fromkeys(agents, bool(terminated))
        truncs = dict.fromkeys(agents, bool(truncated))
        if bool(terminated) or bool(truncated):
            self.agents = []
        return split_agents(np.asarray(obs), agents), rewards, terms, truncs, infos

    def _action_array(self, actions: dict[str, Any]) -> np.ndarray:
        """``actions`` as an array [N, 2] in agent order; :class:`UserError` for an action given
        to a name that is not a rover of the episode, a rover without one, and an action of
        another shape or not finite (NaN would spread to every observation)."""
        unknown = [repr(a) for a in actions if a not in self.agents]
        if unknown:
            raise UserError(
                f"actions given for {', '.join(unknown)}, which are not agents of this episode; the agents are "
                f"{', '.join(self.agents)}"
            )
        shapes = {a: np.shape(actions[a]) for a in self.agents if a in actions}
        wrong = [f"{a} {shape}" for a, shape in shapes.items() if shape != (ACTION_SIZE,)]
        if wrong:
            raise UserError(f"each action must have shape ({ACTION_SIZE},), got {', '.join(wrong)}")
        stacked = stack_agents(actions, self.agents)
        bad = [a for a, action in zip(self.agents, stacked) if not np.isfinite(action).all()]
        if bad:
            raise UserError(
                f"the actions of {', '.join(bad)} are not finite (NaN or infinity); each action is a force in "
                "[-1, 1]^2, larger values are clipped"
            )
        return stacked

    def state(self) -> np.ndarray:
        """Global state: every rover's observation, concatenated."""
        if self._state is None:
            raise UserError("state() called before reset(); call reset() first")
        return np.asarray(observe(self._state, self.params)).reshape(-1)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None or self._state is None:
            return None
        if self._renderer is None:
            self._renderer = FrameRenderer(self.params)
        s = self._state
        return self._renderer.frame(
            np.stack(self._trail),
            np.asarray(s.poi_pos),
            np.asarray(s.trap_pos),
            np.asarray(s.observed),
            f"step {int(s.time)}/{self.params.max_steps}",
        )

    def close(self) -> None:
        self._renderer = None
