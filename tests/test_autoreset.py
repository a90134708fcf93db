"""The auto-resetting ``step`` against a plain loop of ``reset`` + ``step_env`` with the same keys
(staggered episodes, vmapped, nested vmap, one environment, batched params), and the layout
sampler against a NumPy loop over its rule."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.env import EnvParams, get_scenario, reset, step, step_env
from roverswarm.env.layouts import LAYOUT_CANDIDATES
from roverswarm.env.scenarios import padded_scenario, sized

ENVS, STEPS = 6, 40
# three episodes end together at step 25 (more than one chunk of resets), one at the first step
START_TIMES = jnp.array([0, 0, 0, 5, 24, 13], jnp.int32)
SIZES = (2, 4, 3, 4, 2, 3)  # the padded case: each environment's N


def cases():
    unpadded = get_scenario("paper-3").replace(fail_rate=0.5)
    padded = padded_scenario("paper-2..4").replace(fail_rate=0.5)
    return {"unpadded": (unpadded, None), "padded, mixed sizes": (padded, SIZES)}


def params_of(params: EnvParams, sizes, i):
    return params if sizes is None else sized(params, sizes[i])


def run_step(params: EnvParams, sizes, states, actions, keys):
    """``jit(scan(vmap(step)))`` over ``actions`` [T, E, N, 2] and ``keys`` [T, E]; params vmapped
    with the environments when ``sizes`` is given."""
    counts = jnp.asarray(SIZES)  # unused by the unpadded case

    def one(key, state, action, n):
        return step(key, state, action, params if sizes is None else sized(params, n))

    def body(states, xs):
        obs, states, rewards, _, truncated, info = jax.vmap(one)(xs[1], states, xs[0], counts)
        return states, (obs, states, rewards, truncated, info["final_obs"])

    return jax.jit(lambda s, a, k: jax.lax.scan(body, s, (a, k))[1])(states, actions, keys)


@functools.cache
def episodes_of(case: str):
    """(params, sizes, states at the start, actions, keys, outputs of the vmapped step)."""
    params, sizes = cases()[case]
    key = jax.random.PRNGKey(11)
    starts = [jax.jit(reset)(k, params_of(params, sizes, i)) for i, k in enumerate(jax.random.split(key, ENVS))]
    states = jax.tree.map(lambda *xs: jnp.stack(xs), *(s for _, s in starts)).replace(time=START_TIMES)
    actions = jax.random.uniform(jax.random.PRNGKey(12), (STEPS, ENVS, params.num_rovers, 2), minval=-1, maxval=1)
    keys = jax.random.split(jax.random.PRNGKey(13), STEPS * ENVS).reshape(STEPS, ENVS, -1)
    return params, sizes, states, actions, keys, run_step(params, sizes, states, actions, keys)


@pytest.fixture(scope="module", params=list(cases()))
def episodes(request):
    return episodes_of(request.param)


def test_auto_reset_episodes_equal_a_loop_of_reset_and_step_env_with_the_same_keys(episodes):
    """Environment by environment, step by step: ``step_env``, and where the episode ended
    ``reset`` with that step's key; the vmapped ``step`` gives the same observations, states,
    rewards and final observations, and its new layouts are those of ``reset`` to the bit."""
    params, sizes, states, actions, keys, (obs, new_states, rewards, truncated, final_obs) = episodes
    one_step, one_reset = jax.jit(step_env), jax.jit(reset)
    resets = 0
    for i in range(ENVS):
        p = params_of(params, sizes, i)
        state = jax.tree.map(lambda x, i=i: x[i], states)
        for t in range(STEPS):
            ref_obs, state, ref_rewards, _, ref_truncated, _ = one_step(state, actions[t, i], p)
            np.testing.assert_allclose(final_obs[t, i], ref_obs, atol=1e-6)
            np.testing.assert_allclose(rewards[t, i], ref_rewards, atol=1e-5)
            assert bool(truncated[t, i]) == bool(ref_truncated)
            if ref_truncated:
                ref_obs, state = one_reset(keys[t, i], p)
                resets += 1
                for got, want in zip(jax.tree.leaves(new_states), jax.tree.leaves(state)):
                    np.testing.assert_array_equal(got[t, i], want)
            np.testing.assert_allclose(obs[t, i], ref_obs, atol=1e-6)
            for got, want in zip(jax.tree.leaves(new_states), jax.tree.leaves(state)):
                np.testing.assert_allclose(got[t, i], want, atol=1e-6)
    assert resets == 8  # once or twice per environment in 40 steps


def test_nested_vmap_and_one_environment_give_the_same_episodes():
    """vmap over 2 x 3 environments, and one environment's ``jit(scan(step))`` without vmap,
    reproduce the flat vmapped run."""
    params, _, states, actions, keys, (obs, _, rewards, _, _) = episodes_of("unpadded")
    grid = lambda x: x.reshape(2, 3, *x.shape[1:])

    def nested(states, actions, keys):
        def body(states, xs):
            out = jax.vmap(jax.vmap(step, in_axes=(0, 0, 0, None)), in_axes=(0, 0, 0, None))(
                xs[1], states, xs[0], params
            )
            return out[1], out[0]

        return jax.lax.scan(body, jax.tree.map(grid, states), (jax.vmap(grid)(actions), jax.vmap(grid)(keys)))[1]

    np.testing.assert_array_equal(jax.jit(nested)(states, actions, keys).reshape(obs.shape), obs)

    def alone(state, actions, keys):
        def body(state, xs):
            _, state, rewards, *_ = step(xs[1], state, xs[0], params)
            return state, rewards

        return jax.lax.scan(body, state, (actions, keys))[1]

    env = 4  # ends at the first step and at step 26
    got = jax.jit(alone)(jax.tree.map(lambda x: x[env], states), actions[:, env], keys[:, env])
    np.testing.assert_allclose(got, rewards[:, env], atol=1e-5)


def test_gradients_flow_through_step_as_through_step_env(paper3):
    """Reverse-mode differentiation of a vmapped ``step`` with respect to the actions works (the
    reset never sees a value with a gradient): the observations' gradient is ``step_env``'s where
    the episode goes on, zero where it ended (a fresh episode does not depend on the actions)."""
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    _, states = jax.vmap(reset, in_axes=(0, None))(keys, paper3)
    states = states.replace(time=jnp.array([0, 24, 3, 24], jnp.int32))
    actions = jax.random.uniform(jax.random.PRNGKey(1), (4, 3, 2), minval=-1, maxval=1)
    with_reset = jax.grad(lambda a: jax.vmap(step, in_axes=(0, 0, 0, None))(keys, states, a, paper3)[0].sum())
    without = jax.grad(lambda a: jax.vmap(step_env, in_axes=(0, 0, None))(states, a, paper3)[0].sum())
    got, want = jax.jit(lambda a: (with_reset(a), without(a)))(actions)
    ended = np.array([False, True, False, True])
    assert np.abs(want).min() > 0
    np.testing.assert_allclose(got, np.where(ended[:, None, None], 0.0, want), atol=1e-6)


def test_gradients_through_many_steps_are_finite_even_with_rovers_at_one_spot(paper3):
    """The contact force took the root of a rover's zero distance to itself: its infinite
    gradient made the gradient of any rollout longer than two steps NaN; two rovers at one
    spot made the forward pass NaN too; a rover standing exactly on a POI (a mission may start
    it there) made the coverage distance's gradient NaN."""
    _, state = reset(jax.random.PRNGKey(0), paper3)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (6, 3, 2), minval=-1, maxval=1)

    def total(actions, state):
        def body(state, a):
            _, state, rewards, *_ = step_env(state, a, paper3)
            return state, rewards.sum()

        return jax.lax.scan(body, state, actions)[1].sum()

    together = state.replace(rover_pos=state.rover_pos.at[1].set(state.rover_pos[0]))
    on_a_poi = state.replace(
        rover_pos=state.rover_pos.at[2].set(state.poi_pos[0]), rover_vel=jnp.zeros_like(state.rover_vel)
    )
    still = actions.at[:, 2].set(0.0)  # the rover on the POI stays there
    for start, acts in ((state, actions), (together, actions), (on_a_poi, still)):
        value, grads = jax.jit(jax.value_and_grad(total))(acts, start)
        assert np.isfinite(value) and np.isfinite(grads).all() and np.abs(grads).max() > 0


# ----------------------------------------------------------------------------- the layout sampler


def reference_layout(key, params: EnvParams, exists=None, spaced: bool = True):
    """The sampler's rule as a NumPy loop, from the candidates of its key schedule: ``split(key, 3)``
    for POIs, traps and rovers; each trap and rover takes its first candidate clear of what it must
    not touch (of the entities that exist), its first if none is. ``spaced=False`` leaves out
    the start zone's spacing between rovers."""
    n, p, t = params.num_rovers, params.num_pois, params.num_traps
    k_poi, k_trap, k_rover = jax.random.split(key, 3)
    size, r = params.map_size, params.rover_radius
    keep = params.trap_radius + r
    pois = np.asarray(jax.random.uniform(k_poi, (p, 2), minval=-size, maxval=size))
    low, high = (-size, size) if params.start_zone is None else params.start_zone
    trap_cand = np.asarray(jax.random.uniform(k_trap, (t, LAYOUT_CANDIDATES, 2), minval=-size, maxval=size))
    rover_cand = np.asarray(jax.random.uniform(k_rover, (n, LAYOUT_CANDIDATES, 2), minval=low, maxval=high))
    rovers_exist, pois_exist, traps_exist = exists or (np.ones(n, bool), np.ones(p, bool), np.ones(t, bool))

    def first_clear(candidates, obstacles):  # obstacles: (position, clearance) pairs
        for c in candidates:
            if all(np.hypot(*(c - o)) >= gap for o, gap in obstacles):
                return c
        return candidates[0]

    traps = np.array([first_clear(trap_cand[j], [(q, keep) for q, e in zip(pois, pois_exist) if e]) for j in range(t)])
    rovers = []
    for i in range(n):
        obstacles = [(q, keep) for q, e in zip(traps, traps_exist) if e]
        if params.start_zone is not None and spaced:
            obstacles += [(q, 2 * r) for q, e in zip(rovers, rovers_exist) if e]
        rovers.append(first_clear(rover_cand[i], obstacles))
    return pois, traps, np.array(rovers)


LAYOUT_CASES = {
    "paper-5": get_scenario("paper-5"),
    "crowded start zone": EnvParams(
        num_rovers=8, num_pois=3, num_traps=4, start_zone=jnp.array([[-0.6, -0.6], [0.1, 0.1]])
    ),
    "padded paper-2..6 at N = 4": sized(padded_scenario("paper-2..6"), 4),
}


@pytest.mark.parametrize("name", list(LAYOUT_CASES))
def test_reset_draws_the_layout_a_numpy_loop_draws_from_the_same_candidates(name):
    params = LAYOUT_CASES[name]
    keys = jax.random.split(jax.random.PRNGKey(21), 30)
    _, states = jax.jit(jax.vmap(reset, in_axes=(0, None)))(keys, params)
    exists = None
    if params.active_rovers is not None:
        exists = tuple(np.arange(params.num_rovers) < params.active_rovers for _ in range(3))
    spacing_mattered = 0
    for i, key in enumerate(keys):
        pois, traps, rovers = reference_layout(key, params, exists)
        np.testing.assert_allclose(states.poi_pos[i], pois, atol=1e-6)
        np.testing.assert_allclose(states.trap_pos[i], traps, atol=1e-6)
        np.testing.assert_allclose(states.rover_pos[i], rovers, atol=1e-6)
        if params.start_zone is not None:
            spacing_mattered += not np.array_equal(rovers, reference_layout(key, params, exists, spaced=False)[2])
    assert params.start_zone is None or spacing_mattered > 0, "the case must exercise the spacing in a start zone"
