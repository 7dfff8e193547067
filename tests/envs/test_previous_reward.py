"""The previous-reward wrapper: what it appends, when, and the spaces it accepts."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from sb3_spikeplastic.envs import PreviousReward


def test_the_previous_reward_and_one_hot_action_follow_the_observation():
    env = PreviousReward(gymnasium.make("CartPole-v1"), action=True)
    assert env.observation_space.shape == (4 + 1 + 2,)
    obs, _ = env.reset(seed=0)
    assert obs[4:].tolist() == [0.0, 0.0, 0.0]  # nothing received, nothing done yet
    inner = env.unwrapped.state
    assert np.allclose(obs[:4], inner)
    obs, reward, *_ = env.step(1)
    assert reward == 1.0 and obs[4:].tolist() == [1.0, 0.0, 1.0]
    obs, *_ = env.step(0)
    assert obs[4:].tolist() == [1.0, 1.0, 0.0]
    obs, _ = env.reset(seed=1)
    assert obs[4:].tolist() == [0.0, 0.0, 0.0]  # a new episode starts without the last one's reward


def test_a_box_action_is_appended_as_it_is_and_the_reward_alone_by_default():
    env = PreviousReward(gymnasium.make("Pendulum-v1"), action=True)
    env.reset(seed=0)
    obs, reward, *_ = env.step(np.array([0.5], dtype=np.float32))
    assert obs.shape == (3 + 1 + 1,) and obs[3] == pytest.approx(reward) and obs[4] == pytest.approx(0.5)
    assert np.allclose(env.observation_space.low[4:], [-2.0]) and np.allclose(env.observation_space.high[4:], [2.0])
    plain = PreviousReward(gymnasium.make("Pendulum-v1"))
    plain.reset(seed=0)
    obs, reward, *_ = plain.step(np.array([0.5], dtype=np.float32))
    assert obs.shape == (4,) and obs[3] == pytest.approx(reward)
    check_env(PreviousReward(gymnasium.make("Pendulum-v1"), action=True), skip_render_check=True)


def test_a_raster_observation_is_a_one_line_error_naming_the_alternative():
    with pytest.raises(ValueError, match=r"needs a 1-D Box observation space.*TMazeReversal-v0") as error:
        PreviousReward(gymnasium.make("TMazeCue-v0"))
    assert "\n" not in str(error.value)


def test_the_wrapper_declares_where_the_reward_is():
    env = PreviousReward(gymnasium.make("CartPole-v1"), action=True)
    assert env.reward_input == {"positive": [4]}
    obs, _ = env.reset(seed=0)
    obs, reward, *_ = env.step(1)
    assert obs[env.reward_input["positive"][0]] == reward == 1.0
