"""``sb3-spikeplastic optimize``: the search space, trials with intermediate evaluations and pruning, the best
entry that ``train --conf`` reads, and bad input."""

import optuna
import pytest

from sb3_spikeplastic.study.optimize import OptimizeSettings, prepare
from sb3_spikeplastic.study.search_space import load_search_space, sample_overrides, searched_space
from sb3_spikeplastic.study.storage import default_storage_url
from sb3_spikeplastic.zoo import config as cfg

SMALL_SPACE = """default:
  learning_rate: {log: [1.0e-4, 1.0e-2]}
  n_steps: {choices: [32, 64]}
  batch_size: {choices: [32, 64]}
  gamma: {choices: [0.95, 0.99]}
"""


@pytest.fixture
def files(files):
    """The study tests' ``files`` (``cartpole.yml``) and ``space.yml``, a small search space."""
    (files / "space.yml").write_text(SMALL_SPACE)
    return files


def tiny_search(files, **kwargs):
    return [
        "optimize",
        "--env",
        "CartPole-v1",
        "--conf",
        files / "cartpole.yml",
        "--search-space",
        files / "space.yml",
        "-n",
        "128",
        "--n-evaluations",
        "2",
        "--eval-episodes",
        "2",
        "--seed",
        "0",
        "-f",
        files / "logs",
        *[str(x) for kv in kwargs.items() for x in kv],
    ]


def test_optimize_writes_a_best_entry_that_train_reads(files, run_cli):
    code, out, err = run_cli(*tiny_search(files), "--n-trials", "3", "--n-startup-trials", "1")
    assert code == 0, err
    assert "3 trials: 3 complete, 0 pruned, 0 failed" in out
    folder = files / "logs" / "optimize" / "CartPole-v1_cartpole"
    study = optuna.load_study(study_name="CartPole-v1_cartpole", storage=default_storage_url(folder))
    assert len(study.trials) == 3
    for trial in study.trials:  # every evaluation reported, so that the pruner can act on it
        assert sorted(trial.intermediate_values) == [0, 1]
        assert trial.value == trial.intermediate_values[1]
        assert (folder / f"trial_{trial.number}" / "ppo" / "CartPole-v1_1" / "evaluations.npz").is_file()

    best_file = folder / "best.yml"
    best = cfg.load_hyperparams_file(best_file)["CartPole-v1"]
    assert best["n_timesteps"] == 512  # the entry's full run, not the trials' 128 steps
    for override in study.best_trial.user_attrs["overrides"]:
        (key,), value = cfg.parse_override(override)
        assert best[key] == value
    code, out, err = run_cli(
        "train",
        "--env",
        "CartPole-v1",
        "--conf",
        best_file,
        "-n",
        "64",
        "--seed",
        "0",
        "-f",
        files / "train",
        "-v",
        "0",
        "--no-progress",
    )
    assert code == 0, err
    run = cfg.load_hyperparams_file(files / "train" / "ppo" / "CartPole-v1_1" / "CartPole-v1" / "config.yml")
    # The run's config.yml is the best entry (-n aside), resolved: every key of it as it was, and more.
    resolved = run["CartPole-v1"]
    assert {k: resolved[k] for k in best if k != "policy_kwargs"} == {
        **{k: v for k, v in best.items() if k != "policy_kwargs"},
        "n_timesteps": 64,
    }
    assert (best.get("policy_kwargs") or {}).items() <= (resolved.get("policy_kwargs") or {}).items()

    # The same study with trials of another length: refused before anything runs.
    code, out, err = run_cli(*tiny_search(files, **{"-n": "256"}), "--n-trials", "1")
    assert code == 2 and err.count("\n") == 1 and "differ in entry" in err
    assert len(optuna.load_study(study_name="CartPole-v1_cartpole", storage=default_storage_url(folder)).trials) == 3


class _AlwaysPrune(optuna.pruners.BasePruner):
    def prune(self, study, trial):
        return True


def test_a_pruned_trial_stops_training(files):
    settings = OptimizeSettings(
        "CartPole-v1",
        conf=str(files / "cartpole.yml"),
        n_timesteps=256,
        n_evaluations=4,
        eval_episodes=1,
        log_folder=files / "logs",
        search_space=files / "space.yml",
        seeds_per_trial=2,
    )
    search = prepare(settings)
    study = optuna.create_study(direction="maximize", pruner=_AlwaysPrune())
    study.optimize(search.objective, n_trials=1)
    (trial,) = study.trials
    assert trial.state == optuna.trial.TrialState.PRUNED
    assert list(trial.intermediate_values) == [0]  # stopped at its first evaluation, the second seed never ran
    assert len(trial.user_attrs["run_dirs"]) == 1


def test_an_invalid_sampled_configuration_fails_its_trial_only(files):
    (files / "space.yml").write_text(SMALL_SPACE + "  n_epochs: {choices: [0, 1]}\n")
    settings = OptimizeSettings(
        "CartPole-v1",
        conf=str(files / "cartpole.yml"),
        n_timesteps=64,
        n_evaluations=1,
        eval_episodes=1,
        log_folder=files / "logs",
        search_space=files / "space.yml",
    )
    search = prepare(settings)
    study = optuna.create_study(
        direction="maximize",
        sampler=optuna.samplers.GridSampler(
            {"learning_rate": [1e-3], "n_steps": [32], "batch_size": [32], "gamma": [0.99], "n_epochs": [0, 1]}
        ),
    )
    study.optimize(search.objective, n_trials=2, catch=(Exception,))
    states = {t.params["n_epochs"]: t for t in study.trials}
    assert states[1].state == optuna.trial.TrialState.COMPLETE
    assert states[0].state == optuna.trial.TrialState.FAIL
    assert "n_epochs=0 must be >= 1" in states[0].user_attrs["error"]


def sampled_entries(env_id, conf=None, rule=None, fixed=(), n=25):
    entry = cfg.resolve_hyperparams(env_id, conf, fixed, rule=rule)
    fixed_keys = [".".join(cfg.parse_override(o)[0]) for o in fixed]
    space = searched_space(load_search_space(env_id), entry, fixed_keys, rule_fixed=rule is not None)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=1))
    for _ in range(n):
        overrides = sample_overrides(study.ask(), space, entry, fixed_keys)
        yield space, overrides, cfg.resolve_hyperparams(env_id, conf, [*fixed, *overrides], rule=rule)


def test_the_packaged_space_samples_consistent_spiking_entries():
    rules = set()
    for space, overrides, entry in sampled_entries("TMazeCue-v0"):
        assert {
            "policy_kwargs.alpha_lr_scale",
            "policy_kwargs.alpha_init_mean",
            "policy_kwargs.rule_kwargs.eta_init",
            "bptt_steps",
            "policy_kwargs.rule",
            "learning_rate",
            "n_steps",
            "batch_size",
            "gamma",
            "gae_lambda",
            "ent_coef",
            "clip_range",
            "max_grad_norm",
        } <= set(space)
        bptt, n_steps, batch = entry["bptt_steps"], entry["n_steps"], entry["batch_size"]
        assert n_steps % bptt == 0 and batch % bptt == 0 and batch <= n_steps * entry["n_envs"]
        assert 0 < entry["policy_kwargs"]["rule_kwargs"]["eta_init"] < 1
        assert entry["use_action_masks"] is True  # the entry's own settings stay
        rules.add(entry["policy_kwargs"]["rule"])
    assert len(rules) > 2
    for space, overrides, entry in sampled_entries("TMazeCue-v0", rule="static", n=3):
        assert "policy_kwargs.rule" not in space
        assert not any(o.startswith(("policy_kwargs.alpha", "policy_kwargs.rule_kwargs")) for o in overrides)
    for space, overrides, entry in sampled_entries(
        "HalfCheetah-v5", fixed=["policy_kwargs.rule_kwargs.eta_init=0.1"], n=5
    ):
        assert entry["policy_kwargs"]["rule_kwargs"]["eta_init"] == 0.1
        assert -0.5 <= entry["policy_kwargs"]["alpha_init_mean"] <= 0.5
    for space, overrides, entry in sampled_entries("HalfCheetah-v5", conf="mlp", n=3):  # no spiking keys for an MLP
        assert not any(k.startswith("policy_kwargs.") or k == "bptt_steps" for k in space)
        low, high = space["learning_rate"][1]  # sampled on the log scale of the space, and applied
        sampled = next(float(o.split("=", 1)[1]) for o in overrides if o.startswith("learning_rate="))
        assert low <= sampled <= high and entry["learning_rate"] == pytest.approx(sampled)


#: Options and the error each gives.
BAD_OPTIONS = {
    "--sampler grid": "unknown sampler 'grid'; accepted: tpe, random",
    "--pruner hyperband": "unknown pruner 'hyperband'; accepted: median, none",
    "--n-trials 0": "--n-trials=0 must be >= 1",
    "--n-evaluations 0": "--n-evaluations=0 must be >= 1",
    "--rule hebb": "unknown rule 'hebb'; accepted: static",
    "--hyperparams n_stepz=3": "unknown hyperparameter 'n_stepz'",
}


@pytest.mark.parametrize("options", BAD_OPTIONS)
def test_bad_input_is_one_line_and_writes_nothing(files, run_cli, options):
    code, out, err = run_cli(*tiny_search(files), *options.split())
    assert code == 2 and err.count("\n") == 1 and err.startswith("sb3-spikeplastic: error: ")
    assert BAD_OPTIONS[options] in err
    assert not (files / "logs").exists()


def test_an_output_path_under_a_file_is_refused(files, run_cli):
    (files / "file").write_text("x")
    code, out, err = run_cli(*tiny_search(files)[:-2], "-f", files / "file" / "logs")
    assert code == 2 and "lies under the file" in err and err.count("\n") == 1
    code, out, err = run_cli(*tiny_search(files), "--storage", files / "file" / "journal.log")
    assert code == 2 and "--storage" in err and err.count("\n") == 1
    assert not (files / "logs").exists()
