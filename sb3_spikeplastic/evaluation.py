"""Evaluate a trained model: returns, episode lengths, success rate and, for spiking policies, the energy proxies
(spikes and synaptic operations per environment step, :class:`~sb3_spikeplastic.monitoring.EnergyMeter`)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np


@dataclass
class Evaluation:
    """The episodes of one evaluation.

    :param returns: episode returns
    :param lengths: episode lengths
    :param successes: ``info["is_success"]`` of the episodes whose environment reports it
    :param energy: :meth:`EnergyMeter.summary` for spiking policies, else ``None``
    """

    returns: np.ndarray
    lengths: np.ndarray
    successes: list[float]
    energy: Optional[dict[str, Any]]

    @property
    def success_rate(self) -> Optional[float]:
        return float(np.mean(self.successes)) if self.successes else None

    def as_dict(self) -> dict[str, Any]:
        """Summary statistics, JSON-ready."""
        return dict(episodes=len(self.returns), mean_return=float(self.returns.mean()),
                    std_return=float(self.returns.std()), mean_length=float(self.lengths.mean()),
                    success_rate=self.success_rate, energy=self.energy)


def evaluate_model(model, venv, n_episodes: int, deterministic: bool = True, seed: int = 0,
                   progress: bool = False) -> Evaluation:
    """Run ``n_episodes`` episodes of ``model`` on the (seeded) vectorised ``venv`` with SB3's ``evaluate_policy``,
    which carries a recurrent policy's state and resets it at episode starts.

    :param model: a trained algorithm (``sb3_spikeplastic.PPO``, SB3's or sb3-contrib's)
    :param venv: the evaluation environments (Monitor-wrapped, as ``evaluate_policy`` wants)
    :param n_episodes: episodes to run
    :param deterministic: mean / arg-max actions instead of samples
    :param seed: torch seed (the input spikes and sampled actions)
    :param progress: show a progress bar over episodes
    """
    import torch
    from stable_baselines3.common.evaluation import evaluate_policy
    from tqdm.auto import tqdm

    from .monitoring import EnergyMeter

    successes: list[float] = []
    bar = tqdm(total=n_episodes, unit="episode", disable=not progress, dynamic_ncols=True)

    def on_step(local_vars: dict, _globals: dict) -> None:
        if local_vars["done"] and "episode" in local_vars["info"]:
            bar.update(1)
            value = local_vars["info"].get("is_success")
            if value is not None:
                successes.append(float(value))

    torch.manual_seed(seed)
    snn = getattr(model.policy, "snn", None)
    try:
        with EnergyMeter(snn) if snn is not None else contextlib.nullcontext() as meter:
            returns, lengths = evaluate_policy(model, venv, n_eval_episodes=n_episodes, deterministic=deterministic,
                                               return_episode_rewards=True, callback=on_step)
    finally:
        bar.close()
    return Evaluation(np.asarray(returns, dtype=float), np.asarray(lengths, dtype=float), successes,
                      meter.summary() if meter is not None else None)
