"""Stopping jobs that train side by side (``reproduce`` and ``sweep`` with ``--jobs``, or their
Ray tasks: :mod:`~roverswarm.experiments.remote`) on Ctrl-C or SIGTERM, without a traceback
and without leaving a lock behind.

The first signal asks every running job to stop at its next chunk (each saves a checkpoint),
and no new job starts; further signals are ignored until the jobs have stopped, so the
parent always returns through its ``finally`` blocks (its folder lock is released). Jobs
start with SIGINT ignored: one signalled while it is still importing or compiling just goes
on until training installs its own handler, and the parent repeats its request every second
until every job has ended.
"""

from __future__ import annotations

import os
import signal
import time
from typing import Iterable

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class JobsStop:
    """A context in which SIGINT and SIGTERM set :attr:`asked` (in the main thread)."""

    def __init__(self):
        self.asked = False
        self._previous: dict[int, object] = {}
        self._told = 0.0

    def __enter__(self) -> JobsStop:
        try:
            self._previous = {sig: signal.signal(sig, self._handle) for sig in SIGNALS}
        except ValueError:  # not the main thread: signals stay as they are
            self._previous = {}
        return self

    def _handle(self, signum, frame) -> None:
        if not self.asked:
            print("roverswarm: stopping: every running job stops at its next chunk with a checkpoint", flush=True)
        self.asked = True

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)

    def tell(self, processes: Iterable, every: float = 1.0) -> None:
        """Ask every live process of ``processes`` to stop (SIGINT), at most once per ``every`` seconds."""
        if time.monotonic() - self._told < every:
            return
        self._told = time.monotonic()
        for process in processes:
            if process.is_alive():
                os.kill(process.pid, signal.SIGINT)

    def wait(self, processes: list) -> None:
        """Ask ``processes`` to stop and wait until every one has ended."""
        while any(p.is_alive() for p in processes):
            self.tell(processes)
            time.sleep(0.1)
        for process in processes:
            process.join()


def start_job(process) -> None:
    """Start ``process`` (a spawned one) with SIGINT ignored until training installs its handler."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # inherited through exec
    try:
        process.start()
    finally:
        signal.signal(signal.SIGINT, previous)
