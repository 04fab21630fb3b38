"""95% intervals of a mean error: over test tosses (percentile bootstrap), over seeds (Student t), and of the
difference between two models scored on the same tosses (paired)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import stats

LEVEL = 0.95
RESAMPLES = 2000
# One fixed seed for every bootstrap: the same runs give the same intervals, byte for byte, in any order.
BOOTSTRAP_SEED = 0
# Resamples averaged at once: bounds the memory of a split with thousands of tosses.
_CHUNK = 250


@dataclass(frozen=True)
class Interval:
    low: float
    high: float
    over: str  # "tosses" (bootstrap over the test tosses) or "seeds" (Student t over the seeds' means)

    @property
    def width(self) -> float:
        return self.high - self.low

    def covers(self, value: float) -> bool:
        return self.low <= value <= self.high


@functools.lru_cache(maxsize=8)
def _draws(n: int) -> np.ndarray:
    """[RESAMPLES, n] toss indices drawn with replacement. Cached by n alone, so two models scored on the same n tosses
    are resampled alike: their difference is a paired bootstrap."""
    draws = np.random.default_rng(BOOTSTRAP_SEED).integers(0, n, size=(RESAMPLES, n), dtype=np.int32)
    draws.setflags(write=False)
    return draws


def over_tosses(values) -> Interval | None:
    """The percentile bootstrap interval of the mean of per-toss values [n]; None unless every toss has a finite one."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.size == 0 or not np.isfinite(values).all():
        return None
    draws = _draws(values.size)
    means = np.concatenate([values[draws[i : i + _CHUNK]].mean(axis=1) for i in range(0, RESAMPLES, _CHUNK)])
    tail = 100 * (1 - LEVEL) / 2
    low, high = np.percentile(means, [tail, 100 - tail])
    return Interval(float(low), float(high), "tosses")


def _t_interval(centre: float, variance_of_mean: float, dof: float) -> Interval:
    half = float(stats.t.ppf(1 - (1 - LEVEL) / 2, dof)) * float(np.sqrt(variance_of_mean))
    return Interval(centre - half, centre + half, "seeds")


def over_seeds(means) -> Interval | None:
    """The Student-t interval of the mean of the seeds' means; None with fewer than two seeds, or seeds that all
    scored the same (a model the seed does not change: its seeds say nothing about its uncertainty)."""
    means = np.asarray(means, dtype=float)
    if means.size < 2 or not np.isfinite(means).all() or means.var() == 0:
        return None
    return _t_interval(float(means.mean()), float(means.var(ddof=1)) / means.size, means.size - 1)


def wider(*intervals: Interval | None) -> Interval | None:
    """The widest of the intervals given (the first of equals), None if none is."""
    given = [interval for interval in intervals if interval is not None]
    return max(given, key=lambda interval: interval.width) if given else None


def _averaged(per_seed: list[np.ndarray] | None) -> np.ndarray | None:
    """Per-toss values averaged over seeds [n] (the seeds were scored on the same tosses); None if they were not."""
    if not per_seed or len({len(values) for values in per_seed}) != 1:
        return None
    return np.mean(np.stack(per_seed), axis=0)


def of_cell(per_seed: list[np.ndarray] | None, seed_means: list[float]) -> Interval | None:
    """A cell's interval: one seed, over its tosses; several, the wider of the interval over seeds' means and the one
    over tosses of the per-toss values averaged over the seeds. Seeds that barely differ would claim almost no
    uncertainty at all; the tosses still bound it."""
    averaged = _averaged(per_seed)
    return wider(over_seeds(seed_means), None if averaged is None else over_tosses(averaged))


def of_difference(
    a: list[np.ndarray] | None, b: list[np.ndarray] | None, a_means: list[float], b_means: list[float]
) -> Interval | None:
    """The interval of mean(a) - mean(b) for two models scored on the same tosses: a paired bootstrap over tosses of
    the per-toss differences (each model's values averaged over its seeds), and with several seeds on either side the
    wider of that and Welch's t-interval over the seeds' means. None when neither can be computed."""
    left, right = _averaged(a), _averaged(b)
    paired = None if left is None or right is None or len(left) != len(right) else over_tosses(left - right)
    a_means, b_means = np.asarray(a_means, dtype=float), np.asarray(b_means, dtype=float)
    seeds = None
    if max(a_means.size, b_means.size) > 1 and np.isfinite(a_means).all() and np.isfinite(b_means).all():
        # a side with one seed adds no variance term: its seed spread is unknown, not zero
        terms = [m.var(ddof=1) / m.size for m in (a_means, b_means) if m.size > 1]
        dofs = [m.size - 1 for m in (a_means, b_means) if m.size > 1]
        variance = float(sum(terms))
        if variance > 0:
            dof = variance**2 / sum(term**2 / dof for term, dof in zip(terms, dofs) if term > 0)
            seeds = _t_interval(float(a_means.mean() - b_means.mean()), variance, dof)
    return wider(seeds, paired)
