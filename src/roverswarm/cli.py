"""The ``roverswarm`` command line: thin. Each command parses a typed config (defined beside the
function it runs) and calls that function; the checks live in the functions, so a notebook
meets the same ones.

A :class:`roverswarm.errors.UserError` ends the command with one line on stderr and exit code 2.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Literal, Union

import tyro
from rich.cells import cell_len
from rich.measure import Measurement
from rich.segment import Segment
from rich.table import Table

from roverswarm.animation import RenderConfig
from roverswarm.config import TrainConfig, fields_by_name, resumed_config
from roverswarm.console import console as _console
from roverswarm.errors import RunStopped, UserError, require
from roverswarm.evaluate import EvaluateConfig
from roverswarm.experiments import ReproduceConfig, reproduce
from roverswarm.experiments.sweep import SweepConfig
from roverswarm.export import CHECK_OBSERVATIONS, ExportConfig, export_run
from roverswarm.finetune import PROGRESS, FinetuneConfig, finetune
from roverswarm.limits import read_config
from roverswarm.mission import MissionConfig, MissionRunConfig
from roverswarm.presets import PRESETS
from roverswarm.runs import CONFIG
from roverswarm.trainer import train, training_notes
from roverswarm.tyro_errors import refusal


@dataclass(frozen=True)
class ScenariosCommand:
    """List the scenario presets with their observation and action sizes."""


@dataclass(frozen=True)
class TrainCommand:
    """Train MADDPG, DDPG, MAPPO or IPPO on a scenario (seeds vmapped); writes metrics, checkpoints, curves."""

    preset: Literal["default", "reference", "swarm", "mappo", "ippo", "anysize", "anysize-ddpg"] = "default"
    """Starting values of every option: `default` (MADDPG tuned to learn), `reference` (the
    reference MADDPG code's), `swarm` (shared networks with rover ids, MATD3, nearest-first view; provisional,
    see docs/results/swarm), `mappo` or `ippo` (PPO), `anysize` (MAPPO over each rover's
    nearest rovers, POIs and traps on paper-2..10: one policy for every swarm size),
    `anysize-ddpg` (the same from the swarm preset's DDPG). Options given beside it change them."""
    config: TrainConfig = field(default_factory=TrainConfig)
    out: Path | None = None
    """Output folder (config.json, metrics.csv, tb/, checkpoint.npz, learning_curve.png)."""
    resume: Path | None = None
    """Continue the interrupted run in this folder with its own config; with --episodes M,
    extend it (finished or not) to M episodes per seed (docs/training.md#extending-a-run), with
    a larger --budget-minutes, continue a run its budget ended."""


@dataclass(frozen=True)
class ReproduceCommand:
    """Run the paper's grid (N = 2..5 x DDPG, MADDPG, MADDPG + optimizer) and write its
    Table I, Figures 8-9 and a report. Finished runs are kept; rerunning finishes the rest."""

    config: ReproduceConfig = field(default_factory=ReproduceConfig)


def run_train(cmd: TrainCommand) -> None:
    if cmd.resume is None:
        _train_notes(cmd.config, cmd.out)
        result = train(cmd.config, out=cmd.out)
    else:
        require((cmd.resume / CONFIG).exists(), f"--resume: '{cmd.resume}' holds no config.json")
        require(
            cmd.out is None or cmd.out.resolve() == cmd.resume.resolve(),  # one folder however spelt
            f"--out '{cmd.out}' and --resume '{cmd.resume}' name different folders; a run is resumed in its own "
            "folder: give --resume alone",
        )
        saved = read_config(cmd.resume / CONFIG)
        algo = PRESETS[cmd.preset].learner.algo
        require(
            cmd.preset == "default" or saved.learner.algo == algo,
            f"--resume: the run in '{cmd.resume}' is --algo {saved.learner.algo} and --preset {cmd.preset} trains "
            f"--algo {algo}; resume it without --preset",
        )
        config = resumed_config(cmd.config, saved)
        _train_notes(config, cmd.resume)
        result = train(config, out=cmd.resume, resume=True)
    last = [r for r in result.metrics if r["episodes"] == result.metrics[-1]["episodes"]]
    mean = sum(r["episode_reward"] for r in last) / len(last)
    _console().print(
        f"done: mean episode reward {mean:.2f} over the last {result.config.log_every} episodes"
        + (f"; results in {result.out}" if result.out else "")
    )


def _train_notes(config: TrainConfig, out: Path | None) -> None:
    for note in training_notes(config, out):
        _console().print(f"note: {note}")


def run_reproduce(cmd: ReproduceCommand) -> None:
    report = reproduce(cmd.config)
    _console().print(f"\ndone: {report} (with table1.md, table1.csv, final_policies.csv, fig8.png, fig9.png)")


def run_sweep(cmd: SweepConfig) -> None:
    from roverswarm.experiments.sweep import sweep

    table = sweep(cmd)
    _console().print(table.read_text(), soft_wrap=True)
    written = [table, table.with_suffix(".csv"), table.with_suffix(".png")]
    _console().print(f"wrote {', '.join(str(path) for path in written if path.exists())}")


def print_table(title: str, rows: list[dict[str, object]], left: tuple[str, ...]) -> None:
    """``rows`` as a rich table; columns named in ``left`` left-aligned, numbers to 3 decimals.
    Nothing is cut short: each column is at least as wide as its longest word (a policy's whole
    name), and where the terminal (or the 80 columns of output piped to a file) is too
    narrow for that, the table is printed at its full width."""
    cells = {c: [f"{v:.3f}" if isinstance(v, float) else str(v) for v in (r[c] for r in rows)] for c in rows[0]}
    table = Table(title=title)
    for column, values in cells.items():
        header, no_wrap = column.replace("_", " "), column == "policy"
        words = [*(values if no_wrap else (w for v in values for w in v.split())), *header.split()]
        width = max(map(cell_len, words), default=0)  # terminal cells: a wide character takes two
        table.add_column(header, justify="left" if column in left else "right", no_wrap=no_wrap, min_width=width)
    for i in range(len(rows)):
        table.add_row(*(values[i] for values in cells.values()))
    console = _console()
    # rich narrows a table that does not fit below its columns' minimums, and then crops it:
    # rendered wider than the console, it is printed at its full width instead
    lines = Segment.split_lines(console.render(table, console.options))
    if max(map(Segment.get_line_length, lines)) > console.width:
        console = _console(width=Measurement.get(console, console.options.update_width(10_000), table).maximum)
    console.print(table)


def run_evaluate(cmd: EvaluateConfig) -> None:
    from roverswarm.evaluate import evaluate_run

    rows = evaluate_run(
        cmd.run, cmd.episodes, cmd.seed, cmd.sub_policies, cmd.partners, cmd.scenario, cmd.shield, progress=True
    )
    keys = ("scenario", "policy") if "scenario" in rows[0] else ("policy",)
    print_table(f"{cmd.run}: {cmd.episodes} deterministic episodes, seed {cmd.seed}", rows, keys)


def run_scenarios(cmd: ScenariosCommand) -> None:
    from roverswarm.env.scenarios import SIZE_RULE, scenario_table

    print_table("roverswarm scenarios", scenario_table(), ("name", "description"))
    _console().print(SIZE_RULE)


def run_render(cmd: RenderConfig) -> None:
    from roverswarm.animation import render_episode
    from roverswarm.env.render import check_animation_path
    from roverswarm.env.scenarios import get_scenario
    from roverswarm.policies import REFERENCE_POLICIES
    from roverswarm.runs import Run, load_policy

    check_animation_path(cmd.out)
    if cmd.scenario is None and cmd.policy not in REFERENCE_POLICIES and Path(cmd.policy).is_dir():
        run = Run(cmd.policy)  # its own environment: scenario or mission, as trained
        params, where = run.params, run.config.env_name()
    else:
        where = cmd.scenario or "paper-3"
        params = get_scenario(where)
    policy = load_policy(
        cmd.policy,
        params,
        f"scenario '{where}'",
        cmd.policy_seed,
        shield=cmd.shield,
        sets=f"one episode of {params.max_steps} steps",
    )
    png = render_episode(params, policy, cmd.out, cmd.seed, label=f"{where} {policy.name}")
    _console().print(f"wrote {cmd.out} and {png}")


def run_mission(cmd: MissionConfig) -> None:
    from roverswarm import mission

    action, console = cmd.action, _console()
    if isinstance(action, MissionRunConfig):
        result = mission.run_mission(
            action.mission,
            action.policy,
            action.out,
            action.fail,
            action.episodes,
            action.seed,
            action.policy_seed,
            action.animation,
            action.shield,
        )
        console.print(result.files["metrics.md"].read_text(), soft_wrap=True)
        console.print(f"wrote {', '.join(str(p) for p in result.files.values())}")
    else:
        from roverswarm.stress import stress_mission

        rows = stress_mission(
            action.mission,
            action.policy,
            action.out,
            action.episodes,
            action.seed,
            action.policy_seed,
            action.shield,
            action.failures,
        )
        console.print(mission.markdown_table(list(rows[0]), [list(r.values()) for r in rows]), soft_wrap=True)
        console.print(f"wrote {action.out / 'stress.md'}, stress.csv and stress.png")


def run_export(cmd: ExportConfig) -> None:
    result = export_run(cmd.run, cmd.out, cmd.seed, cmd.shield)
    checked = (
        "not checked against JAX (onnxruntime is not installed)"
        if result.difference is None
        else f"ONNX and JAX actions differ by at most {result.difference:.1e} on {CHECK_OBSERVATIONS} random layouts"
    )
    layer = " with the safety layer" if result.meta["shield"] else ""
    behind = " (both behind the safety layer)" if result.meta["shield"] and result.difference is not None else ""
    _console().print(f"wrote {cmd.out}{layer} ({', '.join(result.files)}); {checked}{behind}")


def run_finetune(cmd: FinetuneConfig) -> None:
    out = finetune(cmd)
    _console().print(f"done: {out} is a run of its own (evaluate, mission, export read it); progress in {PROGRESS}")


COMMANDS: dict[str, tuple[type, Callable]] = {
    "scenarios": (ScenariosCommand, run_scenarios),
    "render": (RenderConfig, run_render),
    "train": (TrainCommand, run_train),
    "evaluate": (EvaluateConfig, run_evaluate),
    "sweep": (SweepConfig, run_sweep),
    "reproduce": (ReproduceCommand, run_reproduce),
    "mission": (MissionConfig, run_mission),
    "export": (ExportConfig, run_export),
    "finetune": (FinetuneConfig, run_finetune),
}


def _option(argv: list[str], name: str) -> str | None:
    """The value of option ``name`` in ``argv`` (``--name VALUE`` or ``--name=VALUE``; the last one)."""
    value = None
    for i, arg in enumerate(argv):
        if arg == name and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith(name + "="):
            value = arg.split("=", 1)[1]
    return value


def _train_defaults(argv: list[str]) -> dict[str, object]:
    """Default instances of the commands: ``train --preset NAME`` starts from that preset;
    ``train --resume RUN`` from the run's own config, so that an option given beside it is
    one that changes the run (only ``--episodes`` and ``--budget-minutes`` may:
    :func:`~roverswarm.config.resumed_config`)."""
    if argv[:1] != ["train"]:
        return {}
    preset = _option(argv, "--preset") or "default"
    if preset not in PRESETS:
        return {}  # tyro reports the bad choice
    config = PRESETS[preset]
    resume = _option(argv, "--resume")
    if resume is not None:
        with contextlib.suppress(UserError, OSError):  # run_train reports it
            config = read_config(Path(resume) / CONFIG)
    return {"train": TrainCommand(preset=preset, config=config)}


def _check_not_empty(argv: list[str]) -> None:
    """Refuses an empty argument (``--out ""``, ``--out=``; most often an unset shell variable),
    which tyro would take as the current folder or an empty name."""
    for before, arg in zip(["roverswarm", *argv], argv):
        if arg.startswith("--") and arg.endswith("="):
            what = f"{arg[:-1]} was given an empty value"
        elif not arg.strip():
            what = (
                f"{before} was given an empty value" if before.startswith("--") else f"an empty argument after {before}"
            )
        else:
            continue
        raise UserError(f"{what}, most likely an unset shell variable: give the value itself")


def _check_lists_given(cmd, argv: list[str]) -> None:
    """Refuses a list option given with no value (``--variants`` followed by nothing, as an
    unset shell variable leaves it), which tyro takes as the empty default: a silent change of
    what runs (``reproduce --variants`` trained the default arms)."""
    for name, value in fields_by_name(cmd).items():  # the flags: one per leaf field, prefixes omitted
        flag = "--" + name.replace("_", "-")
        if value == () and flag in argv:
            raise UserError(f"{flag} was given no value, most likely an unset shell variable: give at least one")


def _parse(commands: tuple, argv: list[str]):
    """tyro's parse of ``argv``. What tyro refuses (a value it cannot convert, a choice or an
    option it does not know, a missing argument) is a :class:`UserError`: one line and exit
    code 2, as every other bad value; so is an empty value. Its help is its own."""
    _check_not_empty(argv)
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            cmd = tyro.cli(
                Union[commands],  # type: ignore[valid-type]
                prog="roverswarm",
                config=(tyro.conf.OmitArgPrefixes, tyro.conf.OmitSubcommandPrefixes),
                description="Multi-agent reinforcement learning of rover swarms exploring a planetary surface.",
                args=argv,
            )
    except SystemExit as exit:
        line = refusal(captured.getvalue(), argv, tuple(COMMANDS)) if exit.code else None
        if line is None:
            sys.stderr.write(captured.getvalue())
            raise
        raise UserError(line) from None
    sys.stderr.write(captured.getvalue())
    _check_lists_given(cmd, argv)
    return cmd


SIGPIPE_EXIT = 141
"""The exit code of a command whose output's reader went away (``roverswarm reproduce --help | head``):
a shell's code for a process that SIGPIPE ended (128 + 13), as ``yes | head`` gives."""


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``roverswarm`` command. Returns the exit code (0, 2 for user errors,
    :data:`SIGPIPE_EXIT` when what reads the output closes it early)."""
    try:
        return _main(sys.argv[1:] if argv is None else argv)
    except BrokenPipeError:
        # the rest of the output, and Python's flush at exit, go nowhere instead of a traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return SIGPIPE_EXIT


def _main(argv: list[str]) -> int:
    defaults = _train_defaults(argv)
    commands = tuple(
        Annotated[cls, tyro.conf.subcommand(name=name, **({"default": defaults[name]} if name in defaults else {}))]
        for name, (cls, _) in COMMANDS.items()
    )
    try:
        cmd = _parse(commands, argv)
    except UserError as error:  # a value of the wrong type
        print(f"roverswarm: error: {error}", file=sys.stderr)
        return 2
    from roverswarm.jaxcache import enable_compilation_cache

    enable_compilation_cache()
    run = next(run for cls, run in COMMANDS.values() if isinstance(cmd, cls))
    try:
        run(cmd)
    except UserError as error:
        print(f"roverswarm: error: {error}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the output's reader went away: see main
        raise
    except OSError as error:  # a full disk, a read-only or vanished folder: what the machine refused, in one line
        where = f" '{error.filename}'" if error.filename else ""
        print(f"roverswarm: error: cannot read or write{where}: {error.strerror or error}", file=sys.stderr)
        return 2
    except RunStopped as stopped:
        print(f"roverswarm: stopped: {stopped}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # a Ctrl-C outside training's chunks (loading, evaluating): files are written whole
        print("roverswarm: interrupted; what was saved before is kept", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
