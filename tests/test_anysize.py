"""One policy for every swarm size: the on-policy family with entity networks, trained on a
range of sizes, evaluated on sizes it never saw; the checks that keep other policies to theirs."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm import train
from roverswarm.algos import ppo
from roverswarm.algos.ppo_networks import swarm_tokens
from roverswarm.config import validate, with_options
from roverswarm.env import get_scenario, reset
from roverswarm.env.entities import (
    CLAIM,
    LEAD,
    TOKEN_FEATURES,
    flat_tokens,
    greedy_match,
    nearest_entities,
    observe_entities,
    observe_nearest,
    uncross,
)
from roverswarm.env.mars import NEVER, pairwise_dist, step_env
from roverswarm.episodes import reset_all, size_cap, training_params
from roverswarm.errors import UserError
from roverswarm.evaluate import evaluate_run
from roverswarm.learners.onpolicy import collect, configure, make_batch
from roverswarm.metrics import chunk_means
from roverswarm.presets import ANYSIZE
from roverswarm.runs import Run


@pytest.fixture(scope="module")
def anysize_run(tiny_anysize, tmp_path_factory):
    out = tmp_path_factory.mktemp("anysize")
    train(tiny_anysize, out=out, progress=False)
    return out


def test_mixed_sizes_mask_the_rovers_that_do_not_exist(tiny_anysize):
    """Each training environment draws its own size; samples of empty rover slots are masked,
    earn nothing, and the padded view shows no entity past the drawn counts."""
    many = dataclasses.replace(tiny_anysize, num_envs=20)  # enough environments to draw every size
    config, params = configure(many, validate(many)), validate(many)
    state = ppo.init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, 0)
    traj, episode = jax.jit(lambda k: collect(config, params, state.actor, k))(jax.random.PRNGKey(3))
    sizes = np.asarray(traj.rovers[0].sum(-1)).astype(int)  # [E]
    assert set(sizes) <= {2, 3, 4} and len(set(sizes)) > 1
    exists = np.asarray(traj.rovers) > 0
    assert not np.asarray(traj.rewards)[~exists].any()
    assert np.asarray(traj.rewards)[exists].all()
    tokens = np.asarray(traj.obs.mask).sum(-1)  # [T, E, N] real tokens per rover: 3 (n - 1) for a rover of n
    np.testing.assert_array_equal(tokens, np.where(exists, 3 * sizes[None, :, None] - 1, 0))
    # --balance-sizes: each rover's weight is (largest size) / (its swarm's size), so that every
    # live step of every episode weighs the same in the loss, whatever its size
    live = np.asarray(traj.mask)[..., None] * exists  # [T, E, N]
    batch = jax.jit(make_batch, static_argnums=0)
    made = {
        balance: batch(
            dataclasses.replace(config, ppo=dataclasses.replace(config.ppo, balance_sizes=balance)), state, traj
        )
        for balance in (False, True)
    }
    for balance, weight in ((False, 1.0), (True, params.num_rovers / sizes[None, :, None])):
        got = np.asarray(made[balance][0].mask).reshape(exists.shape)
        np.testing.assert_allclose(got, live * weight, rtol=1e-6)
    for statistic in ("mean", "var"):  # the value targets' running statistics count each sample once
        np.testing.assert_allclose(getattr(made[True][1], statistic), getattr(made[False][1], statistic))
    np.testing.assert_allclose(got.sum(-1), params.num_rovers * np.asarray(traj.mask), rtol=1e-6)
    # a chunk's agent_i_reward: rover i's mean over the episodes in which it exists, not diluted
    # by the zeros of the episodes without it (a NumPy loop over the episodes)
    np.testing.assert_array_equal(np.asarray(episode["rovers"]), exists[0])
    rewards = np.asarray(episode["agent_rewards"])
    want = [np.mean([rewards[e, i] for e in range(len(sizes)) if exists[0, e, i]]) for i in range(params.num_rovers)]
    np.testing.assert_allclose(chunk_means(episode, (0,))["agent_rewards"], want, rtol=1e-5)


def test_the_logged_reward_of_a_rover_slot_counts_the_episodes_it_exists_in(anysize_run):
    """paper-2..4: rover 3 exists in the 4-rover episodes only, where every rover's (negative)
    reward is larger (more POIs to cover): its logged reward is not a third of rover 0's, as the
    zeros of the other episodes made it."""
    for row in Run(anysize_run).metrics():
        assert row["agent_3_reward"] / row["agent_0_reward"] > 0.8, row


def test_stop_when_complete_ends_an_episode_once_every_poi_is_observed(tiny_anysize):
    """--stop-when-complete: with the same keys, an episode's steps are those of a run without
    it until the first step at which every POI is observed (read from the POI tokens' flags of
    that run); that step terminates the episode and nothing after it counts. Without the option
    no episode terminates. A wide observation radius lets the untrained policy finish some."""
    many = dataclasses.replace(tiny_anysize, num_envs=20)
    params = validate(many).replace(observe_radius=0.6)
    state = ppo.init_ppo(jax.random.PRNGKey(0), configure(many, params), params.num_rovers, 0)
    runs = {}
    for stop in (False, True):
        config = configure(dataclasses.replace(many, stop_when_complete=stop), params)
        runs[stop] = jax.jit(lambda k, c=config: collect(c, params, state.actor, k))(jax.random.PRNGKey(3))[0]
    plain, stopped = runs[False], runs[True]
    assert not np.asarray(plain.terminated).any()
    tokens, exists = np.asarray(plain.next_obs.tokens)[:, :, 0], np.asarray(plain.next_obs.mask)[:, :, 0]  # rover 0
    pois = exists & (tokens[..., 5] == 1)  # [T, E, M]
    complete = np.all(~pois | (tokens[..., 8] == 1), axis=-1)  # [T, E]: every POI observed after step t
    terminated, ended = np.asarray(stopped.terminated), complete.any(axis=0)
    assert 0 < ended.sum() < many.num_envs
    np.testing.assert_array_equal(terminated.any(axis=0), ended)
    for e in range(many.num_envs):
        last = int(complete[:, e].argmax()) if ended[e] else complete.shape[0] - 1
        assert not ended[e] or terminated[last, e] and terminated[:, e].sum() == 1
        np.testing.assert_array_equal(np.asarray(stopped.mask)[:, e], np.arange(len(complete)) <= last)
        rewards = np.asarray(stopped.rewards)[:, e]
        np.testing.assert_array_equal(rewards[: last + 1], np.asarray(plain.rewards)[: last + 1, e])
        assert not rewards[last + 1 :].any()


def test_the_sizes_are_drawn_from_bits_no_layout_uses(tiny_anysize, monkeypatch):
    """The key of the swarm sizes is none of the environments' layout keys nor of the keys a
    layout draws its POIs, traps and rovers from (it was environment 1's: its layout and the
    sizes came from the same bits)."""
    import roverswarm.episodes as episodes_module

    config = configure(tiny_anysize, validate(tiny_anysize))
    drawn = []
    real = episodes_module.draw_sizes
    monkeypatch.setattr(episodes_module, "draw_sizes", lambda key, *args: drawn.append(key) or real(key, *args))
    key = jax.random.PRNGKey(3)
    reset_all(config, training_params(config, validate(tiny_anysize)), key, jnp.asarray(0))
    layouts = jax.random.split(key, config.num_envs)
    used = np.concatenate([np.asarray(layouts), *(np.asarray(jax.random.split(k, 3)) for k in layouts)])
    (size_key,) = drawn
    assert not (used == np.asarray(size_key)).all(axis=-1).any()


def test_fail_max_rovers_fails_and_shapes_only_the_small_swarms(tiny_anysize):
    """--fail-max-rovers 3 over paper-2..4 with --fail-rate 1: every episode of 2 or 3 rovers
    has one failing rover and none of 4 has; the unobserved shaping changes the rewards of the
    small swarms only (the same keys give the same steps, since the shaping moves nothing)."""
    many = dataclasses.replace(tiny_anysize, num_envs=20, fail_rate=1.0, fail_max_rovers=3)
    params = validate(many)
    config = configure(many, params)
    state = reset_all(config, training_params(config, params), jax.random.PRNGKey(3), jnp.asarray(0))
    sizes = np.asarray(state.rover_mask).sum(-1)
    assert {3, 4} <= set(sizes)
    failing = (np.asarray(state.fail_step) < NEVER).sum(-1)
    np.testing.assert_array_equal(failing, (sizes <= 3).astype(int))
    actor = ppo.init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, 0).actor
    rewards = {}
    for weight in (0.0, 1.0):
        shaped = configure(with_options(many, {"unobserved_shaping": weight}), params)
        traj = jax.jit(lambda k, c=shaped: collect(c, params, actor, k)[0])(jax.random.PRNGKey(3))
        rewards[weight], sizes = np.asarray(traj.rewards), np.asarray(traj.rovers[0]).sum(-1)
    charged = rewards[1.0] - rewards[0.0]  # [T, E, N]
    np.testing.assert_array_equal(charged[:, sizes == 4], 0.0)
    assert (charged[:, sizes <= 3] <= 1e-6).all() and (charged[:, sizes <= 3] < -1e-3).any()


def test_fail_count_reaches_the_training_episodes(tiny_anysize):
    """--fail-count 2 over paper-2..4 with --fail-rate 1: a swarm of 2 loses one rover, a swarm
    of 3 or 4 one or two, as the training environments draw them."""
    many = dataclasses.replace(tiny_anysize, num_envs=100, fail_rate=1.0, fail_count=2)
    params = validate(many)
    config = configure(many, params)
    state = reset_all(config, training_params(config, params), jax.random.PRNGKey(3), jnp.asarray(10**6))
    sizes = np.asarray(state.rover_mask).sum(-1)
    failing = (np.asarray(state.fail_step) < NEVER).sum(-1)
    assert (failing[sizes == 2] == 1).all()
    assert set(failing[sizes >= 3]) == {1, 2}


def test_size_curriculum_widens_the_range():
    config = configure(
        dataclasses.replace(ANYSIZE, size_curriculum=1000), validate(dataclasses.replace(ANYSIZE, size_curriculum=1000))
    )
    assert float(size_cap(config, jnp.asarray(0))) == 2
    assert float(size_cap(config, jnp.asarray(500))) == 6
    assert float(size_cap(config, jnp.asarray(5000))) == 10


def test_the_entity_policy_is_permutation_equivariant(anysize_run):
    """Renumbering the rovers renumbers their actions; reordering POIs and traps changes nothing."""
    policy = Run(anysize_run).policy(1)
    params = get_scenario("paper-6")
    _, state = jax.jit(reset)(jax.random.PRNGKey(4), params)
    state = state.replace(rover_vel=jax.random.normal(jax.random.PRNGKey(5), (6, 2)))
    acting = jax.jit(lambda s, weights: policy.act(None, None, s, None, weights, params))
    act = lambda s: np.asarray(acting(s, policy.weights))  # noqa: E731
    rovers, pois, traps = (np.random.default_rng(i).permutation(6) for i in range(3))
    shuffled = state.replace(
        rover_pos=state.rover_pos[rovers],
        rover_vel=state.rover_vel[rovers],
        poi_pos=state.poi_pos[pois],
        observed=state.observed[pois],
        trap_pos=state.trap_pos[traps],
    )
    np.testing.assert_allclose(act(shuffled), act(state)[rovers], atol=1e-5)
    assert np.abs(act(state)).sum() > 0


def test_a_size_agnostic_run_evaluates_on_sizes_it_never_saw(anysize_run, capsys, monkeypatch):
    rows = evaluate_run(anysize_run, episodes=20, scenario="paper-5,6")
    assert [(r["scenario"], r["policy"]) for r in rows] == [
        (f"paper-{n}", p) for n in (5, 6) for p in ("random", "oracle", "mappo seed 0", "mappo seed 1")
    ]
    assert all(np.isfinite(r["normalized_score"]) for r in rows)
    own = evaluate_run(anysize_run, episodes=20)  # the run's own range: every size of it
    assert sorted({r["scenario"] for r in own}) == ["paper-2", "paper-3", "paper-4"]
    from roverswarm.cli import main

    monkeypatch.setenv("COLUMNS", "250")  # the whole table on one line per row
    assert main(["evaluate", str(anysize_run), "--episodes", "20", "--scenario", "paper-6"]) == 0
    assert "paper-6" in capsys.readouterr().out


def test_other_seeds_partners_fill_a_swarm_of_any_size(anysize_run):
    """--partners other-seeds at a size the run never trained on: rover i of seed s's swarm is
    seed (s + i) mod S's, for every one of the swarm's rovers (it once took the run's own size)."""
    rows = evaluate_run(anysize_run, episodes=20, scenario="paper-3,5", partners="other-seeds")
    mixed = [(r["scenario"], r["policy"]) for r in rows if r["policy"] not in ("random", "oracle")]
    assert mixed == [
        ("paper-3", "mappo agents of seeds 0/1/0"),
        ("paper-3", "mappo agents of seeds 1/0/1"),
        ("paper-5", "mappo agents of seeds 0/1/0/1/0"),
        ("paper-5", "mappo agents of seeds 1/0/1/0/1"),
    ]
    assert all(np.isfinite(r["normalized_score"]) for r in rows)


def test_a_flat_policy_refuses_another_size(tiny_ppo_config, tmp_path, capsys):
    from roverswarm.cli import main

    train(tiny_ppo_config, out=tmp_path, progress=False)
    assert main(["evaluate", str(tmp_path), "--episodes", "5", "--scenario", "paper-5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "was trained for 2 rovers" in err[0]


def test_a_size_the_run_cannot_drive_is_blamed_on_the_option_that_asked_for_it(tiny_config, tmp_path, capsys):
    """`evaluate --scenario` names --scenario and what is allowed (it said --policy, which evaluate
    has not); render and the mission commands, whose policy comes from --policy, keep naming it."""
    from roverswarm.cli import main
    from roverswarm.config import config_to_json

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(config_to_json(tiny_config))  # paper-2, the flat view
    (run / "checkpoint.npz").write_bytes(b"")  # never read: the check comes first
    trained = f"'{run}' was trained for 2 rovers, 2 POIs, 2 traps (paper-2); "
    mission, out = str(Path(__file__).parent.parent / "examples" / "mission.yaml"), str(tmp_path / "out.gif")
    for argv, message in (
        (
            ["evaluate", str(run), "--scenario", "paper-3"],
            f"--scenario: {trained}scenario 'paper-3' has 3 rovers, 3 POIs, 3 traps. Its policies drive those numbers "
            "only: omit --scenario (its own paper-2) or give a scenario of the same numbers; for any size, train with "
            "--network nearest (or entity with --algo mappo or ippo).",
        ),
        (
            ["render", "--policy", str(run), "--scenario", "paper-3", "--out", out],
            f"--policy: {trained}scenario 'paper-3' has 3",
        ),
        (["mission", "run", mission, "--policy", str(run), "--out", out], f"--policy: {trained}mission 'jezero-delta'"),
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"roverswarm: error: {message}") and err.count("\n") == 1, err


@pytest.mark.parametrize(
    "options, pattern",
    [
        ({"scenario": "paper-2..4", "network": "mlp"}, "needs --network nearest, or entity with"),
        ({"entity_nearest": 0}, "--network nearest needs --entity-nearest K >= 1"),
        ({"poi_order": "free", "network": "entity", "entity_nearest": 0}, "--poi-order free orders the POIs"),
        ({"poi_order": "closest"}, "--poi-order must be one of nearest, free, matched, got 'closest'"),
        (
            {
                "poi_order": "matched",
                "network": "mlp",
                "scenario": "paper-3",
                "size_curriculum": 0,
                "balance_sizes": False,
            },
            "--poi-order matched orders the POIs",
        ),
        ({"fail_rate": 1.5}, r"--fail-rate must be in \[0, 1\]"),
        ({"size_curriculum": 100, "scenario": "paper-3"}, "--size-curriculum needs a range"),
        ({"balance_sizes": True, "size_curriculum": 0, "scenario": "paper-3"}, "--balance-sizes needs a range"),
        ({"entity_heads": 3, "entity_dim": 8}, "must be >= 1 and divide --entity-dim"),
        ({"swarm_value": True, "algo": "ippo"}, "--swarm-value is MAPPO's centralised value over --network nearest"),
        ({"fail_count": 2}, "--fail-count 2 says how many rovers a failure episode loses; give --fail-rate"),
        ({"fail_count": 0, "fail_rate": 1.0}, r"--fail-count must be in \[1, 9\] .*, got 0"),
        (
            {"fail_count": 10, "fail_rate": 1.0},
            r"--fail-count must be in \[1, 9\] .*of the largest swarm's 10.*, got 10",
        ),
        ({"fail_max_rovers": 3}, "--fail-max-rovers 3 limits --fail-rate to small swarms"),
        ({"fail_max_rovers": -1, "fail_rate": 1.0}, "--fail-max-rovers must be >= 0"),
        ({"fail_max_rovers": 10, "fail_rate": 1.0}, r"--fail-max-rovers 10 must be in \[2, 9\]"),
        ({"size_draw_power": -1.0}, "size-draw-power"),
        (
            {"size_draw_power": 1.0, "scenario": "paper-3", "size_curriculum": 0, "balance_sizes": False},
            "--size-draw-power needs a range",
        ),
    ],
)
def test_bad_any_size_options_name_the_field(options, pattern):
    with pytest.raises(UserError, match=pattern):
        validate(with_options(ANYSIZE, options))


def test_the_nearest_view_is_the_k_nearest_of_each_type_sorted_and_padded():
    """nearest_entities against a NumPy sort of each type's real tokens, padded to k; the same
    view whatever the numbering of the layout."""
    params = get_scenario("paper-6").replace(active_rovers=3, active_pois=5, active_traps=6)
    _, state = reset(jax.random.PRNGKey(9), params)
    k = 4
    view = observe_entities(state, params)
    near = nearest_entities(view, params, k)
    assert near.tokens.shape == (6, 3 * k, TOKEN_FEATURES)
    for i in range(3):
        tokens, mask = np.asarray(view.tokens[i]), np.asarray(view.mask[i])
        for g, (start, stop) in enumerate(((0, 5), (5, 11), (11, 17))):
            real = tokens[start:stop][mask[start:stop]]
            real = real[np.argsort(np.sum(real[:, :2] ** 2, axis=-1), kind="stable")][:k]
            got = np.asarray(near.tokens[i, g * k : (g + 1) * k])
            np.testing.assert_allclose(got[: len(real)], real, atol=1e-6)
            assert not got[len(real) :].any() and np.asarray(near.mask[i, g * k : (g + 1) * k]).sum() == len(real)
    perm = np.random.default_rng(0).permutation(5)
    shuffled = state.replace(poi_pos=state.poi_pos.at[:5].set(state.poi_pos[:5][perm]))
    again = nearest_entities(observe_entities(shuffled, params), params, k)
    np.testing.assert_allclose(again.tokens, near.tokens, atol=1e-6)


def test_free_pois_first_shows_the_open_pois_before_the_taken_ones():
    """--poi-order free against a plain sort: each rover's real POI tokens ordered by (a nearer
    rover claims it, distance), cut to k. In a hand-made layout the plain cut hides the one
    POI nobody claims from the rover whose nearest POIs are taken; the free-first cut shows it
    first."""
    params = get_scenario("paper-6").replace(active_rovers=3, active_pois=5, active_traps=6)
    _, state = reset(jax.random.PRNGKey(9), params)
    k, pois = 2, slice(5, 11)  # 5 other rover slots, then the 6 POI slots
    view = observe_entities(state, params)
    near = nearest_entities(view, params, k, free_first=True)
    for i in range(3):
        tokens, mask = np.asarray(view.tokens[i, pois]), np.asarray(view.mask[i, pois])
        real = sorted(tokens[mask], key=lambda t: (t[CLAIM] <= 0, t[0] ** 2 + t[1] ** 2))[:k]
        np.testing.assert_allclose(np.asarray(near.tokens[i, k : 2 * k]), real, atol=1e-6)
    # rovers 0 and 1 both nearest to POI A (rover 1 nearer), rover 2 to B; C is nobody's nearest
    rovers = jnp.array([[0.0, 0.0], [0.25, 0.0], [0.0, 0.5]] + [[0.0, 0.0]] * 3)
    layout = jnp.array([[0.3, 0.0], [0.0, 0.6], [-0.9, -0.9]] + [[0.0, 0.0]] * 3)  # A, B, C
    params = params.replace(active_pois=3)
    hand = reset(jax.random.PRNGKey(9), params)[1].replace(rover_pos=rovers, poi_pos=layout)
    every = observe_entities(hand, params)
    plain, free = (nearest_entities(every, params, k, free_first=f).tokens[0, k : 2 * k, :2] for f in (False, True))
    far = np.array([-0.9, -0.9])
    assert not np.any(np.all(np.isclose(np.asarray(plain), far), axis=-1))  # A and B: C out of sight
    np.testing.assert_allclose(np.asarray(free[0]), far, atol=1e-6)  # C first, then A
    np.testing.assert_allclose(np.asarray(free[1]), [0.3, 0.0], atol=1e-6)


def test_matched_pois_first_puts_each_rovers_greedy_poi_first():
    """--poi-order matched against NumPy: the claim feature is a greedy matching of the working
    rovers to the POIs, the open POIs then handed to the rovers whose POI is observed (plain
    loops over the pairs, nearest first), and that POI takes each rover's first POI slot; a
    failed rover gets none."""
    from roverswarm.export_numpy import poi_matches

    params = get_scenario("paper-5")
    for key in range(6):
        _, state = reset(jax.random.PRNGKey(key), params)
        observed = np.asarray(jax.random.bernoulli(jax.random.PRNGKey(100 + key), 0.4, (5,)))
        failed = key % 5
        state = state.replace(fail_step=state.fail_step.at[failed].set(0), observed=jnp.asarray(observed))
        dist = np.linalg.norm(np.asarray(state.rover_pos)[:, None] - np.asarray(state.poi_pos)[None], axis=-1)
        working = np.arange(5) != failed
        expected = poi_matches(dist.astype(np.float32), working, observed)
        assert expected.sum() == 4 and not expected[failed].any()
        view = observe_entities(state, params, matched=True)
        np.testing.assert_array_equal(np.asarray(view.tokens[:, 4:9, CLAIM]), expected)
        near = observe_nearest(state, params, 2, poi_order="matched")
        for i in np.flatnonzero(working):
            own_poi = np.asarray(state.poi_pos)[np.argmax(expected[i])] - np.asarray(state.rover_pos)[i]
            np.testing.assert_allclose(np.asarray(near.tokens[i, 2, :2]), own_poi, atol=1e-6)
            assert near.tokens[i, 2, CLAIM] == 1 and near.tokens[i, 3, CLAIM] == 0


def test_the_matching_swaps_routes_that_cross():
    """Rover 0 at the left end, POI A, rover 1, POI B along a line: the greedy matching takes the
    nearest pair (rover 1 and A) first and sends rover 0 past it to B (2.2 in all); the view's
    matching swaps them (rover 0 to A, rover 1 to B: 1.3), and :func:`uncross` leaves a matching
    without crossings as it is."""
    params = get_scenario("paper-2")
    _, state = reset(jax.random.PRNGKey(0), params)
    state = state.replace(
        rover_pos=jnp.array([[-0.9, 0.0], [0.05, 0.0]]), poi_pos=jnp.array([[-0.4, 0.05], [0.85, 0.05]])
    )
    dist = pairwise_dist(state.rover_pos, state.poi_pos)
    assert greedy_match(dist).tolist() == [1, 0]
    assert uncross(jnp.array([1, 0]), dist).tolist() == [0, 1]
    assert uncross(jnp.array([0, 1]), dist).tolist() == [0, 1]
    np.testing.assert_array_equal(observe_entities(state, params, matched=True).tokens[:, 1:3, CLAIM], np.eye(2))


def test_the_matching_hands_a_failed_rovers_poi_to_a_rover_whose_poi_is_observed():
    """The oracle's rule in the view: rover 0 fails before reaching POI A; rover 1 sits on POI B,
    observed; rover 2 drives to POI C, not yet observed. The matching gives A to rover 1 (though
    rover 2 is nearer to A), and C stays rover 2's; with B not yet observed nobody is free and A
    stays open."""
    params = get_scenario("paper-3")
    _, state = reset(jax.random.PRNGKey(0), params)
    state = state.replace(
        rover_pos=jnp.array([[-0.9, -0.9], [0.8, 0.8], [0.0, 0.5]]),
        poi_pos=jnp.array([[-0.2, 0.2], [0.8, 0.8], [0.0, 0.6]]),  # A, B, C
        fail_step=jnp.array([0, NEVER, NEVER], jnp.int32),
    )
    claim = lambda s: np.asarray(observe_entities(s, params, matched=True).tokens[:, 2:5, CLAIM])  # noqa: E731
    handed = [[0, 0, 0], [1, 0, 0], [0, 0, 1]]  # rover 1 takes A, rover 2 keeps C
    np.testing.assert_array_equal(claim(state.replace(observed=jnp.array([False, True, False]))), handed)
    np.testing.assert_array_equal(claim(state.replace(observed=jnp.zeros(3, bool))), np.diag([0.0, 1, 1]))


@pytest.mark.parametrize("poi_order", ["free", "matched"])
def test_the_poi_order_reaches_every_view_a_policy_acts_on(poi_order):
    """The option from the config to the view: MAPPO's networks, the off-policy family's view
    (acting and replay), the export's policy.json and its NumPy runtime all order the POIs as
    asked (a layout where that differs from the plain cut)."""
    from roverswarm import export, export_numpy
    from roverswarm.algos.ppo_networks import policy_networks
    from roverswarm.learners.offpolicy import view_of
    from roverswarm.presets import ANYSIZE_DDPG

    params = get_scenario("paper-6")
    _, state = reset(jax.random.PRNGKey(3), params)
    ordered, plain = (observe_nearest(state, params, 2, poi_order=o).tokens for o in (poi_order, "nearest"))
    assert not np.allclose(ordered, plain)
    mappo = with_options(ANYSIZE, {"entity_nearest": 2, "poi_order": poi_order})
    ddpg = with_options(ANYSIZE_DDPG, {"entity_nearest": 2, "poi_order": poi_order})
    np.testing.assert_array_equal(policy_networks(mappo.learner, mappo.ppo).observe(state, params).tokens, ordered)
    np.testing.assert_array_equal(view_of(ddpg.learner)(state, params).tokens, ordered)
    meta = {"view": export.view_of(mappo), "env": {"rover_radius": 0.15, "observe_radius": 0.1, "trap_radius": 0.1}}
    assert meta["view"]["poi_order"] == poi_order and "first" in meta["view"]["order"]
    s = jax.device_get(state)
    inputs = export_numpy.model_inputs(meta, s.rover_pos, s.rover_vel, s.poi_pos, s.trap_pos, s.observed)
    np.testing.assert_allclose(inputs["tokens"][0], ordered, atol=1e-6)


def test_the_command_line_offers_exactly_the_poi_orders_the_view_knows():
    """--poi-order's choices (AlgoConfig's Literal, which tyro shows) are env.entities.POI_ORDERS,
    the orders observe_nearest implements: adding one to either alone fails here."""
    import typing

    from roverswarm.algos.learner import AlgoConfig
    from roverswarm.env.entities import POI_ORDERS

    assert typing.get_args(typing.get_type_hints(AlgoConfig)["poi_order"]) == POI_ORDERS


def test_a_config_from_before_the_poi_order_loads_with_its_order():
    """A run folder's config.json with ``free_pois_first`` (before --poi-order) loads as
    ``poi_order="free"``, and an export's policy.json with it runs its view the same way."""
    import json

    from roverswarm import export, export_numpy
    from roverswarm.config import config_from_json, config_to_json

    free = with_options(ANYSIZE, {"poi_order": "free"})
    raw = json.loads(config_to_json(free))
    del raw["learner"]["poi_order"]
    raw["learner"]["free_pois_first"] = True
    assert config_from_json(json.dumps(raw)) == free
    params = get_scenario("paper-6")
    s = jax.device_get(reset(jax.random.PRNGKey(3), params)[1])
    env = {"rover_radius": 0.15, "observe_radius": 0.1, "trap_radius": 0.1}
    new = {"view": export.view_of(free), "env": env}
    old = {"view": {**new["view"], "free_pois_first": True}, "env": env}
    del old["view"]["poi_order"]
    inputs = (export_numpy.model_inputs(m, s.rover_pos, s.rover_vel, s.poi_pos, s.trap_pos) for m in (new, old))
    np.testing.assert_array_equal(*(i["tokens"] for i in inputs))


def _padded_state(key: int, active: int = 4):
    """A paper-6 layout with ``active`` rovers, POIs and traps, one step into its episode."""
    params = get_scenario("paper-6").replace(active_rovers=active, active_pois=active, active_traps=active)
    _, state = reset(jax.random.PRNGKey(key), params)
    actions = jax.random.uniform(jax.random.PRNGKey(key + 1), (6, 2), minval=-1)
    return params, *step_env(state, actions, params)[1:]


def test_the_swarm_value_sees_the_mean_of_the_rovers_that_exist_in_any_order():
    """--swarm-value's input against NumPy: each rover's own flat view, then the mean of the
    existing rovers' (4 of 6 slots) and 4 / 10; reordering the rovers reorders the rows only."""
    params, state, *_ = _padded_state(30)
    view = nearest_entities(observe_entities(state, params), params, 3)
    flat, inputs = np.asarray(flat_tokens(view)), np.asarray(swarm_tokens(view))
    width = flat.shape[-1]
    swarm = np.concatenate([flat[:4].mean(axis=0), [0.4]])
    np.testing.assert_allclose(inputs[:, :width], flat)
    np.testing.assert_allclose(inputs[:4, width:], np.broadcast_to(swarm, (4, width + 1)), atol=1e-6)
    order = np.array([2, 0, 5, 3, 1, 4])
    shuffled = jax.tree.map(lambda x: x[order], view)
    np.testing.assert_allclose(np.asarray(swarm_tokens(shuffled)), inputs[order], atol=1e-6)


def test_a_pois_lead_matches_a_plain_loop():
    """A POI token's lead is the nearest other working rover's distance less the rover's own: a
    failed rover (rover 1 here) and the empty slots never count."""
    params, state, *_ = _padded_state(20)
    state = state.replace(fail_step=state.fail_step.at[1].set(0))
    pos, pois = np.asarray(state.rover_pos)[:4], np.asarray(state.poi_pos)[:4]
    view = observe_entities(state, params)
    for i in range(4):
        others = np.delete(pos, [i, 1], axis=0)
        poi_tokens = np.asarray(view.tokens[i])[np.asarray(view.mask[i])][3:7]  # 3 other rovers, then the POIs
        for j, token in enumerate(poi_tokens):
            mine, theirs = np.linalg.norm(pos[i] - pois[j]), np.linalg.norm(others - pois[j], axis=-1).min()
            assert token[LEAD] == pytest.approx(np.clip(theirs - mine, -2, 2), abs=1e-5)


def test_a_pois_claim_lead_matches_a_plain_loop():
    """A POI token's claim lead: the nearest of the other working rovers whose nearest existing
    POI it is, their distance less the rover's own (+2 where none claims it); a failed rover
    (rover 2) and the empty slots never count."""
    params, state, *_ = _padded_state(21)
    state = state.replace(fail_step=state.fail_step.at[2].set(0))
    pos, pois = np.asarray(state.rover_pos)[:4], np.asarray(state.poi_pos)[:4]
    view = observe_entities(state, params)
    claimed = set()
    for i in range(4):
        poi_tokens = np.asarray(view.tokens[i])[np.asarray(view.mask[i])][3:7]
        for j, token in enumerate(poi_tokens):
            rivals = [
                np.linalg.norm(pos[k] - pois[j])
                for k in range(4)
                if k not in (i, 2) and np.argmin(np.linalg.norm(pois - pos[k], axis=-1)) == j
            ]
            expected = min(rivals) - np.linalg.norm(pos[i] - pois[j]) if rivals else 2.0
            claimed.update([j] if rivals else [])
            assert token[CLAIM] == pytest.approx(np.clip(expected, -2, 2), abs=1e-5)
    assert 0 < len(claimed) < 4  # some POIs claimed, some free: both cases are checked


@pytest.mark.slow
def test_one_policy_learns_two_sizes_and_beats_random_by_a_wide_margin(tmp_path):
    """The anysize preset on paper-2..3 (its curriculum and annealing shortened), 1000 episodes:
    every seed beats random by a wide margin at both sizes, and at paper-4, which it never
    trained on (0.74 / 0.75, 0.69 / 0.66, 0.61 / 0.61 when written; 2000 episodes: 0.79 at
    worst, training twice as long)."""
    preset = with_options(ANYSIZE, {"anneal_episodes": 1000})
    config = dataclasses.replace(
        preset, scenario="paper-2..3", episodes=1000, size_curriculum=500, seeds=2, num_envs=40
    )
    train(config, out=tmp_path, progress=False)
    rows = evaluate_run(tmp_path, episodes=300, scenario="paper-2,3,4")
    scores = {(r["scenario"], r["policy"]): r["normalized_score"] for r in rows if r["policy"].startswith("mappo")}
    assert len(scores) == 6 and min(scores.values()) > 0.3, scores  # random is 0


def test_a_size_agnostic_run_drives_a_mission_of_another_size(anysize_run, tmp_path):
    """The outpost mission's eight rovers (a size and a layout the run never trained on: paper-2..4)
    are driven by the run's seed 0, with and without a rover failure, beside the oracle: its
    rows without failure are those of the run's policy rolled out on the mission directly."""
    from roverswarm.env.missions import load_mission
    from roverswarm.rollout import MissionStats, rollout
    from roverswarm.stress import stress_mission

    outpost = Path(__file__).parents[1] / "examples" / "outpost.yaml"
    rows = stress_mission(outpost, str(anysize_run), tmp_path, episodes=20)
    params = load_mission(outpost).params
    assert params.num_rovers == 8
    assert [(r["policy"] == "oracle", r["condition"]) for r in rows] == [
        (False, "no failure"),
        (False, "one rover fails"),
        (True, "no failure"),
        (True, "one rover fails"),
    ]
    direct = MissionStats.of(rollout(Run(anysize_run).policy(0), jax.random.PRNGKey(0), params, 20)).summary()
    np.testing.assert_equal({k: v for k, v in rows[0].items() if k not in ("policy", "condition")}, direct)


def test_evaluate_and_mission_stress_drive_the_policy_behind_the_shield(anysize_run, tmp_path, capsys, monkeypatch):
    """``--shield`` puts every seed's policy behind the safety layer: its rows are named so,
    random and the oracle (the references) run as without it, and the shielded seeds touch
    traps less than half as often as the same seeds without it, on the same layouts;
    ``mission stress --shield`` shields the policy, not the oracle beside it."""
    from roverswarm.cli import main

    plain = {r["policy"]: r for r in evaluate_run(anysize_run, episodes=100, scenario="paper-3")}
    monkeypatch.setenv("COLUMNS", "250")
    assert main(["evaluate", str(anysize_run), "--episodes", "100", "--scenario", "paper-3", "--shield"]) == 0
    assert "mappo seed 1, shielded" in capsys.readouterr().out
    safe = {r["policy"]: r for r in evaluate_run(anysize_run, episodes=100, scenario="paper-3", shield=True)}
    assert list(safe) == ["random", "oracle", "mappo seed 0, shielded", "mappo seed 1, shielded"]
    for reference in ("random", "oracle"):
        assert safe[reference] == plain[reference]
    for seed in (0, 1):
        before, after = plain[f"mappo seed {seed}"], safe[f"mappo seed {seed}, shielded"]
        assert after["trap_contacts"] < 0.5 * before["trap_contacts"], (seed, before, after)
    mixed = evaluate_run(anysize_run, episodes=10, scenario="paper-3", partners="other-seeds", shield=True)
    assert [r["policy"] for r in mixed][2:] == [
        "mappo agents of seeds 0/1/0, shielded",
        "mappo agents of seeds 1/0/1, shielded",
    ]

    from roverswarm.stress import stress_mission

    survey = Path(__file__).parents[1] / "examples" / "survey.yaml"
    rows = stress_mission(survey, str(anysize_run), tmp_path, episodes=20, shield=True)
    names = {r["policy"] for r in rows}
    assert len(names) == 2 and "oracle" in names and (names - {"oracle"}).pop().endswith(", shielded"), names
