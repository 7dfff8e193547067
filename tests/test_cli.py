"""The ``sb3-spikeplastic`` command line: train / evaluate / robustness / plot / inspect, and bad input."""

import io
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_spikeplastic import PPO, cli
from sb3_spikeplastic.zoo.run_folder import load_model, locate_run
from sb3_spikeplastic.zoo.zoo_yaml import load_hyperparams_file

TINY_CHEETAH = [
    "n_envs=1",
    "n_steps=32",
    "batch_size=32",
    "bptt_steps=16",
    "n_epochs=1",
    "policy_kwargs.hidden_sizes=[16]",
    "policy_kwargs.steps=10",
    "policy_kwargs.encoder_pop_size=8",
    "policy_kwargs.action_pop_size=4",
    "env_kwargs.max_episode_steps=20",
]


def event_accumulator(folder: Path) -> EventAccumulator:
    ea = EventAccumulator(str(folder), size_guidance={"images": 0, "tensors": 0, "scalars": 0})
    ea.Reload()
    return ea


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("cli")


@pytest.fixture(scope="module")
def tmaze_run(workdir, tiny_tmaze):
    argv = [
        "train",
        "--env",
        "TMazeCue-v0",
        "--rule",
        "ndp-oja",
        "-n",
        "128",
        "--seed",
        "3",
        "-f",
        workdir / "logs",
        "--tensorboard-log",
        workdir / "tb",
        "--hyperparams",
        *tiny_tmaze,
        "--eval-freq",
        "64",
        "--eval-episodes",
        "2",
        "--save-freq",
        "64",
        "--figure-freq",
        "1",
        "-v",
        "0",
        "--no-progress",
    ]
    assert cli.main([str(a) for a in argv]) == 0
    return workdir / "logs" / "ppo" / "TMazeCue-v0_1"


@pytest.fixture(scope="module")
def cheetah_run(workdir):
    argv = [
        "train",
        "--env",
        "HalfCheetah-v5",
        "-n",
        "64",
        "--seed",
        "0",
        "-f",
        workdir / "logs",
        "--hyperparams",
        *TINY_CHEETAH,
        "--figure-freq",
        "1",
        "-v",
        "0",
        "--no-progress",
    ]
    assert cli.main([str(a) for a in argv]) == 0
    return workdir / "logs" / "ppo" / "HalfCheetah-v5_1"


def test_train_tmaze_run_folder(tmaze_run, workdir):
    names = {p.name for p in tmaze_run.iterdir()}
    assert {
        "TMazeCue-v0.zip",
        "best_model.zip",
        "evaluations.npz",
        "command.txt",
        "progress.csv",
        "rl_model_64_steps.zip",
        "rl_model_128_steps.zip",
        "0.monitor.csv",
        "1.monitor.csv",
        "TMazeCue-v0",
    } <= names
    assert not [n for n in names if ".tmp" in n]  # no temporary files left behind
    assert not (tmaze_run / "TMazeCue-v0" / "vecnormalize.pkl").exists()  # normalize: false
    command = (tmaze_run / "command.txt").read_text()
    assert command.startswith("sb3-spikeplastic train --env TMazeCue-v0 --rule ndp-oja -n 128")
    config = load_hyperparams_file(tmaze_run / "TMazeCue-v0" / "config.yml")  # itself a hyperparameter file
    resolved_kwargs = config["TMazeCue-v0"]["policy_kwargs"]
    assert resolved_kwargs["rule"] == "ndp-oja" and resolved_kwargs["hidden_sizes"] == [16]
    assert config["TMazeCue-v0"]["n_timesteps"] == 128 and config["TMazeCue-v0"]["n_steps"] == 32
    assert "seed: 3" in (tmaze_run / "TMazeCue-v0" / "args.yml").read_text()
    assert (tmaze_run / "0.monitor.csv").read_text().splitlines()[1] == "r,l,t,is_success"
    model = PPO.load(tmaze_run / "TMazeCue-v0.zip")
    assert model.policy.snn.rule_name == "ndp-oja" and model.num_timesteps == 128
    PPO.load(tmaze_run / "best_model.zip")
    assert np.load(tmaze_run / "evaluations.npz")["timesteps"].tolist() == [64, 128]


def test_train_tmaze_tensorboard(tmaze_run, workdir):
    runs = list((workdir / "tb" / "TMazeCue-v0").iterdir())
    assert [r.name for r in runs] == ["ppo_ndp-oja_1"]
    ea = event_accumulator(runs[0])
    scalars = ea.Tags()["scalars"]
    for key in (
        "snn/layer0/spike_rate",
        "snn/layer1/silent_fraction",
        "plasticity/layer0/eta",
        "plasticity/layer0/trace_abs_mean",
        "plasticity/layer0/modulation_mean",
        "rollout/success_rate",
        "eval/mean_reward",
        "train/grad_norm",
    ):
        assert key in scalars, key
    images = ea.Images("snn/activity")
    assert [i.step for i in images] == [64, 128]  # --figure-freq 1: every rollout (2 envs x 32 steps)
    image = matplotlib.image.imread(io.BytesIO(images[-1].encoded_image_string), format="png")
    pixels = image.reshape(-1, image.shape[-1])
    assert image.shape[0] > 300 and (pixels != pixels[0]).any()
    text = ea.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "| policy_kwargs.rule | ndp-oja |" in text and "| bptt_steps | 16 |" in text and "| seed | 3 |" in text


def test_train_env_kwargs_reach_the_environment_and_the_config(tmp_path, run_cli):
    # in subprocesses (--vec-env subproc): the env_kwargs travel with the factories
    code, _, err = run_cli(
        "train",
        "--env",
        "NoisyHalfCheetah-v5",
        "-n",
        "32",
        "--seed",
        "0",
        "-f",
        tmp_path,
        "--hyperparams",
        *[h for h in TINY_CHEETAH if not h.startswith("env_kwargs")],
        "--env-kwargs",
        "max_episode_steps=16",
        "action_noise=0.2",
        "-v",
        "0",
        "--no-progress",
        "--vec-env",
        "subproc",
    )
    assert code == 0, err
    run = tmp_path / "ppo" / "NoisyHalfCheetah-v5_1"
    config = load_hyperparams_file(run / "NoisyHalfCheetah-v5" / "config.yml")["NoisyHalfCheetah-v5"]
    assert config["env_kwargs"] == {"max_episode_steps": 16, "action_noise": 0.2}
    assert (run / "0.monitor.csv").read_text().splitlines()[2].split(",")[1] == "16"  # 16-step episodes


def test_train_halfcheetah_normalized(cheetah_run):
    names = {p.name for p in cheetah_run.iterdir()}
    assert {"HalfCheetah-v5.zip", "command.txt", "0.monitor.csv", "HalfCheetah-v5"} <= names
    assert (cheetah_run / "HalfCheetah-v5" / "vecnormalize.pkl").is_file()  # normalize: true in ppo.yml
    assert not {"best_model.zip", "evaluations.npz"} & names  # no --eval-freq
    model = PPO.load(cheetah_run / "HalfCheetah-v5.zip")
    assert model.policy.snn.sizes == [17 * 8, 16, 6 * 4] and hasattr(model.policy, "log_std")
    ea = event_accumulator(cheetah_run)  # no --tensorboard-log: events in the run folder
    assert {"snn/action_std", "snn/layer0/spike_rate", "plasticity/layer0/trace_abs_mean"} <= set(ea.Tags()["scalars"])
    assert len(ea.Images("snn/activity")) == 2
    assert "hyperparameters/text_summary" in ea.Tags()["tensors"]


def test_evaluate(tmaze_run, cheetah_run, run_cli, tmp_path):
    code, out, _ = run_cli("evaluate", "--run", tmaze_run, "--episodes", "6", "-o", tmp_path / "eval.json")
    assert code == 0
    assert "mean return" in out and "over 6 episodes (deterministic)" in out and "success rate" in out
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["episodes"] == 6 and result["deterministic"] and result["env"] == "TMazeCue-v0"
    assert f"success rate {result['success_rate']:.3f}" in out and f"mean return {result['mean_return']:.3f}" in out
    energy = result["energy"]  # spikes and SynOps per environment step, input population first
    assert len(energy["spikes_per_step"]) == len(energy["synops_per_step"]) + 1 and energy["total_synops_per_step"] > 0
    assert f"{energy['total_synops_per_step']:,.0f} SynOps" in out
    code, out, _ = run_cli(
        "evaluate", "--model", tmaze_run / "best_model.zip", "--episodes", "2", "--stochastic", "--n-envs", "2"
    )
    assert code == 0 and "over 2 episodes (stochastic)" in out
    code, out, _ = run_cli("evaluate", "--run", cheetah_run, "--episodes", "2")
    assert code == 0 and "VecNormalize: " in out and "mean episode length 20.0" in out
    assert "success rate" not in out


def test_robustness(cheetah_run, workdir, run_cli, assert_png):
    out_dir = workdir / "robustness"
    code, out, _ = run_cli(
        "robustness",
        "--models",
        f"a={cheetah_run}",
        f"b={cheetah_run / 'HalfCheetah-v5.zip'}",
        "--noise",
        "action",
        "--sigmas",
        "0.2",
        "0.5",
        "--episodes",
        "2",
        "--env-kwargs",
        "max_episode_steps=20",
        "-o",
        out_dir,
        "--no-progress",
    )
    assert code == 0
    assert "| model | noise | sigma |" in out and "| a | action | 0.5 |" in out and "| b | action | 0 |" in out
    stem = out_dir / "robustness_HalfCheetah-v5_action"
    lines = stem.with_suffix(".csv").read_text().splitlines()
    assert lines[0].startswith("model,noise_type,sigma") and len(lines) == 1 + 2 * 3
    assert_png(stem.with_suffix(".png"))


def test_plot(tmaze_run, cheetah_run, workdir, run_cli, assert_png):
    out = workdir / "curves" / "curves.png"
    code, text, _ = run_cli("plot", tmaze_run, cheetah_run, "-o", out, "--smooth", "3")
    assert code == 0 and "TMazeCue-v0_1 (ndp-oja)" in text and "success rate" in text
    assert_png(out)
    code, _, _ = run_cli("plot", tmaze_run, "-o", workdir / "episodes.png", "--x", "episodes")
    assert code == 0
    assert_png(workdir / "episodes.png")


def test_inspect(tmaze_run, workdir, run_cli, assert_png):
    code, out, _ = run_cli("inspect", "--run", tmaze_run, "-o", workdir / "inspect")
    assert code == 0
    for name in ("typical", "all_left", "all_right", "no_cue"):
        assert_png(workdir / "inspect" / f"activity_{name}.png")


BAD_TRAIN = [
    (["--env", "TMazeCue-v9"], r"unknown environment id 'TMazeCue-v9'; did you mean TMazeCue-v0"),
    (["--env", "TMazeCue-v0", "--rule", "hebb"], r"unknown rule 'hebb'; accepted: static, dp-linear, dp-oja"),
    (
        ["--env", "TMazeCue-v0", "--hyperparams", "n_stepz=64"],
        r"unknown hyperparameter 'n_stepz' \(did you mean 'n_steps'\?\); accepted: .*n_steps",
    ),
    (
        ["--env", "TMazeCue-v0", "--hyperparams", "n_steps"],
        r"malformed hyperparameter override 'n_steps'; expected key=value",
    ),
    (["--env", "TMazeCue-v0", "--hyperparams", "n_steps=many"], r"n_steps='many' must be an integer"),
    (["--env", "TMazeCue-v0", "--hyperparams", "learning_rate=fast"], r"learning_rate='fast' must be a number"),
    (
        ["--env", "TMazeCue-v0", "--hyperparams", "policy_kwargs.hidden_sizes=[16]", "bptt_steps=32", "batch_size=48"],
        r"invalid configuration for TMazeCue-v0: batch_size=48 \(transitions\) must be a multiple of bptt_steps=32",
    ),
    (
        ["--env", "TMazeCue-v0", "--hyperparams", "env_kwargs.noise=extreme"],
        r"invalid configuration for TMazeCue-v0: noise='extreme' is not one of \('low', 'high'\)",
    ),
    (["--env", "TMazeCue-v0", "--conf", "missing.yml"], r"cannot read hyperparameter file 'missing.yml'"),
    (["--env", "TMazeCue-v0", "--eval-freq", "-1"], r"--eval-freq=-1 must be >= 0"),
]


@pytest.mark.filterwarnings("ignore:You have specified a mini-batch size")
@pytest.mark.parametrize("args, message", BAD_TRAIN)
def test_bad_train_input_exits_2_and_writes_nothing(args, message, tmp_path, run_cli, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli("train", *args, "-f", tmp_path / "logs", "--tensorboard-log", tmp_path / "tb")
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sb3-spikeplastic: error: ")
    assert __import__("re").search(message, lines[0]), lines[0]
    assert not (tmp_path / "logs").exists() and not (tmp_path / "tb").exists()


def test_bad_robustness_evaluate_and_plot_input(tmaze_run, tmp_path, run_cli):
    cases = [
        (
            ["robustness", "--models", f"a={tmaze_run}", "--noise", "wind", "-o", tmp_path / "r"],
            "unknown noise type 'wind'; accepted: obs, action, friction",
        ),
        (
            ["robustness", "--models", f"a={tmaze_run}", "--noise", "friction", "-o", tmp_path / "r"],
            "friction noise cannot be applied to TMazeCue-v0",
        ),
        (
            [
                "robustness",
                "--models",
                f"a={tmaze_run}",
                "--env",
                "HalfCheetah-v5",
                "--noise",
                "obs",
                "--obs-indices",
                "3",
                "17",
                "-o",
                tmp_path / "r",
            ],
            "obs index 17 in [3, 17] is not one of distinct integers in [0, 16]",
        ),
        (
            ["robustness", "--models", f"a={tmp_path / 'nowhere'}", "--noise", "obs", "-o", tmp_path / "r"],
            "no run folder or model file",
        ),
        (
            [
                "robustness",
                "--models",
                f"a={tmaze_run}",
                "--env",
                "HalfCheetah-v5",
                "--noise",
                "obs",
                "-o",
                tmp_path / "r",
            ],
            "(observations Box(0.0, 1.0, (25, 40), float32), actions Discrete(2)) does not fit HalfCheetah-v5 "
            "(observations Box(-inf, inf, (17,), float64), actions Box(-1.0, 1.0, (6,), float32))",
        ),
        (["evaluate", "--run", tmaze_run, "--env", "HalfCheetah-v5"], "does not fit HalfCheetah-v5 (observations"),
        (["evaluate", "--run", tmp_path], "is not a run folder of `sb3-spikeplastic train`"),
        (
            ["evaluate", "--model", tmaze_run / "TMazeCue-v0.zip", "--env", "Nope-v0"],
            "unknown environment id 'Nope-v0'",
        ),
        (["plot", tmp_path, "-o", tmp_path / "p.png"], "no Monitor files"),
        (["plot", tmaze_run, "--x", "hours", "-o", tmp_path / "p.png"], "unknown --x 'hours'; accepted: timesteps"),
    ]
    for argv, message in cases:
        code, _, err = run_cli(*argv)
        assert code == 2, argv
        assert err.strip().splitlines() == [f"sb3-spikeplastic: error: {err.split('error: ', 1)[1].strip()}"]
        assert message in err, (argv, err)
    assert not (tmp_path / "r").exists() and not (tmp_path / "p.png").exists()


BAD_PATHS = [
    (["train", "--env", "TMazeCue-v0", "-f", "afile/logs"], "-f/--log-folder 'afile/logs' lies under the file 'afile'"),
    (
        ["train", "--env", "TMazeCue-v0", "-f", "logs", "--tensorboard-log", "afile/tb"],
        "--tensorboard-log 'afile/tb' lies under the file 'afile'",
    ),
    (["train", "--env", "TMazeCue-v0", "-f", "afile"], "-f/--log-folder 'afile' is a file, not a folder"),
    (["evaluate", "--run", "RUN", "-o", "afile/x.json"], "-o/--output 'afile/x.json' lies under the file 'afile'"),
    (["evaluate", "--run", "RUN", "-o", "."], "-o/--output '.' is a folder, not a file"),
    (["plot", "RUN", "-o", "afile/x.png"], "-o/--output 'afile/x.png' lies under the file 'afile'"),
    (["robustness", "--models", "a=RUN", "--noise", "obs", "-o", "afile/r"], "-o/--output 'afile/r' lies under"),
    (["inspect", "--run", "RUN", "-o", "afile/figures"], "-o/--output 'afile/figures' lies under the file"),
    (
        ["train", "--env", "HalfCheetah-v5", "-f", "logs", "--hyperparams", "policy_kwargs.hidden_sizes=[-3]"],
        "hidden_sizes=[-3] must be one or more positive integers",
    ),
    (
        ["train", "--env", "HalfCheetah-v5", "-f", "logs", "--hyperparams", "policy_kwargs.hidden_sizes=[0]"],
        "hidden_sizes=[0] must be one or more positive integers",
    ),
    (
        ["train", "--env", "HalfCheetah-v5", "-f", "logs", "--hyperparams", "policy_kwargs.steps=0"],
        "steps=0 must be a positive integer",
    ),
]


@pytest.mark.parametrize("argv, message", BAD_PATHS)
def test_bad_paths_and_sizes_exit_2_before_any_work_and_write_nothing(
    argv, message, tmaze_run, tmp_path, run_cli, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    argv = [str(tmaze_run) if a == "RUN" else a.replace("RUN", str(tmaze_run)) for a in argv]
    code, _, err = run_cli(*argv)
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nothing written, not even MUJOCO_LOG.TXT


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="needs a machine without CUDA")
def test_device_cuda_without_cuda_is_an_error(tmp_path, run_cli):
    code, _, err = run_cli("train", "--env", "TMazeCue-v0", "-f", tmp_path / "logs", "--device", "cuda")
    assert code == 2 and "--device cuda: no CUDA device is available" in err and "accepted here: cpu, auto" in err
    assert not (tmp_path / "logs").exists()


@pytest.fixture
def train_argv(tmp_path, tiny_tmaze):
    """``train_argv(n="128")``: the arguments of a quiet T-maze training of ``n`` steps into ``tmp_path / "logs"``."""

    def argv(n="128"):
        return [
            "train",
            "--env",
            "TMazeCue-v0",
            "-n",
            n,
            "--seed",
            "0",
            "-f",
            str(tmp_path / "logs"),
            "-v",
            "0",
            "--no-progress",
            "--hyperparams",
            *tiny_tmaze,
        ]

    return argv


def test_ctrl_c_saves_the_model(tmp_path, run_cli, monkeypatch, train_argv):
    def interrupted(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(PPO, "train", interrupted)
    code, out, _ = run_cli(*train_argv())
    assert code == 130 and "Interrupted after 64 steps" in out
    run = tmp_path / "logs" / "ppo" / "TMazeCue-v0_1"
    assert PPO.load(run / "TMazeCue-v0.zip").num_timesteps == 64


def test_crash_before_the_first_rollout_removes_the_run_folder(tmp_path, capsys, monkeypatch, train_argv):
    def broken(self, *args, **kwargs):
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(PPO, "collect_rollouts", broken)
    with pytest.raises(RuntimeError, match="simulated crash"):
        cli.main(train_argv())
    assert list((tmp_path / "logs" / "ppo").iterdir()) == []
    assert "removed" in capsys.readouterr().err


def test_crash_later_keeps_the_logs_and_marks_the_run(tmp_path, run_cli, monkeypatch, train_argv):
    def broken(self):
        raise RuntimeError("simulated divergence")

    monkeypatch.setattr(PPO, "train", broken)
    with pytest.raises(RuntimeError, match="simulated divergence"):
        cli.main(train_argv())
    run = tmp_path / "logs" / "ppo" / "TMazeCue-v0_1"
    assert "simulated divergence" in (run / "FAILED.txt").read_text()
    assert not (run / "TMazeCue-v0.zip").exists()  # no half-trained final model
    code, _, err = run_cli("evaluate", "--run", run)
    assert code == 2 and "has no TMazeCue-v0.zip (training failed: see FAILED.txt)" in err


def test_run_folders_are_numbered(tmp_path, capsys, train_argv):
    for expected in ("TMazeCue-v0_1", "TMazeCue-v0_2"):
        assert cli.main(train_argv(n="64")) == 0
        assert (tmp_path / "logs" / "ppo" / expected / "TMazeCue-v0.zip").is_file()


def test_help_and_argparse_errors(capsys):
    assert cli.main(["--help"]) == 0
    assert "train" in capsys.readouterr().out
    assert cli.main(["train"]) == 2  # --env is required
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "sb3-spikeplastic: error: the following arguments are required: --env"


def test_episode_count_takes_both_spellings():
    parser = cli.build_parser()
    for command, dest in (("evaluate", "episodes"), ("robustness", "episodes"), ("enjoy", "n_episodes")):
        extra = ["--noise", "obs", "--models", "a=b"] if command == "robustness" else ["--run", "r"]
        for flag in ("--episodes", "--n-episodes"):
            assert getattr(parser.parse_args([command, *extra, flag, "7"]), dest) == 7


def test_console_script_smoke(tmp_path, tiny_tmaze):
    """One real run of the installed console script."""
    script = Path(sys.executable).parent / "sb3-spikeplastic"
    command = [str(script)] if script.exists() else [sys.executable, "-m", "sb3_spikeplastic.cli"]
    command += [
        "train",
        "--env",
        "TMazeCue-v0",
        "-n",
        "64",
        "--seed",
        "0",
        "-f",
        "logs",
        "-v",
        "0",
        "--no-progress",
        "--hyperparams",
        *tiny_tmaze,
    ]
    result = subprocess.run(
        command, cwd=tmp_path, capture_output=True, text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"}
    )
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "logs" / "ppo" / "TMazeCue-v0_1" / "TMazeCue-v0.zip").is_file()
    assert "Run folder:  logs/ppo/TMazeCue-v0_1" in result.stdout
    assert "sb3-spikeplastic evaluate --run logs/ppo/TMazeCue-v0_1" in result.stdout


def test_train_continues_a_checkpoint_with_its_statistics_counter_and_run_options(
    tmaze_run, cheetah_run, workdir, run_cli
):
    import pickle

    from stable_baselines3.common.vec_env import VecNormalize

    # A --save-freq checkpoint of the T-maze run: its step counter and checkpoint names continue.
    code, out, err = run_cli(
        "train",
        "--env",
        "TMazeCue-v0",
        "--trained-agent",
        tmaze_run / "rl_model_64_steps.zip",
        "-n",
        "192",
        "-f",
        workdir / "continued",
        "--save-freq",
        "64",
        "-v",
        "0",
        "--no-progress",
    )
    assert code == 0, err
    run = workdir / "continued" / "ppo" / "TMazeCue-v0_1"
    model = PPO.load(run / "TMazeCue-v0.zip")
    assert model.num_timesteps == 192 and model.policy.snn.rule_name == "ndp-oja"
    assert {"rl_model_128_steps.zip", "rl_model_192_steps.zip"} <= {p.name for p in run.iterdir()}
    args = (run / "TMazeCue-v0" / "args.yml").read_text()
    assert "start_timesteps: 64" in args and "rl_model_64_steps.zip" in args
    recorded = yaml.safe_load(args)
    assert recorded["seed"] == 3  # the continued run's seed, without --seed
    # ...and its run options, unless given: its evaluations, figures and TensorBoard root (a new TensorBoard run)
    assert (recorded["eval_freq"], recorded["eval_episodes"], recorded["figure_freq"]) == (64, 2, 1)
    assert recorded["save_freq"] == 64 and recorded["continues"] == str(tmaze_run)
    assert recorded["tensorboard_dir"] == str(workdir / "tb" / "TMazeCue-v0" / "ppo_ndp-oja_2")
    assert (run / "evaluations.npz").is_file()
    assert out.splitlines()[0].startswith(f"Continuing {tmaze_run} from step 64 (rl_model_64_steps.zip)")
    # The final model of a normalised run: its VecNormalize statistics go on accumulating.
    code, _, err = run_cli(
        "train",
        "--env",
        "HalfCheetah-v5",
        "-i",
        cheetah_run,
        "-n",
        "96",
        "--seed",
        "1",
        "-f",
        workdir / "continued",
        "-v",
        "0",
        "--no-progress",
    )
    assert code == 0, err
    new = workdir / "continued" / "ppo" / "HalfCheetah-v5_1"
    assert PPO.load(new / "HalfCheetah-v5.zip").num_timesteps == 96
    with open(cheetah_run / "HalfCheetah-v5" / "vecnormalize.pkl", "rb") as f:
        before = pickle.load(f).obs_rms.count
    with open(new / "HalfCheetah-v5" / "vecnormalize.pkl", "rb") as f:
        after = pickle.load(f)
    assert isinstance(after, VecNormalize) and after.obs_rms.count > before
    assert yaml.safe_load((new / "HalfCheetah-v5" / "args.yml").read_text())["seed"] == 1  # --seed wins


def test_default_output_is_a_summary_line_per_tenth_and_tables_at_v2(tmp_path, run_cli, tiny_tmaze):
    """``train`` prints a summary line (steps, return, success, steps/s) every tenth of the run; SB3's tables
    (and its "Using cpu device") only with ``-v 2``."""
    argv = ["train", "--env", "TMazeCue-v0", "-n", "320", "--seed", "0", "--hyperparams", *tiny_tmaze, "--no-progress"]
    code, out, err = run_cli(*argv, "-f", tmp_path / "quiet")
    assert code == 0, err
    lines = [line for line in out.splitlines() if line.rstrip().endswith("steps/s")]
    assert len(lines) >= 5 and "rollout/" not in out and "Using cpu device" not in out
    assert re.match(r"\s+320 steps \| return -?[\d.]+ \| success [\d.]+ \| [\d,]+ steps/s", lines[-1]), lines[-1]
    code, out, err = run_cli(*argv, "-f", tmp_path / "tables", "-v", "2")
    assert code == 0, err
    assert "rollout/" in out and "ep_rew_mean" in out and not out.rstrip().endswith("steps/s")


def test_bad_hyperparameter_value_prints_nothing_before_its_error(tmp_path, run_cli):
    code, out, err = run_cli(
        "train", "--env", "TMazeCue-v0", "--hyperparams", "learning_rate=-0.001", "-f", tmp_path / "logs"
    )
    assert code == 2 and out == "" and err.count("\n") == 1 and "learning rate" in err.lower(), (out, err)
    assert not (tmp_path / "logs").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--hyperparams", "n_steps=64"], "--trained-agent continues a run with its own configuration"),
        (["-n", "64"], "has trained 128 of n_timesteps=64 steps already; pass a larger -n"),
        (["--env", "HalfCheetah-v5"], "was trained on TMazeCue-v0, not HalfCheetah-v5"),
    ],
)
def test_bad_trained_agent_exits_2_and_writes_nothing(tmaze_run, tmp_path, run_cli, extra, message):
    argv = ["train", "--env", "TMazeCue-v0", "-i", tmaze_run, "-f", tmp_path / "logs", *extra]
    if "--env" in extra:
        argv = argv[:1] + argv[3:]
    code, _, err = run_cli(*argv)
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / "logs").exists()


@pytest.mark.parametrize(
    "conf, policy_class", [("mlp", "ActorCriticPolicy"), ("ppo_lstm", "RecurrentActorCriticPolicy")]
)
def test_baselines_train_and_evaluate_through_the_same_commands(conf, policy_class, tmp_path, run_cli):
    tiny = ["n_envs=1", "n_steps=32", "batch_size=32", "n_epochs=1", "env_kwargs.max_episode_steps=20"]
    code, out, err = run_cli(
        "train",
        "--env",
        "HalfCheetah-v5",
        "--conf",
        conf,
        "-n",
        "64",
        "--seed",
        "0",
        "-f",
        tmp_path / "logs",
        "--hyperparams",
        *tiny,
        "-v",
        "0",
        "--no-progress",
    )
    assert code == 0, err
    run = tmp_path / "logs" / "ppo" / "HalfCheetah-v5_1"
    config = load_hyperparams_file(run / "HalfCheetah-v5" / "config.yml")["HalfCheetah-v5"]
    assert config.get("algo", "ppo") == ("ppo_lstm" if conf == "ppo_lstm" else "ppo")
    code, out, err = run_cli("evaluate", "--run", run, "--episodes", "2")
    assert code == 0 and "mean episode length 20.0" in out, err
    model = load_model(locate_run(run))
    assert type(model.policy).__name__ == policy_class and model.num_timesteps == 64


def test_unknown_algo_is_a_one_line_error(tmp_path, run_cli):
    conf = tmp_path / "bad.yml"
    conf.write_text("HalfCheetah-v5:\n  algo: sac\n")
    code, _, err = run_cli("train", "--env", "HalfCheetah-v5", "--conf", conf, "-f", tmp_path / "logs")
    assert code == 2 and "unknown algo 'sac'; accepted: ppo, ppo_lstm" in err
    assert not (tmp_path / "logs").exists()


def start_training_until_a_checkpoint(logs: Path, hyperparams, **popen_kwargs):
    """A T-maze training process (1M steps, a checkpoint every 64, ``--hyperparams HYPERPARAMS``) started in
    ``logs``, returned once its first checkpoint exists, with its run folder."""
    import time

    argv = [
        sys.executable,
        "-m",
        "sb3_spikeplastic.cli",
        "train",
        "--env",
        "TMazeCue-v0",
        "-n",
        "1000000",
        "--seed",
        "0",
        "-f",
        str(logs),
        "--save-freq",
        "64",
        "-v",
        "0",
        "--no-progress",
        "--hyperparams",
        *hyperparams,
    ]
    process = subprocess.Popen(argv, **popen_kwargs)
    run = logs / "ppo" / "TMazeCue-v0_1"
    deadline = time.time() + 180
    while not list(run.glob("rl_model_*_steps.zip")) and time.time() < deadline:
        if process.poll() is not None:
            process.kill()
            pytest.fail("training exited before its first checkpoint")
        time.sleep(0.2)
    return process, run


def test_a_killed_run_keeps_its_checkpoints_and_continues_from_them(tmp_path, run_cli, tiny_tmaze):
    import signal

    logs = tmp_path / "logs"
    process, run = start_training_until_a_checkpoint(
        logs, tiny_tmaze, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    process.send_signal(signal.SIGKILL)  # power loss: no handler runs
    process.wait()
    checkpoints = sorted(run.glob("rl_model_*_steps.zip"), key=lambda p: int(p.name.split("_")[2]))
    assert not (run / "TMazeCue-v0.zip").exists()
    latest = checkpoints[-1]
    code, _, err = run_cli("evaluate", "--run", run)
    assert code == 2 and f"its latest checkpoint is --model '{latest}'" in err
    code, out, err = run_cli("evaluate", "--model", latest, "--episodes", "2")
    assert code == 0 and "mean return" in out, err
    steps = int(latest.name.split("_")[2])
    code, out, err = run_cli(
        "train", "--env", "TMazeCue-v0", "-i", run, "-n", str(steps + 64), "-f", logs, "-v", "0", "--no-progress"
    )
    assert code == 0 and f"continuing from {latest.name}" in out, err
    assert PPO.load(logs / "ppo" / "TMazeCue-v0_2" / "TMazeCue-v0.zip").num_timesteps == steps + 64


def test_sigterm_stops_training_like_ctrl_c(tmp_path, tiny_tmaze):
    """A scheduler's time limit (SIGTERM) saves the model and writes INTERRUPTED.txt, as Ctrl-C does."""
    import signal

    process, run = start_training_until_a_checkpoint(
        tmp_path / "logs", tiny_tmaze, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, err[-2000:]
    assert "Interrupted after" in out
    assert (run / "TMazeCue-v0.zip").exists() and (run / "INTERRUPTED.txt").exists()
    assert PPO.load(run / "TMazeCue-v0.zip").num_timesteps >= 64


def test_checkpoints_are_pruned_to_the_latest(tmp_path, run_cli, train_argv):
    argv = train_argv(n="320") + ["--save-freq", "64", "--keep-checkpoints", "2"]
    assert run_cli(*argv)[0] == 0
    run = tmp_path / "logs" / "ppo" / "TMazeCue-v0_1"
    assert sorted(p.name for p in run.glob("rl_model_*")) == ["rl_model_256_steps.zip", "rl_model_320_steps.zip"]


def test_ctrl_c_leaves_a_marker_that_says_how_to_continue(tmp_path, run_cli, monkeypatch, train_argv):
    def interrupted(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(PPO, "train", interrupted)
    code, out, _ = run_cli(*train_argv(), "--eval-freq", "64", "--eval-episodes", "2")
    run = tmp_path / "logs" / "ppo" / "TMazeCue-v0_1"
    note = (run / "INTERRUPTED.txt").read_text()
    assert code == 130 and "interrupted after 64 of 128 steps" in note
    command = note.splitlines()[1]
    assert command in out  # the terminal shows the command itself
    monkeypatch.undo()
    # That command continues the run exactly: to the original length, with its seed and its evaluations.
    code, out, err = run_cli(*shlex.split(command)[1:], "-v", "0", "--no-progress")
    assert code == 0, err
    continued = tmp_path / "logs" / "ppo" / "TMazeCue-v0_2"
    assert PPO.load(continued / "TMazeCue-v0.zip").num_timesteps == 128
    recorded = yaml.safe_load((continued / "TMazeCue-v0" / "args.yml").read_text())
    assert (recorded["seed"], recorded["eval_freq"], recorded["eval_episodes"]) == (0, 64, 2)
    assert (continued / "evaluations.npz").is_file()


def test_long_runs_checkpoint_by_default(tmp_path, run_cli, monkeypatch, tiny_tmaze):
    seen = {}

    def stop_at_once(self, total_timesteps, callback=None, **kwargs):
        seen["callbacks"] = [type(c).__name__ for c in callback.callbacks]
        seen["freq"] = [c.save_freq for c in callback.callbacks if hasattr(c, "save_freq")]
        return self

    monkeypatch.setattr(PPO, "learn", stop_at_once)
    argv = [
        "train",
        "--env",
        "TMazeCue-v0",
        "-n",
        "200000",
        "-f",
        tmp_path / "logs",
        "-v",
        "0",
        "--no-progress",
        "--hyperparams",
        *tiny_tmaze,
    ]
    assert run_cli(*argv)[0] == 0
    assert seen["callbacks"] == ["AtomicCheckpoint"] and seen["freq"] == [200000 // 10 // 2]  # 2 envs
    assert run_cli(*argv, "--save-freq", "0")[0] == 0 and seen["callbacks"] == []
    assert run_cli(*[a if a != "200000" else "50000" for a in argv])[0] == 0 and seen["callbacks"] == []


def test_progress_bars_count_environment_steps_and_episodes(tmp_path, run_cli, train_argv):
    """-P shows the bar although stderr is not a terminal here; without it, it stays off."""
    argv = [a if a != "--no-progress" else "-P" for a in train_argv()]
    code, _, err = run_cli(*argv)
    assert code == 0 and "128/128" in err and "step/s" in err  # tqdm's line: steps over wall time
    run = tmp_path / "logs" / "ppo" / "TMazeCue-v0_1"
    code, _, err = run_cli("evaluate", "--run", run, "--episodes", "3", "-P")
    assert code == 0 and "3/3" in err and "episode" in err
    code, _, err = run_cli("evaluate", "--run", run, "--episodes", "3")
    assert code == 0 and "3/3" not in err


def test_progress_bar_counts_the_steps_trained(tmp_path, run_cli, train_argv):
    """Whole rollouts run past -n (here 100 of 2 x 64 steps): the bar counts the 128 steps trained."""
    argv = [a if a != "--no-progress" else "-P" for a in train_argv()]
    argv[argv.index("-n") + 1] = "100"
    code, out, err = run_cli(*argv)
    assert code == 0 and "128/128" in err and "/100" not in err and "Done: 128 steps" in out


@pytest.mark.parametrize(
    "flags, terminal, shown",
    [([], True, True), ([], False, False), (["-P"], False, True), (["--no-progress"], True, False)],
)
def test_progress_bar_on_a_terminal_unless_asked(flags, terminal, shown, monkeypatch):
    seen = {}
    monkeypatch.setattr("sb3_spikeplastic.zoo.evaluation.evaluate_command", lambda **options: seen.update(options))
    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    args = cli.build_parser().parse_args(["evaluate", "--run", "r", *flags])
    cli.prepare(args, [])
    assert seen["no_progress"] is not shown and "progress" not in seen
