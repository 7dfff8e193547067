"""Evaluate a trained model: returns, episode lengths, success rate and, for spiking policies, the energy proxies
(spikes and synaptic operations per environment step, :class:`~sb3_spikeplastic.snn.energy.EnergyMeter`).

:func:`evaluate_command` is ``sb3-spikeplastic evaluate``; :func:`load_checked` loads a model and checks it against
the environment it is to play in (for ``evaluate``, ``robustness`` and ``inspect``)."""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .inputs import check_int, check_output_path, model_source
from .run_folder import RunInfo, atomic_write, cpu_settings_of, load_model, make_eval_env

#: The key of ``info_keys`` that is the step's reward as the environment returned it (what the episode's return
#: sums), not a key of the step info: the reward of each step, e.g. to see a return fall and recover in an episode.
REWARD_KEY = "reward"


@dataclass
class Evaluation:
    """The episodes of one evaluation.

    :param returns: episode returns
    :param lengths: episode lengths
    :param successes: ``info["is_success"]`` of the episodes whose environment reports it
    :param energy: :meth:`EnergyMeter.summary` for spiking policies, else ``None``
    :param steps: per requested step-info key, every episode's values at each of its steps (bools as 0/1), in the
        order of ``returns``
    :param aligned: per episode, the requested key of its final step's info (a step index, or ``None``)
    :param episode_energy: per episode, :meth:`EnergyMeter.episode` (SynOps, trace-update MACs, nJ) for spiking
        policies, else ``None``
    """

    returns: np.ndarray
    lengths: np.ndarray
    successes: list[float]
    energy: Optional[dict[str, Any]]
    steps: dict[str, list[list[float]]] = field(default_factory=dict)
    aligned: list[Optional[int]] = field(default_factory=list)
    episode_energy: Optional[list[dict[str, float]]] = None

    @property
    def success_rate(self) -> Optional[float]:
        return float(np.mean(self.successes)) if self.successes else None

    def as_dict(self) -> dict[str, Any]:
        """Summary statistics, JSON-ready."""
        return dict(
            episodes=len(self.returns),
            mean_return=float(self.returns.mean()),
            std_return=float(self.returns.std()),
            mean_length=float(self.lengths.mean()),
            success_rate=self.success_rate,
            energy=self.energy,
        )


def evaluate_model(
    model,
    venv,
    n_episodes: int,
    deterministic: bool = True,
    seed: int = 0,
    progress: bool = False,
    ablation=None,
    info_keys: Sequence[str] = (),
    align: Optional[str] = None,
) -> Evaluation:
    """Run ``n_episodes`` episodes of ``model`` on the (seeded) vectorised ``venv`` with SB3's ``evaluate_policy``,
    which carries a recurrent policy's state and resets it at episode starts.

    :param model: a trained algorithm (``sb3_spikeplastic.PPO``, SB3's or sb3-contrib's)
    :param venv: the evaluation environments (Monitor-wrapped, as ``evaluate_policy`` wants)
    :param n_episodes: episodes to run
    :param deterministic: mean / arg-max actions instead of samples
    :param seed: torch seed (the input spikes and sampled actions)
    :param progress: show a progress bar over episodes
    :param ablation: plasticity ablation to evaluate under (:mod:`sb3_spikeplastic.sb3.ablation`: ``"frozen"``,
        ``"reset-every:N"``, ``"shuffled"``, ``"none"`` or an ``Ablation``; spiking policies only); ``None``: the
        policy's own (``policy.ablation``, normally ``none``)
    :param info_keys: keys of the environment's step info (numbers or bools) whose value at every step of every
        episode is kept (:attr:`Evaluation.steps`), e.g. whether each trial's choice was the good one;
        :data:`REWARD_KEY` (``"reward"``) keeps the step's reward instead of an info key (the steps of an episode
        sum to its return)
    :param align: a key of the final step's info holding a step index (or ``None``), kept per episode
        (:attr:`Evaluation.aligned`) so that the steps can be lined up on an event such as a reversal
    :raises ValueError: a key is missing from the step info, or its value is not a number
    """
    import torch
    from stable_baselines3.common.evaluation import evaluate_policy
    from tqdm.auto import tqdm

    from ..sb3.ablation import ablated, check_ablation
    from ..snn.energy import EnergyMeter

    check_ablation(model, ablation, venv.num_envs)  # before any episode
    successes: list[float] = []
    steps: dict[str, list[list[float]]] = {key: [] for key in info_keys}
    aligned: list[Optional[int]] = []
    episode_energy: list[dict[str, float]] = []
    current: list[dict[str, list[float]]] = [{key: [] for key in info_keys} for _ in range(venv.num_envs)]
    bar = tqdm(total=n_episodes, unit="episode", disable=not progress, dynamic_ncols=True)
    meter = None

    def on_step(local_vars: dict, _globals: dict) -> None:
        i, info = local_vars["i"], local_vars["info"]
        for key in info_keys:
            current[i][key].append(float(local_vars["reward"]) if key == REWARD_KEY else _step_value(info, key))
        if not local_vars["done"]:
            return
        episode, current[i] = current[i], {key: [] for key in info_keys}
        energy = None if meter is None else meter.episode(i, int(local_vars["current_lengths"][i]))
        if "episode" not in info:  # not an episode's end that evaluate_policy counts
            return
        bar.update(1)
        value = info.get("is_success")
        if value is not None:
            successes.append(float(value))
        for key in info_keys:
            steps[key].append(episode[key])
        if align is not None:
            aligned.append(_step_index(info, align))
        if energy is not None:
            episode_energy.append(energy)

    torch.manual_seed(seed)
    snn = getattr(model.policy, "snn", None)
    try:
        with (
            ablated(model, ablation),
            cpu_settings_of(model),
            EnergyMeter(snn) if snn is not None else contextlib.nullcontext() as meter,
        ):
            returns, lengths = evaluate_policy(
                model,
                venv,
                n_eval_episodes=n_episodes,
                deterministic=deterministic,
                return_episode_rewards=True,
                callback=on_step,
            )
    finally:
        bar.close()
    return Evaluation(
        np.asarray(returns, dtype=float),
        np.asarray(lengths, dtype=float),
        successes,
        meter.summary() if meter is not None else None,
        steps,
        aligned,
        episode_energy if meter is not None else None,
    )


def _step_value(info: dict, key: str) -> float:
    """``info[key]`` as a number (a bool as 0/1); ``ValueError`` naming the key when it is missing or no number."""
    if key not in info:
        raise ValueError(f"the step info has no {key!r}; it has {', '.join(map(repr, info)) or 'no key'}")
    value = info[key]
    if isinstance(value, (bool, np.bool_)):
        return float(value)
    if not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"step info {key!r}={value!r} is not a number or a bool")
    return float(value)


def _step_index(info: dict, key: str) -> Optional[int]:
    """``info[key]`` of an episode's final step: a step index or ``None``; ``ValueError`` naming the key
    otherwise."""
    if key not in info:
        raise ValueError(f"the final step's info has no {key!r}; it has {', '.join(map(repr, info)) or 'no key'}")
    value = info[key]
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"final step info {key!r}={value!r} is not a step index (an integer) or None")
    return int(value)


def check_fits(model, info: RunInfo, env_id: str, make_error: Optional[str] = None) -> None:
    """``ValueError`` unless ``env_id``, made with ``info``'s ``env_kwargs``, fits ``model``'s spaces (or cannot be
    made: ``make_error`` starts that message, default ``cannot make <env_id> with env_kwargs=...``)."""
    import gymnasium

    from .run_folder import check_spaces

    try:
        probe = gymnasium.make(env_id, **info.env_kwargs)
    except Exception as exc:
        raise ValueError(f"{make_error or f'cannot make {env_id} with env_kwargs={info.env_kwargs}'}: {exc}") from None
    try:  # the model against the env before the env's VecNormalize statistics (which would blame the env)
        check_spaces(model, probe, env_id, info.model_path)
    finally:
        probe.close()


def load_checked(info: RunInfo, env_id: str, device: str = "cpu"):
    """The model of ``info``, loaded (``ValueError`` if it cannot be) and checked by :func:`check_fits`."""
    model = load_model(info, device)
    check_fits(model, info, env_id)
    return model


def report_lines(
    result: Evaluation, env_id: str, info: RunInfo, deterministic: bool, ablation: Optional[str] = None
) -> list[str]:
    """What ``evaluate`` prints: the model, the mean return and episode length, the success rate (environments
    that report one) and the energy proxies (spiking policies); ``ablation`` (other than ``none``) is named beside
    the action mode."""
    summary = result.as_dict()
    mode = "deterministic" if deterministic else "stochastic"
    if ablation is not None and ablation != "none":
        mode += f", ablation {ablation}"
    lines = [
        f"{env_id}: {info.model_path}" + (f" (VecNormalize: {info.vecnormalize})" if info.vecnormalize else ""),
        f"mean return {summary['mean_return']:.3f} ± {summary['std_return']:.3f} over {summary['episodes']} "
        f"episodes ({mode}); mean episode length {summary['mean_length']:.1f}",
    ]
    if result.successes:
        lines.append(f"success rate {result.success_rate:.3f} ({int(sum(result.successes))}/{len(result.successes)})")
    energy = result.energy
    if energy is not None:
        layers = " / ".join(f"{x:,.0f}" for x in energy["synops_per_step"])
        lines.append(
            f"per environment step: {energy['total_spikes_per_step']:,.1f} spikes in the hidden and output "
            f"layers and {energy['spikes_per_step'][0]:,.1f} in the input population, "
            f"{energy['total_synops_per_step']:,.0f} SynOps ({layers} by layer)"
        )
        joules = energy["energy_nj"]
        if energy["total_plasticity_macs_per_step"] is not None:
            lines.append(
                f"energy estimate per environment step: {joules['total_nj']:,.1f} nJ = SynOps "
                f"{joules['synops_nj']:,.1f} nJ + plasticity {joules['plasticity_nj']:,.1f} nJ "
                f"({energy['total_plasticity_macs_per_step']:,.0f} MACs of trace updates; 45 nm costs, "
                "sb3_spikeplastic.snn.energy)"
            )
    return lines


def evaluate_command(
    run: Optional[str] = None,
    model: Optional[str] = None,
    env: Optional[str] = None,
    vecnormalize: Optional[str] = None,
    best: bool = False,
    env_kwargs: Optional[Sequence[str]] = None,
    episodes: int = 100,
    deterministic: bool = True,
    seed: int = 0,
    n_envs: int = 1,
    output: Optional[str] = None,
    no_progress: bool = False,
    device: str = "cpu",
    torch_threads: int = 1,
    folder: Optional[str] = None,
    exp_id: int = 0,
    load_checkpoint: Optional[int] = None,
    load_last_checkpoint: bool = False,
    ablation: Optional[str] = None,
) -> Callable[[], int]:
    """``sb3-spikeplastic evaluate`` with these options (its long names): the model is found, loaded and checked
    against its environment and the evaluation environments are made (``ValueError``, nothing written); returns
    the evaluation, which prints :func:`report_lines`, writes ``output`` (JSON) if given and returns 0."""
    import torch

    from ..sb3.ablation import Ablation, check_ablation

    check_int("--episodes", episodes, 1)
    check_int("--n-envs", n_envs, 1)
    if ablation is not None:
        Ablation.parse(ablation).check_envs(n_envs)  # a bad --ablation before the model loads
    if output:
        check_output_path(output, "-o/--output", directory=False)
    info, env_id = model_source(
        run, model, env, vecnormalize, best, env_kwargs, folder, exp_id, load_checkpoint, load_last_checkpoint
    )
    torch.set_num_threads(torch_threads)
    loaded = load_checked(info, env_id, device)
    in_force = str(check_ablation(loaded, ablation, n_envs))
    try:
        venv = make_eval_env(env_id, n_envs, seed, info.env_kwargs, info.vecnormalize)
    except Exception as exc:
        raise ValueError(f"cannot make {env_id} with the statistics {str(info.vecnormalize)!r}: {exc}") from None

    def evaluate() -> int:
        try:
            result = evaluate_model(
                loaded, venv, episodes, deterministic, seed, progress=not no_progress, ablation=ablation
            )
        finally:
            venv.close()
        print("\n".join(report_lines(result, env_id, info, deterministic, in_force)))
        if output:
            record = dict(
                env=env_id,
                model=str(info.model_path),
                deterministic=deterministic,
                seed=seed,
                ablation=in_force,
                **result.as_dict(),
            )
            atomic_write(Path(output), lambda f: json.dump(record, f, indent=1), binary=False)
        return 0

    return evaluate
