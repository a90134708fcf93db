"""The jitted, agent-vmapped MADDPG/DDPG update agrees with a plain per-agent reference.

The reference below is written independently of ``roverswarm.algos.maddpg``: a Python loop
over agents (no vmap), its own MLP forward pass read straight from the Flax parameter dicts,
its own global-norm clipping and a hand-written first Adam step (optax defaults, zero
moments). On a fixed random batch (some transitions terminated, target networks perturbed
away from the online ones) and for both algorithms (``maddpg``: centralised critic over all
observations and actions; ``ddpg``: the agent's own), with and without importance weights,
it checks

* the per-sample TD loss ``(Q - y)^2`` [N, B], hence the bootstrapped targets y with the
  bootstrap cut on termination;
* the (weighted) critic loss [N] and the actor loss [N];
* the updated critics, actors (actor step taken on the *updated* critic), target critics
  and target actors.

A last test checks that the comparison discriminates: the reference with the actor step on
the old critic, or without cutting the bootstrap at termination, disagrees with the code.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.algos.maddpg import AlgoConfig, init_learner, update
from roverswarm.buffers.uniform import Transition

N, O, A, B = 3, 20, 2, 32
# float32; the loosest entries are Adam steps on gradients of the order of eps, where the
# step lr * g / (|g| + eps) inherits the rounding of g (observed up to ~2e-5)
TOL = dict(atol=1e-5, rtol=1e-4)
ADAM_B1, ADAM_B2, ADAM_EPS = 0.9, 0.999, 1e-8


# ----------------------------------------------------------------------------- reference


def mlp(params, x):
    """Dense layers Dense_0..Dense_k, ReLU on all but the last."""
    layers = params["params"]
    names = sorted(layers, key=lambda name: int(name.split("_")[1]))
    for name in names[:-1]:
        x = jnp.maximum(x @ layers[name]["kernel"] + layers[name]["bias"], 0.0)
    last = layers[names[-1]]
    return x @ last["kernel"] + last["bias"]


def actor(params, obs):
    """(tanh(pre), pre) for observations [B, O]."""
    pre = mlp(params, obs)
    return jnp.tanh(pre), pre


def q_value(algo, params, obs, actions, i):
    """Agent i's Q [B] of observations [B, N, O] and actions [B, N, A]."""
    if algo == "maddpg":
        inputs = jnp.concatenate([obs.reshape(B, N * O), actions.reshape(B, N * A)], axis=1)
    else:
        inputs = jnp.concatenate([obs[:, i], actions[:, i]], axis=1)
    return mlp(params, inputs)[:, 0]


def clip_and_adam(params, grads, clip, lr):
    """Clip ``grads`` to global norm ``clip``, then one Adam step from zero moments (t = 1)."""
    norm = jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(grads)))
    scale = jnp.minimum(1.0, clip / norm)

    def step(p, g):
        g = g * scale
        m_hat = (1 - ADAM_B1) * g / (1 - ADAM_B1)
        v_hat = (1 - ADAM_B2) * g**2 / (1 - ADAM_B2)
        return p - lr * m_hat / (jnp.sqrt(v_hat) + ADAM_EPS)

    return jax.tree.map(step, params, grads)


def reference_update(cfg, state, batch, weights, actor_on_new_critic=True, cut_bootstrap=True):
    """Every agent's update, one agent at a time; results stacked on a leading [N] axis."""
    agent = lambda tree, i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
    soft = lambda target, online: jax.tree.map(lambda t, o: (1 - cfg.tau) * t + cfg.tau * o, target, online)  # noqa: E731
    results = []
    for i in range(N):
        obs, actions, rewards = batch.obs[i], batch.actions[i], batch.rewards[i]
        next_obs, terminated = batch.next_obs[i], batch.terminated[i]
        w = jnp.ones(B) if weights is None else weights[i]

        next_actions = jnp.stack([actor(agent(state.target_actor, j), next_obs[:, j])[0] for j in range(N)], axis=1)
        not_done = 1.0 - terminated.astype(jnp.float32) if cut_bootstrap else 1.0
        y = rewards[:, i] + cfg.gamma * not_done * q_value(cfg.algo, agent(state.target_critic, i), next_obs, next_actions, i)

        def td_loss(critic_params):
            return (q_value(cfg.algo, critic_params, obs, actions, i) - y) ** 2

        old_critic = agent(state.critic, i)
        critic_grads = jax.grad(lambda p: jnp.mean(w * td_loss(p)))(old_critic)
        critic = clip_and_adam(old_critic, critic_grads, cfg.grad_clip, cfg.critic_lr)
        judge = critic if actor_on_new_critic else old_critic

        def actor_loss(actor_params):
            own, pre = actor(actor_params, obs[:, i])
            joint = jnp.concatenate([actions[:, :i], own[:, None], actions[:, i + 1 :]], axis=1)
            return -jnp.mean(q_value(cfg.algo, judge, obs, joint, i)) + cfg.action_penalty * jnp.mean(pre**2)

        old_actor = agent(state.actor, i)
        new_actor = clip_and_adam(old_actor, jax.grad(actor_loss)(old_actor), cfg.grad_clip, cfg.actor_lr)
        results.append(
            dict(
                td_loss=td_loss(old_critic),
                critic_loss=jnp.mean(w * td_loss(old_critic)),
                actor_loss=actor_loss(old_actor),
                critic=critic,
                actor=new_actor,
                target_critic=soft(agent(state.target_critic, i), critic),
                target_actor=soft(agent(state.target_actor, i), new_actor),
            )
        )
    return jax.tree.map(lambda *xs: jnp.stack(xs), *results)


# ----------------------------------------------------------------------------- fixtures


def perturbed(tree, rng):
    return jax.tree.map(lambda x: x + 0.1 * rng.standard_normal(x.shape).astype(np.float32), tree)


@pytest.fixture(scope="module", params=[(algo, weighted) for algo in ("maddpg", "ddpg") for weighted in (False, True)], ids=lambda p: f"{p[0]}-{'weighted' if p[1] else 'unweighted'}")
def case(request):
    """(config, state, batch, weights, code's new state, code's info, reference results)."""
    algo, weighted = request.param
    # pinned (not the defaults): float32 agreement was established at these widths and rates
    cfg = AlgoConfig(algo=algo, actor_lr=1e-2, critic_lr=1e-2, hidden=(64, 64))
    rng = np.random.default_rng(0)
    state = init_learner(jax.random.PRNGKey(0), cfg, N, O)
    state = state.replace(target_actor=perturbed(state.target_actor, rng), target_critic=perturbed(state.target_critic, rng))
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    batch = Transition(
        obs=f32(rng.standard_normal((N, B, N, O))),
        actions=f32(rng.uniform(-1, 1, (N, B, N, A))),
        rewards=f32(rng.standard_normal((N, B, N))),
        next_obs=f32(rng.standard_normal((N, B, N, O))),
        terminated=jnp.asarray(rng.random((N, B)) < 0.3),
    )
    assert 0 < int(batch.terminated.sum()) < N * B
    weights = f32(rng.uniform(0.1, 2.0, (N, B))) if weighted else None
    new_state, info = jax.jit(update, static_argnums=0)(cfg, state, batch, weights)
    return cfg, state, batch, weights, new_state, info, reference_update(cfg, state, batch, weights)


# ----------------------------------------------------------------------------- tests


def test_td_loss_matches_reference(case):
    *_, info, ref = case
    assert info["td_loss"].shape == (N, B)
    np.testing.assert_allclose(info["td_loss"], ref["td_loss"], **TOL)


def test_critic_and_actor_losses_match_reference(case):
    *_, info, ref = case
    assert info["critic_loss"].shape == (N,)
    np.testing.assert_allclose(info["critic_loss"], ref["critic_loss"], **TOL)
    np.testing.assert_allclose(info["actor_loss"], ref["actor_loss"], **TOL)


@pytest.mark.parametrize("network", ["critic", "actor", "target_critic", "target_actor"])
def test_updated_parameters_match_reference(case, network):
    _, state, *_, new_state, _, ref = case
    moved = jax.tree.map(lambda new, old: np.abs(new - old).max(), getattr(new_state, network), getattr(state, network))
    assert max(jax.tree.leaves(moved)) > 1e-4  # the update did change this network
    jax.tree.map(lambda got, want: np.testing.assert_allclose(got, want, **TOL), getattr(new_state, network), ref[network])


@pytest.mark.parametrize("variant", [dict(actor_on_new_critic=False), dict(cut_bootstrap=False)], ids=["actor_on_old_critic", "no_bootstrap_cut"])
def test_reference_variants_are_caught(case, variant):
    cfg, state, batch, weights, new_state, info, _ = case
    wrong = reference_update(cfg, state, batch, weights, **variant)
    got = info["td_loss"] if "cut_bootstrap" in variant else new_state.actor
    want = wrong["td_loss"] if "cut_bootstrap" in variant else wrong["actor"]
    gap = max(jax.tree.leaves(jax.tree.map(lambda g, w: np.abs(g - w).max(), got, want)))
    assert gap > 1e-3, variant
