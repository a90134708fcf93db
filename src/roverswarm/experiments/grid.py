"""The paper's experiment grid: scenarios x algorithms, seeds vmapped inside each run.

Each (scenario, algorithm) run trains in its own folder ``OUT/runs/<scenario>/<algorithm>``
with :func:`roverswarm.trainer.train`: planned in :mod:`~roverswarm.experiments.arms`, shown
in :mod:`~roverswarm.experiments.live`, trained by :mod:`~roverswarm.experiments.pool` or
:mod:`~roverswarm.experiments.remote`. A finished run is never trained again (unless
``--force``); an interrupted one resumes from its checkpoint. Runs execute in this process
(``--backend local``) or as tasks of a Ray cluster (``--backend ray``), each retried if its
worker dies; either way the files land in the same folders and the same report.
"""

from __future__ import annotations

import shutil
from contextlib import ExitStack
from typing import Callable

from rich.live import Live

from roverswarm.config import TrainConfig, validate_training
from roverswarm.console import console
from roverswarm.errors import RunStopped, within
from roverswarm.experiments.arms import GridRun, ReproduceConfig, check_evaluations, plan, status
from roverswarm.experiments.live import Summary
from roverswarm.experiments.pool import default_jobs, train_runs
from roverswarm.experiments.remote import run_ray
from roverswarm.experiments.results import TIMING
from roverswarm.limits import check_training_memory
from roverswarm.runs import folder_lock


def run_grid(config: ReproduceConfig, base: TrainConfig | None = None, live: bool = True) -> list[GridRun]:
    """Train every run of the grid that is not finished yet; returns all runs of the grid."""
    runs = plan(config, base)
    for run in runs:  # every run checked, its memory too, before the first trains
        with within(f"arm '{run.algorithm}' on {run.scenario}"):  # which arm (a --variants one too) set the flag
            params = validate_training(run.config)
        check_training_memory(run.config, params)
    check_evaluations(runs, config.grid_eval_episodes)
    if config.force:  # once every run is checked: the runs, and the times taken with their settings
        with ExitStack() as locks:  # none deleted while a command writes one (train --resume RUN)
            held = []
            for folder in [run.folder for run in runs if run.folder.exists()]:
                lock = locks.enter_context(ExitStack())
                lock.enter_context(folder_lock(folder))
                held.append((folder, lock))
            for folder, lock in held:
                shutil.rmtree(folder)
                lock.close()  # at once: a writer that makes the folder anew then holds a lock of its own
        (config.out / TIMING).unlink(missing_ok=True)
    done = {run.name for run in runs if status(run) == "done"}
    todo = [run for run in runs if run.name not in done]
    summary = Summary(runs, done)
    if config.backend == "ray":
        execute: Callable[[], None] = lambda: run_ray(todo, summary, config.address, config.retries)  # noqa: E731
    else:
        jobs = config.jobs or default_jobs(todo)
        execute = lambda: train_runs(todo, summary, jobs, config.grid_keep_programs)  # noqa: E731
    try:
        if live:
            with Live(summary, console=console(), refresh_per_second=2):
                execute()
        else:
            execute()
    except RunStopped as stopped:
        if not config.force:
            raise
        # the same command again would delete what the runs saved: --force starts every run anew
        raise RunStopped(f"{stopped} (rerun without --force: with it every run starts again)") from None
    return runs
