"""Fused, jitted training of MADDPG/DDPG: environment, replay and updates in one XLA program.

Shape legend: S seeds, E parallel environments per seed, T steps per episode (25),
N agents, K = T * E transitions per iteration, U = K / update_every updates per iteration.

One *iteration* runs, for every seed at once (vmapped): E fresh episodes of T steps with
exploration noise, their K transitions into the replay (compact records: the rovers' states
and the layout, from which each update's batch rebuilds its observations, see
:mod:`roverswarm.buffers.compact`), then U updates of every agent (once the replay holds
``warmup`` transitions). A *chunk* is ``log_every / E`` iterations in one
``lax.scan``: one jitted call per 1000 episodes. The Python loop around the chunks only logs,
checkpoints and draws progress. The number of updates per environment step is the same
whatever E is: one update of every agent per ``update_every`` environment steps.

With ``--algo mappo`` or ``ippo`` a chunk is :func:`roverswarm.onpolicy.run_chunk` instead;
the host loop of :func:`train` (metrics, checkpoints, resume, signals) is the same.
"""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from tensorboardX import SummaryWriter

from roverswarm import onpolicy
from roverswarm.algos.learner import ON_POLICY, LearnerState, act, init_learner, observe_batch
from roverswarm.algos.maddpg import inference_error, update
from roverswarm.algos.ppo import PPOState
from roverswarm.buffers import compact, make_buffer
from roverswarm.buffers.base import Buffer, BufferState, Draw, importance_weights, newest_fraction, recent_indices
from roverswarm.config import TrainConfig, config_to_json, fields_by_name, validate, with_mission_text
from roverswarm.env.mars import ACTION_SIZE, EnvParams, observation_size, reset, step_env
from roverswarm.errors import RunStopped, require
from roverswarm.limits import check_training_memory, read_config
from roverswarm.rollout import contact_counts, shaped_rewards
from roverswarm.runs import (
    CHECKPOINT,
    CONFIG,
    METRICS,
    Runner,
    atomic_write,
    checkpoint_changes,
    folder_lock,
    load_checkpoint,
    metric_rows,
    plot_learning_curve,
    read_metrics,
    reduce_metric,
    save_checkpoint,
    start_runner,
    write_csv,
)


# ----------------------------------------------------------------------------- jitted core


def run_buffer(config: TrainConfig, params: EnvParams) -> Buffer:
    """The replay of ``config``, with one partition per sub-policy of every agent if K > 1.
    It never holds more than the run's own transitions (``--episodes`` x episode length per
    seed), whatever ``--buffer-size`` says: a replay that never fills draws what a larger one
    would, so a short run gets the same numbers from a fraction of the memory."""
    capacity = min(config.buffer.buffer_size, config.episodes * params.max_steps)
    replay = dataclasses.replace(config.buffer, buffer_size=capacity)
    return make_buffer(replay, params.num_rovers, config.learner.ensemble)


def init_runner(config: TrainConfig, params: EnvParams, buffer: Buffer) -> Runner:
    """Fresh networks and empty replays for every seed."""
    buffers = jax.vmap(lambda _: compact.init(buffer, params, config.num_envs))(jnp.arange(config.seeds))
    sizes = (params.num_rovers, observation_size(params))
    return start_runner(config, lambda key: init_learner(key, config.learner, *sizes), buffers)


def noise_scale(config: TrainConfig, episodes: jax.Array) -> jax.Array:
    """Exploration noise std after ``episodes`` episodes: linear from --noise-std to --noise-final."""
    if config.noise_decay_episodes == 0:
        return jnp.asarray(config.noise_std)
    frac = jnp.minimum(episodes / config.noise_decay_episodes, 1.0)
    return config.noise_std + frac * (config.noise_final - config.noise_std)


def importance_exponent(config: TrainConfig, episodes: jax.Array) -> jax.Array:
    """The importance weights' exponent after ``episodes`` episodes: linear from
    --importance-exponent to 1 at the run's last episode."""
    start = config.buffer.importance_exponent
    return start + jnp.minimum(episodes / config.episodes, 1.0) * (1.0 - start)


def collect(config: TrainConfig, params: EnvParams, learner: LearnerState, key: jax.Array, noise_std: jax.Array):
    """E episodes of one seed with Gaussian exploration noise of std ``noise_std``; with
    ensembles, every agent runs one sub-policy per episode, drawn uniformly in each environment.

    Returns the episodes for the replay (:class:`~roverswarm.buffers.compact.Collected`), the
    observations [T, E, N, O] the actors saw and per-episode stats [E] (reward summed over
    agents and steps, per-agent rewards [E, N], collisions, trap contacts, final coverage
    distance).
    """
    k_reset, k_steps = jax.random.split(key)
    obs, state = jax.vmap(reset, in_axes=(0, None))(jax.random.split(k_reset, config.num_envs), params)
    k = config.learner.ensemble
    policy = None
    if k > 1:
        policy = jax.random.randint(jax.random.fold_in(key, 1), (config.num_envs, params.num_rovers), 0, k)

    def body(carry, step_key):
        obs, state = carry
        noise = noise_std * jax.random.normal(step_key, (config.num_envs, params.num_rovers, ACTION_SIZE))
        actions = jnp.clip(act(config.learner, learner.actor, obs, policy, learner.obs_norm) + noise, -1.0, 1.0)
        next_obs, next_state, rewards, terminated, _, info = jax.vmap(step_env, in_axes=(0, 0, None))(
            state, actions, params
        )
        counts = contact_counts(info)
        stats = (rewards, counts["collisions"], counts["trap_contacts"], info["coverage_distance"])
        learned = shaped_rewards(rewards, info, config.learner.trap_shaping)
        return (next_obs, next_state), ((compact.rovers_of(state), actions, learned, terminated), obs, stats)

    (_, last), (steps, observations, (rewards, collisions, traps, coverage)) = jax.lax.scan(
        body, (obs, state), jax.random.split(k_steps, params.max_steps)
    )
    collected = compact.Collected(*steps, compact.layout_of(state), compact.rovers_of(last), policy)
    episode = {
        "episode_reward": rewards.sum(axis=(0, 2)),
        "agent_rewards": rewards.sum(axis=0),
        "collisions": collisions.sum(axis=0),
        "trap_contacts": traps.sum(axis=0),
        "coverage_distance": coverage[-1],
    }
    return collected, observations, episode


def learn(
    config: TrainConfig,
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
    empty partition gets zero weights, so it changes nothing."""
    expand = partial(compact.expand, buffer_state, params=params, num_envs=config.num_envs)
    batch = expand(draw.indices)
    weights = (
        importance_weights(draw, exponent) if config.buffer.importance_weights else jnp.ones(draw.probabilities.shape)
    )
    weights = weights * (draw.population > 0)[:, None]
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
    info.update(
        sampled_loss=td_loss.mean(-1),
        sampled_loss_max=td_loss.max(-1),
        sampled_newest=newest_fraction(buffer_state, draw.indices, 0.1),
    )
    return learner, buffer_state, info


def iteration(config: TrainConfig, params: EnvParams, buffer: Buffer, runner: Runner, _):
    """E episodes per seed, their transitions into the replay, then U updates per seed."""
    keys = jax.vmap(lambda k: jax.random.split(k, 3))(runner.key)  # [S, 3, 2]
    noise_std = noise_scale(config, runner.episodes)
    collected, observations, episode = jax.vmap(partial(collect, config, params), in_axes=(0, 0, None))(
        runner.learner, keys[:, 0], noise_std
    )
    flat_obs = observations.reshape(observations.shape[0], -1, *observations.shape[3:])  # [S, K, N, O]
    learner = jax.vmap(partial(observe_batch, config.learner))(runner.learner, flat_obs)
    buffer_state = jax.vmap(partial(compact.add, buffer))(runner.buffer, collected)
    episodes = runner.episodes + config.num_envs
    transitions_seen = episodes * params.max_steps
    num_updates = config.num_envs * params.max_steps // config.update_every
    exponent = importance_exponent(config, runner.episodes)

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

    # the warm-up gate is the same for every seed, so this stays a real branch under the seed vmap
    learner, buffer_state, info, updated = jax.lax.cond(
        transitions_seen >= config.warmup, do_updates, skip, learner, buffer_state, keys[:, 1]
    )
    updates = runner.updates + updated.astype(jnp.int32) * num_updates
    due = config.buffer.refresh_due(runner.updates, updates)  # shared by all seeds
    buffer_state = jax.vmap(buffer.refresh, in_axes=(0, None))(buffer_state, due)
    runner = Runner(learner=learner, buffer=buffer_state, key=keys[:, 2], episodes=episodes, updates=updates)
    return runner, (episode, info, updated)


@partial(jax.jit, static_argnums=(0, 2), donate_argnums=(3,))
def run_chunk(config: TrainConfig, params: EnvParams, buffer: Buffer, runner: Runner):
    """``log_every`` episodes per seed; returns the runner and per-seed chunk metrics."""
    iterations = config.log_every // config.num_envs
    runner, (episode, info, updated) = jax.lax.scan(
        partial(iteration, config, params, buffer), runner, None, length=iterations
    )
    # episode: [I, S, E, ...] -> mean over iterations and environments, per seed
    metrics = {k: v.mean(axis=(0, 2)) for k, v in episode.items()}
    count = jnp.maximum(updated.sum(), 1.0)
    for k, v in info.items():  # [I, S, N], over the iterations that updated (the others hold zeros)
        metrics[k] = v.max(axis=0) if k.endswith("_max") else (v * updated[:, None, None]).sum(axis=0) / count
    return runner, metrics


# ----------------------------------------------------------------------------- host loop


@dataclass(frozen=True)
class Result:
    """What :func:`train` returns: the config, the metrics rows and the final networks."""

    config: TrainConfig
    metrics: list[dict[str, float]]
    learner: LearnerState | PPOState  # [S, ...]
    out: Path | None


class _StopFlag:
    """Turns Ctrl-C (SIGINT) and SIGTERM (schedulers, Ray) into a flag the host loop checks
    between chunks (in the main thread only)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.raised = False
        self._previous: dict[int, object] = {}

    def __enter__(self):
        try:
            self._previous = {sig: signal.signal(sig, self._handle) for sig in self.SIGNALS}
        except ValueError:  # not the main thread: leave signals alone
            self._previous = {}
        return self

    def _handle(self, signum, frame):
        self.raised = True

    def __exit__(self, *exc):
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)


def train(
    config: TrainConfig,
    out: Path | None = None,
    resume: bool = False,
    progress: bool = True,
    on_chunk: Callable[[int], None] | None = None,
) -> Result:
    """Train ``config.seeds`` seeds of ``config`` together and return the metrics and networks.

    With ``out``, writes there: ``config.json``, ``metrics.csv`` (one row per seed per
    ``log_every`` episodes), TensorBoard events in ``tb/``, ``checkpoint.npz`` and
    ``learning_curve.png``. ``resume=True`` continues from ``out``'s checkpoint and gives the
    same numbers as an unbroken run. Same config => identical metrics. ``on_chunk(episodes)``
    is called after every chunk (e.g. to draw a summary of many runs instead of the bar).
    """
    if config.mission is not None:  # kept absolute and with its content: resume and evaluate need not find the file
        config = with_mission_text(config)
    params = validate(config)
    check_training_memory(config, params)  # networks, replay, rollouts and minibatches, before any is allocated
    require(out is not None or not resume, "resume=True needs the run folder (--out) to resume")
    require(
        out is not None or config.episodes <= 10_000,
        "give --out for runs of more than 10000 episodes, so that they can be resumed",
    )
    if out is None:
        return _train(config, params, None, resume, progress, on_chunk)
    with folder_lock(Path(out)):  # one writer per run folder
        return _train(config, params, Path(out), resume, progress, on_chunk)


def checkpoint_due(config: TrainConfig, chunks_done: int, saved_at: float) -> bool:
    """A checkpoint is due after every ``--checkpoint-every`` chunks of this session
    (``chunks_done``) and once ``--checkpoint-minutes`` have passed since the last one was
    written (``saved_at``, on ``time.monotonic``)."""
    by_time = config.checkpoint_minutes > 0 and time.monotonic() - saved_at >= 60 * config.checkpoint_minutes
    return chunks_done % config.checkpoint_every == 0 or by_time


def physical_memory() -> int:
    """Bytes of physical memory of this machine."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


RUN_OVERHEAD = 2 * 2**30
"""Memory of a run besides its replay (compiled programs, networks, environment batches, the
Python process): a reproduce --quick grid peaks near 0.9 GB, or 2.1 GB with --keep-programs."""


def replay_bytes(config: TrainConfig, params: EnvParams) -> tuple[int, int, int]:
    """(bytes, transitions, bytes per transition) of every seed's replay of ``config`` (0 for PPO):
    the stored transitions and episodes, and the sampling state of the ranked replay and the
    ensembles' partitions, from their shapes (nothing is allocated)."""
    if config.learner.algo in ON_POLICY:
        return 0, 0, 0
    buffer = run_buffer(config, params)
    shapes = jax.eval_shape(lambda: compact.init(buffer, params, config.num_envs))
    per_transition = math.ceil(compact.nbytes(shapes) / buffer.capacity)
    return config.seeds * buffer.capacity * per_transition, buffer.capacity, per_transition


def run_memory(config: TrainConfig) -> int:
    """Bytes a run of ``config`` needs: its replay plus :data:`RUN_OVERHEAD`."""
    return replay_bytes(config, validate(config))[0] + RUN_OVERHEAD


def _check_replay_fits(config: TrainConfig, params: EnvParams) -> None:
    """Refuse, before allocating it, a replay (every seed's) larger than 80% of the machine's memory."""
    need, capacity, per_transition = replay_bytes(config, params)
    have = physical_memory()
    require(
        need <= 0.8 * have,
        f"the replay needs {need / 2**30:.1f} GiB ({config.seeds} seeds x {capacity} transitions x "
        f"{per_transition} bytes) and this machine has {have / 2**30:.1f} GiB; lower --buffer-size or --seeds",
    )


def _train(
    config: TrainConfig,
    params: EnvParams,
    out: Path | None,
    resume: bool,
    progress: bool,
    on_chunk: Callable[[int], None] | None,
) -> Result:
    if config.learner.algo in ON_POLICY:
        runner = onpolicy.init_runner(config, params)
        chunk_fn = partial(onpolicy.run_chunk, config, params)
    else:
        buffer = run_buffer(config, params)
        _check_replay_fits(config, params)
        runner = init_runner(config, params, buffer)
        chunk_fn = partial(run_chunk, config, params, buffer)
    rows: list[dict[str, float]] = []
    if out is not None:
        checkpoint = out / CHECKPOINT
        if resume:
            require(
                checkpoint.exists() and (out / CONFIG).exists(),
                f"--resume: no run to continue in '{out}' (config.json and checkpoint.npz)",
            )
            saved = fields_by_name(read_config(out / CONFIG))
            differ = [name for name, value in fields_by_name(config).items() if saved[name] != value]
            require(
                not differ,
                f"--resume: the run in '{out}' has other settings ({', '.join(differ)}); resume it with its own config",
            )
            edited = checkpoint_changes(checkpoint, config)
            require(
                not edited,
                f"--resume: '{out / CONFIG}' was edited since its checkpoint was written ({', '.join(edited)}); "
                "restore the values the run was trained with, or start a new run",
            )
            runner = load_checkpoint(checkpoint, runner)
            done = int(runner.episodes)
            rows = [r for r in read_metrics(out / METRICS) if r["episodes"] <= done] if (out / METRICS).exists() else []
            require(
                len(rows) == done // config.log_every * config.seeds,
                f"--resume: '{out / METRICS}' is missing or lacks rows of the {done} episodes in the checkpoint; "
                "restore it (they cannot be rebuilt) or start a new run",
            )
        else:
            require(
                not checkpoint.exists(),
                f"'{out}' already holds a run; continue it with --resume or choose another --out",
            )
            out.mkdir(parents=True, exist_ok=True)
        atomic_write(out / CONFIG, lambda f: f.write(config_to_json(config)))
    writer = SummaryWriter(str(out / "tb")) if out is not None else None

    chunks = config.episodes // config.log_every
    first = int(runner.episodes) // config.log_every
    bar = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("episodes"),
        TextColumn("reward {task.fields[reward]}"),
        TextColumn("{task.fields[rate]} ep/s"),
        TimeRemainingColumn(),
        disable=not progress,
    )
    try:
        with bar, _StopFlag() as stop:
            task = bar.add_task(
                f"{config.learner.algo} {config.env_name()}",
                total=config.episodes,
                completed=first * config.log_every,
                reward="-",
                rate="-",
            )
            saved_at = time.monotonic()
            for chunk in range(first, chunks):
                start = time.perf_counter()
                runner, metrics = chunk_fn(runner)
                metrics = jax.device_get(metrics)
                seconds = time.perf_counter() - start
                episodes = (chunk + 1) * config.log_every
                new_rows = metric_rows(config, metrics, episodes, seconds)
                if not all(math.isfinite(v) for r in new_rows for v in r.values()):
                    kept = (
                        f"the last good checkpoint in '{out}' is kept"
                        if out is not None and (out / CHECKPOINT).exists()
                        else "no checkpoint was saved"
                    )
                    raise RunStopped(
                        f"non-finite loss or reward at episode {episodes}; stopping ({kept}). Try "
                        "smaller learning rates."
                    )
                rows.extend(new_rows)
                if writer is not None:
                    for r in new_rows:
                        for k, v in r.items():
                            if k not in ("seed", "episodes"):
                                writer.add_scalar(f"seed_{int(r['seed'])}/{k}", v, episodes)
                if on_chunk is not None:
                    on_chunk(episodes)
                bar.update(
                    task,
                    completed=episodes,
                    reward=f"{np.mean(metrics['episode_reward']):.1f}",
                    rate=f"{config.log_every / seconds:,.0f}",
                )
                last = chunk + 1 == chunks
                if out is not None:  # every chunk's rows at once; rows past the checkpoint are trimmed on resume
                    write_csv(out / METRICS, rows)
                if out is not None and (last or stop.raised or checkpoint_due(config, chunk + 1 - first, saved_at)):
                    save_checkpoint(out / CHECKPOINT, runner, replay=not last, config_json=config_to_json(config))
                    saved_at = time.monotonic()
                if stop.raised and not last:
                    if out is not None:
                        plot_learning_curve(
                            rows, out / "learning_curve.png", f"{config.learner.algo} on {config.env_name()}"
                        )
                    where = (
                        f"checkpoint saved; continue with: roverswarm train --resume {out}"
                        if out
                        else "nothing saved (no --out)"
                    )
                    raise RunStopped(f"interrupted at episode {episodes}; {where}")
    finally:  # flush TensorBoard also when the run stops early
        if writer is not None:
            writer.close()
    if out is not None:
        plot_learning_curve(rows, out / "learning_curve.png", f"{config.learner.algo} on {config.env_name()}")
    return Result(config=config, metrics=rows, learner=runner.learner, out=out)
