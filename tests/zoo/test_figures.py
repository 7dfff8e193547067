"""Figures: ``plot``'s parts (the Monitor files of run folders, their labels and the summary line of each run) and
the activity figure of one recorded episode."""

import io
import json

import gymnasium as gym
import numpy as np
import pytest
from helpers import tmaze_model
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_spikeplastic import PPO
from sb3_spikeplastic.envs.tmaze import TMazeCueEnv
from sb3_spikeplastic.zoo.figures import activity_figure, curve_summaries, plot_command, read_runs
from sb3_spikeplastic.zoo.recording import record_episode


def monitor_file(path, episodes, t_start=1000.0):
    """An SB3 Monitor file of ``(return, length, seconds, is_success)`` episodes."""
    lines = ["#" + json.dumps({"t_start": t_start, "env_id": "X"}), "r,l,t,is_success"]
    lines += [f"{r},{length},{t},{s}" for r, length, t, s in episodes]
    path.write_text("\n".join(lines) + "\n")


def test_runs_are_read_labelled_and_summed_up(tmp_path):
    run = tmp_path / "TMazeCue-v0_1"
    (run / "TMazeCue-v0").mkdir(parents=True)
    (run / "TMazeCue-v0" / "config.yml").write_text(
        "TMazeCue-v0:\n  policy: SpikePlasticPolicy\n  policy_kwargs: {rule: dp-bcm}\n"
    )
    monitor_file(run / "0.monitor.csv", [(1.0, 10, 1.0, "True"), (0.0, 10, 3.0, "False")])
    monitor_file(run / "1.monitor.csv", [(-1.0, 20, 2.0, "True")])
    other = tmp_path / "other" / "TMazeCue-v0_1"  # the same folder name: labelled by its path
    other.mkdir(parents=True)
    monitor_file(other / "0.monitor.csv", [(5.0, 4, 1.0, "")] * 3)
    runs = read_runs([run, other])
    assert list(runs) == ["TMazeCue-v0_1 (dp-bcm)", "TMazeCue-v0_1"]
    first = runs["TMazeCue-v0_1 (dp-bcm)"]
    assert first["r"].tolist() == [1.0, -1.0, 0.0] and first["l"].tolist() == [10, 20, 10]  # in order of time
    assert first["is_success"].tolist() == [1.0, 1.0, 0.0]
    assert curve_summaries(runs, last=2) == [
        "TMazeCue-v0_1 (dp-bcm): 3 episodes, 40 steps, mean return of the last 2: -0.500, "
        "success rate of the last 2: 0.500",
        "TMazeCue-v0_1: 3 episodes, 12 steps, mean return of the last 2: 5.000",
    ]
    assert np.isnan(runs["TMazeCue-v0_1"]["is_success"]).all()


def test_plot_checks_its_runs_before_writing(tmp_path):
    (tmp_path / "empty").mkdir()
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    monitor_file(unfinished / "0.monitor.csv", [])
    cases = [
        ([tmp_path / "nowhere"], {}, "no run folder"),
        ([tmp_path / "empty"], {}, "no Monitor files"),
        ([unfinished], {}, "no finished episodes"),
        ([unfinished], {"x": "hours"}, "unknown --x 'hours'"),
        ([unfinished], {"smooth": 0}, "--smooth=0 must be >= 1"),
    ]
    for runs, options, message in cases:
        with pytest.raises(ValueError, match=message):
            plot_command(runs, output=tmp_path / "out" / "curves.png", **options)
    assert not (tmp_path / "out").exists()


def test_activity_figure_png(tmp_path, assert_png):
    model = tmaze_model("ndp-oja", n_envs=1, env_kwargs={"neurons_per_population": 10})
    activity = record_episode(model.policy, TMazeCueEnv(), seed=0)
    assert activity.modulation[0] is not None
    fig = activity_figure(activity, title="test")
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=60)
    assert_png(buffer.getvalue())
    # continuous actions, several hidden layers, cut episode
    env = gym.make("Pendulum-v1")
    model = PPO(
        "SpikePlasticPolicy",
        DummyVecEnv([lambda: gym.make("Pendulum-v1")]),
        n_steps=16,
        batch_size=16,
        bptt_steps=8,
        policy_kwargs=dict(rule="ndp-bcm", hidden_sizes=(8, 8), steps=10, encoder_pop_size=8, action_pop_size=4),
    )
    activity = record_episode(model.policy, env, max_steps=7)
    assert activity.n_steps == 7 and not activity.done and len(activity.spikes) == 3
    fig = activity_figure(activity)
    fig.savefig(tmp_path / "pendulum.png", dpi=60)
    assert_png(tmp_path / "pendulum.png")
