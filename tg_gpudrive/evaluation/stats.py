"""Rank correlation of a knob with a per-episode figure, with a bootstrap interval.

The flexibility claims ("a tighter beta gives larger gaps") are statements about the direction in
which a figure moves across the cells of a grid. Each cell's figure is a mean over its evaluated
episodes, so it carries evaluation noise; a correlation over a handful of cells says nothing unless
its interval excludes zero. `spearman_ci` resamples every cell's episodes with replacement
(`n_boot` times, seeded), recomputes each cell's mean and the Spearman correlation with the knob,
and returns the percentile interval of those correlations. A cell given as several runs (one
array of episodes per training seed) is resampled in two stages: its runs with replacement, then
each drawn run's episodes, and its figure is the mean of the drawn runs' means, so the interval
holds training noise too; a cell of one run holds evaluation noise only. `effect_ci` gives the
difference (and ratio) between two cells' figures with the same resampling. `paired_difference`
compares two policies on the same units (the CCE-gap of each agent under each), resampling the units.

Paired cells (`paired=True`): every run of every cell played the same agent-episodes (the same scenes,
agents and rollout seeds, in the same order), so an episode's values under two cells differ by the knob
and sampling, not by the scene. A resample then draws one set of episode indices and applies it to every
run of every cell (the training seeds are still drawn per cell): the interval holds the noise of which
episodes were played once, as a paired test does, rather than once per cell. Episodes without a finite
value in some run are left out of all of them, so every cell averages the same episodes.

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
        return _verdict(self.lo, self.hi, expected_sign)


def spearman_ci(knob: Sequence[float], samples: Sequence[np.ndarray], *, n_boot: int = 2000, level: float = 0.95,
                seed: int = 0, labels: Sequence[str] | None = None, statistic=None,
                paired: bool = False) -> RankCorrelation:
    """Spearman's rho between `knob[c]` and the figure of `samples[c]` (one 1-D array of per-episode
    values per cell c, or a list of them, one per run of the cell), with a `level` percentile
    interval from `n_boot` resamples of every cell (`cell_means`).

    With `statistic`, a cell's figure is not a mean: `samples[c]` is (n, d), one row per episode
    (e.g. its histogram counts; the rows of a cell's runs are pooled), and the figure is
    `statistic(sum of the rows)` ((..., d) -> (...)); a resample weights the rows by multinomial
    counts, so the sums of all resamples are one matrix product. `paired`: see the module docstring (not with a
    `statistic`)."""
    knob = np.asarray(knob, np.float64)
    if len(knob) != len(samples):
        raise ValueError(f"{len(knob)} knob values for {len(samples)} cells")
    names = [labels[c] if labels is not None else f"#{c}" for c in range(len(samples))]
    if statistic is not None:
        if paired:
            raise ValueError("spearman_ci: a statistic of pooled rows resamples each cell alone; paired needs none")
        pooled = [np.concatenate(as_runs(s)) for s in samples]
        return _spearman_ci_of(knob, pooled, statistic, n_boot, level, seed, labels)
    rng = np.random.default_rng(seed)
    cells, idx = _cells_of(samples, names, paired, n_boot, rng)
    means = np.empty((n_boot, len(cells)))
    points = np.empty(len(cells))
    for c, runs in enumerate(cells):
        points[c], means[:, c] = cell_means(runs, n_boot, rng, idx)
    return _interval(float(spearman(knob, points)), spearman(knob, means), len(cells), n_boot, level)


def as_runs(cell) -> list:
    """A cell's per-run arrays: a list (or tuple) of them as given, a bare array as one run."""
    return list(cell) if isinstance(cell, (list, tuple)) else [cell]


def _runs_of(cell, name: str) -> list[np.ndarray]:
    """A cell's finite episode values, one array per run (a bare array is one run)."""
    runs = [np.asarray(r, np.float64).ravel() for r in as_runs(cell)]
    runs = [r[np.isfinite(r)] for r in runs]
    if not runs or any(r.size == 0 for r in runs):
        raise ValueError(f"cell {name} has a run with no finite episode value")
    return runs


def _cells_of(samples, names, paired: bool, n_boot: int, rng: np.random.Generator):
    """Each cell's runs (`_runs_of`) and, when `paired`, the (n_boot, episodes) indices every run's resample
    draws (None otherwise); paired runs keep only the episodes finite in all of them."""
    if not paired:
        return [_runs_of(s, n) for s, n in zip(samples, names)], None
    cells = [[np.asarray(r, np.float64).ravel() for r in as_runs(s)] for s in samples]
    sizes = {len(r) for runs in cells for r in runs}
    if len(sizes) != 1:
        raise ValueError(f"paired cells need the same episodes in every run, got {sorted(sizes)} episodes "
                         f"in cells {', '.join(names)}")
    keep = np.logical_and.reduce([np.isfinite(r) for runs in cells for r in runs])
    cells = [_runs_of([r[keep] for r in runs], n) for runs, n in zip(cells, names)]
    n = int(keep.sum())
    return cells, rng.integers(0, n, (n_boot, n))


def cell_means(runs: Sequence[np.ndarray], n_boot: int, rng: np.random.Generator,
               idx: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """A cell's figure (the mean of its runs' episode means) and `n_boot` two-stage resamples of it:
    runs drawn with replacement, then each drawn run's episodes (with `idx` (n_boot, episodes), those
    episodes for every run: paired cells)."""
    point = float(np.mean([r.mean() for r in runs]))
    R = len(runs)
    pick = rng.integers(0, R, (n_boot, R)) if R > 1 else np.zeros((n_boot, 1), np.int64)
    if idx is not None:
        per_run = np.stack([r[idx].mean(axis=1) for r in runs], axis=1)  # (n_boot, R)
        return point, np.take_along_axis(per_run, pick, axis=1).mean(axis=1)
    means = np.empty((n_boot, R))
    for k in range(R):
        for j, r in enumerate(runs):
            rows = np.nonzero(pick[:, k] == j)[0]
            if rows.size:
                means[rows, k] = r[rng.integers(0, r.size, (rows.size, r.size))].mean(axis=1)
    return point, means.mean(axis=1)


@dataclasses.dataclass(frozen=True)
class Effect:
    """How a figure changes from cell `low` to cell `high`: both figures, their difference (high - low)
    and ratio (high / low) with percentile intervals."""
    low: float
    high: float
    diff: float
    diff_lo: float
    diff_hi: float
    ratio: float
    ratio_lo: float
    ratio_hi: float

    def verdict(self, expected_sign: int) -> str:
        """As RankCorrelation.verdict, for the difference."""
        return _verdict(self.diff_lo, self.diff_hi, expected_sign)


def effect_ci(low, high, *, n_boot: int = 2000, level: float = 0.95, seed: int = 0,
              labels: tuple[str, str] = ("low", "high"), paired: bool = False) -> Effect:
    """The difference and ratio of two cells' figures (each an array of episode values or a list of
    them, one per run), with `level` percentile intervals from `cell_means` resamples; `paired`: the
    cells played the same episodes (module docstring)."""
    rng = np.random.default_rng(seed)
    (runs_a, runs_b), idx = _cells_of([low, high], labels, paired, n_boot, rng)
    a, boot_a = cell_means(runs_a, n_boot, rng, idx)
    b, boot_b = cell_means(runs_b, n_boot, rng, idx)
    tail = 100 * (1 - level) / 2
    d_lo, d_hi = np.percentile(boot_b - boot_a, [tail, 100 - tail])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = boot_b / boot_a
        ratio = b / a if a != 0 else np.nan
    ratios = ratios[np.isfinite(ratios)]
    r_lo, r_hi = np.percentile(ratios, [tail, 100 - tail]) if ratios.size else (np.nan, np.nan)
    return Effect(a, b, b - a, float(d_lo), float(d_hi), float(ratio), float(r_lo), float(r_hi))


@dataclasses.dataclass(frozen=True)
class PairedDifference:
    n: int  # units (agents) compared
    mean_a: float
    mean_b: float
    diff: float  # mean of a - b over the units
    lo: float  # bootstrap percentile interval of diff
    hi: float
    median_diff: float
    share_a_greater: float  # units where a > b

    def verdict(self, expected_sign: int) -> str:
        """As RankCorrelation.verdict, for the paired difference."""
        return _verdict(self.lo, self.hi, expected_sign)


def paired_difference(a: Sequence[float], b: Sequence[float], *, n_boot: int = 2000, level: float = 0.95,
                      seed: int = 0) -> PairedDifference:
    """a - b over paired units (a[i] and b[i] measure the same unit), with the `level` percentile interval
    of the mean difference over `n_boot` resamples of the units (seeded)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise ValueError(f"paired_difference: two equal non-empty 1-d samples needed, got {a.shape} and {b.shape}")
    d = a - b
    rng = np.random.default_rng(seed)
    boot = d[rng.integers(0, d.size, (n_boot, d.size))].mean(axis=1)
    tail = 100 * (1 - level) / 2
    lo, hi = np.percentile(boot, [tail, 100 - tail])
    return PairedDifference(int(d.size), float(a.mean()), float(b.mean()), float(d.mean()), float(lo), float(hi),
                            float(np.median(d)), float((d > 0).mean()))


def _verdict(lo: float, hi: float, expected_sign: int) -> str:
    if np.isnan(lo) or np.isnan(hi):
        return "not shown"
    if expected_sign > 0 and lo > 0 or expected_sign < 0 and hi < 0:
        return "holds"
    if expected_sign > 0 and hi < 0 or expected_sign < 0 and lo > 0:
        return "reversed"
    return "not shown"


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
