"""The experience sample optimizer against a slow NumPy computation of the paper's eq. 12-13."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from roverswarm.buffers.base import Buffer, Transition, importance_weights
from roverswarm.buffers.ranked import _running_sums, ranked_buffer
from roverswarm.buffers.uniform import uniform_buffer

N = 2  # agents: each ranks by its own losses
DRAWS = 400  # batches per check


def reference_probabilities(losses: np.ndarray, alpha: float, beta: float, reading: str = "paper") -> np.ndarray:
    """Eq. 12-13, normalised: P(i) = (1 - beta) w_i / sum_j w_j + beta / M. ``paper``:
    w_i = p_i^alpha with p_i the ascending rank of loss i (ties: average rank; +inf is a new,
    unranked transition, so it ties at the top). ``schaul`` (Schaul et al.'s rank-based
    replay): w_i = d_i^-alpha with d_i the descending rank among the ranked (finite) losses,
    and for each of the n new ones that of their average rank among themselves at the top,
    ((n + 1) / 2)^-alpha; ``rerank``: after a refresh, every loss ranked together (the new ones
    tied at the top, the others below them)."""
    if reading == "paper":
        powered = stats.rankdata(losses, method="average").astype(np.float64) ** alpha
    elif reading == "rerank":
        powered = stats.rankdata(-losses, method="average").astype(np.float64) ** -alpha
    else:
        ranked = np.isfinite(losses)
        descending = stats.rankdata(-losses[ranked], method="average").astype(np.float64)
        powered = np.full(len(losses), ((len(losses) - ranked.sum() + 1) / 2) ** -alpha)
        powered[ranked] = descending**-alpha
    return (1.0 - beta) * powered / powered.sum() + beta / len(losses)


def jitted(buffer: Buffer) -> Buffer:
    """``buffer`` with its functions jitted, as training runs them: one program each instead of
    hundreds of operations run (and prepared) one by one."""
    names = ("init", "add", "draw", "set_priorities", "refresh")
    return dataclasses.replace(buffer, **{name: jax.jit(getattr(buffer, name)) for name in names})


def transitions(first: int, count: int, policy: np.ndarray | None = None) -> Transition:
    """``count`` transitions whose observations hold their number ``first``, ``first + 1``, ...;
    with ``policy`` [count, N], the sub-policy each agent ran (policy ensembles)."""
    number = jnp.arange(first, first + count, dtype=jnp.float32)
    return Transition(
        obs=jnp.broadcast_to(number[:, None, None], (count, N, 1)),
        actions=jnp.zeros((count, N, 2)),
        rewards=jnp.zeros((count, N)),
        next_obs=jnp.zeros((count, N, 1)),
        terminated=jnp.zeros(count, bool),
        policy=None if policy is None else jnp.asarray(policy, jnp.int32),
    )


def filled(capacity: int, batch_size: int, stored: int, alpha: float, beta: float, reading: str = "paper"):
    """A ranked buffer of ``capacity`` holding ``stored`` transitions (slot i holds number i)."""
    buffer = jitted(ranked_buffer(capacity, batch_size, N, alpha, beta, reading=reading))
    example = jax.tree.map(lambda x: x[0], transitions(0, 1))
    return buffer, buffer.add(buffer.init(example), transitions(0, stored))


def with_losses(buffer, state, losses: np.ndarray):
    """Write per-agent ``losses`` [N, M] for slots 0..M-1 back, then re-rank."""
    indices = jnp.broadcast_to(jnp.arange(losses.shape[1]), losses.shape)
    state = buffer.set_priorities(state, indices, jnp.asarray(losses, jnp.float32))
    return buffer.refresh(state, jnp.bool_(True))


def draw(buffer, state, seed: int = 0):
    """DRAWS batches: indices and probabilities [DRAWS, N, B]; checks the batch holds those slots."""

    @jax.jit
    def many(state, key):
        def one(_, k):
            sample = buffer.sample(state, k)
            return None, (sample.indices, sample.probabilities, sample.batch.obs)

        return jax.lax.scan(one, None, jax.random.split(key, DRAWS))[1]

    indices, probabilities, obs = jax.device_get(many(state, jax.random.PRNGKey(seed)))
    np.testing.assert_array_equal(obs[..., 0, 0], indices)  # agent 0's obs column holds the slot
    return indices, probabilities


def assert_matches(indices: np.ndarray, probabilities: np.ndarray, expected: np.ndarray):
    """The draws of every agent follow ``expected`` [N, M] (chi-squared), and each draw reports
    its probability under ``expected``."""
    for agent in range(N):
        counts = np.bincount(indices[:, agent].ravel(), minlength=expected.shape[1])
        assert len(counts) == expected.shape[1], "drew a slot that holds no transition"
        result = stats.chisquare(counts, expected[agent] * counts.sum())
        assert result.pvalue > 1e-3, (agent, result)
        np.testing.assert_allclose(probabilities[:, agent], expected[agent][indices[:, agent]], rtol=1e-4)


def distinct_losses(rng, stored: int) -> np.ndarray:
    """[N, stored] losses, a different order for each agent, each more than a loss bin (~1%)
    apart from the next for up to 5000 transitions, so all ranks are distinct."""
    return np.stack([rng.permutation(np.geomspace(1e-30, 1e30, stored)) for _ in range(N)])


@pytest.mark.parametrize("alpha, beta", [(1.0, 0.0), (2.0, 0.1), (0.5, 0.5), (3.0, 0.2), (0.0, 0.3), (2.0, 1.0)])
def test_sampling_follows_eq_12_13(alpha, beta):
    rng = np.random.default_rng(0)
    buffer, state = filled(capacity=128, batch_size=256, stored=100, alpha=alpha, beta=beta)
    losses = distinct_losses(rng, 100)
    expected = np.stack([reference_probabilities(row, alpha, beta) for row in losses])
    assert_matches(*draw(buffer, with_losses(buffer, state, losses)), expected)
    if alpha == 0.0 or beta == 1.0:
        np.testing.assert_allclose(expected, 1.0 / 100)


@pytest.mark.parametrize("alpha, beta", [(0.7, 0.0), (1.5, 0.1), (0.0, 0.2)])
def test_schaul_sampling_follows_one_over_rank(alpha, beta):
    """The rank-based prioritised replay of Schaul et al.: P ~ rank^-alpha, rank 1 the largest loss."""
    rng = np.random.default_rng(10)
    buffer, state = filled(capacity=128, batch_size=256, stored=100, alpha=alpha, beta=beta, reading="schaul")
    losses = distinct_losses(rng, 100)
    expected = np.stack([reference_probabilities(row, alpha, beta, "schaul") for row in losses])
    assert_matches(*draw(buffer, with_losses(buffer, state, losses)), expected)
    if alpha > 0:  # the largest loss is the most likely draw, far above the average
        assert all(expected[a].argmax() == losses[a].argmax() for a in range(N))
        assert expected[0].max() > 5 / 100


@pytest.mark.parametrize("reading", ["paper", "schaul"])
def test_equal_losses_and_new_transitions_in_each_reading(reading):
    """Ties share their average rank; after an add, the new transitions sit at the top, tied
    above the ranked ones (``paper``; ``schaul``: each with their average rank among
    themselves), and a refresh ranks them so. ``schaul``'s new ones then draw 36% before the
    refresh and 50% after it (the ranked ones' weights are the last refresh's until the next
    one ranks them below the new ones); with weight 1 each they drew 75% before it."""
    rng = np.random.default_rng(11)
    buffer, state = filled(capacity=128, batch_size=256, stored=70, alpha=0.7, beta=0.1, reading=reading)
    losses = np.stack([rng.choice([0.5, 2.0, 8.0, 30.0], size=70) for _ in range(N)])
    state = buffer.add(with_losses(buffer, state, losses), transitions(70, 30))
    now = np.concatenate([losses, np.full((N, 30), np.inf)], axis=1)
    before = np.stack([reference_probabilities(row, 0.7, 0.1, reading) for row in now])
    assert_matches(*draw(buffer, state), before)
    refreshed = "paper" if reading == "paper" else "rerank"
    after = np.stack([reference_probabilities(row, 0.7, 0.1, refreshed) for row in now])
    assert_matches(*draw(buffer, buffer.refresh(state, jnp.bool_(True))), after)  # +inf losses ranked too
    np.testing.assert_allclose(before[:, 70:].sum(-1), after[:, 70:].sum(-1), atol=0.15)


def test_equal_losses_share_their_average_rank():
    rng = np.random.default_rng(1)
    buffer, state = filled(capacity=64, batch_size=256, stored=60, alpha=2.0, beta=0.1)
    losses = np.stack([rng.choice([0.5, 2.0, 8.0, 30.0], size=60) for _ in range(N)])
    expected = np.stack([reference_probabilities(row, 2.0, 0.1) for row in losses])
    assert_matches(*draw(buffer, with_losses(buffer, state, losses)), expected)


def test_many_blocks_partly_filled():
    """Capacity above one 1024-slot block of the sampling table, the last block and the
    buffer both partly filled."""
    rng = np.random.default_rng(2)
    buffer, state = filled(capacity=3000, batch_size=1024, stored=2500, alpha=1.0, beta=0.2)
    losses = distinct_losses(rng, 2500)
    expected = np.stack([reference_probabilities(row, 1.0, 0.2) for row in losses])
    assert_matches(*draw(buffer, with_losses(buffer, state, losses)), expected)


def test_the_tables_running_sums_are_exact_and_never_decrease():
    """A draw descends the table's rows of running sums assuming they never decrease; shares
    of very different scales (and zeros) must keep them so, and match float64 sums."""
    rng = np.random.default_rng(7)
    shares = rng.choice([0.0, 1e-12, 3e-7, 0.1, 1.0], size=(3, 64, 32)) * rng.random((3, 64, 32))
    sums = np.asarray(_running_sums(jnp.asarray(shares, jnp.float32)))
    assert (np.diff(sums, axis=-1) >= 0).all()
    np.testing.assert_allclose(sums, np.cumsum(shares, axis=-1), rtol=1e-6, atol=1e-12)


def test_new_transitions_enter_at_the_top():
    """Added after the last re-ranking, they tie above every ranked transition (loss +inf)."""
    rng = np.random.default_rng(3)
    buffer, state = filled(capacity=128, batch_size=256, stored=80, alpha=2.0, beta=0.1)
    losses = distinct_losses(rng, 80)
    state = with_losses(buffer, state, losses)
    state = buffer.add(state, transitions(80, 20))
    now = np.concatenate([losses, np.full((N, 20), np.inf)], axis=1)
    expected = np.stack([reference_probabilities(row, 2.0, 0.1) for row in now])
    assert_matches(*draw(buffer, state), expected)


def test_a_written_back_huge_loss_is_drawn_far_more_often_after_the_re_ranking():
    rng = np.random.default_rng(4)
    buffer, state = filled(capacity=64, batch_size=256, stored=50, alpha=3.0, beta=0.1)
    losses = distinct_losses(rng, 50)
    state = with_losses(buffer, state, losses)
    before = draw(buffer, state)[0]
    hot = int(np.argmin(losses[0]))  # agent 0's least likely transition becomes its most likely
    state = buffer.set_priorities(state, jnp.full((N, 1), hot), jnp.full((N, 1), 1e36))
    # ranks are lazy: nothing moves until the re-ranking (the trainer relies on it to draw all
    # the batches between two adds at once)
    unchanged = draw(buffer, state)[0]
    np.testing.assert_array_equal(unchanged, before)
    after, probabilities = draw(buffer, buffer.refresh(state, jnp.bool_(True)))
    share = lambda idx: np.mean(idx[:, 0] == hot)  # noqa: E731
    uniform = 1 / 50
    assert share(before) < 0.5 * uniform and share(after) > 3 * uniform
    losses[:, hot] = 1e36
    assert_matches(after, probabilities, np.stack([reference_probabilities(row, 3.0, 0.1) for row in losses]))


def test_importance_weights_match_their_definition():
    rng = np.random.default_rng(5)
    buffer, state = filled(capacity=64, batch_size=32, stored=40, alpha=2.0, beta=0.2)
    losses = distinct_losses(rng, 40)
    state = with_losses(buffer, state, losses)
    sample = buffer.sample(state, jax.random.PRNGKey(9))
    weights = np.asarray(importance_weights(sample))
    for agent in range(N):
        p = reference_probabilities(losses[agent], 2.0, 0.2)[np.asarray(sample.indices[agent])]
        w = 1.0 / (40 * p)  # w_i = (M P(i))^-1, scaled so the batch's largest weight is 1
        np.testing.assert_allclose(weights[agent], w / w.max(), rtol=1e-4)
    assert weights.max() == pytest.approx(1.0)


def test_importance_weights_with_an_exponent_match_their_definition():
    """Schaul et al.'s w_i = (M P(i))^-e / max_j w_j, here with e = 0.5 on the 1/rank reading."""
    rng = np.random.default_rng(12)
    buffer, state = filled(capacity=64, batch_size=32, stored=40, alpha=0.7, beta=0.0, reading="schaul")
    losses = distinct_losses(rng, 40)
    sample = buffer.sample(with_losses(buffer, state, losses), jax.random.PRNGKey(4))
    weights = np.asarray(importance_weights(sample, 0.5))
    for agent in range(N):
        p = reference_probabilities(losses[agent], 0.7, 0.0, "schaul")[np.asarray(sample.indices[agent])]
        w = (40 * p) ** -0.5
        np.testing.assert_allclose(weights[agent], w / w.max(), rtol=1e-4)
    np.testing.assert_allclose(importance_weights(sample, 0.0), 1.0)  # exponent 0: no correction


def test_the_uniform_buffer_weighs_every_sample_equally():
    buffer = jitted(uniform_buffer(64, 32, N))
    state = buffer.add(buffer.init(jax.tree.map(lambda x: x[0], transitions(0, 1))), transitions(0, 40))
    sample = buffer.sample(state, jax.random.PRNGKey(0))
    np.testing.assert_allclose(sample.probabilities, 1 / 40)
    np.testing.assert_allclose(importance_weights(sample), 1.0)


def test_a_steep_alpha_on_a_nearly_empty_buffer_stays_finite():
    """(rank / C)^alpha would underflow to 0 for every transition here; the draw must still
    follow the formula's top ranks and report finite, positive probabilities."""
    rng = np.random.default_rng(6)
    buffer, state = filled(capacity=100_000, batch_size=256, stored=50, alpha=60.0, beta=0.0)
    losses = distinct_losses(rng, 50)
    state = buffer.add(with_losses(buffer, state, losses), transitions(50, 10))
    indices, probabilities = draw(buffer, state)
    now = np.concatenate([losses, np.full((N, 10), np.inf)], axis=1)
    expected = np.stack([reference_probabilities(row, 60.0, 0.0) for row in now])
    assert indices.max() < 60 and np.all(np.isfinite(probabilities)) and np.all(probabilities > 0)
    for agent in range(N):  # the ten fresh transitions tie at the top and take almost everything
        assert np.mean(indices[:, agent] >= 50) == pytest.approx(expected[agent, 50:].sum(), abs=0.01)
        np.testing.assert_allclose(probabilities[:, agent], expected[agent][indices[:, agent]], rtol=1e-3)
