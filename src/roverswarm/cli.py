"""The ``roverswarm`` command line: thin. Each command parses a typed config and calls one function.

A :class:`roverswarm.errors.UserError` ends the command with one line on stderr and exit code 2.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Literal, Union

import tyro
from rich.console import Console
from rich.table import Table

from roverswarm.errors import RunStopped, UserError, require
from roverswarm.experiments import ReproduceConfig, reproduce
from roverswarm.train import CONFIG, PRESETS, TrainConfig, config_from_json, train


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


@dataclass(frozen=True)
class TrainCommand:
    """Train MADDPG or DDPG on a scenario (seeds vmapped); writes metrics, checkpoints, curves."""

    preset: Literal["default", "reference"] = "default"
    """Starting values of every option: `default` (tuned to learn), or `reference` (the
    reference MADDPG code's, as in the paper). Options given beside it change them."""
    config: TrainConfig = field(default_factory=TrainConfig)
    out: Path | None = None
    """Output folder (config.json, metrics.csv, tb/, checkpoint.npz, learning_curve.png)."""
    resume: Path | None = None
    """Continue the interrupted run in this folder; options given with it must match its config."""


@dataclass(frozen=True)
class EvaluateCommand:
    """Deterministic episodes of a trained run beside the random and oracle policies."""

    run: tyro.conf.Positional[Path]
    """Run folder written by `roverswarm train --out`."""
    episodes: int = 1000
    """Evaluation episodes per policy (the same layouts for every policy)."""
    seed: int = 0
    """Seed of the evaluation episodes."""
    sub_policies: Literal["random", "each"] = "random"
    """Runs with --ensemble K: `random` draws every agent's sub-policy per episode, as in
    training; `each` runs sub-policy k of all agents, for every k."""
    partners: Literal["own", "other-seeds"] = "own"
    """`own`: each seed's agents together; `other-seeds`: agent i of seed s beside the other
    agents of seeds s + 1, s + 2, ... (mod seeds), partners it never trained with."""


@dataclass(frozen=True)
class MissionRunCommand:
    """Run a swarm on a mission file: trajectories, an animation, a map of routes, metrics."""

    mission: tyro.conf.Positional[Path]
    """Mission file (YAML or JSON; see examples/mission.yaml)."""
    policy: str = "oracle"
    """`oracle`, `random`, or a run folder of `roverswarm train` (same numbers of rovers, POIs, traps)."""
    out: Path = Path("mission-out")
    """Output folder: trajectories.csv, metrics.csv, metrics.md, routes.png, mission.gif and its last frame mission.png."""
    fail: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """ROVER@STEP: freeze that rover from that step on."""
    episodes: int = 1
    """Episodes to run (they differ when the mission has a release zone or the policy is random); files show episode 0."""
    seed: int = 0
    """Seed of the episodes (release-zone starts, random policy)."""
    policy_seed: int = 0
    """Which seed of a trained run drives the rovers."""
    animation: Literal["gif", "mp4"] = "gif"
    """Animation format."""


@dataclass(frozen=True)
class MissionStressCommand:
    """Many episodes with one random rover failing at a random step: how success and time to
    observe all degrade, for the policy beside the oracle."""

    mission: tyro.conf.Positional[Path]
    """Mission file (YAML or JSON)."""
    policy: str = "oracle"
    """`oracle`, `random`, or a run folder of `roverswarm train`."""
    out: Path = Path("mission-stress")
    """Output folder: stress.csv, stress.md, stress.png."""
    episodes: int = 500
    """Episodes per policy and condition."""
    seed: int = 0
    """Seed of the episodes and of the failures."""
    policy_seed: int = 0
    """Which seed of a trained run drives the rovers."""


@dataclass(frozen=True)
class MissionCommand:
    """Missions: scientists' POIs and traps in; routes, animations and mission metrics out."""

    action: Union[
        Annotated[MissionRunCommand, tyro.conf.subcommand(name="run")],
        Annotated[MissionStressCommand, tyro.conf.subcommand(name="stress")],
    ]


def run_mission(cmd: MissionCommand) -> None:
    from roverswarm import mission

    action, console = cmd.action, Console()
    if isinstance(action, MissionRunCommand):
        result = mission.run_mission(action.mission, action.policy, action.out, action.fail, action.episodes, action.seed, action.policy_seed, action.animation)
        console.print(result.files["metrics.md"].read_text(), markup=False)
        console.print(f"wrote {', '.join(str(p) for p in result.files.values())}")
    else:
        rows = mission.stress_mission(action.mission, action.policy, action.out, action.episodes, action.seed, action.policy_seed)
        console.print(mission.markdown_table(list(rows[0]), [list(r.values()) for r in rows]), markup=False)
        console.print(f"wrote {action.out / 'stress.md'}, stress.csv and stress.png")


def _flat_fields(config) -> dict[str, object]:
    """Every leaf field of a (nested) config dataclass, by name."""
    flat: dict[str, object] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        flat.update(_flat_fields(value) if dataclasses.is_dataclass(value) else {f.name: value})
    return flat


def run_train(cmd: TrainCommand) -> None:
    if cmd.resume is None:
        config = cmd.config
        require(
            config.mission is None or config.scenario == PRESETS[cmd.preset].scenario,
            f"--scenario {config.scenario} and --mission: the mission file sets the layout and the number of rovers; give one of them",
        )
        if config.mission is not None:  # stored absolute, so resume and evaluate work from any folder
            config = dataclasses.replace(config, mission=str(Path(config.mission).resolve()))
        require(cmd.out is not None or config.episodes <= 10_000, "give --out for runs of more than 10000 episodes, so that they can be resumed")
        result = train(config, out=cmd.out)
    else:
        require((cmd.resume / CONFIG).exists(), f"--resume: '{cmd.resume}' holds no config.json")
        require(cmd.out in (None, cmd.resume), "--out and --resume name different folders")
        config = config_from_json((cmd.resume / CONFIG).read_text())
        given, defaults, saved = (_flat_fields(c) for c in (cmd.config, PRESETS[cmd.preset], config))
        for name, value in given.items():  # options given with --resume must match the run
            if value != defaults[name]:
                require(value == saved[name], f"--resume: the run in '{cmd.resume}' has {name}={saved[name]!r}, not {value!r}")
        result = train(config, out=cmd.resume, resume=True)
    last = [r for r in result.metrics if r["episodes"] == result.metrics[-1]["episodes"]]
    mean = sum(r["episode_reward"] for r in last) / len(last)
    Console().print(f"done: mean episode reward {mean:.2f} over the last {config.log_every} episodes" + (f"; results in {result.out}" if result.out else ""))


@dataclass(frozen=True)
class ReproduceCommand:
    """Run the paper's grid (N = 2..5 x DDPG, MADDPG, MADDPG + optimizer) and write its
    Table I, Figures 8-9 and a report. Finished runs are kept; rerunning finishes the rest."""

    config: ReproduceConfig = field(default_factory=ReproduceConfig)


def run_reproduce(cmd: ReproduceCommand) -> None:
    report = reproduce(cmd.config)
    Console().print(f"\ndone: {report} (with table1.md, table1.csv, fig8.png, fig9.png)")


def run_evaluate(cmd: EvaluateCommand) -> None:
    from roverswarm.evaluate import evaluate_run

    rows = evaluate_run(cmd.run, cmd.episodes, cmd.seed, cmd.sub_policies, cmd.partners)
    table = Table(title=f"{cmd.run}: {cmd.episodes} deterministic episodes, seed {cmd.seed}")
    for column in rows[0]:
        table.add_column(column.replace("_", " "), justify="left" if column == "policy" else "right", no_wrap=column == "policy")
    for row in rows:
        table.add_row(*(v if isinstance(v, str) else f"{v:.3f}" for v in row.values()))
    Console().print(table)


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
    "train": (TrainCommand, run_train),
    "evaluate": (EvaluateCommand, run_evaluate),
    "reproduce": (ReproduceCommand, run_reproduce),
    "mission": (MissionCommand, run_mission),
}


def _preset_defaults(argv: list[str]) -> dict[str, object]:
    """Default instances of the commands: ``train --preset NAME`` starts from that preset."""
    preset = "default"
    if argv[:1] == ["train"]:
        for i, arg in enumerate(argv):
            if arg == "--preset" and i + 1 < len(argv):
                preset = argv[i + 1]
            elif arg.startswith("--preset="):
                preset = arg.split("=", 1)[1]
    if preset not in PRESETS:
        return {}  # tyro reports the bad choice
    return {"train": TrainCommand(preset=preset, config=PRESETS[preset])}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``roverswarm`` command. Returns the exit code (0, or 2 for user errors)."""
    argv = sys.argv[1:] if argv is None else argv
    defaults = _preset_defaults(argv)
    commands = tuple(
        Annotated[cls, tyro.conf.subcommand(name=name, **({"default": defaults[name]} if name in defaults else {}))]
        for name, (cls, _) in COMMANDS.items()
    )
    cmd = tyro.cli(
        Union[commands],  # type: ignore[valid-type]
        prog="roverswarm",
        config=(tyro.conf.OmitArgPrefixes, tyro.conf.OmitSubcommandPrefixes),
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
    except RunStopped as stopped:
        print(f"roverswarm: stopped: {stopped}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
