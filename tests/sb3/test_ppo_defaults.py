"""PPO's defaults, the bare line ``PPO("SpikePlasticPolicy", env)`` with no other argument: its gradients stay
finite and moderate for every built-in rule, its updates move the policy, only the documented defaults differ from
SB3's (``MlpPolicy`` keeps SB3's), and (``slow``) it learns HalfCheetah. The bare policy itself: test_policy.py."""

import inspect
import math

import gymnasium as gym
import numpy as np
import pytest
import stable_baselines3
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_spikeplastic import PPO

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
    # Two of SB3's defaults depend on the policy (``None``, resolved when the model is built), as does grad_clip.
    assert {name for name, parameter in sb3.items() if ours[name].default != parameter.default} == {
        "learning_rate",
        "batch_size",
    }
    assert ours["learning_rate"].default is ours["batch_size"].default is ours["grad_clip"].default is None
    mlp = PPO("MlpPolicy", "CartPole-v1")
    reference = stable_baselines3.PPO("MlpPolicy", "CartPole-v1")
    for key in ("learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda", "max_grad_norm"):
        assert getattr(mlp, key) == getattr(reference, key), key
    assert mlp.grad_clip == "global"
    # A spiking policy's values, as PPO's docstring gives them (and the shipped entries use).
    spiking = PPO("SpikePlasticPolicy", "CartPole-v1")
    assert (spiking.learning_rate, spiking.batch_size, spiking.grad_clip) == (1e-3, 256, "per-parameter")


def test_a_batch_size_that_does_not_tile_the_default_chunks_is_one_line():
    with pytest.raises(ValueError, match=r"^batch_size=100 \(transitions\) must be a multiple of bptt_steps=32$"):
        PPO("SpikePlasticPolicy", "CartPole-v1", batch_size=100)


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
    trained, _ = evaluate_policy(
        model, make_vec_env(CHEETAH, n_envs=1, seed=1000), n_eval_episodes=10, deterministic=True
    )
    random = random_policy_return(CHEETAH, 10, seed=1000)
    assert trained > random + 500, (trained, random)
