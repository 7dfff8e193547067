"""Fixtures of the environment tests."""

import gymnasium
import numpy as np
import pytest


class ActionRecorder(gymnasium.Wrapper):
    """Keeps a copy of every action the environment it wraps receives (``actions``)."""

    def __init__(self, env):
        super().__init__(env)
        self.actions = []

    def step(self, action):
        self.actions.append(np.array(action))
        return self.env.step(action)


@pytest.fixture
def action_recorder():
    """``action_recorder(env)``: ``env`` wrapped so as to keep a copy of every action it receives (``.actions``)."""
    return ActionRecorder
