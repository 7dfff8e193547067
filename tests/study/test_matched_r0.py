"""``report.compare`` with ``matched_r0``: each compared group against the reference's budget of the nearest R0, on a
study folder written by hand: the chosen budget, the differences against a hand computation, the intervals against
an independent NumPy two-stage bootstrap, the pooled row, the checks of the study file and the line for a reference
budget without raw data."""

import copy
import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from sb3_spikeplastic.study import study_from_dict
from sb3_spikeplastic.study.intervals import bootstrap_mean_differences
from sb3_spikeplastic.study.layout import StudyFolder
from sb3_spikeplastic.study.report import auc_of, write_report

ENV = "CartPole-v1"
SIGMAS = [0.0, 0.2, 0.4]
#: The episodes of every (model, sigma): offsets around its mean, the same at every sigma (paired), mean 0.
OFFSETS = np.array([-2.0, -1.0, 1.0, 2.0])
#: Mean return at each sigma of each (variant, budget, seed). The reference's R0 is 100, 150 and 200 at 1k, 2k and
#: 3k; ``a`` starts at 145 (nearest: ref@2k), ``b`` at 110 (nearest: ref@1k), both pooled at 127.5 (ref@2k).
MEANS = {
    ("ref", 1000, 0): [90.0, 60.0, 40.0],
    ("ref", 1000, 1): [110.0, 70.0, 50.0],
    ("ref", 2000, 0): [140.0, 110.0, 90.0],
    ("ref", 2000, 1): [160.0, 120.0, 100.0],
    ("ref", 3000, 0): [190.0, 150.0, 120.0],
    ("ref", 3000, 1): [210.0, 170.0, 130.0],
    ("a", 3000, 0): [140.0, 135.0, 130.0],
    ("a", 3000, 1): [150.0, 140.0, 135.0],
    ("b", 3000, 0): [100.0, 95.0, 90.0],
    ("b", 3000, 1): [120.0, 110.0, 100.0],
}
LABELS = {1000: "1k", 2000: "2k", 3000: "3k"}
POOLED = "a + b@3k (pooled: a, b)"
RESAMPLES = 300
STUDY = {
    "conf": "cartpole.yml",
    "envs": [ENV],
    "seeds": [0, 1],
    "budgets": [3000],
    "variants": {"ref": {"budgets": [1000, 2000, 3000]}, "a": {}, "b": {}},
    "evaluations": {"robustness": {"noises": ["obs"], "sigmas": SIGMAS, "episodes": 4}},
    "report": {
        "learned_threshold": 50,
        "resamples": RESAMPLES,
        "compare": [
            {"variants": ["a", "b"], "against": "ref", "pooled": True},
            {"variants": ["a", "b"], "against": "ref", "pooled": True, "matched_r0": True},
        ],
    },
}


def episodes(means):
    """One seed's raw returns, shape (sigmas, episodes)."""
    return np.array([m + OFFSETS for m in means])


def write_study(root: Path) -> None:
    layout = StudyFolder(root)
    for (variant, budget, seed), means in MEANS.items():
        folder = layout.episodes_dir(ENV, variant, budget, seed)
        folder.mkdir(parents=True)
        with open(folder / "robustness_obs.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["model", "noise_type", "sigma", "episode", "return"])
            for sigma, row in zip(SIGMAS, episodes(means)):
                writer.writerows([f"{variant}@{LABELS[budget]}_s{seed}", "obs", sigma, k, r] for k, r in enumerate(row))


@pytest.fixture
def folder(files):
    root = files / "study"
    write_study(root)
    return root


def matched(folder):
    write_report(study_from_dict(STUDY, "synthetic.yml", folder.parent), folder, log=None)
    with open(folder / "verdicts.csv") as f:
        rows = list(csv.DictReader(f))
    return {r["model"]: r for r in rows if r["matched"] == "R0"}, (folder / "verdicts.md").read_text()


# The hand computation: per seed, the ratio 1 + (R - R0) / |R0| and its trapezoid area over the sigma range.


def area(means):
    r = [1 + (m - means[0]) / abs(means[0]) for m in means]
    return sum((r[i] + r[i + 1]) / 2 * (SIGMAS[i + 1] - SIGMAS[i]) for i in range(2)) / (SIGMAS[-1] - SIGMAS[0])


def seeds(variants, budget):
    return [MEANS[(v, budget, s)] for v in variants for s in (0, 1)]


def group(value, chosen):
    return np.mean([value(m) for m in chosen])


def numpy_bootstrap(a, b, statistic):
    """Two-stage percentile bootstrap of ``statistic(a) - statistic(b)`` in plain loops, with the draws in the
    order of the report's bootstrap (per replicate: the seeds of ``a`` then their episodes, then the same for
    ``b``; generator seeded 0)."""
    rng = np.random.default_rng(0)
    replicates = []
    for _ in range(RESAMPLES):
        values = []
        for data in (a, b):
            drawn = []
            for k in rng.integers(len(data), size=len(data)):
                drawn.append(data[k][:, rng.integers(data[k].shape[1], size=data[k].shape[1])].mean(axis=1))
            values.append(statistic(drawn))
        replicates.append(values[0] - values[1])
    return np.quantile(replicates, [0.025, 0.975])


def test_the_reference_budget_of_the_nearest_r0_and_the_differences(folder):
    rows, text = matched(folder)
    assert set(rows) == {"a@3k", "b@3k", POOLED}
    expected = {"a@3k": ("ref@2k", ["a"], 2000), "b@3k": ("ref@1k", ["b"], 1000), POOLED: ("ref@2k", ["a", "b"], 2000)}
    for model, (reference, variants, budget) in expected.items():
        r = rows[model]
        mine, ref = seeds(variants, 3000), seeds(["ref"], budget)
        assert (r["reference"], r["plain_reference"]) == (reference, "ref@3k")
        assert (int(r["seeds"]), int(r["reference_seeds"])) == (len(mine), 2)
        assert float(r["model_r0"]) == pytest.approx(group(lambda m: m[0], mine), abs=0.051)
        assert float(r["reference_r0"]) == pytest.approx(group(lambda m: m[0], ref), abs=0.051)
        d_r0 = group(lambda m: m[0], mine) - group(lambda m: m[0], ref)
        d_top = group(lambda m: m[-1], mine) - group(lambda m: m[-1], ref)
        d_auc = group(area, mine) - group(area, ref)
        assert float(r["r0_difference_estimate"]) == pytest.approx(d_r0, abs=0.051)
        assert float(r["return_at_sigma_0.4_difference_estimate"]) == pytest.approx(d_top, abs=0.051)
        assert float(r["auc_difference_estimate"]) == pytest.approx(d_auc, abs=5.1e-5)
    # a keeps about 0.96 of its R0, ref@2k about 0.80: resolved; its return at sigma 0.4 is higher too.
    assert rows["a@3k"]["auc_verdict"] == "loses less"
    assert rows["a@3k"]["return_verdict"] == "higher"
    assert "## at matched R0" in text
    assert "| a@3k | 145 | ref@2k | 150 | 2 vs 2 |" in text
    assert "| b@3k | 110 | ref@1k | 100 | 2 vs 2 |" in text
    assert f"| {POOLED} | 128 | ref@2k | 150 | 4 vs 2 |" in text
    # the plain table is that of the entry without matched_r0, once, against the reference of the same budget
    plain = text.split("## at matched R0")[0]
    assert plain.count("| a@3k | ref@3k |") == 1 and "ref@2k" not in plain


def test_the_intervals_are_those_of_the_two_stage_bootstrap(folder):
    rows, _ = matched(folder)
    sigmas = np.array(SIGMAS)

    def auc(per_seed):
        ratios = [1 + (m - m[0]) / abs(m[0]) for m in per_seed]
        return np.mean([np.trapezoid(r, sigmas) / (sigmas[-1] - sigmas[0]) for r in ratios])

    statistics = {
        "auc_difference": (auc, 4),
        "r0_difference": (lambda s: np.mean([m[0] for m in s]), 1),
        "return_at_sigma_0.4_difference": (lambda s: np.mean([m[-1] for m in s]), 1),
    }
    for model, variants, budget in (("b@3k", ["b"], 1000), (POOLED, ["a", "b"], 2000)):
        a = [episodes(m) for m in seeds(variants, 3000)]
        b = [episodes(m) for m in seeds(["ref"], budget)]
        for key, (statistic, digits) in statistics.items():
            low, high = numpy_bootstrap(a, b, statistic)
            assert float(rows[model][f"{key}_low"]) == pytest.approx(low, abs=0.51 * 10**-digits), (model, key)
            assert float(rows[model][f"{key}_high"]) == pytest.approx(high, abs=0.51 * 10**-digits), (model, key)
        # and the library's bootstrap on the same data gives the same
        (d_auc,) = bootstrap_mean_differences(a, b, [auc_of(SIGMAS)], n_resamples=RESAMPLES)
        assert float(rows[model]["auc_difference_low"]) == pytest.approx(d_auc.low, abs=1e-4)
        assert float(rows[model]["auc_difference_high"]) == pytest.approx(d_auc.high, abs=1e-4)


def test_a_reference_budget_without_raw_data_is_a_line(folder):
    for seed in (0, 1):
        shutil.rmtree(StudyFolder(folder).episodes_dir(ENV, "ref", 1000, seed))
    rows, text = matched(folder)
    assert rows["b@3k"]["reference"] == "ref@2k"  # the nearest of the budgets with data
    assert rows["b@3k"]["reference_budgets_without_data"] == "1k"
    assert "ref: no raw data at 1k (not trained or not evaluated yet); R0 matched among its other budgets." in text


def check(files, change):
    data = copy.deepcopy(STUDY)
    change(data)
    with pytest.raises(ValueError, match="^[^\n]*$") as error:
        study_from_dict(data, "synthetic.yml", files)
    return str(error.value)


def test_the_study_file_checks(files):
    def not_a_bool(d):
        d["report"]["compare"][1]["matched_r0"] = "yes"

    def no_robustness(d):
        d["evaluations"] = {"final": {"episodes": 4}}

    def one_budget(d):
        d["variants"]["ref"] = {}

    assert "matched_r0='yes' in synthetic.yml must be true or false" in check(files, not_a_bool)
    assert "matched_r0 in synthetic.yml needs a robustness evaluation" in check(files, no_robustness)
    assert "reference 'ref' is declared at one budget" in check(files, one_budget)
    study = study_from_dict(STUDY, "synthetic.yml", files)
    assert [c.matched_r0 for c in study.comparisons] == [False, True]
