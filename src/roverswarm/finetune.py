"""Fine-tuning a trained run by the gradient of its episodes' reward through the environment
(``roverswarm finetune``).

The environment is pure JAX (:mod:`roverswarm.env.mars`), so the gradient of a whole
episode's reward with respect to the actor's weights can be taken through its dynamics
(backpropagation through time, as Brax's analytic policy gradients or SHAC do): exact, without
the sampling noise of a policy gradient, on the deterministic policy that evaluation runs.
Counts have no gradient: each contact count (rovers touched, traps touched) keeps its value and
takes the slope of a sum of ``sigmoid(-gap / tau)`` over the gaps (:func:`smooth_count`);
actions are the actor's mean, clipped to [-1, 1] with the slope of the identity
(straight-through). The objective's value is the paper's reward (eq. 16), plus
``trap_charge`` per trap contact if given; each episode weighs alike whatever its swarm's size
(its reward over N^2).

Every seed of an on-policy run (MAPPO, IPPO) is fine-tuned on the episodes the run trained on
(its scenario or range of sizes, its rover failures), the sizes drawn with ``size_draw_power``,
and written as a run folder of its own: the run's ``config.json`` and checkpoint with the
fine-tuned actors, which ``evaluate``, ``mission`` and ``export`` read as any run, beside
``finetune.json`` (what was done), ``finetune.csv`` and ``finetune.png`` (its progress). The
state is saved every ``checkpoint_every`` iterations; a stopped fine-tune resumes where it
stood when the same command is given again. Measured in ``docs/results/any-size/README.md``.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import tyro
from flax import serialization
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from roverswarm.algos.ppo_networks import policy_networks
from roverswarm.env.mars import observe, pairwise_dist, step_env
from roverswarm.episodes import exists, reset_all, training_params
from roverswarm.errors import RunStopped, require, require_finite, require_positive
from roverswarm.learners import learner_family
from roverswarm.runs import CHECKPOINT, CONFIG, METRICS, Run, plot_learning_curve, write_csv
from roverswarm.storage import atomic_write, flatten, open_arrays, read_arrays, restore, write_text
from roverswarm.trainer import StopFlag

RECORD, PROGRESS, FIGURE, STATE = "finetune.json", "finetune.csv", "finetune.png", "finetune_state.npz"
"""What a fine-tune writes beside the run's files: its settings and progress, its table and its
figure, and its own state (actors, optimiser and iterations done: all a resume reads)."""
OBJECTIVE = "episode reward / N^2 (a step's mean)"
"""What ``finetune.csv``'s ``objective`` is: each seed's mean over the step's episodes."""
MAX_ENVS = 256
"""Episodes per seed and step at most: the gradient keeps every step of every episode, so its
memory grows with them, the seeds and the largest swarm."""
LOG_EVERY = 25
"""Iterations between the rows of ``finetune.csv``."""


@dataclass(frozen=True)
class FinetuneConfig:
    """Fine-tune a trained on-policy run's actors by the gradient of the episode reward through the environment."""

    run: tyro.conf.Positional[Path]
    """Run folder of `roverswarm train --out` (--algo mappo or ippo)."""
    out: Path
    """Output folder: a run folder of its own (config.json, checkpoint.npz, finetune.json, finetune.csv)."""
    iterations: int = 600
    """Gradient steps per seed."""
    envs: int = 32
    """Episodes per seed and gradient step."""
    lr: float = 3e-5
    """Adam's learning rate."""
    tau: float = 0.02
    """Width of the sigmoid whose slope the contact counts take (gaps within a few tau of contact)."""
    trap_charge: float = 0.0
    """Charge per trap contact on top of the paper's 1 (0: the paper's reward)."""
    size_draw_power: float = 1.0
    """Range scenarios: a size N drawn in proportion to N^-p (0: every size alike)."""
    grad_clip: float = 1.0
    """Global norm the gradient is clipped to."""
    checkpoint_every: int = 100
    """Iterations between saves of the fine-tune's state."""
    seed: int = 0
    """Seed of the episodes drawn."""


def smooth_count(gaps: jax.Array, tau: float) -> jax.Array:
    """[..., K] gaps -> [...] the number below 0, whose gradient is that of the sum of
    ``sigmoid(-gap / tau)`` (straight-through: the value stays the count)."""
    soft = jnp.sum(jax.nn.sigmoid(-gaps / tau), axis=-1)
    return jnp.sum(gaps < 0, axis=-1).astype(gaps.dtype) + soft - jax.lax.stop_gradient(soft)


def episode_objective(run: Run, settings: FinetuneConfig):
    """``objective(actor, state) -> (value, (trap contacts, collisions))`` of one episode from
    ``state`` (a reset of the run's padded or single-size environment): the swarm's reward
    summed over its rovers and steps, over N^2, with the slopes of :func:`smooth_count`; for a
    run of ``--stop-when-complete``, up to the step that observes the last POI (none after
    it, as in its training)."""
    config = run.config
    nets = policy_networks(config.learner, config.ppo)
    params = training_params(config, run.params)

    def objective(actor, state):
        rovers = exists(state)
        count = jnp.sum(rovers)

        def step(carry, _):
            state, ended = carry
            view = nets.observe(state, params) if nets.any_size else observe(state, params)
            mean, _ = nets.policy(actor, nets.actor_inputs(view))
            action = mean + jax.lax.stop_gradient(jnp.clip(mean, -1.0, 1.0) - mean)
            _, after, _, terminated, _, info = step_env(state, action, params)
            traps = smooth_count(info["trap_gaps"], settings.tau)
            gaps = pairwise_dist(after.rover_pos, after.rover_pos) - 2 * params.rover_radius
            apart = jnp.eye(gaps.shape[0], dtype=bool) | ~(rovers[:, None] & rovers[None, :])
            touched = smooth_count(jnp.where(apart, jnp.inf, gaps), settings.tau)
            charge = params.trap_penalty + settings.trap_charge
            reward = -info["coverage_distance"] - params.collision_penalty * touched - charge * traps
            counts = jnp.stack([jnp.sum(info["trap_contacts"]), jnp.sum(info["collisions"])])
            total = jnp.where(ended, 0.0, jnp.sum(jnp.where(rovers, reward, 0.0)))
            return (after, ended | terminated), (total, jnp.where(ended, 0, counts))

        _, (rewards, counts) = jax.lax.scan(step, (state, jnp.asarray(False)), None, length=params.max_steps)
        return jnp.sum(rewards) / count**2, jnp.sum(counts, axis=0).astype(jnp.float32)

    return objective, params


def check(settings: FinetuneConfig, run: Run) -> None:
    """Every setting and the run it fine-tunes, before anything is computed."""
    require_positive(settings, ("iterations", "envs", "checkpoint_every"))
    require(
        settings.envs <= MAX_ENVS,
        f"--envs must be at most {MAX_ENVS} episodes per step (every step of each is kept for the gradient), "
        f"got {settings.envs}",
    )
    require_finite(settings.lr, 0.0, "lr", strict=True)
    require_finite(settings.tau, 0.0, "tau", strict=True)
    require_finite(settings.trap_charge, 0.0, "trap-charge")
    require_finite(settings.size_draw_power, 0.0, "size-draw-power")
    require_finite(settings.grad_clip, 0.0, "grad-clip", strict=True)
    require(0 <= settings.seed < 2**32, f"--seed must be an integer in [0, 2^32), got {settings.seed}")
    learner = run.config.learner
    require(
        not learner_family(learner.algo).replay,
        f"finetune needs a run of --algo mappo or ippo (a Gaussian actor's mean); '{settings.run}' is --algo "
        f"{learner.algo}",
    )
    shielded = f"finetune does not take a run trained behind the safety layer (--shield): '{settings.run}'"
    require(not learner.shield, shielded)


def _record(settings: FinetuneConfig) -> dict:
    """What ``finetune.json`` says of the settings (a resume must give the same; the run's
    folder however it is spelt)."""
    fields = dataclasses.asdict(settings)
    return {k: str(v.resolve()) if isinstance(v, Path) else v for k, v in fields.items() if k != "out"}


def _prepare(settings: FinetuneConfig) -> None:
    """Checks ``out`` and, for a new fine-tune, sets it up from the run's files;
    :class:`UserError` if it holds anything but this fine-tune."""
    out = settings.out
    require(out.resolve() != settings.run.resolve(), f"--out '{out}' is the run itself; give a folder of its own")
    if (out / RECORD).exists():
        record = json.loads((out / RECORD).read_text())
        require(
            record["settings"] == _record(settings),
            f"--out '{out}' holds a fine-tune of other settings ({RECORD}); give the same settings to resume it, "
            "or another --out",
        )
        return
    require(not (out / CONFIG).exists(), f"--out '{out}' holds a training run; give a folder of its own")
    out.mkdir(parents=True, exist_ok=True)
    for name in (CONFIG, METRICS, CHECKPOINT):
        if (settings.run / name).exists():
            shutil.copyfile(settings.run / name, out / name)
    _save_record(settings, 0)


def _save_record(settings: FinetuneConfig, done: int) -> None:
    record = {"settings": _record(settings), "iterations_done": done}
    write_text(settings.out / RECORD, json.dumps(record, indent=1) + "\n")


def _saved(settings: FinetuneConfig, actors, opt_states):
    """``(iterations done, actors, optimiser states)`` of the state saved in ``out`` (the
    arguments, which are the run's, and 0 if none is)."""
    if not (settings.out / STATE).exists():
        return 0, actors, opt_states
    state = {"actor": actors, "opt": opt_states, "done": jnp.zeros((), jnp.int32)}
    state = restore(state, read_arrays(settings.out / STATE))
    return int(state["done"]), state["actor"], state["opt"]


def _save(settings: FinetuneConfig, actors, opt_states, done: int) -> None:
    """The fine-tune's state (actors, optimiser, iterations done) in one file, then the
    fine-tuned actors into the output's checkpoint and the record (each file whole: a resume
    reads the state alone, and writes the others again)."""
    out = settings.out
    state = flatten(serialization.to_state_dict({"actor": actors, "opt": opt_states, "done": np.int32(done)}))
    atomic_write(out / STATE, lambda f: np.savez(f, **state), binary=True)
    with open_arrays(out / CHECKPOINT) as saved:
        arrays = {**saved, **flatten(serialization.to_state_dict(actors), "learner/actor/")}
    atomic_write(out / CHECKPOINT, lambda f: np.savez(f, **arrays), binary=True)
    _save_record(settings, done)


def _norm(tree) -> jax.Array:
    """The global (L2) norm of a pytree's leaves."""
    return jnp.sqrt(sum(jnp.sum(jnp.square(leaf)) for leaf in jax.tree.leaves(tree)))


def finetune(settings: FinetuneConfig, progress: bool = True) -> Path:
    """Fine-tune every seed of ``settings.run`` into ``settings.out`` (resumed if it holds this
    fine-tune, stopped part way); returns ``settings.out``."""
    run = Run(settings.run)
    check(settings, run)
    _prepare(settings)
    config = dataclasses.replace(run.config, num_envs=settings.envs, size_draw_power=settings.size_draw_power)
    objective, params = episode_objective(run, settings)
    optimiser = optax.chain(optax.clip_by_global_norm(settings.grad_clip), optax.adam(settings.lr))
    actors = run.learner.actor
    done, actors, opt_states = _saved(settings, actors, jax.vmap(optimiser.init)(actors))
    if done == settings.iterations:  # finished (its checkpoint written again: a stop may have come before it)
        _save(settings, actors, opt_states, done)
        return settings.out

    def loss(actor, key):
        states = reset_all(config, params, key, jnp.asarray(config.episodes))
        values, counts = jax.vmap(objective, in_axes=(None, 0))(actor, states)
        return -jnp.mean(values), jnp.mean(counts, axis=0)

    def update(actor, opt_state, key):
        (value, counts), grads = jax.value_and_grad(loss, has_aux=True)(actor, key)
        step, opt_state = optimiser.update(grads, opt_state, actor)
        return optax.apply_updates(actor, step), opt_state, (value, counts, _norm(grads))

    update_all = jax.jit(jax.vmap(update))
    seeds = config.seeds
    base = jax.random.PRNGKey(settings.seed)
    rows = _rows(settings.out, done)
    bar = Progress(
        TextColumn("finetune", style="bold"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("iterations"),
        TimeRemainingColumn(),
        disable=not progress,
    )
    with bar, StopFlag(announce=progress, unit="iteration") as stop:
        task = bar.add_task("finetune", total=settings.iterations, completed=done)
        for it in range(done, settings.iterations):
            keys = jax.random.split(jax.random.fold_in(base, it), seeds)  # the same draws after a resume
            actors, opt_states, (value, counts, norm) = update_all(actors, opt_states, keys)
            if (it + 1) % LOG_EVERY == 0 or it + 1 == settings.iterations:
                value, counts, norm = jax.device_get((value, counts, norm))
                require(np.all(np.isfinite(value)), f"finetune diverged at iteration {it + 1}: lower --lr")
                rows += [
                    {
                        "iteration": it + 1,
                        "seed": s,
                        "objective": -float(value[s]),
                        "trap_contacts": float(counts[s, 0]),
                        "collisions": float(counts[s, 1]),
                        "gradient_norm": float(norm[s]),
                    }
                    for s in range(seeds)
                ]
                write_csv(settings.out / PROGRESS, rows)
                title = f"finetune of {settings.run.name}"
                plot_learning_curve(rows, settings.out / FIGURE, title, "iteration", "objective", OBJECTIVE)
            bar.update(task, completed=it + 1)
            last, stopping = it + 1 == settings.iterations, stop.raised  # read once: a signal may come between
            if last or stopping or (it + 1) % settings.checkpoint_every == 0:
                _save(settings, actors, opt_states, it + 1)
            if stopping and not last:
                raise RunStopped(f"interrupted at iteration {it + 1}; state saved: give the same command to resume")
    return settings.out


def _rows(out: Path, done: int) -> list[dict]:
    """``finetune.csv``'s rows up to iteration ``done``, the state saved (rows a stopped session
    wrote past it are written again on resume)."""
    if not done or not (out / PROGRESS).exists():
        return []
    lines = (out / PROGRESS).read_text().splitlines()
    header = lines[0].split(",")
    rows = [dict(zip(header, map(float, line.split(",")))) for line in lines[1:]]
    return [{**r, "iteration": int(r["iteration"]), "seed": int(r["seed"])} for r in rows if r["iteration"] <= done]
