"""sb3-spikeplastic: spiking neural network policies with differentiable plasticity for Stable-Baselines3.

Importing the package registers the environments (``TMazeCue-v0``, ``TMazeCueNoisy-v0``,
``NoisyHalfCheetah-v5``) and the policy name ``"SpikePlasticPolicy"`` for :class:`sb3_spikeplastic.PPO`.
"""

import stable_baselines3

from . import envs  # noqa: F401  (registers the Gymnasium environments)
from .plasticity import PlasticityRule, available_rules, register_rule
from .policy import MisusedSpikePlasticPolicy, SpikePlasticPolicy
from .ppo import PPO

# stable_baselines3.PPO("SpikePlasticPolicy", ...) would otherwise fail with "unknown policy"; resolve the name
# to a class that refuses at construction with a message that points to sb3_spikeplastic.PPO.
stable_baselines3.PPO.policy_aliases.setdefault("SpikePlasticPolicy", MisusedSpikePlasticPolicy)
stable_baselines3.A2C.policy_aliases.setdefault("SpikePlasticPolicy", MisusedSpikePlasticPolicy)

__version__ = "0.1.0"
__all__ = ["PPO", "SpikePlasticPolicy", "PlasticityRule", "register_rule", "available_rules"]
