"""User-facing errors.

A :class:`UserError` is a mistake in what the user asked for (a bad config value, an unknown
scenario, a malformed file). The CLI prints its message as one line and exits with code 2;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import errno
import math
from typing import Iterator


class UserError(ValueError):
    """A mistake in the user's input. The message names the field, the value, and what is allowed."""


def require(condition: bool, message: str) -> None:
    """Raise :class:`UserError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise UserError(message)


@contextlib.contextmanager
def within(where: str) -> Iterator[None]:
    """A :class:`UserError` raised inside is raised again with ``where: `` before its message
    (which file, setting or run the options it names came from)."""
    try:
        yield
    except UserError as error:
        raise UserError(f"{where}: {error}") from None


class RunStopped(RuntimeError):
    """A run stopped before its end (diverged, or interrupted); the message says what was kept."""


def require_positive(config, names: tuple[str, ...]) -> None:
    """Every field ``names`` of ``config`` is >= 1; else :class:`UserError` naming its option."""
    for name in names:
        value = getattr(config, name)
        require(value >= 1, f"--{name.replace('_', '-')} must be >= 1, got {value}")


def require_finite(value: float, low: float, what: str, strict: bool = False) -> None:
    """``value`` is finite and >= ``low`` (> with ``strict``); else :class:`UserError` naming option ``what``."""
    ok = math.isfinite(value) and (value > low if strict else value >= low)
    require(ok, f"--{what} must be a finite number {'>' if strict else '>='} {low}, got {value}")


def unwritable(error: OSError) -> str:
    """Why a file or folder could not be made in a folder that exists, in words: ENOENT there is
    a file system that makes none (``/proc``), not a missing path; else the system's reason."""
    return "the file system there makes no new files" if error.errno == errno.ENOENT else str(error.strerror or error)
