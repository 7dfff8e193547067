"""A run folder's ``config.yml`` is the resolved configuration: read back with ``--conf`` it rebuilds the same model
and the same first update, under any later change of the defaults."""

import pytest
import torch

from sb3_spikeplastic.zoo import config as cfg
from sb3_spikeplastic.zoo.experiment import Experiment, resolved_entry

SMALL = ["n_envs=2", "n_steps=32", "bptt_steps=16", "batch_size=32", "n_epochs=1"]


def build(env, config, tmp_path):
    return Experiment(env, config, 0, tmp_path, verbose=0, progress=False).setup()


def parameters(model):
    return [p.detach().clone() for p in model.policy.parameters()]


def after_first_update(model):
    """The parameters after one rollout and its update, every random number generator seeded alike."""
    model.set_random_seed(0)
    model.learn(64)
    return parameters(model)


@pytest.mark.parametrize("env, conf, rule, overrides", [
    ("TMazeCue-v0", None, "ndp-oja", SMALL),
    ("HalfCheetah-v5", "mlp", None, ["n_envs=2", "n_steps=32", "batch_size=32", "n_epochs=1"]),
])
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

    config = cfg.resolve_hyperparams("TMazeCue-v0", None, SMALL, n_timesteps=64)
    entry = resolved_entry(build("TMazeCue-v0", config, tmp_path), config)
    assert entry["grad_clip"] == ppo.POLICY_DEPENDENT_DEFAULTS["grad_clip"][True]
    monkeypatch.setitem(ppo.POLICY_DEPENDENT_DEFAULTS, "grad_clip", ("global", "global"))
    (tmp_path / "config.yml").write_text(cfg.dump_yaml({"TMazeCue-v0": entry}))
    rebuilt = build("TMazeCue-v0", cfg.resolve_hyperparams("TMazeCue-v0", str(tmp_path / "config.yml"), []), tmp_path)
    assert rebuilt.grad_clip == entry["grad_clip"] != "global"
