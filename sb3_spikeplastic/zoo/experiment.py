"""One training run and its run folder (after rl-baselines3-zoo's ``ExperimentManager``): the environments, the
model, the callbacks, the logs and every file that ``sb3-spikeplastic train`` writes (layout:
:mod:`sb3_spikeplastic.zoo.run_folder`).

The model is built in memory first (:meth:`Experiment.setup`), so that bad hyperparameters fail before anything
is written; then :meth:`Experiment.create_run_folder` and :meth:`Experiment.learn`, which saves the final model,
writes ``INTERRUPTED.txt`` on Ctrl-C, and on a crash removes the folder (before the first step) or marks it with
``FAILED.txt``. The command that checks ``train``'s options and runs an :class:`Experiment` is
:mod:`sb3_spikeplastic.zoo.train`.
"""

from __future__ import annotations

import shlex
import shutil
import signal
import threading
import traceback
from collections.abc import Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Optional

import gymnasium

from ..envs import route_mujoco_warnings
from .config import dump_yaml, model_arguments, normalize_arguments, rule_label
from .run_folder import RunInfo, atomic_write, check_spaces, next_run_dir, save_model, save_vecnormalize
from .validation import META_KEYS, algorithm_class, ppo_argument_hints


class SuccessColumn(gymnasium.Wrapper):
    """Puts ``info["is_success"] = None`` at episode ends where the env reports no success, so that the Monitor
    files always have an ``is_success`` column (empty for such envs; SB3 ignores ``None`` successes)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            info.setdefault("is_success", None)
        return obs, reward, terminated, truncated, info


def make_train_env(
    env_id: str, n_envs: int, env_kwargs: dict, monitor_dir: Optional[Path] = None, vec_env: str = "dummy"
):
    """``n_envs`` monitored environments (Monitor CSVs in ``monitor_dir`` when given), stepped in this process
    (``vec_env="dummy"``) or each in a process of its own (``"subproc"``)."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    def factory(rank: int):
        def make():
            route_mujoco_warnings()  # in a subprocess too: the parent's route does not reach it
            env = SuccessColumn(gymnasium.make(env_id, **env_kwargs))
            filename = None if monitor_dir is None else str(monitor_dir / str(rank))
            return Monitor(env, filename=filename, info_keywords=("is_success",))

        return make

    factories = [factory(i) for i in range(n_envs)]
    return SubprocVecEnv(factories) if vec_env == "subproc" else DummyVecEnv(factories)


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

    entry = {k: config[k] for k in META_KEYS if k in config and k != "policy_kwargs"}
    algo = config.get("algo", "ppo")
    defaults = inspect.signature(algorithm_class(algo).__init__).parameters
    for key in ppo_argument_hints(algo):
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

    def __init__(
        self,
        env_id: str,
        config: dict,
        seed: int,
        log_folder: Path,
        tensorboard_log: Optional[Path] = None,
        device: str = "cpu",
        verbose: int = 1,
        eval_freq: int = 0,
        eval_episodes: int = 20,
        save_freq: int = 0,
        keep_checkpoints: int = 2,
        figure_freq: int = 0,
        vec_env: str = "dummy",
        progress: bool = True,
        trained_agent: Optional[RunInfo] = None,
        after_eval=None,
        log_interval: int = 1,
    ):
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

        norm_kwargs = normalize_arguments(self.config)
        return venv if norm_kwargs is None else VecNormalize(venv, **norm_kwargs)

    def setup(self):
        """Build the environments and the model (or load the continued one) in memory, without writing anything:
        bad hyperparameters raise here (``ValueError``, ``TypeError``; gymnasium's errors for bad env_kwargs)."""
        from .run_folder import load_model

        probe = self._normalized(make_train_env(self.env_id, self.n_envs, self.env_kwargs))
        try:
            if self.source is None:
                policy, ppo_kwargs, policy_kwargs = model_arguments(self.config)
                algorithm = algorithm_class(self.config.get("algo", "ppo"))
                # Quiet while built (SB3 says "Using cpu device"): bad hyperparameters must fail on one line.
                self.model = algorithm(
                    policy,
                    probe,
                    **ppo_kwargs,
                    policy_kwargs=policy_kwargs,
                    seed=self.seed,
                    device=self.device,
                    verbose=0,
                )
                self.model.verbose = self.sb3_verbose
            else:
                self.model = load_model(self.source, device=self.device)
                check_spaces(self.model, probe, self.env_id, self.source.model_path)
                self.model.verbose = self.sb3_verbose
                if self.model.num_timesteps >= self.config["n_timesteps"]:
                    raise ValueError(
                        f"{str(self.source.model_path)!r} has trained {self.model.num_timesteps:,} of "
                        f"n_timesteps={self.config['n_timesteps']:,} steps already; pass a larger -n "
                        "(the run's total)"
                    )
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
        entry = dump_yaml({self.env_id: resolved_entry(self.model, self.config)})
        atomic_write(meta_dir / "config.yml", lambda f: f.write(entry), binary=False)
        run_args = {
            **args,
            "seed": self.seed,
            "env": self.env_id,
            "run_dir": str(self.run_dir),
            "tensorboard_dir": str(self.tb_dir),
        }
        if self.source is not None:
            run_args.update(
                trained_agent=str(self.source.model_path),
                start_timesteps=self.model.num_timesteps,
                continues=None if self.source.run_dir is None else str(self.source.run_dir),
            )
        atomic_write(meta_dir / "args.yml", lambda f: f.write(dump_yaml(run_args)), binary=False)
        return self.run_dir

    def _callbacks(self, eval_env) -> list:
        from stable_baselines3.common.callbacks import EvalCallback

        from .callbacks import ActivityFigureCallback, AtomicCheckpoint, SaveBest, TrainingSummary, WallClockProgress

        callbacks = [WallClockProgress()] if self.progress else []
        if self.verbose == 1:
            callbacks.append(TrainingSummary(self.config["n_timesteps"] // 10))
        if eval_env is not None:
            callbacks.append(
                EvalCallback(
                    eval_env,
                    callback_on_new_best=SaveBest(self.run_dir / "best_model.zip"),
                    n_eval_episodes=self.eval_episodes,
                    eval_freq=max(self.eval_freq // self.n_envs, 1),
                    log_path=str(self.run_dir),
                    best_model_save_path=None,
                    deterministic=True,
                    verbose=self.sb3_verbose,
                    callback_after_eval=self.after_eval,
                )
            )
        if self.save_freq:
            callbacks.append(
                AtomicCheckpoint(max(self.save_freq // self.n_envs, 1), self.run_dir, self.keep_checkpoints)
            )
        if self.figure_freq:
            callbacks.append(
                ActivityFigureCallback(self.env_id, every=self.figure_freq, env_kwargs=self.env_kwargs, seed=self.seed)
            )
        return callbacks + list(self.extra_callbacks)

    def _environments(self):
        """The training environments (the continued run's statistics too) and the evaluation environment."""
        from stable_baselines3.common.vec_env import VecNormalize

        from .run_folder import make_eval_env

        env = make_train_env(self.env_id, self.n_envs, self.env_kwargs, self.run_dir, self.vec_env)
        norm_kwargs = normalize_arguments(self.config)
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
        argv = [
            "sb3-spikeplastic",
            "train",
            "--env",
            self.env_id,
            "-i",
            str(self.model_path),
            "-f",
            str(self.log_folder),
            "-n",
            str(self.config["n_timesteps"]),
        ]
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
            write_hyperparameters(
                model.logger, {"env_id": self.env_id, "seed": self.seed, **resolved_entry(model, self.config)}
            )
            # Continuing: the remaining steps with the counter kept, so schedules resume where they stopped.
            callback = CallbackList(self._callbacks(eval_env))
            with sigterm_interrupts():
                model.learn(
                    self.config["n_timesteps"] - model.num_timesteps,
                    callback=callback,
                    reset_num_timesteps=self.source is None,
                    log_interval=self.log_interval,
                )
        except KeyboardInterrupt:
            self.save()
            note = (
                f"interrupted after {model.num_timesteps:,} of {self.config['n_timesteps']:,} steps; continue "
                f"with\n{self.continue_command()}\n"
            )
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
