"""The training callbacks: what ``train`` prints (steps per second that count the updates, the rounding of ``-n``
to whole rollouts, a line per evaluation, a summary before the first episode ends), and the activity figure and the
hyperparameter text in TensorBoard."""

import re
import time
from types import SimpleNamespace

import pytest
from helpers import tmaze_model
from stable_baselines3.common.logger import Logger, make_output_format
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_spikeplastic import PPO
from sb3_spikeplastic.zoo.callbacks import ActivityFigureCallback, TrainingSummary, rounding_note
from sb3_spikeplastic.zoo.hparams import write_hyperparameters

#: seconds each update is made to last, so that a rate that leaves it out is far above one that counts it
UPDATE_SECONDS = 0.5


def test_train_lines_count_updates_rounding_and_evaluations(tmp_path, run_cli, tiny_tmaze, monkeypatch):
    update = PPO.train

    def slow_update(self):
        time.sleep(UPDATE_SECONDS)
        update(self)

    monkeypatch.setattr(PPO, "train", slow_update)
    code, out, err = run_cli(
        "train",
        "--env",
        "TMazeCue-v0",
        "-n",
        "100",
        "--seed",
        "0",
        "-f",
        tmp_path,
        "--hyperparams",
        *tiny_tmaze,
        "--eval-freq",
        "64",
        "--eval-episodes",
        "2",
    )
    assert code == 0, err
    lines = out.splitlines()
    assert "trains 128 steps: -n is rounded up to whole rollouts of n_steps x n_envs = 64" in lines
    evaluations = [line for line in lines if "| evaluation:" in line]
    assert [int(line.split()[0].replace(",", "")) for line in evaluations] == [64, 128], out
    assert all(
        re.fullmatch(
            r"\s+[\d,]+ steps \| evaluation: return -?[\d.]+ ± [\d.]+ over 2 episodes \| "
            r"success [\d.]+",
            line,
        )
        for line in evaluations
    ), evaluations
    summaries = [re.fullmatch(r"\s+([\d,]+) steps \| .* \| ([\d,]+) steps/s", line) for line in lines]
    (steps, rate), *_ = [(int(m[1].replace(",", "")), int(m[2].replace(",", ""))) for m in summaries if m]
    assert steps == 64 and rate <= 64 / UPDATE_SECONDS  # written after the first update, whose time it counts
    assert "step/s" not in err  # no progress bar: stderr is not a terminal here


def test_summary_says_when_no_episode_has_finished():
    model = SimpleNamespace(num_timesteps=2048, ep_info_buffer=[], ep_success_buffer=[], n_steps=2048, n_envs=1)
    summary = TrainingSummary(every=100)
    summary.model, summary.start_steps, summary.start_time = model, 0, time.perf_counter() - 1.0
    assert re.fullmatch(r"\s+2,048 steps \| no episode finished yet \| [\d,]+ steps/s", summary.summary())
    model.ep_info_buffer = [{"r": -3.0}, {"r": -1.0}]
    assert "| return -2 |" in summary.summary()


def test_rounding_note():
    model = SimpleNamespace(num_timesteps=0, n_steps=2048, n_envs=1)
    assert rounding_note(model, 1000) == (
        "trains 2,048 steps: -n is rounded up to whole rollouts of n_steps x n_envs = 2,048"
    )
    assert rounding_note(model, 4096) is None
    model = SimpleNamespace(num_timesteps=500, n_steps=64, n_envs=8)  # continuing a run
    assert rounding_note(model, 1000).startswith("trains 512 steps (to 1,012): ")


def test_figure_callback_and_hyperparameter_text_reach_tensorboard(tmp_path, assert_png):
    model = tmaze_model("dp-oja", env_kwargs={"neurons_per_population": 10})
    model.set_logger(Logger(str(tmp_path), [make_output_format("tensorboard", str(tmp_path))]))
    config = {"n_steps": 32, "policy_kwargs": {"rule": "dp-oja", "hidden_sizes": [16]}, "normalize": False}
    assert write_hyperparameters(model.logger, config)
    model.learn(192, callback=ActivityFigureCallback("TMazeCue-v0", every=2))
    model.logger.close()
    ea = EventAccumulator(str(tmp_path), size_guidance={"images": 0, "tensors": 0})
    ea.Reload()
    tags = ea.Tags()
    assert "snn/layer0/spike_rate" in tags["scalars"] and "plasticity/layer0/eta" in tags["scalars"]
    images = ea.Images("snn/activity")
    assert [i.step for i in images] == [128]  # rollout 2 of 3, 64 steps each
    assert_png(images[0].encoded_image_string)
    text = ea.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "| policy_kwargs.rule | dp-oja |" in text and "| n_steps | 32 |" in text


def test_figure_callback_validates_its_interval():
    with pytest.raises(ValueError, match="every=0 must be >= 1"):
        ActivityFigureCallback("TMazeCue-v0", every=0)
