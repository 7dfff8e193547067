"""The spiking policy's input code as an MLP's input: SB3 features extractors that read an observation with the
place cells of :class:`~sb3_spikeplastic.snn.coding.PopulationEncoder`, to tell the code's share of a result from the
spiking network's (e.g. ``PPO("MlpPolicy", env, policy_kwargs=dict(features_extractor_class=PlaceCellFeatures))``,
or ``policy_kwargs.features_extractor_class=PlaceCellFeatures`` in a hyperparameter file or a study).

The defaults are :class:`~sb3_spikeplastic.sb3.policy.SpikePlasticPolicy`'s for vector observations, so the MLP sees
what the spiking policy's first layer receives.
"""

from __future__ import annotations

import inspect

import gymnasium
import numpy as np
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from ..snn.coding import PopulationEncoder, hash32
from .policy import VECTOR_STEPS, SpikePlasticPolicy

_ENCODER = {
    k: v.default
    for k, v in inspect.signature(SpikePlasticPolicy).parameters.items()
    if k in ("encoder_pop_size", "encoder_beta", "encoder_p_min", "obs_bounds")
}


class PlaceCellFeatures(BaseFeaturesExtractor):
    r"""The place cells' firing probabilities, without sampling: every observation dimension clipped to
    ``obs_bounds`` and read by ``pop_size`` Gaussian cells, :math:`p = \mathrm{clip}(e^{-\beta(\Omega - x)^2},
    p_{min}, 1)` (SpikePropamine appendix 5.2).

    :param observation_space: a ``Box``
    :param pop_size: cells per dimension
    :param beta: the cells' sharpness
    :param p_min: floor probability
    :param obs_bounds: ``(low, high)`` of every dimension
    """

    def __init__(
        self,
        observation_space: gymnasium.spaces.Box,
        pop_size: int = _ENCODER["encoder_pop_size"],
        beta: float = _ENCODER["encoder_beta"],
        p_min: float = _ENCODER["encoder_p_min"],
        obs_bounds: tuple = tuple(_ENCODER["obs_bounds"]),
    ):
        n = int(np.prod(observation_space.shape))
        super().__init__(observation_space, features_dim=n * pop_size)
        self.encoder = PopulationEncoder(np.full(n, obs_bounds[0]), np.full(n, obs_bounds[1]), pop_size, beta, p_min)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.encoder.probabilities(observations.flatten(1))


class SpikeCountFeatures(PlaceCellFeatures):
    """The place cells' spike counts over ``steps`` network steps divided by ``steps``: Bernoulli spikes with the
    cells' probabilities from the encoder's counter-based sampler, keyed by a hash of the observation's bits, so
    the same observation always draws the same spikes and PPO's update re-evaluates the rollout's inputs.

    :param steps: network steps (the spiking policy's T)
    """

    def __init__(
        self,
        observation_space: gymnasium.spaces.Box,
        pop_size: int = _ENCODER["encoder_pop_size"],
        beta: float = _ENCODER["encoder_beta"],
        p_min: float = _ENCODER["encoder_p_min"],
        obs_bounds: tuple = tuple(_ENCODER["obs_bounds"]),
        steps: int = VECTOR_STEPS,
    ):
        super().__init__(observation_space, pop_size, beta, p_min, obs_bounds)
        self.steps = int(steps)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        obs = observations.flatten(1).to(torch.float32).contiguous()
        keys = torch.zeros(obs.shape[0], dtype=torch.int32, device=obs.device)
        for bits in obs.view(torch.int32).unbind(1):
            keys = hash32(keys ^ bits)
        return self.encoder(obs, keys, self.steps).mean(1)
