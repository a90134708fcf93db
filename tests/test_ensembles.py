"""Policy ensembles and inferred policies outside the update (which ``test_maddpg_update``
checks against its reference): the replay partitions D_i^(k) against a slow NumPy scan of the
stored sub-policies, for the uniform and the ranked replay (eq. 12-13 within a partition);
training, resume and evaluation with both options; bad input."""

from __future__ import annotations

import dataclasses
import shutil
import signal

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from scipy import stats
from test_ranked import N, jitted, transitions

from roverswarm.algos.learner import act, init_learner
from roverswarm.buffers.base import Transition, gather, importance_weights, recent_indices, update_weights
from roverswarm.buffers.ranked import ranked_buffer
from roverswarm.buffers.uniform import uniform_buffer
from roverswarm.cli import main
from roverswarm.config import validate, with_options
from roverswarm.env.mars import observation_size, reset
from roverswarm.errors import RunStopped, UserError
from roverswarm.evaluate import evaluate_run
from roverswarm.learners import offpolicy
from roverswarm.runs import CHECKPOINT, Run
from roverswarm.trainer import train

K = 3  # sub-policies per agent: with test_ranked's N = 2 agents, G = 6 sampling groups
DRAWS = 300


def numbered(first: int, policy: np.ndarray) -> Transition:
    """len(policy) transitions numbered from ``first`` (in obs), agent sub-policies ``policy`` [T, N]."""
    return transitions(first, len(policy), policy)


def fill(buffer, rng, total: int, chunk: int):
    """Add ``total`` transitions in chunks with random sub-policies; returns the state and the
    sub-policies of every transition ever added [total, N] (transition t holds number t)."""
    policies = rng.integers(0, K, (total, N))
    state = buffer.init(jax.tree.map(lambda x: x[0], numbered(0, policies[:1])))
    for start in range(0, total, chunk):
        state = buffer.add(state, numbered(start, policies[start : start + chunk]))
    return state, policies


def members(policies: np.ndarray, capacity: int, group: int) -> np.ndarray:
    """Slow scan: the numbers of the stored transitions (the newest ``capacity``) in ``group``'s partition."""
    stored = np.arange(max(0, len(policies) - capacity), len(policies))
    return stored[policies[stored, group // K] == group % K]


def draw(buffer, state, seed: int = 0):
    """DRAWS batches: the transition numbers drawn and their probabilities [DRAWS, G, B]."""

    @jax.jit
    def many(state, key):
        def one(_, k):
            sample = buffer.sample(state, k)
            return None, (sample.batch.obs[..., 0, 0], sample.probabilities, sample.population)

        return jax.lax.scan(one, None, jax.random.split(key, DRAWS))[1]

    numbers, probabilities, population = jax.device_get(many(state, jax.random.PRNGKey(seed)))
    return numbers.astype(int), probabilities, population[0]


@pytest.mark.parametrize("total", [700, 2300], ids=["filling", "overwritten"])
def test_uniform_partitions_draw_only_their_members_uniformly(total):
    capacity = 1000
    buffer = jitted(uniform_buffer(capacity, 64, N, K))
    state, policies = fill(buffer, np.random.default_rng(0), total, 130)  # adds that wrap the ring
    numbers, probabilities, population = draw(buffer, state)
    for g in range(N * K):
        mine = members(policies, capacity, g)
        assert population[g] == len(mine)
        assert np.isin(numbers[:, g], mine).all(), f"group {g} drew outside its partition"
        counts = np.array([np.sum(numbers[:, g] == m) for m in mine])
        assert stats.chisquare(counts).pvalue > 1e-3
        np.testing.assert_allclose(probabilities[:, g], 1.0 / len(mine))


def reference_probabilities(losses: np.ndarray, alpha: float, beta: float) -> np.ndarray:
    """Eq. 12-13 over one partition's losses (ties: average rank; +inf: a new transition)."""
    powered = stats.rankdata(losses, method="average").astype(np.float64) ** alpha
    return (1.0 - beta) * powered / powered.sum() + beta / len(losses)


def test_ranked_partitions_follow_eq_12_13_within_each_partition():
    """Losses written back for every stored transition, then a re-ranking, then fresh ones:
    each group's draws follow the formula over its own partition's ranks."""
    capacity, alpha, beta = 1000, 2.0, 0.1
    buffer = jitted(ranked_buffer(capacity, 256, N, alpha, beta, K))
    rng = np.random.default_rng(1)
    state, policies = fill(buffer, rng, 600, 130)
    losses = np.stack([rng.permutation(np.geomspace(1e-20, 1e20, 600)) for _ in range(N)])  # [N, slots]
    agent = np.arange(N * K) // K
    slots = jnp.asarray(np.broadcast_to(np.arange(600), (N * K, 600)))
    state = buffer.set_priorities(state, slots, jnp.asarray(losses[agent], jnp.float32))
    state = buffer.refresh(state, jnp.bool_(True))
    fresh = rng.integers(0, K, (50, N))
    state = buffer.add(state, numbered(600, fresh))
    policies = np.concatenate([policies, fresh])
    numbers, probabilities, _ = draw(buffer, state)
    now = np.concatenate([losses, np.full((N, 50), np.inf)], axis=1)
    for g in range(N * K):
        mine = members(policies, capacity, g)
        expected = reference_probabilities(now[g // K, mine], alpha, beta)
        assert np.isin(numbers[:, g], mine).all()
        counts = np.array([np.sum(numbers[:, g] == m) for m in mine])
        assert stats.chisquare(counts, expected * counts.sum()).pvalue > 1e-3
        lookup = dict(zip(mine, expected))
        np.testing.assert_allclose(probabilities[:, g].ravel(), [lookup[n] for n in numbers[:, g].ravel()], rtol=1e-4)


def overwritten_reference(losses, policies, group, num_policies, alpha, beta, capacity, ranked_count):
    """The documented rule (``buffers.ranked``), slowly: the probability of each transition
    number ``group``'s draw can return, after ``ranked_count`` transitions were ranked (with
    ``losses``, by number) and more were added since, overwriting the oldest. The ranked
    part keeps each survivor's share of the last refresh (eq. 12-13 within the partition);
    the new ones share the weight of being tied at the top ((M_r + (n + 1) / 2)^alpha each)
    and the shares of the overwritten ones, evenly; beta goes to every live one evenly."""
    total = len(policies)
    agent, k = divmod(group, num_policies)
    members = lambda numbers: numbers[policies[numbers, agent] == k]  # noqa: E731
    ranked, live = members(np.arange(ranked_count)), members(np.arange(total - capacity, total))
    fresh = members(np.arange(ranked_count, total))
    weights = stats.rankdata(losses[ranked], method="average") ** alpha
    rank_share = dict(zip(ranked, weights / weights.sum()))
    stale = sum(share for number, share in rank_share.items() if number < total - capacity)
    top = len(fresh) * (len(ranked) + (len(fresh) + 1) / 2) ** alpha
    to_fresh = top / (top + weights.sum())
    reference = {n: beta / len(live) + (1 - beta) * (1 - to_fresh) * rank_share[n] for n in live if n < ranked_count}
    reference.update(
        {n: beta / len(live) + (1 - beta) * (to_fresh + (1 - to_fresh) * stale) / len(fresh) for n in fresh}
    )
    return reference


@pytest.mark.parametrize("num_policies", [1, K], ids=["plain", "ensemble"])
def test_ranked_draws_after_overwrites_report_their_probabilities(num_policies):
    """A full buffer whose oldest slots were overwritten since the re-ranking: every draw
    comes from the group's live partition, the draws follow the probabilities reported
    (the exact probability of the draw as made, which importance weights rely on), and those
    are the documented rule's (:func:`overwritten_reference`)."""
    capacity = 500
    buffer = jitted(ranked_buffer(capacity, 256, N, 1.5, 0.2, num_policies))
    rng = np.random.default_rng(2)
    policies = rng.integers(0, num_policies, (700, N))
    state = buffer.init(jax.tree.map(lambda x: x[0], numbered(0, policies[:1])))
    state = buffer.add(state, numbered(0, policies[:500]))
    groups = N * num_policies
    losses = rng.permutation(np.geomspace(1e-10, 1e10, 500))
    slots = jnp.asarray(np.broadcast_to(np.arange(500), (groups, 500)))
    state = buffer.set_priorities(state, slots, jnp.asarray(np.broadcast_to(losses, (groups, 500)), jnp.float32))
    state = buffer.refresh(state, jnp.bool_(True))
    state = buffer.add(state, numbered(500, policies[500:]))  # overwrites the 200 oldest
    numbers, probabilities, _ = draw(buffer, state)
    for g in range(groups):
        mine = members(policies, capacity, g) if num_policies > 1 else np.arange(200, 700)
        assert np.isin(numbers[:, g], mine).all()
        drawn, p = numbers[:, g].ravel(), probabilities[:, g].ravel()
        unique, first, inverse = np.unique(drawn, return_index=True, return_inverse=True)
        np.testing.assert_allclose(p, p[first][inverse], rtol=1e-5, err_msg="one transition, two probabilities")
        reported = dict(zip(unique.tolist(), p[first]))
        unseen = 1.0 - sum(reported.values())
        assert unseen >= -1e-4, "the reported probabilities sum to more than one"
        want = overwritten_reference(losses, policies, g, num_policies, 1.5, 0.2, capacity, 500)
        assert sum(want.values()) == pytest.approx(1.0) and set(reported) <= set(want)
        np.testing.assert_allclose([reported[n] for n in reported], [want[n] for n in reported], rtol=1e-3)
        counts = np.array([np.sum(numbers[:, g] == n) for n in reported])
        expected = np.array(list(reported.values()), np.float64)
        if unseen > 1e-6:  # transitions never drawn: one bin of count 0
            counts, expected = np.append(counts, 0), np.append(expected, unseen)
        assert stats.chisquare(counts, expected / expected.sum() * counts.sum()).pvalue > 1e-3
    weights = importance_weights(buffer.sample(state, jax.random.PRNGKey(3)))
    assert np.asarray(weights).max() == pytest.approx(1.0)


def test_a_group_without_transitions_gets_zero_weights_not_nan():
    """With beta 0 a sub-policy that has no transitions yet draws a placeholder of probability
    0 (no uniform share to fall back on): its importance weight would be inf, and inf / inf
    made the agent's whole critic loss NaN. The update weighs such a group 0; the others keep
    their importance weights."""
    buffer = jitted(ranked_buffer(64, 16, N, 0.7, 0.0, K, reading="schaul"))
    only_first = np.zeros((20, N), np.int64)  # every agent acted with sub-policy 0 only
    state = buffer.add(buffer.init(jax.tree.map(lambda x: x[0], numbered(0, only_first[:1]))), numbered(0, only_first))
    state = buffer.refresh(state, jnp.bool_(True))
    sample = buffer.sample(state, jax.random.PRNGKey(0))
    empty = np.asarray(sample.population) == 0
    assert empty.sum() == N * (K - 1)
    assert not np.isfinite(np.asarray(importance_weights(sample, 0.5))[empty]).all()  # what the update met
    weights = np.asarray(update_weights(sample, 0.5))
    assert (weights[empty] == 0).all()
    np.testing.assert_array_equal(weights[~empty], np.asarray(importance_weights(sample, 0.5))[~empty])
    uniform = np.asarray(update_weights(sample, None))
    np.testing.assert_array_equal(uniform, np.broadcast_to(np.where(empty, 0.0, 1.0)[:, None], uniform.shape))


@pytest.fixture(scope="module")
def ensemble_run(tiny_config, tmp_path_factory):
    """A tiny run with two sub-policies per agent, inferred policies and the ranked replay."""
    config = with_options(tiny_config, dict(replay="ranked", refresh_every=10, ensemble=2, infer_policies=True))
    out = tmp_path_factory.mktemp("ensemble")
    return train(config, out=out, progress=False)


def test_every_sub_policy_learns(ensemble_run):
    """Each agent's sub-policies all moved away from their initial networks (each got batches
    from its own partition), and by different amounts (they learn apart)."""
    config = ensemble_run.config
    params = validate(config)
    start = offpolicy.init(offpolicy.configure(config, params), params, config.seed).learner.actor
    moved = np.max(
        [
            np.abs(a - b).max(axis=tuple(range(2, a.ndim)))
            for a, b in zip(jax.tree.leaves(ensemble_run.learner.actor), jax.tree.leaves(start))
        ],
        axis=0,
    )
    assert moved.shape == (config.seeds, 2 * 2)
    assert moved.min() > 1e-2, moved
    assert len(np.unique(np.round(moved, 6))) == moved.size


@pytest.mark.parametrize(
    "added, window, expected", [(70, 10, range(60, 70)), (30, 50, range(0, 30)), (130, 50, range(80, 130))]
)
def test_recent_batches_come_uniformly_from_the_newest_window(added, window, expected):
    """The batches the approximations fit: the newest ``window`` transitions (all stored ones if
    fewer), each equally likely, also after the ring wrapped (capacity 50)."""
    buffer = jitted(uniform_buffer(50, 8, N))
    state = buffer.init(jax.tree.map(lambda x: x[0], transitions(0, 1)))
    for start in range(0, added, 10):
        state = buffer.add(state, transitions(start, 10))
    draw = jax.jit(lambda key: gather(state, recent_indices(state, key, window, 400)).obs[:, 0, 0])
    numbers = np.concatenate([np.asarray(draw(jax.random.PRNGKey(seed))) for seed in range(5)]).astype(int)
    counts = np.bincount(numbers - expected.start, minlength=len(expected))
    assert set(numbers) == set(expected) and len(counts) == len(expected)
    assert stats.chisquare(counts).pvalue > 1e-3


def test_the_inferred_policies_learn_the_other_agents(tiny_config):
    """The approximations' loss (negative log-likelihood of the others' replayed actions minus
    the entropy bonus) falls to well under half of what the first updates see, for every seed;
    the error against the others' current actions is logged and finite."""
    config = dataclasses.replace(
        tiny_config, update_every=5, learner=dataclasses.replace(tiny_config.learner, infer_policies=True)
    )
    result = train(config, progress=False)
    for seed in range(config.seeds):
        rows = [r for r in result.metrics if r["seed"] == seed and r["critic_loss"] > 0]
        assert len(rows) >= 3 and all(np.isfinite(r["infer_error"]) and r["infer_error"] > 0 for r in rows)
        assert rows[-1]["infer_loss"] < 0.5 * rows[0]["infer_loss"], [r["infer_loss"] for r in rows]


def test_the_approximations_learn_what_each_other_agent_does_in_each_state():
    """Eq. 7 on its own: agent 0 fits its approximations to three other agents acting by fixed
    policies of their own (``tanh`` of a random linear map of their observations). The means
    come to explain nearly all of each agent's actions (where a constant, e.g. a log-std that
    only shrank, explains none), the std shrinks towards the small error left, and agent 0's
    approximation of itself is never moved."""
    from roverswarm.algos.inference import approx_actions, fit_approximations, gaussian_policies

    n, obs_size, batch, hidden = 4, 6, 256, (32,)
    optimizer = optax.adam(1e-2)
    keys = jax.random.split(jax.random.PRNGKey(0), n + 1)
    approx = jax.vmap(lambda k: gaussian_policies(hidden).init(k, jnp.zeros((1, obs_size))))(keys[:n])
    maps = jax.random.normal(keys[n], (n, obs_size, 2)) / np.sqrt(obs_size)  # each agent's own policy

    def data(key):
        obs = jax.random.normal(key, (batch, n, obs_size))
        actions = jnp.tanh(jnp.einsum("bno,noa->bna", obs, maps))
        return Transition(obs=obs, actions=actions, rewards=None, next_obs=None, terminated=None)

    @jax.jit
    def fit(approx, approx_opt, key):
        batch = data(key)
        approx, approx_opt, loss = fit_approximations(hidden, optimizer, 1e-3, approx, approx_opt, jnp.int32(0), batch)
        return approx, approx_opt, loss

    approx_opt, first = jax.vmap(optimizer.init)(approx), approx
    for step in range(400):
        approx, approx_opt, loss = fit(approx, approx_opt, jax.random.PRNGKey(step + 1))
    test = data(jax.random.PRNGKey(10_000))
    mean, log_std = approx_actions(hidden, approx, test.obs)  # [B, N, A]
    error = np.square(np.asarray(mean - test.actions)).mean(axis=(0, 2))
    spread = np.asarray(test.actions).var(axis=0).mean(-1)
    assert (error[1:] < 0.05 * spread[1:]).all(), (error, spread)  # R^2 above 0.95 for every other agent
    assert (np.asarray(log_std)[:, 1:] < -1.5).all()  # from 0: std under a quarter of where it started
    for got, start in zip(jax.tree.leaves(approx), jax.tree.leaves(first)):
        np.testing.assert_array_equal(got[0], start[0])


def test_ensemble_run_resumes_to_the_same_numbers(ensemble_run, tmp_path, signal_at_chunk):
    """Ctrl-C mid-run (partitions, sub-policies, approximations and ranks checkpointed), resume."""
    disarm = signal_at_chunk(signal.SIGINT)
    with pytest.raises(RunStopped, match="interrupted at episode 200"):
        train(ensemble_run.config, out=tmp_path, progress=False)
    disarm()
    resumed = train(ensemble_run.config, out=tmp_path, resume=True, progress=False)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]  # noqa: E731
    assert strip(resumed.metrics) == strip(ensemble_run.metrics)


def test_a_checkpoint_from_before_the_approximations_targets_loads(ensemble_run, tmp_path):
    """A run trained before the inferred policies had targets (its checkpoint holds no
    ``target_approx``) loads with the targets equal to the approximations, as a fresh run
    starts them, and evaluates as before."""
    old = tmp_path / "old"
    shutil.copytree(ensemble_run.out, old)
    with np.load(old / CHECKPOINT) as data:
        arrays = {k: data[k] for k in data.files if "/target_approx/" not in k}
    assert any("/approx/" in k for k in arrays)
    np.savez(old / CHECKPOINT, **arrays)
    learner = Run(old).learner
    assert jax.tree.structure(learner.target_approx) == jax.tree.structure(learner.approx)
    for target, approx in zip(jax.tree.leaves(learner.target_approx), jax.tree.leaves(learner.approx)):
        np.testing.assert_array_equal(target, approx)
    new = Run(ensemble_run.out).learner  # trained with targets: they lag the approximations
    assert any(np.abs(t - a).max() > 0 for t, a in zip(jax.tree.leaves(new.target_approx), jax.tree.leaves(new.approx)))
    rewards = [[r["episode_reward"] for r in evaluate_run(run, episodes=40)] for run in (old, ensemble_run.out)]
    assert rewards[0] == rewards[1]


def test_evaluation_runs_random_draws_or_each_sub_policy(ensemble_run, capsys):
    drawn = evaluate_run(ensemble_run.out, episodes=40)
    assert [r["policy"] for r in drawn][2:] == [
        "maddpg seed 0, random sub-policies",
        "maddpg seed 1, random sub-policies",
    ]
    each = evaluate_run(ensemble_run.out, episodes=40, sub_policies="each")
    names = [r["policy"] for r in each][2:]
    assert names == [f"maddpg seed {s}, sub-policy {k}" for s in range(2) for k in range(2)]
    rewards = {r["policy"]: r["episode_reward"] for r in each}
    assert rewards["maddpg seed 0, sub-policy 0"] != rewards["maddpg seed 0, sub-policy 1"]
    assert main(["evaluate", str(ensemble_run.out), "--episodes", "40", "--sub-policies", "each"]) == 0
    assert "sub-policy 1" in capsys.readouterr().out


def test_each_sub_policy_of_a_run_without_ensembles_is_refused(tiny_config):
    """``--sub-policies each`` on a run with one policy per agent would evaluate the same
    policies as ``random``: refused, not run under another name."""
    with pytest.raises(UserError, match=r"^--sub-policies each needs a run trained with --ensemble K > 1"):
        Run.of(tiny_config, learner=None).policies("each")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--ensemble", "0"], "--ensemble must be >= 1 (sub-policies per agent), got 0"),
        (["--infer-policies", "--infer-entropy", "-0.1"], "--infer-entropy must be >= 0, got -0.1"),
        (["--algo", "ddpg", "--infer-policies"], "--infer-policies needs --algo maddpg"),
        (["--infer-policies", "--infer-window", "0"], "--infer-window must be >= 1 transition, got 0"),
    ],
)
def test_bad_ensemble_or_inference_input_is_one_line_and_exit_2(argv, message, capsys, tmp_path):
    assert main(["train", *argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def _observations(params, episodes: int = 6):
    """States and observations [E, N, O] of ``episodes`` fresh layouts."""
    obs, states = jax.vmap(lambda k: reset(k, params))(jax.random.split(jax.random.PRNGKey(3), episodes))
    return obs, states


def test_other_seeds_partners_take_agent_i_from_seed_s_plus_i(ensemble_run, capsys):
    """``--partners other-seeds``: in seed s's swarm agent i acts as agent i of seed (s + i) mod S,
    every sub-policy included: compared with the actors' rows mixed by a slow loop and run
    through the learner's own act; a one-seed run is refused."""
    config, learner = ensemble_run.config, ensemble_run.learner
    params, k = validate(config), config.learner.ensemble
    policies = Run.of(config, learner).policies(partners="other-seeds")
    assert [p.name for p in policies] == [
        "maddpg agents of seeds 0/1, random sub-policies",
        "maddpg agents of seeds 1/0, random sub-policies",
    ]
    obs, states = _observations(params)
    plan = np.random.default_rng(0).integers(0, k, obs.shape[:2]).astype(np.int32)
    for s, policy in enumerate(policies):
        mixed = jax.tree.map(
            lambda x: np.stack([np.asarray(x)[(s + row // k) % config.seeds, row] for row in range(x.shape[1])]),
            learner.actor,
        )
        got = jax.vmap(policy.act, in_axes=(None, 0, 0, 0, None, None))(
            jax.random.PRNGKey(0), obs, states, plan, policy.weights, params
        )
        np.testing.assert_allclose(got, act(config.learner, mixed, obs, plan), rtol=1e-6, atol=1e-7)
    one_seed = jax.tree.map(lambda x: x[:1], learner)
    with pytest.raises(UserError, match="--partners other-seeds needs a run trained with --seeds >= 2, this one has 1"):
        Run.of(dataclasses.replace(config, seeds=1), one_seed).policies(partners="other-seeds")
    assert main(["evaluate", str(ensemble_run.out), "--episodes", "40", "--partners", "other-seeds"]) == 0
    assert "agents of seeds 1/0" in capsys.readouterr().out


def test_other_seeds_partners_of_a_shared_network_with_normalised_observations(tiny_config):
    """A shared actor with observation normalisation (untrained, with a different normaliser
    per seed): rover i of seed s's mixed swarm acts as seed (s + i) mod 3's network does for
    rover i (its id, its normaliser), by a loop over the rovers of the plain per-seed act."""
    config = with_options(tiny_config, dict(scenario="paper-3", seeds=3, share_parameters=True, normalize_obs=True))
    params = validate(config)
    sizes = (params.num_rovers, observation_size(params))
    learner = jax.vmap(lambda key: init_learner(key, config.learner, *sizes))(
        jax.random.split(jax.random.PRNGKey(1), 3)
    )
    rng = np.random.default_rng(1)
    norm = learner.obs_norm.replace(
        mean=jnp.asarray(rng.normal(size=learner.obs_norm.mean.shape), jnp.float32),
        var=jnp.asarray(rng.uniform(0.5, 2.0, size=learner.obs_norm.var.shape), jnp.float32),
    )
    learner = learner.replace(obs_norm=norm)
    policies = Run.of(config, learner).policies(partners="other-seeds")
    assert [p.name for p in policies] == [f"maddpg agents of seeds {s}/{(s + 1) % 3}/{(s + 2) % 3}" for s in range(3)]
    obs, states = _observations(params)
    pick = lambda tree, s: jax.tree.map(lambda x: x[s], tree)  # noqa: E731
    for s, policy in enumerate(policies):
        got = jax.vmap(policy.act, in_axes=(None, 0, 0, None, None, None))(
            jax.random.PRNGKey(0), obs, states, None, policy.weights, params
        )
        for i in range(params.num_rovers):
            seed = (s + i) % 3
            own = act(config.learner, pick(learner.actor, seed), obs, obs_norm=pick(norm, seed))
            np.testing.assert_allclose(got[:, i], own[:, i], rtol=1e-6, atol=1e-7)
        assert not np.allclose(got, act(config.learner, pick(learner.actor, s), obs, obs_norm=pick(norm, s)))
