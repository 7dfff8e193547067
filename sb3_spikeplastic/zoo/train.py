"""``sb3-spikeplastic train``: every option checked and the model built in memory before anything is written
(:func:`train_command`), the run whose ``--trained-agent`` is continued (:func:`continued_run`), the torch threads
of ``--torch-threads auto`` (:func:`training_threads`), and the lines that say where the run writes and what it
wrote. The run itself is an :class:`~sb3_spikeplastic.zoo.experiment.Experiment`.
"""

from __future__ import annotations

import os
import random
import shlex
import sys
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Union

from .config import check_env_id, print_replaced_mappings, resolve_hyperparams, rule_label
from .experiment import Experiment
from .inputs import check_device, check_int, check_output_path, parse_env_kwargs
from .run_folder import RunInfo, latest_checkpoint, locate_run, read_run_args, read_run_config
from .validation import validate_entry
from .zoo_yaml import load_hyperparams_file

#: ``train --torch-threads auto``: a policy with a weight matrix of at least this many entries trains on every core,
#: a smaller one on one (its products are too small to split). Measured on 2 cores: the HalfCheetah entry
#: (170 x 64 input layer) and RecurrentPPO (1024 x 256) train ~25 % faster on two threads, MlpPolicy (64 x 64) and
#: the T-maze entry (40 x 64) at most 3 % (``benchmarks/README.md``).
AUTO_THREADS_MIN_WEIGHTS = 8192


def training_threads(policy, cores: int, load: float = 0.0) -> int:
    """The torch thread count that ``train --torch-threads auto`` uses for ``policy``: the cores that other
    processes leave free (``cores`` minus the one-minute ``load``, at least 1) for a policy big enough to gain from
    them, else 1 (see :data:`AUTO_THREADS_MIN_WEIGHTS`). Threads on busy cores only wait for each other: on a
    loaded machine a second thread makes training slower, not faster (``benchmarks/README.md``, "Threads")."""
    largest = max((p.numel() for p in policy.parameters() if p.dim() >= 2), default=0)
    if largest < AUTO_THREADS_MIN_WEIGHTS:
        return 1
    return max(1, min(cores, int(cores - load + 0.5)))


def machine_load() -> float:
    """The one-minute load average (0 where the platform has none)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return 0.0


#: ``train`` runs at least this long checkpoint every tenth of their steps unless ``--save-freq`` says otherwise.
AUTO_CHECKPOINT_MIN_STEPS = 100_000


def continued_run(trained_agent: str, env_id: str, overridden: bool = False) -> RunInfo:
    """The model (final or checkpoint) that ``--trained-agent`` names, with its run's config, VecNormalize
    statistics and TensorBoard folder; ``ValueError`` if it cannot be continued as asked (``overridden``: options
    that would change its configuration were given)."""
    if overridden:
        raise ValueError(
            "--trained-agent continues a run with its own configuration; only -n (the total "
            "steps), --seed and the callback options may be given with it"
        )
    folder = Path(trained_agent)
    env_id_of_folder = read_run_config(folder)[0] if folder.is_dir() else None
    if env_id_of_folder and not (folder / f"{env_id_of_folder}.zip").is_file() and latest_checkpoint(folder):
        # A run killed before its end (no final model): continue from its latest checkpoint.
        info = locate_run(latest_checkpoint(folder))
        print(f"sb3-spikeplastic: {str(folder)!r} has no final model; continuing from {info.model_path.name}")
    else:
        info = locate_run(trained_agent)
    if not info.model_path.is_file() or info.model_path.suffix != ".zip":
        raise ValueError(f"--trained-agent needs a model .zip or a run folder, got {trained_agent!r}")
    if info.env_id is not None and info.env_id != env_id:
        raise ValueError(f"--trained-agent {trained_agent!r} was trained on {info.env_id}, not {env_id}")
    if info.run_dir is not None:
        tb = read_run_args(info.run_dir, info.env_id).get("tensorboard_dir")
        info.tensorboard_dir = Path(tb) if tb else None
    return info


def train_config(
    env_id: str,
    conf: Optional[str] = None,
    rule: Optional[str] = None,
    hyperparams: Optional[Sequence[str]] = None,
    env_kwargs: Optional[Sequence[str]] = None,
    n_timesteps: Optional[int] = None,
    n_envs: Optional[int] = None,
    source: Optional[RunInfo] = None,
) -> dict:
    """The resolved entry of ``train``'s options: a continued run's own entry (with ``n_timesteps``), else the
    file's entry with the overrides (``env_kwargs`` ``KEY=VALUE`` after ``hyperparams``: they win)."""
    if source is not None and source.config:
        return validate_entry({**source.config, **({"n_timesteps": n_timesteps} if n_timesteps else {})})
    parse_env_kwargs(env_kwargs)  # a malformed entry's error names --env-kwargs
    overrides = [*(hyperparams or ()), *[f"env_kwargs.{item}" for item in env_kwargs or ()]]
    return resolve_hyperparams(env_id, conf, overrides, rule=rule, n_timesteps=n_timesteps, n_envs=n_envs)


def build(experiment: Experiment) -> None:
    """:meth:`Experiment.setup`, any error of it a one-line ``ValueError``: the model is built from the user's
    input, so its errors (and gymnasium's for bad env_kwargs) are bad input."""
    try:
        experiment.setup()
    except (ValueError, TypeError, AssertionError) as exc:
        message = " ".join(str(exc).split()) or type(exc).__name__
        if experiment.source is not None:
            raise ValueError(message) from None
        raise ValueError(f"invalid configuration for {experiment.env_id}: {message}") from None
    except Exception as exc:
        if type(exc).__module__.startswith("gymnasium"):
            raise ValueError(
                f"cannot make {experiment.env_id} with env_kwargs={experiment.env_kwargs}: {exc}"
            ) from None
        raise


def train_command(
    env: str,
    rule: Optional[str] = None,
    n_timesteps: Optional[int] = None,
    seed: Optional[int] = None,
    log_folder: str = "logs",
    tensorboard_log: Optional[str] = None,
    hyperparams: Optional[Sequence[str]] = None,
    env_kwargs: Optional[Sequence[str]] = None,
    conf: Optional[str] = None,
    n_envs: Optional[int] = None,
    vec_env: Optional[str] = None,
    eval_freq: Optional[int] = None,
    eval_episodes: Optional[int] = None,
    save_freq: Optional[int] = None,
    keep_checkpoints: Optional[int] = None,
    figure_freq: Optional[int] = None,
    trained_agent: Optional[str] = None,
    verbose: int = 1,
    no_progress: bool = False,
    device: str = "cpu",
    torch_threads: Union[int, str] = "auto",
    log_interval: int = 1,
    command_line: str = "sb3-spikeplastic train",
) -> Callable[[], int]:
    """``sb3-spikeplastic train`` with these options (its long names): every option is checked and the model built
    in memory (``ValueError``, nothing written); returns the run, which creates the run folder (``command_line``
    in ``command.txt``, the options in ``<EnvId>/args.yml``), trains, prints the files written and returns the exit
    status (130 when interrupted). The run options left ``None`` take, with ``trained_agent``, the continued run's
    values (the environments' process, evaluations, checkpoints, figures, TensorBoard root), else their defaults."""
    import torch

    from ..snn.cpu_settings import keep_freed_memory
    from ..snn.plasticity import get_rule_class

    env_id = check_env_id(env, list(load_hyperparams_file(conf)))
    if rule is not None:
        get_rule_class(rule)
    for name, value, minimum in (
        ("--n-timesteps", n_timesteps, 1),
        ("--n-envs", n_envs, 1),
        ("--eval-freq", eval_freq, 0),
        ("--eval-episodes", eval_episodes, 1),
        ("--save-freq", save_freq, 0),
        ("--keep-checkpoints", keep_checkpoints, 0),
        ("--figure-freq", figure_freq, 0),
        ("--log-interval", log_interval, 1),
    ):
        check_int(name, value, minimum)
    check_device(device)
    check_output_path(log_folder, "-f/--log-folder", directory=True)
    if tensorboard_log:
        check_output_path(tensorboard_log, "--tensorboard-log", directory=True)
    source = None
    if trained_agent:
        source = continued_run(trained_agent, env_id, bool(hyperparams or rule or n_envs or conf or env_kwargs))
        inherited = read_run_args(source.run_dir, source.env_id or env_id) if source.run_dir is not None else {}
        given = dict(
            vec_env=vec_env,
            eval_freq=eval_freq,
            eval_episodes=eval_episodes,
            save_freq=save_freq,
            keep_checkpoints=keep_checkpoints,
            figure_freq=figure_freq,
            tensorboard_log=tensorboard_log,
        )
        chosen = {k: inherited.get(k) if v is None else v for k, v in given.items()}
        vec_env, eval_freq, eval_episodes, save_freq, keep_checkpoints, figure_freq, tensorboard_log = chosen.values()
    vec_env = vec_env or "dummy"
    eval_freq = 0 if eval_freq is None else eval_freq
    eval_episodes = 20 if eval_episodes is None else eval_episodes
    keep_checkpoints = 2 if keep_checkpoints is None else keep_checkpoints
    figure_freq = 0 if figure_freq is None else figure_freq
    config = train_config(env_id, conf, rule, hyperparams, env_kwargs, n_timesteps, n_envs, source)
    if hyperparams and source is None:
        print_replaced_mappings(env_id, conf, hyperparams, rule)
    if figure_freq and config["policy"] != "SpikePlasticPolicy":
        raise ValueError(f"--figure-freq needs policy SpikePlasticPolicy, not {config['policy']!r}")
    # Checkpoints by default on long runs (a run killed outright keeps its latest tenth), none on short ones.
    if save_freq is None:
        save_freq = config["n_timesteps"] // 10 if config["n_timesteps"] >= AUTO_CHECKPOINT_MIN_STEPS else 0
    cores = torch.get_num_threads()  # torch's default: the physical cores
    if torch_threads != "auto":
        torch.set_num_threads(torch_threads)
    keep_freed_memory()
    if seed is None and source is not None and source.run_dir is not None:  # a continued run keeps its seed
        seed = read_run_args(source.run_dir, source.env_id or env_id).get("seed")
    if seed is None:
        seed = random.SystemRandom().randrange(2**31 - 1)
    experiment = Experiment(
        env_id,
        config,
        seed,
        Path(log_folder),
        tensorboard_log,
        device=device,
        verbose=verbose,
        eval_freq=eval_freq,
        eval_episodes=eval_episodes,
        save_freq=save_freq,
        keep_checkpoints=keep_checkpoints,
        figure_freq=figure_freq,
        vec_env=vec_env,
        progress=not no_progress,
        trained_agent=source,
        log_interval=log_interval,
    )
    build(experiment)
    if torch_threads == "auto":
        load = machine_load()
        chosen = training_threads(experiment.model.policy, cores, load)
        torch.set_num_threads(chosen)
        if verbose:
            print(
                f"--torch-threads auto: {chosen} of {cores} core(s) (load {load:.1f}; "
                f"{'a policy big enough to split' if chosen > 1 or load >= cores - 0.5 else 'a small policy'})"
            )
    options = dict(
        env=env,
        rule=rule,
        n_timesteps=n_timesteps,
        seed=seed,
        log_folder=log_folder,
        tensorboard_log=tensorboard_log,
        hyperparams=hyperparams,
        env_kwargs=env_kwargs,
        conf=conf,
        n_envs=n_envs,
        vec_env=vec_env,
        eval_freq=eval_freq,
        eval_episodes=eval_episodes,
        save_freq=save_freq,
        keep_checkpoints=keep_checkpoints,
        figure_freq=figure_freq,
        trained_agent=trained_agent,
        verbose=verbose,
        no_progress=no_progress,
        device=device,
        torch_threads=torch_threads,
        log_interval=log_interval,
    )
    return lambda: _train(experiment, command_line, {"command": "train", **options}, tensorboard_log or log_folder)


def _train(experiment: Experiment, command_line: str, options: dict[str, Any], tensorboard_root) -> int:
    """Create the run folder, train and report: the run of :func:`train_command`."""
    import torch

    config, env_id = experiment.config, experiment.env_id
    run_dir = experiment.create_run_folder(command_line, dict(sorted(options.items())))
    algo_name = "RecurrentPPO" if config.get("algo") == "ppo_lstm" else "PPO"
    if experiment.source is not None:
        print(
            f"Continuing {experiment.source.run_dir or experiment.source.model_path} from step "
            f"{experiment.model.num_timesteps:,} ({experiment.source.model_path.name}), with its seed and run "
            "options unless given"
        )
    print(
        f"Training {algo_name} ({config['policy']}, rule {rule_label(config)}) on {env_id} for "
        f"{config['n_timesteps']:,} steps, seed {experiment.seed}, {torch.get_num_threads()} torch thread(s)"
    )
    print(f"Run folder:  {run_dir}")
    print(f"TensorBoard: tensorboard --logdir {tensorboard_root}")
    sys.stdout.flush()
    model = experiment.model
    try:
        finished = experiment.learn()
    except BaseException:
        if run_dir.exists():
            print(
                f"sb3-spikeplastic: training failed after {model.num_timesteps:,} steps; logs kept in {run_dir} "
                "(see FAILED.txt; no final model written)",
                file=sys.stderr,
            )
        else:
            print(
                f"sb3-spikeplastic: training failed before its first environment step; removed {run_dir}",
                file=sys.stderr,
            )
        raise
    if not finished:
        print(
            f"\nInterrupted after {model.num_timesteps:,} steps; saved {experiment.model_path}. Continue with\n"
            f"  {experiment.continue_command()}"
        )
        return 130
    print(f"\nDone: {model.num_timesteps:,} steps.")
    print(f"  model:        {experiment.model_path}")
    if model.get_vec_normalize_env() is not None:
        print(f"  vecnormalize: {experiment.vecnormalize_path}")
    if experiment.eval_freq:
        best = run_dir / "best_model.zip"
        print(f"  best model:   {best if best.exists() else '(no evaluation ran)'}; evaluations.npz")
    if experiment.save_freq:
        print(f"  checkpoints:  {run_dir}/rl_model_*_steps.zip")
    print(f"  config:       {run_dir / env_id / 'config.yml'}")
    print(f"  monitor:      {run_dir}/*.monitor.csv")
    print(f"  tensorboard:  {experiment.tb_dir}")
    print(f"Evaluate with: sb3-spikeplastic evaluate --run {shlex.quote(str(run_dir))}")
    return 0
