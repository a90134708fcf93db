"""The host loop every learner family shares: :func:`train` runs a family's jitted chunks and
around them writes metrics, checkpoints, TensorBoard events and progress, and turns Ctrl-C and
SIGTERM into a checkpoint and a clean stop.

A chunk (``log_every`` episodes of every seed, one jitted call) is the family's
(:attr:`~roverswarm.learners.base.Family.run_chunk`: :mod:`roverswarm.learners.offpolicy`
for ``--algo maddpg``/``ddpg``, :mod:`roverswarm.learners.onpolicy` for ``mappo``/``ippo``),
compiled once per family config: another seed, episode count or output folder reuses it.
"""

from __future__ import annotations

import math
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from tensorboardX import SummaryWriter

from roverswarm.config import (
    RESUME_CHANGES,
    TrainConfig,
    config_to_json,
    fields_by_name,
    validate,
    validate_training,
    with_mission_text,
)
from roverswarm.env.mars import EnvParams
from roverswarm.errors import RunStopped, require
from roverswarm.learners import learner_family
from roverswarm.limits import check_training_memory, read_config
from roverswarm.runs import (
    CHECKPOINT,
    CONFIG,
    CURVE,
    METRICS,
    budget_spent,
    checkpointed_rows,
    folder_lock,
    metric_rows,
    plot_learning_curve,
    training_seconds,
    write_csv,
)
from roverswarm.storage import checkpoint_changes, load_checkpoint, save_checkpoint, write_text

# ----------------------------------------------------------------------------- host loop


@dataclass(frozen=True)
class Result:
    """What :func:`train` returns: the config, the metrics rows and the final networks."""

    config: TrainConfig
    metrics: list[dict[str, float]]
    learner: Any  # [S, ...] the family's learner state
    out: Path | None


class StopFlag:
    """Turns Ctrl-C (SIGINT) and SIGTERM (schedulers, Ray) into a flag the host loop checks
    between chunks (in the main thread only); with ``announce`` (a command at a terminal, a
    grid's runs in its own process) the first signal says so at once (a job of ``reproduce``
    or ``sweep`` in a process of its own does not: its parent speaks for it). Further signals
    change nothing: the chunk in flight runs in XLA, and leaving Python under it crashed the
    interpreter (a second Ctrl-C that raised KeyboardInterrupt ended in a segmentation fault
    after the chunk anyway)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, announce: bool = False, unit: str = "chunk"):
        self.raised = False
        self.announce = announce
        self.unit = unit  # what the loop finishes before it stops
        self._previous: dict[int, object] = {}

    def __enter__(self):
        try:
            self._previous = {sig: signal.signal(sig, self._handle) for sig in self.SIGNALS}
        except ValueError:  # not the main thread: leave signals alone
            self._previous = {}
        return self

    def _handle(self, signum, frame):
        first, self.raised = not self.raised, True
        if first and self.announce:
            name = signal.Signals(signum).name
            try:  # a closed stderr (`| tee` killed by the same Ctrl-C) must not cost the checkpoint
                print(
                    f"\nroverswarm: {name}: stopping after this {self.unit}, with a checkpoint (SIGKILL stops "
                    "at once, keeping the last checkpoint saved)",
                    file=sys.stderr,
                    flush=True,
                )
            except (OSError, ValueError):
                pass

    def __exit__(self, *exc):
        for sig, previous in self._previous.items():
            if previous is not None:  # None: a handler not set from Python, which cannot be put back
                signal.signal(sig, previous)


def _wait(tree: Any) -> None:
    """Until every array of ``tree`` is computed, waiting in Python: a signal's handler runs only
    when the main thread is in Python, which a blocking read of a chunk's results (minutes,
    in XLA) would hold back to the chunk's end."""
    leaves = jax.tree.leaves(tree)
    while not all(x.is_ready() for x in leaves):
        time.sleep(0.005)  # a few hundred wake-ups a second: nothing beside a chunk


def _all_finite(tree: Any) -> bool:
    """Whether every float in ``tree`` (a learner state: networks, optimisers, statistics) is finite."""
    return all(
        np.isfinite(x).all() for x in jax.device_get(jax.tree.leaves(tree)) if np.issubdtype(x.dtype, np.inexact)
    )


def _same_columns(*tables: list[dict[str, float]]) -> list[list[dict[str, float]]]:
    """``tables`` of metrics rows with every column of any of them, NaN where a row lacks one:
    a run resumed by another version of roverswarm, whose metrics gained or lost a column,
    keeps its earlier rows (the CSV writer refused rows of other keys, with a traceback)."""
    columns = list(dict.fromkeys(c for table in reversed(tables) for c in table[0]))
    return [[{c: r.get(c, math.nan) for c in columns} for r in table] for table in tables]


def _diverged(what: str, episodes: int, out: Path | None) -> RunStopped:
    kept = (
        f"the last good checkpoint in '{out}' is kept"
        if out is not None and (out / CHECKPOINT).exists()
        else "no checkpoint was saved"
    )
    return RunStopped(f"non-finite {what} at episode {episodes}; stopping ({kept}). Try smaller learning rates.")


def train(
    config: TrainConfig,
    out: Path | None = None,
    resume: bool = False,
    progress: bool = True,
    on_chunk: Callable[[int], None] | None = None,
    announce: bool | None = None,
) -> Result:
    """Train ``config.seeds`` seeds of ``config`` together and return the metrics and networks.

    With ``out``, writes there: ``config.json``, ``metrics.csv`` (one row per seed per
    ``log_every`` episodes), TensorBoard events in ``tb/``, ``checkpoint.npz`` and
    ``learning_curve.png``. ``resume=True`` continues from ``out``'s checkpoint and gives the
    same numbers as an unbroken run; ``config`` is the run's own but for ``episodes`` and
    ``budget_minutes``, which may grow to extend a finished or interrupted run
    (docs/training.md#extending-a-run); a budget ends a run early
    (docs/training.md#a-wall-time-budget). Same config => identical metrics.
    ``on_chunk(episodes)`` is called after every chunk (e.g. to draw a summary of many runs
    instead of the bar); if it returns true, the run stops there as on Ctrl-C (a checkpoint,
    then :class:`~roverswarm.errors.RunStopped`). ``announce``: whether the first Ctrl-C or
    SIGTERM says at once that training stops after the chunk (default: with the progress bar;
    a grid's runs in its own process announce without one).
    """
    if config.mission is not None:  # kept absolute and with its content: resume and evaluate need not find the file
        config = with_mission_text(config)
    params = validate_training(config)
    check_training_memory(config, params)  # networks, replay, rollouts and minibatches, before any is allocated
    require(out is not None or not resume, "resume=True needs the run folder (--out) to resume")
    require(
        out is not None or config.episodes <= 10_000,
        "give --out for runs of more than 10000 episodes, so that they can be resumed",
    )
    if out is None:
        return _train(config, params, None, resume, progress, on_chunk, announce)
    with folder_lock(Path(out)):  # one writer per run folder
        return _train(config, params, Path(out), resume, progress, on_chunk, announce)


def training_notes(config: TrainConfig, out: str | Path | None) -> list[str]:
    """What a user should hear before a run of ``config`` into ``out`` starts: that it would
    end without one update (the family's :attr:`~roverswarm.learners.base.Family.idle`), or
    keep nothing (no run folder). ``train`` on the command line prints them."""
    params = validate_training(config)
    notes = [learner_family(config.learner.algo).idle(config, params)]
    if out is None:
        notes.append("no --out: nothing of the run is kept (networks, metrics, learning curve); give --out to keep it")
    return [note for note in notes if note]


def checkpoint_due(config: TrainConfig, chunks_done: int, saved_at: float) -> bool:
    """A checkpoint is due after every ``--checkpoint-every`` chunks of this session
    (``chunks_done``) and once ``--checkpoint-minutes`` have passed since the last one was
    written (``saved_at``, on ``time.monotonic``)."""
    by_time = config.checkpoint_minutes > 0 and time.monotonic() - saved_at >= 60 * config.checkpoint_minutes
    return chunks_done % config.checkpoint_every == 0 or by_time


RUN_OVERHEAD = 2 * 2**30
"""Memory of a run besides its replay (compiled programs, networks, environment batches, the
Python process): a reproduce --quick grid peaks near 0.9 GB, or 2.1 GB with --keep-programs."""


def replay_bytes(config: TrainConfig, params: EnvParams) -> tuple[int, int, int]:
    """(bytes, transitions, bytes per transition) of every seed's replay of ``config`` (0 for a
    family without one), from its shapes (nothing is allocated)."""
    return learner_family(config.learner.algo).replay_bytes(config, params)


def run_memory(config: TrainConfig) -> int:
    """Bytes a run of ``config`` needs: its replay plus :data:`RUN_OVERHEAD`."""
    return replay_bytes(config, validate(config))[0] + RUN_OVERHEAD


def _minutes(seconds: float) -> str:
    """``seconds`` in minutes for a message: 3 significant digits below 1000, whole minutes above."""
    minutes = seconds / 60
    return f"{minutes:.3g}" if minutes < 1000 else f"{minutes:,.0f}"


def _check_resumable(config: TrainConfig, out: Path) -> tuple[int, list[dict[str, float]]]:
    """``out`` holds a run trained with ``config`` but for its episodes and budget (:data:`RESUME_CHANGES`),
    which may grow to extend it, never below what the checkpoint has trained, and whose budget
    is not spent unless it is finished; else :class:`UserError` (before anything is loaded or
    written). Returns :func:`~roverswarm.runs.checkpointed_rows` (read once)."""
    checkpoint = out / CHECKPOINT
    require(
        checkpoint.exists() and (out / CONFIG).exists(),
        f"--resume: no run to continue in '{out}' (config.json and checkpoint.npz)",
    )
    saved = fields_by_name(read_config(out / CONFIG))
    differ = [n for n, value in fields_by_name(config).items() if saved[n] != value and n not in RESUME_CHANGES]
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
    done, rows = checkpointed_rows(out)
    require(
        config.episodes >= done,
        f"--episodes {config.episodes} is below the {done} episodes this run has trained per seed; a run is "
        f"extended, never shortened: give --episodes >= {done}",
    )
    spent = training_seconds(rows)
    require(
        done == config.episodes or not budget_spent(config, spent),
        f"--resume: the run has spent its budget ({_minutes(spent)} of --budget-minutes {config.budget_minutes:g}); "
        "give a larger --budget-minutes to continue it",
    )
    return done, rows


def _train(
    config: TrainConfig,
    params: EnvParams,
    out: Path | None,
    resume: bool,
    progress: bool,
    on_chunk: Callable[[int], None] | None,
    announce: bool | None,
) -> Result:
    family = learner_family(config.learner.algo)
    rows: list[dict[str, float]] = []
    program = family.configure(config, params)
    if out is not None and resume:
        done, rows = _check_resumable(config, out)
        # the fresh runner held by nothing else: its empty replay is let go as the saved one is placed
        runner = load_checkpoint(
            out / CHECKPOINT, family.init(program, params, config.seed), family.replay_buffer(program, params)
        )
    else:
        runner = family.init(program, params, config.seed)
    total = jnp.int32(config.episodes)  # data, not part of the compiled program
    if out is not None:
        if resume:
            require(
                len(rows) == done // config.log_every * config.seeds,
                f"--resume: '{out / METRICS}' is missing or lacks rows of the {done} episodes in the checkpoint; "
                "restore it (they cannot be rebuilt) or start a new run",
            )
        else:
            require(
                not (out / CHECKPOINT).exists(),
                f"'{out}' already holds a run; continue it with --resume or choose another --out",
            )
            # a finished or stopped run always has its checkpoint: one whose checkpoint was removed
            # (to save space) keeps its curve and metrics as its record
            require(
                not (out / CURVE).exists(),
                f"'{out}' holds a run's {METRICS} and {CURVE} but no {CHECKPOINT} (removed?), which training "
                "would overwrite; choose another --out",
            )
            # a mission's outputs, say: a run (even one stopped before its checkpoint) writes config.json first
            require(
                not (out / METRICS).exists() or (out / CONFIG).exists(),
                f"'{out}' holds another command's {METRICS} (no {CONFIG}: not a training run), which training "
                "would overwrite; choose another --out",
            )
            out.mkdir(parents=True, exist_ok=True)
            write_text(out / CONFIG, config_to_json(config))
    # a resumed run's config.json (its --episodes or budget may have grown) is written with its
    # first checkpoint: an extension lost before that leaves the run as it was (finished, say)
    config_due = out is not None and resume
    chunks = config.episodes // config.log_every
    first = int(runner.episodes) // config.log_every
    # on resume TensorBoard drops the events a killed session logged past the checkpoint
    purge = (first + 1) * config.log_every if first else None
    writer = SummaryWriter(str(out / "tb"), purge_step=purge) if out is not None else None
    spent = training_seconds(rows)
    bar = Progress(
        TextColumn("{task.description}", style="bold", markup=False),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("episodes"),
        TextColumn("reward {task.fields[reward]}"),
        TextColumn("{task.fields[rate]} ep/s"),
        TimeRemainingColumn(),
        disable=not progress,
    )
    try:
        with bar, StopFlag(announce=progress if announce is None else announce) as stop:
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
                runner, metrics = family.run_chunk(program, params, runner, total)
                _wait(metrics)
                metrics = jax.device_get(metrics)
                seconds = time.perf_counter() - start
                episodes = (chunk + 1) * config.log_every
                new_rows = metric_rows(config, metrics, episodes, seconds)
                if not all(math.isfinite(v) for r in new_rows for v in r.values()):
                    raise _diverged("loss or reward", episodes, out)
                if rows and set(new_rows[0]) != set(rows[0]):  # resuming a run of another version
                    rows, new_rows = _same_columns(rows, new_rows)
                rows.extend(new_rows)
                spent += seconds
                if writer is not None:
                    for r in new_rows:
                        for k, v in r.items():
                            if k not in ("seed", "episodes") and math.isfinite(v):  # NaN: a column of an older version
                                writer.add_scalar(f"seed_{int(r['seed'])}/{k}", v, episodes)
                if on_chunk is not None and on_chunk(episodes):
                    stop.raised = True
                bar.update(
                    task,
                    completed=episodes,
                    reward=f"{np.mean(metrics['episode_reward']):.1f}",
                    rate=f"{config.log_every / seconds:,.0f}",
                )
                out_of_time = budget_spent(config, spent) and chunk + 1 < chunks
                last = chunk + 1 == chunks or out_of_time
                stopping = stop.raised  # read once: a signal between two reads stopped the run unsaved
                if out is not None:  # every chunk's rows at once; rows past the checkpoint are trimmed on resume
                    write_csv(out / METRICS, rows)
                if out is not None and (last or stopping or checkpoint_due(config, chunk + 1 - first, saved_at)):
                    if not _all_finite(runner.learner):  # the chunk's last update, which no loss saw yet
                        raise _diverged("network parameters", episodes, out)
                    unfinished = chunk + 1 < chunks  # a finished run's replay is dropped (most of the file)
                    save_checkpoint(out / CHECKPOINT, runner, replay=unfinished, config_json=config_to_json(config))
                    if config_due:  # after the checkpoint: lost between the two, resume names the new --episodes
                        write_text(out / CONFIG, config_to_json(config))
                        config_due = False
                    saved_at = time.monotonic()
                if stopping and not last:
                    if out is not None:
                        plot_learning_curve(rows, out / CURVE, f"{config.learner.algo} on {config.env_name()}")
                    where = (
                        f"checkpoint saved; continue with: roverswarm train --resume {out}"
                        if out
                        else "nothing saved (no --out)"
                    )
                    raise RunStopped(f"interrupted at episode {episodes}; {where}")
                if out_of_time:
                    bar.console.print(
                        f"--budget-minutes {config.budget_minutes:g} spent after {_minutes(spent)} minutes: "
                        f"the run ends at episode {episodes} of {config.episodes}"
                    )
                    break
    finally:  # flush TensorBoard also when the run stops early
        if writer is not None:
            writer.close()
    if out is not None:
        plot_learning_curve(rows, out / CURVE, f"{config.learner.algo} on {config.env_name()}")
    return Result(config=config, metrics=rows, learner=runner.learner, out=out)
