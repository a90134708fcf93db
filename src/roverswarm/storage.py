"""How a run's state is kept on disk: atomic writes, and the checkpoint, the trainer's state
as plain arrays in an ``.npz`` file (never pickle), read back into a template of its structure."""

from __future__ import annotations

import errno
import os
import zipfile
from collections import ChainMap
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from roverswarm.buffers.base import placed
from roverswarm.config import RESUME_CHANGES, TrainConfig, config_from_json, fields_by_name
from roverswarm.errors import UserError, require


def leaves(tree: dict, prefix: str = "") -> dict:
    """The leaves of nested dicts ``tree``, as they are, by their slash-joined paths (Nones left out)."""
    flat = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(leaves(value, path + "/"))
        elif value is not None:
            flat[path] = value
    return flat


def flatten(tree: dict, prefix: str = "") -> dict[str, np.ndarray]:
    """:func:`leaves` as NumPy arrays."""
    return {path: np.asarray(value) for path, value in leaves(tree, prefix).items()}


STARTS_AS = {"target_approx": "approx"}
"""Parts of a learner that a checkpoint written before they existed lacks, and the part each
is read from then, as a fresh run starts it: the inferred policies' targets (2026-12-02)
start as the approximations."""


def _older_key(key: str) -> str:
    """The name an older checkpoint gives the array ``key`` (:data:`STARTS_AS`)."""
    return "/".join(STARTS_AS.get(part, part) for part in key.split("/"))


def restore(template, flat: dict[str, np.ndarray], prefix: str = ""):
    """``template`` (a pytree of flax structs) with every leaf replaced by ``flat[path]``
    (or, in a checkpoint older than that leaf, by what it starts as: :data:`STARTS_AS`)."""

    def fill(node, path):
        if isinstance(node, dict):
            return {k: fill(v, f"{path}{k}/") for k, v in node.items()}
        if node is None:
            return None
        key = prefix + path[:-1]
        if key not in flat and _older_key(key) in flat:
            key = _older_key(key)
        if key not in flat:
            raise UserError(f"checkpoint does not match this run: it has no '{key}'")
        value = flat[key]
        if value.shape != np.shape(node):
            raise UserError(
                f"checkpoint does not match this run: '{key}' has shape {value.shape}, expected {np.shape(node)}"
            )
        return jnp.asarray(value)

    return serialization.from_state_dict(template, fill(serialization.to_state_dict(template), ""))


CHECKPOINT_CONFIG = "meta/config_json"
"""The checkpoint's copy of the run's config.json, so that resume notices an edited config.json."""


def checkpoint_changes(path: Path, config: TrainConfig) -> list[str]:
    """The fields in which ``config`` differs from the config checkpoint ``path`` was trained
    with (none for a checkpoint written before it kept its config), but for those a resume
    may change (:data:`~roverswarm.config.RESUME_CHANGES`)."""
    kept = read_arrays(path, CHECKPOINT_CONFIG).get(CHECKPOINT_CONFIG)
    if kept is None:
        return []
    trained = fields_by_name(config_from_json(kept.tobytes().decode()))
    changed = [name for name, value in fields_by_name(config).items() if trained.get(name) != value]
    return [name for name in changed if name not in RESUME_CHANGES]


def save_checkpoint(path: Path, runner, replay: bool = True, config_json: str | None = None) -> None:
    """Write ``runner`` (the trainer's state: ``learner``, ``buffer`` and counters) to ``path``
    atomically (temp file, then rename); plain arrays, no pickle.

    Only the filled part of the replay is written; loading pads it back. With
    ``replay=False`` (a finished run: nothing left to train) the replay is left out, which
    makes the file hundreds of times smaller.
    """
    runner = jax.device_get(runner)
    if runner.buffer is not None:
        filled = int(np.max(runner.buffer.size))
        runner = runner.replace(
            buffer=runner.buffer.replace(data=jax.tree.map(lambda x: x[:, :filled], runner.buffer.data))
        )
    arrays = flatten(serialization.to_state_dict(runner))
    if config_json is not None:
        arrays[CHECKPOINT_CONFIG] = np.frombuffer(config_json.encode(), np.uint8)
    if not replay:
        arrays = {k: v for k, v in arrays.items() if not k.startswith("buffer/")}
    atomic_write(path, lambda f: np.savez(f, **arrays), binary=True)


def _write_temporary(path: Path, write: Callable[[IO], None], binary: bool) -> Path:
    """``write(file)`` into ``path``'s temporary file beside it, flushed to disk; returns it."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)  # a link left there is removed, not written through
    with open(tmp, "wb" if binary else "w", newline=None if binary else "") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    return tmp


def atomic_write(path: Path, write: Callable[[IO], None], binary: bool = False) -> None:
    """``write(file)`` into a temporary file beside ``path``, flushed to disk, then renamed over
    ``path``: a reader sees the old file or the new one, never half of one. If writing fails
    (a full disk, a read-only folder) the temporary file is removed, ``path`` is left as it
    was, and :class:`UserError` says so."""
    try:
        os.replace(_write_temporary(path, write, binary), path)
    except BaseException as error:  # also a second Ctrl-C mid-write: no temporary file left (a checkpoint's are GBs)
        path.with_name(path.name + ".tmp").unlink(missing_ok=True)
        if not isinstance(error, OSError):
            raise
        kept = "the previous version is kept" if path.exists() else "nothing was written"
        raise UserError(f"cannot write '{path}' ({error.strerror or error}); {kept}") from error


def write_text(path: Path, text: str) -> None:
    """``text`` into ``path`` by :func:`atomic_write`: never half a file, never through a symlink."""
    atomic_write(path, lambda f: f.write(text))


def save_figure(figure, path: Path) -> None:
    """A matplotlib ``figure`` into ``path`` (its suffix the format) by :func:`atomic_write`."""
    atomic_write(path, lambda f: figure.savefig(f, format=path.suffix[1:]), binary=True)


def atomic_write_files(contents: dict[Path, str | bytes]) -> None:
    """Each file of ``contents`` (text, or bytes) written as :func:`atomic_write` does, and
    renamed over its path only once every one is written: if any fails, all are left as they
    were (a folder holds one export or the other, never files of both)."""
    try:
        temporary = [_write_temporary(p, lambda f, c=c: f.write(c), isinstance(c, bytes)) for p, c in contents.items()]
        blocked = next((p for p in contents if p.is_dir()), None)  # the one rename that fails in a writable folder
        if blocked is not None:
            raise IsADirectoryError(errno.EISDIR, "is a folder", str(blocked))
    except BaseException as error:
        for path in contents:
            path.with_name(path.name + ".tmp").unlink(missing_ok=True)
        if not isinstance(error, OSError):
            raise
        where = error.filename or "a file"
        raise UserError(f"cannot write '{where}' ({error.strerror or error}); no file was changed") from error
    for tmp, path in zip(temporary, contents):
        os.replace(tmp, path)


def _unreadable(path: Path, error: Exception) -> UserError:
    if isinstance(error, FileNotFoundError):
        return UserError(f"no checkpoint at '{path}': the file does not exist")
    if isinstance(error, ValueError):  # numpy's own text advises loading pickles, which no checkpoint holds
        return UserError(
            f"'{path}' cannot be read (not a file of arrays); it is truncated or not a roverswarm checkpoint"
        )
    return UserError(f"'{path}' cannot be read ({error}); it is truncated or not a roverswarm checkpoint")


_UNREADABLE = (OSError, ValueError, EOFError, zipfile.BadZipFile)
"""What numpy raises reading a missing file, a truncated one or one that is not an ``.npz``."""


class _Arrays(Mapping):
    """The arrays of an open checkpoint by name, each read from the file when asked for: a
    resume holds one of the saved arrays in host memory at a time, not the whole file."""

    def __init__(self, data, path: Path):
        self.data, self.path = data, path

    def __contains__(self, key) -> bool:  # by name: Mapping's would read the array
        return key in self.data.files

    def __getitem__(self, key: str) -> np.ndarray:  # a name not in the file: numpy's KeyError
        try:
            return self.data[key]
        except _UNREADABLE as error:
            raise _unreadable(self.path, error) from error

    def __iter__(self):
        return iter(self.data.files)

    def __len__(self) -> int:
        return len(self.data.files)


@contextmanager
def open_arrays(path: Path) -> Iterator[Mapping[str, np.ndarray]]:
    """The arrays of checkpoint ``path`` (:class:`_Arrays`) while the file is open;
    :class:`UserError` if it is missing, truncated or not a checkpoint."""
    try:
        data = np.load(path, allow_pickle=False)
    except _UNREADABLE as error:
        raise _unreadable(path, error) from error
    with data:
        yield _Arrays(data, path)


def read_arrays(path: Path, prefix: str = "") -> dict[str, np.ndarray]:
    """The arrays of checkpoint ``path`` whose names start with ``prefix``; :class:`UserError`
    if the file is truncated or not a checkpoint."""
    with open_arrays(path) as arrays:
        return {k: arrays[k] for k in arrays if k.startswith(prefix)}


def trained_episodes(path: Path) -> int:
    """Episodes per seed the checkpoint ``path`` has trained (0 for one that never counted them)."""
    return int(read_arrays(path, "episodes").get("episodes", 0))


def load_checkpoint(path: Path, template, buffer=None):
    """Read a runner written by :func:`save_checkpoint` into the structure of ``template``.

    A finished run's checkpoint keeps no replay: ``template``'s empty one is kept. A replay
    of another capacity (a run whose ``--episodes`` changed: docs/training.md#extending-a-run)
    is :func:`~roverswarm.buffers.base.placed` into ``template``'s and made whole by
    ``buffer`` (its :class:`~roverswarm.buffers.base.Buffer`).

    The arrays are read one at a time, each on the device before the next is read, and each
    of ``template``'s replay arrays is let go once its place is filled: given a template no one
    else holds (``load_checkpoint(path, init(...))``), a resume holds about one replay, not
    the empty one, the restored one and host copies of both."""
    with open_arrays(path) as flat:
        if template.buffer is None:
            return restore(template, flat)
        empty = leaves(serialization.to_state_dict(template.buffer), "buffer/")
        capacity = jax.tree.leaves(template.buffer.data)[0].shape[1]
        template = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), template)  # shapes alone
        if not any(k.startswith("buffer/") for k in flat):  # a finished run's checkpoint: no replay kept
            return restore(template, ChainMap(empty, flat))
        resized, replay = False, {}
        for key in [k for k in flat if k.startswith("buffer/")]:
            x = flat[key]
            if key.startswith("buffer/data/"):  # kept up to the filled part
                require(
                    x.shape[1] <= capacity,
                    f"--buffer-size: this run's replay already holds {x.shape[1]} transitions per seed and the "
                    f"config gives room for {capacity}; resume with --buffer-size >= {x.shape[1]}",
                )
            elif key in empty and x.shape != empty[key].shape:
                resized = True
            if key in empty:
                replay[key] = placed(x, empty.pop(key))
        runner = restore(template, ChainMap(replay, flat))
    return runner.replace(buffer=jax.vmap(buffer.resized)(runner.buffer)) if resized else runner
