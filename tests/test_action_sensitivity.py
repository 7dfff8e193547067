"""The action-sensitivity probe of the HalfCheetah protocol: each element's shift moves the action by what the policy
makes of it, from the unshifted step's state, and the table summarises the seeds of each group."""

import numpy as np
import pytest
from helpers import load_experiment

from sb3_spikeplastic.run_folder import make_eval_env


@pytest.fixture(scope="module")
def probe():
    return load_experiment("action_sensitivity")


class CountingPolicy:
    """Action 0 is ``20 * obs[8]`` (mostly beyond the action bound 1, where the probe clips it), the rest 0; the
    state counts the steps and must reach every call of one step unchanged."""

    def __init__(self):
        self.states = []

    def predict(self, obs, state=None, episode_start=None, deterministic=False):
        assert deterministic
        state = 0 if state is None else state
        assert bool(episode_start[0]) == (state == 0)
        self.states.append(state)
        action = np.zeros((obs.shape[0], 6), dtype=np.float32)
        action[:, 0] = 20.0 * obs[:, 8]
        return action, state + 1


def test_sensitivity_is_the_clipped_action_change_of_each_element(probe):
    env = make_eval_env(probe.ENV, 1, seed=3)
    policy = CountingPolicy()
    sensitivity = probe.action_sensitivity(policy, env, shift=0.1)
    steps = len(policy.states) // 18
    assert steps == 1000 and policy.states == [s for s in range(steps) for _ in range(18)]
    assert np.all(sensitivity[np.arange(17) != 8] == 0)
    # unclipped, 20 * 0.1 on one of 6 action dimensions; the clip at 1 removes most of it
    assert 0.0 < sensitivity[8] < 0.2 * 2.0 / 6


def test_unclipped_linear_policy_scores_its_gain(probe):
    class Linear(CountingPolicy):
        def predict(self, obs, state=None, episode_start=None, deterministic=False):
            action = np.zeros((obs.shape[0], 6), dtype=np.float32)
            action[:, 1] = 0.5 * np.tanh(obs[:, 0])  # |action| < 1: never clipped
            return action, state

    sensitivity = probe.action_sensitivity(Linear(), make_eval_env(probe.ENV, 1, seed=3), shift=0.01)
    # d/dx 0.5 tanh(x) at the root's height (|x| < 0.3) is within [0.5 (1 - tanh^2 0.31), 0.5]
    assert 0.5 * 0.01 / 6 * 0.9 < sensitivity[0] < 0.5 * 0.01 / 6 + 1e-6
    assert np.all(sensitivity[1:] == 0)


def test_table_reports_mean_and_range_over_seeds(probe):
    def model(height, angle, sd):
        values = np.zeros(17)
        values[0], values[1:8], values[8:] = height, angle, 0.001
        return values, sd

    data = {"mlp@300k_s0": model(0.1, 0.02, 0.05), "mlp@300k_s1": model(0.2, 0.02, 0.15),
            "static@300k_s0": model(0.02, 0.02, 0.1)}
    lines = probe.table(data, 0.1).splitlines()
    assert "| group | seeds | height | angles | velocities | height / angles | s.d. of height |" in lines
    assert "| mlp@300k | 2 | 0.150 (0.100-0.200) | 0.020 (0.020-0.020) | 0.001 (0.001-0.001) | 7.5 (5.0-10.0) " \
           "| 0.100 (0.050-0.150) |" in lines
    assert "| static@300k | 1 | 0.020 (0.020-0.020) | 0.020 (0.020-0.020) | 0.001 (0.001-0.001) | 1.0 (1.0-1.0) " \
           "| 0.100 (0.100-0.100) |" in lines
