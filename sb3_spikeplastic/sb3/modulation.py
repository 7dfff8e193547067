"""Neuromodulation from outside the network: the signals a policy computes at act time for rules whose
``modulation_source`` is not ``"learned"`` (the third factor of three-factor plasticity).

SpikePropamine's discussion proposes "a pre-defined global signal ... an online reward signal emulating
dopaminergic neurons, error signals from a control system, or a novelty signal" in place of the learned
:math:`M = W_m r_{post}`; Backpropamine (Miconi et al., 2019) trains such reward-modulated plasticity by gradient
descent. A source maps a sequence of observations (and its own per-environment state, carried in
:attr:`~sb3_spikeplastic.snn.network.NetworkState.source`) to one signal per environment step, which every plastic
layer's rule reads through its learned gains (:func:`~sb3_spikeplastic.snn.plasticity.external_modulatory_signal`).

The reward reaches the policy through the observation, so that SB3's API and its rollout buffer need no change and
PPO recomputes every signal of a chunk exactly: :class:`RewardInput` says where it is (the
:class:`~sb3_spikeplastic.envs.PreviousReward` wrapper's element, or a spike-raster environment's outcome
populations), and the environments that carry it declare it as their ``reward_input`` attribute.

Sources of one's own subclass :class:`ModulationSource` and register with :func:`register_modulation_source`
(``docs/neuromodulation.md`` has a novelty signal as the worked example).
"""

from __future__ import annotations

from typing import Any, Callable, ClassVar, NamedTuple, Optional, Sequence, Union

import numpy as np
import torch
from gymnasium import spaces
from torch import Tensor

from ..snn.plasticity import LEARNED_SOURCE

__all__ = [
    "MODULATION_SOURCES",
    "ModulationSource",
    "RewardInput",
    "RewardSource",
    "TDErrorSource",
    "available_modulation_sources",
    "get_modulation_source",
    "read_reward",
    "register_modulation_source",
]


class RewardInput(NamedTuple):
    """Where the previous step's reward is in an observation:
    ``scale * (mean(obs[..., positive]) - mean(obs[..., negative])) + offset``.

    For a vector observation the indices are elements (:class:`~sb3_spikeplastic.envs.PreviousReward`: the one
    element it appends); for a spike raster ``(T, n)`` they are neurons, and the means run over the raster's steps
    too (``TMazeReversal-v0``: its reward and no-reward populations, scaled so that the expected value is the reward
    the previous trial paid).

    :param positive: indices whose mean counts positively.
    :param negative: indices whose mean is subtracted (none: nothing).
    :param scale: the factor on the difference.
    :param offset: added after scaling.
    """

    positive: tuple[int, ...]
    negative: tuple[int, ...] = ()
    scale: float = 1.0
    offset: float = 0.0

    @classmethod
    def parse(cls, value: Union["RewardInput", dict, int, Sequence[int]], space: spaces.Box) -> "RewardInput":
        """A ``RewardInput`` from itself, a dict of its fields, one index or a list of indices, checked against the
        observation ``space`` (one-line errors naming the bad value)."""
        if isinstance(value, RewardInput):
            parsed = value
        elif isinstance(value, dict):
            unknown = sorted(set(value) - set(cls._fields))
            if unknown:
                raise ValueError(f"reward_input keys {unknown} unknown; accepted: {', '.join(cls._fields)}")
            if "positive" not in value:
                raise ValueError(f"reward_input={value!r} needs 'positive' (the indices that carry the reward)")
            parsed = cls(**value)
        elif isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            parsed = cls((int(value),))
        elif isinstance(value, (list, tuple)):
            parsed = cls(tuple(value))
        else:
            raise ValueError(f"reward_input={value!r} must be an index, a list of indices or a dict of {cls._fields}")
        size = int(space.shape[-1])
        indices = []
        for name in ("positive", "negative"):
            given = getattr(parsed, name)
            if isinstance(given, (int, np.integer)):
                given = (given,)
            given = tuple(int(i) for i in given)
            bad = [i for i in given if not -size <= i < size]
            if bad:
                raise ValueError(f"reward_input {name} indices {bad} out of range for observations of size {size}")
            indices.append(tuple(i % size for i in given))
        if not indices[0]:
            raise ValueError("reward_input needs at least one positive index")
        return cls(indices[0], indices[1], float(parsed.scale), float(parsed.offset))

    def as_dict(self) -> dict[str, Any]:
        """The fields as plain Python values (what a saved model records)."""
        return {
            "positive": list(self.positive),
            "negative": list(self.negative),
            "scale": self.scale,
            "offset": self.offset,
        }


def read_reward(reward_input: RewardInput, obs: Tensor, raster: bool) -> Tensor:
    """The reward that ``reward_input`` reads from observations ``(..., n)`` (``raster``: ``(..., T, n)``, averaged
    over ``T`` too), shape ``(...)``."""
    positive = obs[..., list(reward_input.positive)]
    value = positive.mean(-1)
    if reward_input.negative:
        value = value - obs[..., list(reward_input.negative)].mean(-1)
    if raster:
        value = value.mean(-1)
    return value * reward_input.scale + reward_input.offset


class ModulationSource:
    """A signal from outside the network for the plastic layers' rules, computed by the policy at act time.

    Subclasses set :attr:`channels` (the signal's size per environment), :attr:`state_size` (what they carry from
    step to step, e.g. the previous value; 0 for none) and :attr:`needs_reward`, and implement :meth:`sequence`.

    :param observation_space: the policy's observation space.
    :param reward_input: where the observation carries the previous reward (``None`` where none does).
    :param kwargs: the source's own settings (the policy's ``modulation_kwargs``).
    """

    name: ClassVar[str] = ""
    #: the signal's channels per environment (the rules' ``modulation_channels``)
    channels: ClassVar[int] = 1
    #: the per-environment state carried from step to step (:attr:`NetworkState.source`), 0: none
    state_size: ClassVar[int] = 0
    #: whether the source reads the previous reward from the observation
    needs_reward: ClassVar[bool] = False
    #: whether the source reads the policy's value of the observation (``critic="mlp"``)
    needs_observation_value: ClassVar[bool] = False

    def __init__(self, observation_space: spaces.Box, reward_input: Optional[RewardInput], **kwargs: Any):
        if kwargs:
            raise ValueError(f"modulation_kwargs {sorted(kwargs)} unknown to modulation_source {self.name!r}")
        self.observation_space = observation_space
        self.reward_input = reward_input
        self.raster = len(observation_space.shape) == 2

    def initial_state(self, batch: int, device=None) -> Tensor:
        """The state at episode start: zeros ``(batch, state_size)``."""
        return torch.zeros(batch, self.state_size, device=device)

    def reward(self, obs: Tensor) -> Tensor:
        """The previous reward carried by observations ``(L, batch, ...)``: ``(L, batch)``."""
        return read_reward(self.reward_input, obs, self.raster)

    def sequence(self, obs: Tensor, episode_starts: Tensor, state: Tensor, policy: Any) -> tuple[Tensor, Tensor]:
        """The signal of each step of a sequence, and the state after it.

        :param obs: the policy's (preprocessed) observations ``(L, batch, ...)``.
        :param episode_starts: ``(L, batch)``, 1 where an episode starts: the state is zero there before the step.
        :param state: the state before the first step ``(batch, state_size)``.
        :param policy: the policy (its critic, for :attr:`needs_observation_value`).
        :return: ``(signals (L, batch, channels), state (batch, state_size))``.
        """
        raise NotImplementedError


MODULATION_SOURCES: dict[str, type[ModulationSource]] = {}


def register_modulation_source(
    name: str, *, override: bool = False
) -> Callable[[type[ModulationSource]], type[ModulationSource]]:
    """Class decorator that registers a :class:`ModulationSource` under ``name``, accepted as
    ``rule_kwargs=dict(modulation_source=name)``.

    :param name: the source's name (not ``"learned"``).
    :param override: allow replacing an existing registration.
    """

    def decorator(cls: type[ModulationSource]) -> type[ModulationSource]:
        if not (isinstance(cls, type) and issubclass(cls, ModulationSource)):
            raise TypeError(f"register_modulation_source({name!r}) expects a ModulationSource subclass, got {cls!r}")
        if name == LEARNED_SOURCE or (name in MODULATION_SOURCES and not override):
            raise ValueError(f"modulation source {name!r} is already registered (pass override=True to replace it)")
        cls.name = name
        MODULATION_SOURCES[name] = cls
        return cls

    return decorator


def available_modulation_sources() -> tuple[str, ...]:
    """Every accepted ``modulation_source``: ``"learned"`` and the registered sources."""
    return (LEARNED_SOURCE, *MODULATION_SOURCES)


def get_modulation_source(name: str) -> type[ModulationSource]:
    """The source class registered as ``name``; an unknown name is a one-line error listing the accepted ones."""
    try:
        return MODULATION_SOURCES[name]
    except KeyError:
        raise ValueError(
            f"unknown modulation_source {name!r}; accepted: {', '.join(available_modulation_sources())}"
        ) from None


@register_modulation_source("reward")
class RewardSource(ModulationSource):
    """:math:`m_t = r_{t-1}`, the reward the previous step paid, as the observation carries it (0 at an episode's
    first step: :class:`~sb3_spikeplastic.envs.PreviousReward` appends 0 after ``reset``)."""

    needs_reward = True

    def sequence(self, obs, episode_starts, state, policy):
        return self.reward(obs).unsqueeze(-1), state


@register_modulation_source("td-error")
class TDErrorSource(ModulationSource):
    r"""The temporal-difference error of the previous step, with the policy's own critic:
    :math:`m_t = \delta_{t-1} = r_{t-1} + \gamma V(o_t) - V(o_{t-1})` (Schultz et al., 1997: dopamine neurons signal
    a reward prediction error). The value of ``o_t`` must be known before the network runs on it, so the critic must
    read the observation (``critic="mlp"``); the error carries no gradient into the critic. It is 0 at an episode's
    first step (there is no previous value); the reward of an episode's last step is never seen (its next
    observation belongs to the next episode). State: ``(V(o_{t-1}), 1 once a value is held)``.

    :param gamma: the discount :math:`\gamma`; ``None``: :class:`sb3_spikeplastic.PPO` passes its own ``gamma``
        (0.99 elsewhere).
    """

    needs_reward = True
    needs_observation_value = True
    state_size = 2

    def __init__(self, observation_space, reward_input, gamma: Optional[float] = None):
        super().__init__(observation_space, reward_input)
        gamma = 0.99 if gamma is None else gamma
        if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not 0.0 <= gamma <= 1.0:
            raise ValueError(f"modulation_kwargs gamma={gamma!r} must lie in [0, 1]")
        self.gamma = float(gamma)

    def sequence(self, obs, episode_starts, state, policy):
        length, batch = obs.shape[:2]
        with torch.no_grad():
            values = policy.observation_value(obs.flatten(0, 1)).view(length, batch)
        keep = 1.0 - episode_starts.to(values.dtype)
        # Step k's previous value and whether it exists: the state's before the first step, then the sequence's own.
        previous = torch.cat([state[:, 0].unsqueeze(0), values[:-1]]) * keep
        held = torch.cat([state[:, 1].unsqueeze(0), torch.ones_like(values[:-1])]) * keep
        delta = held * (self.reward(obs) + self.gamma * values - previous)
        return delta.unsqueeze(-1), torch.stack([values[-1], torch.ones_like(values[-1])], -1)
