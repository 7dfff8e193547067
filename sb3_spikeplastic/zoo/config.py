"""rl-zoo style hyperparameter files: loading, command-line overrides, validation, and the PPO arguments.

A hyperparameter file (default: ``hyperparams/ppo.yml``, shipped as package data ``sb3_spikeplastic.hyperparams``)
maps Gymnasium ids to entries::

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
value against what :class:`sb3_spikeplastic.PPO`, the policy, its plasticity rule and ``VecNormalize`` accept, so
mistakes surface as one-line ``ValueError``\\ s before anything runs. :func:`model_arguments` turns a resolved entry
into the arguments of ``PPO(policy, env, **ppo_kwargs, policy_kwargs=policy_kwargs)``.

rl-zoo's string form of mappings (``policy_kwargs: "dict(rule='dp-oja', hidden_sizes=[64])"``) is accepted and
parsed by :func:`parse_python_literal`, which reads literals and ``dict(...)`` calls only and never evaluates code.
"""

from __future__ import annotations

import ast
import collections.abc
import copy
import difflib
import importlib.resources
import inspect
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Optional, Sequence, Union

import yaml

#: Keys of an entry that are not PPO arguments (rl-zoo's meta keys that this CLI implements).
META_KEYS = ("algo", "n_timesteps", "n_envs", "policy", "policy_kwargs", "normalize", "env_kwargs")
#: Values of an entry's ``algo`` key (rl-zoo's algorithm names): ``ppo`` is :class:`sb3_spikeplastic.PPO` (spiking
#: and SB3 policies), ``ppo_lstm`` sb3-contrib's ``RecurrentPPO`` (a baseline; ``pip install sb3-contrib``).
ALGOS = ("ppo", "ppo_lstm")
#: PPO arguments that the command line (or the run) sets, not the hyperparameter file.
_PPO_EXCLUDED = ("self", "policy", "env", "policy_kwargs", "tensorboard_log", "verbose", "seed", "device",
                 "_init_setup_model", "rollout_buffer_class", "rollout_buffer_kwargs")
#: PPO arguments that accept rl-zoo's ``lin_<value>`` linear schedules.
SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf")
#: Policy arguments naming a class: accepted as a name (``ReLU``, ``nn.ReLU``, ``th.optim.AdamW``,
#: ``PlaceCellFeatures``...).
_CLASS_KEYS = {"activation_fn": "torch.nn", "optimizer_class": "torch.optim",
               "features_extractor_class": "sb3_spikeplastic.sb3.encoder_features"}
#: Policy arguments of SB3's ActorCriticPolicy that SpikePlasticPolicy passes on and that make sense for it.
_SPIKE_EXTRA_POLICY_KEYS = ("optimizer_class", "optimizer_kwargs")
_UNSETTABLE_POLICY_KEYS = ("self", "observation_space", "action_space", "lr_schedule", "kwargs")


def packaged_hyperparams_path(name: str = "ppo") -> Path:
    """The hyperparameter file ``<name>.yml`` shipped with the package (found both in editable installs and in
    wheels): ``ppo`` (the default), ``paper`` (the paper's HalfCheetah network), ``mlp`` and ``ppo_lstm`` (the
    MlpPolicy and RecurrentPPO baselines, trained with the spiking entry's PPO settings), ``mlp_zoo`` and
    ``ppo_lstm_zoo`` (the same baselines with rl-baselines3-zoo's tuned HalfCheetah settings)."""
    try:
        return Path(str(importlib.resources.files("sb3_spikeplastic.hyperparams").joinpath(f"{name}.yml")))
    except ModuleNotFoundError:  # an editable install made before the data package existed: the source tree's copy
        return Path(__file__).resolve().parent.parent / "hyperparams" / f"{name}.yml"


def default_hyperparams_path() -> Path:
    """The ``ppo.yml`` shipped with the package."""
    return packaged_hyperparams_path("ppo")


PACKAGED_HYPERPARAMS = ("ppo", "paper", "mlp", "ppo_lstm", "mlp_zoo", "ppo_lstm_zoo")


# ----------------------------------------------------------------------------------------------------------------
# YAML with rl-zoo friendly floats

class _Loader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that also reads ``1e5`` / ``3e-4`` as floats (YAML 1.1 needs a dot: ``3.0e-4``)."""


_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:float"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                   |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                   |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                   |[-+]?\.(?:inf|Inf|INF)
                   |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def yaml_load(text: str) -> Any:
    """Parse YAML text safely (no Python objects); ``1e-3`` is a float."""
    return yaml.load(text, Loader=_Loader)


def load_hyperparams_file(path: Union[str, Path, None] = None) -> dict[str, dict]:
    """Read a hyperparameter file: a mapping of environment ids (and ``default``) to entries.

    :param path: the YAML file, or the name of a packaged one (:data:`PACKAGED_HYPERPARAMS`); ``None``:
        :func:`default_hyperparams_path`.
    """
    if path is None:
        path = default_hyperparams_path()
    elif str(path) in PACKAGED_HYPERPARAMS and not Path(path).exists():
        path = packaged_hyperparams_path(str(path))
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"cannot read hyperparameter file {str(path)!r}: {exc.strerror or exc} (packaged files: "
                         f"{', '.join(PACKAGED_HYPERPARAMS)})") from None
    try:
        data = yaml_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"hyperparameter file {str(path)!r} is not valid YAML: {' '.join(str(exc).split())}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise ValueError(f"hyperparameter file {str(path)!r} must map environment ids to mappings of hyperparameters")
    return data


# ----------------------------------------------------------------------------------------------------------------
# Safe parsing of rl-zoo's "dict(...)" strings

_DOTTED_PREFIXES = {"nn": "torch.nn", "th.nn": "torch.nn", "torch.nn": "torch.nn", "optim": "torch.optim",
                    "th.optim": "torch.optim", "torch.optim": "torch.optim"}


def _dotted_name(node: ast.AST) -> Optional[str]:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    parts.append(node.id)
    return ".".join(reversed(parts))


def parse_python_literal(text: str, what: str = "value") -> Any:
    """Parse rl-zoo's Python-syntax values (``"dict(rule='dp-oja', hidden_sizes=[64])"``) without evaluating code.

    Accepted: numbers, strings, ``True``/``False``/``None``, lists, tuples, ``{...}`` dicts, ``dict(key=value, ...)``
    calls, and class names under ``nn.`` / ``th.nn.`` / ``torch.nn.`` / ``th.optim.`` / ``torch.optim.`` (returned as
    their dotted name, e.g. ``"nn.ReLU"``, and resolved only when the model is built). Anything else — other calls,
    names, attribute access, operators — is a ``ValueError``.

    :param text: the Python expression.
    :param what: what the value is, for error messages (e.g. ``"policy_kwargs"``).
    """
    accepted = ("only literals (numbers, strings, True/False/None, lists, tuples, dicts), dict(key=value, ...) "
                "and nn./th.optim. class names are accepted")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError:
        raise ValueError(f"{what}={text!r} is not a valid Python expression; {accepted}") from None

    def convert(node: ast.AST) -> Any:
        if isinstance(node, ast.Constant) and (node.value is None or isinstance(node.value, (bool, int, float, str))):
            return node.value
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            value = convert(node.operand)
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                return -value if isinstance(node.op, ast.USub) else value
        elif isinstance(node, (ast.List, ast.Tuple)):
            items = [convert(e) for e in node.elts]
            return items if isinstance(node, ast.List) else tuple(items)
        elif isinstance(node, ast.Dict):
            if all(k is not None for k in node.keys):
                return {convert(k): convert(v) for k, v in zip(node.keys, node.values)}
        elif isinstance(node, ast.Call):
            if isinstance(node.func, ast.Name) and node.func.id == "dict" and not node.args and all(
                    k.arg is not None for k in node.keywords):
                return {k.arg: convert(k.value) for k in node.keywords}
        elif isinstance(node, ast.Attribute):
            name = _dotted_name(node)
            if name is not None and name.rsplit(".", 1)[0] in _DOTTED_PREFIXES:
                return name
        raise ValueError(f"unsafe or unsupported expression {ast.unparse(node)!r} in {what}={text!r}; {accepted}")

    return convert(tree.body)


# ----------------------------------------------------------------------------------------------------------------
# Overrides

_KEY_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


def parse_override(text: str, what: str = "hyperparameter override",
                   example: str = "n_steps=128 or policy_kwargs.rule=dp-bcm") -> tuple[tuple[str, ...], Any]:
    """Parse one ``key=value`` override, or rl-zoo's ``key:value``: the (dotted) key path and the value read as
    YAML. The key ends at the first ``=`` or ``:`` (keys have neither), so values may hold both.

    ``n_steps=128`` and ``n_steps:128`` -> ``(("n_steps",), 128)``; ``policy_kwargs.hidden_sizes=[32, 32]`` ->
    ``(("policy_kwargs", "hidden_sizes"), [32, 32])``.

    :param what: what ``text`` is, for error messages (``"--env-kwargs entry"``...).
    :param example: valid overrides shown by the error message.
    """
    key, sep, raw = re.match(r"([^=:]*)([=:]?)(.*)", text, re.S).groups()
    key = key.strip()
    if not sep or not _KEY_PATTERN.match(key):
        raise ValueError(f"malformed {what} {text!r}; expected key=value or key:value (e.g. {example})")
    try:
        value = yaml_load(raw) if raw.strip() else None
    except yaml.YAMLError:
        raise ValueError(f"cannot parse the value of {what} {text!r} as YAML") from None
    return tuple(key.split(".")), value


def _as_mapping(value: Any, what: str) -> Any:
    """rl-zoo string form of a mapping -> dict; everything else unchanged."""
    if isinstance(value, str):
        return parse_python_literal(value, what)
    return value


def _set_path(entry: dict, path: Sequence[str], value: Any) -> None:
    node = entry
    for depth, key in enumerate(path[:-1]):
        child = _as_mapping(node.get(key), ".".join(path[:depth + 1]))
        if child is None or child is True:  # normalize: true -> {} before setting one of its arguments
            child = {}
        if not isinstance(child, dict):
            where = ".".join(path[:depth + 1])
            raise ValueError(f"cannot set {'.'.join(path)}: {where} is {child!r}, not a mapping"
                             + (" (set normalize=true first)" if where == "normalize" else ""))
        node[key] = child
        node = child
    node[path[-1]] = value


def deep_merge(base: Mapping, top: Mapping) -> dict:
    """``top`` over ``base``: nested mappings merge key by key, everything else is replaced."""
    out = copy.deepcopy(dict(base))
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


# ----------------------------------------------------------------------------------------------------------------
# Types

def _describe(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return "anything"
    if hint is type(None):
        return "null"
    if hint is bool:
        return "true or false"
    if hint is int:
        return "an integer"
    if hint is float:
        return "a number"
    if hint is str:
        return "a string"
    if hint in (dict, collections.abc.Mapping) or origin in (dict, collections.abc.Mapping):
        return "a mapping"
    if hint is tuple or hint is list:
        return "a list"
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a) for a in args)
    if origin in (list, tuple, collections.abc.Sequence):
        return f"a list of {_describe(args[0]).removeprefix('an ').removeprefix('a ')}s" if args else "a list"
    if origin is typing.Literal:
        return "one of " + ", ".join(map(repr, args))
    return getattr(hint, "__name__", str(hint))


class _Mismatch(Exception):
    pass


def _coerce(value: Any, hint: Any) -> Any:
    """``value`` converted to ``hint`` (integral floats -> int, ints -> float, tuples -> lists), or ``_Mismatch``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any or hint is inspect.Parameter.empty:
        return value
    if hint is type(None):
        if value is None:
            return None
        raise _Mismatch
    if origin in (Union, types.UnionType):
        for arg in sorted(args, key=lambda a: a is str):  # try str last: "1e3" strings stay numbers elsewhere
            try:
                return _coerce(value, arg)
            except _Mismatch:
                pass
        raise _Mismatch
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise _Mismatch
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and math.isfinite(value) and value == int(value):
            return int(value)
        raise _Mismatch
    if hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise _Mismatch
    if hint is str:
        if isinstance(value, str):
            return value
        raise _Mismatch
    if hint in (dict, collections.abc.Mapping) or origin in (dict, collections.abc.Mapping):
        if isinstance(value, dict):
            return value
        raise _Mismatch
    if hint in (tuple, list) or origin in (list, tuple, collections.abc.Sequence):
        if not isinstance(value, (list, tuple)):
            raise _Mismatch
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise _Mismatch
            return [_coerce(v, a) for v, a in zip(value, args)]
        item = args[0] if args else Any
        return [_coerce(v, item) for v in value]
    if origin is typing.Literal:
        if value in args:
            return value
        raise _Mismatch
    return value  # classes, callables...: left to the constructor


def _check_value(name: str, value: Any, hint: Any) -> Any:
    try:
        return _coerce(value, hint)
    except _Mismatch:
        raise ValueError(f"{name}={value!r} must be {_describe(hint)}") from None


def _check_keys(what: str, values: Mapping, accepted: Sequence[str], context: str = "") -> None:
    unknown = [k for k in values if k not in accepted]
    if unknown:
        close = difflib.get_close_matches(str(unknown[0]), sorted(accepted), n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown {what} {unknown[0]!r}{context}{hint}; accepted: "
                         f"{', '.join(sorted(accepted)) or 'none'}")


def _signature_hints(fn) -> dict[str, Any]:
    params = inspect.signature(fn).parameters
    try:
        hints = typing.get_type_hints(fn)
    except Exception:  # unresolvable annotations: no type checks, keys still checked
        hints = {}
    return {name: hints.get(name, Any) for name, p in params.items()
            if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}


def algorithm_class(algo: str = "ppo") -> type:
    """The class trained for an entry's ``algo`` (:data:`ALGOS`)."""
    if algo == "ppo":
        from ..sb3.ppo import PPO

        return PPO
    if algo == "ppo_lstm":
        try:
            from sb3_contrib import RecurrentPPO
        except ImportError:
            raise ValueError("algo='ppo_lstm' needs sb3-contrib: pip install 'sb3-spikeplastic[baselines]'") from None
        return RecurrentPPO
    raise ValueError(f"unknown algo {algo!r}; accepted: {', '.join(ALGOS)}")


def ppo_argument_hints(algo: str = "ppo") -> dict[str, Any]:
    """The algorithm's arguments a hyperparameter entry may set, with their type hints."""
    return {k: v for k, v in _signature_hints(algorithm_class(algo).__init__).items() if k not in _PPO_EXCLUDED}


def accepted_keys() -> tuple[str, ...]:
    """Every top-level key of a hyperparameter entry: :data:`META_KEYS` and the PPO arguments."""
    return (*META_KEYS, *ppo_argument_hints())


def policy_names(algo: str = "ppo") -> tuple[str, ...]:
    """Policy names accepted by ``policy`` (``SpikePlasticPolicy`` and SB3's on-policy ones; for ``ppo_lstm``
    sb3-contrib's LSTM policies)."""
    return tuple(algorithm_class(algo).policy_aliases)


def _policy_class(policy: str, algo: str = "ppo") -> type:
    return algorithm_class(algo).policy_aliases[policy]


def policy_kwarg_hints(policy: str = "SpikePlasticPolicy", algo: str = "ppo") -> dict[str, Any]:
    """The ``policy_kwargs`` a policy accepts from a hyperparameter file, with their type hints."""
    from stable_baselines3.common.policies import ActorCriticPolicy

    base = {k: v for k, v in _signature_hints(ActorCriticPolicy.__init__).items() if k not in _UNSETTABLE_POLICY_KEYS}
    policy_class = _policy_class(policy, algo)
    if policy_class is ActorCriticPolicy or not issubclass(policy_class, ActorCriticPolicy):
        return base
    own = {k: v for k, v in _signature_hints(policy_class.__init__).items() if k not in _UNSETTABLE_POLICY_KEYS}
    if getattr(policy_class, "recurrent", False):  # SpikePlasticPolicy: its own arguments and the optimizer
        return {**own, **{k: base[k] for k in _SPIKE_EXTRA_POLICY_KEYS}}
    return {**base, **own}


def resolve_class_name(name: str, key: str) -> type:
    """A class named in ``activation_fn`` / ``optimizer_class`` (``ReLU``, ``nn.ReLU``, ``th.optim.AdamW``) or
    ``features_extractor_class`` (:mod:`sb3_spikeplastic.sb3.encoder_features`: ``PlaceCellFeatures``...)."""
    import torch

    module_name = _CLASS_KEYS[key]
    if module_name == "sb3_spikeplastic.sb3.encoder_features":
        from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

        from ..sb3 import encoder_features as module

        base = BaseFeaturesExtractor
    else:
        module = torch.nn if module_name == "torch.nn" else torch.optim
        base = torch.nn.Module if module_name == "torch.nn" else torch.optim.Optimizer
    prefix, _, short = name.rpartition(".")
    candidate = getattr(module, short, None) if (not prefix or _DOTTED_PREFIXES.get(prefix) == module_name) else None
    if not (isinstance(candidate, type) and issubclass(candidate, base)):
        choices = sorted(n for n, c in vars(module).items() if isinstance(c, type) and issubclass(c, base) and c is not base)
        raise ValueError(f"policy_kwargs.{key}={name!r} is not a class of {module_name}; accepted: {', '.join(choices)}")
    return candidate


def _check_rule_values(rule: str, rule_kwargs: dict) -> None:
    """The rule's own checks of ``rule_kwargs`` (rates in (0, 1)...), run on a 1 x 1 layer so that a bad value is
    named by its key (``policy_kwargs.rule_kwargs.eta_init=2.0 must lie in (0, 1)``) before any model is built.
    The global torch random state is left as it was."""
    import torch

    from ..snn.plasticity import get_rule_class

    try:
        with torch.random.fork_rng(devices=[]):
            get_rule_class(rule)(1, 1, **rule_kwargs)
    except TypeError:  # a registered rule with other required arguments: left to the model's construction
        return
    except ValueError as exc:
        message = str(exc)
        if message.partition("=")[0] in rule_kwargs:  # the rule named the argument
            raise ValueError(f"policy_kwargs.rule_kwargs.{message}") from None
        raise ValueError(f"policy_kwargs.rule_kwargs={rule_kwargs!r} for rule {rule!r}: {message}") from None


def _validate_policy_kwargs(policy: str, kwargs: Any, algo: str = "ppo") -> dict:
    from ..snn.plasticity import get_rule_class

    kwargs = _as_mapping(kwargs, "policy_kwargs")
    if kwargs is None:
        return {}
    if not isinstance(kwargs, dict):
        raise ValueError(f"policy_kwargs={kwargs!r} must be a mapping")
    hints = policy_kwarg_hints(policy, algo)
    _check_keys("policy_kwargs key", kwargs, list(hints))
    out = {}
    for key, value in kwargs.items():
        if key in _CLASS_KEYS:
            if not isinstance(value, str):
                example = {"activation_fn": "nn.ReLU", "optimizer_class": "th.optim.AdamW"}.get(key, "PlaceCellFeatures")
                raise ValueError(f"policy_kwargs.{key}={value!r} must be a class name such as {example}")
            resolve_class_name(value, key)
            out[key] = value
            continue
        out[key] = _check_value(f"policy_kwargs.{key}", _as_mapping(value, f"policy_kwargs.{key}")
                                if key in ("neuron", "rule_kwargs", "optimizer_kwargs", "net_arch") else value,
                                hints[key])
    if "rule" in out:
        get_rule_class(out["rule"])  # a one-line error for an unknown name
    if "rule" in hints:
        default_rule = inspect.signature(_policy_class(policy, algo).__init__).parameters["rule"].default
        out_rule = out.get("rule", default_rule)
        if out.get("rule_kwargs"):
            rule_hints = {k: v for k, v in _signature_hints(get_rule_class(out_rule).__init__).items()
                          if k not in ("self", "n_in", "n_out", "e_max")}
            _check_keys("policy_kwargs.rule_kwargs key", out["rule_kwargs"], list(rule_hints),
                        f" for rule {out_rule!r}")
            out["rule_kwargs"] = {k: _check_value(f"policy_kwargs.rule_kwargs.{k}", v, rule_hints[k])
                                  for k, v in out["rule_kwargs"].items()}
            _check_rule_values(out_rule, out["rule_kwargs"])
    if out.get("neuron"):
        from ..snn.neurons import SRMParameters

        _check_keys("policy_kwargs.neuron key", out["neuron"], list(SRMParameters._fields))
        out["neuron"] = {k: _check_value(f"policy_kwargs.neuron.{k}", v, float) for k, v in out["neuron"].items()}
    return out


def _validate_normalize(value: Any) -> Union[bool, dict]:
    from stable_baselines3.common.vec_env import VecNormalize

    value = _as_mapping(value, "normalize")
    if value is None:
        return False
    if isinstance(value, bool):
        return value
    if not isinstance(value, dict):
        raise ValueError(f"normalize={value!r} must be true, false or a mapping of VecNormalize arguments")
    hints = {k: v for k, v in _signature_hints(VecNormalize.__init__).items() if k not in ("self", "venv", "training")}
    _check_keys("normalize (VecNormalize) key", value, list(hints))
    return {k: _check_value(f"normalize.{k}", v, hints[k]) for k, v in value.items()}


_LIN = re.compile(r"^lin_(.+)$")


def _validate_schedule(key: str, value: Any, allow_none: bool) -> Any:
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
    raise ValueError(f"{key}={value!r} must be a number or lin_<number> (linear decay)"
                     + (" or null" if allow_none else ""))


def validate_entry(entry: Mapping[str, Any]) -> dict:
    """Check every key and value of a (merged, overridden) entry; return it normalised (numbers as numbers,
    mappings parsed, ``normalize`` as a bool or a mapping).

    :raises ValueError: one line naming the bad key or value and what is accepted.
    """
    algo = entry.get("algo", "ppo")
    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}; accepted: {', '.join(ALGOS)}")
    ppo_hints = ppo_argument_hints(algo)
    _check_keys("hyperparameter", entry, (*META_KEYS, *ppo_hints), "" if algo == "ppo" else f" for algo {algo!r}")
    out: dict[str, Any] = {}
    policy = entry.get("policy", "SpikePlasticPolicy" if algo == "ppo" else "MlpLstmPolicy")
    if policy not in policy_names(algo):
        raise ValueError(f"unknown policy {policy!r}; accepted: {', '.join(policy_names(algo))}")
    out["policy"] = policy
    if algo != "ppo":
        out["algo"] = algo
    for key, value in entry.items():
        if key in ("policy", "algo"):
            continue
        if key == "n_timesteps":
            out[key] = _check_value(key, value, int)
            if out[key] < 1:
                raise ValueError(f"n_timesteps={value!r} must be >= 1")
        elif key == "n_envs":
            out[key] = _check_value(key, value, int)
            if out[key] < 1:
                raise ValueError(f"n_envs={value!r} must be >= 1")
        elif key == "policy_kwargs":
            out[key] = _validate_policy_kwargs(policy, value, algo)
        elif key == "normalize":
            out[key] = _validate_normalize(value)
        elif key == "env_kwargs":
            kwargs = _as_mapping(value, "env_kwargs")
            out[key] = _check_value(key, {} if kwargs is None else kwargs, dict)
        elif key in SCHEDULE_KEYS:
            out[key] = _validate_schedule(key, value, allow_none=key == "clip_range_vf")
        elif key == "grad_clip":
            from ..sb3.ppo import GRAD_CLIP_MODES

            if value not in GRAD_CLIP_MODES:
                raise ValueError(f"grad_clip={value!r} is not accepted; accepted: {', '.join(GRAD_CLIP_MODES)}")
            out[key] = value
        else:
            out[key] = _check_value(key, value, ppo_hints[key])
            if key in ("n_steps", "batch_size", "n_epochs", "bptt_steps") and out[key] is not None and out[key] < 1:
                raise ValueError(f"{key}={value!r} must be >= 1")
    return dict(sorted(out.items()))


def _get_path(entry: Mapping, path: Sequence[str]) -> Any:
    node: Any = entry
    for depth, key in enumerate(path):
        if isinstance(node, str):
            node = _as_mapping(node, ".".join(path[:depth]))
        if not isinstance(node, Mapping):
            return None
        node = node.get(key)
    return _as_mapping(node, ".".join(path)) if isinstance(node, str) and path[-1] in _MAPPING_KEYS else node


#: Entry keys (and policy_kwargs keys) whose values are mappings, also in rl-zoo's string form.
_MAPPING_KEYS = ("policy_kwargs", "normalize", "env_kwargs", "rule_kwargs", "neuron", "optimizer_kwargs")


def _overridden_entry(env_id: str, conf: Union[str, Path, None], parsed: Sequence[tuple[tuple[str, ...], Any]],
                      rule: Optional[str], replaced: Optional[list] = None) -> dict:
    """The file's ``default`` and ``env_id`` entries merged, with the parsed overrides and ``rule`` applied (not
    validated). ``replaced`` collects ``(index, path, keys)`` for each override that replaces a whole mapping."""
    data = load_hyperparams_file(conf)
    where = str(default_hyperparams_path() if conf is None else conf)
    if env_id not in data and "default" not in data:
        raise ValueError(f"no hyperparameters for {env_id!r} in {where} and no 'default' entry; "
                         f"entries: {', '.join(data) or 'none'}")
    base = data.get("default", {})
    entry = deep_merge(base, data.get(env_id, {}))
    for key in ("policy_kwargs", "normalize", "env_kwargs"):  # string forms, before dotted overrides reach in
        if isinstance(entry.get(key), str):
            entry[key] = _as_mapping(entry[key], key)
    for index, (path, value) in enumerate(parsed):
        if replaced is not None:
            old = _get_path(entry, path)
            if isinstance(old, Mapping) and old:
                replaced.append((index, path, list(old)))
        _set_path(entry, path, value)
    if rule is not None:
        _set_path(entry, ("policy_kwargs", "rule"), rule)
    return entry


def print_replaced_mappings(env_id: str, conf: Union[str, Path, None] = None, overrides: Sequence[str] = (),
                            rule: Optional[str] = None) -> None:
    """Print :func:`replaced_mappings`'s lines, one ``sb3-spikeplastic: ...`` notice each (``train``, ``optimize``)."""
    for line in replaced_mappings(env_id, conf, overrides, rule):
        print(f"sb3-spikeplastic: {line}")


def replaced_mappings(env_id: str, conf: Union[str, Path, None] = None, overrides: Sequence[str] = (),
                      rule: Optional[str] = None, option: str = "--hyperparams") -> list[str]:
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
            lines.append(f"{option} {overrides[index]} replaces the entry's whole {name}, dropping its "
                         f"{', '.join(map(str, dropped))} (their defaults apply; {name}.KEY=VALUE sets one key and "
                         "keeps the others)")
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

def linear_schedule(initial: float):
    """rl-zoo's ``lin_<value>``: decays linearly from ``initial`` to 0 over training."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def _schedule(value: Any) -> Any:
    if isinstance(value, str):
        return linear_schedule(float(_LIN.match(value).group(1)))
    return value


def model_arguments(config: Mapping[str, Any]) -> tuple[str, dict, dict]:
    """``(policy, ppo_kwargs, policy_kwargs)`` for ``PPO(policy, env, **ppo_kwargs, policy_kwargs=policy_kwargs)``
    from a resolved entry (meta keys removed, ``lin_`` schedules and class names resolved)."""
    ppo_kwargs = {k: (_schedule(v) if k in SCHEDULE_KEYS else v) for k, v in config.items() if k not in META_KEYS}
    policy_kwargs = dict(config.get("policy_kwargs") or {})
    for key in _CLASS_KEYS:
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
    gamma = config.get("gamma", inspect.signature(algorithm_class(config.get("algo", "ppo")).__init__).parameters[
        "gamma"].default)  # the algorithm's default where the entry does not state it
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
    raise ValueError(f"unknown environment id {env_id!r}; {hint}accepted: an entry of the file ({listed}) or any "
                     f"of gymnasium's {len(gymnasium.registry)} registered ids (python -c 'import gymnasium, "
                     "sb3_spikeplastic; gymnasium.pprint_registry()' lists them)")


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
    return Hyperparams(policy=policy, n_envs=resolved["n_envs"], n_timesteps=resolved["n_timesteps"],
                       normalize=normalize_arguments(resolved), env_kwargs=copy.deepcopy(resolved["env_kwargs"]),
                       model_kwargs={**ppo_kwargs, "policy_kwargs": policy_kwargs},
                       algo=resolved.get("algo", "ppo"))


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
