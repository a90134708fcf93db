"""MAPPO/IPPO: GAE and the loss against plain loops, episode flags under jit(vmap),
determinism, and a short run that learns."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.algos import ppo, ppo_networks
from roverswarm.algos.normalize import init_obs_norm, update_obs_norm
from roverswarm.config import TrainConfig, validate, with_options
from roverswarm.env.mars import EnvParams, observation_size
from roverswarm.env.scenarios import get_scenario
from roverswarm.errors import UserError
from roverswarm.learners import onpolicy
from roverswarm.learners.onpolicy import PPO_METRICS
from roverswarm.policies import ORACLE, RANDOM
from roverswarm.presets import MAPPO
from roverswarm.rollout import normalized_score, rollout
from roverswarm.runs import Run
from roverswarm.trainer import train

TIMELESS = lambda rows: [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]  # noqa: E731


# ----------------------------------------------------------------------------- GAE


def slow_gae(rewards, values, next_values, terminated, truncated, gamma, lam):
    """Advantages and returns, one step at a time, backwards."""
    steps = len(rewards)
    advantages = np.zeros_like(rewards)
    for t in reversed(range(steps)):
        bootstrap = 0.0 if terminated[t] else next_values[t]
        delta = rewards[t] + gamma * bootstrap - values[t]
        ends = terminated[t] or truncated[t] or t == steps - 1
        advantages[t] = delta + (0.0 if ends else gamma * lam * advantages[t + 1])
    return advantages, advantages + values


def test_gae_matches_a_python_loop_across_truncation_and_termination():
    rng = np.random.default_rng(0)
    steps, envs = 12, 3
    rewards, values, next_values = (rng.normal(size=(steps, envs)).astype(np.float32) for _ in range(3))
    terminated = np.zeros((steps, envs), bool)
    truncated = np.zeros((steps, envs), bool)
    truncated[4, 0] = True  # a time limit in the middle: bootstrap, cut the trace
    terminated[7, 1] = True  # a termination: no bootstrap
    truncated[steps - 1] = True
    gamma, lam = 0.95, 0.9

    adv, ret = jax.jit(ppo.gae, static_argnums=(4, 5))(
        jnp.asarray(rewards),
        jnp.asarray(values),
        jnp.asarray(next_values),
        jnp.asarray(terminated),
        gamma,
        lam,
        jnp.asarray(truncated),
    )
    for e in range(envs):
        want_adv, want_ret = slow_gae(
            rewards[:, e], values[:, e], next_values[:, e], terminated[:, e], truncated[:, e], gamma, lam
        )
        np.testing.assert_allclose(np.asarray(adv[:, e]), want_adv, atol=1e-5)
        np.testing.assert_allclose(np.asarray(ret[:, e]), want_ret, atol=1e-5)
    # the truncated step bootstraps with the value of its own next observation
    np.testing.assert_allclose(adv[4, 0], rewards[4, 0] + gamma * next_values[4, 0] - values[4, 0], atol=1e-6)
    np.testing.assert_allclose(adv[7, 1], rewards[7, 1] - values[7, 1], atol=1e-6)
    # without truncation flags the trace runs through step 4 (a different number there)
    adv_through, _ = ppo.gae(
        jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(next_values), jnp.asarray(terminated), gamma, lam
    )
    assert abs(float(adv_through[4, 0] - adv[4, 0])) > 1e-3
    np.testing.assert_allclose(adv_through[5:], adv[5:], atol=1e-6)


# ----------------------------------------------------------------------------- loss


def numpy_loss(config, log_probs, entropy, values, b):
    """The loss as written out: the value's terms over the masked-in samples, the policy's
    over those whose rover had not failed (``acting``)."""
    mask = b["mask"] * b["acting"]

    def mean(x, m=mask):
        return (x * m).sum() / m.sum()

    adv = b["advantages"]
    adv_mean = mean(adv)
    adv = (adv - adv_mean) / (np.sqrt(mean((adv - adv_mean) ** 2)) + 1e-8)
    ratio = np.exp(log_probs - b["log_probs"])
    policy = -mean(np.minimum(ratio * adv, np.clip(ratio, 1 - config.clip_eps, 1 + config.clip_eps) * adv))
    error = (values - b["targets"]) ** 2
    if config.value_clip is not None:
        clipped = b["values"] + np.clip(values - b["values"], -config.value_clip, config.value_clip)
        error = np.maximum(error, (clipped - b["targets"]) ** 2)
    value = 0.5 * mean(error, b["mask"])
    total = policy + config.vf_coef * value - config.ent_coef * mean(entropy)
    return total, policy, value


@pytest.mark.parametrize("value_clip", [0.2, None])
def test_ppo_loss_matches_numpy(value_clip):
    rng = np.random.default_rng(1)
    size = 64

    def f32(x):
        return np.asarray(x, np.float32)

    b = {
        "log_probs": f32(rng.normal(size=size)),
        "advantages": f32(rng.normal(1.0, 2.0, size=size)),
        "targets": f32(rng.normal(size=size)),
        "values": f32(rng.normal(size=size)),
        "mask": f32(rng.random(size) < 0.8),
        "acting": f32(rng.random(size) < 0.7),  # the others: rovers that had failed
    }
    # ratios well beyond the clip range on both sides, value changes beyond the value clip
    log_probs = f32(b["log_probs"] + rng.normal(0, 0.3, size=size))
    values = f32(b["values"] + rng.normal(0, 0.5, size=size))
    entropy = f32(rng.normal(1.0, 0.1, size=size))
    config = ppo.PPOConfig(value_clip=value_clip, ent_coef=0.03, vf_coef=0.7, clip_eps=0.15)
    batch = ppo.Batch(
        actor_inputs=jnp.zeros((size, 1)),
        critic_inputs=jnp.zeros((size, 1)),
        actions=jnp.zeros((size, 2)),
        **{k: jnp.asarray(v) for k, v in b.items()},
    )
    total, parts = jax.jit(ppo.ppo_loss, static_argnums=0)(config, log_probs, entropy, values, batch)
    want_total, want_policy, want_value = numpy_loss(config, log_probs, entropy, values, b)
    np.testing.assert_allclose(parts["policy_loss"], want_policy, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(parts["value_loss"], want_value, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(total, want_total, rtol=1e-5, atol=1e-6)
    ratio = np.exp(log_probs - b["log_probs"])
    acts = b["mask"] * b["acting"]
    clipped = (np.abs(ratio - 1) > config.clip_eps) * acts
    assert 0.1 < clipped.sum() / acts.sum() < 0.9  # the batch exercises both branches
    np.testing.assert_allclose(parts["clip_fraction"], clipped.sum() / acts.sum(), rtol=1e-5)
    # a failed rover's sample moves the value's loss, not the policy's
    failed = np.flatnonzero((b["mask"] == 1) & (b["acting"] == 0))
    changed = batch.replace(advantages=batch.advantages.at[failed].add(5.0), targets=batch.targets.at[failed].add(1.0))
    _, moved = jax.jit(ppo.ppo_loss, static_argnums=0)(config, log_probs, entropy, values, changed)
    assert moved["policy_loss"] == parts["policy_loss"] and moved["value_loss"] != parts["value_loss"]


def test_value_target_statistics_match_numpy_over_masked_batches():
    rng = np.random.default_rng(2)
    batches = [rng.normal(3.0, 2.0, size=50).astype(np.float32) for _ in range(3)]
    masks = [(rng.random(50) < 0.7).astype(np.float32) for _ in range(3)]
    stats = init_obs_norm(1)
    for x, m in zip(batches, masks):
        stats = update_obs_norm(stats, jnp.asarray(x)[:, None], jnp.asarray(m))
    kept = np.concatenate([x[m > 0] for x, m in zip(batches, masks)])
    np.testing.assert_allclose(stats.mean, [kept.mean()], rtol=1e-4)
    np.testing.assert_allclose(stats.var, [kept.var()], rtol=1e-3)
    assert float(stats.count) == len(kept)
    empty = update_obs_norm(stats, jnp.ones((4, 1)), jnp.zeros(4))  # nothing masked in: unchanged
    np.testing.assert_allclose(empty.mean, stats.mean)
    np.testing.assert_allclose(empty.var, stats.var)


def test_validate_names_the_bad_field_and_refuses_options_of_the_other_learner(tiny_ppo_config):
    validate(tiny_ppo_config)  # paper-2: 25 steps x 4 envs x 2 rovers = 200 samples per iteration
    with pytest.raises(UserError, match="--minibatches"):
        validate(with_options(tiny_ppo_config, {"minibatches": 7}))
    with pytest.raises(UserError, match="--twin-critics True does not apply: --algo mappo learns on-policy"):
        validate(with_options(tiny_ppo_config, {"twin_critics": True}))
    with pytest.raises(UserError, match="--batch-size 64 does not apply"):
        validate(with_options(tiny_ppo_config, {"batch_size": 64}))
    with pytest.raises(UserError, match="--epochs 3 does not apply: it is a PPO option"):
        validate(with_options(TrainConfig(), {"epochs": 3}))
    with pytest.raises(UserError, match="--clip-eps"):
        validate(with_options(tiny_ppo_config, {"clip_eps": float("inf")}))


# ----------------------------------------------------------------------------- inputs, rollout flags


def test_inputs_and_deterministic_actions(tiny_ppo_config):
    params = get_scenario("paper-3")
    n, o = params.num_rovers, observation_size(params)
    obs = jax.random.normal(jax.random.PRNGKey(0), (5, n, o))
    inputs = ppo_networks.actor_inputs(obs)
    assert inputs.shape == (5, n, o + n)
    np.testing.assert_array_equal(inputs[..., :o], obs)
    np.testing.assert_array_equal(inputs[:, 1, o:], np.tile([0, 1, 0], (5, 1)))
    mappo = ppo_networks.critic_inputs("mappo", obs)
    assert mappo.shape == (5, n, n * o + n)
    np.testing.assert_array_equal(mappo[:, 2, : n * o], obs.reshape(5, -1))  # rover 2 sees every rover
    np.testing.assert_array_equal(mappo[:, 2, n * o :], np.tile([0, 0, 1], (5, 1)))
    np.testing.assert_array_equal(ppo_networks.critic_inputs("ippo", obs), inputs)

    config = tiny_ppo_config
    state = ppo.init_ppo(jax.random.PRNGKey(0), config, n, o)
    actions = ppo.act(config.learner, config.ppo, state.actor, 10 * obs)
    mean, _ = ppo_networks.networks(config.learner, config.ppo)[0].apply(
        state.actor, ppo_networks.actor_inputs(10 * obs)
    )
    assert actions.shape == (5, n, 2)
    np.testing.assert_array_equal(actions, np.clip(mean, -1, 1))


def test_orthogonal_init_under_vmap_draws_flaxs_matrices_one_qr_at_a_time():
    """Batched over keys, the initialiser gives flax's matrices key by key, and every QR
    factorisation in the compiled program is of one matrix: a batched one waits for its tasks
    on XLA's thread pool, and two at once hung the initialisation on 2 cores."""
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    draw = jax.vmap(lambda key: ppo_networks.orthogonal(2.0)(key, (6, 5)))
    flax_matrices = [np.asarray(jax.nn.initializers.orthogonal(2.0)(key, (6, 5))) for key in keys]
    np.testing.assert_array_equal(np.asarray(draw(keys)), np.stack(flax_matrices))
    qr_calls = [line for line in jax.jit(draw).lower(keys).as_text().splitlines() if "geqrf" in line]
    assert qr_calls and all('num_batch_dims = "0"' in line for line in qr_calls), qr_calls


def test_rollout_flags_under_jit_vmap(tiny_ppo_config):
    # (collect vmaps the environments; jit it as the trainer does)
    # time limit: truncated at the last step only, every step live
    config = tiny_ppo_config
    params = validate(config)
    state = ppo.init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, observation_size(params))
    traj, episode = jax.jit(lambda k: onpolicy.collect(config, params, state.actor, k))(jax.random.PRNGKey(1))
    assert traj.rewards.shape == (params.max_steps, config.num_envs, params.num_rovers)
    assert not traj.terminated.any() and (traj.mask == 1).all()
    np.testing.assert_array_equal(traj.truncated.any(axis=1), np.arange(params.max_steps) == params.max_steps - 1)
    assert traj.truncated[-1].all()
    np.testing.assert_allclose(episode["episode_reward"], traj.rewards.sum(axis=(0, 2)), rtol=1e-5)
    assert (np.abs(traj.actions) > 1).any()  # the unclipped samples are stored

    # mission mode: every POI is observed from the start, so every episode terminates at step 1
    starts = jnp.array([[-0.5, 0.0], [0.5, 0.0]])
    mission = EnvParams(
        num_rovers=2,
        num_pois=2,
        num_traps=1,
        terminate_on_complete=True,
        fixed_pois=starts,
        fixed_starts=starts,
        fixed_traps=jnp.array([[0.0, 0.8]]),
    )
    state = ppo.init_ppo(jax.random.PRNGKey(0), config, mission.num_rovers, observation_size(mission))

    @jax.jit
    def collect_and_batch(key):
        traj, episode = onpolicy.collect(config, mission, state.actor, key)
        values, _ = onpolicy.values_of(config, state.critic, state.returns, traj.obs)
        return traj, episode, onpolicy.make_batch(config, state, traj)[0], values

    traj, episode, batch, values = collect_and_batch(jax.random.PRNGKey(2))
    first = np.arange(mission.max_steps) == 0
    np.testing.assert_array_equal(traj.terminated.all(axis=1), first)
    assert not traj.terminated[1:].any() and not traj.truncated.any()
    np.testing.assert_array_equal(traj.mask[:, 0], first.astype(np.float32))
    assert (traj.rewards[1:] == 0).all()
    np.testing.assert_allclose(episode["episode_reward"], traj.rewards[0].sum(-1), rtol=1e-5)
    # the final coverage distance is the state's the episode ended in (every POI under a rover),
    # in training's metrics and in a rollout's, not the frozen state's stepped on by its velocity
    np.testing.assert_array_equal(episode["coverage_distance"], 0.0)
    np.testing.assert_array_equal(rollout(RANDOM, jax.random.PRNGKey(2), mission, 8).stats.coverage_distance, 0.0)
    # no bootstrap at the termination: the advantage is r - V; later steps are masked out
    advantages = batch.advantages.reshape(traj.rewards.shape)
    np.testing.assert_allclose(advantages[0], traj.rewards[0] - values[0], atol=1e-4)
    assert (batch.mask.reshape(traj.rewards.shape)[1:] == 0).all()


def test_a_failed_rover_is_out_of_the_policys_samples_and_the_value_clip_is_centred_on_its_output(tiny_ppo_config):
    """With a failure in every episode, ``acting`` is 0 exactly where the rover stands still
    for good (its position no longer follows its action); with --value-norm the batch's values
    are the value network's own outputs, so --value-clip's window is centred on them."""
    config = with_options(tiny_ppo_config, {"fail_rate": 1.0, "value_clip": 0.2, "num_envs": 10})
    params = validate(config)
    state = ppo.init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, observation_size(params))
    nets = ppo_networks.policy_networks(config.learner, config.ppo)

    @jax.jit
    def collect_and_batch(key):
        traj, _ = onpolicy.collect(config, params, state.actor, key)
        batch, returns = onpolicy.make_batch(config, state, traj)
        return traj, batch, returns, nets.value(state.critic, batch.critic_inputs)

    traj, batch, returns, outputs = collect_and_batch(jax.random.PRNGKey(3))
    acting = np.asarray(traj.acting)  # [T, E, N]
    assert (np.diff(acting, axis=0) <= 0).all(), "a failed rover does not come back"
    assert (acting[-1] == 0).sum(axis=-1).tolist() == [1] * config.num_envs  # one failure per episode
    position, next_position = (np.asarray(o)[..., 2:4] for o in (traj.obs, traj.next_obs))  # own velocity first
    stands = np.all(next_position == position, axis=-1)
    assert stands[acting == 0].all() and not stands[1:][acting[1:] == 1].any()  # at step 0 no rover has speed yet
    np.testing.assert_array_equal(batch.acting, acting.reshape(-1))
    assert not np.allclose(returns.mean, state.returns.mean)  # the statistics moved with this batch
    np.testing.assert_allclose(batch.values, outputs, rtol=1e-6)


# ----------------------------------------------------------------------------- determinism


# IPPO with the options the presets leave off (MAPPO with the preset's options runs elsewhere)
IPPO_OPTIONS = {"algo": "ippo", "value_clip": 0.2, "value_norm": False, "anneal_episodes": 200}


@pytest.fixture(scope="module")
def tiny_runs(tiny_ppo_config):
    config = with_options(tiny_ppo_config, {**IPPO_OPTIONS, "episodes": 200})
    return (
        train(config, progress=False),
        train(config, progress=False),
        train(dataclasses.replace(config, seed=5), progress=False),
    )


def test_same_seed_same_numbers_different_seeds_different_params(tiny_runs):
    a, b, c = tiny_runs
    assert TIMELESS(a.metrics) == TIMELESS(b.metrics)
    for x, y in zip(jax.tree.leaves(a.learner), jax.tree.leaves(b.learner)):
        np.testing.assert_array_equal(x, y)
    kernel = lambda r: np.asarray(r.learner.actor["params"]["MLP_0"]["Dense_0"]["kernel"])  # noqa: E731
    assert not np.allclose(kernel(a)[0], kernel(a)[1])  # the two seeds of one run
    assert not np.allclose(kernel(a), kernel(c))  # another base seed
    for row in a.metrics:
        for name in ("episode_reward", "collisions", "trap_contacts", "coverage_distance", *PPO_METRICS):
            assert np.isfinite(row[name]), name
        assert row["episode_reward"] == pytest.approx(row["agent_0_reward"] + row["agent_1_reward"], rel=1e-4)
    params = get_scenario("paper-2")  # IPPO: the value network sees the rover's own observation
    local_inputs = observation_size(params) + params.num_rovers
    assert a.learner.critic["params"]["Dense_0"]["kernel"].shape == (2, local_inputs, 16)


# ----------------------------------------------------------------------------- learning


@pytest.mark.slow
def test_mappo_beats_random_on_spread3_by_a_wide_margin():
    config = dataclasses.replace(MAPPO, scenario="spread-3", episodes=5000)  # the preset's options
    result = train(config, progress=False)
    params = validate(config)
    key = jax.random.PRNGKey(7)  # the same 500 layouts for every policy
    rewards = {
        p.name: rollout(p, key, params, 500).stats.summary()["episode_reward"]
        for p in (Run.of(config, result.learner).policy(0), RANDOM, ORACLE)
    }
    trained = rewards.pop(next(iter(rewards)))
    score = normalized_score(trained, rewards["random"], rewards["oracle"])
    assert score > 0.4, (score, trained, rewards)
