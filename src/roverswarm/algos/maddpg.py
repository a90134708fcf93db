"""MADDPG (paper eq. 4-6) and DDPG: one update, the critic's view is the only difference.

Shape legend
    N  agents (rovers), B  batch size, O  observation size, A  action size (2),
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
update is vmapped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from roverswarm.algos.networks import MLP, actor_forward, critic_forward
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


@struct.dataclass
class LearnerState:
    """Every agent's networks, targets and optimiser states, stacked on a leading [N] axis."""

    actor: Any
    critic: Any
    target_actor: Any
    target_critic: Any
    actor_opt: Any
    critic_opt: Any


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


def init_learner(key: jax.Array, config: AlgoConfig, num_agents: int, obs_size: int) -> LearnerState:
    """Fresh networks for ``num_agents`` agents; targets start equal to the online networks."""
    actor_net, critic_net = networks(config)
    actor_opt, critic_opt = optimizers(config)
    k_actor, k_critic = jax.random.split(key)
    obs = jnp.zeros((1, num_agents, obs_size))
    actions = jnp.zeros((1, num_agents, ACTION_SIZE))
    critic_in = critic_inputs(config, obs, actions, jnp.int32(0))
    actor = jax.vmap(actor_net.init, in_axes=(0, None))(jax.random.split(k_actor, num_agents), obs[:, 0])
    critic = jax.vmap(critic_net.init, in_axes=(0, None))(jax.random.split(k_critic, num_agents), critic_in)
    return LearnerState(
        actor=actor,
        critic=critic,
        # copies, not aliases: the training loop donates its state buffers
        target_actor=jax.tree.map(jnp.copy, actor),
        target_critic=jax.tree.map(jnp.copy, critic),
        actor_opt=jax.vmap(actor_opt.init)(actor),
        critic_opt=jax.vmap(critic_opt.init)(critic),
    )


def act(config: AlgoConfig, actor_params, obs: jax.Array) -> jax.Array:
    """Deterministic actions of all agents: [..., N, O] observations -> [..., N, A] actions."""
    actor_net, _ = networks(config)
    forward = lambda p, o: actor_forward(actor_net, p, o)[0]  # noqa: E731
    return jax.vmap(forward, in_axes=(0, -2), out_axes=-2)(actor_params, obs)


def polyak(target, online, tau: float):
    """``(1 - tau) * target + tau * online``, leaf by leaf."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def _agent_update(config: AlgoConfig, state: LearnerState, agent: jax.Array, batch: Transition, weights: jax.Array, target_actors):
    """One agent's update (its slice of ``state``, its own ``batch`` [B, ...]). See module doc."""
    actor_net, critic_net = networks(config)
    actor_opt, critic_opt = optimizers(config)

    next_actions = act(config, target_actors, batch.next_obs)  # [B, N, A]
    next_q = critic_forward(critic_net, state.target_critic, critic_inputs(config, batch.next_obs, next_actions, agent))
    not_done = 1.0 - batch.terminated.astype(jnp.float32)
    target = jax.lax.stop_gradient(batch.rewards[:, agent] + config.gamma * not_done * next_q)

    def critic_loss(params):
        q = critic_forward(critic_net, params, critic_inputs(config, batch.obs, batch.actions, agent))
        td = jnp.square(q - target)
        return jnp.mean(weights * td), (td, q)

    (c_loss, (td, q)), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(state.critic)
    c_updates, critic_opt_state = critic_opt.update(c_grads, state.critic_opt, state.critic)
    critic = optax.apply_updates(state.critic, c_updates)

    def actor_loss(params):
        action, pre = actor_forward(actor_net, params, batch.obs[:, agent])
        actions = batch.actions.at[:, agent].set(action)
        q_pi = critic_forward(critic_net, critic, critic_inputs(config, batch.obs, actions, agent))
        return -jnp.mean(q_pi) + config.action_penalty * jnp.mean(jnp.square(pre))

    a_loss, a_grads = jax.value_and_grad(actor_loss)(state.actor)
    a_updates, actor_opt_state = actor_opt.update(a_grads, state.actor_opt, state.actor)
    actor = optax.apply_updates(state.actor, a_updates)

    new_state = LearnerState(
        actor=actor,
        critic=critic,
        target_actor=polyak(state.target_actor, actor, config.tau),
        target_critic=polyak(state.target_critic, critic, config.tau),
        actor_opt=actor_opt_state,
        critic_opt=critic_opt_state,
    )
    info = {"critic_loss": c_loss, "actor_loss": a_loss, "q_mean": jnp.mean(q), "td_loss": td}
    return new_state, info


def update(config: AlgoConfig, state: LearnerState, batch: Transition, weights: jax.Array | None = None):
    """Update every agent once. ``batch`` has a leading agent axis [N, B, ...] (agent i's own
    sample); ``weights`` [N, B] are optional importance weights of the critic loss.

    Returns ``(state, info)`` with ``critic_loss``, ``actor_loss``, ``q_mean`` [N] and the
    per-sample ``td_loss`` (Q - y)^2 [N, B] for prioritised replay.
    """
    num_agents, batch_size = batch.rewards.shape[:2]
    if weights is None:
        weights = jnp.ones((num_agents, batch_size))
    per_agent = jax.vmap(_agent_update, in_axes=(None, 0, 0, 0, 0, None))
    return per_agent(config, state, jnp.arange(num_agents), batch, weights, state.target_actor)
