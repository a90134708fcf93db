"""The PettingZoo wrapper passes PettingZoo's own API tests and converts agents faithfully."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from roverswarm.env import SCENARIOS
from roverswarm.env.pettingzoo import RoverSwarmEnv, agent_names, split_agents, stack_agents
from roverswarm.errors import UserError


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_parallel_api(scenario):
    parallel_api_test(RoverSwarmEnv(scenario), num_cycles=60)


def test_same_seed_same_episodes():
    parallel_seed_test(lambda: RoverSwarmEnv("paper-3"))


def test_converters_round_trip():
    agents = agent_names(4)
    array = np.arange(8, dtype=np.float32).reshape(4, 2)
    as_dict = split_agents(array, agents)
    assert list(as_dict) == ["rover_0", "rover_1", "rover_2", "rover_3"]
    np.testing.assert_array_equal(stack_agents(as_dict, agents), array)
    shuffled = {a: as_dict[a] for a in reversed(agents)}
    np.testing.assert_array_equal(stack_agents(shuffled, agents), array)


def test_episode_truncates_after_25_steps_and_rewards_match_infos():
    env = RoverSwarmEnv("paper-2")
    obs, _ = env.reset(seed=3)
    assert obs["rover_0"].shape == env.observation_space("rover_0").shape
    for t in range(25):
        assert env.agents == ["rover_0", "rover_1"]
        obs, rewards, terms, truncs, infos = env.step({a: np.zeros(2, np.float32) for a in env.agents})
        for a in rewards:
            info = infos[a]
            expected = -info["coverage_distance"] - info["collisions"] - info["trap_contacts"]
            assert rewards[a] == pytest.approx(expected, abs=1e-5)
    assert all(truncs.values()) and not any(terms.values())
    assert env.agents == []
    with pytest.raises(UserError, match="finished episode"):
        env.step({})


def test_state_before_reset_and_bad_seeds_are_refused():
    env = RoverSwarmEnv("paper-2")
    with pytest.raises(UserError, match=r"^state\(\) called before reset\(\)"):
        env.state()
    for seed in (1.5, -1, 2**32, True):
        with pytest.raises(UserError, match=r"^reset\(seed=...\) must be an integer in \[0, 2\^32\)"):
            env.reset(seed=seed)
    first, _ = env.reset(seed=np.int64(3))  # NumPy's integers are seeds too
    np.testing.assert_array_equal(first["rover_0"], env.reset(seed=3)[0]["rover_0"])
    assert env.state().shape == (2 * first["rover_0"].size,)


def test_missing_or_misshapen_actions_are_refused():
    env = RoverSwarmEnv("paper-2")
    env.reset(seed=0)
    with pytest.raises(UserError, match="no action given for rover_1"):
        env.step({"rover_0": np.zeros(2)})
    with pytest.raises(UserError, match=r"shape \(2,\)"):
        env.step({"rover_0": np.zeros(3), "rover_1": np.zeros(3)})
    with pytest.raises(UserError, match=r"shape \(2,\), got rover_1 \(3,\)"):
        env.step({"rover_0": np.zeros(2), "rover_1": np.zeros(3)})


def test_unknown_agents_and_non_finite_actions_are_refused():
    """An action for a name that is not an agent of the episode, or one with NaN or infinity
    (NaN spread to every observation), is refused and the episode is left as it was."""
    env = RoverSwarmEnv("paper-2")
    obs, _ = env.reset(seed=0)
    zeros = {a: np.zeros(2, np.float32) for a in env.agents}
    with pytest.raises(UserError, match="actions given for 'rover_9', which are not agents of this episode"):
        env.step({**zeros, "rover_9": np.zeros(2)})
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="the actions of rover_1 are not finite"):
            env.step({**zeros, "rover_1": np.array([0.0, bad])})
    obs, *_ = env.step(zeros)
    assert all(np.isfinite(o).all() for o in obs.values())


def test_rgb_array_render_shows_the_rovers():
    env = RoverSwarmEnv("paper-3", render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    env.step({a: np.ones(2, np.float32) for a in env.agents})
    second = env.render()
    assert first.shape == second.shape and first.ndim == 3 and first.shape[2] == 3 and first.dtype == np.uint8
    assert not np.array_equal(first, second)
    assert RoverSwarmEnv("paper-3").render() is None


def test_the_environment_imports_nothing_above_it():
    """The environment package (and its PettingZoo wrapper) loads neither the trainer nor optax."""
    code = (
        "import sys, roverswarm.env.pettingzoo; "
        "print(sorted(m for m in sys.modules if m.startswith(('roverswarm', 'optax'))))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300
    ).stdout
    assert "roverswarm.env.pettingzoo" in loaded
    for above in ("optax", "roverswarm.trainer", "roverswarm.algos", "roverswarm.buffers", "roverswarm.config"):
        assert f"'{above}" not in loaded, loaded
