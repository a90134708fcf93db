"""User-facing errors.

A :class:`UserError` is a mistake in what the user asked for (a bad config value, an unknown
scenario, a malformed file). The CLI prints its message as one line and exits with code 2;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class UserError(ValueError):
    """A mistake in the user's input. The message names the field, the value, and what is allowed."""


def require(condition: bool, message: str) -> None:
    """Raise :class:`UserError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise UserError(message)


class RunStopped(RuntimeError):
    """A run stopped before its end (diverged, or interrupted); the message says what was kept."""
