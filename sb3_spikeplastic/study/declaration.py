"""A study file: what is trained (variants x environments x seeds up to budgets), what every model is evaluated
on, and what the report compares. Every key and value is checked before anything runs.

::

    envs: [HalfCheetah-v5]
    seeds: [0, 1, 2]
    budgets: [300000, 1000000]   # one run per (variant, seed); a checkpoint at every budget is a model
    conf: ppo                    # hyperparameter file of every variant unless it names its own
    hyperparams: []              # overrides of every variant
    eval_freq: 50000             # evaluations during training (the training curves); 0: none
    eval_episodes: 5
    variants:
      static: {rule: static, seeds: [0, 1, 2, 3, 4]}   # seeds and budgets of a variant replace the study's
      dp-oja: {rule: dp-oja}
      wide: {rule: dp-oja, hyperparams: [policy_kwargs.hidden_sizes=[128]]}
      mlp: {conf: mlp}                                 # a baseline is a variant like any other
    evaluations:
      final: {episodes: 100}                           # kind "final": the noise-free return (and success)
      robustness: {noises: [friction, action, obs]}    # kind "robustness": the Fig. 4 protocol (Protocol)
      height: {kind: robustness, noises: [obs], sigmas: [0, 0.1], obs_indices: [0]}
    report:
      compare:                                         # differences with intervals, and verdicts
        - {variants: plastic, against: static, pooled: true}
        - {variants: baselines, against: [static, dp-oja]}

Variant groups in ``compare``: ``plastic`` (spiking policies with a trace), ``static`` (spiking, no trace),
``spiking`` (both), ``baselines`` (every other policy), or a list of variant names.
"""

from __future__ import annotations

import difflib
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence

from ..zoo.config import check_env_id, resolve_hyperparams
from ..zoo.evaluation import REWARD_KEY
from ..zoo.zoo_yaml import PACKAGED_HYPERPARAMS, load_hyperparams_file, parse_override, yaml_load
from .protocol import FIG4, NOISES, Protocol

STUDY_KEYS = (
    "description",
    "envs",
    "seeds",
    "budgets",
    "conf",
    "hyperparams",
    "eval_freq",
    "eval_episodes",
    "variants",
    "evaluations",
    "report",
)
VARIANT_KEYS = ("rule", "conf", "hyperparams", "seeds", "budgets", "train_env", "noises")
EVALUATION_KINDS = ("final", "robustness", "sensitivity")
FINAL_KEYS = (
    "kind",
    "episodes",
    "seed",
    "n_envs",
    "model",
    "ablation",
    "against",
    "info_keys",
    "align",
    "bins",
    "recovery",
    "min_reference",
    "variants",
    "seeds",
    "budgets",
)
FILTER_KEYS = ("variants", "seeds", "budgets")
SENSITIVITY_KEYS = ("kind", "shift", "seed", "groups", "model", *FILTER_KEYS)
ROBUSTNESS_KEYS = (
    "kind",
    "noises",
    "sigmas",
    "episodes",
    "seed",
    "n_envs",
    "friction_target",
    "obs_indices",
    "clip_obs",
    "model",
    "ablation",
    "against",
    *FILTER_KEYS,
)
REPORT_KEYS = ("learned_threshold", "resamples", "compare")
COMPARE_KEYS = ("variants", "against", "pooled", "matched_r0")
GROUPS = ("plastic", "static", "spiking", "baselines")
#: Which model of a budget an evaluation uses: the checkpoint at that budget, or the run's best evaluated model.
MODELS = ("budget", "best")
#: Steps after an aligned change of dynamics whose mean reward is the drop (the first ``early`` steps after it)
#: and the recovered level (the episode's last ``late`` steps): ``recovery: [early, late]`` of a final evaluation.
RECOVERY = (100, 200)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


@dataclass(frozen=True)
class Variant:
    """One variant: a rule, a hyperparameter file and overrides, its own seeds and budgets, the environment it is
    trained on when not the study's (e.g. ``NoisyHalfCheetah-v5``, evaluated on ``HalfCheetah-v5``), and the noises
    of the robustness evaluations it is evaluated on when not all (each optional)."""

    rule: Optional[str] = None
    conf: Optional[str] = None
    hyperparams: tuple[str, ...] = ()
    seeds: Optional[tuple[int, ...]] = None
    budgets: Optional[tuple[int, ...]] = None
    train_env: Optional[str] = None
    noises: Optional[tuple[str, ...]] = None


@dataclass(frozen=True)
class Evaluation:
    """What every model of the study is evaluated on: ``final`` (noise-free episodes) or ``robustness`` (the
    protocol), on held-out episode seeds.

    :param kind: ``final`` or ``robustness``
    :param protocol: episodes, seed, environments side by side, and for ``robustness`` the noises and sigmas
    :param model: ``budget`` (the checkpoint at each budget) or ``best`` (``best_model.zip``, last budget only)
    :param variants: only these variants' models (``None``: all), likewise ``seeds`` and ``budgets``
    :param clip_obs: evaluate with the model's frozen ``VecNormalize`` statistics clipping the standardised
        observation at this bound instead of their own (``None``: as trained)
    :param ablation: evaluate the spiking models under this plasticity ablation (:mod:`sb3_spikeplastic.sb3.ablation`:
        ``frozen``, ``reset-every:N``, ``shuffled``; ``None``: as trained); other models as they are
    :param against: with ``ablation``: the plain evaluation the report pairs this one with, episode by episode
        (``None``: the first of the same kind, model and protocol without ablation;
        :mod:`~sb3_spikeplastic.study.ablation_report`)
    :param shift: ``sensitivity``: the shift of one raw observation element (:mod:`~sb3_spikeplastic.study.probes`)
    :param groups: ``sensitivity``: named groups of observation elements the report averages (``None``: each
        element)
    :param info_keys: ``final``: keys of the step info whose value at every step of every episode the raw file
        keeps (the report's mean at each step position)
    :param align: ``final``: a key of the final step's info holding a step index (or ``None``), kept per episode:
        the report lines the steps up on it as well
    :param bins: ``final``: the report's return per ``bins``-step bin around the aligned step, relative to the same
        episode's bins before it, and the recovery after it (:mod:`sb3_spikeplastic.study.adaptation`); ``None``:
        none
    :param recovery: ``final`` with ``bins``: ``(early, late)``, the steps after the aligned one whose mean reward
        is the drop (the first ``early``) and the recovered level (the episode's last ``late``)
    :param min_reference: ``final`` with ``bins``: episodes whose mean step reward before the change is not above it
        are left out of the adaptation measures (a ratio to a near-zero reference means nothing), and counted
    """

    kind: str
    protocol: Protocol
    model: str = "budget"
    variants: Optional[tuple[str, ...]] = None
    seeds: Optional[tuple[int, ...]] = None
    budgets: Optional[tuple[int, ...]] = None
    clip_obs: Optional[float] = None
    ablation: Optional[str] = None
    against: Optional[str] = None
    shift: Optional[float] = None
    groups: Optional[tuple[tuple[str, tuple[int, ...]], ...]] = None
    info_keys: tuple[str, ...] = ()
    align: Optional[str] = None
    bins: Optional[int] = None
    recovery: tuple[int, int] = RECOVERY
    min_reference: float = 0.0

    def applies(self, variant: str, seed: int, budget: int) -> bool:
        return all(
            chosen is None or value in chosen
            for chosen, value in ((self.variants, variant), (self.seeds, seed), (self.budgets, budget))
        )

    def episode_seeds(self) -> tuple[int, int, int]:
        """What sets the seed of every episode: the first environment seed, the episodes and the environments side
        by side (environment ``i`` is seeded ``seed + i``)."""
        return self.protocol.seed, self.protocol.episodes, self.protocol.n_envs

    def files(self, name: str, noises: Optional[Sequence[str]] = None) -> list[str]:
        """The raw files of this evaluation in a model's episode folder (``noises``: the variant's narrowing)."""
        if self.kind in ("final", "sensitivity"):
            return [f"{name}.csv"]
        return [f"{name}_{noise}.csv" for noise in self.protocol.noises if noises is None or noise in noises]


@dataclass(frozen=True)
class Comparison:
    """Rows of the verdict table: each of ``variants`` against each reference (the same budget), and the
    variants pooled when ``pooled``; with ``matched_r0``, against the reference's budget whose R0 is nearest
    instead (:mod:`~sb3_spikeplastic.study.matched`)."""

    variants: tuple[str, ...]
    against: tuple[str, ...]
    pooled: bool = False
    matched_r0: bool = False


@dataclass(frozen=True)
class Study:
    """A checked study file (see the module docstring)."""

    envs: tuple[str, ...]
    seeds: tuple[int, ...]
    budgets: tuple[int, ...]
    variants: dict[str, Variant]
    evaluations: dict[str, Evaluation] = field(default_factory=dict)
    conf: Optional[str] = None
    hyperparams: tuple[str, ...] = ()
    eval_freq: int = 0
    eval_episodes: int = 5
    comparisons: tuple[Comparison, ...] = ()
    learned_threshold: float = FIG4.learned_threshold
    resamples: int = 2000
    description: str = ""

    def seeds_of(self, variant: str) -> tuple[int, ...]:
        return self.variants[variant].seeds or self.seeds

    def budgets_of(self, variant: str) -> tuple[int, ...]:
        return self.variants[variant].budgets or self.budgets

    def conf_of(self, variant: str) -> Optional[str]:
        return self.variants[variant].conf or self.conf

    def overrides(self, variant: str) -> list[str]:
        return [*self.hyperparams, *self.variants[variant].hyperparams]

    def train_env(self, env: str, variant: str) -> str:
        """The environment a variant's models are trained on (evaluated on ``env``)."""
        return self.variants[variant].train_env or env

    def evaluations_of(self, variant: str, seed: int, budget: int) -> list[tuple[str, Evaluation, list[str]]]:
        """``(name, evaluation, raw files)`` of every evaluation of one model."""
        last = budget == self.budgets_of(variant)[-1]
        return [
            (name, e, e.files(name, self.variants[variant].noises))
            for name, e in self.evaluations.items()
            if e.applies(variant, seed, budget)
            and (e.model == "budget" or last)
            and e.files(name, self.variants[variant].noises)
        ]

    def cells(self) -> list[tuple[str, str, int]]:
        """Every ``(env, variant, seed)``: one training run each, seed first."""
        seeds = sorted({s for v in self.variants for s in self.seeds_of(v)})
        return [
            (env, variant, seed)
            for seed in seeds
            for env in self.envs
            for variant in self.variants
            if seed in self.seeds_of(variant)
        ]

    def config(self, env_id: str, variant: str) -> dict:
        """The resolved entry of ``variant`` on ``env_id``, trained to its largest budget (``ValueError`` naming
        both when it is invalid)."""
        v = self.variants[variant]
        train_env = self.train_env(env_id, variant)
        try:
            check_env_id(train_env, list(load_hyperparams_file(self.conf_of(variant))))
            return resolve_hyperparams(
                train_env,
                self.conf_of(variant),
                self.overrides(variant),
                rule=v.rule,
                n_timesteps=max(self.budgets_of(variant)),
            )
        except ValueError as exc:
            raise ValueError(f"variant {variant!r} on {env_id}: {exc}") from None

    def select(self, variants: Optional[Sequence[str]] = None, seeds: Optional[Sequence[int]] = None) -> "Study":
        """The study restricted to some variants and seeds (what one worker may take)."""
        unknown = [v for v in variants or () if v not in self.variants]
        if unknown:
            raise ValueError(f"unknown variant {unknown[0]!r}; accepted: {', '.join(self.variants)}")
        chosen = {name: self.variants[name] for name in (variants or self.variants)}
        if seeds is not None:
            chosen = {
                name: replace(v, seeds=tuple(s for s in self.seeds_of(name) if s in seeds))
                for name, v in chosen.items()
            }
            chosen = {name: v for name, v in chosen.items() if v.seeds}
        return replace(self, variants=chosen)


def budget_label(steps: int) -> str:
    """``300k``, ``1M``, ``2500k``, ``1500``: a budget in a model name (whole millions, else whole thousands,
    else the steps)."""
    if steps % 1_000_000 == 0:
        return f"{steps // 1_000_000}M"
    if steps % 1000 == 0:
        return f"{steps // 1000}k"
    return str(steps)


def model_name(variant: str, budget: int, seed: int) -> str:
    """``<variant>@<budget>_s<seed>``, e.g. ``dp-oja@300k_s0``."""
    return f"{variant}@{budget_label(budget)}_s{seed}"


# ----------------------------------------------------------------------------------------------------------------
# Reading and checking


def _unknown(what: str, key, accepted: Sequence[str], where: str) -> ValueError:
    close = difflib.get_close_matches(str(key), accepted, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ValueError(f"unknown {what} {key!r} in {where}{hint}; accepted: {', '.join(accepted)}")


def _check_keys(what: str, data: dict, accepted: Sequence[str], where: str) -> None:
    for key in data:
        if key not in accepted:
            raise _unknown(what, key, accepted, where)


def _int(value, what: str, minimum: int) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or not float(value).is_integer()
        or value < minimum
    ):
        raise ValueError(f"{what}={value!r} must be an integer >= {minimum}")
    return int(value)


def _positive_int(value) -> bool:
    """Whether ``value`` is an integer >= 1 (a bool is not)."""
    return not isinstance(value, bool) and isinstance(value, int) and value >= 1


def _ints(value, what: str, minimum: int) -> tuple[int, ...]:
    if not isinstance(value, list) or not value:
        raise ValueError(f"{what}={value!r} must be a non-empty list of integers")
    values = tuple(_int(v, what, minimum) for v in value)
    if len(set(values)) != len(values):
        raise ValueError(f"{what}={value!r} must not repeat a value")
    return values


def _overrides(value, what: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{what} must be a list of KEY=VALUE strings, got {value!r}")
    for item in value:
        parse_override(item)
    return tuple(value)


def _conf(value, what: str, base: Path, where: str = "the study file") -> Optional[str]:
    """A conf name or path; a relative path is read from the study file's folder when it is there."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise ValueError(f"{what}={value!r} must be a packaged file name or a path")
    if value not in PACKAGED_HYPERPARAMS and not Path(value).is_absolute() and (base / value).is_file():
        value = str((base / value).resolve())
    try:
        load_hyperparams_file(value)
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from None
    return value


def _variant(name, spec, where: str, base: Path) -> Variant:
    if not isinstance(name, str) or not _NAME.match(name) or "@" in name:
        raise ValueError(f"variant name {name!r} in {where} must be letters, digits and _ . + - (it names folders)")
    if not isinstance(spec, dict):
        raise ValueError(f"variant {name!r} in {where} must be a mapping with {', '.join(VARIANT_KEYS)}")
    _check_keys(f"key of variant {name!r}", spec, VARIANT_KEYS, where)
    rule = spec.get("rule")
    if rule is not None:
        from ..snn.plasticity import available_rules, get_rule_class

        try:
            get_rule_class(rule)
        except ValueError:
            raise _unknown("rule", rule, list(available_rules()), f"variant {name!r} of {where}") from None
    train_env = spec.get("train_env")
    if train_env is not None and not isinstance(train_env, str):
        raise ValueError(f"train_env={train_env!r} of variant {name!r} in {where} must be an environment id")
    noises = spec.get("noises")
    if noises is not None:
        if not isinstance(noises, list) or not noises:
            raise ValueError(f"noises of variant {name!r} in {where} must be a list of {', '.join(NOISES)}")
        for noise in noises:
            if noise not in NOISES:
                raise _unknown(f"noise of variant {name!r}", noise, NOISES, where)
    return Variant(
        rule,
        _conf(spec.get("conf"), f"conf of variant {name!r}", base),
        _overrides(spec.get("hyperparams"), f"hyperparams of variant {name!r}"),
        None if spec.get("seeds") is None else _ints(spec["seeds"], f"seeds of variant {name!r}", 0),
        None
        if spec.get("budgets") is None
        else tuple(sorted(_ints(spec["budgets"], f"budgets of variant {name!r}", 1))),
        train_env,
        None if noises is None else tuple(noises),
    )


def _filters(spec: dict, what: str, variants: dict) -> dict:
    """An evaluation's ``variants``, ``seeds`` and ``budgets`` (``None``: all)."""
    out = {}
    chosen = spec.get("variants")
    if chosen is not None:
        if not isinstance(chosen, list) or not chosen:
            raise ValueError(f"variants of {what} must be a non-empty list of variant names")
        for v in chosen:
            if v not in variants:
                raise _unknown(f"variant of {what}", v, list(variants), "the study file")
        out["variants"] = tuple(chosen)
    for key, minimum in (("seeds", 0), ("budgets", 1)):
        if spec.get(key) is not None:
            out[key] = _ints(spec[key], f"{key} of {what}", minimum)
    return out


def _evaluation(name, spec, where: str, variants: dict) -> Evaluation:
    if not isinstance(name, str) or not _NAME.match(name) or "_" in name:
        raise ValueError(f"evaluation name {name!r} in {where} must be letters, digits and . + - (it names files)")
    spec = dict(spec or {})
    kind = spec.get("kind", name)
    if kind not in EVALUATION_KINDS:
        raise _unknown(f"kind of evaluation {name!r}", kind, EVALUATION_KINDS, where)
    accepted = {"final": FINAL_KEYS, "robustness": ROBUSTNESS_KEYS, "sensitivity": SENSITIVITY_KEYS}[kind]
    _check_keys(f"key of evaluation {name!r}", spec, accepted, where)
    what = f"evaluation {name!r}"
    model = spec.get("model", "budget")
    if model not in MODELS:
        raise _unknown(f"model of {what}", model, MODELS, where)
    protocol = replace(
        FIG4,
        episodes=_int(spec.get("episodes", FIG4.episodes), f"{what} episodes", 1),
        seed=_int(spec.get("seed", FIG4.seed), f"{what} seed", 0),
        n_envs=_int(spec.get("n_envs", FIG4.n_envs if kind == "robustness" else 1), f"{what} n_envs", 1),
    )
    filters = _filters(spec, what, variants)
    ablation = spec.get("ablation")
    if ablation is not None:
        from ..sb3.ablation import Ablation

        try:
            ablation = str(Ablation.parse(ablation))
        except ValueError as exc:
            raise ValueError(f"ablation of {what} in {where}: {exc}") from None
        filters["ablation"] = None if ablation == "none" else ablation
    against = spec.get("against")
    if against is not None:
        if not isinstance(against, str):
            raise ValueError(f"against={against!r} of {what} in {where} must be the name of an evaluation")
        if filters.get("ablation") is None:
            raise ValueError(
                f"against={against!r} of {what} in {where} needs ablation: it names the plain evaluation to pair with"
            )
        filters["against"] = against
    if kind == "final":
        info_keys = spec.get("info_keys", [])
        if (
            not isinstance(info_keys, list)
            or not all(isinstance(k, str) and k for k in info_keys)
            or len(set(info_keys)) != len(info_keys)
        ):
            raise ValueError(f"info_keys={info_keys!r} of {what} in {where} must be a list of distinct step-info keys")
        align = spec.get("align")
        if align is not None and (not isinstance(align, str) or not align):
            raise ValueError(f"align={align!r} of {what} in {where} must be a key of the final step's info")
        if align is not None and not info_keys:
            raise ValueError(f"align={align!r} of {what} in {where} needs info_keys: the step values it aligns")
        bins = spec.get("bins")
        if bins is not None:
            if not _positive_int(bins):
                raise ValueError(f"bins={bins!r} of {what} in {where} must be an integer >= 1 (the steps of a bin)")
            if align is None or REWARD_KEY not in info_keys:
                raise ValueError(
                    f"bins={bins} of {what} in {where} needs align (the step of the change) and {REWARD_KEY!r} in "
                    "info_keys (the step rewards it sums)"
                )
        recovery = spec.get("recovery", list(RECOVERY))
        if not isinstance(recovery, list) or len(recovery) != 2 or not all(map(_positive_int, recovery)):
            raise ValueError(
                f"recovery={recovery!r} of {what} in {where} must be [early, late], integers >= 1: the steps after "
                "the change whose mean reward is the drop, and the episode's last steps whose mean is the recovered "
                "level"
            )
        if "recovery" in spec and bins is None:
            raise ValueError(f"recovery={recovery!r} of {what} in {where} needs bins")
        min_reference = spec.get("min_reference", 0.0)
        if isinstance(min_reference, bool) or not isinstance(min_reference, (int, float)) or not min_reference >= 0:
            raise ValueError(
                f"min_reference={min_reference!r} of {what} in {where} must be a number >= 0: the mean step reward "
                "before the change that an episode's must exceed to be measured"
            )
        if "min_reference" in spec and bins is None:
            raise ValueError(f"min_reference={min_reference!r} of {what} in {where} needs bins")
        return Evaluation(
            kind,
            replace(protocol, noises=(), sigmas=(0.0,)),
            model,
            info_keys=tuple(info_keys),
            align=align,
            bins=bins,
            recovery=tuple(recovery),
            min_reference=float(min_reference),
            **filters,
        )
    if kind == "sensitivity":
        shift = spec.get("shift", 0.1)
        if isinstance(shift, bool) or not isinstance(shift, (int, float)) or not math.isfinite(shift) or shift == 0:
            raise ValueError(f"shift={shift!r} of {what} in {where} must be a non-zero number")
        groups = spec.get("groups")
        if groups is not None:
            if not isinstance(groups, dict) or not groups:
                raise ValueError(f"groups of {what} in {where} must map names to lists of observation indices")
            groups = tuple((str(g), _ints(idx, f"group {g!r} of {what}", 0)) for g, idx in groups.items())
        return Evaluation(
            kind,
            replace(protocol, episodes=1, n_envs=1, noises=(), sigmas=(0.0,)),
            model,
            shift=float(shift),
            groups=groups,
            **filters,
        )
    noises = spec.get("noises", list(FIG4.noises))
    if not isinstance(noises, list) or not noises:
        raise ValueError(f"noises of {what} in {where} must be a list of {', '.join(NOISES)}")
    for noise in noises:
        if noise not in NOISES:
            raise _unknown(f"noise of {what}", noise, NOISES, where)
    sigmas = spec.get("sigmas", list(FIG4.sigmas))
    if (
        not isinstance(sigmas, list)
        or len(sigmas) < 2
        or any(isinstance(s, bool) or not isinstance(s, (int, float)) or not math.isfinite(s) or s < 0 for s in sigmas)
        or sigmas[0] != 0
        or sorted(set(sigmas)) != sigmas
    ):
        raise ValueError(f"sigmas={sigmas!r} of {what} in {where} must be increasing numbers >= 0 starting with 0 (R0)")
    from ..envs.noise import FRICTION_TARGETS

    target = spec.get("friction_target", FIG4.friction_target)
    if target not in FRICTION_TARGETS:
        raise _unknown(f"friction_target of {what}", target, FRICTION_TARGETS, where)
    indices = spec.get("obs_indices")
    indices = None if indices is None else _ints(indices, f"{what} obs_indices", 0)
    clip = spec.get("clip_obs")
    if clip is not None and (
        isinstance(clip, bool) or not isinstance(clip, (int, float)) or not math.isfinite(clip) or clip <= 0
    ):
        raise ValueError(f"clip_obs={clip!r} of {what} in {where} must be a number > 0")
    return Evaluation(
        kind,
        replace(
            protocol,
            noises=tuple(noises),
            sigmas=tuple(float(s) for s in sigmas),
            friction_target=target,
            obs_indices=indices,
        ),
        model,
        clip_obs=None if clip is None else float(clip),
        **filters,
    )


def _check_against(evaluations: dict[str, Evaluation], where: str) -> None:
    """Each ``against``: a plain evaluation of the same kind and model on the same episode seeds (for
    ``robustness``: the same sigmas and every noise of the ablated one), so that their episodes pair one to one."""
    for name, e in evaluations.items():
        if e.against is None:
            continue
        if e.against not in evaluations:
            raise _unknown(f"evaluation in against of evaluation {name!r}", e.against, list(evaluations), where)
        plain, what = evaluations[e.against], f"against={e.against!r} of evaluation {name!r} in {where}"
        if plain.kind != e.kind:
            raise ValueError(f"{what}: a {plain.kind} evaluation, not {e.kind}")
        if plain.ablation is not None:
            raise ValueError(f"{what}: ablated itself ({plain.ablation}); name an evaluation without ablation")
        if plain.model != e.model:
            raise ValueError(f"{what}: model {plain.model!r}, not {e.model!r} (other models)")
        if plain.episode_seeds() != e.episode_seeds():
            raise ValueError(
                f"{what}: different episode seeds (seed, episodes, n_envs: {plain.episode_seeds()} vs "
                f"{e.episode_seeds()})"
            )
        if plain.protocol.sigmas != e.protocol.sigmas:
            raise ValueError(f"{what}: different sigmas ({list(plain.protocol.sigmas)} vs {list(e.protocol.sigmas)})")
        noises = [n for n in e.protocol.noises if n not in plain.protocol.noises]
        if noises:
            raise ValueError(f"{what}: {e.against!r} has no {', '.join(noises)} noise")


def _comparisons(data, variants: dict[str, Variant], where: str) -> tuple[Comparison, ...]:
    if not isinstance(data, list):
        raise ValueError(f"report.compare in {where} must be a list of mappings with {', '.join(COMPARE_KEYS)}")
    out = []
    for item in data:
        if not isinstance(item, dict):
            raise ValueError(f"report.compare in {where} must be a list of mappings with {', '.join(COMPARE_KEYS)}")
        _check_keys("key of report.compare", item, COMPARE_KEYS, where)
        names = {}
        for key in ("variants", "against"):
            value = item.get(key)
            if value is None:
                raise ValueError(f"report.compare in {where} needs {key!r}")
            value = [value] if isinstance(value, str) else value
            for name in value:
                if name not in variants and name not in GROUPS:
                    raise _unknown(f"variant in report.compare.{key}", name, [*variants, *GROUPS], where)
            names[key] = tuple(value)
        for key in ("pooled", "matched_r0"):
            if not isinstance(item.get(key, False), bool):
                raise ValueError(f"report.compare {key}={item[key]!r} in {where} must be true or false")
        out.append(
            Comparison(names["variants"], names["against"], item.get("pooled", False), item.get("matched_r0", False))
        )
    return tuple(out)


def _check_matched(study: Study, where: str) -> None:
    """A ``matched_r0`` comparison needs a robustness evaluation (R0) and references declared at two or more
    budgets (the checkpoints it chooses from)."""
    for comparison in (c for c in study.comparisons if c.matched_r0):
        if not any(e.kind == "robustness" for e in study.evaluations.values()):
            raise ValueError(f"report.compare matched_r0 in {where} needs a robustness evaluation (R0 and AUC)")
        for name in comparison.against:
            if name in study.variants and len(study.budgets_of(name)) < 2:
                raise ValueError(
                    f"report.compare matched_r0 in {where}: reference {name!r} is declared at one budget; "
                    "it needs two or more (the checkpoints whose R0 is matched)"
                )


def study_from_dict(data, where: str = "the study", base: Path = Path(".")) -> Study:
    """A :class:`Study` from the data of a study file, every key and value checked.

    :param data: the parsed YAML
    :param where: the file, for messages
    :param base: the folder relative ``conf`` paths are read from
    :raises ValueError: one line naming the bad key or value and the accepted ones
    """
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a mapping with the keys {', '.join(STUDY_KEYS)}")
    _check_keys("study key", data, STUDY_KEYS, where)
    for key in ("envs", "variants", "budgets"):
        if not data.get(key):
            raise ValueError(f"{where} needs {key!r}")
    envs = data["envs"]
    if not isinstance(envs, list) or not all(isinstance(e, str) for e in envs) or len(set(envs)) != len(envs):
        raise ValueError(f"envs={envs!r} in {where} must be a list of distinct environment ids")
    if not isinstance(data["variants"], dict):
        raise ValueError(f"variants in {where} must map names to mappings with {', '.join(VARIANT_KEYS)}")
    variants = {name: _variant(name, spec, where, base) for name, spec in data["variants"].items()}
    evaluations = data.get("evaluations") or {}
    if not isinstance(evaluations, dict):
        raise ValueError(f"evaluations in {where} must map names to mappings")
    report = data.get("report") or {}
    if not isinstance(report, dict):
        raise ValueError(f"report in {where} must be a mapping with {', '.join(REPORT_KEYS)}")
    _check_keys("report key", report, REPORT_KEYS, where)
    threshold = report.get("learned_threshold", FIG4.learned_threshold)
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not math.isfinite(threshold):
        raise ValueError(f"report.learned_threshold={threshold!r} in {where} must be a number")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise ValueError(f"description in {where} must be text")
    study = Study(
        tuple(envs),
        _ints(data.get("seeds", [0]), "seeds", 0),
        tuple(sorted(_ints(data["budgets"], "budgets", 1))),
        variants,
        {name: _evaluation(name, spec, where, variants) for name, spec in evaluations.items()},
        _conf(data.get("conf"), "conf", base),
        _overrides(data.get("hyperparams"), "hyperparams"),
        _int(data.get("eval_freq", 0), "eval_freq", 0),
        _int(data.get("eval_episodes", 5), "eval_episodes", 1),
        _comparisons(report.get("compare", []), variants, where),
        float(threshold),
        _int(report.get("resamples", 2000), "report.resamples", 1),
        description.strip(),
    )
    _check_against(study.evaluations, where)
    _check_matched(study, where)
    return study


#: The studies installed with the package (``sb3-spikeplastic study NAME``).
def packaged_studies() -> dict[str, Path]:
    """Name -> file of the study files shipped in ``sb3_spikeplastic.study_files``."""
    from importlib.resources import files

    folder = files("sb3_spikeplastic.study_files")
    return {Path(str(f)).stem: Path(str(f)) for f in folder.iterdir() if str(f).endswith(".yml")}


def study_path(name_or_path: os.PathLike | str) -> Path:
    """A study file: a path, or the name of a packaged study (``fig4``, ``reversal``, ``switch_meta``, ...)."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    shipped = packaged_studies()
    if str(name_or_path) in shipped:
        return shipped[str(name_or_path)]
    raise ValueError(
        f"no study file {str(name_or_path)!r}; give a path or a packaged study: {', '.join(sorted(shipped))}"
    )


def load_study_file(name_or_path: os.PathLike | str) -> tuple[Study, Path]:
    """Read and check a study file (:func:`study_from_dict`); returns the study and its path."""
    path = study_path(name_or_path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"cannot read study file {str(path)!r}: {exc.strerror or exc}") from None
    try:
        data = yaml_load(text)
    except Exception as exc:
        raise ValueError(f"study file {str(path)!r} is not valid YAML: {' '.join(str(exc).split())}") from None
    return study_from_dict(data, f"study file {str(path)!r}", path.parent), path
