"""``sb3-spikeplastic``: train, evaluate, test robustness, plot and inspect spiking plastic policies.

::

    sb3-spikeplastic train --env TMazeCue-v0 --rule dp-oja --seed 0 -f logs --tensorboard-log tb
    sb3-spikeplastic evaluate --run logs/ppo/TMazeCue-v0_1
    sb3-spikeplastic robustness --env HalfCheetah-v5 --noise action --models oja=logs/ppo/HalfCheetah-v5_1 \\
        static=logs/ppo/HalfCheetah-v5_2 --sigmas 0 0.1 0.2 0.4 -o robustness
    sb3-spikeplastic plot logs/ppo/TMazeCue-v0_1 logs/ppo/TMazeCue-v0_2 -o curves.png
    sb3-spikeplastic inspect --run logs/ppo/TMazeCue-v0_1

This module only parses the arguments and hands them to the command's function (:data:`COMMANDS`), which checks them
and returns the work to run: ``train`` is :func:`sb3_spikeplastic.zoo.train.train_command` (the run folder's layout:
:mod:`sb3_spikeplastic.zoo.run_folder`), ``evaluate`` :func:`sb3_spikeplastic.zoo.evaluation.evaluate_command`, and
so on. A ``ValueError`` (or ``FileNotFoundError``) raised while checking is bad input: :func:`main` prints it as one
line ``sb3-spikeplastic: error: ...`` and returns exit status 2.

Everything is checked before anything is written (for ``train``: the environment id, rule, hyperparameter keys and
values, and the model itself is constructed), so bad input writes nothing. If training crashes before its first
environment step, the run folder is removed; later, it is kept (its logs explain the crash) and marked by
``FAILED.txt`` with the traceback, and no final model is written (checkpoints and the best model stay). Ctrl-C
saves the model, writes ``INTERRUPTED.txt`` and exits with status 130. ``train --trained-agent`` continues any of
these.
"""

from __future__ import annotations

import argparse
import importlib
import math
import shlex
import sys
from typing import Callable, Optional, Sequence

from sb3_spikeplastic import __version__
from sb3_spikeplastic.envs import route_mujoco_warnings
from sb3_spikeplastic.study.protocol import FIG4

PROG = "sb3-spikeplastic"

#: command -> (module, function): the function takes the command's options as keywords, checks them (raising
#: ``ValueError`` before anything is written) and returns the work, which returns the exit status.
COMMANDS = {
    "train": ("zoo.train", "train_command"),
    "optimize": ("study.optimize", "optimize_command"),
    "study": ("study.engine", "study_command"),
    "evaluate": ("zoo.evaluation", "evaluate_command"),
    "robustness": ("study.robustness", "robustness_command"),
    "plot": ("zoo.figures", "plot_command"),
    "inspect": ("zoo.inspection", "inspect_command"),
    "enjoy": ("zoo.enjoy", "enjoy_command"),
}


def _threads(value: str):
    """``--torch-threads`` of ``train``: ``auto`` or a positive number."""
    if value == "auto":
        return value
    try:
        number = int(value)
    except ValueError:
        number = 0
    if number < 1:
        raise argparse.ArgumentTypeError(f"{value!r} is not a positive number of threads or 'auto'")
    return number


def _packaged_studies() -> list[str]:
    from sb3_spikeplastic.study.declaration import packaged_studies

    return sorted(packaged_studies())


def _count(text: str) -> int:
    """An integer that may be written 2e5 or 200_000."""
    try:
        value = float(text.replace("_", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid integer {text!r}") from None
    if not math.isfinite(value) or value != int(value):
        raise argparse.ArgumentTypeError(f"invalid integer {text!r}")
    return int(value)


def _algo(value: str) -> str:
    """``--algo`` (rl-zoo's): ``ppo``, the one algorithm here (the entry's ``algo`` key picks RecurrentPPO)."""
    if value != "ppo":
        raise argparse.ArgumentTypeError(f"{value!r} is not available; accepted: ppo (RecurrentPPO: --conf ppo_lstm)")
    return value


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, like every other bad-input error (no usage: --help has it)
        self.exit(2, f"{PROG}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG,
        description="Train and study spiking neural network policies with differentiable "
        "plasticity (SpikePropamine) with Stable-Baselines3's PPO.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    def common(p: argparse.ArgumentParser, auto_threads: bool = False) -> None:
        p.add_argument(
            "--device",
            default="cpu",
            help="torch device: cpu (default), cuda[:n] (the spike kernel and CUDA graphs; an error "
            "where there is no GPU), mps, or auto (cuda when available)",
        )
        if auto_threads:
            p.add_argument(
                "--torch-threads",
                "--num-threads",
                type=_threads,
                default="auto",
                help="torch.set_num_threads: a number, or auto (default): every core for policies big "
                "enough to gain from it (the HalfCheetah entries, LSTMs), one for small ones",
            )
        else:
            p.add_argument(
                "--torch-threads", "--num-threads", type=int, default=1, help="torch.set_num_threads (default: 1)"
            )

    def progress(p: argparse.ArgumentParser) -> None:
        bar = p.add_mutually_exclusive_group()
        bar.add_argument(
            "-P",
            "--progress",
            action="store_true",
            help="show the progress bar, also where stderr is not a terminal (default: shown on a terminal)",
        )
        bar.add_argument("--no-progress", action="store_true", help="no progress bar")

    def study_options(p: argparse.ArgumentParser, command: str, default_name: str) -> None:
        p.add_argument(
            "--storage",
            help="RDB URL (sqlite:///f.db, postgresql://...) or journal file path, shared by "
            f"processes on any machine (default: <log folder>/{command}/<study>/study.db)",
        )
        p.add_argument("--study-name", help=f"default: {default_name}; an existing study is continued")
        p.add_argument("-f", "--log-folder", default="logs", help="log folder (default: logs)")

    # KEY=VALUE options given twice (rl-zoo's --hyperparams a:1 -params b:2) add up: action="extend".
    def model_source(p: argparse.ArgumentParser) -> None:
        p.add_argument("--run", help="run folder written by `train` (uses its <EnvId>.zip, config, VecNormalize)")
        p.add_argument("--model", help="a model .zip (with --env); VecNormalize statistics beside it are found")
        p.add_argument("--env", help="environment id (default: the run's)")
        p.add_argument("--vecnormalize", help="VecNormalize statistics for --model (default: found beside it)")
        p.add_argument("--best", "--load-best", action="store_true", help="of the run: best_model.zip")
        p.add_argument(
            "--env-kwargs",
            nargs="+",
            action="extend",
            metavar="KEY=VALUE",
            help="gymnasium.make arguments, KEY=VALUE or KEY:VALUE, values as YAML (default: the run's "
            "env_kwargs), e.g. max_episode_steps=200 or noise:high",
        )
        # rl-zoo's way of naming a run and its model (enjoy.py)
        p.add_argument(
            "-f",
            "--folder",
            help="rl-zoo style: the log folder of `train -f`; with --env ID the run is <folder>/ppo/<ID>_<exp-id>",
        )
        p.add_argument("--exp-id", type=int, default=0, help="with -f: the run's number (default: 0, the latest)")
        p.add_argument(
            "--load-checkpoint", type=int, metavar="STEPS", help="of the run: the checkpoint rl_model_<STEPS>_steps.zip"
        )
        p.add_argument("--load-last-checkpoint", action="store_true", help="of the run: its latest checkpoint")

    def ablation(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--ablation",
            metavar="MODE",
            help="plasticity ablation of spiking policies: none, frozen "
            "(traces held at zero: W alone), reset-every:N (traces back to zero every N steps of an "
            "episode) or shuffled (each environment on another's traces; --n-envs 2 or more) (default: "
            "the model's own, none)",
        )

    def action_mode(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--deterministic",
            dest="deterministic",
            action="store_true",
            default=True,
            help="mean / arg-max actions (default)",
        )
        p.add_argument("--stochastic", dest="deterministic", action="store_false", help="sampled actions")

    t = sub.add_parser(
        "train",
        help="train a policy (rl-zoo style hyperparameters and log folder)",
        description="Train sb3_spikeplastic.PPO with hyperparameters from hyperparams/ppo.yml.",
    )
    t.add_argument("--env", required=True, help="Gymnasium id, e.g. TMazeCue-v0, HalfCheetah-v5")
    t.add_argument("--rule", help="plasticity rule (sets policy_kwargs.rule)")
    t.add_argument("-n", "--n-timesteps", type=_count, help="total environment steps (default: the file's)")
    t.add_argument(
        "--seed",
        type=int,
        help="random seed (default: with -i the continued run's, else random; recorded in <EnvId>/args.yml)",
    )
    t.add_argument(
        "-f", "--log-folder", default="logs", help="log folder (default: logs); runs go to <folder>/ppo/<EnvId>_<n>"
    )
    t.add_argument("-tb", "--tensorboard-log", help="TensorBoard root (default: events in the run folder)")
    t.add_argument(
        "--hyperparams",
        "-params",
        nargs="+",
        action="extend",
        metavar="KEY=VALUE",
        help="overrides, KEY=VALUE or rl-zoo's KEY:VALUE, values as YAML: n_steps=128 "
        "policy_kwargs.rule=dp-bcm policy_kwargs.hidden_sizes=[32]; a whole mapping "
        "(policy_kwargs=dict(...)) replaces the entry's, and a line names the keys it drops",
    )
    t.add_argument(
        "--env-kwargs",
        nargs="+",
        action="extend",
        metavar="KEY=VALUE",
        help="gymnasium.make arguments, KEY=VALUE or KEY:VALUE, values as YAML (the same as "
        "--hyperparams env_kwargs.KEY=VALUE), e.g. max_episode_steps=200 action_noise=0.1",
    )
    t.add_argument(
        "--conf",
        "--conf-file",
        "-conf",
        dest="conf",
        help="hyperparameter file, or a packaged one by "
        "name: ppo (default), paper, mlp, ppo_lstm, mlp_zoo, ppo_lstm_zoo",
    )
    t.add_argument("--algo", type=_algo, default="ppo", help="rl-zoo's option: ppo, the only one (the default)")
    t.add_argument("--n-envs", type=int, help="number of environments (default: the file's)")
    # The run options below default to None: with -i they default to the continued run's (its args.yml).
    t.add_argument(
        "--vec-env",
        choices=("dummy", "subproc"),
        help="step the environments in this "
        "process (dummy, default) or each in its own (subproc: for slow environments)",
    )
    t.add_argument("--eval-freq", type=int, help="evaluate every N environment steps (0: never, default)")
    t.add_argument("--eval-episodes", type=int, help="episodes per evaluation (default: 20)")
    t.add_argument(
        "--save-freq",
        type=int,
        help="checkpoint every N environment steps (0: never; default: every "
        "tenth of n_timesteps for runs of 100k steps or more, else never)",
    )
    t.add_argument("--keep-checkpoints", type=int, help="keep only the latest N checkpoints (0: all; default 2)")
    t.add_argument("--figure-freq", type=int, help="TensorBoard activity figure every N rollouts (0: never, default)")
    t.add_argument(
        "-i",
        "--trained-agent",
        help="continue training this model (a run folder, its final .zip or "
        "a checkpoint) with its VecNormalize statistics, step counter and schedules, its seed and its "
        "run options (evaluations, checkpoints, figures, TensorBoard root) unless given, up to -n total "
        "steps (default: the run's n_timesteps); writes a new run folder beside it, with its own "
        "TensorBoard events",
    )
    t.add_argument(
        "-v",
        "--verbose",
        type=int,
        default=1,
        help="0: quiet, 1: a summary line (return, success, "
        "steps/s) every tenth of the run and one per evaluation (default), 2: SB3's table every rollout",
    )
    t.add_argument(
        "--log-interval",
        type=int,
        default=1,
        help="SB3's log_interval: write the logged scalars (progress.csv, "
        "TensorBoard, -v 2's table) every N rollouts (default: 1)",
    )
    progress(t)
    common(t, auto_threads=True)

    o = sub.add_parser(
        "optimize",
        help="hyperparameter search with Optuna (rl-zoo style); writes the best trial as a hyperparameter file",
        description="Search hyperparameters of an entry with Optuna: "
        "each trial samples the packaged search space, trains like `train` and is evaluated "
        "n-evaluations times (pruning); the best trial becomes <log folder>/optimize/<study>/best.yml.",
    )
    o.add_argument("--env", required=True, help="Gymnasium id")
    o.add_argument("--conf", help="hyperparameter file the trials start from (default: ppo)")
    o.add_argument("--rule", help="fixed plasticity rule (default: the rule is searched)")
    o.add_argument(
        "--hyperparams",
        "-params",
        nargs="+",
        action="extend",
        metavar="KEY=VALUE",
        help="fixed overrides (not searched), KEY=VALUE or KEY:VALUE",
    )
    o.add_argument(
        "-n", "--n-timesteps", type=_count, help="environment steps per trial and seed (default: the entry's)"
    )
    o.add_argument("--n-trials", type=int, default=20, help="trials this process runs (default: 20)")
    o.add_argument("--sampler", default="tpe", help="tpe (default) or random")
    o.add_argument("--pruner", default="median", help="median (default) or none")
    o.add_argument(
        "--n-startup-trials",
        type=int,
        default=5,
        help="random trials before TPE, and trials before the median pruner prunes (default: 5)",
    )
    o.add_argument(
        "--n-evaluations",
        type=int,
        default=5,
        help="evaluations per trial and seed, reported to the pruner (default: 5)",
    )
    o.add_argument("--eval-episodes", type=int, default=10, help="episodes per evaluation (default: 10)")
    o.add_argument(
        "--seeds-per-trial",
        type=int,
        default=1,
        help="train each trial on seeds 0..N-1; its value is the mean (default: 1)",
    )
    study_options(o, "optimize", "<EnvId>_<conf>[_<rule>]")
    o.add_argument(
        "--seed", type=int, help="seed of the sampler (default: random; give each process sharing a study its own)"
    )
    o.add_argument("--search-space", help="search-space file (default: the packaged search_space.yml)")
    common(o)

    g = sub.add_parser(
        "study",
        help="train and evaluate every cell of a study file once, by workers on any "
        "machines sharing an Optuna storage; `study report FILE`: its tables and figures",
        description="A study file declares variants x environments x seeds x budgets and what every "
        "model is evaluated on (docs/studies.md). `study FILE` runs its cells (a killed worker's cell "
        "is taken over by another; running it again continues what is missing: new seeds, budgets, "
        "variants, evaluations), then writes the report; `study report FILE` derives every table, "
        "verdict and figure from the raw episode files alone. Packaged studies: "
        f"{', '.join(_packaged_studies())}.",
    )
    g.add_argument(
        "study_file",
        nargs="+",
        metavar="[report] FILE",
        help="the study file (YAML), or the name of a packaged study; `report FILE`: only the report",
    )
    study_options(g, "study", "the study file's name without .yml")
    g.add_argument("--folder", help="the study's folder (default: <log folder>/study/<study>)")
    g.add_argument("--workers", type=int, default=1, help="worker processes on this machine (default: 1)")
    g.add_argument(
        "--variants",
        nargs="+",
        metavar="NAME",
        help="only these variants: their cells are queued and run here; other invocations' cells are left to their "
        "own workers (default: all)",
    )
    g.add_argument("--seeds", nargs="+", type=int, metavar="SEED", help="only these seeds (default: all)")
    g.add_argument(
        "--heartbeat-interval", type=int, default=60, help="seconds between heartbeats of a running cell (default: 60)"
    )
    g.add_argument(
        "--grace-period",
        type=int,
        help="seconds without a heartbeat after which a cell is run again (default: twice the interval)",
    )
    g.add_argument(
        "--save-freq",
        type=int,
        default=0,
        help="checkpoint each training every N environment steps, the latest two kept, so that a cell cut short "
        "continues from there (default: 0, only each budget's model)",
    )
    common(g)

    e = sub.add_parser("evaluate", help="mean return (and success rate) of a trained model")
    model_source(e)
    # evaluate, robustness and enjoy take both spellings, so that one command's flag works on the others.
    e.add_argument("--episodes", "--n-episodes", type=int, default=100, help="episodes (default: 100)")
    action_mode(e)
    e.add_argument("--seed", type=int, default=0, help="environment seed (default: 0)")
    e.add_argument("--n-envs", type=int, default=1, help="environments side by side (default: 1)")
    e.add_argument("-o", "--output", help="also write the result as JSON to this file")
    ablation(e)
    progress(e)
    common(e)

    r = sub.add_parser("robustness", help="return ratio under noise for several models (paper Fig. 4 F-H)")
    r.add_argument("--models", nargs="+", required=True, metavar="NAME=RUN_OR_ZIP", help="models to compare")
    r.add_argument("--env", help="noise-free environment id (default: the runs')")
    r.add_argument("--noise", required=True, help="obs, action or friction")
    # The defaults are the protocol of every HalfCheetah result (sb3_spikeplastic.study.protocol.FIG4).
    r.add_argument(
        "--sigmas",
        nargs="+",
        type=float,
        default=list(FIG4.sigmas),
        help=f"noise standard deviations (default: {' '.join(f'{s:g}' for s in FIG4.sigmas)})",
    )
    r.add_argument(
        "--episodes",
        "--n-episodes",
        type=int,
        default=FIG4.episodes,
        help=f"episodes per model and sigma (default: {FIG4.episodes})",
    )
    r.add_argument(
        "--seed",
        type=int,
        default=FIG4.seed,
        help=f"first environment seed (default: {FIG4.seed}, held out from training)",
    )
    r.add_argument(
        "--n-envs",
        type=int,
        default=FIG4.n_envs,
        help=f"environments side by side; with the seed they fix the episode seeds (default: {FIG4.n_envs})",
    )
    r.add_argument(
        "--env-kwargs",
        nargs="+",
        action="extend",
        metavar="KEY=VALUE",
        help="gymnasium.make arguments of the noise-free environment, values as YAML (e.g. max_episode_steps=200)",
    )
    r.add_argument("--friction-target", default="damping", help="damping (default) or geom_friction")
    r.add_argument(
        "--obs-indices",
        nargs="+",
        type=int,
        metavar="I",
        help="obs noise on these observation elements only (default: all)",
    )
    action_mode(r)
    r.add_argument("-o", "--output", default="robustness", help="output folder (default: robustness)")
    ablation(r)
    progress(r)
    common(r)

    p = sub.add_parser("plot", help="training curves from the Monitor files of run folders")
    p.add_argument("runs", nargs="+", metavar="RUN_FOLDER")
    p.add_argument("-o", "--output", default="training_curves.png", help="PNG file (default: training_curves.png)")
    p.add_argument("--x", default="timesteps", help="timesteps (default), episodes or walltime")
    p.add_argument("--smooth", type=int, default=20, help="moving average over N episodes (default: 20)")
    p.add_argument("--title")

    i = sub.add_parser(
        "inspect",
        help="figures of one episode's network activity (T-maze: typical, all-left, all-right and no-cue episodes)",
    )
    model_source(i)
    i.add_argument("-o", "--output", help="output folder (default: <run>/figures)")
    i.add_argument("--seed", type=int, default=0, help="episode seed (default: 0)")
    i.add_argument("--max-steps", type=int, help="environment steps shown (default: about 1 s of network time)")
    action_mode(i)
    progress(i)
    common(i)

    y = sub.add_parser(
        "enjoy",
        help="play a trained model, print each episode and record a video",
        description="Play episodes of a trained model (its VecNormalize statistics frozen, its "
        "recurrent state carried) and optionally record them: one frame after each reset and each "
        "step.",
    )
    model_source(y)
    y.add_argument("--n-episodes", "--episodes", type=int, help="episodes (default: 1; with -n as many as fit)")
    y.add_argument(
        "-n",
        "--n-timesteps",
        type=_count,
        help="rl-zoo style: play N environment steps in all, episode after episode (the last one cut at N)",
    )
    y.add_argument("--algo", type=_algo, default="ppo", help="rl-zoo's option: ppo, the only one (the default)")
    y.add_argument(
        "--no-render",
        action="store_true",
        help="rl-zoo's option, accepted: enjoy opens no window (--video records the episodes)",
    )
    action_mode(y)
    y.add_argument(
        "--seed",
        type=int,
        help="reset seed of the first episode (default: for a task that reports "
        "success, the first of seeds 0-9 whose episode ends as most of them do; else 0)",
    )
    y.add_argument("--max-steps", type=int, help="at most N steps per episode (default: until the env ends it)")
    y.add_argument(
        "--video",
        metavar="FILE",
        help="record the episodes to FILE: .mp4 or .gif (needs "
        'pip install "sb3-spikeplastic[video]"; MuJoCo renders with MUJOCO_GL, else egl or osmesa)',
    )
    y.add_argument("--fps", type=float, help="frames per second of the video (default: the env's render_fps, else 30)")
    y.add_argument(
        "--size",
        type=int,
        nargs=2,
        metavar=("W", "H"),
        help="frame size of the video (default: the env's, 480 480 for MuJoCo)",
    )
    y.add_argument(
        "--raster",
        action="store_true",
        help="draw the hidden layers' spikes of the last 200 ms beside each frame (SpikePlasticPolicy)",
    )
    progress(y)
    common(y)
    return parser


#: rl-zoo's options that name what is the case here anyway (``--algo ppo``, ``--no-render``): checked by the
#: parser, not passed on.
_ZOO_ONLY = ("algo", "no_render")


def _progress_bar(options: dict) -> None:
    """``no_progress`` as the command functions take it: ``-P/--progress`` forces the bar, ``--no-progress`` hides
    it, and by default it shows where stderr is a terminal (redrawn into a file or a pipe, it is only noise)."""
    forced = options.pop("progress", False)
    if "no_progress" in options:
        options["no_progress"] = options["no_progress"] or not (forced or sys.stderr.isatty())


def prepare(args: argparse.Namespace, argv: Sequence[str]) -> Callable[[], int]:
    """The parsed command's work, its options checked (``ValueError``: bad input, nothing written)."""
    module, name = COMMANDS[args.command]
    options = {k: v for k, v in vars(args).items() if k != "command" and k not in _ZOO_ONLY}
    _progress_bar(options)
    if args.command == "train":  # recorded in the run folder
        options["command_line"] = shlex.join([PROG, *argv])
    return getattr(importlib.import_module(f"sb3_spikeplastic.{module}"), name)(**options)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the ``sb3-spikeplastic`` console script; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return int(exc.code or 0)
    route_mujoco_warnings()
    try:
        try:
            work = prepare(args, argv)
        except (ValueError, FileNotFoundError) as exc:  # bad input, found before anything was written
            print(f"{PROG}: error: {exc}", file=sys.stderr)
            return 2
        return int(work() or 0)
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
