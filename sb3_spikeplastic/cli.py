"""``sb3-spikeplastic``: train, evaluate, test robustness, plot and inspect spiking plastic policies.

::

    sb3-spikeplastic train --env TMazeCue-v0 --rule dp-oja --seed 0 -f logs --tensorboard-log tb
    sb3-spikeplastic evaluate --run logs/ppo/TMazeCue-v0_1
    sb3-spikeplastic robustness --env HalfCheetah-v5 --noise action --models oja=logs/ppo/HalfCheetah-v5_1 \\
        static=logs/ppo/HalfCheetah-v5_2 --sigmas 0 0.1 0.2 0.4 -o robustness
    sb3-spikeplastic plot logs/ppo/TMazeCue-v0_1 logs/ppo/TMazeCue-v0_2 -o curves.png
    sb3-spikeplastic inspect --run logs/ppo/TMazeCue-v0_1

``train`` writes an rl-zoo-like run folder ``<log folder>/ppo/<EnvId>_<n>/`` (its layout:
:mod:`sb3_spikeplastic.run_folder`; the run itself: :mod:`sb3_spikeplastic.experiment`). This module only parses
the arguments, checks them and turns bad input into one line.

Everything is validated before the run folder is created (environment id, rule, hyperparameter keys and values,
and the model itself is constructed), so bad input writes nothing and fails with one line
``sb3-spikeplastic: error: ...`` and exit status 2. If training crashes before its first environment step, the run
folder is removed; later, it is kept (its logs explain the crash) and marked by ``FAILED.txt`` with the traceback,
and no final model is written (checkpoints and the best model stay). Ctrl-C saves the model, writes
``INTERRUPTED.txt`` and exits with status 130. ``train --trained-agent`` continues any of these.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shlex
import sys
import warnings
from pathlib import Path
from typing import Any, Optional, Sequence

import gymnasium

from .experiment import Experiment, check_spaces, rule_label, training_threads
from .run_folder import (
    RunInfo,
    atomic_write,
    latest_checkpoint,
    load_model,
    locate_run,
    make_eval_env,
    read_run_args,
    read_run_config,
)

PROG = "sb3-spikeplastic"


class UsageError(Exception):
    """Bad input: reported as one line ``sb3-spikeplastic: error: ...`` with exit status 2."""


def _use_agg() -> None:
    import matplotlib

    matplotlib.use("Agg")


# ----------------------------------------------------------------------------------------------------------------
# Validation helpers


def check_env_id(env_id: str, conf_entries: Sequence[str] = ()) -> str:
    """:func:`sb3_spikeplastic.config.check_env_id` with its error as a usage error."""
    from .config import check_env_id as check

    try:
        return check(env_id, conf_entries)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _check_int(name: str, value: Optional[int], minimum: int) -> None:
    if value is not None and value < minimum:
        raise UsageError(f"{name}={value} must be >= {minimum}")


def _threads(value: str):
    """``--torch-threads`` of ``train``: ``auto`` or a positive number."""
    if value == "auto":
        return value
    try:
        number = int(value)
    except ValueError:
        number = 0
    if number < 1:
        raise argparse.ArgumentTypeError(f"{value!r} is not a positive number of threads or 'auto'")
    return number


def _check_device(device: str) -> str:
    import torch

    try:
        parsed = torch.device(device if device != "auto" else "cpu")
    except (RuntimeError, TypeError):
        raise UsageError(f"unknown device {device!r}; accepted: cpu, cuda, cuda:<n>, mps, auto") from None
    if parsed.type == "cuda" and not torch.cuda.is_available():
        # An explicit request is never downgraded silently (`auto` takes the CPU when there is no GPU).
        raise UsageError(f"--device {device}: no CUDA device is available (torch {torch.__version__}); "
                         "accepted here: cpu, auto")
    if parsed.type == "cuda" and parsed.index is not None and parsed.index >= torch.cuda.device_count():
        raise UsageError(f"--device {device}: only {torch.cuda.device_count()} CUDA device(s) here")
    return device


def check_output_path(path: os.PathLike, flag: str, directory: bool) -> Path:
    """``UsageError`` unless ``path`` can be created or written as a folder (``directory``) or a file: the part that
    exists must be a folder (no file on the way) and the nearest existing folder writable. Checked before any
    work, so that a long run never fails at its end for want of a place to write."""
    path = Path(path)
    if path.exists():
        if directory and not path.is_dir():
            raise UsageError(f"{flag} {str(path)!r} is a file, not a folder")
        if not directory and path.is_dir():
            raise UsageError(f"{flag} {str(path)!r} is a folder, not a file")
    parent = path if directory else path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise UsageError(f"{flag} {str(path)!r} lies under the file {str(parent)!r}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"{flag} {str(path)!r}: no permission to write in {str(parent)!r}")
    return path


def _check_rule(rule: Optional[str]) -> None:
    from .plasticity import get_rule_class

    if rule is not None:
        try:
            get_rule_class(rule)
        except ValueError as exc:
            raise UsageError(str(exc)) from None


# ----------------------------------------------------------------------------------------------------------------
# The run folder, with its errors as usage errors


def _locate(path: str, best: bool = False) -> RunInfo:
    try:
        return locate_run(path, best=best)
    except (ValueError, FileNotFoundError) as exc:
        raise UsageError(str(exc)) from None


def _load(info: RunInfo, device: str):
    try:
        return load_model(info, device)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _check_spaces(model, env, env_id: str, model_path) -> None:
    try:
        check_spaces(model, env, env_id, model_path)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


# ----------------------------------------------------------------------------------------------------------------
# train

#: ``train`` runs at least this long checkpoint every tenth of their steps unless ``--save-freq`` says otherwise.
AUTO_CHECKPOINT_MIN_STEPS = 100_000


def _continued_run(args: argparse.Namespace, env_id: str) -> RunInfo:
    """The model (final or checkpoint) that ``--trained-agent`` names, with its run's config, VecNormalize
    statistics and TensorBoard folder; ``UsageError`` if it cannot be continued as asked."""
    if args.hyperparams or args.rule or args.n_envs or args.conf or args.env_kwargs:
        raise UsageError("--trained-agent continues a run with its own configuration; only -n (the total "
                         "steps), --seed and the callback options may be given with it")
    folder = Path(args.trained_agent)
    env_id_of_folder = read_run_config(folder)[0] if folder.is_dir() else None
    if env_id_of_folder and not (folder / f"{env_id_of_folder}.zip").is_file() and latest_checkpoint(folder):
        # A run killed before its end (no final model): continue from its latest checkpoint.
        info = _locate(str(latest_checkpoint(folder)))
        print(f"{PROG}: {str(folder)!r} has no final model; continuing from {info.model_path.name}")
    else:
        info = _locate(args.trained_agent)
    if not info.model_path.is_file() or info.model_path.suffix != ".zip":
        raise UsageError(f"--trained-agent needs a model .zip or a run folder, got {args.trained_agent!r}")
    if info.env_id is not None and info.env_id != env_id:
        raise UsageError(f"--trained-agent {args.trained_agent!r} was trained on {info.env_id}, not {env_id}")
    if info.run_dir is not None:
        tb = read_run_args(info.run_dir, info.env_id).get("tensorboard_dir")
        info.tensorboard_dir = Path(tb) if tb else None
    return info


def _train_config(args: argparse.Namespace) -> tuple[str, dict, Optional[RunInfo]]:
    """``(env_id, resolved entry, model to continue)`` from the arguments of ``train``, every one checked."""
    from . import config as cfg

    try:
        conf_entries = list(cfg.load_hyperparams_file(args.conf))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    env_id = check_env_id(args.env, conf_entries)
    _check_rule(args.rule)
    for name, value, minimum in (("--n-timesteps", args.n_timesteps, 1), ("--n-envs", args.n_envs, 1),
                                 ("--eval-freq", args.eval_freq, 0), ("--eval-episodes", args.eval_episodes, 1),
                                 ("--save-freq", args.save_freq, 0), ("--keep-checkpoints", args.keep_checkpoints, 0),
                                 ("--figure-freq", args.figure_freq, 0)):
        _check_int(name, value, minimum)
    _check_device(args.device)
    check_output_path(args.log_folder, "-f/--log-folder", directory=True)
    if args.tensorboard_log:
        check_output_path(args.tensorboard_log, "--tensorboard-log", directory=True)
    source = _continued_run(args, env_id) if args.trained_agent else None
    try:
        if source is not None and source.config:
            # The run's own resolved configuration: the continued model trains in the same environments.
            config = cfg.validate_entry({**source.config, **({"n_timesteps": args.n_timesteps}
                                                             if args.n_timesteps else {})})
        else:
            # --env-kwargs k=v is --hyperparams env_kwargs.k=v (after the other overrides: it wins)
            overrides = [*(args.hyperparams or ()), *[f"env_kwargs.{item}" for item in args.env_kwargs or ()]]
            config = cfg.resolve_hyperparams(env_id, args.conf, overrides, rule=args.rule,
                                             n_timesteps=args.n_timesteps, n_envs=args.n_envs)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.figure_freq and config["policy"] != "SpikePlasticPolicy":
        raise UsageError(f"--figure-freq needs policy SpikePlasticPolicy, not {config['policy']!r}")
    return env_id, config, source


def _setup(experiment: Experiment) -> None:
    """Build the model in memory: any error here is still bad input."""
    try:
        experiment.setup()
    except (ValueError, TypeError, AssertionError) as exc:
        message = " ".join(str(exc).split()) or type(exc).__name__
        if experiment.source is not None:
            raise UsageError(message) from None
        raise UsageError(f"invalid configuration for {experiment.env_id}: {message}") from None
    except Exception as exc:  # e.g. gymnasium errors from env_kwargs
        if type(exc).__module__.startswith("gymnasium"):
            raise UsageError(f"cannot make {experiment.env_id} with env_kwargs={experiment.env_kwargs}: {exc}") from None
        raise


def cmd_train(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import torch

    from ._fast.allocator import keep_freed_memory

    env_id, config, source = _train_config(args)  # nothing is written before all of this passed
    # Checkpoints by default on long runs (a run killed outright keeps its latest tenth), none on short ones.
    save_freq = args.save_freq if args.save_freq is not None else (
        config["n_timesteps"] // 10 if config["n_timesteps"] >= AUTO_CHECKPOINT_MIN_STEPS else 0)
    cores = torch.get_num_threads()  # torch's default: the physical cores
    if args.torch_threads != "auto":
        torch.set_num_threads(args.torch_threads)
    keep_freed_memory()
    seed = args.seed
    if seed is None and source is not None and source.run_dir is not None:  # a continued run keeps its seed
        seed = read_run_args(source.run_dir, source.env_id or env_id).get("seed")
    if seed is None:
        seed = random.SystemRandom().randrange(2**31 - 1)
    experiment = Experiment(
        env_id, config, seed, Path(args.log_folder), args.tensorboard_log, device=args.device, verbose=args.verbose,
        eval_freq=args.eval_freq, eval_episodes=args.eval_episodes, save_freq=save_freq,
        keep_checkpoints=args.keep_checkpoints, figure_freq=args.figure_freq, vec_env=args.vec_env,
        progress=not args.no_progress, trained_agent=source)
    _setup(experiment)
    if args.torch_threads == "auto":
        torch.set_num_threads(training_threads(experiment.model.policy, cores))
    run_dir = experiment.create_run_folder(shlex.join([PROG, *argv]),
                                           {k: v for k, v in sorted(vars(args).items()) if k != "func"})
    algo_name = "RecurrentPPO" if config.get("algo") == "ppo_lstm" else "PPO"
    print(f"Training {algo_name} ({config['policy']}, rule {rule_label(config)}) on {env_id} for "
          f"{config['n_timesteps']:,} steps, seed {seed}, {torch.get_num_threads()} torch thread(s)")
    print(f"Run folder:  {run_dir}")
    print(f"TensorBoard: tensorboard --logdir {args.tensorboard_log or args.log_folder}")
    sys.stdout.flush()
    model = experiment.model
    try:
        finished = experiment.learn()
    except BaseException:
        if run_dir.exists():
            print(f"{PROG}: training failed after {model.num_timesteps:,} steps; logs kept in {run_dir} "
                  "(see FAILED.txt; no final model written)", file=sys.stderr)
        else:
            print(f"{PROG}: training failed before its first environment step; removed {run_dir}", file=sys.stderr)
        raise
    if not finished:
        print(f"\nInterrupted after {model.num_timesteps:,} steps; saved {experiment.model_path} (see "
              f"{run_dir / 'INTERRUPTED.txt'})")
        return 130
    print(f"\nDone: {model.num_timesteps:,} steps.")
    print(f"  model:        {experiment.model_path}")
    if model.get_vec_normalize_env() is not None:
        print(f"  vecnormalize: {experiment.vecnormalize_path}")
    if args.eval_freq:
        best = run_dir / "best_model.zip"
        print(f"  best model:   {best if best.exists() else '(no evaluation ran)'}; evaluations.npz")
    if save_freq:
        print(f"  checkpoints:  {run_dir}/rl_model_*_steps.zip")
    print(f"  config:       {run_dir / env_id / 'config.yml'}")
    print(f"  monitor:      {run_dir}/*.monitor.csv")
    print(f"  tensorboard:  {experiment.tb_dir}")
    print(f"Evaluate with: {PROG} evaluate --run {shlex.quote(str(run_dir))}")
    return 0


# ----------------------------------------------------------------------------------------------------------------
# optimize and grid (their logic: optimize.py, grid.py and studies.py)


def _check_storage(storage: Optional[str]) -> None:
    from .studies import is_url

    if storage is not None and not is_url(storage):  # a journal file
        check_output_path(storage, "--storage", directory=False)


def cmd_optimize(args: argparse.Namespace, argv: Sequence[str]) -> int:
    from . import optimize

    _check_int("--torch-threads", args.torch_threads, 1)
    _check_device(args.device)
    check_output_path(args.log_folder, "-f/--log-folder", directory=True)
    _check_storage(args.storage)
    settings = optimize.OptimizeSettings(
        args.env, args.conf, args.rule, args.hyperparams or (), args.n_timesteps, args.n_trials, args.sampler,
        args.pruner, args.n_startup_trials, args.n_evaluations, args.eval_episodes, args.seeds_per_trial,
        args.storage, args.study_name, Path(args.log_folder), args.seed, args.device, args.torch_threads,
        args.search_space)
    try:
        search = optimize.prepare(settings)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return optimize.run(search)


def cmd_grid(args: argparse.Namespace, argv: Sequence[str]) -> int:
    from . import grid

    for name, value, minimum in (("--workers", args.workers, 1), ("--heartbeat-interval", args.heartbeat_interval, 1),
                                 ("--grace-period", args.grace_period, args.heartbeat_interval + 1),
                                 ("--torch-threads", args.torch_threads, 1)):
        _check_int(name, value, minimum)
    _check_device(args.device)
    check_output_path(args.log_folder, "-f/--log-folder", directory=True)
    _check_storage(args.storage)
    name = args.study_name or Path(args.grid_file).stem
    try:
        job = grid.prepare(grid.load_grid(args.grid_file), Path(args.log_folder) / "grid" / name, name, args.storage,
                           args.summary_only, heartbeat_interval=args.heartbeat_interval,
                           grace_period=args.grace_period, device=args.device, torch_threads=args.torch_threads)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return grid.run(job, args.workers, args.retry_failed, args.summary_only)


# ----------------------------------------------------------------------------------------------------------------
# evaluate


def _parse_env_kwargs(items: Optional[Sequence[str]]) -> Optional[dict]:
    """``--env-kwargs key=value ...`` as a dict (``None`` when not given)."""
    from .config import parse_override

    if items is None:
        return None
    out: dict[str, Any] = {}
    for item in items:
        try:
            path, value = parse_override(item)
        except ValueError as exc:
            raise UsageError(str(exc).replace("hyperparameter override", "--env-kwargs entry")) from None
        if len(path) != 1:
            raise UsageError(f"malformed --env-kwargs entry {item!r}; expected key=value")
        out[path[0]] = value
    return out


def _resolve_model_args(args: argparse.Namespace) -> tuple[RunInfo, str]:
    if bool(args.run) == bool(args.model):
        raise UsageError("give either --run FOLDER or --model PATH (with --env)")
    info = _locate(args.run or args.model, best=getattr(args, "best", False))
    if args.model and getattr(args, "vecnormalize", None):
        vn = Path(args.vecnormalize)
        if not vn.is_file():
            raise UsageError(f"no VecNormalize statistics file {args.vecnormalize!r}")
        info.vecnormalize = vn
    env_id = args.env or info.env_id
    if env_id is None:
        raise UsageError(f"--env is needed: {args.model!r} is not inside a run folder that names its environment")
    env_kwargs = _parse_env_kwargs(args.env_kwargs)
    if env_kwargs is not None:
        info.config["env_kwargs"] = env_kwargs
    elif args.env and args.env != info.env_id:
        info.config["env_kwargs"] = {}  # the run's env_kwargs belong to its own environment
    return info, check_env_id(env_id)


def cmd_evaluate(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import torch

    from .evaluation import evaluate_model

    _check_int("--episodes", args.episodes, 1)
    _check_int("--n-envs", args.n_envs, 1)
    if args.output:
        check_output_path(args.output, "-o/--output", directory=False)
    info, env_id = _resolve_model_args(args)
    torch.set_num_threads(args.torch_threads)
    model = _load(info, args.device)
    try:
        probe = gymnasium.make(env_id, **info.env_kwargs)
    except Exception as exc:
        raise UsageError(f"cannot make {env_id} with env_kwargs={info.env_kwargs}: {exc}") from None
    try:  # the model against the env before the env's VecNormalize statistics (which would blame the env)
        _check_spaces(model, probe, env_id, info.model_path)
    finally:
        probe.close()
    try:
        venv = make_eval_env(env_id, args.n_envs, args.seed, info.env_kwargs, info.vecnormalize)
    except Exception as exc:
        raise UsageError(f"cannot make {env_id} with the statistics {str(info.vecnormalize)!r}: {exc}") from None
    try:
        result = evaluate_model(model, venv, args.episodes, args.deterministic, args.seed,
                                progress=not args.no_progress)
    finally:
        venv.close()
    summary = result.as_dict()
    mode = "deterministic" if args.deterministic else "stochastic"
    print(f"{env_id}: {info.model_path}" + (f" (VecNormalize: {info.vecnormalize})" if info.vecnormalize else ""))
    print(f"mean return {summary['mean_return']:.3f} ± {summary['std_return']:.3f} over {summary['episodes']} "
          f"episodes ({mode}); mean episode length {summary['mean_length']:.1f}")
    if result.successes:
        print(f"success rate {result.success_rate:.3f} ({int(sum(result.successes))}/{len(result.successes)})")
    energy = result.energy
    if energy is not None:
        layers = " / ".join(f"{x:,.0f}" for x in energy["synops_per_step"])
        print(f"per environment step: {energy['total_spikes_per_step']:,.1f} spikes (input population: "
              f"{energy['spikes_per_step'][0]:,.1f}), {energy['total_synops_per_step']:,.0f} SynOps ({layers} by layer)")
    if args.output:
        record = dict(env=env_id, model=str(info.model_path), deterministic=args.deterministic, seed=args.seed,
                      **summary)
        atomic_write(args.output, lambda f: json.dump(record, f, indent=1), binary=False)
    return 0


# ----------------------------------------------------------------------------------------------------------------
# robustness


def cmd_robustness(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import torch

    from .envs.noise import NOISE_TYPES, FRICTION_TARGETS, make_noisy_env, noise_kwargs
    from .robustness import evaluate_robustness, format_table, write_csv

    if args.noise not in NOISE_TYPES:
        raise UsageError(f"unknown noise type {args.noise!r}; accepted: {', '.join(NOISE_TYPES)}")
    check_output_path(args.output, "-o/--output", directory=True)
    if args.friction_target not in FRICTION_TARGETS:
        raise UsageError(f"unknown friction target {args.friction_target!r}; accepted: {', '.join(FRICTION_TARGETS)}")
    for s in args.sigmas:
        if not math.isfinite(s) or s < 0:
            raise UsageError(f"sigma {s!r} must be a finite number >= 0")
    _check_int("--episodes", args.episodes, 1)
    _check_int("--n-envs", args.n_envs, 1)
    infos: dict[str, RunInfo] = {}
    for spec in args.models:
        name, sep, path = spec.partition("=")
        if not sep:
            name, path = Path(spec.rstrip("/")).name.removesuffix(".zip"), spec
        if not name or not path:
            raise UsageError(f"malformed --models entry {spec!r}; expected NAME=RUN_FOLDER_OR_ZIP")
        if name in infos:
            raise UsageError(f"model name {name!r} given twice in --models")
        infos[name] = _locate(path)
    env_ids = {i.env_id for i in infos.values() if i.env_id}
    env_id = args.env
    if env_id is None:
        if len(env_ids) != 1:
            raise UsageError("--env is needed" + (f": the runs were trained on {', '.join(sorted(env_ids))}"
                                                  if env_ids else ""))
        env_id = env_ids.pop()
    env_id = check_env_id(env_id)
    env_kwargs = _parse_env_kwargs(args.env_kwargs) or {}
    try:  # the noise must apply to this environment: fail before loading models or writing anything
        make_noisy_env(env_id, **noise_kwargs(args.noise, 0.1, args.friction_target), **env_kwargs).close()
    except (ValueError, TypeError) as exc:
        raise UsageError(f"{args.noise} noise cannot be applied to {env_id} (env_kwargs={env_kwargs}): {exc}") from None
    torch.set_num_threads(args.torch_threads)
    models = {name: _load(info, args.device) for name, info in infos.items()}
    probe = gymnasium.make(env_id, **env_kwargs)
    try:
        for name, model in models.items():
            _check_spaces(model, probe, env_id, infos[name].model_path)
    finally:
        probe.close()
    rows = evaluate_robustness(
        models, env_id, args.noise, args.sigmas, n_episodes=args.episodes, seed=args.seed,
        deterministic=args.deterministic,
        vec_normalize_stats={name: info.vecnormalize for name, info in infos.items()},
        progress_bar=not args.no_progress, n_envs=args.n_envs, friction_target=args.friction_target,
        env_kwargs=env_kwargs,
    )
    _use_agg()
    from .figures import robustness_figure

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"robustness_{env_id}_{args.noise}"
    csv_path = write_csv(rows, stem.with_suffix(".csv"))
    table = format_table(rows)
    atomic_write(stem.with_suffix(".md"), lambda f: f.write(table + "\n"), binary=False)
    fig = robustness_figure(rows, title=f"{env_id}: {args.noise} noise ({args.episodes} episodes per point)")
    fig.savefig(stem.with_suffix(".png"), dpi=120)
    print(table)
    print(f"\nwrote {csv_path}, {stem.with_suffix('.md')}, {stem.with_suffix('.png')}")
    return 0


# ----------------------------------------------------------------------------------------------------------------
# plot


def cmd_plot(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import numpy as np

    if args.x not in ("timesteps", "episodes", "walltime"):
        raise UsageError(f"unknown --x {args.x!r}; accepted: timesteps, episodes, walltime")
    _check_int("--smooth", args.smooth, 1)
    check_output_path(args.output, "-o/--output", directory=False)
    from .figures import read_monitor_files

    runs = {}
    for folder in args.runs:
        p = Path(folder)
        if not p.is_dir():
            raise UsageError(f"no run folder {folder!r}")
        if not list(p.glob("*monitor.csv")):
            raise UsageError(f"no Monitor files (*.monitor.csv) in {folder!r}")
        try:
            data = read_monitor_files(p)
        except (ValueError, KeyError) as exc:
            raise UsageError(f"unreadable Monitor file in {folder!r}: {exc}") from None
        if len(data["r"]) == 0:
            raise UsageError(f"no finished episodes in the Monitor files of {folder!r}")
        label = p.name
        env_id, config = read_run_config(p)
        if config:
            label += f" ({rule_label(config)})"
        if label in runs:
            label = str(p)
        runs[label] = data
    _use_agg()
    from .figures import training_curves_figure

    fig = training_curves_figure(runs, x=args.x, smooth=args.smooth, title=args.title)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    for label, data in runs.items():
        last = slice(-100, None)
        line = (f"{label}: {len(data['r'])} episodes, {int(data['l'].sum()):,} steps, mean return of the last "
                f"{len(data['r'][last])}: {data['r'][last].mean():.3f}")
        success = data["is_success"][~np.isnan(data["is_success"])]
        if len(success):
            line += f", success rate of the last {len(success[last])}: {success[last].mean():.3f}"
        print(line)
    print(f"wrote {out}")
    return 0


# ----------------------------------------------------------------------------------------------------------------
# inspect


def cmd_inspect(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import torch

    from .monitoring import inspection_episodes, record_episode, typical_seed

    if args.output:
        check_output_path(args.output, "-o/--output", directory=True)
    info, env_id = _resolve_model_args(args)
    torch.set_num_threads(args.torch_threads)
    model = _load(info, args.device)
    if not hasattr(model.policy, "snn"):
        raise UsageError(f"{str(info.model_path)!r} is not a SpikePlasticPolicy model")
    obs_transform = None
    if info.vecnormalize is not None:
        from stable_baselines3.common.vec_env import VecNormalize

        stats = VecNormalize.load(str(info.vecnormalize), make_eval_env(env_id, 1, 0, info.env_kwargs))
        obs_transform = stats.normalize_obs
    kwargs = info.env_kwargs
    try:
        probe = gymnasium.make(env_id, **kwargs)
    except Exception as exc:
        raise UsageError(f"cannot make {env_id}: {exc}") from None
    episodes = inspection_episodes(env_id, kwargs)
    try:
        _check_spaces(model, probe, env_id, info.model_path)
    finally:
        probe.close()
    out = Path(args.output) if args.output else (info.run_dir / "figures" if info.run_dir else Path("figures"))
    _use_agg()
    from .figures import activity_figure

    out.mkdir(parents=True, exist_ok=True)
    from tqdm.auto import tqdm

    bar = tqdm(episodes.items(), total=len(episodes), unit="episode", disable=args.no_progress, dynamic_ncols=True,
               leave=False)
    for name, make in bar:
        seed, note = args.seed, None
        if name == "typical":
            seed, note = typical_seed(model.policy, make, args.seed, deterministic=args.deterministic,
                                      obs_transform=obs_transform)
        env = make()
        try:
            activity = record_episode(model.policy, env, seed=seed, deterministic=args.deterministic,
                                      max_steps=args.max_steps, obs_transform=obs_transform)
        finally:
            env.close()
        if name == "no_cue":  # the decision is made on the decision cue alone
            activity.info.pop("correct_action", None)
        fig = activity_figure(activity, title=f"{env_id} · {name.replace('_', ' ')}")
        path = out / f"activity_{name}.png"
        fig.savefig(path, dpi=110)
        detail = f" (seed {seed}: {note})" if note else ""
        bar.write(f"{name:>9}: return {activity.episode_return:.3g} over {activity.n_steps} steps{detail} -> {path}")
    return 0


# ----------------------------------------------------------------------------------------------------------------
# enjoy


def cmd_enjoy(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import torch

    from .enjoy import Player, check_video_options

    _check_int("--n-episodes", args.n_episodes, 1)
    _check_int("--max-steps", args.max_steps, 1)
    if args.video:
        check_output_path(args.video, "--video", directory=False)
    try:
        check_video_options(args.video, args.fps, args.size, args.raster)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    info, env_id = _resolve_model_args(args)
    torch.set_num_threads(args.torch_threads)
    model = _load(info, args.device)
    try:
        player = Player(model, env_id, info.env_kwargs, info.vecnormalize, info.model_path, video=args.video,
                        fps=args.fps, size=args.size, raster=args.raster)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    print(f"{env_id}: {info.model_path}" + (f" (VecNormalize: {info.vecnormalize})" if info.vecnormalize else ""))
    torch.manual_seed(args.seed)
    player.run(args.n_episodes, args.deterministic, args.seed, args.max_steps, progress=not args.no_progress)
    return 0


# ----------------------------------------------------------------------------------------------------------------
# parser


def _count(text: str) -> int:
    """An integer that may be written 2e5 or 200_000."""
    try:
        value = float(text.replace("_", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid integer {text!r}") from None
    if not math.isfinite(value) or value != int(value):
        raise argparse.ArgumentTypeError(f"invalid integer {text!r}")
    return int(value)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, like every other bad-input error (argparse adds the usage line)
        self.print_usage(sys.stderr)
        self.exit(2, f"{PROG}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description="Train and study spiking neural network policies with differentiable "
                     "plasticity (SpikePropamine) with Stable-Baselines3's PPO.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    def common(p: argparse.ArgumentParser, auto_threads: bool = False) -> None:
        p.add_argument("--device", default="cpu",
                       help="torch device: cpu (default), cuda[:n] (the spike kernel and CUDA graphs; an error "
                            "where there is no GPU), mps, or auto (cuda when available)")
        if auto_threads:
            p.add_argument("--torch-threads", type=_threads, default="auto",
                           help="torch.set_num_threads: a number, or auto (default): every core for policies big "
                                "enough to gain from it (the HalfCheetah entries, LSTMs), one for small ones")
        else:
            p.add_argument("--torch-threads", type=int, default=1, help="torch.set_num_threads (default: 1)")

    def study_options(p: argparse.ArgumentParser, command: str, default_name: str) -> None:
        p.add_argument("--storage", help="RDB URL (sqlite:///f.db, postgresql://...) or journal file path, shared by "
                       f"processes on any machine (default: <log folder>/{command}/<study>/study.db)")
        p.add_argument("--study-name", help=f"default: {default_name}; an existing study is continued")
        p.add_argument("-f", "--log-folder", default="logs", help="log folder (default: logs)")

    def model_source(p: argparse.ArgumentParser) -> None:
        p.add_argument("--run", help="run folder written by `train` (uses its <EnvId>.zip, config, VecNormalize)")
        p.add_argument("--model", help="a model .zip (with --env); VecNormalize statistics beside it are found")
        p.add_argument("--env", help="environment id (default: the run's)")
        p.add_argument("--vecnormalize", help="VecNormalize statistics for --model (default: found beside it)")
        p.add_argument("--best", action="store_true", help="with --run: use best_model.zip")
        p.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE", help="gymnasium.make arguments, values as "
                       "YAML (default: the run's env_kwargs), e.g. max_episode_steps=200")

    def action_mode(p: argparse.ArgumentParser) -> None:
        p.add_argument("--deterministic", dest="deterministic", action="store_true", default=True,
                       help="mean / arg-max actions (default)")
        p.add_argument("--stochastic", dest="deterministic", action="store_false", help="sampled actions")

    t = sub.add_parser("train", help="train a policy (rl-zoo style hyperparameters and log folder)",
                       description="Train sb3_spikeplastic.PPO with hyperparameters from hyperparams/ppo.yml.")
    t.add_argument("--env", required=True, help="Gymnasium id, e.g. TMazeCue-v0, HalfCheetah-v5")
    t.add_argument("--rule", help="plasticity rule (sets policy_kwargs.rule)")
    t.add_argument("-n", "--n-timesteps", type=_count, help="total environment steps (default: the file's)")
    t.add_argument("--seed", type=int, help="random seed (default: with -i the continued run's, else random; "
                                            "recorded in <EnvId>/args.yml)")
    t.add_argument("-f", "--log-folder", default="logs", help="log folder (default: logs); runs go to "
                   "<folder>/ppo/<EnvId>_<n>")
    t.add_argument("--tensorboard-log", help="TensorBoard root (default: events in the run folder)")
    t.add_argument("--hyperparams", nargs="+", metavar="KEY=VALUE", help="overrides, values as YAML: "
                   "n_steps=128 policy_kwargs.rule=dp-bcm policy_kwargs.hidden_sizes=[32]")
    t.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE", help="gymnasium.make arguments, values as YAML "
                   "(the same as --hyperparams env_kwargs.KEY=VALUE), e.g. max_episode_steps=200 action_noise=0.1")
    t.add_argument("--conf", help="hyperparameter file, or a packaged one by name: ppo (default), paper, mlp, "
                   "ppo_lstm")
    t.add_argument("--n-envs", type=int, help="number of environments (default: the file's)")
    t.add_argument("--vec-env", choices=("dummy", "subproc"), default="dummy", help="step the environments in this "
                   "process (dummy, default) or each in its own (subproc: for slow environments)")
    t.add_argument("--eval-freq", type=int, default=0, help="evaluate every N environment steps (0: never)")
    t.add_argument("--eval-episodes", type=int, default=20, help="episodes per evaluation (default: 20)")
    t.add_argument("--save-freq", type=int, help="checkpoint every N environment steps (0: never; default: every "
                   "tenth of n_timesteps for runs of 100k steps or more, else never)")
    t.add_argument("--keep-checkpoints", type=int, default=2, help="keep only the latest N checkpoints (0: all; "
                   "default 2)")
    t.add_argument("--figure-freq", type=int, default=0, help="TensorBoard activity figure every N rollouts "
                   "(0: never)")
    t.add_argument("-i", "--trained-agent", help="continue training this model (a run folder, its final .zip or "
                   "a --save-freq checkpoint) with its VecNormalize statistics, step counter, schedules and "
                   "TensorBoard run, up to -n total steps (default: the run's n_timesteps); writes a new run folder")
    t.add_argument("-v", "--verbose", type=int, default=1, help="0: quiet, 1: a summary line (return, success, "
                   "steps/s) every tenth of the run (default), 2: SB3's table every rollout")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    common(t, auto_threads=True)
    t.set_defaults(func=cmd_train)

    o = sub.add_parser("optimize", help="hyperparameter search with Optuna (rl-zoo style); writes the best trial "
                       "as a hyperparameter file", description="Search hyperparameters of an entry with Optuna: "
                       "each trial samples the packaged search space, trains like `train` and is evaluated "
                       "n-evaluations times (pruning); the best trial becomes <log folder>/optimize/<study>/best.yml.")
    o.add_argument("--env", required=True, help="Gymnasium id")
    o.add_argument("--conf", help="hyperparameter file the trials start from (default: ppo)")
    o.add_argument("--rule", help="fixed plasticity rule (default: the rule is searched)")
    o.add_argument("--hyperparams", nargs="+", metavar="KEY=VALUE", help="fixed overrides (not searched)")
    o.add_argument("-n", "--n-timesteps", type=_count, help="environment steps per trial and seed (default: the "
                   "entry's)")
    o.add_argument("--n-trials", type=int, default=20, help="trials this process runs (default: 20)")
    o.add_argument("--sampler", default="tpe", help="tpe (default) or random")
    o.add_argument("--pruner", default="median", help="median (default) or none")
    o.add_argument("--n-startup-trials", type=int, default=5, help="random trials before TPE, and trials before "
                   "the median pruner prunes (default: 5)")
    o.add_argument("--n-evaluations", type=int, default=5, help="evaluations per trial and seed, reported to the "
                   "pruner (default: 5)")
    o.add_argument("--eval-episodes", type=int, default=10, help="episodes per evaluation (default: 10)")
    o.add_argument("--seeds-per-trial", type=int, default=1, help="train each trial on seeds 0..N-1; its value is "
                   "the mean (default: 1)")
    study_options(o, "optimize", "<EnvId>_<conf>[_<rule>]")
    o.add_argument("--seed", type=int, help="seed of the sampler (default: random; give each process sharing a "
                   "study its own)")
    o.add_argument("--search-space", help="search-space file (default: the packaged search_space.yml)")
    common(o)
    o.set_defaults(func=cmd_optimize)

    g = sub.add_parser("grid", help="train each cell (variant x env x seed) of a grid file once, by workers on any "
                       "machines sharing an Optuna study", description="A killed worker's cell is run again. "
                       "Writes <log folder>/grid/<study>/: runs/, grid.csv and grid.md.")
    study_options(g, "grid", "the grid file's name without .yml")
    g.add_argument("grid_file", metavar="GRID_FILE", help="the grid (YAML; see docs/cli.md)")
    g.add_argument("--workers", type=int, default=1, help="worker processes on this machine (default: 1)")
    g.add_argument("--heartbeat-interval", type=int, default=60, help="seconds between heartbeats of a running "
                   "cell (default: 60)")
    g.add_argument("--grace-period", type=int, help="seconds without a heartbeat after which a cell is run again "
                   "(default: twice the interval)")
    g.add_argument("--retry-failed", action="store_true", help="first queue again the cells whose training failed")
    g.add_argument("--summary-only", action="store_true", help="only write the summary of the study as it stands")
    common(g)
    g.set_defaults(func=cmd_grid)

    e = sub.add_parser("evaluate", help="mean return (and success rate) of a trained model")
    model_source(e)
    e.add_argument("--episodes", type=int, default=100, help="episodes (default: 100)")
    action_mode(e)
    e.add_argument("--seed", type=int, default=0, help="environment seed (default: 0)")
    e.add_argument("--n-envs", type=int, default=1, help="environments side by side (default: 1)")
    e.add_argument("-o", "--output", help="also write the result as JSON to this file")
    e.add_argument("--no-progress", action="store_true", help="no progress bar")
    common(e)
    e.set_defaults(func=cmd_evaluate)

    r = sub.add_parser("robustness", help="return ratio under noise for several models (paper Fig. 4 F-H)")
    r.add_argument("--models", nargs="+", required=True, metavar="NAME=RUN_OR_ZIP", help="models to compare")
    r.add_argument("--env", help="noise-free environment id (default: the runs')")
    r.add_argument("--noise", required=True, help="obs, action or friction")
    r.add_argument("--sigmas", nargs="+", type=float, default=[0.0, 0.1, 0.2, 0.3, 0.4, 0.5],
                   help="noise standard deviations (default: 0 0.1 0.2 0.3 0.4 0.5)")
    r.add_argument("--episodes", type=int, default=100, help="episodes per model and sigma (default: 100)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--n-envs", type=int, default=1, help="environments side by side (default: 1)")
    r.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE", help="gymnasium.make arguments of the "
                   "noise-free environment, values as YAML (e.g. max_episode_steps=200)")
    r.add_argument("--friction-target", default="damping", help="damping (default) or geom_friction")
    action_mode(r)
    r.add_argument("-o", "--output", default="robustness", help="output folder (default: robustness)")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    common(r)
    r.set_defaults(func=cmd_robustness)

    p = sub.add_parser("plot", help="training curves from the Monitor files of run folders")
    p.add_argument("runs", nargs="+", metavar="RUN_FOLDER")
    p.add_argument("-o", "--output", default="training_curves.png", help="PNG file (default: training_curves.png)")
    p.add_argument("--x", default="timesteps", help="timesteps (default), episodes or walltime")
    p.add_argument("--smooth", type=int, default=20, help="moving average over N episodes (default: 20)")
    p.add_argument("--title")
    p.set_defaults(func=cmd_plot)

    i = sub.add_parser("inspect", help="figures of one episode's network activity (T-maze: typical, all-left, "
                       "all-right and no-cue episodes)")
    model_source(i)
    i.add_argument("-o", "--output", help="output folder (default: <run>/figures)")
    i.add_argument("--seed", type=int, default=0, help="episode seed (default: 0)")
    i.add_argument("--max-steps", type=int, help="environment steps shown (default: about 1 s of network time)")
    action_mode(i)
    i.add_argument("--no-progress", action="store_true", help="no progress bar")
    common(i)
    i.set_defaults(func=cmd_inspect)

    y = sub.add_parser("enjoy", help="play a trained model, print each episode and record a video",
                       description="Play episodes of a trained model (its VecNormalize statistics frozen, its "
                       "recurrent state carried) and optionally record them: one frame after each reset and each "
                       "step.")
    model_source(y)
    y.add_argument("--n-episodes", type=int, default=1, help="episodes (default: 1)")
    action_mode(y)
    y.add_argument("--seed", type=int, default=0, help="reset seed of the first episode (default: 0)")
    y.add_argument("--max-steps", type=int, help="at most N steps per episode (default: until the env ends it)")
    y.add_argument("--video", metavar="FILE", help="record the episodes to FILE: .mp4 or .gif (needs "
                   "pip install \"sb3-spikeplastic[video]\"; MuJoCo renders with MUJOCO_GL, else egl or osmesa)")
    y.add_argument("--fps", type=float, help="frames per second of the video (default: the env's render_fps, "
                   "else 30)")
    y.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="frame size of the video (default: the "
                   "env's, 480 480 for MuJoCo)")
    y.add_argument("--raster", action="store_true", help="draw the hidden layers' spikes of the last 200 ms beside "
                   "each frame (SpikePlasticPolicy)")
    y.add_argument("--no-progress", action="store_true", help="no progress bar")
    common(y)
    y.set_defaults(func=cmd_enjoy)
    return parser


def _route_mujoco_warnings() -> None:
    """MuJoCo's warnings as Python ``RuntimeWarning`` objects: shown once per kind, not once per environment built,
    and no ``MUJOCO_LOG.TXT`` in the working folder; the deprecation of ``settotalmass`` that gymnasium's HalfCheetah
    model triggers at every build is dropped."""
    try:
        import mujoco
    except ImportError:
        return

    def warn(message: str) -> None:
        if "settotalmass" in message:  # gymnasium's HalfCheetah model uses it: nothing a user can change
            return
        warnings.warn(f"MuJoCo: {message.strip()}", RuntimeWarning, stacklevel=2)

    mujoco.set_mju_user_warning(warn)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the ``sb3-spikeplastic`` console script; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return int(exc.code or 0)
    _route_mujoco_warnings()
    try:
        return int(args.func(args, argv) or 0)
    except UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
