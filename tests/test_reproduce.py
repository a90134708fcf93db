"""`roverswarm reproduce`: a tiny grid end to end, resume, --force, and the Ray backend."""

from __future__ import annotations

import csv
import dataclasses
import multiprocessing
import os
import shutil
import signal
import socket
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from local_ray import CHILD_TIMEOUT
from scipy import stats

import roverswarm.experiments.grid as grid_module
import roverswarm.experiments.pool as pool_module
from roverswarm.cli import main
from roverswarm.config import config_from_json, with_options
from roverswarm.errors import RunStopped, UserError
from roverswarm.experiments import ReproduceConfig, reproduce
from roverswarm.experiments.arms import plan
from roverswarm.experiments.results import PAPER_TABLE1
from roverswarm.experiments.significance import holm, paired_change, paired_p, relative_change
from roverswarm.presets import MAPPO, PRESETS
from roverswarm.runs import folder_lock, write_csv

SCENARIOS = ("paper-2", "paper-3")
ALGORITHMS = ("ddpg", "maddpg", "maddpg-optimizer")


@pytest.fixture(scope="module")
def base(tiny_config):
    return with_options(tiny_config, dict(refresh_every=10))


def tiny_grid(out: Path, **changes) -> ReproduceConfig:
    """A grid of tiny runs, trained in this process unless ``changes`` say otherwise."""
    defaults = dict(out=out, scenarios=SCENARIOS, seeds=2, episodes=400, jobs=1, eval_episodes=50)
    return ReproduceConfig(**{**defaults, **changes})  # runs this short keep their compiled programs


@pytest.mark.parametrize(
    "changes, kept",
    [({"quick": True}, True), ({"episodes": 4000}, True), ({}, False), ({"keep_programs": True}, True)],
)
def test_a_grid_of_short_runs_keeps_its_programs_and_a_long_one_releases_them_unless_asked(changes, kept):
    """Runs under 5000 episodes (--quick's 2000) keep their compiled programs until crowded;
    the paper's 60,000-episode runs release them after each run unless --keep-programs."""
    assert ReproduceConfig(**changes).grid_keep_programs == kept


def timeless(rows: dict[int, list[dict[str, float]]]) -> dict[int, list[dict[str, float]]]:
    """Metrics rows without their wall-clock seconds."""
    return {s: [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rs] for s, rs in rows.items()}


@pytest.fixture(scope="module")
def finished(base, tmp_path_factory):
    out = tmp_path_factory.mktemp("grid")
    reproduce(tiny_grid(out), base, live=False)
    return out


def seed_rows(path: Path) -> dict[int, list[dict[str, float]]]:
    """A metrics.csv read with the csv module only, grouped by seed."""
    with open(path, newline="") as f:
        rows = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
    return {s: [r for r in rows if int(r["seed"]) == s] for s in sorted({int(r["seed"]) for r in rows})}


def read_table(path: Path) -> list[dict[str, object]]:
    """A CSV file of the report with its numbers as floats (text columns kept)."""

    def value(text: str) -> object:
        try:
            return float(text)
        except ValueError:
            return text

    with open(path, newline="") as f:
        return [{k: value(v) for k, v in r.items()} for r in csv.DictReader(f)]


def per_seed(folder: Path, window: int = 5000) -> tuple[np.ndarray, np.ndarray]:
    """Slowly, from metrics.csv: every seed's maximum and last-window mean episode reward."""
    rows = seed_rows(folder / "metrics.csv")
    best = np.array([max(r["episode_reward"] for r in seed) for seed in rows.values()])
    last = []
    for seed in rows.values():
        end = max(r["episodes"] for r in seed)
        last.append(np.mean([r["episode_reward"] for r in seed if r["episodes"] > end - window]))
    return best, np.array(last)


def assert_paired(change, low, high, p, treated: np.ndarray, control: np.ndarray) -> None:
    """A Table I change against its definition: the change of the means, the paired t-test, and
    an interval around the change."""
    assert change == pytest.approx(100 * (treated.mean() - control.mean()) / abs(control.mean()), rel=1e-6)
    assert p == pytest.approx(stats.ttest_rel(treated, control).pvalue, rel=1e-6)
    assert low < change < high


def test_table1_comes_from_the_metrics_files(finished):
    table = read_table(finished / "table1.csv")
    assert [int(r["rovers"]) for r in table] == [2, 3] and {r["arm"] for r in table} == {"MADDPG + optimizer"}
    for row, scenario in zip(table, SCENARIOS):
        runs = finished / "runs" / scenario
        (plain, plain_last), (opt, opt_last) = per_seed(runs / "maddpg"), per_seed(runs / "maddpg-optimizer")
        assert_paired(*(row[f"reward_{k}"] for k in ("change_pct", "ci_low", "ci_high", "p")), opt, plain)
        assert_paired(*(row[f"last_{k}"] for k in ("change_pct", "ci_low", "ci_high", "p")), opt_last, plain_last)
        seconds = {
            a: np.array(
                [r["wall_seconds"] * 10 for r in seed_rows(runs / a / "metrics.csv")[0][1:]]
            )  # 100-episode rows
            for a in ("maddpg", "maddpg-optimizer")
        }
        t_plain, t_opt = seconds["maddpg"], seconds["maddpg-optimizer"]
        assert row["time_change_pct"] == pytest.approx(100 * (t_opt.mean() - t_plain.mean()) / t_plain.mean(), rel=1e-6)
        assert (row["paper_reward_change_pct"], row["paper_time_change_pct"]) == PAPER_TABLE1[int(row["rovers"])]
    markdown = (finished / "table1.md").read_text()
    assert markdown.count("\n| ") == 2 and "+8.78%" not in markdown and "+3.08%" in markdown


def test_a_grid_without_an_optimizer_pair_says_table1_has_no_comparison(base, finished, tmp_path):
    """`--algorithms ddpg` (here: its finished runs, copied) has no optimizer arm beside its
    plain learner: Table I says so in words where it was an empty table."""
    for scenario in SCENARIOS:
        shutil.copytree(finished / "runs" / scenario / "ddpg", tmp_path / "runs" / scenario / "ddpg")
    reproduce(tiny_grid(tmp_path, algorithms=("ddpg",)), base, live=False)
    assert read_table(tmp_path / "table1.csv") == []
    said = "No comparison: Table I sets an optimizer arm beside its plain learner"
    assert (tmp_path / "table1.md").read_text().startswith(said)
    report = (tmp_path / "report.md").read_text()
    assert said in report and "Pooled across N" not in report and "for all 0 rows" not in report


def test_two_optimizer_variants_against_one_maddpg_arm(base, finished, tmp_path, capsys):
    """A grid with two readings of the optimizer beside the plain MADDPG runs of ``finished``
    (copied: the same settings, so the grid keeps them): each variant's Table I rows, its pooled
    test and every run's deterministic evaluation, recomputed from the run folders."""
    for scenario in SCENARIOS:
        shutil.copytree(finished / "runs" / scenario / "maddpg", tmp_path / "runs" / scenario / "maddpg")
    # the paper's reading (no options of its own: the compiled programs of the optimizer arm
    # of ``finished``) and Schaul's; a variant's single option (alpha=3) is parsed in
    # test_the_grid_sets_preset_ensembles_inferred_policies_and_the_optimizer
    variants = ("paper", "schaul:reading=schaul,alpha=0.7,beta=0,importance_weights=true")
    grid = tiny_grid(tmp_path, algorithms=("maddpg", "maddpg-optimizer"), variants=variants, time_chunks=2)
    reproduce(grid, base, live=False)
    timing = read_table(tmp_path / "timing.csv")  # 2 chunks of every arm, back to back, per scenario
    timed = {(r["scenario"], r["arm"]): [] for r in timing}
    for r in timing:
        timed[(r["scenario"], r["arm"])].append(r["seconds_per_1000"])
    assert sorted(timed) == sorted(
        (s, a) for s in SCENARIOS for a in ("maddpg", "maddpg-optimizer-paper", "maddpg-optimizer-schaul")
    )
    assert all(len(x) == 2 and min(x) > 0 for x in timed.values())
    arms = {"paper": {}, "schaul": dict(reading="schaul", alpha=0.7, beta=0.0, importance_weights=True)}
    table = read_table(tmp_path / "table1.csv")
    assert [(int(r["rovers"]), r["arm"]) for r in table] == [
        (n, f"MADDPG + optimizer ({name})") for name in arms for n in (2, 3)
    ]
    holm_p = [r["reward_p_holm"] for r in table]  # one family: both variants at both sizes
    for level in (0.01, 0.05, 0.2, 0.5, 0.9):
        assert {i for i, a in enumerate(holm_p) if a <= level} == holm_rejects([r["reward_p"] for r in table], level)
    report = (tmp_path / "report.md").read_text()
    for name, options in arms.items():
        pooled = []
        for scenario in SCENARIOS:
            folder = tmp_path / "runs" / scenario / f"maddpg-optimizer-{name}"
            saved = config_from_json((folder / "config.json").read_text())
            assert saved == with_options(
                base, dict(scenario=scenario, episodes=400, seeds=2, replay="ranked", **options)
            )
            (plain, plain_last), (opt, opt_last) = per_seed(tmp_path / "runs" / scenario / "maddpg"), per_seed(folder)
            row = next(r for r in table if r["arm"].endswith(f"({name})") and r["rovers"] == int(scenario[-1]))
            assert_paired(*(row[f"reward_{k}"] for k in ("change_pct", "ci_low", "ci_high", "p")), opt, plain)
            assert_paired(*(row[f"last_{k}"] for k in ("change_pct", "ci_low", "ci_high", "p")), opt_last, plain_last)
            t_opt, t_plain = (np.array(timed[(scenario, a)]) for a in (f"maddpg-optimizer-{name}", "maddpg"))
            assert row["time_change_pct"] == pytest.approx(100 * (t_opt.mean() / t_plain.mean() - 1), rel=1e-6)
            pooled.append(100 * (opt - plain) / abs(plain.mean()))
        pooled = np.concatenate(pooled)
        line = next(line for line in report.splitlines() if line.startswith(f"| MADDPG + optimizer ({name}) | 2 |"))
        assert f"| {pooled.mean():+.2f}% |" in line and f"| {stats.ttest_1samp(pooled, 0).pvalue:.3g} |" in line
    final = read_table(tmp_path / "final_policies.csv")
    assert len(final) == 6
    for row in final:  # every seed's deterministic score on 50 episodes, as `roverswarm evaluate` gives it
        folder = tmp_path / "runs" / row["scenario"] / row["setting"]
        evaluated = read_table(folder / "evaluation.csv")
        assert {r["episodes"] for r in evaluated} == {50.0}
        scores = [r["normalized_score"] for r in evaluated if r["policy"] not in ("random", "oracle")]
        assert row["scores"] == " / ".join(f"{x:.2f}" for x in scores) and len(scores) == 2
    assert "## Final policies, deterministic evaluation" in report
    # timing.csv serves the arms while their settings hold: an arm trained anew with other
    # settings (its folder deleted, then refresh_every changed) has its scenario timed again
    import roverswarm.experiments.paper as paper_module

    timings = []
    fake = lambda configs, chunks: timings.append([c.scenario for c in configs]) or [[1.0] * chunks for _ in configs]  # noqa: E731
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(paper_module, "chunk_seconds", fake)
        runs = plan(grid, base)
        assert paper_module.time_arms(grid, runs).keys() == timed.keys() and timings == []
        changed = [
            dataclasses.replace(r, config=with_options(r.config, {"refresh_every": 3}))
            if (r.scenario, r.algorithm) == ("paper-3", "maddpg-optimizer-paper")
            else r
            for r in runs
        ]
        again = paper_module.time_arms(grid, changed)
        paper_module.time_arms(grid, changed)  # the new settings kept: timed once
        resumed = [dataclasses.replace(r, config=with_options(r.config, {"checkpoint_every": 7})) for r in changed]
        paper_module.time_arms(grid, resumed)  # what a resume may change and no timing reads
        assert timings == [["paper-3"] * 3]
    assert again[("paper-3", "maddpg")].tolist() == [1000 / base.log_every] * 2
    np.testing.assert_array_equal(again[("paper-2", "maddpg")], timed[("paper-2", "maddpg")])
    assert main(["reproduce", "--out", str(tmp_path), "--variants", "bad:gamma=0.5"]) == 2
    assert "'gamma' in 'bad:gamma=0.5' is not an optimizer option" in capsys.readouterr().err
    assert main(["reproduce", "--out", str(tmp_path), "--variants", "a:alpha=x"]) == 2
    assert "--variants: alpha in 'a:alpha=x'" in capsys.readouterr().err
    # a value the config refuses names the arm (the variant) that set it
    assert main(["reproduce", "--out", str(tmp_path / "b"), "--variants", "a:beta=2"]) == 2
    assert "arm 'maddpg-optimizer-a' on paper-2: --beta must be in [0, 1], got 2.0" in capsys.readouterr().err


def test_the_ensembles_script_compares_two_parts_unpaired_where_both_ran(finished, tmp_path, monkeypatch, capsys):
    """docs/results/paper/ensembles.py on two stand-in parts (reference-k1: the plain MADDPG
    runs of ``finished``; reference-k3: its optimizer runs, at paper-2 only): one row per
    reading at N = 2, each K = 3 vs K = 1 change recomputed with scipy's Welch test."""
    import runpy
    import sys

    for part, arm, scenarios in (
        ("reference-k1", "maddpg", SCENARIOS),
        ("reference-k3", "maddpg-optimizer", SCENARIOS[:1]),
    ):
        for scenario in scenarios:
            shutil.copytree(finished / "runs" / scenario / arm, tmp_path / part / "runs" / scenario / "maddpg")
    seconds = {"reference-k1": [10.0, 11.0, 12.0], "reference-k3": [40.0, 41.0, 45.0]}
    for part, xs in seconds.items():
        rows = [{"scenario": "paper-2", "arm": "maddpg", "chunk": j, "seconds_per_1000": x} for j, x in enumerate(xs)]
        write_csv(tmp_path / part / "timing.csv", rows)
    script = Path(__file__).parents[1] / "docs" / "results" / "paper" / "ensembles.py"
    argv = ["ensembles.py", str(tmp_path), "--csv", str(tmp_path / "e.csv"), "--eval-episodes", "50"]
    monkeypatch.setattr(sys, "argv", argv)
    runpy.run_path(str(script), run_name="__main__")
    rows = {r["reading"]: r for r in read_table(tmp_path / "e.csv")}
    assert {r["rovers"] for r in rows.values()} == {2.0} and len(rows) == 5
    (k1, k1_last), (k3, k3_last) = (per_seed(tmp_path / p / "runs" / "paper-2" / "maddpg") for p in seconds)
    scores = [
        [r["normalized_score"] for r in read_table(tmp_path / p / "runs" / "paper-2" / "maddpg" / "evaluation.csv")[2:]]
        for p in seconds
    ]
    for reading, (control, treated) in {
        "max mean episode reward": (k1, k3),
        "last-window reward": (k1_last, k3_last),
        "deterministic score": scores,
        "s / 1000 episodes": seconds.values(),
    }.items():
        control, treated, row = np.array(control), np.array(treated), rows[reading]
        assert (row["k1"], row["k3"]) == pytest.approx((control.mean(), treated.mean()), rel=1e-6)
        assert row["change_pct"] == pytest.approx(100 * (treated.mean() / control.mean() - 1) * np.sign(control.mean()))
        assert row["p"] == pytest.approx(stats.ttest_ind(treated, control, equal_var=False).pvalue, rel=1e-6)
        assert row["ci_low"] < row["change_pct"] < row["ci_high"]
    assert "| 2 | s / 1000 episodes | 11.00 | 42.00 |" in capsys.readouterr().out


def test_figures_and_report(finished):
    for name in ("fig8.png", "fig9.png"):
        image = iio.imread(finished / name)
        assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 600
        assert image[..., :3].std() > 10  # not a blank canvas
    report = (finished / "report.md").read_text()
    for part in (
        "## Settings",
        "## Machine",
        "Wall time",
        "## Table I",
        "(fig8.png)",
        "(fig9.png)",
        "MADDPG beats DDPG",
        "helps more as N grows",
    ):
        assert part in report
    assert "| 3 | MADDPG + optimizer |" in report
    # the training time: every chunk's seconds of every run, read here with the csv module
    seconds = sum(row["wall_seconds"] for path in finished.glob("runs/*/*/metrics.csv") for row in seed_rows(path)[0])
    assert f"whichever command ran them): {seconds / 60:.1f} min." in report.replace("\n", " ")


def test_the_figures_draw_each_arms_numbers_at_its_size():
    """Figure 8's bars are each arm's mean over seeds (maximum reward, seconds per 1000
    episodes) at the tick of its N, an arm missing at one N leaving no bar there; figure 9's
    lines are each arm's mean curve on its own panel. Made-up results, so every number is known."""
    from types import SimpleNamespace

    from matplotlib.container import BarContainer

    from roverswarm.experiments.figures import figure8, figure9
    from roverswarm.experiments.results import RunResult, label

    rng = np.random.default_rng(0)
    episodes = np.arange(1, 5) * 1000.0

    def result(n, algorithm):
        run = SimpleNamespace(algorithm=algorithm, config=SimpleNamespace(seeds=3))
        curves, seconds = rng.normal(-50 * n, 5, (3, 4)), rng.uniform(10, 20, 3) * n
        return RunResult(run=run, rovers=n, episodes=episodes, curves=curves, chunk_seconds=seconds)

    arms = {2: ("maddpg", "maddpg-optimizer", "ddpg"), 3: ("maddpg", "maddpg-optimizer")}  # no DDPG at N = 3
    results = [result(n, a) for n, algorithms in arms.items() for a in algorithms]
    reward, time = figure8(results).axes
    assert [t.get_text() for t in reward.get_xticklabels()] == ["N = 2", "N = 3"]
    for ax, value in ((reward, lambda r: r.best), (time, lambda r: r.seconds)):
        bars = {c.get_label(): c.patches for c in ax.containers if isinstance(c, BarContainer)}
        assert set(bars) == {label(a) for a in arms[2]}
        for algorithm in arms[2]:
            mine, drawn = [r for r in results if r.run.algorithm == algorithm], bars[label(algorithm)]
            assert [round(p.get_x() + p.get_width() / 2) for p in drawn] == [r.rovers - 2 for r in mine]  # its N's tick
            np.testing.assert_allclose([p.get_height() for p in drawn], [value(r).mean() for r in mine], rtol=1e-6)
    panels = figure9(results).axes
    assert [ax.get_title() for ax in panels[:2]] == ["N = 2 (3 seeds)", "N = 3 (3 seeds)"]
    for ax, n in zip(panels, arms):
        lines = {line.get_label(): line for line in ax.get_lines()}
        assert set(lines) == {label(a) for a in arms[n]}
        for r in (r for r in results if r.rovers == n):
            line = lines[label(r.run.algorithm)]
            np.testing.assert_allclose(line.get_ydata(), r.curves.mean(axis=0))
            np.testing.assert_array_equal(line.get_xdata(), episodes)


def test_an_interrupted_grid_finishes_only_the_missing_runs(base, finished, tmp_path, monkeypatch):
    real = pool_module.train
    calls = []

    def stops_after_two(config, out, **kwargs):
        calls.append(Path(out))
        if len(calls) == 3:
            raise RunStopped("interrupted")
        return real(config, out, **kwargs)

    monkeypatch.setattr(pool_module, "train", stops_after_two)
    small = tiny_grid(tmp_path, scenarios=("paper-2",))
    with pytest.raises(RunStopped):
        reproduce(small, base, live=False)
    calls.clear()
    monkeypatch.setattr(
        pool_module, "train", lambda config, out, **kw: calls.append(Path(out)) or real(config, out, **kw)
    )
    reproduce(small, base, live=False)
    assert calls == [tmp_path / "runs" / "paper-2" / "maddpg-optimizer"]
    for algorithm in ALGORITHMS:  # same seeds, same numbers as the unbroken grid
        ours, theirs = (
            seed_rows(root / "runs" / "paper-2" / algorithm / "metrics.csv") for root in (tmp_path, finished)
        )
        assert [[r["episode_reward"] for r in rows] for rows in ours.values()] == [
            [r["episode_reward"] for r in rows] for rows in theirs.values()
        ]
    calls.clear()
    reproduce(small, base, live=False)  # nothing left: nothing trains
    assert calls == []
    forced = tiny_grid(tmp_path, scenarios=("paper-2",), algorithms=("ddpg",), force=True)
    (tmp_path / "timing.csv").write_text("scenario,arm,chunk,seconds_per_1000\npaper-2,ddpg,0,999.0\n")
    with folder_lock(tmp_path / "runs" / "paper-2" / "ddpg"):  # another command writes the run: nothing deleted
        with pytest.raises(UserError, match="is being written by process"):
            reproduce(forced, base, live=False)
    assert (tmp_path / "runs" / "paper-2" / "ddpg" / "checkpoint.npz").exists() and calls == []
    reproduce(forced, base, live=False)
    assert calls == [tmp_path / "runs" / "paper-2" / "ddpg"]
    # the earlier grid's timings went with its runs (Table I took them for the new grid's; this
    # tiny grid times nothing)
    assert not (tmp_path / "timing.csv").exists()
    # interrupted, a forced grid says to rerun without --force: with it, the runs it saved are deleted
    monkeypatch.setattr(pool_module, "train", stops_after_two)
    calls[:] = [None, None]
    with pytest.raises(RunStopped, match=r"rerun without --force: with it every run starts again"):
        reproduce(forced, base, live=False)


def test_an_on_policy_arm_trains_from_its_preset_beside_the_papers_learners(base, finished, tmp_path):
    shutil.copytree(finished / "runs" / "paper-2" / "maddpg", tmp_path / "runs" / "paper-2" / "maddpg")  # kept
    reproduce(tiny_grid(tmp_path, scenarios=("paper-2",), algorithms=("maddpg", "mappo")), base, live=False)
    saved = config_from_json((tmp_path / "runs" / "paper-2" / "mappo" / "config.json").read_text())
    grid = dict(scenario="paper-2", episodes=400, seeds=2, seed=0, log_every=100, checkpoint_every=1)
    assert saved == with_options(MAPPO, grid)
    best = {
        arm: np.array([max(r["episode_reward"] for r in rows) for rows in seed_rows(folder / "metrics.csv").values()])
        for arm, folder in (
            ("mappo", tmp_path / "runs" / "paper-2" / "mappo"),
            ("maddpg", tmp_path / "runs" / "paper-2" / "maddpg"),
        )
    }
    change = 100 * (best["mappo"].mean() - best["maddpg"].mean()) / abs(best["maddpg"].mean())
    report = (tmp_path / "report.md").read_text()
    assert (
        "MAPPO vs MADDPG* (not a claim of the paper; MAPPO trains from its own preset): maximum mean episode "
        f"reward change N = 2: {change:+.1f}%" in report
    )
    assert "| 2 | MAPPO |" in report


def test_a_folder_with_other_settings_is_not_overwritten(base, finished, capsys):
    with pytest.raises(UserError, match="holds a run with other settings .*; delete that folder"):
        reproduce(tiny_grid(finished, seed=5), base, live=False)
    assert main(["reproduce", "--out", str(finished), "--scenarios", "paper-11"]) == 2
    assert "unknown scenario 'paper-11'" in capsys.readouterr().err
    assert main(["reproduce", "--out", str(finished), "--address", "x:1"]) == 2
    assert "--address needs --backend ray" in capsys.readouterr().err
    assert main(["reproduce", "--out", str(finished), "--scenarios", "paper-3", "spread-3"]) == 2
    assert "give each swarm size N once" in capsys.readouterr().err


def test_the_grid_sets_preset_ensembles_inferred_policies_and_the_optimizer(tmp_path, capsys):
    """The runs the options ask for: every paper learner at the preset with K sub-policies,
    inferred policies for the MADDPG arms only, the optimizer flags on the optimizer arm."""
    config = ReproduceConfig(
        out=tmp_path, scenarios=("paper-4",), preset="default", ensemble=3, infer_policies=True, alpha=2.0, beta=0.0
    )
    runs = {run.algorithm: run.config for run in plan(config, PRESETS[config.preset])}
    grid = dict(scenario="paper-4", episodes=60_000, seeds=5, ensemble=3)
    assert runs == {
        "ddpg": with_options(PRESETS["default"], dict(grid, algo="ddpg")),
        "maddpg": with_options(PRESETS["default"], dict(grid, infer_policies=True)),
        "maddpg-optimizer": with_options(
            PRESETS["default"], dict(grid, infer_policies=True, replay="ranked", alpha=2.0, beta=0.0)
        ),
    }
    swarm = ["reproduce", "--out", str(tmp_path), "--preset", "swarm", "--ensemble", "3"]
    assert main(swarm) == 2
    assert "--share-parameters does not compose with --ensemble > 1" in capsys.readouterr().err
    variants = ReproduceConfig(
        out=tmp_path, scenarios=("paper-4",), algorithms=("ddpg", "ddpg-optimizer"), variants=("a", "b:alpha=3")
    )
    runs = {run.algorithm: run.config for run in plan(variants, PRESETS["reference"])}
    grid = dict(scenario="paper-4", episodes=60_000, seeds=5, algo="ddpg")
    assert runs == {
        "ddpg": with_options(PRESETS["reference"], grid),
        "ddpg-optimizer-a": with_options(PRESETS["reference"], dict(grid, replay="ranked")),
        "ddpg-optimizer-b": with_options(PRESETS["reference"], dict(grid, replay="ranked", alpha=3.0)),
    }
    assert main(["reproduce", "--out", str(tmp_path), "--algorithms", "maddpg", "--variants", "a"]) == 2
    assert "--variants needs maddpg-optimizer or ddpg-optimizer in --algorithms" in capsys.readouterr().err
    # options no arm of the grid reads are refused, not dropped
    refused = {
        ("--algorithms", "ddpg", "--alpha", "3"): "--alpha set the optimizer: give maddpg-optimizer or ddpg-optimizer",
        ("--algorithms", "maddpg", "--reading", "schaul", "--beta", "0"): "--reading, --beta set the optimizer",
        ("--algorithms", "mappo", "--ensemble", "3"): "--ensemble is for the paper's learners",
        ("--algorithms", "ddpg", "ddpg-optimizer", "--infer-policies"): "--infer-policies is for the MADDPG arms",
    }
    for args, message in refused.items():
        assert main(["reproduce", "--out", str(tmp_path), *args]) == 2, args
        assert message in capsys.readouterr().err, args


def test_the_quick_grid_trains_the_smallest_and_largest_swarm_and_the_full_grid_all_four(tmp_path):
    """--quick plans paper-2 and paper-5 (each run compiles its own programs: a short grid's
    time), short and with 2 seeds; without it the paper's four swarms at its budget; given
    --scenarios win either way."""

    def grid(quick: bool, scenarios: tuple[str, ...] | None = None) -> set[tuple[str, str, int, int]]:
        config = ReproduceConfig(out=tmp_path, quick=quick, scenarios=scenarios)
        return {(r.scenario, r.algorithm, r.config.seeds, r.config.episodes) for r in plan(config)}

    arms = ("ddpg", "maddpg", "maddpg-optimizer")
    assert grid(quick=True) == {(s, a, 2, 2000) for s in ("paper-2", "paper-5") for a in arms}
    assert grid(quick=False) == {(f"paper-{n}", a, 5, 60_000) for n in (2, 3, 4, 5) for a in arms}
    given = ("paper-3", "paper-4")
    assert grid(quick=True, scenarios=given) == {(s, a, 2, 2000) for s in given for a in arms}


def test_ddpg_with_the_optimizer_is_compared_with_ddpg(base, finished, tmp_path):
    """A `ddpg-optimizer` arm beside the paper's three learners of ``finished`` (copied): each
    optimizer arm's Table I row is the paired change against its own plain learner, recomputed
    from the run folders; only MADDPG's row carries the paper's value (its Table I is about
    MADDPG)."""
    runs = tmp_path / "runs" / "paper-2"
    for algorithm in ALGORITHMS:
        shutil.copytree(finished / "runs" / "paper-2" / algorithm, runs / algorithm)
    reproduce(tiny_grid(tmp_path, scenarios=("paper-2",), algorithms=(*ALGORITHMS, "ddpg-optimizer")), base, live=False)
    saved = config_from_json((runs / "ddpg-optimizer" / "config.json").read_text())
    assert saved == with_options(base, dict(scenario="paper-2", episodes=400, seeds=2, algo="ddpg", replay="ranked"))
    table = read_table(tmp_path / "table1.csv")
    assert [(r["arm"], r["against"]) for r in table] == [("MADDPG + optimizer", "MADDPG"), ("DDPG + optimizer", "DDPG")]
    for row, (treated, control) in zip(table, [("maddpg-optimizer", "maddpg"), ("ddpg-optimizer", "ddpg")]):
        (plain, plain_last), (opt, opt_last) = per_seed(runs / control), per_seed(runs / treated)
        assert_paired(*(row[f"reward_{k}"] for k in ("change_pct", "ci_low", "ci_high", "p")), opt, plain)
        assert_paired(*(row[f"last_{k}"] for k in ("change_pct", "ci_low", "ci_high", "p")), opt_last, plain_last)
    assert (table[0]["paper_reward_change_pct"], table[0]["paper_time_change_pct"]) == PAPER_TABLE1[2]
    assert np.isnan(table[1]["paper_reward_change_pct"]) and np.isnan(table[1]["paper_time_change_pct"])
    report = (tmp_path / "report.md").read_text()
    assert "- *DDPG + optimizer helps more as N grows* (not a claim of the paper): needs at least two" in report
    assert "- *MADDPG + optimizer helps more as N grows*: needs at least two" in report
    assert "| 2 | DDPG + optimizer | DDPG |" in report and "| 2 | MADDPG + optimizer | MADDPG |" in report


def test_the_paired_change_interval_covers_the_truth_95_percent_of_the_time():
    """Monte Carlo: 5 seeds whose arms share a seed effect (correlated pairs), true change +10%."""
    rng = np.random.default_rng(1)
    hits = 0
    trials = 2000
    for _ in range(trials):
        seed_effect = rng.normal(0.0, 10.0, 5)
        control = -100.0 + seed_effect + rng.normal(0.0, 3.0, 5)
        treated = -90.0 + 0.9 * seed_effect + rng.normal(0.0, 3.0, 5)
        _, low, high, _ = paired_change(treated, control)
        hits += low <= 10.0 <= high
    assert 0.92 <= hits / trials <= 0.985


def holm_rejects(p_values: list[float], level: float) -> set[int]:
    """Holm's procedure as he states it, slowly: go through the hypotheses from the smallest p;
    reject the j-th (counting from 1) while its p <= level / (m - j + 1); stop at the first that is not."""
    tested = sorted((p, i) for i, p in enumerate(p_values) if np.isfinite(p))
    rejected = set()
    for j, (p, i) in enumerate(tested, start=1):
        if p > level / (len(tested) - j + 1):
            break
        rejected.add(i)
    return rejected


@pytest.mark.parametrize(
    "changes, p_holm, word",
    [
        ((+8, -5, -4, +9), (0.004, 0.5, 0.5, 0.3), "not supported"),  # the one gain shown is at N = 2
        ((+1, +2, +3, +9), (0.9, 0.9, 0.9, 0.01), "supported"),
        ((+1, +2, +3, +9), (0.01, 0.01, 0.01, 0.2), "not supported"),  # nothing shown at N = 5
        ((+9, +3, +2, +1), (0.9, 0.9, 0.9, 0.01), "not supported"),  # shown at N = 5, but falling
    ],
)
def test_the_verdict_on_growth_needs_a_gain_shown_at_the_largest_n(changes, p_holm, word):
    from roverswarm.experiments.report import verdicts

    rows = [
        dict(arm="MADDPG + optimizer", against="MADDPG", rovers=n, reward_change_pct=c, reward_p=p, reward_p_holm=p)
        for n, c, p in reversed(list(zip((2, 3, 4, 5), changes, p_holm)))  # in any order
    ]
    (line,) = verdicts([], rows)
    assert line.startswith(f"- *MADDPG + optimizer helps more as N grows*: {word} by our runs"), line


@pytest.mark.parametrize(
    "maddpg_wins, word",
    [((True, True), "supported"), ((True, False), "partly supported"), ((False, False), "not supported")],
)
def test_the_verdict_on_maddpg_against_ddpg_counts_the_sizes_it_wins(maddpg_wins, word):
    """*MADDPG beats DDPG*: supported where MADDPG's best reward is higher at every N, partly
    where at some, not where at none; the change printed is MADDPG's against DDPG's."""
    from types import SimpleNamespace

    from roverswarm.experiments.report import verdicts

    results = []
    for n, wins in zip((2, 3), maddpg_wins):
        ddpg = np.array([-100.0, -102.0, -98.0])
        maddpg = ddpg + (5.0 if wins else -5.0)
        for algorithm, best in (("maddpg", maddpg), ("ddpg", ddpg)):
            results.append(SimpleNamespace(rovers=n, run=SimpleNamespace(algorithm=algorithm), best=best))
    (line,) = verdicts(results, [])[1:]  # after the growth line that no optimizer arm gives
    assert line.startswith(f"- *MADDPG beats DDPG*: {word};"), line
    assert f"N = 2: {'+' if maddpg_wins[0] else '-'}5.0%" in line, line


def test_holm_adjusted_p_values_reject_what_holms_procedure_rejects():
    assert holm([0.01, 0.04, 0.03, float("nan")])[:3] == pytest.approx([0.03, 0.06, 0.06])
    assert np.isnan(holm([0.01, float("nan")])[1]) and holm([]).shape == (0,)
    rng = np.random.default_rng(0)
    for _ in range(200):
        p = rng.uniform(0, 0.2, rng.integers(1, 9)) ** rng.uniform(0.5, 3)
        p[rng.random(len(p)) < 0.15] = np.nan
        p[rng.random(len(p)) < 0.15] = p[0]  # ties
        adjusted = holm(p)
        assert np.array_equal(np.isnan(adjusted), np.isnan(p)) and np.all(adjusted[~np.isnan(p)] >= p[~np.isnan(p)])
        for level in (0.001, 0.01, 0.05, 0.1, 0.3):
            assert {i for i, a in enumerate(adjusted) if a <= level} == holm_rejects(list(p), level)


def test_the_paired_p_value_matches_scipy_and_is_defined_without_spread():
    from scipy import stats

    differences = np.array([1.0, -0.5, 2.0, 0.3, 1.1])
    assert paired_p(differences) == pytest.approx(stats.ttest_1samp(differences, 0.0).pvalue)
    assert paired_p(np.zeros(5)) == 1.0  # identical arms (untrained quick rows): no evidence of a change
    assert paired_p(np.full(5, 2.0)) == 0.0  # a constant nonzero difference: the t-test's limit
    assert np.isnan(paired_p(np.array([1.0])))
    assert paired_change(np.full(3, -10.0), np.full(3, -10.0))[3] == 1.0


def test_the_relative_change_interval_covers_the_truth_95_percent_of_the_time():
    """Monte Carlo: 5 seeds each, true change +10%; the interval should hold it ~95% of the time."""
    rng = np.random.default_rng(0)
    hits = 0
    trials = 2000
    for _ in range(trials):
        control = rng.normal(-100.0, 8.0, 5)
        treated = rng.normal(-90.0, 5.0, 5)
        _, low, high, _ = relative_change(treated, control)
        hits += low <= 10.0 <= high
    assert 0.92 <= hits / trials <= 0.985


def test_the_live_table_starts_a_partial_run_where_it_was_saved(base, tmp_path):
    """A run interrupted at 200 of 400 episodes (its checkpoint's; metrics.csv a chunk ahead)
    waits as "queued 200/400", and the time left counts only its 200 left: one run trains 100
    episodes in a minute, 300 + 200 are left."""
    from rich.console import Console

    from roverswarm.experiments.live import Summary

    fresh, partial = plan(tiny_grid(tmp_path, scenarios=("paper-2",), algorithms=("ddpg", "maddpg")), base)
    partial.folder.mkdir(parents=True)
    write_csv(
        partial.folder / "metrics.csv",
        [{"seed": s, "episodes": e, "wall_seconds": 1.0} for e in (100, 200, 300) for s in range(2)],
    )
    np.savez(partial.folder / "checkpoint.npz", episodes=np.asarray(200))  # what a resume starts from
    summary = Summary([fresh, partial], set())
    summary.progress(fresh, 0)
    summary.progress(fresh, 100)
    summary.started = time.perf_counter() - 60
    console = Console(record=True, width=100)
    console.print(summary)
    text = " ".join(console.export_text().split())  # the title wraps at the table's width
    assert "queued │ 200/400" in text, text
    assert "time left ~ 5 min" in text, text  # (300 + 200) episodes x 2 seeds at 200 a minute


def test_the_live_table_shows_a_ray_task_running_once_it_reported_and_done_once_it_ended(base, tmp_path):
    """With 2 CPUs and 3 tasks sent, the third waits on the cluster: queued until its task
    reports to the board, and a run that ended is not taken back to running by a late report."""
    from rich.console import Console

    from roverswarm.experiments.live import Summary
    from roverswarm.experiments.remote import Board, follow

    runs = plan(tiny_grid(tmp_path, scenarios=("paper-2",)), base)
    summary, board = Summary(runs, set()), Board()
    follow(summary, runs, board.reports())
    assert summary.running == {}
    assert board.report(runs[0].name, 0) is False and board.report(runs[1].name, 0) is False
    board.report(runs[0].name, 200)
    follow(summary, runs, board.reports())
    assert summary.running == {runs[0].name: 200, runs[1].name: 0}
    summary.finish(runs[0])
    follow(summary, runs[1:], board.reports())  # runs[0] no longer pending
    console = Console(width=120, record=True)
    console.print(summary)
    text = console.export_text()
    assert "1 done, 1 running, 1 left" in text
    cells = [[c.strip() for c in line.split("│")[1:3]] for line in text.splitlines() if line.startswith("│ paper-2")]
    assert dict(cells) == {runs[0].name: "done", runs[1].name: "running", runs[2].name: "queued"}, text
    board.ask()
    assert board.report(runs[2].name, 0) is True  # told to stop as it starts


def test_the_ray_backend_gets_the_runs_left_its_address_and_retries(base, finished, tmp_path, monkeypatch):
    """`reproduce --backend ray` hands the runs left to train, its --address and --retries to
    the Ray backend (``run_ray``, tested on a local Ray cluster in test_sweep.py: a killed
    worker retried, the numbers of the local backend); here they train in this process, and
    the grid's report follows with the numbers of the local backend."""
    calls = []

    def ray_here(todo, summary, address, retries):
        calls.append(([run.name for run in todo], address, retries))
        pool_module.train_runs(todo, summary, 1, keep_programs=True)

    monkeypatch.setattr(grid_module, "run_ray", ray_here)
    config = tiny_grid(
        tmp_path,
        scenarios=("paper-2",),
        algorithms=("maddpg",),
        backend="ray",
        jobs=None,
        retries=2,
        address="ray://x:1",
    )
    reproduce(config, base, live=False)
    assert calls == [([run.name for run in plan(config, base)], "ray://x:1", 2)]
    ours, local = (seed_rows(root / "runs" / "paper-2" / "maddpg" / "metrics.csv") for root in (tmp_path, finished))
    assert timeless(ours) == timeless(local)
    assert (tmp_path / "report.md").exists()


@pytest.mark.skipif(len(pool_module.usable_cpus()) < 2, reason="needs 2 CPUs")
def test_jobs_train_runs_side_by_side_to_the_numbers_of_one_process(base, finished, tmp_path, capsys):
    grid = tiny_grid(tmp_path, scenarios=("paper-2",), jobs=2)
    assert [len(share) for share in pool_module.cpu_shares(2)] == [1, 1]
    # a driver process, stopped by SIGTERM once both runs have written rows: each run keeps a checkpoint
    driver = multiprocessing.get_context("spawn").Process(target=reproduce, args=(grid, base), kwargs={"live": False})
    driver.start()
    metrics = [tmp_path / "runs" / "paper-2" / a / "metrics.csv" for a in ALGORITHMS]
    while not all(m.exists() for m in metrics[:2]) and driver.is_alive():
        time.sleep(0.2)
    os.kill(driver.pid, signal.SIGTERM)
    driver.join(timeout=CHILD_TIMEOUT)
    if driver.is_alive():  # not left running: the worker would wait for it at its exit
        driver.kill()
        pytest.fail(f"the grid did not stop within {CHILD_TIMEOUT} s of SIGTERM")
    assert driver.exitcode != 0 and not (tmp_path / "report.md").exists()
    assert all((m.parent / "checkpoint.npz").exists() for m in metrics[:2])
    reproduce(grid, base, live=False)  # resumes the interrupted runs, trains the rest, side by side
    for algorithm in ALGORITHMS:
        ours, theirs = (
            seed_rows(root / "runs" / "paper-2" / algorithm / "metrics.csv") for root in (tmp_path, finished)
        )
        assert timeless(ours) == timeless(theirs)
    for jobs in (0, len(pool_module.usable_cpus()) + 1):
        assert main(["reproduce", "--out", str(tmp_path), "--jobs", str(jobs)]) == 2
        assert f"--jobs must be in [1, {len(pool_module.usable_cpus())}]" in capsys.readouterr().err
    assert main(["reproduce", "--out", str(tmp_path), "--jobs", "1", "--backend", "ray"]) == 2
    assert "--jobs is for --backend local" in capsys.readouterr().err


@pytest.mark.skipif(len(pool_module.usable_cpus()) < 2, reason="needs 2 CPUs")
def test_a_failed_job_is_reported_with_its_own_error(base, tmp_path):
    """Both jobs fail at once (each folder held by a live writer): the error reported is the
    failed run's own, not whichever job's error reached the queue first."""
    runs = plan(tiny_grid(tmp_path, scenarios=("paper-2",), algorithms=("ddpg", "maddpg"), jobs=2), base)
    for run in runs:
        run.folder.mkdir(parents=True)
        (run.folder / ".lock").write_text(f"{os.getpid()} {socket.gethostname()}")  # this test: alive
    with pytest.raises(UserError) as stopped:  # a user's mistake (a folder in use): exit 2, not a crash
        pool_module.run_jobs(runs, pool_module.Summary(runs, set()), jobs=2)
    name = str(stopped.value).split("'")[1]
    folder = next(run.folder for run in runs if run.name == name)
    assert f"'{folder}' is being written by process {os.getpid()}" in str(stopped.value)


@pytest.mark.skipif(len(pool_module.usable_cpus()) < 2, reason="needs 2 CPUs")
def test_a_locked_job_stops_the_others_without_a_traceback(base, tmp_path, capfd):
    """One folder held by a live writer: its job fails at once, the other job (still starting)
    is asked to stop; the command ends in one line, exit 2, and no job prints a traceback."""
    grid = tiny_grid(tmp_path, scenarios=("paper-2",), algorithms=("ddpg", "maddpg"), jobs=2)
    locked = plan(grid, base)[0].folder
    locked.mkdir(parents=True)
    (locked / ".lock").write_text(f"{os.getpid()} {socket.gethostname()}")  # this test: alive
    with pytest.raises(UserError, match="is being written by process"):
        reproduce(grid, base, live=False)
    assert "Traceback" not in capfd.readouterr().err
    assert not (tmp_path / ".lock").exists()


@pytest.mark.skipif(len(pool_module.usable_cpus()) < 2, reason="needs 2 CPUs")
def test_repeated_signals_during_jobs_stop_them_once_with_a_message(tmp_path):
    """SIGTERM, then SIGINT and SIGTERM again while the jobs save: the first asks every job to
    stop at its next chunk, the others are ignored; the command ends with its message (exit 1),
    no traceback, every run keeps a checkpoint and the folder's lock is gone."""
    import subprocess
    import sys

    argv = ["reproduce", "--quick", "--scenarios", "paper-2", "--algorithms", "ddpg", "maddpg", "--seeds", "1"]
    argv += ["--episodes", "2000", "--jobs", "2", "--time-chunks", "0", "--out", str(tmp_path)]
    driver = subprocess.Popen(
        [sys.executable, "-m", "roverswarm.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    metrics = [tmp_path / "runs" / "paper-2" / a / "metrics.csv" for a in ("ddpg", "maddpg")]
    while not all(m.exists() for m in metrics) and driver.poll() is None:
        time.sleep(0.2)
    for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGTERM):
        driver.send_signal(signum)
        time.sleep(0.3)
    out, err = driver.communicate(timeout=600)
    assert driver.returncode == 1, err
    assert "Traceback" not in err and "interrupted; every running run saved a checkpoint" in err, err
    assert "stops at its next chunk" in out
    assert all((m.parent / "checkpoint.npz").exists() for m in metrics)
    assert not list(tmp_path.rglob(".lock"))


def test_a_signal_during_a_grid_in_this_process_is_answered_at_once(base, tmp_path, signal_at_chunk, capsys):
    """--jobs 1 trains in the command's own process, with no progress bar: a Ctrl-C is still
    announced when it comes (not only once the chunk has ended), and the run keeps its checkpoint."""
    disarm = signal_at_chunk(signal.SIGINT, chunk=2)
    try:
        with pytest.raises(RunStopped, match="interrupted at episode 200") as stopped:
            reproduce(tiny_grid(tmp_path, scenarios=("paper-2",), algorithms=("ddpg",)), base, live=False)
    finally:
        disarm()
    # the grid is resumed by its own command, not by resuming the one run (which writes no table)
    assert "rerun the same command to resume" in str(stopped.value) and "train --resume" not in str(stopped.value)
    assert " ".join(capsys.readouterr().err.split()).count("SIGINT: stopping after this chunk, with a checkpoint") == 1
    assert (tmp_path / "runs" / "paper-2" / "ddpg" / "checkpoint.npz").exists()


def test_default_jobs_follow_run_length_cpus_and_memory(base, tmp_path, monkeypatch):
    long = plan(tiny_grid(tmp_path, episodes=60_000), base)  # 6 runs, planned only
    short = plan(tiny_grid(tmp_path), base)
    cpus = len(pool_module.usable_cpus())
    assert pool_module.default_jobs(short) == 1  # start-up and compilation dominate short runs
    assert pool_module.default_jobs(long) == min(6, cpus)
    assert pool_module.default_jobs(long[:1]) == 1
    need = max(pool_module.run_memory(run.config) for run in long)
    monkeypatch.setattr(pool_module, "memory_limit", lambda: int(need / 0.8) + 1)  # room for one run only
    assert pool_module.default_jobs(long) == 1
