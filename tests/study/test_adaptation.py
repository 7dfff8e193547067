"""Adaptation to a change of dynamics within an episode: ``reward`` in ``info_keys`` keeps every step's reward (the
steps of an episode sum to its return) in a real evaluation; the report's return per bin relative to the episode's
bins before the change, its drop and its recovery equal values worked out by hand from raw files written by hand
(an episode with a reference <= 0, or not above a declared ``min_reference``, left out and counted, episodes of
different switch steps); bad ``bins``, ``recovery`` and ``min_reference`` are one line; the packaged switch studies
load."""

import copy
import csv
import json

import numpy as np
import pytest
import yaml

from sb3_spikeplastic.study import engine, load_study_file, study_from_dict
from sb3_spikeplastic.study.intervals import bootstrap_difference, bootstrap_interval
from sb3_spikeplastic.study.layout import StudyFolder, read_final
from sb3_spikeplastic.study.report import write_report

ENV = "CartPole-v1"
#: Each model's episodes: (step rewards, the first step under the changed dynamics or None), with ``bins: 2`` and
#: ``recovery: [2, 3]``. Seed 0 of ``a``: switches at 8 and 6 (three whole bins before it, and a last bin not whole
#: after it), and one whose reference is -1/3 (left out). Seed 1: a reference over steps 2-9 (steps 0-1 are five
#: bins before), too few steps after the change for a recovery, and two episodes without a bin before the change
#: (left out).
EPISODES = {
    ("a", 0): [
        ([1] * 8 + [0, 0, 0, 0, 1, 1, 1, 1], 8),
        ([2] * 6 + [1, 1, 2, 2, 2, 2, 2, 2, 2], 6),
        ([-1, -1, 0, 0, 0, 0, 5, 5, 5, 5, 5, 5], 6),
    ],
    ("a", 1): [([100, 100] + [4] * 8 + [2, 2, 2, 4], 10), ([1, 2, 3, 4], None), ([1, 1, 1, 1, 1, 1], 1)],
    ("b", 0): [([1, 1, 3, 3, 2, 2, 2, 2, 2, 2], 4)],
}
#: By hand, per seed of ``a``: the episodes' values of each measure (bin b: steps [2b, 2b + 2) after the change).
BY_HAND_A = {
    "reference": ([1, 2], [4]),
    "drop": ([0, 0.5], []),
    "recovery": ([1, 0.5], []),
    -4: ([1], [1]),
    -3: ([1, 1], [1]),
    0: ([0, 0.5], [0.5]),
    1: ([0, 1], [0.75]),
    2: ([1, 1], []),
    3: ([1, 1], []),
}
RESAMPLES = 300
STUDY = {
    "conf": "cartpole.yml",
    "envs": [ENV],
    "seeds": [0, 1],
    "budgets": [1000],
    "variants": {"a": {}, "b": {"seeds": [0]}},
    "evaluations": {
        "final": {"episodes": 3, "info_keys": ["reward"], "align": "switch_step", "bins": 2, "recovery": [2, 3]}
    },
    "report": {"resamples": RESAMPLES, "compare": [{"variants": ["b"], "against": ["a"]}]},
}


def write_synthetic_report(files, study: dict):
    """The raw files of :data:`EPISODES` written by hand and ``study``'s report: the report's folder."""
    folder = files / "study"
    for (variant, seed), episodes in EPISODES.items():
        out = StudyFolder(folder).episodes_dir(ENV, variant, 1000, seed)
        out.mkdir(parents=True)
        header = ["episode", "return", "length", "success", "steps:reward", "align:switch_step"]
        rows = [[k, sum(r), len(r), "", json.dumps(r), "" if a is None else a] for k, (r, a) in enumerate(episodes)]
        with open(out / "final.csv", "w", newline="") as f:
            csv.writer(f).writerows([header, *rows])
    write_report(study_from_dict(study, "synthetic.yml", files), folder, log=None)
    return folder


@pytest.fixture
def report(files):
    return write_synthetic_report(files, STUDY)


def rows_of(folder):
    with open(folder / "adaptation_final.csv") as f:
        return {(r["measure"], r["bin_start"], r["group"]): r for r in csv.DictReader(f)}


def check_row(row, seeds):
    """The row against the mean over seeds of the per-seed means and the generic path's two-stage interval."""
    seeds = [np.array(s, dtype=float) for s in seeds if s]
    interval = bootstrap_interval(seeds, lambda s: np.mean([x.mean() for x in s]), n_resamples=RESAMPLES)
    assert int(row["seeds"]) == len(seeds) and int(row["episodes"]) == sum(s.size for s in seeds)
    assert float(row["estimate"]) == pytest.approx(np.mean([s.mean() for s in seeds]), abs=1e-6)
    assert (float(row["low"]), float(row["high"])) == pytest.approx((interval.low, interval.high), abs=1e-6)


def test_the_relative_bins_drop_and_recovery_by_hand(report):
    rows = rows_of(report)
    for measure, seeds in BY_HAND_A.items():
        key = ("relative_return", str(2 * measure), "a@1k") if isinstance(measure, int) else (measure, "", "a@1k")
        check_row(rows[key], seeds)
    # every bin of a: -4 .. 3 and no other (seed 1's steps 0-1 are bin -5: not in the table)
    assert sorted(int(b) for m, b, g in rows if m == "relative_return" and g == "a@1k") == list(range(-8, 8, 2))
    assert float(rows[("relative_return", "0", "a@1k")]["estimate"]) == pytest.approx(0.375)  # (0.25 + 0.5) / 2
    assert float(rows[("recovery", "", "a@1k")]["estimate"]) == pytest.approx(0.75)
    assert {int(r["left_out"]) for r in rows.values() if r["group"] == "a@1k"} == {1}
    # b: reference (1 + 1 + 3 + 3) / 4 = 2; bins -2 and -1 are 2/4 and 6/4; after the change 4/4; recovery 0
    b = {k[:2]: float(r["estimate"]) for k, r in rows.items() if k[2] == "b@1k" and not r["reference"]}
    assert b == pytest.approx(
        {
            ("reference", ""): 2.0,
            ("drop", ""): 1.0,
            ("recovery", ""): 0.0,
            ("relative_return", "-4"): 0.5,
            ("relative_return", "-2"): 1.5,
            ("relative_return", "0"): 1.0,
            ("relative_return", "2"): 1.0,
            ("relative_return", "4"): 1.0,
        }
    )


def test_the_declared_comparison_of_drop_and_recovery(report):
    """b minus a, from the per-seed episode values by hand (a's seed 1 has no drop or recovery: left out), against
    the generic two-stage difference."""
    rows = rows_of(report)
    b = {"drop": [[1.0]], "recovery": [[0.0]]}
    for measure, expected in (("drop", 1.0 - 0.25), ("recovery", 0.0 - 0.75)):
        row = rows[(f"{measure}_difference", "", "b@1k")]
        assert row["reference"] == "a@1k" and row["seeds"] == "1"
        assert float(row["estimate"]) == pytest.approx(expected)
        seeds_a = [np.array(s, dtype=float) for s in BY_HAND_A[measure] if s]
        seeds_b = [np.array(s) for s in b[measure]]
        interval = bootstrap_difference(
            seeds_b, seeds_a, lambda s: np.mean([x.mean() for x in s]), n_resamples=RESAMPLES
        )
        assert (float(row["low"]), float(row["high"])) == pytest.approx((interval.low, interval.high), abs=1e-6)
    table = (report / "adaptation_final.md").read_text()
    assert "## Against the reference" in table and "| b@1k | a@1k | 1 vs 1 | 0.750 [" in table


def test_the_table_counts_the_episodes_left_out(report):
    table = (report / "adaptation_final.md").read_text()
    assert "| a@1k | 2 | 6 | 1 | 2 | 2.750 [" in table  # 6 episodes: 1 with reference <= 0, 2 without a bin before
    assert "| b@1k | 1 | 1 | 0 | 0 | 2.000 [" in table
    assert "| [0, 2) | 0.375 [" in table and "| [-8, -6) | 1.000 [" in table
    assert (report / "adaptation_final.png").is_file()


def test_a_floor_on_the_reference_leaves_more_episodes_out(files):
    """``min_reference: 1.5`` leaves out seed 0's episode of reference 1 as well as the one of -1/3: seed 0 keeps
    the episode of reference 2 (drop 0.5, recovery 0.5); b's reference 2 is above the floor."""
    study = copy.deepcopy(STUDY)
    study["evaluations"]["final"]["min_reference"] = 1.5
    folder = write_synthetic_report(files, study)
    rows = rows_of(folder)
    check_row(rows[("reference", "", "a@1k")], ([2], [4]))
    check_row(rows[("drop", "", "a@1k")], ([0.5], []))
    check_row(rows[("recovery", "", "a@1k")], ([0.5], []))
    assert {int(r["left_out"]) for r in rows.values() if r["group"] == "a@1k"} == {2}
    assert float(rows[("reference", "", "b@1k")]["estimate"]) == pytest.approx(2.0)
    table = (folder / "adaptation_final.md").read_text()
    assert "| left out: reference <= 1.5 |" in table and "| a@1k | 2 | 6 | 2 | 2 | 3.000 [" in table


TINY_SWITCH_CONF = """HalfCheetahSwitch-v5:
  policy: MlpPolicy
  n_timesteps: 64
  n_envs: 1
  n_steps: 64
  batch_size: 64
  n_epochs: 1
  normalize: true
  env_kwargs: {max_episode_steps: 40, window: [15, 25]}
"""


def test_a_real_run_keeps_every_steps_reward(tmp_path):
    """A 64-step HalfCheetahSwitch run with 40-step episodes, the change in steps 15-25: the raw file keeps every
    step's reward, which sums to the episode's return, and the switch step; the report writes the adaptation
    files and counts every episode."""
    (tmp_path / "switch.yml").write_text(TINY_SWITCH_CONF)
    data = {
        "conf": "switch.yml",
        "envs": ["HalfCheetahSwitch-v5"],
        "seeds": [0],
        "budgets": [64],
        "variants": {"mlp": {}},
        "evaluations": {
            "final": {
                "episodes": 4,
                "seed": 100,
                "n_envs": 2,
                "info_keys": ["reward", "switched"],
                "align": "switch_step",
                "bins": 5,
                "recovery": [5, 10],
            }
        },
    }
    study = study_from_dict(data, "switch.yml", tmp_path)
    job = engine.prepare(study, tmp_path / "s", "switch")
    assert engine.run_worker(job, lambda line: None) == 0
    raw = read_final(StudyFolder(tmp_path / "s").episodes_dir("HalfCheetahSwitch-v5", "mlp", 64, 0) / "final.csv")
    assert len(raw["return"]) == 4
    for k in range(4):
        rewards, switched, step = raw["steps"]["reward"][k], raw["steps"]["switched"][k], raw["align"]["switch_step"][k]
        assert len(rewards) == raw["length"][k] == 40
        assert rewards.sum() == pytest.approx(raw["return"][k], rel=1e-5, abs=1e-4)
        assert len(set(rewards.tolist())) > 1  # the step rewards, not a constant
        assert 15 <= step <= 25 and switched.tolist() == [0] * step + [1] * (40 - step)  # step: the first changed
    write_report(study, tmp_path / "s", log=None)
    table = (tmp_path / "s" / "adaptation_final.md").read_text()
    row = next(line for line in table.splitlines() if line.startswith("| mlp@64 |"))
    assert row.split(" | ")[2] == "4"  # every episode counted, kept or left out
    assert (tmp_path / "s" / "adaptation_final.png").is_file()


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(bins=0), "bins=0 of evaluation 'final' in tiny.yml must be an integer >= 1"),
        (dict(bins=2.5), "bins=2.5 of evaluation 'final' in tiny.yml must be an integer >= 1"),
        (dict(bins=True), "bins=True of evaluation 'final' in tiny.yml must be an integer >= 1"),
        (dict(bins=50, info_keys=["reward"]), "bins=50 of evaluation 'final' in tiny.yml needs align"),
        (dict(bins=50, info_keys=["x_velocity"], align="switch_step"), "needs align (the step of the change) and"),
        (dict(bins=50, info_keys=["reward"], align="switch_step", recovery=[100]), "recovery=[100] of evaluation"),
        (dict(bins=50, info_keys=["reward"], align="switch_step", recovery=[100, 0]), "recovery=[100, 0] of"),
        (dict(recovery=[100, 200]), "recovery=[100, 200] of evaluation 'final' in tiny.yml needs bins"),
        (
            dict(bins=50, info_keys=["reward"], align="switch_step", min_reference=-1),
            "min_reference=-1 of evaluation 'final' in tiny.yml must be a number >= 0",
        ),
        (
            dict(bins=50, info_keys=["reward"], align="switch_step", min_reference="1"),
            "min_reference='1' of evaluation 'final' in tiny.yml must be a number >= 0",
        ),
        (dict(min_reference=1.0), "min_reference=1.0 of evaluation 'final' in tiny.yml needs bins"),
    ],
)
def test_bad_bins_are_one_line(files, tiny_study, change, message):
    data = copy.deepcopy(tiny_study)
    data["evaluations"]["final"].update(change)
    with pytest.raises(ValueError) as error:
        study_from_dict(data, "tiny.yml", files)
    assert message in str(error.value) and "\n" not in str(error.value), str(error.value)


def test_bins_are_refused_by_robustness_evaluations(files, tiny_study):
    data = copy.deepcopy(tiny_study)
    data["evaluations"]["robustness"]["bins"] = 50
    with pytest.raises(ValueError, match="unknown key of evaluation 'robustness' 'bins'"):
        study_from_dict(data, "tiny.yml", files)


@pytest.mark.parametrize(
    "name, train_env", [("switch_zero_shot", "HalfCheetah-v5"), ("switch_meta", "HalfCheetahSwitch-v5")]
)
def test_the_packaged_switch_studies(name, train_env):
    study, path = load_study_file(name)
    assert path.name == f"{name}.yml" and study.envs == ("HalfCheetahSwitch-v5",)
    assert study.seeds == (0, 1, 2) and study.budgets == (300_000,)
    assert list(study.variants) == ["static", "dp-oja", "ndp-oja+tanh", "mlp_zoo", "ppo_lstm_zoo"]
    for variant in study.variants:
        assert study.train_env("HalfCheetahSwitch-v5", variant) == train_env
        study.config("HalfCheetahSwitch-v5", variant)  # an entry of its conf for the training environment
    for evaluation_name, ablation in (("final", None), ("frozen", "frozen")):
        evaluation = study.evaluations[evaluation_name]
        assert (evaluation.kind, evaluation.ablation) == ("final", ablation)
        assert (evaluation.protocol.episodes, evaluation.protocol.seed, evaluation.protocol.n_envs) == (
            100,
            1_000_000,
            100,
        )
        assert evaluation.info_keys == ("reward",) and evaluation.align == "switch_step"
        assert (evaluation.bins, evaluation.recovery, evaluation.min_reference) == (50, (100, 200), 1.0)
    assert yaml.safe_load(path.read_text())["description"]
