"""The spiking policy's input code as an MLP's input: ``PlaceCellFeatures`` gives exactly the spiking policy's encoder
probabilities, ``SpikeCountFeatures`` spike counts drawn with them over the spiking policy's T steps, replayed for
the same observation."""

import gymnasium
import numpy as np
import pytest
import torch

from sb3_spikeplastic import PPO
from sb3_spikeplastic.sb3.encoder_features import PlaceCellFeatures, SpikeCountFeatures


@pytest.fixture(scope="module")
def cheetah_spaces():
    env = gymnasium.make("HalfCheetah-v5")
    yield env.observation_space, env.action_space
    env.close()


@pytest.fixture(scope="module")
def spiking_policy(cheetah_spaces):
    """The bare spiking policy of HalfCheetah's spaces, whose input code the features reproduce."""
    return PPO("SpikePlasticPolicy", "HalfCheetah-v5", n_steps=64, batch_size=64, device="cpu").policy


def test_features_are_the_spiking_policys_encoder_probabilities(cheetah_spaces, spiking_policy):
    features = PlaceCellFeatures(cheetah_spaces[0])
    obs = torch.tensor(np.random.default_rng(0).normal(0, 2.5, size=(8, 17)), dtype=torch.float32)
    obs[0, 0] = 7.0  # beyond the bound: clipped as the spiking encoder clips
    expected = spiking_policy.snn.encoder.probabilities(obs)
    assert features.features_dim == expected.shape[1] == 17 * 10
    torch.testing.assert_close(features(obs), expected, rtol=0, atol=0)
    # by hand: cell k of dimension 1, centre -3 + 6 k / 9, beta 0.5, floor 0.05
    k, x = 4, float(obs[1, 1])
    assert float(features(obs)[1, 10 + k]) == pytest.approx(
        max(np.exp(-0.5 * (-3 + 6 * k / 9 - x) ** 2), 0.05), rel=1e-5
    )
    # the edge cell of the clipped value: 7.0 reads as 3.0, where the last cell (centre 3) fires with probability 1
    assert float(features(obs)[0, 9]) == pytest.approx(1.0)


def test_spike_counts_replay_for_the_same_observation_and_average_to_the_probabilities(cheetah_spaces, spiking_policy):
    features = SpikeCountFeatures(cheetah_spaces[0])
    steps = spiking_policy.snn.steps  # the spiking policy's T for vector observations
    assert features.steps == steps
    obs = torch.tensor(np.random.default_rng(1).normal(0, 1.0, size=(4, 17)), dtype=torch.float32)
    counts = features(obs)
    torch.testing.assert_close(features(obs.clone()), counts, rtol=0, atol=0)  # PPO's update sees the rollout's
    assert torch.equal(counts * steps, (counts * steps).round())  # spike counts over T steps
    assert not torch.equal(features(obs + 1e-3), counts)  # another observation, other spikes
    # over many distinct observations of the same cell probabilities the counts average to those probabilities
    many = obs[:1].repeat(4000, 1)
    many[:, 16] += torch.linspace(0, 1e-3, 4000)  # distinct bits, probabilities of the other dimensions unchanged
    mean = features(many)[:, :160].mean(0)
    torch.testing.assert_close(mean, features.encoder.probabilities(obs[:1])[0, :160], rtol=0, atol=0.02)
    # counts over another T are multiples of 1 / T
    three = SpikeCountFeatures(cheetah_spaces[0], steps=3)(obs)
    assert torch.equal(three * 3, (three * 3).round()) and not torch.equal(three * steps, (three * steps).round())
