"""Checks of the input that several ``sb3-spikeplastic`` commands share: counts, the torch device, output paths,
``--env-kwargs`` and the model a command plays (``--run`` / ``--model``).

Each raises ``ValueError`` with a one-line message (the command line prints it as ``sb3-spikeplastic: error: ...``
with exit status 2) and writes nothing, so that every command checks all of its input before any work.
"""

from __future__ import annotations

import os
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
        raise ValueError(f"--device {device}: no CUDA device is available (torch {torch.__version__}); "
                         "accepted here: cpu, auto")
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
    """``--env-kwargs key=value ...`` (values as YAML) as a dict; ``None`` when not given."""
    from .config import parse_override

    if items is None:
        return None
    out: dict[str, Any] = {}
    for item in items:
        try:
            path, value = parse_override(item)
        except ValueError as exc:
            raise ValueError(str(exc).replace("hyperparameter override", "--env-kwargs entry")) from None
        if len(path) != 1:
            raise ValueError(f"malformed --env-kwargs entry {item!r}; expected key=value")
        out[path[0]] = value
    return out


def model_source(run: Optional[str] = None, model: Optional[str] = None, env: Optional[str] = None,
                 vecnormalize: Optional[str] = None, best: bool = False,
                 env_kwargs: Optional[Sequence[str]] = None) -> tuple[RunInfo, str]:
    """The model that ``--run FOLDER`` or ``--model PATH`` names, with the environment it plays in: ``(info,
    env_id)``; ``info.config["env_kwargs"]`` holds the environment's arguments (``--env-kwargs``, else the run's,
    else none when ``--env`` names another environment than the run's)."""
    from .config import check_env_id
    from .run_folder import locate_run

    if bool(run) == bool(model):
        raise ValueError("give either --run FOLDER or --model PATH (with --env)")
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
