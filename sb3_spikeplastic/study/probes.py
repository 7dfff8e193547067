"""Probes of trained policies that a study can declare beside its return evaluations.

:func:`action_sensitivity` — how far each observation element moves a policy's action: on the policy's own
noise-free episode (deterministic actions), every step's action is computed again with one raw observation element
shifted by ``shift`` from the same recurrent state, through the run's frozen ``VecNormalize`` statistics; the
sensitivity of an element is the absolute change of the clipped action, averaged over the action's dimensions and
the episode's steps (0: the policy ignores the element).
"""

from __future__ import annotations

import numpy as np


def action_sensitivity(model, env, shift: float) -> np.ndarray:
    """Mean absolute change of the clipped action per raw observation element shifted by ``shift``, over one
    episode of ``env`` (a 1-environment ``VecNormalize`` with frozen statistics, or a plain ``VecEnv``).

    :param model: a trained algorithm (recurrent state carried by ``predict``)
    :param env: the seeded evaluation environment
    :param shift: the shift of one raw observation element
    :return: one value per observation element
    """
    obs = env.reset()
    normalize = getattr(env, "normalize_obs", lambda o: o)
    low, high = env.action_space.low, env.action_space.high
    state, start, done = None, np.ones(1, dtype=bool), False
    total, steps = np.zeros(env.observation_space.shape[0]), 0
    while not done:
        raw = env.get_original_obs() if hasattr(env, "get_original_obs") else obs
        action, new_state = model.predict(obs, state=state, episode_start=start, deterministic=True)
        action = np.clip(action, low, high)
        for i in range(total.size):
            shifted = raw.copy()
            shifted[:, i] += shift
            moved, _ = model.predict(normalize(shifted), state=state, episode_start=start, deterministic=True)
            total[i] += np.abs(np.clip(moved, low, high) - action).mean()
        obs, _, dones, _ = env.step(action)
        state, start, done, steps = new_state, np.zeros(1, dtype=bool), bool(dones[0]), steps + 1
    return total / steps


def observation_sd(env) -> np.ndarray:
    """The standard deviation of each observation element in a ``VecNormalize``'s statistics (NaN without)."""
    if hasattr(env, "obs_rms"):
        return np.sqrt(env.obs_rms.var)
    return np.full(env.observation_space.shape[0], np.nan)
