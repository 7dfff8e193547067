"""``sb3-spikeplastic optimize``: hyperparameter search with Optuna, after rl-baselines3-zoo's ``--optimize``.

Each trial samples hyperparameters from the packaged search space (``hyperparams/search_space.yml``, per
environment: :mod:`sb3_spikeplastic.study.search_space`), resolves them like ``train --hyperparams`` over the entry
of ``--conf`` (:func:`sb3_spikeplastic.zoo.config.resolve_hyperparams`) and trains one
:class:`~sb3_spikeplastic.zoo.experiment.Experiment` per seed, in a run folder
``<study folder>/trial_<n>/ppo/<EnvId>_<k>/``. Every ``n_timesteps / n_evaluations`` steps a deterministic evaluation is
reported to the trial (``trial.report``), so the pruner can stop it early; the trial's value is the mean over its
seeds of the last evaluation's mean return. A trial whose sampled configuration is invalid, or whose training fails,
is marked failed with the reason in its user attribute ``error``; the study goes on.

The study's best trial becomes a hyperparameter file ``best.yml`` (``{env_id: entry}``, the entry's full
``n_timesteps``) that ``train --conf`` reads. The study lives in an Optuna storage
(:mod:`sb3_spikeplastic.study.storage`), so several processes, on one machine or several, can share it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

from ..zoo.config import check_env_id, dump_yaml, resolve_hyperparams
from ..zoo.zoo_yaml import load_hyperparams_file, parse_override
from .search_space import load_search_space, sample_overrides, searched_space
from .storage import (
    check_model,
    check_settings,
    count_states,
    create_study,
    describe_storage,
    one_line,
    open_storage,
    quiet_optuna,
    storage_exists,
    train_command,
    worker_name,
)

SAMPLERS = ("tpe", "random")
PRUNERS = ("median", "none")
#: The user attribute of a study that holds the settings of its trials.
SETTINGS_KEY = "optimize"


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
            self.last_success = float(sum(successes[-1]) / len(successes[-1])) if successes and successes[-1] else None
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
        return dict(
            env=s.env_id,
            entry=self.entry,
            space={k: list(v) for k, v in self.space.items()},
            n_evaluations=s.n_evaluations,
            eval_episodes=s.eval_episodes,
            seeds=s.seeds,
        )

    def resolve(self, overrides: Sequence[str] = (), full_run: bool = False) -> dict:
        """The entry of one configuration (``full_run``: with the file's ``n_timesteps``, not the trials')."""
        s = self.settings
        return resolve_hyperparams(
            s.env_id, s.conf, [*s.hyperparams, *overrides], rule=s.rule, n_timesteps=None if full_run else s.n_timesteps
        )

    def sampler(self):
        import optuna

        if self.settings.sampler == "random":
            return optuna.samplers.RandomSampler(seed=self.settings.seed)
        return optuna.samplers.TPESampler(n_startup_trials=self.settings.n_startup_trials, seed=self.settings.seed)

    def pruner(self):
        import optuna

        if self.settings.pruner == "none":
            return optuna.pruners.NopPruner()
        return optuna.pruners.MedianPruner(
            n_startup_trials=self.settings.n_startup_trials, n_warmup_steps=self.settings.n_evaluations // 3
        )

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
                experiment = Experiment(
                    s.env_id,
                    config,
                    seed,
                    s.folder / f"trial_{trial.number}",
                    device=s.device,
                    verbose=0,
                    eval_freq=max(config["n_timesteps"] // s.n_evaluations, 1),
                    eval_episodes=s.eval_episodes,
                    progress=False,
                    after_eval=report,
                )
                experiment.setup()
                command = train_command(
                    s.env_id,
                    s.conf,
                    s.rule,
                    [*s.hyperparams, *overrides],
                    seed,
                    config["n_timesteps"],
                    experiment.eval_freq,
                    s.eval_episodes,
                )
                run_dirs.append(
                    str(
                        experiment.create_run_folder(
                            command, dict(study=s.name, trial=trial.number, hyperparams=[*s.hyperparams, *overrides])
                        )
                    )
                )
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
    for name, value, minimum in (
        ("--n-trials", s.n_trials, 1),
        ("--n-evaluations", s.n_evaluations, 1),
        ("--eval-episodes", s.eval_episodes, 1),
        ("--seeds-per-trial", s.seeds_per_trial, 1),
        ("--n-startup-trials", s.n_startup_trials, 0),
    ):
        if value < minimum:
            raise ValueError(f"{name}={value} must be >= {minimum}")
    check_env_id(s.env_id, list(load_hyperparams_file(s.conf)))
    entry = resolve_hyperparams(s.env_id, s.conf, s.hyperparams, rule=s.rule, n_timesteps=s.n_timesteps)
    if entry["n_timesteps"] < s.n_evaluations:
        raise ValueError(f"n_timesteps={entry['n_timesteps']} is less than --n-evaluations={s.n_evaluations}")
    if s.rule is not None and entry["policy"] != "SpikePlasticPolicy":
        raise ValueError(f"--rule needs policy SpikePlasticPolicy, not {entry['policy']!r}")
    fixed = [".".join(parse_override(o)[0]) for o in s.hyperparams]
    space = searched_space(load_search_space(s.env_id, s.search_space), entry, fixed, rule_fixed=s.rule is not None)
    search = Search(s, entry, space, fixed)
    overrides = sample_overrides(
        optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0)).ask(), space, entry, fixed
    )
    try:
        check_model(s.env_id, search.resolve(overrides), s.device)
    except ValueError as exc:
        raise ValueError(
            f"the search space gives an invalid configuration for {s.env_id} ({' '.join(overrides)}): {exc}"
        ) from None
    if storage_exists(s.storage, s.folder):
        check_settings(open_storage(s.storage, s.folder), s.name, SETTINGS_KEY, search.fingerprint)
    return search


def trial_line(study, trial) -> str:
    """One line about a finished trial."""
    if trial.state.name == "COMPLETE":
        seeds = trial.user_attrs.get("values", [])
        success = trial.user_attrs.get("success_rate")
        line = (
            f"trial {trial.number}: {trial.value:.4g}"
            + (f" (seeds: {' / '.join(f'{v:.4g}' for v in seeds)})" if len(seeds) > 1 else "")
            + (f", success {success:.3f}" if success is not None else "")
        )
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
    lines = [
        f"Study {study.study_name!r} ({describe_storage(search.settings.storage, search.settings.folder)}): "
        f"{sum(counts.values())} trials: {counts.get('COMPLETE', 0)} complete, {counts.get('PRUNED', 0)} "
        f"pruned, {counts.get('FAIL', 0)} failed" + (f", {counts['RUNNING']} running" if counts.get("RUNNING") else "")
    ]
    if counts.get("COMPLETE"):
        best = study.best_trial
        s = search.settings
        success = best.user_attrs.get("success_rate")
        lines.append(
            f"Best trial {best.number}: {best.value:.4g} (mean return of the last evaluation, "
            f"{s.eval_episodes} episodes, over {len(s.seeds)} seed(s))"
            + (f", success rate {success:.3f}" if success is not None else "")
        )
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
    header = (
        f"# Best trial {best.number} of the study {study.study_name!r}: {best.value:.6g}, the mean return of "
        f"the last evaluation ({s.eval_episodes} deterministic episodes) over {len(s.seeds)} seed(s) after "
        f"{search.entry['n_timesteps']:,} steps.\n# Train it: sb3-spikeplastic train --env {s.env_id} "
        f"--conf {path}\n"
    )
    text = header + dump_yaml({s.env_id: search.best_entry(study)})
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
    log(
        f"Study {s.name!r} in {describe_storage(s.storage, s.folder)}: {s.n_trials} trial(s) of "
        f"{search.entry['n_timesteps']:,} steps x {len(s.seeds)} seed(s) on {s.env_id}, searching "
        f"{', '.join(search.space) or 'nothing'}"
    )
    status = 0
    try:
        study.optimize(
            search.objective,
            n_trials=s.n_trials,
            catch=(Exception,),
            gc_after_trial=True,
            callbacks=[lambda st, trial: log(trial_line(st, trial))],
        )
    except KeyboardInterrupt:
        log("interrupted")
        status = 130
    for line in summary(search, study):
        log(line)
    if not count_states(study).get("COMPLETE"):
        log("no trial has completed: no best entry written")
        return status or 1
    log(
        f"Best entry: {write_best(search, study)} (sb3-spikeplastic train --env {s.env_id} --conf "
        f"{s.folder / 'best.yml'})"
    )
    return status


def optimize_command(
    env: str,
    conf: Optional[str] = None,
    rule: Optional[str] = None,
    hyperparams: Optional[Sequence[str]] = None,
    n_timesteps: Optional[int] = None,
    n_trials: int = 20,
    sampler: str = "tpe",
    pruner: str = "median",
    n_startup_trials: int = 5,
    n_evaluations: int = 5,
    eval_episodes: int = 10,
    seeds_per_trial: int = 1,
    storage: Optional[str] = None,
    study_name: Optional[str] = None,
    log_folder: str = "logs",
    seed: Optional[int] = None,
    search_space: Optional[str] = None,
    device: str = "cpu",
    torch_threads: int = 1,
) -> Callable[[], int]:
    """``sb3-spikeplastic optimize`` with these options (its long names): everything is checked by
    :func:`prepare` (``ValueError``, nothing written); returns the search (:func:`run`)."""
    from ..zoo.inputs import check_device, check_int, check_output_path
    from .storage import check_storage

    check_int("--torch-threads", torch_threads, 1)
    check_device(device)
    check_output_path(log_folder, "-f/--log-folder", directory=True)
    check_storage(storage)
    search = prepare(
        OptimizeSettings(
            env,
            conf,
            rule,
            hyperparams or (),
            n_timesteps,
            n_trials,
            sampler,
            pruner,
            n_startup_trials,
            n_evaluations,
            eval_episodes,
            seeds_per_trial,
            storage,
            study_name,
            Path(log_folder),
            seed,
            device,
            torch_threads,
            search_space,
        )
    )
    if hyperparams:
        from ..zoo.config import print_replaced_mappings

        print_replaced_mappings(env, conf, hyperparams, rule)
    return lambda: run(search)
