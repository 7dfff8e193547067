"""Checks of the input that several ``sb3-spikeplastic`` commands share: counts, the torch device, output paths,
``--env-kwargs`` and the model a command plays (``--run`` / ``--model``, or rl-zoo's ``-f LOGS --env ID --exp-id N``).

Each raises ``ValueError`` with a one-line message (the command line prints it as ``sb3-spikeplastic: error: ...``
with exit status 2) and writes nothing, so that every command checks all of its input before any work.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Optional, Sequence

from .run_folder import RunInfo


def check_int(name: str, value: Optional[int], minimum: int) -> None:
    """``ValueError`` if ``value`` is given and below ``minimum`` (``name`` is the option, e.g. ``--episodes``)."""
    if value is not None and value < minimum:
        raise ValueError(f"{name}={value} must be >= {minimum}")


def check_device(device: str) -> str:
    """``device`` if torch knows it and this machine has it (``auto`` is always accepted: it falls back to the
    CPU; an explicit CUDA device is never downgraded silently)."""
    import torch

    try:
        parsed = torch.device(device if device != "auto" else "cpu")
    except (RuntimeError, TypeError):
        raise ValueError(f"unknown device {device!r}; accepted: cpu, cuda, cuda:<n>, mps, auto") from None
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"--device {device}: no CUDA device is available (torch {torch.__version__}); accepted here: cpu, auto"
        )
    if parsed.type == "cuda" and parsed.index is not None and parsed.index >= torch.cuda.device_count():
        raise ValueError(f"--device {device}: only {torch.cuda.device_count()} CUDA device(s) here")
    return device


def check_output_path(path: os.PathLike, flag: str, directory: bool) -> Path:
    """``ValueError`` unless ``path`` can be created or written as a folder (``directory``) or a file: the part that
    exists must be a folder (no file on the way) and the nearest existing folder writable. Checked before any
    work, so that a long run never fails at its end for want of a place to write."""
    path = Path(path)
    if path.exists():
        if directory and not path.is_dir():
            raise ValueError(f"{flag} {str(path)!r} is a file, not a folder")
        if not directory and path.is_dir():
            raise ValueError(f"{flag} {str(path)!r} is a folder, not a file")
    parent = path if directory else path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"{flag} {str(path)!r} lies under the file {str(parent)!r}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{flag} {str(path)!r}: no permission to write in {str(parent)!r}")
    return path


def parse_env_kwargs(items: Optional[Sequence[str]]) -> Optional[dict]:
    """``--env-kwargs key=value ...`` (or rl-zoo's ``key:value``; values as YAML) as a dict; ``None`` when not
    given. Errors name ``--env-kwargs``."""
    from .zoo_yaml import parse_override

    if items is None:
        return None
    out: dict[str, Any] = {}
    for item in items:
        path, value = parse_override(item, "--env-kwargs entry", "max_episode_steps=200 or noise:high")
        if len(path) != 1:
            raise ValueError(
                f"malformed --env-kwargs entry {item!r}; expected key=value or key:value with a key without dots"
            )
        out[path[0]] = value
    return out


def zoo_run_folder(folder: os.PathLike, env_id: Optional[str], exp_id: int = 0) -> Path:
    """The run that rl-zoo's ``-f LOGS --env ID --exp-id N`` names: ``LOGS/ppo/<ID>_<N>``, ``N = 0`` the latest
    (the highest number). ``FileNotFoundError`` naming the runs there when it does not exist."""
    if not env_id:
        raise ValueError("-f/--folder needs --env ID: the run is <folder>/ppo/<ID>_<exp-id>")
    if exp_id < 0:
        raise ValueError(f"--exp-id {exp_id}: accepted: 0 (the latest run) or a run's number")
    root = Path(folder) / "ppo"
    pattern = re.compile(rf"{re.escape(env_id)}_(\d+)")
    numbers = sorted(
        int(m.group(1))
        for p in (root.iterdir() if root.is_dir() else ())
        if p.is_dir() and (m := pattern.fullmatch(p.name))
    )
    if not numbers:
        raise FileNotFoundError(
            f"no run of {env_id} in {str(root)!r} (-f {folder}): `sb3-spikeplastic train --env "
            f"{env_id} -f {folder}` writes one"
        )
    run = root / f"{env_id}_{exp_id or numbers[-1]}"
    if not run.is_dir():
        raise FileNotFoundError(
            f"no run folder {str(run)!r} (--exp-id {exp_id}); runs of {env_id} there: "
            f"{', '.join(map(str, numbers))} (--exp-id 0: the latest)"
        )
    return run


def checkpoint_of(run: os.PathLike, steps: Optional[int] = None) -> Path:
    """The checkpoint ``rl_model_<steps>_steps.zip`` of a run folder, or its latest one (``steps=None``);
    ``FileNotFoundError`` naming the checkpoints there when it does not exist."""
    from .run_folder import CHECKPOINT, latest_checkpoint

    if steps is None:
        path = latest_checkpoint(Path(run))
        if path is None:
            raise FileNotFoundError(
                f"run folder {str(run)!r} has no checkpoint (rl_model_<steps>_steps.zip: train --save-freq writes them)"
            )
        return path
    path = Path(run) / f"rl_model_{steps}_steps.zip"
    if not path.is_file():
        found = sorted(
            int(m.group(1)) for p in Path(run).glob("rl_model_*_steps.zip") if (m := CHECKPOINT.fullmatch(p.name))
        )
        raise FileNotFoundError(
            f"run folder {str(run)!r} has no checkpoint {path.name}; its checkpoints: "
            f"{', '.join(map(str, found)) or 'none'} (--load-checkpoint STEPS)"
        )
    return path


def model_source(
    run: Optional[str] = None,
    model: Optional[str] = None,
    env: Optional[str] = None,
    vecnormalize: Optional[str] = None,
    best: bool = False,
    env_kwargs: Optional[Sequence[str]] = None,
    folder: Optional[str] = None,
    exp_id: int = 0,
    load_checkpoint: Optional[int] = None,
    load_last_checkpoint: bool = False,
) -> tuple[RunInfo, str]:
    """The model that ``--run FOLDER``, ``--model PATH`` or rl-zoo's ``-f LOGS --env ID --exp-id N``
    (:func:`zoo_run_folder`) names, with the environment it plays in: ``(info, env_id)``. Of a run, the final
    model, ``best`` (``--best``/``--load-best``) ``best_model.zip``, ``load_checkpoint`` the checkpoint of that
    many steps, ``load_last_checkpoint`` the latest. ``info.config["env_kwargs"]`` holds the environment's
    arguments (``--env-kwargs``, else the run's, else none when ``--env`` names another environment than the
    run's)."""
    from .config import check_env_id
    from .run_folder import locate_run

    if folder is not None:
        if run or model:
            raise ValueError("give one of --run FOLDER, --model PATH or -f/--folder LOGS with --env ID")
        run = str(zoo_run_folder(folder, env, exp_id))
    if bool(run) == bool(model):
        raise ValueError("give either --run FOLDER or --model PATH (with --env)")
    if load_checkpoint is not None or load_last_checkpoint:
        chosen = [
            flag
            for flag, given in (
                ("--best", best),
                ("--load-checkpoint", load_checkpoint is not None),
                ("--load-last-checkpoint", load_last_checkpoint),
            )
            if given
        ]
        if len(chosen) > 1:
            raise ValueError(f"{' and '.join(chosen)}: give one of them")
        if not run:
            raise ValueError(
                f"{chosen[0]} picks a checkpoint of a run: give --run FOLDER or -f LOGS --env ID, "
                "or the checkpoint itself as --model PATH"
            )
        run, model = None, str(checkpoint_of(run, load_checkpoint))
    info = locate_run(run or model, best=best)
    if model and vecnormalize:
        if not Path(vecnormalize).is_file():
            raise ValueError(f"no VecNormalize statistics file {vecnormalize!r}")
        info.vecnormalize = Path(vecnormalize)
    env_id = env or info.env_id
    if env_id is None:
        raise ValueError(f"--env is needed: {model!r} is not inside a run folder that names its environment")
    parsed = parse_env_kwargs(env_kwargs)
    if parsed is not None:
        info.config["env_kwargs"] = parsed
    elif env and env != info.env_id:
        info.config["env_kwargs"] = {}  # the run's env_kwargs belong to its own environment
    return info, check_env_id(env_id)
