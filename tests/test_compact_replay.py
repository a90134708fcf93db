"""The compact replay against a replay of full observations: the same stream of transitions,
the same draws, and the batches a learner reads must be equal bit for bit, for every replay
kind (uniform, ranked; with and without the partitions of policy ensembles), for the
recent batches of inferred policies, and for both observation orders."""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.buffers import ReplayConfig, Transition, compact, make_buffer
from roverswarm.buffers.base import gather, recent_indices
from roverswarm.buffers.compact import Collected, layout_of, rovers_of
from roverswarm.config import TrainConfig, validate, with_options
from roverswarm.env.mars import ACTION_SIZE, observation_size, observe, reset, step_env
from roverswarm.env.scenarios import get_scenario
from roverswarm.trainer import replay_bytes

ENVS = 8  # one add: 8 episodes of 25 steps, as an iteration of 8 environments
CAPACITY = 450  # not a multiple of an add, so the ring wraps mid-add and mid-episode


def stream(params, adds: int, ensemble: int, seed: int = 0):
    """``adds`` batches of ENVS episodes of random actions, both as full :class:`Transition`
    (flattened time-major, as the trainer adds them) and as the compact replay's
    :class:`~roverswarm.buffers.compact.Collected`."""

    @jax.jit
    def episodes(key):
        k_reset, k_act, k_policy = jax.random.split(key, 3)
        _, start = jax.vmap(reset, in_axes=(0, None))(jax.random.split(k_reset, ENVS), params)
        policy = jax.random.randint(k_policy, (ENVS, params.num_rovers), 0, ensemble) if ensemble > 1 else None

        def body(state, k):
            actions = jax.random.uniform(k, (ENVS, params.num_rovers, ACTION_SIZE), minval=-1, maxval=1)
            _, next_state, rewards, terminated, _, _ = jax.vmap(step_env, in_axes=(0, 0, None))(state, actions, params)
            full = Transition(
                obs=jax.vmap(observe, in_axes=(0, None))(state, params),
                actions=actions,
                rewards=rewards,
                next_obs=jax.vmap(observe, in_axes=(0, None))(next_state, params),
                terminated=terminated,
                policy=policy,
            )
            return next_state, (full, rovers_of(state))

        last, (full, rovers) = jax.lax.scan(body, start, jax.random.split(k_act, params.max_steps))
        collected = Collected(
            rovers, full.actions, full.rewards, full.terminated, layout_of(start), rovers_of(last), policy
        )
        return jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), full), collected

    return [episodes(key) for key in jax.random.split(jax.random.PRNGKey(seed), adds)]


@pytest.mark.parametrize("nearest_first", [False, True], ids=["index-order", "nearest-first"])
@pytest.mark.parametrize("ensemble", [1, 2], ids=["K=1", "K=2"])
@pytest.mark.parametrize("replay", ["uniform", "ranked"])
def test_compact_batches_equal_the_full_replays(replay, ensemble, nearest_first):
    params = dataclasses.replace(get_scenario("paper-3"), nearest_first=nearest_first)
    buffer = make_buffer(ReplayConfig(replay=replay, buffer_size=CAPACITY, batch_size=64), params.num_rovers, ensemble)
    batches = stream(params, adds=5, ensemble=ensemble)  # 1000 transitions: the ring wraps twice
    full_state = buffer.init(jax.tree.map(lambda x: x[0], batches[0][0]))
    compact_state = compact.init(buffer, params, ENVS)
    add_full, add_compact = jax.jit(buffer.add), jax.jit(partial(compact.add, buffer))
    expand = jax.jit(partial(compact.expand, params=params, num_envs=ENVS))
    losses = np.random.default_rng(0)
    for i, (full, collected) in enumerate(batches):
        full_state, compact_state = add_full(full_state, full), add_compact(compact_state, collected)
        key = jax.random.PRNGKey(i)
        picked = jax.jit(buffer.draw)(compact_state, key)
        np.testing.assert_array_equal(picked.indices, jax.jit(buffer.draw)(full_state, key).indices)
        jax.tree.map(
            np.testing.assert_array_equal, expand(compact_state, picked.indices), gather(full_state, picked.indices)
        )
        recent = recent_indices(compact_state, key, 300, 64)
        jax.tree.map(np.testing.assert_array_equal, expand(compact_state, recent), gather(full_state, recent))
        # every stored transition, the oldest (partly overwritten adds) included
        stored = jnp.arange(int(full_state.size))
        jax.tree.map(np.testing.assert_array_equal, expand(compact_state, stored), gather(full_state, stored))
        # the ranked replay's losses and re-ranking read only indices, so both stay in step
        written = jnp.asarray(losses.random(picked.indices.shape), jnp.float32)
        full_state = buffer.set_priorities(full_state, picked.indices, written)
        compact_state = buffer.set_priorities(compact_state, picked.indices, written)
        full_state, compact_state = buffer.refresh(full_state, True), buffer.refresh(compact_state, True)
    assert int(compact_state.size) == CAPACITY


def test_a_transition_is_stored_in_at_most_15_percent_of_the_bytes_at_n5_and_10_percent_at_n10():
    for scenario, share in (("paper-5", 0.15), ("paper-10", 0.10)):
        config = with_options(TrainConfig(), {"scenario": scenario})
        params = validate(config)
        n = params.num_rovers
        # full: observation and next observation (N x O floats each), actions, rewards, terminated
        full_bytes = 4 * (2 * n * observation_size(params) + n * ACTION_SIZE + n) + 1
        per_transition = replay_bytes(config, params)[2]
        assert per_transition <= share * full_bytes, (scenario, per_transition, full_bytes)
