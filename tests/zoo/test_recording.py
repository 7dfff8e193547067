"""One episode's recorded activity (``record_episode``) and the choice of the episode shown (``typical_seed``)."""

import numpy as np
import torch
from helpers import tmaze_model

from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
from sb3_spikeplastic.zoo.recording import record_episode


def test_record_episode_tmaze_is_complete_and_leaves_global_rng_alone():
    model = tmaze_model("dp-bcm", n_envs=1, env_kwargs={"neurons_per_population": 10})
    env = TMazeCueEnv()
    rng = torch.random.get_rng_state()
    activity = record_episode(model.policy, env, seed=3)
    assert torch.equal(rng, torch.random.get_rng_state())
    assert activity.done and activity.n_steps == env.n_frames
    total = activity.n_steps * 25
    assert activity.input_spikes.shape == (total, 40)
    assert [s.shape for s in activity.spikes] == [(total, 16), (total, 2)]
    assert [m.shape for m in activity.membrane] == [(total, 16), (total, 2)]
    assert activity.traces[0].shape == (activity.n_steps, 16, 40)
    assert activity.modulation == [None, None]  # dp-bcm is not neuromodulated
    maze = TMazeCueEnv()
    maze.reset(seed=3)  # the same episode: its cues decide the correct arm
    assert activity.info["correct_action"] == maze.correct_action
    assert activity.info["is_success"] == (int(activity.actions[-1]) == maze.correct_action)
    assert [g[0] for g in activity.input_groups] == ["left cue", "right cue", "decision", "noise"]
    # the recorded raster is the environment's: same seed, same spikes
    first, _ = TMazeCueEnv().reset(seed=3)
    assert np.array_equal(activity.input_spikes[:25], first)
    # replayable: the same seed gives the same episode
    again = record_episode(model.policy, TMazeCueEnv(), seed=3)
    assert np.array_equal(again.spikes[0], activity.spikes[0]) and again.actions == activity.actions


def test_typical_seed_is_the_first_episode_that_ends_as_most_do(monkeypatch):
    from types import SimpleNamespace

    from sb3_spikeplastic.zoo import recording

    outcomes = {}

    def episode(policy, env, seed, **kwargs):
        return SimpleNamespace(done=True, info={} if outcomes is None else {"is_success": outcomes[seed]})

    monkeypatch.setattr(recording, "record_episode", episode)
    make = lambda: SimpleNamespace(close=lambda: None)  # noqa: E731
    outcomes = {5: False, 6: True, 7: True, 8: False}
    assert recording.typical_seed(None, make, 5, n_episodes=4) == (6, "2 of 4 episodes from seed 5 succeeded")
    outcomes = {0: True, 1: False, 2: False}
    assert recording.typical_seed(None, make, 0, n_episodes=3) == (1, "1 of 3 episodes from seed 0 succeeded")
    outcomes = None  # no success reported: the seed asked for
    assert recording.typical_seed(None, make, 3, n_episodes=3) == (3, None)
