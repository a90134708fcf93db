"""The jitted, agent-vmapped MADDPG/DDPG update agrees with a plain per-agent reference.

The reference below is written independently of ``roverswarm.algos.maddpg``: a Python loop
over agents (no vmap), its own MLP forward pass read straight from the Flax parameter dicts,
its own global-norm clipping and a hand-written Adam step (optax defaults) from the moments
of one earlier update. On a fixed random batch (some transitions terminated, target networks perturbed
away from the online ones) and for both algorithms (``maddpg``: centralised critic over all
observations and actions; ``ddpg``: the agent's own), with and without importance weights,
with policy ensembles (K sub-policies, one batch per partition, eq. 9-11) and inferred
policies (eq. 7-8), it checks

* the per-sample TD loss ``(Q - y)^2`` [N * K, B], hence the bootstrapped targets y with the
  bootstrap cut on termination, the target sub-policy each agent ran in the transition, and
  (inferred policies) the other agents' target approximations (eq. 8's primes) instead of
  their target actors;
* the (weighted) critic loss [N] and the actor loss [N];
* the updated critics, actors (each sub-policy on its own batch, on the *updated* critic),
  target critics, target actors, approximations and their targets (one step on the Gaussian negative
  log-likelihood minus lambda times the entropy, on the separate batch of recent transitions;
  an agent's approximation of itself unused).

K = 1 without inference is plain MADDPG: the same reference, the same code path.

The swarm options are in the same reference: twin critics (the smaller target estimate, both
critics fit it, the first one's TD loss reported), target-policy smoothing (clipped Gaussian
noise on every target action, drawn from the update's key as the code splits it: one key per
agent), layer norm (written out here from the LayerNorm parameters), observation
standardisation by a given running mean and variance and reward scaling (applied to the
batch first), and shared parameters (one actor and critic with the agent's one-hot index,
the critic's view ordered own-first, every agent's losses averaged into one Adam step), and
the critic over the nearest C other rovers (``critic_neighbors``: the order computed one
transition at a time, C = 1 and C = 2, so both the choice and the order of the neighbours
count).
Variants without the smoothing, with the larger twin estimate, with the shared critic's
view in global order or with the neighbours taken by index disagree with the code; a delayed
actor update leaves the actor and the targets alone on the off steps.
The last tests check that the comparison discriminates: the reference with the actor step
on the old critic, without cutting the bootstrap at termination, with the true target
policies in place of the approximations, with the online approximations in place of their
targets, with the approximations fitted on the agent's own
sample instead of the recent transitions, or with sub-policy 0 for every agent in the
target, disagrees with the code.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.algos.learner import AlgoConfig, init_learner, observe_batch
from roverswarm.algos.maddpg import inference_error, update
from roverswarm.algos.normalize import ObsNorm
from roverswarm.buffers.base import Transition

N, O, A, B = 3, 20, 2, 32
# float32; the loosest entries are Adam steps on gradients of the order of eps, where the
# step lr * g / (|g| + eps) inherits the rounding of g (observed up to ~2e-5)
TOL = dict(atol=1e-5, rtol=1e-4)
# updated parameters: an Adam step moves each one by up to about lr = 1e-2, by
# lr * m / (sqrt(v) + eps), so where the gradients are near eps it inherits their float32
# rounding (measured from zero moments: a handful of the ensembles' ~1e5 parameters by up to
# ~4e-4, 4% of a step, and one entry with |g| below eps, 3e-9 against 1e-8, by a quarter of a
# step); a real error moves many


def assert_parameters_close(got, want):
    """Over a whole network (all its leaves together: a small bias leaf of 192 entries may hold
    the one near-eps entry), all but 1 in 10^3 entries within TOL, all but 1 in 10^4 within 10%
    of an Adam step, and every entry within one step."""
    got = np.concatenate([np.ravel(x) for x in jax.tree.leaves(got)])
    want = np.concatenate([np.ravel(x) for x in jax.tree.leaves(want)])
    off, gap = ~np.isclose(got, want, **TOL), np.abs(got - want)
    assert off.mean() <= 1e-3 and (gap > 1e-3).mean() <= 1e-4 and gap.max() < 1e-2, (off.sum(), np.sort(gap)[-3:])


ADAM_B1, ADAM_B2, ADAM_EPS = 0.9, 0.999, 1e-8

KEY = jax.random.PRNGKey(7)  # the update's key (target-policy smoothing noise)
# fresh networks in one compiled program (op by op, each case's shapes cost dozens of compilations)
fresh_learner = jax.jit(init_learner, static_argnums=(1, 2, 3))
_rng = np.random.default_rng(1)
RECENT = Transition(  # the recent transitions the approximations fit (a batch of 24, not B)
    obs=jnp.asarray(_rng.standard_normal((24, N, O)), jnp.float32),
    actions=jnp.asarray(_rng.uniform(-1, 1, (24, N, A)), jnp.float32),
    rewards=jnp.zeros((24, N)),
    next_obs=jnp.zeros((24, N, O)),
    terminated=jnp.zeros(24, bool),
)


# ----------------------------------------------------------------------------- reference


LAYER_NORM_EPS = 1e-6  # flax.linen.LayerNorm's default


def mlp(params, x, layer_norm=False):
    """Dense layers Dense_0..Dense_k, ReLU on all but the last; with ``layer_norm``,
    LayerNorm_j (x - mean) / sqrt(var + eps) * scale + bias after Dense_j, before its ReLU."""
    layers = params["params"]
    names = sorted((n for n in layers if n.startswith("Dense_")), key=lambda name: int(name.split("_")[1]))
    for j, name in enumerate(names[:-1]):
        x = x @ layers[name]["kernel"] + layers[name]["bias"]
        if layer_norm:
            norm = layers[f"LayerNorm_{j}"]
            mean = x.mean(-1, keepdims=True)
            var = jnp.square(x - mean).mean(-1, keepdims=True)
            x = (x - mean) / jnp.sqrt(var + LAYER_NORM_EPS) * norm["scale"] + norm["bias"]
        x = jnp.maximum(x, 0.0)
    last = layers[names[-1]]
    return x @ last["kernel"] + last["bias"]


def one_hot(i, rows):
    """[rows, N] copies of agent i's one-hot index."""
    return jnp.broadcast_to(jnp.eye(N)[i], (rows, N))


def actor(params, obs, cfg=None, i=None):
    """(tanh(pre), pre) for observations [B, O] (of agent i: its one-hot index appended if shared)."""
    if cfg is not None and cfg.share_parameters:
        obs = jnp.concatenate([obs, one_hot(i, len(obs))], axis=1)
    pre = mlp(params, obs, cfg is not None and cfg.layer_norm)
    return jnp.tanh(pre), pre


def nearest_rows(cfg, obs, actions, i, by_index=False):
    """Critic inputs [B, (1 + K) * (O + A)] of --critic-neighbors K, one transition at a time:
    agent i, then the K other rovers nearest to it (positions at entries 2-3 of each rover's
    observation; ties to the lower index), or with ``by_index`` the first K others by index."""
    orders = []
    for o in np.asarray(obs):  # the order from the positions; actions may be traced (actor loss)
        others = [j for j in range(N) if j != i]
        if not by_index:
            others.sort(key=lambda j: (float(np.sum((o[j, 2:4] - o[i, 2:4]) ** 2)), j))
        orders.append([i] + others[: cfg.critic_neighbors])
    rows = np.arange(len(orders))[:, None]  # each transition's rovers in its order, gathered at once
    chosen = lambda x: x[rows, np.array(orders)].reshape(len(orders), -1)  # noqa: E731
    return jnp.concatenate([chosen(obs), chosen(actions)], axis=1)


def q_values(cfg, params, obs, actions, i, global_order=False):
    """Agent i's Q [B] of observations [B, N, O] and actions [B, N, A], one per critic (two if twin).
    ``global_order``: the wrong views the tests must catch (others in index order)."""
    rows = len(obs)
    if cfg.algo == "maddpg" and cfg.critic_neighbors:
        inputs = nearest_rows(cfg, obs, actions, i, by_index=global_order)
    elif cfg.algo == "maddpg":
        order = [i] + [j for j in range(N) if j != i] if cfg.share_parameters and not global_order else list(range(N))
        inputs = jnp.concatenate([obs[:, order].reshape(rows, N * O), actions[:, order].reshape(rows, N * A)], axis=1)
    else:
        inputs = jnp.concatenate([obs[:, i], actions[:, i]], axis=1)
    if cfg.share_parameters:
        inputs = jnp.concatenate([inputs, one_hot(i, rows)], axis=1)
    critics = [jax.tree.map(lambda x: x[c], params) for c in range(2)] if cfg.twin_critics else [params]
    return [mlp(p, inputs, cfg.layer_norm)[:, 0] for p in critics]


def q_value(algo, params, obs, actions, i):
    """Agent i's Q [B] of a plain (per-agent, single) critic."""
    return q_values(AlgoConfig(algo=algo), params, obs, actions, i)[0]


def prepared(cfg, norm, batch):
    """The batch as the networks see it: observations standardised by ``norm`` (mean, var),
    clipped to +-10, rewards scaled."""
    if cfg.normalize_obs:
        mean, var = norm
        standard = lambda x: jnp.clip((x - mean) / jnp.sqrt(var + 1e-8), -10.0, 10.0)  # noqa: E731
        batch = batch.replace(obs=standard(batch.obs), next_obs=standard(batch.next_obs))
    return batch.replace(rewards=batch.rewards * cfg.reward_scale)


def smoothing(cfg, key, shape, smooth=True):
    """Target-policy smoothing noise of ``shape`` drawn with ``key`` (zeros if off)."""
    if cfg.target_noise == 0 or not smooth:
        return jnp.zeros(shape)
    return jnp.clip(cfg.target_noise * jax.random.normal(key, shape), -cfg.target_noise_clip, cfg.target_noise_clip)


def td_target(cfg, target_critic, next_obs, next_actions, rewards, not_done, i, twin_max=False):
    """y [B] of agent i: the smaller (``twin_max``: larger) of the target critics' estimates."""
    estimates = jnp.stack(q_values(cfg, target_critic, next_obs, next_actions, i))
    return rewards[:, i] + cfg.gamma * not_done * (estimates.max(0) if twin_max else estimates.min(0))


def clip_and_adam(params, grads, opt, clip, lr):
    """Clip ``grads`` to global norm ``clip``, then one Adam step from the moments and step
    count in ``opt`` (the network's optimiser state: clip's, then Adam's)."""
    norm = jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(grads)))
    scale = jnp.minimum(1.0, clip / norm)
    adam = opt[1][0]  # optax.adam: (scale_by_adam, scale_by_learning_rate)
    t = adam.count + 1

    def step(p, g, mu, nu):
        g = g * scale
        m_hat = (ADAM_B1 * mu + (1 - ADAM_B1) * g) / (1 - ADAM_B1**t)
        v_hat = (ADAM_B2 * nu + (1 - ADAM_B2) * g**2) / (1 - ADAM_B2**t)
        return p - lr * m_hat / (jnp.sqrt(v_hat) + ADAM_EPS)

    return jax.tree.map(step, params, grads, adam.mu, adam.nu)


def gaussian(params, obs):
    """An inferred policy's (mean, log_std) on observations [B, O]: tanh(MLP) and the clipped log-std."""
    mean = jnp.tanh(mlp({"params": params["params"]["MLP_0"]}, obs))
    return mean, jnp.clip(params["params"]["log_std"], -5.0, 1.0)


def reference_update(
    cfg,
    state,
    batch,
    weights,
    actor_on_new_critic=True,
    cut_bootstrap=True,
    true_targets=False,
    ignore_sub_policy=False,
    fit_on_sample=False,
    online_approximations=False,
    smooth=True,
    twin_max=False,
    global_order=False,
    clip_grads=True,
):
    """Every agent's update, one agent at a time; results stacked on a leading [N] axis
    ([N * K] for the actors, [N * K, B] for the TD loss). ``batch`` [N * K, B, ...] holds agent
    i's batch from sub-policy k's partition at i * K + k; the approximations fit RECENT.
    Shared parameters: :func:`reference_shared_update`."""
    norm = None if state.obs_norm is None else (state.obs_norm.mean, state.obs_norm.var)
    batch = prepared(cfg, norm, batch)
    if cfg.share_parameters:
        return reference_shared_update(
            cfg, state, batch, weights, actor_on_new_critic, cut_bootstrap, smooth, twin_max, global_order, clip_grads
        )
    recent = prepared(cfg, norm, RECENT)
    K = cfg.ensemble
    clip = cfg.grad_clip if clip_grads else np.inf
    pick = lambda tree, i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
    soft = lambda target, online: jax.tree.map(lambda t, o: (1 - cfg.tau) * t + cfg.tau * o, target, online)  # noqa: E731
    noise_keys = jax.random.split(KEY, N)
    results = []
    for i in range(N):
        rows = [i * K + k for k in range(K)]
        joined = lambda x: jnp.concatenate([x[r] for r in rows])  # noqa: E731  the K batches as one
        obs, actions, rewards = joined(batch.obs), joined(batch.actions), joined(batch.rewards)
        next_obs, terminated = joined(batch.next_obs), joined(batch.terminated)
        policy = joined(batch.policy) if K > 1 and not ignore_sub_policy else jnp.zeros((K * B, N), jnp.int32)
        w = jnp.ones(K * B) if weights is None else joined(weights)
        result = {}

        approx = None
        if cfg.infer_policies:  # eq. 7: one step on each other agent's approximation, before the critic
            approx, infer_loss = [], []
            for j in range(N):
                params = pick(pick(state.approx, i), j)

                fit_obs, fit_actions = (obs, actions) if fit_on_sample else (recent.obs, recent.actions)

                def nll(p, j=j, fit_obs=fit_obs, fit_actions=fit_actions):
                    mean, log_std = gaussian(p, fit_obs[:, j])
                    logp = (
                        -0.5 * ((fit_actions[:, j] - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * np.log(2 * np.pi)
                    )
                    entropy = jnp.sum(log_std + 0.5 * np.log(2 * np.pi * np.e))
                    return -jnp.mean(logp.sum(-1)) - cfg.infer_entropy * entropy

                if j != i:
                    infer_loss.append(nll(params))
                    opt = pick(pick(state.approx_opt, i), j)
                    params = clip_and_adam(params, jax.grad(nll)(params), opt, clip, cfg.actor_lr)
                approx.append(params)
            result["infer_loss"] = jnp.mean(jnp.stack(infer_loss))

        def target_action(j):
            if cfg.infer_policies and j != i and not true_targets:  # eq. 8: the target approximation's mean
                guess = approx[j] if online_approximations else pick(pick(state.target_approx, i), j)
                return gaussian(guess, next_obs[:, j])[0]
            every = [actor(pick(state.target_actor, j * K + k), next_obs[:, j], cfg)[0] for k in range(K)]
            return sum(jnp.where((policy[:, j] == k)[:, None], every[k], 0.0) for k in range(K))

        next_actions = jnp.stack([target_action(j) for j in range(N)], axis=1)
        next_actions = jnp.clip(next_actions + smoothing(cfg, noise_keys[i], next_actions.shape, smooth), -1.0, 1.0)
        not_done = 1.0 - terminated.astype(jnp.float32) if cut_bootstrap else 1.0
        y = td_target(cfg, pick(state.target_critic, i), next_obs, next_actions, rewards, not_done, i, twin_max)

        def td_losses(critic_params):
            return [(q - y) ** 2 for q in q_values(cfg, critic_params, obs, actions, i, global_order)]

        def critic_loss(critic_params):
            return sum(jnp.mean(w * td) for td in td_losses(critic_params))

        old_critic = pick(state.critic, i)
        opt = pick(state.critic_opt, i)
        critic = clip_and_adam(old_critic, jax.grad(critic_loss)(old_critic), opt, clip, cfg.critic_lr)
        judge = critic if actor_on_new_critic else old_critic

        actors, actor_losses = [], []
        for k, row in enumerate(rows):  # eq. 11: sub-policy k on its own partition's batch

            def actor_loss(actor_params, row=row):
                own, pre = actor(actor_params, batch.obs[row][:, i], cfg)
                joint = batch.actions[row].at[:, i].set(own)
                return -jnp.mean(
                    q_values(cfg, judge, batch.obs[row], joint, i, global_order)[0]
                ) + cfg.action_penalty * jnp.mean(pre**2)

            old_actor = pick(state.actor, i * K + k)
            opt = pick(state.actor_opt, i * K + k)
            actors.append(clip_and_adam(old_actor, jax.grad(actor_loss)(old_actor), opt, clip, cfg.actor_lr))
            actor_losses.append(actor_loss(old_actor))
        stack = lambda trees: jax.tree.map(lambda *xs: jnp.stack(xs), *trees)  # noqa: E731
        old_targets = [pick(state.target_actor, i * K + k) for k in range(K)]
        result.update(
            td_loss=td_losses(old_critic)[0].reshape(K, B),
            critic_loss=critic_loss(old_critic),
            actor_loss=jnp.mean(jnp.stack(actor_losses)),
            critic=critic,
            actor=stack(actors),
            target_critic=soft(pick(state.target_critic, i), critic),
            target_actor=stack([soft(t, a) for t, a in zip(old_targets, actors)]),
        )
        if approx is not None:
            result["approx"] = stack(approx)
            result["target_approx"] = stack([soft(pick(pick(state.target_approx, i), j), approx[j]) for j in range(N)])
        results.append(result)
    out = jax.tree.map(lambda *xs: jnp.stack(xs), *results)
    flat = lambda tree: jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), tree)  # noqa: E731  [N, K] -> [N * K]
    return {
        **out,
        "td_loss": flat(out["td_loss"]),
        "actor": flat(out["actor"]),
        "target_actor": flat(out["target_actor"]),
    }


def reference_shared_update(
    cfg, state, batch, weights, actor_on_new_critic, cut_bootstrap, smooth, twin_max, global_order, clip_grads
):
    """One shared actor and critic: agent i's losses on its own batch ``batch[i]`` (already
    prepared) as in :func:`reference_update`, averaged over the agents, then one clipped Adam
    step per network. Parameters keep a leading group axis of 1."""
    one = lambda tree: jax.tree.map(lambda x: x[0], tree)  # noqa: E731
    soft = lambda target, online: jax.tree.map(lambda t, o: (1 - cfg.tau) * t + cfg.tau * o, target, online)  # noqa: E731
    noise_keys = jax.random.split(KEY, N)
    w = jnp.ones((N, B)) if weights is None else weights
    targets = []
    for i in range(N):
        next_obs = batch.next_obs[i]
        next_actions = jnp.stack([actor(one(state.target_actor), next_obs[:, j], cfg, j)[0] for j in range(N)], axis=1)
        next_actions = jnp.clip(next_actions + smoothing(cfg, noise_keys[i], next_actions.shape, smooth), -1.0, 1.0)
        not_done = 1.0 - batch.terminated[i].astype(jnp.float32) if cut_bootstrap else 1.0
        targets.append(
            td_target(cfg, one(state.target_critic), next_obs, next_actions, batch.rewards[i], not_done, i, twin_max)
        )

    def td_losses(critic_params, i):
        return [
            (q - targets[i]) ** 2 for q in q_values(cfg, critic_params, batch.obs[i], batch.actions[i], i, global_order)
        ]

    def critic_losses(critic_params):
        return jnp.stack([sum(jnp.mean(w[i] * td) for td in td_losses(critic_params, i)) for i in range(N)])

    old_critic = one(state.critic)
    clip = cfg.grad_clip if clip_grads else np.inf
    grads = jax.grad(lambda p: critic_losses(p).mean())(old_critic)
    critic = clip_and_adam(old_critic, grads, one(state.critic_opt), clip, cfg.critic_lr)
    judge = critic if actor_on_new_critic else old_critic

    def actor_losses(actor_params):
        losses = []
        for i in range(N):
            own, pre = actor(actor_params, batch.obs[i][:, i], cfg, i)
            joint = batch.actions[i].at[:, i].set(own)
            q = q_values(cfg, judge, batch.obs[i], joint, i, global_order)[0]
            losses.append(-jnp.mean(q) + cfg.action_penalty * jnp.mean(pre**2))
        return jnp.stack(losses)

    old_actor = one(state.actor)
    grads = jax.grad(lambda p: actor_losses(p).mean())(old_actor)
    new_actor = clip_and_adam(old_actor, grads, one(state.actor_opt), clip, cfg.actor_lr)
    group = lambda tree: jax.tree.map(lambda x: x[None], tree)  # noqa: E731
    return {
        "td_loss": jnp.stack([td_losses(old_critic, i)[0] for i in range(N)]),
        "critic_loss": critic_losses(old_critic),
        "actor_loss": actor_losses(old_actor),
        "critic": group(critic),
        "actor": group(new_actor),
        "target_critic": group(soft(one(state.target_critic), critic)),
        "target_actor": group(soft(one(state.target_actor), new_actor)),
    }


# ----------------------------------------------------------------------------- fixtures


def perturbed(tree, rng):
    return jax.tree.map(lambda x: x + 0.1 * rng.standard_normal(x.shape).astype(np.float32), tree)


CASES = {
    "maddpg-weighted": dict(algo="maddpg", weighted=True),
    "ddpg-weighted": dict(algo="ddpg", weighted=True),
    "maddpg-ensemble3-weighted": dict(algo="maddpg", ensemble=3, weighted=True),
    "ddpg-ensemble2": dict(algo="ddpg", ensemble=2),
    "maddpg-infer": dict(algo="maddpg", infer_policies=True),
    "ddpg-twin-smoothed-weighted": dict(algo="ddpg", twin_critics=True, target_noise=0.3, weighted=True),
    "maddpg-ensemble2-twin-smoothed-infer": dict(
        algo="maddpg", ensemble=2, twin_critics=True, target_noise=0.3, infer_policies=True
    ),
    "ddpg-shared-layernorm": dict(algo="ddpg", share_parameters=True, layer_norm=True),
    "maddpg-neighbors1-twin": dict(algo="maddpg", critic_neighbors=1, twin_critics=True, target_noise=0.3),
    "maddpg-neighbors1-ensemble2-infer": dict(algo="maddpg", critic_neighbors=1, ensemble=2, infer_policies=True),
    "maddpg-neighbors2-weighted": dict(algo="maddpg", critic_neighbors=2, weighted=True),
    "maddpg-swarm-weighted": dict(
        algo="maddpg",
        share_parameters=True,
        twin_critics=True,
        target_noise=0.3,
        layer_norm=True,
        normalize_obs=True,
        reward_scale=0.1,
        weighted=True,
    ),
    "maddpg-swarm-neighbors1-weighted": dict(
        algo="maddpg", share_parameters=True, twin_critics=True, critic_neighbors=1, normalize_obs=True, weighted=True
    ),
}
"""The configurations compared with the reference, each a compiled update of its own (about 10 s
from a cold cache). Unweighted draws (``weights=None``) are weights of ones in ``update``, so the
weighted cases stand for them; a combination stands for its parts where one case holds them all
(ensembles with inferred policies: beside twin critics and smoothing, and beside neighbours)."""


def random_batch(rng, K):
    """A batch [N * K, B, ...] of random transitions; with K > 1, batch i * K + k comes from
    agent i's partition k: agent i ran sub-policy k, the others anything."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    G = N * K
    policy = None
    if K > 1:
        policy = rng.integers(0, K, (G, B, N))
        for g in range(G):
            policy[g, :, g // K] = g % K
        policy = jnp.asarray(policy, jnp.int32)
    return Transition(
        obs=f32(rng.standard_normal((G, B, N, O))),
        actions=f32(rng.uniform(-1, 1, (G, B, N, A))),
        rewards=f32(rng.standard_normal((G, B, N))),
        next_obs=f32(rng.standard_normal((G, B, N, O))),
        terminated=jnp.asarray(rng.random((G, B)) < 0.3),
        policy=policy,
    )


@pytest.fixture(scope="module", params=list(CASES), ids=list(CASES))
def case(request):
    """(config, state, batch, weights, code's new state, code's info, reference results).

    The state has taken one update already (on another batch), so Adam's moments are not
    zero: from zero moments Adam's first step is lr * g / (|g| + eps), about lr * sign(g),
    and the comparison would miss anything that scales a gradient (its clipping, a loss
    summed instead of averaged)."""
    options = dict(CASES[request.param])
    weighted = options.pop("weighted", False)
    # pinned (not the defaults): float32 agreement was established at these widths and rates
    cfg = AlgoConfig(actor_lr=1e-2, critic_lr=1e-2, hidden=(64, 64), infer_entropy=0.05, **options)
    K = cfg.ensemble
    rng = np.random.default_rng(0)
    state = fresh_learner(jax.random.PRNGKey(0), cfg, N, O)
    state = state.replace(
        target_actor=perturbed(state.target_actor, rng), target_critic=perturbed(state.target_critic, rng)
    )
    if cfg.infer_policies:
        state = state.replace(target_approx=perturbed(state.target_approx, rng))
    if cfg.normalize_obs:  # a normaliser that has seen something: every entry shifted and scaled
        mean, var = rng.normal(0, 0.5, O).astype(np.float32), rng.uniform(0.5, 2.0, O).astype(np.float32)
        state = state.replace(obs_norm=ObsNorm(mean=jnp.asarray(mean), var=jnp.asarray(var), count=jnp.asarray(100.0)))
    batch = random_batch(rng, K)
    assert 0 < int(batch.terminated.sum()) < N * K * B
    weights = jnp.asarray(rng.uniform(0.1, 2.0, (N * K, B)), jnp.float32) if weighted else None
    step = jax.jit(update, static_argnums=0)
    state = step(cfg, state, random_batch(rng, K), weights, RECENT, jax.random.PRNGKey(8))[0]  # the moments
    adam = state.critic_opt[1][0]
    assert (np.asarray(adam.count) == 1).all() and max(float(np.abs(m).max()) for m in jax.tree.leaves(adam.mu)) > 0
    new_state, info = step(cfg, state, batch, weights, RECENT, KEY)
    return cfg, state, batch, weights, new_state, info, reference_update(cfg, state, batch, weights)


# ----------------------------------------------------------------------------- tests


def test_td_loss_matches_reference(case):
    cfg, *_, info, ref = case
    assert info["td_loss"].shape == (N * cfg.ensemble, B)
    np.testing.assert_allclose(info["td_loss"], ref["td_loss"], **TOL)


def test_critic_and_actor_losses_match_reference(case):
    *_, info, ref = case
    assert info["critic_loss"].shape == (N,)
    np.testing.assert_allclose(info["critic_loss"], ref["critic_loss"], **TOL)
    np.testing.assert_allclose(info["actor_loss"], ref["actor_loss"], **TOL)


@pytest.mark.parametrize("network", ["critic", "actor", "target_critic", "target_actor", "approx", "target_approx"])
def test_updated_parameters_match_reference(case, network):
    cfg, state, *_, new_state, _, ref = case
    if network in ("approx", "target_approx") and not cfg.infer_policies:
        assert getattr(new_state, network) is None
        return
    moved = jax.tree.map(lambda new, old: np.abs(new - old).max(), getattr(new_state, network), getattr(state, network))
    assert max(jax.tree.leaves(moved)) > 1e-4  # the update did change this network
    assert jax.tree.structure(getattr(new_state, network)) == jax.tree.structure(ref[network])
    assert_parameters_close(getattr(new_state, network), ref[network])


def caught(pairs):
    """Parametrize a test over (case, variant) pairs: each variant of the reference is checked
    on the cases named for it, not on all of them (each check runs the reference again, op by
    op: over every case they took half of this module's time, 195 s of 463 from a cold cache)."""
    return pytest.mark.parametrize(
        "case, variant",
        [pytest.param(case, variant, id=f"{case}-{name}") for name, variant, cases in pairs for case in cases],
        indirect=["case"],
    )


@caught(
    [
        (name, variant, ["maddpg-weighted", "ddpg-shared-layernorm", "maddpg-ensemble2-twin-smoothed-infer"])
        for name, variant in [
            ("actor_on_old_critic", dict(actor_on_new_critic=False)),
            ("no_bootstrap_cut", dict(cut_bootstrap=False)),
            ("unclipped_gradients", dict(clip_grads=False)),
        ]
    ]
)
def test_reference_variants_are_caught(case, variant):
    """The reference with the actor on the critic before its step, without the bootstrap cut at
    terminal steps or without gradient clipping disagrees with the code: per-agent and shared
    networks, and an ensemble with inferred policies."""
    cfg, state, batch, weights, new_state, info, _ = case
    wrong = reference_update(cfg, state, batch, weights, **variant)
    seen = {"cut_bootstrap": "td_loss", "clip_grads": "critic"}.get(next(iter(variant)), "actor")
    got = info["td_loss"] if seen == "td_loss" else getattr(new_state, seen)
    want = wrong[seen]
    gap = max(jax.tree.leaves(jax.tree.map(lambda g, w: np.abs(g - w).max(), got, want)))
    assert gap > 1e-3, variant


@caught(
    [
        ("true_target_policies", dict(true_targets=True), ["maddpg-infer", "maddpg-ensemble2-twin-smoothed-infer"]),
        ("approximations_fit_the_sample", dict(fit_on_sample=True), ["maddpg-infer"]),
        ("online_approximations", dict(online_approximations=True), ["maddpg-infer"]),
        ("target_sub_policy_0", dict(ignore_sub_policy=True), ["ddpg-ensemble2", "maddpg-ensemble3-weighted"]),
    ]
)
def test_the_target_actions_are_caught(case, variant):
    """Inferred policies: the targets use the approximations' targets, and the approximations fit
    the recent transitions (seen in their parameters: the targets do not move with this step's
    fit); ensembles: the target sub-policy each agent ran in the transition. The reference
    without that disagrees with the code."""
    cfg, state, batch, weights, new_state, info, _ = case
    wrong = reference_update(cfg, state, batch, weights, **variant)
    if "fit_on_sample" in variant:
        gap = jax.tree.map(lambda g, w: np.abs(g - w).max(), new_state.approx, wrong["approx"])
        assert max(jax.tree.leaves(gap)) > 1e-3
        return
    assert np.abs(np.asarray(info["td_loss"]) - np.asarray(wrong["td_loss"])).max() > 1e-3


def test_inferred_policy_loss_and_error_match_reference(case):
    cfg, state, batch, _, new_state, info, ref = case
    if not cfg.infer_policies:
        assert "infer_loss" not in info
        return
    np.testing.assert_allclose(info["infer_loss"], ref["infer_loss"], **TOL)
    for i in range(N):  # an agent's approximation of itself never moves
        mine = jax.tree.map(lambda new, old: np.abs(new[i, i] - old[i, i]).max(), new_state.approx, state.approx)
        assert max(jax.tree.leaves(mine)) == 0.0
    # the logged error (outside the update): the approximations against the others' current
    # deterministic actions, of the sub-policy they ran
    logged = inference_error(cfg, state, batch)
    K = cfg.ensemble
    for i in range(N):
        obs = jnp.concatenate([batch.obs[i * K + k] for k in range(K)])
        policy = (
            jnp.concatenate([batch.policy[i * K + k] for k in range(K)]) if K > 1 else jnp.zeros((K * B, N), jnp.int32)
        )
        errors = []
        for j in range(N):
            if j == i:
                continue
            every = [actor(jax.tree.map(lambda x: x[j * K + k], state.actor), obs[:, j])[0] for k in range(K)]
            true = sum(jnp.where((policy[:, j] == k)[:, None], every[k], 0.0) for k in range(K))
            mean = gaussian(jax.tree.map(lambda x: x[i, j], state.approx), obs[:, j])[0]
            errors.append(jnp.abs(mean - true).mean())
        np.testing.assert_allclose(logged[i], np.mean(errors), **TOL)


def test_an_empty_partition_leaves_its_sub_policy_alone(case):
    """Zero weights for a group (its partition is empty) leave that sub-policy's actor and its
    optimiser state as they were, also after it has learned (Adam's momentum would move it on
    a zero gradient)."""
    cfg, state, batch, weights, *_ = case
    if cfg.ensemble == 1:
        pytest.skip("no partitions")
    full = jnp.ones((N * cfg.ensemble, B)) if weights is None else weights
    step = jax.jit(update, static_argnums=0)
    for start in (state, step(cfg, state, batch, full, RECENT, KEY)[0]):  # fresh, and with momentum
        new_state, _ = step(cfg, start, batch, full.at[1].set(0.0), RECENT, KEY)
        mine = lambda s: (s.actor, s.actor_opt)  # noqa: E731
        still = jax.tree.map(lambda new, old: np.abs(new[1] - old[1]).max(), mine(new_state), mine(start))
        moved = jax.tree.map(lambda new, old: np.abs(new[0] - old[0]).max(), new_state.actor, start.actor)
        assert max(jax.tree.leaves(still)) == 0.0 and max(jax.tree.leaves(moved)) > 1e-4


@caught(
    [
        ("no_smoothing", dict(smooth=False), ["ddpg-twin-smoothed-weighted", "maddpg-swarm-weighted"]),
        ("larger_twin", dict(twin_max=True), ["maddpg-neighbors1-twin", "maddpg-swarm-weighted"]),
        ("global_order", dict(global_order=True), ["maddpg-neighbors1-twin", "maddpg-swarm-weighted"]),
    ]
)
def test_the_swarm_options_are_caught(case, variant):
    """The reference without target smoothing, with the larger of the twin estimates, with the
    shared MADDPG critic's view in global order (not own-first), or with --critic-neighbors'
    others taken by index (not nearest first) disagrees with the code."""
    cfg, state, batch, weights, new_state, info, _ = case
    wrong = reference_update(cfg, state, batch, weights, **variant)
    assert np.abs(np.asarray(info["td_loss"]) - np.asarray(wrong["td_loss"])).max() > 1e-3


@pytest.mark.parametrize("shared", [False, True], ids=["per-agent", "shared"])
def test_delayed_actor_updates_skip_the_actor_and_targets(shared):
    """--actor-delay 2: the first update moves every network (as without the delay), the second
    only the critics; the third moves the actors again."""
    cfg = AlgoConfig(hidden=(32, 32), actor_delay=2, twin_critics=True, target_noise=0.2, share_parameters=shared)
    rng = np.random.default_rng(3)
    batch = Transition(
        obs=jnp.asarray(rng.standard_normal((N, B, N, O)), jnp.float32),
        actions=jnp.asarray(rng.uniform(-1, 1, (N, B, N, A)), jnp.float32),
        rewards=jnp.asarray(rng.standard_normal((N, B, N)), jnp.float32),
        next_obs=jnp.asarray(rng.standard_normal((N, B, N, O)), jnp.float32),
        terminated=jnp.zeros((N, B), bool),
    )
    step = jax.jit(update, static_argnums=0)
    states = [fresh_learner(jax.random.PRNGKey(0), cfg, N, O)]
    for _ in range(3):
        states.append(step(cfg, states[-1], batch, key=KEY)[0])
    undelayed = step(dataclasses.replace(cfg, actor_delay=1), states[0].replace(updates=None), batch, key=KEY)[0]
    gap = lambda a, b: max(jax.tree.leaves(jax.tree.map(lambda x, y: float(np.abs(x - y).max()), a, b)))  # noqa: E731
    assert [int(s.updates) for s in states] == [0, 1, 2, 3]
    for network in ("actor", "critic", "target_actor", "target_critic"):
        assert gap(getattr(states[1], network), getattr(undelayed, network)) < 1e-6, (
            network
        )  # another program: rounding
        assert gap(getattr(states[1], network), getattr(states[0], network)) > 0.0, network  # targets move by tau * lr
    for network in ("actor", "target_actor", "target_critic", "actor_opt"):
        assert gap(getattr(states[2], network), getattr(states[1], network)) == 0.0, network
    assert gap(states[2].critic, states[1].critic) > 1e-4
    assert gap(states[3].actor, states[2].actor) > 1e-4


def test_the_observation_normaliser_matches_numpy():
    """Two batches folded in one after the other give the mean and variance of all of them."""
    cfg = AlgoConfig(hidden=(8,), normalize_obs=True)
    rng = np.random.default_rng(4)
    first = rng.normal(3.0, 2.0, (5, 7, N, O)).astype(np.float32)
    second = rng.normal(-1.0, 0.5, (11, N, O)).astype(np.float32)
    state = fresh_learner(jax.random.PRNGKey(0), cfg, N, O)
    state = observe_batch(cfg, observe_batch(cfg, state, jnp.asarray(first)), jnp.asarray(second))
    seen = np.concatenate([first.reshape(-1, O), second.reshape(-1, O)]).astype(np.float64)
    np.testing.assert_allclose(state.obs_norm.mean, seen.mean(0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(state.obs_norm.var, seen.var(0), rtol=1e-4, atol=1e-5)
    assert float(state.obs_norm.count) == len(seen)
    plain = fresh_learner(jax.random.PRNGKey(0), AlgoConfig(hidden=(8,)), N, O)
    assert plain.obs_norm is None and observe_batch(AlgoConfig(hidden=(8,)), plain, jnp.asarray(first)) is plain
