"""The compiled tensor ops as :func:`sb3_spikeplastic.snn._fast.dispatch` runs them: for each a :class:`Kernel`
(which operands it takes, how it runs them) and NamedTuples of its outputs, named as the op's schema names them.

A kernel's ``run`` takes the compiled namespace as its first argument, so that this module never loads the library
itself: :mod:`sb3_spikeplastic.snn._fast` decides whether a compiled op runs at all.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import torch
from torch import Tensor

__all__ = [
    "BERNOULLI_SPIKES",
    "Kernel",
    "PLASTIC_LINEAR",
    "ProductGradients",
    "ProductOutputs",
    "SRM_LOOP",
    "SpikeLoopOutputs",
    "TRACE_STEP",
    "TraceStepGradients",
    "TraceStepOutputs",
    "cpu_float_operands",
]


class Kernel(NamedTuple):
    """A compiled op as :func:`~sb3_spikeplastic.snn._fast.dispatch` runs it.

    :param name: the op's name in the compiled library.
    :param applies: ``applies(*operands)``: whether the compiled op takes these operands (dtypes, devices, shapes).
    :param run: ``run(ops, *operands)``: the op's result from the compiled namespace ``ops``, as the eager code that
        stands in for it returns it.
    :param cuda: whether it also runs on CUDA tensors (then from the CUDA library, by the first operand's device).
    """

    name: str
    applies: Callable[..., bool]
    run: Callable[..., Any]
    cuda: bool = False


def cpu_float_operands(first: Tensor, *others: Tensor) -> bool:
    """Whether ``first`` is a CPU float32/float64 tensor and ``others`` are CPU tensors of its dtype (what every
    compiled op needs besides its shapes)."""
    dtype = first.dtype
    if not (first.is_cpu and (dtype is torch.float32 or dtype is torch.float64)):
        return False
    for t in others:
        if t.dtype is not dtype or not t.is_cpu:
            return False
    return True


# --- srm_loop (srm_loop.cpp, srm_loop_cuda.cu) -------------------------------------------------------------------


class SpikeLoopOutputs(NamedTuple):
    """``srm_loop``'s outputs: spikes and membrane ``(batch, L, n)``, the refractory state ``h1, h2`` ``(batch, n)``."""

    spikes: Tensor
    membrane: Tensor
    h1: Tensor
    h2: Tensor


def _srm_loop_applies(synaptic: Tensor, h1: Tensor, h2: Tensor, d: float, kappa: float, theta: float) -> bool:
    """float32/float64 ``synaptic (batch, L, n)`` and ``h1, h2 (batch, n)`` of one dtype, all on the CPU or all on
    one CUDA device."""
    if not (synaptic.dim() == 3 and h1.shape == h2.shape == (synaptic.shape[0], synaptic.shape[2])):
        return False
    if synaptic.is_cuda:
        return synaptic.dtype in (torch.float32, torch.float64) and all(
            t.dtype is synaptic.dtype and t.device == synaptic.device for t in (h1, h2)
        )
    return cpu_float_operands(synaptic, h1, h2)


def _run_srm_loop(
    ops: Any, synaptic: Tensor, h1: Tensor, h2: Tensor, d: float, kappa: float, theta: float
) -> SpikeLoopOutputs:
    with torch.no_grad():
        return SpikeLoopOutputs._make(ops.srm_loop(synaptic, h1, h2, d, kappa, theta))


#: :func:`sb3_spikeplastic.snn.neurons.srm_spike_loop`'s recursion; no autograd (:class:`SpikeLoopOutputs`)
SRM_LOOP = Kernel("srm_loop", _srm_loop_applies, _run_srm_loop, cuda=True)


# --- trace_step (trace_step.cpp) ---------------------------------------------------------------------------------


class TraceStepOutputs(NamedTuple):
    """``trace_step_forward``'s outputs: the new trace and ``p = post - [E pre]`` (kept for the backward pass)."""

    trace: Tensor
    p: Tensor


class TraceStepGradients(NamedTuple):
    """``trace_step_backward``'s outputs: the gradient of each of ``trace_step_forward``'s tensors, named as it."""

    E: Tensor
    post: Tensor
    pre: Tensor
    eta: Tensor


class _TraceStep(torch.autograd.Function):
    """``clamp((1-eta) E + (eta p) (x) pre, +-e_max)`` with ``p = post - [E pre]``, fused (see ``trace_step.cpp``).

    Forward: one pass over ``E``. Backward: one pass over ``E`` and the incoming gradient, recomputing the clip
    mask instead of storing the pre-clip trace; returns the gradients of ``E``, ``post``, ``pre`` and ``eta``.
    """

    @staticmethod
    def forward(ctx, ops, E: Tensor, post: Tensor, pre: Tensor, eta: Tensor, e_max: float, oja: bool) -> Tensor:
        eta_value = float(eta)
        out = TraceStepOutputs._make(ops.trace_step_forward(E, post, pre, eta_value, e_max, oja))
        ctx.save_for_backward(E, out.p, pre)
        ctx.ops, ctx.eta_value, ctx.e_max, ctx.oja = ops, eta_value, e_max, oja
        ctx.eta_shape, ctx.eta_dtype = eta.shape, eta.dtype
        return out.trace

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        E, p, pre = ctx.saved_tensors
        d = TraceStepGradients._make(ctx.ops.trace_step_backward(grad, E, p, pre, ctx.eta_value, ctx.e_max, ctx.oja))
        return None, d.E, d.post, d.pre, d.eta.to(ctx.eta_dtype).reshape(ctx.eta_shape), None, None


def _trace_step_applies(E: Tensor, post: Tensor, pre: Tensor, eta: Tensor, e_max: float, oja: bool) -> bool:
    """CPU float32/float64 ``E (B, n_out, n_in)``, ``post (B, n_out)``, ``pre (B, n_in)`` and a one-element ``eta``
    of one dtype."""
    return (
        cpu_float_operands(E, post, pre)
        and eta.dtype is E.dtype
        and eta.numel() == 1
        and E.dim() == 3
        and post.shape == E.shape[:2]
        and pre.shape == (E.shape[0], E.shape[2])
    )


def _run_trace_step(ops: Any, E: Tensor, post: Tensor, pre: Tensor, eta: Tensor, e_max: float, oja: bool) -> Tensor:
    return _TraceStep.apply(ops, E, post, pre, eta, float(e_max), bool(oja))


#: :func:`sb3_spikeplastic.snn.plasticity.hebbian_trace_step`'s update and clip; differentiable once
TRACE_STEP = Kernel("trace_step", _trace_step_applies, _run_trace_step)


# --- plastic_linear (plastic_linear.cpp) -------------------------------------------------------------------------


class ProductOutputs(NamedTuple):
    """``plastic_linear_forward``'s outputs: the product of the rows and that of the carried rows (empty without)."""

    Y: Tensor
    Y_carried: Tensor


class ProductGradients(NamedTuple):
    """``plastic_linear_backward``'s outputs: the gradient of each of its forward tensors, named as it."""

    X: Tensor
    W: Tensor
    alpha: Tensor
    E: Tensor
    carried: Tensor


class _PlasticLinear(torch.autograd.Function):
    """``X[b] (W + alpha * E[b])^T`` per environment, and the same product of the rows ``C[b]`` carried beside ``X``
    (when given: a layer's PSP state), the efficacy of a few environments at a time, blocks split between torch's
    threads (see ``plastic_linear.cpp``); the gradients of ``X`` and ``C`` are computed only when needed."""

    @staticmethod
    def forward(ctx, ops, x: Tensor, weight: Tensor, alpha: Tensor, E: Tensor, carried: Optional[Tensor]):
        ctx.save_for_backward(x, weight, alpha, E, carried)
        ctx.ops = ops
        ctx.set_materialize_grads(False)  # an unused output's gradient is read as zero, not filled with it
        out = ProductOutputs._make(ops.plastic_linear_forward(x, weight, alpha, E, carried))
        if carried is None:
            ctx.mark_non_differentiable(out.Y_carried)
        return out.Y, out.Y_carried

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Optional[Tensor], grad_carried: Optional[Tensor]):
        x, weight, alpha, E, carried = ctx.saved_tensors
        _, need_x, _, _, _, need_carried = ctx.needs_input_grad
        if grad is None:
            grad = x.new_zeros(x.shape[0], x.shape[1], weight.shape[0])
        d = ProductGradients._make(
            ctx.ops.plastic_linear_backward(grad, grad_carried, x, weight, alpha, E, carried, need_x or need_carried)
        )
        return None, d.X if need_x else None, d.W, d.alpha, d.E, d.carried if need_carried else None


def _plastic_linear_applies(
    x: Tensor, weight: Tensor, alpha: Optional[Tensor], E: Tensor, carried: Optional[Tensor] = None
) -> bool:
    """CPU float32/float64 ``x (B, L, n_in)``, ``W, alpha (n_out, n_in)``, ``E (B, n_out, n_in)`` and
    ``carried (B, 2, n_in)`` (when given) of one dtype."""
    return (
        alpha is not None
        and cpu_float_operands(E, x, weight, alpha, *([] if carried is None else [carried]))
        and E.dim() == 3
        and x.dim() == 3
        and weight.shape == alpha.shape == E.shape[1:]
        and x.shape[0] == E.shape[0]
        and x.shape[2] == E.shape[2]
        and (carried is None or carried.shape == (x.shape[0], 2, x.shape[2]))
    )


def _run_plastic_linear(
    ops: Any, x: Tensor, weight: Tensor, alpha: Tensor, E: Tensor, carried: Optional[Tensor] = None
) -> Tensor:
    out = ProductOutputs._make(_PlasticLinear.apply(ops, x, weight, alpha, E, carried))
    return out.Y if carried is None else torch.cat([out.Y, out.Y_carried], 1)


#: :meth:`~sb3_spikeplastic.snn.functional.project`'s ``x[b] @ (W + alpha * E[b]).T``; with ``carried``, the product of
#: the rows ``[x; carried]`` ``(B, L + 2, n_out)`` without copying them into one tensor; differentiable once
PLASTIC_LINEAR = Kernel("plastic_linear", _plastic_linear_applies, _run_plastic_linear)


# --- bernoulli_spikes (bernoulli.cpp) ----------------------------------------------------------------------------


def _bernoulli_applies(p: Tensor, keys: Tensor, index_hash: Tensor) -> bool:
    """CPU float32/float64 ``p (B, n)``, int32 ``keys (B,)`` and ``index_hash (T, n)``."""
    return (
        cpu_float_operands(p)
        and keys.is_cpu
        and p.dim() == 2
        and keys.dtype is torch.int32
        and keys.shape == p.shape[:1]
        and index_hash.shape[1:] == p.shape[1:]
    )


def _run_bernoulli(ops: Any, p: Tensor, keys: Tensor, index_hash: Tensor) -> Tensor:
    with torch.no_grad():
        return ops.bernoulli_spikes(p, keys, index_hash)


#: :meth:`sb3_spikeplastic.snn.coding.CounterBernoulli.sample`'s hash sampler; no autograd (spikes are samples)
BERNOULLI_SPIKES = Kernel("bernoulli_spikes", _bernoulli_applies, _run_bernoulli)
