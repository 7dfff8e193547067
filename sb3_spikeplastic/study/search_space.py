"""The search space of ``sb3-spikeplastic optimize``: per environment, how each hyperparameter is sampled
(``hyperparams/search_space.yml``: ``{log: [low, high]}``, ``{uniform: ...}``, ``{int: ...}``, ``{choices: [...]}``),
which of its keys a trial samples for an entry, and one sampled configuration as ``--hyperparams`` overrides,
made consistent (a rule without a trace samples none of its parameters; the batch fits in the rollout and
``bptt_steps`` divides ``n_steps`` and ``batch_size``).
"""

from __future__ import annotations

import inspect
import json
import math
from pathlib import Path
from typing import Any, Optional, Sequence

from ..zoo.validation import META_KEYS, algorithm_class, policy_kwarg_hints, ppo_argument_hints
from ..zoo.zoo_yaml import load_hyperparams_file, packaged_hyperparams_path, yaml_load

#: How a search-space key is sampled (see ``hyperparams/search_space.yml``).
SPACE_FORMS = ("log", "uniform", "int", "choices")
RULE_KEY = "policy_kwargs.rule"
#: Keys that only matter for a rule with a trace.
PLASTIC_PREFIXES = ("policy_kwargs.alpha_", "policy_kwargs.rule_kwargs.")


def load_search_space(env_id: str, path: Optional[Path] = None) -> dict[str, tuple[str, list]]:
    """The search space of ``env_id``: ``{key: (form, values)}`` with ``form`` one of :data:`SPACE_FORMS`.

    :param env_id: its entry is merged over ``default`` (a ``null`` value removes a key)
    :param path: a search-space file (default: the packaged ``search_space.yml``)
    :raises ValueError: one line naming a malformed key
    """
    path = Path(path) if path is not None else packaged_hyperparams_path("search_space")
    data = load_hyperparams_file(path)
    space: dict[str, tuple[str, list]] = {}
    for key, spec in {**data.get("default", {}), **data.get(env_id, {})}.items():
        if spec is None:
            continue
        where = f"search space {key!r} in {str(path)!r}"
        if not (isinstance(spec, dict) and len(spec) == 1 and next(iter(spec)) in SPACE_FORMS):
            raise ValueError(
                f"{where} must be one of {{log: [low, high]}}, {{uniform: [low, high]}}, "
                f"{{int: [low, high]}}, {{choices: [...]}}; got {spec!r}"
            )
        form, values = next(iter(spec.items()))
        if not isinstance(values, list) or not values:
            raise ValueError(f"{where}: {form} needs a non-empty list, got {values!r}")
        if form != "choices":
            numbers = len(values) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
            if (
                not numbers
                or values[0] >= values[1]
                or (form == "log" and values[0] <= 0)
                or (form == "int" and not all(float(v).is_integer() for v in values))
            ):
                raise ValueError(
                    f"{where}: {form} needs [low, high] with low < high"
                    + (" and low > 0" if form == "log" else "")
                    + (", both integers" if form == "int" else "")
                    + f"; got {values!r}"
                )
        space[key] = (form, values)
    return space


def _overlaps(key: str, fixed: str) -> bool:
    return key == fixed or key.startswith(fixed + ".") or fixed.startswith(key + ".")


def searched_space(space: dict, entry: dict, fixed: Sequence[str] = (), rule_fixed: bool = False) -> dict:
    """The keys of ``space`` that a trial samples for ``entry`` (a resolved hyperparameter entry): those its
    algorithm and policy take, not fixed by ``fixed`` (``--hyperparams`` keys) or, for the rule, ``rule_fixed``.

    :param space: :func:`load_search_space`
    :param entry: the resolved entry the trials start from
    :param fixed: dotted keys set on the command line
    :param rule_fixed: whether ``--rule`` was given
    """
    algo, policy = entry.get("algo", "ppo"), entry["policy"]
    top_keys = (*META_KEYS, *ppo_argument_hints(algo))
    policy_keys = policy_kwarg_hints(policy, algo)
    spiking = policy == "SpikePlasticPolicy"
    out = {}
    for key, spec in space.items():
        path = key.split(".")
        if any(_overlaps(key, f) for f in fixed) or (key == RULE_KEY and rule_fixed):
            continue
        if path[0] == "policy_kwargs":
            if len(path) < 2 or path[1] not in policy_keys:
                continue
        elif path[0] not in top_keys or (key == "bptt_steps" and not spiking):
            continue
        out[key] = spec
    return out


def _suggest(trial, key: str, form: str, values: list) -> Any:
    if form == "choices":
        return trial.suggest_categorical(key, values)
    if form == "int":
        return trial.suggest_int(key, int(values[0]), int(values[1]))
    return trial.suggest_float(key, float(values[0]), float(values[1]), log=form == "log")


def _algorithm_default(entry: dict, key: str) -> Any:
    parameter = inspect.signature(algorithm_class(entry.get("algo", "ppo")).__init__).parameters.get(key)
    if parameter is None:
        return None
    if parameter.default is None and entry.get("algo", "ppo") == "ppo":
        from ..sb3.ppo import POLICY_DEPENDENT_DEFAULTS

        if key in POLICY_DEPENDENT_DEFAULTS:  # the value PPO resolves None to for the entry's policy
            return POLICY_DEPENDENT_DEFAULTS[key][entry.get("policy", "SpikePlasticPolicy") == "SpikePlasticPolicy"]
    return parameter.default


def sample_overrides(trial, space: dict, entry: dict, fixed: Sequence[str] = ()) -> list[str]:
    """Sample one configuration: ``key=value`` overrides (as ``--hyperparams`` takes them) for ``entry``.

    The rule comes first; a rule without a trace samples no ``alpha_*`` or ``rule_kwargs.*`` key. Then the sizes
    are made consistent (keys fixed by ``fixed`` are left alone): ``batch_size`` at most ``n_steps * n_envs``,
    and ``bptt_steps`` the greatest common divisor of itself, ``n_steps`` and ``batch_size``.

    :param trial: an Optuna trial
    :param space: :func:`searched_space`
    :param entry: the resolved entry the trial starts from
    :param fixed: dotted keys set on the command line
    """
    from ..snn.plasticity import get_rule_class

    values: dict[str, Any] = {}
    if RULE_KEY in space:
        values[RULE_KEY] = _suggest(trial, RULE_KEY, *space[RULE_KEY])
    rule = values.get(RULE_KEY) or (entry.get("policy_kwargs") or {}).get("rule") or "dp-oja"
    traced = entry["policy"] == "SpikePlasticPolicy" and get_rule_class(rule).has_trace
    for key, spec in space.items():
        if key != RULE_KEY and (traced or not key.startswith(PLASTIC_PREFIXES)):
            values[key] = _suggest(trial, key, *spec)

    def current(key):
        return values[key] if key in values else entry.get(key, _algorithm_default(entry, key))

    free = {k for k in ("batch_size", "bptt_steps") if not any(_overlaps(k, f) for f in fixed)}
    n_steps = current("n_steps")
    if "batch_size" in free and isinstance(n_steps, int) and isinstance(current("batch_size"), int):
        if current("batch_size") > n_steps * entry["n_envs"]:
            values["batch_size"] = n_steps * entry["n_envs"]
    if "bptt_steps" in free and "bptt_steps" in space:
        values["bptt_steps"] = math.gcd(current("bptt_steps"), n_steps, current("batch_size"))
    return [f"{key}={_yaml_value(value)}" for key, value in values.items()]


def _yaml_value(value: Any) -> str:
    """``value`` as ``--hyperparams`` reads it back: JSON (valid YAML), strings unquoted where YAML allows."""
    text = json.dumps(value)
    return value if isinstance(value, str) and yaml_load(value) == value else text
