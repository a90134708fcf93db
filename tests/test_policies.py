"""Reference policies: the oracle's assignment is optimal and it beats random by a wide margin."""

from __future__ import annotations

import dataclasses
import itertools
import math

import jax
import numpy as np
import pytest

from roverswarm.algos.learner import AlgoConfig, init_learner
from roverswarm.config import TrainConfig
from roverswarm.env import get_scenario
from roverswarm.env.mars import observation_size
from roverswarm.oracle import assign_pois
from roverswarm.policies import ORACLE, RANDOM, trained_policy
from roverswarm.rollout import normalized_score, rollout


def test_hungarian_assignment_matches_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(50):
        rovers, pois = rng.uniform(-1, 1, (5, 2)), rng.uniform(-1, 1, (5, 2))
        assigned = assign_pois(rovers, pois)
        goals = pois[assigned]
        best = min(
            sum(np.linalg.norm(rovers[i] - pois[j]) for i, j in enumerate(perm))
            for perm in itertools.permutations(range(5))
        )
        assert np.linalg.norm(rovers - goals, axis=1).sum() == pytest.approx(best, rel=1e-5)
        assert sorted(assigned) == list(range(5))


def test_assignment_with_more_rovers_than_pois_leaves_the_far_rover_without_one():
    rovers = np.array([[0.0, 0.0], [1.0, 1.0]])
    np.testing.assert_array_equal(assign_pois(rovers, np.array([[0.9, 0.9]])), [-1, 0])


@pytest.mark.parametrize("scenario", ["paper-2", "paper-3", "paper-4", "paper-5"])
def test_oracle_beats_random_by_a_wide_margin_with_few_trap_contacts(scenario):
    params = get_scenario(scenario)
    key = jax.random.PRNGKey(7)
    oracle = rollout(ORACLE, key, params, 1000).stats.summary()
    random = rollout(RANDOM, key, params, 1000).stats.summary()
    # rewards are negative: the oracle loses less than half of what random loses
    assert oracle["episode_reward"] > 0.5 * random["episode_reward"], (oracle, random)
    assert oracle["pois_observed"] > 0.95 * params.num_pois
    assert oracle["trap_contacts"] < 0.2 * random["trap_contacts"], (oracle, random)
    rover_steps = params.num_rovers * params.max_steps
    assert oracle["trap_contacts"] / rover_steps < 0.02, oracle


def test_the_normalised_score_places_random_at_0_the_oracle_at_1_and_is_undefined_where_they_tie():
    assert normalized_score(-30.0, -50.0, -10.0) == 0.5
    assert normalized_score(-50.0, -50.0, -10.0) == 0.0 and normalized_score(-5.0, -50.0, -10.0) == 1.125
    assert math.isnan(normalized_score(-7.0, -10.0, -10.0))  # no ZeroDivisionError after the rollouts


def test_rollouts_are_reproducible():
    params = get_scenario("paper-2")
    a = rollout(RANDOM, jax.random.PRNGKey(1), params, 16)
    b = rollout(RANDOM, jax.random.PRNGKey(1), params, 16)
    c = rollout(RANDOM, jax.random.PRNGKey(2), params, 16)
    np.testing.assert_array_equal(a.stats.reward, b.stats.reward)
    assert not np.array_equal(a.stats.reward, c.stats.reward)


def test_episode_reward_is_the_sum_of_per_rover_step_rewards():
    params = get_scenario("paper-3")
    result = rollout(RANDOM, jax.random.PRNGKey(0), params, 8)
    np.testing.assert_allclose(result.stats.reward, result.rewards.sum(axis=(1, 2)), rtol=1e-6)
    np.testing.assert_allclose(result.stats.agent_rewards.sum(axis=1), result.stats.reward, rtol=1e-5)
    assert result.rover_pos.shape == (8, params.max_steps + 1, 3, 2)


def test_a_trained_policy_sees_the_view_it_was_trained_on_whatever_the_environment_shows():
    params = get_scenario("paper-3")
    config = TrainConfig(learner=AlgoConfig(share_parameters=True, hidden=(16,)), nearest_first=True)
    learner = init_learner(jax.random.PRNGKey(0), config.learner, params.num_rovers, observation_size(params))
    key = jax.random.PRNGKey(1)
    nearest = trained_policy(config, learner.actor)
    shown = {view: rollout(nearest, key, params.replace(nearest_first=view), 8).rewards for view in (True, False)}
    np.testing.assert_allclose(shown[True], shown[False], rtol=1e-5)  # other programs: rounding only
    indexed = rollout(trained_policy(dataclasses.replace(config, nearest_first=False), learner.actor), key, params, 8)
    assert not np.allclose(indexed.rewards, shown[True])


def test_the_rollouts_of_trained_shielded_and_mixed_policies_keep_their_programs(tmp_path, monkeypatch):
    """A trained policy's act function is a closure; it names itself after its learner config
    (the same in every process, another for another config), as the shielded and mixed ones
    built on it do, so a rollout's program is kept on disk: one for the reset, one per policy;
    read back after the programs in memory are released, it gives the same numbers."""
    from roverswarm import jaxcache
    from roverswarm.policies import mixed_policy, shielded

    monkeypatch.setattr(jaxcache, "_store_dir", lambda: tmp_path)
    jaxcache.release_compiled_programs()  # none in memory: each is looked for in the store
    params = get_scenario("paper-2")
    config = TrainConfig(learner=AlgoConfig(share_parameters=True, hidden=(8,)))
    learner = init_learner(jax.random.PRNGKey(0), config.learner, params.num_rovers, observation_size(params))
    policy = trained_policy(config, learner.actor)
    wider = trained_policy(dataclasses.replace(config, learner=AlgoConfig(share_parameters=True, hidden=(9,))), None)
    policies = [policy, shielded(policy), mixed_policy("mix", [policy, policy]), wider]
    names = [jaxcache.stable_name(p.act) for p in policies]
    assert None not in names and len(set(names)) == 4, names
    assert names[0] == jaxcache.stable_name(trained_policy(config, learner.actor).act)
    first = [rollout(p, jax.random.PRNGKey(1), params, 4).rewards for p in policies[:3]]
    assert len(list(tmp_path.rglob("*.program"))) == 1 + 3  # in the source version's folder
    jaxcache.release_compiled_programs()
    again = [rollout(p, jax.random.PRNGKey(1), params, 4).rewards for p in policies[:3]]
    assert all(np.array_equal(a, b) for a, b in zip(first, again)) and len(list(tmp_path.rglob("*.program"))) == 4
