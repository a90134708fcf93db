"""The off-policy family (``--algo maddpg`` or ``ddpg``, with the MATD3 options): environment,
replay and updates in one jitted chunk; :mod:`roverswarm.algos.maddpg` holds the update and
its equations, :func:`roverswarm.trainer.train` the host loop every family shares.

Shape legend: S seeds, E parallel environments per seed, T steps per episode (25),
N agents, K = T * E transitions per iteration, U = K / update_every updates per iteration.

One *iteration* runs, for every seed at once (vmapped): E fresh episodes of T steps with
exploration noise, their K transitions into the replay (compact records: the rovers' states
and the layout, from which each update's batch rebuilds its observations, see
:mod:`roverswarm.buffers.compact`), then U updates of every agent (once the replay holds
``warmup`` transitions). A *chunk* is ``log_every / E`` iterations in one ``lax.scan``: one
jitted call per 1000 episodes, keyed on :class:`OffPolicyConfig` only. The number of updates
per environment step is the same whatever E is: one update of every agent per
``update_every`` environment steps.

Across swarm sizes (``--scenario paper-2..10`` over ``--network nearest`` with
``--share-parameters``): every episode draws its size as on-policy
(:mod:`roverswarm.episodes`, with ``--size-curriculum``, ``--size-draw-power`` and
failures), N is the range's largest, the replay keeps each episode's masks, and the update
weighs only the rovers that exist (:func:`roverswarm.algos.maddpg.presence`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from functools import partial
from typing import Callable

import jax
import jax.numpy as jnp

from roverswarm.algos.learner import AlgoConfig, LearnerState, act, init_learner, observation_width, observe_batch
from roverswarm.algos.maddpg import inference_error, presence, update
from roverswarm.buffers import compact, make_buffer
from roverswarm.buffers.base import (
    Buffer,
    BufferState,
    Draw,
    ReplayConfig,
    newest_fraction,
    recent_indices,
    update_weights,
)
from roverswarm.env.entities import EntityView, flat_tokens, observe_nearest
from roverswarm.env.mars import ACTION_SIZE, EnvParams, masks_of, observe, step_env
from roverswarm.episodes import executed, exists, reset_all, sizes_of, training_params, training_rewards
from roverswarm.jaxcache import stored_jit
from roverswarm.learners.base import Family, Runner, start_runner
from roverswarm.learners.offpolicy_config import RUN_OPTIONS, OffPolicyConfig, check, configure, run_replay
from roverswarm.metrics import chunk_means, episode_totals, masked_mean, reduce_metric, step_stats

LEARNER_METRICS = ("critic_loss", "actor_loss", "q_mean", "sampled_loss", "sampled_loss_max", "sampled_newest")
"""Per-update metrics in ``metrics.csv`` (mean over agents; ``*_max``: max over agents and updates)."""
INFER_METRICS = ("infer_loss", "infer_error")
"""With --infer-policies: the approximations' loss, and the mean absolute error of their means
against the other agents' current actions on the sampled observations."""


def run_buffer(config, params: EnvParams) -> Buffer:
    """The replay of run ``config`` (:func:`run_replay`), with one partition per sub-policy of
    every agent if K > 1."""
    return make_buffer(run_replay(config, params), params.num_rovers, config.learner.ensemble)


def _buffer(config: OffPolicyConfig, params: EnvParams) -> Buffer:
    return make_buffer(config.buffer, params.num_rovers, config.learner.ensemble)


@functools.lru_cache(maxsize=None)
def view_of(learner: AlgoConfig) -> Callable | None:
    """What a policy of ``learner`` sees, (state, params) -> its view, when it is not the flat
    view: with --network nearest, the --entity-nearest K nearest of each type
    (:func:`~roverswarm.env.entities.observe_nearest`; any swarm size). None: the flat view.
    One function per config, so programs that close over it are reused."""
    if learner.network != "nearest":
        return None
    return partial(observe_nearest, k=learner.entity_nearest, poi_order=learner.poi_order)


@functools.lru_cache(maxsize=None)
def vector_view(learner: AlgoConfig) -> Callable | None:
    """:func:`view_of` as the networks and the replay read it, one vector per rover
    (:func:`~roverswarm.env.entities.flat_tokens`); None: the flat view."""
    view = view_of(learner)
    return None if view is None else lambda state, params: flat_tokens(view(state, params))


def _replay(config: OffPolicyConfig, params: EnvParams) -> BufferState:
    """One seed's empty compact replay; it keeps the observed POIs when the view shows them,
    each episode's masks when sizes are mixed and its failure steps when rovers fail."""
    return compact.init(
        _buffer(config, params),
        params,
        config.num_envs,
        observed=view_of(config.learner) is not None,
        padded=sizes_of(config) is not None,
        failures=_keeps_failures(config),
    )


def _keeps_failures(config: OffPolicyConfig) -> bool:
    """Whether the replay keeps each episode's failure steps: rovers fail in training and the
    view shows it (the flat view does not)."""
    return config.fail_rate > 0 and view_of(config.learner) is not None


def _sizes(learner: AlgoConfig, params: EnvParams) -> tuple[int, int]:
    """(N, O): the agents and the width of one rover's observation in ``learner``'s view."""
    return params.num_rovers, observation_width(learner, params)


def _init_seed(config: OffPolicyConfig, params: EnvParams, key: jax.Array) -> LearnerState:
    """One seed's fresh networks."""
    return init_learner(key, config.learner, *_sizes(config.learner, params))


def _replays(config: OffPolicyConfig, params: EnvParams) -> BufferState:
    """Every seed's empty replay [S, ...]."""
    return jax.vmap(lambda _: _replay(config, params))(jnp.arange(config.seeds))


def init(config: OffPolicyConfig, params: EnvParams, seed: int) -> Runner:
    """Fresh networks and empty replays for every seed of base seed ``seed``."""
    return start_runner(seed, config, params, _init_seed, _replays)


def learners(config: OffPolicyConfig, params: EnvParams) -> LearnerState:
    """Every seed's fresh networks [S, ...] (a checkpoint's template)."""
    return start_runner(0, config, params, _init_seed).learner  # base seed 0's, without replays


def replay_bytes(config, params: EnvParams) -> tuple[int, int, int]:
    """(bytes, transitions, bytes per transition) of every seed's replay of run ``config``: the
    stored transitions and episodes, and the sampling state of the ranked replay and the
    ensembles' partitions, from their shapes (nothing is allocated)."""
    configured = configure(config, params)
    capacity = _buffer(configured, params).capacity
    shapes = jax.eval_shape(lambda: _replay(configured, params))
    per_transition = math.ceil(compact.nbytes(shapes) / capacity)
    return config.seeds * capacity * per_transition, capacity, per_transition


# ----------------------------------------------------------------------------- jitted core


def noise_scale(config: OffPolicyConfig, episodes: jax.Array) -> jax.Array:
    """Exploration noise std after ``episodes`` episodes: linear from --noise-std to --noise-final."""
    if config.noise_decay_episodes == 0:
        return jnp.asarray(config.noise_std)
    frac = jnp.minimum(episodes / config.noise_decay_episodes, 1.0)
    return config.noise_std + frac * (config.noise_final - config.noise_std)


def importance_exponent(config: OffPolicyConfig, episodes: jax.Array, total: jax.Array) -> jax.Array:
    """The importance weights' exponent after ``episodes`` of the run's ``total`` episodes:
    linear from --importance-exponent to 1 at the run's last episode."""
    start = config.buffer.importance_exponent
    return start + jnp.minimum(episodes / total, 1.0) * (1.0 - start)


def collect(
    config: OffPolicyConfig,
    params: EnvParams,
    learner: LearnerState,
    key: jax.Array,
    noise_std: jax.Array,
    episodes: jax.Array | int = 0,
):
    """E episodes of one seed with Gaussian exploration noise of std ``noise_std``, after
    ``episodes`` episodes of training (the size curriculum reads it), each of a size drawn
    from a range scenario and with failures as the run says (:mod:`~roverswarm.episodes`);
    with ensembles, every agent runs one sub-policy per episode, drawn uniformly in each environment.

    Returns the episodes for the replay (:class:`~roverswarm.buffers.compact.Collected`), the
    observations [T, E, N, O] the actors saw and the episode totals [E]
    (:func:`~roverswarm.metrics.episode_totals`, with ``rovers`` [E, N], those that exist).
    """
    k_reset, k_steps = jax.random.split(key)
    params = training_params(config, params)
    state = reset_all(config, params, k_reset, episodes)
    rovers = exists(state)
    view = vector_view(config.learner)

    def see(flat, states):  # what the actors see: the flat view, or the learner's own
        return flat if view is None else jax.vmap(view, in_axes=(0, None))(states, params)

    obs = see(jax.vmap(observe, in_axes=(0, None))(state, params), state)
    k = config.learner.ensemble
    policy = None
    if k > 1:
        policy = jax.random.randint(jax.random.fold_in(key, 1), (config.num_envs, params.num_rovers), 0, k)

    def body(carry, step_key):
        obs, state = carry
        noise = noise_std * jax.random.normal(step_key, (config.num_envs, params.num_rovers, ACTION_SIZE))
        actions = jnp.clip(act(config.learner, learner.actor, obs, policy, learner.obs_norm) + noise, -1.0, 1.0)
        next_obs, next_state, rewards, terminated, _, info = jax.vmap(step_env, in_axes=(0, 0, None))(
            state, executed(config.learner, state, actions, params), params
        )
        learned = training_rewards(config, rewards, info, rovers)
        stored = (compact.rovers_of(state), actions, learned, terminated, state.observed)
        return (see(next_obs, next_state), next_state), (stored, obs, step_stats(rewards, info))

    (_, last), (steps, observations, stats) = jax.lax.scan(
        body, (obs, state), jax.random.split(k_steps, params.max_steps)
    )
    *steps, observed = steps
    kept = {} if view is None else {"observed": observed, "final_observed": last.observed}
    if sizes_of(config) is not None:
        kept["masks"] = masks_of(state)
    if _keeps_failures(config):
        kept["fail_step"] = state.fail_step
    collected = compact.Collected(*steps, compact.layout_of(state), compact.rovers_of(last), policy, **kept)
    return collected, observations, {**episode_totals(stats), "rovers": rovers}


def learn(
    config: OffPolicyConfig,
    params: EnvParams,
    buffer: Buffer,
    learner: LearnerState,
    buffer_state: BufferState,
    key: jax.Array,
    draw: Draw,
    exponent: jax.Array,
):
    """One update of every agent of one seed on the transitions of ``draw``, drawn from its
    replay (observations rebuilt from the compact records); the sampled TD losses go back to
    it. ``key`` draws the recent batch of inference; ``exponent`` is the importance weights'.

    Info per agent [N] (the update's losses and Q; with --infer-policies the approximations'
    error before the update) or per sampling group [N * K] (what was sampled: its mean and
    max TD loss, and the fraction drawn from the newest 10% of the replay). A group with an
    empty partition gets zero weights, so it changes nothing. With --one-batch every group
    learns from the first group's draw, rebuilt once; with mixed sizes the update weighs only
    the rovers that exist (:func:`~roverswarm.algos.maddpg.presence`), and so does the mean
    sampled TD loss."""
    expand = partial(
        compact.expand, buffer_state, params=params, num_envs=config.num_envs, view=vector_view(config.learner)
    )
    if config.learner.one_batch:  # every rover learns from the first group's draw, rebuilt once
        draw = draw.replace(indices=jnp.broadcast_to(draw.indices[:1], draw.indices.shape))
        batch = jax.tree.map(
            lambda x: jnp.broadcast_to(x, (draw.indices.shape[0], *x.shape[1:])), expand(draw.indices[:1])
        )
    else:
        batch = expand(draw.indices)
    weights = update_weights(draw, exponent if config.buffer.importance_weights else None)
    error = recent = None
    if config.learner.infer_policies:
        error = inference_error(config.learner, learner, batch)
        recent = expand(
            recent_indices(
                buffer_state, jax.random.fold_in(key, 1), config.learner.infer_window, config.buffer.batch_size
            )
        )
    learner, info = update(config.learner, learner, batch, weights, recent, jax.random.fold_in(key, 2))
    if error is not None:
        info["infer_error"] = error
    td_loss = info.pop("td_loss")
    buffer_state = buffer.set_priorities(buffer_state, draw.indices, td_loss)
    sampled_loss = td_loss.mean(-1)
    if batch.rovers is not None:  # over the samples whose rover exists
        sampled_loss = masked_mean(td_loss, presence(batch.rovers) > 0, -1)
    info.update(
        sampled_loss=sampled_loss,
        sampled_loss_max=td_loss.max(-1),
        sampled_newest=newest_fraction(buffer_state, draw.indices, 0.1),
    )
    return learner, buffer_state, info


def iteration(config: OffPolicyConfig, params: EnvParams, buffer: Buffer, total: jax.Array, runner: Runner, _):
    """E episodes per seed, their transitions into the replay, then U updates per seed."""
    keys = jax.vmap(lambda k: jax.random.split(k, 3))(runner.key)  # [S, 3, 2]
    noise_std = noise_scale(config, runner.episodes)
    collected, observations, episode = jax.vmap(partial(collect, config, params), in_axes=(0, 0, None, None))(
        runner.learner, keys[:, 0], noise_std, runner.episodes
    )
    flat_obs = observations.reshape(observations.shape[0], -1, *observations.shape[3:])  # [S, K, N, O]
    learner = jax.vmap(partial(observe_batch, config.learner))(runner.learner, flat_obs)
    buffer_state = jax.vmap(partial(compact.add, buffer))(runner.buffer, collected)
    episodes = runner.episodes + config.num_envs
    transitions_seen = episodes * params.max_steps
    num_updates = config.num_envs * params.max_steps // config.update_every
    exponent = importance_exponent(config, runner.episodes, total)

    # jitted, its one trace serves both the branch below and the shapes of its skipped twin (a
    # second trace, by eval_shape, took the tests' tiny chunk 4.3 s to trace instead of 2.5 s);
    # XLA inlines the call
    @jax.jit
    def do_updates(learner, buffer_state, key):
        def one(carry, xs):
            learner, buffer_state = carry
            learner, buffer_state, info = jax.vmap(partial(learn, config, params, buffer), in_axes=(0, 0, 0, 0, None))(
                learner, buffer_state, *xs, exponent
            )
            return (learner, buffer_state), info

        update_keys = jax.vmap(lambda k: jax.random.split(k, num_updates), out_axes=1)(key)  # [U, S]
        # a draw reads nothing the updates change, so all U are drawn at once: [U, S, G, B]
        draws = jax.vmap(jax.vmap(buffer.draw, in_axes=(None, 0)), in_axes=(0, 1), out_axes=1)(
            buffer_state, update_keys
        )
        (learner, buffer_state), info = jax.lax.scan(one, (learner, buffer_state), (update_keys, draws))
        return learner, buffer_state, {k: reduce_metric(k, v, 0) for k, v in info.items()}, jnp.ones(())

    def skip(learner, buffer_state, key):
        shapes = jax.eval_shape(do_updates, learner, buffer_state, key)[2]
        return learner, buffer_state, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes), jnp.zeros(())

    # the warm-up gate is the same for every seed, so this stays a real branch under the seed
    # vmap. The replay's own count follows from the transitions seen, but for a finished run
    # extended (its final checkpoint keeps no replay): its replay warms up again
    stored = jnp.min(buffer_state.size)
    warm = (transitions_seen >= config.warmup) & (stored >= min(config.warmup, config.buffer.buffer_size))
    learner, buffer_state, info, updated = jax.lax.cond(warm, do_updates, skip, learner, buffer_state, keys[:, 1])
    updates = runner.updates + updated.astype(jnp.int32) * num_updates
    due = config.buffer.refresh_due(runner.updates, updates)  # shared by all seeds
    buffer_state = jax.vmap(buffer.refresh, in_axes=(0, None))(buffer_state, due)
    runner = Runner(learner=learner, buffer=buffer_state, key=keys[:, 2], episodes=episodes, updates=updates)
    return runner, (episode, info, updated)


@stored_jit(static_argnums=(0,), donate_argnums=(2,))
def run_chunk(config: OffPolicyConfig, params: EnvParams, runner: Runner, total: jax.Array):
    """``log_every`` episodes per seed of a run of ``total`` episodes (traced: another length
    compiles nothing new); returns the runner and per-seed chunk metrics."""
    iterations = config.log_every // config.num_envs
    buffer = _buffer(config, params)
    runner, (episode, info, updated) = jax.lax.scan(
        partial(iteration, config, params, buffer, total), runner, None, length=iterations
    )
    # episode: [I, S, E, ...] -> mean over iterations and environments, per seed
    metrics = chunk_means(episode, (0, 2))
    count = jnp.maximum(updated.sum(), 1.0)
    for k, v in info.items():  # [I, S, N], over the iterations that updated (the others hold zeros)
        metrics[k] = v.max(axis=0) if k.endswith("_max") else (v * updated[:, None, None]).sum(axis=0) / count
    return runner, metrics


def metric_names(learner: AlgoConfig) -> tuple[str, ...]:
    """The per-update metrics a run with these learner options logs."""
    return LEARNER_METRICS + (INFER_METRICS if learner.infer_policies else ())


def _act(learner: AlgoConfig, weights, obs, plan) -> jax.Array:
    """Actions of ``obs``: the flat view [..., N, O], or the nearest view (:func:`view_of`)."""
    actor, obs_norm = weights
    if isinstance(obs, EntityView):
        obs = flat_tokens(obs)
    return act(learner, actor, obs, plan, obs_norm)


def idle(config, params: EnvParams) -> str | None:
    """Why a run of ``config`` (a ``TrainConfig``) makes no update at all: its episodes end before the replay holds
    ``--warmup`` transitions per seed (the update gate in :func:`iteration`); else None."""
    seen = config.episodes * params.max_steps
    if seen >= config.warmup:
        return None
    return (
        f"no update will run: --episodes {config.episodes} x {params.max_steps} steps give {seen} transitions per "
        f"seed, fewer than --warmup {config.warmup} before the first update; the policy stays as initialised "
        f"(give --episodes >= {-(-config.warmup // params.max_steps)} or a smaller --warmup)"
    )


FAMILY = Family(
    name="off-policy",
    configure=configure,
    check=check,
    init=init,
    run_chunk=run_chunk,
    learners=learners,
    acting=lambda config: config.learner,
    act=_act,
    view=view_of,
    weights=lambda state: (state.actor, state.obs_norm),
    metric_names=lambda config: metric_names(config.learner),
    replay=True,
    replay_buffer=_buffer,
    replay_bytes=replay_bytes,
    options=frozenset(
        [f.name for f in dataclasses.fields(AlgoConfig)]
        + [f.name for f in dataclasses.fields(ReplayConfig)]
        + list(RUN_OPTIONS)
    ),
    misfit="it is a PPO option (--algo mappo or ippo), and this run is --algo {algo}",
    idle=idle,
)
"""MADDPG and DDPG (and the MATD3 options) learning from a replay."""
