"""The compiled layer interval as autograd nodes, and as the step that :func:`sb3_spikeplastic.snn._fast.dispatch`
runs in place of :func:`sb3_spikeplastic.snn.functional.interval_step` where it applies (:data:`FUSED_INTERVAL`).

:class:`_FusedInterval` runs a whole interval of a layer on the CPU, with a built-in rule's trace update, as one
compiled op forward and one backward (``_fast/srm_interval.cpp``); :class:`_DeferredInterval` the same with the trace
update deferred to the next interval. Both hand the op's tensors over as the NamedTuples of
:mod:`sb3_spikeplastic.snn._fast.interval`, and nothing here reads an output or gradient by position.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional

import torch
from torch import Tensor

from . import _fast
from ._fast import interval
from ._fast.interval import NO_RULE, IntervalConstants, IntervalInputs, IntervalOutputs, RuleForm
from .functional import IntervalParameters, LayerOutput, LayerState, interval_result
from .neurons import AlphaFilterState
from .plasticity import PlasticState

__all__ = ["FUSED_INTERVAL", "IntervalCall", "fused_interval_step", "interval_inputs"]


class IntervalCall(NamedTuple):
    """The fused interval's arguments besides its tensors.

    :param ops: the compiled namespace.
    :param constants: the layer's :class:`~sb3_spikeplastic.snn._fast.interval.IntervalConstants` for this length.
    :param form: the rule's form (:data:`~sb3_spikeplastic.snn._fast.interval.NO_RULE` where the op does not update
        the trace: static layers, rules of one's own).
    :param write_trace: ``None`` for the op that updates the trace at the interval's end; for the deferred op,
        whether it writes out the trace it used.
    """

    ops: Any
    constants: IntervalConstants
    form: RuleForm
    write_trace: Optional[bool]


def interval_inputs(
    spikes_in: Tensor, state: LayerState, parameters: IntervalParameters, form: Optional[RuleForm]
) -> IntervalInputs:
    """The op's tensors for one interval of a layer: those of the rule only where ``form`` (a built-in rule's update
    in the op) takes them, the pending updates those of ``state``."""
    rule, plastic = parameters.rule, parameters.alpha is not None
    bcm = form is not None and form.bcm
    (p_first, q_first), (p_second, q_second) = (*(state.plastic.pending or ()), (None, None), (None, None))[:2]
    return IntervalInputs(
        x=spikes_in,
        h1=state.psp.h1,
        h2=state.psp.h2,
        ref_h1=state.refractory.h1,
        ref_h2=state.refractory.h2,
        trace=state.plastic.trace if plastic else None,
        phi=state.plastic.extra[0] if bcm else None,
        p_first=p_first,
        q_first=q_first,
        p_second=p_second,
        q_second=q_second,
        weight=parameters.weight,
        alpha=parameters.alpha,
        eta=rule.eta if form is not None else None,
        eta_phi=rule.eta_phi if bcm else None,
        psi=rule.psi if bcm else None,
        w_m=rule.w_m if form is not None and form.modulation else None,
    )


class _FusedInterval(torch.autograd.Function):
    """One layer interval on the CPU as a single autograd node: :func:`~sb3_spikeplastic.snn.functional.synaptic_input`,
    the spike recursion, the surrogate, both mean rates and, for a built-in rule, the trace update with the rule's
    terms, in one compiled op forward and one backward (``_fast/srm_interval.cpp``, where the backward pass is
    written out; the trace-sized gradients of the product and of the update are summed in one pass).

    The forward op runs the eager step's and rule's ops and kernels in the same order, except that it filters by the
    alpha filter's recurrence (``_fast/alpha_filter.cpp``) where the eager step multiplies by its operator, so
    membrane, states and the new trace equal the eager step's to float rounding (spikes then only differ where the
    membrane lies within rounding of the threshold); the gradients are those of the eager graph (tested for every
    built-in rule) up to the surrogate, which the spike loop computes with an exponential of its own (within 2 ulp
    of :func:`~sb3_spikeplastic.snn.neurons.slayer_surrogate` in float32). Eager autograd builds ~15 nodes per layer
    and interval, whose overhead dominates the small CPU networks' training step.

    ``apply(call, *inputs)`` takes an :class:`IntervalCall` and the flattened
    :class:`~sb3_spikeplastic.snn._fast.interval.IntervalInputs`, and returns the flattened
    :class:`~sb3_spikeplastic.snn._fast.interval.IntervalOutputs` (:func:`run_interval` rebuilds them).
    """

    @staticmethod
    def applies(spikes_in: Tensor, state: LayerState, parameters: IntervalParameters, *flags) -> bool:
        """Whether the compiled op takes these operands: CPU float32/float64 tensors of one dtype, spikes
        ``(batch, L, n_in)``."""
        tensors = [parameters.weight, state.psp.h1, state.psp.h2, state.refractory.h1, state.refractory.h2]
        if parameters.alpha is not None:
            tensors += [parameters.alpha, state.plastic.trace]
        return spikes_in.dim() == 3 and _fast.cpu_float_operands(spikes_in, *tensors)

    @staticmethod
    def forward(ctx, call: IntervalCall, *tensors: Optional[Tensor]):
        inputs = interval.named(IntervalInputs, tensors)
        outputs, residuals = interval.run_forward(call.ops, inputs, call.constants, call.form, True, call.write_trace)
        if call.write_trace is False:  # the deferred op passes the input trace on (see _DeferredInterval)
            outputs = outputs._replace(trace=inputs.trace)
        # The backward op reads the parameters, the trace, the threshold and the pending updates of the inputs.
        ctx.save_for_backward(*interval.saved(inputs, residuals))
        # The rows' gradients only where the input spikes or the carried PSP state have one (not the input layer).
        need_rows = inputs.x.requires_grad or inputs.h1.requires_grad or inputs.h2.requires_grad
        ctx.call, ctx.need_rows = call, need_rows
        # The membrane and the refractory state carry no gradient (as in
        # :class:`~sb3_spikeplastic.snn.neurons.SRMSpikeRecursion`), nor, without the rows' gradients, the PSP state
        # and r_pre, which depend on those only.
        if need_rows:
            ctx.mark_non_differentiable(outputs.membrane, outputs.ref_h1, outputs.ref_h2)
        else:
            ctx.mark_non_differentiable(
                outputs.membrane, outputs.ref_h1, outputs.ref_h2, outputs.h1, outputs.h2, outputs.r_pre
            )
        # Outputs the loss does not reach (the membrane, the output layer's spikes, unused rates, the final trace)
        # get None, which the op reads as zero, instead of a zero-filled tensor of their size.
        ctx.set_materialize_grads(False)
        return outputs

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grad_outputs: Optional[Tensor]):
        call = ctx.call
        # The op's gradients in the inputs' order, None for those not given; autograd drops those of inputs that
        # need none.
        gradients = interval.backward_saved(
            call.ops, grad_outputs, ctx.saved_tensors, call.constants, call.form, ctx.need_rows, call.write_trace
        )
        return (None, *gradients)


class _DeferredInterval(_FusedInterval):
    """:class:`_FusedInterval` with the trace update deferred (``srm_interval_deferred_*`` in
    ``_fast/srm_interval.cpp``): the op first applies the state's pending updates ``clip((1 - eta) E + (eta p) (x)
    q)``, oldest first, in the pass over ``E`` that builds the efficacy, and returns its own update as ``(p_next,
    q_next)`` for the next interval, where :class:`_FusedInterval` passes over ``E`` once more for it. The trace it
    used is written out only with ``write_trace``; otherwise the input trace is passed on (one of the updates stays
    pending), and the interval that writes recomputes the one between in registers, forward and backward: a sequence
    stores every other trace. The same values as :class:`_FusedInterval`'s bit for bit, gradients equal to float
    rounding (tested).
    """


def run_interval(function: type[_FusedInterval], call: IntervalCall, inputs: IntervalInputs) -> IntervalOutputs:
    """The op's outputs: one autograd node of ``function`` when training, the op alone without autograd (rollouts,
    no surrogate)."""
    if torch.is_grad_enabled():
        return interval.named(IntervalOutputs, function.apply(call, *inputs))
    outputs, _ = interval.run_forward(call.ops, inputs, call.constants, call.form, False, call.write_trace)
    if call.write_trace is False:  # the deferred op passes the input trace on
        return outputs._replace(trace=inputs.trace)
    return outputs


def fused_interval_step(
    ops: Any,
    spikes_in: Tensor,
    state: LayerState,
    parameters: IntervalParameters,
    monitor: bool = False,
    defer_update: bool = False,
    modulator: Optional[Tensor] = None,
) -> tuple[LayerOutput, LayerState]:
    """:func:`~sb3_spikeplastic.snn.functional.interval_step` by the compiled op (``ops``: its namespace).

    Other rules than the built-in ones, and rules that take an external ``modulator``, run their
    :meth:`~sb3_spikeplastic.snn.plasticity.PlasticityRule.step` after the op. With ``defer_update`` (a built-in
    rule, without ``monitor``) the update is returned as the state's
    :attr:`~sb3_spikeplastic.snn.plasticity.PlasticState.pending` instead, and the next interval applies it in its
    own pass over ``E`` (:class:`_DeferredInterval`): the same values, one pass over the trace fewer each way. Every
    other such interval leaves the update before it pending too and passes its input trace on unchanged, so that a
    sequence stores half of its traces. Pending updates in ``state`` are always applied first.
    """
    rule, plastic, form = parameters.rule, parameters.alpha is not None, parameters.form
    pending = state.plastic.pending if plastic else None
    if form is not None and (defer_update or pending is not None) and not monitor:
        # Every other trace is stored: an interval with one update pending leaves it pending with its own and
        # passes its input trace on; the next one applies both and writes the trace out.
        write = pending is not None and (len(pending) == 2 or not defer_update)
        call = IntervalCall(ops, parameters.constants, form, write)
        out = run_interval(_DeferredInterval, call, interval_inputs(spikes_in, state, parameters, form))
        kept = () if write or pending is None else pending
        new_plastic = PlasticState(out.trace, (out.phi,) if form.bcm else (), (*kept, (out.p_next, out.q_next)))
        if not defer_update:
            new_plastic = rule.apply_pending(new_plastic)
    else:
        if pending is not None:
            state = state._replace(plastic=rule.apply_pending(state.plastic))
        call = IntervalCall(ops, parameters.constants, form if form is not None else NO_RULE, None)
        out = run_interval(_FusedInterval, call, interval_inputs(spikes_in, state, parameters, form))
        if form is not None:  # the op updated the trace
            new_plastic = PlasticState(out.trace, (out.phi,) if form.bcm else ())
        else:
            new_plastic = rule.step(out.r_pre, out.r_post, state.plastic, modulator) if plastic else state.plastic
    return interval_result(
        out.spikes,
        out.membrane,
        AlphaFilterState(out.h1, out.h2),
        AlphaFilterState(out.ref_h1, out.ref_h2),
        out.r_pre,
        out.r_post,
        new_plastic,
        parameters,
        monitor,
        modulator,
    )


#: the compiled interval for :func:`~sb3_spikeplastic.snn._fast.dispatch`, with the operands of
#: :func:`~sb3_spikeplastic.snn.functional.interval_step`; whether it applies is looked up on :class:`_FusedInterval`
#: at each call
FUSED_INTERVAL = _fast.Kernel("srm_interval", lambda *operands: _FusedInterval.applies(*operands), fused_interval_step)
