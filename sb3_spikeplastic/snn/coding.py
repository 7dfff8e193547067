"""Spike coding: population encoder with a replayable sampler, raster input, and action decoders.

* :class:`PopulationEncoder` — place-cell encoding of real observations (SpikePropamine appendix 5.2).
* :class:`RasterInput` — observations that already are spike rasters ``(T, n)`` pass straight through.
* :class:`ObservationStandardizer` — running standardisation of unbounded observation dimensions, so that they
  reach the encoder's range.
* :class:`ContinuousDecoder` / :class:`DiscreteDecoder` — output populations to actions (appendix 5.3, §3.1).

Randomness is replayable: Bernoulli spikes come from a counter-based hash of a per-environment 32-bit key and
the spike's index, never from a global RNG, so re-evaluating a stored step with the same key draws the same
spikes bit for bit (PPO re-evaluates every rollout step). The key advances by a Weyl increment each step.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from . import _fast

#: the place cells' exponent floor: exp(-87) ~ 1.6e-38 is still a normal float32
EXP_FLOOR = -87.0
#: the smallest ``p_min`` for which the floor is applied, well above exp(EXP_FLOOR) in any rounding
EXP_FLOOR_MIN_P = 1e-37

# Constants as signed int32 (products wrap modulo 2**32, which is what the hash needs).
_C1 = 0x7FEB352D
_C2 = 0x846CA68B - (1 << 32)
_WEYL = 0x9E3779B9 - (1 << 32)


def _as_int32(x: int) -> int:
    x &= 0xFFFFFFFF
    return x - (1 << 32) if x >= 1 << 31 else x


def hash32(x: Tensor) -> Tensor:
    """A 32-bit integer mixing function on int32 tensors (all 2**32 bit patterns are valid inputs).

    The multiply/xor-shift finaliser of Wellons' "lowbias32" (2018). int32 products wrap modulo 2**32; the
    right shifts are arithmetic in torch, so their sign-extended bits are masked off to make them logical.
    int32 rather than int64 because torch vectorises it: 10x faster on CPU (measured).
    """
    x = x ^ ((x >> 16) & 0xFFFF)
    x = x * _C1
    x = x ^ ((x >> 15) & 0x1FFFF)
    x = x * _C2
    return x ^ ((x >> 16) & 0xFFFF)


def advance_keys(keys: Tensor) -> Tensor:
    """The next step's per-environment keys (Weyl sequence modulo 2**32)."""
    return keys + _WEYL


def initial_keys(batch: int, seed: int = 0, device=None) -> Tensor:
    """Distinct deterministic int32 keys for ``batch`` environments derived from ``seed``."""
    base = hash32(torch.tensor(_as_int32(seed), dtype=torch.int32, device=device))
    return hash32(torch.arange(batch, dtype=torch.int32, device=device) + base)


class CounterBernoulli:
    """Bernoulli sampler driven by a counter-based hash: ``spike[b, t, i] = U(key_b, t, i) < p[b, i]``.

    ``U`` is 24 bits of ``hash32(hash32(t * n + i) ^ hash32(key_b))`` scaled to ``[0, 1)``; the hashes of the
    indices are cached per shape.
    """

    def __init__(self) -> None:
        self._index_hash: dict[tuple, Tensor] = {}

    def index_hash(self, steps: int, n: int, device) -> Tensor:
        """``hash32(t * n + i)`` of shape ``(steps, n)`` (cached per shape and device)."""
        cache_key = (steps, n, device)
        idx = self._index_hash.get(cache_key)
        if idx is None:
            idx = hash32(torch.arange(steps * n, dtype=torch.int32, device=device)).view(steps, n)
            self._index_hash[cache_key] = idx
        return idx

    def uniform(self, keys: Tensor, steps: int, n: int) -> Tensor:
        """Uniform variates of shape ``(batch, steps, n)`` for the given keys."""
        return _uniform(keys, self.index_hash(steps, n, keys.device))

    def sample(self, p: Tensor, keys: Tensor, steps: int) -> Tensor:
        """Spikes ``(batch, steps, n)`` with per-neuron probability ``p`` of shape ``(batch, n)``.

        On CPU the compiled sampler of :mod:`sb3_spikeplastic.snn._fast` (bit-identical, one pass), else eager."""
        return _fast.dispatch(
            _fast.BERNOULLI_SPIKES, _bernoulli_eager, p, keys, self.index_hash(steps, p.shape[-1], keys.device)
        )


def _uniform(keys: Tensor, index_hash: Tensor) -> Tensor:
    """:meth:`CounterBernoulli.uniform` from the cached index hashes ``(steps, n)``."""
    h = hash32(index_hash.unsqueeze(0) ^ hash32(keys).view(-1, 1, 1))
    return ((h >> 8) & 0xFFFFFF).to(torch.float32) * (1.0 / (1 << 24))


def _bernoulli_eager(p: Tensor, keys: Tensor, index_hash: Tensor) -> Tensor:
    """:meth:`CounterBernoulli.sample` in eager ops, with the compiled op's arguments
    (:data:`~._fast.BERNOULLI_SPIKES`)."""
    return (_uniform(keys, index_hash) < p.unsqueeze(1)).to(p.dtype)


class PopulationEncoder(nn.Module):
    """Place-cell population code for a real vector ``x`` of ``P`` dimensions (SpikePropamine appendix 5.2).

    Each dimension has ``pop_size`` cells with centres :math:`\\Omega` evenly spaced over ``[low, high]``; a cell
    fires at every network step with probability

    .. math:: p = \\mathrm{clip}(e^{-\\beta(\\Omega - x)^2}, \\vartheta_{min}, 1).

    :param low: lower bounds of the observation dimensions (finite).
    :param high: upper bounds of the observation dimensions (finite).
    :param pop_size: cells per dimension, :math:`P_{dim}` (paper: 50).
    :param beta: tuning-curve sharpness (paper: 15).
    :param p_min: floor probability :math:`\\vartheta_{min}` (paper: 0.05).
    :param indices: the observation dimensions to encode (``None``: all). ``low`` and ``high`` are those of the
        whole observation; the paper's HalfCheetah network encodes only the 12 joint angles and velocities.

    Each encoded value is clipped to its ``[low, high]`` before encoding, as the paper clips its measurements: a
    value beyond the bounds fires the edge cell instead of silencing its whole population.
    """

    def __init__(
        self,
        low: Sequence[float],
        high: Sequence[float],
        pop_size: int = 50,
        beta: float = 15.0,
        p_min: float = 0.05,
        indices: Optional[Sequence[int]] = None,
    ):
        super().__init__()
        low_t = torch.as_tensor(np.asarray(low, dtype=np.float64).reshape(-1))
        high_t = torch.as_tensor(np.asarray(high, dtype=np.float64).reshape(-1))
        if low_t.shape != high_t.shape:
            raise ValueError(f"encoder bounds differ in shape: low {tuple(low_t.shape)} vs high {tuple(high_t.shape)}")
        self.n_obs = low_t.numel()
        if indices is not None:
            indices = [int(i) for i in indices]
            bad = [i for i in indices if not 0 <= i < self.n_obs]
            if bad or not indices or len(set(indices)) != len(indices):
                raise ValueError(f"encoder indices {indices} must be distinct values in 0..{self.n_obs - 1}")
            self.register_buffer("indices", torch.tensor(indices, dtype=torch.long))
            low_t, high_t = low_t[indices], high_t[indices]
        else:
            self.indices = None
        if not (torch.isfinite(low_t).all() and torch.isfinite(high_t).all() and (high_t > low_t).all()):
            raise ValueError(
                f"encoder bounds must be finite with high > low, got low={low_t.tolist()} high={high_t.tolist()}"
            )
        if pop_size < 2:
            raise ValueError(f"pop_size must be at least 2, got {pop_size}")
        self.n_dims, self.pop_size, self.beta, self.p_min = low_t.numel(), int(pop_size), float(beta), float(p_min)
        frac = torch.linspace(0.0, 1.0, pop_size, dtype=torch.float64)
        centres = low_t[:, None] + (high_t - low_t)[:, None] * frac[None, :]
        self.register_buffer("centres", centres.to(torch.float32))
        self.register_buffer("low", low_t.to(torch.float32))
        self.register_buffer("high", high_t.to(torch.float32))
        self.sampler = CounterBernoulli()

    @property
    def n_neurons(self) -> int:
        return self.n_dims * self.pop_size

    def probabilities(self, x: Tensor) -> Tensor:
        """Firing probabilities ``(batch, P * pop_size)`` for observations ``(batch, n_obs)`` (the encoded ``P``
        dimensions are selected and clipped to their bounds)."""
        if self.indices is not None:
            x = x.index_select(-1, self.indices)
        return self._tuning(torch.maximum(torch.minimum(x, self.high), self.low))

    def _tuning(self, x: Tensor) -> Tensor:
        """The place cells' probabilities for values ``(batch, P)`` of the encoded dimensions.

        With ``p_min >= EXP_FLOOR_MIN_P`` the exponent is floored at :data:`EXP_FLOOR`: the cells far from ``x``
        (~40 % of them at the paper's beta = 15) would otherwise underflow, which the CPU's ``exp`` takes on a slow
        path (~70x: 245 against 3.5 us for the paper network's 32 x 600 cells), and they end at ``p_min`` either
        way, so the probabilities are bit-identical.
        """
        exponent = -self.beta * (self.centres - x.unsqueeze(-1)) ** 2
        if self.p_min >= EXP_FLOOR_MIN_P:
            exponent = exponent.clamp(min=EXP_FLOOR)
        return torch.exp(exponent).clamp(self.p_min, 1.0).flatten(1)

    def rms_rate(self) -> float:
        """Root-mean-square firing probability over cells, for ``x`` uniform within the bounds (for weight init)."""
        grid = self.centres[:, :1] + (self.centres[:, -1:] - self.centres[:, :1]) * torch.linspace(0, 1, 101)
        p = self._tuning(grid.T.contiguous())
        return float(p.pow(2).mean().sqrt())

    def forward(self, x: Tensor, keys: Tensor, steps: int) -> Tensor:
        """Input spikes ``(batch, steps, P * pop_size)`` for observations ``x`` and per-environment ``keys``."""
        return self.sampler.sample(self.probabilities(x), keys, steps)


class ObservationStandardizer(nn.Module):
    """Running standardisation ``clip((x - mean) / sqrt(var + eps), -clip, clip)`` of the observation dimensions
    selected by ``mask`` (the others pass unchanged), as ``VecNormalize`` does for observations.

    ``mean``, ``var`` and ``count`` are buffers: they are part of the policy's ``state_dict`` and so are saved and
    loaded with the model. They change only through :meth:`update` (the algorithm calls it with each rollout's
    observations once the rollout has been trained on), never in ``forward``: a rollout and its re-evaluation
    see the same statistics, and evaluation or ``predict`` leave them as they are. At the start (mean 0,
    variance 1) it is the identity, up to the clip.

    :param mask: ``True`` for each observation dimension to standardise (flattened observation).
    :param clip: bound of the standardised values (``VecNormalize``'s default ``clip_obs``).
    :param eps: added to the variance.
    """

    def __init__(self, mask: Sequence[bool], clip: float = 10.0, eps: float = 1e-8):
        super().__init__()
        mask_t = torch.as_tensor(np.asarray(mask, dtype=bool).reshape(-1))
        self.register_buffer("mask", mask_t, persistent=False)
        self.register_buffer("mean", torch.zeros(mask_t.shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(mask_t.shape, dtype=torch.float64))
        # As SB3's RunningMeanStd: a tiny prior count, so that the first update replaces the initial values.
        self.register_buffer("count", torch.tensor(1e-4, dtype=torch.float64))
        self.clip, self.eps = float(clip), float(eps)

    @property
    def active(self) -> bool:
        """Whether any dimension is standardised."""
        return bool(self.mask.any())

    def forward(self, obs: Tensor) -> Tensor:
        flat = obs.flatten(1)
        z = (flat - self.mean.to(flat.dtype)) / torch.sqrt(self.var.to(flat.dtype) + self.eps)
        z = z.clamp(-self.clip, self.clip)
        return torch.where(self.mask, z, flat).view(obs.shape)

    @torch.no_grad()
    def update(self, observations: Tensor) -> None:
        """Add a batch of observations ``(..., *obs_shape)`` to the running mean and variance (Chan et al.'s
        parallel update, as SB3's ``RunningMeanStd``)."""
        x = observations.reshape(-1, self.mask.numel()).to(self.mean.device, torch.float64)
        batch_mean, batch_var, n = x.mean(0), x.var(0, unbiased=False), x.shape[0]
        delta, total = batch_mean - self.mean, self.count + n
        m2 = self.var * self.count + batch_var * n + delta.square() * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        # Models saved before the standardiser existed have no statistics: they load with the identity ones.
        for name in ("mean", "var", "count"):
            state_dict.setdefault(prefix + name, getattr(self, name).clone())
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )

    def extra_repr(self) -> str:
        return f"dims={int(self.mask.sum())}/{self.mask.numel()}, clip={self.clip}, count={float(self.count):.0f}"


class RasterInput(nn.Module):
    """Observations that are spike rasters of shape ``(steps, n)`` (e.g. ``TMazeCue``) pass through unchanged.

    :param steps: raster length (network steps per environment step).
    :param n_neurons: input neurons.
    :param rms_rate: expected root-mean-square firing probability of the inputs (for weight init).
    """

    def __init__(self, steps: int, n_neurons: int, rms_rate: float = 0.25):
        super().__init__()
        self.steps, self.n_neurons, self._rms_rate = int(steps), int(n_neurons), float(rms_rate)

    def rms_rate(self) -> float:
        return self._rms_rate

    def forward(self, x: Tensor, keys: Tensor, steps: int) -> Tensor:
        if x.shape[1:] != (self.steps, self.n_neurons) or steps != self.steps:
            raise ValueError(
                f"spike-raster observation of shape {tuple(x.shape[1:])} does not match the network's "
                f"(T={self.steps}, n={self.n_neurons}) with T={steps}"
            )
        return x


def population_difference(rates: Tensor, n_groups: int) -> Tensor:
    """:math:`A_p = \\frac{2}{N}\\sum_n w_n r_n` per group with ``w = +1`` on the first half of each group of ``N``
    neurons and ``-1`` on the second: the mean rate of the first half minus that of the second, in ``[-1, 1]``."""
    grouped = rates.view(rates.shape[0], n_groups, -1)
    half = grouped.shape[-1] // 2
    return grouped[..., :half].mean(-1) - grouped[..., half:].mean(-1)


class ContinuousDecoder(nn.Module):
    """The paper's action population (appendix 5.3): per action dimension ``pop_size`` output neurons, weights
    ``+1`` for the first half and ``-1`` for the second,

    .. math:: A_p = \\frac{2}{N}\\frac{1}{T}\\sum_t\\sum_n w_n S_n(t) \\in [-1, 1],

    rescaled linearly to the action bounds ``[low, high]``.

    :param low: action lower bounds.
    :param high: action upper bounds.
    :param pop_size: neurons per action dimension, even (paper: 100).
    """

    def __init__(self, low: Sequence[float], high: Sequence[float], pop_size: int = 100):
        super().__init__()
        if pop_size < 2 or pop_size % 2:
            raise ValueError(f"the action population size must be even and >= 2, got {pop_size}")
        low_t = torch.as_tensor(np.asarray(low, dtype=np.float32).reshape(-1))
        high_t = torch.as_tensor(np.asarray(high, dtype=np.float32).reshape(-1))
        if not (torch.isfinite(low_t).all() and torch.isfinite(high_t).all()):
            raise ValueError(f"continuous actions need finite bounds, got low={low_t.tolist()} high={high_t.tolist()}")
        self.n_actions, self.pop_size = low_t.numel(), int(pop_size)
        self.register_buffer("centre", (high_t + low_t) / 2)
        self.register_buffer("half_range", (high_t - low_t) / 2)

    @property
    def n_neurons(self) -> int:
        return self.n_actions * self.pop_size

    def forward(self, rates: Tensor) -> Tensor:
        """Mean actions ``(batch, n_actions)`` from output rates ``(batch, n_actions * pop_size)``."""
        return self.centre + self.half_range * population_difference(rates, self.n_actions)


class DiscreteDecoder(nn.Module):
    """One output population per action; logits are the populations' mean rates times a learned scale
    (the paper uses the two output rates as log-odds, §3.1).

    :param n_actions: number of discrete actions.
    :param pop_size: neurons per action.
    :param logit_scale_init: initial scale (rates are spikes/ms, so the scale must be large for the rates to
        matter: 20 worked on the T-maze).
    """

    def __init__(self, n_actions: int, pop_size: int = 1, logit_scale_init: float = 20.0):
        super().__init__()
        if pop_size < 1:
            raise ValueError(f"pop_size must be >= 1, got {pop_size}")
        self.n_actions, self.pop_size = int(n_actions), int(pop_size)
        self.logit_scale = nn.Parameter(torch.tensor(float(logit_scale_init)))

    @property
    def n_neurons(self) -> int:
        return self.n_actions * self.pop_size

    def forward(self, rates: Tensor) -> Tensor:
        """Logits ``(batch, n_actions)`` from output rates ``(batch, n_actions * pop_size)``."""
        return self.logit_scale * rates.view(rates.shape[0], self.n_actions, self.pop_size).mean(-1)
