"""The bare line, ``PPO("SpikePlasticPolicy", env)`` with no other argument: its gradients stay finite and moderate
for every built-in rule, its updates move the policy, the observation standardisation is saved with the model,
``MlpPolicy`` keeps SB3's defaults, and (``slow``) it learns HalfCheetah."""

import inspect
import math

import gymnasium as gym
import numpy as np
import pytest
import stable_baselines3
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecNormalize

from sb3_spikeplastic import PPO
from sb3_spikeplastic.sb3.policy import previous_defaults_filled
from sb3_spikeplastic.sb3.ppo import POLICY_DEPENDENT_DEFAULTS

CHEETAH = "HalfCheetah-v5"
RULES = ["static", "dp-linear", "dp-oja", "dp-bcm", "ndp-oja", "ndp-bcm"]
#: A bound on the global gradient norm (before clipping) that the bare line stays far below; the defaults before
#: zero-mean alpha and the bounded modulation reached 1e16-1e18.
GRAD_NORM_BOUND = 1e4


def record_gradient_norms(model):
    """Every minibatch's global gradient norm before clipping (``nan`` where a step was skipped)."""
    norms, clip = [], model._clip_gradients

    def recording():
        total = clip()
        norms.append(math.nan if total is None else total)
        return total

    model._clip_gradients = recording
    return norms


def test_bare_halfcheetah_updates_keep_gradients_moderate_and_move_the_policy():
    model = PPO("SpikePlasticPolicy", CHEETAH, seed=0)
    assert (model.n_steps, model.batch_size, model.bptt_steps, model.grad_clip) == (2048, 256, 32, "per-parameter")
    norms = record_gradient_norms(model)
    weights = {n: p.detach().clone() for n, p in model.policy.snn.named_parameters() if n.endswith("weight")}
    log_std = model.policy.log_std.detach().clone()
    model.learn(2048)  # one update of the true defaults: ten epochs of eight minibatches
    assert len(norms) == 10 * 2048 // 256
    assert all(math.isfinite(n) for n in norms) and max(norms) < GRAD_NORM_BOUND, max(norms)
    assert model.logger.name_to_value["train/skipped_steps"] == 0
    assert not torch.equal(model.policy.log_std, log_std)  # the action std moves
    for name, p in model.policy.snn.named_parameters():  # every spiking layer learns, not only the readout
        if name in weights:
            assert not torch.equal(p, weights[name]), name


@pytest.mark.parametrize("rule", RULES)
def test_every_rule_of_the_bare_halfcheetah_line_has_finite_gradients(rule):
    # One rollout of 256 steps (one minibatch, ten epochs): every other setting is the default.
    model = PPO("SpikePlasticPolicy", CHEETAH, n_steps=256, seed=0, policy_kwargs=dict(rule=rule))
    norms = record_gradient_norms(model)
    model.learn(256)
    assert len(norms) == 10 and all(math.isfinite(n) for n in norms), norms
    assert max(norms) < GRAD_NORM_BOUND, norms


def test_spiking_defaults_differ_from_sb3_only_where_documented_and_mlp_keeps_sb3s():
    sb3 = inspect.signature(stable_baselines3.PPO.__init__).parameters
    ours = inspect.signature(PPO.__init__).parameters
    for name, parameter in sb3.items():
        if name not in POLICY_DEPENDENT_DEFAULTS:
            assert ours[name].default == parameter.default, name
    mlp = PPO("MlpPolicy", "CartPole-v1")
    reference = stable_baselines3.PPO("MlpPolicy", "CartPole-v1")
    for key in ("learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda", "max_grad_norm"):
        assert getattr(mlp, key) == getattr(reference, key), key
    assert mlp.grad_clip == "global"
    spiking = PPO("SpikePlasticPolicy", "CartPole-v1")
    assert (spiking.learning_rate, spiking.batch_size, spiking.grad_clip) == tuple(
        POLICY_DEPENDENT_DEFAULTS[k][1] for k in ("learning_rate", "batch_size", "grad_clip"))


def test_a_batch_size_that_does_not_tile_the_default_chunks_is_one_line():
    with pytest.raises(ValueError, match=r"^batch_size=100 \(transitions\) must be a multiple of bptt_steps=32$"):
        PPO("SpikePlasticPolicy", "CartPole-v1", batch_size=100)


def test_bare_policy_shapes_by_observation_kind():
    cheetah = PPO("SpikePlasticPolicy", CHEETAH).policy
    assert cheetah.snn.sizes == [17 * 10, 64, 64, 6 * 20] and cheetah.snn.steps == 10
    assert cheetah.snn.neuron.tau_s == 2.0 and cheetah.snn_config["critic"] == "mlp"
    assert cheetah.obs_standardizer.active
    assert float(torch.exp(cheetah.log_std.detach()).mean()) == pytest.approx(math.exp(-2))
    alpha = torch.cat([layer.alpha.flatten() for layer in cheetah.snn.layers])
    assert abs(alpha.mean().item()) < 0.1 and alpha.std().item() == pytest.approx(1.0, rel=0.1)
    for rule in ("ndp-oja", "ndp-bcm"):
        snn = PPO("SpikePlasticPolicy", CHEETAH, policy_kwargs=dict(rule=rule)).policy.snn
        assert {layer.rule.modulation_form for layer in snn.layers} == {"tanh"}
    paper_form = PPO("SpikePlasticPolicy", CHEETAH, policy_kwargs=dict(rule="ndp-oja",
                                                                     rule_kwargs=dict(modulation="linear")))
    assert {layer.rule.modulation_form for layer in paper_form.policy.snn.layers} == {"linear"}
    # Spike rasters: the raster length as T, the paper's neuron constants, the rules' positive alpha, the spiking
    # critic; nothing is standardised. Finite bounds (Pendulum) are not standardised either.
    tmaze = PPO("SpikePlasticPolicy", "TMazeCue-v0").policy
    assert tmaze.snn.steps == 25 and tmaze.snn.neuron.tau_s == 10.0 and tmaze.snn_config["critic"] == "snn"
    assert tmaze.snn.layers[0].alpha.mean().item() > 5 and not tmaze.obs_standardizer.active
    assert not PPO("SpikePlasticPolicy", "Pendulum-v1").policy.obs_standardizer.active


def test_observation_standardisation_is_saved_and_loaded_and_frozen_outside_training(tmp_path):
    env = make_vec_env(CHEETAH, n_envs=2, seed=0)
    model = PPO("SpikePlasticPolicy", env, n_steps=32, batch_size=64, n_epochs=1, seed=0)
    standardizer = model.policy.obs_standardizer
    model.learn(3 * 2 * 32)  # the first two rollouts join the statistics at the next rollout's start
    assert float(standardizer.count) == pytest.approx(2 * 2 * 32, abs=1e-3)
    assert not torch.allclose(standardizer.var, torch.ones_like(standardizer.var))
    obs = env.reset()
    actions, _ = model.predict(obs, deterministic=True)
    evaluate_policy(model, env, n_eval_episodes=1)  # evaluation leaves the statistics as they are
    assert float(standardizer.count) == pytest.approx(2 * 2 * 32, abs=1e-3)
    model.save(tmp_path / "bare")
    loaded = PPO.load(tmp_path / "bare", env=env)
    for name in ("mean", "var", "count"):
        assert torch.equal(getattr(loaded.policy.obs_standardizer, name), getattr(standardizer, name)), name
    assert loaded.policy.snn_config == model.policy.snn_config
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], actions, rtol=0, atol=1e-6)
    # Without the standardisation (e.g. where VecNormalize does it), the same observation gives other actions.
    raw = PPO("SpikePlasticPolicy", env, n_steps=32, batch_size=64, seed=0, policy_kwargs=dict(standardize_obs=False))
    raw.policy.load_state_dict(model.policy.state_dict())
    assert not raw.policy.obs_standardizer.active
    assert not np.allclose(raw.predict(obs, deterministic=True)[0], actions)


def test_a_model_saved_under_the_previous_defaults_loads_as_it_was_built(tmp_path):
    env = make_vec_env(CHEETAH, n_envs=1, seed=0)
    given = {"rule": "ndp-oja", "hidden_sizes": (16,)}
    old = PPO("SpikePlasticPolicy", env, n_steps=64, batch_size=64, seed=0,
              policy_kwargs=previous_defaults_filled(given, env.observation_space, env.action_space))
    assert old.policy.snn.sizes == [17 * 50, 16, 6 * 100] and old.policy.snn.steps == 50
    assert old.policy.snn.layers[0].rule.modulation_form == "linear" and not old.policy.obs_standardizer.active
    old.policy_kwargs = dict(given)  # what the model recorded then: only its user's arguments
    old.save(tmp_path / "old")
    loaded = PPO.load(tmp_path / "old")
    assert loaded.policy.snn_config == old.policy.snn_config
    obs = env.reset()
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], old.predict(obs, deterministic=True)[0])
    # A model saved now records what its defaults resolved to.
    assert PPO("SpikePlasticPolicy", env).policy_kwargs["encoder_pop_size"] == 10


def test_the_standardisation_composes_with_vecnormalize():
    env = VecNormalize(make_vec_env(CHEETAH, n_envs=2, seed=0))
    model = PPO("SpikePlasticPolicy", env, n_steps=32, batch_size=64, n_epochs=1, seed=0)
    model.learn(3 * 2 * 32)
    mean, var = model.policy.obs_standardizer.mean, model.policy.obs_standardizer.var
    # VecNormalize's output is already standardised: the policy's statistics stay near the identity.
    assert mean.abs().max() < 3 and var.max() < 10
    assert math.isfinite(model.logger.name_to_value["train/grad_norm"])


def random_policy_return(env_id, episodes, seed):
    env = gym.make(env_id)
    env.action_space.seed(seed)
    returns = []
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


@pytest.mark.slow
def test_bare_halfcheetah_line_beats_a_random_policy_in_100k_steps():
    torch.set_num_threads(1)
    model = PPO("SpikePlasticPolicy", CHEETAH, seed=0)
    model.learn(100_000)
    trained, _ = evaluate_policy(model, make_vec_env(CHEETAH, n_envs=1, seed=1000), n_eval_episodes=10,
                                 deterministic=True)
    random = random_policy_return(CHEETAH, 10, seed=1000)
    assert trained > random + 500, (trained, random)
