"""Models saved by sb3-spikeplastic 0.1.0, whose files name the modules of its flat layout
(``sb3_spikeplastic.policy``, ``.buffers``, ``.encoder_features``), load and act as they did."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

DATA = Path(__file__).parent / "data"


def test_a_spiking_tmaze_model_of_0_1_0_acts_as_before():
    from sb3_spikeplastic import PPO, SpikePlasticPolicy

    model = PPO.load(DATA / "tmaze_ndp_oja_0.1.0.zip", device="cpu")
    assert isinstance(model.policy, SpikePlasticPolicy)
    assert model.policy_kwargs["rule"] == "ndp-oja"
    env = gym.make("TMazeCue-v0")
    obs, _ = env.reset(seed=3)
    state, start, actions = None, np.ones(1, bool), []
    for _ in range(40):
        action, state = model.predict(
            obs[None],
            state=state,
            episode_start=start,
            deterministic=True,
            action_masks=env.unwrapped.action_masks()[None],
        )
        start = np.zeros(1, bool)
        obs, _, terminated, truncated, _ = env.step(int(action[0]))
        actions.append(int(action[0]))
        if terminated or truncated:
            break
    # recorded with 0.1.0 on the same file
    assert actions == [0] * 16 + [1]


def test_an_mlp_with_place_cell_features_of_0_1_0_acts_as_before():
    from stable_baselines3 import PPO

    from sb3_spikeplastic.sb3.encoder_features import PlaceCellFeatures

    model = PPO.load(DATA / "pendulum_place_cells_0.1.0.zip", device="cpu")
    assert isinstance(model.policy.features_extractor, PlaceCellFeatures)
    action = model.predict(np.linspace(-1, 1, 3, dtype=np.float32)[None], deterministic=True)[0]
    assert action[0, 0] == pytest.approx(0.0021592234261333942, abs=1e-7)


def test_old_module_names_are_the_new_modules():
    import sb3_spikeplastic.policy as old
    import sb3_spikeplastic.sb3.policy as new

    assert old is new
