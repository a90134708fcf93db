"""A local Ray cluster for the tests of `--backend ray` (`reproduce`, `sweep`), and a thread that
SIGKILLs one of its workers while it trains.

Use them in a process of the test's own (``multiprocessing.get_context("spawn")``): Ray's
driver threads outlive ``ray.shutdown()`` and crashed the test process minutes later (a
segfault after the last test, twice on CI).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

CHILD_TIMEOUT = 600
"""Seconds a test waits for a process of its own (a Ray driver, a grid it stops) before it
fails: such a child takes under a minute from an empty compilation cache; a wedged one
should fail the test with its name, not hang the suite."""

TASK = b"ray::train_remote"
"""The process title of a Ray worker running a training task."""


def training_workers() -> list[int]:
    """Process ids of the Ray workers running a training task now."""
    pids = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            if TASK in Path(f"/proc/{pid}/cmdline").read_bytes():
                pids.append(int(pid))
        except OSError:
            continue
    return pids


def wait_for_training(timeout: float = 300.0) -> int:
    """The first Ray worker seen running a training task (waits for one)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pids := training_workers():
            return pids[0]
        time.sleep(0.05)
    raise TimeoutError("no Ray worker started a training task")


@contextlib.contextmanager
def local_ray() -> Iterator[str]:
    """A local Ray cluster of 2 CPUs for this process; yields its address (for `--address`)."""
    import ray

    # Ray starts its workers at nice 15: beside other busy processes (the other test worker
    # runs at nice 0) they starve; a run took 58 s at nice 15 and 9 s at nice 0
    os.environ["RAY_worker_niceness"] = "0"
    context = ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield context.address_info["gcs_address"]
    finally:
        ray.shutdown()


@contextlib.contextmanager
def killing_a_worker(after: float) -> Iterator[list[int]]:
    """While the block runs, a thread SIGKILLs the first Ray worker seen running a training
    task, ``after`` seconds after seeing it (once); yields the list of the pids it killed."""
    killed: list[int] = []
    done = threading.Event()

    def kill() -> None:
        while not done.is_set():
            if pids := training_workers():
                time.sleep(after)
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
                return
            time.sleep(0.05)

    thread = threading.Thread(target=kill, daemon=True)
    thread.start()
    try:
        yield killed
    finally:
        done.set()
