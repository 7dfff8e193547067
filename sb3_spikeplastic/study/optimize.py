"""``sb3-spikeplastic optimize``: hyperparameter search with Optuna, after rl-baselines3-zoo's ``--optimize``.

Each trial samples hyperparameters from the packaged search space (``hyperparams/search_space.yml``, per
environment: :func:`load_search_space`), resolves them like ``train --hyperparams`` over the entry of ``--conf``
(:func:`sb3_spikeplastic.zoo.config.resolve_hyperparams`) and trains one :class:`~sb3_spikeplastic.zoo.experiment.
Experiment` per seed, in a run folder ``<study folder>/trial_<n>/ppo/<EnvId>_<k>/``. Every ``n_timesteps /
n_evaluations`` steps a deterministic evaluation is reported to the trial (``trial.report``), so the pruner can
stop it early; the trial's value is the mean over its seeds of the last evaluation's mean return. A trial whose
sampled configuration is invalid, or whose training fails, is marked failed with the reason in its user attribute
``error``; the study goes on.

The study's best trial becomes a hyperparameter file ``best.yml`` (``{env_id: entry}``, the entry's full
``n_timesteps``) that ``train --conf`` reads. The study lives in an Optuna storage
(:mod:`sb3_spikeplastic.study.storage`), so several processes, on one machine or several, can share it.
"""

from __future__ import annotations

import inspect
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..zoo import config as cfg
from .storage import (check_model, check_settings, count_states, create_study, describe_storage, open_storage,
                      one_line, quiet_optuna, storage_exists, train_command, worker_name)

SAMPLERS = ("tpe", "random")
PRUNERS = ("median", "none")
#: How a search-space key is sampled (see ``hyperparams/search_space.yml``).
SPACE_FORMS = ("log", "uniform", "int", "choices")
RULE_KEY = "policy_kwargs.rule"
#: Keys that only matter for a rule with a trace.
PLASTIC_PREFIXES = ("policy_kwargs.alpha_", "policy_kwargs.rule_kwargs.")
#: The user attribute of a study that holds the settings of its trials.
SETTINGS_KEY = "optimize"


# ----------------------------------------------------------------------------------------------------------------
# The search space

def load_search_space(env_id: str, path: Optional[Path] = None) -> dict[str, tuple[str, list]]:
    """The search space of ``env_id``: ``{key: (form, values)}`` with ``form`` one of :data:`SPACE_FORMS`.

    :param env_id: its entry is merged over ``default`` (a ``null`` value removes a key)
    :param path: a search-space file (default: the packaged ``search_space.yml``)
    :raises ValueError: one line naming a malformed key
    """
    path = Path(path) if path is not None else cfg.packaged_hyperparams_path("search_space")
    data = cfg.load_hyperparams_file(path)
    space: dict[str, tuple[str, list]] = {}
    for key, spec in {**data.get("default", {}), **data.get(env_id, {})}.items():
        if spec is None:
            continue
        where = f"search space {key!r} in {str(path)!r}"
        if not (isinstance(spec, dict) and len(spec) == 1 and next(iter(spec)) in SPACE_FORMS):
            raise ValueError(f"{where} must be one of {{log: [low, high]}}, {{uniform: [low, high]}}, "
                             f"{{int: [low, high]}}, {{choices: [...]}}; got {spec!r}")
        form, values = next(iter(spec.items()))
        if not isinstance(values, list) or not values:
            raise ValueError(f"{where}: {form} needs a non-empty list, got {values!r}")
        if form != "choices":
            numbers = len(values) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                               for v in values)
            if not numbers or values[0] >= values[1] or (form == "log" and values[0] <= 0) or (
                    form == "int" and not all(float(v).is_integer() for v in values)):
                raise ValueError(f"{where}: {form} needs [low, high] with low < high"
                                 + (" and low > 0" if form == "log" else "")
                                 + (", both integers" if form == "int" else "") + f"; got {values!r}")
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
    top_keys = (*cfg.META_KEYS, *cfg.ppo_argument_hints(algo))
    policy_keys = cfg.policy_kwarg_hints(policy, algo)
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
    parameter = inspect.signature(cfg.algorithm_class(entry.get("algo", "ppo")).__init__).parameters.get(key)
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
    return value if isinstance(value, str) and cfg.yaml_load(value) == value else text


# ----------------------------------------------------------------------------------------------------------------
# Trials

def _trial_report_class():
    from stable_baselines3.common.callbacks import BaseCallback

    class TrialReport(BaseCallback):
        """Run after each evaluation of :class:`~sb3_spikeplastic.zoo.experiment.Experiment` (SB3's
        ``callback_after_eval``): reports the evaluation's mean return to the trial, numbered across the trial's
        seeds, and stops training when the pruner says so.

        :param trial: the Optuna trial
        """

        def __init__(self, trial):
            super().__init__()
            self.trial, self.step, self.pruned = trial, 0, False
            self.last_value: Optional[float] = None
            self.last_success: Optional[float] = None

        def _on_step(self) -> bool:
            self.last_value = float(self.parent.last_mean_reward)
            successes = self.parent.evaluations_successes
            self.last_success = float(sum(successes[-1]) / len(successes[-1])) if successes and successes[-1] \
                else None
            self.trial.report(self.last_value, self.step)
            self.step += 1
            if self.trial.should_prune():
                self.pruned = True
                return False
            return True

    return TrialReport


@dataclass
class OptimizeSettings:
    """What ``sb3-spikeplastic optimize`` searches and how (its command-line options)."""

    env_id: str
    conf: Optional[str] = None
    rule: Optional[str] = None
    hyperparams: Sequence[str] = ()
    n_timesteps: Optional[int] = None
    n_trials: int = 20
    sampler: str = "tpe"
    pruner: str = "median"
    n_startup_trials: int = 5
    n_evaluations: int = 5
    eval_episodes: int = 10
    seeds_per_trial: int = 1
    storage: Optional[str] = None
    study_name: Optional[str] = None
    log_folder: Path = Path("logs")
    seed: Optional[int] = None
    device: str = "cpu"
    torch_threads: int = 1
    search_space: Optional[Path] = None

    @property
    def name(self) -> str:
        """The study name (default: ``<EnvId>_<conf>[_<rule>]``)."""
        if self.study_name:
            return self.study_name
        conf = Path(self.conf).stem if self.conf else "ppo"
        return "_".join([self.env_id, conf, *([self.rule] if self.rule else [])])

    @property
    def folder(self) -> Path:
        """``<log folder>/optimize/<study>``: the default storage, ``best.yml`` and the trials' run folders."""
        return Path(self.log_folder) / "optimize" / self.name

    @property
    def seeds(self) -> list[int]:
        """The training seeds of every trial (the same for all, so that trials differ only in hyperparameters)."""
        return list(range(self.seeds_per_trial))


@dataclass
class Search:
    """A checked search, ready to run (:func:`prepare`)."""

    settings: OptimizeSettings
    #: the resolved entry the trials start from (``--conf``, ``--hyperparams``, ``--rule``, ``-n``)
    entry: dict
    #: the keys each trial samples (:func:`searched_space`)
    space: dict
    fixed_keys: list[str] = field(default_factory=list)

    @property
    def fingerprint(self) -> dict:
        """What makes the trials comparable: an existing study must have been made with the same."""
        s = self.settings
        return dict(env=s.env_id, entry=self.entry, space={k: list(v) for k, v in self.space.items()},
                    n_evaluations=s.n_evaluations, eval_episodes=s.eval_episodes, seeds=s.seeds)

    def resolve(self, overrides: Sequence[str] = (), full_run: bool = False) -> dict:
        """The entry of one configuration (``full_run``: with the file's ``n_timesteps``, not the trials')."""
        s = self.settings
        return cfg.resolve_hyperparams(s.env_id, s.conf, [*s.hyperparams, *overrides], rule=s.rule,
                                       n_timesteps=None if full_run else s.n_timesteps)

    def sampler(self):
        import optuna

        if self.settings.sampler == "random":
            return optuna.samplers.RandomSampler(seed=self.settings.seed)
        return optuna.samplers.TPESampler(n_startup_trials=self.settings.n_startup_trials, seed=self.settings.seed)

    def pruner(self):
        import optuna

        if self.settings.pruner == "none":
            return optuna.pruners.NopPruner()
        return optuna.pruners.MedianPruner(n_startup_trials=self.settings.n_startup_trials,
                                           n_warmup_steps=self.settings.n_evaluations // 3)

    def objective(self, trial) -> float:
        """Train the trial's configuration on every seed; the mean of the last evaluations."""
        import optuna

        from ..zoo.experiment import Experiment

        s = self.settings
        try:
            trial.set_user_attr("worker", worker_name())
            overrides = sample_overrides(trial, self.space, self.entry, self.fixed_keys)
            trial.set_user_attr("overrides", overrides)
            config = self.resolve(overrides)
            report = _trial_report_class()(trial)
            values, successes, run_dirs = [], [], []
            for seed in s.seeds:
                experiment = Experiment(s.env_id, config, seed, s.folder / f"trial_{trial.number}", device=s.device,
                                        verbose=0, eval_freq=max(config["n_timesteps"] // s.n_evaluations, 1),
                                        eval_episodes=s.eval_episodes, progress=False, after_eval=report)
                experiment.setup()
                command = train_command(s.env_id, s.conf, s.rule, [*s.hyperparams, *overrides], seed,
                                        config["n_timesteps"], experiment.eval_freq, s.eval_episodes)
                run_dirs.append(str(experiment.create_run_folder(command, dict(
                    study=s.name, trial=trial.number, hyperparams=[*s.hyperparams, *overrides]))))
                trial.set_user_attr("run_dirs", run_dirs)
                evaluations = report.step
                if not experiment.learn():
                    raise KeyboardInterrupt
                if report.pruned:
                    raise optuna.TrialPruned(f"pruned after evaluation {report.step}")
                if report.step == evaluations:
                    raise RuntimeError(f"no evaluation ran in {config['n_timesteps']} steps")
                values.append(report.last_value)
                successes.append(report.last_success)
            trial.set_user_attr("values", values)
            if all(x is not None for x in successes):
                trial.set_user_attr("success_rate", sum(successes) / len(successes))
            return sum(values) / len(values)
        except (optuna.TrialPruned, KeyboardInterrupt):
            raise
        except Exception as exc:  # an invalid sampled configuration, or a training that failed: this trial only
            trial.set_user_attr("error", one_line(exc))
            raise

    def best_entry(self, study) -> dict:
        """The best trial's configuration as a full-length entry."""
        return self.resolve(study.best_trial.user_attrs.get("overrides", []), full_run=True)


def prepare(settings: OptimizeSettings) -> Search:
    """Check everything ``optimize`` would do, writing nothing: the environment, the file and its entry, the
    overrides, the search space (one sampled configuration is resolved and its model built), the storage and
    an existing study's settings.

    :raises ValueError: one line naming the bad value and the accepted ones
    """
    quiet_optuna()  # first: without Optuna, its one-line install hint
    import optuna

    s = settings
    if s.sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {s.sampler!r}; accepted: {', '.join(SAMPLERS)}")
    if s.pruner not in PRUNERS:
        raise ValueError(f"unknown pruner {s.pruner!r}; accepted: {', '.join(PRUNERS)}")
    for name, value, minimum in (("--n-trials", s.n_trials, 1), ("--n-evaluations", s.n_evaluations, 1),
                                 ("--eval-episodes", s.eval_episodes, 1), ("--seeds-per-trial", s.seeds_per_trial, 1),
                                 ("--n-startup-trials", s.n_startup_trials, 0)):
        if value < minimum:
            raise ValueError(f"{name}={value} must be >= {minimum}")
    cfg.check_env_id(s.env_id, list(cfg.load_hyperparams_file(s.conf)))
    entry = cfg.resolve_hyperparams(s.env_id, s.conf, s.hyperparams, rule=s.rule, n_timesteps=s.n_timesteps)
    if entry["n_timesteps"] < s.n_evaluations:
        raise ValueError(f"n_timesteps={entry['n_timesteps']} is less than --n-evaluations={s.n_evaluations}")
    if s.rule is not None and entry["policy"] != "SpikePlasticPolicy":
        raise ValueError(f"--rule needs policy SpikePlasticPolicy, not {entry['policy']!r}")
    fixed = [".".join(cfg.parse_override(o)[0]) for o in s.hyperparams]
    space = searched_space(load_search_space(s.env_id, s.search_space), entry, fixed, rule_fixed=s.rule is not None)
    search = Search(s, entry, space, fixed)
    overrides = sample_overrides(optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0)).ask(), space,
                                 entry, fixed)
    try:
        check_model(s.env_id, search.resolve(overrides), s.device)
    except ValueError as exc:
        raise ValueError(f"the search space gives an invalid configuration for {s.env_id} ({' '.join(overrides)}): "
                         f"{exc}") from None
    if storage_exists(s.storage, s.folder):
        check_settings(open_storage(s.storage, s.folder), s.name, SETTINGS_KEY, search.fingerprint)
    return search


def trial_line(study, trial) -> str:
    """One line about a finished trial."""
    if trial.state.name == "COMPLETE":
        seeds = trial.user_attrs.get("values", [])
        success = trial.user_attrs.get("success_rate")
        line = f"trial {trial.number}: {trial.value:.4g}" + (
            f" (seeds: {' / '.join(f'{v:.4g}' for v in seeds)})" if len(seeds) > 1 else "") + (
            f", success {success:.3f}" if success is not None else "")
        best = study.best_trial
        return line + f"; best {best.value:.4g} (trial {best.number})"
    if trial.state.name == "PRUNED":
        values = trial.intermediate_values
        last = f", last {values[max(values)]:.4g}" if values else ""
        return f"trial {trial.number}: pruned after {len(values)} evaluation(s){last}"
    return f"trial {trial.number}: failed: {trial.user_attrs.get('error', 'interrupted or killed')}"


def summary(search: Search, study) -> list[str]:
    """The study's trial counts and its best trial, as printed at the end."""
    counts = count_states(study)
    lines = [f"Study {study.study_name!r} ({describe_storage(search.settings.storage, search.settings.folder)}): "
             f"{sum(counts.values())} trials: {counts.get('COMPLETE', 0)} complete, {counts.get('PRUNED', 0)} "
             f"pruned, {counts.get('FAIL', 0)} failed"
             + (f", {counts['RUNNING']} running" if counts.get("RUNNING") else "")]
    if counts.get("COMPLETE"):
        best = study.best_trial
        s = search.settings
        success = best.user_attrs.get("success_rate")
        lines.append(f"Best trial {best.number}: {best.value:.4g} (mean return of the last evaluation, "
                     f"{s.eval_episodes} episodes, over {len(s.seeds)} seed(s))"
                     + (f", success rate {success:.3f}" if success is not None else ""))
        lines += [f"  {o}" for o in best.user_attrs.get("overrides", [])]
    return lines


def write_best(search: Search, study) -> Path:
    """``<study folder>/best.yml``: the best trial as ``{env_id: entry}``, with a header saying where it comes
    from and how to train it."""
    from ..zoo.run_folder import atomic_write

    s = search.settings
    best = study.best_trial
    path = s.folder / "best.yml"
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (f"# Best trial {best.number} of the study {study.study_name!r}: {best.value:.6g}, the mean return of "
              f"the last evaluation ({s.eval_episodes} deterministic episodes) over {len(s.seeds)} seed(s) after "
              f"{search.entry['n_timesteps']:,} steps.\n# Train it: sb3-spikeplastic train --env {s.env_id} "
              f"--conf {path}\n")
    text = header + cfg.dump_yaml({s.env_id: search.best_entry(study)})
    return atomic_write(path, lambda f: f.write(text), binary=False)


def run(search: Search, log: Callable[[str], None] = print) -> int:
    """Run ``n_trials`` trials of the search (added to the study's earlier ones), then print the summary and
    write ``best.yml``. Returns the exit status: 0, 1 when no trial of the study has completed, 130 when
    interrupted (Ctrl-C: the running trial is marked failed, the summary still written).

    :param search: :func:`prepare`
    :param log: where the lines go
    """
    import torch

    from ..snn.cpu_settings import keep_freed_memory

    s = search.settings
    torch.set_num_threads(s.torch_threads)
    keep_freed_memory()
    storage = open_storage(s.storage, s.folder)
    study = create_study(storage, s.name, SETTINGS_KEY, search.fingerprint, search.sampler(), search.pruner())
    log(f"Study {s.name!r} in {describe_storage(s.storage, s.folder)}: {s.n_trials} trial(s) of "
        f"{search.entry['n_timesteps']:,} steps x {len(s.seeds)} seed(s) on {s.env_id}, searching "
        f"{', '.join(search.space) or 'nothing'}")
    status = 0
    try:
        study.optimize(search.objective, n_trials=s.n_trials, catch=(Exception,), gc_after_trial=True,
                       callbacks=[lambda st, trial: log(trial_line(st, trial))])
    except KeyboardInterrupt:
        log("interrupted")
        status = 130
    for line in summary(search, study):
        log(line)
    if not count_states(study).get("COMPLETE"):
        log("no trial has completed: no best entry written")
        return status or 1
    log(f"Best entry: {write_best(search, study)} (sb3-spikeplastic train --env {s.env_id} --conf "
        f"{s.folder / 'best.yml'})")
    return status


def optimize_command(env: str, conf: Optional[str] = None, rule: Optional[str] = None,
                     hyperparams: Optional[Sequence[str]] = None, n_timesteps: Optional[int] = None,
                     n_trials: int = 20, sampler: str = "tpe", pruner: str = "median", n_startup_trials: int = 5,
                     n_evaluations: int = 5, eval_episodes: int = 10, seeds_per_trial: int = 1,
                     storage: Optional[str] = None, study_name: Optional[str] = None, log_folder: str = "logs",
                     seed: Optional[int] = None, search_space: Optional[str] = None, device: str = "cpu",
                     torch_threads: int = 1) -> Callable[[], int]:
    """``sb3-spikeplastic optimize`` with these options (its long names): everything is checked by
    :func:`prepare` (``ValueError``, nothing written); returns the search (:func:`run`)."""
    from ..zoo.inputs import check_device, check_int, check_output_path
    from .storage import check_storage

    check_int("--torch-threads", torch_threads, 1)
    check_device(device)
    check_output_path(log_folder, "-f/--log-folder", directory=True)
    check_storage(storage)
    search = prepare(OptimizeSettings(
        env, conf, rule, hyperparams or (), n_timesteps, n_trials, sampler, pruner, n_startup_trials, n_evaluations,
        eval_episodes, seeds_per_trial, storage, study_name, Path(log_folder), seed, device, torch_threads,
        search_space))
    if hyperparams:
        from ..zoo.config import print_replaced_mappings

        print_replaced_mappings(env, conf, hyperparams, rule)
    return lambda: run(search)
