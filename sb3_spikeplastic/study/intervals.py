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

import functools
from collections.abc import Callable, Sequence
from typing import NamedTuple, Optional

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


def fmt(interval: Interval, digits: int = 0) -> str:
    """``estimate [low, high]`` with ``digits`` decimals: an interval in a report's table."""
    return f"{interval.estimate:.{digits}f} [{interval.low:.{digits}f}, {interval.high:.{digits}f}]"


def verdict(difference: Interval, above: str, below: str) -> str:
    """The word of a report's table for a difference: ``above`` where its interval lies above 0, ``below`` where
    it lies below, else ``not resolved``.

    :param difference: a difference and its interval.
    :param above: the word for a difference resolved above 0 (e.g. ``higher``).
    :param below: the word for a difference resolved below 0.
    """
    if difference.low > 0:
        return above
    if difference.high < 0:
        return below
    return "not resolved"


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
    drawn with replacement, the same indices for every leading index.

    Each drawn array is C-contiguous, episodes last, as in :func:`bootstrap_mean_intervals`: indexing the last axis
    of a 2-D array gives a Fortran-ordered one, whose mean over episodes numpy sums in another order (a different
    last bit), and the two would not give the same intervals."""
    drawn = rng.integers(len(groups), size=len(groups))
    out = []
    for k in drawn:
        data = groups[k]
        out.append(np.ascontiguousarray(data[..., rng.integers(data.shape[-1], size=data.shape[-1])]))
    return out


def _percentiles(replicates: np.ndarray, level: float) -> tuple[float, float]:
    replicates = replicates[np.isfinite(replicates)]
    if replicates.size == 0:
        return float("nan"), float("nan")
    tail = (1.0 - level) / 2.0
    low, high = np.quantile(replicates, [tail, 1.0 - tail])
    return float(low), float(high)


def bootstrap_interval(
    groups: Sequence[np.ndarray], statistic: Statistic, n_resamples: int = 2000, level: float = 0.95, seed: int = 0
) -> Interval:
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


def bootstrap_difference(
    groups_a: Sequence[np.ndarray],
    groups_b: Sequence[np.ndarray],
    statistic: Statistic,
    n_resamples: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> Interval:
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


@functools.lru_cache(maxsize=64)
def _draws(sizes: tuple[tuple[int, int], ...], n_resamples: int, seed: int) -> tuple[tuple[np.ndarray, ...], ...]:
    """The draws of ``n_resamples`` two-stage resamples in the order of :func:`resample`, for one set of seeds
    (``bootstrap_interval``) or two drawn in turn (``bootstrap_difference``): for each set of ``k`` seeds of ``n``
    episodes, the drawn seeds ``(R, k)`` and each drawn seed's episodes ``(R, k, n)``. They depend on the sizes
    and the seed alone, so every interval of the same sizes shares them."""
    rng = np.random.default_rng(seed)
    seeds = [np.empty((n_resamples, k), np.int64) for k, _ in sizes]
    episodes = [np.empty((n_resamples, k, n), np.int64) for k, n in sizes]
    for r in range(n_resamples):
        for i, (k, n) in enumerate(sizes):
            seeds[i][r] = rng.integers(k, size=k)
            for j in range(k):
                episodes[i][r, j] = rng.integers(n, size=n)
    for array in (*seeds, *episodes):
        array.flags.writeable = False
    return tuple(zip(seeds, episodes))


def _resampled_means(arrays: Sequence[np.ndarray], seeds: np.ndarray, episodes: np.ndarray) -> np.ndarray:
    """Each replicate's per-seed means over the resampled episodes, shape ``(R, k, *leading)``."""
    stacked = np.stack([a.reshape(-1, a.shape[-1]) for a in arrays])  # (k, L, n)
    rows = np.arange(stacked.shape[1])[None, None, :, None]
    gathered = stacked[seeds[:, :, None, None], rows, episodes[:, :, None, :]]  # (R, k, L, n), episodes last
    return gathered.mean(axis=-1).reshape(*seeds.shape, *arrays[0].shape[:-1])


def _means(arrays: Sequence[np.ndarray]) -> np.ndarray:
    return np.stack([a.mean(axis=-1) for a in arrays])


def _sizes(arrays: Sequence[np.ndarray]) -> Optional[tuple[int, int]]:
    """``(seeds, episodes)`` when every seed has the same shape (the vectorised path), else ``None``."""
    return (len(arrays), arrays[0].shape[-1]) if all(a.shape == arrays[0].shape for a in arrays) else None


MeanStatistic = Callable[[np.ndarray], np.ndarray]


def bootstrap_mean_intervals(
    groups: Sequence[np.ndarray],
    statistics: Sequence[MeanStatistic],
    n_resamples: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> list[Interval]:
    """:func:`bootstrap_interval` of statistics of the per-seed mean returns, all replicates at once.

    The draws are those of :func:`bootstrap_interval` with the same ``seed``, so each interval is the same; only
    the statistics' form differs: each maps per-seed means of shape ``(..., k, *leading)`` (``k`` seeds, the
    leading axes of each seed's data, e.g. sigma) to shape ``(...)``. The resampled means are computed once for
    all the statistics.

    :param groups: one array per seed, episodes on the last axis.
    :param statistics: vectorised functions of the per-seed means.
    :param n_resamples: bootstrap replicates.
    :param level: coverage of the intervals.
    :param seed: seed of the resampling generator.
    """
    arrays = _check(groups, n_resamples, level)
    sizes = _sizes(arrays)
    if sizes is None:
        return [
            bootstrap_interval(arrays, lambda s, f=f: float(f(_means(s))), n_resamples, level, seed) for f in statistics
        ]
    ((seeds, episodes),) = _draws((sizes,), n_resamples, seed)
    means, measured = _resampled_means(arrays, seeds, episodes), _means(arrays)
    return [Interval(float(f(measured)), *_percentiles(np.asarray(f(means), dtype=float), level)) for f in statistics]


def bootstrap_mean_differences(
    groups_a: Sequence[np.ndarray],
    groups_b: Sequence[np.ndarray],
    statistics: Sequence[MeanStatistic],
    n_resamples: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> list[Interval]:
    """:func:`bootstrap_difference` of statistics of the per-seed means (see :func:`bootstrap_mean_intervals`),
    with the same draws as :func:`bootstrap_difference`."""
    a, b = _check(groups_a, n_resamples, level), _check(groups_b, n_resamples, level)
    sizes_a, sizes_b = _sizes(a), _sizes(b)
    if sizes_a is None or sizes_b is None:
        return [
            bootstrap_difference(a, b, lambda s, f=f: float(f(_means(s))), n_resamples, level, seed) for f in statistics
        ]
    (seeds_a, eps_a), (seeds_b, eps_b) = _draws((sizes_a, sizes_b), n_resamples, seed)
    means_a, means_b = _resampled_means(a, seeds_a, eps_a), _resampled_means(b, seeds_b, eps_b)
    measured_a, measured_b = _means(a), _means(b)
    return [
        Interval(
            float(f(measured_a) - f(measured_b)), *_percentiles(np.asarray(f(means_a) - f(means_b), dtype=float), level)
        )
        for f in statistics
    ]


def robustness_difference_row(
    env: str,
    evaluation: str,
    noise: str,
    model: str,
    reference: str,
    seeds: int,
    reference_seeds: int,
    largest_sigma: float,
    differences: tuple[Interval, Interval, Interval],
) -> dict:
    """One row of ``verdicts.csv`` for a robustness comparison: the differences ``(AUC, return at the largest sigma,
    R0)`` of ``model`` minus ``reference`` with their intervals, and the verdict words of ``verdicts.md``."""
    d_auc, d_top, d_r0 = differences
    return dict(
        env=env,
        evaluation=evaluation,
        noise=noise,
        model=model,
        reference=reference,
        seeds=seeds,
        reference_seeds=reference_seeds,
        **{f"auc_difference_{k}": round(v, 4) for k, v in d_auc._asdict().items()},
        **{f"return_at_sigma_{largest_sigma:g}_difference_{k}": round(v, 1) for k, v in d_top._asdict().items()},
        **{f"r0_difference_{k}": round(v, 1) for k, v in d_r0._asdict().items()},
        auc_verdict=verdict(d_auc, "loses less", "loses more"),
        return_verdict=verdict(d_top, "higher", "lower"),
    )
