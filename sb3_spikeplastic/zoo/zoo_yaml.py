"""Reading rl-zoo-style hyperparameter files: YAML that reads ``1e-3`` as a float, the files shipped with the
package, rl-zoo's Python-syntax strings (``"dict(rule='dp-oja', hidden_sizes=[64])"``, ``nn.ReLU``) parsed without
evaluating code, and ``key=value`` overrides. Turns text into plain data; what the data may hold is checked by
:mod:`sb3_spikeplastic.zoo.validation`.
"""

from __future__ import annotations

import ast
import importlib.resources
import re
from pathlib import Path
from typing import Any, Optional, Union

import yaml


def packaged_hyperparams_path(name: str = "ppo") -> Path:
    """The hyperparameter file ``<name>.yml`` shipped with the package (found both in editable installs and in
    wheels): ``ppo`` (the default), ``paper`` (the paper's HalfCheetah network), ``mlp`` and ``ppo_lstm`` (the
    MlpPolicy and RecurrentPPO baselines, trained with the spiking entry's PPO settings), ``mlp_zoo`` and
    ``ppo_lstm_zoo`` (the same baselines with rl-baselines3-zoo's tuned HalfCheetah settings)."""
    try:
        return Path(str(importlib.resources.files("sb3_spikeplastic.hyperparams").joinpath(f"{name}.yml")))
    except ModuleNotFoundError:  # an editable install made before the data package existed: the source tree's copy
        return Path(__file__).resolve().parents[2] / "hyperparams" / f"{name}.yml"


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
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                   |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                   |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                   |[-+]?\.(?:inf|Inf|INF)
                   |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
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
        raise ValueError(
            f"cannot read hyperparameter file {str(path)!r}: {exc.strerror or exc} (packaged files: "
            f"{', '.join(PACKAGED_HYPERPARAMS)})"
        ) from None
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

DOTTED_PREFIXES = {
    "nn": "torch.nn",
    "th.nn": "torch.nn",
    "torch.nn": "torch.nn",
    "optim": "torch.optim",
    "th.optim": "torch.optim",
    "torch.optim": "torch.optim",
}


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
    accepted = (
        "only literals (numbers, strings, True/False/None, lists, tuples, dicts), dict(key=value, ...) "
        "and nn./th.optim. class names are accepted"
    )
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
            if (
                isinstance(node.func, ast.Name)
                and node.func.id == "dict"
                and not node.args
                and all(k.arg is not None for k in node.keywords)
            ):
                return {k.arg: convert(k.value) for k in node.keywords}
        elif isinstance(node, ast.Attribute):
            name = _dotted_name(node)
            if name is not None and name.rsplit(".", 1)[0] in DOTTED_PREFIXES:
                return name
        raise ValueError(f"unsafe or unsupported expression {ast.unparse(node)!r} in {what}={text!r}; {accepted}")

    return convert(tree.body)


def as_mapping(value: Any, what: str) -> Any:
    """rl-zoo string form of a mapping -> dict; everything else unchanged."""
    if isinstance(value, str):
        return parse_python_literal(value, what)
    return value


# ----------------------------------------------------------------------------------------------------------------
# Overrides

_KEY_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


def parse_override(
    text: str, what: str = "hyperparameter override", example: str = "n_steps=128 or policy_kwargs.rule=dp-bcm"
) -> tuple[tuple[str, ...], Any]:
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
