"""``roverswarm reproduce``: the paper's grid trained (:mod:`~roverswarm.experiments.grid`),
its arms timed back to back, its final policies evaluated, then Table I, Figures 8-9 and the
report written (:mod:`~roverswarm.experiments.results`, :mod:`~roverswarm.experiments.figures`,
:mod:`~roverswarm.experiments.report`)."""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import time
from pathlib import Path

import numpy as np

from roverswarm.config import TrainConfig, config_to_json
from roverswarm.console import console
from roverswarm.experiments.arms import GridRun, ReproduceConfig
from roverswarm.experiments.figures import figure8, figure9
from roverswarm.experiments.grid import run_grid
from roverswarm.experiments.report import table1_markdown, write_report
from roverswarm.experiments.results import TABLE1_COLUMNS, TIMING, RunResult, arm_order, label, load, table1
from roverswarm.experiments.sweep import evaluation, table_row
from roverswarm.experiments.timing import chunk_seconds
from roverswarm.jaxcache import release_compiled_programs
from roverswarm.learners import learner_family
from roverswarm.runs import folder_lock, write_csv
from roverswarm.storage import save_figure, write_text

UNTIMED = ("budget_minutes", "checkpoint_every", "checkpoint_minutes")
"""Settings a resume may change that no timed chunk reads (timing trains without checkpoints)."""


def settings_of(config: TrainConfig) -> str:
    """A fingerprint of a run's training settings (its replay's size, its learner, ...) but
    :data:`UNTIMED`: an arm's times in ``timing.csv`` count only while its settings are those
    it was timed with."""
    timed = dataclasses.replace(config, **{name: getattr(TrainConfig(), name) for name in UNTIMED})
    return hashlib.sha256(config_to_json(timed).encode()).hexdigest()[:16]


def time_arms(config: ReproduceConfig, runs: list[GridRun]) -> dict[tuple[str, str], np.ndarray]:
    """(scenario, arm) -> seconds per 1000 episodes of ``config.grid_time_chunks`` chunks of every
    paper-learner arm, timed back to back per scenario (:func:`~roverswarm.experiments.timing.chunk_seconds`).
    Kept in ``timing.csv`` with each arm's :func:`settings_of`: a scenario whose arms were all
    timed with their present settings is not timed again."""
    chunks = config.grid_time_chunks
    path = config.out / TIMING
    timed: dict[tuple[str, str], list[float]] = {}
    settings: dict[tuple[str, str], str] = {}
    if chunks == 0:
        return {}
    if path.exists():
        try:
            with open(path, newline="") as f:
                for row in csv.DictReader(f):
                    key = (row["scenario"], row["arm"])
                    timed.setdefault(key, []).append(float(row["seconds_per_1000"]))
                    settings[key] = row["settings"]
        except (ValueError, KeyError, TypeError):  # unreadable, or from before the settings were kept: time again
            timed = {}
    for scenario in config.grid_scenarios:
        arms = [r for r in runs if r.scenario == scenario and learner_family(r.config.learner.algo).replay]
        kept = (settings.get((scenario, r.algorithm)) == settings_of(r.config) for r in arms)
        if all(kept) and all(len(timed.get((scenario, r.algorithm), [])) >= chunks for r in arms):
            continue
        console().print(f"timing {scenario}: {len(arms)} arms x {chunks} chunks, back to back")
        for run, seconds in zip(arms, chunk_seconds([r.config for r in arms], chunks)):
            timed[(scenario, run.algorithm)] = [s * 1000 / run.config.log_every for s in seconds]
            settings[(scenario, run.algorithm)] = settings_of(run.config)
        rows = [
            {"scenario": s, "arm": a, "chunk": j, "seconds_per_1000": x, "settings": settings[(s, a)]}
            for (s, a), xs in timed.items()
            for j, x in enumerate(xs)
        ]
        write_csv(path, rows)
    return {key: np.array(xs) for key, xs in timed.items()}


def final_policies(results: list[RunResult], episodes: int, keep_programs: bool = False) -> list[dict[str, object]]:
    """Every run's final policies evaluated deterministically beside random and the oracle (kept
    in each run folder as ``evaluation.csv``): one row per run, every seed's score. Each
    run's rollout programs are released after it (with ``keep_programs``, only when crowded)."""
    rows = []
    for r in sorted(results, key=lambda r: (r.rovers, arm_order(r.run.algorithm))):
        row = table_row(r.run, evaluation(r.run, episodes))
        rows.append({"rovers": r.rovers, "arm": label(r.run.algorithm), **row})
        release_compiled_programs(only_if_crowded=keep_programs)
    return rows


def reproduce(config: ReproduceConfig, base: TrainConfig | None = None, live: bool = True) -> Path:
    """Run (or finish) the grid, then write table1.md/.csv, final_policies.csv, fig8.png,
    fig9.png and report.md.

    ``base`` holds the training settings of the paper's learners (default: ``config.preset``'s);
    the grid sets its scenario, algorithm, replay, ensembles, inferred policies, episodes, seeds
    and seed. One writer at a time: the folder is locked while the grid runs."""
    with folder_lock(Path(config.out)):
        return _reproduce(config, base, live)


def _reproduce(config: ReproduceConfig, base: TrainConfig | None, live: bool) -> Path:
    start = time.perf_counter()
    runs = run_grid(config, base, live=live)
    timed = time_arms(config, runs)
    results = [load(run, timed) for run in runs]
    rows = table1(results)
    final = final_policies(results, config.grid_eval_episodes, config.grid_keep_programs)
    config.out.mkdir(parents=True, exist_ok=True)
    write_csv(config.out / "table1.csv", rows, TABLE1_COLUMNS)
    write_csv(config.out / "final_policies.csv", final)
    write_text(config.out / "table1.md", table1_markdown(rows))
    save_figure(figure8(results), config.out / "fig8.png")
    save_figure(figure9(results), config.out / "fig9.png")
    return write_report(config, results, rows, final, time.perf_counter() - start)
