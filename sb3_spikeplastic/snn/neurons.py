"""Spike Response Model (SRM) neurons with recursive alpha kernels and the SLAYER surrogate gradient.

The neuron is SLAYER's ``SRMALPHA`` (Shrestha & Orchard, *SLAYER: Spike Layer Error Reassignment in Time*,
NeurIPS 2018) as used by SpikePropamine (Schmidgall et al. 2021, §2.1 and appendix 5.5), in discrete time with
step ``dt``:

.. math::
    a(t) = (\\varepsilon * s_{in})(t), \\qquad
    \\varepsilon(k) = \\frac{k\\,dt}{\\tau_s} e^{1 - k\\,dt/\\tau_s}

    u(t) = W a(t) + (\\nu * s)(t), \\qquad
    \\nu(k) = -\\mathrm{scale_{ref}}\\,\\vartheta\\,\\frac{k\\,dt}{\\tau_{ref}} e^{1 - k\\,dt/\\tau_{ref}}

    s(t) = H(u(t) - \\vartheta)

Both kernels vanish at ``k = 0``: an input spike reaches the membrane one step later and a neuron's own spike
starts its refractory response on the next step. There is no hard reset; the refractory kernel is the reset.

The kernels are infinite, so they are computed recursively. For :math:`d = e^{-dt/\\tau}` and
:math:`c = e\\,dt/\\tau`, the kernel is :math:`\\varepsilon(k) = c\\,k\\,d^k` and two cascaded exponential filters

.. math::
    h_1(t) = d\\,h_1(t-1) + s(t), \\qquad h_2(t) = d\\,(h_2(t-1) + h_1(t-1)), \\qquad (\\varepsilon * s)(t) = c\\,h_2(t)

reproduce it exactly, so the state carried between environment steps is two numbers per neuron and kernel.
Within an interval of ``L`` steps the same recursion is a linear map of the interval's spikes and the carried
state (:func:`alpha_filter_operator`), which lets a layer filter a whole interval with one matrix product.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from . import _fast


class SRMParameters(NamedTuple):
    """Constants of the SRM-alpha neuron (SpikePropamine appendix 5.5 defaults).

    :param theta: firing threshold :math:`\\vartheta` (mV).
    :param tau_s: PSP (alpha kernel) time constant (ms).
    :param tau_ref: refractory kernel time constant (ms).
    :param scale_ref: relative refractory response scaling.
    :param tau_rho: surrogate-gradient width, in units of ``theta``.
    :param scale_rho: surrogate-gradient height scale.
    :param dt: network integration step (ms).
    """

    theta: float = 10.0
    tau_s: float = 10.0
    tau_ref: float = 2.0
    scale_ref: float = 2.0
    tau_rho: float = 1.0
    scale_rho: float = 1.0
    dt: float = 1.0


class AlphaFilterState(NamedTuple):
    """State of the two cascaded exponential filters behind an alpha kernel, each of shape ``(batch, n)``."""

    h1: Tensor
    h2: Tensor


def alpha_kernel_sum(tau: float, dt: float = 1.0) -> float:
    """:math:`\\sum_{k\\ge0} \\varepsilon(k)`, the PSP area of one spike (about ``e * tau / dt``); scales initial
    weights."""
    d, c = _decay_and_gain(tau, dt)
    return c * d / (1 - d) ** 2


def _decay_and_gain(tau: float, dt: float) -> tuple[float, float]:
    return math.exp(-dt / tau), math.e * dt / tau


def alpha_filter_step(
    s: Tensor, state: AlphaFilterState, tau: float, dt: float = 1.0
) -> tuple[Tensor, AlphaFilterState]:
    """Advance the alpha filter by one step with input spikes ``s``; returns ``(psp, new_state)``.

    ``psp`` at step ``t`` depends on spikes up to ``t - 1`` only (the kernel is 0 at lag 0).
    """
    d, c = _decay_and_gain(tau, dt)
    h2 = d * (state.h2 + state.h1)
    h1 = d * state.h1 + s
    return c * h2, AlphaFilterState(h1, h2)


def alpha_filter_matrices(length: int, tau: float, dt: float = 1.0, dtype=torch.float32, device=None):
    """Matrices that run the alpha filter over ``length`` steps as linear maps.

    For spikes ``S`` of shape ``(..., length, n)`` (time on the second-to-last axis) and a carried state
    ``(h1, h2)`` from before the interval:

    * ``psp = K @ S + g1[:, None] * h1 + g2[:, None] * h2`` (``K`` strictly lower-triangular Toeplitz,
      ``K[t, t'] = eps(t - t')``),
    * ``h1_end = v1 @ S + d**length * h1`` and ``h2_end = v2 @ S + d**length * (h2 + length * h1)``.

    :return: ``(K, g1, g2, v1, v2, d_len)`` with ``d_len = d**length``.
    """
    d, c = _decay_and_gain(tau, dt)
    t = torch.arange(length, dtype=torch.float64)
    lag = t[:, None] - t[None, :]
    kernel = torch.where(lag > 0, c * lag * d**lag, torch.zeros(()))
    g1 = c * (t + 1) * d ** (t + 1)
    g2 = c * d ** (t + 1)
    v1 = d ** (length - 1 - t)
    v2 = (length - 1 - t) * d ** (length - 1 - t)
    out = [x.to(dtype=dtype, device=device) for x in (kernel, g1, g2, v1, v2)]
    return (*out, d**length)


def alpha_filter_operator(length: int, tau: float, dt: float = 1.0, dtype=torch.float32, device=None) -> Tensor:
    """The alpha filter over an interval of ``length`` steps as one ``(length + 2, length + 2)`` matrix ``M``.

    For rows ``X = [S; h1; h2]`` (the interval's spikes ``(..., length, n)``, then the carried state's ``h1`` and
    ``h2`` as two more rows), ``M @ X = [psp; h1_end; h2_end]``: the PSP of every step, then the state carried into
    the next interval (the maps of :func:`alpha_filter_matrices` in one block matrix, so that a layer filters an
    interval, carried state included, with one matrix product).
    """
    kernel, g1, g2, v1, v2, d_len = alpha_filter_matrices(length, tau, dt, torch.float64)
    op = torch.zeros(length + 2, length + 2, dtype=torch.float64)
    op[:length, :length], op[:length, length], op[:length, length + 1] = kernel, g1, g2
    op[length, :length], op[length, length] = v1, d_len
    op[length + 1, :length], op[length + 1, length], op[length + 1, length + 1] = v2, length * d_len, d_len
    return op.to(dtype=dtype, device=device)


def alpha_filter_interval(spikes: Tensor, state: AlphaFilterState, operator: Tensor) -> tuple[Tensor, AlphaFilterState]:
    """Filter an interval of spikes ``(batch, length, n)`` with the carried state; returns ``(psp, new_state)``.

    Equal to ``length`` calls of :func:`alpha_filter_step` (tested); ``operator`` is :func:`alpha_filter_operator`.
    """
    length = spikes.shape[-2]
    out = operator @ torch.cat([spikes, state.h1.unsqueeze(-2), state.h2.unsqueeze(-2)], -2)
    return out[..., :length, :], AlphaFilterState(out[..., length, :], out[..., length + 1, :])


def slayer_surrogate(u: Tensor, params: SRMParameters) -> Tensor:
    """SLAYER's spike-function derivative used as surrogate gradient.

    .. math::
        \\frac{\\partial s}{\\partial u} \\approx \\frac{\\mathrm{scale}_\\rho}{\\tau_\\rho \\vartheta}
        \\exp\\left(-\\frac{|u - \\vartheta|}{\\tau_\\rho \\vartheta}\\right)
    """
    width = params.tau_rho * params.theta
    # In place after the first op: one buffer instead of five (each a fresh allocation of the membrane's size).
    # Dividing by -width rounds exactly as negating and dividing by width.
    return torch.sub(u, params.theta).abs_().div_(-width).exp_().mul_(params.scale_rho / width)


class SLAYERSpike(torch.autograd.Function):
    """Heaviside spike with the SLAYER surrogate gradient.

    Forward: :math:`s = H(u - \\vartheta)` (1 where ``u >= theta``).
    Backward: :math:`\\partial L/\\partial u = \\partial L/\\partial s \\cdot` :func:`slayer_surrogate` ``(u)``.
    """

    @staticmethod
    def forward(ctx, u: Tensor, params: SRMParameters) -> Tensor:
        ctx.save_for_backward(u)
        ctx.params = params
        return (u >= params.theta).to(u.dtype)

    @staticmethod
    def backward(ctx, grad_s: Tensor):
        (u,) = ctx.saved_tensors
        return grad_s * slayer_surrogate(u, ctx.params), None


def spike_constants(params: SRMParameters) -> tuple[float, float, float, float, float]:
    """``(d, kappa, theta, width, scale)``: the refractory filter's decay ``d`` and gain ``kappa`` (as
    :func:`srm_spike_loop` uses them) and the surrogate's ``theta``, ``width`` and ``scale`` (as
    :func:`slayer_surrogate`), for compiled code that runs both."""
    d, c = _decay_and_gain(params.tau_ref, params.dt)
    return d, params.scale_ref * params.theta * c, params.theta, params.tau_rho * params.theta, params.scale_rho


def srm_spike_loop(
    synaptic: Tensor, state: AlphaFilterState, params: SRMParameters
) -> tuple[Tensor, Tensor, AlphaFilterState]:
    """Run the threshold/refractory recursion over an interval of synaptic input ``(batch, length, n)``.

    ``state`` holds the refractory filter (``h1``, ``h2``) of the layer's own spikes. Returns
    ``(spikes, membrane, new_state)``, all without autograd (see :class:`SRMSpikeRecursion`).

    On CPU (float32/float64) and CUDA this runs the compiled loop of :mod:`sb3_spikeplastic.snn._fast`, built on
    first use; elsewhere, with ``SB3_SPIKEPLASTIC_NO_COMPILE=1``, or if the build failed (one warning), the eager
    loop (:func:`_srm_spike_loop_reference`). Both give bit-identical spikes, membrane and state.
    """
    d, kappa, *_ = spike_constants(params)
    out = _fast.dispatch(_fast.SRM_LOOP, _srm_loop_eager, synaptic, state.h1, state.h2, d, kappa, params.theta)
    return out.spikes, out.membrane, AlphaFilterState(out.h1, out.h2)


def _srm_spike_loop_reference(
    synaptic: Tensor, state: AlphaFilterState, params: SRMParameters
) -> tuple[Tensor, Tensor, AlphaFilterState]:
    """Pure-PyTorch :func:`srm_spike_loop`: the fallback (any device) and the specification of the fast path."""
    d, kappa, *_ = spike_constants(params)
    out = _srm_loop_eager(synaptic, state.h1, state.h2, d, kappa, params.theta)
    return out.spikes, out.membrane, AlphaFilterState(out.h1, out.h2)


def _srm_loop_eager(
    synaptic: Tensor, h1: Tensor, h2: Tensor, d: float, kappa: float, theta: float
) -> _fast.SpikeLoopOutputs:
    """The recursion in eager PyTorch, with the compiled op's arguments and outputs (:data:`~._fast.SRM_LOOP`).

    Per step, in the tensors' dtype: ``h2 = (h2 + h1) * d``, ``u = syn - h2 * kappa``, ``s = (u >= theta)``,
    ``h1 = h1 * d + s``, every operation rounded separately. ``u`` is deliberately two ops rather than
    ``torch.sub(syn, h2, alpha=kappa)``, which PyTorch's vectorised CPU kernels evaluate with a fused
    multiply-add (depending on the CPU capability), so its rounding cannot be reproduced portably.
    """
    h1, h2 = h1.clone(), h2.clone()
    spikes = torch.empty_like(synaptic)
    membrane = torch.empty_like(synaptic)
    # In-place ops on preallocated slices (~1.5x over fresh tensors when this loop is the hot path).
    for t in range(synaptic.shape[-2]):
        h2.add_(h1).mul_(d)
        u = membrane[:, t]
        torch.mul(h2, kappa, out=u)
        torch.sub(synaptic[:, t], u, out=u)
        s = spikes[:, t]
        torch.ge(u, theta, out=s)
        h1.mul_(d).add_(s)
    return _fast.SpikeLoopOutputs(spikes, membrane, h1, h2)


class SRMSpikeRecursion(torch.autograd.Function):
    """Spikes of an SRM layer over an interval, differentiable with respect to its synaptic input.

    Forward: :func:`srm_spike_loop`. Backward: as in SLAYER, the refractory feedback (a neuron's own spikes
    back into its membrane) is not differentiated, so :math:`\\partial s(t)/\\partial u_{syn}(t') = 0` for
    :math:`t' \\ne t` and the gradient is element-wise,

    .. math::
        \\frac{\\partial L}{\\partial u_{syn}(t)} = \\frac{\\partial L}{\\partial s(t)}\\,\\rho(u(t)).

    Differentiating the refractory path multiplies gradients by up to ~12 per step and overflows at T = 50.
    """

    @staticmethod
    def forward(ctx, synaptic: Tensor, h1: Tensor, h2: Tensor, params: SRMParameters):
        spikes, membrane, new_state = srm_spike_loop(synaptic, AlphaFilterState(h1, h2), params)
        # Rollouts run under no_grad: computing the surrogate there was the layer's main cost (measured 8x at B=64).
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(slayer_surrogate(membrane, params))
        ctx.mark_non_differentiable(new_state.h1, new_state.h2)
        return spikes, membrane, new_state.h1, new_state.h2

    @staticmethod
    def backward(ctx, grad_spikes, grad_membrane, _grad_h1, _grad_h2):
        (surrogate,) = ctx.saved_tensors
        return grad_spikes * surrogate, None, None, None


def srm_spikes(
    synaptic: Tensor, state: AlphaFilterState, params: SRMParameters
) -> tuple[Tensor, Tensor, AlphaFilterState]:
    """Differentiable :func:`srm_spike_loop`: returns ``(spikes, membrane, new_refractory_state)``.

    The membrane output carries no gradient; it is returned for monitoring and figures.
    """
    spikes, membrane, h1, h2 = SRMSpikeRecursion.apply(synaptic, state.h1, state.h2, params)
    return spikes, membrane.detach(), AlphaFilterState(h1, h2)
