"""The report's text: Table I and the pooled changes as Markdown, the verdicts on the paper's
claims, and ``report.md``."""

from __future__ import annotations

import os
import platform
import sys
from importlib import metadata
from pathlib import Path

import numpy as np

from roverswarm.config import config_to_json
from roverswarm.experiments.arms import OPTIMIZERS, ReproduceConfig, optimizer_of, run_rows
from roverswarm.experiments.results import LABELS, LAST_WINDOW, RunResult, arm_order, label, pooled_rows
from roverswarm.experiments.significance import mean_interval, relative_change
from roverswarm.runs import markdown_table, training_seconds
from roverswarm.storage import write_text


def _fmt(x: float, digits: int = 2, suffix: str = "") -> str:
    return "n/a" if not np.isfinite(x) else f"{x:+.{digits}f}{suffix}"


def _change(change: float, low: float, high: float, p: float) -> str:
    """A change with its interval and p-value as table cells."""
    return f"{_fmt(change)}% | [{_fmt(low)}, {_fmt(high)}] | {p:.3g}"


def table1_markdown(rows: list[dict[str, object]]) -> str:
    if not rows:
        pairs = ", ".join(f"{arm} beside {plain}" for arm, plain in OPTIMIZERS.items())
        return (
            f"No comparison: Table I sets an optimizer arm beside its plain learner at the same N ({pairs}); "
            "this grid has no such pair.\n"
        )
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


def _table1_notes(rows: list[dict[str, object]], results: list[RunResult], time_note: str) -> str:
    """What Table I's columns mean, and its changes pooled across N (for a table with rows)."""
    return f"""Relative changes of the means, `100 * (optimizer - plain) / |plain|`. Rewards: per seed, the maximum mean
episode reward and the mean over the last {LAST_WINDOW} episodes (training rows, noise on), compared paired
over the seeds the arms share (delta-method 95% intervals, paired t-test p-values). `p, Holm`: the
max-reward p-value adjusted by Holm's step-down method for all {len(rows)} rows of the table, one family
(the verdicts below count it).
{time_note}

Pooled across N (every seed's relative difference, one-sample t-test):

{pooled_markdown(pooled_rows(results))}"""


def verdicts(results: list[RunResult], rows: list[dict[str, object]]) -> list[str]:
    """Plain statements of whether the numbers support the paper's two claims."""
    lines = []
    family = sum(1 for r in rows if np.isfinite(r["reward_p"]))
    for arm in dict.fromkeys(r["arm"] for r in rows):
        mine = sorted((r for r in rows if r["arm"] == arm), key=lambda r: r["rovers"])
        aside = "" if mine[0]["against"] == LABELS["maddpg"] else " (not a claim of the paper)"
        if len(mine) < 2:
            lines.append(f"- *{arm} helps more as N grows*{aside}: needs at least two swarm sizes with both arms.")
            continue
        sizes = [r["rovers"] for r in mine]
        changes = [r["reward_change_pct"] for r in mine]
        slope = float(np.polyfit(sizes, changes, 1)[0])
        gains = [r for r in mine if r["reward_change_pct"] > 0]
        significant = sum(1 for r in gains if r["reward_p_holm"] < 0.05)
        # a rising trend that ends in a gain shown at the largest N (one at a small N says nothing of growth)
        grows = slope > 0 and changes[-1] > 0 and mine[-1]["reward_p_holm"] < 0.05
        lines.append(
            f"- *{arm} helps more as N grows*{aside}: "
            f"{'supported' if grows else 'not supported'} by our runs (that needs a rising trend and a gain "
            f"with p < 0.05 after Holm at the largest N). "
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
    return [lines[a] for a in sorted(lines, key=arm_order)]


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
    for r in sorted(results, key=lambda r: (r.rovers, arm_order(r.run.algorithm))):
        cells = [f"{m:.2f} ± {h:.2f}" for m, h in map(mean_interval, (r.best, r.last, r.seconds))]
        body.append([str(r.rovers), label(r.run.algorithm), *cells])
    per_run = markdown_table(header, body)
    training = sum(training_seconds(run_rows(r.run)) for r in results)  # every chunk as it was timed
    shown = next((r.run for r in results if r.run.algorithm == "maddpg"), results[0].run)  # its config, in full
    example, example_label = shown.config, label(shown.algorithm)
    arms = ", ".join(label(a) for a in sorted(dict.fromkeys(r.run.algorithm for r in results), key=arm_order))
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
- Grid: scenarios {", ".join(config.grid_scenarios)} x {arms}; \
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
{_table1_notes(rows, results, time_note) if rows else ""}
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
    write_text(path, text)
    return path
