"""The package's rich consoles: what the CLI prints, the live tables of ``reproduce`` and
``sweep``, evaluation's progress bar and the timing lines.

:func:`console` prints text as it is, not as rich markup (a folder named ``run[v1]`` or
``a[/b]`` is printed whole; as markup the first lost its ``[v1]``, the second raised an error
after the work was done), and leaves a closed pipe to the CLI: rich would exit with 1, the
code of a stopped run, where the CLI ends quietly with the shell's code for SIGPIPE
(:data:`roverswarm.cli.SIGPIPE_EXIT`).
"""

from __future__ import annotations

from rich.console import Console


class _Console(Console):
    def on_broken_pipe(self) -> None:
        """The output's reader went away (``roverswarm sweep FILE | head``): raised for the CLI
        to end the command."""
        raise BrokenPipeError


def console(**options) -> Console:
    """A rich console (``options`` as rich's) that prints text as it is and raises
    :class:`BrokenPipeError` when what reads its output closes it."""
    return _Console(markup=False, **options)
