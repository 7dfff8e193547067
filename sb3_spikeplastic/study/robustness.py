"""Robustness to noise after training: the measurement of the paper's Fig. 4 F-H (§3.2); its protocol (sigma grid,
episodes, held-out seed) is :data:`sb3_spikeplastic.study.protocol.FIG4`, the defaults of ``robustness``.

For one noise type and a grid of standard deviations ``sigma``, every model's mean return over ``n_episodes``
episodes is measured and reported as a ratio to the same model's mean return without noise (``sigma = 0``, always
evaluated). The noise is applied by the wrappers of :mod:`sb3_spikeplastic.envs.noise`.

Every (model, ``sigma``) cell is evaluated on a fresh vectorised environment seeded alike, so all models and noise
levels see the same initial states, and the noise draws of a given ``sigma`` are the same for every model: the
comparison between models is paired.

:func:`write_report` writes the rows as CSV, Markdown and a figure; :func:`robustness_command` is
``sb3-spikeplastic robustness``.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import gymnasium
import numpy as np
import torch
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv
from tqdm.auto import tqdm

from sb3_spikeplastic.envs.noise import FRICTION_TARGETS, NOISE_TYPES, make_noisy_env, noise_kwargs

from ..sb3.ablation import Ablation, ablated, check_ablation
from ..zoo.inputs import check_int, check_output_path, parse_env_kwargs
from ..zoo.run_folder import RunInfo, atomic_write, cpu_settings_of, frozen_eval_env, load_model, locate_run
from .protocol import FIG4

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure


@dataclasses.dataclass(frozen=True)
class RobustnessRow:
    r"""The result of one (model, ``sigma``) cell.

    :param model: the model's name (its key in ``models``).
    :param noise_type: ``"obs"``, ``"action"`` or ``"friction"``.
    :param sigma: the noise's standard deviation.
    :param mean_return: mean episode return.
    :param std_return: standard deviation of the episode returns.
    :param n_episodes: number of episodes.
    :param ratio: the return relative to the same model's at ``sigma = 0``, :math:`1 + (R_\sigma - R_0) / |R_0|`
        (NaN if :math:`R_0 = 0`): the paper's :math:`R_\sigma / R_0` when :math:`R_0 > 0`, and for a negative
        :math:`R_0` still below 1 exactly when the noise lowers the return (a plain quotient would read -5.3 ->
        -1.6 as 0.3, a loss).
    :param returns: every episode's return, sorted by (episode within its environment, environment): a position
        holds the same seeded environment's same episode in every cell, which pairs the episodes of different
        ``sigma`` and models.
    """

    model: str
    noise_type: str
    sigma: float
    mean_return: float
    std_return: float
    n_episodes: int
    ratio: float
    returns: tuple[float, ...] = ()


def _make_eval_env(
    env_id: str,
    noise: Mapping[str, Any],
    env_kwargs: Mapping[str, Any],
    n_envs: int,
    seed: int,
    vec_normalize_path: str | os.PathLike | None,
) -> VecEnv:
    """:func:`frozen_eval_env` of the noise-wrapped ``env_id``."""
    return frozen_eval_env(lambda: make_noisy_env(env_id, **noise, **env_kwargs), n_envs, seed, vec_normalize_path)


def evaluate_robustness(
    models: Mapping[str, Any],
    env_id: str,
    noise_type: str,
    sigmas: Sequence[float],
    n_episodes: int = 100,
    seed: int = 0,
    deterministic: bool = True,
    vec_normalize_stats: Mapping[str, str | os.PathLike | None] | None = None,
    progress_bar: bool = True,
    env_kwargs: Mapping[str, Any] | None = None,
    n_envs: int = 1,
    friction_target: str = "damping",
    obs_indices: Sequence[int] | None = None,
    ablation: str | Ablation | None = None,
) -> list[RobustnessRow]:
    """Mean return of every model under one noise type, for each ``sigma`` (paper Fig. 4 F-H).

    Episodes are run by Stable-Baselines3's ``evaluate_policy``, which passes the recurrent state and
    ``episode_start`` to ``model.predict`` at every step, so recurrent and plastic policies keep (and reset) their
    state correctly.

    :param models: name -> trained model (anything with SB3's ``predict(obs, state, episode_start,
        deterministic)``).
    :param env_id: registered id of the noise-free environment, e.g. ``"HalfCheetah-v5"``.
    :param noise_type: one of :data:`sb3_spikeplastic.envs.noise.NOISE_TYPES`.
    :param sigmas: noise standard deviations; 0 is added if missing, and the grid is evaluated in increasing order.
    :param n_episodes: episodes per (model, ``sigma``); the paper uses 100.
    :param seed: seed of the environments (environment ``i`` gets ``seed + i``) and, when ``deterministic`` is
        False, of torch's generator before every cell, so that the sampled actions are reproducible too.
    :param deterministic: whether the policies act deterministically.
    :param vec_normalize_stats: name -> path of the model's saved ``VecNormalize`` statistics (or None); they are
        loaded frozen, with reward normalisation off.
    :param progress_bar: show a tqdm progress bar over all episodes.
    :param env_kwargs: arguments of ``gymnasium.make`` for ``env_id`` (e.g. ``max_episode_steps``).
    :param n_envs: environments stepped side by side (batches the policy's forward pass).
    :param friction_target: the friction parameters perturbed by ``"friction"`` noise.
    :param obs_indices: the observation elements perturbed by ``"obs"`` noise (None: all of them).
    :param ablation: plasticity ablation every model is evaluated under (:mod:`sb3_spikeplastic.sb3.ablation`; spiking
        policies only); ``None``: each policy's own (``policy.ablation``, normally ``none``).
    :return: one row per (model, ``sigma``), models in the given order, ``sigma`` increasing, with every episode's
        return (:attr:`RobustnessRow.returns`).
    """
    noise_kwargs(noise_type, 0.0, friction_target, obs_indices)  # fail on a bad noise type or target before any work
    grid = sorted({0.0, *(float(s) for s in sigmas)})
    for sigma in grid:
        noise_kwargs(noise_type, sigma)
    if not models:
        raise ValueError("models is empty: pass at least one name -> model")
    if isinstance(n_episodes, bool) or not isinstance(n_episodes, int) or n_episodes < 1:
        raise ValueError(f"n_episodes={n_episodes!r} must be an integer >= 1")
    if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
        raise ValueError(f"n_envs={n_envs!r} must be an integer >= 1")
    for name, model in models.items():
        try:
            check_ablation(model, ablation, n_envs)
        except ValueError as exc:
            raise ValueError(f"model {name!r}: {exc}") from None
    stats = dict(vec_normalize_stats or {})
    unknown = sorted(set(stats) - set(models))
    if unknown:
        raise ValueError(f"vec_normalize_stats names {unknown} that are not in models {sorted(models)}")
    env_kwargs = dict(env_kwargs or {})
    if obs_indices is not None:  # indices must fit the observation: fail before any work
        make_noisy_env(env_id, **noise_kwargs(noise_type, 1.0, obs_indices=obs_indices), **env_kwargs).close()

    rows: list[RobustnessRow] = []
    with tqdm(
        total=len(models) * len(grid) * n_episodes, disable=not progress_bar, desc="robustness", unit="episode"
    ) as bar:
        finished: list[tuple[int, int]] = []  # (episode within its environment, environment) of each return

        def count_episode(local_vars: dict[str, Any], _globals: dict[str, Any]) -> None:
            # evaluate_policy calls back for every counted step; a Monitor "episode" entry marks a finished episode,
            # whose return evaluate_policy appends right after this call.
            if local_vars["done"] and "episode" in local_vars["info"]:
                env = local_vars["i"]
                finished.append((int(local_vars["episode_counts"][env]), env))
                bar.update(1)

        for name, model in models.items():
            baseline = math.nan
            for sigma in grid:
                bar.set_postfix(model=name, noise=noise_type, sigma=sigma)
                venv = _make_eval_env(
                    env_id,
                    noise_kwargs(noise_type, sigma, friction_target, obs_indices),
                    env_kwargs,
                    n_envs,
                    seed,
                    stats.get(name),
                )
                if not deterministic:
                    torch.manual_seed(seed)
                finished.clear()
                try:
                    with ablated(model, ablation), cpu_settings_of(model):
                        returns, _ = evaluate_policy(
                            model,
                            venv,
                            n_eval_episodes=n_episodes,
                            deterministic=deterministic,
                            return_episode_rewards=True,
                            callback=count_episode,
                        )
                finally:
                    venv.close()
                ordered = tuple(float(r) for _, r in sorted(zip(finished, returns), key=lambda pair: pair[0]))
                mean = float(np.mean(ordered))
                if sigma == 0.0:
                    baseline = mean
                ratio = return_ratio(mean, baseline)
                rows.append(
                    RobustnessRow(name, noise_type, sigma, mean, float(np.std(ordered)), len(ordered), ratio, ordered)
                )
    return rows


def return_ratio(mean_return: float, baseline: float) -> float:
    r""":math:`1 + (R_\sigma - R_0) / |R_0|`, the return relative to the noise-free one (see :class:`RobustnessRow`);
    NaN when ``baseline`` is 0."""
    return 1.0 + (mean_return - baseline) / abs(baseline) if baseline != 0.0 else math.nan


def write_csv(rows: Sequence[RobustnessRow], path: str | os.PathLike) -> Path:
    """Write the rows to a CSV file with a header (parent folders are created).

    :param rows: rows from :func:`evaluate_robustness`.
    :param path: the file to write.
    :return: the path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [field.name for field in dataclasses.fields(RobustnessRow) if field.name != "returns"]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=names)
        writer.writeheader()
        writer.writerows({name: getattr(row, name) for name in names} for row in rows)
    return path


def write_episodes_csv(rows: Sequence[RobustnessRow], path: str | os.PathLike) -> Path:
    """Write every episode's return, one line per (model, ``sigma``, episode) with the columns ``model``,
    ``noise_type``, ``sigma``, ``episode`` (the position in :attr:`RobustnessRow.returns`) and ``return``: the raw
    data of intervals over seeds and episodes.

    :param rows: rows from :func:`evaluate_robustness`.
    :param path: the file to write (parent folders are created).
    :return: the path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "noise_type", "sigma", "episode", "return"])
        for row in rows:
            writer.writerows([row.model, row.noise_type, row.sigma, k, r] for k, r in enumerate(row.returns))
    return path


def format_table(rows: Sequence[RobustnessRow]) -> str:
    """Format the rows as a Markdown table.

    :param rows: rows from :func:`evaluate_robustness`.
    :return: the table, one line per row after the header.
    """
    lines = [
        "| model | noise | sigma | mean return | std return | episodes | ratio to sigma=0 |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r.model} | {r.noise_type} | {r.sigma:g} | {r.mean_return:.2f} | {r.std_return:.2f} | {r.n_episodes} "
        f"| {r.ratio:.3f} |"
        for r in rows
    ]
    return "\n".join(lines)


def write_report(
    rows: Sequence[RobustnessRow],
    folder: str | os.PathLike,
    env_id: str,
    noise_type: str,
    n_episodes: int,
    ablation: str | Ablation | None = None,
) -> tuple[str, list[Path]]:
    """Write ``robustness_<env_id>_<noise_type>`` ``.csv`` (:func:`write_csv`), ``.md`` (:func:`format_table`),
    ``.png`` (:func:`robustness_figure`) and, when the rows hold their episodes,
    ``_episodes.csv`` (:func:`write_episodes_csv`) into ``folder`` (created if needed). Under an ``ablation`` other
    than ``none`` the names end in ``_<ablation>`` (``_frozen``, ``_reset-every-50``, ``_shuffled``), so that the
    ablations of one comparison sit beside its unablated files, and the figure's title names it.

    :return: the Markdown table and the files written.
    """
    import matplotlib

    matplotlib.use("Agg")

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    ablation = Ablation.parse(ablation)
    suffix = f"_{str(ablation).replace(':', '-')}" if ablation.active else ""
    stem = out / f"robustness_{env_id}_{noise_type}{suffix}"
    csv_path = write_csv(rows, stem.with_suffix(".csv"))
    table = format_table(rows)
    atomic_write(stem.with_suffix(".md"), lambda f: f.write(table + "\n"), binary=False)
    named = f", ablation {ablation}" if ablation.active else ""
    fig = robustness_figure(rows, title=f"{env_id}: {noise_type} noise ({n_episodes} episodes per point{named})")
    fig.savefig(stem.with_suffix(".png"), dpi=120)
    paths = [csv_path, stem.with_suffix(".md"), stem.with_suffix(".png")]
    if any(row.returns for row in rows):
        paths.append(write_episodes_csv(rows, stem.parent / f"{stem.name}_episodes.csv"))
    return table, paths


def parse_models(specs: Sequence[str]) -> dict[str, RunInfo]:
    """``--models`` entries ``NAME=RUN_FOLDER_OR_ZIP`` (or a bare path, named after its folder or file) located."""
    infos: dict[str, RunInfo] = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep:
            name, path = Path(spec.rstrip("/")).name.removesuffix(".zip"), spec
        if not name or not path:
            raise ValueError(f"malformed --models entry {spec!r}; expected NAME=RUN_FOLDER_OR_ZIP")
        if name in infos:
            raise ValueError(f"model name {name!r} given twice in --models")
        infos[name] = locate_run(path)
    return infos


def robustness_command(
    models: Sequence[str],
    noise: str,
    env: Optional[str] = None,
    sigmas: Sequence[float] = FIG4.sigmas,
    episodes: int = FIG4.episodes,
    seed: int = FIG4.seed,
    n_envs: int = FIG4.n_envs,
    env_kwargs: Optional[Sequence[str]] = None,
    friction_target: str = "damping",
    obs_indices: Optional[Sequence[int]] = None,
    deterministic: bool = True,
    output: str = "robustness",
    no_progress: bool = False,
    device: str = "cpu",
    torch_threads: int = 1,
    ablation: Optional[str] = None,
) -> Callable[[], int]:
    """``sb3-spikeplastic robustness`` with these options (its long names): the noise is applied to the
    environment once, the models are loaded and checked against it (``ValueError``, nothing written); returns the
    comparison, which prints the table, writes it (:func:`write_report`) and returns 0."""
    from ..zoo.config import check_env_id
    from ..zoo.run_folder import check_spaces

    if noise not in NOISE_TYPES:
        raise ValueError(f"unknown noise type {noise!r}; accepted: {', '.join(NOISE_TYPES)}")
    check_output_path(output, "-o/--output", directory=True)
    if friction_target not in FRICTION_TARGETS:
        raise ValueError(f"unknown friction target {friction_target!r}; accepted: {', '.join(FRICTION_TARGETS)}")
    for s in sigmas:
        if not math.isfinite(s) or s < 0:
            raise ValueError(f"sigma {s!r} must be a finite number >= 0")
    check_int("--episodes", episodes, 1)
    check_int("--n-envs", n_envs, 1)
    if ablation is not None:
        Ablation.parse(ablation).check_envs(n_envs)  # a bad --ablation before any model loads
    infos = parse_models(models)
    env_ids = {i.env_id for i in infos.values() if i.env_id}
    env_id = env
    if env_id is None:
        if len(env_ids) != 1:
            raise ValueError(
                "--env is needed" + (f": the runs were trained on {', '.join(sorted(env_ids))}" if env_ids else "")
            )
        env_id = env_ids.pop()
    env_id = check_env_id(env_id)
    kwargs = parse_env_kwargs(env_kwargs) or {}
    try:  # the noise must apply to this environment: fail before loading models or writing anything
        make_noisy_env(env_id, **noise_kwargs(noise, 0.1, friction_target, obs_indices), **kwargs).close()
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{noise} noise cannot be applied to {env_id} (env_kwargs={kwargs}): {exc}") from None
    torch.set_num_threads(torch_threads)
    loaded = {name: load_model(info, device) for name, info in infos.items()}
    probe = gymnasium.make(env_id, **kwargs)
    try:
        for name, model in loaded.items():
            check_spaces(model, probe, env_id, infos[name].model_path)
    finally:
        probe.close()
    for name, model in loaded.items():
        try:
            check_ablation(model, ablation, n_envs)
        except ValueError as exc:
            raise ValueError(f"--models {name}: {exc}") from None

    def compare() -> int:
        rows = evaluate_robustness(
            loaded,
            env_id,
            noise,
            sigmas,
            n_episodes=episodes,
            seed=seed,
            deterministic=deterministic,
            vec_normalize_stats={name: info.vecnormalize for name, info in infos.items()},
            progress_bar=not no_progress,
            n_envs=n_envs,
            friction_target=friction_target,
            obs_indices=obs_indices,
            env_kwargs=kwargs,
            ablation=ablation,
        )
        table, paths = write_report(rows, output, env_id, noise, episodes, ablation)
        print(table)
        print(f"\nwrote {', '.join(str(p) for p in paths)}")
        return 0

    return compare


def robustness_figure(rows: Sequence["RobustnessRow"], title: Optional[str] = None) -> Figure:
    """Return ratio (:func:`~sb3_spikeplastic.study.robustness.return_ratio`, the mean return relative to the one at
    ``sigma = 0``) against ``sigma``, one line per model
    (paper Fig. 4 F-H). Error bars: one standard deviation of the episode returns over ``|mean return at 0|``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.5, 4.5), layout="constrained")
    ax = fig.subplots()
    models = list(dict.fromkeys(r.model for r in rows))
    for k, name in enumerate(models):
        mine = sorted((r for r in rows if r.model == name), key=lambda r: r.sigma)
        base = next((r.mean_return for r in mine if r.sigma == 0.0), math.nan)
        sigmas = [r.sigma for r in mine]
        ratios = [r.ratio for r in mine]
        errors = [r.std_return / abs(base) if base not in (0.0,) and math.isfinite(base) else math.nan for r in mine]
        ax.errorbar(sigmas, ratios, yerr=errors, marker="o", capsize=3, linewidth=1.4, label=name, color=f"C{k % 10}")
    ax.axhline(1.0, color="0.6", linestyle=":", linewidth=0.8)
    noise = rows[0].noise_type if rows else ""
    ax.set_xlabel(f"{noise} noise σ")
    # RobustnessRow.ratio: R_sigma / R_0 for a positive R_0, and below 1 exactly when the noise lowers the return.
    ax.set_ylabel(
        r"return ratio $1 + (R_\sigma - R_0)\,/\,|R_0|$"
        "\n"
        r"($R_\sigma / R_0$ for $R_0 > 0$; $R$: mean return)"
    )
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    return fig
