"""Study files: every bad key or value is one line naming it (before anything is written), the packaged studies,
selections of a study, and model names."""

import copy

import pytest
import yaml

from sb3_spikeplastic.study import FIG4, load_study_file, study_from_dict
from sb3_spikeplastic.study.declaration import budget_label, model_name
from sb3_spikeplastic.study.engine import prepare


def changed(tiny_study, change):
    """A copy of the tiny study's mapping changed by ``change``."""
    data = copy.deepcopy(tiny_study)
    change(data)
    return data


def test_the_tiny_study_reads(files, tiny_study):
    study = study_from_dict(tiny_study, "tiny.yml", files)
    assert study.cells() == [
        ("CartPole-v1", "small", 0),
        ("CartPole-v1", "large", 0),
        ("CartPole-v1", "small", 1),
        ("CartPole-v1", "large", 1),
    ]
    assert study.conf == str(files / "cartpole.yml")  # a relative conf is read from the study file's folder
    robustness = study.evaluations["robustness"]
    assert robustness.protocol.sigmas == (0.0, 0.5) and robustness.files("robustness") == ["robustness_obs.csv"]
    assert study.evaluations["final"].files("final") == ["final.csv"]
    assert study.config("CartPole-v1", "large")["policy_kwargs"]["net_arch"] == [16]
    assert study.config("CartPole-v1", "large")["n_timesteps"] == 256  # trained to the largest budget


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.update(budget=[1]), "unknown study key 'budget' in tiny.yml (did you mean 'budgets'?)"),
        (
            lambda d: d["variants"]["small"].update(hyperparameters=[]),
            "unknown key of variant 'small' 'hyperparameters' in tiny.yml (did you mean 'hyperparams'?)",
        ),
        (lambda d: d["variants"]["small"].update(rule="dp-ojaa"), "unknown rule 'dp-ojaa'"),
        (lambda d: d.update(conf="nope.yml"), "nope.yml"),
        (lambda d: d["variants"]["large"].update(conf="nope.yml"), "nope.yml"),
        (
            lambda d: d["evaluations"]["robustness"].update(noises=["wind"]),
            "unknown noise of evaluation 'robustness' 'wind' in tiny.yml",
        ),
        (lambda d: d["evaluations"]["robustness"].update(sigmas=[0.1, 0.5]), "starting with 0"),
        (lambda d: d["evaluations"]["robustness"].update(sigmas=[0, 0.5, 0.2]), "increasing"),
        (
            lambda d: d["report"]["compare"].append({"variants": ["medium"], "against": "small"}),
            "unknown variant in report.compare.variants 'medium'",
        ),
        (
            lambda d: d["report"]["compare"].append({"variants": ["large"], "against": "smal"}),
            "'smal' in tiny.yml (did you mean 'small'?)",
        ),
        (
            lambda d: d["evaluations"].update(held={"kind": "finall"}),
            "unknown kind of evaluation 'held' 'finall' in tiny.yml (did you mean 'final'?)",
        ),
        (lambda d: d["evaluations"].update(held={}), "unknown kind of evaluation 'held' 'held'"),
        (lambda d: d["evaluations"]["final"].update(noises=["obs"]), "unknown key of evaluation 'final' 'noises'"),
        (lambda d: d["evaluations"]["final"].update(model="last"), "unknown model of evaluation 'final' 'last'"),
        (lambda d: d.update(seeds=[0, 0]), "must not repeat a value"),
        (lambda d: d.update(budgets=[0]), "budgets=0 must be an integer >= 1"),
        (lambda d: d["variants"].update({"a@b": {}}), "variant name 'a@b'"),
        (lambda d: d.pop("envs"), "needs 'envs'"),
    ],
)
def test_bad_study_files_are_one_line(files, change, message, tiny_study):
    with pytest.raises(ValueError) as error:
        study_from_dict(changed(tiny_study, change), "tiny.yml", files)
    assert message in str(error.value) and "\n" not in str(error.value), str(error.value)


def write(files, data, name="bad.yml"):
    (files / name).write_text(yaml.safe_dump(data, sort_keys=False))
    return files / name


@pytest.mark.parametrize(
    "change, message",
    [
        (
            lambda d: d.update(budgets=[128, 257]),
            "budget 257 of variant 'small' on CartPole-v1 is not a multiple of its n_envs=2",
        ),
        (
            lambda d: d["evaluations"]["robustness"].update(noises=["obs", "action"]),
            "evaluation 'robustness': action noise cannot be applied to CartPole-v1",
        ),
        (lambda d: d["evaluations"]["robustness"].update(noises=["friction"]), "friction noise cannot be applied"),
        (
            lambda d: d["variants"]["small"].update(hyperparams=["policy_kwargs.net_arc=[8]"]),
            "variant 'small' on CartPole-v1",
        ),
        (lambda d: d.update(envs=["CartPol-v1"]), "'CartPol-v1'"),
    ],
)
def test_studies_that_cannot_run_are_refused_before_anything_is_written(files, run_cli, change, message, tiny_study):
    data = changed(tiny_study, change)
    with pytest.raises(ValueError, match="^[^\n]*$") as error:
        prepare(study_from_dict(data, "bad.yml", files), files / "s", "bad")
    assert message in str(error.value)
    code, out, err = run_cli("study", write(files, data), "-f", files / "logs")
    assert code == 2 and err.count("\n") == 1 and err.startswith("sb3-spikeplastic: error: ") and message in err
    assert not (files / "s").exists() and not (files / "logs").exists()


def test_bad_files_and_options_through_the_cli(files, run_cli, tiny_study):
    for text, message in (
        ("- a list\n", "must be a mapping"),
        ("a: [\n", "is not valid YAML"),
        (yaml.safe_dump({**tiny_study, "budget": 1}), "did you mean 'budgets'"),
    ):
        (files / "bad.yml").write_text(text)
        code, out, err = run_cli("study", files / "bad.yml", "-f", files / "logs")
        assert code == 2 and err.count("\n") == 1 and message in err, err
    good = write(files, tiny_study, "tiny.yml")
    for argv, message in (
        ([good, "--workers", "0"], "--workers=0"),
        ([good, "--variants", "medium"], "unknown variant 'medium'"),
        (["no-such-study"], "no study file 'no-such-study'"),
    ):
        code, out, err = run_cli("study", *argv, "-f", files / "logs")
        assert code == 2 and err.count("\n") == 1 and message in err, err
    assert not (files / "logs").exists()


def test_report_of_a_folder_without_study_data(files, run_cli, tiny_study):
    good = write(files, tiny_study, "tiny.yml")
    code, out, err = run_cli("study", "report", good, "-f", files / "logs")
    assert code == 2 and err.count("\n") == 1 and "holds no study" in err, err
    assert not (files / "logs").exists()
    # a study that was prepared but has not written a raw file yet
    (files / "logs" / "study" / "tiny").mkdir(parents=True)
    (files / "logs" / "study" / "tiny" / "study.db").write_bytes(b"")
    code, out, err = run_cli("study", "report", good, "-f", files / "logs")
    assert code == 2 and "holds no study" in err and "logs/study/tiny" in err, err


#: The variants of the paper's Fig. 4 E-H in the packaged fig4 study (which may hold controls besides).
PAPER = [
    "dp-bcm",
    "dp-linear",
    "dp-oja",
    "mlp",
    "mlp_zoo",
    "ndp-bcm+tanh",
    "ndp-bcm",
    "ndp-oja+tanh",
    "ppo_lstm",
    "ppo_lstm_zoo",
    "static",
]


def test_the_packaged_studies():
    fig4, path = load_study_file("fig4")
    assert path.name == "fig4.yml" and fig4.envs == ("HalfCheetah-v5",)
    assert set(PAPER) <= set(fig4.variants)
    assert len(fig4.select(PAPER).cells()) == 37  # 9 variants x 3 seeds, dp-oja and static x 5
    assert fig4.seeds_of("static") == (0, 1, 2, 3, 4) and fig4.budgets_of("dp-bcm") == (300000,)
    assert fig4.budgets_of("mlp") == (300000, 1000000)
    assert fig4.evaluations["robustness"].protocol == FIG4 and fig4.learned_threshold == FIG4.learned_threshold
    assert fig4.variants["ndp-oja+tanh"].hyperparams == (
        "policy_kwargs.rule_kwargs.modulation=tanh",
        "policy_kwargs.rule_kwargs.wm_init_gain=5",
    )
    tmaze, _ = load_study_file("tmaze")
    assert len(tmaze.variants) == 8 and tmaze.envs == ("TMazeCue-v0", "TMazeCueNoisy-v0")
    assert len(tmaze.cells()) == 48
    best = tmaze.evaluations["best"]
    assert best.kind == "final" and best.model == "best" and best.protocol.episodes == 1000
    assert best.protocol.n_envs == 10 and best.protocol.seed == 1_000_000
    tanh = tmaze.config("TMazeCueNoisy-v0", "ndp-bcm+tanh")["policy_kwargs"]
    assert tanh["rule"] == "ndp-bcm" and tanh["rule_kwargs"]["modulation"] == "tanh"
    paper, _ = load_study_file("paper_network")
    config = paper.config("HalfCheetah-v5", "ndp-oja+tanh")
    assert config["n_envs"] == 6 and config["policy_kwargs"]["steps"] == 50  # hyperparams/paper.yml's network
    assert (
        config["policy_kwargs"]["rule"] == "ndp-oja"
        and paper.config("HalfCheetah-v5", "static")["policy_kwargs"]["rule"] == "static"
    )
    assert [name for name, _, _ in paper.evaluations_of("static", 0, 999_000)] == ["robustness"]
    assert [name for name, _, _ in paper.evaluations_of("ndp-oja+tanh", 0, 999_000)] == ["robustness", "frozen"]
    assert config["bptt_steps"] == 10 and paper.config("HalfCheetah-v5", "static")["bptt_steps"] == 10
    assert paper.config("HalfCheetah-v5", "static-bptt20")["bptt_steps"] == 20  # the model trained before the change
    assert paper.variants["static-bptt20"].seeds == (0,)
    with pytest.raises(
        ValueError, match="no study file 'fig5'.*fig4, paper_network, reversal, switch_meta, switch_zero_shot, tmaze"
    ):
        load_study_file("fig5")


def test_select():
    fig4, _ = load_study_file("fig4")
    n_cells = len(fig4.cells())
    assert fig4.select(["static"], seeds=[3]).cells() == [("HalfCheetah-v5", "static", 3)]
    # seeds only some variants have: the others drop out
    late = fig4.select(["dp-oja", "mlp", "static"], seeds=[3, 4])
    assert list(late.variants) == ["dp-oja", "static"] and len(late.cells()) == 4
    only = fig4.select(["dp-bcm", "mlp"])
    assert list(only.variants) == ["dp-bcm", "mlp"] and len(only.cells()) == 6
    assert only.budgets_of("dp-bcm") == (300000,) and only.budgets_of("mlp") == (300000, 1000000)
    assert fig4.select(seeds=[0]).seeds_of("static") == (0,)
    assert len(fig4.cells()) == n_cells  # the study itself is unchanged
    with pytest.raises(ValueError, match="unknown variant 'nope'; accepted: dp-bcm"):
        fig4.select(["nope"])


@pytest.mark.parametrize(
    "steps, label",
    [
        (128, "128"),
        (1000, "1k"),
        (300000, "300k"),
        (1000000, "1M"),
        (2000000, "2M"),
        (2500000, "2500k"),
        (1500, "1500"),
    ],
)
def test_budget_label(steps, label):
    assert budget_label(steps) == label


def test_model_name():
    assert model_name("dp-oja", 300000, 0) == "dp-oja@300k_s0"
    assert model_name("ndp-oja+tanh", 1000000, 12) == "ndp-oja+tanh@1M_s12"
