"""Rank correlation of a knob with a per-episode figure, with a bootstrap interval.

The flexibility claims ("a tighter beta gives larger gaps") are statements about the direction in
which a figure moves across the cells of a grid. Each cell's figure is a mean over its evaluated
episodes, so it carries evaluation noise; a correlation over a handful of cells says nothing unless
its interval excludes zero. `spearman_ci` resamples every cell's episodes with replacement
(`n_boot` times, seeded), recomputes each cell's mean and the Spearman correlation with the knob,
and returns the percentile interval of those correlations. It measures only evaluation noise:
training noise (another seed per cell) is not in it.

Must not: decide a claim holds (the caller compares the interval with the expected sign), or drop
cells with no episodes silently (that is a ValueError naming the cell).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np


def average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of x along its last axis, ties sharing their mean rank (n is a grid's cells: the
    O(n^2) comparison is the plain definition and costs nothing here)."""
    x = np.asarray(x, np.float64)
    less = (x[..., None, :] < x[..., :, None]).sum(axis=-1)
    equal = (x[..., None, :] == x[..., :, None]).sum(axis=-1)
    return less + (equal + 1) / 2.0


def spearman(x: Sequence[float], y: np.ndarray) -> np.ndarray:
    """Spearman's rho of x (n,) with y (..., n): Pearson correlation of their average ranks.

    NaN where either side is constant (no order to correlate)."""
    rx = average_ranks(np.asarray(x, np.float64))
    ry = average_ranks(np.asarray(y, np.float64))
    rx = rx - rx.mean()
    ry = ry - ry.mean(axis=-1, keepdims=True)
    den = np.sqrt((rx * rx).sum() * (ry * ry).sum(axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (ry * rx).sum(axis=-1) / np.where(den > 0, den, 1.0), np.nan)


@dataclasses.dataclass(frozen=True)
class RankCorrelation:
    rho: float  # on the cells' means
    lo: float  # bootstrap percentile interval
    hi: float
    n_cells: int
    n_boot: int
    level: float

    def verdict(self, expected_sign: int) -> str:
        """'holds' when the interval lies on the expected side of 0, 'reversed' on the other side,
        'not shown' when it contains 0."""
        if np.isnan(self.lo) or np.isnan(self.hi):
            return "not shown"
        if expected_sign > 0 and self.lo > 0 or expected_sign < 0 and self.hi < 0:
            return "holds"
        if expected_sign > 0 and self.hi < 0 or expected_sign < 0 and self.lo > 0:
            return "reversed"
        return "not shown"


def spearman_ci(knob: Sequence[float], samples: Sequence[np.ndarray], *, n_boot: int = 2000, level: float = 0.95,
                seed: int = 0, labels: Sequence[str] | None = None, statistic=None) -> RankCorrelation:
    """Spearman's rho between `knob[c]` and the mean of `samples[c]` (one 1-D array of per-episode
    values per cell c), with a `level` percentile interval from `n_boot` resamples of every cell's
    episodes.

    With `statistic`, a cell's figure is not a mean: `samples[c]` is (n, d), one row per episode
    (e.g. its histogram counts), and the figure is `statistic(sum of the rows)` ((..., d) -> (...));
    a resample weights the rows by multinomial counts, so the sums of all resamples are one matrix
    product."""
    knob = np.asarray(knob, np.float64)
    if len(knob) != len(samples):
        raise ValueError(f"{len(knob)} knob values for {len(samples)} cells")
    if statistic is not None:
        return _spearman_ci_of(knob, samples, statistic, n_boot, level, seed, labels)
    cells = [np.asarray(s, np.float64).ravel() for s in samples]
    cells = [s[np.isfinite(s)] for s in cells]
    for c, s in enumerate(cells):
        if s.size == 0:
            name = labels[c] if labels is not None else f"#{c}"
            raise ValueError(f"cell {name} has no finite episode value to correlate")
    rho = float(spearman(knob, np.array([s.mean() for s in cells])))
    rng = np.random.default_rng(seed)
    means = np.empty((n_boot, len(cells)))
    for c, s in enumerate(cells):
        means[:, c] = s[rng.integers(0, s.size, (n_boot, s.size))].mean(axis=1)
    return _interval(rho, spearman(knob, means), len(cells), n_boot, level)


def _interval(rho: float, boot: np.ndarray, n_cells: int, n_boot: int, level: float) -> RankCorrelation:
    boot = boot[np.isfinite(boot)]
    tail = 100 * (1 - level) / 2
    lo, hi = (np.percentile(boot, [tail, 100 - tail]) if boot.size else (np.nan, np.nan))
    return RankCorrelation(rho, float(lo), float(hi), n_cells, n_boot, level)


def _spearman_ci_of(knob, samples, statistic, n_boot, level, seed, labels) -> RankCorrelation:
    """spearman_ci with a figure `statistic` of each cell's summed (resampled) rows."""
    cells = [np.asarray(s, np.float64) for s in samples]
    for c, s in enumerate(cells):
        if s.ndim != 2 or len(s) == 0:
            name = labels[c] if labels is not None else f"#{c}"
            raise ValueError(f"cell {name}: a statistic needs (episodes, d) rows, got shape {s.shape}")
    rho = float(spearman(knob, np.array([float(statistic(s.sum(0))) for s in cells])))
    rng = np.random.default_rng(seed)
    figs = np.empty((n_boot, len(cells)))
    for c, s in enumerate(cells):
        w = rng.multinomial(len(s), np.full(len(s), 1.0 / len(s)), size=n_boot)  # (n_boot, n) resample counts
        figs[:, c] = statistic(w @ s)
    return _interval(rho, spearman(knob, figs), len(cells), n_boot, level)
