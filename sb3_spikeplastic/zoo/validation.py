"""What a hyperparameter entry may hold, checked against the constructors it feeds: the algorithm (``algo``:
:data:`ALGOS`), its policy and ``policy_kwargs``, the plasticity rule's ``rule_kwargs``, the neuron parameters and
``VecNormalize``'s arguments. :func:`validate_entry` raises a one-line ``ValueError`` naming the bad key or value and
what is accepted, before anything is built.
"""

from __future__ import annotations

import inspect
from typing import Any, Mapping, Union

from .coercion import check_keys, check_value, signature_hints
from .schedules import SCHEDULE_KEYS, check_schedule
from .zoo_yaml import DOTTED_PREFIXES, as_mapping

#: Keys of an entry that are not PPO arguments (rl-zoo's meta keys that this CLI implements).
META_KEYS = ("algo", "n_timesteps", "n_envs", "policy", "policy_kwargs", "normalize", "env_kwargs")
#: Values of an entry's ``algo`` key (rl-zoo's algorithm names): ``ppo`` is :class:`sb3_spikeplastic.PPO` (spiking
#: and SB3 policies), ``ppo_lstm`` sb3-contrib's ``RecurrentPPO`` (a baseline; ``pip install sb3-contrib``).
ALGOS = ("ppo", "ppo_lstm")
#: PPO arguments that the command line (or the run) sets, not the hyperparameter file.
_PPO_EXCLUDED = (
    "self",
    "policy",
    "env",
    "policy_kwargs",
    "tensorboard_log",
    "verbose",
    "seed",
    "device",
    "_init_setup_model",
    "rollout_buffer_class",
    "rollout_buffer_kwargs",
)
#: Policy arguments naming a class: accepted as a name (``ReLU``, ``nn.ReLU``, ``th.optim.AdamW``,
#: ``PlaceCellFeatures``...).
CLASS_KEYS = {
    "activation_fn": "torch.nn",
    "optimizer_class": "torch.optim",
    "features_extractor_class": "sb3_spikeplastic.sb3.encoder_features",
}
#: Policy arguments of SB3's ActorCriticPolicy that SpikePlasticPolicy passes on and that make sense for it.
_SPIKE_EXTRA_POLICY_KEYS = ("optimizer_class", "optimizer_kwargs")
_UNSETTABLE_POLICY_KEYS = ("self", "observation_space", "action_space", "lr_schedule", "kwargs")


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
    return {k: v for k, v in signature_hints(algorithm_class(algo).__init__).items() if k not in _PPO_EXCLUDED}


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

    base = {k: v for k, v in signature_hints(ActorCriticPolicy.__init__).items() if k not in _UNSETTABLE_POLICY_KEYS}
    policy_class = _policy_class(policy, algo)
    if policy_class is ActorCriticPolicy or not issubclass(policy_class, ActorCriticPolicy):
        return base
    own = {k: v for k, v in signature_hints(policy_class.__init__).items() if k not in _UNSETTABLE_POLICY_KEYS}
    if getattr(policy_class, "recurrent", False):  # SpikePlasticPolicy: its own arguments and the optimizer
        return {**own, **{k: base[k] for k in _SPIKE_EXTRA_POLICY_KEYS}}
    return {**base, **own}


def resolve_class_name(name: str, key: str) -> type:
    """A class named in ``activation_fn`` / ``optimizer_class`` (``ReLU``, ``nn.ReLU``, ``th.optim.AdamW``) or
    ``features_extractor_class`` (:mod:`sb3_spikeplastic.sb3.encoder_features`: ``PlaceCellFeatures``...)."""
    import torch

    module_name = CLASS_KEYS[key]
    if module_name == "sb3_spikeplastic.sb3.encoder_features":
        from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

        from ..sb3 import encoder_features as module

        base = BaseFeaturesExtractor
    else:
        module = torch.nn if module_name == "torch.nn" else torch.optim
        base = torch.nn.Module if module_name == "torch.nn" else torch.optim.Optimizer
    prefix, _, short = name.rpartition(".")
    candidate = getattr(module, short, None) if (not prefix or DOTTED_PREFIXES.get(prefix) == module_name) else None
    if not (isinstance(candidate, type) and issubclass(candidate, base)):
        choices = sorted(
            n for n, c in vars(module).items() if isinstance(c, type) and issubclass(c, base) and c is not base
        )
        raise ValueError(
            f"policy_kwargs.{key}={name!r} is not a class of {module_name}; accepted: {', '.join(choices)}"
        )
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


def _check_modulation_source(name: Any) -> None:
    """A one-line error for a ``modulation_source`` that no source is registered under, before any model is built."""
    from ..sb3.modulation import available_modulation_sources

    if name is not None and name not in available_modulation_sources():
        raise ValueError(
            f"policy_kwargs.rule_kwargs.modulation_source={name!r} unknown; accepted: "
            f"{', '.join(available_modulation_sources())}"
        )


def _validate_policy_kwargs(policy: str, kwargs: Any, algo: str = "ppo") -> dict:
    from ..snn.plasticity import get_rule_class

    kwargs = as_mapping(kwargs, "policy_kwargs")
    if kwargs is None:
        return {}
    if not isinstance(kwargs, dict):
        raise ValueError(f"policy_kwargs={kwargs!r} must be a mapping")
    hints = policy_kwarg_hints(policy, algo)
    check_keys("policy_kwargs key", kwargs, list(hints))
    out = {}
    for key, value in kwargs.items():
        if key in CLASS_KEYS:
            if not isinstance(value, str):
                example = {"activation_fn": "nn.ReLU", "optimizer_class": "th.optim.AdamW"}.get(
                    key, "PlaceCellFeatures"
                )
                raise ValueError(f"policy_kwargs.{key}={value!r} must be a class name such as {example}")
            resolve_class_name(value, key)
            out[key] = value
            continue
        out[key] = check_value(
            f"policy_kwargs.{key}",
            as_mapping(value, f"policy_kwargs.{key}")
            if key in ("neuron", "rule_kwargs", "optimizer_kwargs", "net_arch")
            else value,
            hints[key],
        )
    if "rule" in out:
        get_rule_class(out["rule"])  # a one-line error for an unknown name
    if "rule" in hints:
        default_rule = inspect.signature(_policy_class(policy, algo).__init__).parameters["rule"].default
        out_rule = out.get("rule", default_rule)
        if out.get("rule_kwargs"):
            rule_hints = {
                k: v
                for k, v in signature_hints(get_rule_class(out_rule).__init__).items()
                if k not in ("self", "n_in", "n_out", "e_max")
            }
            check_keys("policy_kwargs.rule_kwargs key", out["rule_kwargs"], list(rule_hints), f" for rule {out_rule!r}")
            out["rule_kwargs"] = {
                k: check_value(f"policy_kwargs.rule_kwargs.{k}", v, rule_hints[k])
                for k, v in out["rule_kwargs"].items()
            }
            _check_rule_values(out_rule, out["rule_kwargs"])
            _check_modulation_source(out["rule_kwargs"].get("modulation_source"))
    if out.get("neuron"):
        from ..snn.neurons import SRMParameters

        check_keys("policy_kwargs.neuron key", out["neuron"], list(SRMParameters._fields))
        out["neuron"] = {k: check_value(f"policy_kwargs.neuron.{k}", v, float) for k, v in out["neuron"].items()}
    return out


def _validate_normalize(value: Any) -> Union[bool, dict]:
    from stable_baselines3.common.vec_env import VecNormalize

    value = as_mapping(value, "normalize")
    if value is None:
        return False
    if isinstance(value, bool):
        return value
    if not isinstance(value, dict):
        raise ValueError(f"normalize={value!r} must be true, false or a mapping of VecNormalize arguments")
    hints = {k: v for k, v in signature_hints(VecNormalize.__init__).items() if k not in ("self", "venv", "training")}
    check_keys("normalize (VecNormalize) key", value, list(hints))
    return {k: check_value(f"normalize.{k}", v, hints[k]) for k, v in value.items()}


def validate_entry(entry: Mapping[str, Any]) -> dict:
    """Check every key and value of a (merged, overridden) entry; return it normalised (numbers as numbers,
    mappings parsed, ``normalize`` as a bool or a mapping).

    :raises ValueError: one line naming the bad key or value and what is accepted.
    """
    algo = entry.get("algo", "ppo")
    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}; accepted: {', '.join(ALGOS)}")
    ppo_hints = ppo_argument_hints(algo)
    check_keys("hyperparameter", entry, (*META_KEYS, *ppo_hints), "" if algo == "ppo" else f" for algo {algo!r}")
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
            out[key] = check_value(key, value, int)
            if out[key] < 1:
                raise ValueError(f"n_timesteps={value!r} must be >= 1")
        elif key == "n_envs":
            out[key] = check_value(key, value, int)
            if out[key] < 1:
                raise ValueError(f"n_envs={value!r} must be >= 1")
        elif key == "policy_kwargs":
            out[key] = _validate_policy_kwargs(policy, value, algo)
        elif key == "normalize":
            out[key] = _validate_normalize(value)
        elif key == "env_kwargs":
            kwargs = as_mapping(value, "env_kwargs")
            out[key] = check_value(key, {} if kwargs is None else kwargs, dict)
        elif key in SCHEDULE_KEYS:
            out[key] = check_schedule(key, value, allow_none=key == "clip_range_vf")
        elif key == "grad_clip":
            from ..sb3.ppo import GRAD_CLIP_MODES

            if value not in GRAD_CLIP_MODES:
                raise ValueError(f"grad_clip={value!r} is not accepted; accepted: {', '.join(GRAD_CLIP_MODES)}")
            out[key] = value
        else:
            out[key] = check_value(key, value, ppo_hints[key])
            if key in ("n_steps", "batch_size", "n_epochs", "bptt_steps") and out[key] is not None and out[key] < 1:
                raise ValueError(f"{key}={value!r} must be >= 1")
    return dict(sorted(out.items()))
