"""Plasticity ablations at evaluation: does a trained plastic network act on its traces ``E`` (and the BCM
thresholds ``phi``) or on its learned weights ``W`` alone?

An :class:`Ablation` names a mode; :func:`ablate` applies it to the network state a step runs on (after the
episode-start reset), given each environment's step count since its episode start:

* ``none`` — nothing changes (the default).
* ``frozen`` — every trace and rule state (``E``, ``phi``) is held at its episode-start value, zero: the network runs
  on ``W`` alone (``alpha * E`` adds nothing), also between the plasticity updates inside one environment step.
* ``reset-every:N`` — traces and rule states back to zero every ``N`` environment steps, counted per environment
  from its episode start (the first ``N`` steps of an episode run as without ablation).
* ``shuffled`` — each environment runs on another environment's traces: before every step the plastic state is
  rolled by one environment (environment ``i`` gets that of ``i - 1``), which needs 2 or more environments.

A static network (rule ``static``) keeps no plastic state, so every mode leaves it unchanged. The modes act on
evaluation only: :meth:`SpikePlasticPolicy.predict <sb3_spikeplastic.sb3.policy.SpikePlasticPolicy.predict>` (and so
``evaluate_policy``, ``EvalCallback``, ``evaluate``, ``robustness`` and ``enjoy``) applies the policy's
``ablation``; :class:`sb3_spikeplastic.PPO`'s rollouts and updates never do.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator, NamedTuple, Optional, Union

import torch
from torch import Tensor

from ..snn.layers import LayerState
from ..snn.network import NetworkState, map_tensors, tensor_leaves

#: The ablation modes (``reset-every`` is written ``reset-every:N``).
MODES = ("none", "frozen", "reset-every", "shuffled")

ACCEPTED = "none, frozen, reset-every:N (N >= 1 environment steps), shuffled"


@dataclass(frozen=True)
class Ablation:
    """A plasticity ablation mode (module docstring), written ``none``, ``frozen``, ``reset-every:N`` or
    ``shuffled`` on the command line and in YAML (:meth:`parse`, ``str()``).

    :param mode: one of :data:`MODES`.
    :param every: ``N``, environment steps between resets (``reset-every`` only).
    """

    mode: str = "none"
    every: Optional[int] = None

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"unknown ablation mode {self.mode!r}; accepted: {', '.join(MODES)}")
        if self.mode == "reset-every":
            if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
                raise ValueError(
                    f"reset-every needs every=N, a whole number of environment steps >= 1, got {self.every!r}"
                )
        elif self.every is not None:
            raise ValueError(f"every={self.every!r} applies to mode 'reset-every' only, not {self.mode!r}")

    @classmethod
    def parse(cls, value: Union[str, "Ablation", None]) -> "Ablation":
        """The ablation written ``value`` (``None``: ``none``; an :class:`Ablation` as it is)."""
        if value is None:
            return cls()
        if isinstance(value, Ablation):
            return value
        if not isinstance(value, str):
            raise ValueError(f"ablation {value!r} is not a string; accepted: {ACCEPTED}")
        mode, sep, every = value.strip().partition(":")
        if mode == "reset-every":
            try:
                n = int(every)
            except ValueError:
                n = 0
            if not sep or n < 1:
                raise ValueError(f"ablation {value!r} needs N, a whole number of environment steps >= 1: reset-every:N")
            return cls(mode, n)
        if sep or mode not in MODES:
            raise ValueError(f"unknown ablation {value!r}; accepted: {ACCEPTED}")
        return cls(mode)

    def __str__(self) -> str:
        return f"{self.mode}:{self.every}" if self.mode == "reset-every" else self.mode

    @property
    def active(self) -> bool:
        """Whether the mode changes anything (not ``none``)."""
        return self.mode != "none"

    @property
    def holds_plastic(self) -> bool:
        """Whether the plastic updates inside an environment step are dropped too (``frozen``)."""
        return self.mode == "frozen"

    def check_envs(self, n_envs: int) -> None:
        """``ValueError`` where the mode cannot run on ``n_envs`` environments side by side (``shuffled``: < 2)."""
        if self.mode == "shuffled" and n_envs < 2:
            raise ValueError(
                f"ablation 'shuffled' needs 2 or more environments side by side (each runs on "
                f"another's traces), got n_envs={n_envs}"
            )


class AblatedState(NamedTuple):
    """The recurrent state :meth:`SpikePlasticPolicy.predict <sb3_spikeplastic.sb3.policy.SpikePlasticPolicy.predict>`
    returns under an ablation: the network state and each environment's step count since its episode start.

    :param network: the :class:`~sb3_spikeplastic.snn.network.NetworkState`.
    :param steps: ``(batch,)`` int64, environment steps since each environment's episode start.
    """

    network: NetworkState
    steps: Tensor


def _plastic_map(fn, state: NetworkState) -> NetworkState:
    """``state`` with ``fn`` applied to every tensor of every layer's plastic state (traces and rule state)."""
    layers = tuple(LayerState(s.psp, s.refractory, map_tensors(fn, s.plastic)) for s in state.layers)
    return state._replace(layers=layers)


def ablate(ablation: Ablation, state: NetworkState, steps: Tensor) -> NetworkState:
    """The network state a step runs on under ``ablation``: ``state`` (already reset where episodes start) with
    its plastic state (traces ``E``, rule states such as ``phi``) changed as the mode says (module docstring).

    :param ablation: the mode.
    :param state: the network state of ``batch`` environments.
    :param steps: ``(batch,)`` environment steps since each environment's episode start (``reset-every``).
    :return: the state to run the step on; ``state`` itself for ``none`` and for a network without plastic state.
    """
    ablation.check_envs(state.noise_key.shape[0])
    if not ablation.active or not any(x.numel() for s in state.layers for x in tensor_leaves(s.plastic)):
        return state
    if ablation.mode == "frozen":
        return _plastic_map(torch.zeros_like, state)
    if ablation.mode == "shuffled":
        return _plastic_map(lambda x: x.roll(1, 0), state)
    reset = (steps.to(state.noise_key.device) % ablation.every) == 0
    if not bool(reset.any()):
        return state
    return _plastic_map(
        lambda x: torch.where(
            reset.view(-1, *([1] * (x.dim() - 1))), torch.zeros((), dtype=x.dtype, device=x.device), x
        ),
        state,
    )


def check_ablation(model, ablation: Union[str, Ablation, None], n_envs: Optional[int] = None) -> Ablation:
    """The ablation ``model`` (an algorithm or its policy) runs under with ``ablation`` (``None``: its policy's own,
    ``none`` if it has none), parsed and checked: ``ValueError`` for a mode other than ``none`` on a policy that is
    not spiking, or ``shuffled`` where ``n_envs`` (if given) is below 2."""
    policy = getattr(model, "policy", model)
    own = getattr(policy, "ablation", None) if hasattr(type(policy), "ablation") else None
    ablation = Ablation.parse(own if ablation is None else ablation)
    if ablation.active:
        if own is None:
            raise ValueError(
                f"ablation {str(ablation)!r} needs a spiking plastic policy (SpikePlasticPolicy), not "
                f"{type(policy).__name__}"
            )
        if n_envs is not None:
            ablation.check_envs(n_envs)
    return ablation


@contextlib.contextmanager
def ablated(model, ablation: Union[str, Ablation, None]) -> Iterator[Ablation]:
    """Run ``model`` (an algorithm or its policy) under ``ablation`` inside the ``with`` block and give it its own
    back after it (``None``: its own throughout; a policy that is not spiking runs as it is under ``none``)::

        with ablated(model, "reset-every:50"):
            evaluate_policy(model, env)

    :return: the ablation in force inside the block.
    """
    ablation_in_force = check_ablation(model, ablation)
    policy = getattr(model, "policy", model)
    if ablation is None or not hasattr(type(policy), "ablation"):
        yield ablation_in_force
        return
    before = policy.ablation
    policy.ablation = ablation_in_force
    try:
        yield ablation_in_force
    finally:
        policy.ablation = before
