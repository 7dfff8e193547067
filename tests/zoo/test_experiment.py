"""Experiments, what ``train`` runs: its checks as a Python call (bad input raises ``ValueError`` before the run
folder is created), the run folder's ``config.yml`` (the resolved configuration: read back with ``--conf`` it rebuilds
the same model and the same first update, under any later change of the defaults) and the training threads."""

import pytest
import torch
from helpers import shipped_model

from sb3_spikeplastic.zoo import config as cfg
from sb3_spikeplastic.zoo.experiment import Experiment, make_train_env, resolved_entry
from sb3_spikeplastic.zoo.train import continued_run, train_command, training_threads

#: Overrides of the T-maze entry to one 64-step rollout per update.
ROLLOUT_64 = ["n_envs=2", "n_steps=32", "bptt_steps=16", "batch_size=32", "n_epochs=1"]


@pytest.mark.parametrize(
    "options, message",
    [
        ({"env": "TMazeCue-v0", "eval_freq": -1}, r"^--eval-freq=-1 must be >= 0$"),
        ({"env": "TMazeCue-v0", "rule": "hebb"}, "unknown rule 'hebb'"),
        (
            {
                "env": "TMazeCue-v0",
                "hyperparams": ["policy_kwargs.hidden_sizes=[16]", "bptt_steps=32", "batch_size=48"],
            },
            r"^invalid configuration for TMazeCue-v0: batch_size=48",
        ),
        ({"env": "HalfCheetah-v5", "conf": "mlp", "figure_freq": 1}, "--figure-freq needs policy SpikePlasticPolicy"),
    ],
)
def test_bad_options_raise_before_anything_is_written(options, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        train_command(log_folder=str(tmp_path / "logs"), tensorboard_log=str(tmp_path / "tb"), **options)
    assert list(tmp_path.iterdir()) == []


def test_a_continued_run_keeps_its_configuration(tmp_path):
    with pytest.raises(ValueError, match="continues a run with its own configuration"):
        continued_run(str(tmp_path), "TMazeCue-v0", overridden=True)
    with pytest.raises(FileNotFoundError, match="no run folder or model file"):
        continued_run(str(tmp_path / "nowhere"), "TMazeCue-v0")


def test_auto_threads_split_the_halfcheetah_entry_but_not_small_policies():
    """``train --torch-threads auto``: every core for the HalfCheetah entry (a 170 x 64 input layer) and for an
    LSTM's 1024 x 256 matrices, one for the T-maze entry's 40 x 64 layer and SB3's 64 x 64 MlpPolicy."""
    from sb3_contrib import RecurrentPPO

    small = dict(n_envs=1, n_steps=32, batch_size=32)
    cheetah = shipped_model("HalfCheetah-v5", **small, bptt_steps=16).policy
    assert training_threads(cheetah, 4) == 4
    # On a loaded machine only the free cores: a thread on a busy core waits for the others.
    assert [training_threads(cheetah, 4, load) for load in (0.4, 1.0, 2.6, 3.7, 9.0)] == [4, 3, 1, 1, 1]
    assert training_threads(shipped_model("HalfCheetah-v5", conf="mlp", **small).policy, 4) == 1
    assert training_threads(RecurrentPPO("MlpLstmPolicy", "HalfCheetah-v5", n_steps=32, batch_size=32).policy, 4) == 4
    tmaze = shipped_model("TMazeCue-v0", n_envs=1, n_steps=64, batch_size=64)
    assert training_threads(tmaze.policy, 4) == 1


def build(env, config, tmp_path):
    return Experiment(env, config, 0, tmp_path, verbose=0, progress=False).setup()


def parameters(model):
    return [p.detach().clone() for p in model.policy.parameters()]


def after_first_update(model):
    """The parameters after one rollout and its update, every random number generator seeded alike."""
    model.set_random_seed(0)
    model.learn(64)
    return parameters(model)


@pytest.mark.parametrize(
    "env, conf, rule, overrides",
    [
        ("TMazeCue-v0", None, "ndp-oja", ROLLOUT_64),
        ("HalfCheetah-v5", "mlp", None, ["n_envs=2", "n_steps=32", "batch_size=32", "n_epochs=1"]),
    ],
)
def test_config_yml_rebuilds_the_model_and_its_first_update(tmp_path, env, conf, rule, overrides):
    config = cfg.resolve_hyperparams(env, conf, overrides, rule=rule, n_timesteps=64)
    model = build(env, config, tmp_path)
    entry = resolved_entry(model, config)
    # Every default the model resolved is written down, not only what the file said.
    assert {"gamma", "clip_range", "ent_coef", "batch_size"} <= set(entry)
    if rule:
        assert entry["policy_kwargs"]["rule"] == rule and "encoder_pop_size" in entry["policy_kwargs"]
    (tmp_path / "config.yml").write_text(cfg.dump_yaml({env: entry}))
    again = build(env, cfg.resolve_hyperparams(env, str(tmp_path / "config.yml"), []), tmp_path)
    assert all(torch.equal(a, b) for a, b in zip(parameters(model), parameters(again)))
    updated = after_first_update(model)
    assert all(torch.equal(a, b) for a, b in zip(updated, after_first_update(again)))
    assert not all(torch.equal(a, b) for a, b in zip(updated, parameters(build(env, config, tmp_path))))


def test_a_later_default_does_not_change_a_recorded_run(tmp_path, monkeypatch):
    """The entry records PPO's policy-dependent defaults, so changing one later leaves the rebuilt model alone."""
    from sb3_spikeplastic.sb3 import ppo

    config = cfg.resolve_hyperparams("TMazeCue-v0", None, ROLLOUT_64, n_timesteps=64)
    entry = resolved_entry(build("TMazeCue-v0", config, tmp_path), config)
    assert entry["grad_clip"] == ppo.POLICY_DEPENDENT_DEFAULTS["grad_clip"][True]
    monkeypatch.setitem(ppo.POLICY_DEPENDENT_DEFAULTS, "grad_clip", ("global", "global"))
    (tmp_path / "config.yml").write_text(cfg.dump_yaml({"TMazeCue-v0": entry}))
    rebuilt = build("TMazeCue-v0", cfg.resolve_hyperparams("TMazeCue-v0", str(tmp_path / "config.yml"), []), tmp_path)
    assert rebuilt.grad_clip == entry["grad_clip"] != "global"


def test_subprocess_environments_route_mujoco_warnings(mujoco_log_in_tmp):
    """`--vec-env subproc`: each environment's process routes MuJoCo's warnings itself (a spawned process does not
    inherit the parent's route), so HalfCheetah's deprecation notice writes no ./MUJOCO_LOG.TXT there."""
    venv = make_train_env("HalfCheetah-v5", 2, {}, vec_env="subproc")
    venv.reset()
    venv.close()
    assert not (mujoco_log_in_tmp / "MUJOCO_LOG.TXT").exists()
