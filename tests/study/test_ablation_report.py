"""``ablation_<evaluation>.md/.csv`` of ``sb3-spikeplastic study report``: an ablated evaluation against its plain
counterpart, from raw files written by hand: the differences plain - ablated by hand, the paired two-stage bootstrap
interval against an independent NumPy loop, the pooled row of the plastic variants, a model without its ablated file
listed as missing, and the one-line errors of ``against``."""

import copy
import csv
import json

import numpy as np
import pytest

from sb3_spikeplastic.study import study_from_dict
from sb3_spikeplastic.study.ablation_report import counterpart
from sb3_spikeplastic.study.layout import StudyFolder
from sb3_spikeplastic.study.report import write_report

ENV = "TMazeReversal-v0"
RESAMPLES = 400
SIGMAS = [0.0, 0.2, 0.4]
#: Final evaluation: (plain returns, frozen returns) of each model's 4 episodes. linear seed 0 loses exactly 3 in
#: every episode (a paired interval of [3, 3]); linear seed 1 has no frozen file.
FINAL = {
    ("oja", 0): ([10, 12, 14, 16], [4, 6, 5, 9]),
    ("oja", 1): ([20, 20, 22, 22], [20, 19, 23, 18]),
    ("linear", 0): ([5, 9, 7, 11], [2, 6, 4, 8]),
    ("linear", 1): ([30, 30, 30, 30], None),
    ("static", 0): ([1, 2, 3, 4], [1, 2, 3, 4]),
    ("static", 1): ([1, 2, 3, 4], [1, 2, 3, 4]),
    ("mlp", 0): ([5, 5, 5, 5], [5, 5, 5, 5]),
    ("mlp", 1): ([5, 5, 5, 5], [5, 5, 5, 5]),
}
#: Every model's success and ``good_choice`` at each step of its 4 episodes, plain and frozen.
SUCCESS = {"plain": [1, 0, 1, 1], "frozen": [0, 0, 1, 0]}
GOOD = {"plain": [[1, 1], [1, 0, 1, 1], [0], [1, 1, 1]], "frozen": [[0, 1], [0, 0, 0, 1], [1], [0, 0, 0]]}
#: Robustness: each model's mean return at each sigma, plain and frozen; linear seed 1 did not learn (R0 30 < 50).
MEANS = {
    ("oja", 0): ([100, 90, 70], [80, 60, 40]),
    ("oja", 1): ([120, 110, 100], [120, 100, 80]),
    ("linear", 0): ([110, 100, 90], [100, 90, 80]),
    ("linear", 1): ([30, 30, 30], [30, 20, 10]),
    ("static", 0): ([100, 90, 80], [100, 90, 80]),
    ("static", 1): ([100, 90, 80], [100, 90, 80]),
    ("mlp", 0): ([100, 90, 80], [100, 90, 80]),
    ("mlp", 1): ([100, 90, 80], [100, 90, 80]),
}
#: The episodes around each mean: paired (episode k is the same seeded episode plain and frozen), other offsets.
OFFSETS = {"plain": [-2.0, -1.0, 1.0, 2.0], "frozen": [2.0, -2.0, 1.0, -1.0]}
FINAL_EVAL = {"episodes": 4, "seed": 100, "info_keys": ["good_choice"]}
ROBUSTNESS = {"kind": "robustness", "noises": ["obs"], "sigmas": SIGMAS, "episodes": 4}
STUDY = {
    "envs": [ENV],
    "seeds": [0, 1],
    "budgets": [1000],
    "variants": {
        "static": {"rule": "static"},
        "oja": {"rule": "dp-oja"},
        "linear": {"rule": "dp-linear"},
        "mlp": {"conf": "mlp"},
    },
    "evaluations": {
        "final": FINAL_EVAL,
        "frozen": {**FINAL_EVAL, "kind": "final", "ablation": "frozen"},
        "robustness": ROBUSTNESS,
        "noise-frozen": {**ROBUSTNESS, "ablation": "frozen"},
    },
    "report": {"learned_threshold": 50, "resamples": RESAMPLES},
}


def write_final(path, returns, which):
    rows = [[k, r, len(GOOD[which][k]), SUCCESS[which][k], json.dumps(GOOD[which][k])] for k, r in enumerate(returns)]
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([["episode", "return", "length", "success", "steps:good_choice"], *rows])


def write_robustness(path, model, means, which):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "noise_type", "sigma", "episode", "return"])
        for sigma, mean in zip(SIGMAS, means):
            writer.writerows([model, "obs", sigma, k, mean + o] for k, o in enumerate(OFFSETS[which]))


def write_study(folder, means):
    """The raw files written by hand (robustness means ``means``) and the study's report: the report's folder."""
    for (variant, seed), (plain, frozen) in FINAL.items():
        out = StudyFolder(folder).episodes_dir(ENV, variant, 1000, seed)
        out.mkdir(parents=True)
        write_final(out / "final.csv", plain, "plain")
        if frozen is not None:
            write_final(out / "frozen.csv", frozen, "frozen")
        model = f"{variant}@1k_s{seed}"
        write_robustness(out / "robustness_obs.csv", model, means[(variant, seed)][0], "plain")
        write_robustness(out / "noise-frozen_obs.csv", model, means[(variant, seed)][1], "frozen")
    write_report(study_from_dict(STUDY, "synthetic.yml"), folder, log=None)
    return folder


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    return write_study(tmp_path_factory.mktemp("ablation") / "study", MEANS)


def rows_of(path):
    with open(path) as f:
        return {r["model"]: r for r in csv.DictReader(f)}


def paired_interval(seeds, statistic):
    """The independent paired two-stage bootstrap: per replicate, the seeds drawn with replacement, then each drawn
    seed's episodes, the same episode indices for its plain and frozen data; the 2.5 and 97.5 percentiles of the
    mean over drawn seeds of ``statistic(plain means, frozen means)``."""
    rng = np.random.default_rng(0)
    replicates = []
    for _ in range(RESAMPLES):
        drawn = rng.integers(len(seeds), size=len(seeds))
        values = []
        for k in drawn:
            plain, frozen = seeds[k]
            idx = rng.integers(plain.shape[-1], size=plain.shape[-1])
            values.append(statistic(plain[..., idx].mean(axis=-1), frozen[..., idx].mean(axis=-1)))
        replicates.append(np.mean(values))
    return np.quantile(replicates, [0.025, 0.975])


def final_seeds(models):
    return [tuple(np.array(FINAL[m][i], dtype=float) for i in (0, 1)) for m in models]


def test_final_differences_by_hand(report):
    rows = rows_of(report / "ablation_frozen.csv")
    # Only the spiking plastic groups and their pool: static and mlp have no row.
    assert list(rows) == ["oja@1k", "linear@1k", "plastic@1k (pooled: oja, linear)"]
    oja, linear, pooled = rows.values()
    # oja: seed means 13 vs 6 and 21 vs 20: plain 17, frozen 13, difference 4.
    assert float(oja["return_plain"]) == pytest.approx(17)
    assert float(oja["return_ablated"]) == pytest.approx(13)
    assert float(oja["return_difference_estimate"]) == pytest.approx(4)
    assert oja["seeds"] == "2" and linear["seeds"] == "1"  # linear seed 1 has no frozen file
    # linear seed 0 loses 3 in every episode: the paired interval is [3, 3], resolved.
    assert [float(linear[f"return_difference_{k}"]) for k in ("estimate", "low", "high")] == pytest.approx([3, 3, 3])
    assert linear["return_verdict"] == "frozen: lower"
    # Pooled over oja seeds 0, 1 and linear seed 0: (7 + 1 + 3) / 3.
    assert float(pooled["return_difference_estimate"]) == pytest.approx(11 / 3)
    assert pooled["seeds"] == "3"
    # Success 3/4 plain, 1/4 frozen; good_choice's episode means 0.6875 plain, 0.4375 frozen, for every model.
    for row in rows.values():
        assert float(row["success_difference_estimate"]) == pytest.approx(0.5)
        assert float(row["mean_good_choice_plain"]) == pytest.approx(0.6875)
        assert float(row["mean_good_choice_difference_estimate"]) == pytest.approx(0.25)


@pytest.mark.parametrize(
    "label, models",
    [
        ("oja@1k", [("oja", 0), ("oja", 1)]),
        ("plastic@1k (pooled: oja, linear)", [("oja", 0), ("oja", 1), ("linear", 0)]),
    ],
)
def test_final_paired_interval(report, label, models):
    row = rows_of(report / "ablation_frozen.csv")[label]
    low, high = paired_interval(final_seeds(models), lambda p, f: p - f)
    assert float(row["return_difference_low"]) == pytest.approx(low, abs=1e-5)
    assert float(row["return_difference_high"]) == pytest.approx(high, abs=1e-5)
    assert low < float(row["return_difference_estimate"]) < high
    expected = "frozen: lower" if low > 0 else "frozen: higher" if high < 0 else "not resolved"
    assert row["return_verdict"] == expected


def auc(means):
    """The trapezoid area under 1 + (R - R0) / |R0| over the sigma range."""
    r = [1 + (m - means[0]) / abs(means[0]) for m in means]
    return sum((r[i] + r[i + 1]) / 2 * (SIGMAS[i + 1] - SIGMAS[i]) for i in range(len(r) - 1)) / SIGMAS[-1]


def test_robustness_differences_and_paired_interval(report):
    rows = rows_of(report / "ablation_noise-frozen.csv")
    assert list(rows) == ["oja@1k", "linear@1k", "plastic@1k (pooled: oja, linear)"]
    oja, linear = rows["oja@1k"], rows["linear@1k"]
    assert oja["noise"] == "obs" and oja["against"] == "robustness"
    assert float(oja["r0_difference_estimate"]) == pytest.approx(((100 - 80) + (120 - 120)) / 2)
    assert float(oja["return_at_sigma_0.4_difference_estimate"]) == pytest.approx(((70 - 40) + (100 - 80)) / 2)
    # AUC by hand: seed 0 0.875 - 0.75, seed 1 0.91667 - 0.83333.
    assert auc(MEANS[("oja", 0)][0]) == pytest.approx(0.875) and auc(MEANS[("oja", 0)][1]) == pytest.approx(0.75)
    assert float(oja["auc_difference_estimate"]) == pytest.approx((0.125 + 1 / 12) / 2, abs=1e-6)
    # linear seed 1 did not learn (plain R0 30): left out, linear keeps one seed.
    assert linear["seeds"] == "1"
    assert "Did not learn (plain R0 < 50), left out: linear@1k_s1." in (report / "ablation_noise-frozen.md").read_text()
    seeds = [
        tuple(np.array([[m + o for o in OFFSETS[w]] for m in MEANS[model][i]]) for i, w in enumerate(OFFSETS))
        for model in [("oja", 0), ("oja", 1)]
    ]
    low, high = paired_interval(seeds, lambda p, f: auc(p) - auc(f))
    assert float(oja["auc_difference_low"]) == pytest.approx(low, abs=1e-5)
    assert float(oja["auc_difference_high"]) == pytest.approx(high, abs=1e-5)


def test_a_model_that_stops_running_when_ablated_has_no_auc(tmp_path):
    """linear seed 0 frozen has R0 20, below the learned threshold: its R0 and return at sigma 0.4 differences stay
    (110 - 20, 90 - 5), its AUC is left out of its row and of the pooled one, which then equals oja's."""
    means = {**MEANS, ("linear", 0): ([110, 100, 90], [20, 10, 5])}
    folder = write_study(tmp_path / "study", means)
    rows = rows_of(folder / "ablation_noise-frozen.csv")
    linear, oja, pooled = rows["linear@1k"], rows["oja@1k"], rows["plastic@1k (pooled: oja, linear)"]
    assert float(linear["r0_difference_estimate"]) == pytest.approx(90)
    assert float(linear["return_at_sigma_0.4_difference_estimate"]) == pytest.approx(85)
    assert linear["auc_difference_estimate"] == "" and linear["auc_seeds"] == "0"
    assert float(pooled["r0_difference_estimate"]) == pytest.approx((20 + 0 + 90) / 3)
    assert (pooled["seeds"], pooled["auc_seeds"], oja["auc_seeds"]) == ("3", "2", "2")
    for k in ("estimate", "low", "high"):
        assert float(pooled[f"auc_difference_{k}"]) == pytest.approx(float(oja[f"auc_difference_{k}"]))
    text = (folder / "ablation_noise-frozen.md").read_text()
    assert "left out of the AUC columns only: linear@1k_s0." in text
    assert "| linear@1k | 1 | 110 | 20 | 90 [" in text and "| - | - | - | - |" in text
    assert "(2 of 3 seeds)" in text


def test_the_table_and_its_missing_model(report):
    text = (report / "ablation_frozen.md").read_text()
    assert text.startswith(f"# {ENV}: evaluation 'frozen' (frozen) against 'final'")
    assert "positive: the model loses this much when its traces are frozen" in text
    assert "| oja@1k | 2 | 17.000 | 13.000 | 4.000 [" in text
    assert "## Missing" in text and "* linear@1k_s1: frozen.csv" in text
    assert "static" not in text and "mlp" not in text


def declared(**frozen):
    study = copy.deepcopy(STUDY)
    study["evaluations"]["frozen"].update(frozen)
    return study


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(against="fnal"), "unknown evaluation in against of evaluation 'frozen' 'fnal'"),
        (dict(against="robustness"), "against='robustness' of evaluation 'frozen' in x.yml: a robustness evaluation"),
        (dict(against="final", seed=101), "against='final' of evaluation 'frozen' in x.yml: different episode seeds"),
        (dict(against="final", episodes=5), "different episode seeds"),
        (dict(against="noise-frozen"), "a robustness evaluation, not final"),
        (dict(against="final", ablation="none"), "needs ablation"),
        (dict(against=3), "must be the name of an evaluation"),
    ],
)
def test_against_errors(change, message):
    with pytest.raises(ValueError, match=message) as info:
        study_from_dict(declared(**change), "x.yml")
    assert "\n" not in str(info.value)


def test_against_an_ablated_evaluation_or_other_sigmas():
    study = copy.deepcopy(STUDY)
    study["evaluations"]["shuffled"] = {**ROBUSTNESS, "ablation": "shuffled", "against": "noise-frozen"}
    with pytest.raises(ValueError, match="ablated itself"):
        study_from_dict(study, "x.yml")
    study["evaluations"]["shuffled"].update(against="robustness", sigmas=[0, 0.4])
    with pytest.raises(ValueError, match="different sigmas"):
        study_from_dict(study, "x.yml")


def test_the_counterpart():
    study = copy.deepcopy(STUDY)
    study["evaluations"]["final2"] = {**FINAL_EVAL, "kind": "final"}
    assert counterpart(study_from_dict(study), "frozen") == "final"  # the first plain one alike
    assert counterpart(study_from_dict(study), "noise-frozen") == "robustness"
    study["evaluations"]["frozen"]["against"] = "final2"
    assert counterpart(study_from_dict(study), "frozen") == "final2"
    # Other episode seeds and no against: nothing to pair with (no table).
    assert counterpart(study_from_dict(declared(seed=101)), "frozen") is None


#: Adaptation (``bins: 2``, ``recovery: [2, 2]``): each model's episodes, plain and frozen, as (step rewards, the
#: first step under the changed dynamics or None). By hand: oja seed 0 plain has drops 0.5, 0 and recoveries 0.5, 1,
#: frozen drops 0.5, 1 and recoveries 0, 0 (the third episode has no change in either); oja seed 1 pairs only its
#: first episode (drop 0 both, recovery 1 against 0): its second has a reference of -1 plain, its third too few steps
#: after the change. linear has no change in any episode: no row of its own in the adaptation table.
SWITCH_EPISODES = {
    ("oja", 0): (
        [([2, 2, 2, 2, 1, 1, 1, 1, 2, 2], 4), ([1, 1, 1, 1, 0, 0, 1, 1], 4), ([1, 1, 1, 1], None)],
        [([2, 2, 2, 2, 1, 1, 1, 1, 1, 1], 4), ([1, 1, 1, 1, 1, 1, 1, 1], 4), ([1, 1, 1, 1], None)],
    ),
    ("oja", 1): (
        [([1, 1, 0, 0, 1, 1], 2), ([-1, -1, 1, 1, 1, 1], 2), ([1, 1, 1, 1], 2)],
        [([1, 1, 0, 0, 0, 0], 2), ([1, 1, 1, 1, 1, 1], 2), ([1, 1, 1, 1], 2)],
    ),
    ("linear", 0): ([([1, 1, 1, 1], None)] * 3, [([2, 2, 2, 2], None)] * 3),
}
#: Per paired episode of each oja seed: (plain drop, plain recovery, frozen drop, frozen recovery).
SWITCH_BY_HAND = {0: [(0.5, 0.5, 0.5, 0.0), (0.0, 1.0, 1.0, 0.0)], 1: [(0.0, 1.0, 0.0, 0.0)]}


@pytest.fixture(scope="module")
def switch_report(tmp_path_factory):
    """A final evaluation with ``bins`` and its frozen twin, raw files written by hand: the report's folder."""
    folder = tmp_path_factory.mktemp("switch") / "study"
    final = {"episodes": 3, "seed": 100, "info_keys": ["reward"], "align": "switch_step", "bins": 2}
    final["recovery"] = [2, 2]
    study = {
        "envs": [ENV],
        "seeds": [0, 1],
        "budgets": [1000],
        "variants": {"oja": {"rule": "dp-oja"}, "linear": {"rule": "dp-linear", "seeds": [0]}},
        "evaluations": {"final": final, "frozen": {**final, "kind": "final", "ablation": "frozen"}},
        "report": {"resamples": RESAMPLES},
    }
    header = ["episode", "return", "length", "success", "steps:reward", "align:switch_step"]
    for (variant, seed), both in SWITCH_EPISODES.items():
        out = StudyFolder(folder).episodes_dir(ENV, variant, 1000, seed)
        out.mkdir(parents=True)
        for name, episodes in zip(("final", "frozen"), both):
            rows = [[k, sum(r), len(r), "", json.dumps(r), "" if a is None else a] for k, (r, a) in enumerate(episodes)]
            with open(out / f"{name}.csv", "w", newline="") as f:
                csv.writer(f).writerows([header, *rows])
    write_report(study_from_dict(study, "synthetic.yml"), folder, log=None)
    return folder


def test_drop_and_recovery_plain_against_frozen_by_hand(switch_report):
    rows = rows_of(switch_report / "ablation_frozen.csv")
    oja = rows["oja@1k"]
    per_seed = {s: np.array(v).mean(axis=0) for s, v in SWITCH_BY_HAND.items()}  # seed -> the four means
    expected = {
        "drop_plain": (per_seed[0][0] + per_seed[1][0]) / 2,
        "recovery_plain": (per_seed[0][1] + per_seed[1][1]) / 2,
        "drop_ablated": (per_seed[0][2] + per_seed[1][2]) / 2,
        "recovery_ablated": (per_seed[0][3] + per_seed[1][3]) / 2,
    }
    for key, value in expected.items():
        assert float(oja[key]) == pytest.approx(value), key
    assert float(oja["drop_difference_estimate"]) == pytest.approx(-0.25)
    assert float(oja["recovery_difference_estimate"]) == pytest.approx(0.875)
    assert oja["adaptation_seeds"] == "2"
    # The paired interval over the paired episodes, against the independent loop.
    seeds = [tuple(np.array(SWITCH_BY_HAND[s]).T[i : i + 2] for i in (0, 2)) for s in (0, 1)]
    low, high = paired_interval(seeds, lambda p, f: p[1] - f[1])
    assert float(oja["recovery_difference_low"]) == pytest.approx(low, abs=1e-5)
    assert float(oja["recovery_difference_high"]) == pytest.approx(high, abs=1e-5)
    # linear keeps its return row but has no episode with a change: no drop or recovery, and no pooled one either.
    assert rows["linear@1k"]["return_difference_estimate"] and not rows["linear@1k"].get("drop_plain")
    pooled = rows["plastic@1k (pooled: oja, linear)"]
    assert not pooled.get("drop_plain")
    text = (switch_report / "ablation_frozen.md").read_text()
    assert "## After the change at 'switch_step'" in text
    assert "| oja@1k | 2 | 0.125 | 0.375 | -0.250 [" in text
