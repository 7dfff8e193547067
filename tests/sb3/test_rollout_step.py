"""The policy's step without gradients (rollouts, ``predict``, evaluation): the compiled network step
(:mod:`sb3_spikeplastic.snn.compiled_step`) and the Gaussian sample without distribution objects
(:func:`~sb3_spikeplastic.sb3.policy.diag_gaussian_sample`) give what the modules and SB3's distribution give."""

from __future__ import annotations

import pytest
import torch
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.env_util import make_vec_env

from sb3_spikeplastic import PPO
from sb3_spikeplastic.sb3.policy import diag_gaussian_sample
from sb3_spikeplastic.snn import _fast
from sb3_spikeplastic.snn.network import tensor_leaves


@pytest.mark.parametrize("deterministic", [False, True])
def test_the_gaussian_sample_is_sb3s_distribution_op_for_op(deterministic):
    g = torch.Generator().manual_seed(0)
    mean, log_std = torch.randn(5, 3, generator=g), torch.randn(3, generator=g)
    distribution = DiagGaussianDistribution(3).proba_distribution(mean, log_std)
    torch.manual_seed(1)
    want = distribution.get_actions(deterministic=deterministic)
    want_log_prob, want_next = distribution.log_prob(want), torch.rand(1)
    torch.manual_seed(1)
    got, got_log_prob = diag_gaussian_sample(mean, log_std, deterministic)
    assert torch.equal(got, want) and torch.equal(got_log_prob, want_log_prob)
    assert torch.equal(torch.rand(1), want_next)  # the same draws from the random stream
    assert got_log_prob.shape == (5,) and not torch.equal(got_log_prob, torch.zeros(5))


def rollout(policy, obs_sequence, starts, grad: bool):
    """Each step's ``(actions, values, log_probs)`` and final state, seeded alike: with gradients on, the network runs
    through the layers' autograd nodes and the actions through SB3's distribution; off, through the fast paths."""
    torch.manual_seed(2)
    state, steps = policy.initial_state(obs_sequence.shape[1], seed=3), []
    with torch.set_grad_enabled(grad):
        for obs, start in zip(obs_sequence, starts):
            actions, values, log_probs, state, _ = policy.step(obs, state, start)
            steps.append((actions.detach(), values.detach(), log_probs.detach()))
    return steps, state


@pytest.mark.skipif(_fast.interval_ops() is None, reason="needs the compiled CPU ops")
@pytest.mark.parametrize("rule", ["dp-oja", "ndp-bcm", "static"])
def test_the_rollout_step_without_gradients_equals_the_training_paths_step(rule):
    env = make_vec_env("HalfCheetah-v5", n_envs=3, seed=0)
    policy = PPO("SpikePlasticPolicy", env, policy_kwargs=dict(rule=rule), seed=0).policy
    g = torch.Generator().manual_seed(4)
    obs_sequence = torch.randn(12, 3, 17, generator=g) * 2
    starts = torch.zeros(12, 3)
    starts[5, 1] = 1
    want, want_state = rollout(policy, obs_sequence, starts, grad=True)
    got, got_state = rollout(policy, obs_sequence, starts, grad=False)
    for step_want, step_got in zip(want, got):
        for a, b in zip(step_want, step_got):
            assert torch.equal(a, b)
    for a, b in zip(tensor_leaves(want_state), tensor_leaves(got_state)):
        assert torch.equal(a.detach(), b)
