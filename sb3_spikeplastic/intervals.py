"""Bootstrap confidence intervals over training seeds and evaluation episodes.

A training seed is the experimental unit of an RL comparison, and each seed's model is evaluated on many episodes.
The two-stage bootstrap resamples the seeds with replacement and then, within each drawn seed, its episodes
(Davison & Hinkley 1997, *Bootstrap Methods and their Application*, §2.4 and §3.8), so that the interval carries
both the spread between seeds and the episode noise; the interval is the percentile interval of the replicated
statistic (Efron & Tibshirani 1993, *An Introduction to the Bootstrap*, ch. 13). With few seeds (3-5) the seed
stage dominates, and the interval is a rough one: Agarwal et al. 2021 (*Deep RL at the Edge of the Statistical
Precipice*) for why it is still better than a mean ± std.

Each seed's data is an array whose **last axis is the episode**; its leading axes (e.g. the noise levels) are
resampled with the same episode indices, which keeps paired measurements (the same seeded episode at every noise
level) paired.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

Statistic = Callable[[Sequence[np.ndarray]], float]


class Interval(NamedTuple):
    """A point estimate and its two-sided percentile bootstrap interval.

    :param estimate: the statistic of the data as measured.
    :param low: lower end of the interval.
    :param high: upper end of the interval.
    """

    estimate: float
    low: float
    high: float

    def excludes_zero(self) -> bool:
        """Whether zero lies outside the interval (a difference resolved at this level)."""
        return self.low > 0.0 or self.high < 0.0


def _check(groups: Sequence[np.ndarray], n_resamples: int, level: float) -> list[np.ndarray]:
    if not 0.0 < level < 1.0:
        raise ValueError(f"level={level!r} must lie strictly between 0 and 1")
    if isinstance(n_resamples, bool) or not isinstance(n_resamples, int) or n_resamples < 1:
        raise ValueError(f"n_resamples={n_resamples!r} must be an integer >= 1")
    arrays = [np.asarray(g, dtype=float) for g in groups]
    if not arrays:
        raise ValueError("no seeds: pass at least one array of episode values")
    if any(a.ndim == 0 or a.shape[-1] == 0 for a in arrays):
        raise ValueError(f"every seed needs at least one episode (last axis); shapes {[a.shape for a in arrays]}")
    return arrays


def resample(groups: Sequence[np.ndarray], rng: np.random.Generator) -> list[np.ndarray]:
    """One two-stage resample: as many seeds as given, drawn with replacement, each with its episodes (last axis)
    drawn with replacement, the same indices for every leading index."""
    drawn = rng.integers(len(groups), size=len(groups))
    out = []
    for k in drawn:
        data = groups[k]
        out.append(data[..., rng.integers(data.shape[-1], size=data.shape[-1])])
    return out


def _percentiles(replicates: np.ndarray, level: float) -> tuple[float, float]:
    replicates = replicates[np.isfinite(replicates)]
    if replicates.size == 0:
        return float("nan"), float("nan")
    tail = (1.0 - level) / 2.0
    low, high = np.quantile(replicates, [tail, 1.0 - tail])
    return float(low), float(high)


def bootstrap_interval(groups: Sequence[np.ndarray], statistic: Statistic, n_resamples: int = 2000,
                       level: float = 0.95, seed: int = 0) -> Interval:
    """Two-stage (seeds, then episodes) percentile bootstrap interval of ``statistic``.

    :param groups: one array per seed, episodes on the last axis.
    :param statistic: a function of a list of such arrays (the seeds) returning a number, e.g. the mean over seeds
        of each seed's mean return.
    :param n_resamples: bootstrap replicates.
    :param level: coverage of the interval, e.g. 0.95.
    :param seed: seed of the resampling generator (the interval is reproducible).
    :return: the statistic of ``groups`` and its interval.
    """
    arrays = _check(groups, n_resamples, level)
    rng = np.random.default_rng(seed)
    replicates = np.array([statistic(resample(arrays, rng)) for _ in range(n_resamples)])
    return Interval(float(statistic(arrays)), *_percentiles(replicates, level))


def bootstrap_difference(groups_a: Sequence[np.ndarray], groups_b: Sequence[np.ndarray], statistic: Statistic,
                         n_resamples: int = 2000, level: float = 0.95, seed: int = 0) -> Interval:
    """Interval of ``statistic(a) - statistic(b)`` for two independent sets of seeds (e.g. plastic vs static
    models), each resampled in two stages on its own.

    :param groups_a: one array per seed of the first set, episodes on the last axis.
    :param groups_b: the same for the second set.
    :param statistic: as in :func:`bootstrap_interval`.
    :param n_resamples: bootstrap replicates.
    :param level: coverage of the interval.
    :param seed: seed of the resampling generator.
    :return: the measured difference and its interval.
    """
    a, b = _check(groups_a, n_resamples, level), _check(groups_b, n_resamples, level)
    rng = np.random.default_rng(seed)
    replicates = np.array([statistic(resample(a, rng)) - statistic(resample(b, rng)) for _ in range(n_resamples)])
    return Interval(float(statistic(a) - statistic(b)), *_percentiles(replicates, level))
