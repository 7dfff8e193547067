"""HalfCheetah with the shipped hyperparameters: gradients stay finite and updates move the policy; the plastic
trace's Hebbian loop and the guard against a non-finite gradient."""

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from sb3_spikeplastic import PPO, SpikePlasticPolicy
from sb3_spikeplastic.zoo.config import model_arguments, normalize_arguments, resolve_hyperparams
from sb3_spikeplastic.snn.network import ALPHA_REFERENCE_FAN_IN
from sb3_spikeplastic.snn.plasticity import DPOjaRule

ENV_ID = "HalfCheetah-v5"


def shipped_model(seed=0, conf=None, **overrides):
    """A model built from the packaged HalfCheetah-v5 entry (``conf``: another packaged file) with ``overrides``
    (e.g. a smaller rollout)."""
    config = resolve_hyperparams(ENV_ID, conf, [f"{k}={v}" for k, v in overrides.items()])
    n_envs = config["n_envs"]
    policy, ppo_kwargs, policy_kwargs = model_arguments(config)
    env = make_vec_env(ENV_ID, n_envs, seed=seed)
    norm = normalize_arguments(config)
    if norm is not None:
        env = VecNormalize(env, **norm)
    return PPO(policy, env, **ppo_kwargs, policy_kwargs=policy_kwargs, seed=seed)


def test_shipped_entry_updates_move_the_policy_with_finite_gradients():
    model = shipped_model(n_envs=2, n_steps=32, batch_size=64, n_epochs=2, bptt_steps=16)
    spiking = {n: p.detach().clone() for n, p in model.policy.snn.named_parameters()}
    log_std = model.policy.log_std.detach().clone()
    model.learn(3 * 2 * 32)
    values = model.logger.name_to_value
    assert values["train/approx_kl"] > 0
    assert math.isfinite(values["train/grad_norm"]) and values["train/skipped_steps"] == 0
    assert not torch.equal(model.policy.log_std, log_std)
    for name, p in model.policy.snn.named_parameters():  # every spiking layer learns, not only the readouts
        if name.endswith("weight"):
            assert not torch.equal(p, spiking[name]), name


def test_paper_network_updates_with_finite_gradients():
    model = shipped_model(conf="paper", n_envs=2, n_steps=20, batch_size=40, n_epochs=2)
    assert model.policy.snn.sizes == [12 * 50, 64, 64, 6 * 100] and model.policy.snn.steps == 50
    log_std = model.policy.log_std.detach().clone()
    weights = [layer.weight.detach().clone() for layer in model.policy.snn.layers]
    model.learn(2 * 2 * 20)  # two rollouts: at the first update the annealed rate is still half its start
    values = model.logger.name_to_value
    assert values["train/skipped_steps"] == 0 and math.isfinite(values["train/grad_norm"])
    assert not torch.equal(model.policy.log_std, log_std)
    for layer, before in zip(model.policy.snn.layers, weights):
        assert not torch.equal(layer.weight, before)


def last_action_gradient(policy, obs, steps):
    """Norm of the gradient of the last step's mean action, after ``steps`` steps of BPTT from a warmed state,
    with respect to the first layer's weights."""
    snn = policy.snn
    state = snn.initial_state(obs.shape[1])
    with torch.no_grad():
        for k in range(8):
            _, state = snn(obs[k], state)
    snn.zero_grad()
    outputs, _ = snn.forward_sequence(obs[8:8 + steps], torch.zeros(steps, obs.shape[1]), state)
    outputs[-1].action.sum().backward()
    return snn.layers[0].weight.grad.norm().item()


@pytest.fixture(scope="module")
def cheetah_observations():
    env = gym.make(ENV_ID)
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
    space, action_space = gym.make(ENV_ID).observation_space, gym.make(ENV_ID).action_space
    small = dict(hidden_sizes=(32, 32), steps=10, encoder_pop_size=10, action_pop_size=20, rule="dp-oja",
                 encoder_beta=15.0, neuron=dict(tau_s=10.0))
    positive = [DPOjaRule.alpha_init_mean * ALPHA_REFERENCE_FAN_IN / n for n in (170, 32, 32)]  # the rule's scaling
    torch.manual_seed(0)
    exploding = SpikePlasticPolicy(space, action_space, lambda _: 1e-3, alpha_init_mean=positive,
                                   alpha_init_std=[0.1 * a for a in positive], **small)
    torch.manual_seed(0)
    bounded = SpikePlasticPolicy(space, action_space, lambda _: 1e-3, alpha_init_mean=0.0, alpha_init_std=1.0, **small)
    growth = last_action_gradient(exploding, cheetah_observations, 12) / last_action_gradient(
        exploding, cheetah_observations, 4)
    assert growth > 1e3
    bounded_growth = last_action_gradient(bounded, cheetah_observations, 12) / last_action_gradient(
        bounded, cheetah_observations, 4)
    assert bounded_growth < 10


def test_nonfinite_gradient_skips_the_step_counts_it_and_warns_once():
    model = shipped_model(n_envs=2, n_steps=32, batch_size=64, n_epochs=2, bptt_steps=16)
    before = {n: p.detach().clone() for n, p in model.policy.named_parameters()}
    model.policy.snn.layers[0].weight.register_hook(lambda g: g * float("inf"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.learn(2 * 32)
    nonfinite = [w for w in caught if "non-finite gradient norm" in str(w.message)]
    assert len(nonfinite) == 1
    # one rollout of 64 transitions, one minibatch per epoch, two epochs: both steps skipped
    assert model.logger.name_to_value["train/skipped_steps"] == 2
    for name, p in model.policy.named_parameters():
        assert torch.equal(p, before[name]), name  # neither NaN nor moved


@pytest.mark.slow
def test_short_run_of_the_shipped_entry_passes_a_return_of_1500():
    """100k steps of the shipped entry (~6 min on one core): the deterministic policy passes a return of 1500, as
    the README says, far above a uniformly random policy (about -280 per episode) and standing still (about 0)."""
    from stable_baselines3.common.evaluation import evaluate_policy

    model = shipped_model()
    model.learn(100_000)
    train_env = model.get_vec_normalize_env()
    eval_env = VecNormalize(make_vec_env(ENV_ID, 1, seed=123), training=False, norm_reward=False)
    eval_env.obs_rms = train_env.obs_rms
    trained, _ = evaluate_policy(model, eval_env, n_eval_episodes=5, deterministic=True)
    assert trained > 1500.0, trained


def test_auto_threads_split_the_halfcheetah_entry_but_not_small_policies():
    """``train --torch-threads auto``: every core for the HalfCheetah entry (a 170 x 64 input layer) and for an
    LSTM's 1024 x 256 matrices, one for the T-maze entry's 40 x 64 layer and SB3's 64 x 64 MlpPolicy."""
    from sb3_contrib import RecurrentPPO

    from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
    from sb3_spikeplastic.zoo.experiment import training_threads

    small = dict(n_envs=1, n_steps=32, batch_size=32)
    cheetah = shipped_model(**small, bptt_steps=16).policy
    assert training_threads(cheetah, 4) == 4
    # On a loaded machine only the free cores: a thread on a busy core waits for the others.
    assert [training_threads(cheetah, 4, load) for load in (0.4, 1.0, 2.6, 3.7, 9.0)] == [4, 3, 1, 1, 1]
    assert training_threads(shipped_model(conf="mlp", **small).policy, 4) == 1
    assert training_threads(RecurrentPPO("MlpLstmPolicy", ENV_ID, n_steps=32, batch_size=32).policy, 4) == 4
    policy, ppo_kwargs, policy_kwargs = model_arguments(resolve_hyperparams("TMazeCue-v0", None, []))
    tmaze = PPO(policy, make_vec_env(TMazeCueEnv, 1), **{**ppo_kwargs, "n_steps": 64, "batch_size": 64},
                policy_kwargs=policy_kwargs)
    assert training_threads(tmaze.policy, 4) == 1
