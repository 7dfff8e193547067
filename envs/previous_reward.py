"""The previous reward (and optionally the previous action) as part of the observation: the convention of RL²
(Duan et al., 2016) and of meta-RL with recurrent policies (Wang et al., 2018), so that a policy can learn from
the rewards of the current episode, and a recurrent baseline gets exactly the input a plastic policy gets."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces


class PreviousReward(gymnasium.Wrapper, gymnasium.utils.RecordConstructorArgs):
    """Appends the reward of the previous step (0 after ``reset``) to a 1-D ``Box`` observation, and with
    ``action=True`` the previous action (one-hot for ``Discrete``, the action itself for ``Box``; zeros after
    ``reset``).

    The observation becomes ``[obs, reward, action...]``: the reward is element ``obs_dim``, the action follows it.
    ``reward_bounds`` are the appended element's bounds in the observation space.

    :param env: an environment with a 1-D ``Box`` observation space.
    :param action: also append the previous action.
    :param reward_bounds: ``(low, high)`` of the reward element (default unbounded).
    """

    def __init__(
        self, env: gymnasium.Env, action: bool = False, reward_bounds: tuple[float, float] = (-np.inf, np.inf)
    ) -> None:
        gymnasium.utils.RecordConstructorArgs.__init__(self, action=action, reward_bounds=reward_bounds)
        gymnasium.Wrapper.__init__(self, env)
        space = env.observation_space
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise ValueError(
                f"PreviousReward needs a 1-D Box observation space, not {space}; spike-raster "
                "environments show outcomes as spikes of their own populations (TMazeReversal-v0)"
            )
        self._action_size = 0
        if action and isinstance(env.action_space, spaces.Discrete):
            self._action_size = int(env.action_space.n)
        elif action and isinstance(env.action_space, spaces.Box) and len(env.action_space.shape) == 1:
            self._action_size = int(env.action_space.shape[0])
        elif action:
            raise ValueError(
                f"PreviousReward(action=True) needs a Discrete or 1-D Box action space, not {env.action_space}"
            )
        self.with_action = bool(action)
        extra = 1 + self._action_size
        if self.with_action and isinstance(env.action_space, spaces.Box):
            action_low, action_high = env.action_space.low, env.action_space.high
        else:
            action_low, action_high = np.zeros(self._action_size), np.ones(self._action_size)
        low = np.concatenate([space.low, [reward_bounds[0]], action_low]).astype(space.dtype)
        high = np.concatenate([space.high, [reward_bounds[1]], action_high]).astype(space.dtype)
        self.observation_space = spaces.Box(low, high, shape=(space.shape[0] + extra,), dtype=space.dtype)
        #: where the observation carries the reward, for the policies that read it
        #: (:class:`sb3_spikeplastic.sb3.modulation.RewardInput`; ``modulation_source="reward"``)
        self.reward_input = {"positive": [int(space.shape[0])]}

    def _observation(self, obs: np.ndarray, reward: float, action: Any) -> np.ndarray:
        encoded = np.zeros(self._action_size, dtype=self.observation_space.dtype)
        if self.with_action and action is not None:
            if isinstance(self.env.action_space, spaces.Discrete):
                encoded[int(action)] = 1.0
            else:
                encoded[:] = np.asarray(action, dtype=encoded.dtype)
        extra = np.concatenate([[reward], encoded]).astype(self.observation_space.dtype)
        return np.concatenate([np.asarray(obs, dtype=self.observation_space.dtype), extra])

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict]:
        obs, info = self.env.reset(**kwargs)
        return self._observation(obs, 0.0, None), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._observation(obs, float(reward), action), reward, terminated, truncated, info
