"""Gymnasium environments of sb3-spikeplastic; importing this module registers their ids.

* ``TMazeCue-v0``: the spiking cue-association T-maze, low noise (:class:`TMazeCueEnv`).
* ``TMazeCueNoisy-v0``: the same with the paper's high-noise spike probabilities.
* ``NoisyHalfCheetah-v5``: ``HalfCheetah-v5`` with observation, action and joint-friction noise (``obs_noise``,
  ``action_noise``, ``friction_noise`` standard deviations, ``friction_target``; all 0 by default;
  ``obs_indices`` limits the observation noise to some elements).
* ``TMazeReversal-v0`` / ``TMazeReversalNoisy-v0``: a spiking two-armed T-maze whose paying arm is hidden, must be
  learned from the outcomes within the episode and reverses once (:class:`TMazeReversalEnv`); low / high noise.
* :class:`PreviousReward`: a wrapper that appends the previous reward (and optionally action) to a vector
  observation (the RL² convention), for policies that learn from reward within an episode.
* ``HalfCheetahSwitch-v5``: ``HalfCheetah-v5`` whose dynamics change once during each episode (``kind``,
  ``window``, ``factor_range``, ``target``; :class:`DynamicsSwitch`).

This package imports neither torch nor the rest of the plugin.
"""

import warnings
from typing import Any

import gymnasium

from sb3_spikeplastic.envs.noise import (
    FRICTION_TARGETS,
    NOISE_TYPES,
    ActionNoise,
    FrictionNoise,
    ObservationNoise,
    make_noisy_env,
    noise_kwargs,
)
from sb3_spikeplastic.envs.previous_reward import PreviousReward
from sb3_spikeplastic.envs.reversal import TMazeReversalEnv
from sb3_spikeplastic.envs.switch import SWITCH_KINDS, DynamicsSwitch, make_switch_env
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv

__all__ = [
    "FRICTION_TARGETS",
    "NOISE_TYPES",
    "SWITCH_KINDS",
    "ActionNoise",
    "DynamicsSwitch",
    "FrictionNoise",
    "ObservationNoise",
    "PreviousReward",
    "TMazeCueEnv",
    "TMazeReversalEnv",
    "make_noisy_env",
    "make_switch_env",
    "noise_kwargs",
    "route_mujoco_warnings",
]


def route_mujoco_warnings() -> None:
    """Route MuJoCo's warnings into Python's ``warnings`` (``RuntimeWarning``): shown once per kind instead of once
    per environment built, and no ``MUJOCO_LOG.TXT`` in the working folder. The deprecation of ``settotalmass``,
    which gymnasium's HalfCheetah model triggers at every build, is dropped. The command line does this at start;
    scripts building many MuJoCo environments may call it too."""
    try:
        import mujoco
    except ImportError:
        return

    def warn(message: str) -> None:
        if "settotalmass" in message:  # gymnasium's HalfCheetah model uses it: nothing a user can change
            return
        warnings.warn(f"MuJoCo: {message.strip()}", RuntimeWarning, stacklevel=2)

    mujoco.set_mju_user_warning(warn)


def _register(env_id: str, **kwargs: Any) -> None:
    # Re-registering an id makes gymnasium warn; a reload of this module must stay silent.
    if env_id not in gymnasium.registry:
        gymnasium.register(id=env_id, **kwargs)


_register("TMazeCue-v0", entry_point="sb3_spikeplastic.envs.tmaze:TMazeCueEnv", kwargs={"noise": "low"})
_register("TMazeCueNoisy-v0", entry_point="sb3_spikeplastic.envs.tmaze:TMazeCueEnv", kwargs={"noise": "high"})
_register("TMazeReversal-v0", entry_point="sb3_spikeplastic.envs.reversal:TMazeReversalEnv", kwargs={"noise": "low"})
_register(
    "TMazeReversalNoisy-v0", entry_point="sb3_spikeplastic.envs.reversal:TMazeReversalEnv", kwargs={"noise": "high"}
)
_register(
    "NoisyHalfCheetah-v5",
    entry_point="sb3_spikeplastic.envs.noise:make_noisy_base_env",
    kwargs={
        "base_id": "HalfCheetah-v5",
        "obs_noise": 0.0,
        "action_noise": 0.0,
        "friction_noise": 0.0,
        "friction_target": "damping",
        "obs_indices": None,
    },
    max_episode_steps=1000,
)
_register(
    "HalfCheetahSwitch-v5",
    entry_point="sb3_spikeplastic.envs.switch:make_switch_base_env",
    kwargs={
        "base_id": "HalfCheetah-v5",
        "kind": "actuator_gain",
        "window": (300, 700),
        "factor_range": (0.2, 0.5),
        "target": None,
    },
    max_episode_steps=1000,
)
