"""The paper's results from a finished grid: each run's rows, and Table I's comparisons (the
statistics are :mod:`~roverswarm.experiments.significance`'s).

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

from dataclasses import dataclass

import numpy as np

from roverswarm.env.scenarios import get_scenario
from roverswarm.experiments.arms import OPTIMIZERS, GridRun, optimizer_of, run_rows
from roverswarm.experiments.significance import holm, paired_change, pooled_change, relative_change

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


def arm_order(algorithm: str) -> int:
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
    rows = run_rows(run)
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
    plain learner is the arm of :data:`~roverswarm.experiments.arms.OPTIMIZERS` (MADDPG for
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
