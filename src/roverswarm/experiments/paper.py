"""The paper's results from a finished grid: Table I, Figures 8 and 9, and a Markdown report.

Definitions (the paper's, made precise):

* *mean episode reward*: a 1000-episode row of ``metrics.csv`` (episode reward summed over
  the agents, averaged over the 1000 episodes, exploration noise on, as during training);
* *maximum mean episode reward* of a seed: the best of its rows over the run;
* *time per 1000 episodes*: a row's wall seconds (all seeds of the run together, vmapped);
  the first row of a run is left out, since it includes compilation.

Table I's relative changes compare MADDPG with the optimizer against plain MADDPG at each N:
``100 * (mean_opt - mean_plain) / |mean_plain|``. Seeds are the samples for rewards,
1000-episode rows for time. The 95% interval is the delta-method interval of that ratio
(both means estimated) with Welch's degrees of freedom; the p-value is Welch's two-sided
t-test of the difference. The time rows of one run are not independent (and a resumed run
has one more row with compilation in it), so read the time intervals as indicative.
"""

from __future__ import annotations

import csv
import os
import platform
import sys
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np
from scipy import stats

from roverswarm.env.scenarios import get_scenario
from roverswarm.experiments.grid import GridRun, ReproduceConfig, run_grid
from roverswarm.config import REFERENCE, TrainConfig, config_to_json
from roverswarm.runs import METRICS, folder_lock, read_metrics

PAPER_TABLE1: dict[int, tuple[float, float]] = {2: (1.42, 2.26), 3: (3.08, 2.50), 4: (4.71, 2.69), 5: (8.78, 1.79)}
"""The paper's Table I: N -> (% change in episode reward, % change in training time)."""

LABELS = {
    "ddpg": "DDPG",
    "maddpg": "MADDPG",
    "maddpg-optimizer": "MADDPG + optimizer",
    "mappo": "MAPPO",
    "ippo": "IPPO",
}


@dataclass(frozen=True)
class RunResult:
    """What the report needs from one run's ``metrics.csv``."""

    run: GridRun
    rovers: int
    episodes: np.ndarray  # [T] episodes at each row
    curves: np.ndarray  # [S, T] mean episode reward per seed and row
    chunk_seconds: np.ndarray  # [T - 1] wall seconds per 1000 episodes, first row left out

    @property
    def best(self) -> np.ndarray:
        """[S] maximum mean episode reward of each seed."""
        return self.curves.max(axis=1)


def load(run: GridRun) -> RunResult:
    rows = read_metrics(run.folder / METRICS)
    seeds = sorted({int(r["seed"]) for r in rows})
    curves = np.array([[r["episode_reward"] for r in rows if int(r["seed"]) == s] for s in seeds])
    first = [r for r in rows if int(r["seed"]) == seeds[0]]
    per_1000 = np.array([r["wall_seconds"] for r in first]) * 1000 / run.config.log_every
    return RunResult(
        run=run,
        rovers=get_scenario(run.scenario).num_rovers,
        episodes=np.array([r["episodes"] for r in first]),
        curves=curves,
        chunk_seconds=per_1000[1:] if len(per_1000) > 1 else per_1000,
    )


def mean_interval(x: np.ndarray) -> tuple[float, float]:
    """Mean and half-width of its 95% t-interval (nan with fewer than two samples)."""
    x = np.asarray(x, float)
    if len(x) < 2:
        return float(np.mean(x)), float("nan")
    return float(np.mean(x)), float(stats.t.ppf(0.975, len(x) - 1) * stats.sem(x))


def relative_change(treated: np.ndarray, control: np.ndarray) -> tuple[float, float, float, float]:
    """(% change of the means, 95% interval low, high, Welch p-value) of treated vs control."""
    treated, control = np.asarray(treated, float), np.asarray(control, float)
    scale = abs(control.mean()) / 100.0
    change = (treated.mean() - control.mean()) / scale
    if min(len(treated), len(control)) < 2:
        return change, float("nan"), float("nan"), float("nan")
    vt, vc = treated.var(ddof=1) / len(treated), control.var(ddof=1) / len(control)
    if vt + vc == 0:
        return change, change, change, float("nan")
    df = (vt + vc) ** 2 / (vt**2 / (len(treated) - 1) + vc**2 / (len(control) - 1))
    ratio = treated.mean() / control.mean()
    se = np.sqrt(vt + ratio**2 * vc) / (100.0 * scale)  # delta method for mean_t / mean_c
    half = 100.0 * stats.t.ppf(0.975, df) * se
    p = stats.ttest_ind(treated, control, equal_var=False).pvalue
    return change, change - half, change + half, float(p)


TABLE1_COLUMNS = [
    "rovers",
    "reward_change_pct",
    "reward_ci_low",
    "reward_ci_high",
    "reward_p",
    "paper_reward_change_pct",
    "time_change_pct",
    "time_ci_low",
    "time_ci_high",
    "time_p",
    "paper_time_change_pct",
]


def table1(results: list[RunResult]) -> list[dict[str, float]]:
    """One row per N with both MADDPG variants: Table I with intervals, p-values and the paper's values."""
    by = {(r.rovers, r.run.algorithm): r for r in results}
    rows = []
    for n in sorted({r.rovers for r in results}):
        plain, optimized = by.get((n, "maddpg")), by.get((n, "maddpg-optimizer"))
        if plain is None or optimized is None:
            continue
        reward = relative_change(optimized.best, plain.best)
        seconds = relative_change(optimized.chunk_seconds, plain.chunk_seconds)
        paper = PAPER_TABLE1.get(n, (float("nan"), float("nan")))
        rows.append(dict(zip(TABLE1_COLUMNS, (n, *reward, paper[0], *seconds, paper[1]))))
    return rows


def _fmt(x: float, digits: int = 2, suffix: str = "") -> str:
    return "n/a" if not np.isfinite(x) else f"{x:+.{digits}f}{suffix}"


def table1_markdown(rows: list[dict[str, float]]) -> str:
    lines = [
        "| N | episode reward change (ours) | 95% CI | p | paper | time per 1000 episodes change "
        "(ours) | 95% CI | p | paper |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['rovers']} | {_fmt(r['reward_change_pct'])}% | [{_fmt(r['reward_ci_low'])}, "
            f"{_fmt(r['reward_ci_high'])}] "
            f"| {r['reward_p']:.3g} | {_fmt(r['paper_reward_change_pct'], suffix='%')} | {_fmt(r['time_change_pct'])}% "
            f"| [{_fmt(r['time_ci_low'])}, {_fmt(r['time_ci_high'])}] | {r['time_p']:.3g} | "
            f"{_fmt(r['paper_time_change_pct'], suffix='%')} |"
        )
    return "\n".join(lines) + "\n"


def _figure(width: float, height: float, panels: tuple[int, int]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(*panels, squeeze=False)


def figure8(results: list[RunResult], path: Path) -> None:
    """(a) maximum mean episode reward and (b) time per 1000 episodes, per N and algorithm."""
    fig, axes = _figure(11, 4, (1, 2))
    sizes = sorted({r.rovers for r in results})
    algorithms = [a for a in LABELS if any(r.run.algorithm == a for r in results)]
    width = 0.8 / len(algorithms)
    for k, algorithm in enumerate(algorithms):
        for ax, value in zip(axes[0], (lambda r: r.best, lambda r: r.chunk_seconds)):
            stats_ = [
                mean_interval(value(r))
                for n in sizes
                for r in results
                if r.rovers == n and r.run.algorithm == algorithm
            ]
            xs = [
                i + (k - (len(algorithms) - 1) / 2) * width
                for i, n in enumerate(sizes)
                if any(r.rovers == n and r.run.algorithm == algorithm for r in results)
            ]
            ax.bar(
                xs,
                [m for m, _ in stats_],
                width,
                yerr=[np.nan_to_num(h) for _, h in stats_],
                capsize=3,
                label=LABELS[algorithm],
            )
    for ax, title, ylabel in zip(
        axes[0],
        ("(a) maximum mean episode reward", "(b) time per 1000 episodes"),
        ("reward (mean over seeds, 95% CI)", "seconds (all seeds vmapped, 95% CI)"),
    ):
        ax.set_xticks(range(len(sizes)), [f"N = {n}" for n in sizes])
        ax.set_title(title)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)


def figure9(results: list[RunResult], path: Path) -> None:
    """Mean episode reward curves per N: mean over seeds with a 95% band, one line per algorithm."""
    sizes = sorted({r.rovers for r in results})
    cols = min(2, len(sizes))
    rows = -(-len(sizes) // cols)
    fig, axes = _figure(5.5 * cols, 3.8 * rows, (rows, cols))
    for i, n in enumerate(sizes):
        ax = axes[i // cols][i % cols]
        for r in (r for r in results if r.rovers == n):
            mean = r.curves.mean(axis=0)
            half = np.nan_to_num(np.array([mean_interval(c)[1] for c in r.curves.T]))
            ax.plot(r.episodes, mean, label=LABELS[r.run.algorithm])
            ax.fill_between(r.episodes, mean - half, mean + half, alpha=0.2)
        ax.set_title(f"N = {n} ({results[0].run.config.seeds} seeds)")
        ax.set_xlabel("episodes")
        ax.set_ylabel("mean episode reward")
        ax.legend(fontsize=8)
    for j in range(len(sizes), rows * cols):
        axes[j // cols][j % cols].set_visible(False)
    fig.tight_layout()
    fig.savefig(path)


def verdicts(results: list[RunResult], rows: list[dict[str, float]]) -> list[str]:
    """Plain statements of whether the numbers support the paper's two claims."""
    lines = []
    if len(rows) >= 2:
        sizes = [r["rovers"] for r in rows]
        changes = [r["reward_change_pct"] for r in rows]
        slope = float(np.polyfit(sizes, changes, 1)[0])
        significant = sum(1 for r in rows if r["reward_p"] < 0.05 and r["reward_change_pct"] > 0)
        grows = slope > 0 and changes[-1] > 0
        lines.append(
            "- *The optimizer helps more as N grows*: "
            f"{'supported' if grows and significant else 'not supported'} by our runs. "
            f"Its reward change goes {', '.join(f'{c:+.1f}%' for c in changes)} for N = {', '.join(map(str, sizes))} "
            f"(trend {slope:+.2f} points per rover); {significant} of {len(rows)} changes are positive with p < 0.05."
        )
    else:
        lines.append(
            "- *The optimizer helps more as N grows*: needs at least two swarm sizes with both MADDPG variants."
        )
    by = {(r.rovers, r.run.algorithm): r for r in results}
    pairs = [
        (n, by[(n, "maddpg")], by[(n, "ddpg")])
        for n in sorted({r.rovers for r in results})
        if (n, "maddpg") in by and (n, "ddpg") in by
    ]
    if pairs:
        count = sum(m.best.mean() > d.best.mean() for _, m, d in pairs)
        word = "supported" if count == len(pairs) else ("partly supported" if count else "not supported")
        lines.append(
            f"- *MADDPG beats DDPG*: {word}; MADDPG's maximum mean episode reward vs DDPG's: {_changes(pairs)}."
        )
    for arm in ("mappo", "ippo"):
        beside = [
            (n, by[(n, arm)], by[(n, "maddpg")]) for n in sorted(n for n, a in by if a == arm and (n, "maddpg") in by)
        ]
        if beside:
            lines.append(
                f"- *Beside the paper, {LABELS[arm]} vs MADDPG* (not a claim of the paper; {LABELS[arm]} trains "
                f"from its own preset): maximum mean episode reward change {_changes(beside)}."
            )
    return lines


def _changes(pairs: list[tuple[int, RunResult, RunResult]]) -> str:
    """Per (N, treated, control): the relative change of the maximum mean episode reward and its p-value."""
    changes = ((n, relative_change(treated.best, control.best)) for n, treated, control in pairs)
    return "; ".join(f"N = {n}: {c[0]:+.1f}% (p = {c[3]:.2g})" for n, c in changes)


def _versions() -> str:
    names = ("roverswarm", "jax", "jaxlib", "flax", "optax", "numpy", "scipy")
    found = []
    for name in names:
        try:
            found.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    return ", ".join([f"python {sys.version.split()[0]}", *found])


def write_report(
    config: ReproduceConfig, results: list[RunResult], rows: list[dict[str, float]], elapsed: float
) -> Path:
    """``report.md``: settings, machine, versions, wall time, tables, figures and verdicts."""
    per_run = [
        "| N | algorithm | max mean episode reward (mean, 95% CI) | s / 1000 episodes (mean, 95% CI) |",
        "|---|---|---|---|",
    ]
    for r in sorted(results, key=lambda r: (r.rovers, list(LABELS).index(r.run.algorithm))):
        (m, h), (t, th) = mean_interval(r.best), mean_interval(r.chunk_seconds)
        per_run.append(f"| {r.rovers} | {LABELS[r.run.algorithm]} | {m:.2f} ± {h:.2f} | {t:.2f} ± {th:.2f} |")
    training = sum(float(r.chunk_seconds.sum()) for r in results)
    example = results[0].run.config
    text = f"""# roverswarm reproduce: the paper's Table I and Figures 8-9

## Settings
- Grid: scenarios {", ".join(config.scenarios)} x {", ".join(LABELS[a] for a in config.algorithms)}; \
{example.seeds} seeds per run (vmapped), {example.episodes} episodes per seed{" (--quick)" if config.quick else ""}.
- One run's full training configuration (the grid sets scenario, algorithm, replay, episodes, seeds and seed; \
the rest is the same for every run of the paper's learners; MAPPO and IPPO start from their own presets, \
stored in their runs' `config.json`):

```json
{config_to_json(example)}
```

## Machine
- {platform.platform()}, {os.cpu_count()} CPUs, {platform.processor() or platform.machine()}
- {_versions()}
- Wall time of this command: {elapsed / 60:.1f} min (runs finished by an earlier, interrupted command not \
counted); training time recorded in the runs' metrics (all runs, all chunks, whichever command ran them): \
{training / 60:.1f} min.

## Table I: MADDPG + experience sample optimizer vs MADDPG

{table1_markdown(rows)}
Relative changes of the means, `100 * (optimizer - plain) / |plain|`; 95% delta-method intervals (Welch df);
two-sided Welch t-test p-values. Rewards: one maximum mean episode reward per seed.
Time: one value per 1000-episode row (all seeds together), the first row of each run left out.

## Every run

{chr(10).join(per_run)}

## Figures

![Figure 8](fig8.png)

![Figure 9](fig9.png)

## Do our results support the paper's claims?

{chr(10).join(verdicts(results, rows))}
"""
    path = config.out / "report.md"
    path.write_text(text)
    return path


def reproduce(config: ReproduceConfig, base: TrainConfig = REFERENCE, live: bool = True) -> Path:
    """Run (or finish) the grid, then write table1.md/.csv, fig8.png, fig9.png and report.md.

    ``base`` holds the training settings of every run (default: the paper's); the grid sets
    its scenario, algorithm, replay, episodes, seeds and seed. One writer at a time: the
    folder is locked while the grid runs."""
    with folder_lock(Path(config.out)):
        return _reproduce(config, base, live)


def _reproduce(config: ReproduceConfig, base: TrainConfig, live: bool) -> Path:
    start = time.perf_counter()
    runs = run_grid(config, base, live=live)
    results = [load(run) for run in runs]
    rows = table1(results)
    config.out.mkdir(parents=True, exist_ok=True)
    with open(config.out / "table1.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=TABLE1_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    (config.out / "table1.md").write_text(table1_markdown(rows))
    figure8(results, config.out / "fig8.png")
    figure9(results, config.out / "fig9.png")
    return write_report(config, results, rows, time.perf_counter() - start)
