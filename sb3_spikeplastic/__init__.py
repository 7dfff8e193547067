"""sb3-spikeplastic: spiking neural network policies with differentiable plasticity for Stable-Baselines3.

The package is layered; each layer imports only the ones before it:

* :mod:`sb3_spikeplastic.snn` — the network in plain PyTorch (neurons, plasticity, coding, layers, kernels)
* :mod:`sb3_spikeplastic.sb3` — the policy and the recurrent PPO
* :mod:`sb3_spikeplastic.zoo` — the experiment tooling behind the command line
* :mod:`sb3_spikeplastic.study` — studies, the robustness protocol, intervals, hyperparameter search
* :mod:`sb3_spikeplastic.cli` — the command line, which only parses and dispatches

Importing the package registers the environments (``TMazeCue-v0``, ``TMazeCueNoisy-v0``, ``TMazeReversal-v0``,
``TMazeReversalNoisy-v0``, ``NoisyHalfCheetah-v5``, ``HalfCheetahSwitch-v5``) and nothing else: torch and
Stable-Baselines3 load when one of the names below is first used (``sb3_spikeplastic.PPO``...), so that
``sb3_spikeplastic.envs`` and the command line's ``--help`` stay light.
"""

import importlib
import importlib.abc
import importlib.util
import sys
from typing import Any

from . import envs  # noqa: F401  (registers the Gymnasium environments)

__version__ = "0.2.0"

#: Public name -> the module that defines it (imported on first use, PEP 562).
_LAZY = {
    "PPO": "sb3.ppo",
    "SpikePlasticPolicy": "sb3.policy",
    "PlasticityRule": "snn.plasticity",
    "register_rule": "snn.plasticity",
    "available_rules": "snn.plasticity",
    "load_hyperparams": "zoo.config",
    "Ablation": "sb3.ablation",
    "ablated": "sb3.ablation",
    "ModulationSource": "sb3.modulation",
    "register_modulation_source": "sb3.modulation",
}
__all__ = list(_LAZY)

#: Modules of 0.1.0 -> where they live now. Saved models name their classes by module (the policy, the rollout
#: buffer, features extractors), so a model saved by 0.1.0 loads through these names.
_MOVED = {
    **{m: f"snn.{m}" for m in ("neurons", "plasticity", "coding", "layers", "network", "energy")},
    **{m: f"sb3.{m}" for m in ("policy", "ppo", "buffers", "cuda_graphs", "encoder_features", "ablation")},
    **{m: f"zoo.{m}" for m in ("config", "experiment", "run_folder", "callbacks", "evaluation", "figures", "enjoy")},
    **{m: f"study.{m}" for m in ("robustness", "intervals", "optimize")},
}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports ``sb3_spikeplastic.<old name>`` as the module that now holds its contents."""

    def find_spec(self, fullname, path=None, target=None):
        package, _, name = fullname.rpartition(".")
        if package != __name__ or name not in _MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        return None  # a placeholder, replaced below

    def exec_module(self, module):
        # The import system returns whatever sys.modules holds under the name once this returns.
        sys.modules[module.__name__] = importlib.import_module(
            f"{__name__}.{_MOVED[module.__name__.rpartition('.')[2]]}"
        )


if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
    sys.meta_path.append(_MovedModuleFinder())


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value  # later lookups skip this hook
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
