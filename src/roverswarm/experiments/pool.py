"""Training a grid's runs locally: one after another in this process, or side by side in
processes of their own, each pinned to its share of the CPUs."""

from __future__ import annotations

import multiprocessing
import os
import sys
import time
from pathlib import Path

from roverswarm.config import config_from_json, config_to_json
from roverswarm.errors import RunStopped, UserError
from roverswarm.experiments.arms import SHORT_RUN, GridRun, episodes_done, episodes_logged, status, usable_cpus
from roverswarm.experiments.live import Summary
from roverswarm.experiments.stopping import JobsStop, start_job
from roverswarm.jaxcache import release_compiled_programs
from roverswarm.limits import memory_limit
from roverswarm.trainer import run_memory, train


def run_local(runs: list[GridRun], summary: Summary, keep_programs: bool = False) -> None:
    """Train ``runs`` one after another in this process (resuming interrupted ones), releasing
    each run's compiled programs after it (with ``keep_programs``, only when crowded)."""
    for run in runs:
        resume = status(run) == "partial"
        summary.progress(run, episodes_done(run) if resume else 0)
        try:
            train(  # no bar (the summary shows every run), but a Ctrl-C is answered at once
                run.config,
                out=run.folder,
                resume=resume,
                progress=False,
                on_chunk=lambda e, r=run: summary.progress(r, e),
                announce=True,
            )
        except RunStopped:  # train's own message names the run alone, which finishes no grid
            raise RunStopped(
                f"interrupted at episode {episodes_done(run)} of run '{run.name}', checkpoint saved: "
                "rerun the same command to resume"
            ) from None
        release_compiled_programs(only_if_crowded=keep_programs)  # each run compiles its own programs
        summary.finish(run)


def default_jobs(runs: list[GridRun]) -> int:
    """Runs to train side by side: one at a time for short runs (:data:`SHORT_RUN`), else at
    most one per CPU, as many as fit in 80% of the memory this process may use
    (:func:`~roverswarm.trainer.run_memory`), and no more than there are runs."""
    if not runs or max(run.config.episodes for run in runs) < SHORT_RUN:
        return 1
    fit = int(0.8 * memory_limit() // max(run_memory(run.config) for run in runs))
    return max(1, min(len(runs), len(usable_cpus()), fit))


def train_runs(runs: list[GridRun], summary: Summary, jobs: int, keep_programs: bool = False) -> None:
    """Train ``runs`` ``jobs`` at a time in processes of their own (:func:`run_jobs`), or with
    one job one after another in this process (:func:`run_local`)."""
    if jobs > 1:
        run_jobs(runs, summary, jobs)
    else:
        run_local(runs, summary, keep_programs)


def cpu_shares(jobs: int) -> list[list[int]]:
    """The CPUs this process may use, dealt out to ``jobs`` (at most one job per CPU)."""
    cpus = usable_cpus()
    return [cpus[i::jobs] for i in range(jobs)]


def run_jobs(runs: list[GridRun], summary: Summary, jobs: int) -> None:
    """Train ``runs`` ``jobs`` at a time, each in its own process pinned to its share of this
    process's CPUs (resuming interrupted ones); the summary follows each run's metrics.csv.

    Ctrl-C or SIGTERM stops every running run at its next chunk with a checkpoint (rerun the
    command to resume); a run that fails stops the others the same way and is reported."""
    free = cpu_shares(jobs)
    context = multiprocessing.get_context("spawn")  # a fresh JAX per process (fork would copy threads)
    failures = context.Queue()
    queue, running, reported = list(runs), {}, {}
    with JobsStop() as stop:  # first Ctrl-C or SIGTERM: every job stops at its next chunk; later ones ignored
        try:
            while (queue and not stop.asked) or running:
                while queue and free and not stop.asked:
                    run, share = queue.pop(0), free.pop()
                    args = (config_to_json(run.config), str(run.folder), status(run) == "partial", share, failures)
                    process = context.Process(target=_train_job, args=args, daemon=False)
                    start_job(process)
                    running[process] = (run, share)
                time.sleep(0.5)
                if stop.asked:
                    stop.tell(running)
                for process in [p for p in running if not p.is_alive()]:
                    run, share = running.pop(process)
                    free.append(share)
                    if process.exitcode != 0 and not stop.asked:
                        while not failures.empty():  # every job's error so far, by its folder
                            folder, kind, text = failures.get()
                            reported[folder] = (kind, text)
                        kind, message = reported.get(str(run.folder), ("stopped", f"exit code {process.exitcode}"))
                        raise (UserError if kind == "user" else RunStopped)(f"run '{run.name}': {message}")
                    if process.exitcode == 0:
                        summary.finish(run)
                for run, _ in running.values():
                    summary.progress(run, episodes_logged(run))
        finally:  # stop the others at their next chunk, with a checkpoint
            stop.wait(list(running))
    if stop.asked:
        raise RunStopped("interrupted; every running run saved a checkpoint: rerun the same command to resume")


def _train_job(config_json: str, folder: str, resume: bool, cpus: list[int], failures) -> None:
    """A job of :func:`run_jobs`: one run on ``cpus``; its error (one line) goes to ``failures``
    beside its folder, so the error reported is the failed run's own."""
    if hasattr(os, "sched_setaffinity"):  # Linux; elsewhere the jobs share every CPU
        os.sched_setaffinity(0, cpus)  # before JAX starts its threads, which it sizes by the CPUs it may use
    from roverswarm.jaxcache import enable_compilation_cache

    enable_compilation_cache()
    try:
        train(config_from_json(config_json), out=Path(folder), resume=resume, progress=False)
    except (UserError, RunStopped, OSError) as error:
        failures.put((folder, "user" if isinstance(error, UserError) else "stopped", str(error)))
        sys.exit(1)
    except KeyboardInterrupt:  # stopped before training installed its handler: nothing to save yet
        failures.put((folder, "stopped", "interrupted before its first chunk"))
        sys.exit(1)
