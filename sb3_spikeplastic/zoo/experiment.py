"""One training run and its run folder (after rl-baselines3-zoo's ``ExperimentManager``): the environments, the
model, the callbacks, the logs and every file that ``sb3-spikeplastic train`` writes (layout:
:mod:`sb3_spikeplastic.zoo.run_folder`).

The model is built in memory first (:meth:`Experiment.setup`), so that bad hyperparameters fail before anything
is written; then :meth:`Experiment.create_run_folder` and :meth:`Experiment.learn`, which saves the final model,
writes ``INTERRUPTED.txt`` on Ctrl-C, and on a crash removes the folder (before the first step) or marks it with
``FAILED.txt``.

:func:`train_command` is ``sb3-spikeplastic train``: it checks the options and builds the model (``ValueError``,
nothing written yet), and returns the run, which prints where it writes and what it wrote.
"""

from __future__ import annotations

import os
import random
import shlex
import shutil
import signal
import sys
import threading
import traceback
from collections.abc import Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Union

import gymnasium

from . import config as cfg
from .inputs import check_device, check_int, check_output_path, parse_env_kwargs
from .config import rule_label
from .run_folder import (RunInfo, atomic_write, check_spaces, latest_checkpoint, locate_run, next_run_dir, read_run_args,
                         read_run_config, save_model, save_vecnormalize)


class SuccessColumn(gymnasium.Wrapper):
    """Puts ``info["is_success"] = None`` at episode ends where the env reports no success, so that the Monitor
    files always have an ``is_success`` column (empty for such envs; SB3 ignores ``None`` successes)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            info.setdefault("is_success", None)
        return obs, reward, terminated, truncated, info


def make_train_env(env_id: str, n_envs: int, env_kwargs: dict, monitor_dir: Optional[Path] = None,
                   vec_env: str = "dummy"):
    """``n_envs`` monitored environments (Monitor CSVs in ``monitor_dir`` when given), stepped in this process
    (``vec_env="dummy"``) or each in a process of its own (``"subproc"``)."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    def factory(rank: int):
        def make():
            env = SuccessColumn(gymnasium.make(env_id, **env_kwargs))
            filename = None if monitor_dir is None else str(monitor_dir / str(rank))
            return Monitor(env, filename=filename, info_keywords=("is_success",))

        return make

    factories = [factory(i) for i in range(n_envs)]
    return SubprocVecEnv(factories) if vec_env == "subproc" else DummyVecEnv(factories)


#: ``train --torch-threads auto``: a policy with a weight matrix of at least this many entries trains on every core,
#: a smaller one on one (its products are too small to split). Measured on 2 cores: the HalfCheetah entry
#: (170 x 64 input layer) and RecurrentPPO (1024 x 256) train ~25 % faster on two threads, MlpPolicy (64 x 64) and
#: the T-maze entry (40 x 64) at most 3 % (``benchmarks/README.md``).
AUTO_THREADS_MIN_WEIGHTS = 8192


def training_threads(policy, cores: int, load: float = 0.0) -> int:
    """The torch thread count that ``train --torch-threads auto`` uses for ``policy``: the cores that other
    processes leave free (``cores`` minus the one-minute ``load``, at least 1) for a policy big enough to gain from
    them, else 1 (see :data:`AUTO_THREADS_MIN_WEIGHTS`). Threads on busy cores only wait for each other: on a
    loaded machine a second thread makes training slower, not faster (``benchmarks/README.md``, "Threads")."""
    largest = max((p.numel() for p in policy.parameters() if p.dim() >= 2), default=0)
    if largest < AUTO_THREADS_MIN_WEIGHTS:
        return 1
    return max(1, min(cores, int(cores - load + 0.5)))


def machine_load() -> float:
    """The one-minute load average (0 where the platform has none)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return 0.0


@contextmanager
def sigterm_interrupts():
    """Within the block, SIGTERM (a scheduler's time limit, ``docker stop``, ``kill``) raises ``KeyboardInterrupt``,
    so that training stops as on Ctrl-C: the model is saved and the run can be continued. Only in the main
    thread (where Python runs signal handlers); the previous handler is restored afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _plain_value(value: Any) -> bool:
    """Whether ``value`` reads back from YAML as it is (numbers, text, None, lists and mappings of them)."""
    if isinstance(value, (list, tuple)):
        return all(_plain_value(v) for v in value)
    if isinstance(value, Mapping):
        return all(isinstance(k, str) and _plain_value(v) for k, v in value.items())
    return value is None or isinstance(value, (bool, int, float, str))


def resolved_entry(model, config: Mapping[str, Any]) -> dict:
    """The hyperparameter entry that rebuilds ``model`` under any later defaults: ``config``'s meta keys and every
    algorithm argument as the model resolved it (``sb3_spikeplastic.PPO``'s policy-dependent defaults included;
    ``lin_`` schedules as written), and the policy's arguments as it recorded them (a spiking policy records every
    one, the rule included; classes by name). ``train --conf <run>/<EnvId>/config.yml`` reads it back."""
    import inspect

    entry = {k: config[k] for k in cfg.META_KEYS if k in config and k != "policy_kwargs"}
    algo = config.get("algo", "ppo")
    defaults = inspect.signature(cfg.algorithm_class(algo).__init__).parameters
    for key in cfg.ppo_argument_hints(algo):
        if key in config:
            entry[key] = config[key]
            continue
        value = getattr(model, key, defaults[key].default)
        if not _plain_value(value):  # a schedule or object the model made from its argument: the argument
            value = defaults[key].default
        if _plain_value(value) and value is not inspect.Parameter.empty:
            entry[key] = value
    policy_kwargs = {}
    for key, value in {**(config.get("policy_kwargs") or {}), **(getattr(model, "policy_kwargs", None) or {})}.items():
        if isinstance(value, type):
            value = value.__name__
        if _plain_value(value):
            policy_kwargs[key] = list(value) if isinstance(value, tuple) else value
    if policy_kwargs:
        entry["policy_kwargs"] = policy_kwargs
    return entry


class Experiment:
    """One training run of ``config`` (a validated hyperparameter entry) on ``env_id``.

    :param env_id: Gymnasium id
    :param config: the resolved hyperparameter entry (:func:`sb3_spikeplastic.zoo.config.resolve_hyperparams`)
    :param seed: seed of the model and the environments
    :param log_folder: runs go to ``<log_folder>/ppo/<env_id>_<n>``
    :param tensorboard_log: TensorBoard root (``<root>/<env_id>/ppo_<rule>_<n>``); ``None``: events in the run
        folder, or the continued run's TensorBoard folder
    :param device: torch device of the model
    :param verbose: 0 quiet, 1 a summary line every tenth of the run (:class:`~sb3_spikeplastic.zoo.callbacks.
        TrainingSummary`), 2 SB3's table every rollout and SB3's own messages
    :param eval_freq: deterministic evaluation every this many environment steps (0: never)
    :param eval_episodes: episodes per evaluation
    :param save_freq: checkpoint every this many environment steps (0: never)
    :param keep_checkpoints: checkpoints kept (0: all)
    :param figure_freq: TensorBoard activity figure every this many rollouts (0: never)
    :param vec_env: ``dummy`` (environments in this process) or ``subproc``
    :param progress: show a progress bar
    :param trained_agent: a model to continue (its run's VecNormalize statistics too)
    :param after_eval: a callback run after each evaluation (SB3's ``callback_after_eval``: it reads the result
        from its ``parent``, the ``EvalCallback``, and stops training by returning ``False``), e.g. to report
        evaluations to an Optuna trial
    :param log_interval: SB3's ``log_interval``: the logged scalars (``progress.csv``, TensorBoard, ``-v 2``'s
        table) are written every this many rollouts
    """

    def __init__(self, env_id: str, config: dict, seed: int, log_folder: Path, tensorboard_log: Optional[Path] = None,
                 device: str = "cpu", verbose: int = 1, eval_freq: int = 0, eval_episodes: int = 20,
                 save_freq: int = 0, keep_checkpoints: int = 2, figure_freq: int = 0, vec_env: str = "dummy",
                 progress: bool = True, trained_agent: Optional[RunInfo] = None, after_eval=None,
                 log_interval: int = 1):
        self.env_id, self.config, self.seed = env_id, config, seed
        self.log_interval = log_interval
        self.log_folder, self.tensorboard_log = Path(log_folder), tensorboard_log
        self.device, self.verbose, self.vec_env, self.progress = device, verbose, vec_env, progress
        self.eval_freq, self.eval_episodes, self.figure_freq = eval_freq, eval_episodes, figure_freq
        self.save_freq, self.keep_checkpoints = save_freq, keep_checkpoints
        self.source = trained_agent
        self.after_eval = after_eval
        #: more callbacks for ``learn`` (e.g. a study's checkpoints at its budgets)
        self.extra_callbacks: list = []
        self.model = None
        self.run_dir: Optional[Path] = None
        self.tb_dir: Optional[Path] = None

    @property
    def sb3_verbose(self) -> int:
        """SB3's own verbosity (its tables, its messages): on from ``verbose=2``."""
        return 1 if self.verbose >= 2 else 0

    @property
    def n_envs(self) -> int:
        return self.config["n_envs"]

    @property
    def env_kwargs(self) -> dict:
        return dict(self.config["env_kwargs"])

    @property
    def model_path(self) -> Path:
        return self.run_dir / f"{self.env_id}.zip"

    @property
    def vecnormalize_path(self) -> Path:
        return self.run_dir / self.env_id / "vecnormalize.pkl"

    def _normalized(self, venv):
        from stable_baselines3.common.vec_env import VecNormalize

        norm_kwargs = cfg.normalize_arguments(self.config)
        return venv if norm_kwargs is None else VecNormalize(venv, **norm_kwargs)

    def setup(self):
        """Build the environments and the model (or load the continued one) in memory, without writing anything:
        bad hyperparameters raise here (``ValueError``, ``TypeError``; gymnasium's errors for bad env_kwargs)."""
        from .run_folder import load_model

        probe = self._normalized(make_train_env(self.env_id, self.n_envs, self.env_kwargs))
        try:
            if self.source is None:
                policy, ppo_kwargs, policy_kwargs = cfg.model_arguments(self.config)
                algorithm = cfg.algorithm_class(self.config.get("algo", "ppo"))
                # Quiet while built (SB3 says "Using cpu device"): bad hyperparameters must fail on one line.
                self.model = algorithm(policy, probe, **ppo_kwargs, policy_kwargs=policy_kwargs, seed=self.seed,
                                       device=self.device, verbose=0)
                self.model.verbose = self.sb3_verbose
            else:
                self.model = load_model(self.source, device=self.device)
                check_spaces(self.model, probe, self.env_id, self.source.model_path)
                self.model.verbose = self.sb3_verbose
                if self.model.num_timesteps >= self.config["n_timesteps"]:
                    raise ValueError(f"{str(self.source.model_path)!r} has trained {self.model.num_timesteps:,} of "
                                     f"n_timesteps={self.config['n_timesteps']:,} steps already; pass a larger -n "
                                     "(the run's total)")
        finally:
            probe.close()
        return self.model

    def create_run_folder(self, command: str, args: dict) -> Path:
        """The next free run folder, with ``command.txt``, ``<EnvId>/config.yml`` and ``<EnvId>/args.yml`` (``args``
        plus the seed, the folders and, when continuing, the source model and its step count)."""
        self.run_dir = next_run_dir(self.log_folder / "ppo", self.env_id)
        meta_dir = self.run_dir / self.env_id
        meta_dir.mkdir()
        rule = rule_label(self.config)
        if self.tensorboard_log:
            from stable_baselines3.common.utils import get_latest_run_id

            tb_root = Path(self.tensorboard_log) / self.env_id
            tb_root.mkdir(parents=True, exist_ok=True)
            self.tb_dir = tb_root / f"ppo_{rule}_{get_latest_run_id(str(tb_root), f'ppo_{rule}') + 1}"
        else:  # a continued run too: its own events, whose step axis goes on from the continued run's
            self.tb_dir = self.run_dir
        atomic_write(self.run_dir / "command.txt", lambda f: f.write(command + "\n"), binary=False)
        entry = cfg.dump_yaml({self.env_id: resolved_entry(self.model, self.config)})
        atomic_write(meta_dir / "config.yml", lambda f: f.write(entry), binary=False)
        run_args = {**args, "seed": self.seed, "env": self.env_id, "run_dir": str(self.run_dir),
                    "tensorboard_dir": str(self.tb_dir)}
        if self.source is not None:
            run_args.update(trained_agent=str(self.source.model_path), start_timesteps=self.model.num_timesteps,
                            continues=None if self.source.run_dir is None else str(self.source.run_dir))
        atomic_write(meta_dir / "args.yml", lambda f: f.write(cfg.dump_yaml(run_args)), binary=False)
        return self.run_dir

    def _callbacks(self, eval_env) -> list:
        from stable_baselines3.common.callbacks import EvalCallback

        from .callbacks import ActivityFigureCallback, AtomicCheckpoint, SaveBest, TrainingSummary, WallClockProgress

        callbacks = [WallClockProgress()] if self.progress else []
        if self.verbose == 1:
            callbacks.append(TrainingSummary(self.config["n_timesteps"] // 10))
        if eval_env is not None:
            callbacks.append(EvalCallback(
                eval_env, callback_on_new_best=SaveBest(self.run_dir / "best_model.zip"),
                n_eval_episodes=self.eval_episodes, eval_freq=max(self.eval_freq // self.n_envs, 1),
                log_path=str(self.run_dir), best_model_save_path=None, deterministic=True, verbose=self.sb3_verbose,
                callback_after_eval=self.after_eval))
        if self.save_freq:
            callbacks.append(AtomicCheckpoint(max(self.save_freq // self.n_envs, 1), self.run_dir,
                                              self.keep_checkpoints))
        if self.figure_freq:
            callbacks.append(ActivityFigureCallback(self.env_id, every=self.figure_freq, env_kwargs=self.env_kwargs,
                                                    seed=self.seed))
        return callbacks + list(self.extra_callbacks)

    def _environments(self):
        """The training environments (the continued run's statistics too) and the evaluation environment."""
        from stable_baselines3.common.vec_env import VecNormalize

        from .run_folder import make_eval_env

        env = make_train_env(self.env_id, self.n_envs, self.env_kwargs, self.run_dir, self.vec_env)
        norm_kwargs = cfg.normalize_arguments(self.config)
        if norm_kwargs is not None:
            if self.source is not None and self.source.vecnormalize is not None:
                env = VecNormalize.load(str(self.source.vecnormalize), env)
                env.training = True
            else:
                env = VecNormalize(env, **norm_kwargs)
        env.seed(self.seed)
        eval_env = None
        if self.eval_freq:
            eval_env = make_eval_env(self.env_id, 1, self.seed + self.n_envs, self.env_kwargs)
            if norm_kwargs is not None:  # synchronised with the training statistics by EvalCallback
                eval_env = VecNormalize(eval_env, training=False, **{**norm_kwargs, "norm_reward": False})
        return env, eval_env

    def continue_command(self) -> str:
        """The ``train`` command that continues this run exactly: the saved model, the total steps and the
        TensorBoard root; ``-i`` brings back the seed and every other run option from ``args.yml``."""
        argv = ["sb3-spikeplastic", "train", "--env", self.env_id, "-i", str(self.model_path), "-f",
                str(self.log_folder), "-n", str(self.config["n_timesteps"])]
        if self.tensorboard_log:
            argv += ["--tensorboard-log", str(self.tensorboard_log)]
        return shlex.join(argv)

    def save(self) -> list[Path]:
        """The final model and its ``VecNormalize`` statistics, atomically; returns the files written."""
        saved = [save_model(self.model, self.model_path)]
        if self.model.get_vec_normalize_env() is not None:
            saved.append(save_vecnormalize(self.model.get_vec_normalize_env(), self.vecnormalize_path))
        return saved

    def learn(self) -> bool:
        """Train up to the entry's ``n_timesteps`` and save the final model. Returns ``False`` when interrupted by
        Ctrl-C or SIGTERM (the model is saved and ``INTERRUPTED.txt`` says how to continue); other errors propagate
        after the run folder is removed (no step taken) or marked with ``FAILED.txt``."""
        from stable_baselines3.common.callbacks import CallbackList
        from stable_baselines3.common.logger import Logger, make_output_format

        from .hparams import write_hyperparameters

        model, env, eval_env = self.model, None, None
        try:
            env, eval_env = self._environments()
            model.set_random_seed(self.seed)
            model.set_env(env)
            formats = ["stdout"] if self.verbose >= 2 else []
            outputs = [make_output_format(f, str(self.run_dir)) for f in formats + ["csv"]]
            outputs.append(make_output_format("tensorboard", str(self.tb_dir)))
            model.set_logger(Logger(str(self.run_dir), outputs))
            write_hyperparameters(model.logger, {"env_id": self.env_id, "seed": self.seed,
                                                 **resolved_entry(model, self.config)})
            # Continuing: the remaining steps with the counter kept, so schedules resume where they stopped.
            callback = CallbackList(self._callbacks(eval_env))
            with sigterm_interrupts():
                model.learn(self.config["n_timesteps"] - model.num_timesteps, callback=callback,
                            reset_num_timesteps=self.source is None, log_interval=self.log_interval)
        except KeyboardInterrupt:
            self.save()
            note = (f"interrupted after {model.num_timesteps:,} of {self.config['n_timesteps']:,} steps; continue "
                    f"with\n{self.continue_command()}\n")
            atomic_write(self.run_dir / "INTERRUPTED.txt", lambda f: f.write(note), binary=False)
            return False
        except BaseException:
            if model.num_timesteps == 0:  # nothing worth keeping
                shutil.rmtree(self.run_dir, ignore_errors=True)
                if self.tb_dir != self.run_dir:
                    shutil.rmtree(self.tb_dir, ignore_errors=True)
            else:
                failure = traceback.format_exc()
                atomic_write(self.run_dir / "FAILED.txt", lambda f: f.write(failure), binary=False)
            raise
        finally:
            for venv in (env, eval_env):
                if venv is not None:
                    venv.close()
            try:
                model.logger.close()
            except Exception:
                pass
        self.save()
        return True


# ----------------------------------------------------------------------------------------------------------------
# sb3-spikeplastic train

#: ``train`` runs at least this long checkpoint every tenth of their steps unless ``--save-freq`` says otherwise.
AUTO_CHECKPOINT_MIN_STEPS = 100_000


def continued_run(trained_agent: str, env_id: str, overridden: bool = False) -> RunInfo:
    """The model (final or checkpoint) that ``--trained-agent`` names, with its run's config, VecNormalize
    statistics and TensorBoard folder; ``ValueError`` if it cannot be continued as asked (``overridden``: options
    that would change its configuration were given)."""
    if overridden:
        raise ValueError("--trained-agent continues a run with its own configuration; only -n (the total "
                         "steps), --seed and the callback options may be given with it")
    folder = Path(trained_agent)
    env_id_of_folder = read_run_config(folder)[0] if folder.is_dir() else None
    if env_id_of_folder and not (folder / f"{env_id_of_folder}.zip").is_file() and latest_checkpoint(folder):
        # A run killed before its end (no final model): continue from its latest checkpoint.
        info = locate_run(latest_checkpoint(folder))
        print(f"sb3-spikeplastic: {str(folder)!r} has no final model; continuing from {info.model_path.name}")
    else:
        info = locate_run(trained_agent)
    if not info.model_path.is_file() or info.model_path.suffix != ".zip":
        raise ValueError(f"--trained-agent needs a model .zip or a run folder, got {trained_agent!r}")
    if info.env_id is not None and info.env_id != env_id:
        raise ValueError(f"--trained-agent {trained_agent!r} was trained on {info.env_id}, not {env_id}")
    if info.run_dir is not None:
        tb = read_run_args(info.run_dir, info.env_id).get("tensorboard_dir")
        info.tensorboard_dir = Path(tb) if tb else None
    return info


def train_config(env_id: str, conf: Optional[str] = None, rule: Optional[str] = None,
                 hyperparams: Optional[Sequence[str]] = None, env_kwargs: Optional[Sequence[str]] = None,
                 n_timesteps: Optional[int] = None, n_envs: Optional[int] = None,
                 source: Optional[RunInfo] = None) -> dict:
    """The resolved entry of ``train``'s options: a continued run's own entry (with ``n_timesteps``), else the
    file's entry with the overrides (``env_kwargs`` ``KEY=VALUE`` after ``hyperparams``: they win)."""
    if source is not None and source.config:
        return cfg.validate_entry({**source.config, **({"n_timesteps": n_timesteps} if n_timesteps else {})})
    parse_env_kwargs(env_kwargs)  # a malformed entry's error names --env-kwargs
    overrides = [*(hyperparams or ()), *[f"env_kwargs.{item}" for item in env_kwargs or ()]]
    return cfg.resolve_hyperparams(env_id, conf, overrides, rule=rule, n_timesteps=n_timesteps, n_envs=n_envs)


def build(experiment: Experiment) -> None:
    """:meth:`Experiment.setup`, any error of it a one-line ``ValueError``: the model is built from the user's
    input, so its errors (and gymnasium's for bad env_kwargs) are bad input."""
    try:
        experiment.setup()
    except (ValueError, TypeError, AssertionError) as exc:
        message = " ".join(str(exc).split()) or type(exc).__name__
        if experiment.source is not None:
            raise ValueError(message) from None
        raise ValueError(f"invalid configuration for {experiment.env_id}: {message}") from None
    except Exception as exc:
        if type(exc).__module__.startswith("gymnasium"):
            raise ValueError(f"cannot make {experiment.env_id} with env_kwargs={experiment.env_kwargs}: {exc}") from None
        raise


def train_command(env: str, rule: Optional[str] = None, n_timesteps: Optional[int] = None,
                  seed: Optional[int] = None, log_folder: str = "logs", tensorboard_log: Optional[str] = None,
                  hyperparams: Optional[Sequence[str]] = None, env_kwargs: Optional[Sequence[str]] = None,
                  conf: Optional[str] = None, n_envs: Optional[int] = None, vec_env: Optional[str] = None,
                  eval_freq: Optional[int] = None, eval_episodes: Optional[int] = None,
                  save_freq: Optional[int] = None, keep_checkpoints: Optional[int] = None,
                  figure_freq: Optional[int] = None, trained_agent: Optional[str] = None,
                  verbose: int = 1, no_progress: bool = False, device: str = "cpu",
                  torch_threads: Union[int, str] = "auto", log_interval: int = 1,
                  command_line: str = "sb3-spikeplastic train") -> Callable[[], int]:
    """``sb3-spikeplastic train`` with these options (its long names): every option is checked and the model built
    in memory (``ValueError``, nothing written); returns the run, which creates the run folder (``command_line``
    in ``command.txt``, the options in ``<EnvId>/args.yml``), trains, prints the files written and returns the exit
    status (130 when interrupted). The run options left ``None`` take, with ``trained_agent``, the continued run's
    values (the environments' process, evaluations, checkpoints, figures, TensorBoard root), else their defaults."""
    import torch

    from ..snn.cpu_settings import keep_freed_memory
    from ..snn.plasticity import get_rule_class

    env_id = cfg.check_env_id(env, list(cfg.load_hyperparams_file(conf)))
    if rule is not None:
        get_rule_class(rule)
    for name, value, minimum in (("--n-timesteps", n_timesteps, 1), ("--n-envs", n_envs, 1),
                                 ("--eval-freq", eval_freq, 0), ("--eval-episodes", eval_episodes, 1),
                                 ("--save-freq", save_freq, 0), ("--keep-checkpoints", keep_checkpoints, 0),
                                 ("--figure-freq", figure_freq, 0), ("--log-interval", log_interval, 1)):
        check_int(name, value, minimum)
    check_device(device)
    check_output_path(log_folder, "-f/--log-folder", directory=True)
    if tensorboard_log:
        check_output_path(tensorboard_log, "--tensorboard-log", directory=True)
    source = None
    if trained_agent:
        source = continued_run(trained_agent, env_id, bool(hyperparams or rule or n_envs or conf or env_kwargs))
        inherited = read_run_args(source.run_dir, source.env_id or env_id) if source.run_dir is not None else {}
        given = dict(vec_env=vec_env, eval_freq=eval_freq, eval_episodes=eval_episodes, save_freq=save_freq,
                     keep_checkpoints=keep_checkpoints, figure_freq=figure_freq, tensorboard_log=tensorboard_log)
        chosen = {k: inherited.get(k) if v is None else v for k, v in given.items()}
        vec_env, eval_freq, eval_episodes, save_freq, keep_checkpoints, figure_freq, tensorboard_log = chosen.values()
    vec_env = vec_env or "dummy"
    eval_freq = 0 if eval_freq is None else eval_freq
    eval_episodes = 20 if eval_episodes is None else eval_episodes
    keep_checkpoints = 2 if keep_checkpoints is None else keep_checkpoints
    figure_freq = 0 if figure_freq is None else figure_freq
    config = train_config(env_id, conf, rule, hyperparams, env_kwargs, n_timesteps, n_envs, source)
    if hyperparams and source is None:
        cfg.print_replaced_mappings(env_id, conf, hyperparams, rule)
    if figure_freq and config["policy"] != "SpikePlasticPolicy":
        raise ValueError(f"--figure-freq needs policy SpikePlasticPolicy, not {config['policy']!r}")
    # Checkpoints by default on long runs (a run killed outright keeps its latest tenth), none on short ones.
    if save_freq is None:
        save_freq = config["n_timesteps"] // 10 if config["n_timesteps"] >= AUTO_CHECKPOINT_MIN_STEPS else 0
    cores = torch.get_num_threads()  # torch's default: the physical cores
    if torch_threads != "auto":
        torch.set_num_threads(torch_threads)
    keep_freed_memory()
    if seed is None and source is not None and source.run_dir is not None:  # a continued run keeps its seed
        seed = read_run_args(source.run_dir, source.env_id or env_id).get("seed")
    if seed is None:
        seed = random.SystemRandom().randrange(2**31 - 1)
    experiment = Experiment(
        env_id, config, seed, Path(log_folder), tensorboard_log, device=device, verbose=verbose, eval_freq=eval_freq,
        eval_episodes=eval_episodes, save_freq=save_freq, keep_checkpoints=keep_checkpoints, figure_freq=figure_freq,
        vec_env=vec_env, progress=not no_progress, trained_agent=source, log_interval=log_interval)
    build(experiment)
    if torch_threads == "auto":
        load = machine_load()
        chosen = training_threads(experiment.model.policy, cores, load)
        torch.set_num_threads(chosen)
        if verbose:
            print(f"--torch-threads auto: {chosen} of {cores} core(s) (load {load:.1f}; "
                  f"{'a policy big enough to split' if chosen > 1 or load >= cores - 0.5 else 'a small policy'})")
    options = dict(env=env, rule=rule, n_timesteps=n_timesteps, seed=seed, log_folder=log_folder,
                   tensorboard_log=tensorboard_log, hyperparams=hyperparams, env_kwargs=env_kwargs, conf=conf,
                   n_envs=n_envs, vec_env=vec_env, eval_freq=eval_freq, eval_episodes=eval_episodes,
                   save_freq=save_freq, keep_checkpoints=keep_checkpoints, figure_freq=figure_freq,
                   trained_agent=trained_agent, verbose=verbose, no_progress=no_progress, device=device,
                   torch_threads=torch_threads, log_interval=log_interval)
    return lambda: _train(experiment, command_line, {"command": "train", **options}, tensorboard_log or log_folder)


def _train(experiment: Experiment, command_line: str, options: dict[str, Any], tensorboard_root) -> int:
    """Create the run folder, train and report: the run of :func:`train_command`."""
    import torch

    config, env_id = experiment.config, experiment.env_id
    run_dir = experiment.create_run_folder(command_line, dict(sorted(options.items())))
    algo_name = "RecurrentPPO" if config.get("algo") == "ppo_lstm" else "PPO"
    if experiment.source is not None:
        print(f"Continuing {experiment.source.run_dir or experiment.source.model_path} from step "
              f"{experiment.model.num_timesteps:,} ({experiment.source.model_path.name}), with its seed and run "
              "options unless given")
    print(f"Training {algo_name} ({config['policy']}, rule {rule_label(config)}) on {env_id} for "
          f"{config['n_timesteps']:,} steps, seed {experiment.seed}, {torch.get_num_threads()} torch thread(s)")
    print(f"Run folder:  {run_dir}")
    print(f"TensorBoard: tensorboard --logdir {tensorboard_root}")
    sys.stdout.flush()
    model = experiment.model
    try:
        finished = experiment.learn()
    except BaseException:
        if run_dir.exists():
            print(f"sb3-spikeplastic: training failed after {model.num_timesteps:,} steps; logs kept in {run_dir} "
                  "(see FAILED.txt; no final model written)", file=sys.stderr)
        else:
            print(f"sb3-spikeplastic: training failed before its first environment step; removed {run_dir}",
                  file=sys.stderr)
        raise
    if not finished:
        print(f"\nInterrupted after {model.num_timesteps:,} steps; saved {experiment.model_path}. Continue with\n"
              f"  {experiment.continue_command()}")
        return 130
    print(f"\nDone: {model.num_timesteps:,} steps.")
    print(f"  model:        {experiment.model_path}")
    if model.get_vec_normalize_env() is not None:
        print(f"  vecnormalize: {experiment.vecnormalize_path}")
    if experiment.eval_freq:
        best = run_dir / "best_model.zip"
        print(f"  best model:   {best if best.exists() else '(no evaluation ran)'}; evaluations.npz")
    if experiment.save_freq:
        print(f"  checkpoints:  {run_dir}/rl_model_*_steps.zip")
    print(f"  config:       {run_dir / env_id / 'config.yml'}")
    print(f"  monitor:      {run_dir}/*.monitor.csv")
    print(f"  tensorboard:  {experiment.tb_dir}")
    print(f"Evaluate with: sb3-spikeplastic evaluate --run {shlex.quote(str(run_dir))}")
    return 0
