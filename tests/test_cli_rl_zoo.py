"""rl-baselines3-zoo's command lines (``train.py`` and ``enjoy.py`` as its documentation writes them) run as
``sb3-spikeplastic train`` / ``enjoy``: every value arrives where rl-zoo would put it, and its other spellings are
one-line errors."""

import inspect
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers import tmaze_model

from sb3_spikeplastic import PPO, __version__, cli
from sb3_spikeplastic.zoo import train as experiment
from sb3_spikeplastic.zoo.config import dump_yaml
from sb3_spikeplastic.zoo.zoo_yaml import packaged_hyperparams_path


def prepared_run(monkeypatch, argv):
    """``argv`` through the parser and ``train_command``'s checks (the model is built), not trained: the
    :class:`~sb3_spikeplastic.zoo.experiment.Experiment` it would run and the printed lines."""
    seen = {}
    monkeypatch.setattr(
        experiment,
        "_train",
        lambda exp, command_line, options, tb_root: (
            seen.update(experiment=exp, command_line=command_line, options=options) or 0
        ),
    )
    args = cli.build_parser().parse_args([str(a) for a in argv])
    threads = torch.get_num_threads()
    try:
        assert cli.prepare(args, [str(a) for a in argv])() == 0
        seen["threads"] = torch.get_num_threads()
    finally:
        torch.set_num_threads(threads)
    return seen["experiment"], seen


def test_train_command_line_of_rl_zoo(tmp_path, monkeypatch, capsys):
    # python train.py --algo ppo --env CartPole-v1 -n 5000 --eval-freq 1000 --eval-episodes 5 --save-freq 1000
    #   -f logs/ -tb tb/ --hyperparams n_steps:128 -params learning_rate:0.001 --env-kwargs ... --seed 0
    #   --num-threads 1 -P --conf-file hyperparams/ppo.yml
    run, seen = prepared_run(
        monkeypatch,
        [
            "train",
            "--algo",
            "ppo",
            "--env",
            "TMazeCue-v0",
            "-n",
            "5000",
            "--eval-freq",
            "1000",
            "--eval-episodes",
            "5",
            "--save-freq",
            "1000",
            "-f",
            f"{tmp_path}/logs/",
            "-tb",
            f"{tmp_path}/tb/",
            "--hyperparams",
            "n_steps:128",
            "-params",
            "learning_rate:0.001",
            "--env-kwargs",
            "noise:high",
            "--seed",
            "0",
            "--num-threads",
            "1",
            "-P",
            "--conf-file",
            packaged_hyperparams_path("ppo"),
        ],
    )
    config = run.config
    assert (config["n_timesteps"], config["n_steps"], config["learning_rate"]) == (5000, 128, 0.001)
    assert config["env_kwargs"] == {"noise": "high"}
    assert (run.eval_freq, run.eval_episodes, run.save_freq, run.seed) == (1000, 5, 1000, 0)
    assert run.log_folder == tmp_path / "logs" and Path(run.tensorboard_log) == tmp_path / "tb"
    assert run.progress and seen["threads"] == 1  # -P: the bar although stderr is not a terminal here
    assert not (tmp_path / "logs").exists()  # checked and built, nothing written


def test_train_command_line_of_rl_zoo_on_halfcheetah(tmp_path, monkeypatch, capsys):
    # both forms in one line, a zoo dict string, and --conf-file by name
    run, seen = prepared_run(
        monkeypatch,
        [
            "train",
            "--env",
            "NoisyHalfCheetah-v5",
            "--algo",
            "ppo",
            "-n",
            "2e4",
            "-params",
            "n_epochs:3",
            "policy_kwargs.hidden_sizes=[32]",
            "--hyperparams",
            "gae_lambda:0.9",
            "--env-kwargs",
            "max_episode_steps:200",
            "obs_noise=0.1",
            "--conf-file",
            "ppo",
            "-f",
            tmp_path,
            "--no-progress",
            "--num-threads",
            "2",
        ],
    )
    config = run.config
    assert (config["n_timesteps"], config["n_epochs"], config["gae_lambda"]) == (20000, 3, 0.9)
    assert config["policy_kwargs"]["hidden_sizes"] == [32]
    assert config["env_kwargs"] == {"max_episode_steps": 200, "obs_noise": 0.1}
    assert not run.progress and seen["threads"] == 2


@pytest.mark.skipif(
    "log_interval" not in inspect.signature(experiment.train_command).parameters,
    reason="train_command does not take log_interval yet",
)
def test_log_interval_reaches_learn(tmp_path, monkeypatch, run_cli):
    seen = {}

    def learn(self, total_timesteps, callback=None, **kwargs):
        seen.update(kwargs)
        return self

    monkeypatch.setattr(PPO, "learn", learn)
    code, _, err = run_cli(
        "train",
        "--env",
        "TMazeCue-v0",
        "-n",
        "64",
        "--log-interval",
        "10",
        "-f",
        tmp_path,
        "-v",
        "0",
        "--hyperparams",
        "n_envs:2",
        "n_steps:32",
        "batch_size:32",
        "bptt_steps:16",
        "policy_kwargs.hidden_sizes=[16]",
    )
    assert code == 0, err
    assert seen["log_interval"] == 10


@pytest.mark.parametrize(
    "argv, message",
    [
        (["train", "--env", "TMazeCue-v0", "-n", "abc"], "argument -n/--n-timesteps: invalid integer 'abc'"),
        (["train", "--env", "TMazeCue-v0", "--algo", "sac"], "argument --algo: 'sac' is not available; accepted: ppo"),
        (["enjoy", "--env", "TMazeCue-v0", "--algo", "a2c"], "argument --algo: 'a2c' is not available; accepted: ppo"),
        (
            ["train", "--env", "TMazeCue-v0", "--env-kwargs", "noise"],
            "malformed --env-kwargs entry 'noise'; expected key=value or key:value",
        ),
        (
            ["train", "--env", "TMazeCue-v0", "--hyperparams", "policy_kwargs.rule_kwargs.eta_init=2"],
            "policy_kwargs.rule_kwargs.eta_init=2.0 must lie in (0, 1)",
        ),
        (
            [
                "train",
                "--env",
                "TMazeCue-v0",
                "-params",
                "policy_kwargs.rule=dp-bcm",
                "policy_kwargs.rule_kwargs:{eta_phi_init: 1.5}",
            ],
            "policy_kwargs.rule_kwargs.eta_phi_init=1.5 must lie in (0, 1)",
        ),
        (
            [
                "train",
                "--env",
                "TMazeReversal-v0",
                "-params",
                "policy_kwargs.rule=ndp-oja",
                "policy_kwargs.rule_kwargs.modulation_source=dopamine",
            ],
            "policy_kwargs.rule_kwargs.modulation_source='dopamine' unknown; accepted: learned, reward, td-error",
        ),
    ],
)
def test_bad_input_is_one_line_naming_its_option(argv, message, tmp_path, run_cli):
    code, out, err = run_cli(*argv, "-f" if argv[0] == "train" else "--run", tmp_path / "logs")
    assert code == 2 and out == ""
    assert err.splitlines() == [f"sb3-spikeplastic: error: {err.split('error: ', 1)[1].strip()}"]
    assert message in err and "hyperparameter override" not in err, err
    assert not (tmp_path / "logs").exists()


def test_version_and_python_dash_m(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "sb3_spikeplastic", "--version"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0 and result.stdout.strip() == f"sb3-spikeplastic {__version__}", result.stderr
    result = subprocess.run(
        [sys.executable, "-m", "sb3_spikeplastic", "train", "--env", "TMazeCue-v0", "-n", "x"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "invalid integer 'x'" in result.stderr


@pytest.fixture(scope="module")
def zoo_logs(tmp_path_factory):
    """Two T-maze runs in rl-zoo's layout, ``logs/ppo/TMazeCue-v0_<1|2>``, each with a final model, a best model
    and checkpoints at 64 and 128 steps (the same small model: these tests choose files, not play well)."""
    logs = tmp_path_factory.mktemp("zoo") / "logs"
    model = tmaze_model(n_envs=1)
    entry = {"TMazeCue-v0": {"policy": "SpikePlasticPolicy", "env_kwargs": {"neurons_per_population": 4}}}
    for n in (1, 2):
        run = logs / "ppo" / f"TMazeCue-v0_{n}"
        (run / "TMazeCue-v0").mkdir(parents=True)
        (run / "TMazeCue-v0" / "config.yml").write_text(dump_yaml(entry))
        for name in ("TMazeCue-v0.zip", "best_model.zip", "rl_model_64_steps.zip", "rl_model_128_steps.zip"):
            model.save(run / name)
    return logs


def prepared_enjoy(monkeypatch, capsys, argv):
    """``enjoy ARGV`` prepared and run with the playing left out: (the model file it loaded, Player.run's
    arguments)."""
    from sb3_spikeplastic.zoo import enjoy, recording

    seen = {}
    monkeypatch.setattr(recording, "typical_seed", lambda *args, **kwargs: (0, None))
    monkeypatch.setattr(enjoy.Player, "run", lambda self, *args, **kwargs: seen.update(args=args, kwargs=kwargs))
    args = cli.build_parser().parse_args([str(a) for a in argv])
    assert cli.prepare(args, argv)() == 0
    return capsys.readouterr().out.splitlines()[0].split(": ", 1)[1], seen


def test_enjoy_command_line_of_rl_zoo(zoo_logs, monkeypatch, capsys):
    # python enjoy.py --algo ppo --env X -f logs/ --exp-id 1 --load-best -n 1000
    path, seen = prepared_enjoy(
        monkeypatch,
        capsys,
        [
            "enjoy",
            "--algo",
            "ppo",
            "--env",
            "TMazeCue-v0",
            "-f",
            f"{zoo_logs}/",
            "--exp-id",
            "1",
            "--load-best",
            "-n",
            "1000",
        ],
    )
    assert path == str(zoo_logs / "ppo" / "TMazeCue-v0_1" / "best_model.zip")
    assert seen["args"][0] is None and seen["kwargs"]["total_steps"] == 1000  # episodes: as many as 1000 steps hold
    for extra, expected in [
        (["--exp-id", "0"], "TMazeCue-v0_2/TMazeCue-v0.zip"),  # 0: the latest run
        ([], "TMazeCue-v0_2/TMazeCue-v0.zip"),
        (["--exp-id", "1", "--load-checkpoint", "64"], "TMazeCue-v0_1/rl_model_64_steps.zip"),
        (["--load-last-checkpoint"], "TMazeCue-v0_2/rl_model_128_steps.zip"),
    ]:
        path, seen = prepared_enjoy(monkeypatch, capsys, ["enjoy", "--env", "TMazeCue-v0", "-f", zoo_logs, *extra])
        assert path == str(zoo_logs / "ppo" / expected), extra
        assert seen["args"][0] == 1 and seen["kwargs"]["total_steps"] is None  # one episode, as without -n


def test_enjoy_n_plays_that_many_steps_in_all(zoo_logs, run_cli):
    code, out, err = run_cli(
        "enjoy",
        "--env",
        "TMazeCue-v0",
        "-f",
        zoo_logs,
        "--exp-id",
        "1",
        "--load-checkpoint",
        "128",
        "-n",
        "40",
        "--seed",
        "0",
        "--no-render",
    )
    assert code == 0, err
    lengths = [int(line.split(", ")[1].split()[0]) for line in out.splitlines() if line.startswith("episode ")]
    assert sum(lengths) == 40 and len(lengths) >= 3  # T-maze episodes of 16-19 steps, the last one cut
    assert out.splitlines()[len(lengths)].endswith("(cut by -n)") and "40 steps in all" in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--exp-id", "3"],
            "ppo/TMazeCue-v0_3' (--exp-id 3); runs of TMazeCue-v0 there: 1, 2 (--exp-id 0: the latest)",
        ),
        (["--load-checkpoint", "999"], "has no checkpoint rl_model_999_steps.zip; its checkpoints: 64, 128"),
        (["--load-best", "--load-last-checkpoint"], "--best and --load-last-checkpoint: give one of them"),
        (["--run", "somewhere"], "give one of --run FOLDER, --model PATH or -f/--folder LOGS with --env ID"),
    ],
)
def test_bad_zoo_model_choice_is_one_line(zoo_logs, run_cli, argv, message):
    for command in ("enjoy", "evaluate"):
        code, out, err = run_cli(command, "--env", "TMazeCue-v0", "-f", zoo_logs, *argv)
        assert code == 2 and len(err.splitlines()) == 1 and message in err, err
    code, _, err = run_cli("evaluate", "-f", zoo_logs)
    assert code == 2 and "-f/--folder needs --env ID" in err
