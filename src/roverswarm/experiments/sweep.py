"""Sweeps: train a list of learner settings on a list of scenarios, evaluate every seed, one table.

A sweep file (YAML) names a starting preset, the scenarios, seeds and episodes, and the
settings, each a set of options over the preset (the option names of `roverswarm train`,
with underscores)::

    preset: default
    scenarios: [paper-5]
    seeds: 2
    episodes: 20000
    settings:
      default: {}
      shared: {share_parameters: true}
      shared-td3: {share_parameters: true, twin_critics: true, target_noise: 0.2, actor_delay: 2}
      mappo: {preset: mappo}      # a setting may start from another preset

Every (scenario, setting) trains in ``OUT/runs/<scenario>/<setting>`` (seeds vmapped; a
finished run is kept, an interrupted one resumes; here, in processes side by side, or as Ray
tasks: :class:`~roverswarm.experiments.arms.Backend`), then every seed's policy is evaluated
deterministically on the same 1000 episodes as the random and oracle policies
(:func:`roverswarm.evaluate.evaluate_run`, kept in the run folder as ``evaluation.csv``).
``OUT/sweep.csv`` and ``OUT/sweep.md`` get one row per run: every seed's normalised score,
their minimum and mean, POIs observed, collisions and trap contacts beside the oracle's, the
random and oracle rewards the score is measured against, and minutes of training.
``OUT/sweep.png`` plots every seed's score per scenario and setting (with ``paper-2`` ...
``paper-8`` as the scenarios: the score against the number of rovers).

A scenario may be any ``paper-N``, or a range or list of sizes (``paper-2..10``) for the
presets that train one policy for every size (``anysize``, ``anysize-ddpg``): such a run is
evaluated at each size of its range and gives a row per size, its setting named with the
range (``anysize (paper-2..10)``).
"""

from __future__ import annotations

import csv
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro
from rich.live import Live

from roverswarm.config import validate_training, with_options
from roverswarm.console import console
from roverswarm.env.scenarios import scenario_sizes
from roverswarm.errors import UserError, require, within
from roverswarm.experiments.arms import (
    Backend,
    GridRun,
    check_backend,
    check_evaluations,
    episodes_done,
    run_rows,
    status,
)
from roverswarm.experiments.live import Summary
from roverswarm.experiments.pool import default_jobs, train_runs
from roverswarm.experiments.remote import run_ray
from roverswarm.limits import check_memory, open_limited, read_limited, safe_name, training_parts
from roverswarm.parsing import load_text
from roverswarm.presets import PRESETS
from roverswarm.runs import folder_lock, markdown_table, training_seconds, write_csv
from roverswarm.storage import save_figure, write_text

EVALUATION = "evaluation.csv"


@dataclass(frozen=True)
class SweepConfig(Backend):
    """A sweep file, where its runs and table go, and where its runs train (--backend, as
    `reproduce`'s: the table grows after each group of --jobs, or in the file's order as Ray
    tasks come back)."""

    file: tyro.conf.Positional[Path]
    """Sweep file (YAML): preset, scenarios, seeds, episodes and named settings (docs/training.md#sweeps)."""
    out: Path = Path("results/sweep")
    """Output folder: runs/, sweep.csv, sweep.md and sweep.png."""
    eval_episodes: int = 1000
    """Deterministic evaluation episodes per policy (the same layouts for every policy)."""


ROW_OPTIONS = ("scenario", "mission", "mission_text", "seeds")
"""Options a setting may not change: the sweep's rows and folders are named by them."""


def load_sweep(path: Path, out: Path) -> list[GridRun]:
    """The runs of sweep file ``path`` (checked: scenarios, options, types, presets, names,
    each run's memory), with folders under ``out``: ``out/runs/<scenario>/<setting>``, the
    setting's name checked to be one path component (:func:`~roverswarm.limits.safe_name`)."""
    require(Path(path).is_file(), f"sweep file '{path}' does not exist")
    spec = load_text(read_limited(path, "sweep file"), "YAML", f"sweep file '{path}'")
    require(
        isinstance(spec, dict),
        f"sweep file '{path}' must hold a mapping (preset, scenarios, seeds, episodes, settings)",
    )
    known = {"preset", "scenarios", "seeds", "episodes", "settings"}
    unknown = sorted(map(str, set(spec) - known))
    require(not unknown, f"sweep file '{path}': unknown keys {unknown}; known: {sorted(known)}")
    preset = spec.get("preset", "default")
    require(
        isinstance(preset, str) and preset in PRESETS,
        f"sweep file '{path}': preset must be one of {', '.join(PRESETS)}, got {preset!r}",
    )
    scenarios = spec.get("scenarios", ["paper-3"])
    require(isinstance(scenarios, list) and scenarios, f"sweep file '{path}': scenarios must be a non-empty list")
    for name in scenarios:
        require(isinstance(name, str), f"sweep file '{path}': scenarios must be names, got {name!r}")
        with within(f"sweep file '{path}'"):
            scenario_sizes(name)
    require(
        len(set(scenarios)) == len(scenarios),
        f"sweep file '{path}': scenarios must each be given once, got {', '.join(scenarios)}",
    )
    settings = spec.get("settings")
    require(isinstance(settings, dict) and settings, f"sweep file '{path}': settings must map names to options")
    folded: dict[str, str] = {}
    for name in settings:
        safe_name(name, f"sweep file '{path}': setting name")
        require(
            name.casefold() not in folded,
            f"sweep file '{path}': setting names '{folded.get(name.casefold())}' and '{name}' differ only in case "
            "(one folder on some file systems); rename one",
        )
        folded[name.casefold()] = name
    common = {k: spec[k] for k in ("seeds", "episodes") if k in spec}
    runs = []
    for scenario in scenarios:
        for name, options in settings.items():
            require(
                isinstance(options, dict | None),
                f"sweep file '{path}': setting '{name}' must map option names to values",
            )
            options = dict(options or {})
            for option in ROW_OPTIONS:
                require(
                    option not in options,
                    f"sweep file '{path}': setting '{name}' may not set '{option}' (it names the row); "
                    "give scenarios and seeds at the top of the file",
                )
            start = options.pop("preset", preset)
            require(
                isinstance(start, str) and start in PRESETS,
                f"sweep file '{path}': setting '{name}': preset must be one of {', '.join(PRESETS)}, got {start!r}",
            )
            base = with_options(PRESETS[start], common, f"sweep file '{path}'")
            config = with_options(
                dataclasses.replace(base, scenario=scenario), options, f"sweep file '{path}': setting '{name}'"
            )
            with within(f"sweep file '{path}': setting '{name}' on {scenario}"):  # where the flag's value came from
                params = validate_training(config)
            check_memory(training_parts(config, params), f"setting '{name}' on {scenario}")
            runs.append(GridRun(scenario, name, config, Path(out) / "runs" / scenario / name))
    return runs


def evaluation(run: GridRun, episodes: int) -> list[dict[str, object]]:
    """The deterministic evaluation rows of ``run`` (random, oracle, every seed), computed once
    and kept in the run folder: again for other evaluation episodes or once the run has been
    trained further (extended: ``train --resume RUN --episodes M`` or ``--budget-minutes``)."""
    from roverswarm.evaluate import evaluate_run

    path = run.folder / EVALUATION
    key = {"episodes": episodes, "trained_episodes": episodes_done(run)}
    if path.exists():
        rows = read_table(path)
        if all(rows[0].get(k) == v for k, v in key.items()):
            return rows
    rows = [{**row, **key} for row in evaluate_run(run.folder, episodes)]
    write_csv(path, rows)
    return rows


def table_row(run: GridRun, rows: list[dict[str, object]]) -> dict[str, object]:
    """One row of the sweep table: every seed's score and what the swarm did, beside the oracle."""
    by_name = {str(r["policy"]): r for r in rows}
    seeds = [r for name, r in by_name.items() if name not in ("random", "oracle")]
    scores = np.array([float(r["normalized_score"]) for r in seeds])
    mean = lambda key: float(np.mean([float(r[key]) for r in seeds]))  # noqa: E731
    minutes = training_seconds(run_rows(run)) / 60
    return {
        "scenario": run.scenario,
        "setting": run.algorithm,
        "episodes": episodes_done(run),  # fewer than configured where a --budget-minutes ended the run
        "seeds": run.config.seeds,
        "scores": " / ".join(f"{s:.2f}" for s in scores),
        "min_score": float(scores.min()),
        "mean_score": float(scores.mean()),
        "pois_observed": mean("pois_observed"),
        "collisions": mean("collisions"),
        "trap_contacts": mean("trap_contacts"),
        "oracle_trap_contacts": float(by_name["oracle"]["trap_contacts"]),
        "random_reward": float(by_name["random"]["episode_reward"]),
        "oracle_reward": float(by_name["oracle"]["episode_reward"]),
        "train_minutes": minutes,
    }


def table_rows(run: GridRun, rows: list[dict[str, object]]) -> list[dict[str, object]]:
    """The sweep table's rows of ``run`` (:func:`table_row`): one, or for a run trained across
    sizes (``paper-2..10``) one per size it is evaluated at, each with that size as its
    scenario and the range in its setting's name (``anysize (paper-2..10)``), so that its line
    in the figure is the score against N and stays apart from the specialists'."""
    if "scenario" not in rows[0]:
        return [table_row(run, rows)]
    sizes: dict[str, list[dict[str, object]]] = {}
    for row in rows:
        sizes.setdefault(str(row["scenario"]), []).append(row)
    setting = f"{run.algorithm} ({run.scenario})"
    return [{**table_row(run, mine), "scenario": name, "setting": setting} for name, mine in sizes.items()]


def gapped(x: list[int], y: list[float]) -> tuple[list[float], list[float]]:
    """Points ``(x, y)`` in order of ``x`` with a NaN between two that are not neighbours
    (``x`` differs by more than 1), so a line drawn through them stops at a scenario the
    setting did not run instead of bridging it."""
    xs: list[float] = []
    ys: list[float] = []
    for a, b in sorted(zip(x, y)):
        if xs and a > xs[-1] + 1:
            xs.append(np.nan)
            ys.append(np.nan)
        xs.append(a)
        ys.append(b)
    return xs, ys


def setting_colours(count: int) -> list[tuple[float, float, float]]:
    """One colour per setting of a figure: matplotlib's own ten (tab10) up to ten settings,
    else tab20's twenty (tab10 would repeat from the eleventh), then repeating."""
    from matplotlib import colormaps

    palette = colormaps["tab10" if count <= 10 else "tab20"].colors
    return [palette[i % len(palette)] for i in range(count)]


def by_size(scenarios: list[str]) -> list[str]:
    """``scenarios`` in order of their swarm size (a stable sort: names of one size keep their
    order), or as given if one of them is not a scenario name."""
    try:
        return sorted(scenarios, key=lambda name: scenario_sizes(name)[0])
    except UserError:
        return scenarios


def figure(rows: list[dict[str, object]], path: Path, episodes: int = 1000) -> None:
    """Left: every seed's score (dots) and their mean (line; dotted across scenarios a setting
    skipped) per scenario, by swarm size, one colour per setting, beside random (0) and the
    oracle (1), evaluated on ``episodes`` episodes per policy. Right: minutes of training per
    run (a run across sizes: at each size it was evaluated at)."""
    from matplotlib.figure import Figure

    scenarios = by_size(list(dict.fromkeys(str(r["scenario"]) for r in rows)))
    fig = Figure(figsize=(1.2 * len(scenarios) + 6, 4.5), dpi=100)
    ax, clock = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 2]})
    settings = list(dict.fromkeys(str(r["setting"]) for r in rows))
    colours = setting_colours(len(settings))
    for i, setting in enumerate(settings):
        mine = [r for r in rows if r["setting"] == setting]
        x = [scenarios.index(str(r["scenario"])) for r in mine]
        scores = [[float(v) for v in str(r["scores"]).split(" / ")] for r in mine]
        means = [float(np.mean(v)) for v in scores]
        (line,) = ax.plot(*gapped(x, means), marker="o", label=setting, color=colours[i])
        if len(gapped(x, means)[0]) > len(x):  # a scenario skipped: bridge it with a dotted line
            ax.plot(*zip(*sorted(zip(x, means))), linestyle=":", linewidth=1, color=line.get_color())
        for xi, v in zip(x, scores):
            ax.scatter([xi] * len(v), v, s=12, color=line.get_color(), alpha=0.5)
        clock.plot(*gapped(x, [float(r["train_minutes"]) for r in mine]), marker="o", color=line.get_color())
    for level, name in ((1.0, "oracle"), (0.0, "random")):
        ax.axhline(level, color="grey", linestyle="--", linewidth=1)
        ax.annotate(name, (len(scenarios) - 0.5, level), fontsize=8, color="grey", va="bottom", ha="right")
    for axes in (ax, clock):
        axes.set_xticks(range(len(scenarios)), scenarios, rotation=30 if len(scenarios) > 4 else 0)
        axes.set_xlim(-0.5, len(scenarios) - 0.5)
    ax.set_ylabel("normalised score (every seed; line: mean)")
    ax.set_title(f"deterministic evaluation, {episodes} episodes per policy", fontsize=10)
    ax.legend(fontsize=8)
    clock.set_ylabel("minutes of training per run (all seeds)")
    clock.set_title("training wall time per run", fontsize=10)
    clock.set_ylim(bottom=0)
    fig.tight_layout()
    save_figure(fig, path)


def read_table(path: Path) -> list[dict[str, object]]:
    """The rows of a sweep or evaluation table, numbers as numbers (whole ones as ``int``), the rest as text."""

    def value(text: str) -> object:
        for kind in (int, float):
            try:
                return kind(text)
            except ValueError:
                pass
        return text

    with open_limited(path, "evaluation table") as f:
        return [{k: value(v) for k, v in row.items()} for row in csv.DictReader(f)]


def markdown(rows: list[dict[str, object]]) -> str:
    """The sweep table in Markdown (numbers to 2 decimals)."""
    header = list(rows[0])
    cell = lambda v: f"{v:.2f}" if isinstance(v, float) else str(v)  # noqa: E731
    return markdown_table([h.replace("_", " ") for h in header], [[cell(r[h]) for h in header] for r in rows])


def sweep(config: SweepConfig, live: bool = True) -> Path:
    """Train and evaluate every run of the sweep file; write ``sweep.csv`` and ``sweep.md``
    after each run, in the file's order (locally, each group of ``jobs`` runs trained side by
    side; on Ray, as the tasks come back), so a long sweep shows its results as they come.
    Returns ``sweep.md``."""
    require(config.eval_episodes >= 1, f"--eval-episodes must be >= 1, got {config.eval_episodes}")
    check_backend(config)
    runs = load_sweep(config.file, config.out)
    check_evaluations(runs, config.eval_episodes)
    done = {run.name for run in runs if status(run) == "done"}
    todo = [run for run in runs if run.name not in done]
    summary = Summary(runs, done)
    table: list[dict[str, object]] = []
    tabulated = []  # the runs in the table, in the file's order

    def tabulate(finished: set[str]) -> None:  # the runs after the table's last, while finished
        for run in runs[len(tabulated) :]:
            if run.name not in finished:
                return
            table.extend(table_rows(run, evaluation(run, config.eval_episodes)))
            tabulated.append(run)
            write_csv(config.out / "sweep.csv", table)
            write_text(config.out / "sweep.md", markdown(table))
            figure(table, config.out / "sweep.png", config.eval_episodes)

    def execute() -> None:
        finished = set(done)
        tabulate(finished)
        if config.backend == "ray":

            def finish(run: GridRun) -> None:
                finished.add(run.name)
                tabulate(finished)

            run_ray(todo, summary, config.address, config.retries, finish)
            return
        jobs = config.jobs or default_jobs(todo)
        for start in range(0, len(todo), jobs):  # each group side by side, in the file's order
            group = todo[start : start + jobs]
            train_runs(group, summary, len(group))
            finished.update(run.name for run in group)
            tabulate(finished)

    with folder_lock(config.out):  # one writer at a time
        if live:
            with Live(summary, console=console(), refresh_per_second=1):
                execute()
        else:
            execute()
    return config.out / "sweep.md"
