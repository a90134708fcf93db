"""Any swarm size in one program: padded layouts against the unpadded environment, the entity
view against the flat view, rover failures against a plain loop over the rules, sizes and ranges."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.env import get_scenario, observe, reset, step, step_env
from roverswarm.env.entities import POI, ROVER, TOKEN_FEATURES, TRAP, observe_entities, token_count
from roverswarm.env.mars import NEVER, EnvState, observation_size
from roverswarm.env.scenarios import draw_sizes, padded_scenario, scenario_sizes, sized
from roverswarm.env.validation import validate_params
from roverswarm.errors import UserError
from roverswarm.policies import ORACLE, RANDOM
from roverswarm.rollout import MissionStats, rollout

MAX = 10
STEPS = 25


def pad(state: EnvState, n_max: int, key: jax.Array) -> EnvState:
    """``state`` of an unpadded layout placed in the first slots of a layout of ``n_max`` rovers,
    POIs and traps; the empty slots hold random positions and velocities (which must not matter)."""

    def grow(x, fill):
        return jnp.concatenate([x, fill[: n_max - x.shape[0]]])

    noise = jax.random.uniform(key, (4, n_max, 2), minval=-1, maxval=1)
    exists = lambda count: jnp.arange(n_max) < count  # noqa: E731
    return EnvState(
        rover_pos=grow(state.rover_pos, noise[0]),
        rover_vel=grow(state.rover_vel, noise[1]),
        poi_pos=grow(state.poi_pos, noise[2]),
        trap_pos=grow(state.trap_pos, noise[3]),
        observed=grow(state.observed, jnp.ones(n_max, bool)),
        time=state.time,
        fail_step=grow(state.fail_step, jnp.full(n_max, NEVER, jnp.int32)),
        rover_mask=exists(state.rover_pos.shape[0]),
        poi_mask=exists(state.poi_pos.shape[0]),
        trap_mask=exists(state.trap_pos.shape[0]),
    )


def active_part(obs, n: int, n_max: int):
    """The flat observations' columns of the first n POIs, traps and other rovers of a layout of n_max."""
    cols = np.concatenate(
        [np.arange(4 + 2 * n), 4 + 2 * n_max + np.arange(2 * n), 4 + 4 * n_max + np.arange(2 * n - 2)]
    )
    return np.asarray(obs)[..., cols]


def episode(state, actions, params):
    """Scan ``step_env`` over ``actions`` [T, N, 2]: (obs, rewards, collisions, traps, coverage, observed) per step."""

    def body(state, a):
        obs, state, rewards, _, _, info = step_env(state, a, params)
        return state, (
            obs,
            rewards,
            info["collisions"],
            info["trap_contacts"],
            info["coverage_distance"],
            state.observed,
        )

    return jax.lax.scan(body, state, actions)[1]


@jax.jit
def _start(key, params):
    """Layout of ``params`` from ``key``, random actions, and both placed in :data:`MAX` slots,
    where rovers that do not exist get wild actions (they must still stand still and change
    nothing). Jitted: one program per size instead of hundreds of operations run one by one."""
    n = params.num_rovers
    _, state = reset(key, params)
    actions = jax.random.uniform(jax.random.fold_in(key, 1), (STEPS, n, 2), minval=-1, maxval=1)
    big_actions = jnp.concatenate([actions, 5 * jnp.ones((STEPS, MAX - n, 2))], axis=1)
    return state, actions, pad(state, MAX, jax.random.fold_in(key, 2)), big_actions


@pytest.mark.parametrize("nearest_first", [False, True])
def test_padded_layout_steps_as_the_unpadded_environment_for_every_n(nearest_first):
    """For N = 2..10, the padded environment (maximum 10) with N active rovers, POIs and traps,
    started from the unpadded environment's layout, gives the same observations (active part),
    rewards, contacts, coverage and observed POIs at every step of an episode."""
    padded = padded_scenario(f"paper-2..{MAX}").replace(nearest_first=nearest_first)
    run_padded = jax.jit(lambda state, actions, n: episode(state, actions, sized(padded, n)))
    for n in range(2, MAX + 1):
        params = get_scenario(f"paper-{n}").replace(nearest_first=nearest_first)
        key = jax.random.PRNGKey(n)
        state, actions, padded_state, big_actions = _start(key, params)
        ref = jax.jit(episode, static_argnums=2)(state, actions, params)
        got = run_padded(padded_state, big_actions, n)
        obs = np.asarray(got[0])
        np.testing.assert_allclose(active_part(obs[:, :n], n, MAX), ref[0], atol=1e-6, err_msg=f"observations, N = {n}")
        assert observation_size(params) == active_part(obs, n, MAX).shape[-1]
        assert not obs[:, n:].any() and np.abs(obs).sum() == pytest.approx(np.abs(active_part(obs, n, MAX)).sum())
        for name, a, b in zip(("rewards", "collisions", "trap contacts"), got[1:4], ref[1:4]):
            np.testing.assert_allclose(np.asarray(a)[:, :n], b, atol=1e-5, err_msg=f"{name}, N = {n}")
            assert not np.asarray(a)[:, n:].any(), f"{name} of rovers that do not exist"
        np.testing.assert_allclose(got[4], ref[4], atol=1e-5, err_msg=f"coverage, N = {n}")
        np.testing.assert_array_equal(np.asarray(got[5])[:, :n], ref[5])
        assert not np.asarray(got[5])[:, n:].any(), "a POI that does not exist is never observed"
        # episode totals
        np.testing.assert_allclose(np.asarray(got[1]).sum(), np.asarray(ref[1]).sum(), rtol=1e-5)


def test_one_program_steps_a_batch_of_mixed_sizes():
    """reset + step vmapped over N = 2..10 in one jitted program: the empty slots never move or
    score, the layout of each N keeps its clearances, and the auto-reset keeps the sizes."""
    padded = padded_scenario("paper-2..10")
    sizes = jnp.asarray(scenario_sizes("paper-2..10"))

    @jax.jit
    def run(key):
        def one(key, n):
            params = sized(padded, n)
            _, state = reset(key, params)
            start = state

            def body(state, k):
                a = jax.random.uniform(k, (MAX, 2), minval=-1, maxval=1)
                _, state, rewards, _, _, info = step(k, state, a, params)
                return state, (rewards, state.rover_pos)

            last, (rewards, pos) = jax.lax.scan(body, state, jax.random.split(key, 2 * STEPS))
            return start, last, rewards, pos

        return jax.vmap(one)(jax.random.split(key, sizes.shape[0]), sizes)

    start, last, rewards, pos = run(jax.random.PRNGKey(0))
    for row, n in enumerate(np.asarray(sizes)):
        exists = np.arange(MAX) < n
        np.testing.assert_array_equal(start.rover_mask[row], exists)
        np.testing.assert_array_equal(last.poi_mask[row], exists)  # kept by the auto-reset
        assert not np.asarray(rewards)[row][:, ~exists].any()
        assert np.asarray(rewards)[row][:, exists].all()
        assert np.all(np.asarray(pos)[row][: STEPS - 1, ~exists] == np.asarray(start.rover_pos)[row][~exists])
        traps, rovers, pois = (np.asarray(x)[row][:n] for x in (start.trap_pos, start.rover_pos, start.poi_pos))
        assert np.linalg.norm(traps[:, None] - pois[None], axis=-1).min() >= 0.25 - 1e-6 or n == 0
        assert np.abs(rovers).max() <= 1.0


def _tokens_of(view, rover, kind):
    sel = np.asarray(view.mask[rover]) & (np.asarray(view.tokens[rover, :, 4 + kind]) == 1)
    return np.asarray(view.tokens[rover])[sel]


@pytest.mark.parametrize("padded", [False, True])
def test_entity_view_rebuilds_the_flat_views(padded):
    """The flat view (index order and nearest first) is rebuilt from the entity view alone."""
    n = 4
    base = get_scenario("paper-6").replace(active_rovers=n, active_pois=n, active_traps=n) if padded else None
    params = base if padded else get_scenario(f"paper-{n}")
    _, state = reset(jax.random.PRNGKey(3), params)
    _, state, *_ = step_env(state, jax.random.uniform(jax.random.PRNGKey(4), (params.num_rovers, 2)), params)
    view = observe_entities(state, params)
    assert view.tokens.shape == (params.num_rovers, token_count(params), TOKEN_FEATURES)
    for nearest_first in (False, True):
        flat = active_part(observe(state, params.replace(nearest_first=nearest_first)), n, params.num_rovers)
        for i in range(n):
            groups = []
            for kind in (POI, TRAP, ROVER):
                rel = _tokens_of(view, i, kind)[:, :2]
                if nearest_first:
                    rel = rel[np.argsort(np.sum(rel**2, axis=-1), kind="stable")]
                groups.append(rel.reshape(-1))
            np.testing.assert_allclose(flat[i], np.concatenate([np.asarray(view.own[i]), *groups]), atol=1e-6)
    if padded:
        assert not np.asarray(view.mask[n:]).any() and not np.asarray(view.tokens)[~np.asarray(view.mask)].any()


def test_entity_view_is_the_same_set_under_any_permutation_of_the_layout():
    """Permuting POIs, traps and rovers permutes the rovers' rows and reorders each row's
    tokens, and nothing else."""
    params = get_scenario("paper-5")
    _, state = reset(jax.random.PRNGKey(7), params)
    _, state, *_ = step_env(state, jax.random.uniform(jax.random.PRNGKey(8), (5, 2), minval=-1), params)
    state = state.replace(fail_step=state.fail_step.at[1].set(0), observed=state.observed.at[2].set(True))
    rng = np.random.default_rng(0)
    perm_r, perm_p, perm_t = (rng.permutation(5) for _ in range(3))
    shuffled = state.replace(
        rover_pos=state.rover_pos[perm_r],
        rover_vel=state.rover_vel[perm_r],
        fail_step=state.fail_step[perm_r],
        poi_pos=state.poi_pos[perm_p],
        observed=state.observed[perm_p],
        trap_pos=state.trap_pos[perm_t],
    )
    a, b = observe_entities(state, params), observe_entities(shuffled, params)
    as_set = lambda tokens: tokens[np.lexsort(np.asarray(tokens).T[::-1])]  # noqa: E731
    for new, old in enumerate(perm_r):
        np.testing.assert_allclose(b.own[new], a.own[old])
        np.testing.assert_allclose(as_set(np.asarray(b.tokens[new])), as_set(np.asarray(a.tokens[old])), atol=1e-6)
    assert float(a.tokens[..., 8].sum()) == pytest.approx(4 + 5), "failed rover seen by 4 others, observed POI by 5"


def test_a_failed_rover_never_moves_again_and_totals_match_a_plain_loop():
    """fail_rate 1: one rover fails at a drawn step and stays put; the episode's reward,
    collisions and trap contacts equal a NumPy loop over the rules on the recorded positions."""
    params = get_scenario("paper-4").replace(fail_rate=1.0)
    _, state = reset(jax.random.PRNGKey(11), params)
    failed = np.flatnonzero(np.asarray(state.fail_step) != NEVER)
    assert len(failed) == 1
    when = int(state.fail_step[failed[0]])

    # drive every rover hard towards the centre, so that contacts happen
    def body(state, k):
        a = jnp.clip(-3 * state.rover_pos + 0.3 * jax.random.normal(k, (4, 2)), -1, 1)
        _, state, rewards, _, _, info = step_env(state, a, params)
        return state, (state.rover_pos, rewards, info["collisions"], info["trap_contacts"])

    _, (pos, rewards, collisions, traps) = jax.lax.scan(body, state, jax.random.split(jax.random.PRNGKey(12), STEPS))
    pos = np.asarray(pos)
    frozen_at = np.asarray(state.rover_pos)[failed[0]] if when == 0 else pos[when - 1, failed[0]]
    np.testing.assert_array_equal(pos[when:, failed[0]], np.broadcast_to(frozen_at, pos[when:, failed[0]].shape))
    poi, trap = np.asarray(state.poi_pos), np.asarray(state.trap_pos)
    total_reward = total_collisions = total_traps = 0.0
    for t in range(STEPS):
        for i in range(4):
            touching = sum(np.linalg.norm(pos[t, i] - pos[t, j]) < 0.3 for j in range(4) if j != i)
            in_trap = sum(np.linalg.norm(pos[t, i] - c) < 0.25 for c in trap)
            coverage = sum(min(np.linalg.norm(pos[t, m] - q) for m in range(4)) for q in poi)
            total_reward += -coverage - touching - in_trap
            total_collisions += touching
            total_traps += in_trap
    assert float(np.asarray(rewards).sum()) == pytest.approx(total_reward, rel=1e-4)
    assert int(np.asarray(collisions).sum()) == total_collisions > 0
    assert int(np.asarray(traps).sum()) == total_traps


def test_fail_rate_draws_failures_at_that_rate_without_changing_the_layout():
    params = get_scenario("paper-3")
    keys = jax.random.split(jax.random.PRNGKey(0), 2000)
    resets = jax.vmap(reset, in_axes=(0, None))
    _, plain = resets(keys, params)
    _, some = resets(keys, params.replace(fail_rate=0.3))
    np.testing.assert_array_equal(plain.rover_pos, some.rover_pos)
    failing = np.asarray(some.fail_step != NEVER)
    assert failing.sum(axis=1).max() == 1
    assert abs(failing.any(axis=1).mean() - 0.3) < 0.04
    assert np.asarray(some.fail_step)[failing].max() < STEPS


def test_fail_count_fails_up_to_k_distinct_rovers_and_keeps_one_working():
    """fail_count 3 on padded paper-2..6 layouts: k failing rovers, k uniform in [1, min(3,
    active - 1)], only rovers that exist, each slot equally often, steps uniform in [0, 25);
    the first failure is the one fail_count 1 draws (the same key), the layout unchanged."""
    keys = jax.random.split(jax.random.PRNGKey(1), 6000)
    active = np.asarray(jax.random.randint(jax.random.PRNGKey(2), (6000,), 2, 7))
    padded = padded_scenario("paper-2..6").replace(fail_rate=1.0)
    draw = jax.vmap(lambda k, n, p: reset(k, sized(p, n))[1], in_axes=(0, 0, None))
    one, three = draw(keys, active, padded), draw(keys, active, padded.replace(fail_count=3))
    np.testing.assert_array_equal(one.rover_pos, three.rover_pos)
    first = np.asarray(one.fail_step) != NEVER
    failing = np.asarray(three.fail_step) != NEVER
    np.testing.assert_array_equal(np.asarray(three.fail_step)[first], np.asarray(one.fail_step)[first])
    assert not (failing & ~np.asarray(three.rover_mask)).any()
    count = failing.sum(axis=1)
    for n in range(2, 7):
        top = min(3, n - 1)
        shares = np.bincount(count[active == n], minlength=top + 1)[1:] / np.sum(active == n)
        np.testing.assert_allclose(shares, np.full(top, 1 / top), atol=0.06)
        slots = failing[active == n][:, :n].mean(axis=0)  # each rover's share: E[k] / n
        np.testing.assert_allclose(slots, np.full(n, (top + 1) / 2 / n), atol=0.06)
    steps = np.asarray(three.fail_step)[failing]
    assert steps.min() == 0 and steps.max() == STEPS - 1
    assert abs(steps.mean() - (STEPS - 1) / 2) < 0.5


def test_oracle_and_random_on_a_padded_layout_match_the_unpadded_layout_in_distribution():
    """Evaluation on a padded layout with N active: the oracle observes every POI as often and
    scores near the unpadded environment's (different layouts, same distribution)."""
    n, episodes = 3, 300
    key = jax.random.PRNGKey(5)
    padded = sized(padded_scenario("paper-2..6"), n)
    plain = get_scenario(f"paper-{n}")
    for policy in (ORACLE, RANDOM):
        a = rollout(policy, key, padded, episodes)
        b = rollout(policy, key, plain, episodes)
        assert abs(a.stats.reward.mean() - b.stats.reward.mean()) < 0.1 * abs(b.stats.reward.mean())
        assert a.stats.pois_observed.max() <= n
        assert not a.rover_exists[:, n:].any() and not np.abs(np.diff(a.rover_pos[:, :, n:], axis=1)).any()
    success = MissionStats.of(rollout(ORACLE, key, padded, episodes)).success.mean()
    assert success > 0.8


def test_sizes_beyond_ten_grow_the_map_to_keep_the_density():
    for n in (16, 32):
        params = get_scenario(f"paper-{n}")
        assert params.num_rovers == n
        assert params.map_size == pytest.approx(np.sqrt(n / 10))
        density = 3 * n / (2 * params.map_size) ** 2
        assert density == pytest.approx(3 * 10 / 4)
    assert get_scenario("paper-10").map_size == 1.0
    assert scenario_sizes("paper-2,8,4") == (2, 4, 8)
    sizes = np.asarray(draw_sizes(jax.random.PRNGKey(0), (2, 4, 8), 3000))
    assert set(np.unique(sizes)) == {2, 4, 8}


@pytest.mark.parametrize("cap, expected", [(None, {2: 4 / 7, 4: 2 / 7, 8: 1 / 7}), (4, {2: 2 / 3, 4: 1 / 3})])
def test_a_size_draw_power_draws_small_swarms_more_often(cap, expected):
    """power 1: a size N with probability proportional to 1 / N, among the sizes up to the cap."""
    sizes = np.asarray(draw_sizes(jax.random.PRNGKey(0), (2, 4, 8), 20_000, cap, power=1.0))
    shares = {int(n): float(np.mean(sizes == n)) for n in np.unique(sizes)}
    assert shares.keys() == expected.keys()
    for n, share in expected.items():
        assert shares[n] == pytest.approx(share, abs=0.015)


@pytest.mark.parametrize(
    "name, pattern",
    [
        ("paper-2..100", "every N must be in 2..64"),
        ("paper-1..4", "every N must be in 2..64"),
        ("paper-5..3", "needs A < B"),
        ("paper-2..99999999999999999999", r"2\.\.64, got 2\.\.99999999999999999999$"),  # refused before building it
        ("paper-1", r"2\.\.64, got 1$"),
        ("paper-2,2", "names each size once"),
        ("paper-x", "unknown scenario"),
        ("spread-3..5", "unknown scenario"),
        pytest.param("paper-" + "9" * 5000, "every N must be in 2..64", id="5000 digits"),  # int() would raise
        ("paper-0,3", r"2\.\.64, got 0, 3$"),  # a list, not a range
        ("paper-02", "unknown scenario"),  # one spelling per scenario
        ("paper-\u0663", "unknown scenario"),  # an Arabic-Indic 3: a digit to \\d, not to us
    ],
)
def test_bad_ranges_name_the_rule(name, pattern):
    with pytest.raises(UserError, match=pattern):
        scenario_sizes(name)


def test_bad_failure_rates_and_counts_are_refused():
    params = get_scenario("paper-4")
    with pytest.raises(UserError, match=r"fail_rate must be in \[0, 1\]"):
        validate_params(params.replace(fail_rate=1.5))
    with pytest.raises(UserError, match="fail_count must be an integer >= 1"):
        validate_params(params.replace(fail_rate=1.0, fail_count=0))
    with pytest.raises(UserError, match=r"active_rovers must be in \[1, 4\]"):
        validate_params(params.replace(active_rovers=5))
    with pytest.raises(UserError, match="fail_rate above 0 needs at least 2 rovers in every episode.*got 1$"):
        validate_params(params.replace(active_rovers=jnp.array([3, 1]), fail_rate=0.5))  # would lose the only rover
    validate_params(params.replace(active_rovers=jnp.array([3, 1])))  # without failures, one rover is a swarm
    with pytest.raises(UserError, match="range of swarm sizes"):
        get_scenario("paper-2..4")


def test_cli_refuses_a_bad_range_in_one_line(capsys):
    from roverswarm.cli import main

    assert main(["render", "--scenario", "paper-2..99", "--out", "x.gif"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "every N must be in 2..64" in err[0]


def test_pettingzoo_serves_any_paper_size():
    from roverswarm.env.pettingzoo import RoverSwarmEnv

    env = RoverSwarmEnv("paper-16")
    obs, _ = env.reset(seed=0)
    assert len(obs) == 16 and obs["rover_0"].shape == (4 + 6 * 16 - 2,)
    obs, rewards, *_ = env.step({a: env.action_space(a).sample() for a in env.agents})
    assert len(rewards) == 16 and np.abs(obs["rover_15"][2:4]).max() <= np.sqrt(1.6) + 0.5
    # a padded layout (a batch's program for several sizes) is no single swarm: its empty slots
    # were agents observed as zeros and rovers drawn inside traps
    with pytest.raises(UserError, match="serves one swarm size"):
        RoverSwarmEnv(params=sized(padded_scenario("paper-2..5"), 2))
