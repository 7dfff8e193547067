"""The bare policy, ``PPO("SpikePlasticPolicy", env)``: its network by observation kind, the observation
standardisation (saved with the model, frozen outside training, composed with VecNormalize), models saved under the
previous defaults, and the initial alpha that keeps the plastic trace's loop from exploding on HalfCheetah."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecNormalize

from sb3_spikeplastic import PPO, SpikePlasticPolicy
from sb3_spikeplastic.sb3.policy import previous_defaults_filled
from sb3_spikeplastic.snn.network import ALPHA_REFERENCE_FAN_IN
from sb3_spikeplastic.snn.plasticity import DPOjaRule

CHEETAH = "HalfCheetah-v5"


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
    paper_form = PPO(
        "SpikePlasticPolicy", CHEETAH, policy_kwargs=dict(rule="ndp-oja", rule_kwargs=dict(modulation="linear"))
    )
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
    old = PPO(
        "SpikePlasticPolicy",
        env,
        n_steps=64,
        batch_size=64,
        seed=0,
        policy_kwargs=previous_defaults_filled(given, env.observation_space, env.action_space),
    )
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


def last_action_gradient(policy, obs, steps):
    """Norm of the gradient of the last step's mean action, after ``steps`` steps of BPTT from a warmed state,
    with respect to the first layer's weights."""
    snn = policy.snn
    state = snn.initial_state(obs.shape[1])
    with torch.no_grad():
        for k in range(8):
            _, state = snn(obs[k], state)
    snn.zero_grad()
    outputs, _ = snn.forward_sequence(obs[8 : 8 + steps], torch.zeros(steps, obs.shape[1]), state)
    outputs[-1].action.sum().backward()
    return snn.layers[0].weight.grad.norm().item()


@pytest.fixture(scope="module")
def cheetah_observations():
    env = gym.make(CHEETAH)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    seq = []
    for _ in range(32):
        obs, *_ = env.step(rng.uniform(-1, 1, 6).astype(np.float32))
        seq.append(obs)
    # Rough normalisation, as VecNormalize gives the policy; 4 environments from shifted windows.
    seq = np.array(seq, dtype=np.float32)
    seq = (seq - seq.mean(0)) / (seq.std(0) + 1e-3)
    return torch.tensor(np.stack([np.roll(seq, 3 * i, axis=0) for i in range(4)], 1))


def test_positive_mean_alpha_makes_the_trace_loop_explode_and_the_shipped_init_does_not(cheetah_observations):
    # dp-oja with the rule's default alpha (positive mean, tuned for the T-maze's memory): the trace's Hebbian
    # loop E -> firing -> E gains ~7x per environment step, so the gradient grows geometrically with BPTT length.
    # With zero-mean alpha (the HalfCheetah entries) it stays at the static network's scale.
    space, action_space = gym.make(CHEETAH).observation_space, gym.make(CHEETAH).action_space
    small = dict(
        hidden_sizes=(32, 32),
        steps=10,
        encoder_pop_size=10,
        action_pop_size=20,
        rule="dp-oja",
        encoder_beta=15.0,
        neuron=dict(tau_s=10.0),
    )
    positive = [DPOjaRule.alpha_init_mean * ALPHA_REFERENCE_FAN_IN / n for n in (170, 32, 32)]  # the rule's scaling
    torch.manual_seed(0)
    exploding = SpikePlasticPolicy(
        space,
        action_space,
        lambda _: 1e-3,
        alpha_init_mean=positive,
        alpha_init_std=[0.1 * a for a in positive],
        **small,
    )
    torch.manual_seed(0)
    bounded = SpikePlasticPolicy(space, action_space, lambda _: 1e-3, alpha_init_mean=0.0, alpha_init_std=1.0, **small)
    growth = last_action_gradient(exploding, cheetah_observations, 12) / last_action_gradient(
        exploding, cheetah_observations, 4
    )
    assert growth > 1e3
    bounded_growth = last_action_gradient(bounded, cheetah_observations, 12) / last_action_gradient(
        bounded, cheetah_observations, 4
    )
    assert bounded_growth < 10
