"""``sb3-spikeplastic grid``: a declared grid of training runs (variants × environments × seeds), run by workers
that share one Optuna study.

A grid file (YAML)::

    envs: [TMazeCue-v0, TMazeCueNoisy-v0]
    seeds: [0, 1, 2]
    n_timesteps: 200000          # default: each entry's own
    conf: ppo                    # hyperparameter file of every variant unless it names its own
    hyperparams: []              # overrides of every cell
    eval_freq: 5000              # evaluations during training (evaluations.npz, best_model.zip); 0: none
    eval_episodes: 100
    final_eval: {episodes: 1000, seed: 1000000, n_envs: 10, best_model: true}
    variants:
      dp-oja: {rule: dp-oja}                      # a mapping: rule, conf and/or hyperparams
      wide: [policy_kwargs.hidden_sizes=[128]]    # or a list of overrides

Each cell (environment, variant, seed) is one point of Optuna's ``GridSampler`` over the parameters ``env``,
``variant`` and ``seed``. A worker asks the study for the next cell, trains it through the same code as ``train``
(:class:`~sb3_spikeplastic.experiment.Experiment`, in ``<grid folder>/runs/<env>_<variant>_<seed>/ppo/<env>_<k>``),
evaluates the final model (``final_eval``: held-out seeds, written to ``final_eval.json`` in the run folder, and
``final_eval_best.json`` for ``best_model.zip``) and records the mean return as the trial's value, with the run
folder and the evaluations as user attributes. Workers on one machine or several (same ``--storage``) share the
cells: the first trials take the grid's points one each, later ones the points not started, and a worker that
finds its cell already done or taken by an earlier trial (it waits until every earlier running trial has chosen
its cell) marks its trial pruned (``duplicate_of``) instead of training it. A killed worker's cell is failed
after the heartbeat grace period and queued again (:mod:`sb3_spikeplastic.studies`); a worker whose cells are all
taken waits until every cell has finished, so that it can take over such a cell. A cell interrupted with Ctrl-C
is queued again too; a cell whose training raised is left failed (``--retry-failed`` queues it again).

The results (:func:`write_summary`): ``grid.csv``, one row per cell, and ``grid.md``, per variant and
environment the final return and success rate per seed with their mean ± standard deviation.
"""

from __future__ import annotations

import csv
import json
import math
import multiprocessing
import os
import re
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

from . import config as cfg
from .studies import (HEARTBEAT_INTERVAL, check_model, check_settings, create_study, describe_storage, open_storage,
                      one_line, quiet_optuna, retry_callback, storage_exists, train_command, worker_name)

GRID_KEYS = ("envs", "seeds", "variants", "conf", "hyperparams", "n_timesteps", "eval_freq", "eval_episodes",
             "final_eval")
VARIANT_KEYS = ("rule", "conf", "hyperparams")
FINAL_EVAL_KEYS = ("episodes", "seed", "n_envs", "best_model")
#: The user attribute of a study that holds its grid.
SETTINGS_KEY = "grid"
#: Seconds a worker without a cell to start waits before it looks at the study again.
POLL_INTERVAL = 5
#: Seconds between checks while an earlier trial has not chosen its cell yet (:meth:`CellRunner.duplicate_of`).
CLAIM_POLL_INTERVAL = 0.1
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


@dataclass
class Variant:
    """One variant of a grid: a rule, a hyperparameter file and overrides (each optional)."""

    rule: Optional[str] = None
    conf: Optional[str] = None
    hyperparams: list[str] = field(default_factory=list)


@dataclass
class FinalEval:
    """The evaluation of each cell's final model that gives the cell's value.

    :param episodes: deterministic episodes (0: none; the value is then the last evaluation during training)
    :param seed: first environment seed (far from the training's, so that no training evaluation saw them)
    :param n_envs: environments side by side
    :param best_model: also evaluate ``best_model.zip`` (written by the evaluations during training)
    """

    episodes: int = 20
    seed: int = 1_000_000
    n_envs: int = 1
    best_model: bool = False


@dataclass
class Grid:
    """A grid of training runs (see the module docstring for the file)."""

    envs: list[str]
    seeds: list[int]
    variants: dict[str, Variant]
    conf: Optional[str] = None
    hyperparams: list[str] = field(default_factory=list)
    n_timesteps: Optional[int] = None
    eval_freq: int = 0
    eval_episodes: int = 20
    final_eval: FinalEval = field(default_factory=FinalEval)

    def cells(self) -> list[tuple[str, str, int]]:
        """Every ``(env, variant, seed)``, seed first (the order of the summary)."""
        return [(env, variant, seed) for seed in self.seeds for env in self.envs for variant in self.variants]

    def search_space(self) -> dict[str, list]:
        """The ``GridSampler`` search space: ``env``, ``variant`` and ``seed``."""
        return {"env": list(self.envs), "variant": list(self.variants), "seed": list(self.seeds)}

    def conf_of(self, variant: str) -> Optional[str]:
        return self.variants[variant].conf or self.conf

    def overrides(self, variant: str) -> list[str]:
        return [*self.hyperparams, *self.variants[variant].hyperparams]

    def config(self, env_id: str, variant: str) -> dict:
        """The resolved entry of ``variant`` on ``env_id`` (``ValueError`` naming both when it is invalid)."""
        v = self.variants[variant]
        try:
            cfg.check_env_id(env_id, list(cfg.load_hyperparams_file(self.conf_of(variant))))
            return cfg.resolve_hyperparams(env_id, self.conf_of(variant), self.overrides(variant), rule=v.rule,
                                           n_timesteps=self.n_timesteps)
        except ValueError as exc:
            raise ValueError(f"variant {variant!r} on {env_id}: {exc}") from None

    def select(self, envs: Optional[Sequence[str]] = None, variants: Optional[Sequence[str]] = None,
               seeds: Optional[Sequence[int]] = None, **changes) -> "Grid":
        """A copy with only the given environments, variants and seeds (in the given order) and other fields
        replaced (``n_timesteps=...``)."""
        unknown = [v for v in variants or () if v not in self.variants]
        if unknown:
            raise ValueError(f"unknown variant {unknown[0]!r}; accepted: {', '.join(self.variants)}")
        return replace(self, envs=list(envs or self.envs), seeds=list(seeds if seeds is not None else self.seeds),
                       variants={v: self.variants[v] for v in (variants or self.variants)}, **changes)


def _check_keys(what: str, data: dict, accepted: Sequence[str], where: str) -> None:
    unknown = [k for k in data if k not in accepted]
    if unknown:
        raise ValueError(f"unknown {what} {unknown[0]!r} in {where}; accepted: {', '.join(accepted)}")


def _overrides(value, what: str) -> list[str]:
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{what} must be a list of KEY=VALUE strings, got {value!r}")
    for item in value:
        cfg.parse_override(item)
    return list(value)


def _int(value, what: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer() or \
            value < minimum:
        raise ValueError(f"{what}={value!r} must be an integer >= {minimum}")
    return int(value)


def _conf(value, what: str, base: Path) -> Optional[str]:
    """A conf name or path; a relative path is read from the grid file's folder when it is there."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise ValueError(f"{what}={value!r} must be a packaged file name or a path")
    if value not in cfg.PACKAGED_HYPERPARAMS and not Path(value).is_absolute() and (base / value).is_file():
        value = str((base / value).resolve())
    cfg.load_hyperparams_file(value)
    return value


def grid_from_dict(data, where: str = "the grid", base: Path = Path(".")) -> Grid:
    """A :class:`Grid` from the data of a grid file, every key and value checked.

    :param data: the parsed YAML
    :param where: the file, for messages
    :param base: the folder relative ``conf`` paths are read from
    :raises ValueError: one line naming the bad key or value and the accepted ones
    """
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a mapping with the keys {', '.join(GRID_KEYS)}")
    _check_keys("grid key", data, GRID_KEYS, where)
    for key in ("envs", "variants"):
        if not data.get(key):
            raise ValueError(f"{where} needs {key!r}")
    envs, seeds = data["envs"], data.get("seeds", [0])
    if not isinstance(envs, list) or not all(isinstance(e, str) for e in envs) or len(set(envs)) != len(envs):
        raise ValueError(f"envs={envs!r} in {where} must be a list of distinct environment ids")
    if not isinstance(seeds, list) or not seeds or len(set(map(str, seeds))) != len(seeds):
        raise ValueError(f"seeds={seeds!r} in {where} must be a non-empty list of distinct integers")
    seeds = [_int(s, "seed", 0) for s in seeds]
    if not isinstance(data["variants"], dict):
        raise ValueError(f"variants in {where} must map names to a list of overrides or a mapping with "
                         f"{', '.join(VARIANT_KEYS)}")
    variants = {}
    for name, spec in data["variants"].items():
        if not isinstance(name, str) or not _NAME.match(name):
            raise ValueError(f"variant name {name!r} in {where} must be letters, digits and _ . + - (it names "
                             "folders)")
        if isinstance(spec, dict):
            _check_keys(f"key of variant {name!r}", spec, VARIANT_KEYS, where)
            rule = spec.get("rule")
            if rule is not None:
                from .plasticity import get_rule_class

                get_rule_class(rule)
            variants[name] = Variant(rule, _conf(spec.get("conf"), f"variant {name!r} conf", base),
                                     _overrides(spec.get("hyperparams"), f"hyperparams of variant {name!r}"))
        else:
            variants[name] = Variant(hyperparams=_overrides(spec, f"variant {name!r}"))
    final = data.get("final_eval") or {}
    if not isinstance(final, dict):
        raise ValueError(f"final_eval in {where} must be a mapping with {', '.join(FINAL_EVAL_KEYS)}")
    _check_keys("final_eval key", final, FINAL_EVAL_KEYS, where)
    if not isinstance(final.get("best_model", False), bool):
        raise ValueError(f"final_eval.best_model={final['best_model']!r} must be true or false")
    final_eval = FinalEval(_int(final.get("episodes", 20), "final_eval.episodes", 0),
                           _int(final.get("seed", 1_000_000), "final_eval.seed", 0),
                           _int(final.get("n_envs", 1), "final_eval.n_envs", 1), final.get("best_model", False))
    grid = Grid(list(envs), seeds, variants, _conf(data.get("conf"), "conf", base),
                _overrides(data.get("hyperparams"), "hyperparams"),
                None if data.get("n_timesteps") is None else _int(data["n_timesteps"], "n_timesteps", 1),
                _int(data.get("eval_freq", 0), "eval_freq", 0), _int(data.get("eval_episodes", 20), "eval_episodes", 1),
                final_eval)
    if not grid.final_eval.episodes and not grid.eval_freq:
        raise ValueError(f"{where} gives the cells no value: set final_eval.episodes or eval_freq")
    if grid.final_eval.best_model and not grid.eval_freq:
        raise ValueError(f"final_eval.best_model in {where} needs eval_freq (best_model.zip comes from the "
                         "evaluations during training)")
    return grid


def load_grid(path: os.PathLike) -> Grid:
    """Read and check a grid file (:func:`grid_from_dict`)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"cannot read grid file {str(path)!r}: {exc.strerror or exc}") from None
    try:
        data = cfg.yaml_load(text)
    except Exception as exc:
        raise ValueError(f"grid file {str(path)!r} is not valid YAML: {' '.join(str(exc).split())}") from None
    return grid_from_dict(data, f"grid file {str(path)!r}", path.parent)


# ----------------------------------------------------------------------------------------------------------------
# Workers

@dataclass
class GridJob:
    """A checked grid and where it runs (:func:`prepare`).

    :param grid: the grid
    :param folder: the grid's folder (default storage, ``runs/``, ``grid.csv``, ``grid.md``)
    :param study_name: the Optuna study
    :param storage: ``--storage`` (``None``: SQLite in ``folder``)
    :param configs: the resolved entry of each ``(env, variant)``
    :param heartbeat_interval: seconds between heartbeats of a running cell
    :param grace_period: seconds without a heartbeat after which a running cell is failed and queued again
    :param device: torch device of the models
    :param torch_threads: ``torch.set_num_threads`` of each worker
    :param command: the command line, for the messages
    """

    grid: Grid
    folder: Path
    study_name: str
    storage: Optional[str]
    configs: dict[tuple[str, str], dict]
    heartbeat_interval: int = HEARTBEAT_INTERVAL
    grace_period: Optional[int] = None
    device: str = "cpu"
    torch_threads: int = 1

    @property
    def fingerprint(self) -> dict:
        """What the study must hold to be this grid: the grid and every resolved entry."""
        grid = self.grid
        return {"cells": grid.search_space(), "eval_freq": grid.eval_freq, "eval_episodes": grid.eval_episodes,
                "final_eval": asdict(grid.final_eval),
                "configs": {f"{env} {variant}": c for (env, variant), c in self.configs.items()}}

    def load_study(self):
        """The grid's study as it stands (``ValueError`` if there is none)."""
        import optuna

        try:
            return optuna.load_study(study_name=self.study_name, storage=open_storage(self.storage, self.folder))
        except KeyError:
            raise ValueError(f"no study {self.study_name!r} in {describe_storage(self.storage, self.folder)}") \
                from None

    def open_study(self):
        """The grid's study (created if new) with a ``GridSampler`` over its cells."""
        import optuna

        storage = open_storage(self.storage, self.folder, self.heartbeat_interval, self.grace_period, retry=True)
        sampler = optuna.samplers.GridSampler(self.grid.search_space(), seed=0)
        return create_study(storage, self.study_name, SETTINGS_KEY, self.fingerprint, sampler,
                            optuna.pruners.NopPruner())


def prepare(grid: Grid, folder: Path, study_name: str, storage: Optional[str] = None, summary_only: bool = False,
            **options) -> GridJob:
    """Check a grid before anything is written: every ``(env, variant)`` entry resolves (and, unless
    ``summary_only``, its model is built once), and an existing study of that name holds the same grid
    (``summary_only``: it must exist).

    :param grid: the grid
    :param folder: the grid's folder
    :param study_name: the study
    :param storage: ``--storage``
    :param summary_only: the summary of an existing study is all that will be done
    :param options: the other fields of :class:`GridJob`
    :raises ValueError: one line
    """
    quiet_optuna()
    configs = {(env, variant): grid.config(env, variant) for env in grid.envs for variant in grid.variants}
    job = GridJob(grid, Path(folder), study_name, storage, configs, **options)
    if not summary_only:  # built once, as `train` does
        for (env, variant), config in configs.items():
            try:
                check_model(env, config, job.device)
            except ValueError as exc:
                raise ValueError(f"variant {variant!r} on {env}: {exc}") from None
    if storage_exists(storage, job.folder):
        check_settings(open_storage(storage, job.folder), study_name, SETTINGS_KEY, job.fingerprint)
    elif summary_only:
        raise ValueError(f"no study {study_name!r} in {describe_storage(storage, job.folder)}")
    return job


class CellRunner:
    """The objective of a grid worker: one cell per trial.

    :param job: the grid and where it runs
    :param log: where the progress lines go
    """

    def __init__(self, job: GridJob, log: Callable[[str], None] = print):
        self.job, self.log = job, log
        self.current: Optional[int] = None  # the number of the trial being run

    def duplicate_of(self, study, trial) -> Optional[int]:
        """The trial that owns ``trial``'s cell, if another one does: done, queued, or running with a lower number.

        Trial numbers order the claims on a cell, so a running trial with a lower number must have chosen its cell
        before this one can decide: two workers that start the same cell at once would otherwise each check before
        the other had chosen, and both train it. So this waits (polling the storage) while a lower-numbered running
        trial has no cell yet; a worker killed before choosing is failed after the heartbeat grace period.
        """
        import optuna

        n_params = len(trial.params)
        while True:
            undecided = False
            for other in study.get_trials(deepcopy=False):
                if other.number == trial.number:
                    continue
                state, earlier = other.state.name, other.number < trial.number
                running_earlier = state == "RUNNING" and earlier
                if other.params == trial.params and (state in ("COMPLETE", "WAITING") or running_earlier):
                    return other.number
                undecided |= running_earlier and len(other.params) < n_params
            if not undecided:
                return None
            time.sleep(CLAIM_POLL_INTERVAL)
            optuna.storages.fail_stale_trials(study)

    def __call__(self, trial) -> float:
        import optuna

        from .experiment import Experiment

        grid, job = self.job.grid, self.job
        env = trial.suggest_categorical("env", grid.envs)
        variant = trial.suggest_categorical("variant", list(grid.variants))
        seed = trial.suggest_categorical("seed", grid.seeds)
        self.current = trial.number
        trial.set_user_attr("worker", worker_name())
        owner = self.duplicate_of(trial.study, trial)
        if owner is not None:
            trial.set_user_attr("duplicate_of", owner)
            raise optuna.TrialPruned(f"cell taken by trial {owner}")
        config = job.configs[(env, variant)]
        self.log(f"{env} {variant} seed {seed}: started (trial {trial.number})")
        try:
            experiment = Experiment(env, config, seed, job.folder / "runs" / f"{env}_{variant}_{seed}", verbose=0,
                                    device=job.device, eval_freq=grid.eval_freq, eval_episodes=grid.eval_episodes,
                                    progress=False)
            experiment.setup()
            v = grid.variants[variant]
            command = train_command(env, grid.conf_of(variant), v.rule, grid.overrides(variant), seed,
                                    config["n_timesteps"], grid.eval_freq, grid.eval_episodes)
            run_dir = experiment.create_run_folder(command, dict(study=job.study_name, trial=trial.number,
                                                                 variant=variant))
            trial.set_user_attr("run_dir", str(run_dir))
            if not experiment.learn():
                raise KeyboardInterrupt
            return self.evaluate(trial, run_dir)
        except (optuna.TrialPruned, KeyboardInterrupt):
            raise
        except Exception as exc:
            trial.set_user_attr("error", one_line(exc))
            raise

    def evaluate(self, trial, run_dir: Path) -> float:
        """The final evaluations of a finished cell (user attributes ``final_eval``, ``final_eval_best``); the
        final model's mean return, or without them the last evaluation during training."""
        import numpy as np

        final = self.job.grid.final_eval
        if not final.episodes:
            results = np.load(run_dir / "evaluations.npz")
            successes = results["successes"] if "successes" in results.files else []
            last = {"mean_return": float(results["results"][-1].mean()), "success_rate":
                    float(np.mean(successes[-1])) if len(successes) and len(successes[-1]) else None}
            trial.set_user_attr("final_eval", last)
            return last["mean_return"]
        result = evaluate_run(run_dir, final, best=False, device=self.job.device)
        trial.set_user_attr("final_eval", result)
        if final.best_model and (run_dir / "best_model.zip").exists():
            trial.set_user_attr("final_eval_best", evaluate_run(run_dir, final, best=True, device=self.job.device))
        return result["mean_return"]


def evaluate_run(run_dir: Path, final: FinalEval, best: bool = False, device: str = "cpu") -> dict:
    """Evaluate a run folder's final model (``best``: ``best_model.zip``) as ``sb3-spikeplastic evaluate --run``
    does, writing ``final_eval.json`` (``final_eval_best.json``) beside it; returns the summary (mean and standard
    deviation of the return, mean length, success rate, episodes)."""
    from .evaluation import evaluate_model
    from .run_folder import atomic_write, load_model, locate_run, make_eval_env

    info = locate_run(run_dir, best=best)
    model = load_model(info, device)
    venv = make_eval_env(info.env_id, final.n_envs, final.seed, info.env_kwargs, info.vecnormalize)
    try:
        summary = evaluate_model(model, venv, final.episodes, deterministic=True, seed=final.seed).as_dict()
    finally:
        venv.close()
    record = dict(env=info.env_id, model=str(info.model_path), deterministic=True, seed=final.seed, **summary)
    atomic_write(Path(run_dir) / ("final_eval_best.json" if best else "final_eval.json"),
                 lambda f: json.dump(record, f, indent=1), binary=False)
    return {k: summary[k] for k in ("episodes", "mean_return", "std_return", "mean_length", "success_rate")}


def _status(study, n_cells: int) -> tuple[bool, int]:
    """``(whether a cell is left to start, number of running cells)``: a cell is left when a trial waits or a
    grid point was never started (a trial just created by another worker has no grid point yet: it takes one)."""
    trials = study.get_trials(deepcopy=False)
    started = {t.system_attrs["grid_id"] for t in trials if t.state.name != "WAITING" and "grid_id" in t.system_attrs}
    starting = sum(t.state.name == "RUNNING" and "grid_id" not in t.system_attrs for t in trials)
    waiting = any(t.state.name == "WAITING" for t in trials)
    running = sum(t.state.name == "RUNNING" for t in trials)
    return waiting or len(set(range(n_cells)) - started) > starting, running


def cell_line(trial) -> str:
    """One line about a finished cell."""
    p = trial.params
    head = f"{p.get('env')} {p.get('variant')} seed {p.get('seed')} (trial {trial.number})"
    if trial.state.name == "COMPLETE":
        final = trial.user_attrs.get("final_eval", {})
        success = final.get("success_rate")
        return (f"{head}: done, return {trial.value:.4g}" + (f", success {success:.3f}" if success is not None else "")
                + f" -> {trial.user_attrs.get('run_dir')}")
    if trial.state.name == "PRUNED":
        return f"{head}: skipped, taken by trial {trial.user_attrs.get('duplicate_of')}"
    return f"{head}: failed: {trial.user_attrs.get('error', 'interrupted')}"


def run_worker(job: GridJob, log: Callable[[str], None] = print) -> int:
    """Run cells until none is left to start and none is running; returns 0, or 130 when interrupted (the
    interrupted cell is queued again).

    :param job: :func:`prepare`
    :param log: where the progress lines go
    """
    import optuna
    import torch

    from ._fast.allocator import keep_freed_memory

    torch.set_num_threads(job.torch_threads)
    keep_freed_memory()
    study = job.open_study()
    runner = CellRunner(job, log)
    n_cells = len(job.grid.cells())
    while True:
        optuna.storages.fail_stale_trials(study)
        left, running = _status(study, n_cells)
        if left:
            try:
                study.optimize(runner, n_trials=1, catch=(Exception,), callbacks=[lambda _, t: log(cell_line(t))])
            except KeyboardInterrupt:
                interrupted = [t for t in study.get_trials(deepcopy=False) if t.number == runner.current]
                if interrupted and interrupted[0].state.name == "FAIL":
                    retry_callback(max_retry=None)(study, interrupted[0])
                    log(f"interrupted: trial {runner.current} queued again")
                return 130
        elif running:  # other workers' cells: wait, to take one over if its worker dies
            time.sleep(min(job.heartbeat_interval, POLL_INTERVAL))
        else:
            return 0


def _worker_process(job: GridJob, index: int) -> None:
    prefix = f"[worker {index}] "
    sys.exit(run_worker(job, lambda line: print(prefix + line, flush=True)))


def run_workers(job: GridJob, workers: int = 1, log: Callable[[str], None] = print) -> int:
    """Run ``workers`` workers on this machine (one in this process, or each in a process of its own) and wait
    for them; returns the largest exit status."""
    if workers == 1:
        return run_worker(job, log)
    job.open_study()  # created once, before the workers load it
    context = multiprocessing.get_context("spawn")
    processes = [context.Process(target=_worker_process, args=(job, i + 1)) for i in range(workers)]
    for process in processes:
        process.start()
    try:
        for process in processes:
            process.join()
    except KeyboardInterrupt:  # the workers got it too: they queue their cells again and stop
        for process in processes:
            process.join()
        return 130
    # A worker killed by signal N (exit code -N) counts as the shell's 128 + N.
    return max(code if code >= 0 else 128 - code for code in (p.exitcode or 0 for p in processes))


def retry_failed(job: GridJob) -> int:
    """Queue again every cell whose trials all failed; returns how many."""
    study = job.open_study()
    queued = 0
    for cell, trials in _trials_by_cell(job, study).items():
        if trials and all(t.state.name == "FAIL" for t in trials):
            retry_callback(max_retry=None)(study, trials[-1])
            queued += 1
    return queued


def _trials_by_cell(job: GridJob, study) -> dict[tuple[str, str, int], list]:
    """The trials of each cell (duplicates left out), in the order of :meth:`Grid.cells`."""
    trials = [t for t in study.get_trials(deepcopy=False) if "duplicate_of" not in t.user_attrs]
    return {(env, variant, seed): [t for t in trials if t.params == {"env": env, "variant": variant, "seed": seed}]
            for env, variant, seed in job.grid.cells()}


# ----------------------------------------------------------------------------------------------------------------
# Summary

def collect(job: GridJob, study) -> list[dict]:
    """One row per cell: its state (``done``, ``running``, ``waiting``, ``failed``, ``not run``), final return and
    success rate, the best model's, the minutes it took, its run folder, worker and error."""
    rows = []
    for (env, variant, seed), mine in _trials_by_cell(job, study).items():
        done = [t for t in mine if t.state.name == "COMPLETE"]
        states = {t.state.name for t in mine}
        state = ("done" if done else "running" if "RUNNING" in states else "waiting" if "WAITING" in states
                 else "failed" if "FAIL" in states else "not run")
        trial = done[0] if done else (mine[-1] if mine else None)
        final = trial.user_attrs.get("final_eval", {}) if trial else {}
        best = trial.user_attrs.get("final_eval_best", {}) if trial else {}
        minutes = ((trial.datetime_complete - trial.datetime_start).total_seconds() / 60
                   if trial and trial.datetime_complete and trial.datetime_start else None)
        rows.append(dict(env=env, variant=variant, seed=seed, state=state,
                         trial=trial.number if trial else None, final_return=final.get("mean_return"),
                         final_success=final.get("success_rate"), best_model_return=best.get("mean_return"),
                         best_model_success=best.get("success_rate"), episodes=final.get("episodes"),
                         minutes=minutes, run_dir=trial.user_attrs.get("run_dir") if trial else None,
                         worker=trial.user_attrs.get("worker") if trial else None,
                         error=trial.user_attrs.get("error") if trial and not done else None))
    return rows


def _mean_std(values: list) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / len(values))
    return f"{mean:.4g} ± {std:.2g}"


def markdown_table(job: GridJob, rows: list[dict]) -> str:
    """Per variant and environment: cells done, the final return and success rate per seed (``-``: not done)
    and their mean ± standard deviation over the seeds done."""
    def fmt(v):
        return "-" if v is None else f"{v:.4g}"

    lines = ["| variant | env | done | final return per seed | mean ± std | final success per seed | mean ± std |",
             "|---|---|---|---|---|---|---|"]
    for variant in job.grid.variants:
        for env in job.grid.envs:
            group = sorted((r for r in rows if r["env"] == env and r["variant"] == variant), key=lambda r: r["seed"])
            returns = [r["final_return"] for r in group]
            successes = [r["final_success"] for r in group]
            done = sum(r["state"] == "done" for r in group)
            lines.append(f"| {variant} | {env} | {done}/{len(group)} | {' / '.join(map(fmt, returns))} | "
                         f"{_mean_std(returns)} | {' / '.join(map(fmt, successes))} | {_mean_std(successes)} |")
    return "\n".join(lines) + "\n"


def write_summary(job: GridJob, study) -> tuple[Path, Path, str]:
    """``grid.csv`` (one row per cell) and ``grid.md`` (:func:`markdown_table`) in the grid's folder; returns
    their paths and the table."""
    from .run_folder import atomic_write

    rows = collect(job, study)
    job.folder.mkdir(parents=True, exist_ok=True)

    def write_csv(f):
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    csv_path = atomic_write(job.folder / "grid.csv", write_csv, binary=False)
    table = markdown_table(job, rows)
    md_path = atomic_write(job.folder / "grid.md", lambda f: f.write(table), binary=False)
    return csv_path, md_path, table


def run(job: GridJob, workers: int = 1, retry: bool = False, summary_only: bool = False,
        log: Callable[[str], None] = print) -> int:
    """``sb3-spikeplastic grid``: run the workers (unless ``summary_only``), then write and print the summary.

    :param job: :func:`prepare`
    :param workers: worker processes on this machine
    :param retry: first queue again the cells whose trials all failed
    :param summary_only: only write the summary of the study as it stands
    :param log: where the lines go
    """
    status = 0
    if not summary_only:
        cells = len(job.grid.cells())
        log(f"Grid {job.study_name!r} ({cells} cell{'s' if cells > 1 else ''}) in "
            f"{describe_storage(job.storage, job.folder)}; {workers} worker(s) here; run folders under "
            f"{job.folder / 'runs'}")
        if retry:
            log(f"queued again: {retry_failed(job)} failed cell(s)")
        status = run_workers(job, workers, log)
    csv_path, md_path, table = write_summary(job, job.load_study())
    log(table.rstrip())
    log(f"wrote {csv_path}, {md_path}")
    return status


def grid_command(grid_file: str, workers: int = 1, heartbeat_interval: int = 60, grace_period: Optional[int] = None,
                 retry_failed: bool = False, summary_only: bool = False, storage: Optional[str] = None,
                 study_name: Optional[str] = None, log_folder: str = "logs", device: str = "cpu",
                 torch_threads: int = 1) -> Callable[[], int]:
    """``sb3-spikeplastic grid`` with these options (its long names): the grid file and the study are checked by
    :func:`prepare` (``ValueError``, nothing written); returns the work (:func:`run`)."""
    from .inputs import check_device, check_int, check_output_path
    from .studies import check_storage

    for name, value, minimum in (("--workers", workers, 1), ("--heartbeat-interval", heartbeat_interval, 1),
                                 ("--grace-period", grace_period, heartbeat_interval + 1),
                                 ("--torch-threads", torch_threads, 1)):
        check_int(name, value, minimum)
    check_device(device)
    check_output_path(log_folder, "-f/--log-folder", directory=True)
    check_storage(storage)
    name = study_name or Path(grid_file).stem
    job = prepare(load_grid(grid_file), Path(log_folder) / "grid" / name, name, storage, summary_only,
                  heartbeat_interval=heartbeat_interval, grace_period=grace_period, device=device,
                  torch_threads=torch_threads)
    return lambda: run(job, workers, retry_failed, summary_only)
