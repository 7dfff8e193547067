"""Two-stage bootstrap intervals: the episode stage alone matches the normal interval of a mean, the seed stage
widens it by the spread between seeds, coverage of a known mean, paired resampling, differences and bad input."""

import numpy as np
import pytest

from sb3_spikeplastic.intervals import Interval, bootstrap_difference, bootstrap_interval, resample


def grand_mean(groups):
    return float(np.mean([g.mean() for g in groups]))


def test_one_seed_gives_the_normal_interval_of_its_episode_mean():
    episodes = np.random.default_rng(1).normal(5.0, 2.0, size=400)
    interval = bootstrap_interval([episodes], grand_mean, n_resamples=4000)
    half_width = 1.96 * episodes.std() / np.sqrt(episodes.size)  # the normal approximation, 0.196 for sigma 2
    assert interval.estimate == pytest.approx(episodes.mean())
    assert interval.low == pytest.approx(episodes.mean() - half_width, abs=0.03)
    assert interval.high == pytest.approx(episodes.mean() + half_width, abs=0.03)


def test_seeds_that_disagree_widen_the_interval_beyond_the_episode_noise():
    rng = np.random.default_rng(2)
    seeds = [rng.normal(m, 0.1, size=100) for m in (0.0, 10.0, 20.0)]
    interval = bootstrap_interval(seeds, grand_mean, n_resamples=4000)
    # Means of three seed means drawn with replacement from {0, 10, 20}: all three seeds 0 has probability
    # 1/27 = 0.037 > 0.025 (all three 20 likewise), so the 95 % interval is [0, 20] up to the episode noise.
    assert interval.low == pytest.approx(0.0, abs=0.1) and interval.high == pytest.approx(20.0, abs=0.1)
    episodes_only = bootstrap_interval([np.concatenate(seeds)], grand_mean)  # seeds pooled as one
    assert interval.high - interval.low > 5 * (episodes_only.high - episodes_only.low)


def test_95_percent_interval_covers_a_known_mean_about_95_percent_of_the_time():
    rng = np.random.default_rng(3)
    covered = 0
    trials = 200
    for trial in range(trials):
        seeds = [rng.normal(1.0 + rng.normal(0.0, 0.5), 1.0, size=30) for _ in range(8)]
        interval = bootstrap_interval(seeds, grand_mean, n_resamples=400, seed=trial)
        covered += interval.low <= 1.0 <= interval.high
    # Percentile intervals undercover slightly with 8 seeds; far from 95 % (e.g. an episode-only interval, ~50 %)
    # would fail.
    assert 0.84 <= covered / trials <= 0.99


def test_leading_axes_are_resampled_with_the_same_episode_indices():
    episodes = np.arange(6.0)
    paired = np.stack([episodes, 10 * episodes])  # e.g. two noise levels of the same seeded episodes
    for drawn in resample([paired], np.random.default_rng(4)):
        np.testing.assert_array_equal(drawn[1], 10 * drawn[0])


def test_difference_of_two_independent_sets():
    rng = np.random.default_rng(5)
    a = [rng.normal(3.0, 1.0, size=200) for _ in range(5)]
    b = [rng.normal(1.0, 1.0, size=200) for _ in range(5)]
    difference = bootstrap_difference(a, b, grand_mean)
    assert difference.estimate == pytest.approx(grand_mean(a) - grand_mean(b))
    assert difference.low < difference.estimate < difference.high and difference.excludes_zero()
    same = bootstrap_difference(a, a, grand_mean)
    assert not same.excludes_zero()
    assert bootstrap_interval(a, grand_mean, seed=7) == bootstrap_interval(a, grand_mean, seed=7)  # reproducible


def test_a_constant_has_a_degenerate_interval():
    assert bootstrap_interval([np.full(10, 2.5), np.full(4, 2.5)], grand_mean) == Interval(2.5, 2.5, 2.5)


@pytest.mark.parametrize("kwargs, bad", [
    ({"level": 1.0}, "level=1.0"),
    ({"n_resamples": 0}, "n_resamples=0"),
    ({"groups": []}, "no seeds"),
    ({"groups": [np.ones(3), np.ones(0)]}, "(0,)"),
])
def test_bad_arguments_name_the_value(kwargs, bad):
    arguments = {"groups": [np.ones(3)], "statistic": grand_mean, **kwargs}
    with pytest.raises(ValueError, match=bad.replace("(", r"\(").replace(")", r"\)")):
        bootstrap_interval(**arguments)
