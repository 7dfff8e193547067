"""rl-zoo style hyperparameter entries: merged, overridden, validated, and turned into the algorithm's arguments.

A hyperparameter file (default: ``hyperparams/ppo.yml``, shipped as package data ``sb3_spikeplastic.hyperparams``;
read by :mod:`sb3_spikeplastic.zoo.zoo_yaml`) maps Gymnasium ids to entries::

    TMazeCue-v0:
      n_timesteps: !!float 2e5          # meta keys: n_timesteps, n_envs, policy, policy_kwargs, normalize, env_kwargs
      n_envs: 8
      policy: SpikePlasticPolicy
      policy_kwargs: {rule: dp-oja, hidden_sizes: [64]}
      normalize: false                  # or true, or a mapping of VecNormalize arguments
      n_steps: 64                       # everything else: arguments of sb3_spikeplastic.PPO
      bptt_steps: 32

The ``default`` entry is merged under the environment's entry (mappings key by key, anything else replaced); an id
without an entry uses ``default`` alone. :func:`resolve_hyperparams` applies overrides (``key=value`` strings, values
parsed as YAML, dotted keys such as ``policy_kwargs.rule=dp-bcm`` reach into mappings) and validates every key and
value against what :class:`sb3_spikeplastic.PPO`, the policy, its plasticity rule and ``VecNormalize`` accept
(:mod:`sb3_spikeplastic.zoo.validation`), so mistakes surface as one-line ``ValueError``\\ s before anything runs.
:func:`model_arguments` turns a resolved entry into the arguments of
``PPO(policy, env, **ppo_kwargs, policy_kwargs=policy_kwargs)``; :func:`load_hyperparams` gives a packaged entry
as Python arguments.

rl-zoo's string form of mappings (``policy_kwargs: "dict(rule='dp-oja', hidden_sizes=[64])"``) is accepted and
parsed by :func:`sb3_spikeplastic.zoo.zoo_yaml.parse_python_literal`, which reads literals and ``dict(...)`` calls
only and never evaluates code.
"""

from __future__ import annotations

import copy
import difflib
import inspect
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Optional, Sequence, Union

import yaml

from .schedules import SCHEDULE_KEYS, schedule_argument
from .validation import CLASS_KEYS, META_KEYS, algorithm_class, resolve_class_name, validate_entry
from .zoo_yaml import as_mapping, default_hyperparams_path, load_hyperparams_file, parse_override

# ----------------------------------------------------------------------------------------------------------------
# Merging and overriding


def deep_merge(base: Mapping, top: Mapping) -> dict:
    """``top`` over ``base``: nested mappings merge key by key, everything else is replaced."""
    out = copy.deepcopy(dict(base))
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _set_path(entry: dict, path: Sequence[str], value: Any) -> None:
    node = entry
    for depth, key in enumerate(path[:-1]):
        child = as_mapping(node.get(key), ".".join(path[: depth + 1]))
        if child is None or child is True:  # normalize: true -> {} before setting one of its arguments
            child = {}
        if not isinstance(child, dict):
            where = ".".join(path[: depth + 1])
            raise ValueError(
                f"cannot set {'.'.join(path)}: {where} is {child!r}, not a mapping"
                + (" (set normalize=true first)" if where == "normalize" else "")
            )
        node[key] = child
        node = child
    node[path[-1]] = value


def _get_path(entry: Mapping, path: Sequence[str]) -> Any:
    node: Any = entry
    for depth, key in enumerate(path):
        if isinstance(node, str):
            node = as_mapping(node, ".".join(path[:depth]))
        if not isinstance(node, Mapping):
            return None
        node = node.get(key)
    return as_mapping(node, ".".join(path)) if isinstance(node, str) and path[-1] in _MAPPING_KEYS else node


#: Entry keys (and policy_kwargs keys) whose values are mappings, also in rl-zoo's string form.
_MAPPING_KEYS = ("policy_kwargs", "normalize", "env_kwargs", "rule_kwargs", "neuron", "optimizer_kwargs")


def _overridden_entry(
    env_id: str,
    conf: Union[str, Path, None],
    parsed: Sequence[tuple[tuple[str, ...], Any]],
    rule: Optional[str],
    replaced: Optional[list] = None,
) -> dict:
    """The file's ``default`` and ``env_id`` entries merged, with the parsed overrides and ``rule`` applied (not
    validated). ``replaced`` collects ``(index, path, keys)`` for each override that replaces a whole mapping."""
    data = load_hyperparams_file(conf)
    where = str(default_hyperparams_path() if conf is None else conf)
    if env_id not in data and "default" not in data:
        raise ValueError(
            f"no hyperparameters for {env_id!r} in {where} and no 'default' entry; entries: {', '.join(data) or 'none'}"
        )
    base = data.get("default", {})
    entry = deep_merge(base, data.get(env_id, {}))
    for key in ("policy_kwargs", "normalize", "env_kwargs"):  # string forms, before dotted overrides reach in
        if isinstance(entry.get(key), str):
            entry[key] = as_mapping(entry[key], key)
    if rule is not None:
        _drop_other_rules_arguments(entry, rule)
    for index, (path, value) in enumerate(parsed):
        if replaced is not None:
            old = _get_path(entry, path)
            if isinstance(old, Mapping) and old:
                replaced.append((index, path, list(old)))
        _set_path(entry, path, value)
    if rule is not None:
        _set_path(entry, ("policy_kwargs", "rule"), rule)
    return entry


def _drop_other_rules_arguments(entry: dict, rule: str) -> None:
    """Leave out of the file's ``rule_kwargs`` what ``rule`` does not take: they are the arguments of the file's own
    rule (``--conf paper --rule static`` drops the NDP rule's ``wm_init_gain``). Overrides are applied after this, so
    an argument given on the command line is still checked against ``rule``."""
    import inspect

    from ..snn.plasticity import get_rule_class

    policy_kwargs = entry.get("policy_kwargs")
    if not isinstance(policy_kwargs, Mapping) or not isinstance(policy_kwargs.get("rule_kwargs"), Mapping):
        return
    accepted = inspect.signature(get_rule_class(rule).__init__).parameters
    kept = {k: v for k, v in policy_kwargs["rule_kwargs"].items() if k in accepted}
    entry["policy_kwargs"] = {**policy_kwargs, "rule_kwargs": kept}


def print_replaced_mappings(
    env_id: str, conf: Union[str, Path, None] = None, overrides: Sequence[str] = (), rule: Optional[str] = None
) -> None:
    """Print :func:`replaced_mappings`'s lines, one ``sb3-spikeplastic: ...`` notice each (``train``, ``optimize``)."""
    for line in replaced_mappings(env_id, conf, overrides, rule):
        print(f"sb3-spikeplastic: {line}")


def replaced_mappings(
    env_id: str,
    conf: Union[str, Path, None] = None,
    overrides: Sequence[str] = (),
    rule: Optional[str] = None,
    option: str = "--hyperparams",
) -> list[str]:
    """One line for each override that replaces a whole mapping of the entry and so drops some of its keys
    (``policy_kwargs=dict(hidden_sizes=[32])`` drops the entry's other ``policy_kwargs``, whose defaults then
    apply), naming them; a dotted key (``policy_kwargs.hidden_sizes=[32]``) sets one key and keeps the others.
    Keys set again by later overrides or ``rule`` are not dropped. ``[]`` when nothing is dropped.

    :param option: the option the overrides came from, for the lines.
    """
    parsed = [parse_override(o) for o in overrides]
    replaced: list = []
    entry = _overridden_entry(env_id, conf, parsed, rule, replaced)
    lines = []
    for index, path, keys in replaced:
        final = _get_path(entry, path)
        dropped = [k for k in keys if not (isinstance(final, Mapping) and k in final)]
        if dropped:
            name = ".".join(path)
            lines.append(
                f"{option} {overrides[index]} replaces the entry's whole {name}, dropping its "
                f"{', '.join(map(str, dropped))} (their defaults apply; {name}.KEY=VALUE sets one key and "
                "keeps the others)"
            )
    return lines


def resolve_hyperparams(
    env_id: str,
    conf: Union[str, Path, None] = None,
    overrides: Sequence[str] = (),
    rule: Optional[str] = None,
    n_timesteps: Optional[int] = None,
    n_envs: Optional[int] = None,
) -> dict:
    """The validated hyperparameters of ``env_id``.

    Precedence, lowest first: the file's ``default`` entry, the environment's entry, ``overrides`` in order, then
    ``rule`` (``policy_kwargs.rule``), ``n_timesteps`` and ``n_envs``.

    :param env_id: Gymnasium id (its entry, or ``default`` alone when it has none).
    :param conf: hyperparameter file; ``None``: the packaged ``hyperparams/ppo.yml``.
    :param overrides: ``key=value`` strings (:func:`parse_override`).
    :param rule: plasticity rule, one of :func:`sb3_spikeplastic.available_rules`.
    :param n_timesteps: total environment steps.
    :param n_envs: number of environments.
    :raises ValueError: a one-line message naming the bad key or value and the accepted ones.
    """
    from ..snn.plasticity import get_rule_class

    parsed = [parse_override(o) for o in overrides]  # syntax first: cheap and independent of the file
    if rule is not None:
        get_rule_class(rule)  # a one-line error for an unknown name
    entry = _overridden_entry(env_id, conf, parsed, rule)
    if n_timesteps is not None:
        entry["n_timesteps"] = n_timesteps
    if n_envs is not None:
        entry["n_envs"] = n_envs
    if rule is not None and entry.get("policy", "SpikePlasticPolicy") != "SpikePlasticPolicy":
        raise ValueError(f"rule={rule!r} needs policy SpikePlasticPolicy, not {entry['policy']!r}")
    resolved = validate_entry(entry)
    resolved.setdefault("n_timesteps", 1_000_000)
    resolved.setdefault("n_envs", 1)
    resolved.setdefault("normalize", False)
    resolved.setdefault("policy_kwargs", {})
    resolved.setdefault("env_kwargs", {})
    return dict(sorted(resolved.items()))


# ----------------------------------------------------------------------------------------------------------------
# From a resolved entry to the model's arguments


def model_arguments(config: Mapping[str, Any]) -> tuple[str, dict, dict]:
    """``(policy, ppo_kwargs, policy_kwargs)`` for ``PPO(policy, env, **ppo_kwargs, policy_kwargs=policy_kwargs)``
    from a resolved entry (meta keys removed, ``lin_`` schedules and class names resolved)."""
    ppo_kwargs = {
        k: (schedule_argument(v) if k in SCHEDULE_KEYS else v) for k, v in config.items() if k not in META_KEYS
    }
    policy_kwargs = dict(config.get("policy_kwargs") or {})
    for key in CLASS_KEYS:
        if key in policy_kwargs:
            policy_kwargs[key] = resolve_class_name(policy_kwargs[key], key)
    if "obs_bounds" in policy_kwargs:
        policy_kwargs["obs_bounds"] = tuple(policy_kwargs["obs_bounds"])
    return config.get("policy", "SpikePlasticPolicy"), ppo_kwargs, policy_kwargs


def normalize_arguments(config: Mapping[str, Any]) -> Optional[dict]:
    """``VecNormalize`` arguments of a resolved entry (``None``: no normalisation). As in rl-zoo, the reward
    normalisation's ``gamma`` defaults to PPO's ``gamma``."""
    normalize = config.get("normalize", False)
    if normalize is False:
        return None
    kwargs = {} if normalize is True else dict(normalize)
    gamma = config.get(
        "gamma", inspect.signature(algorithm_class(config.get("algo", "ppo")).__init__).parameters["gamma"].default
    )  # the algorithm's default where the entry does not state it
    kwargs.setdefault("gamma", gamma)
    return kwargs


class Hyperparams(NamedTuple):
    """A packaged entry, ready to build the environment and the model (:func:`load_hyperparams`)::

    env = make_vec_env(env_id, n_envs=h.n_envs, env_kwargs=h.env_kwargs)
    if h.normalize is not None:
        env = VecNormalize(env, **h.normalize)
    model = PPO(h.policy, env, **h.model_kwargs)
    model.learn(h.n_timesteps)
    """

    #: Policy name for the algorithm's first argument (``"SpikePlasticPolicy"``, ``"MlpPolicy"``...).
    policy: str
    #: Number of environments stepped side by side.
    n_envs: int
    #: Total environment steps of a full run (all environments together).
    n_timesteps: int
    #: ``VecNormalize`` keyword arguments, or ``None`` when the entry does not normalise.
    normalize: Optional[dict]
    #: Keyword arguments of ``gymnasium.make(env_id, ...)`` (usually empty).
    env_kwargs: dict
    #: Keyword arguments of the algorithm's constructor after ``(policy, env)``, ``policy_kwargs`` included
    #: (``lin_`` schedules and class names already resolved).
    model_kwargs: dict
    #: The entry's algorithm (:data:`ALGOS`): ``"ppo"`` for :class:`sb3_spikeplastic.PPO`, ``"ppo_lstm"`` for
    #: sb3-contrib's ``RecurrentPPO`` (:func:`algorithm_class` gives the class).
    algo: str = "ppo"


def check_env_id(env_id: str, entries: Sequence[str] = ()) -> str:
    """``env_id`` if Gymnasium knows it (the plugin's environments included) or ``entries`` lists it.

    :raises ValueError: one line naming ``env_id``, the closest registered ids and what is accepted.
    """
    import gymnasium

    from .. import envs  # noqa: F401  (registers TMazeCue-v0, TMazeCueNoisy-v0, NoisyHalfCheetah-v5)

    if env_id in gymnasium.registry or (env_id in entries and env_id != "default"):
        return env_id
    close = difflib.get_close_matches(env_id, sorted(gymnasium.registry), n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    listed = ", ".join(e for e in entries if e != "default") or "none"
    raise ValueError(
        f"unknown environment id {env_id!r}; {hint}accepted: an entry of the file ({listed}) or any "
        f"of gymnasium's {len(gymnasium.registry)} registered ids (python -c 'import gymnasium, "
        "sb3_spikeplastic; gymnasium.pprint_registry()' lists them)"
    )


def load_hyperparams(env_id: str, conf: Union[str, Path] = "ppo", rule: Optional[str] = None) -> Hyperparams:
    """The hyperparameters that ``sb3-spikeplastic train --env ENV_ID [--conf CONF] [--rule RULE]`` uses, as
    arguments for Python.

    :param env_id: a Gymnasium id. Its entry in the file is merged over ``default``; a registered id without an
        entry (``CartPole-v1``) gets ``default`` alone, as on the command line.
    :param conf: a packaged file by name (:data:`PACKAGED_HYPERPARAMS`: ``ppo``, ``paper``, ``mlp``,
        ``ppo_lstm``) or the path of a hyperparameter file, e.g. a run's ``config.yml``.
    :param rule: plasticity rule replacing the entry's ``policy_kwargs.rule`` (one of
        :func:`sb3_spikeplastic.available_rules`); only for ``SpikePlasticPolicy`` entries.
    :return: a :class:`Hyperparams` ``(policy, n_envs, n_timesteps, normalize, env_kwargs, model_kwargs, algo)``:
        ``PPO(h.policy, env, **h.model_kwargs)`` builds the model on an environment made with ``h.n_envs``,
        ``h.env_kwargs`` and, unless ``h.normalize`` is ``None``, ``VecNormalize(env, **h.normalize)``. Every
        dictionary is a fresh copy: change it freely (e.g. ``h.model_kwargs["n_steps"] = 64``).
    :raises ValueError: one line naming the bad environment id, file or rule and the accepted ones.
    """
    data = load_hyperparams_file(conf)
    check_env_id(env_id, tuple(data))
    resolved = resolve_hyperparams(env_id, conf, rule=rule)
    policy, ppo_kwargs, policy_kwargs = model_arguments(resolved)
    return Hyperparams(
        policy=policy,
        n_envs=resolved["n_envs"],
        n_timesteps=resolved["n_timesteps"],
        normalize=normalize_arguments(resolved),
        env_kwargs=copy.deepcopy(resolved["env_kwargs"]),
        model_kwargs={**ppo_kwargs, "policy_kwargs": policy_kwargs},
        algo=resolved.get("algo", "ppo"),
    )


def dump_yaml(data: Any) -> str:
    """YAML text of plain data (tuples as lists, keys in the given order)."""

    def plain(x):
        if isinstance(x, Mapping):
            return {str(k): plain(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [plain(v) for v in x]
        return x

    return yaml.safe_dump(plain(data), sort_keys=False, default_flow_style=None)


def rule_label(config: dict) -> str:
    """Short name of a run's policy for folder names and messages: the rule, or ``mlp``, ``mlplstm``..."""
    if config.get("policy") != "SpikePlasticPolicy":
        return str(config.get("policy", "policy")).lower().replace("policy", "") or "policy"
    return str((config.get("policy_kwargs") or {}).get("rule", "dp-oja"))
