"""Training the runs of a grid or a sweep on a Ray cluster (``--backend ray``).

Each run is one Ray task (one CPU), retried if its worker dies (``--retries``). A task trains
in the worker's scratch space (workers need not share a file system): an interrupted run's
files go with its task, which resumes it, and the files of the run come back to its folder
when the task ends. While its task is out, the command holds the run folder's lock, as a run
training here does, so a second writer is refused.

Ctrl-C or SIGTERM (:class:`~roverswarm.experiments.stopping.JobsStop`: the first asks, later
ones are ignored until the tasks have ended) sets a flag the tasks read after every chunk
(on :class:`Board`, a Ray actor): each running task stops at its next chunk with a checkpoint
and returns its files, a task not started yet returns nothing, and rerunning the command
resumes every run from what came back. The tasks also report their episodes there after each
chunk, so the live table shows a task waiting for a free CPU as queued, not running.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable
from pathlib import Path

from roverswarm.config import config_from_json, config_to_json
from roverswarm.errors import RunStopped, UserError, within
from roverswarm.experiments.arms import GridRun, episodes_done, status
from roverswarm.experiments.live import Summary
from roverswarm.experiments.stopping import JobsStop
from roverswarm.runs import CHECKPOINT, LOCK, folder_lock
from roverswarm.storage import atomic_write
from roverswarm.trainer import train

Files = dict[str, bytes]
"""A run folder's files by their path inside it."""


class Board:
    """A Ray actor between the command and its tasks: whether the command asked them to stop,
    and how many episodes each task that started has trained."""

    def __init__(self):
        self.stop = False
        self.episodes: dict[str, int] = {}

    def ask(self) -> None:
        self.stop = True

    def report(self, name: str, episodes: int) -> bool:
        """Task ``name`` has trained ``episodes`` (per seed); returns whether to stop."""
        self.episodes[name] = episodes
        return self.stop

    def reports(self) -> dict[str, int]:
        return dict(self.episodes)


def read_files(folder: Path) -> Files:
    """Every file of run folder ``folder`` but its lock and temporary files."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != LOCK and not p.name.endswith(".tmp")
    }


def write_files(folder: Path, files: Files) -> None:
    """``files`` into ``folder``, each atomically, the checkpoint last: at every moment the
    folder holds a run that resumes (a checkpoint never ahead of its metrics)."""
    for name in sorted(files, key=lambda name: name == CHECKPOINT):
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, lambda f, content=files[name]: f.write(content), binary=True)


def train_remote(
    config_json: str, files: Files | None, board, name: str, start: int
) -> tuple[Files, str | None] | None:
    """A Ray task: train run ``name`` in a scratch folder, resuming the interrupted run ``files``
    holds (``start`` episodes; none: 0), reporting its episodes to ``board`` (a :class:`Board`)
    as it starts and after each chunk, and stopping at the next chunk once the board says so.
    Returns the run folder's files and why the run stopped before its end (None: it finished),
    or None if the stop came before it started."""
    import ray

    from roverswarm.jaxcache import enable_compilation_cache

    if ray.get(board.report.remote(name, start)):
        return None
    enable_compilation_cache()
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(scratch) / "run"
        out.mkdir()
        write_files(out, files or {})

        def asked(episodes: int) -> bool:
            return ray.get(board.report.remote(name, episodes))

        try:
            train(config_from_json(config_json), out=out, resume=bool(files), progress=False, on_chunk=asked)
            stopped = None
        except RunStopped as error:  # asked to, or a non-finite loss (the last good checkpoint kept)
            stopped = str(error)
        return read_files(out), stopped


def _ray():
    try:
        import ray
    except ImportError as error:
        raise UserError("--backend ray needs Ray: pip install 'roverswarm[ray]'") from error
    return ray


def run_ray(
    runs: list[GridRun],
    summary: Summary,
    address: str | None,
    retries: int,
    on_finish: Callable[[GridRun], None] | None = None,
) -> None:
    """Train ``runs`` as Ray tasks (see the module docstring), writing each run's files into its
    folder as its task ends; ``on_finish(run)`` follows each run that finished.

    :class:`UserError` if a run's folder is being written by another process (before anything
    is sent) or a task fails with one; :class:`~roverswarm.errors.RunStopped` after a signal or
    a run that stopped on its own, once every task has ended. An error here on one run's files
    or row (a full disk) is raised the same way: once every other task's files are back."""
    with contextlib.ExitStack() as locks:
        for run in runs:  # every folder first: a run already being written sends nothing
            with within(f"run '{run.name}'"):
                locks.enter_context(folder_lock(run.folder))
        ray = _ray()
        if not ray.is_initialized():
            ray.init(address=address, log_to_driver=False)  # sets its own SIGTERM handler: before JobsStop
        task = ray.remote(num_cpus=1, max_retries=retries)(train_remote)
        board = ray.remote(num_cpus=0)(Board).remote()
        failure: Exception | None = None
        with JobsStop() as stop:
            pending = {}
            try:
                for run in runs:
                    resume = status(run) == "partial"
                    files, start = (read_files(run.folder), episodes_done(run)) if resume else (None, 0)
                    pending[task.remote(config_to_json(run.config), files, board, run.name, start)] = run
                told = False
                while pending:
                    if (stop.asked or failure is not None) and not told:
                        board.ask.remote()
                        told = True
                    follow(summary, list(pending.values()), ray.get(board.reports.remote()))
                    for ref in ray.wait(list(pending), num_returns=1, timeout=0.5)[0]:
                        run = pending.pop(ref)
                        try:
                            result = ray.get(ref)
                        except ray.exceptions.RayError as error:  # failed, or its worker died past its retries
                            failure = failure or _failure(run, error, retries)
                            continue
                        if result is not None:
                            files, stopped = result
                            try:  # an error here (a full disk, a damaged table) leaves the others to collect
                                write_files(run.folder, files)
                                if stopped is None:
                                    summary.finish(run)
                                    if on_finish is not None:
                                        on_finish(run)
                            except Exception as error:  # raised once the others are back
                                failure = failure or error
                                continue
                            if stopped is not None and not stop.asked:
                                failure = failure or RunStopped(f"run '{run.name}': {stopped}")
            finally:  # a task left running (this command failed) stops at its next chunk
                if pending:
                    board.ask.remote()
    if failure is not None:
        raise failure
    if stop.asked:
        raise RunStopped("interrupted; every running run saved a checkpoint: rerun the same command to resume")


def follow(summary: Summary, pending: list[GridRun], reports: dict[str, int]) -> None:
    """The live table's progress of the ``pending`` runs whose task reported to the board: a
    task not started yet stays queued, and a run that ended is not taken back to running."""
    for run in pending:
        if run.name in reports:
            summary.progress(run, reports[run.name])


def _failure(run: GridRun, error: Exception, retries: int) -> Exception:
    """The one-line error of ``run``'s task: its own :class:`UserError` or
    :class:`RunStopped`, another error's first line, or a worker lost more often than retried."""
    cause = getattr(error, "cause", None)
    if isinstance(cause, (UserError, RunStopped)):
        return type(cause)(f"run '{run.name}': {cause}")
    if cause is not None:
        first = (str(cause).strip().splitlines() or [""])[0]
        return RunStopped(f"run '{run.name}': its task failed ({type(cause).__name__}: {first})")
    return RunStopped(
        f"run '{run.name}': its worker was lost {retries + 1} times ({type(error).__name__}); "
        "rerun the same command to resume"
    )
