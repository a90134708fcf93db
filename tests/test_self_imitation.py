"""Self-imitation (``--self-imitation``): the memory keeps the best samples, draws them by
priority, the loss is the paper's formula, the returns are the episodes' discounted sums, and a
run with it learns, resumes exactly and refuses bad options."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm import train
from roverswarm.algos import ppo, self_imitation
from roverswarm.algos.ppo_networks import policy_networks
from roverswarm.algos.self_imitation import PRIORITY_EXPONENT, VALUE_WEIGHT, Memory
from roverswarm.cli import main
from roverswarm.config import ANYSIZE, TrainConfig, validate, with_options
from roverswarm.errors import UserError
from roverswarm.evaluate import evaluate_run
from roverswarm.learners import learner_family
from roverswarm.learners.onpolicy import collect, configure, make_batch, values_of
from roverswarm.runs import read_metrics


@pytest.fixture(scope="module")
def tiny_sil():
    """The anysize preset with self-imitation, shrunk: sizes 2 to 4, small networks, a small
    memory, few episodes."""
    config = with_options(
        ANYSIZE,
        {
            "self_imitation": 0.02,
            "self_imitation_memory": 500,
            "hidden": (32, 32),
            "anneal_episodes": 0,
            "actor_lr": 3e-3,
        },
    )
    return dataclasses.replace(
        config, scenario="paper-2..4", size_curriculum=0, episodes=600, seeds=1, num_envs=20, log_every=200
    )


@pytest.fixture(scope="module")
def sil_run(tiny_sil, tmp_path_factory):
    """``tiny_sil`` trained at once, 600 episodes."""
    out = tmp_path_factory.mktemp("sil")
    train(tiny_sil, out=out, progress=False)
    return out


def _rows(rng, count: int, width: int = 3) -> Memory:
    return Memory(
        actor_inputs=jnp.asarray(rng.normal(size=(count, width)), jnp.float32),
        critic_inputs=jnp.asarray(rng.normal(size=(count, width)), jnp.float32),
        actions=jnp.asarray(rng.normal(size=(count, 2)), jnp.float32),
        returns=jnp.asarray(rng.normal(size=count), jnp.float32),
        weights=jnp.asarray(rng.choice([0.0, 1.0, 2.5], size=count), jnp.float32),
    )


def test_the_memory_keeps_the_rows_whose_return_beat_the_value_most():
    """Memory and samples ranked together by max(R - V, 0) (empty rows 0), computed here in
    NumPy: the C best rows are kept, with their A+."""
    rng = np.random.default_rng(0)
    memory, samples = _rows(rng, 8), _rows(rng, 20)
    values = rng.normal(size=28).astype(np.float32)
    scale = lambda r: (r - 0.5) / 2.0  # noqa: E731  (a value-target standardisation)
    kept, best = self_imitation.remember(
        memory, samples, lambda rows: self_imitation.clipped_advantages(rows, jnp.asarray(values), scale)
    )
    returns = np.concatenate([memory.returns, samples.returns])
    weights = np.concatenate([memory.weights, samples.weights])
    plus = np.where(weights > 0, np.maximum(scale(returns) - values, 0.0), 0.0)
    order = np.argsort(-plus, kind="stable")[:8]
    assert plus[order].min() > 0  # the test ranks positive advantages only (ties at 0 are arbitrary)
    np.testing.assert_allclose(np.asarray(best), plus[order], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(kept.returns), returns[order])
    np.testing.assert_array_equal(np.asarray(kept.weights), weights[order])


def test_rows_are_drawn_in_proportion_to_their_advantage_to_the_power_0_6():
    rng = np.random.default_rng(1)
    memory = _rows(rng, 5)
    advantages = jnp.asarray([0.0, 0.5, 1.0, 2.0, 4.0])
    memory = memory.replace(returns=jnp.arange(5.0))  # each row's index, to count the draws
    drawn = self_imitation.draw(jax.random.PRNGKey(0), memory, advantages, (200, 1000))
    counts = np.bincount(np.asarray(drawn.returns).astype(int).ravel(), minlength=5) / 200_000
    want = np.asarray(advantages) ** PRIORITY_EXPONENT
    np.testing.assert_allclose(counts, want / want.sum(), atol=0.005)
    assert counts[0] == 0  # a row with nothing to teach is never drawn
    uniform = self_imitation.draw(jax.random.PRNGKey(1), memory, jnp.zeros(5), (100, 1000))
    counts = np.bincount(np.asarray(uniform.returns).astype(int).ravel(), minlength=5) / 100_000
    np.testing.assert_allclose(counts, 0.2, atol=0.01)


def test_the_update_adds_the_papers_loss_and_leaves_the_log_std_alone(tiny_sil):
    """With every PPO sample masked out, an update is self-imitation's alone: its loss is
    mean_w[-log pi(a|s) A+] + 0.01 * 0.5 * mean_w[A+^2] (computed here in NumPy from the
    networks' outputs), the actor's mean moves toward the remembered actions, and its log-std
    does not move."""
    params = validate(tiny_sil)
    config = configure(tiny_sil, params)
    nets = policy_networks(config.learner, config.ppo)
    state = jax.tree.map(lambda x: x[0], learner_family("mappo").learners(config, params))
    traj, _ = collect(config, params, state.actor, jax.random.PRNGKey(3))
    batch, _ = make_batch(config, state, traj)
    rows = 64
    rng = np.random.default_rng(2)
    pick = lambda x: x[:rows]  # noqa: E731
    values = nets.value(state.critic, pick(batch.critic_inputs))
    memory = Memory(
        actor_inputs=pick(batch.actor_inputs),
        critic_inputs=pick(batch.critic_inputs),
        actions=jnp.asarray(rng.uniform(-1, 1, size=(rows, 2)), jnp.float32),
        returns=values + jnp.asarray(rng.normal(0.3, 1.0, size=rows), jnp.float32),  # in units of mean 0, var 1
        weights=jnp.asarray(rng.choice([0.0, 1.0, 2.0], size=rows), jnp.float32),
    )
    silent = jax.tree.map(lambda x: x[:rows], batch.replace(discounted=None))
    silent = silent.replace(mask=jnp.zeros(rows))
    state = state.replace(returns=state.returns.replace(mean=jnp.zeros(1), var=jnp.ones(1)))
    new, parts = jax.jit(ppo.update_minibatch, static_argnums=0)(config, state, silent, memory)

    mean, log_std = (np.asarray(x) for x in nets.policy(state.actor, memory.actor_inputs))
    a, w = np.asarray(memory.actions), np.asarray(memory.weights)
    log_prob = np.sum(-0.5 * np.square((a - mean) / np.exp(log_std)) - log_std - 0.5 * np.log(2 * np.pi), axis=-1)
    plus = np.where(w > 0, np.maximum(np.asarray(memory.returns) - np.asarray(values), 0.0), 0.0)
    want = np.sum(-log_prob * plus * w) / w.sum() + VALUE_WEIGHT * 0.5 * np.sum(plus**2 * w) / w.sum()
    assert 0.2 < (plus > 0).mean() < 0.9
    np.testing.assert_allclose(parts["self_imitation_loss"], want, rtol=1e-4)
    np.testing.assert_allclose(parts["self_imitation_advantage"], np.sum(plus * w) / w.sum(), rtol=1e-5)

    moved, moved_log_std = (np.asarray(x) for x in nets.policy(new.actor, memory.actor_inputs))
    np.testing.assert_array_equal(moved_log_std, log_std)
    taught = (plus * w) > 0
    before = np.sum(np.square(mean - a), axis=-1)[taught]
    after = np.sum(np.square(moved - a), axis=-1)[taught]
    assert np.average(after, weights=plus[taught]) < np.average(before, weights=plus[taught])


def test_the_remembered_returns_are_the_episodes_discounted_sums(tiny_sil):
    """R_t = r_t + gamma R_{t+1}, the time limit's last step bootstrapping with the value of
    its next state: a plain Python loop over every environment and rover."""
    params = validate(tiny_sil)
    config = configure(tiny_sil, params)
    state = jax.tree.map(lambda x: x[0], learner_family("mappo").learners(config, params))
    traj, _ = jax.jit(collect, static_argnums=(0,))(config, params, state.actor, jax.random.PRNGKey(4))
    batch, _ = jax.jit(make_batch, static_argnums=0)(config, state, traj)
    rewards = np.asarray(traj.rewards)  # [T, E, N]
    last = np.asarray(values_of(config, state.critic, state.returns, traj.next_obs))[-1]  # [E, N]
    gamma = tiny_sil.learner.gamma
    want = np.zeros_like(rewards)
    steps, envs, rovers = rewards.shape
    for e in range(envs):
        for i in range(rovers):
            total = last[e, i]
            for t in reversed(range(steps)):
                total = rewards[t, e, i] + gamma * total
                want[t, e, i] = total
    assert not np.asarray(traj.terminated).any() and np.asarray(traj.truncated)[-1].all()
    np.testing.assert_allclose(np.asarray(batch.discounted), want.reshape(-1), rtol=1e-4, atol=1e-3)


def test_a_run_with_self_imitation_learns_and_logs_its_loss(sil_run):
    """600 episodes: 2 and 3 rovers well above random (0; this run scored 0.29 and 0.23 when
    the test was written, the same run without self-imitation 0.35 and 0.26), the memory's
    mean A+ logged."""
    rows = read_metrics(sil_run / "metrics.csv")
    assert len(rows) == 3 and all(r["self_imitation_advantage"] > 0 for r in rows)
    scores = [
        r["normalized_score"]
        for r in evaluate_run(sil_run, episodes=100, scenario="paper-2,3")
        if r["policy"].startswith("mappo")
    ]
    assert len(scores) == 2 and min(scores) > 0.15, scores


def test_a_run_with_self_imitation_resumes_with_its_memory(tiny_sil, sil_run, tmp_path):
    """400 episodes, then extended to 600: the metrics of the 600-episode run at once (the
    memory is in the checkpoint)."""
    train(dataclasses.replace(tiny_sil, episodes=400), out=tmp_path, progress=False)
    assert main(["train", "--resume", str(tmp_path), "--episodes", "600"]) == 0
    timeless = lambda rows: [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]  # noqa: E731
    assert timeless(read_metrics(tmp_path / "metrics.csv")) == timeless(read_metrics(sil_run / "metrics.csv"))


@pytest.mark.parametrize(
    "options, pattern",
    [
        ({"self_imitation": -1.0}, "--self-imitation must be"),
        ({"self_imitation": 1.0, "self_imitation_memory": 0}, "--self-imitation-memory must be a positive number"),
    ],
)
def test_bad_self_imitation_options_name_the_field(options, pattern):
    with pytest.raises(UserError, match=pattern):
        validate(with_options(ANYSIZE, options))


def test_the_off_policy_family_refuses_self_imitation(capsys):
    with pytest.raises(UserError, match="--self-imitation"):
        validate(with_options(TrainConfig(), {"self_imitation": 1.0}))
    assert main(["train", "--algo", "maddpg", "--self-imitation", "1", "--episodes", "100"]) == 2
    assert "--self-imitation" in capsys.readouterr().err
