"""The paper's results from a finished grid: Table I, Figures 8 and 9, and a Markdown report.

Definitions (the paper's, made precise):

* *mean episode reward*: a 1000-episode row of ``metrics.csv`` (episode reward summed over
  the agents, averaged over the 1000 episodes, exploration noise on, as during training);
* *maximum mean episode reward* of a seed: the best of its rows over the run;
* *time per 1000 episodes*: a row's wall seconds (all seeds of the run together, vmapped);
  the first row of a run is left out, since it includes compilation.

* *last-window reward* of a seed: the mean of its rows over the last :data:`LAST_WINDOW`
  episodes (all rows of a shorter run), where the maximum rewards a lucky peak;
* *final policies*: every seed's policy at the end of training, evaluated deterministically on
  the same 1000 episodes as the random and oracle policies (normalised score, POIs observed,
  collisions, trap contacts), as in ``roverswarm sweep``.

Table I's relative changes compare each optimizer arm (MADDPG with the optimizer, one arm
per ``--variants`` reading; DDPG with it, if the grid has it) against its plain learner
(MADDPG; DDPG) at each N:
``100 * (mean_opt - mean_plain) / |mean_plain|``. The arms share their seeds (same
initialisation keys and layouts), so rewards are compared *paired*, seed by seed
(:func:`paired_change`): the 95% interval is the delta-method interval of the ratio of the
means from the per-seed residuals ``opt_s - ratio * plain_s`` (t with S - 1 degrees of
freedom), the p-value the paired two-sided t-test. A test *pooled across N* puts every N's
per-seed relative differences ``100 * (opt_s - plain_s) / |mean_plain|`` together (one-sample
t-test). Time, where the arms were timed back to back after training (``--time-chunks``,
:func:`time_arms`), pairs chunk j of each arm (:func:`paired_change`); otherwise it compares
the runs' own 1000-episode rows, unpaired (Welch's interval and test, :func:`relative_change`).
Those rows of one run are not independent, other load on the machine shifts them, and a
resumed run has one more row with compilation in it: read them as indicative.
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

from rich.console import Console

from roverswarm.algos.learner import ON_POLICY
from roverswarm.env.scenarios import get_scenario
from roverswarm.experiments.grid import OPTIMIZERS, GridRun, ReproduceConfig, optimizer_of, run_grid
from roverswarm.experiments.sweep import evaluation, table_row
from roverswarm.experiments.timing import chunk_seconds
from roverswarm.jaxcache import release_compiled_programs
from roverswarm.config import TrainConfig, config_to_json
from roverswarm.runs import METRICS, folder_lock, markdown_table, read_metrics, write_csv

PAPER_TABLE1: dict[int, tuple[float, float]] = {2: (1.42, 2.26), 3: (3.08, 2.50), 4: (4.71, 2.69), 5: (8.78, 1.79)}
"""The paper's Table I: N -> (% change in episode reward, % change in training time)."""

LABELS = {
    "ddpg": "DDPG",
    "ddpg-optimizer": "DDPG + optimizer",
    "maddpg": "MADDPG",
    "maddpg-optimizer": "MADDPG + optimizer",
    "mappo": "MAPPO",
    "ippo": "IPPO",
}

LAST_WINDOW = 5000
"""Episodes at the end of a run over which its last-window reward is averaged."""
TIMING = "timing.csv"


def label(algorithm: str) -> str:
    """A grid arm's name in tables and figures; an optimizer variant's is "MADDPG + optimizer (NAME)"
    (or "DDPG + optimizer (NAME)")."""
    if algorithm in LABELS:
        return LABELS[algorithm]
    optimizer = optimizer_of(algorithm)
    return f"{LABELS[optimizer]} ({algorithm.removeprefix(optimizer + '-')})"


def _order(algorithm: str) -> int:
    """Sort key of the arms: the order of :data:`LABELS`, optimizer variants where the
    optimizer is (a stable sort keeps them in the grid's order)."""
    return list(LABELS).index(optimizer_of(algorithm) or algorithm)


@dataclass(frozen=True)
class RunResult:
    """What the report needs from one run's ``metrics.csv``."""

    run: GridRun
    rovers: int
    episodes: np.ndarray  # [T] episodes at each row
    curves: np.ndarray  # [S, T] mean episode reward per seed and row
    chunk_seconds: np.ndarray  # [T - 1] wall seconds per 1000 episodes, first row left out
    timed: np.ndarray | None = None  # [C] seconds per 1000 episodes timed back to back (--time-chunks)

    @property
    def seconds(self) -> np.ndarray:
        """Seconds per 1000 episodes: timed back to back if it was, else the run's own rows."""
        return self.chunk_seconds if self.timed is None else self.timed

    @property
    def best(self) -> np.ndarray:
        """[S] maximum mean episode reward of each seed."""
        return self.curves.max(axis=1)

    @property
    def last(self) -> np.ndarray:
        """[S] mean episode reward of each seed over the last :data:`LAST_WINDOW` episodes."""
        return self.curves[:, self.episodes > self.episodes[-1] - LAST_WINDOW].mean(axis=1)


def load(run: GridRun, timed: dict[tuple[str, str], np.ndarray]) -> RunResult:
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
        timed=timed.get((run.scenario, run.algorithm)),
    )


def time_arms(config: ReproduceConfig, runs: list[GridRun]) -> dict[tuple[str, str], np.ndarray]:
    """(scenario, arm) -> seconds per 1000 episodes of ``config.grid_time_chunks`` chunks of every
    paper-learner arm, timed back to back per scenario (:func:`~roverswarm.experiments.timing.chunk_seconds`).
    Kept in ``timing.csv``: a scenario whose arms were all timed is not timed again."""
    chunks = config.grid_time_chunks
    path = config.out / TIMING
    timed: dict[tuple[str, str], list[float]] = {}
    if chunks == 0:
        return {}
    if path.exists():
        try:
            with open(path, newline="") as f:
                for row in csv.DictReader(f):
                    timed.setdefault((row["scenario"], row["arm"]), []).append(float(row["seconds_per_1000"]))
        except (ValueError, KeyError, TypeError):  # unreadable: time again
            timed = {}
    for scenario in config.scenarios:
        arms = [r for r in runs if r.scenario == scenario and r.config.learner.algo not in ON_POLICY]
        if all(len(timed.get((scenario, r.algorithm), [])) >= chunks for r in arms):
            continue
        Console().print(f"timing {scenario}: {len(arms)} arms x {chunks} chunks, back to back")
        for run, seconds in zip(arms, chunk_seconds([r.config for r in arms], chunks)):
            timed[(scenario, run.algorithm)] = [s * 1000 / run.config.log_every for s in seconds]
        rows = [
            {"scenario": s, "arm": a, "chunk": j, "seconds_per_1000": x}
            for (s, a), xs in timed.items()
            for j, x in enumerate(xs)
        ]
        write_csv(path, rows)
    return {key: np.array(xs) for key, xs in timed.items()}


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
    if vt + vc == 0:  # no spread: as paired_p says
        return change, change, change, 0.0 if change else 1.0
    df = (vt + vc) ** 2 / (vt**2 / (len(treated) - 1) + vc**2 / (len(control) - 1))
    ratio = treated.mean() / control.mean()
    se = np.sqrt(vt + ratio**2 * vc) / (100.0 * scale)  # delta method for mean_t / mean_c
    half = 100.0 * stats.t.ppf(0.975, df) * se
    p = stats.ttest_ind(treated, control, equal_var=False).pvalue
    return change, change - half, change + half, float(p)


def paired_change(treated: np.ndarray, control: np.ndarray) -> tuple[float, float, float, float]:
    """(% change of the means, 95% interval low, high, paired t-test p-value) of ``treated``
    against ``control``, matched element by element (the same seeds)."""
    treated, control = np.asarray(treated, float), np.asarray(control, float)
    change = 100.0 * (treated.mean() - control.mean()) / abs(control.mean())
    if len(treated) < 2:
        return change, float("nan"), float("nan"), float("nan")
    ratio = treated.mean() / control.mean()
    # delta method for mean_t / mean_c with paired samples: the residuals t_s - ratio * c_s
    se = np.std(treated - ratio * control, ddof=1) / np.sqrt(len(treated)) / abs(control.mean())
    half = 100.0 * stats.t.ppf(0.975, len(treated) - 1) * se
    return change, change - half, change + half, paired_p(treated - control)


def paired_p(differences: np.ndarray) -> float:
    """Two-sided one-sample t-test p-value of ``differences`` against 0. Differences without
    spread give 1 when all are 0 (the arms agree exactly) and 0 otherwise (the limit of the t-test),
    rather than the undefined 0/0."""
    differences = np.asarray(differences, float)
    if len(differences) < 2:
        return float("nan")
    if differences.std() == 0:
        return 0.0 if differences.any() else 1.0
    return float(stats.ttest_1samp(differences, 0.0).pvalue)


def pooled_change(pairs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[float, float, float, float]:
    """(mean, 95% interval low, high, p-value) of the per-seed relative differences
    ``100 * (treated_s - control_s) / |mean control|`` of every (treated, control) pair, pooled."""
    pooled = np.concatenate([100.0 * (t - c) / abs(np.mean(c)) for t, c in pairs])
    mean, half = mean_interval(pooled)
    return mean, mean - half, mean + half, paired_p(pooled)


def holm(p_values) -> np.ndarray:
    """Holm's step-down adjustment of ``p_values``, taken as one family (NaN entries are left
    out of it and stay NaN): each hypothesis's smallest family-wise error rate at which the
    procedure rejects it, ``max_{j <= i} min(1, (m - j + 1) p_(j))`` for the i-th smallest."""
    p = np.asarray(p_values, float)
    adjusted = np.full(p.shape, np.nan)
    tested = np.flatnonzero(np.isfinite(p))
    order = tested[np.argsort(p[tested], kind="stable")]
    scaled = np.minimum(1.0, (len(order) - np.arange(len(order))) * p[order])
    adjusted[order] = np.maximum.accumulate(scaled)
    return adjusted


TABLE1_COLUMNS = [
    "rovers",
    "arm",
    "against",
    "reward_change_pct",
    "reward_ci_low",
    "reward_ci_high",
    "reward_p",
    "reward_p_holm",
    "last_change_pct",
    "last_ci_low",
    "last_ci_high",
    "last_p",
    "paper_reward_change_pct",
    "time_change_pct",
    "time_ci_low",
    "time_ci_high",
    "time_p",
    "paper_time_change_pct",
]


def optimizer_pairs(results: list[RunResult]) -> list[tuple[int, RunResult, RunResult]]:
    """(N, optimizer arm, its plain learner) for every optimizer arm and N where both ran; the
    plain learner is the arm of :data:`~roverswarm.experiments.grid.OPTIMIZERS` (MADDPG for
    MADDPG + optimizer)."""
    by = {(r.rovers, r.run.algorithm): r for r in results}
    arms = list(dict.fromkeys(r.run.algorithm for r in results if optimizer_of(r.run.algorithm)))  # grid order
    runs = sorted(
        (r for r in results if r.run.algorithm in arms), key=lambda r: (arms.index(r.run.algorithm), r.rovers)
    )
    keys = ((r, (r.rovers, OPTIMIZERS[optimizer_of(r.run.algorithm)])) for r in runs)
    return [(r.rovers, r, by[key]) for r, key in keys if key in by]


def table1(results: list[RunResult]) -> list[dict[str, object]]:
    """One row per N and optimizer arm: Table I (maximum and last-window reward, paired; time)
    against the arm's plain learner, with intervals, p-values and the paper's values (for
    MADDPG + optimizer only: the paper's Table I compares it with MADDPG). ``reward_p_holm``
    adjusts the maximum-reward p-values for the table's many comparisons (:func:`holm`)."""
    rows = []
    for n, optimized, plain in optimizer_pairs(results):
        reward = paired_change(optimized.best, plain.best)
        last = paired_change(optimized.last, plain.last)
        if optimized.timed is not None and plain.timed is not None:  # chunk j of each ran back to back
            seconds = paired_change(optimized.timed, plain.timed)
        else:
            seconds = relative_change(optimized.chunk_seconds, plain.chunk_seconds)
        papers = PAPER_TABLE1 if plain.run.algorithm == "maddpg" else {}
        paper = papers.get(n, (float("nan"), float("nan")))
        arms = (label(optimized.run.algorithm), label(plain.run.algorithm))
        values = (n, *arms, *reward, float("nan"), *last, paper[0], *seconds, paper[1])
        rows.append(dict(zip(TABLE1_COLUMNS, values)))
    for row, adjusted in zip(rows, holm([r["reward_p"] for r in rows])):  # every arm and N: one family
        row["reward_p_holm"] = float(adjusted)
    return rows


def pooled_rows(results: list[RunResult]) -> list[dict[str, object]]:
    """Per optimizer arm: its change against its plain learner pooled across N, for the maximum
    and the last-window reward (:func:`pooled_change`)."""
    rows = []
    every = optimizer_pairs(results)
    for arm in dict.fromkeys(t.run.algorithm for _, t, _ in every):
        pairs = [(t, c) for _, t, c in every if t.run.algorithm == arm]
        best = pooled_change([(t.best, c.best) for t, c in pairs])
        last = pooled_change([(t.last, c.last) for t, c in pairs])
        rows.append({"arm": label(arm), "sizes": len(pairs), "best": best, "last": last})
    return rows


def _fmt(x: float, digits: int = 2, suffix: str = "") -> str:
    return "n/a" if not np.isfinite(x) else f"{x:+.{digits}f}{suffix}"


def _change(change: float, low: float, high: float, p: float) -> str:
    """A change with its interval and p-value as table cells."""
    return f"{_fmt(change)}% | [{_fmt(low)}, {_fmt(high)}] | {p:.3g}"


def table1_markdown(rows: list[dict[str, object]]) -> str:
    change = lambda r, part: _change(*(r[f"{part}_{k}"] for k in ("change_pct", "ci_low", "ci_high", "p")))  # noqa: E731
    header = [
        "N",
        "optimizer arm",
        "against",
        "max reward change (ours) | 95% CI | p | p, Holm",
        "last-window reward change | 95% CI | p",
    ]
    header += ["paper", "time per 1000 episodes change (ours) | 95% CI | p", "paper"]
    body = [
        [
            str(r["rovers"]),
            str(r["arm"]),
            str(r["against"]),
            f"{change(r, 'reward')} | {r['reward_p_holm']:.3g}",
            change(r, "last"),
            _fmt(r["paper_reward_change_pct"], suffix="%"),
            change(r, "time"),
            _fmt(r["paper_time_change_pct"], suffix="%"),
        ]
        for r in rows
    ]
    return markdown_table(header, body)


def pooled_markdown(rows: list[dict[str, object]]) -> str:
    header = ["optimizer arm", "sizes N", "max reward change, pooled | 95% CI | p"]
    header.append("last-window change, pooled | 95% CI | p")
    return markdown_table(
        header, [[str(r["arm"]), str(r["sizes"]), _change(*r["best"]), _change(*r["last"])] for r in rows]
    )


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
    algorithms = sorted(dict.fromkeys(r.run.algorithm for r in results), key=_order)
    width = 0.8 / len(algorithms)
    for k, algorithm in enumerate(algorithms):
        for ax, value in zip(axes[0], (lambda r: r.best, lambda r: r.seconds)):
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
                label=label(algorithm),
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
            ax.plot(r.episodes, mean, label=label(r.run.algorithm))
            ax.fill_between(r.episodes, mean - half, mean + half, alpha=0.2)
        ax.set_title(f"N = {n} ({results[0].run.config.seeds} seeds)")
        ax.set_xlabel("episodes")
        ax.set_ylabel("mean episode reward")
        ax.legend(fontsize=8)
    for j in range(len(sizes), rows * cols):
        axes[j // cols][j % cols].set_visible(False)
    fig.tight_layout()
    fig.savefig(path)


def verdicts(results: list[RunResult], rows: list[dict[str, object]]) -> list[str]:
    """Plain statements of whether the numbers support the paper's two claims."""
    lines = []
    family = sum(1 for r in rows if np.isfinite(r["reward_p"]))
    for arm in dict.fromkeys(r["arm"] for r in rows):
        mine = [r for r in rows if r["arm"] == arm]
        aside = "" if mine[0]["against"] == LABELS["maddpg"] else " (not a claim of the paper)"
        if len(mine) < 2:
            lines.append(f"- *{arm} helps more as N grows*{aside}: needs at least two swarm sizes with both arms.")
            continue
        sizes = [r["rovers"] for r in mine]
        changes = [r["reward_change_pct"] for r in mine]
        slope = float(np.polyfit(sizes, changes, 1)[0])
        gains = [r for r in mine if r["reward_change_pct"] > 0]
        significant = sum(1 for r in gains if r["reward_p_holm"] < 0.05)
        grows = slope > 0 and changes[-1] > 0
        lines.append(
            f"- *{arm} helps more as N grows*{aside}: "
            f"{'supported' if grows and significant else 'not supported'} by our runs. "
            f"Its maximum-reward change against {mine[0]['against']} goes "
            f"{', '.join(f'{c:+.1f}%' for c in changes)} for "
            f"N = {', '.join(map(str, sizes))} (trend {slope:+.2f} points per rover); {significant} of {len(mine)} "
            f"changes are positive with p < 0.05 (paired over seeds) after Holm's correction for the "
            f"{family} comparisons of Table I ({sum(1 for r in gains if r['reward_p'] < 0.05)} before it)."
        )
    if not rows:
        lines.append(
            "- *The optimizer helps more as N grows*: needs an optimizer arm and its plain learner at the same N."
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


def final_policies(results: list[RunResult], episodes: int, keep_programs: bool = False) -> list[dict[str, object]]:
    """Every run's final policies evaluated deterministically beside random and the oracle (kept
    in each run folder as ``evaluation.csv``): one row per run, every seed's score. Each
    run's rollout programs are released after it (with ``keep_programs``, only when crowded)."""
    rows = []
    for r in sorted(results, key=lambda r: (r.rovers, _order(r.run.algorithm))):
        row = table_row(r.run, evaluation(r.run, episodes))
        rows.append({"rovers": r.rovers, "arm": label(r.run.algorithm), **row})
        release_compiled_programs(only_if_crowded=keep_programs)
    return rows


def _final_markdown(rows: list[dict[str, object]]) -> str:
    header = ["N", "arm", "score, every seed", "mean score", "POIs observed", "collisions", "trap contacts (oracle)"]
    body = [
        [
            str(r["rovers"]),
            str(r["arm"]),
            str(r["scores"]),
            f"{r['mean_score']:.2f}",
            f"{r['pois_observed']:.2f}",
            f"{r['collisions']:.2f}",
            f"{r['trap_contacts']:.2f} ({r['oracle_trap_contacts']:.2f})",
        ]
        for r in rows
    ]
    return markdown_table(header, body)


def _arm_settings(results: list[RunResult]) -> list[str]:
    """One line per optimizer arm: its ranked replay's settings."""
    names = ("reading", "alpha", "beta", "refresh_every", "importance_weights", "importance_exponent")
    lines = {}
    for r in results:
        if optimizer_of(r.run.algorithm):
            replay = r.run.config.buffer
            options = ", ".join(f"{n}={getattr(replay, n)}" for n in names)
            lines.setdefault(r.run.algorithm, f"  - {label(r.run.algorithm)}: {options}")
    return [lines[a] for a in sorted(lines, key=_order)]


def write_report(
    config: ReproduceConfig,
    results: list[RunResult],
    rows: list[dict[str, object]],
    final: list[dict[str, object]],
    elapsed: float,
) -> Path:
    """``report.md``: settings, machine, versions, wall time, tables, figures and verdicts."""
    header = ["N", "arm", "max mean episode reward (mean, 95% CI)", "last-window reward (mean, 95% CI)"]
    header.append("s / 1000 episodes (mean, 95% CI)")
    body = []
    for r in sorted(results, key=lambda r: (r.rovers, _order(r.run.algorithm))):
        cells = [f"{m:.2f} ± {h:.2f}" for m, h in map(mean_interval, (r.best, r.last, r.seconds))]
        body.append([str(r.rovers), label(r.run.algorithm), *cells])
    per_run = markdown_table(header, body)
    training = sum(float(r.chunk_seconds.sum()) for r in results)
    shown = next((r.run for r in results if r.run.algorithm == "maddpg"), results[0].run)  # its config, in full
    example, example_label = shown.config, label(shown.algorithm)
    arms = ", ".join(label(a) for a in sorted(dict.fromkeys(r.run.algorithm for r in results), key=_order))
    if any(r.timed is not None for r in results):
        time_note = (
            f"Time: {config.grid_time_chunks} chunks of 1000 episodes (all seeds) per arm, timed back to back after "
            "training with the replay full, chunk j of each arm paired (`timing.csv`; on-policy arms: their rows)."
        )
    else:
        time_note = (
            "Time: one value per 1000-episode row of the run (all seeds together), the first row left out "
            "(Welch interval and test); other load on the machine while the runs trained shifts these."
        )
    text = f"""# roverswarm reproduce: the paper's Table I and Figures 8-9

## Settings
- Grid: scenarios {", ".join(config.scenarios)} x {arms}; \
{example.seeds} seeds per run (vmapped), {example.episodes} episodes per seed{" (--quick)" if config.quick else ""}; \
the paper's learners at `--preset {config.preset}`.
- Optimizer arms (the ranked replay's settings; the rest as their plain learner's):
{chr(10).join(_arm_settings(results))}
- {example_label}'s full training configuration (the grid sets scenario, algorithm, replay, episodes, seeds and \
seed; the rest is the same for every run of the paper's learners; MAPPO and IPPO start from their own presets, \
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

## Table I: the experience sample optimizer vs the same learner without it

{table1_markdown(rows)}
Relative changes of the means, `100 * (optimizer - plain) / |plain|`. Rewards: per seed, the maximum mean
episode reward and the mean over the last {LAST_WINDOW} episodes (training rows, noise on), compared paired
over the seeds the arms share (delta-method 95% intervals, paired t-test p-values). `p, Holm`: the
max-reward p-value adjusted by Holm's step-down method for all {len(rows)} rows of the table, one family
(the verdicts below count it).
{time_note}

Pooled across N (every seed's relative difference, one-sample t-test):

{pooled_markdown(pooled_rows(results))}
## Final policies, deterministic evaluation

Every seed's final policy on the same {config.grid_eval_episodes} episodes as the random (score 0)
and oracle (score 1) policies; normalised score `(R - R_random) / (R_oracle - R_random)`.

{_final_markdown(final)}
## Every run

{per_run}

## Figures

![Figure 8](fig8.png)

![Figure 9](fig9.png)

## Do our results support the paper's claims?

{chr(10).join(verdicts(results, rows))}
"""
    path = config.out / "report.md"
    path.write_text(text)
    return path


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
    final = final_policies(results, config.grid_eval_episodes, config.keep_programs)
    config.out.mkdir(parents=True, exist_ok=True)
    write_csv(config.out / "table1.csv", rows, TABLE1_COLUMNS)
    write_csv(config.out / "final_policies.csv", final)
    (config.out / "table1.md").write_text(table1_markdown(rows))
    figure8(results, config.out / "fig8.png")
    figure9(results, config.out / "fig9.png")
    return write_report(config, results, rows, final, time.perf_counter() - start)
