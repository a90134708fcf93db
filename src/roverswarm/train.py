"""Fused, jitted training of MADDPG/DDPG: environment, replay and updates in one XLA program.

Shape legend: S seeds, E parallel environments per seed, T steps per episode (25),
N agents, K = T * E transitions per iteration, U = K / update_every updates per iteration.

One *iteration* runs, for every seed at once (vmapped): E fresh episodes of T steps with
exploration noise, their K transitions into the replay, then U updates of every agent (once
the replay holds ``warmup`` transitions). A *chunk* is ``log_every / E`` iterations in one
``lax.scan``: one jitted call per 1000 episodes. The Python loop around the chunks only logs,
checkpoints and draws progress. The number of updates per environment step is the same
whatever E is: one update of every agent per ``update_every`` environment steps.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import signal
import sys
import time
import types
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Callable, Literal

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization, struct
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from tensorboardX import SummaryWriter

from roverswarm.algos.maddpg import ALGOS, AlgoConfig, LearnerState, act, inference_error, init_learner, observe_batch, update
from roverswarm.buffers.ranked import ranked_buffer
from roverswarm.buffers.uniform import Buffer, BufferState, Draw, Transition, gather, importance_weights, newest_fraction, sample_recent, uniform_buffer
from roverswarm.env.mars import ACTION_SIZE, EnvParams, observation_size, reset, step_env
from roverswarm.env.missions import load_mission
from roverswarm.env.scenarios import get_scenario
from roverswarm.errors import RunStopped, UserError, require


# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class TrainConfig:
    """A training run. Defaults are tuned to learn with continuous actions: four times as many
    updates per environment step as the reference code, on batches a quarter the size (the
    same compute), noise 0.2; :data:`REFERENCE` holds the reference values."""

    scenario: str = "paper-3"
    """Scenario preset (see `roverswarm scenarios`)."""
    mission: str | None = None
    """Mission file (YAML/JSON) to train on instead of --scenario (which is then ignored): its
    POIs and traps fixed, rover starts drawn anywhere in the map, fixed-length episodes. The
    command line stores its absolute path; the file is read again on resume and evaluation."""
    learner: AlgoConfig = field(default_factory=AlgoConfig)
    episodes: int = 60_000
    """Training episodes per seed (a multiple of --log-every)."""
    seeds: int = 1
    """Independent seeds, trained together (vmapped) in one program."""
    seed: int = 0
    """Base random seed; seed s of the run uses a key derived from (seed, s)."""
    num_envs: int = 20
    """Parallel environments per seed. Does not change the updates per environment step."""
    batch_size: int = 256
    """Transitions per update, per agent."""
    buffer_size: int = 1_000_000
    """Replay capacity in transitions."""
    replay: Literal["uniform", "ranked"] = "uniform"
    """`uniform`: the reference replay; `ranked`: the paper's experience sample optimizer
    (eq. 12-15), sampling by the rank of each transition's latest TD loss."""
    alpha: float = 1.0
    """Ranked replay: amplification of the loss rank, P ~ rank^alpha (0 = uniform)."""
    beta: float = 0.1
    """Ranked replay: share of samples drawn uniformly, in [0, 1] (1 = uniform)."""
    importance_weights: bool = False
    """Weight each sample's critic loss by 1 / (M * P(i)), normalised to a batch maximum of 1."""
    refresh_every: int = 1000
    """Ranked replay: updates between re-rankings of the whole buffer (checked once per iteration)."""
    update_every: int = 25
    """Environment steps (summed over parallel environments) per update of every agent."""
    warmup: int = 1024 * 25
    """Transitions stored before the first update."""
    noise_std: float = 0.2
    """Standard deviation of the Gaussian exploration noise added to actions (then clipped)."""
    noise_final: float = 0.2
    """Noise standard deviation after --noise-decay-episodes (linear decay from --noise-std)."""
    noise_decay_episodes: int = 0
    """Episodes over which the noise decays linearly to --noise-final; 0 keeps --noise-std."""
    log_every: int = 1000
    """Episodes per metrics row (and per jitted chunk)."""
    checkpoint_every: int = 10
    """Chunks (of --log-every episodes) between checkpoints; one is always written at the end."""

    def env_name(self) -> str:
        """What the run trains on: the scenario, or the mission file's name."""
        return self.scenario if self.mission is None else f"mission {Path(self.mission).stem}"


REFERENCE = TrainConfig(
    learner=AlgoConfig(actor_lr=1e-2, critic_lr=1e-2, gamma=0.95, tau=0.01, grad_clip=0.5, hidden=(64, 64), action_penalty=1e-3),
    batch_size=1024,
    buffer_size=1_000_000,
    update_every=100,
    warmup=1024 * 25,
    noise_std=0.1,
    noise_final=0.1,
    noise_decay_episodes=0,
    refresh_every=250,
)
"""The reference MADDPG code's hyper-parameters (openai/maddpg), used by the paper."""

PRESETS: dict[str, TrainConfig] = {"default": TrainConfig(), "reference": REFERENCE}
"""Named starting points of `roverswarm train --preset`; other options change them."""


def validate(config: TrainConfig) -> EnvParams:
    """Check ``config``; raise :class:`UserError` naming the bad field. Returns the env params."""
    params = get_scenario(config.scenario) if config.mission is None else load_mission(config.mission).training_params()
    learner = config.learner
    require(learner.algo in ALGOS, f"--algo must be one of {', '.join(ALGOS)}, got '{learner.algo}'")
    require(config.replay in ("uniform", "ranked"), f"--replay must be 'uniform' or 'ranked', got '{config.replay}'")
    require(config.alpha >= 0, f"--alpha must be >= 0, got {config.alpha}")
    require(0 <= config.beta <= 1, f"--beta must be in [0, 1], got {config.beta}")
    for name in ("episodes", "seeds", "num_envs", "batch_size", "buffer_size", "update_every", "log_every", "checkpoint_every", "refresh_every"):
        value = getattr(config, name)
        require(value >= 1, f"--{name.replace('_', '-')} must be >= 1, got {value}")
    require(config.warmup >= 0, f"--warmup must be >= 0, got {config.warmup}")
    require(
        config.batch_size <= config.buffer_size,
        f"--batch-size ({config.batch_size}) must not exceed --buffer-size ({config.buffer_size})",
    )
    require(
        config.log_every % config.num_envs == 0,
        f"--log-every ({config.log_every}) must be a multiple of --num-envs ({config.num_envs})",
    )
    require(
        config.episodes % config.log_every == 0,
        f"--episodes ({config.episodes}) must be a multiple of --log-every ({config.log_every})",
    )
    steps = config.num_envs * params.max_steps
    require(
        steps % config.update_every == 0,
        f"--num-envs x episode length ({steps}) must be a multiple of --update-every ({config.update_every})",
    )
    for name in ("actor_lr", "critic_lr", "tau", "grad_clip"):
        value = getattr(learner, name)
        require(value > 0, f"--{name.replace('_', '-')} must be positive, got {value}")
    require(learner.ensemble >= 1, f"--ensemble must be >= 1 (sub-policies per agent), got {learner.ensemble}")
    require(learner.infer_entropy >= 0, f"--infer-entropy must be >= 0, got {learner.infer_entropy}")
    require(learner.infer_window >= 1, f"--infer-window must be >= 1 transition, got {learner.infer_window}")
    require(
        not learner.infer_policies or learner.algo == "maddpg",
        "--infer-policies needs --algo maddpg: a DDPG critic never sees the other agents' actions",
    )
    require(not learner.infer_policies or params.num_rovers >= 2, "--infer-policies needs at least 2 rovers: there is no other agent to infer")
    require(
        not learner.share_parameters or (learner.ensemble == 1 and not learner.infer_policies),
        "--share-parameters does not compose with --ensemble > 1 or --infer-policies (they need one network per agent)",
    )
    require(learner.actor_delay >= 1, f"--actor-delay must be >= 1, got {learner.actor_delay}")
    for name in ("target_noise", "target_noise_clip"):
        value = getattr(learner, name)
        require(math.isfinite(value) and value >= 0, f"--{name.replace('_', '-')} must be a finite number >= 0, got {value}")
    require(math.isfinite(learner.reward_scale) and learner.reward_scale > 0, f"--reward-scale must be a finite number > 0, got {learner.reward_scale}")
    require(
        config.buffer_size >= steps,
        f"--buffer-size ({config.buffer_size}) must hold one iteration's transitions (--num-envs x episode length = {steps})",
    )
    require(0 <= learner.gamma <= 1, f"--gamma must be in [0, 1], got {learner.gamma}")
    for name in ("noise_std", "noise_final", "noise_decay_episodes"):
        value = getattr(config, name)
        require(value >= 0, f"--{name.replace('_', '-')} must be >= 0, got {value}")
    return params


# ----------------------------------------------------------------------------- jitted core


@struct.dataclass
class Runner:
    """Everything the training carries from chunk to chunk (leading [S] where per seed)."""

    learner: LearnerState  # [S, N, ...]
    buffer: BufferState  # [S, C, ...]
    key: jax.Array  # [S] PRNG keys
    episodes: jax.Array  # [] int32, episodes per seed so far (shared by all seeds)
    updates: jax.Array  # [] int32, updates of every agent per seed so far (shared)


def example_transition(config: TrainConfig, params: EnvParams) -> Transition:
    n, o = params.num_rovers, observation_size(params)
    return Transition(
        obs=jnp.zeros((n, o)),
        actions=jnp.zeros((n, ACTION_SIZE)),
        rewards=jnp.zeros((n,)),
        next_obs=jnp.zeros((n, o)),
        terminated=jnp.zeros((), bool),
        policy=jnp.zeros((n,), jnp.int32) if config.learner.ensemble > 1 else None,
    )


def make_buffer(config: TrainConfig, params: EnvParams) -> Buffer:
    """The replay of ``config``, with one partition per sub-policy of every agent if K > 1."""
    k = config.learner.ensemble
    if config.replay == "ranked":
        return ranked_buffer(config.buffer_size, config.batch_size, params.num_rovers, config.alpha, config.beta, k)
    return uniform_buffer(config.buffer_size, config.batch_size, params.num_rovers, k)


def init_runner(config: TrainConfig, params: EnvParams, buffer: Buffer) -> Runner:
    """Fresh networks and empty replays for every seed."""
    keys = jax.vmap(lambda s: jax.random.fold_in(jax.random.PRNGKey(config.seed), s))(jnp.arange(config.seeds))
    init_keys, run_keys = jnp.split(jax.vmap(jax.random.split)(keys), 2, axis=1)
    learner = jax.vmap(lambda k: init_learner(k, config.learner, params.num_rovers, observation_size(params)))(init_keys[:, 0])
    buffers = jax.vmap(lambda _: buffer.init(example_transition(config, params)))(jnp.arange(config.seeds))
    counter = lambda: jnp.zeros((), jnp.int32)  # noqa: E731 (separate arrays: the runner is donated)
    return Runner(learner=learner, buffer=buffers, key=run_keys[:, 0], episodes=counter(), updates=counter())


def noise_scale(config: TrainConfig, episodes: jax.Array) -> jax.Array:
    """Exploration noise std after ``episodes`` episodes: linear from --noise-std to --noise-final."""
    if config.noise_decay_episodes == 0:
        return jnp.asarray(config.noise_std)
    frac = jnp.minimum(episodes / config.noise_decay_episodes, 1.0)
    return config.noise_std + frac * (config.noise_final - config.noise_std)


def collect(config: TrainConfig, params: EnvParams, learner: LearnerState, key: jax.Array, noise_std: jax.Array):
    """E episodes of one seed with Gaussian exploration noise of std ``noise_std``; with
    ensembles, every agent runs one sub-policy per episode, drawn uniformly in each environment.

    Returns transitions [T, E, ...] and per-episode stats [E] (reward summed over agents and
    steps, per-agent rewards [E, N], collisions, trap contacts, final coverage distance).
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
        next_obs, state, rewards, terminated, _, info = jax.vmap(step_env, in_axes=(0, 0, None))(state, actions, params)
        transition = Transition(
            obs=obs, actions=actions, rewards=rewards, next_obs=next_obs, terminated=terminated, policy=policy
        )
        stats = (jnp.sum(info["collisions"], -1) / 2, jnp.sum(info["trap_contacts"], -1), info["coverage_distance"])
        return (next_obs, state), (transition, stats)

    _, (transitions, (collisions, traps, coverage)) = jax.lax.scan(
        body, (obs, state), jax.random.split(k_steps, params.max_steps)
    )
    episode = {
        "episode_reward": transitions.rewards.sum(axis=(0, 2)),
        "agent_rewards": transitions.rewards.sum(axis=0),
        "collisions": collisions.sum(axis=0),
        "trap_contacts": traps.sum(axis=0),
        "coverage_distance": coverage[-1],
    }
    return transitions, episode


def learn(config: TrainConfig, buffer: Buffer, learner: LearnerState, buffer_state: BufferState, key: jax.Array, draw: Draw):
    """One update of every agent of one seed on the transitions of ``draw``, drawn from its
    replay; the sampled TD losses go back to it. ``key`` draws the recent batch of inference.

    Info per agent [N] (the update's losses and Q; with --infer-policies the approximations'
    error before the update) or per sampling group [N * K] (what was sampled: its mean and
    max TD loss, and the fraction drawn from the newest 10% of the replay). A group with an
    empty partition gets zero weights, so it changes nothing."""
    batch = gather(buffer_state, draw.indices)
    weights = importance_weights(draw) if config.importance_weights else jnp.ones(draw.probabilities.shape)
    weights = weights * (draw.population > 0)[:, None]
    error = recent = None
    if config.learner.infer_policies:
        error = inference_error(config.learner, learner, batch)
        recent = sample_recent(buffer_state, jax.random.fold_in(key, 1), config.learner.infer_window, config.batch_size)
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


def _reduce(name: str, x: jax.Array, axis) -> jax.Array:
    """Aggregate a metric: ``*_max`` metrics by their maximum, the others by their mean."""
    return x.max(axis=axis) if name.endswith("_max") else x.mean(axis=axis)


def iteration(config: TrainConfig, params: EnvParams, buffer: Buffer, runner: Runner, _):
    """E episodes per seed, their transitions into the replay, then U updates per seed."""
    keys = jax.vmap(lambda k: jax.random.split(k, 3))(runner.key)  # [S, 3, 2]
    noise_std = noise_scale(config, runner.episodes)
    transitions, episode = jax.vmap(partial(collect, config, params), in_axes=(0, 0, None))(
        runner.learner, keys[:, 0], noise_std
    )
    flat = jax.tree.map(lambda x: x.reshape(x.shape[0], -1, *x.shape[3:]), transitions)  # [S, K, ...]
    learner = jax.vmap(partial(observe_batch, config.learner))(runner.learner, flat.obs)
    buffer_state = jax.vmap(buffer.add)(runner.buffer, flat)
    episodes = runner.episodes + config.num_envs
    transitions_seen = episodes * params.max_steps
    num_updates = config.num_envs * params.max_steps // config.update_every

    def do_updates(learner, buffer_state, key):
        def one(carry, xs):
            learner, buffer_state = carry
            learner, buffer_state, info = jax.vmap(partial(learn, config, buffer))(learner, buffer_state, *xs)
            return (learner, buffer_state), info

        update_keys = jax.vmap(lambda k: jax.random.split(k, num_updates), out_axes=1)(key)  # [U, S]
        # a draw reads nothing the updates change, so all U are drawn at once: [U, S, G, B]
        draws = jax.vmap(jax.vmap(buffer.draw, in_axes=(None, 0)), in_axes=(0, 1), out_axes=1)(buffer_state, update_keys)
        (learner, buffer_state), info = jax.lax.scan(one, (learner, buffer_state), (update_keys, draws))
        return learner, buffer_state, {k: _reduce(k, v, 0) for k, v in info.items()}, jnp.ones(())

    def skip(learner, buffer_state, key):
        shapes = jax.eval_shape(do_updates, learner, buffer_state, key)[2]
        return learner, buffer_state, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes), jnp.zeros(())

    # the warm-up gate is the same for every seed, so this stays a real branch under the seed vmap
    learner, buffer_state, info, updated = jax.lax.cond(
        transitions_seen >= config.warmup, do_updates, skip, learner, buffer_state, keys[:, 1]
    )
    updates = runner.updates + updated.astype(jnp.int32) * num_updates
    due = updates // config.refresh_every > runner.updates // config.refresh_every  # shared by all seeds
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


# ----------------------------------------------------------------------------- checkpoints


CHECKPOINT = "checkpoint.npz"
CONFIG = "config.json"
METRICS = "metrics.csv"


def _flatten(tree: dict, prefix: str = "") -> dict[str, np.ndarray]:
    flat = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, path + "/"))
        elif value is not None:
            flat[path] = np.asarray(value)
    return flat


def _restore(template, flat: dict[str, np.ndarray], prefix: str = ""):
    """``template`` (a pytree of flax structs) with every leaf replaced by ``flat[path]``."""

    def fill(node, path):
        if isinstance(node, dict):
            return {k: fill(v, f"{path}{k}/") for k, v in node.items()}
        if node is None:
            return None
        key = prefix + path[:-1]
        if key not in flat:
            raise UserError(f"checkpoint does not match this run: it has no '{key}'")
        value = flat[key]
        if value.shape != np.shape(node):
            raise UserError(f"checkpoint does not match this run: '{key}' has shape {value.shape}, expected {np.shape(node)}")
        return jnp.asarray(value)

    return serialization.from_state_dict(template, fill(serialization.to_state_dict(template), ""))


def save_checkpoint(path: Path, runner: Runner, replay: bool = True) -> None:
    """Write ``runner`` to ``path`` atomically (temp file, then rename); plain arrays, no pickle.

    Only the filled part of the replay is written; loading pads it back with zeros. With
    ``replay=False`` (a finished run: nothing left to train) the replay is left out, which
    makes the file hundreds of times smaller.
    """
    runner = jax.device_get(runner)
    filled = int(np.max(runner.buffer.size))
    runner = runner.replace(buffer=runner.buffer.replace(data=jax.tree.map(lambda x: x[:, :filled], runner.buffer.data)))
    arrays = _flatten(serialization.to_state_dict(runner))
    if not replay:
        arrays = {k: v for k, v in arrays.items() if not k.startswith("buffer/")}
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_checkpoint(path: Path, template: Runner) -> Runner:
    """Read a runner written by :func:`save_checkpoint` into the structure of ``template``."""
    capacity = jax.tree.leaves(template.buffer.data)[0].shape[1]
    with np.load(path, allow_pickle=False) as data:
        flat = dict(data)
    if not any(k.startswith("buffer/") for k in flat):  # a finished run's checkpoint: no replay kept
        flat.update(_flatten(serialization.to_state_dict(template.buffer), "buffer/"))
    for key, x in flat.items():
        if key.startswith("buffer/data/"):
            flat[key] = np.concatenate([x, np.zeros((x.shape[0], capacity - x.shape[1], *x.shape[2:]), x.dtype)], axis=1)
    return _restore(template, flat)


def load_run(out: Path) -> tuple[TrainConfig, LearnerState]:
    """The config and final (last checkpointed) networks [S, N, ...] of the run in ``out``."""
    out = Path(out)
    require((out / CONFIG).exists() and (out / CHECKPOINT).exists(), f"'{out}' holds no trained run (config.json and checkpoint.npz)")
    config = config_from_json((out / CONFIG).read_text())
    params = validate(config)
    keys = jax.random.split(jax.random.PRNGKey(0), config.seeds)
    template = jax.vmap(lambda k: init_learner(k, config.learner, params.num_rovers, observation_size(params)))(keys)
    with np.load(out / CHECKPOINT, allow_pickle=False) as data:
        flat = {k: data[k] for k in data.files if k.startswith("learner/")}
    return config, _restore(template, flat, prefix="learner/")


def config_to_json(config: TrainConfig) -> str:
    return json.dumps(dataclasses.asdict(config), indent=2)


def config_from_json(text: str) -> TrainConfig:
    raw = json.loads(text)
    learner = raw.pop("learner")
    learner["hidden"] = tuple(learner["hidden"])
    return TrainConfig(**raw, learner=AlgoConfig(**learner))


# ----------------------------------------------------------------------------- host loop


@dataclass(frozen=True)
class Result:
    """What :func:`train` returns: the config, the metrics rows and the final networks."""

    config: TrainConfig
    metrics: list[dict[str, float]]
    learner: LearnerState  # [S, N, ...]
    out: Path | None


LEARNER_METRICS = ("critic_loss", "actor_loss", "q_mean", "sampled_loss", "sampled_loss_max", "sampled_newest")
"""Per-update metrics in ``metrics.csv`` (mean over agents; ``*_max``: max over agents and updates)."""
INFER_METRICS = ("infer_loss", "infer_error")
"""With --infer-policies: the approximations' loss, and the mean absolute error of their means
against the other agents' current actions on the sampled observations."""


def learner_metrics(config: TrainConfig) -> tuple[str, ...]:
    """The per-update metrics ``config``'s run logs."""
    return LEARNER_METRICS + (INFER_METRICS if config.learner.infer_policies else ())


def metric_rows(config: TrainConfig, metrics: dict[str, np.ndarray], episodes: int, seconds: float) -> list[dict[str, float]]:
    """One row per seed for a chunk. ``wall_seconds`` is the chunk's time for all seeds together."""
    rows = []
    for s in range(config.seeds):
        row: dict[str, float] = {"seed": s, "episodes": episodes, "episode_reward": float(metrics["episode_reward"][s])}
        for i, r in enumerate(metrics["agent_rewards"][s]):
            row[f"agent_{i}_reward"] = float(r)
        for k in ("collisions", "trap_contacts", "coverage_distance"):
            row[k] = float(metrics[k][s])
        for k in learner_metrics(config):
            row[k] = float(_reduce(k, metrics[k][s], None))
        row["wall_seconds"] = seconds
        rows.append(row)
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    """``rows`` (dicts with the same keys) as a CSV file, written atomically (temp file + rename)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


COUNT_COLUMNS = ("seed", "episodes")
"""Integer columns of ``metrics.csv``; kept integers when a resumed run rewrites the file."""


def read_metrics(path: Path) -> list[dict[str, float]]:
    """The rows of a ``metrics.csv``: ``seed`` and ``episodes`` as ints, the rest as floats."""
    with open(path, newline="") as f:
        return [{k: int(float(v)) if k in COUNT_COLUMNS else float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def plot_learning_curve(rows: list[dict[str, float]], path: Path, title: str) -> None:
    """Mean episode reward per 1000 episodes: one thin line per seed and their mean."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    seeds = sorted({int(r["seed"]) for r in rows})
    curves = []
    for s in seeds:
        xs = [r["episodes"] for r in rows if int(r["seed"]) == s]
        ys = [r["episode_reward"] for r in rows if int(r["seed"]) == s]
        ax.plot(xs, ys, lw=0.8, alpha=0.5, label=f"seed {s}")
        curves.append(ys)
    length = min(len(c) for c in curves)
    ax.plot(xs[:length], np.mean([c[:length] for c in curves], axis=0), color="black", lw=2, label="mean")
    ax.set_xlabel("episodes")
    ax.set_ylabel("mean episode reward")
    ax.set_title(title)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)


class _StopFlag:
    """Turns Ctrl-C into a flag the host loop checks between chunks (the main thread only)."""

    def __init__(self):
        self.raised = False
        self._previous = None

    def __enter__(self):
        try:
            self._previous = signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not the main thread: leave signals alone
            self._previous = None
        return self

    def _handle(self, signum, frame):
        self.raised = True

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


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
    params = validate(config)
    buffer = make_buffer(config, params)
    runner = init_runner(config, params, buffer)
    rows: list[dict[str, float]] = []
    if out is not None:
        out = Path(out)
        checkpoint = out / CHECKPOINT
        if resume:
            require(checkpoint.exists(), f"--resume: no checkpoint in '{out}'")
            runner = load_checkpoint(checkpoint, runner)
            done = int(runner.episodes)
            rows = [r for r in read_metrics(out / METRICS) if r["episodes"] <= done] if (out / METRICS).exists() else []
        else:
            require(
                not checkpoint.exists(),
                f"'{out}' already holds a run; continue it with --resume or choose another --out",
            )
            out.mkdir(parents=True, exist_ok=True)
        (out / CONFIG).write_text(config_to_json(config))
    writer = SummaryWriter(str(out / "tb")) if out is not None else None

    chunks = config.episodes // config.log_every
    first = int(runner.episodes) // config.log_every
    bar = Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
        TextColumn("reward {task.fields[reward]}"), TextColumn("{task.fields[rate]} ep/s"), TimeRemainingColumn(),
        disable=not progress,
    )
    try:
        with bar, _StopFlag() as stop:
            task = bar.add_task(
                f"{config.learner.algo} {config.env_name()}", total=config.episodes, completed=first * config.log_every,
                reward="-", rate="-",
            )
            for chunk in range(first, chunks):
                start = time.perf_counter()
                runner, metrics = run_chunk(config, params, buffer, runner)
                metrics = jax.device_get(metrics)
                seconds = time.perf_counter() - start
                episodes = (chunk + 1) * config.log_every
                new_rows = metric_rows(config, metrics, episodes, seconds)
                finite = all(math.isfinite(r[k]) for r in new_rows for k in ("episode_reward", "critic_loss", "actor_loss"))
                if not finite:
                    kept = f"the last good checkpoint in '{out}' is kept" if out is not None else "nothing was saved"
                    raise RunStopped(f"non-finite loss or reward at episode {episodes}; stopping ({kept}). Try smaller learning rates.")
                rows.extend(new_rows)
                if writer is not None:
                    for r in new_rows:
                        for k, v in r.items():
                            if k not in ("seed", "episodes"):
                                writer.add_scalar(f"seed_{int(r['seed'])}/{k}", v, episodes)
                if on_chunk is not None:
                    on_chunk(episodes)
                bar.update(
                    task, completed=episodes, reward=f"{np.mean(metrics['episode_reward']):.1f}",
                    rate=f"{config.log_every / seconds:,.0f}",
                )
                last = chunk + 1 == chunks
                if out is not None and (last or stop.raised or (chunk + 1 - first) % config.checkpoint_every == 0):
                    # metrics first: a crash between the two leaves rows that resume trims
                    write_csv(out / METRICS, rows)
                    save_checkpoint(out / CHECKPOINT, runner, replay=not last)
                if stop.raised and not last:
                    if out is not None:
                        plot_learning_curve(rows, out / "learning_curve.png", f"{config.learner.algo} on {config.env_name()}")
                    where = f"checkpoint saved; continue with: roverswarm train --resume {out}" if out else "nothing saved (no --out)"
                    raise RunStopped(f"interrupted at episode {episodes}; {where}")
    finally:  # flush TensorBoard also when the run stops early
        if writer is not None:
            writer.close()
    if out is not None:
        plot_learning_curve(rows, out / "learning_curve.png", f"{config.learner.algo} on {config.env_name()}")
    return Result(config=config, metrics=rows, learner=runner.learner, out=out)


class _CallableModule(types.ModuleType):
    """``roverswarm.train(config)`` calls :func:`train`, while ``roverswarm.train`` stays
    this module (imports and attributes work as for any module)."""

    def __call__(self, *args, **kwargs) -> Result:
        return train(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
