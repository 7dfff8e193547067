"""Step info in final evaluations: a real run's raw file keeps every step's info values, the alignment and the
energy of each episode; the report's mean at each step (and relative to the aligned step) and its interval equal
an independent computation from raw files written by hand; bad ``info_keys`` and ``align`` are one line."""

import copy
import csv
import json

import numpy as np
import pytest
import yaml

from sb3_spikeplastic.study import engine, load_study_file, study_from_dict
from sb3_spikeplastic.study.intervals import bootstrap_interval
from sb3_spikeplastic.study.layout import StudyFolder, read_final
from sb3_spikeplastic.study.report import write_report

REVERSAL_STUDY = """envs: [TMazeReversal-v0]
seeds: [0]
budgets: [512]
hyperparams: [n_envs=2, n_steps=64, batch_size=64, bptt_steps=16, n_epochs=1, "policy_kwargs.hidden_sizes=[16]"]
variants:
  static: {rule: static}
  dp-oja: {rule: dp-oja}
evaluations:
  final: {episodes: 6, seed: 100, n_envs: 2, info_keys: [good_choice, paid], align: reversal_trial}
"""


def test_a_real_run_keeps_every_steps_info_and_the_energy(tmp_path):
    study = study_from_dict(yaml.safe_load(REVERSAL_STUDY))
    job = engine.prepare(study, tmp_path / "s", "reversal")
    assert engine.run_worker(job, lambda line: None) == 0
    from sb3_spikeplastic.snn.energy import plasticity_operations
    from sb3_spikeplastic.zoo.run_folder import load_model, locate_run

    layout = StudyFolder(tmp_path / "s")
    for variant in ("static", "dp-oja"):
        data = read_final(layout.episodes_dir("TMazeReversal-v0", variant, 512, 0) / "final.csv")
        assert len(data["return"]) == 6 and set(data["steps"]) == {"good_choice", "paid"}
        for k in range(6):
            good, paid = data["steps"]["good_choice"][k], data["steps"]["paid"][k]
            assert len(good) == len(paid) == data["length"][k] == 10  # one value per trial
            assert set(good) <= {0.0, 1.0} and set(paid) <= {0.0, 1.0}
            assert paid.sum() == data["return"][k]  # the reward is whether the chosen arm paid
            assert 4 <= data["align"]["reversal_trial"][k] <= 6  # the env's reversal window
        assert (data["energy"]["synops"] > 0).all()
        model = load_model(locate_run(layout.model_at("TMazeReversal-v0", variant, 0, 512)), "cpu")
        macs = sum(plasticity_operations(model.policy.snn))
        assert (macs > 0) == (variant == "dp-oja")
        np.testing.assert_allclose(data["energy"]["plasticity_macs"], 10 * macs, rtol=1e-5)
    write_report(study, tmp_path / "s", log=None)
    for name in ("steps_final.md", "steps_final.csv", "steps_final_good_choice.png", "steps_final_paid.png"):
        assert (tmp_path / "s" / name).is_file(), name
    assert "| dp-oja@512 | 1 |" in (tmp_path / "s" / "table.md").read_text()  # the energy table


ENV = "CartPole-v1"
#: Each model's episodes: (good_choice at every step, the reversal step or None). Episodes differ in length, and
#: the episode without alignment has values the aligned table would show if it counted it.
EPISODES = {
    ("a", 0): [([1, 0, 1, 1], 2), ([0, 0, 1], 1), ([1, 1], None)],
    ("a", 1): [([1, 1, 1, 0], 1), ([0, 1, 0, 1], 3), ([1, 1, 1, 1], 2)],
    ("b", 0): [([0, 0, 0, 0], 2), ([0, 1, 0, 0], 2), ([1, 0, 0, 1], 1)],
    ("b", 1): [([9, 9, 9, 9], None), ([0, 0, 1, 1], 1), ([1, 0, 0, 0], 3)],
}
#: SynOps per episode of the spiking variant ``a`` (``b`` records none: a baseline).
SYNOPS = {0: [100.0, 200.0, 300.0], 1: [400.0, 500.0, 600.0]}
RESAMPLES = 300
STUDY = {
    "conf": "cartpole.yml",
    "envs": [ENV],
    "seeds": [0, 1],
    "budgets": [1000],
    "variants": {"a": {}, "b": {}},
    "evaluations": {"final": {"episodes": 3, "info_keys": ["good_choice"], "align": "reversal_trial"}},
    "report": {"resamples": RESAMPLES},
}


@pytest.fixture
def report(files):
    """The raw files of :data:`EPISODES` written by hand and the study's report: the report's folder."""
    folder = files / "study"
    for (variant, seed), episodes in EPISODES.items():
        out = StudyFolder(folder).episodes_dir(ENV, variant, 1000, seed)
        out.mkdir(parents=True)
        header = ["episode", "return", "length", "success", "steps:good_choice", "align:reversal_trial"]
        rows = [[k, sum(v), len(v), "", json.dumps(v), "" if a is None else a] for k, (v, a) in enumerate(episodes)]
        if variant == "a":  # the energy columns, as a spiking model's file has them
            header += ["synops", "plasticity_macs", "energy_nj"]
            for k, row in enumerate(rows):
                row += [SYNOPS[seed][k], 0, SYNOPS[seed][k] * 0.9 / 1000]
        with open(out / "final.csv", "w", newline="") as f:
            csv.writer(f).writerows([header, *rows])
    write_report(study_from_dict(STUDY, "synthetic.yml", files), folder, log=None)
    return folder


def by_hand(variant: str, position: int, aligned: bool):
    """Per seed, the values at ``position`` (relative to the aligned step when ``aligned``) of the episodes that
    have it; their mean over seeds of the per-seed means; and the two-stage bootstrap interval computed by the
    generic (non-vectorised) path."""
    seeds = []
    for seed in (0, 1):
        values = []
        for episode, align in EPISODES[(variant, seed)]:
            if aligned and align is None:
                continue
            step = position + (align if aligned else 0)
            if 0 <= step < len(episode):
                values.append(float(episode[step]))
        if values:
            seeds.append(np.array(values))
    estimate = np.mean([s.mean() for s in seeds])
    interval = bootstrap_interval(seeds, lambda s: np.mean([x.mean() for x in s]), n_resamples=RESAMPLES)
    return seeds, estimate, interval


def rows_of(folder):
    with open(folder / "steps_final.csv") as f:
        return {(r["aligned_on"], int(r["step"]), r["group"]): r for r in csv.DictReader(f)}


def test_the_mean_at_each_step_and_its_interval(report):
    rows = rows_of(report)
    absolute = {k: r for k, r in rows.items() if k[0] == ""}
    assert sorted({k[1] for k in absolute}) == [0, 1, 2, 3]
    for (_, position, group), row in absolute.items():
        seeds, estimate, interval = by_hand(group.split("@")[0], position, aligned=False)
        assert int(row["seeds"]) == len(seeds) and int(row["episodes"]) == sum(s.size for s in seeds)
        assert float(row["estimate"]) == pytest.approx(estimate, abs=1e-6)
        assert (float(row["low"]), float(row["high"])) == pytest.approx((interval.low, interval.high), abs=1e-6)
    # a's step 3: seed 0 has one episode that long (1), seed 1 three (0, 1, 1): (1 + 2/3) / 2
    assert float(absolute[("", 3, "a@1k")]["estimate"]) == pytest.approx(5 / 6, abs=1e-6)
    assert int(absolute[("", 3, "a@1k")]["episodes"]) == 4
    table = (report / "steps_final.md").read_text()
    assert "| step | a@1k | b@1k |" in table and "| 3 | 0.833 [" in table
    assert (report / "steps_final_good_choice.png").is_file()


def test_the_aligned_table_leaves_out_episodes_without_alignment(report):
    rows = rows_of(report)
    aligned = {k: r for k, r in rows.items() if k[0] == "reversal_trial"}
    assert sorted({k[1] for k in aligned}) == [-3, -2, -1, 0, 1, 2]  # no episode reaches 3 steps past its own
    for (_, offset, group), row in aligned.items():
        seeds, estimate, interval = by_hand(group.split("@")[0], offset, aligned=True)
        assert int(row["episodes"]) == sum(s.size for s in seeds)
        assert float(row["estimate"]) == pytest.approx(estimate, abs=1e-6)
        assert (float(row["low"]), float(row["high"])) == pytest.approx((interval.low, interval.high), abs=1e-6)
    # b's aligned step: seed 0 (0, 0, 0), seed 1 (0, 0) without the unaligned episode of 9s; with it, 3.0
    assert float(aligned[("reversal_trial", 0, "b@1k")]["estimate"]) == 0.0
    assert int(aligned[("reversal_trial", 0, "b@1k")]["episodes"]) == 5
    assert "2 episode(s) without it are left out" in (report / "steps_final.md").read_text()


def test_the_energy_table_has_the_groups_that_recorded_it(report):
    table = (report / "table.md").read_text()
    energy = table[table.index("energy per episode") :]
    assert f"| a@1k | 2 | {np.mean([np.mean(v) for v in SYNOPS.values()]):.0f} [" in energy  # 350
    assert "| b@1k |" not in energy


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(info_keys="good_choice"), "info_keys='good_choice' of evaluation 'final'"),
        (dict(info_keys=[1]), "info_keys=[1] of evaluation 'final'"),
        (dict(info_keys=["paid", "paid"]), "info_keys=['paid', 'paid'] of evaluation 'final'"),
        (dict(info_keys=["paid"], align=3), "align=3 of evaluation 'final'"),
        (dict(align="reversal_trial"), "align='reversal_trial' of evaluation 'final' in tiny.yml needs info_keys"),
    ],
)
def test_bad_info_keys_and_align_are_one_line(files, tiny_study, change, message):
    data = copy.deepcopy(tiny_study)
    data["evaluations"]["final"].update(change)
    with pytest.raises(ValueError) as error:
        study_from_dict(data, "tiny.yml", files)
    assert message in str(error.value) and "\n" not in str(error.value), str(error.value)


def test_info_keys_are_refused_by_robustness_evaluations(files, tiny_study):
    data = copy.deepcopy(tiny_study)
    data["evaluations"]["robustness"]["info_keys"] = ["paid"]
    with pytest.raises(ValueError, match="unknown key of evaluation 'robustness' 'info_keys'"):
        study_from_dict(data, "tiny.yml", files)


def test_the_packaged_reversal_study():
    study, path = load_study_file("reversal")
    assert (
        path.name == "reversal.yml"
        and study.envs == ("TMazeReversal-v0", "TMazeReversalNoisy-v0")
        and study.budgets == (150000,)
    )
    assert list(study.variants) == [
        "static",
        "dp-oja",
        "ndp-oja+tanh",
        "ndp-oja-reward",
        "ndp-oja-td",
        "ppo_lstm",
        "mlp",
    ]
    for name, ablation in (("final", None), ("frozen", "frozen")):
        evaluation = study.evaluations[name]
        assert (evaluation.kind, evaluation.ablation, evaluation.protocol.episodes) == ("final", ablation, 1000)
        assert evaluation.info_keys == ("good_choice", "paid") and evaluation.align == "reversal_trial"
    assert [c.against for c in study.comparisons] == [("static",), ("ndp-oja+tanh",)]


def test_the_energy_of_the_episodes_adds_up_to_the_evaluations():
    """Two environments side by side, two 10-trial episodes each: every forward pass belongs to a counted episode,
    so the episodes' SynOps together are the evaluation's SynOps per step times its 40 steps."""
    from sb3_spikeplastic import PPO
    from sb3_spikeplastic.zoo.evaluation import evaluate_model
    from sb3_spikeplastic.zoo.run_folder import make_eval_env

    venv = make_eval_env("TMazeReversal-v0", 2, 7, {}, None)
    model = PPO("SpikePlasticPolicy", venv, policy_kwargs=dict(hidden_sizes=[16], rule="dp-oja"), seed=0)
    result = evaluate_model(model, venv, 4, info_keys=["paid"], align="reversal_trial")
    venv.close()
    synops = [e["synops"] for e in result.episode_energy]
    assert len(synops) == 4 and len(set(synops)) > 1  # each episode its own spikes
    assert sum(synops) == pytest.approx(result.energy["total_synops_per_step"] * 40, rel=1e-6)  # float32 rates
    assert [sum(v) for v in result.steps["paid"]] == result.returns.tolist()


def test_the_raw_file_keeps_step_values_to_seven_digits(tmp_path):
    """Integers stay integers; other values keep 7 significant digits: a value read back is within 5e-7 of the one
    the environment returned, relatively."""
    from types import SimpleNamespace

    from sb3_spikeplastic.study.cell import write_final

    rewards = np.array([-0.123456789012345, 3.0, 1234.56789012, 2.5e-9, 0.1 + 0.2])
    result = SimpleNamespace(
        returns=np.array([rewards.sum()]),
        lengths=np.array([5]),
        successes=[],
        steps={"reward": [rewards]},
        aligned=[None],
        episode_energy=None,
    )
    path = tmp_path / "final.csv"
    with path.open("w", newline="") as f:
        write_final(f, result, None)
    written = next(csv.DictReader(path.open()))["steps:reward"]
    assert written == "[-0.1234568, 3, 1234.568, 2.5e-09, 0.3]"
    back = read_final(path)["steps"]["reward"][0]
    np.testing.assert_allclose(back, rewards, rtol=5e-7)
    assert not np.array_equal(back, rewards)  # rounded, not the full values
