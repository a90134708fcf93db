"""The run folder's lock: atomic, stale or not, released on every exit path."""

from __future__ import annotations

import os
import socket
import subprocess
import warnings
from pathlib import Path

import pytest

from roverswarm.errors import UserError
from roverswarm.runs import LOCK, folder_lock


def contend(folder: Path, go: int, release: int, result: int) -> None:
    """In a forked child: wait for ``go``, try the lock, write 'won' or 'lost' to ``result``;
    a winner holds the lock until ``release`` is readable."""
    try:
        os.read(go, 1)
        try:
            with folder_lock(folder):
                os.write(result, b"W")
                os.read(release, 1)
        except UserError as error:
            os.write(result, b"L" if "is being written by process" in str(error) else b"?")
    finally:
        os._exit(0)


def dead_pid() -> int:
    process = subprocess.Popen(["true"])
    process.wait()
    return process.pid


@pytest.mark.parametrize("stale", [True, False])
def test_writers_started_together_on_a_stale_lock_get_it_exactly_once(tmp_path, stale):
    """The issue's race: writers released at once on a folder whose .lock names a dead process
    (or none); exactly one takes the lock, the others are refused, in every round."""
    contenders = 8
    for round in range(15):
        folder = tmp_path / f"run{round}"
        folder.mkdir()
        if stale:
            (folder / LOCK).write_text(f"{dead_pid()} {socket.gethostname()}")
        go, release, result = os.pipe(), os.pipe(), os.pipe()
        children = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # JAX warns about fork; the children only touch files
            for _ in range(contenders):
                pid = os.fork()
                if pid == 0:
                    contend(folder, go[0], release[0], result[1])
                children.append(pid)
        os.write(go[1], b"g" * contenders)  # every child wakes at once
        outcomes = b""
        while len(outcomes) < contenders:
            outcomes += os.read(result[0], contenders)
        os.write(release[1], b"r" * contenders)
        for pid in children:
            os.waitpid(pid, 0)
        for fd in (*go, *release, *result):
            os.close(fd)
        assert sorted(outcomes.decode()) == ["L"] * (contenders - 1) + ["W"], (round, outcomes)
        assert not (folder / LOCK).exists()


def test_the_lock_is_released_on_every_exit_path_and_a_held_one_refused(tmp_path):
    folder = tmp_path / "run"
    with pytest.raises(RuntimeError):
        with folder_lock(folder):
            assert (folder / LOCK).read_text().split()[0] != ""
            with pytest.raises(UserError, match="is being written by process"):
                with folder_lock(folder):  # a second writer, even in the same process
                    pass
            raise RuntimeError("boom")
    assert not folder.exists()  # created here, left empty: removed
    folder.mkdir()
    (folder / LOCK).write_text("")  # an empty lock file (a writer killed between open and write)
    with folder_lock(folder):
        pass
    assert not (folder / LOCK).exists()
