"""The run folder that ``sb3-spikeplastic train`` writes and ``evaluate``, ``robustness``, ``inspect`` and
``train --trained-agent`` read, as a Python API.

Layout of ``<log folder>/ppo/<EnvId>_<n>/`` (after rl-baselines3-zoo's):

* ``<EnvId>.zip`` — the final model; ``best_model.zip`` and ``evaluations.npz`` with evaluations; checkpoints
  ``rl_model_<steps>_steps.zip`` with their statistics ``rl_model_vecnormalize_<steps>_steps.pkl``;
* ``<EnvId>/config.yml`` — the resolved hyperparameters (itself a hyperparameter file), ``<EnvId>/args.yml`` —
  the command's arguments, ``<EnvId>/vecnormalize.pkl`` — the final ``VecNormalize`` statistics;
* ``command.txt``, ``<i>.monitor.csv``, ``progress.csv``, TensorBoard events; ``INTERRUPTED.txt`` or
  ``FAILED.txt`` when the run did not finish.

Every model and statistics file is written through :func:`atomic_write`, so a crash never leaves a half-written
one. Errors are ``FileNotFoundError`` (nothing there) and ``ValueError`` (something there, but not usable).
"""

from __future__ import annotations

import os
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional

if TYPE_CHECKING:  # pragma: no cover
    import gymnasium
    from stable_baselines3.common.vec_env import VecEnv

CHECKPOINT = re.compile(r"rl_model_(\d+)_steps\.zip")


def atomic_write(path: os.PathLike, write: Callable[[Any], None], binary: bool = True) -> Path:
    """Write ``path`` through ``write(file)`` into a temporary file beside it, then rename it into place."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def save_model(model, path: os.PathLike) -> Path:
    """``model.save`` to ``path`` atomically."""
    return atomic_write(path, model.save)


def save_vecnormalize(venv, path: os.PathLike) -> Path:
    """``VecNormalize`` statistics to ``path`` atomically (the same pickle as ``VecNormalize.save``)."""
    return atomic_write(path, lambda f: pickle.dump(venv, f))


def checkpoint_statistics(checkpoint: Path) -> Path:
    """The ``VecNormalize`` statistics file that belongs to a checkpoint ``rl_model_<steps>_steps.zip``."""
    return checkpoint.with_name(checkpoint.name.replace("rl_model_", "rl_model_vecnormalize_")).with_suffix(".pkl")


def next_run_dir(root: Path, env_id: str) -> Path:
    """Create and return ``root/<env_id>_<n>`` with ``n`` the next free integer (from 1)."""
    root.mkdir(parents=True, exist_ok=True)
    pattern = re.compile(rf"^{re.escape(env_id)}_(\d+)$")
    n = max([int(m.group(1)) for p in root.iterdir() if (m := pattern.match(p.name))], default=0) + 1
    while True:
        candidate = root / f"{env_id}_{n}"
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            n += 1


@dataclass
class RunInfo:
    """What a run folder (or a model file) holds.

    :param model_path: the model ``.zip``
    :param env_id: the environment it was trained on (``None`` for a file outside a run folder)
    :param vecnormalize: its ``VecNormalize`` statistics, if any
    :param config: the run's resolved hyperparameters (``{}`` if unknown)
    :param run_dir: the run folder (``None`` for a file outside one)
    :param tensorboard_dir: the run's TensorBoard folder, when known
    """

    model_path: Path
    env_id: Optional[str] = None
    vecnormalize: Optional[Path] = None
    config: dict = field(default_factory=dict)
    run_dir: Optional[Path] = None
    tensorboard_dir: Optional[Path] = None

    @property
    def env_kwargs(self) -> dict:
        return dict(self.config.get("env_kwargs") or {})


def read_run_config(run_dir: Path) -> tuple[Optional[str], Optional[dict]]:
    """``(env_id, config)`` from ``run_dir/<EnvId>/config.yml``, or ``(None, None)`` if there is none."""
    from .zoo_yaml import yaml_load

    for cfg in sorted(Path(run_dir).glob("*/config.yml")):
        data = yaml_load(cfg.read_text())
        if isinstance(data, dict) and len(data) == 1:
            env_id, config = next(iter(data.items()))
            return env_id, config
    return None, None


def read_run_args(run_dir: Path, env_id: str) -> dict:
    """The arguments of the command that wrote ``run_dir`` (``<EnvId>/args.yml``; ``{}`` if absent)."""
    from .zoo_yaml import yaml_load

    path = Path(run_dir) / env_id / "args.yml"
    return (yaml_load(path.read_text()) or {}) if path.is_file() else {}


def latest_checkpoint(run_dir: Path) -> Optional[Path]:
    """The ``rl_model_<steps>_steps.zip`` of ``run_dir`` with the most steps (``None`` if there is none)."""
    found = [
        (int(m.group(1)), p) for p in Path(run_dir).glob("rl_model_*_steps.zip") if (m := CHECKPOINT.fullmatch(p.name))
    ]
    return max(found)[1] if found else None


def locate_run(path: os.PathLike, best: bool = False) -> RunInfo:
    """Resolve a run folder (its final model, or ``best_model.zip`` with ``best``) or a model ``.zip`` (a
    checkpoint finds its own statistics) into a :class:`RunInfo`."""
    p = Path(path)
    if p.is_dir():
        env_id, config = read_run_config(p)
        if env_id is None:
            raise ValueError(
                f"{str(path)!r} is not a run folder of `sb3-spikeplastic train` (no <EnvId>/config.yml in it)"
            )
        model = p / ("best_model.zip" if best else f"{env_id}.zip")
        if not model.is_file():
            failed = " (training failed: see FAILED.txt)" if (p / "FAILED.txt").exists() else ""
            checkpoint = latest_checkpoint(p)
            hint = f"; its latest checkpoint is --model {str(checkpoint)!r}" if checkpoint is not None else ""
            raise FileNotFoundError(f"run folder {str(path)!r} has no {model.name}{failed}{hint}")
        vecnorm = p / env_id / "vecnormalize.pkl"
        return RunInfo(model, env_id, vecnorm if vecnorm.is_file() else None, config or {}, p)
    if p.is_file() or Path(f"{path}.zip").is_file():
        p = p if p.is_file() else Path(f"{path}.zip")
        env_id, config = read_run_config(p.parent)
        candidates = [checkpoint_statistics(p)] if CHECKPOINT.fullmatch(p.name) else []
        candidates += [p.parent / p.stem / "vecnormalize.pkl", p.parent / "vecnormalize.pkl"]
        if env_id is not None:
            candidates.append(p.parent / env_id / "vecnormalize.pkl")
        vecnorm = next((c for c in candidates if c.is_file()), None)
        return RunInfo(p, env_id, vecnorm, config or {}, p.parent if env_id else None)
    raise FileNotFoundError(f"no run folder or model file {str(path)!r}")


def load_model(info: RunInfo, device: str = "cpu"):
    """The model of ``info``, loaded with the algorithm its run used (``algo`` of its config)."""
    from .validation import algorithm_class

    try:
        algorithm = algorithm_class(info.config.get("algo", "ppo"))
    except ValueError as exc:
        raise ValueError(f"cannot load model {str(info.model_path)!r}: {exc}") from None
    try:
        return algorithm.load(str(info.model_path), device=device)
    except Exception as exc:  # a corrupt or foreign file
        raise ValueError(f"cannot load model {str(info.model_path)!r}: {type(exc).__name__}: {exc}") from None


def make_eval_env(
    env_id: str, n_envs: int, seed: int, env_kwargs: Optional[dict] = None, vecnormalize: Optional[Path] = None
):
    """Monitored ``DummyVecEnv`` of ``env_id`` with the run's frozen ``VecNormalize`` statistics if given."""
    import gymnasium

    kwargs = dict(env_kwargs or {})
    return frozen_eval_env(lambda: gymnasium.make(env_id, **kwargs), n_envs, seed, vecnormalize)


def check_spaces(model, env, env_id: str, model_path) -> None:
    """``ValueError`` naming both sides unless ``model`` was trained on ``env``'s observation and action spaces."""
    from stable_baselines3.common.utils import check_for_correct_spaces

    try:
        check_for_correct_spaces(env, model.observation_space, model.action_space)
    except ValueError:
        raise ValueError(
            f"model {str(model_path)!r} (observations {model.observation_space}, actions "
            f"{model.action_space}) does not fit {env_id} (observations {env.observation_space}, "
            f"actions {env.action_space})"
        ) from None


def frozen_eval_env(
    make: Callable[[], gymnasium.Env], n_envs: int, seed: int, vec_normalize_path: str | os.PathLike | None = None
) -> VecEnv:
    """Seeded ``DummyVecEnv`` of ``Monitor(make())``, with frozen ``VecNormalize`` statistics if given.

    The Monitor is outermost so that it records the returns of the (possibly noisy) environment.
    """
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    venv: VecEnv = DummyVecEnv([lambda: Monitor(make()) for _ in range(n_envs)])
    venv.seed(seed)
    if vec_normalize_path is not None:
        venv = VecNormalize.load(str(vec_normalize_path), venv)
        # Evaluation must neither update the statistics nor see normalised rewards.
        venv.training = False
        venv.norm_reward = False
    return venv


def cpu_settings_of(model):
    """The CPU settings ``model`` runs its episodes under: :meth:`sb3_spikeplastic.PPO.cpu_settings` (flush-to-zero
    for spiking policies), nothing for other algorithms."""
    import contextlib

    settings = getattr(model, "cpu_settings", None)
    return settings() if callable(settings) else contextlib.nullcontext()
