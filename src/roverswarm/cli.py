"""The ``roverswarm`` command line: thin. Each command parses a typed config and calls one function.

A :class:`roverswarm.errors.UserError` ends the command with one line on stderr and exit code 2.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Callable, Literal

import tyro
from rich.console import Console
from rich.table import Table

from roverswarm.errors import UserError


@dataclass(frozen=True)
class ScenariosCommand:
    """List the scenario presets with their observation and action sizes."""


@dataclass(frozen=True)
class RenderCommand:
    """Draw one episode of a reference policy to a GIF or MP4, plus a PNG of the last frame."""

    scenario: str = "paper-3"
    """Scenario preset (see `roverswarm scenarios`)."""
    policy: Literal["oracle", "random"] = "oracle"
    """Policy that drives the rovers."""
    out: Path = Path("episode.gif")
    """Output animation, .gif or .mp4; the last frame is also written beside it as .png."""
    seed: int = 0
    """Random seed of the episode layout and of the random policy."""


def run_scenarios(cmd: ScenariosCommand) -> None:
    from roverswarm.env.scenarios import scenario_table

    rows = scenario_table()
    table = Table(title="roverswarm scenarios")
    for column in rows[0]:
        table.add_column(column, justify="left" if column in ("name", "description") else "right")
    for row in rows:
        table.add_row(*(str(v) for v in row.values()))
    Console().print(table)


def run_render(cmd: RenderCommand) -> None:
    from roverswarm.env.render import check_animation_path, render_episode
    from roverswarm.env.scenarios import get_scenario
    from roverswarm.policies import REFERENCE_POLICIES

    params = get_scenario(cmd.scenario)
    check_animation_path(cmd.out)
    png = render_episode(params, REFERENCE_POLICIES[cmd.policy], cmd.out, cmd.seed, label=f"{cmd.scenario} {cmd.policy}")
    Console().print(f"wrote {cmd.out} and {png}")


COMMANDS: dict[str, tuple[type, Callable]] = {
    "scenarios": (ScenariosCommand, run_scenarios),
    "render": (RenderCommand, run_render),
}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``roverswarm`` command. Returns the exit code (0, or 2 for user errors)."""
    cmd = tyro.extras.subcommand_cli_from_dict(
        {name: Annotated[cls, tyro.conf.arg(name=name)] for name, (cls, _) in COMMANDS.items()},
        prog="roverswarm",
        description="Multi-agent reinforcement learning of rover swarms exploring a planetary surface.",
        args=argv,
    )
    from roverswarm.jaxcache import enable_compilation_cache

    enable_compilation_cache()
    run = next(run for cls, run in COMMANDS.values() if isinstance(cmd, cls))
    try:
        run(cmd)
    except UserError as error:
        print(f"roverswarm: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
