"""sb3-spikeplastic: spiking neural network policies with differentiable plasticity for Stable-Baselines3.

Importing the package registers the environments (``TMazeCue-v0``, ``TMazeCueNoisy-v0``,
``NoisyHalfCheetah-v5``) and nothing else: torch and Stable-Baselines3 load when one of the names below is first
used (``sb3_spikeplastic.PPO``...), so that ``sb3_spikeplastic.envs`` and the command line's ``--help`` stay light.
"""

import importlib
from typing import Any

from . import envs  # noqa: F401  (registers the Gymnasium environments)

__version__ = "0.1.0"

#: Public name -> the module that defines it (imported on first use, PEP 562).
_LAZY = {
    "PPO": "ppo",
    "SpikePlasticPolicy": "policy",
    "PlasticityRule": "plasticity",
    "register_rule": "plasticity",
    "available_rules": "plasticity",
    "load_hyperparams": "config",
    "Ablation": "ablation",
    "ablated": "ablation",
}
__all__ = list(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value  # later lookups skip this hook
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
