"""rl-zoo's linear schedules: ``learning_rate: lin_3e-4`` in a hyperparameter entry decays the value linearly from
3e-4 to 0 over training. The entry keeps the string (so that a run's ``config.yml`` says what was written); the
function is built only for the algorithm's constructor.

The function is a closure: a saved model pickles it by value (cloudpickle), so loading one never imports this
module.
"""

from __future__ import annotations

import re
from typing import Any, Callable

#: PPO arguments that accept rl-zoo's ``lin_<value>`` linear schedules.
SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf")

_LIN = re.compile(r"^lin_(.+)$")


def linear_schedule(initial: float) -> Callable[[float], float]:
    """rl-zoo's ``lin_<value>``: decays linearly from ``initial`` to 0 over training."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def check_schedule(key: str, value: Any, allow_none: bool) -> Any:
    """``value`` of the schedule argument ``key`` as an entry keeps it: a float, a ``lin_<number>`` string, or
    ``None`` where ``allow_none``; ``ValueError`` naming the key otherwise."""
    if value is None and allow_none:
        return None
    if isinstance(value, str):
        match = _LIN.match(value)
        if match:
            try:
                float(match.group(1))
                return value
            except ValueError:
                pass
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    raise ValueError(
        f"{key}={value!r} must be a number or lin_<number> (linear decay)" + (" or null" if allow_none else "")
    )


def schedule_argument(value: Any) -> Any:
    """A checked schedule value (:func:`check_schedule`) as the algorithm takes it: ``lin_<number>`` becomes
    :func:`linear_schedule`, anything else stays."""
    if isinstance(value, str):
        return linear_schedule(float(_LIN.match(value).group(1)))
    return value
