"""MADDPG (paper eq. 4-6) and DDPG: one update, the critic's view is the only difference.

Shape legend
    N  agents (rovers), K  sub-policies per agent (1 without ensembles), B  batch size,
    O  observation size, A  action size (2),
    D  critic input size: N * (O + A) for MADDPG (all observations and actions),
       (1 + C) * (O + A) with ``critic_neighbors`` C, O + A for DDPG (the agent's own);
       + N with shared parameters over the flat view (the one-hot index).

Every agent i has an actor mu_i(o_i) and a critic Q_i. One update of agent i, on a batch
drawn for it (``batch`` carries a leading agent axis: agent i's own sample):

    a'_j = mu'_j(o'_j) for every j                  (target actors)
    y    = r_i + gamma * (1 - terminated) * Q'_i(x', a'_1..a'_N)               (eq. 6)
    critic: minimise  mean_b w_b (Q_i(x, a_1..a_N) - y)^2                       (eq. 5)
    actor:  minimise -mean_b Q_i(x, a_1..mu_i(o_i)..a_N) + c * mean(pre_i^2)    (eq. 4)
    targets: theta' <- (1 - tau) theta' + tau theta

where the other agents' actions in the actor step come from the replay, the actor step uses
the freshly updated critic, and ``pre_i`` is the actor's pre-tanh output (the reference
code's 1e-3 action regulariser). Gradients are clipped to a global norm per network. All
agents update at once: parameters are stacked on a leading agent axis and the per-agent
update is vmapped (actors on a leading [N * K] axis, see below).

Policy ensembles (eq. 9-11, ``ensemble`` K > 1): agent i has K sub-policies mu_i^(k) (actors
stacked agent-major on one [N * K] axis: sub-policy k of agent i at i * K + k). Each stored
transition records the sub-policy every agent ran. An update of agent i draws one batch from
each partition D_i^(k) (its transitions that sub-policy k of agent i made); sub-policy k's
actor step uses its own batch (eq. 11), the critic step uses all K batches together (the
critic of agent i learns from every sub-policy's experience), and the target actions are
those of the target sub-policies each agent ran in the sampled transition. K = 1 is plain
MADDPG.

Inferred policies (eq. 7-8, ``infer_policies``): agent i keeps a Gaussian approximation
mu_hat_i^j of every other agent j's policy (mean tanh(MLP(o_j)), learned log-std), fitted
before each critic step to the other agents' actions in a batch of recent transitions (the
``recent`` argument of :func:`update`: the others' current behaviour, not their average over
the whole replay) by minimising the negative log-likelihood minus ``infer_entropy`` (lambda)
times the entropy. Agent i's target
then uses the means of the approximations' targets mu_hat'_i^j for the other agents (eq. 8's
primes: copies soft-updated by ``tau`` as the target actors are, so that the target moves as
slowly as it does without inference),

    y = r_i + gamma * (1 - terminated) * Q'_i(x', mu_hat'_i^1(o'_1), .., mu'_i(o'_i), .., mu_hat'_i^N(o'_N))

so it never reads the other agents' true policies (:func:`inference_error`, outside the
update, reads them to log how far the approximations are).

A group whose batch weights are all zero (an empty partition, before its sub-policy was
ever drawn) leaves its sub-policy's actor alone.

Options for swarms (homogeneous rovers), each off by default and composable:

* ``share_parameters``: one actor mu(o_i, e_i) and one critic Q(x_i, a_i, e_i) for every
  rover, e_i the rover's one-hot index (none over the nearest view, ``network="nearest"``:
  mu(o_i) and Q(x_i, a_i) then serve any number of rovers). The critic's view is ordered own-first: rover i's
  observation and action, then the others' in index order (x_i = o_i, o_{-i}; for DDPG its
  own only; with ``critic_neighbors``, nearest first), so the same weights mean the same
  thing for every rover. Each update takes every rover's batch: the losses below are
  averaged over rovers, one gradient step per network, so the shared networks learn from N
  times the data. Parameters keep a leading group axis of size 1.
* Mixed swarm sizes (a batch with ``rovers``, the slots that exist; shared parameters
  only): a sample whose agent's rover does not exist weighs nothing in either loss, the others
  weigh alike (:func:`presence`), so the means run over the rovers that exist; the critic's
  neighbours are picked among them; empty slots hand the replay a TD loss of 0.
* ``critic_neighbors`` C > 0 (MADDPG): the critic of rover i sees o_i, a_i and the
  observations and actions of the C other rovers nearest to it in that transition, nearest
  first, in place of all N: between the centralised critic and DDPG's local one.
* ``twin_critics`` (TD3/MATD3): two critics per group; the target takes the smaller,
  ``y = r_i + gamma * (1 - terminated) * min_c Q'_{i,c}(x', a')``; both fit y (losses summed);
  the actor follows the first; the TD loss handed to the replay is the first critic's.
* ``target_noise`` (target-policy smoothing): every target action is
  ``clip(mu'_j(o'_j) + clip(eps, -target_noise_clip, target_noise_clip), -1, 1)``, eps ~ N(0, target_noise^2).
* ``actor_delay`` d: the critics update every time; the actors and both target networks
  every d-th update (the first update is one of them).
* ``layer_norm``: LayerNorm after each hidden layer of actors and critics.
* ``normalize_obs``: observations are standardised by a running mean and variance (one per
  observation entry, shared by the rovers, clipped to +-10), updated from every collected
  observation by :func:`observe_batch` and kept in the learner state (so in checkpoints);
  actors and critics only ever see standardised observations; the replay keeps raw ones.
* ``reward_scale``: rewards are multiplied by this before the targets (Q in scaled units).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from roverswarm.algos.inference import approx_actions, fit_approximations, own_target_action
from roverswarm.algos.learner import (
    AlgoConfig,
    LearnerState,
    act,
    actor_inputs,
    critic_inputs,
    critic_values,
    networks,
    optimizers,
    prepare,
    smoothed,
)
from roverswarm.algos.networks import actor_forward
from roverswarm.buffers.base import Transition
from roverswarm.metrics import masked_mean


def inference_error(config: AlgoConfig, state: LearnerState, batch: Transition) -> jax.Array:
    """[N] per agent i: mean absolute difference between its approximations' means and the
    other agents' current deterministic actions (of the sub-policies they ran) on agent i's
    batch [N * K, B, ...]. For the log only: the update never calls it."""
    num_agents = state.approx["params"]["log_std"].shape[0]
    batch = prepare(config, state, batch)
    joint = jax.tree.map(lambda x: x.reshape(num_agents, -1, *x.shape[2:]), batch)  # [N, K * B, ...]
    true = act(config, state.actor, joint.obs, joint.policy)  # [N, K * B, N, A]
    guess = jax.vmap(lambda approx, obs: approx_actions(config.hidden, approx, obs)[0])(state.approx, joint.obs)
    gap = jnp.abs(guess - true).mean(axis=(1, 3))  # [N (agent i), N (other j)]
    others = 1.0 - jnp.eye(num_agents)
    return (gap * others).sum(-1) / jnp.maximum(others.sum(-1), 1.0)


def polyak(target, online, tau: float):
    """``(1 - tau) * target + tau * online``, leaf by leaf."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def _select(flag: jax.Array, new, old):
    """``new`` where ``flag`` else ``old``, leaf by leaf."""
    return jax.tree.map(lambda n, o: jnp.where(flag, n, o), new, old)


# ----------------------------------------------------------------------------- losses of one agent


def _td_target(
    config: AlgoConfig, target_critic, agent: jax.Array, batch: Transition, next_actions: jax.Array
) -> jax.Array:
    """y [B] of agent ``agent`` (eq. 6; twin critics: the smaller target estimate)."""
    inputs = critic_inputs(config, batch.next_obs, next_actions, agent, batch.rovers)
    next_q = critic_values(config, target_critic, inputs).min(axis=0)
    not_done = 1.0 - batch.terminated.astype(jnp.float32)
    return jax.lax.stop_gradient(batch.rewards[:, agent] + config.gamma * not_done * next_q)


def _critic_loss(
    config: AlgoConfig, critic, agent: jax.Array, batch: Transition, target: jax.Array, weights: jax.Array
):
    """(weighted mean squared TD error, summed over twin critics; (first critic's TD loss [B], its Q [B]))."""
    q = critic_values(config, critic, critic_inputs(config, batch.obs, batch.actions, agent, batch.rovers))  # [C, B]
    td = jnp.square(q - target)
    return sum(jnp.mean(weights * t) for t in td), (td[0], q[0])


def _actor_loss(
    config: AlgoConfig,
    actor,
    critic,
    agent: jax.Array,
    obs: jax.Array,
    actions: jax.Array,
    rovers: jax.Array | None = None,
    weights: jax.Array | None = None,
) -> jax.Array:
    """Agent ``agent``'s actor loss (eq. 4) on [B, N, O] observations: the other agents'
    actions from the replay, its own from ``actor``, judged by the (first) critic; of mixed
    swarm sizes, ``rovers`` [B, N] are the rovers that exist and ``weights`` [B] each sample's
    weight (0 where the agent does not exist)."""
    actor_net, _ = networks(config)
    action, pre = actor_forward(actor_net, actor, actor_inputs(config, obs)[:, agent])
    actions = actions.at[:, agent].set(action)
    q_pi = critic_values(config, critic, critic_inputs(config, obs, actions, agent, rovers))[0]
    penalty = jnp.square(pre)
    if weights is not None:
        q_pi, penalty = weights * q_pi, weights[:, None] * penalty
    return -jnp.mean(q_pi) + config.action_penalty * jnp.mean(penalty)


def _apply(optimizer: optax.GradientTransformation, grads, opt_state, params):
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


def _finish(
    config: AlgoConfig, state: LearnerState, actor, actor_opt, critic, critic_opt, due: jax.Array, **extra
) -> LearnerState:
    """The state after an update: new critics; new actors and soft target updates where ``due``
    (every --actor-delay updates)."""
    actor, actor_opt = _select(due, (actor, actor_opt), (state.actor, state.actor_opt))
    return state.replace(
        actor=actor,
        critic=critic,
        target_actor=_select(due, polyak(state.target_actor, actor, config.tau), state.target_actor),
        target_critic=_select(due, polyak(state.target_critic, critic, config.tau), state.target_critic),
        actor_opt=actor_opt,
        critic_opt=critic_opt,
        **extra,
    )


# ----------------------------------------------------------------------------- updates


def _agent_update(
    config: AlgoConfig,
    state: LearnerState,
    agent: jax.Array,
    batch: Transition,
    weights: jax.Array,
    target_actors,
    recent: Transition | None,
    key: jax.Array,
    due: jax.Array,
):
    """One agent's update with its own networks: its slice of ``state`` (its K sub-policies),
    its K batches [K, B, ...] (one per partition), every agent's ``target_actors`` [N * K] and,
    with inferred policies, the ``recent`` transitions its approximations fit. See the module docstring."""
    actor_opt, critic_opt = optimizers(config)
    joint = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), batch)  # the K batches as one [K * B, ...]
    info = {}

    approx, approx_opt = state.approx, state.approx_opt
    target_approx = state.target_approx
    if config.infer_policies:  # eq. 8: the others' target approximations, its own target actor
        approx, approx_opt, info["infer_loss"] = fit_approximations(
            config.hidden, optimizers(config)[0], config.infer_entropy, approx, approx_opt, agent, recent
        )
        inferred = approx_actions(config.hidden, target_approx, joint.next_obs)[0]
        target_approx = _select(due, polyak(target_approx, approx, config.tau), target_approx)
        own = own_target_action(
            networks(config)[0], config.ensemble, target_actors, agent, joint.next_obs, joint.policy
        )
        next_actions = inferred.at[:, agent].set(own)
    else:
        next_actions = act(config, target_actors, joint.next_obs, joint.policy)  # [K * B, N, A]
    target = _td_target(config, state.target_critic, agent, joint, smoothed(config, next_actions, key))

    loss = lambda params: _critic_loss(config, params, agent, joint, target, weights.reshape(-1))  # noqa: E731
    (c_loss, (td, q)), c_grads = jax.value_and_grad(loss, has_aux=True)(state.critic)
    critic, critic_opt_state = _apply(critic_opt, c_grads, state.critic_opt, state.critic)

    active = (weights.max(axis=-1) > 0).astype(jnp.float32)  # [K]: sub-policies with a batch

    def scaled(params, obs, actions, on):  # a sub-policy without a batch (on = 0) gets no gradient
        return on * _actor_loss(config, params, critic, agent, obs, actions)

    a_loss, a_grads = jax.vmap(jax.value_and_grad(scaled))(state.actor, batch.obs, batch.actions, active)
    actor, actor_opt_state = jax.vmap(lambda g, o, p: _apply(actor_opt, g, o, p))(a_grads, state.actor_opt, state.actor)
    # a zero gradient still moves Adam's parameters by its momentum: keep such a sub-policy as it was
    actor, actor_opt_state = jax.vmap(
        lambda on, new, old: jax.tree.map(lambda n, o: jnp.where(on > 0, n, o), new, old)
    )(active, (actor, actor_opt_state), (state.actor, state.actor_opt))

    new_state = _finish(
        config,
        state,
        actor,
        actor_opt_state,
        critic,
        critic_opt_state,
        due,
        approx=approx,
        approx_opt=approx_opt,
        target_approx=target_approx,
    )
    info.update(critic_loss=c_loss, actor_loss=a_loss.mean(), q_mean=jnp.mean(q), td_loss=td.reshape(weights.shape))
    return new_state, info


def presence(rovers: jax.Array) -> jax.Array:
    """[N, B] each agent's sample weight in a batch of mixed swarm sizes, from ``rovers`` [N, B,
    N] (agent i's batch: which rovers exist): 0 where the agent's rover does not exist, and
    the same weight for every sample where it does, so that a mean over [N, B] is the mean over
    the rovers that exist."""
    own = jax.vmap(lambda r, i: r[:, i])(rovers, jnp.arange(rovers.shape[0])).astype(jnp.float32)
    return own * (own.size / jnp.maximum(own.sum(), 1.0))


def _shared_update(
    config: AlgoConfig,
    state: LearnerState,
    batch: Transition,
    weights: jax.Array,
    key: jax.Array,
    due: jax.Array,
    present: jax.Array | None,
):
    """One step of the shared actor and critic on every agent's batch [N, B, ...]: each
    agent's losses as in :func:`_agent_update`, averaged over agents; of mixed swarm sizes,
    over the rovers that exist (``present`` [N, B], :func:`presence`; ``weights`` carry it)."""
    actor_opt, critic_opt = optimizers(config)
    num_agents = batch.rewards.shape[0]
    agents = jnp.arange(num_agents)
    one = lambda tree: jax.tree.map(lambda x: x[0], tree)  # noqa: E731  the group axis of size 1
    keys = jax.random.split(key, num_agents) if config.target_noise > 0 else jnp.zeros(num_agents)

    def target(agent, b, k, next_actions=None):
        if next_actions is None:
            next_actions = act(config, state.target_actor, b.next_obs)
        return _td_target(config, one(state.target_critic), agent, b, smoothed(config, next_actions, k))

    if config.one_batch:  # every agent's batch is the same: its target actions once
        next_actions = act(config, state.target_actor, batch.next_obs[0])
        targets = jax.vmap(target, in_axes=(0, 0, 0, None))(agents, batch, keys, next_actions)  # [N, B]
    else:
        targets = jax.vmap(target)(agents, batch, keys)

    def critic_loss(params):
        losses, aux = jax.vmap(lambda i, b, y, w: _critic_loss(config, params, i, b, y, w))(
            agents, batch, targets, weights
        )
        return losses.mean(), (losses, aux)

    (_, (c_loss, (td, q))), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(one(state.critic))
    critic, critic_opt_state = _apply(critic_opt, c_grads, one(state.critic_opt), one(state.critic))

    def actor_loss(params):
        losses = jax.vmap(lambda i, b, w: _actor_loss(config, params, critic, i, b.obs, b.actions, b.rovers, w))(
            agents, batch, present
        )
        return losses.mean(), losses

    (_, a_loss), a_grads = jax.value_and_grad(actor_loss, has_aux=True)(one(state.actor))
    actor, actor_opt_state = _apply(actor_opt, a_grads, one(state.actor_opt), one(state.actor))
    group = lambda tree: jax.tree.map(lambda x: x[None], tree)  # noqa: E731
    new_state = _finish(
        config, state, group(actor), group(actor_opt_state), group(critic), group(critic_opt_state), due
    )
    q_mean = q.mean(-1)
    if present is not None:  # a sample of an agent that does not exist is no reason to draw it again
        there = present > 0
        td, q_mean = td * there, masked_mean(q, there, -1)
    return new_state, dict(critic_loss=c_loss, actor_loss=a_loss, q_mean=q_mean, td_loss=td)


def update(
    config: AlgoConfig,
    state: LearnerState,
    batch: Transition,
    weights: jax.Array | None = None,
    recent: Transition | None = None,
    key: jax.Array | None = None,
):
    """Update every agent once. ``batch`` has a leading group axis [N * K, B, ...]: agent i's
    sample from its sub-policy k's partition at i * K + k (K = 1: agent i's own sample at i);
    ``weights`` [N * K, B] are optional importance weights of the critic loss (a batch of
    mixed swarm sizes, with ``rovers``, also weighs by :func:`presence`); ``recent``
    [B', ...] (required with --infer-policies) are the recent transitions every agent's
    approximations fit before its critic step; ``key`` (required with --target-noise) draws
    the smoothing noise. Batches hold raw observations and rewards (:func:`prepare` is applied here).

    Returns ``(state, info)`` with ``critic_loss``, ``actor_loss`` (mean over sub-policies),
    ``q_mean`` [N] (over the samples whose rover exists), with --infer-policies ``infer_loss``
    [N], and the per-sample TD loss (Q - y)^2 [N * K, B] for prioritised replay (0 where the
    rover does not exist).
    """
    if config.infer_policies and recent is None:
        raise ValueError("update: --infer-policies needs the recent transitions its approximations fit")
    if config.target_noise > 0 and key is None:
        raise ValueError("update: --target-noise needs a key for the smoothing noise")
    num_groups, batch_size = batch.rewards.shape[:2]
    if weights is None:
        weights = jnp.ones((num_groups, batch_size))
    batch = prepare(config, state, batch)
    recent = None if recent is None else prepare(config, state, recent)
    due = jnp.asarray(True) if state.updates is None else state.updates % config.actor_delay == 0
    present = None
    if batch.rovers is not None:
        if not config.share_parameters:
            raise ValueError("update: a batch of mixed swarm sizes needs --share-parameters")
        present = presence(batch.rovers)
        weights = weights * present
    if config.share_parameters:
        new, info = _shared_update(config, state, batch, weights, key, due, present)
    else:
        by_agent = lambda tree: jax.tree.map(lambda x: x.reshape(-1, config.ensemble, *x.shape[1:]), tree)  # noqa: E731
        flat = lambda tree: jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), tree)  # noqa: E731
        sliced = state.replace(
            actor=by_agent(state.actor),
            target_actor=by_agent(state.target_actor),
            actor_opt=by_agent(state.actor_opt),
            obs_norm=None,
            updates=None,
        )
        num_agents = num_groups // config.ensemble
        keys = jax.random.split(key, num_agents) if config.target_noise > 0 else jnp.zeros(num_agents)
        per_agent = jax.vmap(_agent_update, in_axes=(None, 0, 0, 0, 0, None, None, 0, None))
        new, info = per_agent(
            config,
            sliced,
            jnp.arange(num_agents),
            by_agent(batch),
            by_agent(weights),
            state.target_actor,
            recent,
            keys,
            due,
        )
        new = new.replace(actor=flat(new.actor), target_actor=flat(new.target_actor), actor_opt=flat(new.actor_opt))
        info["td_loss"] = flat(info["td_loss"])
    if state.updates is not None:
        new = new.replace(updates=state.updates + 1)
    return new.replace(obs_norm=state.obs_norm), info
