"""MAPPO and IPPO: PPO with a clipped objective and GAE, one actor shared by every rover.

Shape legend
    S  seeds (vmapped), E  parallel environments per seed, T  steps per episode (25),
    N  rovers (agents), O  observation size of one rover, A  action size (2),
    B  samples per iteration = T * E * N (one per rover and step), M  minibatches,
    D  value input size: N * O + N for MAPPO (every rover's observation and the rover's
       one-hot index), O + N for IPPO (its own observation and its one-hot index).

Policy: one Gaussian actor shared by all rovers, its input the rover's own observation and
its one-hot index, pi(u | o_i, i) = Normal(mu(o_i, i), exp(log_std)) with a learned,
state-independent log-std. The environment receives clip(u, -1, 1); the log-probability is
that of the unclipped sample u. The deterministic action is clip(mu, -1, 1).

Value: one network shared by all rovers. MAPPO: V(o_1..o_N, i), centralised (every rover
gets its own value of the shared state). IPPO: V(o_i, i), local.

The presets train on the environment's nearest-first view (``--nearest-first``): each
rover's POIs, traps and other rovers ordered by distance, which makes "head for the nearest
POI" one fixed input slot. On ``paper-5`` it doubled what MAPPO reached in 10,000 episodes
(normalised score 0.46 against 0.21 to 0.24 in index order, 2 seeds).

One *iteration* (per seed, :mod:`roverswarm.onpolicy`): E fresh episodes of T steps, then ``epochs`` passes over the
B samples in M shuffled minibatches. Each rover has its own advantage (GAE, per rover):

    delta_t = r_t + gamma * (1 - term_t) * V'_t - V_t          V'_t = V(next observation at t)
    A_t     = delta_t + gamma * lambda * (1 - term_t) * (1 - trunc_t) * A_{t+1}
    R_t     = A_t + V_t                                         (the value target)

The time limit is a truncation: the last step bootstraps with the value of its next
observation. A termination (mission mode) stops the bootstrap; the steps after it in the
fixed-length episode are masked out of the loss and the metrics. On a minibatch, with
rho = pi(u | o) / pi_old(u | o) and advantages normalised to zero mean and unit std:

    policy loss  L_pi = -mean min(rho * A, clip(rho, 1 - eps, 1 + eps) * A)
    value loss   L_V  = 0.5 * mean max((V - R)^2, (V_old + clip(V - V_old, -eps_V, eps_V) - R)^2)
                        (plain 0.5 * mean (V - R)^2 without value clipping)
    total             = L_pi + c_V * L_V - c_H * mean H[pi]

With --teacher w (an option, learning from more than the reward) the total gains
w * mean |mu(o) - u*|^2, u* the oracle's action in the rollout's state; with
--teacher-episodes E, w decays linearly to 0 over the first E episodes (kickstarting).

Actor and value network each have their own Adam (gradient norm clipped per network).
With ``value_norm`` (MAPPO's ValueNorm) the value network predicts returns standardised by a
running mean and variance of the value targets; V above is then the de-standardised output
and L_V is computed on standardised values and targets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from roverswarm.algos.learner import AlgoConfig
from roverswarm.algos.normalize import ObsNorm, init_obs_norm
from roverswarm.algos.ppo_networks import policy_networks
from roverswarm.episodes import EpisodeOptions
from roverswarm.metrics import masked_mean

# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class PPOConfig:
    """What only PPO uses (``--algo mappo`` or ``ippo``); learning rates, gamma, hidden widths
    and the gradient clip are the learner's (``--actor-lr`` ...), the parallel environments
    ``--num-envs``. Defaults: the MAPPO paper's MPE settings (tanh networks, GAE lambda 0.95,
    clip 0.2, value normalisation), tuned on ``paper-5``: 5 epochs x 4 minibatches, no value
    clipping, a small entropy bonus."""

    epochs: int = 5
    """Passes over an iteration's samples."""
    minibatches: int = 4
    """Minibatches per pass (must divide episode length x --num-envs x rovers)."""
    anneal_episodes: int = 0
    """Episodes per seed over which both learning rates decay linearly to 0; 0 keeps them constant."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    clip_eps: float = 0.2
    """Clip range of the probability ratio."""
    value_clip: float | None = None
    """Clip range of the value change around the rollout's value (in standardised units with
    --value-norm); None turns value clipping off."""
    ent_coef: float = 0.005
    """Weight of the entropy bonus."""
    vf_coef: float = 1.0
    """Weight of the value loss. Actor and value network have their own Adam, so it only
    scales the value gradient before its norm is clipped."""
    activation: Literal["tanh", "relu"] = "tanh"
    """Activation of the hidden layers (`--network mlp` and `nearest`; the attention network of
    `--network entity` has its own: ReLU, and Flax's default initialisation)."""
    init_log_std: float = -0.5
    """Initial log standard deviation of the Gaussian policy (per action dimension)."""
    value_norm: bool = True
    """Standardise value targets by a running mean and variance (MAPPO's ValueNorm)."""
    normalize_advantages: bool = True
    """Standardise advantages per minibatch."""
    balance_sizes: bool = False
    """With mixed swarm sizes: weight each rover's samples by (largest size) / (its swarm's
    size) in the loss, so that every episode counts the same whatever its size (unweighted, a
    swarm of 10 gives 5 times the samples of a swarm of 2)."""
    swarm_value: bool = False
    """MAPPO with ``--network nearest``: the value sees the whole swarm besides the rover's own
    view (the mean of every rover's view and the swarm's size), a centralised value for any
    size; off, the value sees what the actor sees."""
    teacher: float = 0.0
    """Weight of an imitation loss beside PPO's: the squared distance of the policy's mean action
    from the oracle's (:mod:`roverswarm.oracle`, its assignment drawn greedily per episode) in
    the states of the rollout, which the policy itself drives (DAgger's way: the student
    drives, the oracle labels). 0 learns from the reward alone."""
    teacher_episodes: int = 0
    """Episodes per seed over which the --teacher weight decays linearly to 0 (kickstarting:
    the oracle teaches first, the reward alone finishes); 0 keeps the weight constant."""


@dataclass(frozen=True)
class OnPolicyConfig(EpisodeOptions):
    """What shapes the on-policy family's chunk, and all this module reads: the fields of the
    run's :class:`~roverswarm.config.TrainConfig` of the same names (so a ``TrainConfig``
    serves wherever one is read), the episodes' among them."""

    learner: AlgoConfig
    ppo: PPOConfig
    seeds: int
    num_envs: int
    log_every: int


def updates_per_iteration(config: PPOConfig) -> int:
    """Optimiser steps of each network per iteration: epochs x minibatches."""
    return config.epochs * config.minibatches


def gaussian_log_prob(actions: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """log N(actions | mean, exp(log_std)) summed over the action axis: [..., A] -> [...]."""
    z = (actions - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * jnp.square(z) - log_std - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy of a diagonal Gaussian, summed over the action axis: [..., A] -> [...]."""
    return jnp.sum(log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e), axis=-1)


def act(learner: AlgoConfig, config: PPOConfig, actor_params, obs) -> jax.Array:
    """Deterministic actions clip(mean, -1, 1) of all rovers: observations of the network kind's
    view ([..., N, O], or an entity view) -> [..., N, A]."""
    nets = policy_networks(learner, config)
    mean, _ = nets.policy(actor_params, nets.actor_inputs(obs))
    return jnp.clip(mean, -1.0, 1.0)


# ----------------------------------------------------------------------------- learner state


@struct.dataclass
class PPOState:
    """One seed's networks and optimiser states (leading [S] axis when seeds are vmapped)."""

    actor: Any  # actor parameters (shared by all rovers), including "log_std" [A]
    critic: Any  # value network parameters (shared by all rovers)
    actor_opt: Any  # Adam state of the actor
    critic_opt: Any  # Adam state of the value network
    returns: ObsNorm  # running mean and variance of the value targets [1] (--value-norm)


def _updates(config: OnPolicyConfig, episodes: int) -> int:
    """Gradient steps per seed in ``episodes`` episodes (at least one iteration's)."""
    return max(episodes // config.num_envs, 1) * updates_per_iteration(config.ppo)


def teacher_weight(config: OnPolicyConfig, actor_opt: Any) -> jax.Array | float:
    """The --teacher weight at the actor's current gradient step (Adam's count in
    ``actor_opt``): constant, or with --teacher-episodes linear from --teacher to 0."""
    ppo = config.ppo
    if ppo.teacher_episodes == 0:
        return ppo.teacher
    (adam,) = [s for s in jax.tree.leaves(actor_opt, is_leaf=_is_adam) if _is_adam(s)]
    return optax.linear_schedule(ppo.teacher, 0.0, _updates(config, ppo.teacher_episodes))(adam.count)


def _is_adam(node: Any) -> bool:
    return isinstance(node, optax.ScaleByAdamState)


def optimizers(config: OnPolicyConfig) -> tuple[optax.GradientTransformation, optax.GradientTransformation]:
    """Adam (eps 1e-5) with global-norm clipping (--grad-clip), for (actor, value network);
    with --anneal-episodes the learning rates decay linearly to 0 over that many episodes."""
    learner, ppo = config.learner, config.ppo

    def make(lr: float) -> optax.GradientTransformation:
        rate: Any = lr
        if ppo.anneal_episodes > 0:
            rate = optax.linear_schedule(lr, 0.0, _updates(config, ppo.anneal_episodes))
        return optax.chain(optax.clip_by_global_norm(learner.grad_clip), optax.adam(rate, eps=1e-5))

    return make(learner.actor_lr), make(learner.critic_lr)


def init_ppo(key: jax.Array, config: OnPolicyConfig, num_rovers: int, obs_size: int) -> PPOState:
    """Fresh networks of one seed (``num_rovers`` and ``obs_size`` shape the flat view's
    networks; an entity network's parameters depend on neither)."""
    actor_opt, critic_opt = optimizers(config)
    actor, critic = policy_networks(config.learner, config.ppo).init(key, num_rovers, obs_size)
    return PPOState(
        actor=actor,
        critic=critic,
        actor_opt=actor_opt.init(actor),
        critic_opt=critic_opt.init(critic),
        returns=init_obs_norm(1),
    )


# ----------------------------------------------------------------------------- GAE and loss


def gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    gamma: float,
    lam: float,
    truncated: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation along the leading time axis (a reverse ``lax.scan``).

    ``rewards``, ``values`` (V of the observation at t), ``next_values`` (V of the observation
    after step t, also across a time-limit truncation) are [T, ...]; ``terminated`` and
    ``truncated`` (optional; episode ended at t by the time limit) are [T, ...] flags. A
    termination stops the bootstrap and the trace; a truncation keeps the bootstrap
    (``next_values``) and stops only the trace, so several episodes may follow each other
    along T. Nothing follows the last step: its advantage is its delta.

    Returns ``(advantages, returns)`` [T, ...], returns = advantages + values.
    """
    not_term = 1.0 - terminated.astype(values.dtype)
    cont = not_term if truncated is None else not_term * (1.0 - truncated.astype(values.dtype))
    deltas = rewards + gamma * not_term * next_values - values

    def body(next_adv, xs):
        delta, c = xs
        adv = delta + gamma * lam * c * next_adv
        return adv, adv

    _, advantages = jax.lax.scan(body, jnp.zeros_like(values[0]), (deltas, cont), reverse=True)
    return advantages, advantages + values


@struct.dataclass
class Batch:
    """Samples of the update, one per rover and step, flattened: leading [B] (or a minibatch)."""

    actor_inputs: Any  # [B, ...] what the actor sees of each sample (e.g. [B, O + N])
    critic_inputs: Any  # [B, ...] what the value network sees (e.g. [B, D])
    actions: jax.Array  # [B, A] unclipped Gaussian samples
    log_probs: jax.Array  # [B] under the rollout's policy
    advantages: jax.Array  # [B]
    targets: jax.Array  # [B] value targets R (standardised with --value-norm)
    values: jax.Array  # [B] the value network's output at the rollout, V_old (standardised with --value-norm)
    mask: jax.Array  # [B] sample weights: 0 after a termination or for no rover, else 1 (--balance-sizes: B / N)
    teacher: jax.Array | None = None  # [B, A] the oracle's actions (--teacher), else None
    acting: jax.Array | None = None  # [B] 0 where the rover had failed (its action moved nothing), else 1; None: all 1


def ppo_loss(
    config: PPOConfig, log_probs: jax.Array, entropy: jax.Array, values: jax.Array, batch: Batch
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The PPO loss on one minibatch (see the module docstring).

    ``log_probs`` [B] of the batch's actions, ``entropy`` [B] and ``values`` [B] under the
    current networks; ``batch`` holds the rollout's log-probabilities, advantages, value
    targets, values and mask (means, and the advantages' standardisation, are weighted by the
    mask: over the masked-in samples, each by its --balance-sizes weight). The policy's terms
    leave out the samples of failed rovers (``batch.acting``), whose actions moved nothing; the
    value's keep them (the swarm's reward still follows).

    Returns ``(total, parts)``, parts: ``policy_loss``, ``value_loss``, ``entropy``,
    ``approx_kl`` (mean of (rho - 1) - log rho), ``clip_fraction`` (|rho - 1| > eps).
    """
    mask = batch.mask
    acts = policy_mask(batch)
    adv = batch.advantages
    if config.normalize_advantages:
        mean = masked_mean(adv, acts)
        std = jnp.sqrt(masked_mean(jnp.square(adv - mean), acts))
        adv = (adv - mean) / (std + 1e-8)
    log_ratio = log_probs - batch.log_probs
    ratio = jnp.exp(log_ratio)
    surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - config.clip_eps, 1 + config.clip_eps) * adv)
    policy_loss = -masked_mean(surrogate, acts)
    value_error = jnp.square(values - batch.targets)
    if config.value_clip is not None:
        clipped = batch.values + jnp.clip(values - batch.values, -config.value_clip, config.value_clip)
        value_error = jnp.maximum(value_error, jnp.square(clipped - batch.targets))
    value_loss = 0.5 * masked_mean(value_error, mask)
    mean_entropy = masked_mean(entropy, acts)
    total = policy_loss + config.vf_coef * value_loss - config.ent_coef * mean_entropy
    parts = {
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy": mean_entropy,
        "approx_kl": masked_mean((ratio - 1.0) - log_ratio, acts),
        "clip_fraction": masked_mean((jnp.abs(ratio - 1.0) > config.clip_eps).astype(jnp.float32), acts),
    }
    return total, parts


def policy_mask(batch: Batch) -> jax.Array:
    """[B] the weights of the policy's terms: the batch's mask without the failed rovers' samples."""
    return batch.mask if batch.acting is None else batch.mask * batch.acting


def update_minibatch(config: OnPolicyConfig, state: PPOState, batch: Batch) -> tuple[PPOState, dict[str, jax.Array]]:
    """One gradient step of the actor and of the value network on ``batch``; returns the
    state (networks and optimiser states changed) and :func:`ppo_loss`'s parts (with
    --teacher, also ``imitation_loss``: the mean squared distance of the mean action from the
    oracle's, the samples weighted as in the PPO loss)."""
    nets = policy_networks(config.learner, config.ppo)
    actor_opt, critic_opt = optimizers(config)

    def loss(actor, critic):
        mean, log_std = nets.policy(actor, batch.actor_inputs)
        log_probs = gaussian_log_prob(batch.actions, mean, log_std)
        entropy = jnp.broadcast_to(gaussian_entropy(log_std), log_probs.shape)
        values = nets.value(critic, batch.critic_inputs)
        total, parts = ppo_loss(config.ppo, log_probs, entropy, values, batch)
        if batch.teacher is None:
            return total, parts
        imitation = masked_mean(jnp.sum(jnp.square(mean - batch.teacher), axis=-1), policy_mask(batch))
        weight = teacher_weight(config, state.actor_opt)
        return total + weight * imitation, {**parts, "imitation_loss": imitation}

    (_, parts), (actor_grads, critic_grads) = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(
        state.actor, state.critic
    )
    actor_updates, actor_opt_state = actor_opt.update(actor_grads, state.actor_opt, state.actor)
    critic_updates, critic_opt_state = critic_opt.update(critic_grads, state.critic_opt, state.critic)
    state = state.replace(
        actor=optax.apply_updates(state.actor, actor_updates),
        critic=optax.apply_updates(state.critic, critic_updates),
        actor_opt=actor_opt_state,
        critic_opt=critic_opt_state,
    )
    return state, parts
