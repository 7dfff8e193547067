"""``sb3-spikeplastic study report``: the numbers of a study folder written by hand against an independent
computation (R0, ratio to R0, AUC, models that did not learn, missing files, comparisons and verdicts), and the
committed Fig. 4 tables regenerated from the committed raw files."""

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from sb3_spikeplastic.study import load_study_file, study_from_dict
from sb3_spikeplastic.study.layout import StudyFolder
from sb3_spikeplastic.study.protocol import auc, ratio_to_r0
from sb3_spikeplastic.study.report import write_report

ENV = "CartPole-v1"
SIGMAS = [0.0, 0.2, 0.4]
#: The episodes of every (model, sigma): offsets around its mean, the same at every sigma (paired), mean 0.
OFFSETS = np.array([-2.0, -1.0, 1.0, 2.0])
#: Mean return at each sigma of each model. ``good`` loses almost nothing; ``ref`` loses 25-40 %; ``weak`` seed 0
#: lies between ref's seeds, and weak seed 1 did not learn (R0 30 < the threshold 50).
MEANS = {
    ("ref", 0): [100.0, 80.0, 60.0],
    ("ref", 1): [120.0, 110.0, 90.0],
    ("good", 0): [200.0, 198.0, 196.0],
    ("good", 1): [220.0, 218.0, 216.0],
    ("weak", 0): [110.0, 95.0, 75.0],
    ("weak", 1): [30.0, 30.0, 30.0],
}
#: Mean noise-free return of the final evaluation (4 episodes), and successes.
FINAL = {
    ("ref", 0): 100.0,
    ("ref", 1): 110.0,
    ("good", 0): 300.0,
    ("good", 1): 320.0,
    ("weak", 0): 105.0,
    ("weak", 1): 20.0,
}
SUCCESS = [1, 0, 1, 1]
STUDY = {
    "conf": "cartpole.yml",
    "envs": [ENV],
    "seeds": [0, 1],
    "budgets": [1000],
    "variants": {"ref": {}, "good": {}, "weak": {}},
    "evaluations": {"final": {"episodes": 4}, "robustness": {"noises": ["obs"], "sigmas": SIGMAS, "episodes": 4}},
    "report": {
        "learned_threshold": 50,
        "resamples": 500,
        "compare": [{"variants": ["good", "weak"], "against": "ref", "pooled": True}],
    },
}


def write_study(root: Path) -> None:
    """The raw files of :data:`STUDY` in the layout of ``sb3_spikeplastic.study.layout``."""
    layout = StudyFolder(root)
    for (variant, seed), means in MEANS.items():
        folder = layout.episodes_dir(ENV, variant, 1000, seed)
        folder.mkdir(parents=True)
        with open(folder / "robustness_obs.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["model", "noise_type", "sigma", "episode", "return"])
            for sigma, mean in zip(SIGMAS, means):
                writer.writerows([f"{variant}@1k_s{seed}", "obs", sigma, k, mean + o] for k, o in enumerate(OFFSETS))
        with open(folder / "final.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["episode", "return", "length", "success"])
            writer.writerows([k, FINAL[(variant, seed)] + o, 50, s] for k, (o, s) in enumerate(zip(OFFSETS, SUCCESS)))


@pytest.fixture
def report(files):
    """The study written by hand and its report: ``(study, folder)``."""
    study = study_from_dict(STUDY, "synthetic.yml", files)
    folder = files / "study"
    write_study(folder)
    write_report(study, folder, log=None)
    return study, folder


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


# The independent computation: per seed, the mean return at each sigma; the ratio 1 + (R - R0) / |R0|; the AUC as
# the trapezoid sum over the sigma range; a group's value the mean over its seeds.


def ratios(means):
    return [1 + (m - means[0]) / abs(means[0]) for m in means]


def area(means):
    r = ratios(means)
    trapezoids = sum((r[i] + r[i + 1]) / 2 * (SIGMAS[i + 1] - SIGMAS[i]) for i in range(len(r) - 1))
    return trapezoids / (SIGMAS[-1] - SIGMAS[0])


def group(variant, value, seeds=(0, 1)):
    return sum(value(MEANS[(variant, s)]) for s in seeds) / len(seeds)


LEARNED = {"ref": (0, 1), "good": (0, 1), "weak": (0,)}


def test_r0_ratio_and_auc_of_each_group(report):
    _, folder = report
    table = (folder / "table.md").read_text()
    # R0 = mean over seeds of each seed's mean noise-free return; a model below the threshold listed apart
    assert "| ref@1k | 2 of 2 | 100 / 120 | 110 [" in table
    assert "| good@1k | 2 of 2 | 200 / 220 | 210 [" in table
    assert "| weak@1k | 1 of 2 | 110 / 30 (did not learn) | 110 [" in table
    assert "Did not learn (R0 < 50): weak@1k_s1." in table
    points = {(r["group"], float(r["sigma"])): r for r in rows(folder / "points.csv")}
    assert len(points) == 3 * len(SIGMAS)
    for variant, seeds in LEARNED.items():
        for j, sigma in enumerate(SIGMAS):
            point = points[(f"{variant}@1k", sigma)]
            assert int(point["seeds"]) == len(seeds)
            assert float(point["return_estimate"]) == pytest.approx(group(variant, lambda m: m[j], seeds), abs=0.05)
            assert float(point["ratio_estimate"]) == pytest.approx(
                group(variant, lambda m: ratios(m)[j], seeds), abs=5e-5
            )
            assert float(point["return_low"]) <= float(point["return_estimate"]) <= float(point["return_high"])
        returns = " | ".join(
            f"{group(variant, lambda m: m[j], seeds):.0f} ({group(variant, lambda m: ratios(m)[j], seeds):.2f})"
            for j in range(len(SIGMAS))
        )
        assert f"| {variant}@1k | {len(seeds)} | {returns} | {group(variant, area, seeds):.2f} [" in table
    # the model that did not learn is left out of its group's ratios (with it, weak's R0 would be 70)
    assert float(points[("weak@1k", 0.4)]["return_estimate"]) == 75.0
    assert "## Missing" not in table


def test_comparisons_and_verdicts(report):
    _, folder = report
    verdicts = {(r["evaluation"], r["model"]): r for r in rows(folder / "verdicts.csv")}
    pooled = "good + weak@1k (pooled: good, weak)"
    assert set(verdicts) == {(e, m) for e in ("final", "robustness") for m in ("good@1k", "weak@1k", pooled)}
    good, weak, both = (verdicts[("robustness", m)] for m in ("good@1k", "weak@1k", pooled))
    assert good["reference"] == weak["reference"] == both["reference"] == "ref@1k"
    assert (good["seeds"], weak["seeds"], both["seeds"], both["reference_seeds"]) == ("2", "1", "3", "2")
    for row, variant, seeds in ((good, "good", (0, 1)), (weak, "weak", (0,))):
        assert float(row["auc_difference_estimate"]) == pytest.approx(
            group(variant, area, seeds) - group("ref", area), abs=5e-5
        )
        assert float(row["r0_difference_estimate"]) == pytest.approx(group(variant, lambda m: m[0], seeds) - 110)
        assert float(row["return_at_sigma_0.4_difference_estimate"]) == pytest.approx(
            group(variant, lambda m: m[-1], seeds) - 75
        )
    pooled_auc = (area(MEANS[("good", 0)]) + area(MEANS[("good", 1)]) + area(MEANS[("weak", 0)])) / 3
    assert float(both["auc_difference_estimate"]) == pytest.approx(pooled_auc - group("ref", area), abs=5e-5)
    # good loses clearly less and keeps a higher return; weak lies within ref's spread: no verdict
    assert (good["auc_verdict"], good["return_verdict"]) == ("loses less", "higher")
    assert float(good["auc_difference_low"]) > 0 and float(good["return_at_sigma_0.4_difference_low"]) > 0
    assert (weak["auc_verdict"], weak["return_verdict"]) == ("not resolved", "not resolved")
    final = verdicts[("final", "good@1k")]
    assert float(final["return_difference_estimate"]) == pytest.approx(310 - 105)
    assert final["return_verdict"] == "higher" and final["success_verdict"] == "not resolved"
    assert float(final["success_difference_estimate"]) == 0.0
    assert verdicts[("final", "weak@1k")]["seeds"] == "2"  # the final evaluation keeps every model
    # a verdict exactly where the interval excludes 0
    for row in verdicts.values():
        for prefix, key in (
            ("auc_difference", "auc_verdict"),
            ("return_at_sigma_0.4_difference", "return_verdict"),
            ("return_difference", "return_verdict"),
            ("success_difference", "success_verdict"),
        ):
            if row.get(f"{prefix}_low"):
                low, high = float(row[f"{prefix}_low"]), float(row[f"{prefix}_high"])
                assert (row[key] == "not resolved") == (low <= 0 <= high), (row["model"], prefix)
    markdown = (folder / "verdicts.md").read_text()
    assert f"| {pooled} | ref@1k | 3 vs 2 |" in markdown and "| loses less |" in markdown


def test_final_evaluation_table(report):
    _, folder = report
    table = (folder / "table.md").read_text()
    assert table.startswith(f"# {ENV}: evaluation 'final'")
    section = table.split("\n# ")[0]  # up to the robustness evaluation's heading
    final = {
        cells[0]: cells[1:]
        for cells in (line.strip("| ").split(" | ") for line in section.splitlines() if "@1k" in line)
    }
    assert list(final) == ["ref@1k", "good@1k", "weak@1k"]
    assert final["ref@1k"][:2] == ["2", "100 / 110"] and final["ref@1k"][2].startswith("105.000 [")
    assert final["weak@1k"][:2] == ["2", "105 / 20"] and final["weak@1k"][2].startswith("62.500 [")
    for cells in final.values():  # success: 3 of 4 in every seed
        assert cells[3] == "0.750 / 0.750" and cells[4].startswith("0.750 [")


def test_a_missing_file_is_listed(report):
    study, folder = report
    (StudyFolder(folder).episodes_dir(ENV, "good", 1000, 1) / "final.csv").unlink()
    write_report(study, folder, log=None)
    table = (folder / "table.md").read_text()
    missing = table[table.index("## Missing") :]
    assert "1 raw file(s) not there yet" in missing and f"* {ENV} good@1k_s1: final.csv" in missing
    assert "| good@1k | 1 | 300 | 300.000 [" in table  # the final table has the seed that is there
    assert "| good@1k | 2 of 2 | 200 / 220 |" in table  # its robustness file is still read


def test_ratio_to_r0_and_auc():
    """A loss is a ratio below 1 whatever R0's sign (a negative R0 that falls further is worse, not better)."""
    np.testing.assert_allclose(
        ratio_to_r0(np.array([[100.0, 80.0, 50.0], [-100.0, -150.0, -50.0]])), [[1.0, 0.8, 0.5], [1.0, 0.5, 1.5]]
    )
    assert np.isnan(ratio_to_r0(np.array([0.0, 10.0]))).all()  # no ratio to a zero return
    # trapezoids over unequal steps, divided by the sigma range: (0.1 * 0.9 + 0.3 * 0.65) / 0.4
    assert auc(np.array([1.0, 0.8, 0.5]), [0.0, 0.1, 0.4]) == pytest.approx(0.7125)
    assert auc(np.ones(5), SIGMAS + [0.6, 0.8]) == pytest.approx(1.0)


def test_a_folder_without_study_data(files):
    with pytest.raises(ValueError, match="holds no study"):
        write_report(study_from_dict(STUDY, "synthetic.yml", files), files / "empty", log=None)


FIG4 = Path(__file__).resolve().parents[2] / "results" / "halfcheetah" / "fig4"


def test_the_fig4_report_regenerates_the_committed_tables(tmp_path):
    shutil.copytree(FIG4 / "episodes", tmp_path / "episodes")
    write_report(load_study_file("fig4")[0], tmp_path, log=None)

    def without_missing(text):
        return text.split("\n## Missing")[0]

    assert without_missing((tmp_path / "table.md").read_text()) == without_missing((FIG4 / "table.md").read_text())
    for name in ("verdicts.md", "verdicts.csv", "points.csv"):
        assert (tmp_path / name).read_bytes() == (FIG4 / name).read_bytes(), name
