"""Figures 8 and 9 of the paper from a grid's results: the optimizer's effect per N as bars,
and every arm's learning curves. Each returns its matplotlib figure (the report saves it)."""

from __future__ import annotations

import numpy as np

from roverswarm.experiments.results import RunResult, arm_order, label
from roverswarm.experiments.significance import mean_interval


def _figure(width: float, height: float, panels: tuple[int, int]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(*panels, squeeze=False)


def figure8(results: list[RunResult]):
    """(a) maximum mean episode reward and (b) time per 1000 episodes, per N and algorithm."""
    fig, axes = _figure(11, 4, (1, 2))
    sizes = sorted({r.rovers for r in results})
    algorithms = sorted(dict.fromkeys(r.run.algorithm for r in results), key=arm_order)
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
    return fig


def figure9(results: list[RunResult]):
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
    return fig
