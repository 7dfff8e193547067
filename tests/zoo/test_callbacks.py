"""What ``train`` and the other commands print: steps per second that count the updates, the rounding of ``-n``
to whole rollouts, a line per evaluation, a summary before the first episode ends, the overrides that drop keys,
the install hint of ``optimize``, and the progress bar only on a terminal unless asked for."""

import re
import sys
import time
from types import SimpleNamespace

import pytest
from helpers import run_cli

from sb3_spikeplastic import PPO, cli
from sb3_spikeplastic.zoo.callbacks import TrainingSummary, rounding_note
from sb3_spikeplastic.zoo.config import replaced_mappings

TINY_TMAZE = ["n_envs=2", "n_steps=32", "batch_size=32", "bptt_steps=16", "n_epochs=1",
              "policy_kwargs.hidden_sizes=[16]"]
#: seconds each update is made to last, so that a rate that leaves it out is far above one that counts it
UPDATE_SECONDS = 0.5


def test_train_lines_count_updates_rounding_and_evaluations(tmp_path, capsys, monkeypatch):
    update = PPO.train

    def slow_update(self):
        time.sleep(UPDATE_SECONDS)
        update(self)

    monkeypatch.setattr(PPO, "train", slow_update)
    code, out, err = run_cli(capsys, "train", "--env", "TMazeCue-v0", "-n", "100", "--seed", "0", "-f", tmp_path,
                             "--hyperparams", *TINY_TMAZE, "--eval-freq", "64", "--eval-episodes", "2")
    assert code == 0, err
    lines = out.splitlines()
    assert "trains 128 steps: -n is rounded up to whole rollouts of n_steps x n_envs = 64" in lines
    evaluations = [line for line in lines if "| evaluation:" in line]
    assert [int(line.split()[0].replace(",", "")) for line in evaluations] == [64, 128], out
    assert all(re.fullmatch(r"\s+[\d,]+ steps \| evaluation: return -?[\d.]+ ± [\d.]+ over 2 episodes \| "
                            r"success [\d.]+", line) for line in evaluations), evaluations
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
    assert rounding_note(model, 1000) == ("trains 2,048 steps: -n is rounded up to whole rollouts of n_steps x "
                                          "n_envs = 2,048")
    assert rounding_note(model, 4096) is None
    model = SimpleNamespace(num_timesteps=500, n_steps=64, n_envs=8)  # continuing a run
    assert rounding_note(model, 1000).startswith("trains 512 steps (to 1,012): ")


@pytest.mark.parametrize("flags, terminal, shown", [([], True, True), ([], False, False), (["-P"], False, True),
                                                    (["--no-progress"], True, False)])
def test_progress_bar_on_a_terminal_unless_asked(flags, terminal, shown, monkeypatch):
    seen = {}
    monkeypatch.setattr("sb3_spikeplastic.zoo.evaluation.evaluate_command", lambda **options: seen.update(options))
    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    args = cli.build_parser().parse_args(["evaluate", "--run", "r", *flags])
    cli.prepare(args, [])
    assert seen["no_progress"] is not shown and "progress" not in seen


def test_whole_mapping_override_names_the_keys_it_drops(tmp_path, capsys):
    lines = replaced_mappings("TMazeCue-v0", None, ["policy_kwargs=dict(hidden_sizes=[32], alpha_lr_scale=2)"])
    assert len(lines) == 1 and lines[0].startswith("--hyperparams policy_kwargs=dict(hidden_sizes=[32], "
                                                   "alpha_lr_scale=2) replaces the entry's whole policy_kwargs, ")
    dropped = lines[0].split("dropping its ")[1].split(" (")[0].split(", ")
    assert "alpha_init_mean" in dropped and "alpha_lr_scale" not in dropped  # the entry's, less those given
    # a dotted key keeps the others; a key set again by a later override is not dropped
    assert replaced_mappings("TMazeCue-v0", None, ["policy_kwargs.hidden_sizes=[32]"]) == []
    again = replaced_mappings("TMazeCue-v0", None, ["policy_kwargs:{hidden_sizes: [32]}",
                                                    "policy_kwargs.alpha_init_mean=0"])
    assert "alpha_init_mean" not in again[0].split("dropping its ")[1]
    # the command line prints it once the command is checked and its model built, before the run
    argv = ["train", "--env", "HalfCheetah-v5", "-f", str(tmp_path), "--hyperparams",
            "policy_kwargs=dict(hidden_sizes=[16], steps=5)"]
    cli.prepare(cli.build_parser().parse_args(argv), argv)
    out = capsys.readouterr().out
    assert "sb3-spikeplastic: --hyperparams policy_kwargs=dict(hidden_sizes=[16], steps=5) replaces the entry's " \
           "whole policy_kwargs, dropping its " in out
    assert list(tmp_path.iterdir()) == []


def test_optimize_without_optuna_is_the_install_hint(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna fails as if it were not installed
    code, out, err = run_cli(capsys, "optimize", "--env", "TMazeCue-v0", "-f", tmp_path / "logs")
    assert code == 2 and err.count("\n") == 1, err
    assert 'need Optuna: pip install "sb3-spikeplastic[optimize]"' in err and "Traceback" not in err
    assert not (tmp_path / "logs").exists()
