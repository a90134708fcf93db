"""The statistics of Table I: intervals, paired and unpaired relative changes, pooled tests and
Holm's correction (see :mod:`roverswarm.experiments.results` for how they are used).

``scipy.stats`` is imported where it is used: half a second that every process importing the
experiments (each job of a grid or sweep, each CLI command) paid, most never comparing arms."""

from __future__ import annotations

import numpy as np


def mean_interval(x: np.ndarray) -> tuple[float, float]:
    """Mean and half-width of its 95% t-interval (nan with fewer than two samples)."""
    from scipy import stats

    x = np.asarray(x, float)
    if len(x) < 2:
        return float(np.mean(x)), float("nan")
    return float(np.mean(x)), float(stats.t.ppf(0.975, len(x) - 1) * stats.sem(x))


def relative_change(treated: np.ndarray, control: np.ndarray) -> tuple[float, float, float, float]:
    """(% change of the means, 95% interval low, high, Welch p-value) of treated vs control."""
    from scipy import stats

    treated, control = np.asarray(treated, float), np.asarray(control, float)
    scale = abs(control.mean()) / 100.0
    change = (treated.mean() - control.mean()) / scale
    if min(len(treated), len(control)) < 2:
        return change, float("nan"), float("nan"), float("nan")
    vt, vc = treated.var(ddof=1) / len(treated), control.var(ddof=1) / len(control)
    if vt + vc == 0:  # no spread: as paired_p says
        return change, change, change, 0.0 if change else 1.0
    ratio = treated.mean() / control.mean()
    vr = ratio**2 * vc  # the control's share of the ratio's variance (delta method for mean_t / mean_c)
    if vt + vr > 0:
        df = (vt + vr) ** 2 / (vt**2 / (len(treated) - 1) + vr**2 / (len(control) - 1))  # Welch's, of that sum
        half = 100.0 * stats.t.ppf(0.975, df) * np.sqrt(vt + vr) / (100.0 * scale)
    else:  # a treated arm at 0 without spread: the ratio is known exactly
        half = 0.0
    p = stats.ttest_ind(treated, control, equal_var=False).pvalue
    return change, change - half, change + half, float(p)


def paired_change(treated: np.ndarray, control: np.ndarray) -> tuple[float, float, float, float]:
    """(% change of the means, 95% interval low, high, paired t-test p-value) of ``treated``
    against ``control``, matched element by element (the same seeds)."""
    from scipy import stats

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
    from scipy import stats

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
