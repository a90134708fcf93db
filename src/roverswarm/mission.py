"""Running a swarm on a mission: routes, an animation and mission metrics.

``roverswarm mission run`` as a function, and the mission commands' configs (``mission
stress``, the failure stress test, is :mod:`roverswarm.stress`). A policy is
``oracle``, ``random``, or a run folder of ``roverswarm train``; a trained policy runs on any
mission with the numbers of rovers, POIs and traps it was trained for (the positions may
differ: observations are relative).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Iterable, Literal, Union

import jax
import numpy as np
import tyro

from roverswarm import runs
from roverswarm.animation import episode_frames
from roverswarm.env.mars import NEVER, EnvParams
from roverswarm.env.missions import Mission, load_mission
from roverswarm.env.render import FrameRenderer, save_animation
from roverswarm.errors import require
from roverswarm.limits import check_seed
from roverswarm.policies import Policy
from roverswarm.rollout import MissionStats, Rollout, rollout
from roverswarm.runs import check_not_run, folder_lock, write_csv
from roverswarm.storage import save_figure, write_text


@dataclass(frozen=True)
class MissionRunConfig:
    """Run a swarm on a mission file: trajectories, an animation, a map of routes, metrics."""

    mission: tyro.conf.Positional[Path]
    """Mission file (YAML or JSON; see examples/mission.yaml)."""
    policy: str = "oracle"
    """`oracle`, `random`, or a run folder of `roverswarm train` (same numbers of rovers, POIs, traps)."""
    out: Path = Path("mission-out")
    """Output folder: trajectories.csv, metrics.csv, metrics.md, routes.png, mission.gif and
    its last frame mission.png."""
    fail: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """ROVER@STEP: freeze that rover from that step on."""
    episodes: int = 1
    """Episodes to run (they differ when the mission has a release zone or the policy is
    random): trajectories.csv and metrics.csv hold every one; metrics.md details episode 0
    and sums up all of them; routes.png and the animation show episode 0."""
    seed: int = 0
    """Seed of the episodes (release-zone starts, random policy)."""
    policy_seed: int = 0
    """Which seed of a trained run drives the rovers."""
    animation: Literal["gif", "mp4"] = "gif"
    """Animation format."""
    shield: bool = False
    """Drive the policy behind the safety layer: each rover's action turned along the tangent of
    any trap or other rover it would reach within a few steps (as the oracle steers)."""


@dataclass(frozen=True)
class MissionStressConfig:
    """Many episodes with one random rover (or --failures of them) failing at a random step:
    how success and time to observe all degrade, for the policy beside the oracle."""

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
    shield: bool = False
    """Drive the policy behind the safety layer: each rover's action turned along the tangent
    of any trap or other rover it would reach within a few steps (with --policy oracle, the
    oracle too; the oracle row beside it runs as it is)."""
    failures: int = 1
    """Rovers that fail in each failure episode: distinct, drawn uniformly, each at its own
    random step before the swarm would have finished without failures; at most the mission's
    rovers less one."""


@dataclass(frozen=True)
class MissionConfig:
    """Missions: scientists' POIs and traps in; routes, animations and mission metrics out."""

    action: Union[
        Annotated[MissionRunConfig, tyro.conf.subcommand(name="run")],
        Annotated[MissionStressConfig, tyro.conf.subcommand(name="stress")],
    ]


_FAILURE = re.compile(r"^(\d{1,9})@(\d{1,9})$")  # at most 9 digits: int() refuses 4300


def load_policy(spec: str, mission: Mission, seed: int = 0, shield: bool = False, episodes: int = 1) -> Policy:
    """``oracle``, ``random``, or seed ``seed`` of the trained run in folder ``spec``, checked
    against the mission's numbers of rovers, POIs and traps, and against memory for ``episodes``
    of the mission's episodes at once (``--episodes`` and the mission's ``episode_length``), before
    any rollout; with ``shield``, behind the safety layer."""
    length = f"the mission's episode_length {mission.params.max_steps}"
    return runs.load_policy(
        spec,
        mission.params,
        f"mission '{mission.name}'",
        seed,
        "Train on the mission with `roverswarm train --mission FILE`.",
        shield,
        episodes,
        f"--episodes {episodes}, {length}" if episodes > 1 else length,  # one episode is the fewest
    )


def parse_failures(failures: list[str], params: EnvParams) -> np.ndarray:
    """``["ROVER@STEP", ...]`` -> fail_step [N] (NEVER for rovers that keep working)."""
    fail_step = np.full(params.num_rovers, NEVER, np.int32)
    for text in failures:
        match = _FAILURE.match(text.strip())
        require(match is not None, f"--fail: expected ROVER@STEP such as 1@10, got '{text}'")
        rover, step = int(match[1]), int(match[2])
        require(rover < params.num_rovers, f"--fail {text}: rover must be in [0, {params.num_rovers}), got {rover}")
        require(step < params.max_steps, f"--fail {text}: step must be in [0, {params.max_steps}), got {step}")
        require(
            fail_step[rover] == NEVER,
            f"--fail {text}: rover {rover} already fails at step {fail_step[rover]}; give each rover one --fail",
        )
        fail_step[rover] = step
    return fail_step


# ----------------------------------------------------------------------------- mission run


@dataclass(frozen=True)
class MissionResult:
    """What ``mission run`` wrote and measured."""

    stats: MissionStats
    files: dict[str, Path]


def _metrics_rows(stats: MissionStats, mission: Mission) -> list[dict[str, object]]:
    rows = []
    for e in range(len(stats.success)):
        row: dict[str, object] = {
            "episode": e,
            "success": bool(stats.success[e]),
            "pois_observed": int(stats.pois_observed[e]),
            "time_to_all": stats.time_to_all[e],
            "collisions": stats.collisions[e],
            "trap_contacts": stats.trap_contacts[e],
        }
        row.update({f"path_length_rover_{i}": v for i, v in enumerate(stats.path_length[e])})
        row.update({f"observed_{name}": v for name, v in zip(mission.poi_names, stats.first_observed[e])})
        rows.append(row)
    return rows


def _fmt(value: object) -> str:
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (float, np.floating)):
        return "never" if np.isnan(value) else f"{value:g}" if float(value).is_integer() else f"{value:.2f}"
    return str(value).replace("|", "\\|")  # a POI named "a|b" stays in its column


TRAJECTORY_COLUMNS = ["episode", "step", "rover", "x", "y", "working", "pois_observed"]
"""Columns of ``trajectories.csv``."""


def write_rows(rows: Iterable[dict[str, object]], path: Path, columns: list[str] | None = None) -> None:
    """CSV with NaN (never observed, never completed) as an empty cell, written row by row as
    ``rows`` come (a generator is never held whole); ``columns`` default to the first row's keys
    (``rows`` is then a list)."""
    cells = ({k: ("" if isinstance(v, float) and np.isnan(v) else v) for k, v in row.items()} for row in rows)
    write_csv(path, cells, columns or list(rows[0]))


def markdown_table(header: list[str], rows: list[list[object]]) -> str:
    """:func:`roverswarm.runs.markdown_table` with the values formatted for mission reports."""
    return runs.markdown_table(header, [[_fmt(v) for v in row] for row in rows])


def episode_ends(stats: MissionStats, params: EnvParams) -> np.ndarray:
    """[E] the steps each episode ran: when the mission stops once complete, to the step its
    last POI was first observed (at least 1: the first step ends one complete at the start);
    else all ``max_steps``. The rollout's positions after the end repeat the last."""
    stopped = stats.success & params.terminate_on_complete
    return np.where(stopped, np.maximum(np.nan_to_num(stats.time_to_all), 1), params.max_steps).astype(int)


def _failure_text(rover: int, step: int, end: int) -> str:
    """``--fail ROVER@STEP`` as reported: a failure the episode ended before is named so."""
    return f"rover {rover} at step {step}" + (f" (not reached: the episode ended at step {end})" if step >= end else "")


def mission_report(stats: MissionStats, mission: Mission, policy: str, fail_step: np.ndarray) -> str:
    """Markdown: the summary, each POI's first observation and each rover's path (episode 0)."""
    dt = float(mission.params.dt)
    end = int(episode_ends(stats, mission.params)[0])
    failed = [_failure_text(i, s, end) for i, s in enumerate(fail_step) if s != NEVER]
    lines = [
        f"# Mission '{mission.name}': {policy}\n",
        f"{mission.counts()}; {mission.params.max_steps} steps of {dt:g} time units"
        + (f"; failures: {', '.join(failed)}" if failed else "")
        + ".\n",
        markdown_table(
            [
                "success",
                "POIs observed",
                "time to observe all (steps)",
                "collisions",
                "trap contacts",
                "total path length",
            ],
            [
                [
                    stats.success[0],
                    f"{stats.pois_observed[0]}/{mission.params.num_pois}",
                    stats.time_to_all[0],
                    stats.collisions[0],
                    stats.trap_contacts[0],
                    stats.path_length[0].sum(),
                ]
            ],
        ),
        markdown_table(
            ["POI", "first observed (step)"], [[n, t] for n, t in zip(mission.poi_names, stats.first_observed[0])]
        ),
        markdown_table(
            ["rover", "path length", "failed at step"],
            [
                [i, length, "-" if s == NEVER else int(s) if s < end else f"{s} (not reached)"]
                for i, (length, s) in enumerate(zip(stats.path_length[0], fail_step))
            ],
        ),
    ]
    if len(stats.success) > 1:
        mean = stats.summary()
        timing = (
            f"time to observe all {mean['time_to_all']:.1f} steps (successful episodes)"
            if stats.success.any()
            else "none succeeded"
        )
        lines.append(
            f"Over {len(stats.success)} episodes: success {mean['success']:.0%}, {timing}, "
            f"collisions {mean['collisions']:.2f}, trap contacts {mean['trap_contacts']:.2f}.\n"
        )
    return "\n".join(lines)


def _routes_png(
    data: Rollout, mission: Mission, stats: MissionStats, fail_step: np.ndarray, path: Path, title: str
) -> None:
    """The whole route of episode 0 with the POIs named and their observation steps."""
    renderer = FrameRenderer(mission.params, pixels=640)
    renderer.frame(data.rover_pos[0], data.poi_pos[0], data.trap_pos[0], data.observed[0, -1], title)
    ax = renderer.ax
    for (x, y), name, t in zip(data.poi_pos[0], mission.poi_names, stats.first_observed[0]):
        ax.annotate(
            f"{name} ({'never' if np.isnan(t) else f't={t:.0f}'})",
            (x, y),
            xytext=(6, 6),
            textcoords="offset points",
            fontsize=8,
        )
    end = int(episode_ends(stats, mission.params)[0])
    for i, s in enumerate(fail_step):
        if s < end:  # a failure the episode ended before is not drawn
            x, y = data.rover_pos[0, -1, i]
            ax.plot([x], [y], marker="x", color="black", markersize=14, mew=3)
            ax.annotate(f"rover {i} failed (t={s})", (x, y), xytext=(6, -12), textcoords="offset points", fontsize=8)
    for i in range(mission.params.num_rovers):
        ax.plot(*data.rover_pos[0, 0, i], marker="s", color="black", markersize=4)
        ax.annotate(
            f"start {i}", tuple(data.rover_pos[0, 0, i]), xytext=(4, -10), textcoords="offset points", fontsize=7
        )
    save_figure(renderer.figure, path)


def run_mission(
    mission_path: str | Path,
    policy_spec: str,
    out: str | Path,
    failures: tuple[str, ...] = (),
    episodes: int = 1,
    seed: int = 0,
    policy_seed: int = 0,
    animation: str = "gif",
    shield: bool = False,
) -> MissionResult:
    """Run ``policy_spec`` on the mission; write trajectories.csv and metrics.csv (every
    episode), metrics.md, routes.png and mission.gif (or .mp4, with its last frame as
    mission.png) of episode 0 into ``out``."""
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    require(animation in ("gif", "mp4"), f"--animation must be gif or mp4, got '{animation}'")
    check_seed(seed)
    out = Path(out)
    with folder_lock(out):  # first: a bad --out is refused before the episodes run, and no one else writes there
        check_not_run(out)
        mission = load_mission(mission_path)
        policy = load_policy(policy_spec, mission, policy_seed, shield, episodes)
        fail_step = parse_failures(list(failures), mission.params)
        data = rollout(policy, jax.random.PRNGKey(seed), mission.params, episodes, fail_step=fail_step)
        stats = MissionStats.of(data)
        files = {
            name: out / name
            for name in (
                "trajectories.csv",
                "metrics.csv",
                "metrics.md",
                "routes.png",
                f"mission.{animation}",
                "mission.png",
            )
        }
        trajectory = (  # row by row as it is written: a list of every rover's every step outgrew the rollout
            {
                "episode": e,
                "step": t,
                "rover": i,
                "x": float(x),
                "y": float(y),
                "working": bool(t < fail_step[i]),
                "pois_observed": int(data.observed[e, t].sum()),
            }
            for e, end in enumerate(episode_ends(stats, mission.params))
            for t in range(end + 1)
            for i, (x, y) in enumerate(data.rover_pos[e, t])
        )
        write_rows(trajectory, files["trajectories.csv"], TRAJECTORY_COLUMNS)
        write_rows(_metrics_rows(stats, mission), files["metrics.csv"])
        write_text(files["metrics.md"], mission_report(stats, mission, policy.name, fail_step))
        title = f"{mission.name}: {policy.name}"
        _routes_png(data, mission, stats, fail_step, files["routes.png"], title)
        save_animation(episode_frames(data, mission.params, 0, title).frames, files[f"mission.{animation}"])
        return MissionResult(stats=stats, files=files)
