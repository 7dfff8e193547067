"""The work of one cell of a study: one ``(env, variant, seed)``, trained to the variant's largest budget with a
checkpoint when it reaches each budget (the model of that budget), then every declared evaluation of every budget's
model, each written as raw episodes (:mod:`sb3_spikeplastic.study.layout`).

The work is resumable: a run cut short continues from its latest checkpoint (a budget's, or a periodic one with
``study --save-freq``), a finished run whose budget was raised continues from its final model (``train
--trained-agent``, the step counter kept), and an evaluation whose file exists is not run again. ``job`` is the
:class:`~sb3_spikeplastic.study.engine.StudyJob` whose queue handed out the cell (its study, folder, resolved entries
and device).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Optional

from .declaration import Evaluation, model_name
from .layout import ALIGN_COLUMN, ENERGY_COLUMNS, STEPS_COLUMN, StudyFolder
from .storage import train_command


def _cell_checkpoints(budgets, run_dir: Path, save_freq: int):
    """A callback that saves the model (and its ``VecNormalize`` statistics) when training first reaches each
    budget, ``rl_model_<steps>_steps.zip``: the model of that budget, never removed; and, every ``save_freq`` calls
    (0: never), a checkpoint of which the latest two stay, for a run cut short to continue from."""
    from ..zoo.callbacks import AtomicCheckpoint

    class CellCheckpoints(AtomicCheckpoint):
        def _on_step(self) -> bool:
            if any(self.num_timesteps >= budget > self.num_timesteps - self.model.n_envs for budget in budgets):
                self.save()  # not among the pruned checkpoints
            elif self.save_freq:
                super()._on_step()
            return True

    return CellCheckpoints(save_freq, run_dir, keep=2)


def trained_steps(layout: StudyFolder, env: str, variant: str, seed: int, train_env: str) -> int:
    """How far the cell's training got: its latest checkpoint, or a run's final model (one that ended, or that
    was interrupted and saved)."""
    steps = max(layout.checkpoints(env, variant, seed), default=0)
    for folder in layout.run_folders(env, variant, seed):
        if (folder / f"{train_env}.zip").is_file():
            steps = max(steps, _final_steps(folder, train_env))
    return steps


def _final_steps(folder: Path, env: str) -> int:
    """The step count of a run folder's final model (the counter saved in the model file)."""
    import json
    import zipfile

    with zipfile.ZipFile(folder / f"{env}.zip") as archive:
        data = json.loads(archive.read("data"))
    return int(data["num_timesteps"])


def train_cell(job, env: str, variant: str, seed: int, trial=None) -> None:
    """Train the cell to its variant's largest budget, continuing its latest run if there is one."""
    from ..zoo.experiment import Experiment
    from ..zoo.train import continued_run

    layout, study = job.layout, job.study
    budgets, train_env = study.budgets_of(variant), study.train_env(env, variant)
    if trained_steps(layout, env, variant, seed, train_env) >= max(budgets):
        return
    source, folders = None, layout.run_folders(env, variant, seed)
    for folder in reversed(folders):
        if (folder / f"{train_env}.zip").is_file() or any(folder.glob("rl_model_*_steps.zip")):
            source = continued_run(str(folder), train_env)
            break
    config = job.configs[(env, variant)]
    experiment = Experiment(
        train_env,
        config,
        seed,
        layout.run_root(env, variant, seed),
        verbose=0,
        device=job.device,
        eval_freq=study.eval_freq,
        eval_episodes=study.eval_episodes,
        progress=False,
        trained_agent=source,
    )
    experiment.setup()
    v = study.variants[variant]
    command = train_command(
        train_env,
        study.conf_of(variant),
        v.rule,
        study.overrides(variant),
        seed,
        max(budgets),
        study.eval_freq,
        study.eval_episodes,
    )
    run_dir = experiment.create_run_folder(
        command, dict(study=job.name, variant=variant, trial=None if trial is None else trial.number)
    )
    if trial is not None:
        trial.set_user_attr("run_dir", str(run_dir))
    save_freq = max(job.save_freq // config["n_envs"], 1) if job.save_freq else 0
    experiment.extra_callbacks = [_cell_checkpoints(budgets, run_dir, save_freq)]
    if not experiment.learn():
        raise KeyboardInterrupt


def write_training_curve(layout: StudyFolder, env: str, variant: str, seed: int) -> Optional[Path]:
    """The cell's evaluations during training (every run folder's ``evaluations.npz``) as raw episodes."""
    import numpy as np

    from ..zoo.run_folder import atomic_write

    rows = []
    for folder in layout.run_folders(env, variant, seed):
        if (folder / "evaluations.npz").is_file():
            data = np.load(folder / "evaluations.npz")
            for steps, returns in zip(data["timesteps"], data["results"]):
                rows += [(int(steps), k, float(r)) for k, r in enumerate(returns)]
    if not rows:
        return None

    def write(f):
        writer = csv.writer(f)
        writer.writerow(["timesteps", "episode", "return"])
        writer.writerows(sorted(rows))

    path = layout.training_file(env, variant, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, write, binary=False)


def _ablation_for(model, evaluation: Evaluation) -> Optional[str]:
    """The evaluation's plasticity ablation for a spiking model; ``None`` (as it is) for any other policy, so that
    a study can ablate its spiking variants beside baselines evaluated as they are."""
    spiking = getattr(model.policy, "snn", None) is not None
    return evaluation.ablation if spiking else None


def clipped_statistics(source: Path, target: Path, env: str, clip: float) -> Path:
    """A copy of the ``VecNormalize`` statistics ``source`` that clips the standardised observation at ``clip``."""
    import gymnasium
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    stats = VecNormalize.load(str(source), DummyVecEnv([lambda: gymnasium.make(env)]))
    stats.clip_obs = clip
    stats.save(str(target))
    stats.close()
    return target


def evaluate_model_file(
    job,
    env: str,
    name: str,
    evaluation: Evaluation,
    model_path: Path,
    folder: Path,
    files: list[str],
    eval_name: str,
    same_env: bool = True,
) -> int:
    """Run one evaluation of one model on ``env``, writing each of its missing raw ``files`` whole; returns how
    many. ``same_env``: the model was trained on ``env`` (its ``env_kwargs`` apply), else on another environment
    (evaluated on ``env`` as registered)."""
    import tempfile

    missing = [f for f in files if not (folder / f).is_file()]
    if not missing:
        return 0
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        return _evaluate(job, env, name, evaluation, model_path, folder, missing, eval_name, same_env, Path(tmp))


def _step_value(v: float):
    """A step value as the raw file keeps it: integers as integers, others to 7 significant digits (a relative error
    below 5e-7, about float32's), which keeps a 1000-step HalfCheetah episode's rewards at ~9 kB instead of ~20 kB."""
    return int(v) if v.is_integer() else float(f"{v:.7g}")


def write_final(f, result, align: Optional[str]) -> None:
    """A final evaluation's raw rows: episode, return, length, success (empty where the task reports none), then
    each step-info key's values at every step (a JSON list; bools as 0/1), the alignment key of the final step
    (empty for ``None``) and, for a spiking model, the episode's energy (:data:`~.layout.ENERGY_COLUMNS`).

    :param f: the open text file
    :param result: :class:`sb3_spikeplastic.zoo.evaluation.Evaluation` of the episodes
    :param align: the final step's info key that ``result.aligned`` holds, or ``None``
    """
    import json

    n = len(result.returns)
    columns = {
        "episode": list(range(n)),
        "return": result.returns.tolist(),
        "length": result.lengths.astype(int).tolist(),
        "success": result.successes if len(result.successes) == n else [""] * n,
    }
    for key, episodes in result.steps.items():
        columns[f"{STEPS_COLUMN}{key}"] = [json.dumps([_step_value(v) for v in e]) for e in episodes]
    if align is not None:
        columns[f"{ALIGN_COLUMN}{align}"] = ["" if a is None else a for a in result.aligned]
    if result.episode_energy is not None:
        for key in ENERGY_COLUMNS:
            columns[key] = [f"{e[key]:.6g}" for e in result.episode_energy]
    writer = csv.writer(f)
    writer.writerow(columns)
    writer.writerows(zip(*columns.values()))


def _evaluate(
    job,
    env: str,
    name: str,
    evaluation: Evaluation,
    model_path: Path,
    folder: Path,
    missing: list[str],
    eval_name: str,
    same_env: bool,
    tmp: Path,
) -> int:
    from ..zoo.evaluation import evaluate_model
    from ..zoo.run_folder import atomic_write, cpu_settings_of, load_model, locate_run, make_eval_env
    from .robustness import evaluate_robustness, write_episodes_csv

    info = locate_run(model_path)
    model = load_model(info, job.device)
    env_kwargs = info.env_kwargs if same_env else {}
    statistics = info.vecnormalize
    if evaluation.clip_obs is not None:
        if statistics is None:
            raise ValueError(f"{name}: clip_obs needs VecNormalize statistics beside {model_path}")
        statistics = clipped_statistics(Path(statistics), tmp / "vecnormalize.pkl", env, evaluation.clip_obs)
    p = evaluation.protocol
    if evaluation.kind == "sensitivity":
        from .probes import action_sensitivity, observation_sd

        venv = make_eval_env(env, 1, p.seed, env_kwargs, statistics)
        try:
            with cpu_settings_of(model):
                values, sd = action_sensitivity(model, venv, evaluation.shift), observation_sd(venv)
        finally:
            venv.close()

        def write_sensitivity(f):
            writer = csv.writer(f)
            writer.writerow(["element", "sensitivity", "obs_sd"])
            writer.writerows((i, f"{v:.6g}", f"{d:.6g}") for i, (v, d) in enumerate(zip(values, sd)))

        atomic_write(folder / missing[0], write_sensitivity, binary=False)
        return 1
    if evaluation.kind == "final":
        venv = make_eval_env(env, p.n_envs, p.seed, env_kwargs, statistics)
        try:
            result = evaluate_model(
                model,
                venv,
                p.episodes,
                deterministic=True,
                seed=p.seed,
                ablation=_ablation_for(model, evaluation),
                info_keys=evaluation.info_keys,
                align=evaluation.align,
            )
        finally:
            venv.close()
        atomic_write(folder / missing[0], lambda f: write_final(f, result, evaluation.align), binary=False)
        return 1
    for file in missing:
        noise = file[len(eval_name) + 1 : -len(".csv")]
        rows = evaluate_robustness(
            {name: model},
            env,
            noise,
            p.sigmas,
            n_episodes=p.episodes,
            seed=p.seed,
            vec_normalize_stats={name: statistics},
            progress_bar=False,
            env_kwargs=env_kwargs,
            n_envs=p.n_envs,
            friction_target=p.friction_target,
            ablation=_ablation_for(model, evaluation),
            obs_indices=p.obs_indices,
        )
        tmp = folder / f".{file}.tmp"
        write_episodes_csv(rows, tmp)
        tmp.replace(folder / file)
    return len(missing)


def has_every_file(job, env: str, variant: str, seed: int) -> bool:
    """Whether every raw file of the cell is written: each evaluation of each budget's model and, where the study
    evaluates during training, the training curve. A folder of raw files without the runs (``results/``) then
    needs no training."""
    layout, study = job.layout, job.study
    if study.eval_freq and not layout.training_file(env, variant, seed).is_file():
        return False
    return all(
        (layout.episodes_dir(env, variant, budget, seed) / file).is_file()
        for budget in study.budgets_of(variant)
        for _, _, files in study.evaluations_of(variant, seed, budget)
        for file in files
    )


def run_cell(job, env: str, variant: str, seed: int, trial=None) -> int:
    """Train the cell, write its training curve, and run every evaluation not yet written; returns the number
    of raw files written (none, and no training, where every raw file is there)."""
    layout, study = job.layout, job.study
    if has_every_file(job, env, variant, seed):
        return 0
    train_cell(job, env, variant, seed, trial)
    written = int(write_training_curve(layout, env, variant, seed) is not None)
    same_env = study.train_env(env, variant) == env
    for budget in study.budgets_of(variant):
        name = model_name(variant, budget, seed)
        for eval_name, evaluation, files in study.evaluations_of(variant, seed, budget):
            if evaluation.model == "best":
                folders = [f for f in layout.run_folders(env, variant, seed) if (f / "best_model.zip").is_file()]
                if not folders:
                    raise ValueError(f"evaluation {eval_name!r} needs best_model.zip (set eval_freq)")
                model = folders[-1] / "best_model.zip"
            else:
                model = layout.model_at(env, variant, seed, budget)
                if model is None:
                    raise ValueError(
                        f"{env} {name}: no checkpoint at {budget} steps under {layout.run_root(env, variant, seed)}"
                    )
            written += evaluate_model_file(
                job,
                env,
                name,
                evaluation,
                model,
                layout.episodes_dir(env, variant, budget, seed),
                files,
                eval_name,
                same_env,
            )
    return written
