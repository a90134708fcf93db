"""MADDPG (paper eq. 4-6) and DDPG: one update, the critic's view is the only difference.

Shape legend
    N  agents (rovers), K  sub-policies per agent (1 without ensembles), B  batch size,
    O  observation size, A  action size (2),
    D  critic input size: N * (O + A) for MADDPG (all observations and actions),
       O + A for DDPG (the agent's own).

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
then uses the approximations' means for the other agents,

    y = r_i + gamma * (1 - terminated) * Q'_i(x', mu_hat_i^1(o'_1), .., mu'_i(o'_i), .., mu_hat_i^N(o'_N))

so it never reads the other agents' true policies (:func:`inference_error`, outside the
update, reads them to log how far the approximations are).

A group whose batch weights are all zero (an empty partition, before its sub-policy was
ever drawn) leaves its sub-policy's actor alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from roverswarm.algos.networks import MLP, GaussianPolicy, actor_forward, critic_forward
from roverswarm.buffers.uniform import Transition
from roverswarm.env.mars import ACTION_SIZE

Algo = Literal["maddpg", "ddpg"]
ALGOS: tuple[str, ...] = ("maddpg", "ddpg")


@dataclass(frozen=True)
class AlgoConfig:
    """Learner hyper-parameters. Defaults are tuned to learn with continuous actions (wider
    networks, smaller learning rates than the reference code's 2x64 and 1e-2; see
    ``roverswarm.train.REFERENCE``)."""

    algo: Algo = "maddpg"
    """`maddpg`: centralised critics Q_i(x, a_1..a_N); `ddpg`: local critics Q_i(o_i, a_i)."""
    actor_lr: float = 1e-3
    """Adam learning rate of the actors."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critics."""
    gamma: float = 0.95
    """Discount factor."""
    tau: float = 0.01
    """Soft target update rate."""
    grad_clip: float = 0.5
    """Global gradient-norm clip of each network's update."""
    hidden: tuple[int, ...] = (128, 128)
    """Hidden layer widths of actors and critics (ReLU)."""
    action_penalty: float = 1e-3
    """Weight of the mean squared pre-tanh actor output in the actor loss."""
    ensemble: int = 1
    """Sub-policies per agent (policy ensembles, eq. 9-11): one drawn per agent per episode,
    each learning from its own replay partition; 1 = plain MADDPG."""
    infer_policies: bool = False
    """MADDPG only: each agent learns Gaussian approximations of the other agents' policies
    from the replay and uses them in its critic's target instead of their true policies (eq. 7-8)."""
    infer_entropy: float = 1e-3
    """lambda: weight of the entropy bonus in the approximations' loss (--infer-policies)."""
    infer_window: int = 10_000
    """--infer-policies: the approximations fit batches drawn from the newest this many
    transitions of the replay, so they follow the others' current policies."""


@struct.dataclass
class LearnerState:
    """Every agent's networks, targets and optimiser states, stacked on a leading agent axis
    ([N * K] for the actors: sub-policy k of agent i at i * K + k)."""

    actor: Any  # [N * K, ...]: sub-policy k of agent i at i * K + k
    critic: Any  # [N, ...]
    target_actor: Any  # [N * K, ...]
    target_critic: Any  # [N, ...]
    actor_opt: Any  # [N * K, ...]
    critic_opt: Any  # [N, ...]
    approx: Any = None  # [N, N, ...]: agent i's approximation of agent j's policy (inferred policies)
    approx_opt: Any = None  # [N, N, ...]


def networks(config: AlgoConfig) -> tuple[MLP, MLP]:
    """The (actor, critic) modules of ``config``."""
    return MLP(config.hidden, ACTION_SIZE), MLP(config.hidden, 1)


def optimizers(config: AlgoConfig) -> tuple[optax.GradientTransformation, optax.GradientTransformation]:
    """Adam with global-norm clipping, for (actors, critics)."""
    clip = optax.clip_by_global_norm(config.grad_clip)
    return optax.chain(clip, optax.adam(config.actor_lr)), optax.chain(clip, optax.adam(config.critic_lr))


def critic_inputs(config: AlgoConfig, obs: jax.Array, actions: jax.Array, agent: jax.Array) -> jax.Array:
    """What agent ``agent``'s critic sees: [B, N, O] observations and [B, N, A] actions -> [B, D]."""
    if config.algo == "maddpg":
        batch = obs.shape[0]
        return jnp.concatenate([obs.reshape(batch, -1), actions.reshape(batch, -1)], axis=-1)
    return jnp.concatenate([obs[:, agent], actions[:, agent]], axis=-1)


def approximation(config: AlgoConfig) -> GaussianPolicy:
    """The module of an inferred policy (a Gaussian over the action, same widths as the actor)."""
    return GaussianPolicy(config.hidden, ACTION_SIZE)


def init_learner(key: jax.Array, config: AlgoConfig, num_agents: int, obs_size: int) -> LearnerState:
    """Fresh networks for ``num_agents`` agents; targets start equal to the online networks."""
    actor_net, critic_net = networks(config)
    actor_opt, critic_opt = optimizers(config)
    k_actor, k_critic = jax.random.split(key)
    obs = jnp.zeros((1, num_agents, obs_size))
    actions = jnp.zeros((1, num_agents, ACTION_SIZE))
    critic_in = critic_inputs(config, obs, actions, jnp.int32(0))
    actor = jax.vmap(actor_net.init, in_axes=(0, None))(jax.random.split(k_actor, num_agents * config.ensemble), obs[:, 0])
    critic = jax.vmap(critic_net.init, in_axes=(0, None))(jax.random.split(k_critic, num_agents), critic_in)
    approx = approx_opt = None
    if config.infer_policies:
        keys = jax.random.split(jax.random.fold_in(key, 2), num_agents * num_agents)
        flat = jax.vmap(approximation(config).init, in_axes=(0, None))(keys, obs[:, 0])
        approx = jax.tree.map(lambda x: x.reshape(num_agents, num_agents, *x.shape[1:]), flat)
        approx_opt = jax.vmap(jax.vmap(optimizers(config)[0].init))(approx)
    return LearnerState(
        approx=approx,
        approx_opt=approx_opt,
        actor=actor,
        critic=critic,
        # copies, not aliases: the training loop donates its state buffers
        target_actor=jax.tree.map(jnp.copy, actor),
        target_critic=jax.tree.map(jnp.copy, critic),
        actor_opt=jax.vmap(actor_opt.init)(actor),
        critic_opt=jax.vmap(critic_opt.init)(critic),
    )


def act(config: AlgoConfig, actor_params, obs: jax.Array, policy: jax.Array | None = None) -> jax.Array:
    """Deterministic actions of all agents: [..., N, O] observations -> [..., N, A] actions;
    with ensembles (K > 1), of the sub-policies ``policy`` [..., N] the agents run."""
    actor_net, _ = networks(config)
    forward = lambda p, o: actor_forward(actor_net, p, o)[0]  # noqa: E731
    if config.ensemble == 1:
        return jax.vmap(forward, in_axes=(0, -2), out_axes=-2)(actor_params, obs)
    params = jax.tree.map(lambda x: x.reshape(-1, config.ensemble, *x.shape[1:]), actor_params)  # [N, K, ...]
    every = jax.vmap(jax.vmap(forward, in_axes=(0, None), out_axes=-2), in_axes=(0, -2), out_axes=-3)(params, obs)
    return jnp.take_along_axis(every, policy[..., None, None], axis=-2)[..., 0, :]  # [..., N, K, A] -> [..., N, A]


def approx_actions(config: AlgoConfig, approx, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One agent's approximations [N] of every agent's policy on [..., N, O]: mean and log-std [..., N, A]."""
    return jax.vmap(approximation(config).apply, in_axes=(0, -2), out_axes=-2)(approx, obs)


def _infer(config: AlgoConfig, approx, approx_opt, agent: jax.Array, batch: Transition):
    """Agent ``agent``'s step on its approximations of the other agents' policies (eq. 7):
    minimise -log N(a_j | mean_j(o_j), std_j) - lambda * entropy_j, for every j != agent.

    Returns the new approximations, their optimiser state and the mean loss over the others."""
    optimizer = optimizers(config)[0]
    others = (jnp.arange(batch.actions.shape[-2]) != agent).astype(jnp.float32)

    def loss(params, obs, actions):  # one other agent's approximation: [B, O], [B, A]
        mean, log_std = approximation(config).apply(params, obs)
        nll = 0.5 * jnp.square((actions - mean) * jnp.exp(-log_std)) + log_std + 0.5 * jnp.log(2 * jnp.pi)
        entropy = log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e)
        return jnp.mean(nll.sum(-1)) - config.infer_entropy * jnp.mean(entropy.sum(-1))

    losses, grads = jax.vmap(jax.value_and_grad(loss), in_axes=(0, -2, -2))(approx, batch.obs, batch.actions)
    grads = jax.tree.map(lambda g: g * others.reshape(-1, *([1] * (g.ndim - 1))), grads)  # its own: unused, left alone
    updates, approx_opt = jax.vmap(optimizer.update)(grads, approx_opt, approx)
    approx = optax.apply_updates(approx, updates)
    return approx, approx_opt, (losses * others).sum() / jnp.maximum(others.sum(), 1.0)


def inference_error(config: AlgoConfig, state: LearnerState, batch: Transition) -> jax.Array:
    """[N] per agent i: mean absolute difference between its approximations' means and the
    other agents' current deterministic actions (of the sub-policies they ran) on agent i's
    batch [N * K, B, ...]. For the log only: the update never calls it."""
    num_agents = state.approx["params"]["log_std"].shape[0]
    joint = jax.tree.map(lambda x: x.reshape(num_agents, -1, *x.shape[2:]), batch)  # [N, K * B, ...]
    true = act(config, state.actor, joint.obs, joint.policy)  # [N, K * B, N, A]
    guess = jax.vmap(lambda approx, obs: approx_actions(config, approx, obs)[0])(state.approx, joint.obs)
    gap = jnp.abs(guess - true).mean(axis=(1, 3))  # [N (agent i), N (other j)]
    others = 1.0 - jnp.eye(num_agents)
    return (gap * others).sum(-1) / jnp.maximum(others.sum(-1), 1.0)


def _own_target_action(config: AlgoConfig, target_actors, agent: jax.Array, obs: jax.Array, policy: jax.Array | None) -> jax.Array:
    """Agent ``agent``'s target action [B, A] (of the sub-policy it ran) on observations
    [B, N, O], reading no other agent's target actor."""
    actor_net, _ = networks(config)
    own = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, agent * config.ensemble, config.ensemble), target_actors)
    every = jax.vmap(lambda p: actor_forward(actor_net, p, obs[:, agent])[0])(own)  # [K, B, A]
    chosen = jnp.zeros(obs.shape[0], jnp.int32) if policy is None else policy[:, agent]
    return jnp.take_along_axis(every, chosen[None, :, None], axis=0)[0]


def polyak(target, online, tau: float):
    """``(1 - tau) * target + tau * online``, leaf by leaf."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def _agent_update(
    config: AlgoConfig, state: LearnerState, agent: jax.Array, batch: Transition, weights: jax.Array, target_actors, recent: Transition | None
):
    """One agent's update: its slice of ``state`` (its K sub-policies), its K batches
    [K, B, ...] (one per partition), every agent's ``target_actors`` [N * K] and, with
    inferred policies, the ``recent`` transitions its approximations fit. See the module docstring."""
    actor_net, critic_net = networks(config)
    actor_opt, critic_opt = optimizers(config)
    joint = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), batch)  # the K batches as one [K * B, ...]
    info = {}

    approx, approx_opt = state.approx, state.approx_opt
    if config.infer_policies:  # eq. 8: the others' approximations, its own target actor
        approx, approx_opt, info["infer_loss"] = _infer(config, approx, approx_opt, agent, recent)
        inferred = approx_actions(config, approx, joint.next_obs)[0]
        own = _own_target_action(config, target_actors, agent, joint.next_obs, joint.policy)
        next_actions = inferred.at[:, agent].set(own)
    else:
        next_actions = act(config, target_actors, joint.next_obs, joint.policy)  # [K * B, N, A]
    next_q = critic_forward(critic_net, state.target_critic, critic_inputs(config, joint.next_obs, next_actions, agent))
    not_done = 1.0 - joint.terminated.astype(jnp.float32)
    target = jax.lax.stop_gradient(joint.rewards[:, agent] + config.gamma * not_done * next_q)

    def critic_loss(params):
        q = critic_forward(critic_net, params, critic_inputs(config, joint.obs, joint.actions, agent))
        td = jnp.square(q - target)
        return jnp.mean(weights.reshape(-1) * td), (td, q)

    (c_loss, (td, q)), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(state.critic)
    c_updates, critic_opt_state = critic_opt.update(c_grads, state.critic_opt, state.critic)
    critic = optax.apply_updates(state.critic, c_updates)

    def actor_loss(params, obs, actions):  # one sub-policy on its own batch (eq. 11)
        action, pre = actor_forward(actor_net, params, obs[:, agent])
        actions = actions.at[:, agent].set(action)
        q_pi = critic_forward(critic_net, critic, critic_inputs(config, obs, actions, agent))
        return -jnp.mean(q_pi) + config.action_penalty * jnp.mean(jnp.square(pre))

    active = (weights.max(axis=-1) > 0).astype(jnp.float32)  # [K]: sub-policies with a batch
    scaled = lambda params, obs, actions, on: on * actor_loss(params, obs, actions)  # noqa: E731
    a_loss, a_grads = jax.vmap(jax.value_and_grad(scaled))(state.actor, batch.obs, batch.actions, active)
    a_updates, actor_opt_state = jax.vmap(actor_opt.update)(a_grads, state.actor_opt, state.actor)
    actor = optax.apply_updates(state.actor, a_updates)

    new_state = LearnerState(
        actor=actor,
        critic=critic,
        target_actor=polyak(state.target_actor, actor, config.tau),
        target_critic=polyak(state.target_critic, critic, config.tau),
        actor_opt=actor_opt_state,
        critic_opt=critic_opt_state,
        approx=approx,
        approx_opt=approx_opt,
    )
    info.update(critic_loss=c_loss, actor_loss=a_loss.mean(), q_mean=jnp.mean(q), td_loss=td.reshape(weights.shape))
    return new_state, info


def update(config: AlgoConfig, state: LearnerState, batch: Transition, weights: jax.Array | None = None, recent: Transition | None = None):
    """Update every agent once. ``batch`` has a leading group axis [N * K, B, ...]: agent i's
    sample from its sub-policy k's partition at i * K + k (K = 1: agent i's own sample at i);
    ``weights`` [N * K, B] are optional importance weights of the critic loss; ``recent``
    [B', ...] (required with --infer-policies) are the recent transitions every agent's
    approximations fit before its critic step.

    Returns ``(state, info)`` with ``critic_loss``, ``actor_loss`` (mean over sub-policies),
    ``q_mean`` [N], with --infer-policies ``infer_loss`` [N], and the
    per-sample TD loss (Q - y)^2 [N * K, B] for prioritised replay.
    """
    if config.infer_policies and recent is None:
        raise ValueError("update: --infer-policies needs the recent transitions its approximations fit")
    groups, batch_size = batch.rewards.shape[:2]
    if weights is None:
        weights = jnp.ones((groups, batch_size))
    by_agent = lambda tree: jax.tree.map(lambda x: x.reshape(-1, config.ensemble, *x.shape[1:]), tree)  # noqa: E731
    flat = lambda tree: jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), tree)  # noqa: E731
    sliced = state.replace(actor=by_agent(state.actor), target_actor=by_agent(state.target_actor), actor_opt=by_agent(state.actor_opt))
    per_agent = jax.vmap(_agent_update, in_axes=(None, 0, 0, 0, 0, None, None))
    num_agents = groups // config.ensemble
    new, info = per_agent(config, sliced, jnp.arange(num_agents), by_agent(batch), by_agent(weights), state.target_actor, recent)
    new = new.replace(actor=flat(new.actor), target_actor=flat(new.target_actor), actor_opt=flat(new.actor_opt))
    info["td_loss"] = flat(info["td_loss"])
    return new, info
