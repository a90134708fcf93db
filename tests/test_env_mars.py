"""The environment: parity with mpe2, reward terms, truncation/auto-reset, layout, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.env import EnvParams, EnvState, get_scenario, observe, reset, step, step_env, validate_params
from roverswarm.env.mars import NEVER, observation_size
from roverswarm.errors import UserError


def make_state(rover_pos, rover_vel=None, poi_pos=(), trap_pos=()) -> EnvState:
    rover_pos = jnp.asarray(rover_pos, jnp.float32)
    poi_pos = jnp.asarray(poi_pos, jnp.float32).reshape(-1, 2)
    return EnvState(
        rover_pos=rover_pos,
        rover_vel=jnp.zeros_like(rover_pos) if rover_vel is None else jnp.asarray(rover_vel, jnp.float32),
        poi_pos=poi_pos,
        trap_pos=jnp.asarray(trap_pos, jnp.float32).reshape(-1, 2),
        observed=jnp.zeros((poi_pos.shape[0],), bool),
        time=jnp.zeros((), jnp.int32),
        fail_step=jnp.full((rover_pos.shape[0],), NEVER, jnp.int32),
    )


# ----------------------------------------------------------------------------- parity with mpe2


@pytest.mark.parametrize("n", [3, 5])
def test_one_step_matches_mpe2_simple_spread(n):
    """From the same positions, velocities and actions, one step of our environment (no traps)
    gives mpe2's positions, velocities, observations, coverage distance and collision counts."""
    from mpe2.simple_spread.simple_spread import Scenario

    scenario = Scenario()
    world = scenario.make_world(n)
    scenario.reset_world(world, np.random.default_rng(0))
    params = EnvParams(num_rovers=n, num_pois=n, num_traps=0)
    rng = np.random.default_rng(n)
    samples = 300
    # a crowded region, so that many states have rovers in contact
    pos = rng.uniform(-0.5, 0.5, (samples, n, 2))
    vel = rng.normal(0.0, 0.7, (samples, n, 2))
    poi = rng.uniform(-1.0, 1.0, (samples, n, 2))
    act = rng.uniform(-1.0, 1.0, (samples, n, 2))

    states = jax.vmap(make_state)(pos, vel, poi, np.zeros((samples, 0, 2)))
    obs, new, rewards, _, _, info = jax.jit(jax.vmap(step_env, in_axes=(0, 0, None)))(
        states, jnp.asarray(act, jnp.float32), params
    )

    contacts_seen = 0
    for s in range(samples):
        for i, agent in enumerate(world.agents):
            agent.state.p_pos = pos[s, i].copy()
            agent.state.p_vel = vel[s, i].copy()
            agent.action.u = params.sensitivity * act[s, i]
            agent.action.c = np.zeros(world.dim_c)
        for j, landmark in enumerate(world.landmarks):
            landmark.state.p_pos = poi[s, j].copy()
        world.step()
        ref_pos = np.stack([a.state.p_pos for a in world.agents])
        ref_vel = np.stack([a.state.p_vel for a in world.agents])
        np.testing.assert_allclose(new.rover_pos[s], ref_pos, atol=1e-5)
        np.testing.assert_allclose(new.rover_vel[s], ref_vel, atol=1e-5)
        np.testing.assert_allclose(info["coverage_distance"][s], -scenario.global_reward(world), atol=1e-5)
        ref_collisions = [-scenario.reward(a, world) for a in world.agents]
        np.testing.assert_array_equal(info["collisions"][s], ref_collisions)
        contacts_seen += int(sum(ref_collisions) > 0)
        for i, agent in enumerate(world.agents):
            ref_obs = scenario.observation(agent, world)[: observation_size(params)]  # minus comm
            np.testing.assert_allclose(obs[s, i], ref_obs, atol=1e-5)
            ref_reward = scenario.global_reward(world) + scenario.reward(agent, world)
            np.testing.assert_allclose(rewards[s, i], ref_reward, atol=1e-5)
    assert contacts_seen > samples // 10, "the parity test must exercise contact forces"


# ----------------------------------------------------------------------------- reward terms


def test_two_touching_rovers_each_count_one_collision():
    params = EnvParams(num_rovers=3, num_pois=1, num_traps=0)
    state = make_state([[0.0, 0.0], [0.2, 0.0], [0.9, 0.9]], poi_pos=[[0.0, 0.0]])
    _, _, rewards, _, _, info = step_env(state, jnp.zeros((3, 2)), params)
    np.testing.assert_array_equal(info["collisions"], [1, 1, 0])
    np.testing.assert_allclose(info["coverage_distance"], 0.0, atol=1e-6)
    np.testing.assert_allclose(rewards, [-1.0, -1.0, 0.0], atol=1e-6)


def test_rover_inside_trap_counts_one_trap_contact():
    params = EnvParams(num_rovers=2, num_pois=1, num_traps=2)
    state = make_state([[0.5, 0.5], [-0.5, -0.5]], poi_pos=[[0.5, 0.5]], trap_pos=[[0.55, 0.5], [0.0, 0.0]])
    _, _, rewards, _, _, info = step_env(state, jnp.zeros((2, 2)), params)
    np.testing.assert_array_equal(info["trap_contacts"], [1, 0])
    np.testing.assert_array_equal(info["collisions"], [0, 0])
    np.testing.assert_allclose(rewards, [-1.0, 0.0], atol=1e-6)


def test_rover_far_from_everything_pays_only_the_coverage_distance():
    params = EnvParams(num_rovers=2, num_pois=2, num_traps=1)
    state = make_state([[-0.9, -0.9], [0.9, 0.9]], poi_pos=[[-0.9, -0.5], [0.9, 0.0]], trap_pos=[[0.0, 0.0]])
    _, _, rewards, _, _, info = step_env(state, jnp.zeros((2, 2)), params)
    np.testing.assert_allclose(info["coverage_distance"], 0.4 + 0.9, atol=1e-6)
    np.testing.assert_allclose(rewards, [-1.3, -1.3], atol=1e-6)
    assert int(info["collisions"].sum()) == 0 and int(info["trap_contacts"].sum()) == 0


def test_a_rover_never_collides_with_itself():
    params = EnvParams(num_rovers=1, num_pois=1, num_traps=0)
    state = make_state([[0.0, 0.0]], poi_pos=[[0.0, 0.0]])
    obs, new, rewards, _, _, info = step_env(state, jnp.zeros((1, 2)), params)
    assert int(info["collisions"][0]) == 0
    assert np.all(np.isfinite(np.asarray(new.rover_vel)))
    np.testing.assert_allclose(rewards, [0.0], atol=1e-6)


def test_pois_are_observed_within_the_observe_radius_and_stay_observed():
    params = EnvParams(num_rovers=1, num_pois=2, num_traps=0)
    state = make_state([[0.0, 0.0]], rover_vel=[[10.0, 0.0]], poi_pos=[[0.05, 0.0], [0.9, 0.9]])
    _, state2, _, _, _, info = step_env(state, jnp.zeros((1, 2)), params)  # moves 1.0 to the right
    assert int(info["pois_observed"]) == 0  # observed is taken after the move
    state = state.replace(rover_vel=jnp.zeros((1, 2)))
    _, state, _, _, _, info = step_env(state, jnp.zeros((1, 2)), params)
    assert int(info["pois_observed"]) == 1
    _, _, _, _, _, info = step_env(state.replace(rover_vel=jnp.array([[10.0, 0.0]])), jnp.zeros((1, 2)), params)
    assert int(info["pois_observed"]) == 1  # it stays observed after leaving


def test_pois_first_observed_counts_each_poi_at_the_step_a_rover_first_reaches_it(paper3):
    """info["pois_first_observed"] against NumPy: a POI counts once, at the first step after
    which a rover's centre is within the observe radius of it (not if it was at the reset)."""
    params = paper3.replace(observe_radius=0.15)
    step_jit = jax.jit(step_env)
    for seed in range(4):
        _, state = reset(jax.random.PRNGKey(seed), params)
        pois = np.asarray(state.poi_pos)
        seen = np.asarray(state.observed).copy()
        counts, expected = [], []
        for _ in range(params.max_steps):  # rover i heads for POI i, overshooting now and then
            actions = jnp.clip(3.0 * (state.poi_pos - state.rover_pos), -1.0, 1.0)
            _, state, _, _, _, info = step_jit(state, actions, params)
            near = np.linalg.norm(np.asarray(state.rover_pos)[:, None] - pois[None], axis=-1) < params.observe_radius
            now = near.any(axis=0)
            expected.append(int(np.sum(now & ~seen)))
            seen |= now
            counts.append(int(info["pois_first_observed"]))
        assert counts == expected
        assert sum(counts) >= 1 and int(info["pois_observed"]) == int(seen.sum())


def test_unobserved_distance_counts_open_pois_from_working_rovers_only(paper3):
    """info["unobserved_distance"] against NumPy: the sum over POIs not yet observed of the
    nearest working rover's distance; rover 0 fails after its first step and never counts."""
    params = paper3.replace(observe_radius=0.15)
    step_jit = jax.jit(step_env)
    _, state = reset(jax.random.PRNGKey(5), params)
    state = state.replace(fail_step=state.fail_step.at[0].set(1))
    pois, seen = np.asarray(state.poi_pos), np.asarray(state.observed).copy()
    values, expected, with_rover_0 = [], [], []
    for _ in range(params.max_steps):
        actions = jnp.clip(3.0 * (state.poi_pos - state.rover_pos), -1.0, 1.0)
        _, state, _, _, _, info = step_jit(state, actions, params)
        dist = np.linalg.norm(np.asarray(state.rover_pos)[:, None] - pois[None], axis=-1)  # [N, P]
        seen |= (dist < params.observe_radius).any(axis=0)
        expected.append(float(np.sum(np.where(seen, 0.0, dist[1:].min(axis=0)))))  # rovers 1 and 2
        with_rover_0.append(float(np.sum(np.where(seen, 0.0, dist.min(axis=0)))))
        values.append(float(info["unobserved_distance"]))
    np.testing.assert_allclose(values, expected, rtol=1e-5, atol=1e-6)
    assert not np.allclose(expected, with_rover_0, rtol=1e-3)  # the failed rover would have counted


# ----------------------------------------------------------------------------- episodes


def test_truncation_at_25_steps_under_jit_vmap_and_auto_reset_keeps_final_obs(paper3):
    envs, steps = 4, 60

    def run(key):
        keys = jax.random.split(key, envs)
        obs, states = jax.vmap(reset, in_axes=(0, None))(keys, paper3)

        def body(carry, k):
            obs, states = carry
            ka, ks = jax.random.split(k)
            actions = jax.random.uniform(ka, (envs, paper3.num_rovers, 2), minval=-1, maxval=1)
            expected = jax.vmap(step_env, in_axes=(0, 0, None))(states, actions, paper3)
            out = jax.vmap(step, in_axes=(0, 0, 0, None))(jax.random.split(ks, envs), states, actions, paper3)
            return (out[0], out[1]), (out, expected[0])

        return jax.lax.scan(body, (obs, states), jax.random.split(key, steps))[1]

    (obs, states, rewards, terminated, truncated, info), expected_obs = jax.jit(run)(jax.random.PRNGKey(0))
    truncated, terminated = np.asarray(truncated), np.asarray(terminated)
    ends = np.zeros((steps, envs), bool)
    ends[[24, 49]] = True
    np.testing.assert_array_equal(truncated, ends)
    assert not terminated.any(), "the time limit is a truncation, never a termination"
    np.testing.assert_array_equal(np.asarray(states.time)[:, 0], [(t + 1) % 25 for t in range(steps)])
    # the final observation is the true next observation; the returned one starts a new episode
    np.testing.assert_allclose(info["final_obs"], expected_obs, atol=1e-6)
    assert not np.allclose(obs[24], expected_obs[24])
    np.testing.assert_allclose(
        obs[24], jax.vmap(observe, in_axes=(0, None))(jax.tree.map(lambda x: x[24], states), paper3), atol=1e-6
    )
    np.testing.assert_allclose(obs[23], expected_obs[23], atol=1e-6)


def test_reset_layout_keeps_traps_off_pois_and_rovers_out_of_traps(paper3):
    obs, states = jax.vmap(reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(1), 2000), paper3)
    keep = paper3.trap_radius + paper3.rover_radius
    poi_trap = np.linalg.norm(states.poi_pos[:, :, None] - states.trap_pos[:, None], axis=-1)
    rover_trap = np.linalg.norm(states.rover_pos[:, :, None] - states.trap_pos[:, None], axis=-1)
    assert poi_trap.min() >= keep - 1e-6
    assert rover_trap.min() >= keep - 1e-6
    for positions in (states.rover_pos, states.poi_pos, states.trap_pos):
        assert np.abs(np.asarray(positions)).max() <= paper3.map_size
    assert obs.shape == (2000, 3, observation_size(paper3))
    np.testing.assert_array_equal(states.rover_vel, 0.0)


def test_params_are_a_pytree_that_can_be_vmapped():
    params = get_scenario("paper-2")
    sizes = jnp.array([0.25, 4.0])
    _, states = jax.vmap(lambda s: reset(jax.random.PRNGKey(0), params.replace(map_size=s)))(sizes)
    extent = np.abs(np.asarray(states.poi_pos)).max(axis=(1, 2))
    assert extent[0] <= 0.25 and extent[1] > 1.0


def test_same_key_same_episode_different_key_different_episode(paper3):
    a = reset(jax.random.PRNGKey(3), paper3)[1]
    b = reset(jax.random.PRNGKey(3), paper3)[1]
    c = reset(jax.random.PRNGKey(4), paper3)[1]
    np.testing.assert_array_equal(a.rover_pos, b.rover_pos)
    assert not np.allclose(a.rover_pos, c.rover_pos)


def test_nearest_first_view_matches_a_python_sort_and_ignores_the_numbering():
    params = get_scenario("paper-5").replace(nearest_first=True)
    _, states = jax.vmap(reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(5), 20), params)
    obs = np.asarray(jax.vmap(observe, in_axes=(0, None))(states, params))
    for e in range(20):
        rovers, pois, traps = (
            np.asarray(x[e], np.float64) for x in (states.rover_pos, states.poi_pos, states.trap_pos)
        )
        for i, me in enumerate(rovers):
            expected = [*states.rover_vel[e, i], *me]
            for group in (pois, traps, np.delete(rovers, i, axis=0)):
                expected += [c for point in sorted(group - me, key=lambda d: d @ d) for c in point]
            np.testing.assert_allclose(obs[e, i], expected, atol=1e-6)
    # renumbering the POIs, traps and rovers only renumbers the rows
    one = jax.tree.map(lambda x: x[0], states)
    shuffled = one.replace(
        rover_pos=one.rover_pos[::-1],
        rover_vel=one.rover_vel[::-1],
        poi_pos=one.poi_pos[::-1],
        trap_pos=one.trap_pos[::-1],
    )
    np.testing.assert_allclose(observe(shuffled, params), obs[0][::-1], atol=1e-6)
    assert not np.allclose(observe(one, params.replace(nearest_first=False)), obs[0])


# ----------------------------------------------------------------------------- bad input


def test_unknown_preset_names_the_choices():
    with pytest.raises(UserError, match="unknown scenario 'mars-11'.*paper-2.*spread-3.*paper-N"):
        get_scenario("mars-11")


@pytest.mark.parametrize(
    "field, value, pattern",
    [
        ("rover_radius", 0.0, "rover_radius must be positive"),
        ("observe_radius", -1.0, "observe_radius must be positive"),
        ("trap_radius", -0.1, "trap_radius must be positive"),
        ("num_rovers", 0, "num_rovers must be >= 1"),
        ("num_traps", -1, "num_traps must be >= 0"),
        ("num_pois", 0, "num_pois must be >= 1"),  # nothing to observe: the views had no POI to match
        ("map_size", 0.0, "map_size must be positive"),
        ("trap_radius", 1e39, "trap_radius must be a finite number representable as float32"),
        ("collision_penalty", float("nan"), "collision_penalty must be a finite number"),
        ("max_steps", 10**20, "max_steps must be below 2"),
    ],
)
def test_bad_params_name_the_field(field, value, pattern):
    with pytest.raises(UserError, match=pattern):
        validate_params(EnvParams().replace(**{field: value}))


def test_actions_of_the_wrong_shape_are_refused(paper3):
    _, state = reset(jax.random.PRNGKey(0), paper3)
    with pytest.raises(UserError, match=r"actions must have shape \(3, 2\).*got \(2, 2\)"):
        step(jax.random.PRNGKey(0), state, jnp.zeros((2, 2)), paper3)
