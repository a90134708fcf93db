"""The on-policy family (``--algo mappo`` or ``ippo``): rollouts, GAE and PPO updates of every
seed in one jitted chunk, keyed on :class:`~roverswarm.algos.ppo.OnPolicyConfig` only;
:mod:`roverswarm.algos.ppo` holds the networks, the loss and the equations,
:func:`roverswarm.trainer.train` the host loop every family shares.

Shape legend: S seeds, E parallel environments per seed, T steps per episode, N rovers,
O observation size, B = T * E * N samples per iteration.

One *iteration* (per seed): E fresh episodes of T steps with the stochastic policy, GAE per
rover, then ``epochs`` passes over the B samples in ``minibatches`` shuffled minibatches. A
*chunk* is ``log_every / E`` iterations in one ``lax.scan`` with the seeds vmapped.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from roverswarm.algos.learner import AlgoConfig
from roverswarm.algos.normalize import ObsNorm, std, update_obs_norm
from roverswarm.algos.ppo import (
    Batch,
    OnPolicyConfig,
    PPOConfig,
    PPOState,
    act,
    gae,
    gaussian_log_prob,
    init_ppo,
    update_minibatch,
    updates_per_iteration,
)
from roverswarm.algos.ppo_networks import policy_networks
from roverswarm.env.mars import EnvParams, failed_rovers, observation_size, step_env
from roverswarm.episodes import executed, exists, reset_all, training_params, training_rewards
from roverswarm.errors import require, require_finite, require_positive
from roverswarm.jaxcache import stored_jit
from roverswarm.learners.base import Family, Runner, no_replay, start_runner
from roverswarm.metrics import chunk_means, episode_totals, settled_coverage, step_stats
from roverswarm.oracle import greedy_plan, oracle_actions

LOG_STD_RANGE = (-10.0, 2.0)
"""The --init-log-std values accepted: beyond 2 the Gaussian's spread dwarfs the action's [-1, 1]."""
PPO_METRICS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction")
"""Per-update metrics of --algo mappo/ippo (means over the chunk's updates)."""

PPO_USES = (
    "algo",
    "actor_lr",
    "critic_lr",
    "gamma",
    "grad_clip",
    "hidden",
    "trap_shaping",
    "trap_margin",
    "collision_shaping",
    "observe_bonus",
    "unobserved_shaping",
    "shield",
    "network",
    "entity_dim",
    "entity_heads",
    "entity_layers",
    "entity_nearest",
    "poi_order",
)
"""The learner options PPO reads; the other ones are the off-policy family's."""


@struct.dataclass
class Trajectory:
    """E episodes of T steps of one seed: leading [T, E]."""

    obs: Any  # [T, E, N, O], or an entity view [T, E, N, ...]
    actions: jax.Array  # [T, E, N, A] unclipped samples
    log_probs: jax.Array  # [T, E, N]
    rewards: jax.Array  # [T, E, N], 0 after a termination
    next_obs: Any  # as obs
    terminated: jax.Array  # [T, E] bool
    truncated: jax.Array  # [T, E] bool
    mask: jax.Array  # [T, E] float, 1 until (and including) the terminating step
    rovers: jax.Array  # [T, E, N] float, 1 for a rover that exists (all of them unless sizes are mixed)
    acting: jax.Array  # [T, E, N] float, 1 for a rover whose action moves it (0 once it has failed)
    teacher: jax.Array | None = None  # [T, E, N, A] the oracle's actions (--teacher), else None


def check(config, params: EnvParams) -> None:
    """The PPO options of run ``config`` (a ``TrainConfig``) are in range; else :class:`UserError`."""
    ppo = config.ppo
    require_positive(ppo, ("epochs", "minibatches"))
    samples = params.max_steps * config.num_envs * params.num_rovers
    require(
        samples % ppo.minibatches == 0,
        f"--minibatches ({ppo.minibatches}) must divide the samples per iteration "
        f"(episode length x --num-envs x rovers = {samples})",
    )
    require_finite(ppo.clip_eps, 0, "clip-eps", strict=True)
    if ppo.value_clip is not None:
        require_finite(ppo.value_clip, 0, "value-clip", strict=True)
    require(0 <= ppo.gae_lambda <= 1, f"--gae-lambda must be in [0, 1], got {ppo.gae_lambda}")
    for name in ("ent_coef", "vf_coef", "teacher"):
        require_finite(getattr(ppo, name), 0, name.replace("_", "-"))
    for name in ("anneal_episodes", "teacher_episodes"):
        require(getattr(ppo, name) >= 0, f"--{name.replace('_', '-')} must be >= 0, got {getattr(ppo, name)}")
    require(
        not ppo.teacher_episodes or ppo.teacher > 0,
        f"--teacher-episodes decays the --teacher weight; give --teacher > 0 with it (got --teacher {ppo.teacher})",
    )
    require(
        math.isfinite(ppo.init_log_std) and LOG_STD_RANGE[0] <= ppo.init_log_std <= LOG_STD_RANGE[1],
        f"--init-log-std must be in [{LOG_STD_RANGE[0]}, {LOG_STD_RANGE[1]}] (a standard deviation from "
        f"{math.exp(LOG_STD_RANGE[0]):.1e} to {math.exp(LOG_STD_RANGE[1]):.1f} for actions in [-1, 1]), got "
        f"{ppo.init_log_std}",
    )
    require(ppo.activation in ("tanh", "relu"), f"--activation must be 'tanh' or 'relu', got '{ppo.activation}'")
    require(
        not ppo.swarm_value or (config.learner.network == "nearest" and config.learner.algo == "mappo"),
        f"--swarm-value is MAPPO's centralised value over --network nearest; got --algo {config.learner.algo} "
        f"--network {config.learner.network} (add --no-swarm-value)",
    )


def configure(config, params: EnvParams) -> OnPolicyConfig:
    """The on-policy config of run ``config`` (a ``TrainConfig``)."""
    return OnPolicyConfig(**{f.name: getattr(config, f.name) for f in dataclasses.fields(OnPolicyConfig)})


def _init_seed(config: OnPolicyConfig, params: EnvParams, key: jax.Array) -> PPOState:
    """One seed's fresh networks (the flat view's shaped by N and the observation's width; an
    entity network's by neither)."""
    return init_ppo(key, config, params.num_rovers, observation_size(params))


def init(config: OnPolicyConfig, params: EnvParams, seed: int) -> Runner:
    """Fresh networks for every seed of base seed ``seed`` (keys derived from (seed, s) as
    off-policy); no replay."""
    return start_runner(seed, config, params, _init_seed)


def learners(config: OnPolicyConfig, params: EnvParams) -> PPOState:
    """Every seed's fresh networks [S, ...] (a checkpoint's template)."""
    return start_runner(0, config, params, _init_seed).learner  # base seed 0's, without replays


def _where_env(done: jax.Array, old, new):
    """Per environment [E]: ``old`` where ``done``, else ``new`` (pytrees with leading [E])."""
    return jax.tree.map(lambda o, n: jnp.where(done.reshape(-1, *([1] * (n.ndim - 1))), o, n), old, new)


def collect(
    config: OnPolicyConfig, params: EnvParams, actor, key: jax.Array, episodes: jax.Array | int = 0
) -> tuple[Trajectory, dict[str, jax.Array]]:
    """E fresh episodes of T steps of one seed with the stochastic policy ``actor``, after
    ``episodes`` episodes of training (the size curriculum reads it).

    After a termination (mission mode) an episode stands still and its steps are masked out.
    With --teacher, the trajectory also holds the oracle's action in every state.
    Returns the trajectory [T, E, ...] and per-episode stats [E], as the MADDPG trainer's:
    ``episode_reward``, ``agent_rewards`` [E, N], ``collisions``, ``trap_contacts``,
    ``coverage_distance`` (at the last step) and ``rovers`` [E, N] (those that exist).
    """
    nets = policy_networks(config.learner, config.ppo)
    observe_all = jax.vmap(nets.observe, in_axes=(0, None))
    params = training_params(config, params)
    k_reset, k_steps = jax.random.split(key)
    env_state = reset_all(config, params, k_reset, episodes)
    obs = observe_all(env_state, params)
    rovers = exists(env_state)
    plan = jax.vmap(greedy_plan, in_axes=(0, None))(env_state, params) if config.ppo.teacher else None

    def body(carry, step_key):
        obs, env_state, done = carry
        mean, log_std = nets.policy(actor, nets.actor_inputs(obs))
        actions = mean + jnp.exp(log_std) * jax.random.normal(step_key, mean.shape)
        _, next_state, rewards, terminated, truncated, info = jax.vmap(step_env, in_axes=(0, 0, None))(
            env_state, executed(config.learner, env_state, actions, params), params
        )
        next_obs = observe_all(next_state, params)
        live = ~done
        step = Trajectory(
            obs=obs,
            actions=actions,
            log_probs=gaussian_log_prob(actions, mean, log_std),
            rewards=training_rewards(config, rewards, info, rovers) * live[:, None],
            next_obs=next_obs,
            terminated=terminated & live,
            truncated=truncated & live,
            mask=live.astype(jnp.float32),
            rovers=rovers.astype(jnp.float32),
            acting=(~jax.vmap(failed_rovers)(env_state)).astype(jnp.float32),
            teacher=None if plan is None else jax.vmap(oracle_actions, in_axes=(0, 0, None))(env_state, plan, params),
        )
        stats = step_stats(rewards, info, live, jax.vmap(settled_coverage, in_axes=(0, None))(env_state, params))
        carry = (_where_env(done, obs, next_obs), _where_env(done, env_state, next_state), done | terminated)
        return carry, (step, stats)

    done = jnp.zeros((config.num_envs,), bool)
    _, (traj, stats) = jax.lax.scan(body, (obs, env_state, done), jax.random.split(k_steps, params.max_steps))
    return traj, {**episode_totals(stats), "rovers": rovers}


def values_of(config: OnPolicyConfig, critic, returns: ObsNorm, obs) -> tuple[jax.Array, jax.Array]:
    """Every rover's value [..., N] of observations [..., N, ...], de-standardised with
    --value-norm, and the value network's own output (the same without it)."""
    nets = policy_networks(config.learner, config.ppo)
    output = nets.value(critic, nets.critic_inputs(obs))
    if config.ppo.value_norm:
        return returns.mean[0] + std(returns)[0] * output, output
    return output, output


def make_batch(config: OnPolicyConfig, state: PPOState, traj: Trajectory) -> tuple[Batch, ObsNorm]:
    """GAE per rover on ``traj`` and the flat [B] batch of the update; with --value-norm the
    value-target statistics are updated first and targets standardised by them (the values: the
    value network's own output, the centre of --value-clip's window). Samples of rovers that
    do not exist (mixed sizes) are masked out like steps after a termination; a failed rover's
    are out of the policy's loss (its action moves nothing), not the value's. Returns the batch
    and the (updated) value-target statistics."""
    nets = policy_networks(config.learner, config.ppo)
    values, outputs = values_of(config, state.critic, state.returns, traj.obs)  # [T, E, N]
    next_values, _ = values_of(config, state.critic, state.returns, traj.next_obs)
    per_rover = lambda x: jnp.broadcast_to(x[..., None], values.shape)  # noqa: E731
    advantages, targets = gae(
        traj.rewards,
        values,
        next_values,
        per_rover(traj.terminated),
        config.learner.gamma,
        config.ppo.gae_lambda,
        per_rover(traj.truncated),
    )
    mask = per_rover(traj.mask) * traj.rovers
    returns = state.returns
    if config.ppo.value_norm:
        returns = update_obs_norm(returns, targets[..., None], mask)
        targets = (targets - returns.mean[0]) / std(returns)[0]
    flat = lambda tree: jax.tree.map(lambda x: x.reshape(-1, *x.shape[3:]), tree)  # noqa: E731
    batch = Batch(
        actor_inputs=flat(nets.actor_inputs(traj.obs)),
        critic_inputs=flat(nets.critic_inputs(traj.obs)),
        actions=flat(traj.actions),
        log_probs=flat(traj.log_probs),
        advantages=flat(advantages),
        targets=flat(targets),
        values=flat(outputs),
        mask=flat(mask * size_weights(traj.rovers) if config.ppo.balance_sizes else mask),
        acting=flat(traj.acting),
        teacher=flat(traj.teacher),
    )
    return batch, returns


def size_weights(rovers: jax.Array) -> jax.Array:
    """--balance-sizes: each sample's weight (largest size) / (its swarm's size), [..., N] from
    the rovers' existence mask [..., N]."""
    return rovers.shape[-1] / jnp.maximum(jnp.sum(rovers, axis=-1, keepdims=True), 1.0)


def iteration(config: OnPolicyConfig, params: EnvParams, state: PPOState, xs: tuple[jax.Array, jax.Array]):
    """One PPO iteration of one seed (``xs``: its key and the episodes trained before it): E
    episodes, GAE, ``epochs`` x ``minibatches`` updates.

    Returns the state and ``(episode stats [E], learner info (means over the updates))``."""
    key, episodes = xs
    k_collect, k_shuffle = jax.random.split(key)
    traj, episode = collect(config, params, state.actor, k_collect, episodes)
    batch, returns = make_batch(config, state, traj)
    state = state.replace(returns=returns)
    size = batch.mask.shape[0]

    def epoch(state, key):
        order = jax.random.permutation(key, size)
        minibatches = jax.tree.map(lambda x: x[order].reshape(config.ppo.minibatches, -1, *x.shape[1:]), batch)
        return jax.lax.scan(partial(update_minibatch, config), state, minibatches)

    state, info = jax.lax.scan(epoch, state, jax.random.split(k_shuffle, config.ppo.epochs))
    return state, (episode, jax.tree.map(jnp.mean, info))


@stored_jit(static_argnums=(0,), donate_argnums=(2,))
def run_chunk(config: OnPolicyConfig, params: EnvParams, runner: Runner, total: jax.Array | None = None):
    """``log_every`` episodes per seed (``log_every / num_envs`` iterations, seeds vmapped);
    returns the runner and per-seed chunk metrics [S]: the episode totals and
    :data:`PPO_METRICS` (means over the chunk's episodes and updates). The run's length
    ``total`` changes nothing here (annealing counts --anneal-episodes)."""
    iterations = config.log_every // config.num_envs

    def one_seed(state: PPOState, key: jax.Array):
        keys = jax.random.split(key, iterations + 1)
        episodes = runner.episodes + config.num_envs * jnp.arange(iterations)
        state, (episode, info) = jax.lax.scan(partial(iteration, config, params), state, (keys[1:], episodes))
        metrics = chunk_means(episode, (0, 1))  # [I, E, ...]
        metrics.update({k: v.mean(axis=0) for k, v in info.items()})  # [I]
        return state, metrics, keys[0]

    learner, metrics, keys = jax.vmap(one_seed)(runner.learner, runner.key)
    runner = runner.replace(
        learner=learner,
        key=keys,
        episodes=runner.episodes + config.log_every,
        updates=runner.updates + iterations * updates_per_iteration(config.ppo),
    )
    return runner, metrics


def _act(acting: tuple[AlgoConfig, PPOConfig], weights, obs, plan) -> jax.Array:
    return act(*acting, weights[0], obs)


def check_training(config) -> None:
    """Episodes past ``--anneal-episodes`` would train at learning rate 0: refused (an
    extended run keeps its own horizon: docs/training.md#extending-a-run)."""
    episodes, anneal = config.episodes, config.ppo.anneal_episodes
    require(
        not anneal or episodes <= anneal,
        f"--episodes {episodes} goes past --anneal-episodes {anneal}, where the learning rates reach 0: the last "
        f"{episodes - anneal} episodes per seed would train nothing; give --anneal-episodes >= {episodes} "
        f"(or 0: constant rates) with it, or at most --episodes {anneal} to extend a run annealed over {anneal}",
    )


def _view(acting: tuple[AlgoConfig, PPOConfig]):
    nets = policy_networks(*acting)
    return nets.observe if nets.any_size else None


FAMILY = Family(
    name="on-policy",
    configure=configure,
    check=check,
    init=init,
    run_chunk=run_chunk,
    learners=learners,
    acting=lambda config: (config.learner, config.ppo),
    act=_act,
    view=_view,
    weights=lambda state: (state.actor, None),  # no observation normaliser
    metric_names=lambda config: PPO_METRICS + (("imitation_loss",) if config.ppo.teacher else ()),
    replay=False,
    replay_buffer=lambda program, params: None,
    replay_bytes=no_replay,
    options=frozenset(PPO_USES + tuple(f.name for f in dataclasses.fields(PPOConfig))),
    misfit="--algo {algo} learns on-policy (start from --preset {algo})",
    check_training=check_training,
)
"""MAPPO and IPPO: PPO with one shared actor and a centralised or local value."""
